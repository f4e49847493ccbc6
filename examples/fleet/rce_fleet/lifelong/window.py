"""A windowed plan for MAPF_T robots: PIBT over short action sequences, refined by LNS.

PIBT (Okumura et al., AIJ 2022) decides one next cell per robot; under MAPF_T a robot must
first turn to face it, and the conversion to actions (:func:`~.kernels.mapf_t_actions`)
cancels moves along chains of robots that do not move in step. Here a robot's candidates are
*operations*, every sequence of ``DEPTH`` (3) actions (F, R, C, W; R and C never adjacent, and
no C C, which R R equals), each a path in (cell, heading) over the window. Robots choose in
priority order; an operation is taken when no robot already planned holds any of its cells at
the same step (vertex) or crosses it (swap), and a robot not yet planned that stands in its
way plans next with inherited priority, depth-first, undone when it finds no operation
(priority inheritance with backtracking over operations, as in EPIBT: Yukhnevich and
Andreychuk, "Enhancing PIBT via Multi-Action Operations", arXiv 2511.09193, 2025; :mod:`.epibt`).
The plan of the window is then refined by large neighbourhood search while the step's time lasts (the LoRR 2023 winner's
windowed planning, Jiang et al., "Scaling Lifelong Multi-Agent Path Finding to More Realistic
Settings", SoCS 2024): the robots around a random robot are planned again in a random order,
and the new operations are kept when their summed cost is lower. Only the first action of
each operation is executed; the next step plans again, the rest of the last step's operation
favoured. The lifelong planner (:class:`~.pibt.PIBTPlanner`, ``ops``) takes this first step as
one candidate of its lookahead: it is executed when PIBT rolled out from it brings the robots
closest, so a plan that would walk into a deadlock PIBT resolves (a corridor swap) is not chosen.

Cost of an operation: the heading-aware distance (:func:`~.kernels.heading_cost`) at the
window's end, plus 0.05 of those on the way, plus a tie-break; an operation that reaches the
goal at step t costs t - DEPTH - 1 (earlier is better). A robot without a goal prefers to
stay. The plan is free of vertex and swap conflicts at every step of the window by
construction, so its first step is a valid joint action.
"""
from __future__ import annotations

import itertools

import numpy as np
from numba import njit

from ..numba_cache import seed
from .kernels import ACT_C, ACT_F, ACT_R, ACT_W, heading_cost, turned

seed(__file__)          # numba's cache entries prepared in the tree (sandboxed nodes)

__all__ = ["CONTINUE", "DEPTH", "OPERATIONS", "WindowPlan", "continuations", "lns_rounds", "op_costs", "plan_window",
           "warm_up"]

DEPTH = 3


def _operations(depth: int) -> np.ndarray:
    """Action sequences of ``depth`` actions without R/C next to each other and without C C;
    (m, depth) int64, the all-wait sequence first."""
    out = []
    for seq in itertools.product((ACT_W, ACT_F, ACT_R, ACT_C), repeat=depth):
        pairs = zip(seq[:-1], seq[1:], strict=True)
        if any(p in ((ACT_R, ACT_C), (ACT_C, ACT_R), (ACT_C, ACT_C)) for p in pairs):
            continue
        out.append(seq)
    return np.array(out, dtype=np.int64)


OPERATIONS = _operations(DEPTH)


@njit(cache=True)
def _trajectory(nbr, ops, k, u, h, cells, heads):
    """Cells and headings of operation ``k`` from (u, h) into ``cells``/``heads`` (DEPTH + 1,);
    False when it moves off the map or into an obstacle."""
    cells[0] = u
    heads[0] = h
    for t in range(ops.shape[1]):
        x = ops[k, t]
        if x == ACT_F:
            v = nbr[u, h]
            if v < 0:
                return False
            u = v
        h = turned(h, x)
        cells[t + 1] = u
        heads[t + 1] = h
    return True


