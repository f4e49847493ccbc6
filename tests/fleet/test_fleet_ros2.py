"""``rce-fleet demo --ros2``: the fleet with ROS 2 robots (:mod:`rce_fleet.live.ros2_robots`).

The demo as a subprocess (the engine as processes, each robot's ``rce-ros --ros2`` a process, the
robots' rclpy nodes in the simulator's process, each robot on a ROS 2 domain of its own), cut to a
short run by tasks on 3 robots: it ends with exit 0 and its KPIs, and meanwhile an rclpy node of this
test joins Robot1's domain (the one the demo printed) and takes its ``/odom``, ``/scan`` and
``/amcl_pose`` as their ROS 2 classes, with the robot's bridge ``/Robot1`` on the same graph. The
bridges' counts at the end say what crossed between ROS 2 and the cloud, both ways.

Synchronisation is on printed lines, messages taken and exits, each with a deadline; no sleeps.
"""
from __future__ import annotations

import json
import queue
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from rce.messages import default_registry
from rce_client.ros2_types import rclpy_class
from rce_fleet.configs import robot_config, ros2_config
from rce_fleet.live.points_wire import PointsWire

RCE_FLEET = Path(sys.executable).parent / "rce-fleet"
RUN_TIMEOUT_S = 240.0        # wall s the whole run may take (a loaded 2-core machine); the limit of a hang
LISTEN_S = 60.0              # wall s the test's node has to take each topic once
GOAL = "/move_base_simple/goal"
DOMAIN = re.compile(r"rce-fleet: Robot1: a ROS 2 robot on domain (\d+) ")
CARRIED = re.compile(r"carried (\d+) messages from ROS 2 to the cloud \((\d+) of them [^)]*\) and (\d+) to "
                     r"ROS 2, (\d+) dropped, (\d+) failed \((\d+) lost on the robots' graphs, their QoS keeping the "
                     r"newest\); the robots published (\d+) and took (\d+) "
                     r"\((\d+) dropped or refused\)")


def test_a_ros2_robots_config_names_ros2_classes_on_the_robot_side_only_and_rclpy_has_them():
    cfg = robot_config(2, placement="auto")
    r2 = ros2_config(cfg)
    robot_side = [it for it in r2["interfaces"] if it["eTag"] == "Robot2"]
    assert {it["iCls"] for it in robot_side} == {"geometry_msgs/msg/PoseWithCovarianceStamped",
                                                 "geometry_msgs/msg/PoseArray", "geometry_msgs/msg/PoseStamped",
                                                 "actionlib_msgs/msg/GoalID"}
    for it in robot_side:
        assert rclpy_class(it["iTag"], it["iCls"]).__name__ == it["iCls"].rsplit("/", 1)[1]
    cloud = [it for it in r2["interfaces"] if it["eTag"] != "Robot2"]
    assert cloud == [it for it in cfg["interfaces"] if it["eTag"] != "Robot2"]       # the cloud keeps ROS 1
    assert all(it["iCls"].count("/") == 1 for it in cfg["interfaces"])                # and the input is untouched


def test_a_ros2_robots_obstacles_are_the_cdr_the_registry_and_rclpy_read():
    from geometry_msgs.msg import PoseArray
    from rclpy.serialization import deserialize_message
    reg = default_registry()
    t = reg.msg_type("geometry_msgs/msg/PoseArray")
    for frame in ("map", "ab", "abc", "abcd", "odom_frame"):
        wire = PointsWire(frame, ros2=True)
        for xy in (np.array([[1.5, 2.5], [3.0, -1.25]]), np.zeros((0, 2))):
            b = wire.pack(12, 345, xy)
            msg = {"header": {"stamp": {"secs": 12, "nsecs": 345}, "frame_id": frame},
                   "poses": [{"position": {"x": x, "y": y, "z": 0.0}, "orientation": {"w": 1.0}} for x, y in xy]}
            assert b == reg.json_to_bytes(t, msg), frame
            m = deserialize_message(b, PoseArray)
            assert m.header.frame_id == frame and m.header.stamp.sec == 12 and m.header.stamp.nanosec == 345
            assert [(p.position.x, p.position.y, p.orientation.w) for p in m.poses] == [(x, y, 1.0) for x, y in xy]


def test_serve_ros2_refuses_relays_and_link_faults_by_name(tmp_path):
    for args, flag in ((("serve", "--robots", "2", "--out-of-coverage", "Robot2"), "--out-of-coverage"),
                       (("demo", "--mission", "--robots", "2", "--fault", "link:Robot1@3"), "--fault link:")):
        p = subprocess.run([str(RCE_FLEET), *args, "--ros2", "--headless"], capture_output=True, text=True,
                           timeout=60, cwd=tmp_path)
        assert p.returncode == 2 and f"--ros2 with {flag}" in p.stderr, p.stderr


def _lines(proc: subprocess.Popen, out: queue.Queue) -> None:
    for line in proc.stdout:
        out.put(line)
    out.put(None)


