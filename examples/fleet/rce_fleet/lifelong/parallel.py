"""One-shot MAPF on several cores: LaCAM with other seeds on the other cores, the best first
solution kept (:func:`solve_lacam_parallel`), or restarted on every core until the first
solves (:func:`race_lacam`), and anytime LNS with :class:`~.refine.Refiner`
copies in forked worker processes, each re-planning only its own agents, merged in rounds
(:func:`refine_parallel`; lacam3 refines on several threads, Okumura AAMAS-24; here processes,
as the searches hold the GIL between compiled calls).

Each round every refiner improves its copy for ``round_s`` seconds of its own clock; the
workers send the changes they accepted, in order; the main refiner replays each where its
paths fit (:meth:`~.refine.Refiner.replay`) and sends back the paths of every agent changed in
the round. Agents are owned by goal column, and between sweeps the owners' borders move on.
The work is forked (``multiprocessing``'s "fork" start method, so the compiled kernels and
the instance are inherited, not sent): callers fork only from a process that may fork (no
other threads).
"""
from __future__ import annotations

import itertools
import multiprocessing
import os
import time
from multiprocessing.connection import wait

import numpy as np

from .distances import DistanceCache, one_shot_distances
from .grid import LifelongGrid
from .lacam import solve_lacam
from .refine import Refiner

__all__ = ["children_cpu", "race_lacam", "refine_parallel", "solve_lacam_parallel"]


def _fork(target, *args, **kwargs) -> tuple:
    """``target(conn, *args, **kwargs)`` started on a forked process (the instance and the
    compiled kernels inherited, not sent), ``conn`` its end of a pipe: returns (this end, the
    process)."""
    ctx = multiprocessing.get_context("fork")
    here, there = ctx.Pipe()
    p = ctx.Process(target=target, args=(there, *args), kwargs=kwargs, daemon=True)
    p.start()
    there.close()
    return here, p


def _worker(conn, ref: Refiner, clock) -> None:
    """Serve rounds until told to stop: (seconds, the merged paths of the agents changed in the
    last round: agents, paths, lengths) in, (this round's accepted changes, iterations) out."""
    try:
        while True:
            msg = conn.recv()
            if msg is None:
                break
            seconds, own, changed = msg
            ref.own = own
            ref.sync(*changed)
            ref.log = []
            ref.improve(seconds, clock)
            conn.send((ref.log, ref.iterations))
    finally:
        conn.close()


