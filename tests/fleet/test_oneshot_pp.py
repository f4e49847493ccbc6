"""rce_fleet.lifelong.pp and .oneshot: prioritized planning for one-shot MAPF (valid paths: no
vertex or swap conflict, one-cell moves, every agent at its goal and staying there), its
order by aisle depth, its failure, and the LaCAM fallback of plan_one_shot."""
from __future__ import annotations

import itertools
import time
from pathlib import Path

import numpy as np
import pytest

from rce_fleet.lifelong import MAPF, DistanceCache, LifelongGrid, check_actions
from rce_fleet.lifelong.kernels import MOVE_WAIT, UNREACHABLE
from rce_fleet.lifelong.kernels import warm_up as warm_kernels
from rce_fleet.lifelong.oneshot import plan_one_shot
from rce_fleet.lifelong.pp import aisle_depth, solve_pp
from rce_fleet.lifelong.refine import warm_up
from rce_fleet.planning import load_movingai_map, load_movingai_scen

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
WAREHOUSE = DATA / "mapf" / "warehouse-10-20-10-2-1"


def grid(rows: list[str]) -> LifelongGrid:
    return LifelongGrid(np.array([[ch == "." for ch in r] for r in rows]))


def assert_valid(g: LifelongGrid, res: dict, starts, goals) -> None:
    """The solution is valid under the simulator's rules, every agent ends on its goal and
    stays there from its last arrival on, and sum of costs is those arrivals summed."""
    paths = res["paths"]
    starts, goals = np.asarray(starts), np.asarray(goals)
    assert (paths[0] == starts).all() and (paths[-1] == goals).all()
    n = paths.shape[1]
    head = np.zeros(n, dtype=np.int64)
    for a, b in zip(paths[:-1], paths[1:], strict=True):
        moved = np.flatnonzero(a != b)
        hit = g.nbr[a[moved]] == b[moved][:, None]
        assert hit.any(axis=1).all(), "a move of more than one cell"
        act = np.full(n, MOVE_WAIT, dtype=np.int64)
        act[moved] = np.argmax(hit, axis=1)
        errors = check_actions(g, a, head, act, MAPF)[2]
        assert not errors, errors                      # vertex and swap conflicts
    off = paths != goals[None, :]
    arrival = np.where(off.any(axis=0), paths.shape[0] - np.argmax(off[::-1], axis=0), 0)
    for i in range(n):
        assert (paths[arrival[i]:, i] == goals[i]).all()
    assert res["sum_of_costs"] == int(arrival.sum())


def test_aisle_depth_is_the_way_to_the_nearest_junction():
    g = grid(["......",
              "@@.@@@",
              "@@.@@@",
              "@@.@@@"])
    d = aisle_depth(g).reshape(4, 6)
    assert d[0, 2] == 0 and d[0, 0] == 2 and d[0, 5] == 3     # the junction; the corridor's ends
    assert d[3, 2] == 3                                        # the dead end's bottom
    assert d[1, 0] == -1                                       # an obstacle


def test_pp_fills_a_dead_end_deepest_goal_first_and_keeps_every_rule():
    warm_kernels()
    warm_up()
    g = grid(["......",
              "......",
              "@@.@@@",
              "@@.@@@",
              "@@.@@@"])
    # three agents park in the dead end below cell 8: the deepest goal (26) must be taken first,
    # though its agent is the nearest to it
    starts, goals = [7, 0, 11], [26, 14, 20]
    res = solve_pp(g, np.array(starts), np.array(goals), time_limit_s=5)
    assert res["solved"] and res["restarts"] == 0 and res["planned"] == 3
    assert_valid(g, res, starts, goals)


def test_pp_on_a_crowded_random_grid_is_valid_and_near_the_lower_bound():
    rng = np.random.default_rng(5)
    g = LifelongGrid(rng.random((16, 16)) > 0.15)
    cells = np.flatnonzero(g.flat)
    reach = DistanceCache(g).from_source(int(cells[0]))
    big = cells[reach[cells] < UNREACHABLE]
    pick = rng.choice(big, 80, replace=False)
    starts, goals = pick[:40], pick[40:]
    res = solve_pp(g, starts, goals, time_limit_s=10, seed=1)
    assert res["solved"]
    assert_valid(g, res, starts, goals)
    cache = DistanceCache(g)
    lb = sum(int(cache.table[cache.slot(int(b)), a]) for a, b in zip(starts, goals, strict=True))
    assert lb <= res["sum_of_costs"] <= 1.5 * lb


def test_pp_restarts_with_the_failed_agent_first_and_the_fallback_is_lacam():
    g = grid(["......",
              "@@.@@@"])
    # two agents swap the corridor's ends, one waits in the bay below cell 2. The deeper goal's
    # agent (0) goes first and runs over agent 1 on its way; with agent 1 first, agent 0 waits
    # in the bay
    starts, goals = [0, 5], [5, 0]
    warm_up()
    once = solve_pp(g, np.array(starts), np.array(goals), time_limit_s=0)
    assert not once["solved"] and once["planned"] == 1 and once["restarts"] == 0
    assert once["paths"].shape[1] == 2 and (once["paths"][0] == starts).all()
    res = solve_pp(g, np.array(starts), np.array(goals), time_limit_s=30, clock=time.process_time)
    assert res["solved"] and res["restarts"] == 1
    assert_valid(g, res, starts, goals)
    # a clock of calls, not of CPU: a kernel's first call (numba compiles it) must not use up the budget
    calls = itertools.count(0.0, 1e-3)
    out = plan_one_shot(g, np.array(starts), np.array(goals), time_limit_s=1.0, initial="pp", pp_share=0.0,
                        clock=lambda: next(calls))
    assert out["solved"] and out["initial"] == "lacam" and out["pp_planned"] == 1
    assert_valid(g, out, starts, goals)
    with pytest.raises(ValueError, match="share"):
        solve_pp(g, np.array([0, 0]), np.array([1, 2]))
    with pytest.raises(ValueError, match="initial"):
        plan_one_shot(g, np.array(starts), np.array(goals), initial="cbs")


def test_pp_solves_400_agents_on_the_movingai_warehouse_and_lns_keeps_it_valid():
    graph = load_movingai_map(WAREHOUSE.with_suffix(".map"))
    scen = load_movingai_scen(Path(f"{WAREHOUSE}-random-1.scen"), graph)[:400]
    g = LifelongGrid.from_graph(graph)
    starts = np.array([s for s, _ in scen])
    goals = np.array([t for _, t in scen])
    res = solve_pp(g, starts, goals, time_limit_s=60)
    assert res["solved"]
    assert_valid(g, res, starts, goals)
    out = plan_one_shot(g, starts, goals, time_limit_s=3.0, initial="pp", pp_share=0.9,
                        clock=time.process_time)
    assert out["solved"] and out["initial"] == "pp"
    assert out["sum_of_costs"] <= out["first_sum_of_costs"]
    assert_valid(g, out, starts, goals)
