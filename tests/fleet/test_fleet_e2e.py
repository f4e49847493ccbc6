"""The fleet end to end: ``rce-fleet demo`` as a subprocess (the real engine as processes,
the fleet container with global_planner and move_clients, pymunk robots as in-process
rce-ros clients), asserting on its JSON report (``--report``), whose ground truth comes
from the simulator (cells entered, closest distance between robots at every physics step).

Scenarios (the seed paper, section IV-A, and this project's issue):
* 3 robots on turtlebot3_world cut 8x8 reach their goals;
* blocking cell 26 at 5 s (in test_fleet_bag, whose run records its bag too): exactly the robots
  whose paths crossed it get cancelGoal, re-route, and no robot enters cell 26 afterwards;
* an obstacle only the lidars can see blocks its cell and the robots go around it;
* 10 robots on warehouse.yaml (1.2 m cells) swap sides and never come closer than two radii;
* an unreachable goal is reported at once, with the reason.
"""
from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

from rce_fleet.configs import dumps, robot_config
from rce_fleet.maps.geometry import GridGeometry
from rce_fleet.maps.grid import make_grid
from rce_fleet.maps.occupancy import load_map

ROOT = Path(__file__).resolve().parents[2]
MAPS = ROOT.parent / "shared" / "data" / "maps"
TB3 = MAPS / "turtlebot3_world.yaml"
WAREHOUSE = MAPS / "warehouse.yaml"
RCE_FLEET = Path(sys.executable).parent / "rce-fleet"
RADIUS = 0.105
DEMO_TIMEOUT_S = 150.0  # wall s a demo's mission may take (its --timeout): the limit of a hang, not a speed bound
                        # (a 10-robot mission takes 40 - 60 s while the suite runs, 85 s on a machine 4x oversubscribed)
EXIT_GRACE_S = 60.0     # wall s beyond --timeout for the demo's teardown and report before it is killed


# turtlebot3_world 8x8: cell 26 links only 25 and 27, so Robot1 (30 -> 17) and Robot2
# (14 -> 25) must cross it on their shortest paths; Robot3 (50 -> 38) does not. At 5 s
# nobody is near it (Robot1, the closest, is two cells away).
TB3_MISSION = ["--start", "Robot1=30", "--goal", "Robot1=17", "--start", "Robot2=14", "--goal", "Robot2=25",
               "--start", "Robot3=50", "--goal", "Robot3=38"]


def run_demo(tmp_path: Path, *args: str, timeout: float = DEMO_TIMEOUT_S) -> tuple[int, dict, str]:
    """Run ``rce-fleet demo --headless`` with a report (a mission unless ``--lifelong`` is given);
    returns (exit code, report, output)."""
    report, plot = tmp_path / "report.json", tmp_path / "paths.png"
    argv = [str(RCE_FLEET), "demo", *(() if "--lifelong" in args else ("--mission",)), "--headless", "--no-live",
            "--report", str(report), "--plot", str(plot),
            "--workdir", str(tmp_path / "run"), "--timeout", str(timeout), *args]
    t0 = time.monotonic()
    p = subprocess.run(argv, capture_output=True, text=True, timeout=timeout + EXIT_GRACE_S, cwd=tmp_path)
    out = p.stdout + p.stderr
    assert report.exists(), f"no report ({time.monotonic() - t0:.1f} s):\n{out[-4000:]}"
    rep = json.loads(report.read_text())
    if rep.get("plot"):
        assert Path(rep["plot"]).stat().st_size > 10_000
    return p.returncode, rep, out


def _explain(rep: dict, out: str) -> str:
    per = {r: {k: v[k] for k in ("start", "goal", "reached", "state", "error", "cancel_goal")}
           for r, v in rep["per_robot"].items()}
    return f"{rep['reason']}\n{json.dumps(per, indent=1)}\n{out[-3000:]}"


def test_committed_robot_configs_are_the_generators_output():
    for n in range(1, 11):
        path = ROOT / "examples" / "fleet" / "configs" / f"robot{n}.config"
        assert path.read_text() == dumps(robot_config(n)), f"{path} differs: run `rce-fleet configs`"


