"""The live fleet on tasks without end: ``rce-fleet demo --lifelong`` on the warehouse with 20,
50 and 100 robots for 10 simulated minutes each, beside the lifelong planner's offline
prediction for the very same task stream.

Per robot count N, one run of the whole system (engine processes, the fleet container with
the global planner and N move_clients, N pymunk robots with batteries as in-process rce-ros
clients, generated pick-up -> drop-off tasks at ``--rate-per-robot`` x N per simulated minute,
:class:`rce_fleet.live.task_stream.TaskStream`), as a subprocess; measured:

- ``tasks_per_hour``: tasks done per simulated hour (the report's ``tasks.per_hour``);
- ``real_time_factor``: simulated s per wall s the run held (asked: ``--speedup``);
- ``host_cpu_per_sim_s``: CPU s the demo process (the simulator and the robots' bridges) spent
  per simulated s of the run (what the machine's other load does not change much);
- ``goal_to_motion_p99_s``: p99 of the sim s from a task's assignment to its robot's first
  motion (robots standing when they got it);
- ``engine_cpu_pct``: CPU of the engine's processes that descend from the demo process
  (rce-master, rce-robot, rce-container and what of the container's node processes is
  visible from outside its sandbox), % of one core over the run, with the demo process
  itself (the simulator and the robots' bridges) beside it, and ``machine_cpu_pct``: the
  whole machine's busy CPU over the run (% of one core; the container's nodes, the global
  planner and every move_client, are in it);
- ``control``: the live fleet's control loop without physics and engine
  (:func:`rce_fleet.live.kinematic.run_stream`: the global planner core, the dispatcher, the
  move_clients and unicycle robots at the simulated robots' speed and turn rate) on the same
  starts and task stream: ``tasks_done`` and ``s_per_cell``, the seconds the robots take per
  cell while they drive (turns and slowing included), and ``time_split``: the share of the
  robots' time by what they did (:data:`rce_fleet.live.kinematic.TIME_SPLIT`: no task, driving,
  held by the dependency graph's order, waiting beside a taken station, ...);
- ``offline``: the same allocator (:class:`rce_fleet.lifelong.GreedyScheduler`) and planner
  (:class:`rce_fleet.lifelong.PIBTPlanner`, 4-neighbour moves) on the cell graph without
  physics, one step per ``control.s_per_cell`` (the robots' own cell rate), from the same
  starts with the same task stream for the same simulated time: ``tasks_done``,
  ``moving_share`` and ``no_task_share`` (of the robot-steps);
  ``live_share`` = live done / offline done (the goal: >= 0.8), ``control_share`` = control
  done / offline done (what planning and dispatch lose; the rest is physics and transport).

``--quick``: 3 robots on the lab map for 40 simulated s (a smoke test of this script).
``--control-only``: the control loop and the offline prediction only (no live run), with the
control run's re-plan times; what to iterate on when changing planning or dispatch.
Prints a table; ``--out FILE`` writes the JSON.
"""
from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import psutil

from common import process_cpu_s

ROOT = Path(__file__).resolve().parents[1]
WAREHOUSE = ROOT.parent / "shared" / "data" / "maps" / "warehouse.yaml"
RCE_FLEET = Path(sys.executable).parent / "rce-fleet"
SAMPLE_S = 1.0            # wall s between CPU samples of the run's processes
EXIT_GRACE_S = 120        # wall s beyond the run's timeout before it is killed


def _geometry(map_path: str | None, robots: int):
    """The grid, places and starts the demo uses for ``map_path`` (None: the lab map) and ``robots``."""
    from rce_fleet.live.demo import choose_cells
    from rce_fleet.maps.geometry import GridGeometry
    from rce_fleet.maps.grid import fleet_grid
    from rce_fleet.maps.lab_map import write_lab_map
    from rce_fleet.maps.occupancy import load_map
    from rce_fleet.operations.places import generate_places
    with tempfile.TemporaryDirectory() as d:
        occ = load_map(map_path or write_lab_map(d))
    grid, _ = fleet_grid(occ)
    geo = GridGeometry.from_cellgrid(grid)
    names = [f"Robot{i}" for i in range(1, robots + 1)]
    return geo, generate_places(geo, robots), choose_cells(geo, names, 1, {}, {}, False)[0]