@njit(cache=True, nogil=True)
def op_path(nbr, ops, a, k, pos, head, cells, heads, traj):
    """Operation ``k`` of robot ``a`` from (pos[a], head[a]): its cells into ``traj[a, k]`` (DEPTH +
    1,) and ``cells``/``heads``; False (and ``traj[a, k, 0]`` -1) when it moves off the map or
    into an obstacle."""
    if not _trajectory(nbr, ops, k, pos[a], head[a], cells, heads):
        traj[a, k, 0] = -1
        return False
    for t in range(ops.shape[1] + 1):
        traj[a, k, t] = cells[t]
    return True


@njit(cache=True)
def op_costs(nbr, ops, pos, head, dist, slot, goal, rnd, prev_op, keep_bonus, seed, traj, cost, rank):
    """Cost of every operation of every robot, and the operations sorted by it.

    pos, head, goal (n,) int64; dist (k, cells) uint16 rows, slot (n,) a robot's row (-1: no
    goal); rnd (n,) tie-break scale (a robot stuck in a jam gets a larger one: a random walk),
    the tie-breaks drawn anew from ``seed`` at each call; prev_op (n,)
    the operation whose rest continues the last step's plan (-1: none), favoured by
    ``keep_bonus``. Writes traj (n, m, DEPTH + 1) cells (-1: not allowed), cost (n, m) and
    rank (n, m): operation indices by increasing cost, the not allowed ones last."""
    np.random.seed(seed)
    n = pos.shape[0]
    m = ops.shape[0]
    depth = ops.shape[1]
    cells = np.empty(depth + 1, np.int64)
    heads = np.empty(depth + 1, np.int64)
    for a in range(n):
        s = slot[a]
        for k in range(m):
            if not op_path(nbr, ops, a, k, pos, head, cells, heads, traj):
                cost[a, k] = 1e18
                continue
            moves = 0
            for t in range(depth):
                if ops[k, t] != ACT_W:
                    moves += 1
            c = 0.0
            if s < 0:
                c = 0.01 * moves
            else:
                reach = -1
                for t in range(1, depth + 1):
                    if cells[t] == goal[a]:
                        reach = t
                        break
                if reach >= 0:
                    c = float(reach - depth - 1) + 0.001 * moves
                else:
                    c = heading_cost(nbr, dist, s, cells[depth], heads[depth])
                    for t in range(1, depth):
                        c += 0.05 * heading_cost(nbr, dist, s, cells[t], heads[t])
            c += rnd[a] * np.random.random() * 0.01
            if k == prev_op[a]:
                c -= keep_bonus
            cost[a, k] = c
        rank[a] = np.argsort(cost[a])


@njit(cache=True)
def _fits(a, k, traj, res, planned):
    """Whether robot ``a``'s operation ``k`` is free of vertex and swap conflicts with the
    robots already planned (``res`` (DEPTH + 1, cells): the robot at each cell and step; row 0
    is where every robot stands now)."""
    depth = traj.shape[2] - 1
    if traj[a, k, 0] < 0:
        return False
    for t in range(1, depth + 1):
        v = traj[a, k, t]
        r = res[t, v]
        if r >= 0 and r != a:
            return False
        u = traj[a, k, t - 1]
        if v != u:
            w = res[t - 1, v]
            if w >= 0 and w != a and (t > 1 or planned[w] >= 0) and res[t, u] == w:
                return False
    return True


@njit(cache=True)
def _place(a, k, traj, res, planned, log, top):
    depth = traj.shape[2] - 1
    for t in range(1, depth + 1):
        res[t, traj[a, k, t]] = a
    planned[a] = k
    log[top] = a
    return top + 1


@njit(cache=True)
def _undo(mark, top, traj, res, planned, log):
    depth = traj.shape[2] - 1
    while top > mark:
        top -= 1
        a = log[top]
        k = planned[a]
        for t in range(1, depth + 1):
            v = traj[a, k, t]
            if res[t, v] == a:
                res[t, v] = -1
        planned[a] = -1
    return top


