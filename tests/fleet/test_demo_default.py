"""``rce-fleet demo`` as a newcomer runs it (``make demo``), under a pseudo-terminal: the warehouse by
tasks (12 robots, batteries), the operator page's URL first, the live table (no JSON log lines), and
at the end the KPIs and the PNG of tasks done and activity; exit 0. Cut to 30 simulated seconds."""
from __future__ import annotations

import re
import sys
from pathlib import Path

from ptyrun import run_on_a_terminal

BIN = Path(sys.executable).parent
RUN_TIMEOUT_S = 240


def test_default_demo_runs_the_warehouse_by_tasks_and_prints_its_kpis(tmp_path):
    png = tmp_path / "tasks.png"
    code, out = run_on_a_terminal([str(BIN / "rce-fleet"), "demo", "--duration", "30", "--web-port", "0",
                                   "--plot", str(png), "--workdir", str(tmp_path / "run")], tmp_path, RUN_TIMEOUT_S)
    assert code == 0, out[-4000:]
    lines = [ln.strip() for ln in out.splitlines() if ln.strip()]
    assert not [ln for ln in lines if ln.startswith("{")], "no JSON log lines on a terminal"
    url = next(i for i, ln in enumerate(lines) if "operator page: http://" in ln)
    table = next(i for i, ln in enumerate(lines) if "robots by tasks on warehouse" in ln)
    assert url < table, "the page's URL comes before the live table"
    assert "Robot12" in out and re.search(r"\b(driving|at errand|idle|charging|to charger|parking)\b", out)
    kpi = re.search(r"tasks done \d+ in (\d+) s sim \(\d+ per hour\)", out)
    assert kpi and 30 <= int(kpi.group(1)) <= 35, out[-2000:]   # the last tick may pass the cut
    assert re.search(r"task time mean [\d.]+ s, p95 [\d.]+ s; utilisation \d+ %; charges \d+", out)
    assert f"tasks done and activity plotted to {png}" in out and png.stat().st_size > 10_000
