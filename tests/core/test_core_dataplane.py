"""rce.transport.dataplane: endpoint <-> endpoint links, on in-memory streams (``asyncio.open_connection``
is replaced by a dial into another in-process plane; no sockets). Each plane has its data key, and
a sender the credential the master would hand it (:mod:`rce.transport.cluster_auth`)."""
from __future__ import annotations

import asyncio

import pytest
from memlink import pipe

from rce.transport import cluster_auth

from rce.transport import dataplane

from rce.transport import framing
from rce.transport.cluster_auth import ClusterKey
from rce.transport.dataplane import DataPlane
from rce.plumbing.errors import NotFound, RequestError, Timeout, Unavailable
from rce.transport.framing import MSG

STEP = 5.0   # s, the longest any single wait may take
KEY = ClusterKey.generate()


def allow(sender: DataPlane, src: int, dst: int, dst_addr: str) -> None:
    """What the master's ``connect`` gives the sender: the credential of ``src -> dst``."""
    sender.allow(src, dst, bytes.fromhex(KEY.connection_token(src, dst, dst_addr)))


class MemNet:
    """Dials by address into planes registered here; ``gate`` holds every dial until set."""

    def __init__(self):
        self.planes: dict[str, DataPlane] = {}
        self.gate = asyncio.Event()
        self.gate.set()

    def plane(self, addr: str, **kw) -> DataPlane:
        p = DataPlane(addr, data_key=KEY.data_key(addr), **kw)
        p.addr = addr
        self.planes[addr] = p
        return p

    async def open_connection(self, host, port, limit=None):
        await self.gate.wait()
        target = self.planes.get(f"{host}:{port}")
        if target is None:
            raise ConnectionRefusedError(f"nothing listens at {host}:{port}")
        (ra, wa), (rb, wb) = pipe()
        await target._accept(rb, wb)          # what the target's listener does with a new connection
        return ra, wa


class Iface:
    """A receiver: records messages, serves calls with ``handler``."""

    def __init__(self, iid: int, peers: dict[int, str], handler=None, takes_messages=True):
        self.iid, self.peers, self.handler, self.takes_messages = iid, peers, handler, takes_messages
        self.inbox: asyncio.Queue = asyncio.Queue()

    def on_message(self, payload: memoryview) -> None:
        if not self.takes_messages:
            raise RequestError(f"interface {self.iid} does not receive messages")
        self.inbox.put_nowait(bytes(payload))

    async def serve(self, payload: bytes) -> bytes:
        return await self.handler(payload)


async def stuck(payload: bytes) -> bytes:
    """A service that never answers."""
    await asyncio.Event().wait()
    return b""


@pytest.fixture
async def net(monkeypatch):
    n = MemNet()
    monkeypatch.setattr(asyncio, "open_connection", n.open_connection)
    yield n
    for p in n.planes.values():
        await p.close()


async def test_message_and_counters(net):
    a, b = net.plane("a:1"), net.plane("b:2")
    dst = b.interfaces[20] = Iface(20, {10: "a:1"})
    allow(a, 10, 20, "b:2")
    assert a.send("b:2", MSG, 20, 10, 0, memoryview(b"hello"))
    assert await asyncio.wait_for(dst.inbox.get(), STEP) == b"hello"
    assert (a.msgs_out, a.bytes_out, b.msgs_in, b.bytes_in) == (1, 5, 1, 5)
    assert a.stats()["links"] == 1


async def test_service_call_result_refusal_and_crash(net):
    a, b = net.plane("a:1"), net.plane("b:2")

    async def echo(p: bytes) -> bytes:
        if p == b"missing":
            raise NotFound("no such service")
        if p == b"crash":
            raise KeyError("bug")
        return p.upper()
    b.interfaces[20] = Iface(20, {10: "a:1"}, echo)
    allow(a, 10, 20, "b:2")
    assert await a.call("b:2", 20, 10, b"hi", STEP) == b"HI"
    with pytest.raises(RequestError, match="^no such service$"):
        await a.call("b:2", 20, 10, b"missing", STEP)
    with pytest.raises(RequestError, match="^internal error: KeyError: 'bug'$"):
        await a.call("b:2", 20, 10, b"crash", STEP)
    assert len(a.calls) == 0


