"""Compiled hot loops of the lifelong planner (numba, ``cache=True``): breadth-first
distance maps, one PIBT step, the MAPF_T conversion with its move check, and the binary heap
of the one-shot searches.

Why compiled (measured on sortation_large_2000, 2,000 robots, 70,000 cells): one PIBT step
costs 27 ms in pure Python and 0.9 ms compiled; one breadth-first map 150 ms and 3.5 ms.
The lookahead runs many PIBT steps per time step, and every new goal needs a map.
Call :func:`warm_up` once before the first timed step: it compiles (or loads from the
on-disk cache) every kernel on a tiny grid, so compile time never counts against a step.

Arrays: ``nbr`` (cells, 4) int32 from :class:`~.grid.LifelongGrid`; distance rows are
uint16 with :data:`UNREACHABLE` for cells that cannot reach the goal.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from ..numba_cache import seed

seed(__file__)          # numba's cache entries prepared in the tree (sandboxed nodes)

__all__ = ["ACT_C", "ACT_F", "ACT_R", "ACT_W", "MOVE_WAIT", "NO_PREFER", "UNREACHABLE", "bfs_fill", "bfs_multi",
           "bfs_pair", "dial_fill", "heading_cost", "heap_pop", "heap_push", "prefer_table", "preferred",
           "mapf_t_actions", "heading_costs", "pibt_step", "turned", "warm_up"]

UNREACHABLE = 65535
# MAPF_T actions (start-kit order of the letters F, R, C, W)
ACT_F, ACT_R, ACT_C, ACT_W = 0, 1, 2, 3
# 4-neighbour actions: 0..3 move towards heading E, S, W, N; 4 waits
MOVE_WAIT = 4
# pibt_step's ``prefer`` when no agent has a preferred next cell (see :func:`prefer_table`)
NO_PREFER = np.full((0, 2), -1, dtype=np.int64)


@njit(cache=True)
def _prefer_slot(prefer, key):
    """The slot of ``key`` in the open-addressing table ``prefer``, or the empty slot where it
    would go."""
    mask = prefer.shape[0] - 1
    i = (key ^ (key >> 17) ^ (key >> 31)) & mask
    while prefer[i, 0] != -1 and prefer[i, 0] != key:
        i = (i + 1) & mask
    return i


@njit(cache=True)
def prefer_table(agents, cells, nxt, n_cells):
    """A hash table of preferred next cells for :func:`pibt_step`: agent ``agents[k]`` standing
    on ``cells[k]`` tries ``nxt[k]`` first. (size, 2) int64, size a power of two at least twice
    the entries (memory: 32 bytes per entry at most, whatever the map's size); rows (key, next
    cell) with key = agent * ``n_cells`` + cell, -1 keys empty."""
    size = 2
    while size < 2 * agents.shape[0]:
        size *= 2
    out = np.full((size, 2), -1, np.int64)
    for k in range(agents.shape[0]):
        key = agents[k] * n_cells + cells[k]
        i = _prefer_slot(out, key)
        out[i, 0] = key
        out[i, 1] = nxt[k]
    return out


@njit(cache=True)
def preferred(prefer, a, u, n_cells):
    """The next cell agent ``a`` on ``u`` tries first in ``prefer`` (:func:`prefer_table`), or -1."""
    if prefer.shape[0] == 0:
        return -1
    i = _prefer_slot(prefer, a * n_cells + u)
    return prefer[i, 1] if prefer[i, 0] >= 0 else -1


@njit(cache=True)
def heap_push(hk, hv, size, key, val):
    """Push (``key``, ``val``) on the binary min-heap ``hk`` (int64 keys) / ``hv`` (values) of
    ``size`` entries; returns the new size (the arrays must have room). The parents above
    the new entry's place move down one level each, and the entry is written once."""
    i = size
    while i > 0:
        p = (i - 1) >> 1
        if hk[p] <= key:
            break
        hk[i] = hk[p]
        hv[i] = hv[p]
        i = p
    hk[i] = key
    hv[i] = val
    return size + 1