def refine_parallel(grid: LifelongGrid, paths: np.ndarray, goals: np.ndarray, time_limit_s: float,
                    workers: int = 2, round_s: float = 0.02, seed: int = 0, cache: DistanceCache | None = None,
                    clock=time.perf_counter) -> dict:
    """:func:`~.refine.refine_lns` on ``workers`` processes (this one and ``workers`` - 1
    forked): the same arguments and result (``iterations`` summed over the processes), plus
    ``changes`` (the workers' accepted changes replayed here, and all of them),
    ``workers_lost`` (workers that died: the changes of their last round are lost, their
    agents go to the others) and ``worker_cpu_s`` (the workers' CPU seconds). Each process
    spends ``time_limit_s`` seconds of its own ``clock``: with ``time.process_time`` the CPU of
    all of them together is up to ``workers`` x ``time_limit_s``. Agents are owned by goal
    column (each process a run of the agents in the order of their goals' columns, the runs
    moved on between sweeps). Raises ValueError when the last row of ``paths`` is not
    ``goals`` or ``workers`` < 1."""
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    t0, cpu0 = clock(), children_cpu()
    ref = Refiner(grid, paths, goals, seed=seed, cache=cache)
    n = ref.goals.shape[0]
    rank = np.argsort(np.argsort(ref.goals % grid.free.shape[1], kind="stable"))
    live = []                                  # [pipe, process, its iterations] per worker
    for w in range(1, workers):
        ref.rng = np.random.default_rng([seed, w])
        live.append([*_fork(_worker, ref, clock), 0])
    ref.rng = np.random.default_rng([seed, 0])
    applied = changes = rounds = 0
    gone: list[list] = []
    shift = max(n // (8 * workers), 1)         # the owners' borders move on by this many agents each round
    none = np.zeros(0, dtype=np.int64)
    changed = (none, ref.res.paths[none], ref.res.lengths[none])
    try:
        while True:
            left = time_limit_s - (clock() - t0)
            if left <= 0.01:
                break
            if not live:                       # every worker lost: this process owns all
                ref.own = np.ones(n, dtype=bool)
                ref.improve(left, clock)
                break
            seconds = min(round_s, left)
            if not ref.queue:                  # between sweeps: the owners' borders move on
                rounds += 1
            owner = (rank + rounds * shift) % n * (1 + len(live)) // n
            lost = []
            for w, entry in enumerate(live, 1):
                try:
                    entry[0].send((seconds, owner == w, changed))
                except OSError:
                    lost.append(entry)
            ref.own = owner == 0
            ref.log = []
            ref.improve(seconds, clock)
            touched = [g for g, _, _ in ref.log]
            for entry in live:
                if entry in lost:
                    continue
                try:
                    log, entry[2] = entry[0].recv()
                except (EOFError, OSError):    # the worker died: its round is lost, its agents go to the others
                    lost.append(entry)
                    continue
                applied += ref.replay(log)
                changes += len(log)
                touched += [g for g, _, _ in log]
            for entry in lost:
                live.remove(entry)
                gone.append(entry)
                entry[0].close()
                entry[1].join()
            agents = np.unique(np.concatenate(touched)) if touched else none
            changed = (agents, ref.res.paths[agents], ref.res.lengths[agents])
    finally:
        for link, p, _ in live:
            try:
                link.send(None)
            except OSError:
                pass                           # it died meanwhile
            link.close()
            p.join()
    return {**ref.solution(), "iterations": ref.iterations + sum(e[2] for e in live + gone),
            "accepted": ref.accepted, "changes": (applied, changes), "workers_lost": len(gone),
            "expanded": int(ref.res.stats[0]), "time_s": clock() - t0, "worker_cpu_s": children_cpu() - cpu0}


def _lacam(conn, *args, **kwargs) -> None:
    try:
        conn.send(solve_lacam(*args, **kwargs))
    finally:
        conn.close()


def solve_lacam_parallel(grid: LifelongGrid, starts: np.ndarray, goals: np.ndarray, time_limit_s: float = 5.0,
                         seeds: tuple[int, ...] = (0, 1), cache: DistanceCache | None = None,
                         scatter_share: float = 0.0, clock=time.perf_counter) -> dict:
    """:func:`~.lacam.solve_lacam` once per seed, the first here and each other on a forked
    process, each within ``time_limit_s`` seconds of its own ``clock``: the solved result of
    least sum of costs (the first seed's when none solved), plus ``tries`` ((seed, sum of
    costs or None when unsolved) per seed). Raises as :func:`~.lacam.solve_lacam`."""
    kwargs = {"cache": cache, "scatter_share": scatter_share, "clock": clock}
    forked = [_fork(_lacam, grid, starts, goals, time_limit_s, seed=s, **kwargs) for s in seeds[1:]]
    links, procs = [link for link, _ in forked], [p for _, p in forked]
    try:
        results = [solve_lacam(grid, starts, goals, time_limit_s, seed=seeds[0], **kwargs)]
        for link in links:
            try:
                results.append(link.recv())
            except EOFError:                   # the child failed (it raised as this process did not) or died
                results.append({"solved": False, "sum_of_costs": None})
    finally:
        for link in links:
            link.close()
        for p in procs:
            p.join()
    solved = [r for r in results if r["solved"]] or results[:1]
    best = min(solved, key=lambda r: r["sum_of_costs"])
    tries = [(s, r["sum_of_costs"] if r["solved"] else None) for s, r in zip(seeds, results, strict=True)]
    return {**best, "tries": tries}


def _restarts(grid: LifelongGrid, starts: np.ndarray, goals: np.ndarray, time_limit_s: float, runs, clock,
              report, **kwargs) -> dict | None:
    """:func:`~.lacam.solve_lacam` for each (seed, node cap) of ``runs`` in turn, until one
    solves or ``time_limit_s`` seconds of ``clock`` are spent; ``report(seed, result or None)``
    after each (None: unsolved). Returns the solved result or None."""
    t0 = clock()
    for s, cap in runs:
        left = time_limit_s - (clock() - t0)
        if left <= 0:
            break
        r = solve_lacam(grid, starts, goals, left, seed=s, max_nodes=cap, clock=clock, **kwargs)
        report(s, r if r["solved"] else None)
        if r["solved"]:
            return r
    return None


def _race(conn, *args, **kwargs) -> None:
    try:
        _restarts(*args, report=lambda s, r: conn.send((s, r)), **kwargs)
    finally:
        conn.close()


def race_lacam(grid: LifelongGrid, starts: np.ndarray, goals: np.ndarray, time_limit_s: float, seed: int = 0,
               workers: int = 1, cache: DistanceCache | None = None, cap: float = 3.0, growth: float = 1.25,
               clock=time.perf_counter, **kwargs) -> dict:
    """LaCAM restarted with new seeds under growing node caps, on ``workers`` processes, the
    first solution wins: restarts cut the heavy tail of randomised search (Gomes, Selman and
    Kautz, AAAI-98), and a LaCAM run that solves quickly is a PIBT rollout with little
    backtracking, whose paths are also the shortest. Measured at 1000 agents on the MovingAI
    warehouse along one-way lanes to the end (``bench/lacam_restarts.py --tail-share 0``, 12
    instances x 10 seeds): the runs that solved within 3x the longest start-goal distance in
    nodes ended at 1.69 - 1.93x the lower bound, those that took 3 - 10x at 1.82 - 2.80x, and 0
    - 6 of an instance's 10 seeds did not solve in 10x. With the shortest ways in the tail
    (:func:`~.lacam.solve_lacam`'s ``tail_share``) nearly every first run solves there; the
    restarts stay the guard for maps and crowds where runs do not.

    Process ``w`` (0 ... ``workers`` - 1) runs the seeds ``seed + w``, ``seed + w +
    workers``, ...; its ``j``-th run is capped at ``cap`` x ``growth`` ** ``j`` x the longest
    start-goal distance high-level nodes (:func:`~.lacam.solve_lacam`'s ``max_nodes``: a run
    generates about one node per step of its makespan), so a map where solutions take longer
    still gets them. Each process stops after ``time_limit_s`` seconds of its own ``clock``.
    With ``workers`` > 1 every run is on a forked process (the distances are computed here
    first, and inherited), the others are stopped once one has solved: call it from a process
    that may fork. ``kwargs`` (e.g. ``guide``, ``noise``) go to every run.

    Returns the solved result (a dict as :func:`~.lacam.solve_lacam`; ``{"solved": False,
    "sum_of_costs": None}`` when none solved) plus ``tries``: (seed, sum of costs or None) of
    every run that ended, in the order they ended. Raises ValueError for ``cap`` < 0 or
    ``growth`` < 1, and as :func:`~.lacam.solve_lacam`.
    """
    if cap < 0 or growth < 1:
        raise ValueError(f"race_lacam needs cap >= 0 and growth >= 1, got cap={cap}, growth={growth}")
    starts, goals, cache, _, d0 = one_shot_distances(grid, starts, goals, cache)
    if isinstance(kwargs.get("guide"), DistanceCache):   # the guide's rows once, for every run
        kwargs["guide"] = kwargs["guide"].rows(goals)
    base = cap * max(int(d0.max()) if d0.size else 1, 1)
    tries: list[tuple[int, int | None]] = []
    won: list[dict] = []

    def record(s: int, r: dict | None) -> None:
        tries.append((s, r["sum_of_costs"] if r is not None else None))
        if r is not None:
            won.append(r)

    def runs(w: int):
        return ((seed + w + j * workers, int(base * growth ** min(j, 200))) for j in itertools.count())

    if workers <= 1:
        _restarts(grid, starts, goals, time_limit_s, runs(0), clock, record, cache=cache, **kwargs)
    else:
        forked = [_fork(_race, grid, starts, goals, time_limit_s, runs(w), clock, cache=cache, **kwargs)
                  for w in range(workers)]
        links, procs = [link for link, _ in forked], [p for _, p in forked]
        try:
            pending = list(links)
            while pending and not won:
                for link in wait(pending):
                    try:
                        record(*link.recv())
                    except EOFError:           # the process ended (or died): no more runs from it
                        pending.remove(link)
        finally:
            for p in procs:
                p.kill()                       # still searching: a solution is in
            for link in links:
                link.close()
            for p in procs:
                p.join()
    best = min(won, key=lambda r: r["sum_of_costs"]) if won else {"solved": False, "sum_of_costs": None}
    return {**best, "tries": tries}


def children_cpu() -> float:
    """CPU seconds of this process's waited-for children."""
    t = os.times()
    return t.children_user + t.children_system