async def test_call_timeout(net):
    a, b = net.plane("a:1"), net.plane("b:2")
    b.interfaces[20] = Iface(20, {10: "a:1"}, stuck)
    allow(a, 10, 20, "b:2")
    with pytest.raises(Timeout, match="did not answer the service call to interface 20 within 0.05 s"):
        await a.call("b:2", 20, 10, b"x", 0.05)
    await b.close()


async def test_call_to_a_gone_interface(net):
    a = net.plane("a:1")
    net.plane("b:2")
    allow(a, 10, 20, "b:2")                             # 20 was connected, and is gone
    with pytest.raises(RequestError, match="interface 20 is gone"):
        await a.call("b:2", 20, 10, b"x", STEP)


async def test_a_refused_message_is_counted_and_the_link_lives_on(net):
    a, b = net.plane("a:1"), net.plane("b:2")
    b.interfaces[20] = Iface(20, {10: "a:1"}, takes_messages=False)
    ok = b.interfaces[21] = Iface(21, {10: "a:1"})
    for dst in (20, 99, 21):
        allow(a, 10, dst, "b:2")
    a.send("b:2", MSG, 20, 10, 0, b"refused")
    a.send("b:2", MSG, 99, 10, 0, b"nobody")
    a.send("b:2", MSG, 21, 10, 0, b"after")
    assert await asyncio.wait_for(ok.inbox.get(), STEP) == b"after"
    assert b.dropped == 2 and b.msgs_in == 3


async def test_unreachable_peer_drops_and_counts(net):
    a = net.plane("a:1")
    assert a.send("nowhere:9", MSG, 1, 2, 0, b"x")     # waits in the backlog while dialling
    while a.stats()["links"]:                           # until the dial has failed
        await asyncio.sleep(0)
    assert a.dropped == 1
    assert a.send("nowhere:9", MSG, 1, 2, 0, b"y")     # the next message dials again


async def test_backlog_while_connecting_is_bounded(net):
    # 200 bytes: the link's first pass holds the grant (about 100 bytes) and the frame in its cork
    a, b = net.plane("a:1", max_buffer=200), net.plane("b:2")
    dst = b.interfaces[20] = Iface(20, {10: "a:1"})
    allow(a, 10, 20, "b:2")
    net.gate.clear()
    assert a.send("b:2", MSG, 20, 10, 0, b"x" * 40)     # 33 header + 40 bytes
    assert not a.send("b:2", MSG, 20, 10, 0, b"y" * 150)  # would pass 200 bytes: dropped
    assert a.dropped == 1
    net.gate.set()
    assert await asyncio.wait_for(dst.inbox.get(), STEP) == b"x" * 40


async def test_close_fails_calls_in_flight(net):
    a, b = net.plane("a:1"), net.plane("b:2")
    b.interfaces[20] = Iface(20, {10: "a:1"}, stuck)
    allow(a, 10, 20, "b:2")
    call = asyncio.ensure_future(a.call("b:2", 20, 10, b"x", STEP))
    while b.responder.in_flight == 0:                   # until b serves it
        await asyncio.sleep(0)
    await a.close()
    with pytest.raises(Unavailable, match="data plane a:1 closed"):
        await call
    await b.close()
    assert b.responder.in_flight == 0


# -- only peers the master introduced send (rce.transport.cluster_auth, "Data-plane credentials") --------------
async def raw_link(net: MemNet, addr: str) -> tuple[asyncio.StreamReader, object, bytes]:
    """An attacker's link to the plane at ``addr``: (reader, writer, the nonce it was sent)."""
    host, port = addr.split(":")
    reader, writer = await net.open_connection(host, int(port))
    first = framing.FrameDecoder().feed(await asyncio.wait_for(reader.read(4096), STEP))
    return reader, writer, bytes.fromhex(first[0]["nonce"])


