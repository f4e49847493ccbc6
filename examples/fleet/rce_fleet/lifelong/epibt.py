"""EPIBT: PIBT over operations, every robot always holding a plan, refined by LNS.

Yukhnevich and Andreychuk, "Enhancing PIBT via Multi-Action Operations" (arXiv 2511.09193,
2025; the operations planner of the League of Robot Runners 2024). Each robot holds an
*operation*, a sequence of ``EPIBT_DEPTH`` (4) actions (:data:`EPIBT_OPERATIONS`), and its path in
(cell, heading) over the window; the plans of all robots are free of vertex and swap conflicts
at every step of the window at all times. A step starts from last step's operations continued
(their rest, then a wait), or where those do not fit together, from waits and the continued
operations that fit.

*Build* of a robot: its plan is taken out, then its operations are tried from the cheapest; an
operation that meets no plan is taken; one that meets exactly one robot's plan takes that
robot's place, and that robot builds in turn (priority inheritance); one that meets two or more
is skipped. A robot already in the chain is never displaced, and a robot is displaced at most
``revisits`` times per pass; a displacement undone (the displaced robot found nothing, both plans
put back) does not count, as the winner's code forgets it, and one build tries at most
``MAX_PUSHES`` displacements (3,000, the winner's bound). When the chain finds nothing every plan
is put back; when it finds a plan, its robots stay as built for the rest of the pass (as in the
authors' code).

- **First pass**: robots in priority order build (a robot displaced earlier in the pass does not
  build again as a root), and only robots of lower priority than the root may be displaced.
  Priority: PIBT's (steps since the robot's goal last changed; robots without a task last), except
  that a robot without progress for 20 steps yields to the robots that progress
  (:class:`~.pibt.PIBTPlanner`'s ``yield_steps``: two robots head-on in a dead-end corridor; the
  runner turns it off in dense teams). The
  paper orders by the steps left of each robot's task; on random-32-32-20 at 400 and 700 robots
  that finished fewer tasks here (docs/lifelong.md).
- **LNS** while the step's time lasts, as the 2024 winner's code runs it (github.com/Straple/LORR24,
  MIT; ``EPIBT_LNS``, ``PEPIBT_LNS``): annealed restarts, each
  from the first pass's plans. A restart draws ``restart`` x n robots (30 x n) at random
  (with replacement); each builds again, any robot may be displaced (a robot in the way is skipped
  with probability ``skip_p``, 0.3), and the new plans are kept when the weighted progress of
  all robots does not fall, or when it fell by the share f with probability exp(-f / T), T from
  ``temp`` (0.001) times ``decay`` (0.999) per build (simulated annealing). The best plans any
  restart reached are answered. One chain of restarts runs per core (two on a 2-core machine;
  threads, the compiled builds release the GIL). Progress of a robot: the cost of waiting minus
  the cost of its operation (:func:`epibt_costs`), weighted by ((n + 1 - rank) / (n + 1))^2 of
  its priority rank (0 without a task). On RANDOM-04 of the 2024 main round (700 robots) the
  restarts finished 5 % more tasks than passes of greedy LNS in the same time
  (docs/lifelong.md); ``anneal=False`` runs those passes instead: robots in a random order build
  again, and the new plans are kept only when the progress does not fall.

The builds run compiled, without the GIL, in calls of ``chunk`` robots (first pass) or
``anneal_chunk`` builds (LNS) between readings of the step's clock; a call starts no more builds
once its builds have tried ``CALL_PUSHES`` displacements (about 10 ms here), so one build of many
displacements cannot carry a call far past the step's deadline.

Only the first action of each operation is executed; it is a valid joint action by
construction. Two habits of the 2024 winner's code (github.com/Straple/LORR24, ``get_smart_dist``
and ``ENABLE_SMART_OPERATION_EXECUTION`` in ``epibt.cpp``) let a robot turn where its plan stands
still:

- **Waits at the end are turns to be**: an operation whose last action is a wait is costed from the
  best heading that wait could turn to (a quarter turn either way; after two waits, the half turn
  too), so an operation that stops short of a corner is not charged for the turn it has time for.
- **A turn in place is chosen when executed**: where the plan waits or turns in place this step
  (all waits; a turn then a wait; two equal turns), the robot executes the one of those in-place
  actions that leaves it facing closest to its goal (:func:`turn_in_place`), the wait on a tie. A
  robot in place holds only its cell, so the joint action stays valid, and its plan continues from
  its new heading through the same cells (:func:`in_place_continuations`).
"""
from __future__ import annotations

