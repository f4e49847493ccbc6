"""Smoke test of bench/lanes.py: one short run (rce with lanes and the rate estimated, the FIFO
bottleneck) in the network namespaces it makes, to the end: JSON with the documented keys, every cancel
back, the estimator's trace, and its PNG."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.timeout(400)
def test_lanes_smoke(tmp_path):
    out = tmp_path / "lanes.json"
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "lanes.py"), "--idle", "2", "--camera", "3",
                        "--systems", "rce-auto", "--setups", "fifo", "--out", str(out)],
                       cwd=ROOT, capture_output=True, text=True, timeout=390)
    assert r.returncode == 0, f"exit {r.returncode}\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    d = json.loads(out.read_text())
    assert d["link_Bps"] == 1_250_000 and [(x["system"], x["setup"]) for x in d["runs"]] == [("rce-auto", "fifo")]
    run = d["runs"][0]
    for phase in ("idle", "camera"):
        assert run[phase]["cancels"] > 0 and run[phase]["lost"] == 0 and run[phase]["p99_ms"] > 0, run[phase]
    assert run["camera"]["frames_acked"] > 0 and 0 < run["camera"]["goodput_share"] <= 1
    assert out.with_suffix(".png").stat().st_size > 10_000
    trace = run["pacing_trace"]
    assert trace and {p[3] for p in trace} <= {"startup", "cruise", "probe", "drain"}
    assert any(p[2] is not None for p in trace), trace          # the estimate known by the phase's end
