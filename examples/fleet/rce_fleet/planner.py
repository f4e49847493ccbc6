"""The fleet's global planner core (sans-I/O: plain classes, no sockets, no asyncio).

What the seed paper does (section IV-A): Dijkstra on the grid of cells, one
robot at a time; a blocked cell triggers re-planning and a ``cancelGoal`` for
the robots whose paths crossed it. What it lacks, and this module adds:

* **Collision-free multi-robot plans.** Paths are space-time sequences of cells
  (one cell per step, a wait is a repeated cell). No two robots occupy one cell
  at one step, no two swap cells between steps, and a robot that has arrived
  stays at its goal for ever (its cell is reserved for all later steps).
  Algorithm: prioritized planning with a reservation table (Erdmann &
  Lozano-Perez 1987; Silver 2005, "Cooperative Pathfinding", AIIDE), each robot
  planned by space-time A* over safe intervals (SIPP, Phillips & Likhachev
  2011), with the true-distance heuristic of a reverse Dijkstra from its goal
  (unit costs, scipy ``csgraph``). Priority: shorter trips first (they park
  early; long trips route around them, instead of short trips waiting for a
  long one to pass their goal). A robot that cannot be planned is moved to the
  front of the order and the plan restarted (priority bumping); when restarts
  or the time budget run out, robots that still cannot be planned are parked
  where they are and reported in ``unreachable``, so nobody waits for ever on
  a goal that will not come.
* **Re-planning.** After a block only the robots whose remaining paths cross
  the cell are re-planned, around the others' kept remaining paths; if that
  fails (or the kept paths no longer fit together) everybody is re-planned.
  A robot already cleared into its next cell keeps that move (it may be
  driving), so re-plans never pull a cell from under a moving robot.
* **Execution that keeps the plan's order under delays.** Robots do not move in
  lock-step. :class:`ActionDependencyGraph` (Hoenig et al. 2019, "Persistent
  and Robust Execution of MAPF Schedules in Warehouses", IEEE RA-L) lets a robot
  enter a cell only after every robot planned to be in that cell *earlier* has
  left it. With a conflict-free plan this is collision- and deadlock-free under
  any delays (the dependency graph is acyclic: its edges go forward in plan time).
* **Clear failure reasons**: a goal that is not a free cell, blocked, walled off,
  taken by another robot, occupied by a parked robot, or not plannable.

Units: cells are integers ``r * cols + c`` (row 0 at the top of the map image,
see :mod:`rce_fleet.grid`); steps are plan time steps (one cell move or one wait).
The graph is undirected (a robot can drive both ways between two cells).
"""
from __future__ import annotations

import bisect
import heapq
import math
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra as _csgraph_dijkstra

__all__ = [
    "PlannerError", "UnreachableGoal", "GridGraph", "load_movingai_scen", "shortest_path",
    "Conflict", "check_conflicts", "safe_interval_astar", "Reservations", "ActionDependencyGraph",
    "PlanResult", "FleetPlanner",
]

INF = math.inf


class PlannerError(ValueError):
    """A request the planner cannot take: unknown robot, cell outside the grid."""


class UnreachableGoal(PlannerError):
    """Raised by ``FleetPlanner.set_goal(..., strict=True)``: ``robot``'s ``goal`` cannot be reached, ``reason`` says why."""

    def __init__(self, robot: str, goal: int, reason: str):
        super().__init__(f"robot {robot}: goal cell {goal} unreachable: {reason}")
        self.robot, self.goal, self.reason = robot, goal, reason


