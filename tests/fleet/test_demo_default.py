"""``rce-fleet demo`` as a newcomer runs it (``make demo``), under a pseudo-terminal: the warehouse by
tasks (12 robots, batteries), the operator page's URL first, the live table (no JSON log lines), and
at the end the KPIs and the PNG of tasks done and activity; exit 0. Cut to 30 simulated seconds."""
from __future__ import annotations

import os
import pty
import re
import select
import subprocess
import sys
import time
from pathlib import Path

BIN = Path(sys.executable).parent
RUN_TIMEOUT_S = 240
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b\][^\x07]*\x07")


def run_on_a_terminal(argv: list[str], cwd: Path, timeout: float) -> tuple[int, str]:
    """Run ``argv`` with stdin, stdout and stderr on a pseudo-terminal; (exit code, what it printed)."""
    master, slave = pty.openpty()
    p = subprocess.Popen(argv, stdin=slave, stdout=slave, stderr=slave, cwd=cwd, close_fds=True,
                         env={**os.environ, "COLUMNS": "140", "LINES": "50", "TERM": "xterm-256color"})
    os.close(slave)
    out = bytearray()
    end = time.monotonic() + timeout
    try:
        while time.monotonic() < end:
            ready, _, _ = select.select([master], [], [], 1.0)
            if ready:
                try:
                    chunk = os.read(master, 65536)
                except OSError:             # EIO: the child closed the terminal
                    break
                if not chunk:
                    break
                out += chunk
            elif p.poll() is not None:
                break
        code = p.wait(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
        os.close(master)
    return code, ANSI.sub("", out.decode(errors="replace")).replace("\r", "")


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
    assert re.search(r"tasks done \d+ in 30 s sim \(\d+ per hour\)", out), out[-2000:]
    assert re.search(r"task time mean [\d.]+ s, p95 [\d.]+ s; utilisation \d+ %; charges \d+", out)
    assert f"tasks done and activity plotted to {png}" in out and png.stat().st_size > 10_000