import itertools
import time
from functools import partial

import numpy as np
from numba import njit

from ..numba_cache import seed
from .kernels import ACT_C, ACT_F, ACT_R, ACT_W, heading_cost, turned
from .window import continuations, op_path

seed(__file__)          # numba's cache entries prepared in the tree (sandboxed nodes)

__all__ = ["EPIBT_DEPTH", "EPIBT_OPERATIONS", "EPIBTPlan", "epibt_operations", "in_place_continuations",
           "trailing_waits", "turn_in_place", "warm_up"]

WAIT_OP = 0             # the first operation of every set: wait, wait, wait
MAX_PUSHES = 3000       # displacements one build tries at most (the 2024 winner's code: 3,000)
CALL_PUSHES = 20000     # displacements after which a compiled call starts no more builds (about 10 ms)


def _walk(seq, h: int = 0) -> tuple[tuple, int]:
    """The cells (row, col offsets from the start, one per action) an action sequence passes through
    from heading ``h``, and the heading it ends with; any fixed convention of headings serves, since
    only paths are compared."""
    dr = ((0, 1), (1, 0), (0, -1), (-1, 0))
    r = c = 0
    cells = []
    for a in seq:
        if a == ACT_F:
            r, c = r + dr[h][0], c + dr[h][1]
        elif a == ACT_R:
            h = (h + 1) % 4
        elif a == ACT_C:
            h = (h + 3) % 4
        cells.append((r, c))
    return tuple(cells), h


def epibt_operations(depth: int) -> np.ndarray:
    """EPIBT's operations for MAPF_T (the paper's rules): action sequences of ``depth`` in which
    every turn is followed by a forward move later in the sequence (a turn at the end buys
    nothing the cost of the end state does not see), with no turn undone or repeated three times
    before that move, and one sequence per path (the cells at each step and the last heading;
    of sequences with the same path the one that turns first). (m, depth) int64, the all-wait
    sequence first; 17 sequences at depth 3 (where all sequences without a turn undone are 45),
    48 at depth 4, 136 at depth 5."""
    out = [(ACT_W,) * depth]
    seen = {(0, ((0, 0),) * depth)}                     # (last heading, cells) of the sequences kept
    for seq in itertools.product((ACT_F, ACT_R, ACT_C, ACT_W), repeat=depth):
        last_f = max((i for i, a in enumerate(seq) if a == ACT_F), default=-1)
        if any(a in (ACT_R, ACT_C) for a in seq[last_f + 1:]):
            continue
        runs: list[int] = []
        ok = True
        for a in seq:                        # the turns before each forward move
            if a == ACT_F:
                ok = ok and len(set(runs)) <= 1 and len(runs) <= 2
                runs = []
            elif a != ACT_W:
                runs.append(a)
        if not ok:
            continue
        cells, h = _walk(seq)
        key = (h, cells)
        if key not in seen:
            seen.add(key)
            out.append(seq)
    return np.array(out, dtype=np.int64)


# Four actions, as the 2024 winner's entry runs: on the main round's RANDOM-03 and RANDOM-04 (400
# and 700 robots) 6 - 8 % more tasks than three, and five fewer again (docs/lifelong.md).
EPIBT_DEPTH = 4
EPIBT_OPERATIONS = epibt_operations(EPIBT_DEPTH)


def operation_preference(ops: np.ndarray) -> np.ndarray:
    """(m,) float64 in [0, 1): the tie-break between operations whose costs are equal, larger
    preferred: the paper's operation weight (a forward move at step t of D counts 10 (D - t + 1), a
    wait -3 (D - t), a turn -2 (D - t); t from 0), ranked and divided by m, so that it never
    outweighs a step of cost. Moving now is preferred to moving later."""
    d = ops.shape[1]
    t = np.arange(d)
    w = ((ops == ACT_F) * (d - t + 1) * 10 - (ops == ACT_W) * (d - t) * 3
         - ((ops == ACT_R) | (ops == ACT_C)) * (d - t) * 2).sum(axis=1)
    rank = np.empty(len(ops))
    rank[np.argsort(w, kind="stable")] = np.arange(len(ops))
    return rank / len(ops)


