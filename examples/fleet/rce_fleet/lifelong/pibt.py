"""The lifelong planner: one action per robot per step, within a hard time budget.

:class:`PIBTPlanner` runs one step of PIBT (Okumura et al., AIJ 2022) on the robots' next
cells, costed by the breadth-first distance to each robot's next errand
(:class:`~.distances.DistanceCache`) plus, in the MAPF_T model, a cost per quarter turn;
for MAPF_T it turns the next cells into forward/turn/wait actions and cancels moves into
cells that stay occupied (the move check of the League of Robot Runners 2024 default
entry, after Chen et al., AAAI-24). Priorities grow with the steps since a robot's goal
last changed (PIBT's rule), ties broken at random. Two agents pass each other in a corridor
by LaCAM*'s swap technique (Okumura, IJCAI-23); a robot turning towards a cell holds it for
a step (commitment); a robot stuck for ``stuck_steps`` gets noisy costs; when time allows,
rollouts of ``window`` PIBT steps choose among tie-breaks of the first step (windowed
lookahead in the spirit of the LoRR 2023 winner's windowed planning, Jiang et al., SoCS 2024).
With ``ops`` the first step of a windowed plan of operations refined by LNS
(:class:`~.window.WindowPlan`) is one of those candidates (``ops_candidate``, the default), or
the answer itself (``ops_candidate=False``: measured to jam over long runs, docs/lifelong.md).

Time budget: distance maps for new goals are the only unbounded work; when the step's
deadline is near, a robot whose goal map is not yet computed waits (costs it one step,
never a timeout). The PIBT step itself is a single compiled pass of ~1-5 ms at 2,000 robots.

:func:`solve_one_shot` runs the same PIBT to a fixed goal per agent (one-shot MAPF) and
returns the paths.
"""
from __future__ import annotations

import time

import numpy as np

from .distances import DistanceCache
from .flow import TrafficFlow
from .grid import LifelongGrid
from .kernels import MOVE_WAIT, NO_PREFER, heading_costs, mapf_t_actions, pibt_step
from .simulator import MAPF_T

__all__ = ["PIBTPlanner", "solve_one_shot"]