@njit(cache=True)
def _plan(root, max_depth, traj, rank, res, planned, occ0, log, top, budget, fr_a, fr_j, fr_k, fr_mark, fr_t):
    """Plan robot ``root`` (not planned yet): its operations in order of cost, each taken when it
    fits and every robot standing in its way plans in turn (inheriting the priority, depth-first
    with an explicit stack, at most ``max_depth`` deep, within ``budget[0]`` robots). Returns
    the new log top, or -1 when no operation fits (everything planned in the attempt undone).
    fr_*: (max_depth + 2,) int64 scratch for the stack."""
    depth = traj.shape[2] - 1
    m = rank.shape[1]
    sp = 0
    fr_a[0] = root
    fr_j[0] = 0
    fr_t[0] = 0
    budget[0] -= 1
    result = 0                  # 0: none, 1: the child planned, -1: the child failed
    while sp >= 0:
        a = fr_a[sp]
        if result == -1:        # the child failed: this operation does not work, undo it
            top = _undo(fr_mark[sp], top, traj, res, planned, log)
            fr_t[sp] = 0
            result = 0
        result = 0
        if fr_t[sp] == 0:       # choose the next operation that fits
            k = -1
            while fr_j[sp] < m:
                kk = rank[a, fr_j[sp]]
                fr_j[sp] += 1
                if traj[a, kk, 0] < 0:
                    fr_j[sp] = m
                    break
                if _fits(a, kk, traj, res, planned):
                    k = kk
                    break
            if k < 0:
                sp -= 1
                result = -1
                continue
            fr_k[sp] = k
            fr_mark[sp] = top
            top = _place(a, k, traj, res, planned, log, top)
            fr_t[sp] = 1
        k = fr_k[sp]
        pushed = False
        failed = False
        while fr_t[sp] <= depth:
            b = occ0[traj[a, k, fr_t[sp]]]
            if b < 0 or b == a or planned[b] >= 0:
                fr_t[sp] += 1
                continue
            if sp >= max_depth or budget[0] <= 0:
                failed = True
                break
            budget[0] -= 1
            sp += 1
            fr_a[sp] = b
            fr_j[sp] = 0
            fr_t[sp] = 0
            pushed = True
            break
        if pushed:
            continue
        if failed:
            top = _undo(fr_mark[sp], top, traj, res, planned, log)
            fr_t[sp] = 0
            continue
        sp -= 1                 # planned with every robot in its way
        result = 1
    return top if result == 1 else -1


@njit(cache=True)
def plan_window(traj, rank, pos, order, planned, res, max_depth, budget_per_robot, total_budget):
    """The first plan of the window: robots in ``order`` (decreasing priority) each plan
    (:func:`_plan`) unless planned already by inheritance. ``planned`` (n,) gets each robot's
    operation; ``res`` (DEPTH + 1, cells) the reservations. A robot that cannot move keeps an
    operation that stays on its cell, which always fits for a robot nobody pushed. Returns the
    number of robots placed on a fallback (a stay that fits). ``total_budget`` bounds the robots
    planned through inheritance over the whole call (then robots take operations that push
    nobody), so a packed map costs a bounded time."""
    n = pos.shape[0]
    ncell = res.shape[1]
    res[:] = -1
    occ0 = np.full(ncell, -1, np.int64)
    for a in range(n):
        occ0[pos[a]] = a
        res[0, pos[a]] = a
        planned[a] = -1
    log = np.empty(n, np.int64)
    budget = np.zeros(1, np.int64)
    fr = np.empty((5, max_depth + 2), np.int64)
    fallback = 0
    for r in range(n):
        a = order[r]
        if planned[a] >= 0:
            continue
        budget[0] = min(budget_per_robot, total_budget)
        top = _plan(a, max_depth, traj, rank, res, planned, occ0, log, 0, budget, fr[0], fr[1], fr[2], fr[3], fr[4])
        if top < 0:
            # stay in place: the first operation that fits without pushing anyone
            for j in range(rank.shape[1]):
                k = rank[a, j]
                if traj[a, k, 0] < 0:
                    continue
                still = True
                for t in range(1, traj.shape[2]):
                    if traj[a, k, t] != pos[a]:
                        still = False
                if still and _fits(a, k, traj, res, planned):
                    _place(a, k, traj, res, planned, log, 0)
                    fallback += 1
                    break
        total_budget -= min(budget_per_robot, total_budget) - max(budget[0], 0)
    return fallback


