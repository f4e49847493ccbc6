"""rce_fleet.lifelong.pp, .parallel and .oneshot: prioritized planning for one-shot MAPF (valid
paths: no vertex or swap conflict, one-cell moves, every agent at its goal and staying there),
its order by aisle depth, its failure, and the LaCAM fallback of plan_one_shot; LaCAM and LNS
on two processes, the replay of a worker's changes, and the loss of a forked process."""
from __future__ import annotations

import itertools
import os
import signal
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


def crowded(seed: int, side: int, blocked: float, n: int) -> tuple[LifelongGrid, np.ndarray, np.ndarray]:
    """A random ``side`` x ``side`` grid with a share ``blocked`` of obstacles, and ``n`` agents
    with distinct starts and goals drawn from the part connected to the first free cell."""
    rng = np.random.default_rng(seed)
    g = LifelongGrid(rng.random((side, side)) > blocked)
    cells = np.flatnonzero(g.flat)
    reach = DistanceCache(g).from_source(int(cells[0]))
    pick = rng.choice(cells[reach[cells] < UNREACHABLE], 2 * n, replace=False)
    return g, pick[:n], pick[n:]


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
    g, starts, goals = crowded(5, 16, 0.15, 40)
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
    # 2 agents on 7 cells and a corridor of 5: a crowd, so LaCAM along its lane takes over
    assert out["solved"] and out["initial"] == "lacam lanes" and out["pp_planned"] == 1
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


def test_a_replayed_change_is_applied_only_when_it_fits_and_is_not_worse():
    """Refiner.replay: another refiner's change to agent 0 that collides here with agent 1 (on a
    cell at one step, on its goal after it arrived, or by an exchange of cells) or that arrives
    later is refused and the table stays as it was; one that fits and arrives no later is
    applied."""
    from rce_fleet.lifelong.refine import Refiner
    warm_up()
    g = grid(["...",
              "...",
              "..."])
    # agent 1 goes down the middle column 1 -> 4 -> 7; agent 0 waits on 3 two steps, then 4, 5
    ref = Refiner(g, np.array([[3, 1], [3, 4], [3, 7], [4, 7], [5, 7]]), np.array([5, 7]))
    before = ref.res.occ.copy()

    def change(r, cells, goal):
        row = np.full(r.res.H, goal, dtype=np.int32)
        row[: len(cells)] = cells
        return (np.array([0]), row[None, :], np.array([len(cells)]))

    assert ref.replay([change(ref, [3, 3, 3, 3, 4, 5], 5)]) == 0   # later than its path here
    assert ref.replay([change(ref, [3, 4, 5], 5)]) == 0            # on 4 at step 1, with agent 1
    assert ref.replay([change(ref, [3, 6, 7, 8, 5], 5)]) == 0      # on 7, agent 1's goal, at step 2
    assert (ref.res.occ == before).all()
    assert ref.replay([change(ref, [3, 3, 4, 5], 5)]) == 1         # one wait less: fits
    assert ref.solution()["sum_of_costs"] == 3 + 2
    assert_valid(g, ref.solution(), [3, 1], [5, 7])
    # agent 1 goes 1 -> 5 while agent 0 leaves 5 by 6: by 1 instead, the two would exchange cells
    g = grid(["....",
              "...."])
    swap = Refiner(g, np.array([[5, 1], [6, 5], [2, 5]]), np.array([2, 5]))
    assert swap.replay([change(swap, [5, 1, 2], 2)]) == 0


