"""The ``fleet/global_planner`` container node: I/O shell around
:class:`rce_fleet.nodes.global_planner_core.GlobalPlannerCore` (topics: see that module).

Arguments: ``[--robots Robot1,Robot2,...] [--rate HZ] [--no-lidar-blocking] [--batch S]
[--park-idle] [--replan-bound S]``. Robot IDs come from ``--robots`` or the ``/fleet/robots`` parameter (re-read
every 2 s, so robots can join); the grid from ``/fleet/grid`` (:mod:`rce_fleet.maps.geometry`); the
named places from ``/fleet/places`` (:mod:`rce_fleet.operations.places`) and the robots' battery
parameters from ``/fleet/battery`` (:mod:`rce_fleet.operations.battery`), when set.
Goals arriving within one planning cycle (``--batch``, default 0.05 s) are planned
together; a blocked cell is re-planned at once. A re-plan takes at most ``--replan-bound`` s
of wall time (default :data:`rce_fleet.planning.prioritized.REPLAN_BOUND_S`; 0: no bound):
robots it does not reach keep their plans and are planned at the next tick.
"""
from __future__ import annotations

import argparse
import asyncio
import math
import time

from rce.plumbing.log import get_logger, setup_logging
from rce.node import node_argv

from ..operations.battery import BATTERY_PARAM, BatteryParams
from ..maps.geometry import ROBOTS_PARAM
from .common import PlanarPose, Publishers, load_geometry, planar_pose
from .global_planner_core import GlobalPlannerCore
from ..operations.places import PLACES_PARAM, Places
from ..planning.prioritized import REPLAN_BOUND_S

log = get_logger("fleet.global_planner")

ROBOTS_REFRESH_S = 2.0   # s between reads of the /fleet/robots parameter (robots that join are served)


def parse_args(argv: list[str]) -> argparse.Namespace:
    """The node's arguments (see the module docstring)."""
    p = argparse.ArgumentParser(prog="global_planner")
    p.add_argument("--robots", default="", help="comma-separated robot IDs (default: the /fleet/robots parameter)")
    p.add_argument("--rate", type=float, default=5.0, help="fleet state rate, Hz (default 5)")
    p.add_argument("--batch", type=float, default=0.05, help="planning cycle for goals, s (default 0.05)")
    p.add_argument("--no-lidar-blocking", action="store_true", help="ignore /RobotN/obstacles")
    p.add_argument("--park-idle", action="store_true", help="idle robots drive to the parking places")
    p.add_argument("--replan-bound", type=float, default=REPLAN_BOUND_S,
                   help=f"wall-time bound of one re-plan, s (default {REPLAN_BOUND_S}; 0: none)")
    a = p.parse_args(argv)
    if a.replan_bound < 0:
        p.error(f"--replan-bound must be >= 0 s, got {a.replan_bound}")
    return a