@njit(cache=True)
def lns_rounds(iters, shape, traj, rank, cost, pos, planned, res, saved, radius, max_group, max_depth,
               budget_per_robot, seed):
    """``iters`` rounds of large neighbourhood search on the window's plan (Li et al., IJCAI-21,
    here on operations): the robots within ``radius`` cells (Chebyshev) of a random robot, at
    most ``max_group``, are planned again (:func:`_plan`) in a random order; their new
    operations are kept when they all fit and their summed cost is lower, else the old ones are
    put back. shape: (rows, cols) of the map; saved: (n,) int64 scratch. Returns the number of
    rounds that improved the plan."""
    np.random.seed(seed)
    n = pos.shape[0]
    ncell = res.shape[1]
    depth = traj.shape[2] - 1
    rows, cols = shape[0], shape[1]
    occ0 = np.full(ncell, -1, np.int64)
    for a in range(n):
        occ0[pos[a]] = a
    group = np.empty(max_group, np.int64)
    log = np.empty(n, np.int64)
    budget = np.zeros(1, np.int64)
    fr = np.empty((5, max_depth + 2), np.int64)
    improved = 0
    for _ in range(iters):
        c = np.random.randint(n)
        r0, c0 = pos[c] // cols, pos[c] % cols
        g = 0
        for dr in range(-radius, radius + 1):
            for dc in range(-radius, radius + 1):
                rr, cc = r0 + dr, c0 + dc
                if rr < 0 or cc < 0 or rr >= rows or cc >= cols:
                    continue
                b = occ0[rr * cols + cc]
                if b >= 0 and g < max_group:
                    group[g] = b
                    g += 1
        if g < 2:
            continue
        before = 0.0
        for i in range(g):
            b = group[i]
            k = planned[b]
            saved[b] = k
            before += cost[b, k]
            for t in range(1, depth + 1):
                v = traj[b, k, t]
                if res[t, v] == b:
                    res[t, v] = -1
            planned[b] = -1
        for i in range(g - 1, 0, -1):             # a random order
            j = np.random.randint(i + 1)
            tmp = group[i]
            group[i] = group[j]
            group[j] = tmp
        top = 0
        ok = True
        for i in range(g):
            b = group[i]
            if planned[b] >= 0:
                continue
            budget[0] = budget_per_robot
            nt = _plan(b, max_depth, traj, rank, res, planned, occ0, log, top, budget, fr[0], fr[1], fr[2], fr[3],
                       fr[4])
            if nt < 0:
                ok = False
                break
            top = nt
        if ok:
            after = 0.0
            for i in range(g):
                after += cost[group[i], planned[group[i]]]
            if after < before - 1e-9:
                improved += 1
                continue
        _undo(0, top, traj, res, planned, log)
        for i in range(g):                         # the old operations back
            b = group[i]
            k = saved[b]
            planned[b] = k
            for t in range(1, depth + 1):
                res[t, traj[b, k, t]] = b
    return improved


def continuations(ops: np.ndarray) -> np.ndarray:
    """For each operation of ``ops`` (m, depth), the index of the one that continues it a step
    later (its last actions, then a wait; -1 where the set has none)."""
    index = {tuple(o): i for i, o in enumerate(ops.tolist())}
    return np.array([index.get(tuple(o[1:]) + (ACT_W,), -1) for o in ops.tolist()], dtype=np.int64)


CONTINUE = continuations(OPERATIONS)