@njit(cache=True)
def heap_pop(hk, hv, size):
    """Pop the least key; returns (key, value, new size). The last entry sinks from the root
    into the hole left by the smaller child at each level, and is written once."""
    key = hk[0]
    val = hv[0]
    size -= 1
    k = hk[size]
    v = hv[size]
    i = 0
    while True:
        c = 2 * i + 1
        if c >= size:
            break
        if c + 1 < size and hk[c + 1] < hk[c]:
            c += 1
        if k <= hk[c]:
            break
        hk[i] = hk[c]
        hv[i] = hv[c]
        i = c
    hk[i] = k
    hv[i] = v
    return key, val, size


@njit(cache=True)
def bfs_fill(nbr, goal, out, queue):
    """Breadth-first distances (steps) from every cell to ``goal`` into ``out`` (uint16,
    cells); ``queue`` is int32 scratch of the same length. Moves are symmetric, so the
    distance from ``goal`` is the distance to it."""
    out[:] = UNREACHABLE
    out[goal] = 0
    queue[0] = goal
    head, tail = 0, 1
    while head < tail:
        c = queue[head]
        head += 1
        d = out[c] + 1
        for h in range(4):
            v = nbr[c, h]
            if v >= 0 and out[v] == UNREACHABLE:
                out[v] = d
                queue[tail] = v
                tail += 1
    return tail


@njit(cache=True)
def dial_fill(nbr, cost, goal, out, stacks, sizes):
    """Weighted distances from every cell to ``goal`` into ``out`` (uint16, cells): the least
    sum of ``cost[c, h]`` (uint8 >= 1, the cost of moving from ``c`` towards heading ``h``)
    along a path, by Dijkstra's algorithm with Dial's bucket queue (Dial, CACM 1969).
    ``stacks`` (k + 1, cells) int32 and ``sizes`` (k + 1,) int64 are scratch, k the largest
    cost. With every cost 1 this is :func:`bfs_fill`'s map."""
    nb = stacks.shape[0]
    out[:] = UNREACHABLE
    sizes[:] = 0
    out[goal] = 0
    stacks[0, 0] = goal
    sizes[0] = 1
    left = 1
    cur = 0
    while left > 0:
        b = cur % nb
        while sizes[b] > 0:
            sizes[b] -= 1
            c = stacks[b, sizes[b]]
            left -= 1
            if out[c] != cur:
                continue
            for h in range(4):
                v = nbr[c, h]
                if v < 0:
                    continue
                nd = cur + cost[v, (h + 2) & 3]     # the move v -> c heads opposite to h
                if nd > UNREACHABLE - 1:             # never wraps: a cost beyond uint16 reads as the largest
                    nd = UNREACHABLE - 1
                if nd < out[v]:
                    out[v] = nd
                    bb = nd % nb
                    stacks[bb, sizes[bb]] = v
                    sizes[bb] += 1
                    left += 1
        cur += 1
    return cur


@njit(cache=True)
def bfs_multi(nbr, sources):
    """Breadth-first steps (int64, cells) from the nearest of ``sources`` to every cell; -1
    for cells none of them reaches."""
    out = np.full(nbr.shape[0], -1, np.int64)
    queue = np.empty(nbr.shape[0], np.int64)
    tail = 0
    for s in sources:
        if out[s] < 0:
            out[s] = 0
            queue[tail] = s
            tail += 1
    head = 0
    while head < tail:
        c = queue[head]
        head += 1
        for h in range(4):
            v = nbr[c, h]
            if v >= 0 and out[v] < 0:
                out[v] = out[c] + 1
                queue[tail] = v
                tail += 1
    return out


@njit(cache=True)
def bfs_pair(nbr, src, dst, seen, queue, dist):
    """Breadth-first distance (steps) from ``src`` to ``dst``, stopping when it is found;
    -1 when unreachable. ``seen`` (uint8), ``queue`` and ``dist`` (int32) are scratch of
    length cells; ``seen`` is left all zero."""
    if src == dst:
        return 0
    seen[src] = 1
    queue[0] = src
    dist[src] = 0
    head, tail = 0, 1
    found = -1
    while head < tail and found < 0:
        c = queue[head]
        head += 1
        for h in range(4):
            v = nbr[c, h]
            if v >= 0 and seen[v] == 0:
                seen[v] = 1
                dist[v] = dist[c] + 1
                queue[tail] = v
                tail += 1
                if v == dst:
                    found = dist[v]
                    break
    for k in range(tail):
        seen[queue[k]] = 0
    return found


