"""The bound on robots holding a task, found while the team runs (AIMD), and the schedulers
taking unopened tasks back to keep it."""
from __future__ import annotations

import itertools
import time
from pathlib import Path

import numpy as np
import pytest

from rce_fleet.lifelong import BatchScheduler, DistanceCache, GreedyScheduler, LifelongGrid, TaskPool
from rce_fleet.lifelong.admission import FlowAdmission, JamCut, JamDetector, packed
from rce_fleet.lifelong.runner import jam_detector


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


def test_with_the_jam_gate_the_bound_falls_only_while_robots_pack_in_and_rises_whenever_they_do_not():
    ctl = FlowAdmission(1000, window=2, target=0.8, decrease=0.5, increase=0.1, floor=0.1, start=400,
                        jam_factor=2.0, jam_least=0.05)
    ctl.observe(0, 200, 400, 4)
    assert ctl.observe(1, 200, 400, 4) == 500           # 0.5 moving but 0.01 packed in: no jam, it rises
    ctl.observe(2, 250, 500, 20)
    assert ctl.observe(3, 250, 500, 20) == 600          # 0.04 packed: under the least share, still none
    ctl.observe(4, 300, 600, 60)
    assert ctl.observe(5, 300, 600, 60) == 300          # 0.1 packed, over 2x the first 0.01: a jam, halved
    ctl.observe(6, 280, 300, 60)
    assert ctl.observe(7, 280, 300, 60) == 300          # packed but moving (0.93): held
    ctl.observe(8, 150, 300, 3)
    assert ctl.observe(9, 150, 300, 3) == 400           # the crowd cleared: it rises again
    assert [d[2] for d in ctl.decisions] == [500, 600, 300, 300, 400]


def test_with_the_gate_a_bound_grows_by_its_slow_start_factor_only_while_far_from_a_jam():
    ctl = FlowAdmission(1000, window=2, decrease=0.5, increase=0.01, floor=0.1, start=200, slow_start=1.5,
                        jam_factor=2.0, jam_least=0.1, calm=0.5)
    ctl.observe(0, 100, 200, 2)
    assert ctl.observe(1, 100, 200, 2) == 300           # 0.01 packed, under half the jam's 0.1: x 1.5
    ctl.observe(2, 150, 300, 21)
    assert ctl.observe(3, 150, 300, 21) == 310          # 0.07 packed: no jam, but near one: + 1 % of the team
    ctl.observe(4, 150, 310, 6)
    assert ctl.observe(5, 150, 310, 6) == 465           # calm again: x 1.5
    ctl.observe(6, 150, 465, 60)
    assert ctl.observe(7, 150, 465, 60) == 232          # 0.13 packed: a jam, halved, and slow start is over
    ctl.observe(8, 200, 232, 1)
    assert ctl.observe(9, 200, 232, 1) == 242           # calm, but from now on + 1 % a window


