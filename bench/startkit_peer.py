"""The League of Robot Runners start-kit's default entry as a peer (MAPF-Competition/Start-Kit v2.1.2,
MIT; C++): built from its source outside the repository, run on the same problem, steps and time
limit as rce, its output JSON read back. Its code is never part of rce.

Build it (``bench/lifelong.py --build-peer DIR`` runs the last three steps)::

    git clone --branch v2.1.2 --depth 1 https://github.com/MAPF-Competition/Start-Kit DIR
    apt-get install -y libboost-all-dev cmake g++          # Debian's Boost (program_options, system, log)
    cmake -S DIR -B DIR/build -DPYTHON=false -DCMAKE_BUILD_TYPE=Release && make -C DIR/build -j2

The binary is ``DIR/build/lifelong``.
"""
from __future__ import annotations

import itertools
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PEER_TAG = "v2.1.2"
DEBIAN_PACKAGES = ("libboost-all-dev", "cmake", "g++", "make")
STEP_LINE = re.compile(rb"\[timestep=(\d+)\] planner returns")
FINISH = re.compile(r"timestep=(\d+)\] Agent (\d+) finishes task (\d+)")     # the start-kit's log
# ms of preprocessing an entry has before its first step: the 2024 rules give "30 minutes of preprocessing
# time per map" (the start-kit's Prepare_Your_Submission.md); the start-kit's own default is 30 s, which the
# 2024 winner's code overran on CITY-01 (1,500 robots on Paris_1_256) on this 2-core machine
PREPROCESS_MS = 30 * 60 * 1000


def build_peer(src: Path) -> Path:
    """Build the start-kit checked out at ``src`` (its ``CMakeLists.txt``; Debian's Boost installed
    with apt-get when missing and running as root). Returns the ``lifelong`` binary. Raises
    RuntimeError naming the step that failed."""
    src = src.resolve()
    if not (src / "CMakeLists.txt").is_file():
        raise RuntimeError(f"{src}: no start-kit source here (git clone --branch {PEER_TAG} --depth 1 "
                           f"https://github.com/MAPF-Competition/Start-Kit {src})")
    if not Path("/usr/include/boost/program_options.hpp").exists():
        if os.geteuid() != 0:
            raise RuntimeError("Boost is missing: apt-get install " + " ".join(DEBIAN_PACKAGES))
        _run(["apt-get", "install", "-y", "-q", *DEBIAN_PACKAGES], "apt-get install")
    build = src / "build"
    _run(["cmake", "-S", str(src), "-B", str(build), "-DPYTHON=false", "-DCMAKE_BUILD_TYPE=Release"], "cmake")
    _run(["make", "-C", str(build), f"-j{os.cpu_count() or 1}", "lifelong"], "make")
    binary = build / "lifelong"
    if not binary.is_file():
        raise RuntimeError(f"make finished but {binary} is missing")
    return binary


