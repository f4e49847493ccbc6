"""The rosbridge v2 endpoint, driven by unmodified roslibpy (PyPI) against a real
engine: the Test package's stringEcho in a container a robot creates; roslibpy calls the echo
service, subscribes and publishes (the echo comes back), and lists topics and services (rosapi).
A raw websocket client sends malformed ops: each gets a status error and the session goes on.

roslibpy runs twisted's reactor in a thread of its own (started once per process and left
running: it cannot restart); its blocking steps run in a worker thread with a named bound."""
from __future__ import annotations

import asyncio
import base64
import contextlib
import hashlib
import io
import json
import math
import queue
import time
import urllib.request
from functools import partial
from typing import Any

import cbor2
import numpy as np
import pytest
import roslibpy
from PIL import Image
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from rce.plumbing.errors import ProtocolError, RCEError
from rce.messages import default_registry
from rce.protocol.robot_outbox import CONTROL_BACKLOG
from rce_robot import ws_cork
from rce_robot.endpoint import RobotEndpoint
from rce_robot.link_report import LinkReports
from rce_robot.rosbridge.endpoint import RosbridgeServer
from rce_robot.rosbridge.compression import cbor_publish, cbor_raw_publish, png_op
from rce_robot.rosbridge.fragments import Defragmenter
from rce_robot.rosbridge.outbox import RosbridgeOutbox
from rce_robot.rosbridge.session import Bridge, RosbridgeSession, RosbridgeSubscription
from wsclient import RawRobot

pytestmark = pytest.mark.asyncio

CONNECT_WAIT = 10.0     # s for roslibpy to connect
STEP_WAIT = 15.0        # s for one step: a service call's answer, a status message
GRAPH_WAIT = 30.0       # s for the echo node (started by CN) to show its service on the container's bus
RETRY_EVERY = 0.3       # s between two looks at the graph / two publishes while the echo node is starting
SESSION_WAIT = 60.0     # s for a whole roslibpy session
RECEIVED_MAX = 1000     # messages a test subscription keeps


@pytest.fixture(scope="module")
def eng(shared_engine):
    return shared_engine


def _url(eng, robot: str, ctag: str, password: str = "testUser") -> str:
    port = eng.robot_ready[0]["rosbridge_port"]
    pw = hashlib.sha256(password.encode()).hexdigest()
    return f"ws://127.0.0.1:{port}/?userID=testUser&robotID={robot}&password={pw}&container={ctag}"


async def _echo_container(r: RawRobot, ctag: str) -> None:
    await r.send("CC", {"containerTag": ctag})
    await r.expect("ST", pred=lambda d: d.get("topic") == "container" and d.get("cTag") == ctag
                   and d.get("status") == "running")
    await r.cn(addNodes=[{"containerTag": ctag, "nodeTag": "echo", "pkg": "Test", "exe": "stringEcho.py"}])


def _wait_for_service(ros: roslibpy.Ros, name: str) -> None:
    """Look at the graph (rosapi ``/rosapi/services``) until ``name`` is on it."""
    deadline = time.monotonic() + GRAPH_WAIT
    while name not in ros.get_services():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{name} not on the container's graph within {GRAPH_WAIT} s")
        time.sleep(RETRY_EVERY)