def trailing_waits(ops: np.ndarray) -> np.ndarray:
    """(m,) int64: the waits each operation of ``ops`` (m, depth) ends with, at most 2 (the turns
    they could be: :func:`epibt_costs`)."""
    out = np.zeros(len(ops), np.int64)
    for k, op in enumerate(ops.tolist()):
        while out[k] < min(2, len(op)) and op[len(op) - 1 - out[k]] == ACT_W:
            out[k] += 1
    return out


def in_place_continuations(ops: np.ndarray) -> np.ndarray:
    """(m, 4) int64: for operation k of ``ops`` (m, depth) whose first action is replaced by the
    in-place action x (``ACT_R``, ``ACT_C`` or ``ACT_W``; the robot stays in its cell, facing
    otherwise), the operation that carries the robot from its new heading through k's cells at
    the same steps, then waits (-1: none in the set; for k's own first action, k's continuation).
    Cells are compared in the robot's frame, so one table serves every heading."""
    m = len(ops)
    turn = {ACT_R: 1, ACT_C: 3, ACT_W: 0}
    seqs = ops.tolist()
    by_path = {}
    for j in range(m - 1, -1, -1):            # the first operation of a path wins
        for h in range(4):
            by_path[(h, _walk(seqs[j], h)[0])] = j
    table = np.full((m, 4), -1, np.int64)
    for k in range(m):
        path = _walk(seqs[k])[0]
        want = path[1:] + path[-1:]
        for x in (ACT_R, ACT_C, ACT_W):
            table[k, x] = by_path.get((turn[x], want), -1)
    return table


@njit(cache=True, nogil=True)
def turn_in_place(nbr, ops, desire, pos, head, dist, slot, act, next_op, cont):
    """The in-place action each robot executes (module docstring, after the 2024 winner's
    ``ENABLE_SMART_OPERATION_EXECUTION``): where robot a's operation ``desire[a]`` starts with all
    waits, a turn then a wait, or two equal turns, the candidates are (wait, either turn), (wait,
    that turn) and (either turn); the one whose heading is closest to the goal
    (:func:`~.kernels.heading_cost` of distance row ``slot[a]``) is written into ``act`` (n,), the
    earlier candidate on a tie, and its continuation (``cont``, :func:`in_place_continuations`) into
    ``next_op`` (n,). Robots without a goal (slot -1) keep their plans."""
    cand = np.empty(3, np.int64)
    for a in range(pos.shape[0]):
        s = slot[a]
        if s < 0:
            continue
        k = desire[a]
        x0 = ops[k, 0]
        nc = 0
        if x0 == ACT_R or x0 == ACT_C:
            if ops[k, 1] == x0:
                if ops[k, 2] == ACT_W:
                    cand[0], cand[1], cand[2], nc = ACT_W, ACT_R, ACT_C, 3
                else:
                    cand[0], cand[1], nc = ACT_R, ACT_C, 2
            elif ops[k, 1] == ACT_W:
                cand[0], cand[1], nc = ACT_W, x0, 2
        elif k == WAIT_OP:
            cand[0], cand[1], cand[2], nc = ACT_W, ACT_R, ACT_C, 3
        best = x0
        best_c = np.inf
        for i in range(nc):
            c = heading_cost(nbr, dist, s, pos[a], turned(head[a], cand[i]))
            if c < best_c:
                best_c = c
                best = cand[i]
        if best != x0 and cont[k, best] >= 0:
            act[a] = best
            next_op[a] = cont[k, best]


@njit(cache=True, nogil=True)
def epibt_costs(nbr, ops, pref, pos, head, dist, slot, goal, traj, cost, rank, trail):
    """The paper's cost of every operation of every robot (the "smart distance" of the authors'
    code), and the operations sorted by it. An operation that reaches the robot's goal at step t costs t - 1;
    any other costs the heading-aware steps to the goal from where it ends
    (:func:`~.kernels.heading_cost`) plus the depth; ties go to the larger ``pref`` (m,). A robot
    without a goal: every operation costs 0 less its preference (it moves forward where that is
    free, which finished more than waiting: docs/lifelong.md). pos, head, goal, slot (n,)
    int64 (slot: the robot's row of ``dist`` (k, cells) uint16, -1 without a goal). Writes traj (n,
    m, depth + 1) cells (-1: not allowed), cost (n, m) and rank (n, m): operation indices by
    increasing cost, the not allowed ones last. No noise and no bonus for continuing: the plans
    carried from the last step already start every robot where it was going."""
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
            c = 0.0
            if s >= 0:
                e = cells[depth]
                h = heads[depth]
                c = heading_cost(nbr, dist, s, e, h)
                if trail[k] >= 1:
                    c = min(c, heading_cost(nbr, dist, s, e, turned(h, ACT_R)),
                            heading_cost(nbr, dist, s, e, turned(h, ACT_C)))
                if trail[k] >= 2:
                    c = min(c, heading_cost(nbr, dist, s, e, (h + 2) & 3))
                c += depth
                for t in range(1, depth + 1):
                    if cells[t] == goal[a]:
                        c = float(t - 1)
                        break
            cost[a, k] = c - pref[k]
        rank[a] = np.argsort(cost[a], kind="mergesort")


