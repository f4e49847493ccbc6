"""ROS 2 nodes in containers.

Plain rclpy nodes (``tests/ros2_packages/rce_ros2_test``, written for ROS 2 only) run in the
containers of a real engine, wired to a robot through the client protocol (CN, CX, converters):
a topic round trip, a service, CN parameters read with ``declare_parameter`` at the start and set
on the running node later, a transient-local message published before anyone read it, a QoS the
relay cannot match told to the robot on ST. An unchanged rclpy ActionClient in one container
drives an unchanged ActionServer in another (goal, feedback, result, cancel) through both relays
and the engine. Two containers whose nodes share a topic name do not hear each other, and an
rclpy node of the host on the containers' own domain id finds nothing of theirs. In the unconfined
sandbox (no network namespace) the relay runs on a leased domain id. The rules (which package is
ROS 2, its arguments and parameters, what the relay bridges with which QoS, what the robot is
told) are tested without I/O.
"""
from __future__ import annotations

import asyncio
import json
import os
import sys
import time
from pathlib import Path

import pytest

from rce.bus.core import Bus
from rce.bus.server import BusServer
from rce.interfaces.actions import expand_interface
from rce.interfaces.qos import QoS
from rce.messages import default_registry
from rce.plumbing.errors import NotFound, RequestError
from rce.tools.launch import start_engine
from rce_container.launcher import Launcher
from rce_container.ros1_plan import GraphView, bus_graph
from rce.ros2.domains import lease_domain
from rce_container.ros2_graph import Ros2Graph
from rce_container.ros2_plan import (LATCHED_DEPTH, SUB_DEPTH, Endpoint, Ros2View, domain_of, interface_statuses,
                                     is_ros2_package, node_args, offer_for, plan, relay_name, request_for,
                                     ros2_parameters, status_changes)
from rce_container.sandbox import ProcessGroupSandbox
from wsclient import RawRobot

ROS2_PACKAGES = Path(__file__).resolve().parents[1] / "ros2_packages"
ME = relay_name(1)
REG = default_registry()
STRING = REG.msg_type("std_msgs/msg/String")
STEP = 40.0   # s, the longest one wait may take (a relay and a node start in ~2 s; the machine is shared)
RELIABLE, BEST_EFFORT = QoS(), QoS(reliability="best_effort")
LATCHED = QoS(durability="transient_local", depth=1)


# -- rules, no I/O -----------------------------------------------------------------------------
@pytest.mark.parametrize("xml, ros2", [
    ('<package format="3"><name>a</name><exec_depend>rclpy</exec_depend></package>', True),
    ('<package format="2"><name>a</name><depend>rclcpp</depend></package>', True),
    ('<package format="3"><name>a</name><depend>rospy</depend></package>', False),
    ('<package format="3"><name>a</name><test_depend>rclpy</test_depend></package>', False),
])
def test_package_xml_marks_ros2_packages(tmp_path, xml, ros2):
    (tmp_path / "package.xml").write_text(xml)
    assert is_ros2_package(tmp_path) is ros2
    assert is_ros2_package(ROS2_PACKAGES / "rce_ros2_test") is True
    (tmp_path / "package.xml").write_text("<package><name>a")
    with pytest.raises(RequestError, match="package.xml"):
        is_ros2_package(tmp_path)


def test_node_arguments_and_parameters_as_ros2_launch_gives_them():
    assert node_args("talker", "/robot", "/w/p.yaml") == [
        "--ros-args", "-r", "__node:=talker", "-r", "__ns:=/robot", "--params-file", "/w/p.yaml"]
    params, skipped = ros2_parameters({"/prefix": "p:", "/robot/speed": 1.5, "/ids": [1, 2], "/gains": [1, 2.5],
                                       "/on": True, "/bad-name": 1, "/empty": [], "/mixed": [1, "a"],
                                       "/huge": 2**70, "/none": None})
    assert params == {"prefix": "p:", "robot.speed": 1.5, "ids": [1, 2], "gains": [1.0, 2.5], "on": True}
    assert set(skipped) == {"/bad-name", "/empty", "/mixed", "/huge", "/none"}
    assert "empty list" in skipped["/empty"] and "64 bits" in skipped["/huge"]
    # every container gets a domain id of its own, never 0 (every ROS 2 program's default)
    assert domain_of(1) != domain_of(2) and 0 not in {domain_of(c) for c in range(300)}