def _roslibpy_session(url: str) -> dict:
    """Everything a roslibpy user does: service call, subscribe + publish echo, topic listing."""
    ros = roslibpy.Ros(url)
    ros.run(timeout=CONNECT_WAIT)
    try:
        _wait_for_service(ros, "/stringEchoService")
        answer = roslibpy.Service(ros, "/stringEchoService", "Test/StringEcho").call(
            roslibpy.ServiceRequest({"data": "svc"}), timeout=STEP_WAIT)
        received: queue.Queue = queue.Queue(RECEIVED_MAX)
        roslibpy.Topic(ros, "/stringEchoResp", "std_msgs/String").subscribe(
            lambda m: received.full() or received.put_nowait(m))
        pub = roslibpy.Topic(ros, "/stringEchoReq", "std_msgs/String")
        deadline, echo = time.monotonic() + GRAPH_WAIT, None
        while echo is None and time.monotonic() < deadline:     # the subscription may reach the node late
            pub.publish(roslibpy.Message({"data": "hello"}))
            try:
                echo = received.get(timeout=RETRY_EVERY)
            except queue.Empty:
                continue
        ros.set_param("/rbPy/gain", {"p": 1.5, "axes": [1, 2]})
        ros.set_param("rbPy/name", "robot \u00e9")          # relative: resolved under /, as rosapi does
        params = {"tree": ros.get_param("/rbPy/gain"), "leaf": ros.get_param("/rbPy/gain/p"),
                  "text": ros.get_param("/rbPy/name"), "missing": ros.get_param("/rbPy/nothing"),
                  "names": ros.get_params()}
        ros.delete_param("/rbPy/name")
        params["exists"] = (ros.get_params(), ros.get_param("/rbPy/name"))
        return {"answer": dict(answer), "echo": echo, "topics": ros.get_topics(),
                "type": ros.get_service_type("/stringEchoService"), "params": params}
    finally:
        ros.close()


async def test_roslibpy_service_echo_and_topics(eng):
    async with RawRobot(eng.master_url, "rbOwner") as r:
        await _echo_container(r, "rbC")
        got = await asyncio.wait_for(asyncio.to_thread(_roslibpy_session, _url(eng, "rbPy", "rbC")), SESSION_WAIT)
        await _session_gone(eng, "rbC")           # while the container lives (its end would take them too)
    assert got["answer"] == {"data": "svc"}
    assert got["echo"] == {"data": "hello"}
    assert {"/stringEchoReq", "/stringEchoResp"} <= set(got["topics"])
    assert got["type"] == "Test/StringEcho"
    names, after = got["params"].pop("names"), got["params"].pop("exists")
    assert got["params"] == {"tree": {"p": 1.5, "axes": [1, 2]}, "leaf": 1.5, "text": "robot \u00e9", "missing": None}
    assert {"/rbPy/gain/p", "/rbPy/gain/axes", "/rbPy/name"} <= set(names)
    assert "/rbPy/name" not in after[0] and "/rbPy/gain/p" in after[0] and after[1] is None     # deleted


async def _session_gone(eng, ctag: str) -> None:
    """Once its client has left, a session's interfaces are gone from the master (both sides)."""
    deadline = time.monotonic() + STEP_WAIT
    while True:
        left = [i for i in await asyncio.to_thread(eng.admin, "/api/interfaces")
                if i["tag"].split("/")[0] in ("rbPy", "rbRaw") or "/rosbridge." in i["tag"]]
        if not left:
            return
        assert time.monotonic() < deadline, f"interfaces of a closed rosbridge session left on {ctag}: {left}"
        await asyncio.sleep(RETRY_EVERY)


def _provide_service(url: str, call) -> Any:
    """roslibpy provides ``/rbClientSvc`` (Test/StringEcho, answers the text upper-cased); ``call()``
    (the container calling it, in this thread) returns what the container got."""
    ros = roslibpy.Ros(url)
    ros.run(timeout=CONNECT_WAIT)
    try:
        def handler(request, response):
            response["data"] = request["data"].upper()
            return True
        svc = roslibpy.Service(ros, "/rbClientSvc", "Test/StringEcho")
        svc.advertise(handler)
        _wait_for_service(ros, "/rbClientSvc")        # the advertise has reached the container's bus
        return call()
    finally:
        ros.close()


async def test_roslibpy_service_called_from_the_container(eng):
    async with RawRobot(eng.master_url, "rbOwner4") as r:
        await _echo_container(r, "rbC4")
        call = partial(eng.admin, "/api/containers/testUser/rbC4/call",
                       {"service": "/rbClientSvc", "request": {"data": "shout"}, "timeout": STEP_WAIT})
        got = await asyncio.wait_for(asyncio.to_thread(_provide_service, _url(eng, "rbPy4", "rbC4"), call),
                                     SESSION_WAIT)
    assert got == {"data": "SHOUT"}


