"""Task allocation for a lifelong fleet: who does which open task next.

Both schedulers estimate a robot's *finish time* for a task as the breadth-first distance
from the robot to the task's first errand plus the task's own length (first errand through
the last), along the planner's distance maps (:class:`~.distances.DistanceCache`), minus a
bonus for priority. A task may be given to another robot until its robot reaches the first
errand (the League of Robot Runners' rule), never after.

- :class:`BatchScheduler` (the default; measured better, ``docs/lifelong.md``) and
  :class:`GreedyScheduler`: an auction on finish time, as Open-RMF's dispatcher bids
  (open-rmf/rmf_task, ``TaskPlanner``; minimal finish time wins): each free robot in turn
  takes the open task it would finish first, and may outbid the robot holding an unopened
  task when it would finish that task sooner by ``margin`` steps; the outbid robot bids
  again in the same round.
- :class:`BatchScheduler`: a batch assignment re-solved as robots free up and tasks arrive:
  every robot without an opened task against every unopened task, minimum total finish time
  by the Hungarian method (Kuhn 1955; ``scipy.optimize.linear_sum_assignment``, the LAPJV
  variant of Crouse 2016), with a small bonus for keeping the current assignment.

Distances to a task's first errand come from its cached map; a task whose map is not yet
computed (the budget ran out this step) is estimated by the Manhattan distance. With
``crowd_w`` > 0 a task also costs ``crowd_w`` steps per robot standing, beyond the block's
share of the team, in the 10 x 10 block of its first and of its last errand: robots are
sent elsewhere while an area is packed (a large team otherwise jams there).
"""
from __future__ import annotations

import time

import numpy as np
from scipy.optimize import linear_sum_assignment

from .distances import DistanceCache
from .tasks import Task

__all__ = ["BatchScheduler", "GreedyScheduler", "Scheduler", "make_scheduler"]

PRIORITY_STEPS = 100.0      # one unit of task priority is worth this many steps of finish time


