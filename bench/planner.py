"""Benchmark the fleet planner (rce_fleet.planning).

1. MovingAI MAPF instance ``warehouse-10-20-10-2-1`` (161 x 63 cells) with the
   first K agents of ``...-random-1.scen`` for K = 10, 50, 100, 200: planning
   time, conflicts (must be 0), sum of costs (arrival steps), makespan, the
   lower bound (sum of individual shortest paths) and the ratio.
2. The same instance one-shot up to 400 and 1000 agents (``--lacam-agents``) by
   rce_fleet.lifelong.oneshot.plan_one_shot: a first solution by LaCAM (``--initial lacam``, the
   default) or by prioritized planning with LaCAM as the fallback (``--initial pp``), then LNS
   refinement (rce_fleet.lifelong.refine; on ``--workers`` processes, rce_fleet.lifelong.parallel)
   in the time left of ``--time-limit`` (default 5 s):
   which solver gave the first solution, its time and quality, final time, agents at their
   goals, conflicts, sum of costs against the lower bound; the same on random scenarios of the
   map (``--scen-seeds``: uniform distinct starts and goals, as the scenarios the project has
   not seen). Plus the live fleet's sizes (``--live-sizes``): FleetPlanner against LaCAM on
   the same missions.
3. One re-plan after blocking a cell on the ``warehouse.yaml`` cell grid with
   10 robots.

Usage::

    .venv/bin/python bench/planner.py [--agents 10 50 100 200] [--repeat 3]
        [--lacam-agents 10 50 100 200 400 1000] [--time-limit 5] [--cpu-budget] [--scen-seeds 1]
        [--initial {lacam,pp}] [--workers 1] [--lanes 2]
        [--data ../shared/data] [--map FILE.map --scen FILE.scen] [--lacam3 BIN] [--json PATH] [--plot PATH]

``--lacam3 BIN`` runs lacam3 (Okumura AAMAS-24, C++, built from its repository;
bench/lacam3_peer.py) on the same one-shot instances with the same time limit, as the peer
in the same run.

``--map``/``--scen`` run another MovingAI instance (maps and scenarios in either form of
rce_fleet.planning.movingai); an instance that is not one (too few agents, a shared start or
goal, a goal that cannot be reached) is refused naming the agent, with exit code 2.

Results go to ``bench/results/`` by default (planner.json, planner.png).
"""
from __future__ import annotations

import argparse
import json
import random
import statistics
import sys
import time
from pathlib import Path

from rce_fleet.maps.geometry import components
from rce_fleet.maps.grid import make_grid
from rce_fleet.maps.occupancy import load_map
from rce_fleet.lifelong import LifelongGrid
from rce_fleet.planning import FleetPlanner, GridGraph, check_conflicts, load_movingai_map, load_movingai_scen

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = (ROOT / ".." / "shared" / "data").resolve()
RESULTS = ROOT / "bench" / "results"


def run_mapf(graph: GridGraph, scen: list[tuple[int, int]], k: int, repeat: int) -> dict:
    """Plan the first ``k`` agents ``repeat`` times with a fresh planner; report the median time."""
    times, cpu, out = [], [], {}
    for _ in range(repeat):
        fp = FleetPlanner(graph)
        for i, (s, _) in enumerate(scen[:k]):
            fp.set_position(f"a{i}", s)
        t0, c0 = time.perf_counter(), time.process_time()
        res = fp.set_goals({f"a{i}": g for i, (_, g) in enumerate(scen[:k])})
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        paths = res.paths
        conflicts = check_conflicts(paths)
        soc = sum(len(p) - 1 for p in paths.values())
        lb = sum(int(fp.distance(s, g)) for s, g in scen[:k])
        out = {
            "agents": k,
            "conflicts": len(conflicts),
            "unreachable": len(res.unreachable),
            "reached": sum(1 for i, (_, g) in enumerate(scen[:k]) if paths[f"a{i}"][-1] == g),
            "sum_of_costs": soc,
            "makespan": max(len(p) - 1 for p in paths.values()),
            "lower_bound": lb,
            "ratio": soc / lb if lb else 1.0,
        }
    out["time_s"] = statistics.median(times)
    out["time_min_s"] = min(times)
    out["cpu_s"] = statistics.median(cpu)
    return out


