"""Traffic-flow guidance for the lifelong planner: one guide path per robot, costed by the
flow of the other robots' guide paths, and the distance rows PIBT follows along them.

After Chen, Harabor, Li and Stuckey, "Traffic flow optimisation for lifelong multi-agent path
finding" (AAAI-24), the planner of the League of Robot Runners' default entry:

- Each robot's guide path is an A* path to its goal that minimises its length plus the
  traffic it meets: for a move ``u -> v`` in direction ``d``, the contraflow
  ``(flow[u, d] + 1) * flow[v, opposite d]`` (the guide paths already running against it) and
  the vertex flow ``sum(flow[v, :]) // 2`` (how many guide paths cross ``v``), where
  ``flow[c, d]`` counts the guide paths that leave ``c`` towards ``d``.
- The path's distance row, which PIBT follows instead of the plain distance to the goal:
  for every cell, the breadth-first steps to the nearest cell of the path plus the steps
  left along the path from there (ties to the cell nearer the goal). On its path a robot's
  value falls by one a step; a step off it costs one. Robots keep to their guide paths, so
  opposing streams take different corridors instead of meeting head-on.
- While the step's time lasts, guide paths are planned again against the others' current
  flow (the paper's Frank-Wolfe-style refinement), those most off their path first, then those
  planned longest ago.
- Both the new goals' paths and the refinement run on ``threads`` threads at once (the kernels
  release the GIL), each taking the next robot of the list; a path is planned against the flow as
  it stands, without the paths being planned beside it at that moment (the refinement plans them
  again later), and is added to the flow under a lock, so that the flow stays the sum of the paths.

Arrays: ``nbr`` (cells, 4) int32 from :class:`~.grid.LifelongGrid`; ``cost`` (cells, 4) uint8,
the length of each move (the one-way lanes of :mod:`.guidance`, else all 1); distance rows
uint16 with :data:`~.kernels.UNREACHABLE`.
"""
from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from numba import njit

from ..numba_cache import seed
from .distances import DistanceCache
from .grid import LifelongGrid
from .kernels import UNREACHABLE, heap_pop, heap_push

seed(__file__)

__all__ = ["TrafficFlow", "flow_astar", "path_fill"]

RADIUS = 3         # a path's row reaches this many steps off it (measured: docs/lifelong.md)
_FLOW_CAP = (1 << 22) - 1      # the flow a key can hold; a path that meets more is as bad as any


@njit(cache=True, nogil=True)
def flow_astar(nbr, cost, flow, h, start, goal, g, acc, parent, stamp, label, hk, hv, path, head, turn):
    """A* from ``start`` to ``goal`` minimising length + contraflow + vertex flow (module doc),
    a quarter turn costing ``turn`` steps (MAPF_T: 1; the robot starts facing ``head``, -1
    for any; a cell's heading is the one it was first reached with, so turns are counted
    along the path found, not minimised over every heading).

    h: (cells,) uint16 admissible distances to ``goal`` (its distance map). g, acc, parent,
    stamp: (cells,) int32 scratch, valid where ``stamp == label`` (a new ``label`` per call
    clears them); hk (int64) / hv (int64): heap scratch of 4 x cells; path (cells,) int32
    receives the cells from ``start`` to ``goal``. Ties: the lower length + distance, then
    the longer prefix. Returns the path's number of cells (0 when ``goal`` is unreachable).
    """
    if h[start] == UNREACHABLE:
        return 0
    stamp[start] = label
    g[start] = 0
    acc[start] = 0
    parent[start] = -1
    f0 = np.int64(h[start])
    size = heap_push(hk, hv, 0, (f0 << 40) | (f0 << 20) | np.int64(0xFFFFF), np.int64(start))
    closed = -label
    found = False
    while size > 0:
        key, c, size = heap_pop(hk, hv, size)
        if stamp[c] == closed:
            continue
        total = g[c] + int(h[c]) + acc[c]
        if total != (key >> 40):
            continue                                   # a stale entry: c was reached cheaper since
        stamp[c] = closed
        if c == goal:
            found = True
            break
        fu = flow[c]
        pc = parent[c]
        hin = head
        if pc >= 0:
            dv = c - pc
            hin = 0 if dv == 1 else (2 if dv == -1 else (1 if dv > 0 else 3))
        for d in range(4):
            v = nbr[c, d]
            if v < 0 or stamp[v] == closed or h[v] == UNREACHABLE:
                continue
            fv = flow[v]
            op = (fu[d] + 1) * fv[(d + 2) & 3]
            vert = (fv[0] + fv[1] + fv[2] + fv[3]) // 2
            ng = g[c] + cost[c, d]
            if hin >= 0 and d != hin:
                ng += turn * (2 if ((d - hin) & 3) == 2 else 1)
            na = acc[c] + op + vert
            if na > _FLOW_CAP:
                na = _FLOW_CAP
            if stamp[v] == label and ng + na >= g[v] + acc[v]:
                continue
            stamp[v] = label
            g[v] = ng
            acc[v] = na
            parent[v] = c
            f = ng + int(h[v])
            k = (np.int64(f + na) << 40) | (np.int64(f) << 20) | np.int64(0xFFFFF - min(ng, 0xFFFFF))
            size = heap_push(hk, hv, size, k, np.int64(v))
    if not found:
        return 0
    n = 0
    c = goal
    while c != -1:
        path[n] = c
        n += 1
        c = parent[c]
    path[:n] = path[:n][::-1].copy()
    return n