def test_lns_on_two_processes_keeps_a_crowded_solution_valid_and_replays_the_workers_changes():
    from rce_fleet.lifelong.lacam import solve_lacam
    from rce_fleet.lifelong.parallel import refine_parallel
    warm_up()
    g, starts, goals = crowded(3, 12, 0.2, 30)
    res = solve_lacam(g, starts, goals, time_limit_s=30)
    assert res["solved"]
    # a clock of calls: the same number of rounds however busy the machine
    calls = itertools.count(0.0, 1e-4)
    out = refine_parallel(g, res["paths"], goals, 1.0, workers=2, round_s=0.02, clock=lambda: next(calls))
    applied, changes = out["changes"]
    assert changes > 0 and 0 < applied <= changes
    assert out["sum_of_costs"] <= res["sum_of_costs"]
    assert_valid(g, out, starts, goals)
    calls = itertools.count(0.0, 1e-3)
    shot = plan_one_shot(g, starts, goals, time_limit_s=3, workers=2, lanes=0, clock=lambda: next(calls))
    assert shot["solved"] and shot["sum_of_costs"] <= shot["first_sum_of_costs"]
    tries = dict(shot["first_tries"])          # LaCAM with seeds 0 and 1, one of them forked
    assert set(tries) == {0, 1} and shot["first_sum_of_costs"] == min(tries.values())
    assert_valid(g, shot, starts, goals)
    with pytest.raises(ValueError, match="workers"):
        refine_parallel(g, res["paths"], goals, 1.0, workers=0)


def test_forked_processes_killed_cost_their_work_and_the_main_process_carries_on():
    """kill -9 of the forked processes, from their own clock: refine_parallel counts the worker
    lost and refines on alone; plan_one_shot keeps its own LaCAM solution when the other seed's
    process dies (its sum of costs None). Both solutions valid and never worse than LaCAM's."""
    from rce_fleet.lifelong.lacam import solve_lacam
    from rce_fleet.lifelong.parallel import refine_parallel
    warm_up()
    g, starts, goals = crowded(3, 12, 0.2, 30)
    res = solve_lacam(g, starts, goals, time_limit_s=30)
    assert res["solved"]
    parent = os.getpid()

    def clock_killing():
        calls = itertools.count(0.0, 1e-4)

        def clock():
            if os.getpid() != parent:                      # a forked process, at its first look
                os.kill(os.getpid(), signal.SIGKILL)
            return next(calls)
        return clock

    out = refine_parallel(g, res["paths"], goals, 1.0, workers=2, round_s=0.02, clock=clock_killing())
    assert out["workers_lost"] == 1 and out["changes"] == (0, 0)
    assert out["sum_of_costs"] <= res["sum_of_costs"]
    assert_valid(g, out, starts, goals)
    shot = plan_one_shot(g, starts, goals, time_limit_s=3, workers=2, lanes=0, clock=clock_killing())
    assert shot["solved"] and dict(shot["first_tries"])[1] is None
    assert_valid(g, shot, starts, goals)


AISLES = ["..............",
          ".@@@@.@@@@.@@.",
          "..............",
          ".@@@@.@@@@.@@.",
          ".............."]


