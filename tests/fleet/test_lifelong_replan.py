"""Whole plans on maps of a few cells: LaCAM's plans executed under MAPF_T's turns by an action
dependency graph (adg.py), planned again at every arrival (replan.py), checked under the rules."""
from __future__ import annotations

import time

import numpy as np
import pytest

from rce_fleet.lifelong import DistanceCache, LifelongGrid
from rce_fleet.lifelong.adg import PlanExecution
from rce_fleet.lifelong.grid import EAST, SOUTH, WEST
from rce_fleet.lifelong.kernels import warm_up
from rce_fleet.lifelong.simulator import check_actions


def grid(rows: list[str]) -> LifelongGrid:
    return LifelongGrid(np.array([[ch == "." for ch in row] for row in rows]))


def execute(g: LifelongGrid, paths: np.ndarray, head: np.ndarray, limit: int = 500) -> list[np.ndarray]:
    """Run a plan to its end, every step checked under the rules; returns the positions after each step."""
    ex = PlanExecution(g.nbr, paths)
    pos = paths[0].copy()
    seen = [pos]
    for _ in range(limit):
        if ex.done:
            return seen
        act = ex.step(head)
        pos, head, errors = check_actions(g, pos, head, act)
        assert errors == []
        assert pos.tolist() == ex.expected().tolist()
        seen.append(pos)
    raise AssertionError(f"the plan did not end in {limit} steps")


def test_four_robots_round_a_ring_turn_first_then_move_at_once():
    g = grid(["..", ".."])                       # cells 0 1 / 2 3: a ring 0 -> 1 -> 3 -> 2 -> 0
    paths = np.array([[0, 1, 3, 2], [1, 3, 2, 0]])
    head = np.array([EAST, EAST, EAST, EAST])    # robot 0 faces its next cell, the others must turn
    seen = execute(g, paths, head)
    assert [p.tolist() for p in seen] == [[0, 1, 3, 2], [0, 1, 3, 2], [0, 1, 3, 2], [1, 3, 2, 0]]


def test_a_follower_enters_the_cell_its_leader_leaves_in_the_same_step():
    g = grid(["...."])
    paths = np.array([[1, 0], [2, 1], [3, 2]])   # robot 1 follows robot 0 east
    seen = execute(g, paths, np.array([EAST, EAST]))
    assert [p.tolist() for p in seen] == [[1, 0], [2, 1], [3, 2]]


def test_robots_pass_each_cell_in_the_plans_order_whatever_their_turns_cost():
    # robot 0 crosses cell 4 (the centre) first, facing away from it; robot 1 faces it and would be
    # there at once without the plan's order
    g = grid(["...", "...", "..."])
    paths = np.array([[3, 5], [4, 5], [7, 4], [7, 1]])
    head = np.array([SOUTH, WEST])
    seen = execute(g, paths, head)
    at4 = [p.tolist().index(4) if 4 in p.tolist() else None for p in seen]
    first = next(i for i, a in enumerate(at4) if a is not None)
    assert at4[first] == 0 and [p.tolist() for p in seen][-1] == [7, 1]