@njit(cache=True, nogil=True)
def path_fill(nbr, path, out, dist, togo, queue, radius):
    """The distance row of a guide path ``path`` (int32 cells, start to goal) into ``out``
    (uint16, cells): steps to the nearest path cell plus the steps left along the path from
    it, nearest-to-goal first among equally near ones (a breadth-first search seeded from the
    goal's end), for the cells within ``radius`` steps of the path; the others stay
    UNREACHABLE (a robot pushed that far off plans a new path). dist, togo, queue: (cells,)
    int32 scratch; ``dist`` must be -1 everywhere and is left so. Returns the cells written."""
    out[:] = UNREACHABLE
    n = path.shape[0]
    tail = 0
    for i in range(n - 1, -1, -1):
        c = path[i]
        if dist[c] >= 0:
            continue
        dist[c] = 0
        togo[c] = n - 1 - i
        queue[tail] = c
        tail += 1
    head = 0
    while head < tail:
        c = queue[head]
        head += 1
        v0 = dist[c] + togo[c]
        out[c] = v0 if v0 < UNREACHABLE else UNREACHABLE - 1
        if dist[c] >= radius:
            continue
        for d in range(4):
            v = nbr[c, d]
            if v >= 0 and dist[v] < 0:
                dist[v] = dist[c] + 1
                togo[v] = togo[c]
                queue[tail] = v
                tail += 1
    for k in range(tail):
        dist[queue[k]] = -1
    return tail


@njit(cache=True, nogil=True)
def _flow_add(flow, path, n, sign):
    """Add (sign +1) or remove (-1) the moves of ``path[:n]`` to / from ``flow``."""
    for i in range(n - 1):
        u = path[i]
        v = path[i + 1]
        dv = v - u
        if dv == 1:
            d = 0
        elif dv == -1:
            d = 2
        elif dv > 0:
            d = 1
        else:
            d = 3
        flow[u, d] += sign


class _PathScratch:
    """One thread's scratch for :func:`flow_astar` and :func:`path_fill`: (cells,) int32 arrays
    (``dist`` -1 everywhere between calls), the heap's 4 x cells int64 keys and values, and the
    A* call's label."""

    def __init__(self, cells: int):
        self.g = np.zeros(cells, dtype=np.int32)
        self.acc = np.zeros(cells, dtype=np.int32)
        self.parent = np.zeros(cells, dtype=np.int32)
        self.stamp = np.zeros(cells, dtype=np.int32)
        self.label = 0
        self.hk = np.empty(4 * cells + 8, dtype=np.int64)
        self.hv = np.empty(4 * cells + 8, dtype=np.int64)
        self.path = np.empty(cells, dtype=np.int32)
        self.dist = np.full(cells, -1, dtype=np.int32)
        self.togo = np.empty(cells, dtype=np.int32)
        self.queue = np.empty(cells, dtype=np.int32)