def _run(argv: list[str], what: str) -> None:
    print(f"start-kit: {' '.join(argv)}", flush=True)
    done = subprocess.run(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    if done.returncode:
        raise RuntimeError(f"{what} failed ({done.returncode}):\n{done.stdout.decode(errors='replace')[-3000:]}")


def finished_curve(out: dict, steps: int, task_errands: list[int] | None = None) -> list[int] | None:
    """Tasks finished by the end of each of ``steps`` steps (cumulative), from a start-kit output's
    ``events`` ([timestep, agent, task, errands reached], the timestep counted from 1 after the
    first step's move): a task is finished when its last errand is reached. Each task's errands come
    from the output's ``tasks`` ([task, release, [row, col, ...]]) or, for an output without them
    (the 2024 winner's code writes its events but not its tasks), from ``task_errands``: the
    errands of each line of the problem's task file, task ``i`` being line ``i`` modulo their
    number (the start-kit reveals them in order, round again: ``TaskManager::reveal_tasks``). None
    when the output has no events (written with ``-c`` 2 or 3), neither source of errands is
    there, or the events do not add up to its ``numTaskFinished``."""
    if not out.get("events"):
        return None
    if out.get("tasks"):
        errands = {int(t[0]): len(t[2]) // 2 for t in out["tasks"]}.get
    elif task_errands:
        def errands(task: int) -> int:
            return task_errands[task % len(task_errands)]
    else:
        return None
    return _cumulative((int(t) for t, _, task, seq in out["events"] if seq == errands(int(task))), steps,
                       int(out.get("numTaskFinished", -1)))


def log_curve(log_text: str, steps: int, total: int) -> list[int] | None:
    """Tasks finished by the end of each of ``steps`` steps (cumulative), from the start-kit's log
    (``"[timestep=S] Agent A finishes task T"``, S counted as the output's events count it): for an
    entry whose output leaves its events out (the 2024 winner's code). None when the log's finishes
    do not add up to ``total`` (its ``numTaskFinished``)."""
    return _cumulative((int(m.group(1)) for m in FINISH.finditer(log_text)), steps, total)


def _cumulative(finish_steps, steps: int, total: int) -> list[int] | None:
    """Tasks finished by the end of each of ``steps`` steps from the steps (1-based) of the
    finishes; None when those within the steps do not add up to ``total``."""
    per_step = [0] * steps
    for t in finish_steps:
        if 1 <= t <= steps:
            per_step[t - 1] += 1
    curve = list(itertools.accumulate(per_step))
    return curve if curve and curve[-1] == total else None


def run_peer(binary: Path, problem: Path, steps: int, limit_ms: float, progress=None,
             extra: tuple[str, ...] = (), cwd: Path | None = None, curve: bool = False) -> dict:
    """Run the start-kit on ``problem`` for ``steps`` steps at ``limit_ms`` per step, with the rules'
    preprocessing limit (``PREPROCESS_MS``, 30 minutes). ``extra`` are more arguments for an entry built on
    the start-kit that takes its own (the 2024 winner's ``--pa 'pepibt(4)_lns' --gg enable --sa
    greedy``); ``cwd`` is the directory it runs in, for an entry that reads its own data files
    from there (default: a fresh temporary directory, so that no file it writes lands elsewhere).
    ``progress(step)`` is called as its log says steps are done. Returns its output's
    counts, the wall time and its peak resident memory in MiB: {tasks_finished, timeouts,
    invalid_steps, schedule_errors, wall_s, peak_rss_mib}, and with ``curve`` the tasks finished by
    each step (:func:`finished_curve`; the output then holds its events and paths, about 2 bytes per
    robot-step; the errands of each task from the output, or from ``problem``'s task file when the
    output leaves its tasks out). Raises RuntimeError when it fails, naming its peak memory."""
    with tempfile.TemporaryDirectory(prefix="rce-startkit-") as tmp:
        out, log = Path(tmp) / "out.json", Path(tmp) / "log.txt"
        argv = [str(binary), "-i", str(problem.resolve()), "-o", str(out), "-s", str(steps), "-t", str(int(limit_ms)),
                "-p", str(PREPROCESS_MS), "-c", "1" if curve else "3", "-l", str(log), *extra]
        t0 = time.perf_counter()
        proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=cwd or tmp)
        seen = peak_kib = 0
        while proc.poll() is None:
            peak_kib = max(peak_kib, _hwm_kib(proc.pid))    # read while it runs: growth in its last second unseen
            try:
                proc.wait(timeout=1.0)
            except subprocess.TimeoutExpired:
                pass
            if progress is not None and log.exists():
                seen = _last_step(log, seen)
                progress(seen)
        peak_mib = peak_kib / 1024
        wall = time.perf_counter() - t0
        if proc.returncode != 0 or not out.is_file():
            err = proc.stderr.read().decode(errors="replace")[-2000:] if proc.stderr else ""
            tail = log.read_text(errors="replace")[-1000:] if log.exists() else ""
            why = "killed (out of memory?)" if proc.returncode == -9 else f"exited {proc.returncode}"
            raise RuntimeError(f"start-kit {why} on {problem.name} after {wall:.0f} s, its peak resident memory "
                               f"{peak_mib / 1024:.1f} GiB\n{err}\n{tail}")
        d = json.loads(out.read_text())
        got = {"tasks_finished": int(d["numTaskFinished"]), "timeouts": int(d["numEntryTimeouts"]),
               "invalid_steps": int(d["numPlannerErrors"]), "schedule_errors": int(d["numScheduleErrors"]),
               "wall_s": wall, "peak_rss_mib": peak_mib}
        if curve:
            c = finished_curve(d, steps, None if d.get("tasks") else _task_errands(problem))
            if c is None and log.exists():
                c = log_curve(log.read_text(errors="replace"), steps, got["tasks_finished"])
            if c is not None:
                got["curve"] = c
    return got


def _hwm_kib(pid: int) -> int:
    """``VmHWM`` of ``pid`` in KiB from ``/proc/PID/status`` (the high-water mark of its own address
    space, proc(5)); 0 once it has exited. Not ``wait4``'s ``ru_maxrss``, which counts the parent's
    memory the child held before its exec."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1])
    except (FileNotFoundError, ProcessLookupError):
        pass
    return 0


def _task_errands(problem: Path) -> list[int]:
    """The number of errands of each line of ``problem``'s task file, in order."""
    from rce_fleet.lifelong.lorr import load_problem
    return [len(t) for t in load_problem(problem).tasks]


def _last_step(log: Path, seen: int) -> int:
    """The last ``[timestep=N] planner returns`` in the tail of the start-kit's log (or ``seen``)."""
    with log.open("rb") as f:
        f.seek(0, os.SEEK_END)
        f.seek(max(0, f.tell() - 65536))
        hits = STEP_LINE.findall(f.read())
    return max(seen, int(hits[-1]) + 1) if hits else seen


def main() -> int:
    """``startkit_peer.py SRC``: build the start-kit checked out at SRC; prints the binary's path."""
    if len(sys.argv) != 2:
        print(__doc__)
        return 2
    try:
        print(build_peer(Path(sys.argv[1])))
    except RuntimeError as e:
        print(f"startkit_peer: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