async def until(cond, what: str) -> None:
    for _ in range(1000):
        if cond():
            return
        await asyncio.sleep(0)
    raise AssertionError(f"never: {what}")


async def test_a_frame_without_a_grant_is_refused_and_counted_and_peers_go_on(net):
    a, b = net.plane("a:1"), net.plane("b:2")
    dst = b.interfaces[20] = Iface(20, {10: "a:1"})
    _, writer, _ = await raw_link(net, "b:2")
    writer.transport.write(framing.encode_data(MSG, 20, 10, 0, b"INJECTED"))   # 10 is connected, not this link
    await until(lambda: b.refused == 1, "the injected frame refused")
    allow(a, 10, 20, "b:2")
    a.send("b:2", MSG, 20, 10, 0, b"real")
    assert await asyncio.wait_for(dst.inbox.get(), STEP) == b"real"
    assert dst.inbox.empty() and b.msgs_in == 1
    assert b.stats()["refused"] == 1


async def test_a_wrong_grant_closes_the_link_and_is_counted(net):
    b = net.plane("b:2")
    b.interfaces[20] = Iface(20, {10: "a:1"})
    for token in (b"\0" * 32, bytes.fromhex(KEY.connection_token(10, 20, "c:3"))):   # guessed; another endpoint's
        reader, writer, nonce = await raw_link(net, "b:2")
        proof = cluster_auth.grant_proof(token, nonce, 10, 20).hex()
        writer.transport.write(framing.encode_control({"grant": [10, 20], "proof": proof}))
        assert await asyncio.wait_for(reader.read(), STEP) == b""            # closed on us
    replayed_nonce = nonce
    reader, writer, nonce = await raw_link(net, "b:2")                        # a proof made for another link's nonce
    good = bytes.fromhex(KEY.connection_token(10, 20, "b:2"))
    assert nonce != replayed_nonce
    proof = cluster_auth.grant_proof(good, replayed_nonce, 10, 20).hex()
    writer.transport.write(framing.encode_control({"grant": [10, 20], "proof": proof}))
    assert await asyncio.wait_for(reader.read(), STEP) == b""
    assert b.stats()["unauthenticated"] == 3 and b.msgs_in == 0


async def test_a_granted_sender_is_held_to_its_connections(net):
    a, b = net.plane("a:1"), net.plane("b:2")
    connected = b.interfaces[20] = Iface(20, {10: "a:1"})
    other = b.interfaces[21] = Iface(21, {11: "a:1"})
    allow(a, 10, 20, "b:2")
    a.send("b:2", MSG, 20, 10, 0, b"one")
    assert await asyncio.wait_for(connected.inbox.get(), STEP) == b"one"
    assert not a.send("b:2", MSG, 21, 10, 0, b"no credential")               # 10 -> 21 was never connected
    assert a.dropped == 1
    connected.peers.clear()                                                    # b's end was told: disconnect
    a.send("b:2", MSG, 20, 10, 0, b"after the disconnect")
    await until(lambda: b.refused == 1, "the frame after the disconnect refused")
    a.forbid(10)                                                               # a's end was told too: it stops
    assert not a.send("b:2", MSG, 20, 10, 0, b"x")
    allow(a, 11, 21, "b:2")
    a.send("b:2", MSG, 21, 11, 0, b"two")                                      # other connections go on
    assert await asyncio.wait_for(other.inbox.get(), STEP) == b"two"
    assert connected.inbox.empty()


async def test_a_link_that_grants_nothing_is_closed_and_links_are_bounded(net, monkeypatch):
    b = net.plane("b:2", grant_timeout=0.05)
    reader, _, _ = await raw_link(net, "b:2")                 # says nothing after the nonce
    assert await asyncio.wait_for(reader.read(), STEP) == b""
    assert b.unauthenticated == 1
    monkeypatch.setattr(dataplane, "MAX_ACCEPTED", 1)
    b.grant_timeout = STEP
    await raw_link(net, "b:2")
    reader, _ = await net.open_connection("b", 2)              # one too many: closed before its nonce
    assert await asyncio.wait_for(reader.read(), STEP) == b""
    assert b.unauthenticated == 2


