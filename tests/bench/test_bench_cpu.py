"""bench/common.py's CPU clock of another process (process_cpu_s): a real child that works 3 ms of
CPU reads those 3 ms (the 10-ms ticks of /proc/PID/stat may read 0), its threads' work counts, and
a process that is gone raises psutil.NoSuchProcess."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import psutil
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
from common import process_cpu_s  # noqa: E402

# works until its own CPU clock passed WORK s (in a thread when asked), says so, then waits on stdin
CHILD = """
import sys, threading, time
def work():
    t0 = time.thread_time()
    while time.thread_time() - t0 < {work}:
        pass
if sys.argv[1] == "thread":
    t = threading.Thread(target=work); t.start(); t.join()
else:
    work()
print("done", time.process_time(), flush=True)
sys.stdin.read()
"""


@pytest.mark.parametrize("where", ["main", "thread"])
def test_a_few_ms_of_another_process_read_as_they_are(where):
    work = 0.003
    with subprocess.Popen([sys.executable, "-c", CHILD.format(work=work), where], stdin=subprocess.PIPE,
                          stdout=subprocess.PIPE, text=True) as child:
        try:
            line = child.stdout.readline().split()
            assert line[0] == "done"
            own = float(line[1])                             # the child's own clock, all its threads
            seen = process_cpu_s(psutil.Process(child.pid))
            assert seen >= own >= work                       # ours reads at least what the child read of itself
            assert seen - own < 0.05                         # and little more (the few lines after it read)
            assert process_cpu_s(child.pid) >= seen          # a pid serves as well as a psutil.Process
        finally:
            child.stdin.close()
            child.wait(10)
    with pytest.raises(psutil.NoSuchProcess):
        process_cpu_s(child.pid)