# ---------------------------------------------------------------------------
# the graph
# ---------------------------------------------------------------------------
class GridGraph:
    """Free cells of a rows x cols grid and the 4-neighbour moves between them.

    free: (rows, cols) bool. neighbours: ``nbrs[cell]`` lists the cells a robot
    can move to from ``cell``. Between free cells the moves must be symmetric;
    a cell that is not free gets "escape" moves to its free 4-neighbours (so a
    robot localised in a non-free cell can leave it) but can never be entered.
    """

    def __init__(self, free: np.ndarray, neighbours: Sequence[Sequence[int]] | None = None):
        free = np.asarray(free, dtype=bool)
        if free.ndim != 2:
            raise ValueError(f"free must be a (rows, cols) array, got shape {free.shape}")
        self.rows, self.cols = int(free.shape[0]), int(free.shape[1])
        self.free = free
        flat = free.ravel()
        n = self.rows * self.cols
        nbrs: list[list[int]] = []
        for cell in range(n):
            if flat[cell] and neighbours is not None:
                nbrs.append([int(x) for x in neighbours[cell] if flat[x]])
            else:
                r, c = divmod(cell, self.cols)
                cand = []
                if r > 0:
                    cand.append(cell - self.cols)
                if c > 0:
                    cand.append(cell - 1)
                if c + 1 < self.cols:
                    cand.append(cell + 1)
                if r + 1 < self.rows:
                    cand.append(cell + self.cols)
                nbrs.append([x for x in cand if flat[x]])
        self.nbrs = nbrs
        src, dst = [], []
        for cell in np.flatnonzero(flat):
            for x in nbrs[cell]:
                src.append(int(cell))
                dst.append(x)
        # distances are computed on the free cells only (compact numbering)
        self._free_idx = np.flatnonzero(flat)
        self._compact = np.full(n, -1, dtype=np.int64)
        self._compact[self._free_idx] = np.arange(self._free_idx.size)
        self._src = self._compact[np.asarray(src, dtype=np.int64)]
        self._dst = self._compact[np.asarray(dst, dtype=np.int64)]
        self._csr_cache: tuple[frozenset, csr_matrix] | None = None

    # -- constructors ------------------------------------------------------
    @classmethod
    def from_array(cls, free: np.ndarray) -> "GridGraph":
        """A 4-connected grid from a (rows, cols) bool array of free cells."""
        return cls(free)

    @classmethod
    def from_cellgrid(cls, grid) -> "GridGraph":
        """From a :class:`rce_fleet.grid.CellGrid`, using its free cells and connections."""
        n = grid.rows * grid.cols
        return cls(grid.free, [grid.neighbours(c) for c in range(n)])

    @classmethod
    def from_movingai(cls, path: str | Path) -> "GridGraph":
        """Load a MovingAI map in the converted text form of ``../shared/data/SOURCES.md``.

        Line 1: rows; line 2: columns; then ``rows`` lines of ``cols`` 0/1 values
        (1 = blocked). Also accepts the original MovingAI ``type octile`` format
        (``.`` and ``G`` free, others blocked). Raises ValueError naming the file.
        """
        path = Path(path)
        lines = path.read_text().split("\n")
        try:
            if lines[0].startswith("type"):
                hdr = dict(ln.split(None, 1) for ln in lines[1:3])
                rows, cols = int(hdr["height"]), int(hdr["width"])
                start = next(i for i, ln in enumerate(lines) if ln.strip() == "map") + 1
                body = [ln.rstrip("\r") for ln in lines[start:start + rows]]
                free = np.array([[ch in ".G" for ch in ln[:cols]] for ln in body], dtype=bool)
            else:
                rows, cols = int(lines[0]), int(lines[1])
                body = [ln.split() for ln in lines[2:2 + rows]]
                free = np.array([[v == "0" for v in ln] for ln in body], dtype=bool)
            if free.shape != (rows, cols):
                raise ValueError(f"expected {rows}x{cols} cells, got {free.shape}")
        except (ValueError, KeyError, IndexError, StopIteration) as exc:
            raise ValueError(f"{path}: not a MovingAI map: {exc}") from exc
        return cls(free)

    # -- basics -------------------------------------------------------------
    @property
    def n_cells(self) -> int:
        """rows * cols."""
        return self.rows * self.cols

    def rc(self, cell: int) -> tuple[int, int]:
        """Cell number -> (row, col)."""
        return divmod(int(cell), self.cols)

    def cell(self, r: int, c: int) -> int:
        """(row, col) -> cell number."""
        return int(r) * self.cols + int(c)

    def is_free(self, cell: int) -> bool:
        """True when ``cell`` is inside the grid and free."""
        return 0 <= cell < self.n_cells and bool(self.free.flat[cell])

    def neighbours(self, cell: int) -> list[int]:
        """Cells a robot can move to from ``cell`` (free cells only)."""
        return self.nbrs[cell]

    # -- distances ---------------------------------------------------------
    def _csr(self, blocked: frozenset) -> csr_matrix:
        if self._csr_cache is not None and self._csr_cache[0] == blocked:
            return self._csr_cache[1]
        keep = np.ones(self._src.size, dtype=bool)
        if blocked:
            b = self._compact[np.fromiter(blocked, dtype=np.int64)]
            b = b[b >= 0]
            keep &= ~np.isin(self._src, b) & ~np.isin(self._dst, b)
        n = self._free_idx.size
        m = csr_matrix((np.ones(int(keep.sum())), (self._src[keep], self._dst[keep])), shape=(n, n))
        self._csr_cache = (blocked, m)
        return m

    def distances_to(self, goals: Sequence[int], blocked: Iterable[int] = ()) -> np.ndarray:
        """Steps from every cell to each goal, avoiding ``blocked`` cells.

        Returns (len(goals), n_cells) float64; ``inf`` where unreachable (and at
        blocked or non-free cells). Reverse Dijkstra with unit costs (scipy
        ``csgraph.dijkstra``); equals forward distance since moves are symmetric.
        """
        blocked = frozenset(int(b) for b in blocked)
        goals = [int(g) for g in goals]
        out = np.full((len(goals), self.n_cells), np.inf)
        ok = [i for i, g in enumerate(goals) if self.is_free(g) and g not in blocked]
        if ok:
            d = _csgraph_dijkstra(self._csr(blocked), directed=True, unweighted=True,
                                  indices=self._compact[[goals[i] for i in ok]])
            out[np.ix_(ok, self._free_idx)] = d
        return out


def load_movingai_scen(path: str | Path, graph: GridGraph) -> list[tuple[int, int]]:
    """Read a MovingAI scenario in the converted text form: line 1 = N, then ``sx sy gx gy``.

    Also accepts the original ``version 1`` .scen format. x is the column, y the
    row. Returns (start_cell, goal_cell) per agent, numbered on ``graph``
    (``cell = y * cols + x``). Raises ValueError naming the file.
    """
    path = Path(path)
    cols = graph.cols
    out = []
    lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    try:
        if lines[0].startswith("version"):
            recs = [ln.split("\t") for ln in lines[1:]]
            xy = [(int(r[4]), int(r[5]), int(r[6]), int(r[7])) for r in recs]
        else:
            n = int(lines[0])
            xy = [tuple(int(v) for v in ln.split()[:4]) for ln in lines[1:1 + n]]
    except (ValueError, IndexError) as exc:
        raise ValueError(f"{path}: not a MovingAI scenario: {exc}") from exc
    for sx, sy, gx, gy in xy:
        out.append((sy * cols + sx, gy * cols + gx))
    return out


def shortest_path(graph: GridGraph, start: int, goal: int, blocked: Iterable[int] = ()) -> list[int] | None:
    """Single-robot shortest cell path by Dijkstra (the seed paper's planner), or None.

    Unit cost per move; ``blocked`` cells are never entered (the start may be
    blocked: the robot is leaving it). Returns the list of cells from start to
    goal inclusive, ``[start]`` when start == goal.
    """
    blocked = set(blocked)
    if goal in blocked or not graph.is_free(goal):
        return None
    dist = {start: 0}
    parent = {start: -1}
    heap = [(0, start)]
    while heap:
        d, c = heapq.heappop(heap)
        if c == goal:
            path = []
            while c != -1:
                path.append(c)
                c = parent[c]
            return path[::-1]
        if d > dist[c]:
            continue
        for n in graph.nbrs[c]:
            if n in blocked:
                continue
            if d + 1 < dist.get(n, INF):
                dist[n] = d + 1
                parent[n] = c
                heapq.heappush(heap, (d + 1, n))
    return None


# ---------------------------------------------------------------------------
# conflicts
# ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Conflict:
    """Two robots in one cell at one step (``kind='vertex'``, ``cells=(c,)``);
    swapping cells between ``step`` and ``step + 1`` (``kind='swap'``, ``cells=(a, b)``:
    ``robots[0]`` goes a -> b, ``robots[1]`` b -> a); or a rotation (``kind='cycle'``):
    three or more robots each entering, between ``step`` and ``step + 1``, the cell
    the next one leaves (``cells``: where each robot starts the move)."""

    kind: str
    robots: tuple[str, ...]
    cells: tuple[int, ...]
    step: int


