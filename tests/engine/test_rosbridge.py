"""Issue 13 part 1: the rosbridge v2 endpoint, driven by unmodified roslibpy (PyPI) against a real
engine: the Test package's stringEcho in a container a robot creates; roslibpy calls the echo
service, subscribes and publishes (the echo comes back), and lists topics and services (rosapi).
A raw websocket client sends malformed ops: each gets a status error and the session goes on.

roslibpy runs twisted's reactor in a thread of its own (started once per process and left
running: it cannot restart); its blocking steps run in a worker thread with a named bound."""
from __future__ import annotations

import asyncio
import hashlib
import json
import queue
import time
from functools import partial
from typing import Any

import pytest
import roslibpy
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from rce.errors import RCEError
from rce_robot.rosbridge_session import Bridge, RosbridgeSession, Subscription
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
        return {"answer": dict(answer), "echo": echo, "topics": ros.get_topics(),
                "type": ros.get_service_type("/stringEchoService")}
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


async def test_malformed_ops_get_status_and_session_goes_on(eng):
    async with RawRobot(eng.master_url, "rbOwner2") as r:
        await _echo_container(r, "rbC2")
        async with connect(_url(eng, "rbRaw", "rbC2")) as ws:
            for bad, says in (("not json", "not JSON"), (json.dumps([1]), "JSON object"),
                              (json.dumps({"op": "fly"}), "unknown op 'fly'"),
                              (json.dumps({"op": "publish", "topic": "/x", "msg": {}, "id": "p1"}), "not advertised"),
                              (json.dumps({"op": "subscribe", "topic": "/nowhere", "id": "s1"}), "'/nowhere'"),
                              (json.dumps({"op": "advertise", "topic": "/x", "type": "No/Such"}), "No/Such")):
                await ws.send(bad)
                status = await _next(ws, "status")
                assert status["level"] == "error" and says in status["msg"], (bad, status)
            for ok in ({"op": "subscribe", "topic": "/stringEchoResp", "type": "std_msgs/String", "id": "s2",
                        "throttle_rate": 100, "queue_length": 2},
                       {"op": "unsubscribe", "topic": "/stringEchoResp", "id": "s2"},
                       {"op": "advertise", "topic": "/stringEchoReq", "type": "std_msgs/String", "id": "a1"},
                       {"op": "unadvertise", "topic": "/stringEchoReq", "id": "a1"}):
                await ws.send(json.dumps(ok))
            await ws.send(json.dumps({"op": "call_service", "service": "/rosapi/topics", "id": "t1"}))
            reply = json.loads(await asyncio.wait_for(ws.recv(), STEP_WAIT))      # no status came before it
            assert reply["op"] == "service_response", reply
            assert reply["id"] == "t1" and reply["result"] is True and "topics" in reply["values"]
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
                                      "values": "refused", "result": False}))
            with pytest.raises(RCEError):
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
    session.subs["/t"] = {"sub": Subscription("sub", 1000, 2)}
    for i in range(5):
        assert session.send_dm("s1", "std_msgs/String", "", {"data": str(i)}, data=True)
    assert session.outbox.get_nowait() == {"op": "publish", "topic": "/t", "msg": {"data": "0"}}
    sub = session.subs["/t"]["sub"]
    assert list(sub.pending) == [{"data": "3"}, {"data": "4"}] and sub.dropped == 2 and session.dropped == 2
    assert session.outbox.empty() and sub.timer is not None
    sub.timer.cancel()
    session._flush("/t", sub)              # the timer's work: the oldest waiting one goes, the next waits
    assert session.outbox.get_nowait()["msg"] == {"data": "3"} and list(sub.pending) == [{"data": "4"}]
    assert sub.timer is not None
    sub.timer.cancel()


async def test_handshake_refusals(eng):
    async with RawRobot(eng.master_url, "rbOwner3") as r:
        await _echo_container(r, "rbC3")
        for url, code in ((_url(eng, "rbBad", "rbC3", password="wrong"), 401),
                          (_url(eng, "rbBad", "noSuchContainer"), 404),
                          (_url(eng, "rbBad", "rbC3").split("&container")[0], 400)):
            with pytest.raises(InvalidStatus) as e:
                async with connect(url):
                    pass
            assert e.value.response.status_code == code
