"""Smoke test of bench/placement.py: the whole script with 1 s phases, the three systems (cloud,
robot, placer) in the network namespaces it makes, to the end: JSON of the documented shape, no
result lost or duplicated, and its PNG. The second phase's link is 20 Mbit/s (and the bench's 50 ms
each way, through its delay line) here: the smoke test checks that the script runs to its end and
what it writes, not the placer's numbers, which on a 1 Mbit/s link depend on the machine's speed."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PHASE_S = 1              # s of each of the script's four phases
RUN_TIMEOUT = 110        # s: the calibration and three engines, each 4 x 1 s of script (about 47 s on a quiet machine)
MOVE_KEYS = {"t_s", "from", "to", "gap_s", "why", "began_s"}

@pytest.mark.timeout(RUN_TIMEOUT + 20)
def test_placement_smoke(tmp_path):
    out = tmp_path / "placement.json"
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "placement.py"), "--phase-s", str(PHASE_S),
                        "--bad-rate", "20mbit", "--out", str(out)],
                       cwd=ROOT, capture_output=True, text=True, timeout=RUN_TIMEOUT)
    assert r.returncode == 0, f"exit {r.returncode}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    d = json.loads(out.read_text())
    assert set(d["systems"]) == {"cloud", "robot", "placer"}
    assert (d["bad_rate"], d["bad_delay_ms"], d["scan_points"]) == ("20mbit", 50.0, 1081), d
    cal = d["node_calibration"]             # set on the robot's capped computer: slower there than uncapped
    assert cal["robot_heavy_ms"] > cal["heavy_ms"] > cal["light_ms"] > 0, cal
    assert f"--samples {cal['samples']}" in d["node_args"], (cal, d["node_args"])
    for name, s in d["systems"].items():
        assert isinstance(s["deadline_misses"], int) and isinstance(s["robot_energy_j"], float), name
        by_phase = s["deadline_misses_by_phase"]
        assert len(by_phase) == 4 and all(isinstance(x, int) for x in by_phase)
        assert sum(by_phase) == s["deadline_misses"], name
        assert s["scans"] >= 4 * PHASE_S * 10 * 0.8, (name, s["scans"])        # 10 Hz for 4 phases, give or take
        assert (s["lost"], s["duplicated"]) == (0, 0), (name, s["lost_by_phase"], s["duplicated"], s["drops"])
        for m in s["moves"]:
            assert MOVE_KEYS <= set(m), m
            if s["first_result_s"] is not None and m["began_s"] > s["first_result_s"]:
                assert m["gap_s"] is not None and m["gap_s"] >= 0, m
            else:                                      # it began before the first result (while the container
                assert m["gap_s"] is None, m           # was set up, or on a loaded machine): no handover to time
            assert (m["lost"], m["duplicated"]) == (0, 0), m
    assert d["systems"]["robot"]["robot_energy_j"] > d["systems"]["cloud"]["robot_energy_j"]   # CPU on the robot
    assert not d["systems"]["cloud"]["moves"] and not d["systems"]["robot"]["moves"]          # pinned by placement
    assert out.with_suffix(".png").stat().st_size > 10_000
