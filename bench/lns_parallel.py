"""Benchmark LNS alone (rce_fleet.lifelong.refine, .parallel) from one LaCAM first solution.

From the same first solution (LaCAM, seed 0, the first K agents of warehouse-10-20-10-2-1
random-1):

1. The cost of a re-plan: ``--iterations`` LNS iterations with a clock of calls (the same
   neighbourhoods and answers in every run, whatever the machine's load): CPU seconds,
   states expanded, CPU per state, per iteration.
2. Parallel efficiency, per LNS seed: one process with ``--budget`` CPU-seconds and with twice
   that, and two processes (``refine_parallel``, workers=2) with ``--budget`` each (their own
   ``time.process_time``); the ratio (sum of costs / lower bound) of each, and the share of
   the second CPU budget's gain that the second process gets: (r_1 - r_2p) / (r_1 - r_2).

Usage::

    .venv/bin/python bench/lns_parallel.py [--agents 1000] [--budget 4.5] [--seeds 0 1 2]
        [--iterations 6000] [--data ../shared/data] [--json PATH] [--plot PATH]

Results go to ``bench/results/`` by default (lns_parallel.json, lns_parallel.png).
"""
from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

import numpy as np

from common import RESULTS, pyplot, write_json
from lns import first_solution
from planner import DEFAULT_DATA
from rce_fleet.lifelong import LifelongGrid
from rce_fleet.lifelong.lacam import solve_lacam
from rce_fleet.lifelong.parallel import refine_parallel
from rce_fleet.lifelong.refine import Refiner, refine_lns, warm_up
from rce_fleet.planning import load_movingai_map, load_movingai_scen


def replan_cost(grid, paths, goals, cache, iterations: int) -> dict:
    """``iterations`` LNS iterations (seed 0) timed by this process's CPU."""
    ref = Refiner(grid, paths, goals, 0, cache)
    calls = itertools.count(0.0, 1.0)
    c0 = time.process_time()
    ref.improve(iterations + 0.5, lambda: next(calls))
    cpu = time.process_time() - c0
    expanded = int(ref.res.stats[0])
    return {"iterations": ref.iterations, "accepted": ref.accepted, "expanded": expanded, "cpu_s": cpu,
            "us_per_state": 1e6 * cpu / expanded, "ms_per_iteration": 1e3 * cpu / ref.iterations,
            "sum_of_costs": ref.solution()["sum_of_costs"]}


def efficiency(grid, paths, goals, cache, lb: int, budget: float, seed: int) -> dict:
    """One process with ``budget`` and 2 x ``budget`` CPU-s, two processes with ``budget`` each."""
    out = {"seed": seed}
    for name, run in (("one", lambda: refine_lns(grid, paths, goals, budget, seed, cache, clock=time.process_time)),
                      ("one_double", lambda: refine_lns(grid, paths, goals, 2 * budget, seed, cache,
                                                        clock=time.process_time)),
                      ("two", lambda: refine_parallel(grid, paths, goals, budget, workers=2, seed=seed, cache=cache,
                                                      clock=time.process_time))):
        w0 = time.perf_counter()
        r = run()
        out[name] = {"ratio": r["sum_of_costs"] / lb, "iterations": r["iterations"],
                     "wall_s": time.perf_counter() - w0, "worker_cpu_s": r.get("worker_cpu_s", 0.0),
                     "changes": r.get("changes")}
        print(f"  seed {seed} {name:10s} ratio {out[name]['ratio']:.4f} iterations {r['iterations']}", flush=True)
    gain = out["one"]["ratio"] - out["one_double"]["ratio"]
    out["efficiency"] = (out["one"]["ratio"] - out["two"]["ratio"]) / gain if gain > 0 else None
    return out


