"""One-shot MAPF within a time budget: a first solution, then anytime refinement.

The first solution comes from LaCAM (:func:`~.lacam.solve_lacam`, complete) or, with
``initial="pp"``, from prioritized planning (:func:`~.pp.solve_pp`) within a share of the
budget and from LaCAM in the time left when PP finds none; :func:`~.refine.refine_lns` then
improves it until the budget is spent. LaCAM, guided by lacam3's space utilisation
(:mod:`.scatter`), is the default: on the MovingAI warehouse-10-20-10-2-1 with 5 s of CPU
its first solution at 400 agents is closer to the lower bound than PP's (1.18 - 1.23x against
1.34 - 1.38x) and ends lower after LNS (1.05 - 1.06x against 1.05 - 1.07x); at 1000 agents PP
fails and LaCAM takes over (1.63 - 1.77x after LNS). With ``workers=2`` LaCAM runs with two
seeds and LNS on two processes (:mod:`.parallel`), each within the budget of its own clock:
1.60 - 1.66x at 1000 agents, twice the CPU in the wall time of one. Measurements:
``docs/lifelong.md``.
"""
from __future__ import annotations

import time

import numpy as np

from .distances import DistanceCache
from .grid import LifelongGrid
from .lacam import solve_lacam
from .parallel import children_cpu, refine_parallel, solve_lacam_parallel
from .pp import solve_pp
from .refine import refine_lns

__all__ = ["INITIAL_SOLVERS", "plan_one_shot"]

INITIAL_SOLVERS = ("pp", "lacam")


def plan_one_shot(grid: LifelongGrid, starts: np.ndarray, goals: np.ndarray, time_limit_s: float = 5.0,
                  seed: int = 0, cache: DistanceCache | None = None, initial: str = "lacam", pp_share: float = 0.15,
                  scatter_share: float = 0.2, workers: int = 1, clock=time.perf_counter) -> dict:
    """Solve one-shot MAPF (4-neighbour moves) within ``time_limit_s`` seconds of ``clock``
    (wall time; ``time.process_time`` for this process's CPU).

    starts, goals: (n,) cells. ``initial``: "lacam", or "pp" (prioritized planning within
    ``pp_share`` of the budget, LaCAM in the rest when PP fails); LaCAM spends up to
    ``scatter_share`` of its time on :func:`~.scatter.scatter` paths for PIBT to prefer.
    ``workers`` > 1: LaCAM runs once per process with seeds ``seed`` ... ``seed + workers - 1``
    and the best first solution is kept (:func:`~.parallel.solve_lacam_parallel`), and LNS runs
    on that many processes (:func:`~.parallel.refine_parallel`), each process within the budget
    of its own ``clock``; they are forked: call it from a process that may fork.
    Returns the dict of
    :func:`~.lacam.solve_lacam` (``paths`` (T+1, n), ``solved``, ``sum_of_costs``,
    ``makespan``, ``time_s``) plus ``initial`` (the solver of the first solution, "pp" or
    "lacam"), ``first_time_s`` and ``first_sum_of_costs`` (of the first solution),
    ``pp_planned`` (agents PP planned; n when it solved), ``lns_iterations``,
    ``first_tries`` (each LaCAM seed and its sum of costs, None when unsolved) and
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
    cache = cache or DistanceCache(grid, max_bytes=max(2 * grid.n_cells * (n + 16), 64 * 2 ** 20))
    res, planned = None, 0
    if initial == "pp":
        res = solve_pp(grid, starts, goals, pp_share * time_limit_s, seed=seed, cache=cache, clock=clock)
        planned = res["planned"]
        used = "pp"
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
            "worker_cpu_s": children_cpu() - cpu0}
