"""rce_fleet.lifelong: problem files, tasks, distance maps, schedulers and the PIBT planner
(conflict-free steps for both action models, corridor swaps, one-shot PIBT)."""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import pytest

from rce_fleet.lifelong import (MAPF, MAPF_T, BatchScheduler, DistanceCache, GreedyScheduler, LifelongGrid,
                                PIBTPlanner, ProblemError, Simulator, TaskError, TaskPool, TaskState, check_actions,
                                load_lorr_map, load_problem, solve_one_shot)
from rce_fleet.lifelong.kernels import UNREACHABLE, heading_cost, warm_up
from rce_fleet.lifelong.scheduler import make_scheduler

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
RANDOM = DATA / "lorr" / "random.domain" / "random_32_32_20_100.json"


def grid(rows: list[str]) -> LifelongGrid:
    return LifelongGrid(np.array([[ch == "." for ch in r] for r in rows]))


# -- problem files ---------------------------------------------------------------------------
def test_load_the_lorr_random_problem():
    p = load_problem(RANDOM)
    assert (p.grid.rows, p.grid.cols, p.team_size, p.reveal) == (32, 32, 100, 150)
    assert len(p.tasks) == 100000 and p.tasks[0] == (627, 871)
    assert all(p.grid.is_free(int(c)) for c in p.starts)


def write_problem(tmp_path: Path, agents: str, tasks: str = "1\n3,4\n", mapf: str = "m.map") -> Path:
    (tmp_path / "m.map").write_text("type octile\nheight 2\nwidth 3\nmap\n..@\n.E.\n")
    (tmp_path / "a.agents").write_text(agents)
    (tmp_path / "t.tasks").write_text(tasks)
    prob = tmp_path / "p.json"
    prob.write_text(f'{{"mapFile": "{mapf}", "agentFile": "a.agents", "taskFile": "t.tasks", "teamSize": 2,'
                    f' "numTasksReveal": 1.5}}')
    return prob


def test_problem_errors_name_the_file_and_line(tmp_path):
    good = load_problem(write_problem(tmp_path, "# c\n2\n0\n4\n"))
    assert good.grid.free.tolist() == [[True, True, False], [True, True, True]] and good.reveal == 3
    with pytest.raises(ProblemError, match=r"a\.agents:4: location 2 .* not a free cell"):
        load_problem(write_problem(tmp_path, "# c\n2\n0\n2\n"))
    with pytest.raises(ProblemError, match=r"a\.agents:1: count 3 but 2 entries"):
        load_problem(write_problem(tmp_path, "3\n0\n4\n"))
    with pytest.raises(ProblemError, match=r"t\.tasks:2: expected a location"):
        load_problem(write_problem(tmp_path, "2\n0\n4\n", "1\n3,x\n"))
    with pytest.raises(ProblemError, match=r"nope\.map: no such file"):
        load_problem(write_problem(tmp_path, "2\n0\n4\n", mapf="nope.map"))
    bad = tmp_path / "bad.json"
    bad.write_text('{"mapFile": "m.map",\n "teamSize": }')
    with pytest.raises(ProblemError, match=r"bad\.json:2: not JSON"):
        load_problem(bad)
    with pytest.raises(ProblemError, match=r"missing\.json: no such file"):
        load_problem(tmp_path / "missing.json")


# -- tasks -------------------------------------------------------------------------------------
def test_map_cells_are_read_as_the_start_kit_reads_them(tmp_path):
    """``@`` and ``T`` block; ``.``, ``E``, ``S``, ``W`` and any other character are free; the header is
    MovingAI's or a first line ``rows,cols``."""
    octile = tmp_path / "o.map"
    octile.write_text("type octile\nheight 2\nwidth 4\nmap\n.ESW\n@TG.\n")
    short = tmp_path / "s.map"
    short.write_text("2,4\n.ESW\n@TG.\n")
    for path in (octile, short):
        assert load_lorr_map(path).free.tolist() == [[True] * 4, [False, False, True, True]]
    bad = tmp_path / "b.map"
    bad.write_text("2,x\n....\n")
    with pytest.raises(ProblemError, match=r"b\.map:1: expected 'rows,cols'"):
        load_lorr_map(bad)
    bad.write_text("2,4\n....\n..\n")
    with pytest.raises(ProblemError, match=r"b\.map:3: map row 1 has 2 cells, expected 4"):
        load_lorr_map(bad)


