"""The robot endpoint's websocket, served by either of two libraries (``rce-robot --ws-impl``):
picows (Cython, callback based; about half websockets' CPU per frame, docs/benchmarks.md) or
websockets (pure Python, asyncio).

The session shells (:mod:`rce_robot.namespace`, :mod:`rce_robot.rosbridge.endpoint`) see one surface: the
part of websockets' ``ServerConnection`` they use (``async for frame in ws``, ``await ws.send(m)``
with ``m`` a str, bytes or an async iterable of fragments, ``await ws.drain()``, ``await
ws.close(code, reason)``, ``ws.close_code``, ``ws.remote_address``, ``ws.transport``;
:class:`~websockets.exceptions.ConnectionClosed` from ``send`` and ``drain`` on a lost link), and
the functions here: corked writes (:func:`write`, while :func:`writable`), :func:`paused`, the lag
rule's :func:`behind` and :func:`take_turn`, and :func:`closed_by_peer`. On a websockets
connection they are :mod:`rce_robot.ws_cork`'s; :class:`PicowsLink` implements them itself.

:func:`serve` starts the server: the login is checked at upgrade time by an async
``process_request(connection, request)`` (``request.path``; ``connection.respond(status, text)``
refuses with that HTTP status, its ``headers`` may be added to; attributes set on ``connection``
are on the link the handler gets), TLS with an :class:`ssl.SSLContext`, keepalive pings, and a
bound on the frames read ahead of the handler.

picows' upgrade hook is synchronous, so :class:`PicowsServer` reads the HTTP request itself
(:class:`_FrontDoor`), awaits ``process_request``, and then hands the connection (the request's
bytes replayed) to a picows protocol that sends the answer: 101 and the websocket, or the refusal.
"""
from __future__ import annotations

import asyncio
import logging
import ssl
import socket
import time
from collections import deque
from collections.abc import AsyncIterable, Awaitable, Callable, Iterable
from dataclasses import dataclass, field
from http import HTTPStatus
from typing import Any

from picows import WSListener, WSMsgType, WSUpgradeResponse, WSUpgradeResponseWithListener
from picows.picows import WSAutoPingStrategy, WSProtocol
from websockets.exceptions import ConnectionClosedError

from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks
from rce_robot import ws_cork
from rce_robot.ws_cork import frame_header

log = get_logger("rce.robot")

IMPLS = ("picows", "websockets")
DEFAULT_IMPL = "picows"
CLOSE_TIMEOUT = 10.0          # s a close waits for the peer's close frame before it drops the connection
HANDSHAKE_TIMEOUT = 10.0      # s a new connection has to send its whole HTTP upgrade request
MAX_REQUEST = 8 * 1024        # bytes of an HTTP upgrade request (line and headers)
READ_LOW_WATER = 4            # read-ahead frames at or below which reading resumes (max_queue: pauses)
UNREAD_FRESH = 0.005          # s: a frame taken this soon after it was read leaves nothing behind it in the kernel
UNREAD_SMALL = 64 * 1024      # bytes: ... if it was smaller than this (one read took all there was: PicowsLink.behind)
ABNORMAL = 1006               # close code of a link lost without a close frame (RFC 6455 section 7.4.1)
NO_STATUS = 1005              # a close frame without a code


# -- what the shells call, for either library ----------------------------------------------------------
def writable(ws: Any) -> bool:
    """Can :func:`write` take frames for ``ws`` now: open, and its transport not above its high-water mark?"""
    return ws.writable() if type(ws) is PicowsLink else ws_cork.writable(ws)


def paused(ws: Any) -> bool:
    """Is the open link ``ws`` waiting for its transport to drain (``await ws.drain()``)?"""
    return ws.is_paused() if type(ws) is PicowsLink else ws_cork.paused(ws)


def write(ws: Any, frames: Iterable[str | bytes]) -> int:
    """Frame ``frames`` (str: text, bytes: binary) and write them in one ``writelines``; returns the
    bytes written. Call only while :func:`writable`."""
    return ws.write(frames) if type(ws) is PicowsLink else ws_cork.write(ws, frames)