def _ros(pubs=(), subs=(), types=(), srvs=()) -> Ros2View:
    return Ros2View({t: list(es) for t, es in pubs}, {t: list(es) for t, es in subs}, dict(types),
                    {s: n for s, n, _ in srvs}, {s: t for s, _, t in srvs})


def test_plan_bridges_topics_services_and_an_actions_parts_with_matching_qos():
    bus = bus_graph({"topics": [
        {"name": "/in", "type": "std_msgs/msg/String", "publishers": ["interface:in"], "subscribers": []},
        {"name": "/map", "type": "std_msgs/msg/String", "publishers": [], "subscribers": ["interface:map"]},
        {"name": "/fib/_action/feedback", "type": "test_msgs/action/Fibonacci_FeedbackMessage",
         "publishers": [], "subscribers": ["interface:fib.feedback"]}],
        "services": [{"name": "/bus_srv", "type": "std_srvs/srv/Trigger", "provider": "/rce_node"},
                     {"name": "/ros1_srv", "type": "rce_ros1_test/Echo", "provider": "/rce_ros1_relay_c1"},
                     {"name": f"{ME}/sync", "type": "std_srvs/Empty", "provider": ME}]})
    ros = _ros(pubs=[("/map", [Endpoint("/map_server", LATCHED), Endpoint("/other", LATCHED)]),
                     ("/fib/_action/feedback", [Endpoint("/fib_server", RELIABLE)])],
               subs=[("/in", [Endpoint("/echo", BEST_EFFORT), Endpoint("/echo2", LATCHED)])],
               types=[("/map", "std_msgs/msg/String"), ("/in", "std_msgs/msg/String"),
                      ("/fib/_action/feedback", "test_msgs/action/Fibonacci_FeedbackMessage")],
               srvs=[("/fib/_action/send_goal", "/fib_server", "test_msgs/action/Fibonacci_SendGoal"),
                     ("/fib_server/set_parameters", "/fib_server", "rcl_interfaces/srv/SetParameters")])
    p = plan(bus, ros, ME)
    # bus -> ROS 2: offers what the subscriptions need (one reliable and latched: reliable, latched)
    assert p.to_ros == {"/in": ("std_msgs/msg/String", QoS(durability="transient_local", depth=LATCHED_DEPTH))}
    # ROS 2 -> bus: takes what every publisher offers; the action's hidden feedback topic too
    assert p.to_bus == {"/map": ("std_msgs/msg/String", QoS(durability="transient_local", depth=SUB_DEPTH)),
                        "/fib/_action/feedback": ("test_msgs/action/Fibonacci_FeedbackMessage",
                                                  QoS(depth=SUB_DEPTH))}
    # an action's service goes to the bus, a node's parameter service stays; a bus service goes to
    # ROS 2 unless its class is ROS 1's (and never the relay's own)
    assert p.services_to_bus == {"/fib/_action/send_goal": "test_msgs/action/Fibonacci_SendGoal"}
    assert p.services_to_ros == {"/bus_srv": "std_srvs/srv/Trigger"}


