"""ROS 1 nodes in containers.

A plain rospy node (``tests/ros1_packages/rce_ros1_test``, written for ROS 1 only) runs in a
container of a real engine, wired to a robot through the client protocol (CN, CX, converters):
the robot's message reaches the node's subscriber and its republication comes back, the robot
calls the node's service, a CN parameter reaches ``rospy.get_param``. Removing the node, and
destroying the container, stop the container's rosmaster and relay. In the unconfined sandbox (a
free loopback port) a bus service is also called from the ROS 1 graph (``rosservice call``).
The rules (which package is ROS 1, what the relay bridges, which parameters it copies) are
tested without I/O.
"""
from __future__ import annotations

import asyncio
import time
from pathlib import Path

import psutil
import pytest

from rce.bus.core import Bus
from rce.bus.server import BusServer
from rce.plumbing.errors import RequestError
from rce.tools.launch import start_engine
from rce.messages import default_registry
from rce.node.package_path import load_package_types
from rce_container.launcher import Launcher
from rce_container.ros1_graph import Ros1Graph
from rce_container.ros1_plan import (GraphView, bus_graph, flatten_params, is_ros1_package, param_changes, plan,
                                     relay_name, ros1_graph)
from rce_container.sandbox import ProcessGroupSandbox
from wsclient import RawRobot

ROS1_PACKAGES = Path(__file__).resolve().parents[1] / "ros1_packages"
ME = relay_name(1)
REG = default_registry()
load_package_types(REG, {"RCE_PACKAGE_PATH": str(ROS1_PACKAGES)})
STEP = 30.0   # s, the longest one wait may take (a ROS 1 graph starts in ~2 s; the machine is shared)


# -- rules, no I/O -----------------------------------------------------------------------------
@pytest.mark.parametrize("xml, ros1", [
    ('<package format="2"><name>a</name><depend>rospy</depend></package>', True),
    ('<package><name>a</name><run_depend>roscpp</run_depend></package>', True),            # format 1
    ('<package format="3"><name>a</name><exec_depend> rospy </exec_depend></package>', True),
    ('<package format="2"><name>a</name><depend>std_msgs</depend></package>', False),
    ('<package format="2"><name>a</name><build_depend>rospy</build_depend></package>', False),
])
def test_package_xml_marks_ros1_packages(tmp_path, xml, ros1):
    (tmp_path / "package.xml").write_text(xml)
    assert is_ros1_package(tmp_path) is ros1


def test_package_without_manifest_is_not_ros1_and_a_broken_one_is_named(tmp_path):
    assert is_ros1_package(tmp_path) is False
    assert is_ros1_package(ROS1_PACKAGES / "rce_ros1_test") is True
    (tmp_path / "package.xml").write_text("<package><name>a")
    with pytest.raises(RequestError, match="package.xml"):
        is_ros1_package(tmp_path)


def _ros(pubs=(), subs=(), types=(), srvs=()):
    return ros1_graph([[[t, list(n)] for t, n in pubs], [[t, list(n)] for t, n in subs],
                       [[s, list(n)] for s, n in srvs]], [list(x) for x in types])


def test_plan_bridges_a_topic_where_one_side_publishes_and_the_other_reads():
    bus = bus_graph({"topics": [
        {"name": "/in", "type": "std_msgs/String", "publishers": ["interface:req"], "subscribers": []},
        {"name": "/out", "type": "std_msgs/String", "publishers": [], "subscribers": ["interface:resp"]},
        {"name": "/idle", "type": "std_msgs/String", "publishers": ["interface:x"], "subscribers": []}],
        "services": [{"name": "/rce_srv", "type": "Test/StringEcho", "provider": "/rce_node"},
                     {"name": f"{ME}/sync", "type": "std_srvs/Empty", "provider": ME}]})
    ros = _ros(pubs=[("/out", ["/echo_node"])], subs=[("/in", ["/echo_node"])],
               types=[("/out", "std_msgs/String"), ("/in", "std_msgs/String")], srvs=[("/echo", ["/echo_node"])])
    p = plan(bus, ros, ME)
    assert p.to_ros == {"/in": "std_msgs/String"}          # /idle: nobody reads it in ROS 1
    assert p.to_bus == {"/out": "std_msgs/String"}
    assert p.services_to_bus == {"/echo"} and p.services_to_ros == {"/rce_srv": "Test/StringEcho"}
    # every rospy node's own logger services stay in the ROS 1 graph
    ros = _ros(srvs=[("/echo_node/get_loggers", ["/echo_node"]), ("/echo_node/set_logger_level", ["/echo_node"])])
    assert plan(bus, ros, ME).services_to_bus == set()


