"""The bound on robots holding a task, found while the team runs (AIMD), and the schedulers
taking unopened tasks back to keep it."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from rce_fleet.lifelong import BatchScheduler, DistanceCache, GreedyScheduler, LifelongGrid, TaskPool
from rce_fleet.lifelong.admission import FlowAdmission


def test_the_bound_falls_while_the_team_jams_and_rises_while_it_flows_then_lets_go():
    ctl = FlowAdmission(1000, window=4, target=0.7, band=0.05, decrease=0.5, increase=0.1, floor=0.2)
    assert ctl.bound is None
    for k in range(3):                                    # a window is 4 steps: no word before
        assert ctl.observe(k, 300, 800) is None
    assert ctl.observe(3, 300, 800) == 400                # 0.375 of the holders moved: half of 800
    for k in range(4, 8):
        ctl.observe(k, 100, 400)
    assert ctl.bound == 200                               # still jamming: half again, down to the floor
    for k in range(8, 12):
        ctl.observe(k, 10, 200)
    assert ctl.bound == 200                               # never under floor x team
    for k in range(12, 16):
        ctl.observe(k, 150, 200)                          # 0.75: inside the band, held
    assert ctl.bound == 200
    for k in range(16, 20):
        ctl.observe(k, 190, 200)                          # flowing, and the bound holds robots back
    assert ctl.bound == 300
    for k in range(20, 24):
        ctl.observe(k, 150, 160)                          # flowing, but the bound holds nobody back
    assert ctl.bound == 300
    while ctl.bound is not None and len(ctl.decisions) < 20:
        b = ctl.bound                                     # flowing with the bound full: it rises
        for k in range(4):
            ctl.observe(k, b - 1, b)
    assert ctl.bound is None and len(ctl.decisions) == 13  # up by 100 a window to the team: no bound
    assert [d[2] for d in ctl.decisions[:5]] == [400, 200, 200, 200, 300]
    for bad in ({"target": 0.0}, {"decrease": 1.5}, {"window": 0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            FlowAdmission(10, **bad)


def test_a_bound_that_starts_low_grows_by_its_slow_start_factor_until_the_first_jam():
    ctl = FlowAdmission(1000, window=2, target=0.7, band=0.05, decrease=0.5, increase=0.01, start=100,
                        slow_start=2.0)
    assert ctl.bound == 100
    for want in (200, 400, 800):                          # flowing: doubles each window
        b = ctl.bound
        ctl.observe(0, b, b)
        assert ctl.observe(1, b, b) == want
    ctl.observe(0, 80, 800)
    assert ctl.observe(1, 80, 800) == 400                 # a jam: halved, and slow start is over
    ctl.observe(0, 400, 400)
    assert ctl.observe(1, 400, 400) == 410                  # from now on + 1 % of the team a window
    assert FlowAdmission(1000, start=1000).bound is None  # a start at the team is no bound
    assert FlowAdmission(1000, start=5, floor=0.1).bound == 100       # nor below the floor


@pytest.mark.parametrize("scheduler", [GreedyScheduler, BatchScheduler])
def test_a_lower_bound_takes_unopened_tasks_back_from_the_robots_farthest_from_them(scheduler):
    g = LifelongGrid(np.ones((1, 40), dtype=bool))
    pool = TaskPool()
    tids = [pool.add(errands).id for errands in [(2, 3), (12, 13), (25, 26), (30, 31), (38, 39)]]
    pos = np.array([0, 10, 5, 29, 38])                   # 2, 2, 20, 1 and 0 cells from their first errands
    for a, tid in enumerate(tids):
        pool.assign(tid, a)
    pool.reach(tids[4], 0)                               # robot 4 stands on its first errand: opened
    assignment = np.array(tids)
    sched = scheduler(DistanceCache(g))
    sched.max_active = 3
    prop = sched.schedule(pos, assignment, pool.open, 1, time.perf_counter() + 1)
    assert (prop >= 0).sum() == 3
    assert prop[4] == tids[4]                            # an opened task is never taken back
    assert prop[2] == -1                                 # the farthest from its first errand lost its task
    assert sched.shed >= 1
    sched.max_active = 0                                 # every unopened task goes back; the opened one stays
    prop = sched.schedule(pos, assignment, pool.open, 1, time.perf_counter() + 1)
    assert prop.tolist() == [-1, -1, -1, -1, tids[4]]
    sched.max_active = None                              # no bound: nothing is taken back
    assert (sched.schedule(pos, assignment, pool.open, 1, time.perf_counter() + 1) >= 0).sum() == 5


def test_the_default_bound_is_lower_on_a_map_of_aisles_than_on_an_open_one():
    """From ACTIVE_DENSITY robots per free cell a share of the free cells may hold a task: ACTIVE_FRAC,
    or AISLE_ACTIVE_FRAC where one-cell corridor lanes (shelves' aisles) hold AISLE_SHARE of them."""
    from rce_fleet.lifelong import runner
    from rce_fleet.lifelong.lorr import LorrProblem
    rng = np.random.default_rng(0)

    def problem(free: np.ndarray) -> LorrProblem:
        g = LifelongGrid(free)
        cells = g.free_cells()
        n = int(0.4 * len(cells))
        starts = rng.choice(cells, n, replace=False).astype(np.int64)
        tasks = [tuple(int(c) for c in rng.choice(cells, 2, replace=False)) for _ in range(2 * n)]
        return LorrProblem(path=Path("t.json"), grid=g, starts=starts, tasks=tasks, team_size=n,
                           num_tasks_reveal=1.5)

    aisles = np.ones((21, 30), dtype=bool)
    aisles[1:20:2, 2:28] = False                  # shelves: rows of blocked cells with one-cell aisles between
    open_ = np.ones((21, 30), dtype=bool)
    for free, frac in ((aisles, runner.AISLE_ACTIVE_FRAC), (open_, runner.ACTIVE_FRAC)):
        p = problem(free)
        res = runner.run_lifelong(p, 2, plan_time_limit_ms=300.0, record=False)
        n_free = len(p.grid.free_cells())
        assert (res.stats["aisles"] >= runner.AISLE_SHARE) == (frac == runner.AISLE_ACTIVE_FRAC)
        assert res.stats["max_active"] == int(frac * n_free)
        assert res.summary()["invalid_steps"] == 0