def test_task_states_and_forbidden_transitions():
    pool = TaskPool()
    t = pool.add([3, 4], priority=1.0)
    assert t.state is TaskState.QUEUED and not t.opened
    pool.assign(t.id, 0)
    assert t.state is TaskState.ASSIGNED
    pool.assign(t.id, 1)                      # unopened: reassigned freely
    assert t.agent == 1
    assert not pool.reach(t.id, 5)
    assert t.state is TaskState.ACTIVE and t.opened
    with pytest.raises(TaskError, match="opened by agent 1"):
        pool.assign(t.id, 0)
    with pytest.raises(TaskError, match="active"):
        pool.cancel(t.id)
    assert pool.reach(t.id, 9) and t.state is TaskState.DONE and pool.finished == 1 and len(pool) == 0
    late = pool.add([1], deadline=3)
    assert pool.expire(4) == [late] and late.state is TaskState.FAILED
    with pytest.raises(TaskError):
        pool.add([])


def test_the_pool_owns_every_state_with_times_robot_and_reason():
    pool = TaskPool(keep_closed=2)
    a = pool.add([3, 4], at=10.0)
    pool.assign(a.id, 0, "Robot1", at=11.0)
    pool.unassign(a.id, at=12.0)               # back to the queue: no robot
    assert a.state is TaskState.QUEUED and a.agent == -1 and a.robot == ""
    pool.assign(a.id, 2, "Robot3", at=13.0)
    assert not pool.reach(a.id, 14, at=14.5)
    pool.fail(a.id, "errand cell 4 was blocked (operator)", at=15.0)
    assert a.state is TaskState.FAILED and a.reason == "errand cell 4 was blocked (operator)" and a.robot == "Robot3"
    assert a.times == {"queued": 12.0, "assigned": 13.0, "active": 14.5, "failed": 15.0}
    assert [(h[1], h[3]) for h in a.history] == [("queued", ""), ("assigned", "Robot1"), ("queued", ""),
                                                 ("assigned", "Robot3"), ("active", "Robot3"), ("failed", "Robot3")]
    b = pool.add([5, 6], at=16.0)
    pool.assign(b.id, 1, "Robot2", at=16.0)
    pool.reach(b.id, 17, at=17.0)
    with pytest.raises(TaskError, match="active"):
        pool.cancel(b.id, "operator")          # LoRR's rule
    pool.cancel(b.id, "cancelled by operator", at=18.0, active=True)
    assert b.state is TaskState.CANCELLED and b.times["cancelled"] == 18.0 and b.reason == "cancelled by operator"
    with pytest.raises(TaskError, match="not open"):
        pool.fail(b.id, "again")
    assert pool.closed == {TaskState.DONE: 0, TaskState.FAILED: 1, TaskState.CANCELLED: 1} and len(pool) == 0
    assert pool.get(a.id) is a and pool.get(b.id) is b
    c = pool.add([7], release=19)              # without at: its release step
    pool.cancel(c.id)                          # without at: the newest time the pool was given
    assert c.times == {"queued": 19.0, "cancelled": 19.0}
    assert pool.get(c.id) is c and len(pool.ended) == 2   # keep_closed: the oldest is forgotten
    with pytest.raises(TaskError, match=f"no task {a.id}"):
        pool.get(a.id)


# -- distances -----------------------------------------------------------------------------------
def test_distance_maps_are_bfs_and_the_cache_is_bounded():
    g = grid(["....", ".@@.", "...."])
    cache = DistanceCache(g, max_bytes=0, min_rows=2)
    assert cache.capacity == 2
    s = cache.slot(0)
    assert cache.table[s].reshape(3, 4).tolist() == [[0, 1, 2, 3], [1, UNREACHABLE, UNREACHABLE, 4],
                                                     [2, 3, 4, 5]]
    cache.slot(3)
    cache.pinned = {0}
    cache.slot(11)                            # evicts 3, the least recent unpinned
    assert 0 in cache and 11 in cache and 3 not in cache and len(cache) == 2
    assert cache.dist(0, 11) == 5 and cache.dist(3, 8) == 5   # the second by a search that stops early
    cache.pinned = {0, 11}
    with pytest.raises(RuntimeError, match="pinned"):
        cache.slot(4)



def test_cache_bound_holds_every_free_cell_when_memory_allows_else_a_share_or_an_error():
    from rce_fleet.lifelong.distances import cache_bytes_for
    g = grid(["....", ".@@.", "...."])                # 10 free cells, rows of 24 bytes
    every = 10 * 24
    assert cache_bytes_for(g, 2, available=10 ** 9) == every
    assert DistanceCache(g, max_bytes=every).capacity == 10
    assert DistanceCache(g, max_bytes=10 ** 9).capacity == 10   # never more rows than free cells
    # little memory: a share of it, but at least the floor (10,000 free cells, rows of 20,000 bytes)
    big = LifelongGrid(np.ones((100, 100), dtype=bool))
    assert cache_bytes_for(big, 1, available=40 * 10 ** 6, share=0.25, floor=0) == 10 ** 7
    assert cache_bytes_for(big, 1, available=40 * 10 ** 6, share=0.25, floor=2 * 10 ** 7) == 2 * 10 ** 7
    # a team whose pinned goals do not fit in the share gets their rows, if half the memory holds them
    assert cache_bytes_for(big, 5000, available=2 ** 28, share=0.25, floor=0) == 20_000 * 5016
    # else it is refused up front, with the numbers
    with pytest.raises(MemoryError, match=r"7000 robots need .* GiB"):
        cache_bytes_for(big, 7000, available=2 ** 28, share=0.25, floor=0)
    assert cache_bytes_for(big, 5000, available=2 ** 34) == 2 * 10_000 * 10_000