def check_instance(graph: GridGraph, scen: list[tuple[int, int]], k: int) -> None:
    """Raise ValueError unless the first ``k`` agents of ``scen`` are a MAPF instance: that many
    agents, distinct starts, distinct goals, each goal in its start's connected free cells
    (agent i is the scenario's (i + 1)-th problem; x column, y row)."""
    from scipy import ndimage
    if k > len(scen):
        raise ValueError(f"the scenario has {len(scen)} agents, --agents/--lacam-agents ask for {k}")
    labels = ndimage.label(graph.free)[0].ravel()

    def xy(c: int) -> str:
        return f"(x {c % graph.cols}, y {c // graph.cols})"
    for end, what in ((0, "start"), (1, "goal")):
        first: dict[int, int] = {}
        for i, pair in enumerate(scen[:k]):
            if pair[end] in first:
                raise ValueError(f"agents {first[pair[end]]} and {i} share the {what} {xy(pair[end])}")
            first[pair[end]] = i
    for i, (s, g) in enumerate(scen[:k]):
        if labels[s] != labels[g]:
            raise ValueError(f"agent {i}: the goal {xy(g)} cannot be reached from the start {xy(s)}")


def random_scen(graph: GridGraph, k: int, seed: int) -> list[tuple[int, int]]:
    """``k`` (start, goal) pairs drawn uniformly, all starts distinct and all goals distinct, in
    the largest connected set of free cells (as MovingAI's random scenarios, without their
    distance buckets)."""
    import numpy as np

    from rce_fleet.lifelong import LifelongGrid
    from rce_fleet.lifelong.kernels import UNREACHABLE, bfs_fill
    grid = LifelongGrid.from_graph(graph)
    dist = np.empty(grid.n_cells, dtype=np.uint16)
    queue = np.empty(grid.n_cells, dtype=np.int32)
    comps, left = [], set(grid.free_cells().tolist())
    while left:                                  # components by BFS from an unvisited free cell
        bfs_fill(grid.nbr, next(iter(left)), dist, queue)
        comp = set(np.flatnonzero(dist < UNREACHABLE).tolist())
        comps.append(comp)
        left -= comp
    cells = np.array(sorted(max(comps, key=len)))
    rng = np.random.default_rng(seed)
    return list(zip(rng.choice(cells, k, replace=False).tolist(), rng.choice(cells, k, replace=False).tolist(),
                    strict=True))


def count_conflicts(grid, paths) -> int:
    """Errors of a one-shot solution ((T+1, n) cells) under the simulator's rules
    (rce_fleet.lifelong.simulator.check_actions, 4-neighbour moves): moves that are not one
    step, vertex conflicts and swap conflicts, summed over the steps."""
    import numpy as np

    from rce_fleet.lifelong import MAPF
    from rce_fleet.lifelong.kernels import MOVE_WAIT
    from rce_fleet.lifelong.simulator import check_actions
    n = paths.shape[1]
    head = np.zeros(n, dtype=np.int64)
    errors = 0
    for a, b in zip(paths[:-1], paths[1:], strict=True):
        act = np.full(n, MOVE_WAIT, dtype=np.int64)
        moved = np.flatnonzero(a != b)
        hit = grid.nbr[a[moved]] == b[moved][:, None]
        errors += int((~hit.any(axis=1)).sum())
        act[moved] = np.argmax(hit, axis=1)
        errors += len(check_actions(grid, a, head, act, MAPF)[2])
    return errors


SHARE = 0.96     # of the time limit for plan_one_shot; the rest covers the pipeline's own exit (the
                 # forked worker's last round and join, the solution's assembly: 0.01 - 0.03 s measured)


