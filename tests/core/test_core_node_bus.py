"""rce.node <-> rce.bus.server: nodes on a bus over in-memory streams (the Unix socket a node
dials is replaced by a pair of in-memory streams into the server; no sockets)."""
from __future__ import annotations

import asyncio

import pytest

from rce.plumbing.errors import MessageError, NotFound, RequestError, Timeout

STEP = 5.0   # s, the longest any single wait may take
ECHO = "Test/StringEcho"


async def test_topic_between_two_nodes(bus):
    b, server, node = bus
    talker, listener = await node("talker"), await node("listener")
    got = asyncio.Queue()
    await listener.subscriber("chatter", "std_msgs/String", lambda m: got.put_nowait(m.data))
    pub = await talker.publisher("chatter", "std_msgs/String")
    await pub.publish({"data": "one"})
    assert pub.publish_nowait({"data": "two"})
    assert [await asyncio.wait_for(got.get(), STEP) for _ in range(2)] == ["one", "two"]
    assert sorted(s.node for s in server.sessions) == ["/listener", "/talker"]


async def test_publish_nowait_drops_and_counts_when_the_bus_does_not_read(bus):
    _, _, node = bus
    talker = await node("talker")
    pub = await talker.publisher("chatter", "std_msgs/String")
    talker._peer.link.writer.transport.waiting = talker._peer.link.max_buffer
    assert not pub.publish_nowait({"data": "lost"})
    assert (pub.published, pub.dropped) == (0, 1)


async def test_service_answers_and_refusals(bus):
    _, _, node = bus
    provider, caller = await node("provider"), await node("caller")

    def handler(req):
        if req.data == "missing":
            raise NotFound("nothing called missing")
        if req.data == "crash":
            raise ValueError("handler bug")
        return {"data": req.data.upper()}
    await provider.service("echo", ECHO, handler)
    echo = await caller.service_proxy("/echo", ECHO)
    assert (await echo({"data": "hi"})).data == "HI"
    with pytest.raises(RequestError, match="^nothing called missing$"):
        await echo({"data": "missing"})
    with pytest.raises(RequestError, match="^internal error: ValueError: handler bug$"):
        await echo({"data": "crash"})
    with pytest.raises(NotFound):
        await (await caller.service_proxy("/absent", ECHO))()


async def test_call_timeout_and_a_provider_leaving_mid_call(bus):
    _, _, node = bus
    provider, caller = await node("provider"), await node("caller")
    entered = asyncio.Queue()

    async def stuck(req):
        entered.put_nowait(req.data)
        await asyncio.Event().wait()
    await provider.service("stuck", ECHO, stuck)
    proxy = await caller.service_proxy("/stuck", ECHO)
    with pytest.raises(Timeout, match="within 0.05 s"):
        await proxy({"data": "x"}, timeout=0.05)
    call = asyncio.ensure_future(proxy({"data": "y"}, timeout=STEP))
    while await asyncio.wait_for(entered.get(), STEP) != "y":     # until the provider serves the second call
        pass
    await provider.close()
    with pytest.raises(RequestError, match="node '/provider' left while serving a call"):
        await asyncio.wait_for(call, STEP)


async def test_a_string_that_is_not_utf8_reaches_a_node_and_goes_back_unchanged(bus):
    """ROS strings are bytes (rce.messages.ros_strings): the node gets them as surrogate escapes and its
    publish serializes them back to the very same bytes, as a rospy node passes them through."""
    b, server, node = bus
    talker, echo, listener = await node("talker"), await node("echo"), await node("listener")
    raw = b"not utf-8: \x00\xff\xfe"
    got = asyncio.Queue()
    back = await echo.publisher("resp", "std_msgs/String")
    await echo.subscriber("req", "std_msgs/String", back.publish_nowait)
    await listener.subscriber("resp", "std_msgs/String", lambda m: got.put_nowait(m))
    pub = await talker.publisher("req", "std_msgs/String")
    await pub.publish({"data": raw.decode("utf-8", "surrogateescape")})
    msg = await asyncio.wait_for(got.get(), STEP)
    assert listener.registry.serialize("std_msgs/msg/String", msg) == len(raw).to_bytes(4, "little") + raw


