"""``rce-ros CONFIG --ros2`` against a real ROS 2 graph (rclpy, Fast DDS).

The real engine (``engine`` fixture), ``rce-ros --ros2`` as a real process, and plain rclpy programs
(``tests/client/ros2/robot.py``, separate processes) as the robot's ROS 2 side, all on a ROS 2 domain
of the test's own (:func:`ros2_domain`: an ID held by a lock file, discovery on this host only), so
that tests in parallel never see each other. In the container:

- the Test package's ``stringEcho.py`` (a ROS 1 node: ``std_msgs/String``) twice, in ``/fwd`` (reached
  through forwarders) and ``/conv`` (converters): the robot's ROS 2 ``std_msgs/msg/String`` goes to a
  ROS 1 node and back, the engine converting;
- loops on the container's bus, no node: a service (a ServiceClientInterface calling the
  ServiceProviderInterface at the same address), an action (an ActionClientInterface whose parts call
  and hear an ActionProviderInterface's) and a topic. So the robot's rclpy client calls the cloud and
  the cloud calls the robot's rclpy server, and a Nav2-style rclpy ActionClient on the robot drives an
  unchanged rclpy ActionServer on the robot, every part through the cloud.

Synchronisation is on printed lines and exits, each with a deadline; no sleeps."""
from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import sys
from pathlib import Path

import pytest

from rce.interfaces.qos import QoS
from rce.plumbing.errors import ConfigError
from rce_client.ros2_spin import NoAnswer, Spinner
from rce.ros2.classes import qos_profile
from rce.ros2.domains import lease_domain
from rce_client.ros2_types import node_name, rclpy_class

from .test_e2e_debug import BIN, Proc

STEP = 60.0                  # s for one step (a loaded 2-core machine)
ROBOT = "ros2Robot"
CTAG = "cRos2"
ROBOT_PY = Path(__file__).parent / "ros2" / "robot.py"


@pytest.fixture
def ros2_domain():
    """A ROS 2 domain ID no other test or container of this machine holds, held while the test runs
    (:func:`rce.ros2.domains.lease_domain`)."""
    lease = lease_domain()
    try:
        yield lease.domain
    finally:
        lease.release()