class PIBTPlanner:
    """PIBT with turn costs for a lifelong fleet (module docstring).

    grid: the map; cache: goal distance maps; model: ``"MAPF_T"`` or ``"MAPF"``; turn_w:
    cost of a quarter turn (steps); seed: tie-breaks; swap: LaCAM*'s corridor swap;
    claim_steps: steps a robot keeps holding the cell it turns towards; stuck_steps and
    noise: a robot without progress for that many steps gets tie-breaks scaled by ``noise``
    (a random walk out of a jam); samples, window, sample_frac: the lookahead (rollouts of
    ``window`` steps from ``samples`` tie-breaks, within ``sample_frac`` of the time left;
    samples=1 turns it off); ops, lns, lns_frac, ops_kw, ops_candidate: the windowed plan of
    operations (:class:`~.window.WindowPlan` with ``ops_kw``; LNS on it with ``lns``, until
    ``lns_frac`` of the time to ``deadline``) as a candidate of the lookahead, or answered
    directly; epibt, epibt_kw, epibt_frac: the same with EPIBT (:class:`~.epibt.EPIBTPlan` with
    ``epibt_kw``) in place of the windowed plan (answered directly, it runs until ``epibt_frac``
    of the way from ``deadline`` to ``hard``); window_bias: steps per robot with a goal added to
    the score of the rollout from the windowed plan's (EPIBT's) first step, so that the lookahead
    takes it unless a PIBT rollout brings the robots closer by more; yield_steps: under EPIBT a robot
    without progress for more than this many steps yields its priority (:meth:`_yield_order`; 0:
    never). ``plan(pos, head, goals, deadline)`` returns (n,)
    action codes (:mod:`.kernels`). Measured worth of each: ``docs/lifelong.md``.
    """

    def __init__(self, grid: LifelongGrid, cache: DistanceCache, model: str = MAPF_T, turn_w: float = 0.5,
                 seed: int = 0, swap: bool = True, claim_steps: int = 1,
                 stuck_steps: int = 20, noise: float = 100.0, samples: int = 16, sample_frac: float = 0.5,
                 window: int = 20, flow: TrafficFlow | None = None, flow_frac: float = 0.5,
                 flow_passes: int = 1, ops: bool = False, lns: bool = True, lns_frac: float = 0.5,
                 ops_kw: dict | None = None, ops_candidate: bool = True, epibt: bool = False,
                 epibt_kw: dict | None = None, epibt_frac: float = 0.9, window_bias: float = 0.0,
                 yield_steps: int = 20):
        self.grid, self.cache, self.model, self.turn_w, self.swap = grid, cache, model, float(turn_w), swap
        self.claim_steps = claim_steps
        self.stuck_steps, self.noise = stuck_steps, noise
        self.samples, self.sample_frac, self.window = samples, sample_frac, window
        self.flow, self.flow_frac, self.flow_passes = flow, flow_frac, flow_passes
        self._ptable = cache.table
        self.ops, self.lns, self.lns_frac, self.ops_kw, self.seed = ops, lns, lns_frac, ops_kw or {}, seed
        self.ops_candidate = ops_candidate
        self._window = None
        self.epibt, self.epibt_kw, self.epibt_frac, self._epibt = epibt, epibt_kw or {}, epibt_frac, None
        self.window_bias, self.yield_steps = window_bias, yield_steps
        self.rng = np.random.default_rng(seed)
        self._goal_prev: np.ndarray | None = None
        self.last_slot = np.zeros(0, dtype=np.int64)
        self.elapsed: np.ndarray | None = None
        self.tie: np.ndarray | None = None
        self.stats = {"pibt_ms": 0.0, "maps_ms": 0.0, "maps": 0, "deferred": 0, "cancelled": 0, "samples": 0}

    def plan(self, pos: np.ndarray, head: np.ndarray, goals: np.ndarray, deadline: float,
             hard: float | None = None) -> np.ndarray:
        """Actions for one step. pos, head, goals: (n,) int64 (goal -1: none). ``deadline``
        is a ``time.perf_counter()`` value after which no new distance map or guide path is
        computed; past ``hard`` (default: none) a robot with a new goal gets no row this step
        and waits (:meth:`~.flow.TrafficFlow.update`)."""
        n = pos.shape[0]
        if self._goal_prev is None or self._goal_prev.shape[0] != n:
            self._goal_prev = np.full(n, -2, dtype=np.int64)
            self.elapsed = np.zeros(n)
            self.tie = self.rng.random(n)
            self.claim = np.full(n, -1, dtype=np.int64)
            self.claim_age = np.zeros(n, dtype=np.int64)
            self.best_d = np.zeros(n, dtype=np.int64)
            self.stuck = np.zeros(n, dtype=np.int64)
            self.yield_key = self.rng.random(n)
        changed = goals != self._goal_prev
        self.elapsed[changed] = 0
        self.claim[changed] = -1
        self._goal_prev = goals.copy()
        t0 = time.perf_counter()
        slot = np.full(n, -1, dtype=np.int64)
        cache = self.cache
        cache.pinned = set(goals[goals >= 0].tolist())
        computed0 = cache.computed
        deferred = 0
        for a in np.flatnonzero(goals >= 0):
            g = int(goals[a])
            if g in cache or time.perf_counter() < deadline:
                slot[a] = cache.slot(g)
            else:
                deferred += 1
        pslot = slot
        self.last_slot = slot       # each robot's row of its goal's distance map this step (-1: none)
        self._ptable = cache.table
        if self.flow is not None:
            fhead = head if self.model == MAPF_T else None
            pslot = self.flow.update(pos, goals, slot, deadline, hard, fhead)
            now = time.perf_counter()
            self.flow.refine(pos, slot, now + self.flow_frac * max(0.0, deadline - now), self.flow_passes, fhead)
            self._ptable = self.flow.table
        t1 = time.perf_counter()
        at_goal = (goals >= 0) & (pos == goals)
        self.elapsed += 1
        prio = np.where(goals >= 0, self.elapsed, 0.0) + self.tie
        prio[at_goal] = self.tie[at_goal] * 0.5
        order = np.argsort(-prio, kind="stable").astype(np.int64)
        rnd = self.rng.random((n, 5))
        # progress: steps since the distance to the goal last dropped; a robot stuck longer
        # than ``stuck_steps`` gets noisy costs (a random walk that breaks deadlocks)
        dnow = np.where(slot >= 0, cache.table[np.maximum(slot, 0), pos], 0).astype(np.int64)
        better = changed | (dnow < self.best_d)
        self.best_d = np.where(better, dnow, np.minimum(self.best_d, dnow))
        self.stuck = np.where(better, 0, self.stuck + 1)
        if self.noise > 0:
            rnd[self.stuck > self.stuck_steps] *= self.noise
        self._eorder = self._yield_order(goals, prio, order) if self.epibt else order
        nxt = np.empty(n, dtype=np.int64)
        turns = self.model == MAPF_T
        act = np.empty(n, dtype=np.int64)
        if turns and (self.ops or self.epibt) and self.ops_candidate and self.samples > 1:
            act = self._rollouts(pos, head, goals, slot, pslot, order, rnd, deadline, window=True, hard=hard)
        elif turns and (self.ops or self.epibt):
            act = self._windowed(pos, head, goals, pslot, order, rnd, deadline, hard)
        elif turns and self.samples > 1:
            act = self._rollouts(pos, head, goals, slot, pslot, order, rnd, deadline)
        else:
            self._convert(pos, head, goals, pslot, order, rnd, nxt, act)
        t2 = time.perf_counter()
        self.stats["maps_ms"] += (t1 - t0) * 1e3
        self.stats["pibt_ms"] += (t2 - t1) * 1e3
        self.stats["maps"] += cache.computed - computed0
        self.stats["deferred"] += deferred
        return act

    def _yield_order(self, goals: np.ndarray, prio: np.ndarray, order: np.ndarray) -> np.ndarray:
        """EPIBT's order (n,) int64: PIBT's (``order``, by ``prio``), except that a robot with a
        goal and no progress for more than ``yield_steps`` steps yields: it goes under every robot
        with a goal that progresses (above the robots without one), the robots yielding in an order
        drawn at random, drawn again every ``yield_steps`` steps. EPIBT's chain only displaces robots of
        lower priority than its root, so without it a robot of high priority that cannot pass
        (head-on in a one-cell corridor whose end the other robot cannot leave) holds both
        robots for good: PIBT leaves such a deadlock by noise (``stuck_steps``), EPIBT has none."""
        if self.yield_steps <= 0:
            return order
        over = self.stuck - self.yield_steps
        yielding = (goals >= 0) & (over > 0)
        redraw = yielding & (over % self.yield_steps == 1)
        self.yield_key[redraw] = self.rng.random(int(redraw.sum()))
        prio = np.where(yielding, 1.0 + 0.5 * self.yield_key, np.where(goals >= 0, prio + 2.0, prio))
        return np.argsort(-prio, kind="stable").astype(np.int64)

    def _window_plan(self, pos, head, goals, pslot, order, stop) -> np.ndarray:
        """The first actions of the windowed plan (:class:`~.window.WindowPlan`, or with ``epibt``
        :class:`~.epibt.EPIBTPlan`), LNS until ``stop``."""
        from .epibt import EPIBTPlan
        from .window import WindowPlan
        n = pos.shape[0]
        if self.epibt:
            if self._epibt is None or self._epibt.n != n:
                self._epibt = EPIBTPlan(self.grid, n, seed=self.seed, **self.epibt_kw)
            plan = self._epibt
        else:
            if self._window is None or self._window.n != n:
                self._window = WindowPlan(self.grid, n, seed=self.seed, **self.ops_kw)
            plan = self._window
        if self.epibt:
            return plan.plan(pos, head, self._ptable, pslot, goals, self._eorder, stop, self.lns)
        scale = np.where(self.stuck > self.stuck_steps, self.noise, 1.0) if self.noise > 0 else np.ones(n)
        return plan.plan(pos, head, self._ptable, pslot, goals, order, scale, stop, self.lns)

    def _windowed(self, pos, head, goals, pslot, order, rnd, deadline, hard, act=None) -> np.ndarray:
        """PIBT's one-step answer first (the fallback, always ready; ``act`` when given), then the
        windowed plan of operations refined by LNS (:class:`~.window.WindowPlan`, or EPIBT with
        ``epibt``) until ``lns_frac`` (``epibt_frac``) of the way from ``deadline`` to ``hard``;
        its first actions when it finished in time."""
        n = pos.shape[0]
        if act is None:
            nxt = np.empty(n, dtype=np.int64)
            act = np.empty(n, dtype=np.int64)
            self._convert(pos, head, goals, pslot, order, rnd, nxt, act)
        frac = self.epibt_frac if self.epibt else self.lns_frac
        end = deadline if hard is None else deadline + frac * max(0.0, hard - deadline)
        wact = self._window_plan(pos, head, goals, pslot, order, end)
        if hard is not None and time.perf_counter() > hard:
            self.stats["window_late"] = self.stats.get("window_late", 0) + 1
            return act
        self.claim[:] = -1
        self.claim_age[:] = 0
        return wact

    def _rollouts(self, pos, head, goals, slot, pslot, order, rnd, deadline, window=False,
                  hard=None) -> np.ndarray:
        """Windowed lookahead: the plain PIBT step first (always complete), then, while time
        remains, rollouts of ``window`` PIBT steps from other tie-breaks of the first step;
        keep the first step of the rollout that brings the robots closest (heading-aware, a
        reached goal counts 0). Skipped when two rollouts cannot fit before half the time left
        to ``deadline`` (with ``window``, half the time the windowed plan leaves): then the plain
        step, or with ``window`` the windowed plan alone (:meth:`_windowed`, its LNS on to ``hard``;
        a team of thousands, where one PIBT step takes milliseconds). With ``window``, the first
        step of the windowed plan (refined by LNS for ``lns_frac`` of the time left) is the second
        rollout's, and it answers when the clock cuts its rollout short: a rollout that was never
        scored never outbids it."""
        from .simulator import _apply
        n = pos.shape[0]
        table = self.cache.table
        nbr = self.grid.nbr
        claim0, age0 = self.claim.copy(), self.claim_age.copy()
        nxt = np.empty(n, dtype=np.int64)
        act = np.empty(n, dtype=np.int64)
        t_a = time.perf_counter()
        self._convert(pos, head, goals, pslot, order, rnd, nxt, act)
        plain = (act.copy(), self.claim.copy(), self.claim_age.copy())
        t_step = time.perf_counter() - t_a
        stop = t_a + self.sample_frac * max(0.0, deadline - t_a)
        if window:                           # the windowed plan first takes lns_frac of the time to the deadline
            room = self.sample_frac * (1.0 - self.lns_frac) * max(0.0, deadline - time.perf_counter())
        else:
            room = stop - time.perf_counter()
        if 2 * self.window * t_step * 1.5 > room:   # no time for two rollouts
            if window:
                return self._windowed(pos, head, goals, pslot, order, rnd, deadline, hard, act=plain[0])
            return plain[0]
        wplan = None                         # the windowed plan's first step, as plain: (actions, claim, claim_age)
        if window:
            now = time.perf_counter()
            wfirst = self._window_plan(pos, head, goals, pslot, order, now + self.lns_frac * max(0.0, deadline - now))
            wplan = (wfirst, np.full(n, -1, np.int64), np.zeros(n, np.int64))     # it holds no turn cell
            stop = time.perf_counter() + self.sample_frac * max(0.0, deadline - time.perf_counter())
        d0 = np.empty(n)
        d1 = np.empty(n)
        heading_costs(nbr, table, slot, pos, head, d0)
        has = slot >= 0                      # robots with a goal: the ones a rollout is scored on
        n_goal = int(has.sum())
        best, best_state, best_score = plain[0], plain[1:], -np.inf
        k = chosen = 0
        window_scored = False
        for k in range(self.samples):
            if time.perf_counter() > stop:
                break
            p, h, g, sl, pl = pos, head, goals.copy(), slot.copy(), pslot.copy()
            first = plain
            complete = True
            for step in range(self.window):
                if step == 0 and k == 0:
                    self.claim, self.claim_age = plain[1].copy(), plain[2].copy()
                    act[:] = plain[0]
                else:
                    if step == 0 and k == 1 and wplan is not None:     # the windowed plan's first step
                        self.claim, self.claim_age = wplan[1].copy(), wplan[2].copy()
                        act[:] = wplan[0]
                        first = wplan
                        p, h = _apply(self.grid, p, h, act, MAPF_T)
                        done = (g >= 0) & (p == g)
                        g[done] = -1
                        sl[done] = -1
                        pl[done] = -1
                        continue
                    if step == 0:
                        self.claim, self.claim_age = claim0.copy(), age0.copy()
                    elif time.perf_counter() > stop:
                        complete = False
                        break
                    r = self.rng.random((n, 5))
                    if step == 0 and self.noise > 0:
                        r[self.stuck > self.stuck_steps] *= self.noise
                    self._convert(p, h, g, pl, order, r, nxt, act)
                    if step == 0:
                        first = (act.copy(), self.claim.copy(), self.claim_age.copy())
                p, h = _apply(self.grid, p, h, act, MAPF_T)
                done = (g >= 0) & (p == g)
                g[done] = -1
                sl[done] = -1
                pl[done] = -1
            if not complete:
                break
            heading_costs(nbr, table, sl, p, h, d1)
            score = float((d0 - d1)[has].sum())
            if k == 1 and wplan is not None:
                score += self.window_bias * n_goal
                window_scored = True
            if score > best_score:
                best, best_state, best_score = first[0], first[1:], score
                chosen = k
        self.stats["samples"] += k
        if wplan is not None and not window_scored:     # its rollout never scored: the windowed plan answers
            best, best_state, chosen = wplan[0], wplan[1:], 1
        if wplan is not None and chosen == 1:
            self.stats["window_chosen"] = self.stats.get("window_chosen", 0) + 1
        self.claim, self.claim_age = best_state[0].copy(), best_state[1].copy()
        return best

    def _convert(self, pos, head, goals, slot, order, rnd, nxt, act) -> None:
        """PIBT on cells, then MAPF_T actions with the move check (or 4-neighbour moves)."""
        n = pos.shape[0]
        table = self._ptable
        turns = self.model == MAPF_T
        pibt_step(self.grid.nbr, pos, head if turns else np.full(n, -1, dtype=np.int64), table, slot, goals,
                  order, turns, self.turn_w, rnd, nxt, self.swap, self.claim, np.full(n, -1, dtype=np.int64),
                  NO_PREFER)
        if turns:
            old = self.claim.copy()
            self.stats["cancelled"] += mapf_t_actions(self.grid.nbr, pos, head, nxt, table, slot, act,
                                                      self.claim)
            same = (self.claim == old) & (self.claim >= 0)
            self.claim_age = np.where(same, self.claim_age + 1, 0)
            self.claim[self.claim_age > self.claim_steps] = -1
        else:
            act[:] = MOVE_WAIT
            moved = np.flatnonzero(nxt != pos)
            nb = self.grid.nbr[pos[moved]]
            act[moved] = np.argmax(nb == nxt[moved][:, None], axis=1)


