"""Where the robots stand still: a map picture of a lifelong run's waits, window by window.

A jam shows as robots that wait where they should be moving. Given a run's output JSON in the
start-kit's format (``Input_Output_Format.md``: ``start``, ``actualPaths``; rce's, the default
entry's and the 2024 winner's alike) and its map, this replays every robot's cells (actions F, R,
C, W of the 2024 rules; robots start facing as ``start`` says) and counts, for each window of steps,
the robot-steps of ``W`` in each cell. The PNG puts the windows side by side on the map (obstacles
grey, waits on a log scale), so that "before" and "after" a jam read at a glance, and the JSON
gives each window's waits and the cells that hold most of them.

Usage::

    .venv/bin/python bench/lifelong_waits.py MAP OUTPUT.json --windows 300:400 500:600 \\
        [--out bench/results/waits.png] [--json PATH]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

# start-kit headings: 0 east, 1 south, 2 west, 3 north; R turns clockwise, C counter-clockwise
HEADING = {"E": 0, "S": 1, "W": 2, "N": 3}
STEP = np.array([[0, 1], [1, 0], [0, -1], [-1, 0]], dtype=np.int64)


def read_map(path: Path) -> np.ndarray:
    """(rows, cols) bool free cells of a LoRR map, read as the start-kit reads it
    (:func:`rce_fleet.lifelong.load_lorr_map`). Raises ProblemError (a ValueError) naming the file
    and line."""
    from rce_fleet.lifelong import load_lorr_map
    grid = load_lorr_map(path)
    return grid.flat.reshape(grid.rows, grid.cols)


def actions(output: dict) -> np.ndarray:
    """(robots, steps) uint8 action letters of ``actualPaths``. Raises ValueError when the paths
    are missing or of different lengths."""
    paths = output.get("actualPaths")
    if not isinstance(paths, list) or not paths:
        raise ValueError("the output has no actualPaths")
    rows = [np.frombuffer(p.replace(",", "").encode(), dtype=np.uint8) for p in paths]
    if len({len(r) for r in rows}) != 1:
        raise ValueError("actualPaths of different lengths")
    return np.stack(rows)


def replay(free: np.ndarray, start: list, acts: np.ndarray, last: int | None = None):
    """The robots' states along their actions ``acts`` (:func:`actions` of an output) from ``start``
    (the output's [row, col, heading] per robot) on the map ``free`` ((rows, cols) bool): yields
    (t, actions of step t as uint8 letters, pos (n, 2) int64 row and column, head (n,) int64) with
    the state after t steps, for t = 0 .. ``last`` - 1 (default: every step), then (``last``, None,
    pos, head). The arrays are reused: read them before the next. Raises ValueError when a robot
    leaves the free cells (an output of another map)."""
    last = acts.shape[1] if last is None else last
    pos = np.array([[s[0], s[1]] for s in start], dtype=np.int64)
    head = np.array([HEADING[s[2]] for s in start], dtype=np.int64)
    for t in range(last):
        act = acts[:, t]
        yield t, act, pos, head
        fwd = act == ord("F")
        pos[fwd] += STEP[head[fwd]]
        head[:] = np.where(act == ord("R"), (head + 1) % 4, np.where(act == ord("C"), (head + 3) % 4, head))
        if fwd.any():
            r, c = pos[fwd, 0], pos[fwd, 1]
            if (r < 0).any() or (c < 0).any() or (r >= free.shape[0]).any() or (c >= free.shape[1]).any() \
                    or not free[r, c].all():
                raise ValueError(f"step {t}: a robot moved off the map's free cells (is this the run's map?)")
    yield last, None, pos, head


def wait_maps(free: np.ndarray, output: dict, windows: list[tuple[int, int]]) -> np.ndarray:
    """(len(windows), rows, cols) int64: per window ``[a, b)`` of steps, the robot-steps of ``W`` in
    each cell. Raises ValueError for a window outside the run or a robot that leaves the free cells
    (an output of another map)."""
    acts = actions(output)
    steps = acts.shape[1]
    for a, b in windows:
        if not 0 <= a < b <= steps:
            raise ValueError(f"window {a}:{b} outside the run's {steps} steps")
    out = np.zeros((len(windows), *free.shape), dtype=np.int64)
    for t, act, pos, _ in replay(free, output["start"], acts, max(b for _, b in windows)):
        if act is None:
            break
        wait = act == ord("W")
        for k, (a, b) in enumerate(windows):
            if a <= t < b and wait.any():
                np.add.at(out[k], (pos[wait, 0], pos[wait, 1]), 1)
    return out


def plot(free: np.ndarray, maps: np.ndarray, windows: list[tuple[int, int]], path: Path, title: str) -> None:
    """PNG: one panel per window, obstacles grey, waits per cell on a shared log scale."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    rows, cols = free.shape
    k = len(windows)
    if cols >= 2 * rows:                 # a wide map: the windows one above the other, each the page's width
        fig, axes = plt.subplots(k, 1, figsize=(13.0, k * 13.0 * rows / cols + 1.2), squeeze=False)
        axes = axes[:, 0]
    else:
        w = min(6.0, 14.0 / k)
        fig, axes = plt.subplots(1, k, figsize=(w * k + 1.5, w * rows / cols + 1.0), squeeze=False)
        axes = axes[0]
    top = max(1, int(maps.max()))
    for ax, m, (a, b) in zip(axes, maps, windows, strict=True):
        ax.imshow(np.where(free, 1.0, 0.55), cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        shown = np.ma.masked_where(m == 0, m)
        im = ax.imshow(shown, cmap="inferno_r", norm=LogNorm(vmin=1, vmax=top), interpolation="nearest")
        ax.set_title(f"steps {a}-{b}: {int(m.sum()):,} waits", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(im, ax=list(axes), shrink=0.8, label="robot-steps waiting in the cell")
    fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _window(text: str) -> tuple[int, int]:
    try:
        a, b = (int(x) for x in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected A:B steps, got {text!r}") from None
    return a, b


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("map", type=Path)
    ap.add_argument("output", type=Path, help="the run's output JSON (start-kit format)")
    ap.add_argument("--windows", nargs="+", type=_window, required=True, metavar="A:B")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "waits.png")
    ap.add_argument("--json", type=Path, help="each window's waits and its 20 cells with most (default: beside --out)")
    ap.add_argument("--title", default="")
    args = ap.parse_args(argv)
    try:
        free = read_map(args.map)
        output = json.loads(args.output.read_text())
        maps = wait_maps(free, output, args.windows)
    except (OSError, ValueError, KeyError) as e:
        print(f"lifelong_waits: {e}", file=sys.stderr)
        return 2
    args.out.parent.mkdir(parents=True, exist_ok=True)
    plot(free, maps, args.windows, args.out, args.title or f"{args.output.name} on {args.map.name}")
    rows = []
    for m, (a, b) in zip(maps, args.windows, strict=True):
        top = np.argsort(m.ravel())[::-1][:20]
        rows.append({"window": [a, b], "waits": int(m.sum()), "cells_with_waits": int((m > 0).sum()),
                     "top_cells": [[int(c // free.shape[1]), int(c % free.shape[1]), int(m.ravel()[c])] for c in top]})
        print(f"steps {a}-{b}: {int(m.sum()):,} robot-steps waiting in {int((m > 0).sum()):,} cells")
    js = args.json or args.out.with_suffix(".json")
    js.write_text(json.dumps({"map": str(args.map), "output": str(args.output), "windows": rows}, indent=1))
    print(f"wrote {args.out} and {js}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