def test_robots_keep_right_in_a_corridor_four_cells_wide_and_rooms_keep_no_lanes():
    from rce_fleet.lifelong.guidance import keep_right_costs
    # two 16 x 8 rooms (wider than a corridor's 12) joined by a corridor 4 cells wide and 20 long
    g = grid(["." * 8 + ("." * 20 if 2 <= r <= 5 else "#" * 20) + "." * 8 for r in range(16)])
    cost = keep_right_costs(g, against=4)
    east, south, west, north = 0, 1, 2, 3
    cols = g.cols

    def cell(r, c):
        return r * cols + c
    for c in range(8, 28):
        for r in (2, 3):                      # north half: the lane runs west
            assert cost[cell(r, c), east] == 5 and cost[cell(r, c), west] == 1
        for r in (4, 5):                      # south half: east
            assert cost[cell(r, c), west] == 5 and cost[cell(r, c), east] == 1
        for r in range(2, 6):                 # across the corridor: free
            assert cost[cell(r, c), north] == 1 and cost[cell(r, c), south] == 1
    for c in list(range(8)) + list(range(28, 36)):        # rooms: no lanes
        assert (cost[[cell(r, c) for r in range(16)]] == 1).all()
    # a robot bound west from the south half crosses over first: the way along the south half
    # costs 4 more per cell, so its distance is the plain one plus the two steps across
    lanes = DistanceCache(g, cost=cost)
    plain = DistanceCache(g)
    start, goal = cell(5, 30), cell(5, 4)
    assert lanes.table[lanes.slot(goal), start] == plain.table[plain.slot(goal), start] + 2 + 2
    assert lanes.table[lanes.slot(start), goal] == plain.table[plain.slot(start), goal]
    # added on top of given costs; odd widths leave their middle row free; 0 adds nothing
    base = np.full(g.nbr.shape, 3, dtype=np.uint8)
    assert (keep_right_costs(g, against=4, cost=base)[cell(2, 10)] == [7, 3, 3, 3]).all()
    assert (keep_right_costs(g, against=0) == 1).all()
    odd = grid(["#" * 20, "." * 20, "." * 20, "." * 20, "#" * 20])
    mid = keep_right_costs(odd, against=4)
    assert (mid[2 * 20 + 5] == 1).all() and mid[20 + 5, east] == 5 and mid[3 * 20 + 5, west] == 5
    with pytest.raises(ValueError, match="max_width"):
        keep_right_costs(g, max_width=1)


def test_weighted_maps_equal_bfs_at_unit_cost_and_lanes_send_robots_round_a_one_way_row():
    from rce_fleet.lifelong.guidance import lane_costs
    g = load_problem(RANDOM).grid
    bfs = DistanceCache(g)
    unit = DistanceCache(g, cost=np.ones(g.nbr.shape, dtype=np.uint8))
    for goal in g.free_cells()[::97]:
        assert (bfs.table[bfs.slot(int(goal))] == unit.table[unit.slot(int(goal))]).all()
    w = grid([".........",
              ".###.###.",
              ".........",
              ".###.###.",
              "........."])
    cost = lane_costs(w, against=4)
    east, west = 0, 2
    assert cost[2, west] == 5 and cost[2, east] == 1           # row 0 runs east
    assert cost[20, east] == 5 and cost[20, west] == 1         # row 2 runs west
    assert cost[38, west] == 5 and cost[0].tolist() == [1, 1, 1, 1]   # row 4 east; a crossing is free
    lanes = DistanceCache(w, cost=cost)
    # (0, 7) to (0, 1): 6 moves west against row 0, or 14 round by row 2, which runs west
    plain = DistanceCache(w)
    assert plain.table[plain.slot(1), 7] == 6
    assert lanes.table[lanes.slot(1), 7] == 14
    assert lanes.table[lanes.slot(7), 1] == 6                  # with the lane: straight
    assert (lane_costs(w, against=0) == 1).all()
    # a corridor of 20,000 cells against its lane costs 5 x 19,999: stored as the largest cost, never wrapped
    line = LifelongGrid(np.ones((1, 20_000), dtype=bool))
    far = DistanceCache(line, cost=lane_costs(line, against=4))
    row = far.table[far.slot(0)].astype(np.int64)
    assert row[1] == 5 and row[-1] == UNREACHABLE - 1 and (np.diff(row) >= 0).all()
    with pytest.raises(ValueError, match="cost must be"):
        DistanceCache(w, cost=np.ones((3, 4), dtype=np.uint8))


