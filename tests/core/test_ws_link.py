"""rce_robot.ws_link, the robot endpoint's websocket, on each library (picows, websockets), over real
websockets on loopback: what the session shells use holds the same on both (frames in, corked
writes out, fragments, the upgrade's refusal with a status, close codes, the read-ahead the lag
rule counts, a peer that leaves pings unanswered, TLS, a robot that does not read)."""
from __future__ import annotations

import asyncio
import base64
import json
import os
import time
from http import HTTPStatus

import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from rce.protocol.session import RobotSession, SessionLimits
from rce.transport import tls
from rce.transport.lane_socket import is_mptcp, mptcp_socket
from rce_robot import ws_cork, ws_link
from rce_robot.namespace import RobotNamespace

pytestmark = pytest.mark.asyncio
STEP = 10.0          # s, the longest any single wait may take
IMPLS = pytest.mark.parametrize("impl", ws_link.IMPLS)


async def until(cond, what: str) -> None:
    """Poll ``cond()`` until true, at most STEP s."""
    deadline = asyncio.get_running_loop().time() + STEP
    while not cond():
        if asyncio.get_running_loop().time() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.01)


async def until_ended(srv) -> None:
    while not srv.ended:
        await asyncio.sleep(0.05)


class Server:
    """A ws_link server on loopback: ``handler(link)`` for connections whose path has no ``refuse``
    (those get 429 with Retry-After); ``links`` are the links served, with ``rce_path`` from the upgrade."""

    def __init__(self, impl: str, handler, ssl_context=None, **kw):
        self.impl, self.handler, self.ssl_context = impl, handler, ssl_context
        self.kw = {"max_size": 1 << 20, "ping_interval": 20.0, "ping_timeout": 60.0, "max_queue": 16, **kw}
        self.links: list = []
        self.ended: list = []

    async def _request(self, connection, request):
        await asyncio.sleep(0)               # an async check, as a login's
        if "refuse" in request.path:
            resp = connection.respond(HTTPStatus.TOO_MANY_REQUESTS, "slow down\n")
            resp.headers["Retry-After"] = "7"
            return resp
        connection.rce_path = request.path
        return None

    async def _serve(self, link) -> None:
        self.links.append(link)
        try:
            await self.handler(link)
        finally:
            self.ended.append(link)

    async def __aenter__(self):
        self.server = await ws_link.serve(self.impl, self._serve, "127.0.0.1", 0, process_request=self._request,
                                          ssl_context=self.ssl_context, **self.kw)
        scheme = "wss" if self.ssl_context else "ws"
        self.url = f"{scheme}://127.0.0.1:{self.server.sockets[0].getsockname()[1]}/"
        return self

    async def __aexit__(self, *exc):
        self.server.close()
        await asyncio.wait_for(self.server.wait_closed(), STEP)


async def echo(link) -> None:
    """Each message back as itself and as a binary frame, in one corked write."""
    async for m in link:
        ws_link.write(link, [m, m.encode() if isinstance(m, str) else m])


@IMPLS
async def test_frames_in_and_corked_writes_out(impl):
    async with Server(impl, echo) as srv, connect(srv.url + "?a=1", compression=None) as c:
        await until(lambda: srv.links, "the link")
        assert srv.links[0].rce_path == "/?a=1"          # what the upgrade check set is on the link
        for m in ("hello", "ü" * 300, b"\x00\x01", bytes(70_000)):
            await c.send(m)
            assert await asyncio.wait_for(c.recv(), STEP) == m
            assert await asyncio.wait_for(c.recv(), STEP) == (m.encode() if isinstance(m, str) else m)


@IMPLS
async def test_fragmented_messages_both_ways(impl):
    async def handler(link):
        async for m in link:
            async def parts(m=m):
                for i in range(0, len(m), 3):
                    yield m[i:i + 3]
            await link.send(parts())
    async with Server(impl, handler) as srv, connect(srv.url, compression=None) as c:
        async def fragments(parts):
            for p in parts:
                yield p
        await c.send(fragments(["abc", "défg", "h"]))
        assert await asyncio.wait_for(c.recv(), STEP) == "abcdéfgh"
        await c.send(fragments([b"12", b"345"]))
        assert await asyncio.wait_for(c.recv(), STEP) == b"12345"


