"""The link layer: what every internal link (control plane, data plane, node <-> bus) does
with its stream, written once.

- :class:`FramedLink` owns one stream (TCP or Unix socket) carrying :mod:`rce.framing`
  frames: its transport receives straight into a :class:`~rce.framing.FrameDecoder`'s buffers
  (a buffered protocol: a large frame lands in a buffer of its own and is handed on without a
  copy), bounded writes with an explicit policy for a full link, one idempotent close.
- :class:`Responder` runs the handler of each incoming request (a control op, a data-plane
  ``SRV_REQ``, a bus service call) in a kept task and sends back its result or its error.
- :func:`settle_reply` completes a pending service call (:class:`~rce.pending.PendingCalls`)
  from its ``SRV_RESP``/``SRV_ERR`` frame.

Write policy (``max_buffer``: bytes that may wait in the transport, the peer not reading):

- :meth:`FramedLink.offer` is for frames that may be lost (topic messages, service replies
  whose caller times out): past the bound the frame is dropped, counted in ``dropped``, and
  ``False`` returned.
- :meth:`FramedLink.send` is for frames that must not be lost (control frames, service
  requests and replies): they may pass ``max_buffer`` (so they still get through a link
  that offered messages keep full) up to ``hard_buffer`` (default twice ``max_buffer``);
  past that it raises :class:`LinkFull` and the caller decides (a request fails to its
  caller; :mod:`rce.rpc` cuts a link whose peer no longer reads even those).

A frame always goes onto an idle link, whatever its size (``max_frame`` bounds frames).
"""
from __future__ import annotations

import asyncio
import socket
from collections.abc import Awaitable, Callable, Iterator
from typing import Any

from rce import framing
from rce.errors import ProtocolError, RCEError, RequestError, Unavailable
from rce.log import get_logger
from rce.pending import PendingCalls
from rce.tasks import Tasks

log = get_logger("rce.link")

STREAM_LIMIT = 1024 * 1024           # bytes a stream reader buffers before it stops reading its socket (asyncio limit)
DEFAULT_MAX_BUFFER = 64 * 1024 * 1024   # bytes that may wait in a link's transport (see the module doc)
JOIN_MAX = 64 * 1024                 # bytes: a payload up to this is joined to its frame header (one write)
MAX_IN_FLIGHT = 1024                 # requests one Responder runs at once; more are refused (Unavailable)

Frame = dict | framing.DataFrame


class LinkFull(Unavailable):
    """A frame that must not be lost found its link's write bound reached (the peer is not reading)."""


