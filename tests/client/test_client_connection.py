"""rce_client.connection against a tiny in-test robot endpoint (websockets server on port 0):
requests on the wire, DMs with binary parts in both orders, service msgID matching both ways,
ER/ST callbacks, wait_interfaces_up, barriers, handshake refusals, a connection closed by the cloud."""
from __future__ import annotations

import asyncio
import hashlib

import pytest

from rce.plumbing.errors import AuthError, RequestError, Timeout, Unavailable
from rce_client.connection import Connection, hash_password

from .fakecloud import FakeEndpoint

pytestmark = pytest.mark.asyncio


@pytest.fixture
async def cloud():
    ep = await FakeEndpoint().start()
    yield ep
    await ep.stop()


@pytest.fixture
async def conn(cloud):
    c = await Connection.open(cloud.url, "testUser", "testUser", "testRobot", expiry=0.3)
    await asyncio.wait_for(cloud.connected.wait(), 5)
    yield c
    await c.close()


async def test_handshake_query_has_hex_sha256_password(cloud, conn):
    assert cloud.query == {"userID": "testUser", "robotID": "testRobot", "refusal": "http",
                           "password": hashlib.sha256(b"testUser").hexdigest()}
    assert hash_password("testUser") == cloud.query["password"] and len(cloud.query["password"]) == 64


@pytest.mark.parametrize("status", [401, 403])
async def test_handshake_refused_is_auth_error_with_reason(status):
    ep = await FakeEndpoint(refuse=(status, "invalid user ID or password for user 'testUser'")).start()
    try:
        with pytest.raises(AuthError) as ei:
            await Connection.open(ep.url, "testUser", "wrong", "testRobot")
        assert "invalid user ID or password for user 'testUser'" in ei.value.message
        assert ep.url in ei.value.message
    finally:
        await ep.stop()


async def test_handshake_other_refusal_is_unavailable():
    ep = await FakeEndpoint(refuse=(409, "robot 'testRobot' of user 'testUser' is already connected")).start()
    try:
        with pytest.raises(Unavailable, match="already connected") as ei:
            await Connection.open(ep.url, "testUser", "testUser", "testRobot")
        assert "409" in ei.value.message
    finally:
        await ep.stop()


async def test_requests_on_the_wire(cloud, conn):
    await conn.create_container("cTag_01", group="g1", cpu=0.5, memory=None)
    await conn.destroy_container("cTag_01")
    await conn.add_node("cTag_01", "strEcho", "Test", "stringEcho.py", namespace="ns")
    await conn.remove_node("cTag_01", "strEcho")
    await conn.set_param("cTag_01", "int", 99)
    await conn.delete_param("cTag_01", "int")
    await conn.add_interface("testRobot", "req", "SubscriberConverter", "std_msgs/String")
    await conn.add_interface("cTag_01", "req", "PublisherInterface", "std_msgs/String", "/stringEchoReq")
    await conn.remove_interface("testRobot", "req")
    await conn.connect("cTag_01/req", "testRobot/req")
    await conn.disconnect("cTag_01/req", "testRobot/req")
    await conn.configure({"setParam": [{"containerTag": "c", "name": "a", "value": [1, 2]}]})
    got = [await cloud.recv() for _ in range(12)]
    assert got == [
        {"type": "CC", "data": {"containerTag": "cTag_01", "containerData": {"group": "g1", "cpu": 0.5}}},
        {"type": "DC", "data": {"containerTag": "cTag_01"}},
        {"type": "CN", "data": {"addNodes": [{"containerTag": "cTag_01", "nodeTag": "strEcho", "pkg": "Test",
                                              "exe": "stringEcho.py", "namespace": "ns"}]}},
        {"type": "CN", "data": {"removeNodes": [{"containerTag": "cTag_01", "nodeTag": "strEcho"}]}},
        {"type": "CN", "data": {"setParam": [{"containerTag": "cTag_01", "name": "int", "value": 99}]}},
        {"type": "CN", "data": {"deleteParam": [{"containerTag": "cTag_01", "name": "int"}]}},
        {"type": "CN", "data": {"addInterfaces": [{"endpointTag": "testRobot", "interfaceTag": "req",
                                                   "interfaceType": "SubscriberConverter",
                                                   "className": "std_msgs/String"}]}},
        {"type": "CN", "data": {"addInterfaces": [{"endpointTag": "cTag_01", "interfaceTag": "req",
                                                   "interfaceType": "PublisherInterface",
                                                   "className": "std_msgs/String", "addr": "/stringEchoReq"}]}},
        {"type": "CN", "data": {"removeInterfaces": [{"endpointTag": "testRobot", "interfaceTag": "req"}]}},
        {"type": "CX", "data": {"connect": [{"tagA": "cTag_01/req", "tagB": "testRobot/req"}]}},
        {"type": "CX", "data": {"disconnect": [{"tagA": "cTag_01/req", "tagB": "testRobot/req"}]}},
        {"type": "CN", "data": {"setParam": [{"containerTag": "c", "name": "a", "value": [1, 2]}]}},
    ]
    # CC without containerData has no containerData key
    await conn.create_container("plain")
    assert await cloud.recv() == {"type": "CC", "data": {"containerTag": "plain"}}