def solve_one_shot(grid: LifelongGrid, starts: np.ndarray, goals: np.ndarray, time_limit_s: float = 5.0,
                   max_steps: int = 10_000, seed: int = 0, cache: DistanceCache | None = None) -> dict:
    """One-shot MAPF by repeated PIBT steps on 4-neighbour moves (Okumura et al., AIJ 2022).

    starts, goals: (n,) cells. Stops when every agent stands on its goal, after
    ``max_steps`` or at ``time_limit_s`` wall seconds. Returns a dict: ``paths`` ((T+1, n)
    int64 cells), ``solved`` (bool), ``sum_of_costs`` (each agent's last arrival at its goal,
    summed), ``makespan``, ``time_s``. Raises ValueError for a goal that cannot be reached.
    """
    t0 = time.perf_counter()
    starts = np.asarray(starts, dtype=np.int64)
    goals = np.asarray(goals, dtype=np.int64)
    n = starts.shape[0]
    if cache is None:                          # an empty cache is falsy (len 0) but is the one to use
        cache = DistanceCache(grid, max_bytes=max(2 * grid.n_cells * (n + 16), 64 * 2 ** 20))
    slot = cache.slots(goals)
    if (cache.table[slot, starts] == 65535).any():
        bad = int(np.flatnonzero(cache.table[slot, starts] == 65535)[0])
        raise ValueError(f"agent {bad}: goal {int(goals[bad])} cannot be reached from {int(starts[bad])}")
    rng = np.random.default_rng(seed)
    tie = rng.random(n)
    elapsed = np.zeros(n)
    pos = starts.copy()
    head = np.full(n, -1, dtype=np.int64)
    traj = [pos.copy()]
    nxt = np.empty(n, dtype=np.int64)
    claim = np.full(n, -1, dtype=np.int64)
    free = np.full(n, -1, dtype=np.int64)
    solved = bool((pos == goals).all())
    while not solved and len(traj) <= max_steps and time.perf_counter() - t0 < time_limit_s:
        at = pos == goals
        elapsed = np.where(at, 0.0, elapsed + 1)
        prio = elapsed + tie
        order = np.argsort(-prio, kind="stable").astype(np.int64)
        pibt_step(grid.nbr, pos, head, cache.table, slot, goals, order, False, 0.0, rng.random((n, 5)), nxt, True,
                  claim, free, NO_PREFER)
        pos = nxt.copy()
        traj.append(pos)
        solved = bool((pos == goals).all())
    paths = np.stack(traj)
    off = paths != goals[None, :]
    # arrival: one past the last step an agent was off its goal
    last_off = np.where(off.any(axis=0), paths.shape[0] - 1 - np.argmax(off[::-1], axis=0), -1)
    arrival = last_off + 1
    return {"paths": paths, "solved": solved, "sum_of_costs": int(arrival.sum()),
            "makespan": int(arrival.max()) if n else 0, "time_s": time.perf_counter() - t0}