@pytest.mark.parametrize("seed", range(6))
def test_lacam_plans_on_random_maps_execute_under_the_rules_to_their_goals(seed):
    from rce_fleet.lifelong.lacam import solve_lacam
    warm_up()
    rng = np.random.default_rng(seed)
    free = rng.random((7, 7)) > 0.2
    g = LifelongGrid(free)
    cells = g.free_cells()
    # the largest connected part, so that every goal can be reached
    comp = DistanceCache(g).table[DistanceCache(g).slot(int(cells[0]))]
    part = cells[comp[cells] < 60000]
    n = min(8, len(part) // 2)
    starts = rng.choice(part, n, replace=False)
    goals = rng.choice(part, n, replace=False)
    res = solve_lacam(g, starts, goals, time_limit_s=5, seed=seed)
    assert res["solved"]
    head = rng.integers(0, 4, n)
    seen = execute(g, res["paths"], head)
    assert seen[-1].tolist() == goals.tolist()


def test_a_plan_whose_moves_are_not_moves_is_refused_naming_the_robot():
    g = grid(["...."])
    with pytest.raises(ValueError, match="robot 1: cell 3 at time 1"):
        PlanExecution(g.nbr, np.array([[0, 1], [1, 3]]))


def test_distinct_goals_give_a_shared_goal_to_the_nearest_and_move_the_others_aside():
    from rce_fleet.lifelong.replan import distinct_goals
    g = grid(["....."])
    cache = DistanceCache(g)
    pos = np.array([0, 3, 2, 4])
    goals = np.array([2, 2, -1, -1])              # robots 0 and 1 share cell 2; robot 2 stands on it, no task
    out = distinct_goals(g, pos, goals, cache)
    assert out[1] == 2                            # robot 1 is one cell from it, robot 0 two
    assert out[3] == 4                            # stays where it stands
    assert len(set(out.tolist())) == 4 and out[0] in (0, 1) and out[2] in (1, 3, 0)


def _tunnel(planner_factory, steps: int) -> dict[int, int]:
    g = grid([".@@@", "....", ".@@@", ".@@@", ".@@@", ".@@@"])
    pos, head = np.array([20, 16], np.int64), np.array([WEST, SOUTH], np.int64)
    goals = np.array([6, 20], np.int64)
    planner = planner_factory(g)
    reached = {}
    for t in range(steps):
        now = time.perf_counter()
        act = planner.plan(pos, head, goals, now + 0.5, now + 1.0)
        pos, head, errors = check_actions(g, pos, head, act)
        assert errors == []
        for a in np.flatnonzero((goals >= 0) & (pos == goals)):
            reached[int(a)] = t
            goals[a] = -1
    return reached


def test_whole_plans_bring_two_robots_head_on_in_a_dead_end_corridor_to_their_goals():
    from rce_fleet.lifelong import PIBTPlanner
    from rce_fleet.lifelong.replan import ReplanPlanner
    warm_up()
    made = []

    def factory(g):
        made.append(ReplanPlanner(g, PIBTPlanner(g, DistanceCache(g), seed=1)))
        return made[0]
    reached = _tunnel(factory, 40)
    assert set(reached) == {0, 1}
    assert made[0].stats["replans"] >= 1 and made[0].stats["fallback_steps"] == 0


def test_where_no_plan_exists_the_fallback_answers_and_the_rules_hold():
    from rce_fleet.lifelong import PIBTPlanner
    from rce_fleet.lifelong.replan import ReplanPlanner
    warm_up()
    g = grid(["...."])                            # a corridor without a passing place
    planner = ReplanPlanner(g, PIBTPlanner(g, DistanceCache(g), seed=0))
    pos, head, goals = np.array([0, 3]), np.array([EAST, WEST]), np.array([3, 0])
    for _ in range(5):
        now = time.perf_counter()
        act = planner.plan(pos, head, goals, now + 0.2, now + 0.4)
        pos, head, errors = check_actions(g, pos, head, act)
        assert errors == []
    assert planner.stats["fallback_steps"] == 5 and planner.stats["replans"] == 0


def test_a_goal_its_robot_cannot_reach_leaves_the_step_to_the_fallback():
    from rce_fleet.lifelong import PIBTPlanner
    from rce_fleet.lifelong.replan import ReplanPlanner
    warm_up()
    g = grid(["..@..", "..@.."])                  # two parts, no way between them
    planner = ReplanPlanner(g, PIBTPlanner(g, DistanceCache(g), seed=0))
    pos, head, goals = np.array([0, 9]), np.array([EAST, WEST]), np.array([4, 5])
    now = time.perf_counter()
    act = planner.plan(pos, head, goals, now + 0.2, now + 0.4)
    assert check_actions(g, pos, head, act)[2] == []
    assert planner.stats["fallback_steps"] == 1
    # robot 1 alone in a one-cell part whose cell robot 0 (elsewhere) has for its goal: no distinct goal for it
    g = grid(["..@."])
    planner = ReplanPlanner(g, PIBTPlanner(g, DistanceCache(g), seed=0))
    pos, head, goals = np.array([0, 3]), np.array([EAST, WEST]), np.array([3, -1])
    now = time.perf_counter()
    act = planner.plan(pos, head, goals, now + 0.2, now + 0.4)
    assert check_actions(g, pos, head, act)[2] == []
    assert planner.stats["fallback_steps"] == 1


def test_a_run_on_a_map_of_a_few_cells_plans_whole_plans_and_replays_under_the_rules(tmp_path):
    from rce_fleet.lifelong.lorr import load_problem
    from rce_fleet.lifelong.runner import run_lifelong
    from rce_fleet.lifelong.simulator import replay
    (tmp_path / "m.map").write_text("type octile\nheight 4\nwidth 3\nmap\n.@.\n...\n.@.\n...\n")
    (tmp_path / "a.agents").write_text("3\n0\n2\n9\n")
    (tmp_path / "t.tasks").write_text("4\n11,0\n6,2\n9,5\n3,11\n")
    (tmp_path / "p.json").write_text('{"mapFile": "m.map", "agentFile": "a.agents", "teamSize": 3, '
                                     '"taskFile": "t.tasks", "numTasksReveal": 1.5, "version": "2024 LoRR"}')
    p = load_problem(tmp_path / "p.json")
    r = run_lifelong(p, 120, plan_time_limit_ms=300.0)  # the wall clock of a loaded machine is not what this tests
    s = r.summary()
    assert s["replan"] is True and s["replans"] > 5
    assert s["invalid_steps"] == 0 and s["timeouts"] == 0 and s["tasks_finished"] >= 5
    assert replay(p.grid, p.tasks, p.reveal, r.sim.output()).finished == s["tasks_finished"]


@pytest.mark.parametrize("robots, whole", [(4, True), (14, False)])
def test_on_loops_without_a_dead_end_whole_plans_answer_only_a_sparse_team(tmp_path, robots, whole):
    from rce_fleet.lifelong.generate import write_problem
    from rce_fleet.lifelong.lorr import load_problem
    from rce_fleet.lifelong.runner import run_lifelong
    rows = ["..........", ".@@@@@@@@.", "..........", ".@@@@@@@@.", "..........", ".@@@@@@@@.", ".........."]
    shelves = tmp_path / "shelves.map"                # 46 free cells, three loops, no dead end
    shelves.write_text("type octile\nheight 7\nwidth 10\nmap\n" + "\n".join(rows) + "\n")
    p = load_problem(write_problem(shelves, robots, 1, tmp_path))
    s = run_lifelong(p, 3, plan_time_limit_ms=100.0).summary()
    assert s["replan"] is whole and s["invalid_steps"] == 0
