"""rce.node.links: a node's direct link across a claim's start, on in-memory streams. The node is
a real :class:`rce.node.Node` on a real bus server; its direct link's far end is this test, which
writes what a far data plane writes (:mod:`rce.transport.dataplane`, "Direct links")."""
from __future__ import annotations

import asyncio
import struct

import pytest
from memlink import pipe

from rce.contract import node as to_node
from rce.node import links
from rce.transport import framing
from rce.transport.link import FramedLink

STEP = 5.0     # s, the longest any single wait may take
LID, IID, PEER = 1, 30, 10


def string(text: str) -> bytes:
    """A serialized std_msgs/String."""
    data = text.encode()
    return struct.pack("<I", len(data)) + data


@pytest.fixture
async def node_with_a_link(bus):
    """(bus, server, node, the node's direct links, the far end's writer, what the callback got)."""
    b, server, new_node = bus
    node = await new_node("listener")
    direct = node._direct = links.DirectLinks(node)
    node._peer.handlers.update(links.DIRECT_OPS.handlers(direct))
    got: asyncio.Queue = asyncio.Queue()
    sub = await node.subscriber("/req", "std_msgs/String", lambda m: got.put_nowait(m.data), queue_size=10)
    (ra, wa), (rb, wb) = pipe()
    direct.links[LID] = FramedLink(ra, wa, name="direct link", on_frame=lambda f: direct._on_frame(LID, f)).start()
    await direct.op_direct_subscribe(to_node.DirectSubscribe(link=LID, iid=IID, peers=[PEER], handles=[sub.handle],
                                                             gen=1, size=1))
    yield b, server, node, direct, wb, got


def far_end(writer, *frames) -> None:
    for f in frames:
        writer.transport.write(framing.encode_control(f) if isinstance(f, dict)
                               else framing.encode_data(framing.MSG, IID, PEER, 0, string(f)))


async def taken(got: asyncio.Queue, n: int) -> list[str]:
    return [await asyncio.wait_for(got.get(), STEP) for _ in range(n)]


async def held_route(node, direct, version: int, n: int):
    """A publisher of /resp routed on a second direct link (its far end's reader returned), to
    interface 40 from 20, its route held (``hold``), and ``n`` messages ``r0``... published."""
    (ra, wa), (rb, wb) = pipe()
    direct.links[2] = FramedLink(ra, wa, name="direct link 2", on_frame=lambda f: None).start()
    pub = await node.publisher("/resp", "std_msgs/String")
    await direct.op_direct_publish(to_node.DirectPublish(handle=pub.handle, version=version, targets=[(2, 40, 20)],
                                                         local=False, hold=True))
    for i in range(n):
        assert pub.publish_nowait({"data": f"r{i}"})
    return pub, rb


async def frames_on(reader: asyncio.StreamReader, decoder, n: int) -> list:
    """The next ``n`` frames (at least) on ``reader``."""
    frames: list = []
    while len(frames) < n:
        frames += decoder.feed(await asyncio.wait_for(reader.read(4096), STEP))
    return frames


async def test_direct_messages_behind_a_switch_marker_wait_for_the_bus_path(node_with_a_link):
    """The far end switches while two messages are still on their way by the environment: the
    direct ones wait until the environment's notification comes behind them on the bus."""
    b, server, node, direct, far, got = node_with_a_link
    far_end(far, {"switch": IID, "id": 77}, "direct-2", "direct-3")
    topic = b.topics["/req"]
    for _ in range(100):                                   # the far end's frames are in
        if direct.counts.get(IID, [0])[0] or direct._holds and direct._holds[(LID, IID)].queue:
            break
        await asyncio.sleep(0)
    assert got.empty() and len(direct._holds[(LID, IID)].queue) == 2, "held"
    b.publish(topic, string("bus-0"))
    b.publish(topic, string("bus-1"))
    (session,) = server.sessions
    session.peer.notify("direct_switch", iid=IID, id=77)
    assert await taken(got, 4) == ["bus-0", "bus-1", "direct-2", "direct-3"]
    far_end(far, "direct-4")                               # the hold is over: at once
    assert await taken(got, 1) == ["direct-4"]
    assert direct.switch_timeouts == 0 and direct.counts[IID][:2] == [3, 3 * len(string("direct-2"))]


async def test_a_bus_marker_that_came_first_holds_nothing(node_with_a_link):
    b, server, node, direct, far, got = node_with_a_link
    (session,) = server.sessions
    b.publish(b.topics["/req"], string("bus-0"))
    session.peer.notify("direct_switch", iid=IID, id=5)
    assert await taken(got, 1) == ["bus-0"]
    for _ in range(100):
        if direct._passed:
            break
        await asyncio.sleep(0)
    far_end(far, {"switch": IID, "id": 5}, "direct-1")
    assert await taken(got, 1) == ["direct-1"]
    assert not direct._holds and not direct._passed