def plot(result: dict, path: Path) -> None:
    plt = pyplot()
    runs = result["parallel"]
    fig, ax = plt.subplots(figsize=(7, 4))
    x = np.arange(len(runs))
    b = result["budget_s"]
    for i, (key, label) in enumerate((("one", f"1 process, {b:g} CPU-s"), ("two", f"2 processes, {b:g} CPU-s each"),
                                      ("one_double", f"1 process, {2 * b:g} CPU-s"))):
        ax.bar(x + (i - 1) * 0.27, [r[key]["ratio"] for r in runs], 0.27, label=label)
    ax.set_xticks(x, [f"LNS seed {r['seed']}" for r in runs])
    lo = min(r[k]["ratio"] for r in runs for k in ("one", "two", "one_double"))
    ax.set_ylim(lo - 0.05, None)
    ax.set_ylabel("sum of costs / lower bound")
    ax.set_title(f"LNS from one LaCAM solution, {result['agents']} agents (first {result['first_ratio']:.3f}x)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data directory")
    ap.add_argument("--agents", type=int, default=1000)
    ap.add_argument("--budget", type=float, default=4.5, help="CPU-seconds of LNS per process")
    ap.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2], help="LNS seeds")
    ap.add_argument("--iterations", type=int, default=6000, help="LNS iterations for the re-plan cost (0: none)")
    ap.add_argument("--json", type=Path, default=RESULTS / "lns_parallel.json")
    ap.add_argument("--plot", type=Path, default=RESULTS / "lns_parallel.png")
    args = ap.parse_args(argv)
    mapf = args.data / "mapf"
    map_file, scen_file = mapf / "warehouse-10-20-10-2-1.map", mapf / "warehouse-10-20-10-2-1-random-1.scen"
    if not map_file.is_file() or not scen_file.is_file():
        print(f"bench/lns_parallel.py: MovingAI instance not found under {mapf}", file=sys.stderr)
        return 2
    graph = load_movingai_map(map_file)
    scen = load_movingai_scen(scen_file, graph)
    if not 0 < args.agents <= len(scen):
        print(f"bench/lns_parallel.py: --agents must be 1 - {len(scen)}, got {args.agents}", file=sys.stderr)
        return 2
    grid = LifelongGrid.from_graph(graph)
    starts = np.array([s for s, _ in scen[: args.agents]])
    goals = np.array([g for _, g in scen[: args.agents]])
    solve_lacam(grid, starts[:2], goals[:2], scatter_share=0.5)
    warm_up()
    print(f"LaCAM first solution, {args.agents} agents ...", flush=True)
    cache, lb, first = first_solution(grid, starts, goals, 30.0)
    if not first["solved"]:
        print("bench/lns_parallel.py: LaCAM found no first solution", file=sys.stderr)
        return 1
    paths = first["paths"]
    result = {"agents": args.agents, "lower_bound": lb, "first_ratio": first["sum_of_costs"] / lb,
              "budget_s": args.budget}
    print(f"first solution {result['first_ratio']:.4f}x the lower bound", flush=True)
    if args.iterations:
        cost = replan_cost(grid, paths, goals, cache, args.iterations)
        result["replan"] = cost
        print(f"{cost['iterations']} iterations: {cost['cpu_s']:.2f} CPU-s, {cost['expanded']} states, "
              f"{cost['us_per_state']:.3f} us per state, {cost['ms_per_iteration']:.3f} ms per iteration", flush=True)
    result["parallel"] = [efficiency(grid, paths, goals, cache, lb, args.budget, s) for s in args.seeds]
    print(f"\n{'seed':>4} {'1 x B':>8} {'2 x B':>8} {'1 x 2B':>8} {'efficiency':>10}")
    for r in result["parallel"]:
        eff = "-" if r["efficiency"] is None else f"{r['efficiency']:.2f}"
        print(f"{r['seed']:>4} {r['one']['ratio']:8.4f} {r['two']['ratio']:8.4f} {r['one_double']['ratio']:8.4f} "
              f"{eff:>10}")
    write_json(args.json, result)
    print(f"wrote {args.json}")
    args.plot.parent.mkdir(parents=True, exist_ok=True)
    plot(result, args.plot)
    print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