@njit(cache=True)
def _candidates(a, u, h, nbr, dist, slot, occ_now, turns_model, turn_w, rnd, cand, ncand, prefer):
    """Sort the next cells of agent ``a`` (stay and its free neighbours) by estimated cost, its
    preferred cell in ``prefer`` first when there is one."""
    s = slot[a]
    pv = preferred(prefer, a, u, nbr.shape[0])
    cost = np.empty(5)
    k = 0
    cand[a, 0] = u
    cost[0] = (float(dist[s, u]) if s >= 0 else 0.0) + rnd[a, 4] * 0.01
    k = 1
    for d in range(4):
        v = nbr[u, d]
        if v < 0:
            continue
        c = float(dist[s, v]) if s >= 0 else 1.0
        if turns_model and h >= 0:
            t = (d - h) & 3
            if t == 3:
                t = 1
            c += turn_w * t
        if occ_now[v] >= 0:
            c += 0.25
        c += rnd[a, d] * 0.01
        if v == pv:
            c = -1.0
        j = k
        while j > 0 and cost[j - 1] > c:
            cost[j] = cost[j - 1]
            cand[a, j] = cand[a, j - 1]
            j -= 1
        cost[j] = c
        cand[a, j] = v
        k += 1
    ncand[a] = k


@njit(cache=True)
def _d(dist, slot, a, v):
    s = slot[a]
    return dist[s, v] if s >= 0 else 0


@njit(cache=True)
def _degree_free(nbr, occ_now, goal, u, v_from):
    """Neighbours of ``u`` other than ``v_from`` and dead ends held by an agent at its goal;
    returns (count, one of them)."""
    n, other = 0, -1
    for h in range(4):
        w = nbr[u, h]
        if w < 0 or w == v_from:
            continue
        deg = 0
        for hh in range(4):
            if nbr[w, hh] >= 0:
                deg += 1
        b = occ_now[w]
        if deg == 1 and b >= 0 and goal[b] == w:
            continue
        n += 1
        other = w
    return n, other


@njit(cache=True)
def _swap_required(nbr, dist, slot, occ_now, goal, pusher, puller, v_pusher, v_puller):
    """Whether ``pusher`` (at v_pusher) and ``puller`` (at v_puller) must exchange sides in a
    corridor (the swap test of LaCAM*, Okumura IJCAI-23)."""
    guard = 0
    while _d(dist, slot, pusher, v_puller) < _d(dist, slot, pusher, v_pusher) and guard < nbr.shape[0]:
        guard += 1
        n, other = _degree_free(nbr, occ_now, goal, v_puller, v_pusher)
        if n >= 2:
            return False
        if n <= 0:
            break
        v_pusher, v_puller = v_puller, other
    return (_d(dist, slot, puller, v_pusher) < _d(dist, slot, puller, v_puller)) and \
        (_d(dist, slot, pusher, v_pusher) == 0 or _d(dist, slot, pusher, v_puller) < _d(dist, slot, pusher, v_pusher))


@njit(cache=True)
def _swap_possible(nbr, occ_now, goal, v_pusher0, v_puller0):
    """Whether pulling along the corridor from v_puller0 reaches a branch to swap in."""
    v_pusher, v_puller = v_pusher0, v_puller0
    guard = 0
    while v_puller != v_pusher0 and guard < nbr.shape[0]:
        guard += 1
        n, other = _degree_free(nbr, occ_now, goal, v_puller, v_pusher)
        if n >= 2:
            return True
        if n <= 0:
            return False
        v_pusher, v_puller = v_puller, other
    return False


@njit(cache=True)
def _swap_agent(a, nbr, pos, dist, slot, occ_now, nxt, goal, cand):
    """The agent ``a`` should pull behind it instead of pushing (LaCAM*'s swap), or -1."""
    best = cand[a, 0]
    u = pos[a]
    if best == u:
        return -1
    j = occ_now[best]
    if j >= 0 and nxt[j] == -1 and _swap_required(nbr, dist, slot, occ_now, goal, a, j, u, best) \
            and _swap_possible(nbr, occ_now, goal, best, u):
        return j
    for h in range(4):
        w = nbr[u, h]
        if w < 0:
            continue
        k = occ_now[w]
        if k < 0 or w == best:
            continue
        if _swap_required(nbr, dist, slot, occ_now, goal, k, a, u, best) and \
                _swap_possible(nbr, occ_now, goal, best, u):
            return k
    return -1


