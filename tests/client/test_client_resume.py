"""rce_client.Connection with ``allow_reconnect`` (session resume, docs/INTERNALS.md) against a
stand-in endpoint that runs the real cloud-side rules (tests/client/resumecloud.py), through a TCP
proxy that drops the link (rce/transport/tcpproxy.py): the callbacks, sends and calls across the gap, a
refused resume, a gap that outlasts the attempts, a session the cloud ends, and rce-ros keeping
its local bus up through the gap."""
from __future__ import annotations

import asyncio
import os
import tempfile

import pytest

import rce.node
from rce.protocol.config import parse_config
from rce.plumbing.errors import Unavailable
from rce.transport.tcpproxy import TcpProxy
from rce_client.connection import Connection
from rce_client.rce_ros import RobotBridge

from .fakecloud import login_server, ws_url_answer
from .resumecloud import ResumeCloud

pytestmark = pytest.mark.asyncio
STR = "std_msgs/String"


@pytest.fixture
async def link():
    cloud = await ResumeCloud(echo={"req": "resp"}).start()
    proxy = await TcpProxy(cloud.port).start()
    yield cloud, proxy
    await proxy.close()
    await cloud.stop()


async def until(pred, timeout: float = 5.0) -> None:
    """Wait until ``pred()`` holds (polled: the test observes, nothing is synchronised by it)."""
    deadline = asyncio.get_running_loop().time() + timeout
    while not pred():
        assert asyncio.get_running_loop().time() < deadline, "timed out"
        await asyncio.sleep(0.01)


async def connected(proxy: TcpProxy, **kw) -> Connection:
    conn = await Connection.open(proxy.url, "u", "p", "r1", allow_reconnect=True, **kw)
    await conn.configure({"addInterfaces": [
        {"endpointTag": "r1", "interfaceTag": t, "interfaceType": k, "className": c}
        for t, k, c in (("req", "SubscriberConverter", STR), ("resp", "PublisherConverter", STR),
                        ("svc", "ServiceProviderConverter", "Test/StringEcho"))]})
    await conn.send("CX", {"connect": [{"tagA": f"c1/{t}", "tagB": f"r1/{t}"} for t in ("req", "resp", "svc")]})
    await conn.wait_interfaces_up(["req", "resp", "svc"], timeout=5)
    return conn


async def test_asks_for_resume_and_gets_a_token(link):
    cloud, proxy = link
    conn = await connected(proxy)
    try:
        assert cloud.queries[0]["resume"] == "1" and conn.session.state == "live"
        assert conn.session.token == cloud.session.token and conn.connected
    finally:
        await conn.close()


async def test_a_lost_link_resumes_with_sends_calls_and_callbacks(link):
    cloud, proxy = link
    conn = await connected(proxy)
    seen: list[tuple[str, object]] = []
    conn.on_disconnected(lambda r: seen.append(("disconnected", r)))
    conn.on_reconnected(lambda url: seen.append(("reconnected", url)))
    conn.on_resumed(lambda st: seen.append(("resumed", st)))
    echoes: list[str] = []
    conn.subscriber("resp", STR, lambda m: echoes.append(m["data"]))
    pub = conn.publisher("req", STR)
    try:
        await pub.publish({"data": "before"})
        await until(lambda: echoes == ["before"])
        cloud.hold_calls = True
        call = asyncio.ensure_future(conn.service("svc", "Test/StringEcho").call({"data": "across"}, timeout=10))
        await until(lambda: cloud.held)
        proxy.cut()
        await until(lambda: not conn.connected)
        for i in range(5):                              # sends during the gap are kept, never raise
            await pub.publish({"data": f"gap{i}"})
        await cloud.push("resp", {"data": "from-cloud"})  # what the cloud sends meanwhile is kept
        assert not conn.closed and seen[0][0] == "disconnected"
        proxy.restore()
        await until(lambda: len(echoes) == 7)
        assert echoes == ["before", "from-cloud"] + [f"gap{i}" for i in range(5)]
        await cloud.answer_held()
        assert await call == {"data": "across"}             # the call in flight survived the resume
        assert [k for k, _ in seen] == ["disconnected", "reconnected", "resumed"]
        assert seen[2][1]["status"] == "resumed" and seen[2][1]["dropped"] == 0 and conn.resumes == 1
        resume = cloud.queries[-1]
        assert resume["session"] == conn.session.token and "password" not in resume
        assert resume["ack"] == "4"                         # it had taken 3 STs iu and the echo of "before"
        dms = [d["msg"]["data"] for d in cloud.taken if d["iTag"] == "req"]
        assert dms == ["before"] + [f"gap{i}" for i in range(5)], "each message once, in order"
    finally:
        await conn.close()


