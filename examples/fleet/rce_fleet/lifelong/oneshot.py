"""One-shot MAPF within a time budget: a first solution, then anytime refinement.

The first solution comes from LaCAM (:func:`~.lacam.solve_lacam`, complete) or, with
``initial="pp"``, from prioritized planning (:func:`~.pp.solve_pp`) within a share of the
budget and from LaCAM in the time left when PP finds none; :func:`~.refine.refine_lns` then
improves it until the budget is spent. LaCAM, guided by lacam3's space utilisation
(:mod:`.scatter`), is the default: on the MovingAI warehouse-10-20-10-2-1 with 5 s of CPU
its first solution at 400 agents is closer to the lower bound than PP's (1.18 - 1.23x against
1.34 - 1.38x) and ends lower after LNS (1.05 - 1.06x against 1.05 - 1.07x).

In a crowd (at least ``lane_density`` agents per free cell) on a map of one-cell corridors,
LaCAM first runs without scatter, its PIBT following one-way lanes (:mod:`.guidance`, the
lifelong planner's crisscross guidance: a move against a corridor's lane costs 1 + ``lanes``),
restarted with new seeds under growing node caps until one solves
(:func:`~.parallel.race_lacam`), and LaCAM with scatter only runs when none solves within
``lane_share`` of the budget. Agents meeting head-on in a corridor are what congests PIBT at
high density; along the lanes the first solution comes sooner and closer to the lower bound
(at 1000 agents, 0.175 per free cell: 1.70 - 1.78x in 0.2 - 0.4 s on two processes, against
1.85 - 1.99x in 1.1 - 1.4 CPU-s with scatter); below about 0.17 per free cell they did not
pay (measured before PIBT took the shortest ways in the tail). With ``workers=2`` LNS runs on two processes
(:mod:`.parallel`), and LaCAM with scatter, where it runs, with two seeds; each process within
the budget of its own clock. Measurements: ``docs/lifelong.md``.
"""
from __future__ import annotations

import time

import numpy as np

from .distances import DistanceCache
from .grid import LifelongGrid
from .guidance import lane_costs
from .lacam import solve_lacam
from .parallel import children_cpu, race_lacam, refine_parallel, solve_lacam_parallel
from .pp import solve_pp
from .refine import refine_lns

__all__ = ["INITIAL_SOLVERS", "plan_one_shot"]

INITIAL_SOLVERS = ("pp", "lacam")