def test_lacam_along_one_way_lanes_in_a_crowd_with_scatter_as_the_fallback():
    """In a crowd on a map of one-cell corridors plan_one_shot's first solution is LaCAM along
    one-way lanes (restarted until a seed solves, on one process or two); when none solves
    within its share, LaCAM with scatter; below the density, or on a map without corridors,
    the lanes do not run. Every solution valid, every agent at its goal."""
    from rce_fleet.lifelong.guidance import lane_costs
    from rce_fleet.lifelong.lacam import solve_lacam
    warm_up()
    g = grid(AISLES)
    rng = np.random.default_rng(4)
    pick = rng.choice(np.flatnonzero(g.flat), 30, replace=False)
    starts, goals = pick[:15], pick[15:]                       # 15 agents on 50 free cells
    cache = DistanceCache(g)                                   # empty: still the one solve_lacam fills
    guide = DistanceCache(g, cost=lane_costs(g, against=2))
    res = solve_lacam(g, starts, goals, time_limit_s=30, cache=cache, guide=guide)
    assert res["solved"] and len(cache) == 15 and len(guide) == 15
    assert_valid(g, res, starts, goals)
    # in the tail (here from the start: all agents) PIBT follows the shortest ways, as unguided
    plain = solve_lacam(g, starts, goals, time_limit_s=30, cache=cache, seed=3)
    tail = solve_lacam(g, starts, goals, time_limit_s=30, cache=cache, guide=guide, tail_share=1.0, seed=3)
    lanes = solve_lacam(g, starts, goals, time_limit_s=30, cache=cache, guide=guide, tail_share=0.0, seed=3)
    assert plain["paths"].shape == tail["paths"].shape and (plain["paths"] == tail["paths"]).all()
    assert lanes["paths"].shape != plain["paths"].shape or (lanes["paths"] != plain["paths"]).any()
    calls = itertools.count(0.0, 1e-4)
    out = plan_one_shot(g, starts, goals, time_limit_s=1, clock=lambda: next(calls))
    assert out["solved"] and out["initial"] == "lacam lanes" and out["first_tries"] == []
    seeds = [s for s, _ in out["lane_tries"]]
    assert seeds == list(range(len(seeds)))                    # one process: seeds 0, 1, ... in turn
    assert [c for _, c in out["lane_tries"][:-1]] == [None] * (len(seeds) - 1)
    assert out["first_sum_of_costs"] == out["lane_tries"][-1][1]
    assert out["sum_of_costs"] <= out["first_sum_of_costs"]
    assert_valid(g, out, starts, goals)
    two = plan_one_shot(g, starts, goals, time_limit_s=1, workers=2, clock=lambda: next(calls))
    assert two["solved"] and two["initial"] == "lacam lanes"
    assert two["first_sum_of_costs"] in [c for _, c in two["lane_tries"]]
    assert_valid(g, two, starts, goals)
    # no time for the lanes: LaCAM with scatter takes over
    fallback = plan_one_shot(g, starts, goals, time_limit_s=1, lane_share=0.0, clock=lambda: next(calls))
    assert fallback["solved"] and fallback["initial"] == "lacam"
    assert fallback["lane_tries"] == [] and len(fallback["first_tries"]) == 1
    assert_valid(g, fallback, starts, goals)
    few = plan_one_shot(g, starts[:5], goals[:5], time_limit_s=1, clock=lambda: next(calls))   # 0.1 per cell
    assert few["solved"] and few["initial"] == "lacam" and few["lane_tries"] == []
    open_floor = grid(["......"] * 6)
    pick = rng.choice(36, 20, replace=False)
    flat = plan_one_shot(open_floor, pick[:10], pick[10:], time_limit_s=1, clock=lambda: next(calls))
    assert flat["solved"] and flat["initial"] == "lacam" and flat["lane_tries"] == []
    assert_valid(open_floor, flat, pick[:10], pick[10:])


def test_lacam_restarts_with_new_seeds_under_growing_node_caps_until_one_solves():
    """race_lacam on one process: runs capped below what the instance needs end unsolved, the
    next seed gets a cap ``growth`` times larger, and the first run that solves is the answer;
    a cap the instance never fits under ends unsolved when the time is spent."""
    from rce_fleet.lifelong.parallel import race_lacam
    warm_up()
    g = grid(AISLES)
    pick = np.random.default_rng(4).choice(np.flatnonzero(g.flat), 30, replace=False)
    starts, goals = pick[:15], pick[15:]
    calls = itertools.count(0.0, 1e-4)
    res = race_lacam(g, starts, goals, 3.0, seed=7, cap=0.05, growth=2.0, clock=lambda: next(calls))
    seeds = [s for s, _ in res["tries"]]
    assert res["solved"] and len(seeds) > 1 and seeds == list(range(7, 7 + len(seeds)))
    assert [c for _, c in res["tries"]] == [None] * (len(seeds) - 1) + [res["sum_of_costs"]]
    assert_valid(g, res, starts, goals)
    never = race_lacam(g, starts, goals, 0.05, cap=0.0, clock=lambda: next(calls))
    assert not never["solved"] and never["sum_of_costs"] is None
    assert len(never["tries"]) > 1 and all(c is None for _, c in never["tries"])
    with pytest.raises(ValueError, match="growth"):
        race_lacam(g, starts, goals, 1.0, growth=0.5)


