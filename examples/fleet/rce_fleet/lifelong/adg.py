"""Execute a 4-neighbour MAPF plan under MAPF_T's turns by an action dependency graph.

Hönig, Kiesel, Tinka, Durham and Ayanian, "Persistent and Robust Execution of MAPF Schedules in
Warehouses" (IEEE RA-L 2019). A one-shot plan (:func:`~.lacam.solve_lacam`: a configuration per
time step) says, for every cell, in which order robots pass it. Under MAPF_T a robot must face
a cell before it enters it, and turns take steps the plan does not have, so robots cannot keep
the plan's timing; they keep its *order* instead. A robot enters the next cell of its path once
every robot that passes that cell earlier in the plan has left it, or is leaving it in the same
step (the rules allow following, and cycles of three or more robots moving at once; swaps
cannot occur, as the plan has none). Until then it turns to face that cell, or waits.

Executed so, the plan's order is kept, no two robots ever meet (vertex or swap), and every robot
reaches the end of its path: the order is that of the plan's times, so the dependencies form no
cycle that could hold robots for good (a cycle of robots moving at once into each other's cells
moves at once).

Sans-I/O and free of the clock: :class:`PlanExecution` takes a plan and answers each step's
actions from the robots' cells and headings.
"""
from __future__ import annotations

import numpy as np

from .kernels import ACT_C, ACT_F, ACT_R, ACT_W
from .simulator import turned

__all__ = ["PlanExecution"]


class PlanExecution:
    """One plan being executed (module docstring).

    nbr: (cells, 4) the map's moves (:class:`~.grid.LifelongGrid`'s ``nbr``); paths: (T + 1, n)
    cells, row t the configuration at time t (row 0 where the robots stand). Each robot's path
    is kept without its waits: the cells it enters in order. ``progress`` (n,) is the index of
    the cell each robot stands on in its own path; ``done`` says every robot reached its path's
    end. Raises ValueError for a plan whose consecutive cells of a robot are not neighbours.
    """

    def __init__(self, nbr: np.ndarray, paths: np.ndarray):
        paths = np.asarray(paths, dtype=np.int64)
        if paths.ndim != 2 or paths.shape[0] < 1:
            raise ValueError(f"paths must be (T + 1, n) cells, got shape {paths.shape}")
        self.n = paths.shape[1]
        seqs: list[np.ndarray] = []               # per robot: the cells it enters, in order
        times: list[np.ndarray] = []              # and the plan's time it enters each
        for a in range(self.n):
            col = paths[:, a]
            at = np.concatenate(([0], np.flatnonzero(col[1:] != col[:-1]) + 1))
            seqs.append(col[at])
            times.append(at)
        # every visit (robot, index into its path), and the visit of the same cell just before it in
        # the plan's time: only that one need be waited for, as it waited for the one before it
        lens = np.array([len(c) for c in seqs], dtype=np.int64)
        self._off = np.concatenate(([0], np.cumsum(lens)))[:-1].astype(np.int64)   # each robot's first visit
        cell = np.concatenate(seqs) if self.n else np.zeros(0, np.int64)
        self._cell, self._last = cell, lens - 1
        # the heading a robot faces to enter each visit's cell from its path's cell before (0 for a start)
        start = np.zeros(len(cell), dtype=bool)
        start[self._off] = True
        self._enter = np.zeros(len(cell), dtype=np.int64)
        k = np.flatnonzero(~start)
        match = nbr[cell[k - 1]] == cell[k, None]
        when = np.concatenate(times).astype(np.int64) if self.n else np.zeros(0, np.int64)
        bad = k[~match.any(axis=1)]
        if len(bad):
            v = int(bad[0])
            a = int(np.searchsorted(self._off, v, side="right")) - 1
            raise ValueError(f"robot {a}: cell {cell[v]} at time {when[v]} is not a neighbour of {cell[v - 1]}")
        self._enter[k] = np.argmax(match, axis=1)
        robot = np.repeat(np.arange(self.n, dtype=np.int64), lens)
        index = np.arange(len(cell), dtype=np.int64) - np.repeat(self._off, lens)
        order = np.lexsort((when, cell))
        same = np.zeros(len(cell), dtype=bool)
        same[1:] = cell[order[1:]] == cell[order[:-1]]
        self._pred_robot = np.full(len(cell), -1, dtype=np.int64)
        self._pred_index = np.full(len(cell), -1, dtype=np.int64)
        prev = np.roll(order, 1)
        self._pred_robot[order[same]] = robot[prev[same]]
        self._pred_index[order[same]] = index[prev[same]]
        self.progress = np.zeros(self.n, dtype=np.int64)

    @property
    def done(self) -> bool:
        """True once every robot stands on its path's last cell."""
        return bool((self.progress == self._last).all())

    def expected(self) -> np.ndarray:
        """(n,) the cell each robot stands on by the plan's progress."""
        return self._cell[self._off + self.progress]

    def arrivals(self, head: np.ndarray, limit: int = 10_000) -> np.ndarray:
        """(n,) int64: the step at which each robot would reach its path's end, executed from
        ``progress`` with headings ``head`` (n,); ``progress`` is left as it was. Raises
        RuntimeError when the plan does not end within ``limit`` steps."""
        keep = self.progress.copy()
        head = np.asarray(head, dtype=np.int64).copy()
        at = np.zeros(self.n, dtype=np.int64)
        try:
            for t in range(1, limit + 1):
                if self.done:
                    return at
                cells = self.expected()
                act = self.step(head)
                head = turned(head, act)
                moved = self.expected() != cells
                at[moved] = t
            raise RuntimeError(f"the plan did not end within {limit} steps")
        finally:
            self.progress = keep

    def step(self, head: np.ndarray) -> np.ndarray:
        """The actions (n,) int64 (:mod:`.kernels` codes) of the next step, for robots facing
        ``head`` (n,) and standing where ``progress`` says; advances ``progress`` of the robots
        that move."""
        n = self.n
        want = np.full(n, -1, dtype=np.int64)     # the robot that must leave first (-1: none; -2: blocked)
        act = np.full(n, ACT_W, dtype=np.int64)
        for a in range(n):
            i = int(self.progress[a])
            if i == self._last[a]:
                want[a] = -2
                continue
            k = self._off[a] + i + 1
            d = (int(self._enter[k]) - int(head[a])) % 4
            if d:
                act[a] = ACT_R if d in (1, 2) else ACT_C
                want[a] = -2
                continue
            b, j = int(self._pred_robot[k]), int(self._pred_index[k])
            if b < 0 or self.progress[b] > j:
                continue                          # the cell is free now
            want[a] = b if self.progress[b] == j else -2
        moves = np.zeros(n, dtype=bool)
        state = np.zeros(n, dtype=np.int8)        # 0 unknown, 1 on the path being resolved, 2 resolved
        for a0 in range(n):
            if state[a0]:
                continue
            chain = []
            a = a0
            while a >= 0 and state[a] == 0:
                state[a] = 1
                chain.append(a)
                a = int(want[a])
            if a >= 0 and state[a] == 1:          # a cycle of robots moving into each other's cells (not a swap)
                go = len(chain) - chain.index(a) > 2
            elif a >= 0:                          # reached a robot already resolved
                go = bool(moves[a])
            else:
                go = a == -1                      # the chain ends at a free cell (-1) or a blocked robot (-2)
            for b in reversed(chain):             # a robot moves when the one it waits for does
                go = go and want[b] != -2
                moves[b] = go
                state[b] = 2
        act[moves] = ACT_F
        self.progress[moves] += 1
        return act