def test_qos_of_the_relay_matches_every_endpoint_and_names_what_it_cannot():
    assert request_for([RELIABLE, BEST_EFFORT]).reliability == "best_effort"
    assert request_for([LATCHED, RELIABLE]).durability == "volatile"
    assert request_for([LATCHED]) == QoS(durability="transient_local", depth=SUB_DEPTH)
    assert offer_for([BEST_EFFORT]).reliability == "best_effort" and offer_for([]).durability == "volatile"
    # a subscription asking for a deadline: bridged for the others, and said which and why
    bus = GraphView(publishers={"/strict": {"interface:strict"}}, types={"/strict": "std_msgs/msg/String"})
    ros = _ros(subs=[("/strict", [Endpoint("/n", RELIABLE, "a deadline of 1 s"), Endpoint(ME, RELIABLE)])],
               types=[("/strict", "std_msgs/msg/String")])
    p = plan(bus, ros, ME)
    assert "/strict" in p.to_ros and "/n asks for a deadline of 1 s" in p.incompatible["/strict"]
    # a ROS 1 class on the bus against a ROS 2 type: left alone, said why
    bus = GraphView(publishers={"/c": {"interface:c"}}, types={"/c": "std_msgs/String"})
    p = plan(bus, _ros(subs=[("/c", [Endpoint("/n", RELIABLE)])], types=[("/c", "std_msgs/msg/String")]), ME)
    assert p.to_ros == {} and "std_msgs/msg/String in ROS 2" in p.conflicts["/c"]


def test_the_robot_is_told_each_change_of_an_interfaces_bridging():
    stats = {"incompatible": {"/strict": "x asks for a deadline"}, "problems": {"/c": "type conflict", "/strict": "y"}}
    now = interface_statuses({1: "/strict", 2: "/c", 3: "/fine"}, stats)
    assert now == {1: ("incompatible_qos", "ROS 2 /strict: x asks for a deadline"),
                   2: ("not_bridged", "ROS 2 /c: type conflict")}
    assert status_changes({}, now) == now and status_changes(now, now) == {}
    assert status_changes(now, {2: now[2]}) == {1: ("ok", "")}


def test_domain_leases_are_exclusive_and_skip_the_hosts_own(tmp_path, monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", "1")
    a, b = lease_domain(tmp_path), lease_domain(tmp_path)
    assert 1 not in (a.domain, b.domain) and a.domain != b.domain
    a.release()
    c = lease_domain(tmp_path)
    assert c.domain == a.domain
    b.release()
    c.release()


# -- the graph on its own, in the unconfined sandbox (no network namespace: a leased domain) ---
class _Iface:
    def __init__(self, iid: int, tag: str, addr: str):
        self.iid, self.tag, self.addr = iid, tag, addr


async def _until(cond, what: str, timeout: float = STEP):
    deadline = time.monotonic() + timeout
    while not (got := cond()):
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.05)
    return got