async def _next(ws, op: str) -> dict:
    while True:
        m = json.loads(await asyncio.wait_for(ws.recv(), STEP_WAIT))
        if m["op"] == op:
            return m


async def _first_fragment_of(ws, mid: str) -> dict:
    """The first ``fragment`` op of message ``mid``; anything else (a late echo of an earlier
    subscription, in any form) is passed over."""
    while True:
        frame = await asyncio.wait_for(ws.recv(), STEP_WAIT)
        m = json.loads(frame) if isinstance(frame, str) else {}
        if m.get("op") == "fragment" and m.get("id") == mid:
            return m


async def test_malformed_ops_get_status_and_session_goes_on(eng):
    async with RawRobot(eng.master_url, "rbOwner2") as r:
        await _echo_container(r, "rbC2")
        async with connect(_url(eng, "rbRaw", "rbC2")) as ws:
            for bad, says in (("not json", "not JSON"), (json.dumps([1]), "JSON object"), ("[" * 100_000, "not JSON"),
                              (json.dumps({"op": "fly"}), "unknown op 'fly'"),
                              (json.dumps({"op": "publish", "topic": "/x", "msg": {}, "id": "p1"}), "not advertised"),
                              (json.dumps({"op": "subscribe", "topic": "/nowhere", "id": "s1"}), "'/nowhere'"),
                              (json.dumps({"op": "advertise", "topic": "/x", "type": "No/Such"}), "No/Such"),
                              (json.dumps({"op": "fragment", "id": "f", "data": "{", "num": 0, "total": 0}), "'total'"),
                              (json.dumps({"op": "subscribe", "topic": "/t", "type": "std_msgs/String",
                                           "compression": "zip"}), "compression must be"),
                              (json.dumps({"op": "subscribe", "topic": "/t", "type": "std_msgs/String",
                                           "lane": "fast"}), "field 'lane': unknown lane 'fast'")):
                await ws.send(bad)
                status = await _next(ws, "status")
                assert status["level"] == "error" and says in status["msg"], (bad, status)
            for ok in ({"op": "subscribe", "topic": "/stringEchoResp", "type": "std_msgs/String", "id": "s2",
                        "throttle_rate": 100, "queue_length": 2, "lane": "bulk"},
                       {"op": "unsubscribe", "topic": "/stringEchoResp", "id": "s2"},
                       {"op": "advertise", "topic": "/stringEchoReq", "type": "std_msgs/String", "id": "a1"},
                       {"op": "unadvertise", "topic": "/stringEchoReq", "id": "a1"}):
                await ws.send(json.dumps(ok))
            await ws.send(json.dumps({"op": "call_service", "service": "/rosapi/topics", "id": "t1"}))
            reply = json.loads(await asyncio.wait_for(ws.recv(), STEP_WAIT))      # no status came before it
            assert reply["op"] == "service_response", reply
            assert reply["id"] == "t1" and reply["result"] is True and "topics" in reply["values"]
            await ws.send(json.dumps({"op": "call_service", "service": "/rosapi/set_param", "id": "sp",
                                      "args": {"name": "/p", "value": "not json"}}))
            reply = await _next(ws, "service_response")            # a failed call, as rosapi's exception
            assert reply["id"] == "sp" and reply["result"] is False and "JSON text" in reply["values"], reply
            await ws.send(json.dumps({"op": "publish", "topic": "/stringEchoReq", "msg": {"data": "x"}}))
            assert "not advertised" in (await _next(ws, "status"))["msg"]
            await ws.send(json.dumps({"op": "subscribe", "topic": "/stringEchoResp", "type": "std_msgs/String"}))
            await ws.send(json.dumps({"op": "call_service", "service": "/rosapi/topics", "id": "t2"}))
            assert (await _next(ws, "service_response"))["id"] == "t2"
            await ws.send(json.dumps({"op": "advertise_service", "service": "/rbRawSvc", "type": "Test/StringEcho"}))
            await ws.send(json.dumps({"op": "call_service", "service": "/rosapi/services", "id": "t3"}))
            reply = json.loads(await asyncio.wait_for(ws.recv(), STEP_WAIT))      # ops run in order
            assert reply["id"] == "t3" and "/rbRawSvc" in reply["values"]["services"], reply
            call = asyncio.create_task(asyncio.to_thread(
                eng.admin, "/api/containers/testUser/rbC2/call",
                {"service": "/rbRawSvc", "request": {"data": "x"}, "timeout": STEP_WAIT}))
            request = await _next(ws, "call_service")
            assert request["service"] == "/rbRawSvc" and request["args"] == {"data": "x"}
            await ws.send(json.dumps({"op": "service_response", "service": "/rbRawSvc", "id": request["id"],
                                      "values": "no paper in tray 2", "result": False}))
            with pytest.raises(RCEError, match="refused the call: no paper in tray 2"):
                await asyncio.wait_for(call, STEP_WAIT)
            await ws.send(json.dumps({"op": "unadvertise_service", "service": "/rbRawSvc"}))
            await ws.send(json.dumps({"op": "call_service", "service": "/rosapi/services", "id": "t4"}))
            reply = json.loads(await asyncio.wait_for(ws.recv(), STEP_WAIT))      # no status for the refusal
            assert reply["id"] == "t4" and "/rbRawSvc" not in reply["values"]["services"], reply
        await _session_gone(eng, "rbC2")


