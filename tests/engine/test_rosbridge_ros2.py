"""The rosbridge v2 endpoint with ROS 2 type names, as roslibpy sends them to rosbridge_suite's ROS 2 server,
against a real engine: topics and services whose container interfaces are ROS 2 classes (CDR inside the
engine; JSON times as ``{sec, nanosec}``), a ROS 2 client on the Test package's ROS 1 echo node (the engine
converts), and ROS 2 actions: roslibpy's ``ActionClient`` sending goals (feedback, result, cancel) to an
action that a raw rosbridge client serves with ``advertise_action``."""
from __future__ import annotations

import asyncio
import hashlib
import json
import queue
import threading
import time
from functools import partial

import pytest
import roslibpy
from websockets.asyncio.client import connect

from wsclient import RawRobot

pytestmark = pytest.mark.asyncio

CONNECT_WAIT = 10.0     # s for roslibpy to connect
STEP_WAIT = 20.0        # s for one step: an answer, an echo, a goal's result
RETRY_EVERY = 0.3       # s between two publishes while a subscription is being wired
SESSION_WAIT = 90.0     # s for a whole roslibpy session
STAMP = {"sec": 1_700_000_000, "nanosec": 123_456_789}


@pytest.fixture(scope="module")
def eng(shared_engine):
    return shared_engine


def _url(eng, robot: str, ctag: str) -> str:
    port = eng.robot_ready[0]["rosbridge_port"]
    pw = hashlib.sha256(b"testUser").hexdigest()
    return f"ws://127.0.0.1:{port}/?userID=testUser&robotID={robot}&password={pw}&container={ctag}"


async def _container(r: RawRobot, ctag: str, echo: bool = False) -> None:
    await r.send("CC", {"containerTag": ctag})
    await r.expect("ST", pred=lambda d: d.get("topic") == "container" and d.get("cTag") == ctag
                   and d.get("status") == "running")
    if echo:
        await r.cn(addNodes=[{"containerTag": ctag, "nodeTag": "echo", "pkg": "Test", "exe": "stringEcho.py"}])


def _until_echo(pub: roslibpy.Topic, msg: dict, received: queue.Queue) -> dict:
    """Publish ``msg`` until the subscription hears something (it may be wired a little after the advertise)."""
    deadline = time.monotonic() + STEP_WAIT
    while time.monotonic() < deadline:
        pub.publish(roslibpy.Message(msg))
        try:
            return received.get(timeout=RETRY_EVERY)
        except queue.Empty:
            continue
    raise TimeoutError(f"nothing came back on {pub.name} within {STEP_WAIT} s")


def _ros2_session(url: str) -> dict:
    """One roslibpy client with ROS 2 names only: a Header topic to itself, a Trigger service it serves and
    calls, the graph as rosapi answers it."""
    ros = roslibpy.Ros(url)
    ros.run(timeout=CONNECT_WAIT)
    try:
        received: queue.Queue = queue.Queue(100)
        roslibpy.Topic(ros, "/r2/header", "std_msgs/msg/Header").subscribe(received.put_nowait)
        header = _until_echo(roslibpy.Topic(ros, "/r2/header", "std_msgs/msg/Header"),
                             {"stamp": STAMP, "frame_id": "base_link"}, received)
        svc = roslibpy.Service(ros, "/r2/trigger", "std_srvs/srv/Trigger")
        svc.advertise(lambda req, resp: resp.update(success=True, message="triggered") or True)
        deadline = time.monotonic() + STEP_WAIT
        while "/r2/trigger" not in ros.get_services():
            assert time.monotonic() < deadline, "the advertised service never reached the graph"
            time.sleep(RETRY_EVERY)
        answer = roslibpy.Service(ros, "/r2/trigger", "std_srvs/srv/Trigger").call(
            roslibpy.ServiceRequest({}), timeout=STEP_WAIT)
        return {"header": header, "answer": dict(answer), "topic_type": ros.get_topic_type("/r2/header"),
                "service_type": ros.get_service_type("/r2/trigger")}
    finally:
        ros.close()


async def test_roslibpy_with_ros2_names(eng):
    async with RawRobot(eng.master_url, "r2Owner") as r:
        await _container(r, "r2C")
        got = await asyncio.wait_for(asyncio.to_thread(_ros2_session, _url(eng, "r2Py", "r2C")), SESSION_WAIT)
    assert got["header"] == {"stamp": STAMP, "frame_id": "base_link"}      # ROS 2 rosbridge's time: {sec, nanosec}
    assert got["answer"] == {"success": True, "message": "triggered"}
    # the container's bus has them as ROS 2 classes (rosapi answers from it)
    assert (got["topic_type"], got["service_type"]) == ("std_msgs/msg/Header", "std_srvs/srv/Trigger")