def test_heading_cost_adds_the_turns_to_face_a_shorter_way():
    g = grid(["...."])
    cache = DistanceCache(g)
    s = cache.slot(3)
    assert heading_cost(g.nbr, cache.table, s, 0, 0) == 3      # facing east: 3 moves
    assert heading_cost(g.nbr, cache.table, s, 0, 1) == 4      # facing south: one turn first
    assert heading_cost(g.nbr, cache.table, s, 0, 2) == 5      # facing west: two turns
    assert heading_cost(g.nbr, cache.table, s, 3, 2) == 0


# -- schedulers ------------------------------------------------------------------------------------
def open_tasks(errands: list[tuple[int, ...]]) -> TaskPool:
    pool = TaskPool()
    for e in errands:
        pool.add(e)
    return pool


@pytest.mark.parametrize("cls", [GreedyScheduler, BatchScheduler])
def test_schedulers_give_each_free_robot_the_task_it_finishes_first(cls):
    g = grid(["." * 10])
    pool = open_tasks([(9, 8), (1, 2), (5, 6)])
    sched = cls(DistanceCache(g))
    prop = sched.schedule(np.array([0, 4]), np.array([-1, -1]), pool.open, 0, time.perf_counter() + 1)
    assert prop.tolist() == [1, 2]            # robot 0 -> task at 1, robot 4 -> task at 5


@pytest.mark.parametrize("cls", [GreedyScheduler, BatchScheduler])
def test_schedulers_keep_robots_out_of_a_crowded_block_when_asked(cls):
    g = grid(["." * 40, "." * 40])
    # robot 0 at cell 20 (row 0); a task 3 cells west at 17, one 10 cells east at 30; eight
    # robots (with opened tasks elsewhere) crowd the block of cells 10..19 of both rows
    crowd = [10, 11, 12, 13, 50, 51, 52, 53]
    pool = open_tasks([(17, 16), (30, 31)] + [(c, 0) for c in crowd])
    for k in range(len(crowd)):
        pool.assign(2 + k, 1 + k)
        pool.reach(2 + k, 0)                  # opened: the schedulers leave them alone
    pos = np.array([20, *crowd])
    busy = np.array([-1, *range(2, 2 + len(crowd))])
    near = cls(DistanceCache(g))
    assert near.schedule(pos, busy, pool.open, 0, time.perf_counter() + 1)[0] == 0
    avoid = cls(DistanceCache(g))
    avoid.crowd_w = 2.0         # 8 robots where 2.25 are its share, at both errands of task 0: +23 steps
    assert avoid.schedule(pos, busy, pool.open, 0, time.perf_counter() + 1)[0] == 1


@pytest.mark.parametrize("cls", [GreedyScheduler, BatchScheduler])
def test_schedulers_move_unopened_tasks_never_opened_ones(cls):
    g = grid(["." * 12])
    pool = open_tasks([(2, 3), (11, 10)])
    pool.assign(0, 0)                         # robot 0 at cell 11 holds the task at cell 2
    sched = cls(DistanceCache(g))
    pos = np.array([11, 1])                   # robot 1 frees up next to cell 2
    prop = sched.schedule(pos, np.array([0, -1]), pool.open, 0, time.perf_counter() + 1)
    assert prop.tolist() == [1, 0], "the nearer robot takes the unopened task; the other gets the one by it"
    pool.reach(0, 1)                          # now opened by robot 0
    prop = sched.schedule(pos, np.array([0, -1]), pool.open, 0, time.perf_counter() + 1)
    assert prop[0] == 0 and prop[1] == 1


@pytest.mark.parametrize("cls", [GreedyScheduler, BatchScheduler])
def test_with_length_w_0_a_task_costs_its_way_to_the_first_errand_and_its_deadline_its_whole_length(cls):
    g = grid(["." * 30])
    pool = open_tasks([(3, 29), (6, 7)])      # from cell 0: 3 + 26 steps, or 6 + 1
    short = cls(DistanceCache(g))
    assert short.schedule(np.array([0]), np.array([-1]), pool.open, 0, time.perf_counter() + 1).tolist() == [1]
    near = cls(DistanceCache(g))
    near.length_w = 0.0                       # only the way to the first errand counts
    assert near.schedule(np.array([0]), np.array([-1]), pool.open, 0, time.perf_counter() + 1).tolist() == [0]
    late = TaskPool()
    late.add([3, 29], deadline=20)            # its first errand is near, but it cannot end by step 20
    late.add([6, 7])
    assert near.schedule(np.array([0]), np.array([-1]), late.open, 0, time.perf_counter() + 1).tolist() == [1]
    with pytest.raises(ValueError, match="length_w must be a finite share >= 0"):
        make_scheduler(cls.name, DistanceCache(g), length_w=-1.0)