def test_plan_never_bridges_the_relays_own_output_or_a_type_conflict():
    # the relay's own publications and subscriptions do not count: nothing to bridge
    bus = GraphView(publishers={"/a": {ME}}, subscribers={"/b": {ME}}, types={"/a": "x/A", "/b": "x/B"},
                services={"/s": ME}, service_types={"/s": "x/S"})
    ros = _ros(pubs=[("/b", [ME])], subs=[("/a", [ME])], types=[("/a", "x/A"), ("/b", "x/B")], srvs=[("/s", [ME])])
    p = plan(bus, ros, ME)
    assert (p.to_ros, p.to_bus, p.services_to_bus, p.services_to_ros) == ({}, {}, set(), {})
    # a service provided on both sides by others stays where it is
    p = plan(GraphView(services={"/s": "/n"}, service_types={"/s": "x/S"}), _ros(srvs=[("/s", ["/m"])]), ME)
    assert not p.services_to_bus and not p.services_to_ros
    # the two graphs disagree on a topic's type: left alone, and said why
    bus = GraphView(publishers={"/c": {"interface:c"}}, types={"/c": "std_msgs/String"})
    p = plan(bus, _ros(subs=[("/c", ["/n"])], types=[("/c", "std_msgs/Int32")]), ME)
    assert p.to_ros == {} and "std_msgs/Int32" in p.conflicts["/c"]


def test_parameters_go_bus_to_rosmaster_and_only_what_the_relay_set_is_deleted():
    leaves = flatten_params({"echo_prefix": "p:", "robot": {"speed": 1.5, "ids": [1, 2]}, "empty": {}})
    assert leaves == {"/echo_prefix": "p:", "/robot/speed": 1.5, "/robot/ids": [1, 2], "/empty": {}}
    assert flatten_params({}) == {}
    to_set, to_delete = param_changes({"/a": 1, "/b": 2}, {"/a": 1, "/c": 3})
    assert to_set == {"/b": 2} and to_delete == ["/c"]


# -- a real engine -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ros1_engine(tmp_path_factory):
    """An engine whose package path has the ROS 1 test package."""
    e = start_engine(tmp_path_factory.mktemp("engine"), env={"RCE_PACKAGE_PATH": str(ROS1_PACKAGES)})
    yield e
    e.stop()


def _graph_procs(engine) -> list[psutil.Process]:
    """rosmaster and relay processes under the engine's processes (the Python processes
    themselves, not the sandbox's wrappers around them)."""
    out = []
    for p in engine.procs:
        try:
            kids = psutil.Process(p.pid).children(recursive=True)
        except psutil.NoSuchProcess:
            continue
        for k in kids:
            try:
                cmd = k.cmdline()
            except psutil.Error:
                continue
            if len(cmd) > 2 and "python" in Path(cmd[0]).name and \
                    (cmd[1].endswith("/rosmaster") or cmd[1:3] == ["-m", "rce_container.ros1_relay"]):
                out.append(k)
    return out


async def _until(cond, what: str, timeout: float = STEP):
    deadline = time.monotonic() + timeout
    while not (got := cond()):
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.1)
    return got