async def test_throttle_and_queue_length():
    """Sans-I/O: with throttle_rate 1000 ms and queue_length 2, the first message goes out at once,
    the next two wait, and older waiting ones are dropped (counted)."""
    session = RosbridgeSession("u", "r", "c", master=None)
    bridge = Bridge("s", "/t", "std_msgs/String", "s1", "rosbridge.r.s1")
    session.by_itag["s1"] = bridge
    session.subs["/t"] = {"sub": RosbridgeSubscription("sub", 1000, 2)}
    for i in range(5):
        assert session.send_dm("s1", "std_msgs/String", "", {"data": str(i)}, data=True)
    assert _ops(session) == [{"op": "publish", "topic": "/t", "msg": {"data": "0"}}]
    sub = session.subs["/t"]["sub"]
    assert list(sub.pending) == [{"data": "3"}, {"data": "4"}] and sub.dropped == 2 and session.dropped == 2
    assert session.outbox.empty() and sub.timer is not None
    sub.timer.cancel()
    session._flush(bridge, sub)              # the timer's work: the oldest waiting one goes, the next waits
    assert _ops(session)[0]["msg"] == {"data": "3"} and list(sub.pending) == [{"data": "4"}]
    assert sub.timer is not None
    sub.timer.cancel()


async def test_handshake_refusals(eng):
    async with RawRobot(eng.master_url, "rbOwner3") as r:
        await _echo_container(r, "rbC3")
        for url, code in ((_url(eng, "rbBad", "rbC3", password="wrong"), 401),
                          (_url(eng, "rbBad", "noSuchContainer"), 404),
                          (_url(eng, "rbBad", "rbC3").split("&container")[0], 400),
                          (_url(eng, "rbBad", "rbC3") + "&maxLag=-1", 400)):
            with pytest.raises(InvalidStatus) as e:
                async with connect(url):
                    pass
            assert e.value.response.status_code == code
        # roslibpy and roslibjs show no HTTP reason: the endpoint's log names each refusal
        robot_log = next(p for p in eng.logs if p.name.startswith("robot")).read_text()
        refused = [json.loads(line) for line in robot_log.splitlines() if '"rosbridge client refused"' in line]
        assert {(r["status"], r["robot"], r["container"]) for r in refused} >= {
            (401, "rbBad", "rbC3"), (404, "rbBad", "noSuchContainer"), (400, "rbBad", None)}
        assert any(r["reason"] == "container 'noSuchContainer' does not exist" for r in refused)
        async with connect(_url(eng, "rbNoLag", "rbC3") + "&maxLag=0") as ws:     # its publish ops never shed
            await ws.send(json.dumps({"op": "call_service", "service": "/rosapi/topics", "id": "t"}))
            assert (await _next(ws, "service_response"))["id"] == "t"


