"""rce-robot's Foxglove endpoint on a container whose topics and services are ROS 2 types: channels advertised as
``cdr`` with ``ros2msg`` schemas (the ROS 2 ``.msg`` texts, as Foxglove's ROS 2 bridge does), their messages CDR
that a raw Foxglove protocol client decodes with a rosbags typestore built from the advertised schema alone, CDR
published by the client (rclpy's bytes) reaching the container, and a service call in CDR. The container's ROS 2
graph is a raw rosbridge client's: it advertises the topic and the service, publishes and answers."""
from __future__ import annotations

import asyncio
import hashlib
import json
import struct

import orjson
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from std_msgs.msg import String
from std_srvs.srv import SetBool
from websockets.asyncio.client import connect

from wsclient import RawRobot

pytestmark = pytest.mark.asyncio

CTAG = "fx2C"
SUB = "foxglove.websocket.v1"
STEP_S = 20.0                # one step: an advertisement, a message through, a call's answer
RETRY_S = 0.3                # between publishes while a subscription is being wired
PASSWORD = hashlib.sha256(b"testUser").hexdigest()
POSE = {"header": {"stamp": {"sec": 1_700_000_000, "nanosec": 5}, "frame_id": "map"},
        "pose": {"position": {"x": 1.5, "y": -2.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}


def _url(eng, port_key: str, robot: str | None = None) -> str:
    port = eng.robot_ready[0][port_key]
    robot_q = f"&robotID={robot}" if robot else ""
    return f"ws://127.0.0.1:{port}/?userID=testUser&password={PASSWORD}&container={CTAG}{robot_q}"


async def _rosbridge_graph(ws, published: asyncio.Queue) -> None:
    """The raw rosbridge client's side: answers /fx2/set calls, queues what arrives on /fx2/cmd."""
    while True:
        m = json.loads(await ws.recv())
        if m["op"] == "call_service" and m["service"] == "/fx2/set":
            await ws.send(json.dumps({"op": "service_response", "service": "/fx2/set", "id": m["id"], "result": True,
                                      "values": {"success": m["args"]["data"], "message": "on"}}))
        elif m["op"] == "publish" and m["topic"] == "/fx2/cmd":
            published.put_nowait(m["msg"])


async def _foxglove_next(fox, pred) -> str | bytes:
    async with asyncio.timeout(STEP_S):
        while True:
            m = await fox.recv()
            if pred(m):
                return m


async def test_ros2_channels_services_and_publishing(shared_engine):
    eng = shared_engine
    async with RawRobot(eng.master_url, "fx2Owner") as owner:
        await owner.send("CC", {"containerTag": CTAG})
        await owner.expect("ST", pred=lambda d: d.get("topic") == "container" and d.get("cTag") == CTAG
                           and d.get("status") == "running")
        async with connect(_url(eng, "rosbridge_port", "fx2Graph")) as rb:
            for op in ({"op": "advertise", "topic": "/fx2/pose", "type": "geometry_msgs/msg/PoseStamped"},
                       {"op": "advertise_service", "service": "/fx2/set", "type": "std_srvs/srv/SetBool"},
                       {"op": "subscribe", "topic": "/fx2/cmd", "type": "std_msgs/msg/String"},
                       {"op": "call_service", "service": "/rosapi/topics", "id": "ready"}):
                await rb.send(json.dumps(op))
            async with asyncio.timeout(STEP_S):       # ops run in order: the graph is set up once this answers
                while json.loads(await rb.recv()).get("id") != "ready":
                    pass
            published: asyncio.Queue = asyncio.Queue(100)
            graph = asyncio.create_task(_rosbridge_graph(rb, published))
            try:
                async with connect(_url(eng, "foxglove_port"), subprotocols=[SUB]) as fox:
                    await _in_foxglove(rb, fox, published)
            finally:
                graph.cancel()
        async with asyncio.timeout(STEP_S):           # both sessions end (their interfaces removed) while all is up
            while [r for r in await asyncio.to_thread(eng.admin, "/api/robots")
                   if r["robot"] == "fx2Graph" or r["robot"].startswith("foxglove")]:
                await asyncio.sleep(RETRY_S)


async def _in_foxglove(rb, fox, published: asyncio.Queue) -> None:
    info = orjson.loads(await _foxglove_next(fox, lambda m: isinstance(m, str) and '"serverInfo"' in m))
    assert "cdr" in info["supportedEncodings"]
    channels, services = {}, {}
    async with asyncio.timeout(STEP_S):
        while "/fx2/pose" not in channels or "/fx2/set" not in services:
            msg = orjson.loads(await _foxglove_next(fox, lambda m: isinstance(m, str)))
            if msg["op"] == "advertise":
                channels.update({c["topic"]: c for c in msg["channels"]})
            elif msg["op"] == "advertiseServices":
                services.update({s["name"]: s for s in msg["services"]})
    pose = channels["/fx2/pose"]
    assert (pose["encoding"], pose["schemaName"], pose["schemaEncoding"]) == \
        ("cdr", "geometry_msgs/msg/PoseStamped", "ros2msg")
    assert "\n" + "=" * 80 + "\nMSG: std_msgs/msg/Header\n" in pose["schema"]
    assert "\nMSG: builtin_interfaces/msg/Time\n" in pose["schema"]
    svc = services["/fx2/set"]
    assert (svc["type"], svc["request"]["encoding"], svc["request"]["schemaName"], svc["request"]["schemaEncoding"]) \
        == ("std_srvs/srv/SetBool", "cdr", "std_srvs/srv/SetBool_Request", "ros2msg")

    # the advertised schema alone decodes what the channel carries
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(pose["schema"], pose["schemaName"]))
    await fox.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": pose["id"]}]}))
    data = None
    async with asyncio.timeout(STEP_S):
        while data is None:
            await rb.send(json.dumps({"op": "publish", "topic": "/fx2/pose", "msg": POSE}))
            try:
                data = await asyncio.wait_for(_foxglove_next(fox, lambda m: isinstance(m, bytes) and m[0] == 1),
                                              RETRY_S)
            except TimeoutError:
                pass
    sub_id, _stamp_ns = struct.unpack_from("<IQ", data, 1)
    got = store.deserialize_cdr(data[13:], "geometry_msgs/msg/PoseStamped")
    assert sub_id == 7 and data[13:15] == b"\x00\x01"          # CDR, little endian
    assert (got.header.stamp.sec, got.header.stamp.nanosec, got.header.frame_id) == (1_700_000_000, 5, "map")
    assert (got.pose.position.x, got.pose.position.y, got.pose.orientation.w) == (1.5, -2.0, 1.0)

    # the client publishes CDR (rclpy's bytes) on a channel of its own
    await fox.send(json.dumps({"op": "advertise", "channels": [
        {"id": 3, "topic": "/fx2/cmd", "encoding": "cdr", "schemaName": "std_msgs/msg/String"}]}))
    cmd = None
    async with asyncio.timeout(STEP_S):
        while cmd is None:
            await fox.send(b"\x01" + struct.pack("<I", 3) + serialize_message(String(data="go ahead")))
            try:
                cmd = await asyncio.wait_for(published.get(), RETRY_S)
            except TimeoutError:
                pass
    assert cmd == {"data": "go ahead"}

    # a service call in CDR, answered in CDR
    enc = b"cdr"
    await fox.send(b"\x02" + struct.pack("<III", svc["id"], 41, len(enc)) + enc
                   + serialize_message(SetBool.Request(data=True)))
    answer = await _foxglove_next(fox, lambda m: isinstance(m, bytes) and m[0] == 3)
    service_id, call_id, n = struct.unpack_from("<III", answer, 1)
    assert (service_id, call_id, answer[13:13 + n]) == (svc["id"], 41, enc)
    response = deserialize_message(answer[13 + n:], SetBool.Response)
    assert (response.success, response.message) == (True, "on")


async def test_client_encodings_are_the_servers_choice():
    """Sans-I/O: ``cdr`` is taken only where the server offers it (rce-robot does; the fleet's server does not)."""
    from rce.foxglove import protocol as fp
    services = {1: fp.FoxgloveService(1, "/s", "std_srvs/srv/SetBool", "bool data\n", "bool success\n")}
    advert = json.dumps({"op": "advertise", "channels": [{"id": 1, "topic": "/t", "encoding": "cdr",
                                                          "schemaName": "std_msgs/msg/String"}]})
    call = b"\x02" + struct.pack("<III", 1, 9, 3) + b"cdr" + b"\x00\x01\x00\x00\x01"
    ros1_only = fp.ClientState({}, services)
    assert "encoding 'cdr' is not one of ros1, json" in ros1_only.receive_text(advert)[0].message
    assert "encoding 'cdr' is not one of ros1, json" in ros1_only.receive_binary(call)[0].message
    both = fp.ClientState({}, services, encodings=fp.ALL_CLIENT_ENCODINGS)
    assert isinstance(both.receive_text(advert)[0], fp.Advertised)
    assert isinstance(both.receive_binary(call)[0], fp.ServiceCalled)
    request = services[1].to_json()["request"]
    assert (request["encoding"], request["schemaEncoding"]) == ("cdr", "ros2msg")
