"""The reservation table of prioritized planning (Silver 2005, "Cooperative Pathfinding",
AIIDE): which robot holds which cell at which plan step, for robots planned earlier.

Robots are numbered owners (ints); steps are plan time steps (one cell move or one wait).
"""
from __future__ import annotations

import bisect
from collections.abc import Sequence

import numpy as np

from .sipp_kernel import NEVER

__all__ = ["Reservations"]

_ROWS = 256                 # steps of the dense table at first (doubled as paths grow)


class Reservations:
    """Reservation table for prioritized planning (Silver 2005).

    ``vertex[t * n + cell] = owner`` for every reserved (cell, step);
    ``occ[cell]``: sorted steps at which ``cell`` is reserved;
    ``parked[cell] = t``: the owner stays in ``cell`` from step t for ever;
    ``paths[owner]``: the owner's reserved cells from step 0 (``parks[owner]``:
    whether it stays in the last one for ever).

    The same, dense, for the compiled search (:mod:`.sipp_kernel`): ``vt`` (steps, cells)
    int32 owner or -1 (rows from ``top`` on are free), ``park`` (cells,) int64 (``NEVER``:
    not parked), ``opath`` (owners, steps) int32, ``olen`` (owners,) int64, ``opark``
    (owners,) int8.
    """

    __slots__ = ("n", "vertex", "occ", "parked", "paths", "parks", "vt", "top", "park", "opath", "olen", "opark")

    def __init__(self, n_cells: int):
        self.n = n_cells
        self.vertex: dict[int, int] = {}
        self.occ: dict[int, list[int]] = {}
        self.parked: dict[int, int] = {}
        self.paths: dict[int, list[int]] = {}
        self.parks: dict[int, bool] = {}
        self.vt = np.full((_ROWS, n_cells), -1, dtype=np.int32)
        self.top = 0
        self.park = np.full(n_cells, NEVER, dtype=np.int64)
        self.opath = np.zeros((0, _ROWS), dtype=np.int32)
        self.olen = np.zeros(0, dtype=np.int64)
        self.opark = np.zeros(0, dtype=np.int8)

    def copy(self) -> "Reservations":
        """An independent copy."""
        r = Reservations.__new__(Reservations)
        r.n = self.n
        r.vertex, r.parked = dict(self.vertex), dict(self.parked)
        r.occ = {c: list(ts) for c, ts in self.occ.items()}
        r.paths, r.parks = dict(self.paths), dict(self.parks)
        r.vt, r.top, r.park = self.vt.copy(), self.top, self.park.copy()
        r.opath, r.olen, r.opark = self.opath.copy(), self.olen.copy(), self.opark.copy()
        return r

    def _room(self, steps: int, owner: int) -> None:
        """Grow the dense arrays to hold ``steps`` steps and ``owner``."""
        rows = self.vt.shape[0]
        if steps > rows:
            new = max(steps, 2 * rows)
            self.vt = np.concatenate([self.vt, np.full((new - rows, self.n), -1, dtype=np.int32)])
            self.opath = np.concatenate([self.opath, np.zeros((self.opath.shape[0], new - rows), dtype=np.int32)], 1)
        if owner >= self.olen.shape[0]:
            k = max(owner + 1, 2 * self.olen.shape[0])
            extra = k - self.olen.shape[0]
            self.opath = np.concatenate([self.opath, np.zeros((extra, self.vt.shape[0]), dtype=np.int32)])
            self.olen = np.concatenate([self.olen, np.zeros(extra, dtype=np.int64)])
            self.opark = np.concatenate([self.opark, np.zeros(extra, dtype=np.int8)])

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
        end = t0 + len(path)
        self._room(end, owner)
        self.vt[np.arange(t0, end), np.asarray(path, dtype=np.int64)] = owner
        self.top = max(self.top, end)
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
            self.park[path[-1]] = t0 + len(path) - 1
        if t0 == 0:
            self.paths[owner] = list(path)
            self.parks[owner] = park
            self.opath[owner, :len(path)] = path
            self.olen[owner] = len(path)
            self.opark[owner] = park

    def release(self, path: Sequence[int], owner: int, t0: int = 0) -> None:
        """Undo :meth:`reserve` of ``path`` for ``owner`` (its parked final cell too)."""
        n = self.n
        if self.paths.pop(owner, None) is not None:
            self.olen[owner] = 0
        if self.parks.pop(owner, False) and path and self.parked.get(path[-1]) == t0 + len(path) - 1 \
                and self.vertex.get((t0 + len(path) - 1) * n + path[-1]) == owner:
            del self.parked[path[-1]]
            self.park[path[-1]] = NEVER
        if path:
            ts, cs = np.arange(t0, t0 + len(path)), np.asarray(path, dtype=np.int64)
            mine = self.vt[ts, cs] == owner
            self.vt[ts[mine], cs[mine]] = -1
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