def test_a_slow_jam_is_met_by_its_drop_from_the_best_flow_and_the_bound_stays_under_where_it_jammed():
    ctl = FlowAdmission(1000, window=2, target=0.5, decrease=0.8, increase=0.1, floor=0.1, start=400,
                        jam_factor=2.0, jam_least=0.05, drop=0.05, ceiling=0.7)
    ctl.observe(0, 380, 400, 4)
    assert ctl.observe(1, 380, 400, 4) == 500           # 0.95 moving, 0.01 packed: it rises
    ctl.observe(2, 460, 500, 40)
    assert ctl.observe(3, 460, 500, 40) == 500          # 0.08 packed: a jam, but 0.92 moving is near the best
    ctl.observe(4, 440, 500, 40)
    assert ctl.observe(5, 440, 500, 40) == 350          # 0.88: 0.07 under the best (over target): it falls,
    assert ctl.decisions[-1] == (5, 0.88, 350, 0.08)     # at once to 0.7 x 500, not 0.8 x 500
    ctl.observe(6, 100, 350, 50)
    assert ctl.observe(7, 100, 350, 50) == 280          # the jam goes on: x 0.8, the ceiling is kept
    for k, want in ((8, 350), (10, 350)):
        b = ctl.bound
        ctl.observe(k, b, b, 1)
        assert ctl.observe(k + 1, b, b, 1) == want       # calm: + 100 a window, never over the ceiling
    ctl.observe(12, 150, 350, 40)
    assert ctl.observe(13, 150, 350, 40) == 244         # a jam at the ceiling lowers it: int(0.7 x 350)
    for k in range(14, 30, 2):
        b = ctl.bound
        ctl.observe(k, b, b, 1)
        ctl.observe(k + 1, b, b, 1)
    assert ctl.bound == 244                              # and the new ceiling holds
    free = FlowAdmission(1000, window=2, target=0.5, decrease=0.8, increase=0.1, start=400, jam_factor=2.0,
                         jam_least=0.05)
    for k in range(0, 6, 2):
        free.observe(k, 440 if k else 380, 500 if k else 400, 40 if k else 4)
        free.observe(k + 1, 440 if k else 380, 500 if k else 400, 40 if k else 4)
    assert free.bound == 500                            # without drop: 0.88 moving is over target, held
    with pytest.raises(ValueError, match="ceiling"):
        FlowAdmission(10, ceiling=1.5)


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
    """From ACTIVE_DENSITY robots per free cell a share of the free cells may hold a task: ACTIVE_FRAC
    (EPIBT_ACTIVE_FRAC where EPIBT answers, MAPF_T), or AISLE_ACTIVE_FRAC where one-cell corridor lanes
    (shelves' aisles) hold AISLE_SHARE of them."""
    from rce_fleet.lifelong import runner
    from rce_fleet.lifelong.lorr import LorrProblem
    rng = np.random.default_rng(0)

    def problem(free: np.ndarray) -> LorrProblem:
        g = LifelongGrid(free)
        cells = g.free_cells()
        n = int(0.6 * len(cells))
        starts = rng.choice(cells, n, replace=False).astype(np.int64)
        tasks = [tuple(int(c) for c in rng.choice(cells, 2, replace=False)) for _ in range(2 * n)]
        return LorrProblem(path=Path("t.json"), grid=g, starts=starts, tasks=tasks, team_size=n,
                           num_tasks_reveal=1.5)

    aisles = np.ones((21, 30), dtype=bool)
    aisles[1:20:2, 2:28] = False                  # shelves: rows of blocked cells with one-cell aisles between
    open_ = np.ones((21, 30), dtype=bool)
    assert runner.AISLE_ACTIVE_FRAC < runner.ACTIVE_FRAC < runner.EPIBT_ACTIVE_FRAC < 0.6
    for free, frac, model in ((aisles, runner.AISLE_ACTIVE_FRAC, "MAPF_T"), (open_, runner.EPIBT_ACTIVE_FRAC, "MAPF_T"),
                              (open_, runner.ACTIVE_FRAC, "MAPF")):
        p = problem(free)
        res = runner.run_lifelong(p, 2, plan_time_limit_ms=300.0, record=False, model=model)
        assert res.stats.get("epibt", False) == (model == "MAPF_T")
        n_free = len(p.grid.free_cells())
        assert (res.stats["aisles"] >= runner.AISLE_SHARE) == (frac == runner.AISLE_ACTIVE_FRAC)
        assert res.stats["max_active"] < p.team_size
        assert res.stats["max_active"] == int(frac * n_free)
        assert res.summary()["invalid_steps"] == 0


