"""One-shot MAPF by LaCAM: a depth-first search over configurations whose successors PIBT
generates under constraints (Okumura, "LaCAM: search-based algorithm for quick multi-agent
pathfinding", AAAI-23). Complete: when PIBT would repeat a configuration, the low-level
constraint tree of the current node imposes next cells on agents one by one until a new
successor appears, so corridor livelocks that stop plain PIBT are left.

4-neighbour moves; distances are the per-goal breadth-first maps of
:class:`~.distances.DistanceCache`; the successor generator is the compiled
:func:`~.kernels.pibt_step` (with LaCAM*'s swap technique), optionally guided by lacam3's
space utilisation (:mod:`.scatter`). Agents that stop coming closer to their goals get
noisy tie-breaks, as in the lifelong planner: PIBT otherwise leaves a few agents waiting a few
cells from their goals for hundreds of steps while the rest of the configuration keeps
changing, so no configuration repeats and the search never backtracks (measured on the
MovingAI warehouse at 1000 agents with scatter: first solutions 1.88 - 2.00x the lower bound
and makespans 294 - 395, against 2.09 - 2.10x and 525 - 735 without).
"""
from __future__ import annotations

import time
from collections import deque

import numpy as np

from .distances import DistanceCache, one_shot_distances
from .grid import LifelongGrid
from .kernels import NO_PREFER, lacam_child, pibt_step
from .scatter import scatter

__all__ = ["solve_lacam"]


class _Constraint:
    """A low-level node: agent ``who`` must go to ``where``, on top of ``parent``'s constraints."""

    __slots__ = ("depth", "parent", "where", "who")

    def __init__(self, parent, who: int, where: int):
        self.parent, self.who, self.where = parent, who, where
        self.depth = 0 if parent is None else parent.depth + 1


class _Node:
    """A high-level node: a configuration, its parent, the agents' priorities and order, each
    agent's least distance to its goal so far and the configurations since it last fell, and
    the queue of low-level constraints still to try."""

    __slots__ = ("best", "config", "order", "parent", "prio", "stuck", "tree")

    def __init__(self, config: np.ndarray, parent, prio: np.ndarray, best: np.ndarray, stuck: np.ndarray,
                 order: np.ndarray | None = None):
        self.config, self.parent, self.prio = config, parent, prio
        self.best, self.stuck = best, stuck
        self.order = np.argsort(-prio, kind="stable").astype(np.int64) if order is None else order
        self.tree: deque = deque([_Constraint(None, -1, -1)])