@pytest.fixture
def ros2_env(ros2_domain, tmp_path):
    """The environment of every ROS 2 process of a test: its domain, discovery on this host only, logs in tmp."""
    return dict(os.environ, ROS_DOMAIN_ID=str(ros2_domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                ROS_LOG_DIR=str(tmp_path / "ros_log"), RCE_LOG_JSON="1")


ROBOT_SIDE = [  # iTag, robot iType, robot class, robot addr, container iType, container class, container addr, qos
    ("chat", "SubscriberForwarder", "std_msgs/msg/String", "/chatter",
     "PublisherInterface", "std_msgs/String", "/fwd/stringEchoReq", None),
    ("chatBack", "PublisherForwarder", "std_msgs/msg/String", "/chatter_back",
     "SubscriberInterface", "std_msgs/String", "/fwd/stringEchoResp", None),
    ("convReq", "SubscriberConverter", "std_msgs/msg/String", "/conv_req",
     "PublisherInterface", "std_msgs/String", "/conv/stringEchoReq", None),
    ("convResp", "PublisherConverter", "std_msgs/msg/String", "/conv_resp",
     "SubscriberInterface", "std_msgs/String", "/conv/stringEchoResp", None),
    ("svcIn", "ServiceProviderConverter", "std_srvs/srv/SetBool", "/svc_in",
     "ServiceClientInterface", "std_srvs/srv/SetBool", "/loop/set_bool", None),
    ("svcOut", "ServiceClientForwarder", "std_srvs/srv/SetBool", "/svc_out",
     "ServiceProviderInterface", "std_srvs/srv/SetBool", "/loop/set_bool", None),
    ("fibIn", "ActionProviderForwarder", "test_msgs/action/Fibonacci", "/fib_in",
     "ActionClientInterface", "test_msgs/action/Fibonacci", "/loop/fib", None),
    ("fibOut", "ActionClientForwarder", "test_msgs/action/Fibonacci", "/fib_out",
     "ActionProviderInterface", "test_msgs/action/Fibonacci", "/loop/fib", None),
    ("mapIn", "SubscriberForwarder", "std_msgs/msg/String", "/map_in",
     "PublisherInterface", "std_msgs/msg/String", "/loop/map", None),
    ("map", "PublisherForwarder", "std_msgs/msg/String", "/map",
     "SubscriberInterface", "std_msgs/msg/String", "/loop/map", "map"),
    ("beOut", "PublisherForwarder", "std_msgs/msg/String", "/be_out",
     "SubscriberInterface", "std_msgs/msg/String", "/loop/map", "sensor_data"),
]
ROBOT_INTERFACES = sum(5 if "Action" in itype else 1 for _, itype, *_ in ROBOT_SIDE)


def _config(master_url: str) -> dict:
    itfs, links = [], []
    for tag, itype, cls, addr, c_itype, c_cls, c_addr, qos in ROBOT_SIDE:
        itfs.append({"eTag": ROBOT, "iTag": tag, "iType": itype, "iCls": cls, "addr": addr,
                     **({"qos": qos} if qos else {})})
        itfs.append({"eTag": CTAG, "iTag": tag, "iType": c_itype, "iCls": c_cls, "addr": c_addr})
        links.append({"tagA": f"{CTAG}/{tag}", "tagB": f"{ROBOT}/{tag}"})
    return {"url": master_url, "userID": "testUser", "password": "testUser", "robotID": ROBOT,
            "containers": [{"cTag": CTAG}],
            "nodes": [{"cTag": CTAG, "nTag": f"echo_{ns}", "pkg": "Test", "exe": "stringEcho.py", "namespace": f"/{ns}"}
                      for ns in ("fwd", "conv")],
            "interfaces": itfs, "connections": links}


async def robot(env: dict, *args: str) -> list[str]:
    """Run one mode of the robot's rclpy program to its end; its stdout lines (it must exit 0)."""
    p = await Proc.start(sys.executable, str(ROBOT_PY), *args, env=env)
    assert await p.wait(STEP + 30) == 0, p.dump()
    return p.lines["out"]


async def test_ros2_graph_through_the_cloud(engine, ros2_env, tmp_path):
    cfg = tmp_path / "ros2.config"
    cfg.write_text(json.dumps(_config(engine.master_url)))
    ros = await Proc.start(str(BIN / "rce-ros"), str(cfg), "--ros2", "--timeout", "90", env=ros2_env)
    servers = None
    try:
        await ros.wait_line(rf"^rce-ros: ROS 2 node /{ROBOT} on domain {ros2_env['ROS_DOMAIN_ID']}$")
        await ros.wait_line(rf"^rce-ros: ready \({ROBOT_INTERFACES} interface\(s\) up", timeout=120)
        servers = Proc(await asyncio.create_subprocess_exec(
            sys.executable, str(ROBOT_PY), "serve", "/svc_out", "/fib_out", env=ros2_env,
            stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE),
            "robot.py serve")
        await servers.wait_line(r"^serving$", timeout=STEP)

        # a ROS 2 talker through the cloud's ROS 1 stringEcho and back (forwarders: CDR <-> ROS 1 in the engine)
        assert await robot(ros2_env, "talk", "/chatter", "/chatter_back", "hello", "world") == \
            ["back: hello", "back: world"]
        # bytes that are no std_msgs/msg/String on a converter: refused, named; the converter goes on
        assert await robot(ros2_env, "bad", "/conv_req") == ["published bad bytes"]
        assert await robot(ros2_env, "talk", "/conv_req", "/conv_resp", "still converting") == \
            ["back: still converting"]

        # services both ways: the robot's client -> the cloud -> the robot's server
        assert await robot(ros2_env, "call", "/svc_in") == ["answer: success=True message=robot got True"]

        # an action both ways: goal, feedback, result; then a goal cancelled on its way
        lines = await robot(ros2_env, "goals", "/fib_in")
        assert lines[:2] == ["goal order=5 accepted=True",
                             "result: status=4 sequence=[0, 1, 1, 2, 3, 5] feedback=[[0, 1, 1], [0, 1, 1, 2], "
                             "[0, 1, 1, 2, 3], [0, 1, 1, 2, 3, 5]]"], lines
        assert lines[2:4] == ["goal order=45 accepted=True", "cancel: return_code=0 canceling=1"], lines
        assert lines[4].startswith("result: status=5 sequence=[0, 1, 1, 2") and lines[4].endswith(
            "feedbacks>=2=True"), lines

        # transient local: a subscriber joining after the message still gets it
        assert await robot(ros2_env, "latched", "/map_in", "/map", "map v1") == ["early: map v1", "late: ['map v1']"]
        # an incompatible QoS pair (the robot's reliable subscription, the bridge's best-effort publisher): reported
        assert await robot(ros2_env, "reliable", "/be_out") == ["incompatible QoS: RMW_QOS_POLICY_RELIABILITY"]
        await ros.wait_line(r"^rce-ros: ROS 2 beOut: QoS incompatible with a subscription on /be_out \(RELIABILITY; "
                            r"1 in all\): the bridge's publisher is best_effort, volatile, keep_last 5")

        ros.p.send_signal(signal.SIGINT)
        assert await ros.wait(STEP) == 0, ros.dump()
        text = ros.text()
        assert "rce-ros: convReq: 1 message(s) not sent to the cloud (1 refused)" in text, ros.dump()
        bad = [json.loads(line) for line in ros.lines["err"] if "message not sent to the cloud" in line]
        assert [b["itag"] for b in bad] == ["convReq"], bad
        assert "do not deserialize as std_msgs/msg/String" in bad[0]["reason"], bad
        for line in ("ROS 2 chat: 2 from ROS 2, 0 to ROS 2, 0 dropped, 0 failed",
                     "ROS 2 chatBack: 0 from ROS 2, 2 to ROS 2, 0 dropped, 0 failed",
                     "ROS 2 convReq: 2 from ROS 2, 0 to ROS 2, 0 dropped, 0 failed",
                     "ROS 2 svcIn: 1 from ROS 2, 0 to ROS 2, 0 dropped, 0 failed",
                     "ROS 2 svcOut: 1 from ROS 2, 1 to ROS 2, 0 dropped, 0 failed",
                     "ROS 2 fibIn.send_goal: 2 from ROS 2, 0 to ROS 2, 0 dropped, 0 failed",
                     "ROS 2 fibOut.get_result: 2 from ROS 2, 2 to ROS 2, 0 dropped, 0 failed",
                     "ROS 2 fibOut.cancel_goal: 1 from ROS 2, 1 to ROS 2, 0 dropped, 0 failed",
                     "ROS 2 beOut: 0 from ROS 2, 1 to ROS 2, 0 dropped, 0 failed, 1 QoS incompatible",
                     f"removed {ROBOT_INTERFACES} interface(s), destroyed 1 container(s)"):
            assert f"rce-ros: {line}\n" in text, (line, ros.dump())
    finally:
        await ros.kill()
        if servers is not None:
            servers.p.stdin.close()
            try:
                assert await servers.wait(STEP) == 0, servers.dump()
            finally:
                await servers.kill()


async def test_what_the_robots_graph_replaced_before_a_starved_bridge_took_it_is_counted_lost(engine, ros2_env,
                                                                                                 tmp_path):
    """A writer as amcl's (reliable, transient local, depth 1) at 1 kHz, the bridge stopped (SIGSTOP) for
    4,000 of its messages: Fast DDS replaces what the bridge did not acknowledge and reports it lost. The
    bridge logs and counts it apart from its own drops (none), and goes on."""
    cfg = tmp_path / "flood.config"
    cfg.write_text(json.dumps({
        "url": engine.master_url, "userID": "testUser", "password": "testUser", "robotID": ROBOT,
        "containers": [{"cTag": CTAG}],
        "interfaces": [{"eTag": ROBOT, "iTag": "pose", "iType": "SubscriberForwarder", "iCls": "std_msgs/msg/String",
                        "addr": "/pose", "qos": "map"},
                       {"eTag": CTAG, "iTag": "pose", "iType": "PublisherInterface", "iCls": "std_msgs/msg/String",
                        "addr": "/loop/pose"}],
        "connections": [{"tagA": f"{CTAG}/pose", "tagB": f"{ROBOT}/pose"}]}))
    ros = await Proc.start(str(BIN / "rce-ros"), str(cfg), "--ros2", "--timeout", "90", env=ros2_env)
    writer = None
    try:
        await ros.wait_line(r"^rce-ros: ready \(1 interface\(s\) up", timeout=120)
        writer = Proc(await asyncio.create_subprocess_exec(
            sys.executable, str(ROBOT_PY), "flood", "/pose", env=ros2_env, stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE), "robot.py flood")
        await writer.wait_line(r"^matched$", timeout=STEP)
        for attempt in range(3):          # Fast DDS tells the reader at the writer's next heartbeat (3 s)
            await writer.wait_line(r"^published \d+$", timeout=STEP)
            at = max(int(w.split()[1]) for w in writer.lines["out"] if w.startswith("published "))
            ros.p.send_signal(signal.SIGSTOP)
            try:
                await writer.wait_line(rf"^published {at + 4000}$", timeout=STEP)
            finally:
                ros.p.send_signal(signal.SIGCONT)
            try:
                await ros.wait_line(r'"msg": "messages lost on the robot\'s graph before the bridge took them"',
                                    key="err", timeout=10)
                break
            except AssertionError:
                assert attempt < 2, ros.dump()
        writer.p.stdin.close()
        assert await writer.wait(STEP) == 0, writer.dump()
        ros.p.send_signal(signal.SIGINT)
        assert await ros.wait(STEP) == 0, ros.dump()
        line = await ros.wait_line(r"^rce-ros: ROS 2 pose: ")
        m = re.fullmatch(r"rce-ros: ROS 2 pose: (\d+) from ROS 2, 0 to ROS 2, 0 dropped, 0 failed, (\d+) lost on the "
                         r"robot's graph", line)
        assert m and int(m.group(1)) > 0 and int(m.group(2)) > 0, ros.dump()
        reported = sum(json.loads(e)["lost"] for e in ros.lines["err"] if "lost on the robot's graph" in e)
        assert reported == int(m.group(2)), ros.dump()
        assert "rce-ros: removed 1 interface(s), destroyed 1 container(s)" in ros.text(), ros.dump()
    finally:
        if ros.p.returncode is None:
            ros.p.send_signal(signal.SIGCONT)
        await ros.kill()
        if writer is not None:
            await writer.kill()


@pytest.mark.parametrize("itype, cls, error", [
    ("SubscriberConverter", "std_msgs/String", "interface chat (std_msgs/String): --ros2 bridges ROS 2 classes only, "
     "named pkg/msg/Type, pkg/srv/Type or pkg/action/Type (its ROS 2 name is e.g. std_msgs/msg/String"),
    ("SubscriberForwarder", "nopkg/msg/Nothing", "interface chat (nopkg/msg/Nothing): no rclpy class: the Python "
     "module nopkg.msg is not installed"),
    ("ServiceClientForwarder", "std_msgs/msg/String", "interface chat (std_msgs/msg/String): a ServiceClientForwarder "
     "needs a service class"),
    ("PublisherForwarder", "std_msgs/msg/String", "interfaces tap and chat are both at /chat: on a ROS 2 graph the "
     "bridge would take what it publishes there and send it to the cloud again"),
])
async def test_classes_rclpy_cannot_bridge_are_refused_before_login(tmp_path, ros2_env, itype, cls, error):
    """A ROS 1 class, a class rclpy does not have, a message class for a service, a topic the bridge would
    both publish and take: exit 2 naming the interface and the class, before anything is sent (the
    config's URL is a closed port)."""
    cfg = tmp_path / "ros2.config"
    itfs = [{"eTag": ROBOT, "iTag": "chat", "iType": itype, "iCls": cls, "addr": "/chat"}]
    if itype == "PublisherForwarder":
        itfs.insert(0, {"eTag": ROBOT, "iTag": "tap", "iType": "SubscriberForwarder", "iCls": cls, "addr": "/chat"})
    cfg.write_text(json.dumps({"url": "http://127.0.0.1:9/", "userID": "u", "password": "p", "robotID": ROBOT,
                               "interfaces": itfs}))
    p = await Proc.start(str(BIN / "rce-ros"), str(cfg), "--ros2", env=ros2_env)
    assert await p.wait(STEP) == 2, p.dump()
    assert f"rce-ros: {cfg}: {error}" in p.human_err() and "logging in" not in p.text(), p.dump()


# -- without a graph ------------------------------------------------------------------------------
def test_rclpy_classes_of_names_and_action_parts():
    from action_msgs.msg import GoalStatusArray
    from action_msgs.srv import CancelGoal
    from std_msgs.msg import String
    from test_msgs.action import Fibonacci
    assert rclpy_class("a", "std_msgs/msg/String") is String
    assert rclpy_class("a", "/action_msgs/srv/CancelGoal") is CancelGoal
    assert rclpy_class("a", "action_msgs/msg/GoalStatusArray") is GoalStatusArray
    for part, cls in (("SendGoal", Fibonacci.Impl.SendGoalService), ("GetResult", Fibonacci.Impl.GetResultService),
                      ("FeedbackMessage", Fibonacci.Impl.FeedbackMessage), ("Goal", Fibonacci.Goal)):
        assert rclpy_class("a", f"test_msgs/action/Fibonacci_{part}") is cls
    with pytest.raises(ConfigError, match=r"^interface nav.send_goal \(test_msgs/action/Nothing_SendGoal\): no rclpy "
                                          r"class: test_msgs.action has no Nothing$"):
        rclpy_class("nav.send_goal", "test_msgs/action/Nothing_SendGoal")
    with pytest.raises(ConfigError, match=r"^interface a \(std_msgs/msg/Nothing\): no rclpy class: std_msgs.msg has "
                                          r"no Nothing$"):
        rclpy_class("a", "std_msgs/msg/Nothing")


def test_qos_profiles_and_node_names():
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy, qos_profile_sensor_data
    default = qos_profile(None)
    assert (default.reliability, default.durability, default.history, default.depth) == (
        ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE, HistoryPolicy.KEEP_LAST, 10)
    sensor = qos_profile(QoS(reliability="best_effort", depth=5))
    assert (sensor.reliability, sensor.durability, sensor.depth) == (
        qos_profile_sensor_data.reliability, qos_profile_sensor_data.durability, qos_profile_sensor_data.depth)
    latched = qos_profile(QoS(durability="transient_local", history="keep_all"))
    assert (latched.durability, latched.history) == (DurabilityPolicy.TRANSIENT_LOCAL, HistoryPolicy.KEEP_ALL)
    assert [node_name(r) for r in ("robot1", "my-robot.2", "7up")] == ["robot1", "my_robot_2", "rce_7up"]


async def test_executor_goes_on_past_failing_and_unanswered_calls(ros2_domain, monkeypatch):
    """The bridge's rclpy thread (:class:`Spinner`): a service call left unanswered (NoAnswer) and one whose
    callback fails end alone; the next call, answered from the asyncio loop while the executor waits, still is."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from std_srvs.srv import SetBool
    monkeypatch.setenv("ROS_DOMAIN_ID", str(ros2_domain))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    loop = asyncio.get_running_loop()
    spinner = Spinner("unit_bridge")
    spinner.start()
    outcomes = iter(["no answer", "fail", "answer"])

    async def serve(request, response):                 # in rclpy's thread
        what = next(outcomes)
        if what == "no answer":
            raise NoAnswer("/unit")
        if what == "fail":
            raise ValueError("a fault in one callback")
        fut = asyncio.run_coroutine_threadsafe(asyncio.sleep(0, result="from the loop"), loop)
        response.success, response.message = True, (await spinner.rclpy_future(fut)).result()
        return response
    spinner.node.create_service(SetBool, "/unit", serve, callback_group=spinner.group)

    ctx = Context()                                      # the robot's own program, with its own context
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("unit_robot", context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        client = node.create_client(SetBool, "/unit")
        assert await asyncio.to_thread(client.wait_for_service, timeout_sec=STEP)
        calls = [client.call_async(SetBool.Request(data=True)) for _ in range(3)]
        await asyncio.to_thread(executor.spin_until_future_complete, calls[2], timeout_sec=STEP)
        assert calls[2].result().message == "from the loop"
        assert not calls[0].done() and not calls[1].done() and spinner.callback_errors == 1
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        await asyncio.to_thread(spinner.close, 5.0)