def _ros2_client_on_ros1_node(url: str, interfaces) -> dict:
    ros = roslibpy.Ros(url)
    ros.run(timeout=CONNECT_WAIT)
    try:
        deadline = time.monotonic() + STEP_WAIT
        while "/stringEchoReq" not in ros.get_topics():
            assert time.monotonic() < deadline, "the echo node never showed its topics"
            time.sleep(RETRY_EVERY)
        received: queue.Queue = queue.Queue(100)
        roslibpy.Topic(ros, "/stringEchoResp", "std_msgs/msg/String").subscribe(received.put_nowait)
        echo = _until_echo(roslibpy.Topic(ros, "/stringEchoReq", "std_msgs/msg/String"), {"data": "hallo"}, received)
        return {"echo": echo, "type": ros.get_topic_type("/stringEchoReq"), "interfaces": interfaces()}
    finally:
        ros.close()


async def test_a_ros2_client_reaches_a_ros1_node(eng):
    """The container's end takes the graph's ROS 1 class; the client's converter is ROS 2: the engine converts."""
    async with RawRobot(eng.master_url, "r2Owner2") as r:
        await _container(r, "r2C2", echo=True)
        mine = partial(_interfaces_of, eng, "r2Py2")
        got = await asyncio.wait_for(asyncio.to_thread(_ros2_client_on_ros1_node, _url(eng, "r2Py2", "r2C2"), mine),
                                     SESSION_WAIT)
        deadline = time.monotonic() + STEP_WAIT
        while left := await asyncio.to_thread(mine):       # the session's interfaces go with it
            assert time.monotonic() < deadline, f"interfaces of a closed session left: {left}"
            await asyncio.sleep(RETRY_EVERY)
    assert (got["echo"], got["type"]) == ({"data": "hallo"}, "std_msgs/String")
    assert got["interfaces"] == {("SubscriberInterface", "std_msgs/String"), ("PublisherInterface", "std_msgs/String"),
                                 ("PublisherConverter", "std_msgs/msg/String"),
                                 ("SubscriberConverter", "std_msgs/msg/String")}


def _interfaces_of(eng, robot: str) -> set[tuple[str, str]]:
    """(type, class) of the interfaces a rosbridge session ``robot`` has, both sides."""
    return {(i["type"], i["class"]) for i in eng.admin("/api/interfaces") if robot in i["tag"]}


async def _serve_fibonacci(url: str, served: dict, stop: asyncio.Event) -> None:
    """A raw rosbridge client serving ``/r2/fib`` (test_msgs/action/Fibonacci): each goal gets one feedback per
    element, then its result, or, once canceled, a CANCELED result."""
    async with connect(url) as ws:
        await ws.send(json.dumps({"op": "advertise_action", "action": "/r2/fib", "type": "test_msgs/action/Fibonacci"}))
        await ws.send(json.dumps({"op": "call_service", "service": "/rosapi/action_servers", "id": "as"}))
        while not stop.is_set():
            try:
                async with asyncio.timeout(RETRY_EVERY):
                    m = json.loads(await ws.recv())
            except TimeoutError:
                continue
            if m["op"] == "service_response" and m.get("id") == "as":
                served["action_servers"] = m["values"]["action_servers"]
                served["ready"].set()
            elif m["op"] == "send_action_goal":
                served.setdefault("goals", []).append(m)
                order = m["args"]["order"]
                if order < 0:              # a goal held open until it is canceled
                    served["held"].set()
                    continue
                seq = [0, 1][:order]
                while len(seq) < order:
                    seq.append(seq[-1] + seq[-2])
                for i in range(1, order + 1):
                    await ws.send(json.dumps({"op": "action_feedback", "id": m["id"], "action": m["action"],
                                              "values": {"sequence": seq[:i]}}))
                await ws.send(json.dumps({"op": "action_result", "id": m["id"], "action": m["action"],
                                          "values": {"sequence": seq}, "status": 4, "result": True}))
            elif m["op"] == "cancel_action_goal":
                served.setdefault("canceled", []).append(m["id"])
                await ws.send(json.dumps({"op": "action_result", "id": m["id"], "action": m["action"],
                                          "values": {"sequence": []}, "status": 5, "result": True}))


def _send_goals(url: str, held: threading.Event) -> dict:
    """roslibpy's ActionClient: one goal to its result with feedback, one canceled once the server holds it."""
    ros = roslibpy.Ros(url)
    ros.run(timeout=CONNECT_WAIT)
    try:
        client = roslibpy.ActionClient(ros, "/r2/fib", "test_msgs/action/Fibonacci")
        results: queue.Queue = queue.Queue(10)
        feedback: list = []
        lock = threading.Lock()

        def on_feedback(f):
            with lock:
                feedback.append(f["sequence"])
        done = client.send_goal(roslibpy.Goal({"order": 5}), results.put_nowait, on_feedback, results.put_nowait)
        client.wait_goal(done, timeout=STEP_WAIT)
        first = results.get(timeout=STEP_WAIT)
        goal = client.send_goal(roslibpy.Goal({"order": -1}), results.put_nowait, None, results.put_nowait)
        assert held.wait(STEP_WAIT), "the held goal never reached the action's server"
        client.cancel_goal(goal)
        client.wait_goal(goal, timeout=STEP_WAIT)
        second = results.get(timeout=STEP_WAIT)
        with lock:
            return {"first": dict(first), "feedback": list(feedback), "second": dict(second)}
    finally:
        ros.close()