@pytest.mark.timeout(120)
async def test_ros2_graph_in_an_unconfined_sandbox(tmp_path, monkeypatch):
    monkeypatch.setenv("RCE_PACKAGE_PATH", str(ROS2_PACKAGES))
    bus = Bus("test")
    server = BusServer(bus)
    await server.listen(str(tmp_path / "bus.sock"))
    (tmp_path / "c1").mkdir()
    sandbox = ProcessGroupSandbox(1, "uc", {}, tmp_path / "c1", grace=1.0)
    launcher = Launcher(sandbox, str(tmp_path / "bus.sock"), "uc", lambda *a, **kw: None)
    told = []
    ifaces = {7: _Iface(7, "uc/strict", "/ns/strict")}
    graph = Ros2Graph(launcher, 1, bus, lambda: ifaces, lambda *a: told.append(a))
    try:
        bus.set_param("/prefix", "u:")
        spec = {"ntag": "echo", "pkg": "rce_ros2_test", "exe": "echo_node.py", "namespace": "/ns"}
        kind = await graph.prepare(spec)
        assert kind["env"]["ROS_DOMAIN_ID"] != os.environ.get("ROS_DOMAIN_ID", "0")
        assert kind["env"]["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
        assert kind["args"][:5] == ["--ros-args", "-r", "__node:=echo", "-r", "__ns:=/ns"]
        await launcher.add(spec, kind)
        got: list[bytes] = []
        bus.subscribe("/ns/out", "std_msgs/msg/String", lambda b: got.append(bytes(b)) or True, "test")
        topic = bus.advertise("/ns/in", "std_msgs/msg/String", "test")
        strict = bus.advertise("/ns/strict", "std_msgs/msg/String", "test")
        deadline = time.monotonic() + STEP
        while not got:
            assert time.monotonic() < deadline, f"no republication; relay: {graph.info()} {list(graph.output)}"
            bus.publish(topic, REG.json_to_bytes(STRING, {"data": "x"}))
            await asyncio.sleep(0.2)
        assert REG.bytes_to_json(STRING, got[0]) == {"data": "u:x"}
        # bytes that are no String do not reach (nor stop) the node: refused, counted
        bus.publish(topic, b"\x00\x01\x00\x00\xff\xff\xff\x7f")
        req_t, resp_t = REG.srv_types("std_srvs/srv/SetBool")
        resp = await bus.call_service("/ns/set_flag", REG.json_to_bytes(req_t, {"data": True}), wait=STEP)
        assert REG.bytes_to_json(resp_t, resp) == {"success": True, "message": "u:True@/ns/echo"}
        assert strict is not None
        await _until(lambda: told, "the robot told of /ns/strict")
        assert told[0][:3] == (7, "uc/strict", "incompatible_qos") and "deadline" in told[0][3], told
        await graph.sync()
        relay = graph.info()["relay"]
        assert relay["to_bus"] >= 1 and relay["refused_to_ros"] == 1 and relay["calls"] == 1, relay
        pid = graph.info()["pids"]["relay"]
        await launcher.remove("echo")
        await graph.node_gone("echo")
        assert not graph.running and graph.lease is None
        assert not os.path.exists(f"/proc/{pid}") or open(f"/proc/{pid}/stat").read().split()[2] == "Z"
    finally:
        await launcher.close()
        await graph.close()
        await server.close()


# -- a real engine -----------------------------------------------------------------------------
NEEDS_ROOT = "the namespaced sandbox needs root; CI runs the test suite as root (run these tests as root)"


@pytest.fixture(scope="module")
def ros2_engine(tmp_path_factory):
    """An engine whose package path has the ROS 2 test package, its containers namespaced (their
    graphs' isolation is the network namespace's)."""
    assert os.geteuid() == 0, NEEDS_ROOT
    e = start_engine(tmp_path_factory.mktemp("engine"), env={"RCE_PACKAGE_PATH": str(ROS2_PACKAGES)},
                     container_args=("--sandbox", "namespaced"))
    yield e
    e.stop()


class Inbox:
    """A robot's frames, kept until a test looks for them (``RawRobot.expect`` skips the others)."""

    def __init__(self, robot: RawRobot):
        self.robot, self.frames = robot, []

    async def find(self, type_: str, pred=lambda d: True, timeout: float = STEP) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            for i, f in enumerate(self.frames):
                if f.get("type") == type_ and pred(f["data"]):
                    return self.frames.pop(i)["data"]
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"no {type_} as asked; frames: {self.frames[-10:]}")
            try:
                m = await self.robot.recv(left)
            except TimeoutError:
                continue
            if isinstance(m, dict):
                self.frames.append(m)

    async def up(self, *itags: str) -> None:
        for t in itags:
            await self.find("ST", lambda d, t=t: d.get("topic") == "iu" and d.get("iTag") == t and d.get("status"))


def _iface(etag: str, itag: str, itype: str, cls: str, addr: str | None = None) -> dict:
    return {"endpointTag": etag, "interfaceTag": itag, "interfaceType": itype, "className": cls,
            **({"addr": addr} if addr else {})}


def _action(etag: str, itag: str, itype: str, cls: str, addr: str) -> list[dict]:
    """The five interfaces of an action, as a robot config's loader expands them."""
    return [_iface(e["eTag"], e["iTag"], e["iType"], e["iCls"], e["addr"])
            for e in expand_interface({"eTag": etag, "iTag": itag, "iType": itype, "iCls": cls, "addr": addr})]


def _relays(engine) -> list:
    """The ROS 2 relay processes under the engine's processes."""
    import psutil
    out = []
    for p in engine.procs:
        try:
            kids = psutil.Process(p.pid).children(recursive=True)
        except psutil.NoSuchProcess:
            continue
        for k in kids:
            try:
                if k.cmdline()[1:3] == ["-m", "rce_container.ros2_relay"]:
                    out.append(k)
            except (psutil.Error, IndexError):
                continue
    return out