@njit(cache=True)
def pibt_step(nbr, pos, head, dist, slot, goal, order, turns_model, turn_w, rnd, nxt, use_swap, claim, fixed,
              prefer):
    """One step of PIBT, priority inheritance with backtracking (Okumura, Machida, Defago
    & Tamura, "Priority inheritance with backtracking for iterative multi-agent path
    finding", AIJ 2022), iterative with an explicit stack, with the swap technique of
    LaCAM* (Okumura, "Improving LaCAM for scalable eventually optimal multi-agent
    pathfinding", IJCAI-23) so two agents can pass each other in a corridor.

    pos (n,) int64 cells; head (n,) int64 headings (or -1); dist (k, cells) uint16 goal
    distance rows; slot (n,) int64 row of each agent's goal in ``dist`` (-1: no goal);
    goal (n,) goal cells (-1: none); order (n,) agents by decreasing priority; rnd (n, 5)
    float in [0, 1) for tie-breaks; turns_model adds ``turn_w`` per quarter turn to a
    neighbour's cost. claim (n,): a neighbour cell an agent turns towards since an earlier
    step (-1 none); while it does not face it, the agent stays and holds both cells (the
    commitment of the start-kit's 2024 default planner). fixed (n,): next cells imposed on
    agents (-1 free; LaCAM's constraints). prefer: the cells agents try first from the cell
    they stand on (:func:`prefer_table`; lacam3's scatter, :mod:`.scatter`), or
    :data:`NO_PREFER`. Writes each agent's next cell into
    ``nxt`` (n,): distinct cells, no two agents swap. Returns the number of agents that
    could not move where they wanted first.
    """
    n = pos.shape[0]
    ncell = nbr.shape[0]
    occ_now = np.full(ncell, -1, np.int64)
    occ_next = np.full(ncell, -1, np.int64)
    for i in range(n):
        occ_now[pos[i]] = i
        nxt[i] = -1
    for i in range(n):
        if fixed[i] >= 0:
            nxt[i] = fixed[i]
            occ_next[fixed[i]] = i
    if turns_model:
        for i in range(n):
            c = claim[i]
            if nxt[i] != -1:
                continue
            if c < 0:
                continue
            if nbr[pos[i], head[i]] != c:        # still turning: stays, holds both cells
                nxt[i] = pos[i]
                occ_next[pos[i]] = i
                if occ_next[c] == -1:
                    occ_next[c] = i
            elif occ_next[c] == -1:              # faces it: moves there
                nxt[i] = c
                occ_next[c] = i
        for i in range(n):                       # a claim whose cell another holds: wait
            c = claim[i]
            if c >= 0 and nxt[i] == -1:
                nxt[i] = pos[i]
                if occ_next[pos[i]] == -1:
                    occ_next[pos[i]] = i
    cand = np.empty((n, 5), np.int64)
    ncand = np.zeros(n, np.int64)
    ci = np.zeros(n, np.int64)
    swp = np.full(n, -1, np.int64)
    stack = np.empty(n + 1, np.int64)
    failed = 0
    for r in range(n):
        root = order[r]
        if nxt[root] != -1:
            continue
        stack[0] = root
        sp = 1
        fresh = True
        result = -1
        while sp > 0:
            a = stack[sp - 1]
            if fresh:
                fresh = False
                _candidates(a, pos[a], head[a], nbr, dist, slot, occ_now, turns_model, turn_w, rnd, cand, ncand,
                            prefer)
                ci[a] = 0
                swp[a] = -1
                if use_swap:
                    sw = _swap_agent(a, nbr, pos, dist, slot, occ_now, nxt, goal, cand)
                    if sw >= 0:
                        swp[a] = sw
                        k0, k1 = 0, ncand[a] - 1
                        while k0 < k1:
                            tmp = cand[a, k0]
                            cand[a, k0] = cand[a, k1]
                            cand[a, k1] = tmp
                            k0 += 1
                            k1 -= 1
            if result == 0:
                ci[a] += 1
                result = -1
            if result == -1:
                pushed = False
                while ci[a] < ncand[a]:
                    v = cand[a, ci[a]]
                    if occ_next[v] != -1:
                        ci[a] += 1
                        continue
                    k = occ_now[v]
                    if k != -1 and nxt[k] == pos[a]:
                        ci[a] += 1
                        continue
                    nxt[a] = v
                    occ_next[v] = a
                    if k != -1 and k != a and nxt[k] == -1:
                        stack[sp] = k
                        sp += 1
                        fresh = True
                        pushed = True
                    break
                if pushed:
                    continue
                if ci[a] >= ncand[a]:
                    nxt[a] = pos[a]
                    occ_next[pos[a]] = a
                    failed += 1
                    result = 0
                    sp -= 1
                    continue
            # success of a (directly, or its pushed child succeeded)
            if ci[a] > 0:
                failed += 1
            sw = swp[a]
            if ci[a] == 0 and sw >= 0 and nxt[sw] == -1 and occ_next[pos[a]] == -1:
                nxt[sw] = pos[a]
                occ_next[pos[a]] = sw
            result = 1
            sp -= 1
    return failed