def behind(ws: Any) -> int:
    """Frames, else bytes, of ``ws``'s received and not taken by its reader yet (0: it has taken all)."""
    return ws.behind() if type(ws) is PicowsLink else ws_cork.behind(ws)


async def take_turn(ws: Any) -> None:
    """Let the loop's other work go first when ``ws`` has more received frames waiting."""
    if behind_frames(ws):
        await asyncio.sleep(0)


def behind_frames(ws: Any) -> int:
    """Frames ``ws`` has received that its reader has not taken yet."""
    return len(ws.frames) if type(ws) is PicowsLink else ws_cork.backlog(ws)


def closed_by_peer(ws: Any, codes: Iterable[int]) -> bool:
    """Did the peer end the link itself: its close frame came first, with one of ``codes``?"""
    if type(ws) is PicowsLink:
        return ws.close_rcvd_first and ws.close_rcvd is not None and ws.close_rcvd in codes
    proto = getattr(ws, "protocol", None)
    rcvd = getattr(proto, "close_rcvd", None)
    return rcvd is not None and bool(getattr(proto, "close_rcvd_then_sent", False)) and rcvd.code in codes


# -- the server ------------------------------------------------------------------------------------------
Handler = Callable[[Any], Awaitable[None]]
ProcessRequest = Callable[[Any, Any], Awaitable[Any]]


async def serve(impl: str, handler: Handler, host: str | None, port: int | None, *, sock: socket.socket | None = None,
                process_request: ProcessRequest | None, max_size: int | None, ping_interval: float, ping_timeout: float,
                max_queue: int, ssl_context: ssl.SSLContext | None = None):
    """Listen on ``host``:``port`` (or ``sock``) with library ``impl`` (one of :data:`IMPLS`); each
    connection ``process_request`` lets through is served by ``handler(link)``, and closed (1000; 1011
    when it raised) when the handler returns. ``max_size``: bytes of a message (larger: close 1009; None: no limit);
    ``ping_interval``/``ping_timeout``: s of the keepalive (a link whose pong does not come in
    ``ping_timeout`` is dropped); ``max_queue``: frames read ahead of the handler. Returns the server
    (``sockets``, ``close()``, ``await wait_closed()``). Raises ValueError for an unknown ``impl``."""
    if impl == "websockets":
        from websockets.asyncio.server import serve as ws_serve
        return await ws_serve(handler, host, port, sock=sock, process_request=process_request, max_size=max_size,
                              compression=None, ping_interval=ping_interval, ping_timeout=ping_timeout,
                              max_queue=max_queue, ssl=ssl_context)
    if impl != "picows":
        raise ValueError(f"websocket implementation must be one of {', '.join(IMPLS)}; got {impl!r}")
    server = PicowsServer(handler, process_request, max_size=max_size, ping_interval=ping_interval,
                          ping_timeout=ping_timeout, max_queue=max_queue)
    await server.start(host, port, sock, ssl_context)
    return server


@dataclass
class UpgradeRequest:
    """An HTTP upgrade request as ``process_request`` sees it: ``path`` with its query (str)."""
    path: str


@dataclass
class Refusal:
    """A refusal from ``process_request``: HTTP ``status`` (int), ``body`` (bytes), extra ``headers``."""
    status: int
    body: bytes
    headers: dict[str, str] = field(default_factory=dict)