async def _stats(engine, ctag: str) -> dict:
    return await asyncio.to_thread(engine.admin, f"/api/containers/testUser/{ctag}/stats")


async def _relay_stat(engine, ctag: str, key: str):
    """A counter of container ``ctag``'s ROS 2 relay (None while it has none, or the container is
    still being made)."""
    try:
        stats = await _stats(engine, ctag)
    except NotFound:
        return None
    return (stats.get("ros2") or {}).get("relay", {}).get(key)


async def _until_async(cond, what: str, timeout: float = STEP):
    deadline = time.monotonic() + timeout
    while not (got := await cond()):
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.1)
    return got


async def _dm_until(r: RawRobot, inbox: Inbox, itag: str, data: str, out: str, want,
                    cls: str = "std_msgs/msg/String") -> dict:
    """Send ``data`` (a ``cls``) on ``itag`` until a DM on ``out`` satisfies ``want`` (the relay bridges a
    topic once both ends are there: what is sent before goes nowhere)."""
    deadline = time.monotonic() + STEP
    while True:
        assert time.monotonic() < deadline, f"no answer on {out!r}: {inbox.frames[-10:]}"
        await r.send("DM", {"iTag": itag, "type": cls, "msgID": "", "msg": {"data": data}})
        try:
            dm = await inbox.find("DM", lambda d: d["iTag"] == out, timeout=0.5)
        except TimeoutError:
            continue
        if want(dm["msg"]["data"]):
            return dm