async def node_link(net: MemNet, addr: str, src: int, dst: int) -> tuple[asyncio.StreamReader, object]:
    """A node's direct link to the plane at ``addr``, granted ``src -> dst`` with the credential
    its environment holds (:mod:`rce_container.direct_routes`)."""
    reader, writer, nonce = await raw_link(net, addr)
    token = bytes.fromhex(KEY.connection_token(src, dst, addr))
    writer.transport.write(framing.encode_control(cluster_auth.grant_frame(token, nonce, src, dst)))
    return reader, writer


_READ: dict[int, list] = {}        # id(decoder) -> frames decoded and not yet taken


async def next_frame(reader: asyncio.StreamReader, decoder: framing.FrameDecoder):
    """The next frame on ``reader`` (frames that came in one read are taken one at a time)."""
    pending = _READ.setdefault(id(decoder), [])
    while not pending:
        pending.extend(decoder.feed(await asyncio.wait_for(reader.read(4096), STEP)))
    return pending.pop(0)


async def test_a_complete_claim_set_gets_each_message_once_and_an_incomplete_one_none(net):
    """Direct links: interface 30 (in an environment at e:2) is claimed by two nodes' links to
    the robot's plane r:1. Until both have claimed, and again once one releases, the messages
    go to e:2; while the set is complete, one copy goes to each member and none to e:2."""
    r, e = net.plane("r:1"), net.plane("e:2")
    env_side = e.interfaces[30] = Iface(30, {10: "r:1"})
    r.interfaces[10] = Iface(10, {30: "e:2"})
    allow(r, 10, 30, "e:2")
    (ra, wa), (rb, wb) = await node_link(net, "r:1", 30, 10), await node_link(net, "r:1", 30, 10)
    da, db = framing.FrameDecoder(), framing.FrameDecoder()
    wa.transport.write(framing.encode_control({"claim": 30, "gen": 1, "size": 2}))
    await until(lambda: 30 in r._claims and len(r._claims[30].links) == 1, "the first claim")
    assert r.send("e:2", MSG, 30, 10, 0, b"one")                     # incomplete: by the environment
    assert await asyncio.wait_for(env_side.inbox.get(), STEP) == b"one"
    switched = []
    e.on_switch.append(lambda iid, sid: switched.append((iid, sid)))
    wb.transport.write(framing.encode_control({"claim": 30, "gen": 1, "size": 2}))
    await until(lambda: r.stats()["claims"] == 1, "the set complete")
    assert r.send("e:2", MSG, 30, 10, 0, b"two")
    await until(lambda: switched, "the switch marker behind 'one' at e:2")
    for reader, dec in ((ra, da), (rb, db)):      # 'one' went by e:2: a marker goes ahead of 'two'
        assert await next_frame(reader, dec) == {"switch": 30, "id": switched[0][1]}
        f = await next_frame(reader, dec)
        assert (f.op, f.dst, f.src, bytes(f.payload)) == (MSG, 30, 10, b"two")
    assert env_side.inbox.empty()
    wa.transport.write(framing.encode_control({"claim": 30, "gen": 0, "size": 1}))     # stale: ignored
    wa.transport.write(framing.encode_control({"release": 30}))
    assert await next_frame(ra, da) == {"released": 30}
    assert r.send("e:2", MSG, 30, 10, 0, b"three")                   # a member left: by the environment
    assert await asyncio.wait_for(env_side.inbox.get(), STEP) == b"three"
    wb.transport.write(framing.encode_control({"claim": 30, "gen": 2, "size": 1}))     # a new generation
    await until(lambda: r._claims[30].gen == 2 and r.stats()["claims"] == 1, "generation 2")
    assert r.send("e:2", MSG, 30, 10, 0, b"four")
    assert (await next_frame(rb, db))["switch"] == 30
    assert bytes((await next_frame(rb, db)).payload) == b"four"
    wb.transport.close()                                              # the node dies: its claims go
    await until(lambda: 30 not in r._claims, "the claim gone with its link")
    assert r.send("e:2", MSG, 30, 10, 0, b"five")
    assert await asyncio.wait_for(env_side.inbox.get(), STEP) == b"five"
    assert env_side.inbox.empty()