def _listen(domain: int, monkeypatch) -> dict[str, object]:
    """Take one message of each of Robot1's topics on its domain as their rclpy classes, and what the
    graph says of them (their types, the bridge's node); raises AssertionError after LISTEN_S."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, qos_profile_sensor_data
    from rclpy.signals import SignalHandlerOptions
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import LaserScan
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")      # rcl reads it at init
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("fleet_test_listener", context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    got: dict[str, object] = {}
    try:
        node.create_subscription(Odometry, "/odom", lambda m: got.setdefault("odom", m), 10)
        node.create_subscription(LaserScan, "/scan", lambda m: got.setdefault("scan", m), qos_profile_sensor_data)
        node.create_subscription(PoseWithCovarianceStamped, "/amcl_pose", lambda m: got.setdefault("pose", m),
                                 QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        deadline = time.monotonic() + LISTEN_S
        while time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.2)
            # the graph: a node's name comes with its participant's discovery info, maybe after its endpoints
            got["pose_readers"] = sorted(i.node_name for i in node.get_subscriptions_info_by_topic("/amcl_pose"))
            got["goal_writers"] = sorted(i.node_name for i in node.get_publishers_info_by_topic(GOAL))
            if {"odom", "scan", "pose"} <= got.keys() and "Robot1" in got["pose_readers"] \
                    and "Robot1" in got["goal_writers"]:
                break
        got["types"] = dict(node.get_topic_names_and_types())
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
    return got


def test_demo_ros2_runs_on_ros2_robots_and_ends_with_its_kpis(tmp_path, monkeypatch):
    report = tmp_path / "report.json"
    argv = [str(RCE_FLEET), "demo", "--ros2", "--robots", "3", "--duration", "20", "--headless", "--no-live",
            "--report", str(report), "--plot", str(tmp_path / "tasks.png"), "--workdir", str(tmp_path / "run"),
            "--timeout", str(RUN_TIMEOUT_S)]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path)
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=_lines, args=(proc, lines), daemon=True).start()
    out: list[str] = []
    try:
        deadline = time.monotonic() + RUN_TIMEOUT_S
        domain = None
        while domain is None:
            line = lines.get(timeout=max(0.1, deadline - time.monotonic()))
            assert line is not None, "".join(out)[-4000:]
            out.append(line)
            m = DOMAIN.match(line)
            domain = int(m.group(1)) if m else None
        got = _listen(domain, monkeypatch)
        while (line := lines.get(timeout=max(0.1, deadline - time.monotonic()))) is not None:
            out.append(line)
        code = proc.wait(timeout=max(0.1, deadline - time.monotonic()))
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = "".join(out)
    assert code == 0, text[-4000:]
    # the robot's messages on its ROS 2 graph, as their ROS 2 classes
    assert {"odom", "scan", "pose"} <= got.keys(), (sorted(got), text[-3000:])
    assert got["odom"].header.frame_id == "odom" and got["odom"].child_frame_id == "base_footprint"
    assert got["scan"].header.frame_id == "base_scan" and len(got["scan"].ranges) > 100
    assert got["pose"].header.frame_id == "map" and len(got["pose"].pose.covariance) == 36
    types = got["types"]
    assert types["/odom"] == ["nav_msgs/msg/Odometry"] and types["/scan"] == ["sensor_msgs/msg/LaserScan"]
    assert types["/amcl_pose"] == ["geometry_msgs/msg/PoseWithCovarianceStamped"]
    assert types["/move_base/cancel"] == ["actionlib_msgs/msg/GoalID"]
    assert "Robot1" in got["pose_readers"] and got["goal_writers"] == ["Robot1"]      # the bridge, rce-ros --ros2
    # the KPIs, as without --ros2, then what crossed between the robots' graphs and the cloud
    assert re.search(r"rce-fleet: tasks done \d+ in 2\d s sim", text) and "utilisation" in text, text[-3000:]
    m = CARRIED.search(text)
    assert m, text[-3000:]
    from_ros2, not_sent, to_ros2, dropped, failed, lost, published, took, refused = map(int, m.groups())
    # the bridges drop nothing; what a starved bridge's depth-1 /amcl_pose loses on the graph is counted apart
    per_interface = "".join(p.read_text() for p in sorted((tmp_path / "run" / "ros2").glob("Robot*.log")))
    assert from_ros2 > 100 and to_ros2 > 0 and dropped == failed == refused == 0, (m.group(0), per_interface)
    assert published >= from_ros2 > not_sent and took == to_ros2, m.group(0)
    rep = json.loads(report.read_text())      # written before the bridges stop: what the robots took by then
    goals = sum(r["waypoints_received"] for r in rep["per_robot"].values())
    cancels = sum(r["robot_cancels_received"] for r in rep["per_robot"].values())
    assert rep["ok"] and goals > 0 and goals + cancels <= took