class PicowsLink(WSListener):
    """One robot's websocket on picows, with the surface of websockets' ``ServerConnection`` the
    shells use (module docstring). Whole messages (fragments joined, text decoded) wait in
    ``frames`` (read-ahead: reading pauses at ``max_queue``); writes are framed here (RFC 6455
    section 5.2, a server's frames are unmasked) and go to the transport in one ``writelines``."""

    def __init__(self, server: "PicowsServer", transport: asyncio.Transport):
        super().__init__()
        self.server = server
        self.transport = transport                   # the TCP (or TLS) transport: its socket, its flow control
        self.remote_address = transport.get_extra_info("peername")
        self.frames: deque[str | bytes] = deque()    # whole messages not taken by the reader yet
        self.paused = False                          # the transport's buffer is above its high-water mark
        self.close_rcvd: int | None = None           # the peer's close code (NO_STATUS: none in its frame)
        self.close_rcvd_first = False                # ... and it came before ours
        self.wst: Any = None                         # picows' WSTransport, once open
        self._waiter: asyncio.Future | None = None   # the reader waits for a frame
        self._drained: asyncio.Future | None = None  # a writer waits for the transport to drain
        self._loop = asyncio.get_running_loop()      # kept: each lookup costs a getpid() on Python 3.11
        self._closed = self._loop.create_future()
        self._reading = True
        self._partial: list | None = None            # a fragmented message's parts so far
        self._partial_text = False
        self._partial_size = 0
        self.ping_sent: float | None = None          # monotonic s of the keepalive ping not answered yet
        self._pushed_at = 0.0                        # monotonic s the last whole message was read
        self._pushed_size = 0                        # ... and its bytes

    # -- picows' callbacks
    def on_ws_connected(self, transport) -> None:
        self.wst = transport
        self.server.opened(self)

    def on_ws_frame(self, transport, frame) -> None:
        t = frame.msg_type
        if t is WSMsgType.TEXT or t is WSMsgType.BINARY:
            if self._partial is not None:
                return self._fail(1002, "a new message before the last one's final fragment")
            if frame.fin:
                try:
                    self._push(frame.get_payload_as_utf8_text() if t is WSMsgType.TEXT
                               else frame.get_payload_as_bytes())
                except UnicodeDecodeError:
                    self._fail(1007, "a text frame that is not UTF-8")
                return
            self._partial, self._partial_text = [frame.get_payload_as_bytes()], t is WSMsgType.TEXT
            self._partial_size = len(self._partial[0])
        elif t is WSMsgType.CONTINUATION:
            if self._partial is None:
                return self._fail(1002, "a continuation frame outside a message")
            part = frame.get_payload_as_bytes()
            self._partial.append(part)
            self._partial_size += len(part)
            if self._partial_size > self.server.max_size:
                return self._fail(1009, f"message over {self.server.max_size} bytes")
            if frame.fin:
                data, text, self._partial = b"".join(self._partial), self._partial_text, None
                try:
                    self._push(data.decode() if text else data)
                except UnicodeDecodeError:
                    self._fail(1007, "a text message that is not UTF-8")
        elif t is WSMsgType.PONG:
            self.ping_sent = None
        elif t is WSMsgType.CLOSE:
            code = int(frame.get_close_code())      # picows: 0 for a close frame without a code
            self.close_rcvd = code if code >= 1000 else NO_STATUS
            if not transport.is_close_frame_sent:        # the peer began: answer with its code, then hang up
                self.close_rcvd_first = True
                if self.close_rcvd == NO_STATUS:
                    transport.send(WSMsgType.CLOSE, b"")
                else:
                    transport.send_close(self.close_rcvd)
            transport.disconnect()

    def on_ws_disconnected(self, transport) -> None:
        if not self._closed.done():
            self._closed.set_result(None)
        self._wake()
        if self._drained is not None and not self._drained.done():
            self._drained.set_result(None)
        self.server.gone(self)

    def pause_writing(self) -> None:
        self.paused = True

    def resume_writing(self) -> None:
        self.paused = False
        if self._drained is not None and not self._drained.done():
            self._drained.set_result(None)

    def keepalive(self, now: float, timeout: float) -> None:
        """(:meth:`PicowsServer._keepalive`) Ping the peer, or drop it when it left the last ping
        unanswered for ``timeout`` s."""
        if not self.open():
            return
        if self.ping_sent is None:
            self.ping_sent = now
            self.wst.send_ping()
        elif now - self.ping_sent > timeout:
            log.info("dropping a websocket whose peer does not answer pings", peer=str(self.remote_address),
                     timeout=timeout)
            self.wst.send_close(1011, b"keepalive ping timeout")
            self.wst.disconnect(False)

    # -- reading
    def _push(self, message: str | bytes) -> None:
        self.frames.append(message)
        self._pushed_at, self._pushed_size = time.monotonic(), len(message)
        self._wake()
        if self._reading and len(self.frames) >= self.server.max_queue:
            self._reading = False
            self.transport.pause_reading()

    def _wake(self) -> None:
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)

    def _fail(self, code: int, reason: str) -> None:
        log.info("closing a websocket that broke the protocol", peer=str(self.remote_address), code=code, reason=reason)
        self._partial = None
        self.wst.send_close(code, reason.encode())
        self.wst.disconnect()

    def __aiter__(self) -> "PicowsLink":
        return self

    async def __anext__(self) -> str | bytes:
        """The next whole message; the iteration ends when the link is closed and all are taken."""
        frames = self.frames
        while not frames:
            if self._closed.done():
                raise StopAsyncIteration
            self._waiter = self._loop.create_future()
            await self._waiter
        message = frames.popleft()
        if not self._reading and len(frames) <= READ_LOW_WATER and not self._closed.done():
            self._reading = True
            self.transport.resume_reading()
        return message

    def behind(self) -> int:
        """Frames (else bytes unread in the kernel: :func:`~rce_robot.ws_cork.fionread`) not taken yet.

        The kernel is asked only when the reader may be behind it: not when it took the last message
        within :data:`UNREAD_FRESH` of reading it, and that message was under :data:`UNREAD_SMALL`.
        The loop reads a socket until the kernel has no more (libuv stops at a short read; 32 reads of
        the read buffer, 16 KiB and growing, at most), so bytes there then came after that read, at
        most :data:`UNREAD_FRESH` ago: the endpoint is that far behind at most, which the lag rule
        (``max_lag``, 1 s by default) counts as caught up. An endpoint that lags takes its frames later
        than that, and a large message may have left more in the kernel: both ask it. This saves an
        ``ioctl`` (about 1.3 us on these VMs) per message when the endpoint keeps up."""
        n = len(self.frames)
        if n:
            return n
        if self._pushed_size < UNREAD_SMALL and time.monotonic() - self._pushed_at < UNREAD_FRESH:
            return 0
        return ws_cork.fionread(self.transport.get_extra_info("socket"))

    # -- writing
    def open(self) -> bool:
        """Open: neither side's close frame sent, the connection not lost."""
        wst = self.wst
        return wst is not None and not wst.is_close_frame_sent and not wst.is_disconnected \
            and self.close_rcvd is None

    def writable(self) -> bool:
        return not self.paused and self.open()

    def is_paused(self) -> bool:
        return self.paused and self.open()

    def write(self, frames: Iterable[str | bytes]) -> int:
        out: list = []
        for f in frames:
            if isinstance(f, str):
                f = f.encode()
                out.append(frame_header(0x81, len(f)))
            else:
                out.append(frame_header(0x82, len(f)))
            out.append(f)
        self.transport.writelines(out)
        return sum(map(len, out))

    async def drain(self) -> None:
        """Wait until the transport has drained below its low-water mark. Raises ConnectionClosed when
        the link is lost (or closing) meanwhile."""
        while self.paused:
            if not self.open():
                raise ConnectionClosedError(None, None)
            self._drained = self._loop.create_future()
            await self._drained
        if not self.open():
            raise ConnectionClosedError(None, None)

    async def send(self, message: str | bytes | Iterable[str | bytes] | AsyncIterable[str | bytes]) -> None:
        """Send one message: a str (text), bytes (binary), or an iterable or async iterable of its fragments
        (all str or all bytes; RFC 6455 section 5.4), each written once the transport takes it. Raises
        ConnectionClosed on a link that is closed or closing."""
        await self.drain()
        if isinstance(message, (str, bytes, bytearray, memoryview)):
            self.write((message if isinstance(message, str) else bytes(message),))
            return
        first = True
        if hasattr(message, "__aiter__"):
            async for part in message:
                await self._fragment(part, first)
                first = False
        else:
            for part in message:
                await self._fragment(part, first)
                first = False
        await self.drain()
        self.transport.write(frame_header(0x80 if not first else 0x81, 0))     # the final (empty) fragment

    async def _fragment(self, part: str | bytes, first: bool) -> None:
        """Write one fragment of a message (the first: its opcode; the others: continuation), FIN clear."""
        await self.drain()
        data = part.encode() if isinstance(part, str) else part
        code = (0x1 if isinstance(part, str) else 0x2) if first else 0x0
        self.transport.writelines((frame_header(code, len(data)), data))

    async def close(self, code: int = 1000, reason: str = "") -> None:
        """Send a close frame (``code``, ``reason``), wait up to :data:`CLOSE_TIMEOUT` for the peer's, and
        drop the connection. Nothing to do on a link already closed."""
        if self.wst is not None and self.open():
            self.wst.send_close(code, reason.encode())
        if self._closed.done():
            return
        try:
            async with asyncio.timeout(CLOSE_TIMEOUT):
                await asyncio.shield(self._closed)
        except TimeoutError:
            self.wst.disconnect(False) if self.wst is not None else self.transport.abort()
            await self._closed

    @property
    def close_code(self) -> int | None:
        """The peer's close code; :data:`ABNORMAL` for a link lost without one; None while open."""
        if self.close_rcvd is not None:
            return self.close_rcvd
        return ABNORMAL if self._closed.done() else None

    # -- the handshake's side (the same object is ``process_request``'s ``connection``)
    @staticmethod
    def respond(status: int, text: str) -> Refusal:
        """A refusal with HTTP ``status`` and body ``text``."""
        return Refusal(int(status), text.encode())