class WindowPlan:
    """The windowed plan of a MAPF_T fleet (module docstring), one call per step.

    grid: the map; n: robots; seed: the LNS's random neighbourhoods; keep_bonus: cost taken
    off the operation that continues the last step's plan (steps); max_depth, budget: how deep
    and how many robots a robot may push through inheritance (total_budget: per robot over the
    whole first plan; lns_budget: per robot in an LNS round); radius, max_group: the LNS
    neighbourhood (cells around a random robot, robots at most); chunk_s: seconds of LNS
    rounds per compiled call between clock checks (the count adapts to the measured speed).
    Memory: n x |OPERATIONS| x (DEPTH + 1) int64 cells (1.4 KiB per robot at DEPTH 3). ``stats``
    counts LNS rounds and improvements.
    """

    def __init__(self, grid, n: int, seed: int = 0, keep_bonus: float = 0.2, max_depth: int = 30,
                 budget: int = 400, total_budget: int = 20, lns_budget: int = 50, radius: int = 2,
                 max_group: int = 12, chunk_s: float = 0.002):
        self.grid, self.n = grid, n
        m = OPERATIONS.shape[0]
        self.traj = np.empty((n, m, DEPTH + 1), np.int64)
        self.cost = np.empty((n, m))
        self.rank = np.empty((n, m), np.int64)
        self.planned = np.full(n, -1, np.int64)
        self.saved = np.full(n, -1, np.int64)
        self.res = np.full((DEPTH + 1, grid.n_cells), -1, np.int64)
        self.prev_op = np.full(n, -1, np.int64)
        self.shape = np.array([grid.rows, grid.cols], np.int64)
        self.keep_bonus, self.max_depth, self.budget = keep_bonus, max_depth, budget
        self.total_budget, self.lns_budget = total_budget, lns_budget
        self.radius, self.max_group, self.chunk_s = radius, max_group, chunk_s
        self.rng = np.random.default_rng(seed)
        self.stats = {"window_steps": 0, "lns_rounds": 0, "lns_improved": 0, "window_fallbacks": 0}

    def plan(self, pos: np.ndarray, head: np.ndarray, dist: np.ndarray, slot: np.ndarray, goal: np.ndarray,
             order: np.ndarray, rnd: np.ndarray, stop: float, lns: bool = True) -> np.ndarray:
        """The first actions (n,) int64 of a plan of DEPTH steps. pos, head, goal, slot (n,) int64
        (slot: the robot's row in ``dist``, -1 without a goal); order: robots by decreasing
        priority; rnd (n,) tie-break scale; LNS runs (when ``lns``) until ``time.perf_counter()``
        reaches ``stop``, one chunk of rounds at a time (``chunk_s``)."""
        import time
        op_costs(self.grid.nbr, OPERATIONS, pos, head, dist, slot, goal, rnd, self.prev_op, self.keep_bonus,
                 int(self.rng.integers(2 ** 31)), self.traj, self.cost, self.rank)
        self.stats["window_fallbacks"] += plan_window(self.traj, self.rank, pos, order, self.planned, self.res,
                                                      self.max_depth, self.budget, self.total_budget * len(pos))
        if lns:
            rounds = 4
            while True:
                t = time.perf_counter()
                if t >= stop:
                    break
                self.stats["lns_improved"] += lns_rounds(
                    rounds, self.shape, self.traj, self.rank, self.cost, pos, self.planned, self.res, self.saved,
                    self.radius, self.max_group, self.max_depth, self.lns_budget, int(self.rng.integers(2 ** 31)))
                self.stats["lns_rounds"] += rounds
                dt = time.perf_counter() - t
                # the next chunk: about ``chunk_s`` of work, never past ``stop``
                per = max(dt, 1e-6) / rounds
                rounds = int(max(1, min(4 * rounds, min(self.chunk_s, stop - time.perf_counter()) / per)))
        self.stats["window_steps"] += 1
        self.prev_op = CONTINUE[self.planned]
        return OPERATIONS[self.planned, 0].copy()


def warm_up() -> None:
    """Compile (or load from numba's cache) this module's kernels on a 3 x 3 grid."""
    import time

    from .grid import LifelongGrid
    g = LifelongGrid(np.ones((3, 3), dtype=bool))
    dist = np.zeros((1, g.n_cells), dtype=np.uint16)
    w = WindowPlan(g, 2)
    pos = np.array([0, 4], np.int64)
    w.plan(pos, np.zeros(2, np.int64), dist, np.array([0, -1], np.int64), np.array([8, -1], np.int64),
           np.arange(2, dtype=np.int64), np.zeros(2), time.perf_counter() + 0.001)
    lns_rounds(1, w.shape, w.traj, w.rank, w.cost, pos, w.planned, w.res, w.saved, 1, 4, 2, 8, 0)