async def test_publish_json_and_bytes(cloud, conn):
    pub = conn.publisher("req", "std_msgs/String")
    await pub.publish({"data": "hello"})
    assert await cloud.recv() == {"type": "DM", "data": {"iTag": "req", "type": "std_msgs/String",
                                                         "msg": {"data": "hello"}}}
    await pub.publish(b"\x05\x00\x00\x00hello")      # a forwarder: binary part msg*
    m = await cloud.recv()
    assert m["data"]["msg"] == b"\x05\x00\x00\x00hello" and "msg*" not in m["data"]
    assert pub.sent == 2


@pytest.mark.parametrize("binary_first", [False, True])
async def test_subscriber_gets_binary_parts_in_either_order(cloud, conn, binary_first):
    got: asyncio.Queue = asyncio.Queue()
    sub = conn.subscriber("resp", "std_msgs/String", got.put_nowait)
    await cloud.send("DM", {"iTag": "resp", "type": "std_msgs/String", "msgID": "", "msg": b"\x01\x00\x00\x00x"},
                     binary_first=binary_first)
    await cloud.send("DM", {"iTag": "resp", "type": "std_msgs/String", "msgID": "", "msg": {"data": "json"}})
    assert await asyncio.wait_for(got.get(), 5) == b"\x01\x00\x00\x00x"
    assert await asyncio.wait_for(got.get(), 5) == {"data": "json"}
    assert sub.received == 2


async def test_async_subscriber_callback_and_unhandled_itag(cloud, conn):
    got: asyncio.Queue = asyncio.Queue()

    async def cb(msg):
        await got.put(msg)
    conn.subscriber("resp", "std_msgs/String", cb)
    await cloud.send("DM", {"iTag": "nobody", "type": "std_msgs/String", "msg": {"data": "lost"}})
    await cloud.send("DM", {"iTag": "resp", "type": "std_msgs/String", "msg": {"data": "kept"}})
    assert await asyncio.wait_for(got.get(), 5) == {"data": "kept"}
    assert conn.dropped == 1