async def test_a_client_that_does_not_keep_up_gets_each_subscriptions_newest():
    """Sans-I/O: the rosbridge outbox follows the RCE session's policy, in the same code
    (rce.protocol.outbox): past its bound the busiest subscription drops its oldest publish op (the
    outbox used to drop the newest message), the newest of every subscription goes out, and other
    ops are never dropped."""
    session = RosbridgeSession("u", "r", "c", master=None, max_lag=None)
    session.outbox = RosbridgeOutbox(size=4)
    session.by_itag = {"s1": Bridge("s", "/fast", "std_msgs/String", "s1", "rosbridge.r.s1"),
                       "s2": Bridge("s", "/slow", "std_msgs/String", "s2", "rosbridge.r.s2")}
    session.subs = {"/fast": {"a": RosbridgeSubscription("a", 0, 1)}, "/slow": {"b": RosbridgeSubscription("b", 0, 1)}}
    assert session.send_dm("s2", "std_msgs/String", "", {"data": "s0"}, data=True)
    for i in range(6):
        assert session.send_dm("s1", "std_msgs/String", "", {"data": f"f{i}"}, data=True)
    session.status("error", "an op that was refused")
    out = []
    while not session.outbox.empty():
        out += _ops(session)
    assert [(op["op"], op["msg"]["data"] if op["op"] == "publish" else op["msg"]) for op in out] == [
        ("status", "an op that was refused"),             # control first (docs/lanes.md)
        ("publish", "s0"), ("publish", "f3"), ("publish", "f4"), ("publish", "f5")]
    assert session.dropped == 3 and session.stats()["dropped"] == 3 and session.stats()["msgs_out"] == 8


async def test_a_client_that_does_not_read_is_closed_once_and_loses_no_op():
    """Ops that are not topic data are never dropped; a client that lets CONTROL_BACKLOG x the bound
    of them wait is closed (1008) once, as a robot that does not read."""
    class ClosingLink:
        def __init__(self) -> None:
            self.closes: list[tuple[int, str]] = []

        async def close(self, code: int, reason: str) -> None:
            self.closes.append((code, reason))

    session = RosbridgeSession("u", "r", "c", master=None)
    session.outbox, session.ws = RosbridgeOutbox(size=1), ClosingLink()
    for i in range(CONTROL_BACKLOG + 5):
        session.status("warning", f"w{i}")
    await session.closing
    assert session.ws.closes == [(1008, "the rosbridge client does not read: 11 messages wait for it")]
    out = []
    while not session.outbox.empty():
        out += _ops(session)
    assert [op["msg"] for op in out] == [f"w{i}" for i in range(CONTROL_BACKLOG + 5)] and session.dropped == 0


def _ops(session: RosbridgeSession) -> list[dict]:
    """The ops of the oldest message the session queued (its frames, JSON text)."""
    return [json.loads(f) for f in session.outbox.get_nowait()]


