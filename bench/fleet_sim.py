"""The fleet simulator's own CPU per simulated second: N pymunk robots on the warehouse map,
each driving to random goals with its local planner, as the simulator host runs them
(:class:`rce_fleet.live.simhost.SimHost`: a 10 Hz control tick, a lidar scan every second tick,
five physics substeps a tick), without the engine or the robots' bridges.

Per robot count N it reports the CPU s per simulated s, split into the lidar scans, the local
planner (DWA) and the physics step (with the sensors' noise and the ground-truth pair
distance), and, as the peer in the same run, the lidar through pymunk's own
``Space.segment_query_first`` per beam (``Lidar.fast = False``) on the same robots and poses.
``ratio`` = the compiled caster's scan CPU / pymunk's. The real-time factor the simulator alone
could hold on one core is 1 / ``cpu_per_sim_s``.

::

    .venv/bin/python bench/fleet_sim.py [--robots 20,50,100] [--ticks 100] [--json PATH] [--plot PATH]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
WAREHOUSE = ROOT.parent / "shared" / "data" / "maps" / "warehouse.yaml"
DT, SUBSTEPS, SCAN_EVERY = 0.1, 5, 2      # the simulator host's tick, physics substeps, scan period (ticks)


def run(robots: int, ticks: int, seed: int = 1) -> dict:
    """One run of ``robots`` robots for ``ticks`` control ticks; CPU s per simulated s by part."""
    from rce_fleet.maps.geometry import GridGeometry
    from rce_fleet.maps.grid import make_grid
    from rce_fleet.maps.occupancy import load_map
    from rce_fleet.sim.local_nav import LocalNavigator
    from rce_fleet.sim.obstacles import ObstacleDetector
    from rce_fleet.sim.world import SimWorld
    occ = load_map(WAREHOUSE)
    world, detector = SimWorld(occ, seed=seed), ObstacleDetector(occ)
    geo = GridGeometry.from_cellgrid(make_grid(occ, cell_m=1.2))
    free = np.flatnonzero(np.array(geo.free, dtype=bool))
    rng = np.random.default_rng(seed)
    bots = []
    for i, c in enumerate(rng.choice(free, robots, replace=False)):
        r = world.add_robot(f"Robot{i + 1}", *geo.center(int(c)), float(rng.uniform(-np.pi, np.pi)))
        nav = LocalNavigator(obstacle_detector=detector)
        bots.append((r, nav))
    for _, nav in bots:
        nav.set_goal(*geo.center(int(rng.choice(free))))
    cpu = {"scan": 0.0, "navigator": 0.0, "physics": 0.0, "scan_pymunk": 0.0}
    clock = time.process_time
    for k in range(ticks):
        for r, nav in bots:
            pose = r.localisation()[:3]
            scan = None
            if k % SCAN_EVERY == 0:
                t0 = clock()
                scan = r.scan()
                t1 = clock()
                r.lidar.fast = False
                peer = r.lidar.true_ranges(*r.pose(), r.shape.filter)
                r.lidar.fast = True
                cpu["scan"] += t1 - t0
                cpu["scan_pymunk"] += clock() - t1
                assert peer.shape == scan.shape
            t0 = clock()
            v, w = nav.update(pose, DT, scan)
            cpu["navigator"] += clock() - t0
            r.cmd_vel(v, w)
            if nav.state == "reached":
                nav.set_goal(*geo.center(int(rng.choice(free))))
        t0 = clock()
        for _ in range(SUBSTEPS):
            world.step(DT / SUBSTEPS)
            world.min_pair_distance()
        cpu["physics"] += clock() - t0
    sim_s = ticks * DT
    per = {k: round(v / sim_s, 4) for k, v in cpu.items()}
    total = per["scan"] + per["navigator"] + per["physics"]
    return {"robots": robots, "ticks": ticks, "sim_s": round(sim_s, 2), "cpu_per_sim_s": per,
            "cpu_per_sim_s_total": round(total, 4), "ratio": round(cpu["scan"] / cpu["scan_pymunk"], 3),
            "real_time_factor_one_core": round(1.0 / total, 2) if total else None}


def plot(rows: list[dict], path: Path) -> None:
    """Stacked CPU s per sim s by part, and pymunk's scan beside the caster's, per robot count."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4))
    xs = np.arange(len(rows))
    bottom = np.zeros(len(rows))
    for part in ("scan", "navigator", "physics"):
        vals = np.array([r["cpu_per_sim_s"][part] for r in rows])
        ax.bar(xs - 0.2, vals, 0.4, bottom=bottom, label=part)
        bottom += vals
    ax.bar(xs + 0.2, [r["cpu_per_sim_s"]["scan_pymunk"] for r in rows], 0.4, label="scan, pymunk's query (peer)",
           color="grey")
    ax.set_xticks(xs, [str(r["robots"]) for r in rows])
    ax.set_xlabel("robots")
    ax.set_ylabel("CPU s per simulated s")
    ax.set_title("fleet simulator (warehouse map)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", default="20,50,100", help="robot counts (default 20,50,100)")
    ap.add_argument("--ticks", type=int, default=100, help="control ticks of 0.1 sim s per run (default 100)")
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--plot", help="write a PNG here")
    a = ap.parse_args(argv)
    rows = []
    for n in (int(x) for x in a.robots.split(",")):
        r = run(n, a.ticks)
        rows.append(r)
        c = r["cpu_per_sim_s"]
        print(f"{n:4d} robots: {r['cpu_per_sim_s_total']} CPU s per sim s (scan {c['scan']}, navigator "
              f"{c['navigator']}, physics {c['physics']}); scan through pymunk's query {c['scan_pymunk']} "
              f"(caster/pymunk {r['ratio']}); one core holds {r['real_time_factor_one_core']}x real time",
              flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps({"runs": rows}, indent=1))
    if a.plot:
        plot(rows, Path(a.plot))
    return 0


if __name__ == "__main__":
    sys.exit(main())
