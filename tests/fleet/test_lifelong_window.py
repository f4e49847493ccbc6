"""rce_fleet.lifelong.window: the windowed plan of operations (PIBT over action sequences, LNS on
top) is free of conflicts at every step of its window, LNS never makes it worse, and the planner
that uses it keeps every step valid on a packed map."""
from __future__ import annotations

import time

import numpy as np

from rce_fleet.lifelong import DistanceCache, LifelongGrid, PIBTPlanner, check_actions
from rce_fleet.lifelong.kernels import ACT_C, ACT_F, ACT_R, ACT_W
from rce_fleet.lifelong.window import CONTINUE, DEPTH, OPERATIONS, WindowPlan, lns_rounds, warm_up


def _packed(seed: int, rows: int = 10, cols: int = 10, n: int = 70):
    rng = np.random.default_rng(seed)
    free = rng.random((rows, cols)) > 0.1
    g = LifelongGrid(free)
    cells = g.free_cells()
    pos = rng.choice(cells, size=min(n, len(cells) - 2), replace=False).astype(np.int64)
    goals = rng.choice(cells, size=len(pos)).astype(np.int64)
    goals[::5] = -1                                          # some robots without a task
    head = rng.integers(0, 4, size=len(pos)).astype(np.int64)
    return g, pos, head, goals


def _check_window(g, w, pos):
    """Every step of the window: no two robots on a cell, no swap, moves along the map."""
    n = len(pos)
    cells = w.traj[np.arange(n), w.planned]                  # (n, DEPTH + 1)
    assert (cells[:, 0] == pos).all()
    for t in range(1, DEPTH + 1):
        assert len(set(cells[:, t].tolist())) == n
        moved = cells[:, t] != cells[:, t - 1]
        for a in np.flatnonzero(moved):
            assert cells[a, t] in g.nbr[cells[a, t - 1]]
        before = {int(c): a for a, c in enumerate(cells[:, t - 1])}
        for a in np.flatnonzero(moved):
            b = before.get(int(cells[a, t]))
            assert b is None or cells[b, t] != cells[a, t - 1], f"swap of {a} and {b} at {t}"


def test_operations_are_distinct_sequences_and_continue_each_other():
    ops = [tuple(o) for o in OPERATIONS.tolist()]
    assert len(ops) == len(set(ops)) and ops[0] == (ACT_W,) * DEPTH
    assert (ACT_F, ACT_F, ACT_F) in ops and (ACT_R, ACT_R, ACT_F) in ops
    assert (ACT_C, ACT_C, ACT_F) not in ops and (ACT_R, ACT_C, ACT_W) not in ops   # R R and a wait do the same
    for k, o in enumerate(ops):
        assert ops[CONTINUE[k]] == o[1:] + (ACT_W,)


def test_window_is_conflict_free_and_lns_only_improves():
    warm_up()
    for seed in range(4):
        g, pos, head, goals = _packed(seed)
        cache = DistanceCache(g, max_bytes=2 ** 24)
        slot = np.array([cache.slot(int(x)) if x >= 0 else -1 for x in goals], dtype=np.int64)
        order = np.random.default_rng(seed).permutation(len(pos)).astype(np.int64)
        w = WindowPlan(g, len(pos), seed=seed)
        act = w.plan(pos, head, cache.table, slot, goals, order, np.ones(len(pos)), 0.0, lns=False)
        _check_window(g, w, pos)
        _, _, errors = check_actions(g, pos, head, act)
        assert errors == []
        total = w.cost[np.arange(len(pos)), w.planned].sum()
        improved = lns_rounds(300, w.shape, w.traj, w.rank, w.cost, pos, w.planned, w.res, w.saved, 2, 12, 8, 64,
                              seed)
        after = w.cost[np.arange(len(pos)), w.planned].sum()
        _check_window(g, w, pos)
        assert after <= total + 1e-9
        assert (after < total) == (improved > 0)