async def test_fragments_split_and_reassemble():
    """Sans-I/O: an op longer than fragment_size goes as fragment ops whose data joins back to it;
    the client's fragments are reassembled in any order, within the bounds (ids, characters,
    expiry), and what is thrown away is counted."""
    outbox = RosbridgeOutbox()
    op = {"op": "publish", "topic": "/t", "msg": {"data": "x" * 300}}
    assert outbox.op(op, fragment_size=100) and outbox.fragments == 4
    frags = [json.loads(f) for f in outbox.get_nowait()]
    assert [(f["op"], f["num"], f["total"]) for f in frags] == [("fragment", i, 4) for i in range(4)]
    assert len({f["id"] for f in frags}) == 1 and json.loads("".join(f["data"] for f in frags)) == op
    assert outbox.op(op, fragment_size=1000) and json.loads(outbox.get_nowait()[0]) == op    # short enough: whole

    now = [0.0]
    d = Defragmenter(max_messages=2, max_chars=1000, expiry=5.0, clock=lambda: now[0])
    assert d.add(frags[2]) is None and d.add(frags[0]) is None and d.add(frags[3]) is None
    assert json.loads(d.add(frags[1])) == op and d.messages == 1 and d.held == 0
    d.add({"op": "fragment", "id": "a", "data": "x", "num": 0, "total": 2})
    d.add({"op": "fragment", "id": "b", "data": "x", "num": 0, "total": 2})
    with pytest.raises(ProtocolError, match="already being reassembled"):
        d.add({"op": "fragment", "id": "c", "data": "x", "num": 0, "total": 2})
    with pytest.raises(ProtocolError, match="'total' changed"):
        d.add({"op": "fragment", "id": "b", "data": "x", "num": 1, "total": 3})
    with pytest.raises(ProtocolError, match="exceed 1000 characters"):
        d.add({"op": "fragment", "id": "a", "data": "x" * 1000, "num": 1, "total": 2})
    assert d.dropped == 5 and not d.pending and d.held == 0        # c; b and its fragment; a and its fragment
    d.add({"op": "fragment", "id": "e", "data": "x", "num": 0, "total": 2})
    now[0] = 6.0
    assert d.expire() == ["e"] and d.dropped == 6 and d.held == 0


async def test_png_and_cbor_forms():
    """Sans-I/O: png packs the op's JSON into the RGB pixels of a PNG as rosbridge's
    pngcompression (width floor(sqrt(n/3)), '\\n' padding); cbor carries uint8[] as a byte string
    and float32[] as an RFC 8746 little-endian typed array (tag 85), as rosbridge's cbor_conversion;
    cbor-raw carries the ROS 1 bytes and the receive time."""
    text = json.dumps({"op": "publish", "topic": "/t", "msg": {"data": "h\u00e9llo " * 20}})
    image = Image.open(io.BytesIO(base64.b64decode(png_op(text)["data"])))
    assert image.mode == "RGB" and image.size[0] == math.floor(math.sqrt(len(text) / 3))
    assert image.tobytes().decode("ascii").rstrip("\n") == text
    registry = default_registry()
    image_msg = {"header": {"seq": 1, "stamp": {"secs": 2, "nsecs": 3}, "frame_id": "f"}, "height": 1, "width": 3,
                 "encoding": "mono8", "is_bigendian": 0, "step": 3, "data": base64.b64encode(b"\0\1\2").decode()}
    got = cbor2.loads(cbor_publish(registry, "sensor_msgs/msg/Image", "/im", image_msg))
    assert got == {"op": "publish", "topic": "/im", "msg": {**image_msg, "data": b"\0\1\2"}}
    got = cbor2.loads(cbor_publish(registry, "std_msgs/msg/Float32MultiArray", "/f",
                                   {"layout": {"dim": [], "data_offset": 0}, "data": [1.5, None]}))
    tagged = got["msg"]["data"]
    assert tagged.tag == 85 and np.frombuffer(tagged.value, "<f4")[0] == 1.5 and np.isnan(
        np.frombuffer(tagged.value, "<f4")[1])
    raw = cbor2.loads(cbor_raw_publish(registry, "std_msgs/msg/String", "/s", {"data": "hi"}, 12.25))
    assert raw == {"op": "publish", "topic": "/s", "msg": {"secs": 12, "nsecs": 250_000_000,
                                                           "bytes": b"\x02\x00\x00\x00hi"}}   # ROS 1 bytes