@IMPLS
async def test_a_message_sent_as_an_iterable_of_fragments(impl):
    """What the bulk lane sends (``lane_socket.fragments``): a sync iterable of a message's fragments."""
    async def handler(link):
        async for m in link:
            await link.send(m[i:i + 2] for i in range(0, len(m), 2))
    async with Server(impl, handler) as srv, connect(srv.url, compression=None) as c:
        for m in ("abcde", b"\x01\x02\x03"):
            await c.send(m)
            assert await asyncio.wait_for(c.recv(), STEP) == m


@IMPLS
async def test_a_refused_upgrade_gets_its_status_and_headers(impl):
    async with Server(impl, echo) as srv:
        with pytest.raises(InvalidStatus) as ei:
            async with connect(srv.url + "?refuse=1"):
                pass
        assert ei.value.response.status_code == 429 and ei.value.response.headers["Retry-After"] == "7"
        assert b"slow down" in ei.value.response.body and not srv.links


@IMPLS
async def test_close_codes_each_way(impl):
    async def closer(link):
        async for m in link:
            if m == "close":
                await link.close(1008, "policy")
    async with Server(impl, closer) as srv:
        async with connect(srv.url) as c:           # the server closes: the client sees its code and reason
            await c.send("close")
            with pytest.raises(ConnectionClosed):
                await asyncio.wait_for(c.recv(), STEP)
            assert c.close_code == 1008 and c.close_reason == "policy"
        await until(lambda: len(srv.ended) == 1, "the handler to end")
        assert not ws_link.closed_by_peer(srv.ended[0], (1000, 1001))
        async with connect(srv.url) as c:           # the client closes cleanly
            await until(lambda: len(srv.links) == 2, "the second link")
        await until(lambda: len(srv.ended) == 2, "the handler to end")
        assert ws_link.closed_by_peer(srv.ended[1], (1000, 1001)) and srv.ended[1].close_code == 1000
        async with connect(srv.url) as c:           # the client's connection is cut: no close frame
            await until(lambda: len(srv.links) == 3, "the third link")
            c.transport.abort()
        await until(lambda: len(srv.ended) == 3, "the handler to end")
        link = srv.ended[2]
        assert link.close_code == 1006 and not ws_link.closed_by_peer(link, (1000, 1001))
        assert not ws_link.writable(link) and not ws_link.paused(link)
        with pytest.raises(ConnectionClosed):
            await link.send("late")


@IMPLS
async def test_a_peers_close_code_is_answered_and_kept(impl):
    """An application's code (4000) and a close frame without a code (1005 on the link, RFC 6455
    section 7.1.5) both come back to the peer, and neither counts as a clean end."""
    async def handler(link):
        async for _ in link:
            pass
    async with Server(impl, handler) as srv:
        c = await connect(srv.url)
        await c.close(4000, "done")
        assert c.close_code == 4000
        c = await connect(srv.url)
        c.protocol.send_close()                    # no code
        c.transport.writelines(c.protocol.data_to_send())
        await asyncio.wait_for(c.wait_closed(), STEP)
        assert c.close_code == 1005
        await until(lambda: len(srv.ended) == 2, "both handlers to end")
        assert [link.close_code for link in srv.ended] == [4000, 1005]
        assert not any(ws_link.closed_by_peer(link, (1000, 1001)) for link in srv.ended)


@IMPLS
async def test_a_message_over_max_size_closes_1009(impl):
    async with Server(impl, echo, max_size=1000) as srv, connect(srv.url, compression=None) as c:
        await c.send("x" * 1001)
        with pytest.raises(ConnectionClosed):
            await asyncio.wait_for(c.recv(), STEP)
        assert c.close_code == 1009


@IMPLS
async def test_text_that_is_not_utf8_closes_1007(impl):
    async with Server(impl, echo) as srv, connect(srv.url, compression=None) as c:
        c.protocol.send_text(b"\xff\xfe")          # framed by the sans-I/O protocol, which does not check
        c.transport.writelines(c.protocol.data_to_send())
        with pytest.raises(ConnectionClosed):
            await asyncio.wait_for(c.recv(), STEP)
        assert c.close_code == 1007