def offline_prediction(geo, places, starts: dict[str, int], stream: list, duration_s: float, step_s: float,
                       seed: int = 1) -> dict:
    """Tasks the lifelong allocator and planner finish on the cell graph, one step per
    ``step_s`` seconds (module docstring)."""
    from rce_fleet.lifelong import MAPF, DistanceCache, GreedyScheduler, LifelongGrid, PIBTPlanner, TaskPool
    from rce_fleet.lifelong.simulator import check_actions
    t0 = time.perf_counter()
    grid = LifelongGrid(np.array(geo.free, dtype=bool).reshape(geo.rows, geo.cols))
    cache = DistanceCache(grid, max_bytes=256 * 2 ** 20)
    sched, planner = GreedyScheduler(cache), PIBTPlanner(grid, cache, model=MAPF, seed=seed)
    pool = TaskPool()
    names = sorted(starts, key=lambda r: int(r[5:]))
    pos = np.array([starts[r] for r in names], dtype=np.int64)
    head = np.zeros(len(names), dtype=np.int64)
    assignment = np.full(len(names), -1, dtype=np.int64)
    created, durations = {}, []
    moved = no_task = 0                  # robot-steps moving, and without a task
    nxt = 0
    steps = int(duration_s / step_s)
    for k in range(steps):
        while nxt < len(stream) and stream[nxt][0] <= k * step_s:
            t = pool.add([places.resolve(e) for e in stream[nxt][1]], release=k)
            created[t.id] = k
            nxt += 1
        deadline = time.perf_counter() + 0.2
        prop = sched.schedule(pos, assignment, pool.open, k, deadline)
        for a in np.flatnonzero((assignment >= 0) & (prop != assignment)):
            tid = int(assignment[a])
            if tid in pool.open and pool.open[tid].agent == a and tid not in prop:
                pool.unassign(tid)
        for a in np.flatnonzero((prop >= 0) & (prop != assignment)):
            pool.assign(int(prop[a]), int(a))
        assignment = prop.copy()
        goals = np.array([pool.open[int(t)].goal if t >= 0 else -1 for t in assignment], dtype=np.int64)
        act = planner.plan(pos, head, goals, deadline)
        before = pos
        pos, head, _ = check_actions(grid, pos, head, act, MAPF)
        moved += int((pos != before).sum())
        no_task += int((assignment < 0).sum())
        for a in np.flatnonzero(assignment >= 0):
            tid = int(assignment[a])
            while pos[a] == pool.open[tid].goal:
                if pool.reach(tid, k + 1):
                    durations.append((k + 1 - created[tid]) * step_s)
                    assignment[a] = -1
                    break
    robot_steps = max(1, steps * len(names))
    return {"tasks_done": pool.finished, "steps": steps, "step_s": round(step_s, 3),
            "moving_share": round(moved / robot_steps, 4), "no_task_share": round(no_task / robot_steps, 4),
            "mean_s": round(float(np.mean(durations)), 2) if durations else 0.0,
            "per_hour": round(pool.finished * 3600.0 / duration_s, 2), "wall_s": round(time.perf_counter() - t0, 2)}