async def _frames_until(ws, want: set[str], publish) -> dict[str, Any]:
    """Publish (``publish()``) until each of ``want`` (fragmented, png, cbor) has come back once;
    the fragments of one message are joined."""
    got: dict[str, Any] = {}
    parts: dict[int, str] = {}
    deadline = time.monotonic() + GRAPH_WAIT
    while set(got) < want:
        assert time.monotonic() < deadline, f"only {sorted(got)} of {sorted(want)} came back"
        await publish()
        try:
            frame = await asyncio.wait_for(ws.recv(), RETRY_EVERY)
        except asyncio.TimeoutError:
            continue
        if isinstance(frame, bytes):
            got["cbor"] = cbor2.loads(frame)
            continue
        op = json.loads(frame)
        if op["op"] == "png":
            png = Image.open(io.BytesIO(base64.b64decode(op["data"]))).tobytes().decode("ascii")
            got["png"] = json.loads(png)          # trailing '\n' padding is JSON whitespace
        elif op["op"] == "fragment":
            parts[op["num"]] = op["data"]
            if len(parts) == op["total"]:
                got["fragmented"] = json.loads("".join(parts[i] for i in range(op["total"])))
                parts.clear()
    return got


async def test_fragments_png_cbor_on_the_wire(eng):
    """A raw client subscribes to the echo's answer three times (fragment_size, png, cbor) and
    publishes its request in fragments, out of order; each form comes back as rosbridge sends it.
    A call_service with fragment_size gets its answer in fragments. The metrics count it all."""
    text = "long " * 60
    async with RawRobot(eng.master_url, "rbOwner5") as r:
        await _echo_container(r, "rbC5")
        async with connect(_url(eng, "rbWire", "rbC5")) as ws:
            for sid, extra in (("frag", {"fragment_size": 100}), ("png", {"compression": "png"}),
                               ("cbor", {"compression": "cbor"})):
                await ws.send(json.dumps({"op": "subscribe", "topic": "/stringEchoResp", "type": "std_msgs/String",
                                          "id": sid, **extra}))
            await ws.send(json.dumps({"op": "advertise", "topic": "/stringEchoReq", "type": "std_msgs/String"}))
            request = json.dumps({"op": "publish", "topic": "/stringEchoReq", "msg": {"data": text}})
            pieces = [request[i:i + 90] for i in range(0, len(request), 90)]
            n = iter(range(1_000_000))

            async def publish():
                mid = f"req{next(n)}"
                for i in reversed(range(len(pieces))):
                    await ws.send(json.dumps({"op": "fragment", "id": mid, "data": pieces[i], "num": i,
                                              "total": len(pieces)}))
            got = await _frames_until(ws, {"fragmented", "png", "cbor"}, publish)
            echo = {"op": "publish", "topic": "/stringEchoResp", "msg": {"data": text}}
            assert got == {"fragmented": echo, "png": echo, "cbor": echo}
            for sid in ("frag", "png", "cbor"):
                await ws.send(json.dumps({"op": "unsubscribe", "topic": "/stringEchoResp", "id": sid}))
            await ws.send(json.dumps({"op": "call_service", "service": "/rosapi/get_param_names", "id": "long" * 40,
                                      "fragment_size": 64}))
            frag = await _first_fragment_of(ws, "long" * 40)    # echoes still in flight may come first
            assert frag["num"] == 0 and frag["total"] > 1
            metrics = await asyncio.to_thread(_metrics, eng)
        await _session_gone(eng, "rbC5")
    assert metrics["rce_robot_rosbridge_fragments_in_total"] >= len(pieces)
    assert metrics["rce_robot_rosbridge_fragments_out_total"] >= 4
    assert metrics["rce_robot_rosbridge_sessions_accepted_total"] >= 1 and metrics["rce_robot_rosbridge_sessions"] >= 1
    assert metrics["rce_robot_rosbridge_ops_in_total"] >= 6


def _metrics(eng) -> dict[str, float]:
    """The robot task set's Prometheus metrics (name -> value; unlabelled samples)."""
    port = eng.robot_ready[0]["metrics_port"]
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=STEP_WAIT) as resp:
        text = resp.read().decode()
    return {name: float(value) for name, value in
            (line.split() for line in text.splitlines() if line and not line.startswith("#") and "{" not in line)}


