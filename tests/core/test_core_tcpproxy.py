"""rce.transport.tcpproxy.TcpProxy against real loopback sockets: forwarding both ways, half close, cut
(RST both ways) and refusal, restore, the connection cap, an unreachable target, close."""
from __future__ import annotations

import asyncio
import socket

import pytest

from rce.transport.tcpproxy import TcpProxy

WAIT = 5.0      # s, the longest any step of these tests may take on loopback (a hang fails, not blocks)


class Target:
    """An echo server on 127.0.0.1: echoes every byte, then half closes after the client's EOF.
    ``ended``: per connection, a future with the exception its read ended with (None: EOF)."""

    def __init__(self) -> None:
        self.ended: asyncio.Queue[asyncio.Future] = asyncio.Queue()
        self.server: asyncio.Server | None = None

    async def start(self) -> "Target":
        self.server = await asyncio.start_server(self._echo, "127.0.0.1", 0)
        return self

    @property
    def port(self) -> int:
        return self.server.sockets[0].getsockname()[1]

    async def _echo(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        ended = asyncio.get_running_loop().create_future()
        self.ended.put_nowait(ended)
        try:
            while data := await reader.read(65536):
                writer.write(data)
                await writer.drain()
            writer.write_eof()
            ended.set_result(None)
        except ConnectionError as e:
            ended.set_result(e)
        finally:
            writer.close()

    async def next_end(self):
        return await asyncio.wait_for(await asyncio.wait_for(self.ended.get(), WAIT), WAIT)

    async def close(self) -> None:
        self.server.close()
        await self.server.wait_closed()


@pytest.fixture
async def rig():
    target = await Target().start()
    proxy = await TcpProxy(target.port).start()
    yield target, proxy
    await proxy.close()
    await target.close()


async def dial(proxy: TcpProxy) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    return await asyncio.wait_for(asyncio.open_connection("127.0.0.1", proxy.port), WAIT)


async def roundtrip(r: asyncio.StreamReader, w: asyncio.StreamWriter, data: bytes) -> bytes:
    w.write(data)
    await w.drain()
    return await asyncio.wait_for(r.readexactly(len(data)), WAIT)


async def assert_reset(r: asyncio.StreamReader) -> None:
    with pytest.raises(ConnectionResetError):
        await asyncio.wait_for(r.read(1), WAIT)


async def test_forwards_both_ways_and_passes_a_half_close_on(rig):
    target, proxy = rig
    assert proxy.url == f"ws://127.0.0.1:{proxy.port}/" and proxy.port != target.port
    r, w = await dial(proxy)
    assert await roundtrip(r, w, b"GET /?userID=u HTTP/1.1\r\nHost: x\r\n\r\n") == \
        b"GET /?userID=u HTTP/1.1\r\nHost: x\r\n\r\n"
    assert list(proxy.requests) == [b"GET /?userID=u HTTP/1.1"]
    w.write_eof()                                  # the target sees EOF, answers, half closes in turn
    assert await target.next_end() is None
    assert await asyncio.wait_for(r.read(), WAIT) == b""
    w.close()
    assert proxy.accepted == 1 and proxy.bytes_up == proxy.bytes_down == 36


async def test_a_large_payload_passes_intact_through_a_small_buffer():
    target = await Target().start()
    proxy = await TcpProxy(target.port, buffer_bytes=4096).start()
    try:
        r, w = await dial(proxy)
        payload = bytes(range(256)) * 4096          # 1 MiB
        echo = asyncio.ensure_future(asyncio.wait_for(r.readexactly(len(payload)), WAIT))
        w.write(payload)
        await w.drain()
        assert await echo == payload
        pair = next(iter(proxy._links))
        assert all(p.transport.get_write_buffer_limits()[1] == 4096 for p in pair)   # the bound in force
        w.close()
    finally:
        await proxy.close()
        await target.close()


async def test_cut_resets_both_ends_and_refuses_until_restore(rig):
    target, proxy = rig
    r, w = await dial(proxy)
    assert await roundtrip(r, w, b"x") == b"x"
    proxy.cut()
    assert proxy.refusing and proxy.resets == 1 and proxy.links == 0
    await assert_reset(r)                                        # the client's end: RST
    assert isinstance(await target.next_end(), ConnectionResetError)   # the target's end: RST
    r2, _ = await dial(proxy)                                    # a new connection is reset
    await assert_reset(r2)
    assert proxy.refused == 1 and proxy.accepted == 1
    proxy.restore()
    assert not proxy.refusing and proxy.restored_at > 0
    r3, w3 = await dial(proxy)
    assert await roundtrip(r3, w3, b"back") == b"back"
    assert proxy.accepted == 2
    w3.close()


async def test_cut_for_a_time_refuses_until_the_clock_passes_it():
    now = [100.0]
    target = await Target().start()
    proxy = await TcpProxy(target.port, clock=lambda: now[0]).start()
    try:
        proxy.cut(refuse_s=2.0)
        assert proxy.refusing
        r, _ = await dial(proxy)
        await assert_reset(r)
        now[0] = 102.0                                           # the 2 s are over, no restore()
        assert not proxy.refusing
        r2, w2 = await dial(proxy)
        assert await roundtrip(r2, w2, b"y") == b"y"
        assert proxy.refused == 1 and proxy.accepted == 1
        w2.close()
    finally:
        await proxy.close()
        await target.close()


async def test_connections_over_the_cap_are_reset_and_counted():
    target = await Target().start()
    proxy = await TcpProxy(target.port, max_connections=1).start()
    try:
        r, w = await dial(proxy)
        assert await roundtrip(r, w, b"1") == b"1"
        r2, _ = await dial(proxy)
        await assert_reset(r2)
        assert proxy.over_limit == 1 and proxy.links == 1
        assert await roundtrip(r, w, b"still") == b"still"       # the first link is untouched
        proxy.cut()
        proxy.restore()
        r3, w3 = await dial(proxy)                               # the cut freed the slot
        assert await roundtrip(r3, w3, b"3") == b"3"
        assert proxy.stats() == {"accepted": 2, "reset": 1, "refused": 0, "over_limit": 1, "unreachable": 0,
                                 "bytes_up": 7, "bytes_down": 7}
        w3.close()
    finally:
        await proxy.close()
        await target.close()


async def test_an_unreachable_target_resets_the_client():
    with socket.socket() as s:                  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proxy = await TcpProxy(port).start()
    try:
        r, _ = await dial(proxy)
        await assert_reset(r)
        assert proxy.unreachable == 1 and proxy.accepted == 0
    finally:
        await proxy.close()


async def test_close_resets_links_and_stops_listening(rig):
    target, proxy = rig
    r, w = await dial(proxy)
    assert await roundtrip(r, w, b"z") == b"z"
    port = proxy.port
    await proxy.close()
    await assert_reset(r)
    assert isinstance(await target.next_end(), ConnectionResetError)
    with pytest.raises(ConnectionRefusedError):
        await asyncio.open_connection("127.0.0.1", port)
    await proxy.close()                         # twice is fine


def test_bad_bounds_are_refused():
    with pytest.raises(ValueError, match="max_connections 0"):
        TcpProxy(1, max_connections=0)
