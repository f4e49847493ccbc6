"""Where a lifelong run's robot-steps go: each finished task's steps against the least it could take.

A robot's time splits into cycles, one per task it finished: from its previous finish (or step 0)
to this task's last errand. The least a cycle could take is the least MAPF_T steps (quarter turns
and forward moves, one step each: the 2024 rules) from where the robot stood, facing as it faced,
through the task's errands in order (a breadth-first search over (cell, heading) states:
:func:`~rce_fleet.lifelong.distances.heading_graph`). The steps
beyond it are the planner's (and the team's) cost, split by the actions taken:

- **waits**: the robot's ``W`` in the cycle;
- **turns beyond**: its ``R`` and ``C`` less the least cycle's turns (the least cycle less the
  shortest way in cells: a robot that turns more than the way needs, to dodge or to go round);
- **moves beyond**: its ``F`` less the shortest way in cells through the errands (detours).

Two runs of one problem compare as the work they chose (the least cycle: the scheduler's part)
and the stretch over it (the planner's part). Outputs in the start-kit's format (``start``,
``actualPaths``) from any entry: rce's, the default entry's, the 2024 winner's. Finishes are read
from the output's ``events`` ([step, robot, task, errands done]) or, for an entry whose output
leaves them out, from the start-kit's log (``--log``: "[timestep=S] Agent A finishes task T").

An output without paths (the 2024 winner's code leaves them out; ``--no-paths`` treats any output
so) still splits the scheduler's part from the planner's: a robot that finished a task stands on
its last errand, so each cycle's least is taken from there, facing the best way (the heading is
not known), and the steps are counted, not split by action. Two runs compare fairly when both
are read so.

Usage::

    .venv/bin/python bench/lifelong_steps.py PROBLEM.json OUTPUT.json [OUTPUT.json ...] \\
        [--log OUTPUT.json=LOG ...] [--from STEP] [--to STEP] [--no-paths] [--json PATH]
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import OrderedDict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from lifelong_waits import HEADING, actions, replay  # noqa: E402
from startkit_peer import FINISH  # noqa: E402

ROW_BYTES = 512 * 2 ** 20          # the bound of the per-goal maps kept at once


class LeastSteps:
    """The least MAPF_T steps between (cell, heading) states of one grid, per goal and arrival
    heading, with an LRU bound of ``max_bytes`` on the maps kept (each 8 bytes per cell)."""

    def __init__(self, grid, max_bytes: int = ROW_BYTES):
        from rce_fleet.lifelong.distances import DistanceCache, heading_graph
        self.grid = grid
        self.cells = DistanceCache(grid, max_bytes=max(max_bytes // 4, 2 * grid.n_cells * 16))
        self._pred = heading_graph(grid)
        self._rows: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self._keep = max(8, max_bytes // (8 * grid.n_cells))
        self._queue = np.empty(4 * grid.n_cells, dtype=np.int32)

    def _row(self, goal: int, arrive: int) -> np.ndarray:
        from rce_fleet.lifelong.kernels import bfs_fill
        key = (goal, arrive)
        row = self._rows.get(key)
        if row is None:
            row = np.empty(4 * self.grid.n_cells, dtype=np.uint16)
            bfs_fill(self._pred, goal * 4 + arrive, row, self._queue)
            self._rows[key] = row
            if len(self._rows) > self._keep:
                self._rows.popitem(last=False)
        else:
            self._rows.move_to_end(key)
        return row

    def chain(self, cell: int, head: int | None, errands: list[int]) -> tuple[int, int]:
        """(least steps, shortest cells) from ``cell`` facing ``head`` (None: the best way) through
        ``errands`` in order, arriving at each facing any way; the shortest way in cells counts
        moves alone."""
        cost = np.full(4, np.inf)
        if head is None:
            cost[:] = 0.0
        else:
            cost[head] = 0.0
        cur, moves = cell, 0
        for e in errands:
            new = np.array([min(cost[h] + float(self._row(e, a)[cur * 4 + h]) for h in range(4)) for a in range(4)])
            moves += int(self.cells.table[self.cells.slot(e), cur])
            cost, cur = new, e
        return int(cost.min()), moves


def finishes(output: dict, task_errands: list[int], log: Path | None) -> list[tuple[int, int, int]]:
    """Sorted (step, robot, task) of every task finished: from ``events`` where an event's errands
    done reach the task's count (``task_errands``, per line of the task file: task i is line i mod
    their count, revealed cyclically as the start-kit does), else from the start-kit's ``log``. Raises
    ValueError when neither holds a finish."""
    m = len(task_errands)
    got = [(int(s), int(a), int(t)) for s, a, t, k in output.get("events") or []
           if int(t) >= 0 and int(k) == task_errands[int(t) % m]]
    if not got and log is not None:
        got = [tuple(int(x) for x in m.groups()) for m in FINISH.finditer(log.read_text(errors="replace"))]
    if not got:
        raise ValueError("no finished task in the output's events" + ("" if log else " (give the start-kit's --log)"))
    return sorted(got)


def steps_of(problem, output: dict, log: Path | None = None, least: LeastSteps | None = None,
             start: int = 0, end: int | None = None, paths: bool = True) -> dict:
    """The cycles of one run of ``problem`` (:class:`~rce_fleet.lifelong.lorr.LorrProblem`) from its
    start-kit ``output``: {tasks, robot_steps, cycle, least, least_turns, cells, waits, turns, moves,
    turns_beyond, moves_beyond, tail, paths} (sums over the finished tasks' cycles that begin at step
    ``start`` or later and end by step ``end``, in steps: a run that holds robots back at first counts
    their idle steps in their first cycle; ``tail`` the robot-steps after each robot's last finish).
    Without paths (none in the output, or ``paths`` False) the robots' places come from their
    finishes and the split by action is None (the module says how). Raises ValueError for an output
    of another problem (its team, or a robot off the map's free cells)."""
    grid = problem.grid
    paths = paths and bool(output.get("actualPaths"))
    if paths:
        acts = actions(output)
        n, steps = acts.shape
    else:
        n, steps = len(output.get("start") or []), int(output.get("makespan") or 0)
    if n != problem.team_size:
        raise ValueError(f"the output has {n} robots, the problem {problem.team_size}")
    errands = [list(map(int, e)) for e in problem.tasks]
    done = finishes(output, [len(e) for e in errands], log)
    steps = max(steps, done[-1][0])
    least = least or LeastSteps(grid)
    free = grid.flat.reshape(grid.rows, grid.cols)
    at = {}
    if paths:
        need: dict[int, set[int]] = {}
        for s, a, _ in done:
            need.setdefault(s, set()).add(a)
        for t, _, pos, head in replay(free, output["start"], acts):
            for a in (range(n) if t == 0 else need.get(t, ())):
                at[(t, a)] = (int(pos[a, 0]) * grid.cols + int(pos[a, 1]), int(head[a]))
    else:
        for a, (r, c, h) in enumerate(output["start"]):
            if not (0 <= r < grid.rows and 0 <= c < grid.cols and free[r, c]):
                raise ValueError(f"robot {a} starts off the map's free cells, at ({r}, {c})")
            at[(0, a)] = (r * grid.cols + c, HEADING[h])
        for s, a, task in done:
            at[(s, a)] = (errands[task % len(errands)][-1], None)
    last = {a: 0 for a in range(n)}
    out = dict.fromkeys(("cycle", "least", "cells", "waits", "turns", "moves"), 0)
    counted = 0
    for s, a, task in done:
        p = last[a]
        last[a] = s
        if p < start or (end is not None and s > end):
            continue
        counted += 1
        cell, h = at[(p, a)]
        lst, cells = least.chain(cell, h, errands[task % len(errands)])
        out["cycle"] += s - p
        out["least"] += lst
        out["cells"] += cells
        if paths:
            seg = acts[a, p:s]
            out["waits"] += int((seg == ord("W")).sum())
            out["turns"] += int(((seg == ord("R")) | (seg == ord("C"))).sum())
            out["moves"] += int((seg == ord("F")).sum())
    out.update(tasks=counted, start=start, end=end, paths=paths, robot_steps=n * steps,
               tail=sum(steps - s for s in last.values()), least_turns=out["least"] - out["cells"])
    out["turns_beyond"] = out["turns"] - out["least_turns"]
    out["moves_beyond"] = out["moves"] - out["cells"]
    if not paths:
        for k in ("waits", "turns", "moves", "turns_beyond", "moves_beyond"):
            out[k] = None
    return out


def summary(r: dict) -> str:
    """One paragraph of :func:`steps_of`'s counts, per task and as shares of the steps beyond."""
    k = max(1, r["tasks"])
    beyond = max(1, r["cycle"] - r["least"])
    begun = f" begun from step {r['start']:,}" if r.get("start") else ""
    if r.get("end") is not None:
        begun += f" and finished by step {r['end']:,}"
    head = (f"{r['tasks']:,} tasks{begun}; per task {r['cycle'] / k:.1f} steps against the least {r['least'] / k:.1f} "
            f"(stretch {r['cycle'] / max(1, r['least']):.3f})")
    if not r.get("paths", True):
        return (f"{head}, {r['cells'] / k:.1f} cells; read without paths: the least from each finish facing the "
                f"best way, the steps beyond not split")
    return (f"{head}; beyond it per task: waits {r['waits'] / k:.1f}, "
            f"turns {r['turns_beyond'] / k:.1f}, moves {r['moves_beyond'] / k:.1f} "
            f"({r['waits'] / beyond:.0%} / {r['turns_beyond'] / beyond:.0%} / {r['moves_beyond'] / beyond:.0%}); "
            f"after the last finish {r['tail'] / r['robot_steps']:.1%} of the robot-steps")


def _log_arg(text: str) -> tuple[str, Path]:
    out, sep, log = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"expected OUTPUT.json=LOG, got {text!r}")
    return str(Path(out)), Path(log)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("problem", type=Path, help="the problem JSON the runs ran (LoRR 2024 format)")
    ap.add_argument("outputs", type=Path, nargs="+", help="the runs' output JSONs (start-kit format)")
    ap.add_argument("--log", type=_log_arg, action="append", default=[], metavar="OUTPUT.json=LOG",
                    help="the start-kit log of an output whose events are left out")
    ap.add_argument("--from", dest="start", type=int, default=0, metavar="STEP",
                    help="count only the cycles that begin at this step or later (default 0: all)")
    ap.add_argument("--to", dest="end", type=int, metavar="STEP",
                    help="count only the cycles that end by this step (default: all)")
    ap.add_argument("--no-paths", dest="paths", action="store_false",
                    help="read every output as if it had no paths (to compare with one that has none)")
    ap.add_argument("--json", type=Path, help="write the counts of every run here")
    args = ap.parse_args(argv)
    from rce_fleet.lifelong.lorr import load_problem
    logs = dict(args.log)
    rows = {}
    try:
        problem = load_problem(args.problem)
        least = LeastSteps(problem.grid)
        for path in args.outputs:
            r = steps_of(problem, json.loads(path.read_text()), logs.get(str(path)), least, args.start, args.end,
                         args.paths)
            rows[str(path)] = r
            print(f"{path}: {summary(r)}")
    except (OSError, ValueError, KeyError) as e:
        print(f"lifelong_steps: {e}", file=sys.stderr)
        return 2
    if args.json is not None:
        args.json.write_text(json.dumps({"problem": str(args.problem), "runs": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
