"""rce.dataplane: endpoint <-> endpoint links, on in-memory streams (``asyncio.open_connection``
is replaced by a dial into another in-process plane; no sockets)."""
from __future__ import annotations

import asyncio

import pytest
from memlink import pipe

from rce.dataplane import DataPlane
from rce.errors import NotFound, RequestError, Timeout, Unavailable
from rce.framing import MSG

STEP = 5.0   # s, the longest any single wait may take


class MemNet:
    """Dials by address into planes registered here; ``gate`` holds every dial until set."""

    def __init__(self):
        self.planes: dict[str, DataPlane] = {}
        self.gate = asyncio.Event()
        self.gate.set()

    def plane(self, addr: str, **kw) -> DataPlane:
        p = DataPlane(addr, **kw)
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
    assert await a.call("b:2", 20, 10, b"hi", STEP) == b"HI"
    with pytest.raises(RequestError, match="^no such service$"):
        await a.call("b:2", 20, 10, b"missing", STEP)
    with pytest.raises(RequestError, match="^internal error: KeyError: 'bug'$"):
        await a.call("b:2", 20, 10, b"crash", STEP)
    assert len(a.calls) == 0


async def test_call_timeout(net):
    a, b = net.plane("a:1"), net.plane("b:2")
    b.interfaces[20] = Iface(20, {10: "a:1"}, stuck)
    with pytest.raises(Timeout, match="did not answer the service call to interface 20 within 0.05 s"):
        await a.call("b:2", 20, 10, b"x", 0.05)
    await b.close()


async def test_call_to_a_gone_interface(net):
    a, b = net.plane("a:1"), net.plane("b:2")
    b.interfaces[21] = Iface(21, {10: "a:1"})          # knows where the caller lives; 20 is gone
    with pytest.raises(RequestError, match="interface 20 is gone"):
        await a.call("b:2", 20, 10, b"x", STEP)


async def test_a_refused_message_is_counted_and_the_link_lives_on(net):
    a, b = net.plane("a:1"), net.plane("b:2")
    b.interfaces[20] = Iface(20, {}, takes_messages=False)
    ok = b.interfaces[21] = Iface(21, {})
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
    a, b = net.plane("a:1", max_buffer=100), net.plane("b:2")
    dst = b.interfaces[20] = Iface(20, {})
    net.gate.clear()
    assert a.send("b:2", MSG, 20, 10, 0, b"x" * 40)     # 33 header + 40 bytes
    assert not a.send("b:2", MSG, 20, 10, 0, b"y" * 40)  # would pass 100 bytes: dropped
    assert a.dropped == 1
    net.gate.set()
    assert await asyncio.wait_for(dst.inbox.get(), STEP) == b"x" * 40


async def test_close_fails_calls_in_flight(net):
    a, b = net.plane("a:1"), net.plane("b:2")
    b.interfaces[20] = Iface(20, {10: "a:1"}, stuck)
    call = asyncio.ensure_future(a.call("b:2", 20, 10, b"x", STEP))
    while b.responder.in_flight == 0:                   # until b serves it
        await asyncio.sleep(0)
    await a.close()
    with pytest.raises(Unavailable, match="data plane a:1 closed"):
        await call
    await b.close()
    assert b.responder.in_flight == 0