class Scheduler:
    """Base: keeps the per-task estimates (first-errand map, length) and the cost vectors.

    ``schedule(pos, assignment, tasks, t, deadline)`` returns the proposed (n,) task id per
    robot (-1 none); it never moves an opened task, and stops computing new distance maps at
    ``deadline`` (a ``time.perf_counter()`` value). ``max_active`` (None: no bound): at most that
    many robots hold a task; the others stand aside without one.
    """

    name = "base"
    map_share = 0.5          # share of the scheduler's time for new first-errand maps
    crowd_w = 0.0            # steps added per robot in the block of a task's first and last errand
    crowd_block = 10         # side of those blocks (cells)
    length_w = 1.0           # share of a task's own length (first errand to last) in its cost
    max_active: int | None = None
    shed = 0                 # unopened tasks taken back to keep max_active

    def __init__(self, cache: DistanceCache):
        self.cache = cache
        self.cols = cache.grid.cols

    def _shed(self, pos: np.ndarray, assignment: np.ndarray, tasks: dict[int, Task]) -> np.ndarray:
        """A copy of ``assignment`` within ``max_active``: when more robots hold a task, the
        unopened tasks of those farthest (Manhattan) from their first errand are taken back,
        until the bound holds or no unopened task is left to take."""
        prop = assignment.copy()
        if self.max_active is None:
            return prop
        holders = np.flatnonzero(prop >= 0)
        excess = len(holders) - self.max_active
        if excess <= 0:
            return prop
        unopened = [a for a in holders.tolist() if not tasks[int(prop[a])].opened]
        if not unopened:
            return prop
        ids = np.array(unopened, dtype=np.int64)
        goal = np.fromiter((tasks[int(prop[a])].goal for a in unopened), dtype=np.int64, count=len(unopened))
        far = self._manhattan_pairs(pos[ids], goal)
        drop = ids[np.argsort(-far, kind="stable")[:excess]]
        prop[drop] = -1
        self.shed += len(drop)
        return prop

    # -- estimates ----------------------------------------------------------------------
    def _prepare(self, tasks: list[Task], deadline: float) -> None:
        """Compute first-errand maps and lengths of new tasks while time remains."""
        for tk in tasks:
            if tk.length >= 0:
                continue
            if time.perf_counter() > deadline:
                return
            e = tk.errands
            s = self.cache.slot(e[0])
            length = int(self.cache.table[s, e[1]]) if len(e) > 1 else 0
            for a, b in zip(e[1:], e[2:], strict=False):
                length += self.cache.dist(a, b)
            tk.length = length

    def _estimates(self, tasks: list[Task]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(slot, first errand, length less the priority bonus, the cost's cut) arrays; slot -1 and
        the Manhattan length where no map yet; the cut is the part of each length the cost leaves
        out, (1 - ``length_w``) x length."""
        e0 = np.fromiter((tk.errands[0] for tk in tasks), dtype=np.int64, count=len(tasks))
        slots = np.fromiter((self.cache.cached(int(c)) if tk.length >= 0 else -1
                             for c, tk in zip(e0.tolist(), tasks, strict=True)), dtype=np.int64, count=len(tasks))
        length = np.empty(len(tasks))
        for i, tk in enumerate(tasks):
            if tk.length >= 0 and slots[i] >= 0:
                length[i] = tk.length
            else:
                length[i] = sum(self._manhattan(a, b) for a, b in zip(tk.errands, tk.errands[1:], strict=False))
        bonus = np.fromiter((tk.priority * PRIORITY_STEPS for tk in tasks), dtype=float, count=len(tasks))
        return slots, e0, length - bonus, (1.0 - self.length_w) * length

    def _crowd(self, pos: np.ndarray, tasks: list[Task]) -> np.ndarray:
        """(len(tasks),) steps: ``crowd_w`` x the robots in the block (``crowd_block`` cells
        square) of each task's first and last errand beyond the block's share of the team
        (robots x the block's free cells / all free cells): a packed area costs, an evenly
        spread team costs nothing."""
        if not self.crowd_w:
            return np.zeros(len(tasks))
        b = self.crowd_block
        grid = self.cache.grid
        bcols = -(-self.cols // b)
        if getattr(self, "_blk_free", None) is None:
            free = grid.free_cells()
            self._blk_free = np.bincount((free // self.cols) // b * bcols + (free % self.cols) // b,
                                         minlength=(-(-grid.rows // b)) * bcols).astype(float)
        blk = (pos // self.cols) // b * bcols + (pos % self.cols) // b
        count = np.bincount(blk, minlength=len(self._blk_free))
        excess = np.maximum(0.0, count - self._blk_free * (len(pos) / self._blk_free.sum()))
        ends = np.array([(tk.errands[0], tk.errands[-1]) for tk in tasks], dtype=np.int64)
        eb = (ends // self.cols) // b * bcols + (ends % self.cols) // b
        return self.crowd_w * excess[eb].sum(axis=1)

    def _manhattan(self, a: int, b: int) -> int:
        ra, ca = divmod(a, self.cols)
        rb, cb = divmod(b, self.cols)
        return abs(ra - rb) + abs(ca - cb)

    def _manhattan_pairs(self, cells: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """(k,) Manhattan steps from cells[i] to targets[i]."""
        r0, c0 = np.divmod(targets, self.cols)
        rr, cc = np.divmod(cells, self.cols)
        return np.abs(rr - r0) + np.abs(cc - c0)

    def _travel(self, slots: np.ndarray, e0: np.ndarray, cells: np.ndarray) -> np.ndarray:
        """(len(cells), len(slots)) steps from each cell to each task's first errand."""
        table = self.cache.table
        have = slots >= 0
        out = np.empty((len(cells), len(slots)))
        if have.any():
            out[:, have] = table[slots[have][None, :], cells[:, None]]
        if (~have).any():
            r0, c0 = np.divmod(e0[~have], self.cols)
            rr, cc = np.divmod(cells, self.cols)
            out[:, ~have] = np.abs(rr[:, None] - r0[None, :]) + np.abs(cc[:, None] - c0[None, :])
        return out

    def _travel_pairs(self, slots: np.ndarray, e0: np.ndarray, cells: np.ndarray) -> np.ndarray:
        """(k,) steps from cells[i] to the first errand of task i."""
        out = np.empty(len(slots))
        have = slots >= 0
        out[have] = self.cache.table[slots[have], cells[have]]
        out[~have] = self._manhattan_pairs(cells[~have], e0[~have])
        return out

    def schedule(self, pos: np.ndarray, assignment: np.ndarray, tasks: dict[int, Task], t: int,
                 deadline: float) -> np.ndarray:
        raise NotImplementedError


def _windows(tasks: list[Task], t: int) -> tuple[np.ndarray, np.ndarray]:
    """(steps until each task may start, steps until its deadline (inf: none)) at step ``t``."""
    early = np.fromiter((tk.earliest_start - t for tk in tasks), dtype=float, count=len(tasks))
    late = np.fromiter((np.inf if tk.deadline is None else tk.deadline - t for tk in tasks), dtype=float,
                       count=len(tasks))
    return early, late


def _finish(travel: np.ndarray, length: np.ndarray, early: np.ndarray, late: np.ndarray,
            cut: np.ndarray | float = 0.0) -> np.ndarray:
    """Costs from finish-time estimates with time windows: start no earlier than earliest_start;
    a task that would miss its deadline costs infinity; the others cost their finish time less
    ``cut`` (steps of the task's own length the cost leaves out: :attr:`Scheduler.length_w`)."""
    fin = np.maximum(travel, early) + length
    return np.where(fin > late, np.inf, fin - cut)


class GreedyScheduler(Scheduler):
    """Auction on finish time with outbidding of unopened tasks (module docstring).

    margin: steps by which a bid must beat the holder's to take its task; max_rounds bounds
    the chain of outbid robots per step. Once ``max_active`` robots hold a task, the robots without
    one stand aside and do not bid: the bids of thousands of robots standing aside, every step, took
    the step's time from the planner (docs/lifelong.md). Robots bid in index order, so which robots
    take the free places is not the cheapest choice, as in :class:`BatchScheduler`.
    """

    name = "greedy"

    def __init__(self, cache: DistanceCache, margin: float = 2.0, reassign: bool = True, chunk: int = 64):
        super().__init__(cache)
        self.margin, self.reassign, self.chunk = margin, reassign, chunk

    def schedule(self, pos, assignment, tasks, t, deadline):
        prop = self._shed(pos, assignment, tasks)
        free = [int(a) for a in np.flatnonzero(prop < 0)]
        holding = len(prop) - len(free)
        if not free or self.max_active is not None and holding >= self.max_active:
            return prop
        cand = [tk for tk in tasks.values() if not tk.opened]
        if not cand:
            return prop
        t0 = time.perf_counter()
        self._prepare(cand, t0 + self.map_share * max(0.0, deadline - t0))
        slots, e0, length, cut = self._estimates(cand)
        length = length + self._crowd(pos, cand)
        holder = np.fromiter((tk.agent if tk.agent >= 0 and prop[tk.agent] == tk.id else -1 for tk in cand),
                             dtype=np.int64, count=len(cand))        # a task just shed has none
        early, late = _windows(cand, t)
        holder_bid = np.full(len(cand), np.inf)
        held = np.flatnonzero(holder >= 0)
        if len(held):
            tr = self._travel_pairs(slots[held], e0[held], pos[holder[held]])
            holder_bid[held] = _finish(tr, length[held], early[held], late[held], cut[held])
        queue = list(free)
        rows: dict[int, np.ndarray] = {}
        budget = len(free) + len(cand)
        k = 0
        while k < len(queue) and budget > 0 and (self.max_active is None or holding < self.max_active):
            r = queue[k]
            if r not in rows:                  # bids of the next chunk of robots, while time remains
                if rows and time.perf_counter() > deadline:
                    break
                chunk = [x for x in queue[k:k + self.chunk] if x not in rows]
                bids = _finish(self._travel(slots, e0, pos[np.array(chunk, dtype=np.int64)]), length,
                               early[None, :], late[None, :], cut[None, :])
                rows.update(zip(chunk, bids, strict=True))
            budget -= 1
            k += 1
            bid = rows[r]
            ok = holder < 0
            if self.reassign:
                ok |= (holder >= 0) & (bid < holder_bid - self.margin)
            j = int(np.argmin(np.where(ok, bid, np.inf)))
            if not ok[j] or not np.isfinite(bid[j]):
                continue
            old = int(holder[j])
            if old >= 0:
                prop[old] = -1
                queue.append(old)
            else:
                holding += 1
            holder[j], holder_bid[j] = r, bid[j]
            prop[r] = cand[j].id
        return prop


class BatchScheduler(Scheduler):
    """Batch assignment (module docstring): robots without an opened task against unopened
    tasks, re-solved at each step where a robot is free. keep_bonus: steps of finish time a
    robot's current task is favoured by (hysteresis). Under ``max_active`` the cheapest pairs of
    the assignment are kept; the others stand aside without one (on a packed map fewer robots on
    the move finish more: docs/lifelong.md)."""

    name = "batch"

    def __init__(self, cache: DistanceCache, keep_bonus: float = 2.0, max_cells: int = 1_000_000):
        super().__init__(cache)
        self.keep_bonus, self.max_cells = keep_bonus, max_cells
        self._greedy = GreedyScheduler(cache)
        self.fallbacks = 0

    def schedule(self, pos, assignment, tasks, t, deadline):
        prop = self._shed(pos, assignment, tasks)
        if not (prop < 0).any():
            return prop
        cand = [tk for tk in tasks.values() if not tk.opened]
        if not cand:
            return prop
        opened = {tk.agent for tk in tasks.values() if tk.opened}
        robots = np.array([a for a in range(len(pos)) if a not in opened], dtype=np.int64)
        if len(robots) * len(cand) > self.max_cells:        # too big for one step: bid greedily
            self.fallbacks += 1
            self._greedy.max_active = self.max_active
            return self._greedy.schedule(pos, prop, tasks, t, deadline)     # already within the bound
        self._prepare(cand, deadline)
        slots, e0, length, cut = self._estimates(cand)
        length = length + self._crowd(pos, cand)
        early, late = _windows(cand, t)
        cost = _finish(self._travel(slots, e0, pos[robots]), length, early[None, :], late[None, :], cut[None, :])
        col = {tk.id: j for j, tk in enumerate(cand)}
        for i, a in enumerate(robots.tolist()):
            j = col.get(int(assignment[a]))
            if j is not None:
                cost[i, j] -= self.keep_bonus
        bad = ~np.isfinite(cost)
        cost[bad] = 1e9
        if self.max_active is not None:         # at most max_active robots hold a task: the cheapest pairs
            allowed = max(0, self.max_active - len(opened))
            if 2 * allowed < len(robots):       # only the robots with the cheapest tasks (a smaller problem)
                near = np.argsort(cost.min(axis=1), kind="stable")[:2 * allowed]
                sub, sub_cols = linear_sum_assignment(cost[near])
                rows, cols = near[sub], sub_cols
            else:
                rows, cols = linear_sum_assignment(cost)
            keep = np.argsort(cost[rows, cols], kind="stable")[:allowed]
            rows, cols = rows[keep], cols[keep]
        else:
            rows, cols = linear_sum_assignment(cost)
        prop[robots] = -1
        for i, j in zip(rows.tolist(), cols.tolist(), strict=True):
            if not bad[i, j]:
                prop[robots[i]] = cand[j].id
        return prop


def make_scheduler(name: str, cache: DistanceCache, crowd_w: float = 0.0, length_w: float | None = None) -> Scheduler:
    """``"greedy"`` or ``"batch"``, with ``crowd_w`` (:meth:`Scheduler._crowd`) and ``length_w``
    (:attr:`Scheduler.length_w`; None: its default); raises ValueError for another name or a
    ``length_w`` that is negative or not finite."""
    if length_w is not None and not (np.isfinite(length_w) and length_w >= 0):
        raise ValueError(f"length_w must be a finite share >= 0 of a task's length, got {length_w}")
    if name == "greedy":
        sched: Scheduler = GreedyScheduler(cache)
    elif name == "batch":
        sched = BatchScheduler(cache)
        sched._greedy.crowd_w = crowd_w
    else:
        raise ValueError(f"unknown scheduler {name!r} (greedy, batch)")
    sched.crowd_w = crowd_w
    if length_w is not None:
        sched.length_w = length_w
        if isinstance(sched, BatchScheduler):
            sched._greedy.length_w = length_w
    return sched