async def test_service_call_matches_msg_id_out_of_order(cloud, conn):
    svc = conn.service("echo", "Test/StringEcho")
    c1 = asyncio.create_task(svc.call({"data": "one"}, timeout=5))
    c2 = asyncio.create_task(svc.call(b"\x03\x00\x00\x00two", timeout=5))
    r1, r2 = await cloud.recv(), await cloud.recv()
    assert {r1["data"]["msgID"], r2["data"]["msgID"]} and r1["data"]["msgID"] != r2["data"]["msgID"]
    by_msg = {("bytes" if isinstance(r["data"]["msg"], bytes) else "json"): r["data"] for r in (r1, r2)}
    assert by_msg["json"]["type"] == "Test/StringEcho" and by_msg["json"]["iTag"] == "echo"
    # answer the second first; a stray response with an unknown msgID goes nowhere
    await cloud.send("DM", {"iTag": "echo", "type": "Test/StringEcho", "msgID": "f" * 32, "msg": {"data": "?"}})
    await cloud.send("DM", {"iTag": "echo", "type": "Test/StringEcho", "msgID": by_msg["bytes"]["msgID"],
                            "msg": b"\x03\x00\x00\x00TWO"}, binary_first=True)
    await cloud.send("DM", {"iTag": "echo", "type": "Test/StringEcho", "msgID": by_msg["json"]["msgID"],
                            "msg": {"data": "ONE"}})
    assert await c1 == {"data": "ONE"}
    assert await c2 == b"\x03\x00\x00\x00TWO"
    assert len(conn.session.pending) == 0


async def test_service_call_timeout_and_refusal(cloud, conn):
    svc = conn.service("echo", "Test/StringEcho")
    with pytest.raises(Timeout, match=r"service 'echo' \(Test/StringEcho\) did not answer within 0.2 s"):
        await svc.call({"data": "x"}, timeout=0.2)
    await cloud.recv()
    # the cloud refuses the call with an ER naming its msgID: the call fails at once
    call = asyncio.create_task(svc.call({"data": "x"}, timeout=30))
    msg_id = (await cloud.recv())["data"]["msgID"]
    await cloud.send("ER", f"service call {msg_id!r} on 'echo' failed: service interface cTag_01/echo is not connected")
    with pytest.raises(RequestError, match="is not connected"):
        await asyncio.wait_for(call, 5)


async def test_service_provider_answers_with_the_request_msg_id(cloud, conn):
    async def handler(req):
        return {"data": req["data"].upper()}
    prov = conn.service_provider("robotSvc", "Test/StringEcho", handler)
    conn.service_provider("robotBin", "Test/StringEcho", lambda req: req + b"!")
    await cloud.send("DM", {"iTag": "robotSvc", "type": "Test/StringEcho", "msgID": "a" * 32, "msg": {"data": "hi"}})
    assert await cloud.recv() == {"type": "DM", "data": {"iTag": "robotSvc", "type": "Test/StringEcho",
                                                         "msg": {"data": "HI"}, "msgID": "a" * 32}}
    await cloud.send("DM", {"iTag": "robotBin", "type": "Test/StringEcho", "msgID": "b" * 32, "msg": b"raw"},
                     binary_first=True)
    r = await cloud.recv()
    assert r["data"]["msgID"] == "b" * 32 and r["data"]["msg"] == b"raw!"
    assert prov.served == 1


async def test_service_provider_failure_sends_no_reply(cloud, conn):
    def handler(req):
        raise ValueError("robot side broke")
    prov = conn.service_provider("robotSvc", "Test/StringEcho", handler)
    await cloud.send("DM", {"iTag": "robotSvc", "type": "Test/StringEcho", "msgID": "c" * 32, "msg": {"data": "x"}})
    # a barrier-like round trip: the next thing the cloud receives is what we send next, not a reply
    await conn.publisher("p", "std_msgs/String").publish({"data": "after"})
    assert (await cloud.recv())["data"]["iTag"] == "p"
    assert prov.failed == 1