async def test_sessions_reported_and_closed_by_the_master():
    """Sans-I/O: a rosbridge session is a robot in the task set's register report, and a robot the
    master does not have closes its websocket (1008, the reason)."""
    ep = object.__new__(RobotEndpoint)             # only the tables _report and _obey read
    ep.namespaces, ep.by_iid = {}, {}
    ep.link_reports = LinkReports(lambda *report: None)
    ep.rosbridge = RosbridgeServer(master=None, by_iid=ep.by_iid)
    session = RosbridgeSession("u", "r", "c", master=None)
    closed: list[tuple[int, str]] = []

    class _Ws:
        async def close(self, code: int, reason: str) -> None:
            closed.append((code, reason))
    session.ws = _Ws()
    ep.rosbridge.sessions[("u", "r")] = session
    assert {"user": "u", "robot": "r", "rosbridge": "c"} in ep._report()["robots"]
    await ep._obey({"close_robots": [{"user": "u", "robot": "r"}]})
    assert len(closed) == 1 and closed[0][0] == 1008 and "the master does not know" in closed[0][1]


async def test_an_endpoint_behind_a_flooding_client_sheds_its_publish_ops(eng):
    """Real overload, as tests/engine/test_dataflow.py's robot: a rosbridge client writes 30,000
    ``publish`` ops as fast as its socket takes them. Once the endpoint has been behind it for
    ``max_lag`` (1 s) it sheds them, counted (``rce_robot_rosbridge_shed_total``), until it has
    caught up: the echoes keep their order and the newest one arrives."""
    n = 30_000
    async with RawRobot(eng.master_url, "rbFloodOwner") as r:
        await _echo_container(r, "rbFloodC")
        async with connect(_url(eng, "rbFlood", "rbFloodC")) as ws:
            await ws.send(json.dumps({"op": "advertise", "topic": "/stringEchoReq", "type": "std_msgs/String"}))
            await ws.send(json.dumps({"op": "subscribe", "topic": "/stringEchoResp", "type": "std_msgs/String",
                                      "queue_length": 0}))
            echoed: list[int] = []
            told: list[dict] = []
            some, newest = asyncio.Event(), asyncio.Event()

            async def read() -> None:
                async for m in ws:
                    op = json.loads(m)
                    if op.get("op") == "status":
                        told.append(op)
                    if op.get("op") == "publish":
                        some.set()
                        if op["msg"]["data"].isdigit():      # not a warm-up's (late) echo
                            echoed.append(int(op["msg"]["data"]))
                            if echoed[-1] == n - 1:
                                newest.set()
            reader = asyncio.create_task(read())
            try:
                deadline = time.monotonic() + GRAPH_WAIT
                while not some.is_set():       # the echo node may subscribe a moment after the bridge is up
                    assert time.monotonic() < deadline, "no echo"
                    await ws.send(json.dumps({"op": "publish", "topic": "/stringEchoReq", "msg": {"data": "warm-up"}}))
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(some.wait(), RETRY_EVERY)
                shed0 = _metrics(eng)["rce_robot_rosbridge_shed_total"]
                echoed.clear()
                frames = [json.dumps({"op": "publish", "topic": "/stringEchoReq", "msg": {"data": str(i)}})
                          for i in range(n)]
                for i in range(0, n, 500):      # 500 ops per write: the client outruns its endpoint
                    while not ws_cork.writable(ws):
                        await ws.drain()
                    ws_cork.write(ws, frames[i:i + 500])
                await asyncio.wait_for(newest.wait(), SESSION_WAIT)
            finally:
                reader.cancel()
    shed = _metrics(eng)["rce_robot_rosbridge_shed_total"] - shed0
    assert echoed == sorted(set(echoed)) and echoed[-1] == n - 1
    assert shed > 0 and len(echoed) + shed <= n
    assert any(t["level"] == "warning" and "shed" in t["msg"] for t in told), told    # the client was told
