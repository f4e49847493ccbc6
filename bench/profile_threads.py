"""How busy each thread of a process was, and on what: a py-spy profile drawn per thread.

Input: the raw (collapsed) output of ``py-spy record --threads -f raw -r RATE -d SECONDS -p PID``,
one line per stack with its sample count, the first frame naming the thread. py-spy samples a
thread only while it runs (without ``--idle``), so a thread's samples over ``RATE x SECONDS`` is the
share of the time it was busy. Each sample is put to the deepest frame of the first module of
``--modules`` that the stack passes (by file name), else to "other".

Usage::

    py-spy record --threads -f raw -r 50 -d 40 -p PID -o prof.txt
    .venv/bin/python bench/profile_threads.py prof.txt --rate 50 --seconds 40 \\
        --modules epibt.py flow.py scheduler.py distances.py simulator.py --out threads.png
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from collections import Counter
from pathlib import Path

FRAME = re.compile(r"^(?P<func>[^ ]+) \((?P<file>[^:)]+)")


def busy_shares(raw: str, rate: float, seconds: float, modules: list[str]) -> dict[str, dict[str, float]]:
    """thread -> {module or "other": share of the time (0-1) the thread ran there}. Raises
    ValueError for a line that is not ``stack count``."""
    out: dict[str, Counter] = {}
    for k, line in enumerate(raw.splitlines(), 1):
        if not line.strip():
            continue
        stack, _, count = line.rpartition(" ")
        if not stack or not count.isdigit():
            raise ValueError(f"line {k}: not 'stack count' (py-spy -f raw)")
        frames = stack.split(";")
        thread = re.sub(r"^thread \(\d+\): ", "", frames[0])
        where = "other"
        for f in frames[1:]:
            m = FRAME.match(f)
            if m and (name := Path(m["file"]).name) in modules:
                where = name
        out.setdefault(thread, Counter())[where] += int(count)
    total = rate * seconds
    return {t: {w: n / total for w, n in c.most_common()} for t, c in out.items()}


def plot(shares: dict[str, dict[str, float]], path: Path, title: str) -> None:
    """PNG: one bar per thread, its busy share split by module."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    threads = sorted(shares, key=lambda t: -sum(shares[t].values()))
    mods = sorted({m for s in shares.values() for m in s}, key=lambda m: (m == "other", m))
    fig, ax = plt.subplots(figsize=(8, 0.7 * len(threads) + 1.4))
    for i, t in enumerate(threads):
        left = 0.0
        for j, m in enumerate(mods):
            w = shares[t].get(m, 0.0) * 100
            if w:
                ax.barh(i, w, left=left, color=f"C{j}" if m != "other" else "lightgrey",
                        label=m if i == next(k for k, tt in enumerate(threads) if m in shares[tt]) else None)
                left += w
        ax.text(left + 1, i, f"{left:.0f} %", va="center", fontsize=8)
    ax.set_yticks(range(len(threads)), threads)
    ax.set_xlim(0, 110)
    ax.set_xlabel("% of the time the thread ran")
    ax.invert_yaxis()
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("raw", type=Path, help="py-spy record --threads -f raw output")
    ap.add_argument("--rate", type=float, required=True, help="py-spy's -r (samples per second)")
    ap.add_argument("--seconds", type=float, required=True, help="py-spy's -d (s)")
    ap.add_argument("--modules", nargs="+", required=True, metavar="FILE.py")
    ap.add_argument("--out", type=Path, required=True, help="PNG (its JSON beside it)")
    ap.add_argument("--title", default="")
    args = ap.parse_args(argv)
    try:
        shares = busy_shares(args.raw.read_text(), args.rate, args.seconds, args.modules)
    except (OSError, ValueError) as e:
        print(f"profile_threads: {args.raw}: {e}", file=sys.stderr)
        return 2
    plot(shares, args.out, args.title or args.raw.name)
    args.out.with_suffix(".json").write_text(json.dumps(shares, indent=1))
    for t, s in shares.items():
        print(f"{t}: busy {sum(s.values()) * 100:.0f} % (" + ", ".join(f"{m} {v * 100:.0f} %" for m, v in s.items())
              + ")")
    return 0


if __name__ == "__main__":
    sys.exit(main())
