"""rce_fleet.lifelong.simulator: the League of Robot Runners 2024 rules, one test per rule,
and the start-kit's output JSON (with a replay of it)."""
from __future__ import annotations

import numpy as np
import pytest

from rce_fleet.lifelong import MAPF, MAPF_T, LifelongGrid, Simulator, check_actions, replay
from rce_fleet.lifelong.kernels import ACT_C, ACT_F, ACT_R, ACT_W, MOVE_WAIT

F, R, C, W = ACT_F, ACT_R, ACT_C, ACT_W


def grid(rows: list[str]) -> LifelongGrid:
    return LifelongGrid(np.array([[ch == "." for ch in r] for r in rows]))


G = grid(["....", ".@..", "...."])      # 3 x 4, cell 5 blocked


def sim(starts, tasks=((11,),), reveal=1, model=MAPF_T) -> Simulator:
    return Simulator(G, starts, [tuple(t) for t in tasks], reveal, model=model)


def test_robots_face_east_at_the_start_and_forward_follows_the_heading():
    s = sim([0])
    assert s.head.tolist() == [0]
    s.step(np.array([F]))
    assert s.pos.tolist() == [1]
    s.step(np.array([R]))                     # clockwise: east -> south
    assert s.head.tolist() == [1] and s.pos.tolist() == [1]
    s.step(np.array([C]))
    s.step(np.array([C]))                     # counter-clockwise twice: east -> north
    assert s.head.tolist() == [3]
    s.step(np.array([W]))
    assert s.pos.tolist() == [1] and s.invalid_steps == 0


def test_a_move_into_an_obstacle_or_off_the_map_makes_everybody_wait():
    s = sim([1, 6])
    s.head[:] = [1, 0]                        # robot 0 faces the blocked cell 5
    rep = s.step(np.array([F, F]))
    assert rep.invalid and s.invalid_steps == 1
    assert s.pos.tolist() == [1, 6], "the valid move of robot 1 must not happen either"
    assert ("unallowed move" in e for e in rep.errors)
    assert s.errors[0][:3] == (0, -1, 0)
    s2 = sim([3])                             # east edge, facing east
    assert s2.step(np.array([F])).invalid


def test_a_vertex_conflict_makes_everybody_wait():
    s = sim([0, 2])
    s.head[:] = [0, 2]                        # both head for cell 1
    rep = s.step(np.array([F, F]))
    assert rep.invalid and [e[2] for e in rep.errors] == ["vertex conflict"]
    assert s.pos.tolist() == [0, 2]


def test_a_swap_conflict_makes_everybody_wait():
    s = sim([0, 1])
    s.head[:] = [0, 2]                        # 0 -> 1 and 1 -> 0
    rep = s.step(np.array([F, F]))
    assert rep.invalid and [e[2] for e in rep.errors] == ["edge conflict"]
    assert s.pos.tolist() == [0, 1]


def test_a_chain_of_moves_into_cells_being_left_is_valid():
    s = sim([0, 1, 2])
    rep = s.step(np.array([F, F, F]))
    assert not rep.invalid and s.pos.tolist() == [1, 2, 3]


def test_a_late_planner_makes_an_all_wait_step_counted_as_timeout():
    s = sim([0])
    before = s.assignment.copy()
    rep = s.step(np.array([F]), np.array([0]), plan_time_s=1.2, timed_out=True)
    assert rep.timed_out and s.timeouts == 1 and s.pos.tolist() == [0]
    assert (s.assignment == before).all(), "a late answer's schedule is dropped too"
    assert s.output()["numEntryTimeouts"] == 1


def test_tasks_are_revealed_in_file_order_and_cyclically_keeping_reveal_open():
    s = sim([0, 2], tasks=[(4,), (7,), (9,)], reveal=2)
    assert sorted((t.id, t.errands) for t in s.pool) == [(0, (4,)), (1, (7,))]
    s.step(np.array([W, W]), np.array([0, -1]))       # robot 0 is not on 4: nothing done
    assert s.finished == 0 and len(s.pool) == 2
    s.pos[0] = 4                                      # stand on task 0's errand
    s.step(np.array([W, W]), np.array([0, -1]))
    assert s.finished == 1
    assert sorted((t.id, t.errands) for t in s.pool) == [(1, (7,)), (2, (9,))]
    s.pos[0] = 7
    s.step(np.array([W, W]), np.array([1, -1]))
    # task 3 visits line 3 mod 3 = line 0 again
    assert sorted((t.id, t.errands) for t in s.pool) == [(2, (9,)), (3, (4,))] and s.revealed == 4