def test_on_a_map_of_aisles_a_jam_cuts_the_robots_holding_a_task():
    """Shelves to the map's east edge make every aisle a dead end, and every errand lies deep in them:
    robots going in meet robots coming out head-on and pack the aisles. On a map of aisles, where
    no bound holds, the run cuts the robots holding a task to AISLE_JAM_CUT of those holding one
    when the jam is seen; with ``max_active=0`` (no bound) it does not. The jam takes two 25-step
    windows to be seen, so the run goes on long enough after it for robots whose task is not yet
    opened to let it go."""
    from rce_fleet.lifelong import runner
    from rce_fleet.lifelong.lorr import LorrProblem
    rng = np.random.default_rng(0)
    free = np.ones((21, 40), dtype=bool)
    free[1:20:2, 3:40] = False
    g = LifelongGrid(free)
    cells = g.free_cells()
    n = int(0.15 * len(cells))
    deep = cells[cells % 40 >= 34]
    starts = rng.choice(cells[cells % 40 < 20], n, replace=False).astype(np.int64)
    tasks = [tuple(int(c) for c in rng.choice(deep, 2, replace=False)) for _ in range(2 * n)]
    p = LorrProblem(path=Path("t.json"), grid=g, starts=starts, tasks=tasks, team_size=n, num_tasks_reveal=1.5)
    res = runner.run_lifelong(p, 200, plan_time_limit_ms=200.0, record=False)
    s = res.stats
    assert s["aisle_map"] and s["jam_at"] is not None, s["packed_shares"]
    assert s["jam_cut"] is not None and s["jam_cut"] <= int(runner.AISLE_JAM_CUT * n)
    assert s["jam_bounds"] == [(s["jam_at"], s["jam_cut"])]     # the jam at the aisles' dead ends stays
    assert s["max_active"] == s["jam_cut"]
    assert (res.sim.assignment >= 0).sum() <= s["jam_cut"] + n // 10      # opened tasks are never taken back
    assert res.summary()["invalid_steps"] == 0
    off = runner.run_lifelong(p, 125, plan_time_limit_ms=200.0, record=False, max_active=0)
    assert off.stats["jam_at"] is not None and off.stats["jam_cut"] is None and off.stats["max_active"] is None


def test_packed_robots_are_the_ones_whose_every_free_neighbour_cell_is_held():
    free = np.ones((3, 4), dtype=bool)
    free[0, 3] = False                                    # a blocked neighbour counts as held
    g = LifelongGrid(free)
    pos = np.array([1, 4, 5, 6, 9, 2])                    # (0,1) (1,0) (1,1) (1,2) (2,1) (0,2)
    occupied = np.zeros(g.n_cells + 1, dtype=bool)
    occupied[pos] = True
    # (1,1): all four neighbours held; (0,2): (0,1) and (1,2) held, (0,3) blocked; each other has a free one
    assert packed(g.nbr, pos, occupied).tolist() == [False, False, True, False, False, True]
    occupied[10] = True                                   # (2,2) held: (1,2) still has (1,3) free
    assert packed(g.nbr, np.array([6]), occupied).tolist() == [False]
    occupied[7] = True
    assert packed(g.nbr, np.array([6]), occupied).tolist() == [True]


def test_a_jam_is_a_packed_share_that_grows_past_the_first_window_not_one_that_is_high_all_along():
    flat = JamDetector(window=2)
    for k in range(40):                                   # dense but flowing: 12 % packed all along
        assert flat.observe(k, 12, 100) is False
    assert flat.jam_at is None and flat.shares == [0.12] * 20
    growing = JamDetector(window=2, factor=3.0, least=0.1)
    seen = [growing.observe(k, int(share * 1000), 1000)
            for k, share in enumerate([0.02, 0.02, 0.05, 0.05, 0.08, 0.08, 0.12, 0.12, 0.3, 0.3])]
    # 0.05 and 0.08 are over 3x the first window's 0.02 but under the least share 0.1; 0.12 then 0.3:
    # a jam, seen at the second window over both
    assert seen == [False] * 9 + [True]
    assert growing.jam_at == 9 and growing.shares == [0.02, 0.05, 0.08, 0.12, 0.3]
    # a team setting out: one window over the mark, then spreading (WAREHOUSE's 10,000 robots)
    start = JamDetector(window=1)
    assert not any(start.observe(k, int(share * 1000), 1000)
                   for k, share in enumerate([0.053, 0.115, 0.15, 0.163, 0.137, 0.125, 0.109, 0.163, 0.096]))
    assert start.jam_at is None
    with pytest.raises(ValueError, match="window"):
        JamDetector(window=0)
    with pytest.raises(ValueError, match="persist"):
        JamDetector(persist=0)


