"""The ``fleet/global_planner`` container node: I/O shell around
:class:`rce_fleet.global_planner_core.GlobalPlannerCore` (topics: see that module).

Arguments: ``[--robots Robot1,Robot2,...] [--rate HZ] [--no-lidar-blocking] [--batch S]``.
Robot IDs come from ``--robots`` or the ``/fleet/robots`` parameter (re-read every 2 s,
so robots can join); the grid from ``/fleet/grid`` (:mod:`rce_fleet.geometry`).
Goals arriving within one planning cycle (``--batch``, default 0.05 s) are planned
together; a blocked cell is re-planned at once.
"""
from __future__ import annotations

import argparse
import asyncio
import time

from rce.log import get_logger, setup_logging
from rce.node import node_argv

from .geometry import ROBOTS_PARAM, yaw_from_quaternion
from .node_common import Publishers, load_geometry
from .global_planner_core import GlobalPlannerCore

log = get_logger("fleet.global_planner")

ROBOTS_REFRESH_S = 2.0   # s between reads of the /fleet/robots parameter (robots that join are served)


def parse_args(argv: list[str]) -> argparse.Namespace:
    """The node's arguments (see the module docstring)."""
    p = argparse.ArgumentParser(prog="global_planner")
    p.add_argument("--robots", default="", help="comma-separated robot IDs (default: the /fleet/robots parameter)")
    p.add_argument("--rate", type=float, default=5.0, help="fleet state rate, Hz (default 5)")
    p.add_argument("--batch", type=float, default=0.05, help="planning cycle for goals, s (default 0.05)")
    p.add_argument("--no-lidar-blocking", action="store_true", help="ignore /RobotN/obstacles")
    return p.parse_args(argv)


async def main(node) -> None:
    """Run the global planner on ``node`` (an :class:`rce.node.Node`) until it shuts down."""
    setup_logging()
    args = parse_args(node_argv())
    geo = await load_geometry(node)

    def logf(msg: str, **kw) -> None:
        (log.warning if msg in ("error", "unreachable") else log.info)(msg, **kw)

    core = GlobalPlannerCore(geo, clock=time.monotonic, lidar_blocking=not args.no_lidar_blocking, log=logf)
    pubs = Publishers(node)
    await pubs.add("/fleet/state", "fleet/FleetState", queue_size=5)
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

    def on_goal(m) -> None:
        nonlocal flush_handle
        pending_goals[str(m.robot)] = int(m.cell)
        if flush_handle is None:
            flush_handle = loop.call_later(args.batch, flush_goals)

    def on_block(m) -> None:
        pubs.send(core.on_block(int(m.cell), bool(m.blocked), str(m.source)))

    async def add_robot(r: str) -> None:
        async with lock:
            if r in core.robots:
                return
            for topic, typ in (("goalNodesList", "std_msgs/Int32MultiArray"), ("cancelGoal", "std_msgs/Bool"),
                               ("clearance", "fleet/Clearance")):
                await pubs.add(f"/{r}/{topic}", typ, queue_size=20)

            def on_pose(m, r=r) -> None:
                p = m.pose.pose
                pubs.send(core.on_pose(r, p.position.x, p.position.y, yaw_from_quaternion(p.orientation)))

            def on_obstacles(m, r=r) -> None:
                pubs.send(core.on_obstacles(r, [(p.position.x, p.position.y) for p in m.poses]))

            def on_progress(m, r=r) -> None:
                core.on_progress(r, {"state": m.state, "distance_left": m.distance_left})

            await node.subscriber(f"/{r}/amcl_pose", "geometry_msgs/PoseWithCovarianceStamped", on_pose, queue_size=20)
            await node.subscriber(f"/{r}/obstacles", "geometry_msgs/PoseArray", on_obstacles, queue_size=5)
            await node.subscriber(f"/{r}/progress", "fleet/MoveProgress", on_progress, queue_size=5)
            core.add_robot(r)
            log.info("serving robot", robot=r)

    async def refresh_robots() -> None:
        robots = [r for r in args.robots.split(",") if r]
        if not robots:
            robots = await node.get_param(ROBOTS_PARAM, [])
        for r in robots or []:
            await add_robot(str(r))

    await refresh_robots()
    await node.subscriber("/fleet/goal", "fleet/RobotGoal", on_goal, queue_size=100)
    await node.subscriber("/fleet/block", "fleet/CellBlock", on_block, queue_size=100)
    log.info("global planner up", rows=geo.rows, cols=geo.cols, cell_w=round(geo.cell_w_m, 3),
             cell_h=round(geo.cell_h_m, 3), free=len(geo.free_cells()), robots=sorted(core.robots))

    period = 1.0 / max(args.rate, 0.1)
    last_refresh = loop.time()
    while not node.is_shutdown:
        pubs.send(core.tick())
        pubs.pubs["/fleet/state"].publish_nowait(core.state())
        if loop.time() - last_refresh > ROBOTS_REFRESH_S:
            last_refresh = loop.time()
            await refresh_robots()
        await asyncio.sleep(period)