async def test_a_marker_that_never_comes_by_the_bus_holds_for_switch_hold_at_most(node_with_a_link, monkeypatch):
    """The environment's notification is lost (its node session went): the held messages go on
    after SWITCH_HOLD, counted, in order; a full hold drops its oldest, counted."""
    monkeypatch.setattr(links, "SWITCH_HOLD", 0.2)
    b, server, node, direct, far, got = node_with_a_link
    far_end(far, {"switch": IID, "id": 9}, *[f"d{i}" for i in range(12)])     # the subscriber's queue_size is 10
    assert await taken(got, 10) == [f"d{i}" for i in range(2, 12)]
    assert direct.switch_timeouts == 1 and direct.counts[IID][2] == 2


async def test_a_held_route_sends_once_the_environment_says_go(node_with_a_link):
    """A route given while the publisher's earlier messages may still be on their way by the
    environment (``hold``): its messages wait, in order, until ``direct_go``, then go."""
    b, server, node, direct, far, got = node_with_a_link
    pub, rb = await held_route(node, direct, 4, 3)
    decoder = framing.FrameDecoder()
    await asyncio.sleep(0)
    assert not rb._buffer, "nothing before go"
    (session,) = server.sessions
    session.peer.notify("direct_go", handle=pub.handle, version=4)
    frames = await frames_on(rb, decoder, 3)
    assert [(f.dst, f.src, bytes(f.payload)) for f in frames] == [(40, 20, string(f"r{i}")) for i in range(3)]
    assert pub.publish_nowait({"data": "r3"})          # released: at once
    f = decoder.feed(await asyncio.wait_for(rb.read(4096), STEP))
    assert [bytes(x.payload) for x in f] == [string("r3")]


async def test_a_publisher_that_sent_by_the_bus_holds_its_first_route_without_being_told(node_with_a_link):
    """The environment reads a node's bus messages only behind the node's answer to
    ``direct_publish``, so it cannot know that some are still on their way: a publisher that has
    sent by the bus holds its new route even without ``hold``, answers ``{held: true}``, and sends
    once ``direct_go`` comes. A publisher that never sent by the bus starts at once."""
    b, server, node, direct, far, got = node_with_a_link
    (ra, wa), (rb, wb) = pipe()
    direct.links[2] = FramedLink(ra, wa, name="direct link 2", on_frame=lambda f: None).start()
    fresh = await node.publisher("/fresh", "std_msgs/String")
    answer = await direct.op_direct_publish(to_node.DirectPublish(handle=fresh.handle, version=6,
                                                                  targets=[(2, 41, 21)]))
    assert answer == {"held": False}
    pub = await node.publisher("/resp", "std_msgs/String")
    assert pub.publish_nowait({"data": "by the bus"})
    answer = await direct.op_direct_publish(to_node.DirectPublish(handle=pub.handle, version=7,
                                                                  targets=[(2, 40, 20)]))
    assert answer == {"held": True}
    assert pub.publish_nowait({"data": "r0"}) and fresh.publish_nowait({"data": "f0"})
    decoder = framing.FrameDecoder()
    (f,) = await frames_on(rb, decoder, 1)
    assert (f.dst, bytes(f.payload)) == (41, string("f0")), "the fresh route sends at once, the other holds"
    (session,) = server.sessions
    session.peer.notify("direct_go", handle=pub.handle, version=7)
    (f,) = await frames_on(rb, decoder, 1)
    assert (f.dst, bytes(f.payload)) == (40, string("r0"))


async def test_a_held_route_without_go_sends_after_route_hold(node_with_a_link, monkeypatch):
    """The environment's ``direct_go`` never comes (its call timed out, it went): the route's held
    messages go after ROUTE_HOLD, in order, and the node counts it."""
    monkeypatch.setattr(links, "ROUTE_HOLD", 0.2)
    b, server, node, direct, far, got = node_with_a_link
    pub, rb = await held_route(node, direct, 5, 2)
    frames = await frames_on(rb, framing.FrameDecoder(), 2)
    assert [bytes(f.payload) for f in frames] == [string("r0"), string("r1")]
    assert direct.route_timeouts == 1


async def test_messages_held_when_the_claim_ends_still_reach_the_subscriber(node_with_a_link):
    """The claim ends (released) while direct messages wait behind a switch marker: they were the
    node's, and its subscriber gets them when the bus path's marker comes."""
    b, server, node, direct, far, got = node_with_a_link
    far_end(far, {"switch": IID, "id": 3}, "direct-0")
    for _ in range(100):
        if direct._holds and direct._holds[(LID, IID)].queue:
            break
        await asyncio.sleep(0)
    direct._control(LID, {"released": IID})
    (session,) = server.sessions
    session.peer.notify("direct_switch", iid=IID, id=3)
    assert await taken(got, 1) == ["direct-0"]