def run_lacam(graph: GridGraph, scen: list[tuple[int, int]], k: int, time_limit_s: float,
              scenario: str = "random-1", cpu_budget: bool = False, initial: str = "lacam",
              workers: int = 1, lanes: int = 2) -> dict:
    """The first ``k`` agents one-shot by rce_fleet.lifelong.oneshot.plan_one_shot (a first
    solution by ``initial``, PP with LaCAM as the fallback or LaCAM alone, then LNS) within
    ``SHARE`` x ``time_limit_s`` of wall time, or of this process's CPU time with ``cpu_budget``
    (what an idle machine would give when other work shares the cores); LNS on ``workers``
    processes, each counting its own clock (``worker_cpu_s``: the workers' CPU); ``lanes``:
    plan_one_shot's lane-guided LaCAM tries (a move against a lane costs 1 + ``lanes``; 0 off)."""
    import numpy as np

    from rce_fleet.lifelong import DistanceCache, LifelongGrid
    from rce_fleet.lifelong.kernels import warm_up as warm_kernels
    from rce_fleet.lifelong.lacam import solve_lacam
    from rce_fleet.lifelong.oneshot import plan_one_shot
    from rce_fleet.lifelong.refine import warm_up

    grid = LifelongGrid.from_graph(graph)
    starts = np.array([s for s, _ in scen[:k]], dtype=np.int64)
    goals = np.array([g for _, g in scen[:k]], dtype=np.int64)
    solve_lacam(grid, starts[:2], goals[:2], scatter_share=0.5)  # compile outside the clock
    warm_kernels()
    warm_up()
    cache = DistanceCache(grid, max_bytes=2 * grid.n_cells * (k + 16))
    clock = time.process_time if cpu_budget else time.perf_counter
    t0, c0 = time.perf_counter(), time.process_time()
    res = plan_one_shot(grid, starts, goals, SHARE * time_limit_s, cache=cache, initial=initial, workers=workers,
                        lanes=lanes, clock=clock)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    paths = res["paths"]
    conflicts = count_conflicts(grid, paths)
    lb = int(sum(int(cache.table[cache.slot(int(g)), s]) for s, g in zip(starts, goals, strict=True)))
    return {"agents": k, "scenario": scenario, "planner": f"{initial} + LNS", "first_solver": res["initial"],
            "pp_planned": res["pp_planned"], "time_s": wall, "cpu_s": cpu,
            "time_limit_s": time_limit_s, "budget": "cpu" if cpu_budget else "wall",
            "conflicts": conflicts, "reached": int((paths[-1] == goals).sum()), "solved": res["solved"],
            "sum_of_costs": res["sum_of_costs"], "makespan": res["makespan"], "lower_bound": lb,
            "ratio": res["sum_of_costs"] / lb if lb else 1.0,
            "first_solution_s": res["first_time_s"], "first_ratio": res["first_sum_of_costs"] / lb if lb else 1.0,
            "lns_iterations": res["lns_iterations"], "workers": workers, "worker_cpu_s": res["worker_cpu_s"],
            "first_tries": [(s, c / lb if c is not None and lb else None) for s, c in res["first_tries"]],
            "lane_tries": [(s, c / lb if c is not None and lb else None) for s, c in res["lane_tries"]]}


def run_live_sizes(map_yaml: Path | None, cell_m: float, sizes: list[int], seeds: int,
                   time_limit_s: float) -> list[dict]:
    """The live fleet's sizes: FleetPlanner against LaCAM on the same random missions (starts and
    goals in the largest free component) of the lab grid (or ``map_yaml``'s); medians over seeds."""
    import numpy as np

    from rce_fleet.maps.lab_map import lab_map
    from rce_fleet.lifelong import LifelongGrid
    from rce_fleet.lifelong.lacam import solve_lacam

    grid = make_grid(load_map(map_yaml), cell_m=cell_m) if map_yaml else make_grid(lab_map())
    graph = GridGraph.from_cellgrid(grid)
    lg = LifelongGrid.from_graph(graph)
    best = sorted(components(grid)[0])
    solve_lacam(lg, np.array(best[:1]), np.array(best[1:2]))          # compile outside the clock
    out = []
    for k in sizes:
        if 2 * k > len(best):
            continue
        rec: dict[str, list] = {"fp_s": [], "fp_soc": [], "fp_reached": [], "lc_s": [], "lc_soc": [], "lc_reached": [],
                                "lb": []}
        for seed in range(seeds):
            cells = random.Random(seed).sample(best, 2 * k)
            starts, goals = cells[:k], cells[k:]
            fp = FleetPlanner(graph)
            for i, s in enumerate(starts):
                fp.set_position(f"Robot{i + 1}", s)
            t0 = time.perf_counter()
            res = fp.set_goals({f"Robot{i + 1}": g for i, g in enumerate(goals)})
            rec["fp_s"].append(time.perf_counter() - t0)
            rec["fp_soc"].append(sum(len(p) - 1 for p in res.paths.values()))
            rec["fp_reached"].append(sum(1 for i, g in enumerate(goals) if res.paths[f"Robot{i + 1}"][-1] == g))
            t0 = time.perf_counter()
            lc = solve_lacam(lg, np.array(starts), np.array(goals), time_limit_s=time_limit_s)
            rec["lc_s"].append(time.perf_counter() - t0)
            rec["lc_soc"].append(lc["sum_of_costs"])
            rec["lc_reached"].append(int((lc["paths"][-1] == np.array(goals)).sum()))
            rec["lb"].append(sum(int(fp.distance(s, g)) for s, g in zip(starts, goals, strict=True)))
        lb = sum(rec["lb"])
        out.append({"map": map_yaml.name if map_yaml else "lab (generated)", "grid": f"{grid.rows}x{grid.cols}",
                    "robots": k, "seeds": seeds,
                    "fleetplanner_ms": statistics.median(rec["fp_s"]) * 1e3,
                    "lacam_ms": statistics.median(rec["lc_s"]) * 1e3,
                    "fleetplanner_ratio": sum(rec["fp_soc"]) / lb, "lacam_ratio": sum(rec["lc_soc"]) / lb,
                    "fleetplanner_reached": sum(rec["fp_reached"]), "lacam_reached": sum(rec["lc_reached"]),
                    "missions": k * seeds})
    return out


