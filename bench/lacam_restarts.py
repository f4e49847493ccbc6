"""Benchmark LaCAM along one-way lanes run by run: the data behind race_lacam's node caps.

For each instance (MovingAI ``warehouse-10-20-10-2-1``: the first K agents of its
``random-1`` scenario, and random scenarios ``--scen-seeds`` as bench/planner.py draws them),
:func:`~rce_fleet.lifelong.lacam.solve_lacam` along the one-way lanes that
:func:`~rce_fleet.lifelong.oneshot.plan_one_shot` uses in a crowd runs once per seed in
``--seeds``, capped at ``--max-cap`` x the longest start-goal distance high-level nodes. Each
run gives whether it solved, its nodes over that distance (a run that solves generates about
one node per step of its makespan) and its sum of costs over the lower bound. The table gives
per instance how many runs solved within ``--cap`` x the distance and what they and the
slower ones cost; ``race_lacam`` restarts a run that has not solved within its cap
(``--cap`` x 1.25 ** j for a process's j-th run).

Usage::

    .venv/bin/python bench/lacam_restarts.py [--agents 1000] [--scen-seeds 1 2 3 4 5 6 7 8 9 10 11]
        [--seeds 10] [--cap 3] [--max-cap 10] [--tail-share 0.2] [--lanes 2] [--data ../shared/data]
        [--json PATH] [--plot PATH]

Results go to ``bench/results/`` by default (lacam_restarts.json, lacam_restarts.png: each run's
sum of costs over the lower bound against its nodes over the longest distance).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from common import RESULTS, console, pyplot, write_json
from planner import DEFAULT_DATA, random_scen
from rce_fleet.lifelong import DistanceCache, LifelongGrid
from rce_fleet.lifelong.distances import one_shot_distances
from rce_fleet.lifelong.guidance import lane_costs
from rce_fleet.lifelong.kernels import warm_up
from rce_fleet.lifelong.lacam import solve_lacam
from rce_fleet.planning import load_movingai_map, load_movingai_scen


def run_instance(grid: LifelongGrid, starts: np.ndarray, goals: np.ndarray, seeds: int, max_cap: float,
                 tail_share: float = 0.2, against: int = 2) -> dict:
    """``seeds`` LaCAM runs along the lanes (a move against a lane costing 1 + ``against``;
    the shortest ways once at most ``tail_share`` of the agents are off their goals), each
    capped at ``max_cap`` x the longest start-goal distance nodes: per run (seed, solved,
    nodes / longest distance, sum of costs / lower bound or None, CPU seconds)."""
    cache = DistanceCache(grid, max_bytes=2 * grid.n_cells * (len(goals) + 16))
    _, _, _, _, d0 = one_shot_distances(grid, starts, goals, cache)
    lb, longest = int(d0.sum()), max(int(d0.max()), 1)
    guide = DistanceCache(grid, max_bytes=cache.table.nbytes, cost=lane_costs(grid, against=against))
    rows = guide.rows(goals)
    runs = []
    for s in range(seeds):
        c0 = time.process_time()
        r = solve_lacam(grid, starts, goals, 60.0, seed=s, cache=cache, guide=rows, tail_share=tail_share,
                        max_nodes=int(max_cap * longest))
        runs.append({"seed": s, "solved": r["solved"], "nodes": r["nodes"] / longest,
                     "ratio": r["sum_of_costs"] / lb if r["solved"] else None, "cpu_s": time.process_time() - c0})
    return {"longest": longest, "lower_bound": lb, "runs": runs}


def plot(rows: list[dict], path: Path, cap: float) -> None:
    """PNG at ``path``: each solved run's sum of costs / lower bound against its nodes / longest
    distance, one colour per instance, and the first cap."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for k, row in enumerate(rows):
        solved = [r for r in row["runs"] if r["solved"]]
        ax.scatter([r["nodes"] for r in solved], [r["ratio"] for r in solved], s=14, color=f"C{k % 10}",
                   label=row["scenario"])
    ax.axvline(cap, color="grey", ls="--", lw=0.8, label=f"first cap ({cap:g}x)")
    ax.set_xlabel("high-level nodes / longest start-goal distance")
    ax.set_ylabel("sum of costs / lower bound")
    ax.set_title("LaCAM along one-way lanes, one point per solved run")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data directory")
    ap.add_argument("--agents", type=int, default=1000)
    ap.add_argument("--scen-seeds", type=int, nargs="*", default=list(range(1, 12)),
                    help="random scenarios of the map besides random-1")
    ap.add_argument("--seeds", type=int, default=10, help="LaCAM seeds per instance")
    ap.add_argument("--cap", type=float, default=3.0, help="race_lacam's first cap, x the longest distance")
    ap.add_argument("--max-cap", type=float, default=10.0, help="each run's cap, x the longest distance")
    ap.add_argument("--tail-share", type=float, default=0.2,
                    help="the share of agents off their goals from which the lanes give way to the shortest ways"
                         " (0: lanes to the end)")
    ap.add_argument("--lanes", type=int, default=2,
                    help="a move against a lane costs 1 + LANES (plan_one_shot's lanes)")
    ap.add_argument("--json", type=Path, default=RESULTS / "lacam_restarts.json")
    ap.add_argument("--plot", type=Path, default=RESULTS / "lacam_restarts.png")
    args = ap.parse_args(argv)
    mapf = args.data / "mapf"
    graph = load_movingai_map(mapf / "warehouse-10-20-10-2-1.map")
    grid = LifelongGrid.from_graph(graph)
    random1 = load_movingai_scen(mapf / "warehouse-10-20-10-2-1-random-1.scen", graph)
    warm_up()
    scens = [("random-1", random1)] + [(f"seed {s}", random_scen(graph, args.agents, s)) for s in args.scen_seeds]
    con = console()
    rows = []
    for name, scen in scens:
        pairs = np.array(scen[:args.agents])
        row = {"scenario": name, "agents": args.agents,
               **run_instance(grid, pairs[:, 0], pairs[:, 1], args.seeds, args.max_cap, args.tail_share, args.lanes)}
        rows.append(row)
        fast = [r["ratio"] for r in row["runs"] if r["solved"] and r["nodes"] <= args.cap]
        slow = [r["ratio"] for r in row["runs"] if r["solved"] and r["nodes"] > args.cap]
        row["summary"] = {"fast": len(fast), "slow": len(slow), "unsolved": args.seeds - len(fast) - len(slow)}
        span = lambda xs: f"{min(xs):.2f} - {max(xs):.2f}" if xs else "-"  # noqa: E731
        con.print(f"{name}: {len(fast)} of {args.seeds} solved within {args.cap:g}x ({span(fast)}), "
                  f"{len(slow)} within {args.max_cap:g}x ({span(slow)}), {row['summary']['unsolved']} not")
    solved = [r for row in rows for r in row["runs"] if r["solved"]]
    fast = [r["ratio"] for r in solved if r["nodes"] <= args.cap]
    total = len(rows) * args.seeds
    con.print(f"all: {len(fast)} of {total} runs solved within {args.cap:g}x"
              + (f" ({min(fast):.2f} - {max(fast):.2f}, mean {sum(fast) / len(fast):.3f})" if fast else "")
              + f", {len(solved) - len(fast)} within {args.max_cap:g}x, {total - len(solved)} not")
    write_json(args.json, {"rows": rows, "cap": args.cap, "max_cap": args.max_cap, "tail_share": args.tail_share,
                           "lanes": args.lanes})
    plot(rows, args.plot, args.cap)
    con.print(f"wrote {args.json} and {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