def test_under_the_strong_aisle_lanes_a_team_setting_out_is_no_jam_and_a_jam_still_is():
    # WAREHOUSE's 10,000 robots under the strong lanes, per 25 steps: 0.055 packed in the first window,
    # up to 0.19 as the team sets out, then flowing
    setting_out = [0.055, 0.116, 0.147, 0.158, 0.17, 0.18, 0.19, 0.186, 0.176, 0.15, 0.13, 0.12, 0.125]
    # under the weak lanes a jam kept growing: 0.15 by step 400, 0.28 by step 2,000, 0.41 by step 4,800
    jam = [0.05, 0.1, 0.15, 0.2, 0.24, 0.28, 0.3, 0.33, 0.41]

    def seen(detector, shares):
        """The window (index in ``shares``) that closed on a jam, or None."""
        for k in range(len(shares) * detector.window):
            detector.observe(k, int(shares[k // detector.window] * 10_000), 10_000)
        return None if detector.jam_at is None else detector.jam_at // detector.window
    assert seen(jam_detector(aisle_lanes=False), setting_out) == 5    # the plain mark, 3 x 0.055, cuts a flowing team
    assert seen(jam_detector(aisle_lanes=True), setting_out) is None
    assert seen(jam_detector(aisle_lanes=True), jam) == 6             # 0.28 and 0.3, both over 0.25


# WAREHOUSE's 10,000 robots under the strong aisle lanes, the packed share per 25 steps of a 1,000-step run
# that jammed (2026-11-29): flowing at 0.13, a jam growing from step 300, cut at step 474 to 7,000, clearing
# by step 825 as the tasks opened before the cut ended
WAREHOUSE_JAM = [0.067, 0.139, 0.181, 0.179, 0.164, 0.144, 0.133, 0.129, 0.131, 0.133, 0.129, 0.136, 0.174, 0.183,
                 0.196, 0.225, 0.249, 0.279, 0.311, 0.31, 0.316, 0.325, 0.308, 0.295, 0.289, 0.279, 0.29, 0.281,
                 0.28, 0.277, 0.265, 0.244, 0.198, 0.193, 0.177, 0.179, 0.175, 0.168, 0.173, 0.206]


def test_a_jam_cut_on_a_map_of_aisles_is_lifted_as_the_jam_clears_and_cut_again_at_the_next():
    team = 10_000
    guard = JamCut(jam_detector(aisle_lanes=True), team, cut=0.7, clear=0.8, increase=0.02)
    holding = team                                        # the robots holding a task fill the bound at once

    clock = itertools.count()

    def window(share: float) -> int | None:
        nonlocal holding
        for _ in range(25):
            bound = guard.observe(next(clock), int(share * holding), holding)
        holding = team if bound is None else bound
        return bound
    bounds = [window(share) for share in WAREHOUSE_JAM]
    assert bounds[:18] == [None] * 18                     # one window over the mark (0.25) is no jam yet
    assert bounds[18:32] == [7000] * 14                   # the second is: cut to 0.7 of the holders, and held
    # while the share is over 0.8 of the mark (0.2), then two windows under it: cleared
    assert bounds[32:34] == [7000, 7000]
    assert bounds[34:39] == [7200, 7400, 7600, 7800, 8000]   # + 2 % of the team a window, under 0.2
    assert bounds[39] == 8000                             # 0.206: near the mark, held
    assert guard.changes[0] == (474, 7000) and guard.changes[1] == (874, 7200)
    bounds = [window(0.15) for _ in range(12)]
    assert bounds == [*range(8200, team, 200), None, None, None]     # to no bound at all
    bounds = [window(share) for share in (0.3, 0.3, 0.3)]
    assert bounds == [None, 7000, 7000]                   # a jam again: cut again, from the holders then
    assert [b for _, b in guard.changes].count(7000) == 2
    # a jam seen while the bound grows back cuts it from the robots holding a task then
    for share in (0.1, 0.1, 0.1):
        window(share)
    assert guard.bound == 7200
    assert [window(0.3), window(0.3)] == [7200, int(0.7 * 7200)]
    with pytest.raises(ValueError, match="clear"):
        JamCut(JamDetector(), team, clear=0.0)


def test_a_bound_grows_back_only_while_the_robots_holding_a_task_fill_it():
    guard = JamCut(JamDetector(window=1, least=0.2), 1000, increase=0.1)
    for k, share in enumerate([0.05, 0.3, 0.3, 0.1, 0.1]):     # the mark: 0.2
        guard.observe(k, int(share * 1000), 1000)
    assert guard.bound == 700 and guard.changes == [(2, 700)]
    assert guard.observe(5, 10, 500) == 700               # 500 of 700 hold a task: the bound does not hold them back
    assert guard.observe(6, 70, 699) == 800               # full (within one): it grows


def _two_rooms(door: bool):
    """Two open rooms of 20 x 40 cells with, when ``door``, a wall between them and one door in it;
    190 robots (0.12 per free cell), every task across from one room to the other."""
    from rce_fleet.lifelong.lorr import LorrProblem
    h, w = 20, 40
    free = np.ones((h, 2 * w + 1), dtype=bool)
    if door:
        free[:, w] = False
        free[h // 2, w] = True
    g = LifelongGrid(free)
    rng = np.random.default_rng(0)
    cells = g.free_cells()
    left, right = cells[cells % (2 * w + 1) < w], cells[cells % (2 * w + 1) > w]
    starts = rng.choice(cells, 190, replace=False).astype(np.int64)
    tasks = [(int(rng.choice(left)), int(rng.choice(right)))[::1 if i % 2 else -1] for i in range(760)]
    return LorrProblem(path=Path("t.json"), grid=g, starts=starts, tasks=tasks, team_size=190, num_tasks_reveal=1.5)


def test_a_run_reports_the_jam_at_a_door_and_none_where_the_same_team_has_room():
    from rce_fleet.lifelong import runner
    jam = runner.run_lifelong(_two_rooms(door=True), 100, plan_time_limit_ms=100.0, record=False, admission=False)
    shares = jam.stats["packed_shares"]
    assert jam.stats["jam_at"] in (74, 99)                # the end of the second 25-step window over the mark
    assert max(shares) > max(0.15, 3 * shares[0])
    open_ = runner.run_lifelong(_two_rooms(door=False), 100, plan_time_limit_ms=100.0, record=False,
                                admission=False)
    assert open_.stats["jam_at"] is None and max(open_.stats["packed_shares"]) < 0.05
    assert open_.sim.finished > 3 * jam.sim.finished
    bounded = runner.run_lifelong(_two_rooms(door=True), 100, plan_time_limit_ms=100.0, record=False)
    assert bounded.stats["admission_on"]                  # by default, at 0.12 robots per free cell
    assert bounded.stats["jam_at"] is None and bounded.stats["packed_shares"] is None   # a bound holds: not watched
    bounds = [d[2] for d in bounded.stats["admission"]]
    assert bounds[-1] < bounds[0], bounds                 # it fell as robots packed in
    assert bounded.summary()["invalid_steps"] == 0


def test_the_run_time_bound_is_on_by_default_at_0_1_to_0_3_robots_per_free_cell_without_aisles_on_small_maps():
    """From 0.1 to 0.3 robots per free cell on a map that is not a map of aisles: on maps under ADMISSION_CELLS
    free cells the bound on holders is on; on larger ones a share of the robots pursues its task in its place
    (test_lifelong_pursuit), and the bound on holders is on only when asked for."""
    from rce_fleet.lifelong import runner
    from rce_fleet.lifelong.lorr import LorrProblem
    rng = np.random.default_rng(1)

    def run(free: np.ndarray, density: float, steps: int = 1, **kw):
        g = LifelongGrid(free)
        cells = g.free_cells()
        n = int(density * len(cells))
        starts = rng.choice(cells, n, replace=False).astype(np.int64)
        tasks = [tuple(int(c) for c in rng.choice(cells, 2, replace=False)) for _ in range(2 * n)]
        p = LorrProblem(path=Path("t.json"), grid=g, starts=starts, tasks=tasks, team_size=n, num_tasks_reveal=1.5)
        res = runner.run_lifelong(p, steps, plan_time_limit_ms=300.0 if steps == 1 else 100.0, record=False, **kw)
        assert res.summary()["invalid_steps"] == 0
        return res

    def on(free: np.ndarray, density: float, **kw) -> bool:
        return run(free, density, **kw).stats["admission_on"]

    rooms = np.ones((64, 72), dtype=bool)         # four rooms, walls with two doors each
    rooms[32, :] = rooms[:, 36] = False
    rooms[32, 10] = rooms[32, 50] = rooms[10, 36] = rooms[50, 36] = True
    assert len(LifelongGrid(rooms).free_cells()) >= runner.ADMISSION_CELLS
    aisles = np.ones((104, 80), dtype=bool)
    aisles[1:103:2, 2:78] = False                  # shelves with one-cell aisles between
    assert len(LifelongGrid(aisles).free_cells()) >= runner.ADMISSION_CELLS
    big = run(rooms, 0.15)
    assert not big.stats["admission_on"]
    assert big.stats["pursue"] == int(runner.PURSUE_FRAC * len(LifelongGrid(rooms).free_cells()))
    assert on(rooms, 0.15, admission=True)
    assert not on(rooms, 0.15, admission=False)
    assert not on(rooms, 0.05)                    # too few robots to jam
    assert not on(rooms, 0.35)                    # the fixed bound of dense teams holds instead
    assert not on(aisles, 0.15)                   # a map of aisles
    small = rooms[:30, :60]                       # a small map: on, from half the team
    assert len(LifelongGrid(small).free_cells()) < runner.ADMISSION_CELLS
    res = run(small, 0.15, steps=25)
    team = res.sim.n
    start = int(runner.ADMISSION_SMALL_START * team)
    (step, _, bound, _), = res.stats["admission"]    # the first window: no jam yet, it rises
    assert step == 24 and start < bound <= int(start * runner.ADMISSION_SMALL["slow_start"])


def test_the_jam_note_advises_the_bound_off_maps_of_aisles_only():
    from rce_fleet.lifelong.admission import jam_note
    stats = {"jam_at": 124, "packed_shares": [0.019, 0.2, 0.432], "aisle_map": False}
    assert "--admission on keeps fewer robots moving" in jam_note(stats)
    note = jam_note({**stats, "aisle_map": True})
    assert note.startswith("the team jammed from step 124") and "0.432" in note
    assert "on this map of aisles the run-time bound (--admission on) finished fewer" in note
    assert "held a task from step" not in note
    note = jam_note({**stats, "aisle_map": True, "jam_bounds": [(124, 7000)]})
    assert "at most 7000 robots held a task from step 124, cut from those holding one;" in note
    assert "grew back" not in note and "finished fewer" in note
    note = jam_note({**stats, "aisle_map": True,
                     "jam_bounds": [(124, 7000), (200, 7200), (225, 7400), (300, 5180), (400, 5380)]})
    assert ("from step 124, cut from those holding one; the bound grew back as the jam cleared, from step 200, "
            "and was cut again once at another jam; at most 5380 robots held a task at the end") in note
    note = jam_note({**stats, "aisle_map": True, "jam_bounds": [(124, 7000), (200, 9000), (225, None)]})
    assert "grew back as the jam cleared, from step 200; no bound held from step 225" in note
    assert "cut again" not in note
    assert jam_note({**stats, "jam_at": None}) is None