def solve_lacam(grid: LifelongGrid, starts: np.ndarray, goals: np.ndarray, time_limit_s: float = 5.0, seed: int = 0,
                cache: DistanceCache | None = None, scatter_share: float = 0.0, stuck_steps: int = 20,
                noise: float = 100.0, guide: DistanceCache | np.ndarray | None = None, tail_share: float = 0.2,
                max_nodes: int | None = None, clock=time.perf_counter) -> dict:
    """Solve one-shot MAPF (every agent from its start to its goal, 4-neighbour moves).

    starts, goals: (n,) cells. ``scatter_share``: the share of ``time_limit_s`` for lacam3's
    space utilisation (:func:`~.scatter.scatter`: near-shortest paths that avoid each other,
    whose next cells PIBT tries first; 0 turns it off). An agent that has not come closer to
    its goal for ``stuck_steps`` configurations (along the search's path) gets PIBT's
    tie-breaks scaled by ``noise`` (the lifelong planner's random walk out of a jam; 0 turns it
    off). ``guide``: distances PIBT follows instead of ``cache``'s breadth-first ones (a
    :class:`~.distances.DistanceCache` with move costs, e.g. :func:`~.guidance.lane_costs`'s
    one-way lanes, or its rows for ``goals``, (n, cells) uint16 in their order, to share among
    runs); progress (``stuck_steps``) is still counted in steps to the goal. Once at most
    ``tail_share`` of the agents are off their goals, PIBT follows ``cache``'s distances again:
    the guide's detours pay in a crowd, and in the tail they only keep the last agents
    wandering among parked ones. At 1000 agents on the MovingAI warehouse along one-way lanes
    (``bench/lacam_restarts.py``, 12 instances x 10 seeds), from 0.2 on all 120 runs solved
    within 3x the longest start-goal distance in nodes, at 1.68 - 1.83x the lower bound, against
    49 at 1.69 - 1.93x with the lanes to the end (23 did not solve within 10x); on 11 other
    instances 119 of 120 against 24.
    ``max_nodes``: stop unsolved once the search has generated more high-level nodes (a cap for
    restarts, :func:`~.parallel.race_lacam`; None: no cap).
    Returns a dict as
    :func:`~.pibt.solve_one_shot`: ``paths`` ((T+1, n) cells, the last row the goals when
    ``solved``), ``solved``, ``sum_of_costs`` (each agent's last arrival, summed),
    ``makespan``, ``time_s``, plus ``nodes`` (high-level nodes generated) and ``scatter``
    (:func:`~.scatter.scatter`'s stats, empty when off). Stops unsolved at ``time_limit_s``
    seconds of ``clock`` (wall time; ``time.process_time`` counts this process's CPU, for
    benchmarks on a shared machine). Raises ValueError for a goal that cannot be reached from
    its start or two agents on one start or goal.
    """
    t0 = clock()
    starts, goals, cache, slot, d0 = one_shot_distances(grid, starts, goals, cache)
    n = starts.shape[0]
    rng = np.random.default_rng(seed)
    nbr, table = grid.nbr, cache.table
    step_table, step_slot = table, slot
    if guide is not None:                      # PIBT follows the guide's rows, in the goals' order
        step_table = guide.rows(goals) if isinstance(guide, DistanceCache) else guide
        step_slot = np.arange(n, dtype=np.int64)
    prefer, sc = NO_PREFER, {}
    if scatter_share > 0 and n:
        prefer, sc = scatter(nbr, table, slot, starts, goals, scatter_share * time_limit_s, seed=seed, clock=clock)
    head = np.full(n, -1, dtype=np.int64)
    no_claim = np.full(n, -1, dtype=np.int64)
    owner = np.full(grid.n_cells, -1, dtype=np.int64)
    root = _Node(starts.copy(), None, d0.astype(float) / max(1, int(d0.max())), d0.astype(np.int64),
                 np.zeros(n, dtype=np.int64))
    explored = {starts.tobytes(): root}
    stack = [root]
    goal_key = goals.tobytes()
    found = None
    nxt = np.empty(n, dtype=np.int64)
    cap = max_nodes if max_nodes is not None else float("inf")
    tail = int(tail_share * n)
    while stack and clock() - t0 < time_limit_s and len(explored) <= cap:
        node = stack[-1]
        if node.config.tobytes() == goal_key:
            found = node
            break
        if not node.tree:
            stack.pop()
            continue
        con = node.tree.popleft()
        if con.depth < n:
            i = int(node.order[con.depth])
            u = int(node.config[i])
            cands = [u] + [int(v) for v in nbr[u] if v >= 0]
            rng.shuffle(cands)
            for v in cands:
                node.tree.append(_Constraint(con, i, v))
        fixed = np.full(n, -1, dtype=np.int64)
        c = con
        while c is not None and c.who >= 0:
            fixed[c.who] = c.where
            c = c.parent
        rnd = rng.random((n, 5))
        if noise > 0:
            rnd[node.stuck > stuck_steps] *= noise
        follow = (step_table, step_slot)
        if guide is not None and np.count_nonzero(node.config != goals) <= tail:   # the tail: shortest ways
            follow = (table, slot)
        pibt_step(nbr, node.config, head, *follow, goals, node.order, False, 0.0, rnd, nxt, True, no_claim, fixed,
                  prefer)
        key = nxt.tobytes()
        if key in explored:
            continue
        # constraints PIBT could not honour show up as vertex or swap conflicts
        ok, prio, best, stuck, order = lacam_child(node.config, nxt, owner, goals, table, slot, node.prio,
                                                   node.best, node.stuck)
        if not ok:
            continue
        new = _Node(nxt.copy(), node, prio, best, stuck, order)
        explored[key] = new
        stack.append(new)
    configs = []
    end = found or max(explored.values(), key=lambda nd: int((nd.config == goals).sum()))
    while end is not None:
        configs.append(end.config)
        end = end.parent
    paths = np.stack(configs[::-1])
    off = paths != goals[None, :]
    last_off = np.where(off.any(axis=0), paths.shape[0] - 1 - np.argmax(off[::-1], axis=0), -1)
    arrival = last_off + 1
    return {"paths": paths, "solved": found is not None, "sum_of_costs": int(arrival.sum()),
            "makespan": int(arrival.max()) if n else 0, "time_s": clock() - t0,
            "nodes": len(explored), "scatter": sc}