class FramedLink:
    """One framed stream. ``reader``/``writer``: the asyncio stream pair; ``name`` names the
    peer in logs and errors; ``on_frame(frame)`` gets every frame received, in order (a dict
    for CONTROL, a :class:`~rce.framing.DataFrame` whose payload is a view of the received
    bytes for DATA); ``on_close(link)`` runs once when the link ends; ``max_frame``: largest
    frame accepted, bytes; ``max_buffer`` and ``hard_buffer``: write bounds of :meth:`offer`
    and :meth:`send`, bytes (module doc).

    The link ends on EOF, a socket error, a bad frame (logged, :class:`ProtocolError` from
    the decoder or from ``on_frame``), any other exception from ``on_frame`` (logged with its
    traceback), or :meth:`close`. ``last_rx`` is the loop time of the last bytes received
    (for keepalives); ``dropped`` counts frames :meth:`offer` refused, ``refused`` the
    :class:`LinkFull` raised by :meth:`send`."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, *, name: str = "peer",
                 on_frame: Callable[[Frame], Any],
                 on_close: Callable[["FramedLink"], Any] | None = None,
                 max_frame: int = framing.DEFAULT_MAX_FRAME, max_buffer: int = DEFAULT_MAX_BUFFER,
                 hard_buffer: int | None = None):
        self.reader, self.writer, self.transport = reader, writer, writer.transport
        self.name = name
        self.on_frame = on_frame
        self.on_close = on_close
        self.decoder = framing.FrameDecoder(max_frame)
        self.max_buffer = max_buffer
        self.hard_buffer = 2 * max_buffer if hard_buffer is None else hard_buffer
        self.closed = asyncio.Event()
        self.close_reason = ""
        self.last_rx = asyncio.get_running_loop().time()
        self.dropped = self.refused = 0
        self._receiver: _Receiver | None = None

    @property
    def peername(self) -> str:
        """The peer's address, ``host:port`` (TCP) or the socket path (Unix)."""
        p = self.writer.get_extra_info("peername")
        return f"{p[0]}:{p[1]}" if isinstance(p, tuple) else str(p)

    def start(self) -> "FramedLink":
        """Start reading (returns self; frames come from the next loop iteration on): the link
        takes its transport over with a :class:`_Receiver`, so the stream's bytes go straight
        into the decoder's buffers; what the stream reader had already taken goes first."""
        if self._receiver is None and not self.closed.is_set():
            self._receiver = _Receiver(self, self.transport.get_protocol())
            asyncio.get_running_loop().call_soon(self._take_over)
        return self

    def _take_over(self) -> None:
        if self.closed.is_set():
            return
        self.transport.set_protocol(self._receiver)
        early = self.reader._buffer       # bytes the stream reader took before: they come first
        if early:
            self._received(self.decoder.frames(bytes(early)))
            early.clear()
        if self.closed.is_set():
            return
        if self.reader.at_eof() or self.reader.exception() is not None or self.transport.is_closing():
            self._finish("closed by the peer")      # the connection ended before
        else:
            self.transport.resume_reading()     # the reader may have paused it (its buffer was full)

    # -- reading ---------------------------------------------------------------------------------
    def _received(self, frames: Iterator[Frame]) -> None:
        """Hand every frame of ``frames`` to ``on_frame``; a bad frame or a failing handler ends the link."""
        if self.closed.is_set():
            return
        self.last_rx = asyncio.get_running_loop().time()
        try:
            for frame in frames:
                self.on_frame(frame)
                if self.closed.is_set():      # on_frame closed the link
                    return
        except ProtocolError as e:
            log.warning("closing link on bad frame", link=self.name, reason=e.message)
            self._finish(f"bad frame: {e.message}")
        except Exception as e:
            log.error("link failed", link=self.name, exc_info=e)
            self._finish(f"internal error: {type(e).__name__}: {e}")

    # -- writing ---------------------------------------------------------------------------------
    def _room(self, n: int, bound: int) -> bool:
        waiting = self.transport.get_write_buffer_size()
        return not waiting or waiting + n <= bound

    def offer(self, frame: bytes, payload: bytes | memoryview = b"") -> bool:
        """Write ``frame`` (then ``payload``, unjoined: no copy) if the link is open and within
        its bound; otherwise drop it, count it in ``dropped`` and return False."""
        t = self.transport
        if self.closed.is_set() or t.is_closing() or not self._room(len(frame) + len(payload), self.max_buffer):
            self.dropped += 1
            return False
        _write(t, frame, payload)
        return True

    def send(self, frame: bytes, payload: bytes | memoryview = b"") -> None:
        """Write a frame that must not be lost. Raises :class:`Unavailable` on a closed link and
        :class:`LinkFull` (counted in ``refused``) past ``hard_buffer``."""
        t = self.transport
        if self.closed.is_set() or t.is_closing():
            raise Unavailable(f"the link to {self.name} is closed")
        if not self._room(len(frame) + len(payload), self.hard_buffer):
            self.refused += 1
            raise LinkFull(f"the link to {self.name} is saturated: {t.get_write_buffer_size()} bytes wait "
                           f"unread (bound {self.hard_buffer} bytes)")
        _write(t, frame, payload)

    async def drain(self) -> None:
        """Wait until the transport's buffer is below its low-water mark (backpressure)."""
        if not self.closed.is_set():
            try:
                await self.writer.drain()
            except (ConnectionError, OSError):
                pass

    # -- closing ---------------------------------------------------------------------------------
    def close(self, reason: str = "closed") -> None:
        """Close the stream now (idempotent); ``on_close`` runs once and no frame is handled after."""
        self._finish(reason)

    async def wait_closed(self) -> None:
        """Wait until the link has ended (a link never started: returns at once)."""
        if self._receiver is not None:
            await self.closed.wait()

    def _finish(self, reason: str) -> None:
        if self.closed.is_set():
            return
        self.close_reason = reason
        self.closed.set()
        try:
            self.writer.close()
        except (RuntimeError, OSError):     # the loop is closing
            pass
        if self.on_close is not None:
            try:
                self.on_close(self)
            except Exception as e:
                log.error("on_close handler failed", link=self.name, exc_info=e)


