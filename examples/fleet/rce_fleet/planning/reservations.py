"""The reservation table of prioritized planning (Silver 2005, "Cooperative Pathfinding",
AIIDE): which robot holds which cell at which plan step, for robots planned earlier.

Robots are numbered owners (ints); steps are plan time steps (one cell move or one wait).
"""
from __future__ import annotations

import bisect
from collections.abc import Sequence

__all__ = ["Reservations"]


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

    def cell_of(self, owner: int, step: int) -> int | None:
        """Where ``owner`` is at ``step`` (None when not known: an unplanned robot past its start)."""
        p = self.paths.get(owner)
        if p is None:
            return None
        if step < len(p):
            return p[step]
        return p[-1] if self.parks.get(owner) else None

    def closes_rotation(self, from_cell: int, to_cell: int, step: int) -> bool:
        """True when moving u -> v between t and t + 1 closes a cycle of robots each
        entering the cell the next one leaves (a swap is the 2-cycle)."""
        n, vertex = self.n, self.vertex
        o = vertex.get(step * n + to_cell)
        for _ in range(len(self.paths) + 1):
            if o is None:
                return False
            x = self.cell_of(o, step + 1)
            if x is None:
                return False
            if x == from_cell:
                return True
            o = vertex.get(step * n + x)
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
        """Undo :meth:`reserve` of ``path`` for ``owner`` (its parked final cell too)."""
        n = self.n
        self.paths.pop(owner, None)
        if self.parks.pop(owner, False) and path and self.parked.get(path[-1]) == t0 + len(path) - 1 \
                and self.vertex.get((t0 + len(path) - 1) * n + path[-1]) == owner:
            del self.parked[path[-1]]
        for k, c in enumerate(path):
            t = t0 + k
            if self.vertex.get(t * n + c) == owner:
                del self.vertex[t * n + c]
                ts = self.occ[c]
                ts.pop(bisect.bisect_left(ts, t))
                if not ts:
                    del self.occ[c]

    def blockers(self, path: Sequence[int], owner: int) -> set[int]:
        """The owners whose reservations ``path`` (from step 0, its final cell held for ever
        after) would collide with: a (cell, step) they hold, a cell they are parked in, a swap
        or a rotation with them; empty when ``path`` fits."""
        n, vertex, out = self.n, self.vertex, set()
        for t, c in enumerate(path):
            o = vertex.get(t * n + c)
            if o is not None and o != owner:
                out.add(o)
            p = self.parked.get(c)
            if p is not None and p <= t:
                o = vertex.get(p * n + c)
                if o is not None and o != owner:
                    out.add(o)
            if t > 0 and path[t - 1] != c:
                u = path[t - 1]
                o = vertex.get((t - 1) * n + c)
                if o is not None and o != owner and (vertex.get(t * n + u) == o or self.closes_rotation(u, c, t - 1)):
                    out.add(o)
        end, last = len(path) - 1, path[-1]
        for t in self.occ.get(last, ())[bisect.bisect_right(self.occ.get(last, ()), end):]:
            o = vertex.get(t * n + last)
            if o is not None and o != owner:
                out.add(o)
        return out

    def last(self, cell: int) -> int:
        """Last reserved step of ``cell`` (-1 if none)."""
        ts = self.occ.get(cell)
        return ts[-1] if ts else -1
