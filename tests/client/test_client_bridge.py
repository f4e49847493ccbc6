"""rce-ros's bridge (RobotBridge, in-process) against a minimal stand-in cloud: converters and
forwarders in every direction between the local bus and the websocket, ER/ST printing,
interfaces that never come up, a cloud that goes away, and teardown."""
from __future__ import annotations

import asyncio
import os
import tempfile

import pytest

import rce.node
from rce.protocol.config import parse_config
from rce.messages import default_registry
from rce_client.rce_ros import RobotBridge

from .fakecloud import FakeEndpoint, login_server, ws_url_answer

STR = "std_msgs/msg/String"
ROBOT_SIDE = [
    ("req", "SubscriberForwarder", "std_msgs/String", "/fwd_req"),
    ("resp", "PublisherForwarder", "std_msgs/String", "/fwd_resp"),
    ("jreq", "SubscriberConverter", "std_msgs/String", "/j_req"),
    ("jresp", "PublisherConverter", "std_msgs/String", None),                 # default addr: /jresp
    ("svc", "ServiceProviderConverter", "Test/StringEcho", "/cloud_echo"),
    ("svcb", "ServiceProviderForwarder", "Test/StringEcho", "/cloud_echo_b"),
    ("robotSvc", "ServiceClientConverter", "Test/StringEcho", "/robot_echo"),
    ("robotSvcB", "ServiceClientForwarder", "Test/StringEcho", "/robot_echo_b"),
]


def config(url: str, connect: list[str] | None = None) -> dict:
    itfs = [{"eTag": "r1", "iTag": t, "iType": k, "iCls": c, **({"addr": a} if a else {})}
            for t, k, c, a in ROBOT_SIDE]
    return {"url": url, "userID": "u", "password": "p", "robotID": "r1",
            "containers": [{"cTag": "c1", "cpu": 1}],
            "nodes": [{"cTag": "c1", "nTag": "n", "pkg": "Test", "exe": "stringEcho.py"}],
            "parameters": [{"cTag": "c1", "name": "int", "value": 99}],
            "interfaces": itfs,
            "connections": [{"tagA": f"c1/{t}", "tagB": f"r1/{t}"}
                            for t in (connect if connect is not None else [x[0] for x in ROBOT_SIDE])]}


class Run:
    """A RobotBridge running in the test's loop, with its printed lines."""

    def __init__(self, cfg: dict, **kw):
        self.dir = tempfile.mkdtemp(prefix="rce-b-")
        self.bus = os.path.join(self.dir, "r1.sock")
        self.out: list[str] = []
        self.err: list[str] = []
        self.bridge = RobotBridge(parse_config(cfg, "test.config"), "test.config", self.bus,
                                out=self.out.append, err=self.err.append, **kw)
        self.task = asyncio.create_task(self.bridge.run())

    async def ready(self) -> None:
        done, _ = await asyncio.wait([self.task, asyncio.ensure_future(self.bridge.ready.wait())], timeout=10,
                                     return_when=asyncio.FIRST_COMPLETED)
        assert self.bridge.ready.is_set(), (self.out, self.err, self.task.done() and self.task.result())

    async def stop(self) -> int:
        self.bridge.stop.set()
        return await asyncio.wait_for(self.task, 10)


@pytest.fixture
async def cloud():
    ep = await FakeEndpoint(auto=True, echo={"req": "resp", "jreq": "jresp"}).start()
    async def answer(request):
        return ws_url_answer(ep.url)
    runner, url = await login_server(answer)
    ep.login_url = url
    yield ep
    await runner.cleanup()
    await ep.stop()


async def next_dm(cloud: FakeEndpoint, itag: str) -> dict:
    while True:
        m = await cloud.recv_type("DM")
        if m["data"]["iTag"] == itag:
            return m["data"]