async def test_a_message_a_node_cannot_deserialize_is_counted_and_the_next_one_arrives(bus):
    b, server, node = bus
    talker, listener = await node("talker"), await node("listener")
    got = asyncio.Queue()
    sub = await listener.subscriber("chatter", "std_msgs/Int32", lambda m: got.put_nowait(m.data))
    pub = await talker.publisher("chatter", "std_msgs/Int32")
    good = talker._encode
    talker._encode = lambda typename, msg: b"\x07"          # 1 byte: an int32 needs 4
    await pub.publish({"data": 0})
    talker._encode = good
    await pub.publish({"data": 42})
    assert await asyncio.wait_for(got.get(), STEP) == 42
    assert sub.undecodable == 1 and sub.received == 2
    session = next(s for s in server.sessions if s.node == "/listener")
    async with asyncio.timeout(STEP):           # the node's report travels on its link after the message
        while session.stats()["undecodable"] != 1:
            await asyncio.sleep(0.01)


async def test_a_subscriber_decode_gives_the_callback_what_it_reads_and_its_refusals_count_as_undecodable(bus):
    b, server, node = bus
    talker, listener = await node("talker"), await node("listener")
    got = asyncio.Queue()

    def decode(payload: bytes) -> int:
        if len(payload) != 4:
            raise MessageError(f"{len(payload)} bytes are no int32")
        return int.from_bytes(payload, "little", signed=True) * 10

    sub = await listener.subscriber("chatter", "std_msgs/Int32", got.put_nowait, decode=decode)
    pub = await talker.publisher("chatter", "std_msgs/Int32")
    good = talker._encode
    talker._encode = lambda typename, msg: b"\x07"
    await pub.publish({"data": 0})
    talker._encode = good
    await pub.publish({"data": -4})
    assert await asyncio.wait_for(got.get(), STEP) == -40
    assert sub.undecodable == 1 and sub.received == 2
    session = next(s for s in server.sessions if s.node == "/listener")
    async with asyncio.timeout(STEP):
        while session.stats()["undecodable"] != 1:
            await asyncio.sleep(0.01)


async def test_an_async_callback_takes_messages_one_at_a_time_in_order_and_a_full_queue_drops_its_oldest(bus):
    _, _, node = bus
    talker, listener = await node("talker"), await node("listener")
    release, handled, running = asyncio.Event(), [], []

    async def callback(m):
        running.append(m.data)
        assert len(running) == 1, running            # never two at once
        if m.data == 0:
            await release.wait()
        handled.append(m.data)
        running.pop()

    def fails(m):
        raise ValueError(f"bad {m.data}")

    sub = await listener.subscriber("chatter", "std_msgs/Int32", callback, queue_size=2)
    bad = await listener.subscriber("chatter", "std_msgs/Int32", fails)
    pub = await talker.publisher("chatter", "std_msgs/Int32")
    await pub.publish({"data": 0})
    async with asyncio.timeout(STEP):
        while not running:
            await asyncio.sleep(0.01)
    for i in range(1, 6):
        await pub.publish({"data": i})
    async with asyncio.timeout(STEP):        # 0 is in the callback; 1..5 came while it waited: 2 stay
        while sub.received + len(sub.queue) + sub.dropped < 6:
            await asyncio.sleep(0.01)
    assert (handled, sub.received, len(sub.queue), sub.dropped) == ([], 1, 2, 3)
    release.set()
    async with asyncio.timeout(STEP):
        while len(handled) < 3:
            await asyncio.sleep(0.01)
    assert handled == [0, 4, 5] and not sub.queue
    await pub.publish({"data": 6})                     # the subscriber is idle again: the next one comes
    async with asyncio.timeout(STEP):
        while len(handled) < 4:
            await asyncio.sleep(0.01)
    assert handled == [0, 4, 5, 6]
    assert bad.received == 7 and bad.dropped == 0      # a sync callback that raises takes every message
