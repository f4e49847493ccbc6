"""A task whose errand cell becomes blocked in the live fleet: ``rce-fleet demo --lifelong`` as a
process (engine, fleet container, pymunk robots, generated pick-up -> drop-off tasks) on the lab
map, with the drop-off station drop1 (cell 23) blocked by the operator 15 simulated s in. The
open tasks that still had to go there fail with the reason, and later ones are refused."""
from __future__ import annotations

import json
import subprocess

from .test_battery_charging import BIN, PLACES

RUN_TIMEOUT_S = 150       # wall s the run may take (its --timeout)


def test_a_blocked_errand_cell_fails_its_open_tasks_with_the_reason_and_refuses_new_ones(tmp_path):
    (tmp_path / "places.yaml").write_text(PLACES)
    report = tmp_path / "report.json"
    argv = [str(BIN / "rce-fleet"), "demo", "--lifelong", "--duration", "40", "--robots", "2",
            "--task-rate", "30/min", "--speedup", "12", "--grid", "8x8", "--places", str(tmp_path / "places.yaml"),
            "--block", "23@15", "--headless", "--no-live", "--report", str(report), "--plot", "",
            "--workdir", str(tmp_path / "run"), "--timeout", str(RUN_TIMEOUT_S)]
    p = subprocess.run(argv, capture_output=True, text=True, timeout=RUN_TIMEOUT_S + 60, cwd=tmp_path)
    out = (p.stdout + p.stderr)[-3000:]
    assert p.returncode == 0 and report.exists(), out
    rep = json.loads(report.read_text())
    tasks, ll = rep["tasks"], rep["lifelong"]
    assert [b["cell"] for b in rep["blocks"]] == [23], rep["blocks"]
    why = "errand cell 23 was blocked (operator)"
    assert tasks["failed"] >= 1 and tasks["failed_reasons"].get(why, 0) >= 1, tasks
    assert set(tasks["failed_reasons"]) == {why}, tasks     # nothing else failed, nothing silently
    assert any("cell 23 is blocked (by operator)" in r for r in ll["refused"]), ll["refused"]
    assert tasks["done"] + tasks["failed"] + tasks["queued"] + len(ll["refused"]) <= tasks["generated"]