def plan_one_shot(grid: LifelongGrid, starts: np.ndarray, goals: np.ndarray, time_limit_s: float = 5.0,
                  seed: int = 0, cache: DistanceCache | None = None, initial: str = "lacam", pp_share: float = 0.15,
                  scatter_share: float = 0.2, workers: int = 1, lanes: int = 2, lane_density: float = 0.17,
                  lane_share: float = 0.3, clock=time.perf_counter) -> dict:
    """Solve one-shot MAPF (4-neighbour moves) within ``time_limit_s`` seconds of ``clock``
    (wall time; ``time.process_time`` for this process's CPU).

    starts, goals: (n,) cells. ``initial``: "lacam", or "pp" (prioritized planning within
    ``pp_share`` of the budget, LaCAM in the rest when PP fails); LaCAM spends up to
    ``scatter_share`` of its time on :func:`~.scatter.scatter` paths for PIBT to prefer.
    With n >= ``lane_density`` x the free cells and ``lanes`` > 0 on a map with one-cell
    corridors, LaCAM along one-way lanes (a move against a lane costing 1 + ``lanes``, no
    scatter) runs first, restarted with new seeds under growing node caps on ``workers``
    processes within ``lane_share`` of the budget (:func:`~.parallel.race_lacam`), and the first
    solution wins; LaCAM with scatter (as below) runs only when none solves, in the time left.
    ``workers`` > 1: LaCAM runs once per process with seeds ``seed`` ... ``seed + workers - 1``
    and the best first solution is kept (:func:`~.parallel.solve_lacam_parallel`), and LNS runs
    on that many processes (:func:`~.parallel.refine_parallel`), each process within the budget
    of its own ``clock``; they are forked: call it from a process that may fork.
    Returns the dict of
    :func:`~.lacam.solve_lacam` (``paths`` (T+1, n), ``solved``, ``sum_of_costs``,
    ``makespan``, ``time_s``) plus ``initial`` (the solver of the first solution, "pp" or
    "lacam", or "lacam lanes"), ``first_time_s`` and ``first_sum_of_costs`` (of the first solution),
    ``pp_planned`` (agents PP planned; n when it solved), ``lns_iterations``,
    ``first_tries`` (each LaCAM-with-scatter seed and its sum of costs, None when unsolved;
    empty when it did not run), ``lane_tries`` (the same for the lanes) and
    ``worker_cpu_s`` (CPU seconds of the forked processes, 0 with one). Raises
    ValueError for an unknown ``initial``, a goal that cannot be reached, or two agents on
    one start or goal.
    """
    if initial not in INITIAL_SOLVERS:
        raise ValueError(f"initial must be one of {INITIAL_SOLVERS}, got {initial!r}")
    t0, cpu0 = clock(), children_cpu()
    starts = np.asarray(starts, dtype=np.int64)
    goals = np.asarray(goals, dtype=np.int64)
    n = starts.shape[0]
    if cache is None:                          # an empty cache is falsy (len 0) but is the one to use
        cache = DistanceCache(grid, max_bytes=max(2 * grid.n_cells * (n + 16), 64 * 2 ** 20))
    res, planned = None, 0
    if initial == "pp":
        res = solve_pp(grid, starts, goals, pp_share * time_limit_s, seed=seed, cache=cache, clock=clock)
        planned = res["planned"]
        used = "pp"
    lane_res, lane_tries_out = None, []
    if (res is None or not res["solved"]) and lanes > 0 and n >= lane_density * grid.free_cells().shape[0]:
        lane_res, lane_tries_out = _lane_lacam(grid, starts, goals, cache, lanes, lane_share * time_limit_s, seed,
                                               clock, workers)
        if lane_res is not None:
            res, used = lane_res, "lacam lanes"
    if res is None or not res["solved"]:
        if workers > 1:
            res = solve_lacam_parallel(grid, starts, goals, time_limit_s - (clock() - t0),
                                       seeds=tuple(seed + k for k in range(workers)), cache=cache,
                                       scatter_share=scatter_share, clock=clock)
        else:
            res = solve_lacam(grid, starts, goals, time_limit_s - (clock() - t0), seed=seed, cache=cache,
                              scatter_share=scatter_share, clock=clock)
        used = "lacam"
    first_t, first_soc = clock() - t0, res["sum_of_costs"]
    iterations = 0
    left = time_limit_s - first_t
    if res["solved"] and left > 0:
        if workers > 1:
            ref = refine_parallel(grid, res["paths"], goals, left, workers=workers, seed=seed, cache=cache,
                                  clock=clock)
        else:
            ref = refine_lns(grid, res["paths"], goals, left, seed=seed, cache=cache, clock=clock)
        res = {**res, "paths": ref["paths"], "sum_of_costs": ref["sum_of_costs"], "makespan": ref["makespan"]}
        iterations = ref["iterations"]
    return {**res, "time_s": clock() - t0, "initial": used, "first_time_s": first_t,
            "first_sum_of_costs": first_soc, "pp_planned": planned, "lns_iterations": iterations,
            "first_tries": res.get("tries", [(seed, first_soc if res["solved"] else None)] if used == "lacam" else []),
            "lane_tries": lane_tries_out,
            "worker_cpu_s": children_cpu() - cpu0}


def _lane_lacam(grid: LifelongGrid, starts: np.ndarray, goals: np.ndarray, cache: DistanceCache, against: int,
                time_limit_s: float, seed: int, clock, workers: int = 1) -> tuple[dict | None, list]:
    """LaCAM without scatter, PIBT following one-way lanes (:func:`~.guidance.lane_costs`,
    a move against a lane costing 1 + ``against``), restarted with the seeds ``seed``,
    ``seed + 1``, ... on ``workers`` processes within ``time_limit_s`` seconds of ``clock``
    (:func:`~.parallel.race_lacam`). Returns the first solved result (None when none solved
    or the map has no lanes) and each run's (seed, sum of costs or None)."""
    cost = lane_costs(grid, against=against)
    if not (cost > 1).any():
        return None, []
    guide = DistanceCache(grid, max_bytes=cache.table.nbytes, cost=cost)
    r = race_lacam(grid, starts, goals, time_limit_s, seed=seed, workers=workers, cache=cache, clock=clock,
                   guide=guide)
    best = {key: v for key, v in r.items() if key != "tries"} if r["solved"] else None
    return best, r["tries"]