@njit(cache=True)
def mapf_t_actions(nbr, pos, head, nxt, dist, slot, act, claim):
    """Turn PIBT's next cells into MAPF_T actions and cancel the moves that would collide.

    An agent whose next cell is ahead moves forward (F); one whose next cell is elsewhere
    turns towards it (R, or C for a counter-clockwise quarter turn); one that stays turns
    towards its best neighbour if it does not face it, else waits. Then the move check of
    the start-kit's default planner (MAPF-Competition/Start-Kit 2024, after Chen et al.,
    "Traffic flow optimisation for lifelong multi-agent path finding", AAAI-24): an F into
    the cell of an agent that stays becomes W, along the chain. An agent holding a
    ``claim`` it does not face turns towards it. Writes ``act`` (n,), updates ``claim``
    (the cell each agent now turns towards, -1 none) and returns the number of moves cancelled.
    """
    n = pos.shape[0]
    ncell = nbr.shape[0]
    mover_into = np.full(ncell, -1, np.int64)
    for a in range(n):
        u = pos[a]
        v = nxt[a]
        h = head[a]
        c = claim[a]
        claim[a] = -1
        if c >= 0 and v == u and nbr[u, h] != c:
            v = c
        if v == u:
            act[a] = ACT_W
            s = slot[a]
            if s >= 0 and dist[s, u] > 0:
                best, bd = -1, dist[s, u]
                for d in range(4):
                    w = nbr[u, d]
                    if w >= 0 and (dist[s, w] < bd or (dist[s, w] == bd and d == h)):
                        best, bd = d, dist[s, w]
                if best >= 0 and best != h:
                    t = (best - h) & 3
                    act[a] = ACT_C if t == 3 else ACT_R
            continue
        d = -1
        for dd in range(4):
            if nbr[u, dd] == v:
                d = dd
        if d == h:
            act[a] = ACT_F
            if mover_into[v] != -1:
                act[a] = ACT_W
            else:
                mover_into[v] = a
        else:
            t = (d - h) & 3
            act[a] = ACT_C if t == 3 else ACT_R
            claim[a] = v
    cancelled = 0
    for b in range(n):
        if act[b] == ACT_F:
            continue
        c = pos[b]
        a = mover_into[c]
        while a != -1 and act[a] == ACT_F:
            act[a] = ACT_W
            claim[a] = nxt[a]
            cancelled += 1
            c = pos[a]
            a = mover_into[c]
    return cancelled


@njit(cache=True)
def turned(h, x):
    """The heading (0 - 3, E S W N) after MAPF_T action ``x`` from heading ``h``: ``ACT_R`` a quarter
    turn clockwise, ``ACT_C`` one counter-clockwise, a move or wait none."""
    if x == ACT_R:
        return (h + 1) & 3
    if x == ACT_C:
        return (h + 3) & 3
    return h


@njit(cache=True)
def heading_cost(nbr, dist, s, c, h):
    """Steps to the goal of distance row ``s`` from cell ``c`` facing ``h``: the breadth-first
    distance plus the quarter turns to face the nearest neighbour that is one step closer
    (a lower bound of the MAPF_T cost; 0 at the goal)."""
    d = dist[s, c]
    if d == 0 or d == UNREACHABLE:
        return float(d)
    best = 3
    for dd in range(4):
        w = nbr[c, dd]
        if w >= 0 and dist[s, w] < d:
            t = (dd - h) & 3
            if t == 3:
                t = 1
            if t < best:
                best = t
    return float(d) + best