def check_conflicts(paths: Mapping[str, Sequence[int]], ignore_start: bool = False) -> list[Conflict]:
    """All vertex, swap and rotation conflicts in a set of space-time paths.

    ``paths[robot][k]`` is the robot's cell at step k; after its last step a
    robot stays in its final cell for ever (so a robot passing through another's
    final cell later is a conflict). Empty paths are ignored. With
    ``ignore_start`` shared cells at step 0 are not reported (robots that were
    localised into one cell). Two robots that stay in one cell for ever are
    reported once. Cost O(robots x makespan).
    """
    items = [(r, list(p)) for r, p in paths.items() if len(p)]
    if not items:
        return []
    horizon = max(len(p) for _, p in items)
    out: list[Conflict] = []
    prev: dict[int, str] = {}
    lengths = dict((r, len(p)) for r, p in items)
    for t in range(horizon):
        at: dict[int, str] = {}
        for r, p in items:
            c = p[t] if t < len(p) else p[-1]
            other = at.get(c)
            if other is not None:
                static = t > lengths[r] - 1 and t > lengths[other] - 1   # both parked since before t
                if not (ignore_start and t == 0) and not static:
                    out.append(Conflict("vertex", (other, r), (c,), t))
            else:
                at[c] = r
        if t > 0:
            for r, p in items:
                if t >= len(p):
                    continue
                a, b = p[t - 1], p[t]
                if a == b:
                    continue
                o = prev.get(b)   # who was in b at t-1 ...
                if o is not None and o != r and at.get(a) == o:   # ... and is in a at t
                    if r < o:   # report each swap once
                        out.append(Conflict("swap", (r, o), (a, b), t - 1))
            out.extend(_rotations(items, prev, t))
        prev = at
    return out


def _rotations(items: list[tuple[str, list[int]]], prev: dict[int, str], t: int) -> list[Conflict]:
    """Cycles of >= 3 robots each moving into the cell the next one leaves, between t-1 and t.

    A plan may not contain them: executed with :class:`ActionDependencyGraph`
    (enter a cell only after its previous occupant has left) they deadlock.
    """
    nxt: dict[str, str] = {}
    move: dict[str, tuple[int, int]] = {}
    for r, p in items:
        if t < len(p) and p[t] != p[t - 1]:
            o = prev.get(p[t])
            move[r] = (p[t - 1], p[t])
            if o is not None and o != r:
                nxt[r] = o
    out, done = [], set()
    for r in nxt:
        if r in done:
            continue
        seen, x = [], r
        while x in nxt and x not in seen and x not in done and x in move:
            seen.append(x)
            x = nxt[x]
        if x in seen and x in move:
            cyc = seen[seen.index(x):]
            if len(cyc) >= 3:
                out.append(Conflict("cycle", tuple(cyc), tuple(move[c][0] for c in cyc), t - 1))
        done.update(seen)
    return out


# ---------------------------------------------------------------------------
# space-time A* with a reservation table
# ---------------------------------------------------------------------------
class Reservations:
    """Reservation table for prioritized planning (Silver 2005).

    ``vertex[t * n + cell] = owner`` for every reserved (cell, step);
    ``occ[cell]``: sorted steps at which ``cell`` is reserved;
    ``parked[cell] = t``: the owner stays in ``cell`` from step t for ever;
    ``paths[owner]``: the owner's reserved cells from step 0 (``parks[owner]``:
    whether it stays in the last one for ever).
    """

    __slots__ = ("n", "vertex", "occ", "parked", "paths", "parks")

    def __init__(self, n_cells: int):
        self.n = n_cells
        self.vertex: dict[int, int] = {}
        self.occ: dict[int, list[int]] = {}
        self.parked: dict[int, int] = {}
        self.paths: dict[int, list[int]] = {}
        self.parks: dict[int, bool] = {}

    def copy(self) -> "Reservations":
        """An independent copy."""
        r = Reservations(self.n)
        r.vertex, r.parked = dict(self.vertex), dict(self.parked)
        r.occ = {c: list(ts) for c, ts in self.occ.items()}
        r.paths, r.parks = dict(self.paths), dict(self.parks)
        return r

    def cell_of(self, owner: int, t: int) -> int | None:
        """Where ``owner`` is at step ``t`` (None when not known: an unplanned robot past its start)."""
        p = self.paths.get(owner)
        if p is None:
            return None
        if t < len(p):
            return p[t]
        return p[-1] if self.parks.get(owner) else None

    def closes_rotation(self, u: int, v: int, t: int) -> bool:
        """True when moving u -> v between t and t + 1 closes a cycle of robots each
        entering the cell the next one leaves (a swap is the 2-cycle)."""
        n, vertex = self.n, self.vertex
        o = vertex.get(t * n + v)
        for _ in range(len(self.paths) + 1):
            if o is None:
                return False
            x = self.cell_of(o, t + 1)
            if x is None:
                return False
            if x == u:
                return True
            o = vertex.get(t * n + x)
        return False

    def reserve(self, path: Sequence[int], owner: int, park: bool = True, t0: int = 0) -> None:
        """Reserve ``path[k]`` at step ``t0 + k``; with ``park`` the final cell for ever after."""
        n, vertex, occ = self.n, self.vertex, self.occ
        for k, c in enumerate(path):
            t = t0 + k
            key = t * n + c
            if key in vertex:
                vertex[key] = owner
                continue
            vertex[key] = owner
            ts = occ.get(c)
            if ts is None:
                occ[c] = [t]
            elif ts[-1] < t:
                ts.append(t)
            else:
                bisect.insort(ts, t)
        if park:
            self.parked[path[-1]] = t0 + len(path) - 1
        if t0 == 0:
            self.paths[owner] = list(path)
            self.parks[owner] = park

    def release(self, path: Sequence[int], owner: int, t0: int = 0) -> None:
        """Undo :meth:`reserve` (without ``park``) of ``path`` for ``owner``."""
        n = self.n
        self.paths.pop(owner, None)
        self.parks.pop(owner, None)
        for k, c in enumerate(path):
            t = t0 + k
            if self.vertex.get(t * n + c) == owner:
                del self.vertex[t * n + c]
                ts = self.occ[c]
                ts.pop(bisect.bisect_left(ts, t))
                if not ts:
                    del self.occ[c]

    def last(self, cell: int) -> int:
        """Last reserved step of ``cell`` (-1 if none)."""
        ts = self.occ.get(cell)
        return ts[-1] if ts else -1

    def free_at(self, cell: int, t: int) -> bool:
        """True when nobody holds ``cell`` at step ``t``."""
        if t * self.n + cell in self.vertex:
            return False
        p = self.parked.get(cell)
        return p is None or t < p