async def _wire(r: RawRobot, ctag: str) -> None:
    rid = r.robot
    await r.send("CC", {"containerTag": ctag})
    await r.cn(setParam=[{"containerTag": ctag, "name": "echo_prefix", "value": "ros1:"}])
    await r.cn(addNodes=[{"containerTag": ctag, "nodeTag": "echo", "pkg": "rce_ros1_test", "exe": "echo_node.py"}],
               addInterfaces=[
                   {"endpointTag": ctag, "interfaceTag": "in", "interfaceType": "PublisherInterface",
                    "className": "std_msgs/String", "addr": "/in"},
                   {"endpointTag": ctag, "interfaceTag": "out", "interfaceType": "SubscriberInterface",
                    "className": "std_msgs/String", "addr": "/out"},
                   {"endpointTag": ctag, "interfaceTag": "srv", "interfaceType": "ServiceClientInterface",
                    "className": "rce_ros1_test/Echo", "addr": "/echo"},
                   {"endpointTag": rid, "interfaceTag": "in", "interfaceType": "SubscriberConverter",
                    "className": "std_msgs/String"},
                   {"endpointTag": rid, "interfaceTag": "out", "interfaceType": "PublisherConverter",
                    "className": "std_msgs/String"},
                   {"endpointTag": rid, "interfaceTag": "srv", "interfaceType": "ServiceProviderConverter",
                    "className": "rce_ros1_test/Echo"}])
    await r.send("CX", {"connect": [{"tagA": f"{ctag}/{t}", "tagB": f"{rid}/{t}"} for t in ("in", "out", "srv")]})
    await r.wait_up("in", "out", "srv")


@pytest.mark.timeout(120)
async def test_rospy_node_in_a_container_talks_to_a_robot(ros1_engine):
    async with RawRobot(ros1_engine.master_url, "ros1bot") as r:
        await _wire(r, "ros1C")
        # the relay bridges /in once the node subscribes: repeat until the republication arrives
        dm = None
        deadline = time.monotonic() + STEP
        while dm is None:
            assert time.monotonic() < deadline, "no republication from the rospy node"
            await r.send("DM", {"iTag": "in", "type": "std_msgs/String", "msgID": "", "msg": {"data": "hello"}})
            try:
                dm = await r.expect("DM", timeout=0.5, pred=lambda d: d["iTag"] == "out")
            except TimeoutError:
                continue
        assert dm["msg"] == {"data": "ros1:hello"} and dm["type"] == "std_msgs/String"
        # the service call waits (bounded) for the relay to provide the node's service on the bus
        await r.send("DM", {"iTag": "srv", "type": "rce_ros1_test/Echo", "msgID": "c1", "msg": {"data": "q"}})
        dm = await r.expect("DM", timeout=STEP, pred=lambda d: d["iTag"] == "srv")
        assert dm["msgID"] == "c1" and dm["msg"] == {"data": "ros1:q@/echo"}

        graph = await _until(lambda: len(_graph_procs(ros1_engine)) == 2 and _graph_procs(ros1_engine),
                             "rosmaster and the relay")
        # removing the container's last ROS 1 node stops its rosmaster and relay
        await r.cn(removeNodes=[{"containerTag": "ros1C", "nodeTag": "echo"}])
        await _until(lambda: not any(p.is_running() for p in graph), "rosmaster and relay to stop")
        assert _graph_procs(ros1_engine) == []
        # a new ROS 1 node starts them again; destroying the container stops them
        await r.cn(addNodes=[{"containerTag": "ros1C", "nodeTag": "echo2", "pkg": "rce_ros1_test",
                              "exe": "echo_node.py", "name": "echo2"}])
        graph = await _until(lambda: len(_graph_procs(ros1_engine)) == 2 and _graph_procs(ros1_engine),
                             "a second rosmaster and relay")
        await r.send("DC", {"containerTag": "ros1C"})
        await _until(lambda: not any(p.is_running() for p in graph), "rosmaster and relay to stop with the container")
        assert _graph_procs(ros1_engine) == []


