"""``bench/fleet_live.py --quick`` runs end to end: a real lifelong run of the whole system (3
robots, lab map) beside the offline prediction, and writes its numbers."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[2] / "bench" / "fleet_live.py"


def test_fleet_live_quick_reports_every_number(tmp_path):
    out = tmp_path / "live.json"
    p = subprocess.run([sys.executable, str(BENCH), "--quick", "--out", str(out), "--workdir", str(tmp_path / "w")],
                       capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert p.returncode == 0, (p.stdout + p.stderr)[-3000:]
    run = json.loads(out.read_text())["runs"]["3"]
    assert run["exit_code"] == 0 and run["reason"] == "40 s simulated"
    assert run["generated"] >= 1 and run["tasks"]["generated"] == run["generated"]
    assert 0 < run["real_time_factor"] and run["engine_cpu_pct"] > 0 and run["demo_cpu_pct"] > 0
    assert run["host_cpu_per_sim_s"] > 0
    assert run["machine_cpu_pct"] >= run["engine_cpu_pct"] + run["demo_cpu_pct"] - 5
    assert any(k.startswith("rce-") for k in run["by_process_pct"]), run["by_process_pct"]
    assert run["offline"]["steps"] >= 5 and run["ran_flat"] == 0
    # the offline prediction steps at the cell rate the robots made good in the control-loop run
    assert run["control"]["s_per_cell"] > 0 and run["offline"]["step_s"] == round(run["control"]["s_per_cell"], 3)
    assert run["control_share"] == round(run["control"]["tasks_done"] / run["offline"]["tasks_done"], 3)
    assert "3 robots:" in p.stdout and "tasks/h" in p.stdout