def test_a_robot_in_a_corridor_end_turns_and_leaves_for_one_behind_it():
    # a one-cell corridor: robot 0 at its west end faces north, robot 1 behind it wants the end cell
    g = LifelongGrid(np.array([[True, True, True, True]]))
    cache = DistanceCache(g, max_bytes=2 ** 20)
    pos = np.array([1, 0], dtype=np.int64)
    head = np.array([3, 0], dtype=np.int64)                  # 0 faces north (a wall), 1 faces east
    goals = np.array([3, 1], dtype=np.int64)
    slot = np.array([cache.slot(3), cache.slot(1)], dtype=np.int64)
    w = WindowPlan(g, 2)
    act = w.plan(pos, head, cache.table, slot, goals, np.array([1, 0], dtype=np.int64), np.zeros(2), 0.0,
                 lns=False)
    assert act[0] == ACT_R                                   # turns east to make way
    assert OPERATIONS[w.planned[0]].tolist() == [ACT_R, ACT_F, ACT_F]
    assert OPERATIONS[w.planned[1]].tolist()[:2] == [ACT_W, ACT_F]   # follows once it faces away


def drive_packed(steps: int = 40, soft: float = 0.05, hard: float = 0.1, **planner_kw) -> PIBTPlanner:
    """A :class:`PIBTPlanner` (``planner_kw``) run ``steps`` steps on a packed 12 x 12 map of
    100 robots, each step's actions checked under the rules; it reaches goals."""
    g, pos, head, goals = _packed(7, 12, 12, 100)
    planner = PIBTPlanner(g, DistanceCache(g, max_bytes=2 ** 24), seed=1, **planner_kw)
    reached = 0
    for _ in range(steps):
        now = time.perf_counter()
        act = planner.plan(pos, head, goals, now + soft, now + hard)
        pos, head, errors = check_actions(g, pos, head, act)
        assert errors == []
        done = (goals >= 0) & (pos == goals)
        reached += int(done.sum())
        goals[done] = -1
    assert reached > 0
    return planner


def test_planner_with_the_window_keeps_every_step_valid_on_a_packed_map():
    planner = drive_packed(ops=True)
    # the window is planned whenever the lookahead has time for its rollouts (nearly every step)
    assert planner._window.stats["window_steps"] >= 30


def test_batch_scheduler_gives_tasks_to_at_most_max_active_robots_the_cheapest_pairs():
    from rce_fleet.lifelong import BatchScheduler, TaskPool
    g = LifelongGrid(np.ones((1, 20), dtype=bool))
    pool = TaskPool()
    for errands in [(1, 2), (10, 11), (18, 19), (5, 6)]:
        pool.add(errands)
    sched = BatchScheduler(DistanceCache(g))
    sched.max_active = 2
    pos = np.array([0, 9, 14, 13])
    prop = sched.schedule(pos, np.full(4, -1), pool.open, 0, time.perf_counter() + 1)
    # the assignment of all four (0 -> task 0: finish 2, 9 -> 3: 5, 14 -> 2: 5, 13 -> 1: 4, the least
    # in sum), then its two cheapest pairs
    assert prop.tolist() == [0, -1, -1, 1]
    sched.max_active = None
    assert (sched.schedule(pos, np.full(4, -1), pool.open, 0, time.perf_counter() + 1) >= 0).sum() == 4


def test_the_greedy_bids_of_a_team_too_large_for_one_assignment_keep_max_active_too():
    """A batch too large for one assignment falls back to greedy bids; the bound holds there as
    well: robots without a task take free places until max_active hold one, then stand aside and
    do not bid: the held tasks stay with their holders."""
    from rce_fleet.lifelong import BatchScheduler, TaskPool
    g = LifelongGrid(np.ones((1, 20), dtype=bool))
    pool = TaskPool()
    for errands in [(1, 2), (10, 11), (18, 19), (5, 6)]:
        pool.add(errands)
    sched = BatchScheduler(DistanceCache(g), max_cells=1)      # every batch is too large: greedy bids
    sched.max_active = 2
    pos = np.array([0, 9, 14, 13])
    prop = sched.schedule(pos, np.full(4, -1), pool.open, 0, time.perf_counter() + 1)
    assert sched.fallbacks == 1 and (prop >= 0).sum() == 2
    held = prop.copy()                                       # the next step: the bound still holds
    for a in np.flatnonzero(held >= 0):                      # as the simulator records the schedule
        pool.assign(int(held[a]), int(a))
    assert (sched.schedule(pos, held, pool.open, 1, time.perf_counter() + 1) == held).all()
    pos[1], pos[3] = 19, 10                  # a holder 9 cells from its task, a robot standing aside on it
    assert (sched.schedule(pos, held, pool.open, 2, time.perf_counter() + 1) == held).all()
    sched.max_active = None
    assert (sched.schedule(pos, np.full(4, -1), pool.open, 0, time.perf_counter() + 1) >= 0).sum() == 4