def safe_interval_astar(nbrs: Sequence[Sequence[int]], start: int, goal: int, h: Sequence[float],
                        res: Reservations, max_expansions: int, t0: int = 0,
                        weight: float = 1.0) -> list[int] | None:
    """Space-time A* over safe intervals (SIPP, Phillips & Likhachev 2011, ICRA).

    Finds a path for one robot from ``start`` at step ``t0`` to ``goal``
    around the reservations ``res``: never in a reserved (cell, step), never
    in a parked cell from its park step on, never swapping cells with the
    owner of its target cell nor closing a rotation (a cycle of robots each
    following the next, which ordered execution could not carry out), and arriving in the goal's last, unbounded safe
    interval, so the robot can stay there for ever. Waiting is implicit: a
    state is (cell, safe interval) reached at its earliest step, which keeps
    the search small even when a robot must wait a long time (e.g. until
    another robot has passed through its goal).

    ``h[cell]``: exact distance to ``goal`` ignoring other robots (inf =
    unreachable: pruned). Ordering ``f = g + weight * max(h, G + 1 - g)``
    (G: last reserved step of the goal cell), ties to smaller h then later g.
    ``weight`` 1 gives the earliest arrival; slightly above 1 (weighted A*,
    Pohl 1970) avoids expanding the large ties of 4-connected grids and keeps
    the arrival within ``weight`` x optimal. ``max_expansions`` bounds work.

    Returns cells for steps ``t0 .. arrival`` (``path[0] == start``), or None.
    """
    N = res.n
    vertex, occ, parked = res.vertex, res.occ, res.parked
    if h[start] == INF or goal in parked:
        return None
    G1 = res.last(goal) + 1
    w = weight
    bisect_right = bisect.bisect_right

    # the start interval: from t0 (the robot is there) to the next reservation of the start cell
    ts = occ.get(start, ())
    k = bisect_right(ts, t0)
    e0 = ts[k] - 1 if k < len(ts) else INF
    p = parked.get(start)
    if p is not None and p - 1 < e0:
        e0 = p - 1
    if e0 < t0:
        e0 = t0
    s_key = t0 * N + start
    best = {s_key: t0}
    info = {s_key: (start, t0, e0, -1)}   # state -> (cell, arrival, interval end, parent state)
    h0 = h[start]
    open_ = [(t0 + w * (h0 if h0 > G1 - t0 else G1 - t0), h0, -t0, s_key)]
    closed: set[int] = set()
    push, pop = heapq.heappush, heapq.heappop
    expansions = 0
    while open_:
        _, _, _, skey = pop(open_)
        if skey in closed:
            continue
        closed.add(skey)
        u, a, e, _ = info[skey]
        if u == goal and e == INF:
            cells = []
            while skey != -1:
                c, g, _, par = info[skey]
                cells.append((c, g))
                skey = par
            cells.reverse()
            path: list[int] = []
            for (c, g), nxt in zip(cells, cells[1:] + [None]):
                until = nxt[1] if nxt is not None else g + 1
                path.extend([c] * (until - g))
            return path
        expansions += 1
        if expansions > max_expansions:
            return None
        hi = e + 1                               # latest arrival at a neighbour
        for v in nbrs[u]:
            hv = h[v]
            if hv == INF:
                continue
            lo = a + 1
            vts = occ.get(v)
            pv = parked.get(v, INF)
            if vts is None:
                k, nv = 0, 0
                s_int = 0
            else:
                nv = len(vts)
                k = bisect_right(vts, lo)
                s_int = vts[k - 1] + 1 if k > 0 else 0
            while s_int <= hi and s_int < pv:
                e_int = vts[k] - 1 if k < nv else INF
                if e_int > pv - 1:
                    e_int = pv - 1
                if e_int >= s_int and e_int >= lo:
                    t_arr = lo if lo > s_int else s_int
                    last_ok = e_int if e_int < hi else hi
                    # following whoever is in v at t_arr - 1: no swap, no rotation
                    while t_arr <= last_ok:
                        o = vertex.get((t_arr - 1) * N + v)
                        if o is None:
                            break
                        if vertex.get(t_arr * N + u) != o and not res.closes_rotation(u, v, t_arr - 1):
                            break
                        t_arr += 1
                    if t_arr <= last_ok:
                        key = s_int * N + v
                        if key not in closed and t_arr < best.get(key, INF):
                            best[key] = t_arr
                            info[key] = (v, t_arr, e_int, skey)
                            rest = G1 - t_arr
                            push(open_, (t_arr + w * (hv if hv > rest else rest), hv, -t_arr, key))
                if k >= nv:
                    break
                s_int = vts[k] + 1
                k += 1
    return None


