"""The ``fleet/move_client`` container node (one per robot, namespace ``RobotN``): I/O shell
around :class:`rce_fleet.nodes.move_client_core.MoveClientCore` (topics: see that module).

Arguments: ``[--robot RobotN] [--rate HZ]``; the robot ID defaults to the node's namespace.
Publishes ``/RobotN/move_base_simple/goal`` (geometry_msgs/PoseStamped),
``/RobotN/move_base/cancel`` (actionlib_msgs/GoalID) and ``/RobotN/progress``
(fleet/MoveProgress, on every change and at ``--rate``, default 2 Hz).
"""
from __future__ import annotations

import argparse
import asyncio

from rce.plumbing.log import get_logger, setup_logging
from rce.node import node_argv

from .move_client_core import MoveClientCore, plan_id_of
from .common import PlanarPose, Publishers, load_geometry, planar_pose

log = get_logger("fleet.move_client")


def parse_args(argv: list[str]) -> argparse.Namespace:
    """The node's arguments (see the module docstring)."""
    p = argparse.ArgumentParser(prog="move_client")
    p.add_argument("--robot", default="", help="robot ID (default: the node's namespace)")
    p.add_argument("--rate", type=float, default=2.0, help="progress rate, Hz (default 2)")
    return p.parse_args(argv)


async def main(node) -> None:
    """Run one robot's move client on ``node`` (an :class:`rce.node.Node`) until it shuts down."""
    setup_logging()
    args = parse_args(node_argv())
    robot = args.robot or node.namespace.strip("/").split("/")[-1]
    if not robot:
        raise SystemExit("move_client: no robot ID (pass --robot or run it in the robot's namespace)")
    geo = await load_geometry(node)
    core = MoveClientCore(robot, geo)
    pubs = Publishers(node)
    await pubs.add(core.goal_topic, "geometry_msgs/PoseStamped", queue_size=20)
    await pubs.add(core.cancel_topic, "actionlib_msgs/GoalID", queue_size=20)
    progress_topic = f"/{robot}/progress"
    await pubs.add(progress_topic, "fleet/MoveProgress", queue_size=10)
    last = None

    def report(force: bool = False) -> None:
        nonlocal last
        p = core.progress()
        key = (p["plan"], p["state"], p["index"], p["target"], p["cleared"], p["cell"])
        if force or key != last:
            last = key
            pubs.pubs[progress_topic].publish_nowait(p)

    def handle(outs) -> None:
        for o in outs:
            if o.topic == core.cancel_topic:
                log.info("cancel sent to the robot", robot=robot, plan=core.plan)
        pubs.send(outs)
        report()

    def on_path(msg) -> None:
        label = msg.layout.dim[0].label if len(msg.layout.dim) else ""
        handle(core.on_path(plan_id_of(label), [int(c) for c in msg.data]))

    def on_clearance(msg) -> None:
        handle(core.on_clearance(int(msg.plan), int(msg.index)))

    def on_cancel(msg) -> None:
        if msg.data:
            log.info("cancelGoal", robot=robot, plan=core.plan)
        handle(core.on_cancel(bool(msg.data)))

    def on_pose(pose: PlanarPose) -> None:
        handle(core.on_pose(*pose))

    # cancel first: the planner publishes cancelGoal before the new path, keep that order
    await node.subscriber(f"/{robot}/cancelGoal", "std_msgs/Bool", on_cancel, queue_size=20)
    await node.subscriber(f"/{robot}/goalNodesList", "std_msgs/Int32MultiArray", on_path, queue_size=20)
    await node.subscriber(f"/{robot}/clearance", "fleet/Clearance", on_clearance, queue_size=20)
    await node.subscriber(f"/{robot}/amcl_pose", "geometry_msgs/PoseWithCovarianceStamped", on_pose, queue_size=5,
                          decode=planar_pose)
    log.info("move_client up", robot=robot)
    while not node.is_shutdown:
        report(force=True)
        await asyncio.sleep(1.0 / max(args.rate, 0.1))
