"""rce-robot's Foxglove WebSocket endpoint (``--foxglove-port``, :mod:`rce_robot.foxglove`) on a real engine, with a
raw client: a container's topics and services advertised with their ROS 1 definitions, a subscription streaming
the container's messages, client publishing into the container and a service call, on the Test package's
stringEcho in a container another robot owns; the login refuses a wrong password and an unknown container."""
from __future__ import annotations

import asyncio
import hashlib
import json
import time

import orjson
import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from wsclient import RawRobot

CTAG = "fgC"
SUB = "foxglove.websocket.v1"
STEP_TIMEOUT_S = 30.0        # one step: the container up, a topic advertised, an echo back
RETRY_S = 0.3                # between publishes while the echo node's subscription starts
PASSWORD = hashlib.sha256(b"testUser").hexdigest()


def ros1_string(text: str) -> bytes:
    raw = text.encode()
    return len(raw).to_bytes(4, "little") + raw


def url(eng, ctag: str = CTAG, password: str = PASSWORD) -> str:
    port = eng.robot_ready[0]["foxglove_port"]
    return f"ws://127.0.0.1:{port}/?userID=testUser&password={password}&container={ctag}"


async def advertised(ws) -> tuple[dict, dict]:
    """Channels and services (by name) of one connection's first advertisements."""
    channels, services = {}, {}
    async with asyncio.timeout(STEP_TIMEOUT_S):
        while "/stringEchoResp" not in channels or "/stringEchoService" not in services:
            m = await ws.recv()
            if isinstance(m, str):
                msg = orjson.loads(m)
                if msg["op"] == "advertise":
                    channels.update({c["topic"]: c for c in msg["channels"]})
                elif msg["op"] == "advertiseServices":
                    services.update({s["name"]: s for s in msg["services"]})
    return channels, services


async def test_a_container_in_foxglove(shared_engine):
    eng = shared_engine
    async with RawRobot(eng.master_url, "fgOwner") as owner:
        await owner.send("CC", {"containerTag": CTAG})
        await owner.expect("ST", pred=lambda d: d.get("topic") == "container" and d.get("cTag") == CTAG
                           and d.get("status") == "running")
        await owner.cn(addNodes=[{"containerTag": CTAG, "nodeTag": "echo", "pkg": "Test", "exe": "stringEcho.py"}])
        deadline = time.monotonic() + STEP_TIMEOUT_S
        while True:                 # the echo node's topics reach the bus a little after it starts
            ws = await connect(url(eng), subprotocols=[SUB])
            try:
                channels, services = await asyncio.wait_for(advertised(ws), 2.0)
                break
            except TimeoutError:
                await ws.close()
                assert time.monotonic() < deadline, "the echo node's topics were never advertised"
        try:
            resp = channels["/stringEchoResp"]
            assert (resp["encoding"], resp["schemaName"], resp["schemaEncoding"], resp["schema"]) == \
                ("ros1", "std_msgs/String", "ros1msg", "string data\n")
            svc = services["/stringEchoService"]
            assert svc["type"] == "Test/StringEcho" and svc["request"]["schema"].strip() == "string data"
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 5, "channelId": resp["id"]}]}))
            await ws.send(json.dumps({"op": "advertise", "channels": [
                {"id": 1, "topic": "/stringEchoReq", "encoding": "ros1", "schemaName": "std_msgs/String"}]}))
            got = None
            async with asyncio.timeout(STEP_TIMEOUT_S):
                while got is None:
                    await ws.send(b"\x01" + (1).to_bytes(4, "little") + ros1_string("hello foxglove"))
                    try:
                        async with asyncio.timeout(RETRY_S):
                            while True:
                                m = await ws.recv()
                                if isinstance(m, bytes) and m[0] == 1:
                                    got = m
                                    break
                    except TimeoutError:
                        pass
            assert int.from_bytes(got[1:5], "little") == 5 and got[13:] == ros1_string("hello foxglove")
            # a service call, ROS 1 in and out
            enc = b"ros1"
            await ws.send(b"\x02" + svc["id"].to_bytes(4, "little") + (77).to_bytes(4, "little")
                          + len(enc).to_bytes(4, "little") + enc + ros1_string("hi"))
            async with asyncio.timeout(STEP_TIMEOUT_S):
                while True:
                    m = await ws.recv()
                    if isinstance(m, bytes) and m[0] == 3:
                        break
            assert int.from_bytes(m[5:9], "little") == 77 and m[13:17] == enc and m[17:] == ros1_string("hi")
            # a channel the container does not have
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 6, "channelId": 123456}]}))
            async with asyncio.timeout(STEP_TIMEOUT_S):
                while True:
                    m = await ws.recv()
                    if isinstance(m, str) and orjson.loads(m)["op"] == "status":
                        break
            assert "unknown channel 123456" in orjson.loads(m)["message"]
        finally:
            await ws.close()


async def test_the_login_refuses(shared_engine):
    with pytest.raises(InvalidStatus) as e:
        await connect(url(shared_engine, password=hashlib.sha256(b"nope").hexdigest()), subprotocols=[SUB])
    assert e.value.response.status_code == 401
    with pytest.raises(InvalidStatus) as e:
        await connect(url(shared_engine, ctag="noSuchContainer"), subprotocols=[SUB])
    assert e.value.response.status_code == 404