@njit(cache=True)
def _conflict(a, k, traj, res):
    """The robot whose plan operation ``k`` of robot ``a`` meets (vertex or swap, any step of
    the window): -1 none, -2 more than one. ``res`` (depth + 1, cells): the robot at each cell
    at each step (row 0: where the robots stand now)."""
    depth = traj.shape[2] - 1
    who = -1
    for t in range(1, depth + 1):
        v = traj[a, k, t]
        r = res[t, v]
        if r >= 0 and r != a:
            if who == -1:
                who = r
            elif who != r:
                return -2
        u = traj[a, k, t - 1]
        if v != u:
            w = res[t - 1, v]
            if w >= 0 and w != a and res[t, u] == w:
                if who == -1:
                    who = w
                elif who != w:
                    return -2
    return who


@njit(cache=True)
def _add(a, k, traj, res, gain, score):
    for t in range(1, traj.shape[2]):
        res[t, traj[a, k, t]] = a
    score[0] += gain[a, k]


@njit(cache=True)
def _remove(a, k, traj, res, gain, score):
    for t in range(1, traj.shape[2]):
        v = traj[a, k, t]
        if res[t, v] == a:
            res[t, v] = -1
    score[0] -= gain[a, k]


@njit(cache=True)
def _build(root, inherit, keep_worse, temp, skip_p, traj, rank, gain, res, desire, prank, instack, vstamp, vnum,
           now, revisits, max_chain, fr_a, fr_j, fr_old, fr_child, score, spent):
    """Build robot ``root`` (module docstring). inherit: only robots of lower priority (larger
    ``prank``) than the root may be displaced; keep_worse: keep the result even when the
    weighted progress ``score[0]`` fell; temp > 0: keep a result that fell by the share f of the
    old score with probability exp(-f / temp) (annealing); skip_p: the probability that a robot
    in the way is not displaced (the operation is skipped instead). Returns 1 when a new plan
    was taken, 0 when every plan was put back. fr_*: (max_chain + 1,) int64 scratch; spent: (1,)
    int64, the displacements tried, added to."""
    m = rank.shape[1]
    old_score = score[0]
    _remove(root, desire[root], traj, res, gain, score)
    spent0 = spent[0]                    # the displacements this build tries: spent[0] - spent0
    sp = 0
    fr_a[0] = root
    fr_j[0] = 0
    fr_old[0] = desire[root]
    fr_child[0] = -1
    instack[root] = True
    while True:
        a = fr_a[sp]
        c = fr_child[sp]
        if c >= 0:                       # the robot it displaced found nothing: both back
            _remove(a, desire[a], traj, res, gain, score)
            _add(c, desire[c], traj, res, gain, score)
            fr_child[sp] = -1
            vnum[c] -= 1                 # a displacement undone does not count against the robot
            if vnum[c] <= 0:
                vstamp[c] = -1           # nor keep it from building as a root later in the pass
        pushed = False
        while fr_j[sp] < m:
            k = rank[a, fr_j[sp]]
            fr_j[sp] += 1
            if traj[a, k, 0] < 0:        # not allowed (the rest are not either)
                fr_j[sp] = m
                break
            b = _conflict(a, k, traj, res)
            if b == -2:
                continue
            if b == -1:
                desire[a] = k
                _add(a, k, traj, res, gain, score)
                if not keep_worse and score[0] < old_score - 1e-9 and not (
                        temp > 0.0 and old_score > 0.0
                        and np.random.random() < np.exp(-((old_score - score[0]) / old_score) / temp)):
                    for i in range(sp + 1):          # worse: every plan of the chain back
                        _remove(fr_a[i], desire[fr_a[i]], traj, res, gain, score)
                    for i in range(sp + 1):
                        desire[fr_a[i]] = fr_old[i]
                        _add(fr_a[i], fr_old[i], traj, res, gain, score)
                        instack[fr_a[i]] = False
                    return 0
                for i in range(sp + 1):        # the chain's robots stay as built for the rest of the pass
                    instack[fr_a[i]] = False
                    vstamp[fr_a[i]] = now
                    vnum[fr_a[i]] = revisits
                return 1
            if instack[b] or sp + 1 >= max_chain or spent[0] - spent0 >= MAX_PUSHES:
                continue
            if vstamp[b] == now and vnum[b] >= revisits:
                continue
            if inherit and prank[b] <= prank[root]:
                continue
            if skip_p > 0.0 and np.random.random() < skip_p:
                continue
            desire[a] = k
            _remove(b, desire[b], traj, res, gain, score)
            _add(a, k, traj, res, gain, score)
            fr_child[sp] = b
            spent[0] += 1
            if vstamp[b] != now:
                vstamp[b] = now
                vnum[b] = 0
            vnum[b] += 1
            sp += 1
            fr_a[sp] = b
            fr_j[sp] = 0
            fr_old[sp] = desire[b]
            fr_child[sp] = -1
            instack[b] = True
            pushed = True
            break
        if pushed:
            continue
        desire[a] = fr_old[sp]           # nothing for this robot: its old plan (put back by its parent)
        instack[a] = False
        if sp == 0:
            _add(a, desire[a], traj, res, gain, score)
            return 0
        sp -= 1