def race_clock(parent: int, loser: str):
    """A clock of calls for race_lacam's forked processes: the first to look at it runs; the
    others ``loser``: "block" (search forever) or "kill" (kill -9 themselves); "kill all"
    kills every forked process."""
    import multiprocessing
    import threading
    first = multiprocessing.get_context("fork").Value("i", 0)
    calls = itertools.count(0.0, 1e-4)

    def clock() -> float:
        me = os.getpid()
        if me != parent:
            with first.get_lock():
                if first.value == 0:
                    first.value = me
            if loser == "kill all" or first.value != me:
                if loser == "block":
                    threading.Event().wait()
                os.kill(me, signal.SIGKILL)
        return next(calls)
    return clock


@pytest.mark.parametrize("loser", ["block", "kill"])
def test_lacam_race_on_two_processes_takes_the_first_solution_and_outlives_a_process_killed(loser):
    """race_lacam on two forked processes: the first solution is the answer and the process
    still searching is stopped (here one whose clock never returns), or a process that dies
    (kill -9) only loses its runs; when both die, no solution and plan_one_shot's LaCAM with
    scatter takes over."""
    from rce_fleet.lifelong.parallel import race_lacam
    warm_up()
    g = grid(AISLES)
    pick = np.random.default_rng(4).choice(np.flatnonzero(g.flat), 30, replace=False)
    starts, goals = pick[:15], pick[15:]
    res = race_lacam(g, starts, goals, 3.0, workers=2, clock=race_clock(os.getpid(), loser))
    assert res["solved"] and res["tries"][-1][1] == res["sum_of_costs"]
    assert len({s % 2 for s, _ in res["tries"]}) == 1                # every run from the one process that ran
    assert all(c is None for _, c in res["tries"][:-1])
    assert_valid(g, res, starts, goals)
    none = race_lacam(g, starts, goals, 3.0, workers=2, clock=race_clock(os.getpid(), "kill all"))
    assert not none["solved"] and none["tries"] == []
    shot = plan_one_shot(g, starts, goals, time_limit_s=3, workers=2, clock=race_clock(os.getpid(), "kill all"))
    assert shot["solved"] and shot["initial"] == "lacam" and shot["lane_tries"] == []
    assert_valid(g, shot, starts, goals)


def test_the_restarts_bench_reports_every_run_and_the_runs_within_the_cap(tmp_path):
    """``bench/lacam_restarts.py`` end to end on a small cut: each LaCAM run along the lanes
    (solved or not, its nodes over the longest distance, its ratio to the lower bound), the
    runs counted within the first cap, the rest and the unsolved, and the plot."""
    import json
    import subprocess
    import sys
    bench = Path(__file__).resolve().parents[2] / "bench" / "lacam_restarts.py"
    out, png = tmp_path / "r.json", tmp_path / "r.png"
    p = subprocess.run([sys.executable, str(bench), "--agents", "300", "--scen-seeds", "1", "--seeds", "3",
                        "--json", str(out), "--plot", str(png)], capture_output=True, text=True, timeout=300,
                       cwd=tmp_path)
    assert p.returncode == 0, (p.stdout + p.stderr)[-3000:]
    res = json.loads(out.read_text())
    assert [r["scenario"] for r in res["rows"]] == ["random-1", "seed 1"]
    for row in res["rows"]:
        assert [r["seed"] for r in row["runs"]] == [0, 1, 2]
        assert sum(row["summary"].values()) == 3 and row["longest"] > 0
        for r in row["runs"]:
            assert (r["ratio"] >= 1.0 and r["nodes"] > 1.0) if r["solved"] else r["ratio"] is None
            assert r["nodes"] <= res["max_cap"] + 1
        assert row["summary"]["fast"] == sum(r["solved"] and r["nodes"] <= res["cap"] for r in row["runs"])
    assert png.stat().st_size > 1000 and "solved within 3x" in p.stdout
