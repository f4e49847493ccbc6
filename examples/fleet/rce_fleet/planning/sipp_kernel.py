"""The compiled search of :func:`.sipp.safe_interval_astar` (numba, ``cache=True``), on the
dense mirror of a :class:`.reservations.Reservations` table.

Why compiled (py-spy of the 100-robot control loop, ``bench/fleet_live.py --control-only``):
SIPP took 70 % of the run's CPU, its successor generation 43 %. The logic is the Python
search's, step for step (same states, same order, same paths): only the reservation lookups
change, from sorted step lists to scans of the dense (step, cell) owner table, the layout of
:mod:`rce_fleet.lifelong.spacetime`.

Arrays: ``vt`` (steps, cells) int32 owner or -1, rows from ``top`` on are free; ``park``
(cells,) int64 step from which the cell is held for ever, :data:`NEVER` if not; ``opath``
(owners, steps) int32 each owner's reserved cells from step 0, ``olen`` their lengths (0: no
path), ``opark`` 1 when the owner stays in its last cell for ever.
"""
from __future__ import annotations

import heapq

import numpy as np
from numba import njit

from ..numba_cache import seed

seed(__file__)          # numba's cache entries prepared in the tree (sandboxed nodes)

__all__ = ["NEVER", "sipp_search", "warm_up"]

NEVER = np.int64(2 ** 62)          # "no step" / unbounded interval end


@njit(cache=True)
def _owner(vt, top, t, c):
    if t < 0 or t >= top:
        return -1
    return vt[t, c]


@njit(cache=True)
def _prev_reserved(vt, top, c, t):
    """Largest reserved step <= t of cell c, -1 if none."""
    s = t if t < top - 1 else top - 1
    while s >= 0:
        if vt[s, c] >= 0:
            return s
        s -= 1
    return -1


@njit(cache=True)
def _next_reserved(vt, top, c, t):
    """Smallest reserved step > t of cell c, NEVER if none."""
    s = t + 1
    if s < 0:
        s = 0
    while s < top:
        if vt[s, c] >= 0:
            return s
        s += 1
    return NEVER


@njit(cache=True)
def _cell_of(opath, olen, opark, o, s):
    n = olen[o]
    if n == 0:
        return -1
    if s < n:
        return opath[o, s]
    if opark[o]:
        return opath[o, n - 1]
    return -1


@njit(cache=True)
def _closes_rotation(vt, top, opath, olen, opark, n_paths, frm, to, step):
    """:meth:`.reservations.Reservations.closes_rotation` on the dense table."""
    o = _owner(vt, top, step, to)
    for _ in range(n_paths + 1):
        if o < 0:
            return False
        x = _cell_of(opath, olen, opark, o, step + 1)
        if x < 0:
            return False
        if x == frm:
            return True
        o = _owner(vt, top, step, x)
    return False