# -- the graph on its own, in the unconfined sandbox (the host's network: a free loopback port) --
@pytest.mark.timeout(90)
async def test_ros1_graph_in_an_unconfined_sandbox(tmp_path, monkeypatch):
    monkeypatch.setenv("RCE_PACKAGE_PATH", str(ROS1_PACKAGES))
    bus = Bus("test")
    server = BusServer(bus)
    await server.listen(str(tmp_path / "bus.sock"))
    (tmp_path / "c1").mkdir()
    sandbox = ProcessGroupSandbox(1, "uc", {}, tmp_path / "c1", grace=1.0)
    launcher = Launcher(sandbox, str(tmp_path / "bus.sock"), "uc", lambda *a, **kw: None)
    graph = Ros1Graph(launcher, 1, bus)
    try:
        bus.set_param("/echo_prefix", "u:")
        spec = {"ntag": "echo", "pkg": "rce_ros1_test", "exe": "echo_node.py", "namespace": "/ns"}
        kind = await graph.prepare(spec)
        assert kind["env"]["ROS_MASTER_URI"] != "http://127.0.0.1:11311/" and kind["args"] == ["__name:=echo"]
        await launcher.add(spec, kind)
        got: list[bytes] = []
        bus.subscribe("/ns/out", "std_msgs/String", lambda b: got.append(b) or True, "test")
        topic = bus.advertise("/ns/in", "std_msgs/String", "test")
        payload = REG.json_to_bytes(REG.msg_type("std_msgs/String"), {"data": "x"})
        deadline = time.monotonic() + STEP
        while not got:
            assert time.monotonic() < deadline, f"no republication; relay: {graph.info()} {graph.output}"
            bus.publish(topic, payload)
            await asyncio.sleep(0.2)
        assert REG.bytes_to_json(REG.msg_type("std_msgs/String"), got[0]) == {"data": "u:x"}
        req_t, resp_t = REG.srv_types("rce_ros1_test/Echo")
        resp = await bus.call_service("/ns/echo", REG.json_to_bytes(req_t, {"data": "s"}), wait=STEP)
        assert REG.bytes_to_json(resp_t, resp) == {"data": "u:s@/ns/echo"}
        # a service provided on the bus is called from the ROS 1 graph (Debian's rosservice)
        async def bus_echo(b: bytes) -> bytes:
            return REG.json_to_bytes(resp_t, {"data": "bus:" + REG.bytes_to_json(req_t, b)["data"]})
        bus.advertise_service("/bus_echo", "rce_ros1_test/Echo", bus_echo, "test")
        await graph.sync()
        env = {"PATH": "/usr/bin:/bin", "ROS_MASTER_URI": graph.uri, "ROS_IP": "127.0.0.1",
               "ROS_HOME": str(tmp_path / "ros"), "PYTHONPATH": str(ROS1_PACKAGES / "rce_ros1_test" / "src")}
        proc = await asyncio.create_subprocess_exec("rosservice", "call", "/bus_echo", "data: z", env=env,
                                                    stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        out, err = await asyncio.wait_for(proc.communicate(), STEP)
        assert out.decode().strip() == 'data: "bus:z"', err.decode()
        await graph.sync()
        relay = graph.info()["relay"]
        assert relay["to_bus"] >= 1 and relay["calls"] == 2 and relay["call_errors"] == 0, relay
        assert relay["services_to_ros"] == ["/bus_echo"] and "/ns/echo" in relay["services_to_bus"], relay
        pids = list(graph.info()["pids"].values())
        await launcher.remove("echo")
        await graph.node_gone("echo")
        assert not graph.running and not any(psutil.pid_exists(p) and psutil.Process(p).status() != "zombie"
                                             for p in pids)
    finally:
        await launcher.close()
        await graph.close()
        await server.close()
