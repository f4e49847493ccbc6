"""The Foxglove WebSocket protocol's server side without sockets (:mod:`rce.foxglove.protocol`): one client's
subscriptions and channels, the events of its messages, the problems its bad input makes (each entry on its own),
and the binary layouts of ``@foxglove/ws-protocol``."""
from __future__ import annotations

import json
import struct

import orjson

from rce.foxglove import protocol as fp
from rce.messages import default_registry

CHANNELS = {1: fp.Channel(1, "/a", "std_msgs/String", "string data"),
            2: fp.Channel(2, "/b", "std_msgs/Bool", "bool data")}
SERVICES = {9: fp.FoxgloveService(9, "/echo", "Test/StringEcho", "string data", "string data")}


def state(**kw) -> fp.ClientState:
    return fp.ClientState(CHANNELS, SERVICES, **kw)


def text(op: str, **fields) -> str:
    return json.dumps({"op": op, **fields})


def test_subscribe_and_unsubscribe_each_entry_on_its_own():
    s = state()
    ev = s.receive_text(text("subscribe", subscriptions=[{"id": 10, "channelId": 1}, {"id": 11, "channelId": 99},
                                                         {"id": 10, "channelId": 2}, {"id": 12, "channelId": 1},
                                                         {"id": "x", "channelId": 2}]))
    assert ev[0] == fp.Subscribed(10, 1)
    assert [e.message for e in ev[1:]] == [
        "subscribe: unknown channel 99", "subscribe: subscription id 10 is in use (channel 1)",
        "subscribe: already subscribed to channel 1 as 10",
        "subscribe: each subscription needs integer 'id' and 'channelId', got {'id': 'x', 'channelId': 2}"]
    assert s.subscription_of(1) == 10 and s.subscription_of(2) is None
    assert s.receive_text(text("unsubscribe", subscriptionIds=[10, 10])) == [
        fp.Unsubscribed(10, 1), fp.Problem("unsubscribe: unknown subscription 10")]
    assert s.subscriptions == {} and s.by_channel == {}


def test_bounds():
    s = state()
    subs = [{"id": i, "channelId": 1 + i % 2} for i in range(fp.MAX_IDS + 1)]
    assert s.receive_text(text("subscribe", subscriptions=subs)) == [
        fp.Problem(f"subscribe: 'subscriptions' has {fp.MAX_IDS + 1} entries, over the {fp.MAX_IDS} limit")]
    assert "over the" in s.receive_text("x" * (fp.MAX_TEXT + 1))[0].message
    s.receive_text(text("advertise", channels=[{"id": 1, "topic": "/g", "encoding": "ros1", "schemaName": "a/B"}]))
    big = bytes([fp.CLIENT_MESSAGE_DATA]) + struct.pack("<I", 1) + bytes(fp.MAX_CLIENT_PAYLOAD + 1)
    assert s.receive_binary(big)[0].message.endswith(f"over the {fp.MAX_CLIENT_PAYLOAD}-byte limit; dropped")


def test_bad_messages_are_problems():
    s = state()
    assert s.receive_text("{nope")[0].message.startswith("not JSON")
    assert s.receive_text("[1]")[0].message == "a message must be a JSON object with a string 'op'"
    assert s.receive_text(text("getParameters"))[0].message.startswith("unsupported op 'getParameters'")
    assert s.receive_text(text("subscribe", subscriptions=5))[0].message == "subscribe: 'subscriptions' must be a list"
    assert s.receive_binary(b"")[0].message == "empty binary message"
    assert s.receive_binary(b"\x07abc")[0].message.startswith("unknown binary opcode 7")
    assert s.receive_binary(b"\x01\x00")[0].message.startswith("client message data of 2 bytes")
    assert s.receive_binary(b"\x01" + struct.pack("<I", 5) + b"x")[0].message == \
        "message data on unknown client channel 5: advertise it first"


def test_client_channels_and_publishing():
    s = state()
    ev = s.receive_text(text("advertise", channels=[
        {"id": 3, "topic": "/goal", "encoding": "ros1", "schemaName": "fleet/RobotGoal"},
        {"id": 4, "topic": "/x", "encoding": "cdr", "schemaName": "a/B"},
        {"id": 3, "topic": "/goal", "encoding": "json", "schemaName": "fleet/RobotGoal"}, {"topic": "/y"}]))
    goal = fp.ClientChannel(3, "/goal", "ros1", "fleet/RobotGoal")
    assert ev[0] == fp.Advertised(goal)
    assert [e.message for e in ev[1:]] == ["advertise: channel 4 (/x): encoding 'cdr' is not one of ros1, json",
                                           "advertise: client channel 3 is already advertised",
                                           "advertise: a channel needs an integer 'id' (u32)"]
    assert s.receive_binary(b"\x01" + struct.pack("<I", 3) + b"payload") == [fp.Published(goal, b"payload")]
    assert s.receive_text(text("unadvertise", channelIds=[3, 3])) == [
        fp.Unadvertised(goal), fp.Problem("unadvertise: unknown client channel 3")]
    assert state(client_publish=False).receive_text(text("advertise", channels=[]))[0].message == \
        "advertise: this server does not take client publishing"


def test_service_calls():
    s = state()
    call = struct.pack("<BIII", fp.SERVICE_CALL_REQUEST, 9, 42, 4) + b"ros1" + b"\x02\x00\x00\x00hi"
    assert s.receive_binary(call) == [fp.ServiceCalled(9, 42, "ros1", b"\x02\x00\x00\x00hi")]
    unknown = s.receive_binary(struct.pack("<BIII", 2, 8, 1, 4) + b"ros1")
    assert unknown[0].message == "service call 1: unknown service 8"
    assert s.receive_binary(struct.pack("<BIII", 2, 9, 1, 50) + b"ros1")[0].message.startswith(
        "service call request 1: encoding of 50 bytes runs past")
    assert "encoding 'cdr'" in s.receive_binary(struct.pack("<BIII", 2, 9, 1, 3) + b"cdr")[0].message


def test_server_messages():
    assert fp.message_data(7, 123, b"xy") == b"\x01" + struct.pack("<IQ", 7, 123) + b"xy"
    assert fp.service_call_response(9, 42, "ros1", b"z") == struct.pack("<BIII", 3, 9, 42, 4) + b"ros1z"
    assert orjson.loads(fp.status(fp.WARNING, "careful", "s1")) == {"op": "status", "level": 1, "message": "careful",
                                                                      "id": "s1"}
    info = orjson.loads(fp.server_info("rce", ["clientPublish"], supported_encodings=["ros1"]))
    assert info == {"op": "serverInfo", "name": "rce", "capabilities": ["clientPublish"],
                    "supportedEncodings": ["ros1"]}
    adv = orjson.loads(fp.advertise([CHANNELS[1]]))
    assert adv == {"op": "advertise", "channels": [{"id": 1, "topic": "/a", "encoding": "ros1",
                                                    "schemaName": "std_msgs/String", "schema": "string data",
                                                    "schemaEncoding": "ros1msg"}]}
    svc = orjson.loads(fp.advertise_services([SERVICES[9]]))["services"][0]
    assert svc["request"]["schemaName"] == "Test/StringEcho_Request" and svc["responseSchema"] == "string data"


def test_ros1_schema_is_the_bag_definition():
    text_ = fp.ros1_schema(default_registry().store, "geometry_msgs/msg/PoseStamped")
    assert text_.startswith("std_msgs/Header header\ngeometry_msgs/Pose pose\n")
    assert "\n" + "=" * 80 + "\nMSG: std_msgs/Header\n" in text_ and "MSG: geometry_msgs/Quaternion" in text_