@IMPLS
async def test_behind_counts_what_waits_until_everything_is_read(impl):
    """A client writes 2000 frames at once. While the server has taken only some, the rest wait read
    ahead (at most ``max_queue`` of them plus one read's worth) or in the kernel; once it has taken the
    last one, nothing is behind."""
    n, firsts, last = 2000, [], []

    async def handler(link):
        it = aiter(link)
        await anext(it)
        await until(lambda: ws_link.behind(link) > 0, "frames waiting")
        firsts.append(ws_link.behind(link))
        for _ in range(n - 1):
            await anext(it)
        last.append(ws_link.behind(link))
    async with Server(impl, handler, max_queue=4) as srv, connect(srv.url, compression=None) as c:
        await c.send("first")
        for i in range(0, n - 1, 100):
            for _ in range(min(100, n - 1 - i)):
                await c.send("x" * 1000)
        await until(lambda: last, "the last frame read")
    assert firsts[0] > 0 and last == [0]


async def test_picows_asks_the_kernel_only_when_the_reader_may_be_behind_it():
    """With nothing read ahead, bytes in the kernel count (``FIONREAD``) when the last message was read
    more than ``UNREAD_FRESH`` ago or was large; a small message taken just after it was read leaves
    nothing behind it that the lag rule counts, and the kernel is not asked."""
    seen: dict = {}
    paused, go, done = asyncio.Event(), asyncio.Event(), asyncio.Event()

    async def handler(link):
        it = aiter(link)
        await anext(it)                                   # "a": nothing read ahead now
        link.transport.pause_reading()                    # what comes next stays in the kernel
        paused.set()
        sock = link.transport.get_extra_info("socket")
        await until(lambda: ws_cork.fionread(sock) > 0, "bytes in the kernel")
        link._pushed_at = time.monotonic()                # "a" read just now, small: not asked
        seen["fresh"] = link.behind()
        link._pushed_at -= 2 * ws_link.UNREAD_FRESH       # read longer ago: the kernel's bytes count
        seen["stale"] = link.behind()
        link._pushed_at, link._pushed_size = time.monotonic(), ws_link.UNREAD_SMALL   # large: asked
        seen["large"] = link.behind()
        link.transport.resume_reading()
        assert await anext(it) == "b"
        await until(lambda: ws_cork.fionread(sock) == 0, "the kernel read out")
        link._pushed_at -= 2 * ws_link.UNREAD_FRESH
        seen["caught_up"] = link.behind()
        done.set()
        await go.wait()
    async with Server("picows", handler) as srv, connect(srv.url, compression=None) as c:
        await c.send("a")
        await asyncio.wait_for(paused.wait(), STEP)
        await c.send("b")
        await asyncio.wait_for(done.wait(), STEP)
        go.set()
    assert seen["fresh"] == 0 and seen["stale"] > 0 and seen["large"] == seen["stale"] and seen["caught_up"] == 0


@IMPLS
async def test_a_peer_that_does_not_answer_pings_is_dropped(impl):
    """A client that opens the websocket by hand and then never reads (so never answers a ping) loses
    its link once the ping has waited ``ping_timeout``."""
    async def handler(link):
        async for _ in link:
            pass
    async with Server(impl, handler, ping_interval=0.2, ping_timeout=0.4) as srv:
        port = srv.server.sockets[0].getsockname()[1]
        key = base64.b64encode(os.urandom(16)).decode()
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        try:
            writer.write(f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                         f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode())
            assert (await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), STEP)).startswith(b"HTTP/1.1 101")
            await until(lambda: srv.links and not ws_link.writable(srv.links[0]), "the silent peer's link to close")
            # websockets waits for the peer's close frame (its close_timeout, 10 s) before it lets go
            await asyncio.wait_for(until_ended(srv), 3 * STEP)
        finally:
            writer.close()
        assert srv.ended[0].close_code == 1006