def test_three_robots_turtlebot3_world_reach_their_goals(tmp_path):
    code, rep, out = run_demo(tmp_path, "--map", str(TB3), "--grid", "8x8", "--speedup", "4", *TB3_MISSION)
    assert code == 0 and rep["ok"], _explain(rep, out)
    assert rep["grid"]["rows"] == 8 and rep["grid"]["cols"] == 8
    assert all(v["reached"] for v in rep["per_robot"].values())
    assert rep["min_pair_distance_m"] > 2 * RADIUS
    assert rep["mission_time_s"] > 0
    assert all(v["cancel_goal"] == 0 for v in rep["per_robot"].values())


def test_obstacle_seen_by_lidar_blocks_its_cell(tmp_path):
    code, rep, out = run_demo(tmp_path, "--map", str(TB3), "--grid", "8x8", "--speedup", "4",
                              "--start", "Robot1=30", "--goal", "Robot1=17", "--obstacle", "26@3", "--robots", "1")
    assert code == 0 and rep["ok"], _explain(rep, out)
    assert rep["blocked"].get("26", "").startswith("lidar:Robot1"), rep["blocked"]
    v = rep["per_robot"]["Robot1"]
    assert v["cancel_goal"] >= 1 and 26 not in [c for _, c in v["cells"]]


def _warehouse_swap() -> list[str]:
    """10 robots in the open middle of the warehouse: five in a row at y ~ -3 m and five in a
    row at y ~ +3 m swap rows. The bottom ones go straight up, head-on against the top ones
    coming down, which also swap columns pairwise, so paths meet and cross in the middle."""
    geo = GridGeometry.from_cellgrid(make_grid(load_map(WAREHOUSE), cell_m=1.2))
    lo, hi = geo.cell_of(0.0, -3.0), geo.cell_of(0.0, 3.0)
    row_lo, row_hi = geo.rc(lo)[0], geo.rc(hi)[0]
    cols = [c for c in range(geo.cols) if geo.is_free(row_lo * geo.cols + c) and geo.is_free(row_hi * geo.cols + c)
            and -6.0 <= geo.center(row_lo * geo.cols + c)[0] <= 12.0]
    assert len(cols) >= 10, cols
    pick = cols[::max(1, len(cols) // 5)][:5]
    args = []
    partner = {0: 1, 1: 0, 2: 3, 3: 2, 4: 4}
    for i, c in enumerate(pick):
        a, b = f"Robot{i + 1}", f"Robot{i + 6}"
        args += ["--start", f"{a}={row_lo * geo.cols + c}", "--goal", f"{a}={row_hi * geo.cols + c}",
                 "--start", f"{b}={row_hi * geo.cols + c}", "--goal", f"{b}={row_lo * geo.cols + pick[partner[i]]}"]
    return args


def test_ten_robots_warehouse_swap_sides_without_collisions(tmp_path):
    code, rep, out = run_demo(tmp_path, "--map", str(WAREHOUSE), "--cell", "1.2", "--robots", "10", "--speedup", "3",
                              *_warehouse_swap())
    assert code == 0 and rep["ok"], _explain(rep, out)
    assert rep["robots"] == 10 and all(v["reached"] for v in rep["per_robot"].values())
    # ground truth, every physics step: never closer than two radii (never touching)
    assert rep["min_pair_distance_m"] > 2 * RADIUS, rep["min_pair_at"]
    assert rep["grid"]["rows"] == 42 and rep["grid"]["cols"] == 26


def test_unreachable_goal_is_reported_not_waited_on(tmp_path):
    # the project's lab map: cell 14 holds the table (not a free cell)
    code, rep, out = run_demo(tmp_path, "--robots", "2", "--goal", "Robot1=14", "--speedup", "4", timeout=60)
    assert code == 3 and not rep["ok"], out[-3000:]
    assert "Robot1" in rep["reason"] and "not a free cell" in rep["reason"]
    assert rep["per_robot"]["Robot1"]["state"] == "unreachable"      # the reason is that, not the --timeout
    assert "FAILED" in out and "not a free cell" in out


def test_bad_flags_are_refused(tmp_path):
    p = subprocess.run([str(RCE_FLEET), "demo", "--mission", "--block", "26"], capture_output=True, text=True,
                       cwd=tmp_path)
    assert p.returncode == 2 and "CELL@SECONDS" in p.stderr
    p = subprocess.run([str(RCE_FLEET), "demo", "--mission", "--goal", "Robot7=3"], capture_output=True, text=True,
                       cwd=tmp_path)
    assert p.returncode == 2 and "unknown robot 'Robot7'" in p.stderr