@njit(cache=True, nogil=True)
def epibt_init(traj, pos, prev, desire, res, gain, score):
    """Every robot takes last step's operation continued (prev (n,); -1: none, then it waits).
    When those plans meet (an action other than planned was executed), every robot waits
    instead and takes its continued operation where it fits, in rounds until none more fits (a
    robot that follows another fits once the one ahead moved on; robots that follow each other
    round a cycle wait)."""
    n = pos.shape[0]
    depth = traj.shape[2] - 1
    res[:] = -1
    score[0] = 0.0
    for a in range(n):
        res[0, pos[a]] = a
        k = prev[a]
        desire[a] = k if k > 0 and traj[a, k, 0] >= 0 else 0
        _add(a, desire[a], traj, res, gain, score)
    whole = True
    for a in range(n):
        k = desire[a]
        for t in range(1, depth + 1):
            if res[t, traj[a, k, t]] != a:          # another robot's plan took the cell
                whole = False
        if whole and _conflict(a, k, traj, res) != -1:
            whole = False
        if not whole:
            break
    if whole:
        return
    res[1:] = -1
    score[0] = 0.0
    for a in range(n):
        desire[a] = 0
        _add(a, 0, traj, res, gain, score)
    changed = True
    while changed:
        changed = False
        for a in range(n):
            k = prev[a]
            if desire[a] != 0 or k <= 0 or traj[a, k, 0] < 0:
                continue
            _remove(a, 0, traj, res, gain, score)
            if _conflict(a, k, traj, res) == -1:
                desire[a] = k
                _add(a, k, traj, res, gain, score)
                changed = True
            else:
                _add(a, 0, traj, res, gain, score)


@njit(cache=True, nogil=True)
def epibt_pass(order, start, stop, inherit, keep_worse, traj, rank, gain, res, desire, prank, instack, vstamp,
               vnum, now, revisits, max_chain, score, budget):
    """Robots ``order[start:stop]`` build unless displaced already in this pass (pass stamp
    ``now``), until the builds have tried ``budget`` displacements (the caller reads its clock and
    goes on from where this call stopped). Returns (plans taken, the index in ``order`` to go on
    from)."""
    fr = np.empty((4, max_chain + 1), np.int64)
    spent = np.zeros(1, np.int64)
    took = 0
    for i in range(start, stop):
        if spent[0] >= budget:
            return took, i
        r = order[i]
        if vstamp[r] == now:
            continue
        vstamp[r] = now
        vnum[r] = 1
        took += _build(r, inherit, keep_worse, 0.0, 0.0, traj, rank, gain, res, desire, prank, instack, vstamp,
                       vnum, now, revisits, max_chain, fr[0], fr[1], fr[2], fr[3], score, spent)
    return took, stop