# ---------------------------------------------------------------------------
# execution: action dependency graph
# ---------------------------------------------------------------------------
class ActionDependencyGraph:
    """Keeps execution in plan order under arbitrary delays (Hoenig et al. 2019).

    Each path is compressed into *visits* (a cell, the step it is entered, the
    last step it is held). For every cell the visits of all robots are ordered
    by planned entry step. A robot may enter the cell of its visit k only when
    the visit just before it in that cell's order has been completed (that
    robot has reported a later cell). Because the plan is conflict-free, the
    visits in a cell never overlap in plan time, so this keeps every cell to
    one robot at a time (a robot holds both cells while moving between them),
    rules out swaps, and cannot deadlock: every dependency points to an
    earlier planned step, so the earliest pending move is always allowed.
    """

    def __init__(self, paths: Mapping[str, Sequence[int]]):
        self.visits: dict[str, list[tuple[int, int, int]]] = {}
        for r, p in paths.items():
            vs: list[tuple[int, int, int]] = []
            for t, c in enumerate(p):
                if vs and vs[-1][0] == c:
                    vs[-1] = (c, vs[-1][1], t)
                else:
                    vs.append((c, t, t))
            self.visits[r] = vs
        queues: dict[int, list[tuple[int, int, str, int]]] = {}
        for r, vs in self.visits.items():
            for k, (c, a, lv) in enumerate(vs):
                queues.setdefault(c, []).append((a, lv, r, k))
        self.pred: dict[str, list[tuple[str, int] | None]] = {r: [None] * len(vs) for r, vs in self.visits.items()}
        for q in queues.values():
            q.sort()
            for i in range(1, len(q)):
                _, _, r, k = q[i]
                _, _, pr, pk = q[i - 1]
                self.pred[r][k] = (pr, pk) if pr != r else None
        self.progress: dict[str, int] = {r: 0 for r in self.visits}
        self._cleared: dict[str, int] = {r: 0 for r in self.visits}

    def allowed(self, robot: str, k: int) -> bool:
        """True when ``robot`` may enter the cell of its visit ``k`` now."""
        p = self.pred[robot][k]
        return p is None or self.progress[p[0]] > p[1]

    def cleared_visit(self, robot: str) -> int:
        """Index of the furthest visit ``robot`` may reach without waiting (monotone until replanned)."""
        k = max(self._cleared[robot], self.progress[robot])
        vs = self.visits[robot]
        while k + 1 < len(vs) and self.allowed(robot, k + 1):
            k += 1
        self._cleared[robot] = k
        return k

    def clearance(self, robot: str) -> int:
        """Path index (step) up to which ``robot`` may move now: the last step of its furthest cleared visit."""
        return self.visits[robot][self.cleared_visit(robot)][2]

    def position_index(self, robot: str) -> int:
        """Step at which the robot's current visit begins."""
        return self.visits[robot][self.progress[robot]][1]

    def cell(self, robot: str) -> int:
        """The cell the robot last reported."""
        return self.visits[robot][self.progress[robot]][0]

    def locate(self, robot: str, cell: int) -> int | None:
        """Visit index ``cell`` would move ``robot`` to: current, or a later cleared one; None if neither."""
        k = self.progress[robot]
        vs = self.visits[robot]
        if vs[k][0] == cell:
            return k
        last = self.cleared_visit(robot)
        for j in range(k + 1, last + 1):
            if vs[j][0] == cell:
                return j
        return None

    def future_cells(self, robot: str) -> list[int]:
        """Cells of the visits after the current one."""
        return [c for c, _, _ in self.visits[robot][self.progress[robot] + 1:]]


# ---------------------------------------------------------------------------
# the fleet planner
# ---------------------------------------------------------------------------
@dataclass
class PlanResult:
    """Outcome of a (re)plan.

    paths: every robot's current path (index 0 = its cell when planned).
    changed: robots whose cell sequence changed (send them the new path).
    unreachable: robot -> reason, for robots that are not moving towards their goal.
    cancelled: robots whose old path crossed a newly blocked cell (``cancelGoal``).
    full: True when all robots were re-planned (False: only some, others kept).
    elapsed_s: planning time in seconds.
    clearance: robot -> path index it may move up to now.
    """

    paths: dict[str, list[int]]
    changed: set[str] = field(default_factory=set)
    unreachable: dict[str, str] = field(default_factory=dict)
    cancelled: set[str] = field(default_factory=set)
    full: bool = True
    elapsed_s: float = 0.0
    clearance: dict[str, int] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """True when every robot with a goal got a path to it."""
        return not self.unreachable


def _compress(path: Sequence[int]) -> list[int]:
    out: list[int] = []
    for c in path:
        if not out or out[-1] != c:
            out.append(c)
    return out


