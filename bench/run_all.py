"""Run every benchmark script, one after the other (``make bench``): rtt, rtt_gap (``rtt.py
--gap 1.0`` at 3 B and 1.6 kB: sparse messages), rtt_cpu, fleet_load, paper_experiments, planner,
container_start, faults, stall, login_attack, lanes, ws_impl, foxglove. A script that does not exist
(yet) is skipped with a message.
Each writes its own results to ``bench/results/``; this prints a summary and exits non-zero
if any script failed.

Usage::

    .venv/bin/python bench/run_all.py [--only rtt,planner] [--skip fleet_load]
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parent
SCRIPTS = ("rtt", "rtt_gap", "rtt_cpu", "rtt_ros2", "fleet_load", "paper_experiments", "planner", "container_start",
           "faults", "stall", "login_attack", "lanes", "ws_impl", "foxglove")
# a name that is not a script's: (script, its arguments)
VARIANTS = {"rtt_gap": ("rtt", ["--gap", "1.0", "--sizes", "3,1623"])}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="Run every benchmark script in bench/.")
    p.add_argument("--only", default="", help=f"comma list, a subset of {','.join(SCRIPTS)}")
    p.add_argument("--skip", default="", help="comma list of scripts not to run")
    a = p.parse_args(argv)
    only = [s for s in a.only.split(",") if s]
    skip = {s for s in a.skip.split(",") if s}
    unknown = [s for s in only + sorted(skip) if s not in SCRIPTS]
    if unknown:
        print(f"run_all: unknown script(s) {unknown}; known: {', '.join(SCRIPTS)}", file=sys.stderr)
        return 2
    summary = []
    for name in only or SCRIPTS:
        script, args = VARIANTS.get(name, (name, []))
        path = BENCH / f"{script}.py"
        if name in skip:
            summary.append((name, "skipped (--skip)", 0.0))
            continue
        if not path.exists():
            print(f"== {name}: bench/{script}.py does not exist yet, skipped", flush=True)
            summary.append((name, "missing, skipped", 0.0))
            continue
        print(f"== {name}: {sys.executable} bench/{script}.py {' '.join(args)}".rstrip(), flush=True)
        t0 = time.monotonic()
        rc = subprocess.run([sys.executable, str(path), *args], cwd=BENCH.parent).returncode
        summary.append((name, "ok" if rc == 0 else f"FAILED (exit {rc})", time.monotonic() - t0))
    print("\n== bench summary")
    for name, status, secs in summary:
        print(f"  {name:<18} {status:<20} {secs:7.1f} s")
    print(f"results in {BENCH / 'results'}")
    return 1 if any(s.startswith("FAILED") for _, s, _ in summary) else 0


if __name__ == "__main__":
    sys.exit(main())