@IMPLS
async def test_tls(impl, tmp_path):
    certs = tls.make_dev_certificates(tmp_path)
    async with Server(impl, echo, ssl_context=tls.server_context(certs.cert, certs.key)) as srv:
        assert srv.url.startswith("wss://")
        async with connect(srv.url, ssl=tls.client_context(certs.ca), compression=None) as c:
            await c.send("over tls")
            assert await asyncio.wait_for(c.recv(), STEP) == "over tls"
            assert await asyncio.wait_for(c.recv(), STEP) == b"over tls"


@IMPLS
async def test_an_mptcp_listening_socket(impl):
    """``rce-robot --mptcp``: the server listens on an MPTCP socket (which refuses some TCP options, e.g.
    ``TCP_QUICKACK``) and an MPTCP client talks to it."""
    sock, mptcp = mptcp_socket()
    assert mptcp, "the kernel offers no MPTCP"
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    server = await ws_link.serve(impl, echo, None, None, sock=sock, process_request=None, max_size=1000,
                                 ping_interval=20.0, ping_timeout=60.0, max_queue=16)
    try:
        url = f"ws://127.0.0.1:{server.sockets[0].getsockname()[1]}/"
        client_sock, _ = mptcp_socket()
        client_sock.settimeout(STEP)      # (asyncio's sock_connect cannot resolve with MPTCP as the protocol)
        await asyncio.to_thread(client_sock.connect, server.sockets[0].getsockname())
        client_sock.setblocking(False)
        assert is_mptcp(client_sock)
        async with connect(url, sock=client_sock, compression=None) as c:
            await c.send("over mptcp")
            assert await asyncio.wait_for(c.recv(), STEP) == "over mptcp"
    finally:
        server.close()
        await asyncio.wait_for(server.wait_closed(), STEP)


@IMPLS
async def test_the_server_closing_closes_its_links_going_away(impl):
    async with Server(impl, echo) as srv:
        c = await connect(srv.url)
        await until(lambda: srv.links, "the link")
    await asyncio.wait_for(c.wait_closed(), STEP)
    assert c.close_code == 1001 and srv.ended


@IMPLS
async def test_a_robot_that_does_not_read_pauses_the_link_and_gets_everything_in_order(impl):
    """The robot namespace's write path (corked writes, then the writer task once the link pauses)
    over each library: 300 messages of 64 kB to a client that reads nothing at first."""
    count, part = 300, 64 * 1024
    namespaces: list[RobotNamespace] = []

    async def handler(link):
        async def gone(_ns) -> None:
            return None
        ns = RobotNamespace("u", "r", None, RobotSession("robot", SessionLimits(queue_size=count * 2)), on_gone=gone)
        namespaces.append(ns)
        await ns.serve(link)
    async with Server(impl, handler, max_size=None) as srv, \
            connect(srv.url, max_size=None, compression=None, max_queue=1) as client:
        await until(lambda: namespaces and namespaces[0].ws is not None, "the session")
        ns = namespaces[0]
        ns.session.add_interface("cam", "PublisherForwarder", "std_msgs/String")
        for i in range(count):        # control DMs (data=False): never dropped
            assert ns.send_dm("cam", "std_msgs/String", str(i), i.to_bytes(4, "little") + bytes(part - 4))
        await until(lambda: ws_link.paused(ns.ws), "the link to pause")
        assert ns.session.outbox > 0 and not ws_link.writable(ns.ws)
        got = []
        while len(got) < count:
            text = json.loads(await asyncio.wait_for(client.recv(), STEP))
            data = await asyncio.wait_for(client.recv(), STEP)
            assert text["data"]["msg*"] == data[:32].decode()
            got.append((text["data"]["msgID"], int.from_bytes(data[32:36], "little"), len(data) - 32))
        assert got == [(str(i), i, part) for i in range(count)]
        assert ns.session.outbox == 0


async def test_an_unknown_implementation_is_refused():
    with pytest.raises(ValueError, match="picows, websockets"):
        await ws_link.serve("ws4py", echo, "127.0.0.1", 0, process_request=None, max_size=1, ping_interval=1,
                            ping_timeout=1, max_queue=1)