@njit(cache=True, nogil=True)
def epibt_anneal(seed_, builds, temp, decay, skip_p, traj, rank, gain, res, desire, prank, instack, vstamp, vnum,
                 now, revisits, max_chain, score, budget):
    """``builds`` robots drawn at random (with replacement; numba's generator of this thread
    seeded with ``seed_``) build one after another, any robot may be displaced (each with
    probability 1 - ``skip_p``), and a result that lowers the weighted progress is kept by
    annealing at temperature ``temp``, multiplied by ``decay`` after every build; no build starts
    once the builds have tried ``budget`` displacements (the caller reads its clock). Pass
    stamps from ``now`` on, one per build. Returns (plans taken, the temperature reached, builds
    run)."""
    np.random.seed(seed_)
    fr = np.empty((4, max_chain + 1), np.int64)
    spent = np.zeros(1, np.int64)
    n = desire.shape[0]
    took = 0
    for i in range(builds):
        if spent[0] >= budget:
            return took, temp, i
        r = np.random.randint(0, n)
        vstamp[r] = now + i
        vnum[r] = 1
        took += _build(r, False, False, temp, skip_p, traj, rank, gain, res, desire, prank, instack, vstamp, vnum,
                       now + i, revisits, max_chain, fr[0], fr[1], fr[2], fr[3], score, spent)
        temp *= decay
    return took, temp, builds


class _Chain:
    """One copy of the plans that LNS passes refine (its own plans, reservations, score and
    pass stamps; the operations' paths and gains are shared, read only)."""

    def __init__(self, n: int, res_shape: tuple[int, int]):
        self.desire = np.zeros(n, np.int64)
        self.res = np.full(res_shape, -1, np.int64)
        self.instack = np.zeros(n, np.bool_)
        self.vstamp = np.zeros(n, np.int64)
        self.vnum = np.zeros(n, np.int64)
        self.score = np.zeros(1)
        self.now = 0
        self.passes = 0
        self.taken = 0

    def take(self, other: _Chain) -> None:
        """Start from ``other``'s plans."""
        self.desire[:] = other.desire
        self.res[:] = other.res
        self.score[:] = other.score
        self.instack[:] = False

    def run(self, plan: EPIBTPlan, order: np.ndarray, inherit: bool, keep_worse: bool, prank: np.ndarray,
            stop: float) -> bool:
        """One pass over ``order`` in chunks of robots and of displacements (the kernel runs
        without the GIL); False when ``stop`` came first."""
        self.now += 1
        s = 0
        while s < len(order):
            if time.perf_counter() >= stop:
                return False
            took, s = epibt_pass(order, s, min(len(order), s + plan.chunk), inherit, keep_worse, plan.traj,
                                 plan.rank, plan.gain, self.res, self.desire, prank, self.instack, self.vstamp,
                                 self.vnum, self.now, plan.revisits, plan.max_chain, self.score,
                                 plan.call_pushes)
            self.taken += took
        self.passes += 1
        return True

    def lns(self, plan: EPIBTPlan, prank: np.ndarray, stop: float, seed_: int) -> None:
        """LNS passes in random orders until ``stop``."""
        rng = np.random.default_rng(seed_)
        n = len(self.desire)
        while time.perf_counter() < stop:
            if not self.run(plan, rng.permutation(n).astype(np.int64), False, False, prank, stop):
                break

    def anneal(self, plan: EPIBTPlan, prank: np.ndarray, stop: float, seed_: int, base: _Chain,
               best: _Chain) -> None:
        """Annealed LNS restarts from ``base`` until ``stop``, each of ``restart`` x n builds
        (:func:`epibt_anneal`); ends holding the best plans seen (``base``'s included), ``best``
        its scratch."""
        rng = np.random.default_rng(seed_)
        n = len(self.desire)
        best.take(base)
        while time.perf_counter() < stop:
            self.take(base)
            temp, left = plan.temp, plan.restart * n
            while left > 0 and time.perf_counter() < stop:
                k = min(left, plan.anneal_chunk)
                took, temp, k = epibt_anneal(int(rng.integers(2 ** 31)), k, temp, plan.decay, plan.skip_p,
                                             plan.traj, plan.rank, plan.gain, self.res, self.desire, prank,
                                             self.instack, self.vstamp, self.vnum, self.now + 1, plan.revisits,
                                             plan.max_chain, self.score, plan.call_pushes)
                self.now += k
                self.taken += took
                left -= k
            self.passes += 1
            if self.score[0] > best.score[0]:
                best.take(self)
        self.take(best)