def test_scheduler_respects_time_windows_and_priority():
    g = grid(["." * 10])
    pool = TaskPool()
    pool.add([1], deadline=0)                 # cannot be reached in time
    pool.add([8])
    pool.add([5], priority=1.0)               # far but urgent
    sched = GreedyScheduler(DistanceCache(g))
    prop = sched.schedule(np.array([0]), np.array([-1]), pool.open, 0, time.perf_counter() + 1)
    assert prop.tolist() == [2]


# -- planner ----------------------------------------------------------------------------------------
def run_steps(g, starts, goals, model, steps, seed=0):
    cache = DistanceCache(g)
    pl = PIBTPlanner(g, cache, model=model, seed=seed)
    pos = np.asarray(starts, dtype=np.int64)
    head = np.zeros(len(pos), dtype=np.int64)
    goals = np.asarray(goals, dtype=np.int64)
    for _ in range(steps):
        act = pl.plan(pos, head, goals, time.perf_counter() + 1)
        new_pos, new_head, errs = check_actions(g, pos, head, act, model)
        assert errs == []
        pos, head = new_pos, new_head
    return pos


@pytest.mark.parametrize("model", [MAPF_T, MAPF])
def test_planner_steps_are_conflict_free_and_reach_goals(model):
    rng = np.random.default_rng(1)
    free = np.ones((12, 12), dtype=bool)
    free[rng.random((12, 12)) < 0.15] = False
    g = LifelongGrid(free)
    cells = rng.choice(g.free_cells(), 60, replace=False)
    pos = run_steps(g, cells[:30], cells[30:], model, 120)
    assert (pos == cells[30:]).mean() > 0.8


def test_planner_passes_two_robots_in_a_corridor_with_one_bay():
    g = grid([".....", "@@.@@"])             # a corridor with one side bay below cell 2
    for model in (MAPF, MAPF_T):
        pos = run_steps(g, [0, 4], [4, 0], model, 30)
        assert pos.tolist() == [4, 0], model


def test_planner_defers_a_robot_whose_map_misses_the_deadline():
    g = grid(["....."])
    pl = PIBTPlanner(g, DistanceCache(g), model=MAPF)
    act = pl.plan(np.array([0]), np.array([0]), np.array([4]), time.perf_counter() - 1)
    assert act.tolist() == [4] and pl.stats["deferred"] == 1


def test_one_shot_pibt_on_the_movingai_warehouse():
    from rce_fleet.planning import load_movingai_map, load_movingai_scen
    gg = load_movingai_map(DATA / "mapf" / "warehouse-10-20-10-2-1.map")
    sc = load_movingai_scen(DATA / "mapf" / "warehouse-10-20-10-2-1-random-1.scen", gg)[:50]
    g = LifelongGrid.from_graph(gg)
    res = solve_one_shot(g, np.array([s for s, _ in sc]), np.array([t for _, t in sc]), time_limit_s=10)
    assert res["solved"]
    paths = res["paths"]
    for k in range(1, len(paths)):
        moved = paths[k] != paths[k - 1]
        assert all(paths[k][a] in g.nbr[paths[k - 1][a]] for a in np.flatnonzero(moved))
        assert len(set(paths[k].tolist())) == len(sc)
    lb = sum(int(DistanceCache(g).from_source(t)[s]) for s, t in sc)
    assert lb <= res["sum_of_costs"] <= 1.5 * lb


def test_lifelong_run_on_the_random_problem_finishes_tasks_without_errors():
    from rce_fleet.lifelong.runner import run_lifelong
    res = run_lifelong(load_problem(RANDOM), 60, plan_time_limit_ms=500.0, record=False)
    s = res.summary()
    assert s["invalid_steps"] == 0 and s["schedule_errors"] == 0
    assert s["tasks_finished"] > 60
    assert isinstance(res.sim, Simulator)
    assert (s["yield_steps"], s["stuck_steps"]) == (20, 20)       # 100 robots on 819 free cells