@njit(cache=True)
def sipp_search(nbr, nnbr, h, start, goal, vt, top, park, opath, olen, opark, n_paths, t0, w, max_exp,
                stamp, sid, closed, best, scell, sarr, send, spar, out):
    """SIPP from ``start`` at step ``t0`` to ``goal`` (see :func:`.sipp.safe_interval_astar`).

    nbr (cells, 4) int64 neighbour cells, ``nnbr`` (cells,) how many; ``h`` (cells,) float64
    heuristic (inf: unreachable). ``stamp``, ``closed``, ``best``, ``scell``, ``sarr``,
    ``send``, ``spar``: scratch of length >= (top + 2) * cells, a state seen when
    ``stamp == sid`` (closed when ``closed == sid``). Writes the path into ``out`` and
    returns its length, 0 when there is none, -1 when ``out`` is too short."""
    N = h.shape[0]
    inf = np.inf
    if h[start] == inf or park[goal] < NEVER:
        return 0
    last = _prev_reserved(vt, top, goal, top - 1)
    G1 = last + 1
    # the start interval's end
    nr = _next_reserved(vt, top, start, t0)
    e0 = nr - 1 if nr < NEVER else NEVER
    p = park[start]
    if p < NEVER and p - 1 < e0:
        e0 = p - 1
    if e0 < t0:
        e0 = t0
    s_key = t0 * N + start
    stamp[s_key] = sid
    best[s_key] = t0
    scell[s_key] = start
    sarr[s_key] = t0
    send[s_key] = e0
    spar[s_key] = -1
    h0 = h[start]
    rest0 = float(G1 - t0)
    open_ = [(t0 + w * (h0 if h0 > rest0 else rest0), h0, -t0, s_key)]
    expansions = 0
    found = -1
    while len(open_) > 0:
        item = heapq.heappop(open_)
        skey = item[3]
        if closed[skey] == sid:
            continue
        closed[skey] = sid
        u = scell[skey]
        a = sarr[skey]
        e = send[skey]
        if u == goal and e == NEVER:
            found = skey
            break
        expansions += 1
        if expansions > max_exp:
            break
        lo = a + 1
        hi = e + 1 if e < NEVER else NEVER
        for j in range(nnbr[u]):
            v = nbr[u, j]
            hv = h[v]
            if hv == inf:
                continue
            pv = park[v]
            s_int = _prev_reserved(vt, top, v, lo) + 1
            nxt = _next_reserved(vt, top, v, lo)
            while s_int <= hi and s_int < pv:
                e_int = nxt - 1 if nxt < NEVER else NEVER
                if pv < NEVER and e_int > pv - 1:
                    e_int = pv - 1
                if e_int >= s_int and e_int >= lo:
                    t_arr = lo if lo > s_int else s_int
                    last_ok = e_int if e_int < hi else hi
                    # following whoever is in v at t_arr - 1: no swap, no rotation
                    while t_arr <= last_ok:
                        o = _owner(vt, top, t_arr - 1, v)
                        if o < 0:
                            break
                        if _owner(vt, top, t_arr, u) != o and not _closes_rotation(
                                vt, top, opath, olen, opark, n_paths, u, v, t_arr - 1):
                            break
                        t_arr += 1
                    if t_arr <= last_ok:
                        key = s_int * N + v
                        if closed[key] != sid and (stamp[key] != sid or t_arr < best[key]):
                            stamp[key] = sid
                            best[key] = t_arr
                            scell[key] = v
                            sarr[key] = t_arr
                            send[key] = e_int
                            spar[key] = skey
                            rest = float(G1 - t_arr)
                            heapq.heappush(open_, (t_arr + w * (hv if hv > rest else rest), hv, -t_arr, key))
                if nxt >= NEVER:
                    break
                s_int = nxt + 1
                nxt = _next_reserved(vt, top, v, nxt)
    if found < 0:
        return 0
    # the cells for every step, waits filled in
    length = sarr[found] + 1 - t0
    if length > out.shape[0]:
        return -1
    k = found
    until = sarr[found] + 1
    while k != -1:
        g = sarr[k]
        for t in range(g, until):
            out[t - t0] = scell[k]
        until = g
        k = spar[k]
    return length


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernel on a 1 x 2 grid."""
    nbr = np.array([[1, -1, -1, -1], [0, -1, -1, -1]], dtype=np.int64)
    nnbr = np.array([1, 1], dtype=np.int64)
    vt = np.full((4, 2), -1, dtype=np.int32)
    size = 6 * 2
    scratch = [np.zeros(size, dtype=np.int32), np.zeros(size, dtype=np.int32)] + \
        [np.zeros(size, dtype=np.int64) for _ in range(5)]
    sipp_search(nbr, nnbr, np.array([1.0, 0.0]), 0, 1, vt, 0, np.full(2, NEVER, dtype=np.int64),
                np.zeros((1, 4), dtype=np.int32), np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int8), 0, 0,
                1.0, 10, scratch[0], 1, scratch[1], scratch[2], scratch[3], scratch[4], scratch[5], scratch[6],
                np.zeros(8, dtype=np.int64))