async def test_error_and_status_callbacks(cloud, conn):
    errors: asyncio.Queue = asyncio.Queue()
    statuses: asyncio.Queue = asyncio.Queue()
    conn.on_error(errors.put_nowait)

    async def on_st(st):
        await statuses.put(st)
    conn.on_status(on_st)
    await cloud.send("ER", "CN: container 'nope' does not exist")
    await cloud.send("ST", {"topic": "iu", "iTag": "req", "status": True})
    await cloud.send("ST", {"topic": "node", "cTag": "cTag_01", "nTag": "strEcho", "status": "exited", "code": 1})
    assert await asyncio.wait_for(errors.get(), 5) == "CN: container 'nope' does not exist"
    assert await asyncio.wait_for(statuses.get(), 5) == {"topic": "iu", "iTag": "req", "status": True}
    assert (await asyncio.wait_for(statuses.get(), 5))["nTag"] == "strEcho"
    assert conn.errors == ["CN: container 'nope' does not exist"]
    assert conn.interfaces == {"req": True}


async def test_wait_interfaces_up(cloud, conn):
    waiter = asyncio.create_task(conn.wait_interfaces_up(["a", "b"], timeout=5))
    await cloud.send("ST", {"topic": "iu", "iTag": "a", "status": True})
    await cloud.send("ST", {"topic": "iu", "iTag": "b", "status": False})
    await cloud.send("ST", {"topic": "iu", "iTag": "b", "status": True})
    await asyncio.wait_for(waiter, 5)
    await conn.wait_interfaces_up([], timeout=0)      # nothing to wait for


async def test_wait_interfaces_up_timeout_names_those_down(cloud, conn):
    await cloud.send("ST", {"topic": "iu", "iTag": "up1", "status": True})
    await cloud.send("ER", "CX: interface 'cTag_01/down2' does not exist")
    with pytest.raises(Unavailable) as ei:
        await conn.wait_interfaces_up(["up1", "down1", "down2"], timeout=0.3)
    msg = ei.value.message
    assert "interfaces still down after 0.3 s: down1, down2" in msg
    assert "up1" not in msg.split(";")[0]
    assert "last error from the cloud: CX: interface 'cTag_01/down2' does not exist" in msg


async def test_barrier(cloud, conn):
    errors = []
    conn.on_error(errors.append)
    task = asyncio.create_task(conn.barrier(timeout=5))
    probe = await cloud.recv()
    assert probe["type"] == "CX"
    tag = probe["data"]["connect"][0]["tagA"]
    await cloud.send("ER", f"CX: interface {tag!r} does not exist")
    assert await task is True
    assert errors == [] and conn.errors == []          # the probe's ER is not an error
    # a cloud that never answers: the barrier gives up once, then is skipped
    assert await conn.barrier(timeout=0.2) is False
    await cloud.recv()
    assert await conn.barrier(timeout=5) is False


async def test_expired_binary_part_is_dropped(cloud, conn):
    got = []
    conn.subscriber("resp", "std_msgs/String", got.append)
    await cloud.ws.send('{"type":"DM","data":{"iTag":"resp","type":"std_msgs/String","msg*":"' + "1" * 32 + '"}}')
    await cloud.ws.send("not json")                    # malformed: dropped and counted, connection stays
    deadline = asyncio.get_running_loop().time() + 5
    while conn.dropped < 2 and asyncio.get_running_loop().time() < deadline:
        await asyncio.sleep(0.05)
    assert conn.dropped == 2 and got == [] and not conn.closed


async def test_cloud_closes_connection(cloud, conn):
    svc = conn.service("echo", "Test/StringEcho")
    call = asyncio.create_task(svc.call({"data": "x"}, timeout=30))
    await cloud.recv()
    await cloud.ws.close(1008, "closed by the master")
    assert "closed by the master" in await asyncio.wait_for(conn.wait_closed(), 5)
    with pytest.raises(Unavailable, match="closed"):
        await asyncio.wait_for(call, 5)
    with pytest.raises(Unavailable, match="closed"):
        await conn.create_container("late")
    with pytest.raises(Unavailable, match="closed"):
        await conn.wait_interfaces_up(["x"], timeout=5)


async def test_connection_and_instance_connect_are_distinct():
    assert Connection.connect.__func__ is Connection.login_connect.__func__
    doc = Connection.__dict__["connect"].__doc__
    assert "CX connect" in doc and "Log in at the master" in doc
