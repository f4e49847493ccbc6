"""Which robots pursue their task this step: the steps each has left to the end of its task, and
the bound's choice of those nearest it."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rce_fleet.lifelong import DistanceCache, LifelongGrid, TaskPool
from rce_fleet.lifelong.pursuit import pursuing, steps_left


def wall_map() -> LifelongGrid:
    """A 5 x 9 map with a wall down column 4, open only in row 4: the way from one side to the
    other is much longer than the cells' Manhattan distance."""
    free = np.ones((5, 9), dtype=bool)
    free[0:4, 4] = False
    return LifelongGrid(free)


def test_steps_left_run_to_the_next_errand_then_through_the_later_ones_around_walls():
    g = wall_map()
    cell = lambda r, c: r * 9 + c                      # noqa: E731
    pool = TaskPool()
    a = pool.add((cell(0, 0), cell(0, 8), cell(0, 6))).id      # across the wall, then back two cells
    b = pool.add((cell(0, 3), cell(0, 5))).id
    pool.assign(a, 0)
    pool.assign(b, 1)
    pool.reach(a, 0)                                    # robot 0 stood on its first errand: next is (0, 8)
    cache = DistanceCache(g)
    cache.slot(cell(0, 8))                              # its next errand's map is cached: the way round the wall
    assert cache.cached(cell(0, 8)) >= 0 and cache.cached(cell(0, 3)) == -1     # looking computes nothing
    pos = np.array([cell(0, 0), cell(0, 2), cell(2, 2)])
    prop = np.array([a, b, -1])
    left = steps_left(pos, prop, pool.open, cache)
    assert left[0] == (4 + 8 + 4) + 2                   # down, across row 4, up; then two cells back
    assert left[1] == 1 + (4 + 2 + 4)                   # Manhattan to (0, 3) (no map), then round the wall to (0, 5)
    assert left[2] == np.inf                            # no task


def test_the_robots_nearest_the_end_of_their_task_pursue_it_and_the_rest_stand_aside():
    left = np.array([5.0, np.inf, 2.0, 9.0, 2.0, 7.0])
    assert pursuing(left, 2).tolist() == [False, False, True, False, True, False]
    assert pursuing(left, 3).tolist() == [True, False, True, False, True, False]
    assert pursuing(left, 10).tolist() == [True, False, True, True, True, True]     # all holders, never one without
    assert not pursuing(left, 0).any()
    with pytest.raises(ValueError, match="negative"):
        pursuing(left, -1)


def open_problem(side: int, density: float, seed: int = 0):
    """A side x side map, a tenth of its cells blocked at random, with ``density`` robots per free cell and
    two tasks of two errands per robot."""
    from rce_fleet.lifelong.lorr import LorrProblem
    rng = np.random.default_rng(seed)
    free = rng.random((side, side)) >= 0.1
    g = LifelongGrid(free)
    cells = g.free_cells()
    n = int(density * len(cells))
    starts = rng.choice(cells, n, replace=False).astype(np.int64)
    tasks = [tuple(int(c) for c in rng.choice(cells, 2, replace=False)) for _ in range(2 * n)]
    return LorrProblem(path=Path("t.json"), grid=g, starts=starts, tasks=tasks, team_size=n, num_tasks_reveal=1.5)


def test_on_a_large_map_in_the_bounds_class_every_robot_holds_a_task_and_a_share_pursues_it():
    """From ADMISSION_DENSITY to ACTIVE_DENSITY robots per free cell, on a map of ADMISSION_CELLS free cells
    or more, PURSUE_FRAC of the free cells pursue their task in place of the run-time bound on holders; a
    sparser team has neither."""
    from rce_fleet.lifelong import runner
    p = open_problem(70, 0.12)
    n_free = len(p.grid.free_cells())
    assert n_free >= runner.ADMISSION_CELLS
    res = runner.run_lifelong(p, 3, plan_time_limit_ms=300.0, record=False)
    assert res.stats["pursue"] == int(runner.PURSUE_FRAC * n_free) < p.team_size
    assert not res.stats["admission_on"] and res.stats["max_active"] is None
    assert (res.sim.assignment >= 0).sum() > res.stats["pursue"]      # more hold a task than pursue one
    assert res.summary()["invalid_steps"] == 0
    sparse = runner.run_lifelong(open_problem(70, 0.05), 2, plan_time_limit_ms=300.0, record=False)
    assert sparse.stats["pursue"] == 0


def test_a_few_robots_pursuing_their_task_finish_tasks_under_the_rules_and_bad_bounds_are_refused():
    from rce_fleet.lifelong import runner
    p = open_problem(20, 0.1, seed=1)
    res = runner.run_lifelong(p, 60, plan_time_limit_ms=300.0, pursue=5)
    assert res.stats["pursue"] == 5
    assert res.sim.finished > 0
    assert res.summary()["invalid_steps"] == 0
    for bad, match in (({"pursue": -1}, "negative"), ({"pursue": 5, "max_active": 10}, "max_active"),
                       ({"pursue": 5, "admission": True}, "admission")):
        with pytest.raises(ValueError, match=match):
            runner.run_lifelong(p, 1, plan_time_limit_ms=300.0, record=False, **bad)