@njit(cache=True)
def heading_costs(nbr, dist, slot, pos, head, out):
    """:func:`heading_cost` of every agent with a goal (0 for the others) into ``out`` (n,)."""
    for a in range(pos.shape[0]):
        out[a] = heading_cost(nbr, dist, slot[a], pos[a], head[a]) if slot[a] >= 0 else 0.0


@njit(cache=True)
def lacam_child(config, nxt, cell_of, goals, dist, slot, prio, best, stuck):
    """The configuration PIBT generated from a LaCAM node, checked and scored in one pass.

    config, nxt (n,) int64 cells: the node's configuration and the one generated from it;
    cell_of (cells,) int64 all -1 (scratch, left all -1); goals (n,) cells; dist (k, cells)
    uint16 rows, slot (n,) each agent's row; prio (n,) float64 priorities, best (n,) int64
    least distance to the goal so far, stuck (n,) int64 configurations since it last fell.
    Returns (ok, prio, best, stuck, order) of the new node: ok False when two agents share a
    cell or swap (a constraint PIBT could not honour; the arrays then empty); prio, as in
    LaCAM (Okumura, AAAI-23), + 1 off the goal and its fraction at the goal; order the agents
    by decreasing priority, stable."""
    n = config.shape[0]
    ok = True
    k = 0
    while k < n:                               # vertex conflicts
        if cell_of[nxt[k]] >= 0:
            ok = False
            break
        cell_of[nxt[k]] = k
        k += 1
    for i in range(k):
        cell_of[nxt[i]] = -1
    if ok:                                     # swap conflicts
        for i in range(n):
            cell_of[config[i]] = i
        for i in range(n):
            j = cell_of[nxt[i]]
            if j >= 0 and j != i and nxt[j] == config[i]:
                ok = False
                break
        for i in range(n):
            cell_of[config[i]] = -1
    if not ok:
        e = np.empty(0, np.int64)
        return False, np.empty(0), e, e, e
    p = np.empty(n)
    b = np.empty(n, np.int64)
    st = np.empty(n, np.int64)
    for i in range(n):
        at = nxt[i] == goals[i]
        p[i] = prio[i] - np.floor(prio[i]) if at else prio[i] + 1.0
        d = np.int64(dist[slot[i], nxt[i]])
        b[i] = min(best[i], d)
        st[i] = 0 if (d < best[i] or at) else stuck[i] + 1
    order = np.argsort(-p, kind="mergesort")
    return True, p, b, st, order


def warm_up() -> None:
    """Compile (or load from numba's cache) every kernel on a 3 x 3 grid, so that no timed
    step pays for compilation."""
    from .grid import LifelongGrid
    g = LifelongGrid(np.ones((3, 3), dtype=bool))
    dist = np.empty((1, g.n_cells), dtype=np.uint16)
    q = np.empty(g.n_cells, dtype=np.int32)
    bfs_fill(g.nbr, 8, dist[0], q)
    dial_fill(g.nbr, np.ones((g.n_cells, 4), np.uint8), 8, dist[0], np.empty((2, g.n_cells), np.int32),
              np.zeros(2, np.int64))
    bfs_multi(g.nbr, np.array([4], dtype=np.int64))
    bfs_pair(g.nbr, 0, 8, np.zeros(g.n_cells, np.uint8), q, np.empty(g.n_cells, np.int32))
    pos = np.array([0, 4], dtype=np.int64)
    head = np.zeros(2, dtype=np.int64)
    slot = np.array([0, -1], dtype=np.int64)
    nxt = np.empty(2, dtype=np.int64)
    goal = np.array([8, -1], dtype=np.int64)
    claim = np.full(2, -1, dtype=np.int64)
    pibt_step(g.nbr, pos, head, dist, slot, goal, np.arange(2, dtype=np.int64), True, 1.0, np.zeros((2, 5)), nxt,
              True, claim, np.full(2, -1, dtype=np.int64), NO_PREFER)
    mapf_t_actions(g.nbr, pos, head, nxt, dist, slot, np.empty(2, dtype=np.int64), claim)
    heading_costs(g.nbr, dist, slot, pos, head, np.empty(2))
    lacam_child(pos, pos[::-1].copy(), np.full(g.n_cells, -1, np.int64), goal, dist, np.zeros(2, np.int64),
                np.zeros(2), np.zeros(2, np.int64), np.zeros(2, np.int64))