async def main(node) -> None:
    """Run the global planner on ``node`` (an :class:`rce.node.Node`) until it shuts down."""
    setup_logging()
    args = parse_args(node_argv())
    geo = await load_geometry(node)

    def logf(msg: str, **kw) -> None:
        (log.warning if msg in ("error", "unreachable") else log.info)(msg, **kw)

    places = Places.from_param(await node.get_param(PLACES_PARAM, None), geo)
    battery = BatteryParams.from_param(await node.get_param(BATTERY_PARAM, None))
    core = GlobalPlannerCore(geo, clock=time.monotonic, lidar_blocking=not args.no_lidar_blocking, log=logf,
                             places=places, battery=battery, park_idle=args.park_idle,
                             replan_bound_s=args.replan_bound or math.inf)
    pubs = Publishers(node)
    await pubs.add("/fleet/state", "fleet/FleetState", queue_size=5)
    await pubs.add("/fleet/tasks", "fleet/TaskList", queue_size=5)
    lock = asyncio.Lock()
    pending_goals: dict[str, int] = {}
    loop = asyncio.get_running_loop()
    flush_handle = None

    def flush_goals() -> None:
        nonlocal flush_handle
        flush_handle = None
        goals = dict(pending_goals)
        pending_goals.clear()
        pubs.send(core.on_goals(goals))

    def on_goal(msg) -> None:
        nonlocal flush_handle
        pending_goals[str(msg.robot)] = int(msg.cell)
        if flush_handle is None:
            flush_handle = loop.call_later(args.batch, flush_goals)

    def on_block(msg) -> None:
        pubs.send(core.on_block(int(msg.cell), bool(msg.blocked), str(msg.source)))

    def on_task(msg) -> None:
        pubs.send(core.on_task({"request": msg.request, "id": msg.id, "errands": list(msg.errands),
                                "priority": msg.priority, "earliest_start_s": msg.earliest_start_s,
                                "deadline_s": msg.deadline_s, "source": msg.source}))

    def on_task_cancel(msg) -> None:
        pubs.send(core.on_task_cancel({"request": msg.request, "id": msg.id, "source": msg.source}))

    async def add_robot(robot: str) -> None:
        async with lock:
            if robot in core.robots:
                return
            for topic, typ in (("goalNodesList", "std_msgs/Int32MultiArray"), ("cancelGoal", "std_msgs/Bool"),
                               ("clearance", "fleet/Clearance")):
                await pubs.add(f"/{robot}/{topic}", typ, queue_size=20)

            def on_pose(pose: PlanarPose, robot=robot) -> None:
                pubs.send(core.on_pose(robot, *pose))

            def on_obstacles(msg, robot=robot) -> None:
                st = msg.header.stamp
                pubs.send(core.on_obstacles(robot, [(p.position.x, p.position.y) for p in msg.poses],
                                            st.sec + st.nanosec * 1e-9))

            def on_progress(msg, robot=robot) -> None:
                core.on_progress(robot, {"state": msg.state, "distance_left": msg.distance_left, "goal": msg.goal})

            def on_battery(msg, robot=robot) -> None:
                core.on_battery(robot, float(msg.percentage))

            await node.subscriber(f"/{robot}/amcl_pose", "geometry_msgs/PoseWithCovarianceStamped", on_pose,
                                  queue_size=20, decode=planar_pose)
            await node.subscriber(f"/{robot}/obstacles", "geometry_msgs/PoseArray", on_obstacles, queue_size=5)
            await node.subscriber(f"/{robot}/battery", "sensor_msgs/BatteryState", on_battery, queue_size=2)
            await node.subscriber(f"/{robot}/progress", "fleet/MoveProgress", on_progress, queue_size=5)
            core.add_robot(robot)
            log.info("serving robot", robot=robot)

    async def refresh_robots() -> None:
        robots = [r for r in args.robots.split(",") if r]
        if not robots:
            robots = await node.get_param(ROBOTS_PARAM, [])
        for r in robots or []:
            await add_robot(str(r))

    await refresh_robots()
    await node.subscriber("/fleet/goal", "fleet/RobotGoal", on_goal, queue_size=100)
    await node.subscriber("/fleet/block", "fleet/CellBlock", on_block, queue_size=100)
    await node.subscriber("/fleet/task", "fleet/Task", on_task, queue_size=1000)
    await node.subscriber("/fleet/task_cancel", "fleet/TaskCancel", on_task_cancel, queue_size=100)
    log.info("global planner up", rows=geo.rows, cols=geo.cols, cell_w=round(geo.cell_w_m, 3),
             cell_h=round(geo.cell_h_m, 3), free=len(geo.free_cells()), robots=sorted(core.robots))

    period = 1.0 / max(args.rate, 0.1)
    last_refresh = loop.time()
    while not node.is_shutdown:
        pubs.send(core.tick())
        pubs.send(core.tasks_due())
        pubs.pubs["/fleet/state"].publish_nowait(core.state())
        if loop.time() - last_refresh > ROBOTS_REFRESH_S:
            last_refresh = loop.time()
            await refresh_robots()
        await asyncio.sleep(period)