class PicowsServer:
    """The websocket server on picows (:func:`serve`): a TCP (or TLS) server whose connections start
    with :class:`_FrontDoor` and, once ``process_request`` lets them in, are :class:`PicowsLink` s served
    by ``handler``."""

    def __init__(self, handler: Handler, process_request: ProcessRequest | None, *, max_size: int | None,
                 ping_interval: float, ping_timeout: float, max_queue: int):
        self.handler, self.process_request = handler, process_request
        self.max_size = max_size if max_size is not None else 1 << 62           # None: no limit
        self.ping_interval, self.ping_timeout = ping_interval, ping_timeout
        self.max_queue = max(max_queue, READ_LOW_WATER + 1)
        self.links: set[PicowsLink] = set()
        self.tasks = Tasks("websocket server")         # handshakes and handlers
        self._server: asyncio.Server | None = None
        self._logger = logging.getLogger("picows.server")
        self._pinger: asyncio.Task | None = None

    async def start(self, host: str | None, port: int | None, sock: socket.socket | None,
                    ssl_context: ssl.SSLContext | None) -> None:
        loop = asyncio.get_running_loop()
        self._server = await loop.create_server(lambda: _FrontDoor(self), None if sock else host,
                                                None if sock else port, sock=sock, ssl=ssl_context)

    @property
    def sockets(self):
        return self._server.sockets

    def protocol(self, decide: Callable[[Any], Any]) -> Any:
        """A picows server protocol whose upgrade hook answers with ``decide(request)``."""
        return WSProtocol(None, None, False, decide, self._logger, True, None, False, 0, 0,
                          WSAutoPingStrategy.PING_WHEN_IDLE, True, self.max_size, None, 16 * 1024)

    async def _keepalive(self) -> None:
        """Every ``ping_interval`` s: ping each link whose last ping was answered; drop a link whose ping
        has gone unanswered for ``ping_timeout`` s (close code 1011, as websockets' keepalive)."""
        while True:
            await asyncio.sleep(self.ping_interval)       # a timer: the keepalive's period
            now = time.monotonic()
            for link in list(self.links):
                link.keepalive(now, self.ping_timeout)

    def opened(self, link: PicowsLink) -> None:
        if self._pinger is None and self.ping_interval:
            self._pinger = self.tasks.spawn(self._keepalive(), name="keepalive")
        self.links.add(link)
        self.tasks.spawn(self._run(link), name="websocket handler")

    def gone(self, link: PicowsLink) -> None:
        self.links.discard(link)

    async def _run(self, link: PicowsLink) -> None:
        try:
            await self.handler(link)
        except Exception:
            log.exception("websocket handler failed", peer=str(link.remote_address))
            await link.close(1011, "internal error")
        else:
            await link.close(1000)

    def close(self) -> None:
        """Stop listening and close every link (1001, going away)."""
        self._server.close()
        if self._pinger is not None:
            self._pinger.cancel()
        for link in list(self.links):
            self.tasks.spawn(link.close(1001), name="close link")

    async def wait_closed(self) -> None:
        """Wait until every handler has returned and every link is closed."""
        await self.tasks.wait_all()
        await self._server.wait_closed()