class TreeCpu:
    """CPU seconds of a process and its descendants, sampled (a child's last sample counts)."""

    def __init__(self, pid: int):
        self.root = psutil.Process(pid)
        self.cpu: dict[int, tuple[str, float]] = {}
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self) -> None:
        while not self._stop.wait(SAMPLE_S):
            self.sample()

    def sample(self) -> None:
        try:
            procs = [self.root, *self.root.children(recursive=True)]
        except psutil.Error:
            return
        for p in procs:
            try:
                cpu = process_cpu_s(p)
                name = "demo" if p.pid == self.root.pid else Path(p.cmdline()[1] if len(p.cmdline()) > 1
                                                                     else p.name()).name
                self.cpu[p.pid] = (name, cpu)
            except (psutil.Error, IndexError):
                pass

    @staticmethod
    def _busy() -> float:
        t = psutil.cpu_times()
        return sum(t) - t.idle - getattr(t, "iowait", 0.0)

    def start(self) -> TreeCpu:
        self.w0, self.b0 = time.monotonic(), self._busy()
        self.thread.start()
        return self

    def stop(self) -> dict:
        self._stop.set()
        self.thread.join()
        wall = time.monotonic() - self.w0
        machine = self._busy() - self.b0
        by: dict[str, float] = {}
        for name, s in self.cpu.values():
            by[name] = by.get(name, 0.0) + s
        demo = by.pop("demo", 0.0)
        return {"engine_cpu_pct": round(100 * sum(by.values()) / wall, 1), "demo_cpu_pct": round(100 * demo / wall, 1),
                "machine_cpu_pct": round(100 * machine / wall, 1),
                "by_process_pct": {k: round(100 * v / wall, 1) for k, v in sorted(by.items(), key=lambda kv: -kv[1])},
                "wall_s": round(wall, 1)}


def live_run(map_path: str | None, robots: int, duration: float, rate: float, speedup: float, workdir: Path,
             timeout: float) -> dict:
    """One ``rce-fleet demo --lifelong`` run; its report's numbers and the engine's CPU."""
    report = workdir / f"report-{robots}.json"
    argv = [str(RCE_FLEET), "demo", "--lifelong", "--robots", str(robots), "--duration", str(duration),
            "--task-rate", str(rate), "--speedup", str(speedup), "--headless", "--no-live", "--report", str(report),
            "--plot", "", "--workdir", str(workdir / f"run-{robots}"), "--timeout", str(timeout)]
    if map_path:
        argv += ["--map", map_path]
    log = open(workdir / f"demo-{robots}.log", "wb")
    p = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, cwd=workdir)
    cpu = TreeCpu(p.pid).start()
    try:
        code = p.wait(timeout + EXIT_GRACE_S)
    except subprocess.TimeoutExpired:
        p.kill()
        code = p.wait()
    usage = cpu.stop()
    if not report.exists():
        raise RuntimeError(f"{robots} robots: no report (exit {code}); see {workdir / f'demo-{robots}.log'}")
    rep = json.loads(report.read_text())
    ll = rep.get("lifelong", {})
    per = rep.get("per_robot", {}).values()
    return {"exit_code": code, "reason": rep.get("reason"), "tasks": rep.get("tasks"),
            "tasks_per_hour": (rep.get("tasks") or {}).get("per_hour"), "real_time_factor": ll.get("real_time_factor"),
            "host_cpu_per_sim_s": ll.get("host_cpu_per_sim_s"),
            "asked_speedup": speedup, "sim_lag_resets": rep.get("sim_lag_resets"),
            "sim_max_speedup": rep.get("sim_max_speedup"),
            "goal_to_motion_p99_s": (ll.get("goal_to_motion_s") or {}).get("p99"),
            "goal_to_motion_n": (ll.get("goal_to_motion_s") or {}).get("n"),
            "utilisation_mean": round(float(np.mean([v.get("utilisation", 0) for v in per])), 3) if per else None,
            "battery_min_pct": min((v.get("battery_min_pct") or 100 for v in per), default=None),
            "charges": sum(v.get("charges", 0) for v in per), "ran_flat": sum(bool(v.get("ran_flat")) for v in per),
            "planner": rep.get("planner"), **usage}