def _write(t: asyncio.WriteTransport, frame: bytes, payload: bytes | memoryview) -> None:
    """One frame, in one system call: a small payload is joined to its header (a copy of at
    most :data:`JOIN_MAX` bytes costs less than a second ``write``); a large one follows it
    unjoined, uncopied."""
    if not payload:
        t.write(frame)
    elif len(payload) <= JOIN_MAX:
        t.write(frame + payload)
    else:
        t.write(frame)
        t.write(payload)


class _Receiver(asyncio.BufferedProtocol):
    """A started :class:`FramedLink`'s protocol (asyncio ``BufferedProtocol``): the transport
    receives into :meth:`rce.framing.FrameDecoder.get_buffer`, a large frame straight into its
    own buffer. Flow control and the end of the connection are passed on to the stream's
    protocol ``stream`` as well, so the link's ``StreamWriter`` (``drain``, ``wait_closed``)
    works as before."""

    def __init__(self, link: FramedLink, stream: asyncio.BaseProtocol):
        self.link, self.stream = link, stream

    def get_buffer(self, sizehint: int) -> memoryview:
        return self.link.decoder.get_buffer()

    def buffer_updated(self, nbytes: int) -> None:
        self.link._received(self.link.decoder.buffer_updated(nbytes))

    def eof_received(self) -> bool:
        self.link._finish("closed by the peer")
        return False

    def connection_lost(self, exc: Exception | None) -> None:
        self.link._finish("closed by the peer" if exc is None else f"connection lost: {exc}")
        self.stream.connection_lost(exc)

    def pause_writing(self) -> None:
        self.stream.pause_writing()

    def resume_writing(self) -> None:
        self.stream.resume_writing()


# -- serve and reply -------------------------------------------------------------------------------
class Responder:
    """Runs the handlers of incoming requests, each in a task of ``tasks``, and answers each.

    ``owner`` names the server in logs; at most ``max_in_flight`` requests run at once (more
    are refused with :class:`Unavailable` and counted in ``refused``)."""

    def __init__(self, owner: str, tasks: Tasks | None = None, max_in_flight: int = MAX_IN_FLIGHT):
        self.owner = owner
        self.tasks = tasks or Tasks(owner)
        self.max_in_flight = max_in_flight
        self.in_flight = self.refused = 0

    def serve(self, handler: Callable[[], Awaitable[Any]], reply: Callable[[Any], Any],
              refuse: Callable[[RCEError], Any], what: str) -> None:
        """Run ``await handler()`` in a kept task; then ``reply(result)``, or ``refuse(error)``:
        an :class:`RCEError` as raised, any other exception logged with its traceback and
        refused as ``internal error: Type: message``. ``what`` names the request in logs."""
        if self.in_flight >= self.max_in_flight:
            self.refused += 1
            refuse(Unavailable(f"{self.owner}: {self.in_flight} requests in flight, {what} refused"))
            return
        self.in_flight += 1
        self.tasks.spawn(self._run(handler, reply, refuse, what), name=what).add_done_callback(self._ended)

    def _ended(self, _task: asyncio.Task) -> None:
        self.in_flight -= 1

    async def _run(self, handler: Callable[[], Awaitable[Any]], reply: Callable[[Any], Any],
                   refuse: Callable[[RCEError], Any], what: str) -> None:
        try:
            result = await handler()
        except RCEError as e:
            refuse(e)
            return
        except Exception as e:
            log.error("request handler failed", owner=self.owner, request=what, exc_info=e)
            refuse(RCEError(f"internal error: {type(e).__name__}: {e}"))
            return
        reply(result)


def settle_reply(calls: PendingCalls, f: framing.DataFrame) -> bool:
    """Complete call ``f.call_id`` of ``calls`` from a ``SRV_RESP`` (result: the response bytes)
    or ``SRV_ERR`` frame (error: :class:`RequestError` with the remote reason). False when no
    such call waits (late, or unknown)."""
    if f.op == framing.SRV_RESP:
        return calls.settle(f.call_id, bytes(f.payload))
    return calls.fail(f.call_id, RequestError(bytes(f.payload).decode(errors="replace")))


def nodelay(writer: asyncio.StreamWriter) -> None:
    """Turn Nagle's algorithm off on a TCP stream (small frames go at once); no-op otherwise."""
    sock = writer.get_extra_info("socket")
    if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