def test_a_dense_team_on_a_larger_map_does_not_yield():
    from rce_fleet.lifelong.runner import run_lifelong
    p = load_problem(RANDOM)
    p = dataclasses.replace(p, starts=np.asarray(p.grid.free_cells()[:300], np.int64), team_size=300)  # 0.37 a cell
    assert run_lifelong(p, 2, plan_time_limit_ms=200.0, record=False).stats["yield_steps"] == 0


def test_on_a_map_of_a_few_cells_a_robot_without_progress_yields_after_five_steps(tmp_path):
    from rce_fleet.lifelong.runner import SMALL_MAP_STUCK, run_lifelong
    s = run_lifelong(load_problem(write_problem(tmp_path, "2\n0\n4\n")), 20, plan_time_limit_ms=50.0).summary()
    assert SMALL_MAP_STUCK == 5
    assert s["invalid_steps"] == 0 and (s["yield_steps"], s["stuck_steps"]) == (5, 5)
    kept = run_lifelong(load_problem(write_problem(tmp_path, "2\n0\n4\n")), 5, plan_time_limit_ms=50.0,
                        planner_kw={"yield_steps": 0}).summary()
    assert (kept["yield_steps"], kept["stuck_steps"]) == (0, 5)


def assert_solution(g: LifelongGrid, paths: np.ndarray, starts, goals) -> None:
    assert paths[0].tolist() == list(starts) and paths[-1].tolist() == list(goals)
    for a, b in zip(paths[:-1], paths[1:], strict=True):
        assert len(set(b.tolist())) == len(b), "vertex conflict"
        for i in range(len(a)):
            assert b[i] == a[i] or b[i] in g.nbr[a[i]], "not a move"
            j = np.flatnonzero(a == b[i])
            assert not (len(j) and j[0] != i and b[j[0]] == a[i]), "swap conflict"


def test_lacam_solves_what_needs_a_detour_and_lns_never_makes_it_worse():
    from rce_fleet.lifelong.lacam import solve_lacam
    from rce_fleet.lifelong.refine import refine_lns
    g = grid(["......", "@@.@@@", "@@.@@@"])  # two robots swap ends; the only passing place is the dead end
    starts, goals = [0, 5, 1], [5, 0, 14]
    warm_up()                                  # compile before the solver's clock starts
    res = solve_lacam(g, np.array(starts), np.array(goals), time_limit_s=10)
    assert res["solved"]
    assert_solution(g, res["paths"], starts, goals)
    ref = refine_lns(g, res["paths"], np.array(goals), 0.5)
    assert ref["sum_of_costs"] <= res["sum_of_costs"]
    assert_solution(g, ref["paths"], starts, goals)
    with pytest.raises(ValueError, match="share"):
        solve_lacam(g, np.array([0, 0]), np.array([1, 2]))


def test_scatter_sends_one_of_two_head_on_agents_round_the_other_way_and_guides_lacam():
    from rce_fleet.lifelong.lacam import solve_lacam
    from rce_fleet.lifelong.kernels import preferred
    from rce_fleet.lifelong.scatter import scatter
    g = grid([".......", ".@@@@@.", "......."])   # two corridors joined at both ends
    cache = DistanceCache(g)
    starts, goals = np.array([0, 6]), np.array([6, 0])   # head-on along the top corridor
    rows = np.array([cache.slot(int(x)) for x in goals])
    # within a margin of 3 neither may go round (10 steps against 6): both stay on top and meet
    still = lambda: 0.0                                  # noqa: E731 -- a clock that never runs out: rounds, not time, end it
    prefer, stats = scatter(g.nbr, cache.table, rows, starts, goals, margin=3, clock=still)
    assert stats["collisions"][-1] > 0 and stats["rounds"] == 2
    assert preferred(prefer, 0, 0, g.n_cells) == 1 and preferred(prefer, 1, 6, g.n_cells) == 5
    assert preferred(prefer, 0, 6, g.n_cells) == -1      # off its path: no preference
    prefer, stats = scatter(g.nbr, cache.table, rows, starts, goals, margin=10, clock=still)
    assert stats["collisions"][-1] == 0
    bottom = [preferred(prefer, 0, 0, g.n_cells) == 7, preferred(prefer, 1, 6, g.n_cells) == 13]
    assert sorted(bottom) == [False, True]       # exactly one goes round by the bottom corridor
    for a in range(2):                           # each preferred path leads from start to goal
        c, steps = int(starts[a]), 0
        while c != goals[a]:
            nxt = int(preferred(prefer, a, c, g.n_cells))
            assert nxt in g.nbr[c]
            c, steps = nxt, steps + 1
        assert steps == (10 if bottom[a] else 6)
    warm_up()
    res = solve_lacam(g, starts, goals, time_limit_s=10, scatter_share=0.5)
    assert res["solved"] and res["sum_of_costs"] == 16 and res["scatter"]["rounds"] >= 1
    assert_solution(g, res["paths"], starts.tolist(), goals.tolist())


