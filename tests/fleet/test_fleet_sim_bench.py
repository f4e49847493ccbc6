"""``bench/fleet_sim.py`` runs end to end on the warehouse map and writes its numbers and plot."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[2] / "bench" / "fleet_sim.py"


def test_fleet_sim_bench_reports_cpu_by_part_beside_pymunks_query(tmp_path):
    out, png = tmp_path / "sim.json", tmp_path / "sim.png"
    p = subprocess.run([sys.executable, str(BENCH), "--robots", "3", "--ticks", "6", "--json", str(out),
                        "--plot", str(png)], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert p.returncode == 0, (p.stdout + p.stderr)[-3000:]
    run = json.loads(out.read_text())["runs"][0]
    assert run["robots"] == 3 and run["sim_s"] == 0.6
    cpu = run["cpu_per_sim_s"]
    assert all(cpu[k] > 0 for k in ("scan", "navigator", "physics", "scan_pymunk"))
    assert run["cpu_per_sim_s_total"] == round(cpu["scan"] + cpu["navigator"] + cpu["physics"], 4)
    assert run["ratio"] > 0 and run["real_time_factor_one_core"] > 0
    assert png.stat().st_size > 1000 and "3 robots:" in p.stdout