@pytest.mark.timeout(180)
async def test_rclpy_node_in_a_container_talks_to_a_robot(ros2_engine):
    async with RawRobot(ros2_engine.master_url, "ros2bot") as r:
        inbox, ctag, rid = Inbox(r), "ros2C", r.robot
        await r.send("CC", {"containerTag": ctag})
        await r.cn(setParam=[{"containerTag": ctag, "name": "prefix", "value": "r2:"}])
        await r.cn(addNodes=[{"containerTag": ctag, "nodeTag": "echo", "pkg": "rce_ros2_test", "exe": "echo_node.py"}],
                   addInterfaces=[
                       _iface(ctag, "in", "PublisherInterface", "std_msgs/msg/String", "/in"),
                       _iface(ctag, "out", "SubscriberInterface", "std_msgs/msg/String", "/out"),
                       _iface(ctag, "srv", "ServiceClientInterface", "std_srvs/srv/SetBool", "/set_flag"),
                       _iface(ctag, "strict", "PublisherInterface", "std_msgs/msg/String", "/strict"),
                       _iface(rid, "in", "SubscriberConverter", "std_msgs/msg/String"),
                       _iface(rid, "out", "PublisherConverter", "std_msgs/msg/String"),
                       _iface(rid, "srv", "ServiceProviderConverter", "std_srvs/srv/SetBool"),
                       _iface(rid, "strict", "SubscriberConverter", "std_msgs/msg/String")])
        tags = ("in", "out", "srv", "strict")
        await r.send("CX", {"connect": [{"tagA": f"{ctag}/{t}", "tagB": f"{rid}/{t}"} for t in tags]})
        await inbox.up(*tags)
        # a topic round trip through the rclpy node, with the parameter it declared at its start
        await _dm_until(r, inbox, "in", "hello", "out", lambda d: d == "r2:hello")
        # a service of the node, called by the robot
        await r.send("DM", {"iTag": "srv", "type": "std_srvs/srv/SetBool", "msgID": "c1", "msg": {"data": True}})
        dm = await inbox.find("DM", lambda d: d["iTag"] == "srv")
        assert dm["msgID"] == "c1" and dm["msg"] == {"success": True, "message": "r2:True@/echo"}
        # a parameter changed later is set on the running node that declared it
        await r.cn(setParam=[{"containerTag": ctag, "name": "prefix", "value": "later:"}])
        await _dm_until(r, inbox, "in", "again", "out", lambda d: d != "r2:again")
        dm = await _dm_until(r, inbox, "in", "again", "out", lambda d: True)
        assert dm["msg"]["data"] == "later:again"
        # the node's subscription on /strict asks for a deadline the relay does not offer: the robot is told
        st = await inbox.find("ST", lambda d: d.get("topic") == "interface" and d.get("iTag") == "strict")
        assert st["status"] == "incompatible_qos" and st["cTag"] == ctag and "deadline" in st["reason"], st
        # a transient-local message the node published at its start reaches an interface added now
        await r.cn(addInterfaces=[_iface(ctag, "latched", "SubscriberInterface", "std_msgs/msg/String", "/latched"),
                                  _iface(rid, "latched", "PublisherConverter", "std_msgs/msg/String")])
        await r.send("CX", {"connect": [{"tagA": f"{ctag}/latched", "tagB": f"{rid}/latched"}]})
        dm = await inbox.find("DM", lambda d: d["iTag"] == "latched")
        assert dm["msg"] == {"data": "published once, at the start"}
        # a ROS 1 robot's interfaces (std_msgs/String) reach the same ROS 2 node: the sending ends convert
        await r.cn(addInterfaces=[_iface(ctag, "in1", "PublisherInterface", "std_msgs/msg/String", "/in"),
                                  _iface(rid, "in1", "SubscriberConverter", "std_msgs/String"),
                                  _iface(rid, "out1", "PublisherConverter", "std_msgs/String")])
        await r.send("CX", {"connect": [{"tagA": f"{ctag}/in1", "tagB": f"{rid}/in1"},
                                        {"tagA": f"{ctag}/out", "tagB": f"{rid}/out1"}]})
        await inbox.up("in1", "out1")
        await _dm_until(r, inbox, "in1", "from ROS 1", "out1", lambda d: d == "later:from ROS 1", cls="std_msgs/String")

        stats = await _stats(ros2_engine, ctag)
        assert stats["ros2"]["running"] and stats["ros2"]["nodes"] == ["echo"], stats["ros2"]
        relay = stats["ros2"]["relay"]
        assert relay["topics_to_ros"] == ["/in", "/strict"] and "/set_flag" in relay["services_to_bus"], relay
        assert relay["dropped_to_ros"] == relay["dropped_to_bus"] == relay["call_errors"] == 0, relay
        # removing the container's last ROS 2 node stops its relay; the next one starts it again
        relays = await _until(lambda: _relays(ros2_engine), "the relay")
        await r.cn(removeNodes=[{"containerTag": ctag, "nodeTag": "echo"}])
        await _until(lambda: not any(p.is_running() and p.status() != "zombie" for p in relays), "the relay to stop")
        await r.cn(addNodes=[{"containerTag": ctag, "nodeTag": "echo2", "pkg": "rce_ros2_test", "exe": "echo_node.py"}])
        relays = await _until(lambda: _relays(ros2_engine), "a new relay")
        await r.send("DC", {"containerTag": ctag})
        await _until(lambda: not any(p.is_running() and p.status() != "zombie" for p in relays),
                     "the relay to stop with its container")