def _share(run: dict, off: dict) -> float | None:
    """``run``'s tasks done over the offline prediction's (None when that is 0)."""
    return round(run["tasks_done"] / off["tasks_done"], 3) if off["tasks_done"] else None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", default="20,50,100", help="robot counts (default 20,50,100)")
    ap.add_argument("--duration", type=float, default=600.0, help="simulated s per run (default 600)")
    ap.add_argument("--rate-per-robot", type=float, default=0.5, help="tasks per robot per sim minute (default 0.5)")
    ap.add_argument("--speedup", type=float, default=4.0, help="asked sim speed-up (default 4)")
    ap.add_argument("--map", default=str(WAREHOUSE), help="map YAML (default the shared warehouse)")
    ap.add_argument("--quick", action="store_true", help="3 robots on the lab map for 40 sim s")
    ap.add_argument("--control-only", action="store_true",
                    help="run the control loop and the offline prediction only (no live system)")
    ap.add_argument("--out", help="write the JSON here")
    ap.add_argument("--workdir", help="keep the runs' logs and reports here (default a temp dir)")
    a = ap.parse_args(argv)
    if a.quick:
        sizes, map_path, a.duration, a.speedup, a.rate_per_robot = [3], None, 40.0, 10.0, 2.0
    else:
        sizes, map_path = [int(x) for x in a.robots.split(",")], a.map
    from rce_fleet.live.kinematic import run_stream
    from rce_fleet.live.task_stream import TaskStream
    work = Path(a.workdir or tempfile.mkdtemp(prefix="fleet-live-"))
    work.mkdir(parents=True, exist_ok=True)
    results = {"duration_s": a.duration, "rate_per_robot_per_min": a.rate_per_robot, "map": map_path or "lab",
               "cores": psutil.cpu_count(), "runs": {}}
    for n in sizes:
        rate = a.rate_per_robot * n
        geo, places, starts = _geometry(map_path, n)
        stream = TaskStream(places, rate, 1).times_and_errands(a.duration)
        control = run_stream(geo, places, starts, stream, a.duration)
        off = offline_prediction(geo, places, starts, stream, a.duration, control["s_per_cell"])
        print(f"{n:4d} robots: offline {off['tasks_done']} tasks at {off['step_s']} s per cell, control loop "
              f"without physics {control['tasks_done']} (share {_share(control, off)}; robots sharing a cell "
              f"{control['shared_cells']}; {control['replans']} re-plans, {control['stale_replans']} for stale orders, "
              f"{control['plan_ms']['mean']} ms mean, {control['plan_ms']['max']} ms max; wall {control['wall_s']} s)",
              flush=True)
        split = ", ".join(f"{k} {100 * v:.1f} %" for k, v in control["time_split"].items() if v)
        print(f"      robots' time in the control loop: {split}; offline: moving {100 * off['moving_share']:.1f} %, "
              f"no task {100 * off['no_task_share']:.1f} %", flush=True)
        if a.control_only:
            results["runs"][str(n)] = {"offline": off, "control": control, "control_share": _share(control, off),
                                       "generated": len(stream)}
            continue
        timeout = max(300.0, 4 * a.duration / max(a.speedup, 0.1) + 30 * n)
        live = live_run(map_path, n, a.duration, rate, a.speedup, work, timeout)
        done = (live.get("tasks") or {}).get("done", 0)
        live["offline"], live["control"] = off, control
        live["live_share"] = round(done / off["tasks_done"], 3) if off["tasks_done"] else None
        live["control_share"] = _share(control, off)
        live["generated"] = len(stream)
        results["runs"][str(n)] = live
        print(f"{n:4d} robots: {live['tasks_per_hour']} tasks/h (offline {off['per_hour']}, live share "
              f"{live['live_share']}, control share {live['control_share']}), real-time factor "
              f"{live['real_time_factor']} (asked {a.speedup:g}; the simulator host's CPU "
              f"{live['host_cpu_per_sim_s']} s per sim s), goal->motion "
              f"p99 {live['goal_to_motion_p99_s']} s, engine CPU {live['engine_cpu_pct']} % (demo "
              f"{live['demo_cpu_pct']} %, machine {live['machine_cpu_pct']} %), exit {live['exit_code']}: "
              f"{live['reason']}", flush=True)
    if a.out:
        Path(a.out).write_text(json.dumps(results, indent=1))
    bad = [n for n, r in results["runs"].items()
           if "exit_code" in r and (r["exit_code"] != 0 or not math.isfinite(r["engine_cpu_pct"]))]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