class TrafficFlow:
    """Guide paths for a team of ``n`` robots and their distance rows (module doc).

    ``table`` ((n, cells) uint16) holds robot ``a``'s row in row ``a``: the distance row of its
    guide path, or, until one is planned, a copy of its goal's distance map. ``update`` keeps
    the rows current as goals change; ``refine`` plans guide paths again while time lasts.
    cost: (cells, 4) uint8 move lengths (default all 1); radius: how far off its path a
    robot's row reaches (:func:`path_fill`); turn: the steps a quarter turn costs a guide path
    (1 for MAPF_T, 0 for 4-neighbour moves); threads: the threads that plan paths at once
    (default: the CPUs this process may use, at most 2; 1: in order, as the paper plans them, the
    same paths in every run). Memory: ``n`` rows of 2 bytes a cell (1.4 GB for 10,000 robots on a
    500 x 140 map), written once when made so that no step pays for the pages, and per thread
    about 60 bytes a cell of scratch. Raises MemoryError (from numpy) if they cannot be had.
    """

    def __init__(self, grid: LifelongGrid, cache: DistanceCache, n: int, cost: np.ndarray | None = None,
                 seed_: int = 0, radius: int = RADIUS, turn: int = 1, threads: int | None = None):
        self.grid, self.cache, self.n, self.radius, self.turn = grid, cache, int(n), int(radius), int(turn)
        cells = grid.n_cells
        self.cost = cost if cost is not None else np.ones((cells, 4), dtype=np.uint8)
        self.flow = np.zeros((cells, 4), dtype=np.int32)
        self.table = np.full((self.n, cells), UNREACHABLE, dtype=np.uint16)     # touched now, not in a step
        self.goal = np.full(self.n, -1, dtype=np.int64)         # the goal each row is for
        self.guided = np.zeros(self.n, dtype=bool)               # the row follows a guide path
        self.planned_at = np.zeros(self.n, dtype=np.int64)       # the step its path was planned
        self.paths: list[np.ndarray | None] = [None] * self.n
        if threads is None:
            threads = min(2, len(os.sched_getaffinity(0)))
        self._scratch = [_PathScratch(cells) for _ in range(max(1, int(threads)))]
        self._pool = (ThreadPoolExecutor(len(self._scratch) - 1, thread_name_prefix="guide-paths")
                      if len(self._scratch) > 1 else None)
        self._lock = threading.Lock()          # the flow, the paths, the stats and the list being worked
        self._busy: set[int] = set()           # robots a thread is planning now
        self.rng = np.random.default_rng(seed_)
        self.step = 0
        self.stats = {"guide_paths": 0, "guide_refined": 0, "guide_copied": 0, "guide_deferred": 0, "flow_ms": 0.0,
                      "guide_threads": len(self._scratch)}

    def _drop(self, a: int) -> None:
        with self._lock:
            p = self.paths[a]
            if p is not None:
                _flow_add(self.flow, p, p.shape[0], -1)
                self.paths[a] = None
        self.guided[a] = False

    def _plan(self, a: int, start: int, goal: int, slot: int, head: int, s: _PathScratch) -> bool:
        s.label += 1
        if s.label >= 2 ** 30:
            s.stamp[:] = 0
            s.label = 1
        n = flow_astar(self.grid.nbr, self.cost, self.flow, self.cache.table[slot], start, goal, s.g, s.acc,
                       s.parent, s.stamp, s.label, s.hk, s.hv, s.path, head, self.turn)
        if n == 0:
            return False
        p = s.path[:n].copy()
        with self._lock:
            _flow_add(self.flow, p, n, 1)
            self.paths[a] = p
            self.stats["guide_paths"] += 1
        path_fill(self.grid.nbr, p, self.table[a], s.dist, s.togo, s.queue, self.radius)
        self.guided[a] = True
        self.planned_at[a] = self.step
        return True

    def _each(self, robots: list[int], work: Callable[[int, _PathScratch], bool]) -> int:
        """``work(a, scratch)`` for the robots of ``robots`` in order, on every thread at once,
        each thread taking the next robot not being worked on by another (a robot listed twice is
        skipped while it is); a thread stops when ``work`` returns False (its deadline passed).
        Returns the number of calls that returned True. An error in a thread is raised here."""
        todo = iter(robots)
        lock, busy = self._lock, self._busy

        def worker(s: _PathScratch) -> int:
            done = 0
            while True:
                with lock:
                    a = next(todo, None)
                    while a is not None and a in busy:
                        a = next(todo, None)
                    if a is None:
                        return done
                    busy.add(a)
                try:
                    if not work(a, s):
                        return done
                    done += 1
                finally:
                    with lock:
                        busy.discard(a)

        if self._pool is None or len(robots) < 2:
            return worker(self._scratch[0])
        futures = [self._pool.submit(worker, s) for s in self._scratch[1:]]
        done = worker(self._scratch[0])
        return done + sum(f.result() for f in futures)

    def update(self, pos: np.ndarray, goals: np.ndarray, slot: np.ndarray, deadline: float,
               hard: float | None = None, head: np.ndarray | None = None) -> np.ndarray:
        """Rows for this step. pos, goals (n,) int64 (goal -1: none); slot (n,) int64 rows of
        the goals' maps in the cache (-1: no map yet). Robots with a new goal get a guide path
        while ``deadline`` (``time.perf_counter()``) is ahead, else a copy of the goal's map
        until ``hard`` (default: no limit), else no row this step (they wait, and are served
        at the next). head: (n,) int64 headings the paths start with (default: any).
        Returns (n,) int64: the row of each robot in :attr:`table` (-1: none)."""
        t0 = time.perf_counter()
        self.step += 1
        out = np.full(self.n, -1, dtype=np.int64)
        for a in np.flatnonzero(goals != self.goal).tolist():
            self._drop(a)
            self.goal[a] = -1
        have = np.flatnonzero((goals >= 0) & (slot >= 0))
        kept = have[self.goal[have] == goals[have]]
        out[kept] = kept

        def new_goal(a: int, s: _PathScratch) -> bool:
            g = int(goals[a])
            now = time.perf_counter()
            if now < deadline and self._plan(a, int(pos[a]), g, int(slot[a]), -1 if head is None else int(head[a]), s):
                pass
            elif hard is None or now < hard:
                self.table[a] = self.cache.table[slot[a]]
                with self._lock:
                    self.stats["guide_copied"] += 1
            else:
                with self._lock:
                    self.stats["guide_deferred"] += 1
                return True
            self.goal[a] = g
            out[a] = a
            return True

        self._each(have[self.goal[have] != goals[have]].tolist(), new_goal)
        self.stats["flow_ms"] += (time.perf_counter() - t0) * 1e3
        return out

    def refine(self, pos: np.ndarray, slot: np.ndarray, deadline: float, passes: int = 1,
               head: np.ndarray | None = None) -> int:
        """Plan guide paths again against the others' flow until ``deadline``: first the robots
        whose row at their cell exceeds their goal distance the most (off their path, or on a
        long way round), then those planned longest ago, ties at random; robots still following
        a copied goal map first of all. Returns the number of paths planned."""
        t0 = time.perf_counter()
        have = np.flatnonzero((self.goal >= 0) & (slot >= 0))
        if not len(have) or time.perf_counter() >= deadline:
            return 0
        own = self.table[have, pos[have]].astype(np.int64)
        best = self.cache.table[slot[have], pos[have]].astype(np.int64)
        dev = np.where(self.guided[have], own - best, 1 << 30)
        order = np.lexsort((self.rng.random(len(have)), self.planned_at[have], -dev))

        def again(a: int, s: _PathScratch) -> bool:
            if time.perf_counter() >= deadline:
                return False
            self._drop(a)
            if not self._plan(a, int(pos[a]), int(self.goal[a]), int(slot[a]), -1 if head is None else int(head[a]),
                              s):
                self.table[a] = self.cache.table[slot[a]]
            return True

        k = self._each(np.tile(have[order], passes).tolist(), again)
        self.stats["guide_refined"] += k
        self.stats["flow_ms"] += (time.perf_counter() - t0) * 1e3
        return k


def warm_up() -> None:
    """Compile (or load from numba's cache) this module's kernels on a tiny grid, so that
    compilation never counts against a timed step."""
    free = np.ones((2, 3), dtype=bool)
    grid = LifelongGrid(free)
    cache = DistanceCache(grid, max_bytes=2 * grid.n_cells * 4, min_rows=4)
    tf = TrafficFlow(grid, cache, 2)
    pos = np.array([0, 5], dtype=np.int64)
    goals = np.array([5, 0], dtype=np.int64)
    slot = cache.slots(goals)
    tf.update(pos, goals, slot, time.perf_counter() + 60)
    tf.refine(pos, slot, time.perf_counter() + 60)
