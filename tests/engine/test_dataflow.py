"""Topics and services between robots and containers through converters (JSON)
and forwarders (binary parts), container <-> container, parameters, statuses, teardown.
Real processes on loopback, the raw wire protocol."""
from __future__ import annotations

import asyncio
import contextlib
import json
import urllib.request

import pytest
from rosbags.typesys import Stores, get_typestore
from websockets.exceptions import InvalidStatus

from rce_robot import ws_cork
from wsclient import RawRobot

pytestmark = pytest.mark.asyncio
TS = get_typestore(Stores.ROS1_NOETIC)


@pytest.fixture(scope="module")
def eng(shared_engine):
    return shared_engine




async def _echo_container(r: RawRobot, ctag: str, side: str, data: dict | None = None, pkg: str = "Test") -> None:
    """Container with stringEcho (of package ``pkg``) and robot-side interfaces of ``side``
    (Converter/Forwarder); ``data``: its containerData."""
    rid = r.robot
    await r.send("CC", {"containerTag": ctag, **({"containerData": data} if data else {})})
    await r.cn(addNodes=[{"containerTag": ctag, "nodeTag": "echo", "pkg": pkg, "exe": "stringEcho.py"}],
               addInterfaces=[
                   {"endpointTag": ctag, "interfaceTag": "req", "interfaceType": "PublisherInterface",
                    "className": "std_msgs/String", "addr": "/stringEchoReq"},
                   {"endpointTag": ctag, "interfaceTag": "resp", "interfaceType": "SubscriberInterface",
                    "className": "std_msgs/String", "addr": "/stringEchoResp"},
                   {"endpointTag": ctag, "interfaceTag": "srv", "interfaceType": "ServiceClientInterface",
                    "className": "Test/StringEcho", "addr": "/stringEchoService"},
                   {"endpointTag": rid, "interfaceTag": "req", "interfaceType": f"Subscriber{side}",
                    "className": "std_msgs/String"},
                   {"endpointTag": rid, "interfaceTag": "resp", "interfaceType": f"Publisher{side}",
                    "className": "std_msgs/String"},
                   {"endpointTag": rid, "interfaceTag": "srv", "interfaceType": f"ServiceProvider{side}",
                    "className": "Test/StringEcho"}])
    await r.send("CX", {"connect": [{"tagA": f"{ctag}/{t}", "tagB": f"{rid}/{t}"} for t in ("req", "resp", "srv")]})
    await r.wait_up("req", "resp", "srv")


async def test_converter_topic_and_service_echo(eng):
    async with RawRobot(eng.master_url, "conv") as r:
        await _echo_container(r, "convC", "Converter")
        # the node may subscribe a moment after the interfaces are up: repeat until the echo arrives
        for _ in range(50):
            await r.send("DM", {"iTag": "req", "type": "std_msgs/String", "msgID": "", "msg": {"data": "hello"}})
            try:
                dm = await r.expect("DM", timeout=0.5, pred=lambda d: d["iTag"] == "resp")
                break
            except TimeoutError:
                continue
        assert dm["msg"] == {"data": "hello"} and dm["type"] == "std_msgs/String"
        await r.send("DM", {"iTag": "srv", "type": "Test/StringEcho", "msgID": "call-1", "msg": {"data": "svc"}})
        dm = await r.expect("DM", pred=lambda d: d["iTag"] == "srv")
        assert dm["msgID"] == "call-1" and dm["msg"] == {"data": "svc"}