class _FrontDoor(asyncio.Protocol):
    """A new connection until its HTTP upgrade request is in and ``process_request`` has answered: then
    the connection goes to a picows protocol (:meth:`PicowsServer.protocol`), the request replayed to it."""

    def __init__(self, server: PicowsServer):
        self.server = server
        self.buf = bytearray()
        self.transport: Any = None
        self.timer: asyncio.TimerHandle | None = None
        self.deciding = False

    def connection_made(self, transport) -> None:
        self.transport = transport
        self.timer = asyncio.get_running_loop().call_later(HANDSHAKE_TIMEOUT, transport.abort)

    def data_received(self, data: bytes) -> None:
        self.buf += data
        if self.deciding:
            return
        if b"\r\n\r\n" in self.buf:
            self.deciding = True
            self.timer.cancel()
            self.transport.pause_reading()
            self.server.tasks.spawn(self._decide(), name="websocket handshake")
        elif len(self.buf) > MAX_REQUEST:
            self._answer(Refusal(HTTPStatus.REQUEST_HEADER_FIELDS_TOO_LARGE, b"request too large\n"))

    def connection_lost(self, exc) -> None:
        if self.timer is not None:
            self.timer.cancel()

    def _answer(self, response: Refusal | None, link: PicowsLink | None = None) -> None:
        """Hand the connection to picows, which sends ``response`` (None: the upgrade, for ``link``)."""
        if self.transport.is_closing():
            return

        def decide(request):
            if response is None:
                return link
            return WSUpgradeResponseWithListener(
                WSUpgradeResponse.create_error_response(response.status, response.body, response.headers), None)
        proto = self.server.protocol(decide)
        self.transport.set_protocol(proto)
        proto.connection_made(_LenientTransport(self.transport))
        data = memoryview(bytes(self.buf))
        while data:
            buf = proto.get_buffer(len(data))
            n = min(len(buf), len(data))
            buf[:n] = data[:n]
            proto.buffer_updated(n)
            data = data[n:]
        self.transport.resume_reading()

    async def _decide(self) -> None:
        line = bytes(self.buf).split(b"\r\n", 1)[0].split(b" ")
        link = PicowsLink(self.server, self.transport)
        response = None
        if len(line) == 3 and self.server.process_request is not None:   # else picows answers a malformed one
            try:
                response = await self.server.process_request(link, UpgradeRequest(line[1].decode("latin-1")))
            except Exception:
                log.exception("websocket handshake failed", peer=str(link.remote_address))
                response = Refusal(HTTPStatus.INTERNAL_SERVER_ERROR, b"internal error\n")
        self._answer(response, link)


class _LenientTransport:
    """The transport as picows' protocol sees it: picows sets ``TCP_QUICKACK`` on every socket, which an
    MPTCP socket refuses (EOPNOTSUPP; ``rce-robot --mptcp``); here the socket options the kernel refuses
    are left unset. Everything else (its writes, its close) is the transport's own."""

    def __init__(self, transport: asyncio.Transport):
        self._transport = transport

    def __getattr__(self, name: str) -> Any:
        return getattr(self._transport, name)

    def get_extra_info(self, name: str, default: Any = None) -> Any:
        value = self._transport.get_extra_info(name, default)
        return _LenientSocket(value) if name == "socket" and value is not None else value


class _LenientSocket:
    """(:class:`_LenientTransport`) A socket whose options the kernel refuses read as 0 and are not set."""

    def __init__(self, sock: socket.socket):
        self._sock = sock

    def __getattr__(self, name: str) -> Any:
        return getattr(self._sock, name)

    def setsockopt(self, *args) -> None:
        try:
            self._sock.setsockopt(*args)
        except OSError:
            pass

    def getsockopt(self, *args) -> Any:
        try:
            return self._sock.getsockopt(*args)
        except OSError:
            return 0