class FleetPlanner:
    """Plans all robots together on a CellGrid (or any GridGraph), and clears their moves.

    Typical use (the global planner node is a thin shell around this)::

        fp = FleetPlanner(grid)
        fp.set_position("Robot1", 9); fp.set_position("Robot2", 14)
        fp.set_goal("Robot1", 54)                  # -> PlanResult, paths to publish
        fp.block(26)                               # -> robots to cancelGoal; re-planned
        fp.advance("Robot1", 10)                   # robot reports its cell -> new clearances
        fp.clearance("Robot1")                     # it may drive along paths[r][:k+1]

    State (read-only from outside): ``positions`` robot -> cell; ``goals``
    robot -> cell or None; ``paths`` robot -> list of cells (space-time: one
    cell per step, waits repeat a cell; index 0 = the robot's cell at the last
    re-plan); ``blocked`` cell -> source; ``unreachable`` robot -> reason;
    ``replans`` robot -> number of times its path changed; ``last_result``.

    A robot without a goal, or whose goal cannot be reached, is parked: it
    stays in its cell and other robots plan around it.

    Args:
        grid: a :class:`rce_fleet.grid.CellGrid` or :class:`GridGraph`.
        max_restarts: priority-order restarts before robots that still fail are parked.
        time_budget_s: wall-clock budget per (re)plan for restarts (a plan always finishes).
        expansion_factor, min_expansions: A* budget per robot,
            ``max(min_expansions, expansion_factor * (distance + 1))`` expansions.
        weight: weighted space-time A* factor (1 = each robot's earliest arrival
            given the robots before it; 1.05 default: much faster, paths within 5 %).
    """

    def __init__(self, grid, *, max_restarts: int = 20, time_budget_s: float = 2.0,
                 expansion_factor: int = 60, min_expansions: int = 4000, weight: float = 1.05):
        self.graph = grid if isinstance(grid, GridGraph) else GridGraph.from_cellgrid(grid)
        self.grid = grid
        self.max_restarts = max_restarts
        self.time_budget_s = time_budget_s
        self.expansion_factor = expansion_factor
        self.min_expansions = min_expansions
        self.weight = weight
        self.positions: dict[str, int] = {}
        self.goals: dict[str, int | None] = {}
        self._goal_seq: dict[str, int] = {}
        self._seq = 0
        self.paths: dict[str, list[int]] = {}
        self.blocked: dict[int, str] = {}
        self.unreachable: dict[str, str] = {}
        self.replans: dict[str, int] = {}
        self.last_result: PlanResult | None = None
        self._adg = ActionDependencyGraph({})
        self._dirty: set[str] = set()
        self._hcache: dict[tuple[int, frozenset], list[float]] = {}
        self._bkey: frozenset | None = None

    # -- validation ---------------------------------------------------------
    def _check_cell(self, cell: int, what: str = "cell") -> int:
        if isinstance(cell, bool) or not isinstance(cell, (int, np.integer)):
            raise PlannerError(f"{what} must be an integer cell number, got {cell!r}")
        cell = int(cell)
        if not 0 <= cell < self.graph.n_cells:
            raise PlannerError(f"{what} {cell} is outside the {self.graph.rows}x{self.graph.cols} grid "
                               f"(cells 0..{self.graph.n_cells - 1})")
        return cell

    def _check_robot(self, robot: str) -> None:
        if robot not in self.positions:
            raise PlannerError(f"unknown robot {robot!r}: set_position first")

    # -- heuristics -----------------------------------------------------------
    def _h(self, goals: Iterable[int]) -> None:
        """Fill the distance cache for ``goals`` (batched reverse Dijkstra)."""
        bl = self._blocked_key()
        need = sorted({g for g in goals if (g, bl) not in self._hcache})
        if need:
            if (len(self._hcache) + len(need)) * self.graph.n_cells > 20_000_000:
                self._hcache.clear()
            d = self.graph.distances_to(need, bl)
            for g, row in zip(need, d):
                self._hcache[(g, bl)] = row.tolist()

    def _blocked_key(self) -> frozenset:
        if self._bkey is None or len(self._bkey) != len(self.blocked) or not self._bkey.issuperset(self.blocked):
            self._bkey = frozenset(self.blocked)
        return self._bkey

    def _hrow(self, goal: int) -> list[float]:
        bl = self._blocked_key()
        if (goal, bl) not in self._hcache:
            self._h([goal])
        return self._hcache[(goal, bl)]

    def distance(self, start: int, goal: int) -> float:
        """Steps of the shortest path from ``start`` to ``goal`` ignoring other robots (inf if none)."""
        h = self._hrow(goal)
        if h[start] < INF:
            return h[start]
        best = min((h[n] for n in self.graph.nbrs[start]), default=INF)
        return best + 1

    # -- robots ---------------------------------------------------------------
    def set_position(self, robot: str, cell: int) -> None:
        """Register ``robot`` in ``cell``, or update its cell (e.g. after re-localisation).

        On its planned path (current or a cleared cell) this is :meth:`advance`.
        A new robot, or one found off its plan, is re-planned at once (others
        whose paths now run into it too); the outcome is in ``last_result``
        (publish the paths of ``last_result.changed``).
        Raises PlannerError for a cell outside the grid.
        """
        cell = self._check_cell(cell)
        if robot in self.positions and robot in self._adg.visits and robot not in self._dirty:
            if self._adg.locate(robot, cell) is not None:
                self.advance(robot, cell)
                return
        if robot not in self.positions:
            self.goals.setdefault(robot, None)
            self.replans.setdefault(robot, 0)
        self.positions[robot] = cell
        self._dirty.add(robot)
        self._replan(self._dirty | set(self.unreachable))

    def remove_robot(self, robot: str) -> None:
        """Forget ``robot`` (disconnected). Others keep their paths; call :meth:`plan` to use the freed cells."""
        self._check_robot(robot)
        for d in (self.positions, self.goals, self._goal_seq, self.paths, self.unreachable, self.replans):
            d.pop(robot, None)
        self._dirty.discard(robot)
        progress = dict(self._adg.progress)
        self._adg = ActionDependencyGraph(self.paths)
        for r in self._adg.progress:
            self._adg.progress[r] = progress.get(r, 0)

    def set_goal(self, robot: str, cell: int, *, strict: bool = False) -> PlanResult:
        """Give ``robot`` a goal cell and re-plan it (others keep their paths when possible).

        Returns the PlanResult; an unreachable goal is reported in
        ``result.unreachable[robot]`` (and ``self.unreachable``) with the reason,
        and the robot is parked. With ``strict`` it raises UnreachableGoal
        instead (the goal stays set; it is retried on later re-plans).
        Raises PlannerError for an unknown robot or a cell outside the grid.
        """
        self._check_robot(robot)
        cell = self._check_cell(cell, "goal cell")
        self.goals[robot] = cell
        self._seq += 1
        self._goal_seq[robot] = self._seq
        result = self._replan({robot} | self._dirty | set(self.unreachable))
        if strict and robot in result.unreachable:
            raise UnreachableGoal(robot, cell, result.unreachable[robot])
        return result

    def set_goals(self, goals: Mapping[str, int], *, strict: bool = False) -> PlanResult:
        """Set several goals at once and plan them together (one re-plan instead of many).

        Earlier entries win when two robots want the same cell. Errors as :meth:`set_goal`;
        with ``strict`` raises UnreachableGoal for the first robot that cannot reach its goal.
        """
        checked = {}
        for robot, cell in goals.items():
            self._check_robot(robot)
            checked[robot] = self._check_cell(cell, "goal cell")
        for robot, cell in checked.items():
            self.goals[robot] = cell
            self._seq += 1
            self._goal_seq[robot] = self._seq
        result = self._replan(set(checked) | self._dirty | set(self.unreachable))
        if strict:
            for robot in checked:
                if robot in result.unreachable:
                    raise UnreachableGoal(robot, checked[robot], result.unreachable[robot])
        return result

    def clear_goal(self, robot: str) -> PlanResult:
        """Drop ``robot``'s goal: it parks in its current cell."""
        self._check_robot(robot)
        self.goals[robot] = None
        self._goal_seq.pop(robot, None)
        return self._replan({robot} | self._dirty)

    # -- cells ------------------------------------------------------------------
    def block(self, cell: int, source: str = "operator") -> set[str]:
        """Block ``cell`` (operator, or an obstacle a robot's lidar saw) and re-plan.

        Returns the robots whose remaining paths crossed the cell (or ended in
        it): they must get ``cancelGoal`` and their new path
        (``self.paths``; all changes are in ``self.last_result``). A robot
        standing in the blocked cell may leave it; nobody enters it.
        Raises PlannerError for a cell outside the grid.
        """
        cell = self._check_cell(cell)
        if cell in self.blocked:
            self.blocked[cell] = source
            return set()
        self.blocked[cell] = source
        hit = {r for r in self.paths if r not in self._dirty and cell in self._adg.future_cells(r)}
        hit |= {r for r, g in self.goals.items() if g == cell and r in self.positions and r not in self.unreachable
                and self.positions[r] != cell}
        result = self._replan(hit | self._dirty | set(self.unreachable))
        result.cancelled = set(hit)
        return set(hit)

    def unblock(self, cell: int) -> PlanResult:
        """Unblock ``cell`` and re-plan the robots that were parked as unreachable."""
        cell = self._check_cell(cell)
        self.blocked.pop(cell, None)
        return self._replan(set(self.unreachable) | self._dirty)

    # -- planning ---------------------------------------------------------------
    def plan(self) -> dict[str, list[int]]:
        """Re-plan every robot from its current cell; returns robot -> path (all robots)."""
        self._replan(set(self.positions), full=True)
        return {r: list(p) for r, p in self.paths.items()}

    def _rebased(self, robot: str) -> list[int]:
        """The robot's remaining path from its current visit (dropping waits already cleared)."""
        adg = self._adg
        k = adg.progress[robot]
        c, a, lv = adg.visits[robot][k]
        start = lv if adg.cleared_visit(robot) > k else a
        return list(self.paths[robot][start:])

    def _commitment(self, robot: str) -> int | None:
        """The next cell ``robot`` has been cleared into (it may be driving there), if any."""
        adg = self._adg
        if robot not in adg.visits or robot in self._dirty:
            return None
        k = adg.progress[robot]
        if adg.cleared_visit(robot) > k:
            nxt = adg.visits[robot][k + 1][0]
            if nxt not in self.blocked:
                return nxt
        return None

    def _replan(self, subset: set[str], full: bool = False) -> PlanResult:
        t_start = time.perf_counter()
        subset = {r for r in subset if r in self.positions}
        old = {r: _compress(self._rebased(r)) if (r in self.paths and r in self._adg.visits and r not in self._dirty)
               else None for r in self.positions}
        commit = {r: self._commitment(r) for r in self.positions}
        # current cells
        for r in self.positions:
            if r in self._adg.visits and r not in self._dirty:
                self.positions[r] = self._adg.cell(r)
        result = None
        if not full and len(subset) < len(self.positions):
            fixed = {r: self._rebased(r) for r in self.positions
                     if r not in subset and r in self.paths and r in self._adg.visits and r not in self._dirty}
            subset |= set(self.positions) - set(fixed)
            if not check_conflicts(fixed, ignore_start=True):
                paths, unreachable = self._plan_some(sorted(subset), fixed, commit, t_start)
                allp = {**fixed, **paths}
                if not check_conflicts(allp, ignore_start=True):
                    result = (allp, unreachable, False)
        if result is None:
            paths, unreachable = self._plan_some(sorted(self.positions), {}, commit, t_start)
            result = (paths, unreachable, True)
            subset = set(self.positions)
        allp, unreachable, was_full = result
        for r in subset:
            self.unreachable.pop(r, None)
        self.unreachable.update(unreachable)
        changed = set()
        for r, p in allp.items():
            if old.get(r) != _compress(p):
                changed.add(r)
                self.replans[r] = self.replans.get(r, 0) + 1
        self.paths = allp
        self._dirty.clear()
        self._adg = ActionDependencyGraph(self.paths)
        for r in self.paths:
            self.positions[r] = self.paths[r][0]
        res = PlanResult(paths={r: list(p) for r, p in allp.items()}, changed=changed,
                         unreachable={r: self.unreachable[r] for r in self.unreachable},
                         full=was_full, elapsed_s=time.perf_counter() - t_start,
                         clearance={r: self._adg.clearance(r) for r in allp})
        self.last_result = res
        return res

    # -- the multi-robot search ---------------------------------------------------
    def _static_reason(self, robot: str, start: int, goal: int | None) -> str | None:
        if goal is None:
            return None
        if not self.graph.is_free(goal):
            return f"goal cell {goal} is not a free cell of the map"
        if goal in self.blocked:
            return f"goal cell {goal} is blocked (by {self.blocked[goal]})"
        if goal != start and self.distance(start, goal) == INF:
            return (f"goal cell {goal} cannot be reached from cell {start}: walls or blocked cells "
                    f"({sorted(self.blocked) or 'none'}) separate them")
        return None

    def _plan_some(self, todo: list[str], fixed: dict[str, list[int]], commit: dict[str, int | None],
                   t_start: float) -> tuple[dict[str, list[int]], dict[str, str]]:
        """Plan ``todo`` robots around the ``fixed`` paths. Returns (paths of todo, unreachable reasons)."""
        graph, N = self.graph, self.graph.n_cells
        owner_id = {r: i for i, r in enumerate(sorted(set(todo) | set(fixed)))}
        reasons: dict[str, str] = {}
        paths: dict[str, list[int]] = {}
        starts = {r: self.positions[r] for r in todo}
        # 1. static reasons, goals taken by others, goals occupied by parked robots
        goal_owner: dict[int, str] = {}
        for r, p in fixed.items():
            if self.goals.get(r) is not None and r not in self.unreachable:
                goal_owner[self.goals[r]] = r
        wanting = sorted((r for r in todo if self.goals.get(r) is not None),
                         key=lambda r: self._goal_seq.get(r, 0))
        self._h(self.goals[r] for r in wanting)
        for r in wanting:
            g = self.goals[r]
            why = self._static_reason(r, starts[r], g)
            if why is None and g in goal_owner:
                why = f"goal cell {g} is already the goal of robot {goal_owner[g]}"
            if why is not None:
                reasons[r] = why
            else:
                goal_owner[g] = r
        parked_cells: dict[int, str] = {p[-1]: r for r, p in fixed.items()
                                        if len(_compress(p)) == 1 and (self.goals.get(r) is None or r in self.unreachable)}
        changed = True
        while changed:
            changed = False
            for r in todo:
                if self.goals.get(r) is None or r in reasons:
                    parked_cells.setdefault(starts[r], r)
            for r in wanting:
                g = self.goals[r]
                if r not in reasons and g != starts[r] and g in parked_cells and parked_cells[g] != r:
                    o = parked_cells[g]
                    what = "has no goal" if self.goals.get(o) is None else "cannot move (its own goal is unreachable)"
                    reasons[r] = f"goal cell {g} is occupied by robot {o}, which is parked there ({what})"
                    changed = True
        movers = [r for r in wanting if r not in reasons]
        parked = [r for r in todo if r not in movers]
        # 2. prioritized planning with restarts
        base = Reservations(N)
        for r, p in fixed.items():
            base.reserve(p, owner_id[r])
        for r in parked:
            base.reserve([starts[r]], owner_id[r])
            paths[r] = [starts[r]]
        prefix: dict[str, list[int]] = {}
        for r in movers:
            c = commit.get(r)
            if c is not None and c != starts[r] and graph.is_free(c) and c not in self.blocked \
                    and self._hrow(self.goals[r])[c] < INF:
                prefix[r] = [starts[r], c]
            else:
                prefix[r] = [starts[r]]
        order = sorted(movers, key=lambda r: (self.distance(starts[r], self.goals[r]), r))
        failed_parked: list[str] = []
        attempts = 0
        self._attempts: dict[str, int] = {}
        while True:
            res = base.copy()
            for r in failed_parked:
                res.reserve([starts[r]], owner_id[r])
            for r in order:                      # nobody may run into a robot's start (or committed move)
                res.reserve(prefix[r], owner_id[r], park=False)
            got: dict[str, list[int]] = {}
            failed = None
            order_front = order[0] if order else None
            for r in order:
                res.release(prefix[r], owner_id[r])
                p = self._plan_one(r, prefix[r], res)
                if p is None and len(prefix[r]) > 1:     # cannot continue the committed move: plan from the cell
                    p = self._plan_one(r, prefix[r][:1], res)
                if p is None:
                    failed = r
                    break
                res.reserve(p, owner_id[r])
                got[r] = p
            if failed is None:
                paths.update(got)
                for r in failed_parked:
                    paths[r] = [starts[r]]
                    reasons[r] = self._fail_reason(r, starts[r], fixed, paths)
                return paths, reasons
            attempts += 1
            out_of_budget = attempts > self.max_restarts or time.perf_counter() - t_start > self.time_budget_s
            order.remove(failed)
            if out_of_budget or order_front == failed:
                failed_parked.append(failed)      # fails even with top priority (or no budget left): park it
                self._attempts[failed] = attempts
            else:
                order.insert(0, failed)           # priority bumping: plan it first next time

    def _plan_one(self, robot: str, prefix: list[int], res: Reservations) -> list[int] | None:
        """Path for ``robot`` that starts with ``prefix`` (its cell, maybe a committed next cell), or None."""
        g = self.goals[robot]
        h = self._hrow(g)
        s = prefix[-1]
        if h[s] == INF:             # starting in a non-free or blocked cell: escape moves only
            h = list(h)
            h[s] = self.distance(s, g)
        p = safe_interval_astar(self.graph.nbrs, s, g, h, res, self._budget(h[s]), t0=len(prefix) - 1,
                                weight=self.weight)
        return None if p is None else prefix[:-1] + p

    def _budget(self, dist: float) -> int:
        d = 0 if dist == INF else int(dist)
        return max(self.min_expansions, self.expansion_factor * (d + 1))

    def _fail_reason(self, robot: str, start: int, fixed: dict[str, list[int]], paths: dict[str, list[int]]) -> str:
        g = self.goals[robot]
        parked_by = {}
        for r, p in list(fixed.items()) + list(paths.items()):
            if r != robot and len(_compress(p)) == 1:
                parked_by[p[-1]] = r
        blocked = set(self.blocked) | set(parked_by)
        if shortest_path(self.graph, start, g, blocked - {start}) is None:
            who = sorted({parked_by[c] for c in parked_by})
            return (f"no collision-free path to goal cell {g}: parked robots ({', '.join(who)}) "
                    f"block the way")
        n = self._attempts.get(robot, 0)
        return (f"no collision-free path to goal cell {g} found in {n} planning attempt(s) (other robots' "
                f"paths or parked robots block it); parked, retried on the next re-plan")

    # -- execution ------------------------------------------------------------------
    def advance(self, robot: str, cell: int) -> dict[str, int]:
        """``robot`` reports it is now in ``cell``.

        On its path (current or a cleared later cell) its progress moves on;
        other robots waiting for it may get more clearance. Elsewhere (it left
        its plan, or moved without clearance) it is re-planned from ``cell``
        (``self.last_result`` holds that re-plan). A report of the previous
        cell is ignored (pose jitter at a cell border; filter it in the node).
        Returns robot -> new clearance for every robot whose clearance changed.
        Raises PlannerError for an unknown robot or a cell outside the grid.
        """
        self._check_robot(robot)
        cell = self._check_cell(cell)
        adg = self._adg
        if robot not in adg.visits or robot in self._dirty:
            self.positions[robot] = cell
            self._dirty.add(robot)
            return {}
        before = {r: adg.clearance(r) for r in adg.visits}
        k = adg.locate(robot, cell)
        if k is None:
            prog = adg.progress[robot]
            if prog > 0 and adg.visits[robot][prog - 1][0] == cell:
                return {}
            self.positions[robot] = cell
            self._dirty.add(robot)
            res = self._replan({robot} | set(self.unreachable))
            return {r: c for r, c in res.clearance.items() if before.get(r) != c or r in res.changed}
        adg.progress[robot] = k
        self.positions[robot] = cell
        after = {r: adg.clearance(r) for r in adg.visits}
        return {r: c for r, c in after.items() if before.get(r) != c}

    def clearance(self, robot: str) -> int:
        """Index into ``paths[robot]`` up to which the robot may move now (its current index if it must wait)."""
        self._check_robot(robot)
        if robot not in self._adg.visits:
            return 0
        return self._adg.clearance(robot)

    def progress(self, robot: str) -> int:
        """Index into ``paths[robot]`` of the step at which the robot entered its current cell."""
        self._check_robot(robot)
        if robot not in self._adg.visits:
            return 0
        return self._adg.position_index(robot)

    def cleared_cells(self, robot: str) -> list[int]:
        """Distinct cells the robot may drive through now, after its current one (the goals to send)."""
        p = self.paths.get(robot)
        if not p:
            return []
        return _compress(p[self.progress(robot):self.clearance(robot) + 1])[1:]