def print_live(rows: list[dict]) -> None:
    """The live-size comparison as a table."""
    from rich.console import Console
    from rich.table import Table
    t = Table(title="Live fleet sizes: FleetPlanner (SIPP + ADG) against LaCAM (PIBT), same missions")
    for col in ("map", "grid", "robots", "seeds", "FP ms", "LaCAM ms", "FP cost/LB", "LaCAM cost/LB", "FP reached",
                "LaCAM reached"):
        t.add_column(col, justify="right")
    for r in rows:
        t.add_row(r["map"], r["grid"], str(r["robots"]), str(r["seeds"]), f"{r['fleetplanner_ms']:.1f}",
                  f"{r['lacam_ms']:.1f}", f"{r['fleetplanner_ratio']:.3f}", f"{r['lacam_ratio']:.3f}",
                  f"{r['fleetplanner_reached']}/{r['missions']}", f"{r['lacam_reached']}/{r['missions']}")
    Console(width=max(Console().width, 120)).print(t)


def run_block_replan(map_yaml: Path, cell_m: float, robots: int, seed: int = 1) -> dict:
    """10 robots on the warehouse.yaml grid; block a cell in the middle of robot 0's path; time the re-plan."""
    m = load_map(map_yaml)
    t0 = time.perf_counter()
    grid = make_grid(m, cell_m=cell_m)
    t_grid = time.perf_counter() - t0
    graph = GridGraph.from_cellgrid(grid)
    best = components(grid)[0]          # the largest connected set of free cells
    rng = random.Random(seed)
    cells = rng.sample(sorted(best), 2 * robots)
    fp = FleetPlanner(graph)
    for i in range(robots):
        fp.set_position(f"Robot{i + 1}", cells[i])
    t0 = time.perf_counter()
    fp.set_goals({f"Robot{i + 1}": cells[robots + i] for i in range(robots)})
    t_plan = time.perf_counter() - t0
    path = fp.paths["Robot1"]
    occupied = set(fp.positions.values()) | {g for g in fp.goals.values() if g is not None}
    candidates = [c for c in path[len(path) // 3: 2 * len(path) // 3] if c not in occupied] or \
                 [c for c in path if c not in occupied]
    cell = candidates[len(candidates) // 2]
    t0 = time.perf_counter()
    cancelled = fp.block(cell)
    t_block = time.perf_counter() - t0
    res = fp.last_result
    return {
        "map": str(map_yaml.name), "cell_m": cell_m, "grid": f"{grid.rows}x{grid.cols}",
        "free_cells": len(grid.free_cells()), "robots": robots, "grid_build_s": t_grid,
        "initial_plan_s": t_plan, "blocked_cell": cell, "cancelled": sorted(cancelled),
        "changed": sorted(res.changed), "full_replan": res.full, "replan_s": t_block,
        "conflicts": len(check_conflicts(fp.paths)), "unreachable": len(fp.unreachable),
    }


def print_lacam(rows: list[dict], name: str = "warehouse-10-20-10-2-1") -> None:
    """The LaCAM rows as a table (``name``: the MovingAI map's)."""
    from rich.console import Console
    from rich.table import Table
    t = Table(title=f"One-shot (first solution, then LNS) on MovingAI {name}")
    for col in ("scenario", "agents", "first by", "first (s)", "first ratio", "time (s)", "cpu (s)", "workers' cpu",
                "limit (s)",
                "conflicts", "reached", "sum of costs", "lower bound", "ratio", "makespan", "LNS iters"):
        t.add_column(col, justify="right")
    for r in rows:
        t.add_row(r["scenario"], str(r["agents"]), r["first_solver"], f"{r['first_solution_s']:.3f}",
                  f"{r['first_ratio']:.3f}",
                  f"{r['time_s']:.3f}", f"{r['cpu_s']:.3f}", f"{r['worker_cpu_s']:.3f}",
                  f"{r['time_limit_s']:.0f}", str(r["conflicts"]), f"{r['reached']}/{r['agents']}",
                  str(r["sum_of_costs"]), str(r["lower_bound"]), f"{r['ratio']:.3f}", str(r["makespan"]),
                  str(r["lns_iterations"]))
    Console(width=max(Console().width, 130)).print(t)


def run_peer(binary: Path, graph: GridGraph, scen: list[tuple[int, int]], k: int, time_limit_s: float,
             scenario: str) -> dict:
    """lacam3 (bench/lacam3_peer.py) on the first ``k`` agents of ``scen``; its sum of costs
    against the same lower bound as rce's rows (the sum of BFS distances)."""
    from lacam3_peer import run_lacam3
    d = graph.distances_to([g for _, g in scen[:k]])
    dist = [int(d[i, s]) for i, (s, _) in enumerate(scen[:k])]
    r = run_lacam3(binary, graph.free, scen[:k], dist, time_limit_s)
    lb = sum(dist)
    if r["lower_bound"] is not None and r["lower_bound"] != lb:
        raise RuntimeError(f"lacam3's lower bound {r['lower_bound']} is not the sum of BFS distances {lb}")
    return {"agents": k, "scenario": scenario, "time_limit_s": time_limit_s, **r, "lower_bound": lb,
            "ratio": r["sum_of_costs"] / lb if r["solved"] else None,
            "first_loss_ratio": r["first_sum_of_loss"] / lb if r["first_sum_of_loss"] else None}


def print_peer(peer: list[dict], ours: list[dict]) -> None:
    """lacam3's rows beside rce's on the same instances."""
    from rich.console import Console
    from rich.table import Table
    mine = {(r["scenario"], r["agents"]): r for r in ours}

    def fmt(v: float | None) -> str:
        return "-" if v is None else f"{v:.3f}"
    t = Table(title="lacam3 (C++, 2 cores, wall-clock limit) on the same instances, sum of costs / lower bound")
    for col in ("scenario", "agents", "limit (s)", "lacam3 first (s)", "lacam3", "lacam3 sum of loss", "rce",
                "rce / lacam3"):
        t.add_column(col, justify="right")
    for r in peer:
        m = mine.get((r["scenario"], r["agents"]))
        loss = r["sum_of_loss"] / r["lower_bound"] if r["sum_of_loss"] else None
        t.add_row(r["scenario"], str(r["agents"]), f"{r['time_limit_s']:.0f}", fmt(r["first_solution_s"]),
                  fmt(r["ratio"]) if r["solved"] else "no solution", fmt(loss), fmt(m and m["ratio"]),
                  fmt(m["ratio"] / r["ratio"] if m and r["ratio"] else None))
    Console(width=max(Console().width, 130)).print(t)


def print_tables(rows: list[dict], block: dict | None, name: str = "warehouse-10-20-10-2-1 (random-1.scen)") -> None:
    """The results as tables (rich), or one dict a line without rich (``name``: the instance's)."""
    try:
        from rich.console import Console
        from rich.table import Table
    except ImportError:  # plain text fallback
        for r in rows:
            print(r)
        if block:
            print(block)
        return
    con = Console(width=max(Console().width, 110))
    t = Table(title=f"FleetPlanner on MovingAI {name}")
    for col in ("agents", "time (s)", "cpu (s)", "conflicts", "reached", "sum of costs", "lower bound", "ratio",
                "makespan"):
        t.add_column(col, justify="right")
    for r in rows:
        t.add_row(str(r["agents"]), f"{r['time_s']:.3f}", f"{r['cpu_s']:.3f}", str(r["conflicts"]),
                  f"{r['reached']}/{r['agents']}", str(r["sum_of_costs"]), str(r["lower_bound"]), f"{r['ratio']:.4f}",
                  str(r["makespan"]))
    con.print(t)
    if block:
        b = Table(title=f"Re-plan after block on {block['map']} ({block['grid']} cells of {block['cell_m']} m)")
        for col in ("robots", "free cells", "initial plan (ms)", "blocked cell", "cancelled",
                    "changed", "full re-plan", "re-plan (ms)", "conflicts"):
            b.add_column(col, justify="right")
        b.add_row(str(block["robots"]), str(block["free_cells"]), f"{block['initial_plan_s'] * 1e3:.1f}",
                  str(block["blocked_cell"]), ", ".join(block["cancelled"]) or "-",
                  ", ".join(block["changed"]) or "-", str(block["full_replan"]),
                  f"{block['replan_s'] * 1e3:.1f}", str(block["conflicts"]))
        con.print(b)


def plot(rows: list[dict], path: Path, lacam: list[dict] | None = None, name: str = "warehouse-10-20-10-2-1") -> None:
    """PNG at ``path``: planning time and sum of costs / lower bound against the number of agents."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ks = [r["agents"] for r in rows]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    ax1.plot(ks, [r["time_s"] for r in rows], "o-", label="FleetPlanner (SIPP + ADG)")
    if lacam:
        label = f"one-shot, {lacam[0]['planner']}"
        ax1.plot([r["agents"] for r in lacam], [r["time_s"] for r in lacam], "s", label=label)
        ax2.plot([r["agents"] for r in lacam], [r["ratio"] for r in lacam], "s", label=label)
        ax1.set_xscale("log")
        ax1.set_yscale("log")
    ax1.axhline(1.0, color="grey", ls="--", lw=0.8, label="1 s target (100 agents)")
    ax1.set_xlabel("agents")
    ax1.set_ylabel("planning time (s)")
    ax1.set_title("time to plan")
    ax1.legend()
    ax2.plot(ks, [r["ratio"] for r in rows], "o-", label="FleetPlanner (SIPP + ADG)")
    ax2.axhline(1.2, color="grey", ls="--", lw=0.8, label="1.2 x lower bound")
    ax2.set_xlabel("agents")
    ax2.set_ylabel("sum of costs / lower bound")
    ax2.set_ylim(0.95, max(1.25, max(r["ratio"] for r in rows + (lacam or [])) + 0.05))
    ax2.set_title("solution quality")
    ax2.legend()
    fig.suptitle(f"FleetPlanner, MovingAI {name}")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data directory")
    ap.add_argument("--map", type=Path, help="a MovingAI map instead of warehouse-10-20-10-2-1 (with --scen)")
    ap.add_argument("--scen", type=Path, help="the MovingAI scenario of --map; its first K agents are planned")
    ap.add_argument("--agents", type=int, nargs="+", default=[10, 50, 100, 200])
    ap.add_argument("--repeat", type=int, default=3, help="runs per K (median time reported)")
    ap.add_argument("--lacam-agents", type=int, nargs="*", default=[10, 50, 100, 200, 400, 1000],
                    help="agent counts for the one-shot LaCAM rows (none: skip)")
    ap.add_argument("--time-limit", type=float, default=5.0, help="LaCAM's time limit per instance (s)")
    ap.add_argument("--initial", choices=["pp", "lacam"], default="lacam",
                    help="first solution of the one-shot rows: LaCAM, or prioritized planning (LaCAM when it fails)")
    ap.add_argument("--workers", type=int, default=1,
                    help="processes for the one-shot rows' LNS (each spends the budget of its own clock)")
    ap.add_argument("--lanes", type=int, default=2,
                    help="one-shot rows: LaCAM first along one-way lanes, a move against a lane costing 1 + N (0: off)")
    ap.add_argument("--cpu-budget", action="store_true",
                    help="count --time-limit in this process's CPU seconds instead of wall seconds")
    ap.add_argument("--scen-seeds", type=int, nargs="*", default=[1],
                    help="also run the LaCAM rows on random scenarios of the map drawn with these seeds (none: skip)")
    ap.add_argument("--live-sizes", type=int, nargs="*", default=[3, 10, 20],
                    help="robots for the live-size comparison on the lab grid and warehouse.yaml (none: skip)")
    ap.add_argument("--cell-m", type=float, default=1.0, help="cell size for the warehouse.yaml grid")
    ap.add_argument("--lacam3", type=Path, metavar="BIN",
                    help="also run lacam3's main (built from github.com/Kei18/lacam3) on every one-shot instance, "
                         "with the same time limit (wall, whole seconds): the peer in the same run")
    ap.add_argument("--json", type=Path, default=RESULTS / "planner.json")
    ap.add_argument("--plot", type=Path, default=RESULTS / "planner.png")
    args = ap.parse_args(argv)

    mapf = args.data / "mapf"
    if (args.map is None) != (args.scen is None):
        print("bench/planner.py: --map and --scen go together", file=sys.stderr)
        return 2
    if args.lacam3 is not None and not args.lacam3.is_file():
        print(f"bench/planner.py: lacam3 binary not found: {args.lacam3}", file=sys.stderr)
        return 2
    map_file = args.map or mapf / "warehouse-10-20-10-2-1.map"
    scen_file = args.scen or mapf / "warehouse-10-20-10-2-1-random-1.scen"
    if args.map is None and (not map_file.is_file() or not scen_file.is_file()):
        print(f"MovingAI instance not found under {mapf}", file=sys.stderr)
        return 2
    try:
        graph = load_movingai_map(map_file)
        scen = load_movingai_scen(scen_file, graph)
        check_instance(graph, scen, max(args.agents + args.lacam_agents))
        if args.lacam_agents:
            LifelongGrid.from_graph(graph)      # refuses a maze too long for the one-shot solvers' distance maps
    except ValueError as e:
        print(f"bench/planner.py: {e}", file=sys.stderr)
        return 2
    label = scen_file.stem.removeprefix(map_file.stem).lstrip("-") or scen_file.stem
    name = f"{map_file.stem} ({scen_file.name})"
    rows = [run_mapf(graph, scen, k, args.repeat) for k in args.agents]
    lacam = [run_lacam(graph, scen, k, args.time_limit, label, cpu_budget=args.cpu_budget, initial=args.initial,
                       workers=args.workers, lanes=args.lanes) for k in args.lacam_agents]
    instances = [(label, scen)]
    for seed in args.scen_seeds:
        other = random_scen(graph, max(args.lacam_agents, default=0), seed)
        instances.append((f"seed {seed}", other))
        lacam += [run_lacam(graph, other, k, args.time_limit, f"seed {seed}", args.cpu_budget, args.initial,
                            args.workers, args.lanes) for k in args.lacam_agents]
    peer = []
    if args.lacam3:
        peer = [run_peer(args.lacam3, graph, sc, k, args.time_limit, lab)
                for lab, sc in instances for k in args.lacam_agents]
    wh = args.data / "maps" / "warehouse.yaml"
    block = run_block_replan(wh, args.cell_m, 10) if wh.is_file() else None
    live = []
    if args.live_sizes:
        live = run_live_sizes(None, args.cell_m, args.live_sizes, 5, args.time_limit)
        if wh.is_file():
            live += run_live_sizes(wh, args.cell_m, args.live_sizes, 5, args.time_limit)
    print_tables(rows, block, name)
    if lacam:
        print_lacam(lacam, map_file.stem)
    if peer:
        print_peer(peer, lacam)
    if live:
        print_live(live)

    for p in (args.json, args.plot):
        if p is not None:
            p.parent.mkdir(parents=True, exist_ok=True)
    if args.json:
        args.json.write_text(json.dumps({"mapf": rows, "lacam": lacam, "lacam3": peer, "live_sizes": live,
                                         "block_replan": block},
                                        indent=2))
        print(f"wrote {args.json}")
    if args.plot:
        plot(rows, args.plot, lacam, name)
        print(f"wrote {args.plot}")
    bad = [r for r in rows + lacam if r["conflicts"]]
    return 1 if bad or (block and block["conflicts"]) else 0


if __name__ == "__main__":
    sys.exit(main())