async def test_actions_roslibpy_client_and_a_served_action(eng):
    async with RawRobot(eng.master_url, "r2Owner3") as r:
        await _container(r, "r2C3")
        served: dict = {"ready": asyncio.Event(), "held": threading.Event()}
        stop = asyncio.Event()
        server = asyncio.create_task(_serve_fibonacci(_url(eng, "r2Srv", "r2C3"), served, stop))
        try:
            await asyncio.wait_for(served["ready"].wait(), STEP_WAIT)
            client = asyncio.to_thread(_send_goals, _url(eng, "r2Cli", "r2C3"), served["held"])
            got = await asyncio.wait_for(client, SESSION_WAIT)
        finally:
            stop.set()
            await server
    assert served["action_servers"] == ["/r2/fib"]
    assert got["first"]["status"].value == 4 and got["first"]["values"] == {"sequence": [0, 1, 1, 2, 3]}
    assert got["feedback"] == [[0], [0, 1], [0, 1, 1], [0, 1, 1, 2], [0, 1, 1, 2, 3]]
    assert got["second"]["status"].value == 5            # canceled
    assert [g["args"] for g in served["goals"]] == [{"order": 5}, {"order": -1}]
    assert served["canceled"] == [served["goals"][1]["id"]]


async def test_cbor_of_a_ros2_type():
    """Sans-I/O: ``cbor`` types a ROS 2 message's arrays as for ROS 1; ``cbor-raw`` carries its CDR."""
    import cbor2
    from rce.messages import default_registry
    from rce_robot.rosbridge.compression import cbor_publish, cbor_raw_publish
    reg = default_registry()
    typename = reg.msg_type("std_msgs/msg/Float32MultiArray")
    msg = {"layout": {"dim": [], "data_offset": 0}, "data": [1.5, -2.0]}
    got = cbor2.loads(cbor_publish(reg, typename, "/f", msg))
    assert got["msg"]["data"].tag == 85 and got["msg"]["data"].value == b"\x00\x00\xc0?\x00\x00\x00\xc0"
    string = reg.msg_type("std_msgs/msg/String")
    raw = cbor2.loads(cbor_raw_publish(reg, string, "/s", {"data": "hi"}, 3.5))["msg"]
    assert (raw["secs"], raw["nsecs"], raw["bytes"][:4]) == (3, 500_000_000, b"\x00\x01\x00\x00")   # CDR, little endian
    assert reg.deserialize(string, raw["bytes"]).data == "hi"


async def test_bad_action_ops_get_status_and_goals_to_nobody_end(eng):
    async with RawRobot(eng.master_url, "r2Owner4") as r:
        await _container(r, "r2C4")
        async with connect(_url(eng, "r2Raw", "r2C4")) as ws:
            for bad, says in (({"op": "send_action_goal", "action": "/a", "action_type": "std_msgs/msg/String"},
                               "action type 'pkg/action/Type'"),
                              ({"op": "send_action_goal", "action_type": "test_msgs/action/Fibonacci"}, "'action'"),
                              ({"op": "send_action_goal", "action": "/a", "action_type": "test_msgs/action/Fibonacci",
                                "args": [1]}, "args must be an object"),
                              ({"op": "cancel_action_goal", "action": "/a", "id": "g9"}, "no goal 'g9'"),
                              ({"op": "action_result", "action": "/a", "id": "g9", "status": 4}, "not advertised"),
                              ({"op": "unadvertise_action", "action": "/a"}, "not advertised"),
                              ({"op": "advertise_action", "action": "/a", "type": "test_msgs/action/NoSuch"},
                               "test_msgs/action/NoSuch")):
                await ws.send(json.dumps(bad))
                async with asyncio.timeout(STEP_WAIT):
                    while (m := json.loads(await ws.recv()))["op"] != "status":
                        pass
                assert m["level"] == "error" and says in m["msg"], (bad, m)
            await ws.send(json.dumps({"op": "send_action_goal", "id": "lost", "action": "/nobody",
                                      "action_type": "test_msgs/action/Fibonacci", "args": {"order": 3}}))
            async with asyncio.timeout(STEP_WAIT):
                while (m := json.loads(await ws.recv()))["op"] != "action_result":
                    pass
    assert (m["id"], m["action"], m["result"], m["status"]) == ("lost", "/nobody", False, 0)
    assert "/nobody/_action/send_goal" in m["values"], m       # the container waited 10 s for a server