def test_an_errand_is_done_when_its_robot_stands_on_it_and_the_task_after_the_last():
    s = sim([0], tasks=[(1, 2)], reveal=1)
    s.step(np.array([F]), np.array([0]))
    t = s.pool.open[0]
    assert t.opened and t.next_errand == 1 and s.finished == 0
    assert s.events == [(1, 0, 0, 1)]       # (timestep, robot, task, errands reached)
    s.step(np.array([F]), np.array([0]))
    assert s.finished == 1 and s.assignment.tolist() == [-1] and s.finished_at == [2]


def test_an_opened_task_is_never_given_to_another_robot():
    s = sim([0, 8], tasks=[(1, 11), (10,)], reveal=2)
    s.step(np.array([F, W]), np.array([0, -1]))      # robot 0 opens task 0
    assert s.pool.open[0].opened
    rep = s.step(np.array([W, W]), np.array([-1, 0]))
    assert rep.schedule_refused and s.assignment.tolist() == [0, -1]
    assert s.output()["numScheduleErrors"] == len(s.schedule_errors) >= 1
    assert s.step(np.array([W, W]), np.array([1, -1])).schedule_refused, "nor may its robot drop it"
    # an unopened task moves freely
    s2 = sim([0, 8], tasks=[(11,), (10,)], reveal=2)
    s2.step(np.array([W, W]), np.array([0, -1]))
    assert not s2.step(np.array([W, W]), np.array([-1, 0])).schedule_refused
    assert s2.assignment.tolist() == [-1, 0]


def test_one_task_for_two_robots_is_refused():
    s = sim([0, 8], tasks=[(11,), (10,)], reveal=2)
    assert s.step(np.array([W, W]), np.array([0, 0])).schedule_refused


def test_the_four_neighbour_model_moves_by_direction():
    s = sim([0], model=MAPF)
    s.step(np.array([1]))                     # south: 0 -> 4
    assert s.pos.tolist() == [4] and s.head.tolist() == [0]
    rep = s.step(np.array([0]))               # east: 4 -> 5, the obstacle
    assert rep.invalid and s.pos.tolist() == [4]
    s.step(np.array([MOVE_WAIT]))
    assert s.pos.tolist() == [4] and s.invalid_steps == 1
    assert s.output()["actualPaths"] == ["D,W,W"]


def test_check_actions_rejects_unknown_codes():
    with pytest.raises(ValueError, match="action codes"):
        check_actions(G, np.array([0]), np.array([0]), np.array([7]))


def test_output_json_has_the_start_kit_fields_and_replays_with_its_count():
    s = sim([0, 8], tasks=[(1, 3), (9,), (2,)], reveal=2)
    plan = [([F, F], [0, 1]), ([F, W], [0, 1]), ([F, W], [0, 1]), ([W, W], [1, 2])]
    for acts, sched in plan:
        s.step(np.array(acts), np.array(sched), plan_time_s=0.001)
    out = s.output()
    for key in ("actionModel", "version", "teamSize", "start", "numTaskFinished", "sumOfCost", "makespan",
                "actualPaths", "plannerPaths", "plannerTimes", "errors", "events", "tasks", "actualSchedule",
                "plannerSchedule", "numPlannerErrors", "numScheduleErrors", "numEntryTimeouts"):
        assert key in out, key
    assert out["start"] == [[0, 0, "E"], [2, 0, "E"]]
    assert out["actualPaths"][0] == "F,F,F,W" and out["makespan"] == 4
    assert out["tasks"][0] == [0, 0, [0, 1, 0, 3]]
    assert out["numTaskFinished"] == s.finished == 2
    again = replay(G, [(1, 3), (9,), (2,)], 2, out)
    assert again.finished == out["numTaskFinished"] and again.invalid_steps == 0


def test_schedule_entries_take_effect_at_the_next_timestep_and_a_robot_that_loses_its_task_gets_minus_one():
    s = sim([0, 8], tasks=[(3, 11), (9,), (2,)], reveal=2)    # tasks 0 and 1 open
    s.step(np.array([W, W]), np.array([0, 1]))               # step 0: adopted, in effect at timestep 1
    s.step(np.array([W, W]), np.array([1, 0]))               # unopened tasks swap robots
    s.step(np.array([W, W]), np.array([-1, 0]))              # robot 0 keeps nothing
    assert s.output()["actualSchedule"] == ["1:0,2:1,3:-1", "1:1,2:0"]
    again = replay(G, [(3, 11), (9,), (2,)], 2, s.output())
    assert again.assignment.tolist() == s.assignment.tolist() == [-1, 0]