async def test_forwarder_binary_parts_both_orders(engine_ws_impls):
    eng = engine_ws_impls
    async with RawRobot(eng.master_url, "fwd") as r:
        await _echo_container(r, "fwdC", "Forwarder")
        payload = bytes(TS.serialize_ros1(TS.types["std_msgs/msg/String"](data="b" * 100_000), "std_msgs/msg/String"))
        got = None
        for i in range(50):
            ref = f"{i:032x}"
            if i % 2:   # binary part first, then the JSON frame
                await r.ws.send(ref.encode() + payload)
                await r.send("DM", {"iTag": "req", "type": "std_msgs/String", "msgID": "", "msg*": ref})
            else:
                await r.send("DM", {"iTag": "req", "type": "std_msgs/String", "msgID": "", "msg*": ref})
                await r.ws.send(ref.encode() + payload)
            try:
                dm = await r.expect("DM", timeout=0.5, pred=lambda d: d["iTag"] == "resp")
            except TimeoutError:
                continue
            part = await r.recv()
            assert isinstance(part, bytes) and part[:32].decode() == dm["msg*"]
            got = part[32:]
            break
        assert got == payload
        # service through a forwarder: request and response are serialized halves
        req = bytes(TS.serialize_ros1(TS.types["std_msgs/msg/String"](data="sv"), "std_msgs/msg/String"))
        await r.send("DM", {"iTag": "srv", "type": "Test/StringEcho", "msgID": "f1", "msg*": "f" * 32})
        await r.ws.send(b"f" * 32 + req)
        dm = await r.expect("DM", pred=lambda d: d["iTag"] == "srv")
        part = await r.recv()
        assert dm["msgID"] == "f1" and part[32:] == req
        # large messages back to back: every internal link receives each into a buffer of its own and
        # hands it on without a copy (rce.transport.framing); none may be overwritten while the next one arrives
        bigs = [bytes(TS.serialize_ros1(TS.types["std_msgs/msg/String"](data=c * 3_000_000), "std_msgs/msg/String"))
                for c in "xyz"]
        for i, big in enumerate(bigs):
            ref = f"{0xb16 + i:032x}"
            await r.send("DM", {"iTag": "req", "type": "std_msgs/String", "msgID": "", "msg*": ref})
            await r.ws.send(ref.encode() + big)
        echoed = []
        while len(echoed) < len(bigs):
            m = await r.recv()
            if isinstance(m, bytes) and len(m) == 32 + len(bigs[0]):     # not a late echo of the small ones
                echoed.append(m[32:])
        assert echoed == bigs


async def test_a_string_that_is_not_utf8_goes_through_a_python_node_and_back_unchanged(eng):
    """ROS strings are bytes: a forwarder carries them to the Test package's stringEcho.py, which
    decodes them as rospy does (no error) and publishes and answers them back byte for byte."""
    raw = b"not utf-8: \x00\xff\xfe"
    payload = len(raw).to_bytes(4, "little") + raw
    async with RawRobot(eng.master_url, "bytes") as r:
        await _echo_container(r, "bytesC", "Forwarder")
        got = None
        for i in range(50):          # the node may subscribe a moment after the interfaces are up
            ref = f"{0xb7e5 + i:032x}"
            await r.send("DM", {"iTag": "req", "type": "std_msgs/String", "msgID": "", "msg*": ref})
            await r.ws.send(ref.encode() + payload)
            try:
                await r.expect("DM", timeout=0.5, pred=lambda d: d["iTag"] == "resp")
            except TimeoutError:
                continue
            got = (await r.recv())[32:]
            break
        assert got == payload
        await r.send("DM", {"iTag": "srv", "type": "Test/StringEcho", "msgID": "b1", "msg*": "e" * 32})
        await r.ws.send(b"e" * 32 + payload)
        dm = await r.expect("DM", pred=lambda d: d["iTag"] == "srv")
        part = await r.recv()
        assert dm["msgID"] == "b1" and part[32:] == payload


def _metric(port: int, name: str) -> float:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as resp:
        line = next(x for x in resp.read().decode().splitlines() if x.startswith(name + " "))
    return float(line.split()[1])


@pytest.mark.parametrize("max_lag", ["", "0"])
async def test_an_endpoint_behind_a_flooding_robot_sheds_the_oldest_and_delivers_the_newest(engine_ws_impls, max_lag):
    """Real overload: a robot writes 30,000 topic DMs as fast as its socket takes them, far faster
    than its endpoint converts and relays them. Once the endpoint has been behind the robot for
    ``max_lag`` (1 s) it sheds the robot's topic messages, counted, until it has caught up: the
    echoes keep their order, the newest message gets through, and nothing is counted twice. A
    connection that asked ``maxLag=0`` (an operator's commands) is never shed (10,000 DMs)."""
    eng = engine_ws_impls
    n = 10_000 if max_lag else 30_000
    async with RawRobot(eng.master_url, f"flood{max_lag}", query=f"&maxLag={max_lag}" if max_lag else "") as r:
        await _echo_container(r, f"flood{max_lag}C", "Converter")
        echoed: list[int] = []
        told: list[dict] = []
        newest, some = asyncio.Event(), asyncio.Event()

        async def read() -> None:
            async for m in r.ws:
                d = json.loads(m) if isinstance(m, str) else {}
                if d.get("type") == "ST" and d["data"].get("topic") == "lag":
                    told.append(d["data"])
                text = d["data"]["msg"]["data"] if d.get("type") == "DM" and d["data"]["iTag"] == "resp" else ""
                if text == "up":           # the warm-up's echo (one of them may come after the clear below)
                    some.set()
                elif text.isdigit():
                    echoed.append(int(text))
                    if echoed[-1] == n - 1:
                        newest.set()
        reader = asyncio.create_task(read())
        try:
            for _ in range(50):                # the node may subscribe a moment after the interfaces are up
                await r.send("DM", {"iTag": "req", "type": "std_msgs/String", "msgID": "", "msg": {"data": "up"}})
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(some.wait(), 0.5)
                    break
            assert some.is_set(), "no echo"
            shed0 = _metric(eng.robot_ready[0]["metrics_port"], "rce_robot_shed_total")
            frames = [json.dumps({"type": "DM", "data": {"iTag": "req", "type": "std_msgs/String", "msgID": "",
                                                         "msg": {"data": str(i)}}}) for i in range(n)]
            for i in range(0, n, 500):         # 500 frames per write: the robot outruns its endpoint
                while not ws_cork.writable(r.ws):
                    await r.ws.drain()
                ws_cork.write(r.ws, frames[i:i + 500])
            await asyncio.wait_for(newest.wait(), 120)
        finally:
            reader.cancel()
    shed = _metric(eng.robot_ready[0]["metrics_port"], "rce_robot_shed_total") - shed0
    assert echoed == sorted(set(echoed)) and echoed[-1] == n - 1
    if max_lag:
        assert shed == 0 and told == []
    else:
        assert shed > 0 and len(echoed) + shed <= n
        assert told[0]["status"] == "shedding" and told[0]["behind_s"] >= 1.0 and told[-1]["status"] == "caught_up"