async def test_bridge_everything(cloud):
    reg = default_registry()
    run = Run(config(cloud.login_url))
    await run.ready()
    assert f"  export RCE_BUS={run.bus}" in run.out
    assert any(line.startswith("rce-ros: ready (8 interface(s) up") for line in run.out)

    # setup went out in order: CC (checked by a barrier), setParam, addNodes, addInterfaces, CX
    kinds = [(m["type"], sorted(m["data"])) for m in cloud.log]
    assert kinds[:6] == [("CC", ["containerData", "containerTag"]), ("CX", ["connect"]), ("CN", ["setParam"]),
                         ("CN", ["addNodes"]), ("CN", ["addInterfaces"]), ("CX", ["connect"])]
    assert cloud.log[0]["data"] == {"containerTag": "c1", "containerData": {"cpu": 1.0}}

    node = await rce.node.init_node("tester", bus=run.bus, argv=[])
    try:
        got: asyncio.Queue = asyncio.Queue()
        await node.subscriber("/fwd_resp", "std_msgs/String", lambda m: got.put_nowait(("fwd", m.data)))
        await node.subscriber("/jresp", "std_msgs/String", lambda m: got.put_nowait(("json", m.data)))

        # Forwarder topic: serialized bytes both ways, no JSON
        pub = await node.publisher("/fwd_req", "std_msgs/String")
        await pub.publish({"data": "binary"})
        dm = await next_dm(cloud, "req")
        assert dm["msg"] == reg.json_to_bytes(STR, {"data": "binary"}) and dm["type"] == "std_msgs/String"
        assert await asyncio.wait_for(got.get(), 5) == ("fwd", "binary")

        # Converter topic: JSON both ways
        jpub = await node.publisher("/j_req", "std_msgs/String")
        await jpub.publish({"data": "json"})
        assert (await next_dm(cloud, "jreq"))["msg"] == {"data": "json"}
        assert await asyncio.wait_for(got.get(), 5) == ("json", "json")

        # the robot calls the cloud (ServiceProvider*): converter sends JSON, forwarder bytes
        svc = await node.service_proxy("/cloud_echo", "Test/StringEcho")
        assert (await svc({"data": "call me"})).data == "call me"
        assert (await next_dm(cloud, "svc"))["msg"] == {"data": "call me"}
        svcb = await node.service_proxy("/cloud_echo_b", "Test/StringEcho")
        assert (await svcb({"data": "raw call"})).data == "raw call"
        assert (await next_dm(cloud, "svcb"))["msg"] == reg.json_to_bytes("Test/msg/StringEchoRequest",
                                                                          {"data": "raw call"})

        # the cloud calls the robot (ServiceClient*): the local service answers, same msgID back
        await node.service("/robot_echo", "Test/StringEcho", lambda req: {"data": req.data + "!"})
        await node.service("/robot_echo_b", "Test/StringEcho", lambda req: {"data": req.data + "?"})
        await cloud.send("DM", {"iTag": "robotSvc", "type": "Test/StringEcho", "msgID": "1" * 32,
                                "msg": {"data": "hi"}})
        assert await next_dm(cloud, "robotSvc") == {"iTag": "robotSvc", "type": "Test/StringEcho",
                                                    "msg": {"data": "hi!"}, "msgID": "1" * 32}
        await cloud.send("DM", {"iTag": "robotSvcB", "type": "Test/StringEcho", "msgID": "2" * 32,
                                "msg": reg.json_to_bytes("Test/msg/StringEchoRequest", {"data": "yo"})},
                         binary_first=True)
        dm = await next_dm(cloud, "robotSvcB")
        assert dm["msgID"] == "2" * 32
        assert dm["msg"] == reg.json_to_bytes("Test/msg/StringEchoResponse", {"data": "yo?"})

        # ER and node ST are printed
        await cloud.send("ER", "CN: node 'n' already exists in container 'c1'")
        await cloud.send("ST", {"topic": "node", "cTag": "c1", "nTag": "n", "status": "exited", "code": 3})
        await node.describe()
        await cloud.send("DM", {"iTag": "robotSvc", "type": "Test/StringEcho", "msgID": "3" * 32,
                                "msg": {"data": "sync"}})
        await next_dm(cloud, "robotSvc")          # everything sent before has been handled
        assert "rce-ros: error from the cloud: CN: node 'n' already exists in container 'c1'" in run.err
        assert "rce-ros: node c1/n: exited code=3" in run.out
    finally:
        await node.close()

    assert await run.stop() == 0
    tail = [m for m in cloud.log if m["type"] in ("CN", "DC")][-2:]
    assert tail[0] == {"type": "CN", "data": {"removeInterfaces": [{"endpointTag": "r1", "interfaceTag": t}
                                                                   for t, *_ in ROBOT_SIDE]}}
    assert tail[1] == {"type": "DC", "data": {"containerTag": "c1"}}
    assert "rce-ros: removed 8 interface(s), destroyed 1 container(s)" in run.out
    await asyncio.wait_for(cloud.disconnected.wait(), 5)
    assert not os.path.exists(run.bus)