class EPIBTPlan:
    """EPIBT with LNS for a MAPF_T fleet (module docstring), one call per step.

    grid: the map; n: robots; seed: the LNS's orders; revisits: times a robot may be
    displaced per pass; max_chain: robots in one chain of displacements at most; chunk:
    robots built per compiled call between clock checks (fewer where their builds tried
    ``call_pushes`` displacements, :data:`CALL_PUSHES`; ``anneal_chunk`` likewise); threads: LNS
    chains run at once, each from the first pass's plans with its own random orders, the best kept
    (default: the CPUs this process may use, at most 2; the kernels release the GIL); operations:
    (m, depth) the action sequences tried, the all-wait one first (default :data:`EPIBT_OPERATIONS`); anneal:
    LNS by annealed restarts (module docstring: ``temp``, ``decay`` per build, ``skip_p``,
    ``restart`` x n builds per restart, ``anneal_chunk`` builds per compiled call between clock
    checks), else by greedy passes; in_place: waits at the end of an operation costed as the turns
    they could be, and the in-place action facing the goal best executed (module docstring). Memory:
    n x m x (depth + 1) int64 cells plus three arrays of n x m (about 3 KiB per robot at depth 4),
    and per chain a reservation table of (depth + 1) x cells int64 (with ``anneal`` a second per
    chain, its best plans, and one of the first pass's plans). ``stats`` counts steps, passes
    (restarts with ``anneal``) and plans taken, and the steps whose first pass the deadline cut
    short.
    """

    def __init__(self, grid, n: int, seed: int = 0, revisits: int = 10,
                 max_chain: int = 256, chunk: int = 16, threads: int | None = None,
                 operations: np.ndarray | None = None, anneal: bool = True, temp: float = 0.001,
                 decay: float = 0.999, skip_p: float = 0.3, restart: int = 30, anneal_chunk: int = 128,
                 in_place: bool = True, call_pushes: int = CALL_PUSHES):
        import os
        self.grid, self.n = grid, n
        self.ops = EPIBT_OPERATIONS if operations is None else np.asarray(operations, np.int64)
        self.cont = continuations(self.ops)
        self.pref = operation_preference(self.ops)
        self.in_place = in_place
        self.trail = trailing_waits(self.ops) if in_place else np.zeros(len(self.ops), np.int64)
        self.in_place_cont = in_place_continuations(self.ops) if in_place else None
        m, depth = self.ops.shape
        self.traj = np.empty((n, m, depth + 1), np.int64)
        self.cost = np.empty((n, m))
        self.gain = np.empty((n, m))
        self.rank = np.empty((n, m), np.int64)
        self.prev_op = np.full(n, -1, np.int64)
        if threads is None:
            threads = min(2, len(os.sched_getaffinity(0)))
        self.chains = [_Chain(n, (depth + 1, grid.n_cells)) for _ in range(max(1, threads))]
        self.anneal, self.temp, self.decay, self.skip_p = anneal, temp, decay, skip_p
        self.restart, self.anneal_chunk = restart, anneal_chunk
        self._base = _Chain(n, (depth + 1, grid.n_cells)) if anneal else None
        self._best = [_Chain(n, (depth + 1, grid.n_cells)) for _ in self.chains] if anneal else []
        self._pool = None
        if len(self.chains) > 1:
            from concurrent.futures import ThreadPoolExecutor
            self._pool = ThreadPoolExecutor(len(self.chains) - 1, thread_name_prefix="epibt-lns")
        self.revisits, self.max_chain, self.chunk = revisits, max_chain, chunk
        self.call_pushes = call_pushes
        self.rng = np.random.default_rng(seed)
        self.stats = {"epibt_steps": 0, "epibt_passes": 0, "epibt_taken": 0, "epibt_unfinished": 0,
                      "epibt_lns_skipped": 0, "epibt_threads": len(self.chains)}

    @property
    def desire(self) -> np.ndarray:
        """(n,) each robot's operation in the plans answered last."""
        return self.chains[0].desire

    @property
    def res(self) -> np.ndarray:
        """(depth + 1, cells) the robot at each cell at each step of those plans (-1: none)."""
        return self.chains[0].res

    @property
    def score(self) -> np.ndarray:
        """(1,) their weighted progress."""
        return self.chains[0].score

    def plan(self, pos: np.ndarray, head: np.ndarray, dist: np.ndarray, slot: np.ndarray, goal: np.ndarray,
             order: np.ndarray, stop: float, lns: bool = True) -> np.ndarray:
        """The first actions (n,) int64 of the plans. pos, head, goal, slot (n,) int64 (slot:
        the robot's row in ``dist``, -1 without a goal); order (n,) int64: robots by decreasing
        priority (operations costed by :func:`epibt_costs`). The first pass, then LNS passes (with ``lns``), run
        until ``time.perf_counter()`` reaches ``stop``, or no LNS when the first pass put every robot on its
        best operation (``stats["epibt_lns_skipped"]``); what is built by then is answered (always a valid
        joint action)."""
        n = len(pos)
        epibt_costs(self.grid.nbr, self.ops, self.pref, pos, head, dist, slot, goal, self.traj, self.cost,
                    self.rank, self.trail)
        prank = np.empty(n, np.int64)
        prank[order] = np.arange(n)
        power = np.where(slot >= 0, ((n + 1 - prank) / (n + 1)) ** 2, 0.0)
        allowed = self.traj[:, :, 0] >= 0
        self.gain[:] = np.where(allowed, power[:, None] * (self.cost[:, :1] - np.where(allowed, self.cost, 0.0)),
                                0.0)
        main = self.chains[0]
        passes0, taken0 = sum(c.passes for c in self.chains), sum(c.taken for c in self.chains)
        epibt_init(self.traj, pos, self.prev_op, main.desire, main.res, self.gain, main.score)
        done = main.run(self, order, True, True, prank, stop)
        if not done:
            self.stats["epibt_unfinished"] += 1
        # every robot on its best operation: no plan scores more (the score is the sum of the robots' gains),
        # so LNS could only tie; a team spread out (a few robots, far apart) skips it
        if lns and done and main.score[0] >= self.gain.max(axis=1).sum() - 1e-9:
            self.stats["epibt_lns_skipped"] += 1
        elif lns and done and time.perf_counter() < stop:
            seeds = [int(sd) for sd in self.rng.integers(2 ** 31, size=len(self.chains))]
            if self.anneal:                  # every chain restarts from the first pass's plans
                self._base.take(main)
                jobs = [partial(c.anneal, self, prank, stop, sd, self._base, b)
                        for c, sd, b in zip(self.chains, seeds, self._best, strict=True)]
            else:                            # every chain passes on from the first pass's plans
                for c in self.chains[1:]:
                    c.take(main)
                jobs = [partial(c.lns, self, prank, stop, sd) for c, sd in zip(self.chains, seeds, strict=True)]
            futures = [self._pool.submit(job) for job in jobs[1:]]
            jobs[0]()                        # the main chain on this thread
            for f in futures:
                f.result()
            best = max(self.chains, key=lambda c: c.score[0])
            if best is not main:
                main.take(best)
        self.stats["epibt_steps"] += 1
        self.stats["epibt_passes"] += sum(c.passes for c in self.chains) - passes0
        self.stats["epibt_taken"] += sum(c.taken for c in self.chains) - taken0
        self.prev_op = self.cont[main.desire]
        act = self.ops[main.desire, 0].copy()
        if self.in_place:
            turn_in_place(self.grid.nbr, self.ops, main.desire, pos, head, dist, slot, act, self.prev_op,
                          self.in_place_cont)
        return act


def warm_up() -> None:
    """Compile (or load from numba's cache) this module's kernels on a 3 x 3 grid."""
    from .grid import LifelongGrid
    g = LifelongGrid(np.ones((3, 3), dtype=bool))
    dist = np.zeros((1, g.n_cells), dtype=np.uint16)
    e = EPIBTPlan(g, 2)
    # no clock in the way: the first pass must run (a stop already past would skip it, and its kernel
    # would then compile inside a run's first step, seconds over the step's limit)
    e.plan(np.array([0, 4], np.int64), np.zeros(2, np.int64), dist, np.array([0, -1], np.int64),
           np.array([8, -1], np.int64), np.arange(2, dtype=np.int64), time.perf_counter() + 3600.0,
           lns=False)
    c = e.chains[0]
    epibt_anneal(0, 1, 0.001, 0.999, 0.3, e.traj, e.rank, e.gain, c.res, c.desire, np.arange(2, dtype=np.int64),
                 c.instack, c.vstamp, c.vnum, c.now + 1, e.revisits, e.max_chain, c.score, e.call_pushes)