@pytest.mark.timeout(180)
async def test_an_rclpy_action_client_drives_an_action_server_in_another_container(ros2_engine):
    async with RawRobot(ros2_engine.master_url, "actionbot") as r:
        inbox, rid = Inbox(r), r.robot
        for c in ("fibS", "fibC"):
            await r.send("CC", {"containerTag": c})
        await r.cn(addNodes=[{"containerTag": "fibS", "nodeTag": "server", "pkg": "rce_ros2_test",
                              "exe": "fibonacci_server.py"},
                             {"containerTag": "fibC", "nodeTag": "client", "pkg": "rce_ros2_test",
                              "exe": "fibonacci_client.py"}],
                   addInterfaces=[
                       *_action("fibS", "fib", "ActionClientInterface", "test_msgs/action/Fibonacci", "/fibonacci"),
                       *_action("fibC", "fib", "ActionProviderInterface", "test_msgs/action/Fibonacci", "/fibonacci"),
                       _iface("fibC", "report", "SubscriberInterface", "std_msgs/msg/String", "/report"),
                       _iface(rid, "report", "PublisherConverter", "std_msgs/msg/String")])
        # the client finds the action's five parts in its graph and sends its goal before anything is
        # wired: the call waits in the container for its connection
        await _until_async(lambda: _relay_stat(ros2_engine, "fibC", "calls"), "the client's goal")
        # wired topics first: by the time the goal goes through, its feedback has a way back
        parts = ("feedback", "status", "cancel_goal", "get_result", "send_goal")
        await r.send("CX", {"connect": [{"tagA": "fibC/report", "tagB": f"{rid}/report"}]
                            + [{"tagA": f"fibC/fib.{p}", "tagB": f"fibS/fib.{p}"} for p in parts]})
        done = json.loads((await inbox.find("DM", lambda d: d["iTag"] == "report"))["msg"]["data"])
        if done.get("feedback") != 5:     # where the feedback went: each relay's counts
            done["relays"] = {c: (await _stats(ros2_engine, c))["ros2"]["relay"] for c in ("fibS", "fibC")}
        assert done == {"order": 6, "accepted": True, "status": "succeeded", "sequence": [0, 1, 1, 2, 3, 5, 8],
                        "feedback": 5}, done
        canceled = json.loads((await inbox.find("DM", lambda d: d["iTag"] == "report"))["msg"]["data"])
        assert canceled["status"] == "canceled" and canceled["canceling"] == 1, canceled
        assert 2 <= canceled["feedback"] < 59 and len(canceled["sequence"]) < 61, canceled
        relay = (await _stats(ros2_engine, "fibC"))["ros2"]["relay"]
        assert {f"/fibonacci/_action/{p}" for p in ("send_goal", "get_result", "cancel_goal")} \
            <= set(relay["services_to_ros"]), relay
        assert relay["call_errors"] == 0 and relay["calls"] == 5, relay     # two goals, two results, a cancel


@pytest.mark.timeout(180)
async def test_a_connection_finds_the_relays_bridge_made(ros2_engine):
    """An interface added and wired within the relay's poll: the connection is made with its name
    bridged already (else an action's first feedback, published as soon as the goal it follows is
    wired, would find no bridge)."""
    async with RawRobot(ros2_engine.master_url, "wirebot") as r:
        inbox, ctag, rid = Inbox(r), "wireC", r.robot
        await r.send("CC", {"containerTag": ctag})
        await r.cn(addNodes=[{"containerTag": ctag, "nodeTag": "echo", "pkg": "rce_ros2_test", "exe": "echo_node.py"}])
        await _until_async(lambda: _has(_relay_stat(ros2_engine, ctag, "services_to_bus"), "/set_flag"),
                           "the relay to see the node")
        await r.cn(addInterfaces=[_iface(ctag, "in", "PublisherInterface", "std_msgs/msg/String", "/in"),
                                  _iface(rid, "in", "SubscriberConverter", "std_msgs/msg/String")])
        await r.send("CX", {"connect": [{"tagA": f"{rid}/in", "tagB": f"{ctag}/in"}]})
        await inbox.up("in")      # the robot's end is told last (the receiving end first): both are connected
        relay = (await _stats(ros2_engine, ctag))["ros2"]["relay"]
        assert "/in" in relay["topics_to_ros"], relay


async def _has(stat, item) -> bool:
    return item in ((await stat) or ())


PROBE = """
import json, sys, time, rclpy
from std_msgs.msg import String
name, seconds, target = sys.argv[1], float(sys.argv[2]), sys.argv[3]
rclpy.init()
node = rclpy.create_node(name)
end = time.monotonic() + seconds
if name == "host_control":
    pub = node.create_publisher(String, target, 10)
    while time.monotonic() < end:
        pub.publish(String(data="here"))
        rclpy.spin_once(node, timeout_sec=0.1)
    sys.exit()
while time.monotonic() < end and target not in dict(node.get_topic_names_and_types()):
    rclpy.spin_once(node, timeout_sec=0.1)
rclpy.spin_once(node, timeout_sec=1.0)
print(json.dumps({"topics": sorted(dict(node.get_topic_names_and_types())), "nodes": sorted(node.get_node_names())}))
"""


