"""Execution that keeps the plan's order under delays: the action dependency graph (Hoenig
et al. 2019, "Persistent and Robust Execution of MAPF Schedules in Warehouses", IEEE RA-L).

Robots do not move in lock-step. A robot may enter a cell only after every robot planned to
be in that cell *earlier* has left it. With a conflict-free plan (:mod:`.paths`) this is
collision- and deadlock-free under any delays: the dependencies go forward in plan time,
so the graph is acyclic.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

__all__ = ["ActionDependencyGraph"]


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

    def allowed(self, robot: str, visit: int) -> bool:
        """True when ``robot`` may enter the cell of its ``visit`` now."""
        p = self.pred[robot][visit]
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