async def test_a_robot_that_stops_reading_gets_the_newest_when_it_reads_again(engine_ws_impls):
    """Real stall of the robot's side: it stops reading its websocket (the client library stops
    reading the socket once 16 frames wait, the kernel's buffers fill, then the endpoint's) while
    2,000 echoes of 8 kB come for it. They wait at the endpoint; once the robot reads again, those
    that waited longer than max_lag (1 s) with a newer one of their topic behind them are dropped,
    counted in rce_robot_dropped_total, and the rest come in order, the newest last."""
    eng = engine_ws_impls
    n, pad = 2000, "x" * 8000
    port = eng.robot_ready[0]["metrics_port"]
    async with RawRobot(eng.master_url, "stalled") as r:
        await _echo_container(r, "stalledC", "Converter")
        for _ in range(50):                    # the node may subscribe a moment after the interfaces are up
            await r.send("DM", {"iTag": "req", "type": "std_msgs/String", "msgID": "", "msg": {"data": "-1 "}})
            with contextlib.suppress(TimeoutError):
                await r.expect("DM", 0.5, lambda d: d["iTag"] == "resp")
                break
        dropped0, shed0 = _metric(port, "rce_robot_dropped_total"), _metric(port, "rce_robot_shed_total")
        frames = [json.dumps({"type": "DM", "data": {"iTag": "req", "type": "std_msgs/String", "msgID": "",
                                                     "msg": {"data": f"{i} {pad}"}}}) for i in range(n)]
        for i in range(0, n, 100):             # nothing is read meanwhile
            while not ws_cork.writable(r.ws):
                await r.ws.drain()
            ws_cork.write(r.ws, frames[i:i + 100])
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 60
        while _metric(port, "rce_robot_queue_depth") < 100:      # echoes wait at the endpoint
            assert loop.time() < deadline, "no echoes waited for the stalled robot"
            await asyncio.sleep(0.1)
        await asyncio.sleep(1.2)               # they grow older than max_lag (a real wait: what is tested is age)
        echoed: list[int] = []
        while not echoed or echoed[-1] != n - 1:
            d = await r.expect("DM", 60, lambda d: d["iTag"] == "resp")
            i = int(d["msg"]["data"].split(" ", 1)[0])
            if i >= 0:
                echoed.append(i)
    dropped = _metric(port, "rce_robot_dropped_total") - dropped0
    shed = _metric(port, "rce_robot_shed_total") - shed0
    assert echoed == sorted(set(echoed)) and echoed[-1] == n - 1
    assert dropped > 0 and len(echoed) + dropped + shed <= n, (len(echoed), dropped, shed)


async def test_a_max_lag_that_is_not_seconds_is_refused_at_the_handshake(engine_ws_impls):
    eng = engine_ws_impls
    for bad in ("-1", "soon", "inf"):
        with pytest.raises(InvalidStatus) as ei:
            async with RawRobot(eng.master_url, "badLag", query=f"&maxLag={bad}"):
                pass
        assert ei.value.response.status_code == 400 and b"maxLag" in ei.value.response.body