async def _probe(domain: int, target: str, *names: str, netns_of: int | None = None) -> dict:
    """What an rclpy node of the host (``names[-1]``) sees on ``domain`` once it sees topic ``target``,
    with the other ``names`` started beside it as the host's control nodes (publishing ``target``).
    It discovers as the host's programs do by default (multicast and loopback), or, in the network and
    mount namespaces of process ``netns_of``, as a container's nodes do (loopback only)."""
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}
    env.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
    if netns_of:
        env.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_LOG_DIR="/tmp")    # the rest is read-only there
    enter = ["nsenter", "-t", str(netns_of), "-n", "-m"] if netns_of else []     # its network and its /dev/shm
    procs = [await asyncio.create_subprocess_exec(*enter, sys.executable, "-c", PROBE, name, "15", target, env=env,
                                                  stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
             for name in names]
    out, err = await asyncio.wait_for(procs[-1].communicate(), STEP)
    for p in procs[:-1]:
        p.kill()
        await p.wait()
    assert procs[-1].returncode == 0, err.decode()
    return json.loads(out)


@pytest.mark.timeout(180)
async def test_each_containers_ros2_graph_is_its_own(ros2_engine):
    async with RawRobot(ros2_engine.master_url, "isobot") as r:
        inbox, rid = Inbox(r), r.robot
        for c in ("isoA", "isoB"):
            await r.send("CC", {"containerTag": c})
            await r.cn(addNodes=[{"containerTag": c, "nodeTag": n, "name": n, "pkg": "rce_ros2_test",
                                  "exe": "chatter.py"} for n in (c[-1] + "1", c[-1] + "2")],
                       addInterfaces=[_iface(c, "seen", "SubscriberInterface", "std_msgs/msg/String", "/seen"),
                                      _iface(rid, f"seen{c}", "PublisherConverter", "std_msgs/msg/String")])
            await r.send("CX", {"connect": [{"tagA": f"{c}/seen", "tagB": f"{rid}/seen{c}"}]})
        await inbox.up("seenisoA", "seenisoB")
        # each node hears the other node of its container (the graph works), and nothing of the other's
        reports: dict[str, dict] = {}
        while len(reports) < 4:
            dm = await inbox.find("DM", lambda d: d["iTag"].startswith("seen"))
            seen = json.loads(dm["msg"]["data"])
            mine = {"seenisoA": "A", "seenisoB": "B"}[dm["iTag"]]
            assert all(n.strip("/").startswith(mine) for n in seen["heard"] + seen["nodes"]), seen
            if seen["heard"]:
                reports[seen["me"]] = seen
        assert {m: s["heard"] for m, s in reports.items()} == {"/A1": ["/A2"], "/A2": ["/A1"], "/B1": ["/B2"],
                                                              "/B2": ["/B1"]}
        # a node of the host on a container's own domain id sees the host's other node, and nothing of the container
        stats = await _stats(ros2_engine, "isoA")
        domain = stats["ros2"]["domain_id"]
        assert stats["sandbox"] == "namespaced" and domain != (await _stats(ros2_engine, "isoB"))["ros2"]["domain_id"]
        seen = await _probe(domain, "/host_control", "host_control", "host_probe")
        assert "/host_control" in seen["topics"], seen
        assert not {"/chatter", "/seen"} & set(seen["topics"]), seen        # (the host may have graphs of its own)
        assert not {n for n in seen["nodes"] if n in ("A1", "A2") or n.startswith("rce_ros2_relay")}, seen
        # the same probe in the container's network namespace finds its graph: the namespace is the wall
        inside = await _probe(domain, "/chatter", "host_probe", netns_of=stats["sandbox_info"]["init_pid"])
        assert {"/chatter", "/seen"} <= set(inside["topics"]), inside
        for c in ("isoA", "isoB"):
            await r.send("DC", {"containerTag": c})
        for c in ("isoA", "isoB"):     # what was sent before is read (a full queue would hold up the close)
            await inbox.find("ST", lambda d, c=c: d.get("topic") == "iu" and d.get("iTag") == f"seen{c}"
                             and d.get("status") is False)