def test_prefer_table_finds_every_entry_and_nothing_else():
    from rce_fleet.lifelong.kernels import NO_PREFER, prefer_table, preferred
    rng = np.random.default_rng(0)
    n_cells = 70_000
    keys = rng.choice(500 * n_cells, 3000, replace=False)
    agents, cells = keys // n_cells, keys % n_cells
    nxt = rng.integers(0, n_cells, 3000)
    table = prefer_table(agents, cells, nxt, n_cells)
    assert table.shape == (8192, 2)              # a power of two, at least twice the entries
    assert all(preferred(table, int(a), int(c), n_cells) == int(v) for a, c, v in zip(agents, cells, nxt, strict=True))
    taken = set(keys.tolist())
    absent = [k for k in rng.choice(500 * n_cells, 3000, replace=False).tolist() if k not in taken]
    assert all(preferred(table, k // n_cells, k % n_cells, n_cells) == -1 for k in absent)
    assert preferred(NO_PREFER, 0, 0, n_cells) == -1


@pytest.mark.parametrize("sipp", [False, True], ids=["astar", "sipp"])
def test_space_time_search_waits_for_the_goal_and_never_enters_a_parked_one(sipp):
    from rce_fleet.lifelong.spacetime import SpaceTimeTable
    g = grid([".....", "@@.@@"])                 # a corridor with one bay below its middle
    cache = DistanceCache(g)
    # agent 0 crosses the corridor through cell 2; agent 1 starts in the bay and must go to 2
    starts, goals = np.array([0, 7]), np.array([4, 2])
    hrow = np.array([cache.slot(int(x)) for x in goals])
    res = SpaceTimeTable(2, g.n_cells, 12, 4)
    assert res.plan(g.nbr, cache.table, hrow, starts, goals, [0, 1], 10_000, sipp) == 2
    p0, p1 = res.paths[0, : res.lengths[0]], res.paths[1, : res.lengths[1]]
    assert p0.tolist() == [0, 1, 2, 3, 4]        # the first agent goes straight
    assert res.lengths[1] - 1 >= 3               # the second waits until cell 2 is clear
    T = max(len(p0), len(p1)) + 1
    paths = np.array([[p[min(t, len(p) - 1)] for p in (p0, p1)] for t in range(T)])
    assert_solution(g, paths, starts, goals)
    # a goal parked on for good cannot be entered: agent 1 (start 4) cannot pass agent 0 parked on 2
    res = SpaceTimeTable(2, g.n_cells, 12, 4)
    starts, goals = np.array([0, 4]), np.array([2, 0])
    hrow = np.array([cache.slot(int(x)) for x in goals])
    assert res.plan(g.nbr, cache.table, hrow, starts, goals, [0, 1], 10_000, sipp) == 1


def test_safe_interval_search_arrives_when_the_space_time_astar_does_and_keeps_the_rules():
    """Both searches are exact (earliest arrival around everybody else, vertex and swap
    conflicts, goals held from the arrival on): from a crowded LaCAM solution each agent in turn
    is taken out and re-planned by both; the arrivals agree and the safe-interval path fits the
    reservation table step by step."""
    from rce_fleet.lifelong.lacam import solve_lacam
    from rce_fleet.lifelong.refine import _arrivals
    from rce_fleet.lifelong.spacetime import SpaceTimeTable
    warm_up()
    rng = np.random.default_rng(5)
    g = LifelongGrid(rng.random((14, 14)) > 0.2)
    cache = DistanceCache(g)
    cells = np.flatnonzero(g.flat)
    big = [c for c in cells if cache.from_source(int(cells[0]))[c] < UNREACHABLE]
    pick = rng.choice(big, 80, replace=False)
    starts, goals = pick[:40].astype(np.int64), pick[40:].astype(np.int64)
    sol = solve_lacam(g, starts, goals, time_limit_s=30)
    assert sol["solved"]
    paths = sol["paths"]
    hrow = np.array([cache.slot(int(x)) for x in goals])
    res = SpaceTimeTable(40, g.n_cells, paths.shape[0] + 32, int(cache.table[hrow, starts].max()) + 1)
    res.paths[:, : paths.shape[0]] = paths.T
    res.lengths[:] = _arrivals(paths, goals) + 1
    res.place(goals, np.arange(40))
    for a in range(40):
        old, old_len = res.paths[a].copy(), int(res.lengths[a])
        res.remove(goals, [a])
        assert res.plan(g.nbr, cache.table, hrow, starts, goals, [a], 10 ** 6, False) == 1
        by_astar = int(res.lengths[a])
        assert by_astar <= old_len                 # the old path is one the search may return
        res.remove(goals, [a])
        others = res.occ.copy()
        assert res.plan(g.nbr, cache.table, hrow, starts, goals, [a], 10 ** 6, True) == 1
        assert res.lengths[a] == by_astar
        p = res.paths[a, : res.lengths[a]]
        assert p[0] == starts[a] and p[-1] == goals[a]
        assert (others[p, np.arange(len(p))] == -1).all(), "vertex"
        assert (others[goals[a], len(p) - 1:] == -1).all(), "a goal held by another agent later"
        for t in range(1, len(p)):
            assert p[t] == p[t - 1] or p[t] in g.nbr[p[t - 1]]
            j = others[p[t], t - 1]                # whoever stood on the entered cell
            assert j < 0 or others[p[t - 1], t] != j, "swap"
        res.remove(goals, [a])
        res.paths[a], res.lengths[a] = old, old_len
        res.place(goals, [a])
    long = SpaceTimeTable(1, 4, 2 ** 20, 2)      # a step must fit the heap key's field
    with pytest.raises(ValueError, match="horizon below"):
        long.plan(g.nbr, cache.table, hrow[:1], starts[:1], goals[:1], [0], 100, True)


def test_lns_removes_detours_and_keeps_a_crowded_solution_valid():
    from rce_fleet.lifelong.lacam import solve_lacam
    from rce_fleet.lifelong.refine import refine_lns
    warm_up()
    g = grid(["......", "......", "......"])
    # agent 0 detours through the bottom row for nothing; agent 1 stays on its goal
    wander = [0, 6, 12, 13, 14, 15, 9, 3]
    paths = np.array([[c, 16] for c in wander])
    ref = refine_lns(g, paths, np.array([3, 16]), 5.0)
    assert ref["sum_of_costs"] == 3 and ref["paths"][:, 0].tolist() == [0, 1, 2, 3]
    assert_solution(g, ref["paths"], [0, 16], [3, 16])
    # a crowded random instance: LaCAM's solution, then LNS; valid, all at goals, never worse
    rng = np.random.default_rng(3)
    free = rng.random((12, 12)) > 0.2
    g = LifelongGrid(free)
    cells = np.flatnonzero(g.flat)
    big = [c for c in cells if DistanceCache(g).from_source(int(cells[0]))[c] < UNREACHABLE]
    pick = rng.choice(big, 60, replace=False)
    starts, goals = pick[:30], pick[30:]
    res = solve_lacam(g, starts, goals, time_limit_s=30)
    assert res["solved"]
    guided = solve_lacam(g, starts, goals, time_limit_s=30, scatter_share=0.5)
    assert guided["solved"] and guided["scatter"]["rounds"] >= 2
    assert_solution(g, guided["paths"], starts.tolist(), goals.tolist())
    plain = solve_lacam(g, starts, goals, time_limit_s=30, noise=0.0)      # no random walk when stuck
    assert plain["solved"]
    assert_solution(g, plain["paths"], starts.tolist(), goals.tolist())
    ref = refine_lns(g, res["paths"], goals, 0.5, seed=1)
    assert_solution(g, ref["paths"], starts.tolist(), goals.tolist())
    arrival = [int(np.flatnonzero(ref["paths"][:, a] != goals[a]).max(initial=-1)) + 1 for a in range(30)]
    assert ref["sum_of_costs"] == sum(arrival) <= res["sum_of_costs"]
    with pytest.raises(ValueError, match="last row"):
        refine_lns(g, res["paths"][:1], goals, 0.1)


def test_lns_single_replans_search_past_the_group_cap_and_a_cut_search_keeps_the_old_path():
    """A single agent's re-plan has its own cap (``single_expand``), above a group's
    (``max_expand``): the detour is removed even when a group re-plan may expand only one
    state; with both caps at one state every search is cut short and the old path stays."""
    from rce_fleet.lifelong.refine import refine_lns
    warm_up()
    g = grid(["......", "......", "......"])
    wander = [0, 6, 12, 13, 14, 15, 9, 3]      # agent 0 detours through the bottom row
    paths = np.array([[c, 16] for c in wander])
    goals = np.array([3, 16])
    ref = refine_lns(g, paths, goals, 5.0, max_expand=1)
    assert ref["sum_of_costs"] == 3 and ref["paths"][:, 0].tolist() == [0, 1, 2, 3]
    cut = refine_lns(g, paths, goals, 0.2, max_expand=1, single_expand=1)
    assert cut["sum_of_costs"] == 7 and cut["iterations"] > 0 and cut["accepted"] == 0
    assert cut["paths"][:, 0].tolist() == wander
    assert_solution(g, cut["paths"], [0, 16], [3, 16])
