"""Run a command on a pseudo-terminal, as a person at a terminal would (for tests of what the
console shows): its output with the terminal's escape sequences removed."""
from __future__ import annotations

import os
import pty
import re
import select
import signal
import subprocess
import time
from pathlib import Path

ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b\][^\x07]*\x07")


def run_on_a_terminal(argv: list[str], cwd: Path, timeout: float, interrupt_after: str | None = None,
                      ) -> tuple[int, str]:
    """Run ``argv`` with stdin, stdout and stderr on a pseudo-terminal; (exit code, what it printed).
    ``interrupt_after``: once the output shows this text, press Ctrl-C (SIGINT) as a person would."""
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
                if interrupt_after is not None and interrupt_after.encode() in out:
                    p.send_signal(signal.SIGINT)
                    interrupt_after = None
            elif p.poll() is not None:
                break
        code = p.wait(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
        os.close(master)
    return code, ANSI.sub("", out.decode(errors="replace")).replace("\r", "")
