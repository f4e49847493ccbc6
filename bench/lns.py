"""Benchmark the one-shot LNS (rce_fleet.lifelong.refine) alone, from one saved first solution.

For each instance (MovingAI ``warehouse-10-20-10-2-1``: the first K agents of its
``random-1`` scenario, and random scenarios ``--scen-seeds`` as bench/planner.py draws them),
LaCAM's first solution (seed 0, 5 CPU-s at most) is computed once; then every variant of
:class:`~rce_fleet.lifelong.refine.Refiner` improves a copy of that same solution for
``--cpu`` seconds of this process's CPU, with each LNS seed in ``--seeds``, and the sum of
costs over the lower bound is recorded at the ``--checkpoints`` (CPU seconds). Variants:
``default`` (the refiner's defaults) and ``capped`` (every single re-plan capped at the
group's 5,000 states, ``single_expand=5000``: the peer in the same run). Every final solution
is checked for conflicts step by step (bench/planner.py ``count_conflicts``: must be 0).

``--clock work`` measures the budget and the checkpoints in work instead of CPU: 0.22 us per
state expanded plus 20 us per LNS iteration (the CPU a state and an iteration's Python took
alone, bench/lns_parallel.py). On a machine shared with other jobs the CPU a state costs
varies by 20 % or more from run to run (the searches are memory-bound), which moves a run's
result by as much as a policy change does; on the clock of work a run gives the same result
whatever the load, so policies are compared on the same work.

Usage::

    .venv/bin/python bench/lns.py [--agents 1000] [--scen-seeds 1 2] [--seeds 0 1]
        [--cpu 9] [--checkpoints 2 4 9] [--clock cpu|work] [--data ../shared/data] [--json PATH] [--plot PATH]

Results go to ``bench/results/`` by default (lns.json, lns.png).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from common import RESULTS, pyplot, write_json
from planner import DEFAULT_DATA, count_conflicts, random_scen
from rce_fleet.lifelong import DistanceCache, LifelongGrid
from rce_fleet.lifelong.lacam import solve_lacam
from rce_fleet.lifelong.refine import Refiner, warm_up
from rce_fleet.planning import load_movingai_map, load_movingai_scen

VARIANTS = {"default": {}, "capped": {"single_expand": 5_000}}


def first_solution(grid: LifelongGrid, starts: np.ndarray, goals: np.ndarray,
                   time_limit_s: float = 5.0) -> tuple[DistanceCache, int, dict]:
    """The distance cache, the lower bound (sum of distances) and LaCAM's first solution (seed 0,
    scatter as in the pipeline, within ``time_limit_s`` CPU seconds) that LNS starts from."""
    cache = DistanceCache(grid, max_bytes=2 * grid.n_cells * (len(goals) + 16))
    lb = sum(int(cache.table[cache.slot(int(g)), s]) for s, g in zip(starts, goals, strict=True))
    first = solve_lacam(grid, starts, goals, time_limit_s, seed=0, cache=cache, scatter_share=0.2,
                        clock=time.process_time)
    return cache, lb, first


def run_variant(grid: LifelongGrid, paths: np.ndarray, goals: np.ndarray, cache: DistanceCache, lb: int,
                kwargs: dict, seed: int, checkpoints: list[float], clock: str = "cpu") -> dict:
    """One LNS run from ``paths``: ratio at each checkpoint (seconds of ``clock``: "cpu", this
    process's CPU, or "work", :func:`work_clock`), iterations, conflicts."""
    ref = Refiner(grid, paths, goals, seed, cache, **kwargs)
    tick = time.process_time if clock == "cpu" else work_clock(ref)
    c0, ratios = tick(), {}
    for cp in checkpoints:
        ref.improve(cp - (tick() - c0), tick)
        ratios[cp] = ref.solution()["sum_of_costs"] / lb
    sol = ref.solution()
    return {"ratio": ratios, "iterations": ref.iterations, "accepted": ref.accepted,
            "conflicts": count_conflicts(grid, sol["paths"]), "at_goal": bool((sol["paths"][-1] == goals).all())}


def work_clock(ref: Refiner):
    """A clock of ``ref``'s work (s): 0.22 us per state its searches expanded plus 20 us per
    LNS iteration, the same whatever else runs on the machine."""
    return lambda: ref.res.stats[0] * 0.22e-6 + ref.iterations * 20e-6


def plot(rows: list[dict], path: Path, clock: str = "cpu") -> None:
    """PNG at ``path``: sum of costs / lower bound against CPU seconds, one panel per instance."""
    plt = pyplot()
    names = sorted({(r["scenario"], r["agents"]) for r in rows}, key=str)
    fig, axes = plt.subplots(1, len(names), figsize=(4.5 * len(names), 3.8), squeeze=False)
    for ax, (scen, k) in zip(axes[0], names, strict=True):
        for r in rows:
            if (r["scenario"], r["agents"]) != (scen, k):
                continue
            xs = [float(x) for x in r["ratio"]]
            ax.plot(xs, list(r["ratio"].values()), "o-" if r["variant"] == "default" else "s--",
                    color="C0" if r["variant"] == "default" else "C1", alpha=0.8,
                    label=f"{r['variant']} (seed {r['seed']})")
        ax.axhline(1.3, color="grey", ls="--", lw=0.8)
        ax.set_title(f"{scen}, {k} agents")
        ax.set_xlabel("CPU-s of LNS" if clock == "cpu" else "seconds of work of LNS (0.22 us a state)")
        ax.set_ylabel("sum of costs / lower bound")
        ax.legend(fontsize=7)
    fig.suptitle("LNS from one LaCAM solution, MovingAI warehouse-10-20-10-2-1")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data directory")
    ap.add_argument("--agents", type=int, nargs="+", default=[1000])
    ap.add_argument("--scen-seeds", type=int, nargs="*", default=[1, 2],
                    help="random scenarios of the map besides random-1")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="LNS seeds per instance and variant")
    ap.add_argument("--cpu", type=float, default=9.0, help="CPU seconds of LNS per run")
    ap.add_argument("--checkpoints", type=float, nargs="+", default=[2, 4, 9])
    ap.add_argument("--clock", choices=["cpu", "work"], default="cpu",
                    help="budget and checkpoints in CPU seconds or in seconds of work (states expanded)")
    ap.add_argument("--json", type=Path, default=RESULTS / "lns.json")
    ap.add_argument("--plot", type=Path, default=RESULTS / "lns.png")
    args = ap.parse_args(argv)
    checkpoints = sorted({c for c in args.checkpoints if c < args.cpu} | {args.cpu})
    mapf = args.data / "mapf"
    graph = load_movingai_map(mapf / "warehouse-10-20-10-2-1.map")
    grid = LifelongGrid.from_graph(graph)
    random1 = load_movingai_scen(mapf / "warehouse-10-20-10-2-1-random-1.scen", graph)
    warm_up()
    two = np.array(random1[:2])
    solve_lacam(grid, two[:, 0], two[:, 1], 5.0, scatter_share=0.5)      # compile LaCAM's kernels before the runs
    rows = []
    for k in args.agents:
        scens = [("random-1", random1)]
        scens += [(f"seed {s}", random_scen(graph, k, s)) for s in args.scen_seeds]
        for name, scen in scens:
            starts = np.array([s for s, _ in scen[:k]])
            goals = np.array([g for _, g in scen[:k]])
            cache, lb, first = first_solution(grid, starts, goals)
            if not first["solved"]:
                print(f"{name}, {k} agents: LaCAM found no solution in 5 CPU-s", file=sys.stderr)
                continue
            print(f"{name}, {k} agents: first solution {first['sum_of_costs'] / lb:.4f}x", flush=True)
            for seed in args.seeds:
                for variant, kwargs in VARIANTS.items():
                    r = run_variant(grid, first["paths"], goals, cache, lb, kwargs, seed, checkpoints, args.clock)
                    rows.append({"scenario": name, "agents": k, "first_ratio": first["sum_of_costs"] / lb,
                                 "variant": variant, "seed": seed, **r})
                    print(f"  {variant:8s} seed {seed}: " + "  ".join(f"{c:g} s {v:.4f}" for c, v in r["ratio"].items())
                          + f"  ({r['iterations']} iterations, {r['conflicts']} conflicts)", flush=True)
    write_json(args.json, {"rows": rows, "checkpoints": checkpoints, "clock": args.clock})
    print(f"wrote {args.json}")
    if rows:
        plot(rows, args.plot, args.clock)
        print(f"wrote {args.plot}")
    bad = [r for r in rows if r["conflicts"] or not r["at_goal"]]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