async def test_a_refused_resume_closes_and_fails_pending_calls(link):
    cloud, proxy = link
    conn = await connected(proxy)
    cloud.hold_calls = True
    call = asyncio.ensure_future(conn.service("svc", "Test/StringEcho").call({"data": "x"}, timeout=10))
    await until(lambda: cloud.held)
    proxy.cut()
    await until(lambda: not conn.connected)
    cloud.forget()                                      # the grace passed: the token is void
    proxy.restore()
    reason = await asyncio.wait_for(conn.wait_closed(), 5)
    assert "refused to resume" in reason and "HTTP 401" in reason
    with pytest.raises(Unavailable, match="refused to resume"):
        await call


async def test_gives_up_after_max_reconnect_attempts(link):
    cloud, proxy = link
    conn = await connected(proxy, max_reconnect_attempts=3, reconnect_time_wait=0.01, max_reconnect_wait=0.02)
    proxy.cut()
    reason = await asyncio.wait_for(conn.wait_closed(), 5)
    assert "could not resume the session (3 attempt(s))" in reason
    with pytest.raises(Unavailable):
        await conn.send("DM", {"iTag": "req", "type": STR, "msg": {"data": "late"}})


async def test_a_session_the_cloud_ends_is_not_resumed(link):
    cloud, proxy = link
    conn = await connected(proxy)
    await cloud.close_robot("closed by the master")
    reason = await asyncio.wait_for(conn.wait_closed(), 5)
    assert "1008" in reason and "closed by the master" in reason
    assert all("session" not in q for q in cloud.queries)


async def test_rce_ros_keeps_the_local_bus_up_through_the_gap(link):
    cloud, proxy = link

    async def answer(request):
        return ws_url_answer(proxy.url)
    runner, url = await login_server(answer)
    bus = os.path.join(tempfile.mkdtemp(prefix="rce-r-"), "r1.sock")
    cfg = {"url": url, "userID": "u", "password": "p", "robotID": "r1",
           "interfaces": [{"eTag": "r1", "iTag": "req", "iType": "SubscriberConverter", "iCls": STR, "addr": "/out"},
                          {"eTag": "r1", "iTag": "resp", "iType": "PublisherConverter", "iCls": STR, "addr": "/in"}],
           "connections": [{"tagA": "c1/req", "tagB": "r1/req"}, {"tagA": "c1/resp", "tagB": "r1/resp"}]}
    out, err = [], []
    bridge = RobotBridge(parse_config(cfg, "t.config"), "t.config", bus, out=out.append, err=err.append)
    task = asyncio.create_task(bridge.run())
    node = None
    try:
        await asyncio.wait_for(bridge.ready.wait(), 10)
        node = await rce.node.init_node("local", bus=bus, argv=[])
        got: list[str] = []
        await node.subscriber("/in", STR, lambda m: got.append(m.data))
        pub = await node.publisher("/out", STR)
        await pub.publish({"data": "m0"})
        await until(lambda: got == ["m0"])
        proxy.cut()
        await until(lambda: any("link to the cloud lost" in line for line in err))
        for i in range(1, 6):                            # the local program goes on as if nothing happened
            await pub.publish({"data": f"m{i}"})
        proxy.restore()
        await until(lambda: len(got) == 6, 10)
        assert got == [f"m{i}" for i in range(6)] and not task.done()
        assert any(line.startswith("rce-ros: session resumed (0 message(s)") for line in out)
    finally:
        if node is not None:
            await node.close()
        bridge.stop.set()
        assert await asyncio.wait_for(task, 10) == 0
        await runner.cleanup()