async def test_a_claim_without_a_grant_closes_the_link(net):
    r = net.plane("r:1")
    reader, writer = await node_link(net, "r:1", 31, 10)             # granted 31 -> 10, claims 30
    writer.transport.write(framing.encode_control({"claim": 30, "gen": 1, "size": 1}))
    assert await asyncio.wait_for(reader.read(), STEP) == b""
    reader, writer, _ = await raw_link(net, "r:1")                   # no grant at all
    writer.transport.write(framing.encode_control({"claim": 30, "gen": 1, "size": 1}))
    assert await asyncio.wait_for(reader.read(), STEP) == b""
    assert r.stats()["unauthenticated"] == 2 and not r._claims


async def test_messages_still_on_the_way_to_the_environment_come_before_the_direct_ones(net):
    """The robot's plane r:1 sends interface 30's messages to its environment e:2 while the link
    to e:2 still connects (held in its backlog); then a node claims 30 and the next message goes
    directly. The markers: e:2 gets one behind the held messages (and reports it once it has
    handed them on), the node one ahead of the direct message, with the same id, so that the node
    can hold the direct message until the held ones have come through its bus."""
    r, e = net.plane("r:1"), net.plane("e:2")
    env_side = e.interfaces[30] = Iface(30, {10: "r:1"})
    r.interfaces[10] = Iface(10, {30: "e:2"})                        # the robot's interface, connected to 30
    allow(r, 10, 30, "e:2")
    reader, writer = await node_link(net, "r:1", 30, 10)
    dec = framing.FrameDecoder()
    net.gate.clear()                                                 # the dial to e:2 hangs
    assert r.send("e:2", MSG, 30, 10, 0, b"held-0") and r.send("e:2", MSG, 30, 10, 0, b"held-1")
    switched = []

    def on_switch(iid: int, sid: int) -> None:
        switched.append((iid, sid, env_side.inbox.qsize()))
    e.on_switch.append(on_switch)
    writer.transport.write(framing.encode_control({"claim": 30, "gen": 1, "size": 1}))
    await until(lambda: r.stats()["claims"] == 1, "the set complete")
    assert r.send("e:2", MSG, 30, 10, 0, b"direct")
    marker = await next_frame(reader, dec)
    assert marker.keys() == {"switch", "id"} and marker["switch"] == 30
    assert bytes((await next_frame(reader, dec)).payload) == b"direct"
    assert not switched and env_side.inbox.empty()
    net.gate.set()                                                   # the link to e:2 comes up
    assert await asyncio.wait_for(env_side.inbox.get(), STEP) == b"held-0"
    assert await asyncio.wait_for(env_side.inbox.get(), STEP) == b"held-1"
    await until(lambda: switched, "the marker at e:2")
    assert switched == [(30, marker["id"], 2)], "reported after both held messages were handed on"


async def test_no_switch_marker_when_nothing_went_by_the_environment(net):
    r, e = net.plane("r:1"), net.plane("e:2")
    e.interfaces[30] = Iface(30, {10: "r:1"})
    r.interfaces[10] = Iface(10, {30: "e:2"})
    allow(r, 10, 30, "e:2")
    reader, writer = await node_link(net, "r:1", 30, 10)
    writer.transport.write(framing.encode_control({"claim": 30, "gen": 1, "size": 1}))
    await until(lambda: r.stats()["claims"] == 1, "the set complete")
    assert r.send("e:2", MSG, 30, 10, 0, b"first")
    assert bytes((await next_frame(reader, framing.FrameDecoder())).payload) == b"first"