async def test_local_messages_before_up_are_dropped_and_calls_refused(cloud):
    run = Run(config(cloud.login_url, connect=[]), timeout=0.5)
    # nothing is connected: the interfaces never come up
    code = await asyncio.wait_for(run.task, 10)
    assert code == 1
    assert any("interfaces still down after 0.5 s: req, resp, jreq, jresp, svc, svcb, robotSvc, robotSvcB" in e
               for e in run.err), run.err
    # what it created is removed even so, and the local bus is gone
    assert {"type": "DC", "data": {"containerTag": "c1"}} in cloud.log
    assert not os.path.exists(run.bus)


async def test_keep_sends_no_teardown(cloud):
    run = Run(config(cloud.login_url), keep=True)
    await run.ready()
    n = len(cloud.log)
    assert await run.stop() == 0
    await asyncio.wait_for(cloud.disconnected.wait(), 5)
    assert cloud.log[n:] == []


async def test_refused_container_is_not_destroyed(cloud):
    """A CC the cloud refuses (ER before the barrier's) was not created by this run."""
    orig = cloud._auto

    async def refuse_cc(m):
        if m["type"] == "CC":
            await cloud.send("ER", "CC: container 'c1' already exists")
            return
        await orig(m)
    cloud._auto = refuse_cc
    run = Run(config(cloud.login_url))
    await run.ready()
    assert "rce-ros: error from the cloud: CC: container 'c1' already exists" in run.err
    assert await run.stop() == 0
    assert not any(m["type"] == "DC" for m in cloud.log)
    # its container-side parts are removed one by one instead
    removed = [m["data"] for m in cloud.log if m["type"] == "CN" and "removeNodes" in m["data"]]
    assert removed == [{"removeNodes": [{"containerTag": "c1", "nodeTag": "n"}]}]


async def test_cloud_going_away_exits_1(cloud):
    run = Run(config(cloud.login_url))
    await run.ready()
    await cloud.ws.close(1008, "closed by the master")
    assert await asyncio.wait_for(run.task, 10) == 1
    assert any("connection to the cloud closed: code 1008: closed by the master" in e for e in run.err), run.err
    assert not os.path.exists(run.bus)


async def test_second_bridge_on_the_same_socket_is_refused(cloud):
    run = Run(config(cloud.login_url))
    await run.ready()
    try:
        other = RobotBridge(parse_config(config(cloud.login_url), "x"), "x", run.bus, out=lambda s: None,
                          err=lambda s: None)
        with pytest.raises(Exception, match="another rce-ros already serves a bus at"):
            await other.run()
    finally:
        assert await run.stop() == 0


async def test_a_call_while_its_interface_is_unwired_waits_for_the_wiring_then_fails_naming_it(cloud, monkeypatch):
    from rce_client import rce_ros
    run = Run(config(cloud.login_url))
    await run.ready()
    node = await rce.node.init_node("tester", bus=run.bus, argv=[])
    try:
        await cloud.send("ST", {"topic": "iu", "iTag": "svc", "status": False})     # the cloud side went away
        svc = await node.service_proxy("/cloud_echo", "Test/StringEcho")
        svcb = await node.service_proxy("/cloud_echo_b", "Test/StringEcho")
        waiting = asyncio.ensure_future(svc({"data": "held"}))
        assert (await svcb({"data": "after"})).data == "after"   # the bridge has the first call by now
        assert not waiting.done()
        assert not [m for m in cloud.log if m["type"] == "DM" and m["data"]["iTag"] == "svc"]
        await cloud.send("ST", {"topic": "iu", "iTag": "svc", "status": True})      # wired again: it goes out
        assert (await asyncio.wait_for(waiting, 5)).data == "held"

        monkeypatch.setattr(rce_ros, "CONNECT_WAIT", 0.2)
        await cloud.send("ST", {"topic": "iu", "iTag": "svc", "status": False})
        assert (await svcb({"data": "sync"})).data == "sync"
        with pytest.raises(Exception, match=r"interface svc is not connected to the cloud \(waited 0.2 s\)"):
            await asyncio.wait_for(svc({"data": "never"}), 5)
        assert (await svcb({"data": "still"})).data == "still"                    # the others go on
    finally:
        await node.close()
    assert await run.stop() == 0