async def test_parameters_reach_nodes(eng):
    async with RawRobot(eng.master_url, "params") as r:
        await r.send("CC", {"containerTag": "paramC"})
        await r.cn(setParam=[{"containerTag": "paramC", "name": n, "value": v}
                             for n, v in (("int", 99), ("str", "foo"), ("float", 3.3), ("bool", True))],
                   addNodes=[{"containerTag": "paramC", "nodeTag": "pt", "pkg": "Test", "exe": "paramTest.py"}],
                   addInterfaces=[{"endpointTag": "paramC", "interfaceTag": "pt",
                                   "interfaceType": "ServiceClientInterface",
                                   "className": "Test/ParameterTest", "addr": "/parameterTest"},
                                  {"endpointTag": "params", "interfaceTag": "pt",
                                   "interfaceType": "ServiceProviderConverter", "className": "Test/ParameterTest"}])
        await r.send("CX", {"connect": [{"tagA": "paramC/pt", "tagB": "params/pt"}]})
        await r.wait_up("pt")
        # the call waits for the node to provide the service (bounded), no retry needed
        await r.send("DM", {"iTag": "pt", "type": "Test/ParameterTest", "msgID": "p1", "msg": {}})
        m = await r.expect("DM", pred=lambda d: d["iTag"] == "pt")
        assert m["msgID"] == "p1"
        assert m["msg"]["msg"].splitlines() == ["int:   99", "str:   foo", "float: 3.3", "bool:  True"]


async def test_container_to_container(eng):
    """C2C: a robot's message enters container A, is forwarded A -> B by interfaces, echoed in B, and comes back."""
    async with RawRobot(eng.master_url, "c2c") as r:
        await r.send("CC", {"containerTag": "c2cA"})
        await r.send("CC", {"containerTag": "c2cB"})
        ifs = [("c2cA", "in", "PublisherInterface", "/relay"),          # robot -> A's /relay
               ("c2cA", "toB", "SubscriberInterface", "/relay"),        # A's /relay -> B
               ("c2cB", "fromA", "PublisherInterface", "/stringEchoReq"),
               ("c2cB", "out", "SubscriberInterface", "/stringEchoResp"),
               ("c2c", "in", "SubscriberConverter", None), ("c2c", "out", "PublisherConverter", None)]
        await r.cn(addNodes=[{"containerTag": "c2cB", "nodeTag": "echo", "pkg": "Test", "exe": "stringEcho.py"}],
                   addInterfaces=[{"endpointTag": e, "interfaceTag": t, "interfaceType": k,
                                   "className": "std_msgs/String", **({"addr": a} if a else {})}
                                  for e, t, k, a in ifs])
        await r.send("CX", {"connect": [{"tagA": "c2cA/in", "tagB": "c2c/in"},
                                        {"tagA": "c2cA/toB", "tagB": "c2cB/fromA"},
                                        {"tagA": "c2cB/out", "tagB": "c2c/out"}]})
        await r.wait_up("in", "out")
        for _ in range(50):
            await r.send("DM", {"iTag": "in", "type": "std_msgs/String", "msgID": "", "msg": {"data": "via A and B"}})
            try:
                dm = await r.expect("DM", timeout=0.5, pred=lambda d: d["iTag"] == "out")
                break
            except TimeoutError:
                continue
        assert dm["msg"]["data"] == "via A and B"
        conns = eng.admin("/api/connections")
        assert {"user": "testUser", "tagA": "c2cA/toB", "tagB": "c2cB/fromA"} in [
            {k: c[k] for k in ("user", "tagA", "tagB")} for c in conns] or any(
            {c["tagA"], c["tagB"]} == {"c2cA/toB", "c2cB/fromA"} for c in conns)


async def test_status_on_disconnect_and_teardown_on_robot_leave(eng):
    async with RawRobot(eng.master_url, "leaver") as r:
        await _echo_container(r, "leaverC", "Converter")
        await r.send("CX", {"disconnect": [{"tagA": "leaverC/req", "tagB": "leaver/req"}]})
        st = await r.expect("ST", pred=lambda d: d.get("topic") == "iu" and d["iTag"] == "req")
        assert st["status"] is False
        state = eng.admin("/api/state")
        assert any(c["ctag"] == "leaverC" and c["state"] == "running" for c in state["containers"])
    # the robot left: its container, nodes and interfaces are gone
    for _ in range(200):
        state = eng.admin("/api/state")
        if not any(c["ctag"] == "leaverC" for c in state["containers"]):
            break
        import asyncio
        await asyncio.sleep(0.05)   # polling the admin API for the teardown, bounded
    assert not any(c["ctag"] == "leaverC" for c in state["containers"])
    assert not any(i["tag"].startswith("leaver") for i in state["interfaces"])
