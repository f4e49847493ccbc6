"""Nothing of ``rce-fleet serve`` outlives it: serve as a process (the engine's master, robot endpoint and
container host, the fleet container's environment and nodes, a pymunk robot) is killed with SIGKILL, which
it cannot catch; within 5 s no process it started, directly or through its children, is left. The engine
launcher ties each process it starts to its parent (``PR_SET_PDEATHSIG``, :mod:`rce.plumbing.process`), and
each engine process, on that SIGTERM, stops its own."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil

BIN = Path(sys.executable).parent
UP_TIMEOUT_S = 90         # wall s for serve to start the engine, the fleet container and its robot
GONE_WITHIN_S = 5.0       # wall s after the kill by which every process it started must be gone


def _descendants(pid: int) -> list[psutil.Process]:
    try:
        return psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []


def _alive(p: psutil.Process) -> bool:
    """Whether ``p`` (the very process: psutil checks its start time) still runs; a zombie has ended."""
    try:
        return p.is_running() and p.status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def test_serve_killed_with_sigkill_leaves_no_process_behind(tmp_path):
    log = tmp_path / "serve.log"
    argv = [str(BIN / "rce-fleet"), "serve", "--robots", "1", "--grid", "8x8", "--speedup", "10", "--headless",
            "--no-live", "--workdir", str(tmp_path / "work"), "--timeout", "600"]
    serve = subprocess.Popen(argv, stdout=open(log, "wb"), stderr=subprocess.STDOUT, start_new_session=True,
                             env=dict(os.environ, RCE_LOG_JSON="1"))
    left: list[psutil.Process] = []
    try:
        deadline = time.monotonic() + UP_TIMEOUT_S
        while '"msg": "serving"' not in log.read_text(errors="replace"):
            assert serve.poll() is None, log.read_text(errors="replace")[-3000:]
            assert time.monotonic() < deadline, "serve did not come up:\n" + log.read_text(errors="replace")[-3000:]
            time.sleep(0.1)     # polling the log for a line, with a deadline
        started = _descendants(serve.pid)
        names = " ".join(" ".join(p.cmdline()[:3]) for p in started)
        # the engine (master, robot endpoint, container host) and what the container host runs
        assert len(started) >= 4 and "rce-master" in names and "rce-container" in names, names
        serve.send_signal(signal.SIGKILL)
        serve.wait()
        gone_by = time.monotonic() + GONE_WITHIN_S
        while True:
            left = [p for p in started if _alive(p)]
            if not left or time.monotonic() > gone_by:
                break
            time.sleep(0.05)    # polling the process table, with a deadline
        assert not left, f"left running {GONE_WITHIN_S:g} s after serve's SIGKILL: " + \
            "; ".join(f"{p.pid} {' '.join(p.cmdline()[:4])}" for p in left if _alive(p))
    finally:
        if serve.poll() is None:
            serve.kill()
            serve.wait()
        for p in left:          # what the assertion found, so that a failure leaves nothing either
            try:
                p.kill()
            except psutil.NoSuchProcess:
                pass
