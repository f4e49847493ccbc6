"""The link layer: what every internal link (control plane, data plane, node <-> bus) does
with its stream, written once.

- :class:`FramedLink` owns one stream (TCP or Unix socket) carrying :mod:`rce.transport.framing`
  frames: its transport receives straight into a :class:`~rce.transport.framing.FrameDecoder`'s buffers
  (a buffered protocol: a large frame lands in a buffer of its own and is handed on without a
  copy), bounded writes with an explicit policy for a full link, one idempotent close.
- :class:`Responder` runs the handler of each incoming request (a control op, a data-plane
  ``SRV_REQ``, a bus service call) in a kept task and sends back its result or its error.
- :func:`settle_reply` completes a pending service call (:class:`~rce.plumbing.pending.PendingCalls`)
  from its ``SRV_RESP``/``SRV_ERR`` frame.

Write policy (``max_buffer``: bytes that may wait in the transport, the peer not reading):

- :meth:`FramedLink.offer` is for frames that may be lost (topic messages, service replies
  whose caller times out): past the bound the frame is dropped, counted in ``dropped``, and
  ``False`` returned.
- :meth:`FramedLink.send` is for frames that must not be lost (control frames, service
  requests and replies): they may pass ``max_buffer`` (so they still get through a link
  that offered messages keep full) up to ``hard_buffer`` (default twice ``max_buffer``);
  past that it raises :class:`LinkFull` and the caller decides (a request fails to its
  caller; :mod:`rce.transport.rpc` cuts a link whose peer no longer reads even those).

A frame always goes onto an idle link, whatever its size (``max_frame`` bounds frames).

Under pressure, oldest first (the latest message is the one a robot needs): while the transport
holds more than its high-water mark (asyncio's flow control: the peer is not keeping up), frames
wait in the link's own queue, and leave it for the transport, in order, as the transport drains.
There an offered frame is dropped when it has waited longer than ``max_delay`` (counted in
``expired``), or when a newer frame needs its room under ``max_buffer``, as a ROS subscriber's
``queue_size`` drops its oldest message. So a reader that cannot keep up gets the newest
messages, at most ``max_delay`` late in this process, instead of an ever older backlog. A frame
that must not be lost (:meth:`FramedLink.send`) waits in the same queue, so the order of frames
never changes, and is never dropped: it takes the room of the oldest offered frames first.
``on_drop(tag)`` hears of each offered frame dropped after :meth:`FramedLink.offer` took it
(its ``tag``), so the sender's counters stay right. :meth:`FramedLink.take_back` takes offered frames
that are still in the queue back out, unsent, for a sender that now sends them elsewhere (a moved
container's new copy).

A data link (``data=True``) bounds what waits below its queue in time as well as in bytes. As it
sends, it reads its socket's delivery rate (``TCP_INFO``) at most every :data:`FIT_EVERY` s, and
whenever the kernel measured it while the link had more to send (not app-limited), lets the kernel
(``TCP_NOTSENT_LOWAT``) and the transport (its high-water mark) each hold what the link sends in
:data:`UNSENT_S` at that rate: at least :data:`MIN_UNSENT` bytes, at most :data:`NOTSENT_LOWAT` and
the transport's own mark. On loopback that changes nothing; on a link of 1
Mbit/s the kernel would otherwise hold 1 MiB unsent, 8 s of sending beyond the reach of
``max_delay``, and a stream the link cannot carry would arrive seconds late instead of newest first.

Writes are corked per loop pass: the frames of one pass wait in the link's cork and go out
together in one ``writelines`` (one system call) when the pass ends (a ``call_soon`` callback
the pass's first frame schedules, never a timer), or as soon as :data:`CORK_MAX` bytes wait. A
lone message waits for no timer and no other message, only for the callbacks already ready in
that pass; a busy link (many robots' messages to one node, a node's replies to them) pays one
write per pass instead of one per frame. What waits in the cork counts towards the write
bounds. A payload larger than :data:`JOIN_MAX` is never corked (it may be a view of a receive
buffer): what the cork holds goes first, then it.
"""
from __future__ import annotations

import asyncio
import collections
import socket
from collections.abc import Awaitable, Callable, Iterator
from typing import Any

from rce.transport import framing
from rce.transport.lane_socket import link_sample
from rce.plumbing.errors import ProtocolError, RCEError, RequestError, Unavailable
from rce.plumbing.log import get_logger
from rce.plumbing.pending import PendingCalls
from rce.plumbing.tasks import Tasks

log = get_logger("rce.link")

STREAM_LIMIT = 1024 * 1024           # bytes a stream reader buffers before it stops reading its socket (asyncio limit)
DEFAULT_MAX_BUFFER = 64 * 1024 * 1024   # bytes that may wait in a link's transport and queue (see the module doc)
JOIN_MAX = 64 * 1024                 # bytes: a payload up to this is joined to its frame header (one write)
MAX_IN_FLIGHT = 1024                 # requests one Responder runs at once; more are refused (Unavailable)
DEFAULT_MAX_DELAY = 1.0              # s an offered frame may wait in a link's queue for a slow peer (module doc)
HIGH_WATER = 64 * 1024               # bytes: a transport's high-water mark when it cannot tell its own
NOTSENT_LOWAT = 1024 * 1024           # bytes a data link's socket keeps unsent in the kernel at most (data_socket)
TCP_NOTSENT_LOWAT = getattr(socket, "TCP_NOTSENT_LOWAT", None)   # None: a platform without it
CORK_MAX = 256 * 1024                # bytes a link's cork holds within one loop pass before they go out (module doc)
UNSENT_S = 0.05                      # s of sending, at a data link's measured rate, its kernel and its transport
                                     # may each hold unsent (module doc)
MIN_UNSENT = 16 * 1024               # bytes they may hold whatever the rate
FIT_EVERY = 0.1                      # s between looks at a sending data link's delivery rate

Frame = dict | framing.DataFrame


class LinkFull(Unavailable):
    """A frame that must not be lost found its link's write bound reached (the peer is not reading)."""


class FramedLink:
    """One framed stream. ``reader``/``writer``: the asyncio stream pair; ``name`` names the
    peer in logs and errors; ``on_frame(frame)`` gets every frame received, in order (a dict
    for CONTROL, a :class:`~rce.transport.framing.DataFrame` whose payload is a view of the received
    bytes for DATA); ``on_close(link)`` runs once when the link ends; ``max_frame``: largest
    frame accepted, bytes; ``max_buffer`` and ``hard_buffer``: write bounds of :meth:`offer`
    and :meth:`send`, bytes, counting what waits in the transport and in the link's queue;
    ``max_delay``: s an offered frame may wait in the link's queue (None: no age bound);
    ``on_drop(tag)``: called for each offered frame dropped after it was taken (module doc);
    ``data``: a data link, whose unsent bytes below its queue follow its measured rate (module doc).

    The link ends on EOF, a socket error, a bad frame (logged, :class:`ProtocolError` from
    the decoder or from ``on_frame``), any other exception from ``on_frame`` (logged with its
    traceback), or :meth:`close`. ``last_rx`` is the loop time of the last bytes received
    (for keepalives); ``dropped`` counts the offered frames lost (refused by :meth:`offer`, or
    dropped from the queue), ``expired`` those of them that waited longer than ``max_delay``,
    ``refused`` the :class:`LinkFull` raised by :meth:`send`; ``held``: frames waiting in the
    link's queue."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, *, name: str = "peer",
                 on_frame: Callable[[Frame], Any],
                 on_close: Callable[["FramedLink"], Any] | None = None,
                 max_frame: int = framing.DEFAULT_MAX_FRAME, max_buffer: int = DEFAULT_MAX_BUFFER,
                 hard_buffer: int | None = None, max_delay: float | None = DEFAULT_MAX_DELAY,
                 on_drop: Callable[[Any], Any] | None = None, data: bool = False):
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
        self.max_delay, self.on_drop = max_delay, on_drop
        self.dropped = self.refused = self.expired = 0
        self._receiver: _Receiver | None = None
        limits = getattr(self.transport, "get_write_buffer_limits", None)
        self._high = self._high_max = limits()[1] if limits is not None else HIGH_WATER
        sock = writer.get_extra_info("socket") if data else None
        self._fit_sock = sock if (sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6)
                                  and TCP_NOTSENT_LOWAT is not None) else None
        self._lowat, self._fitted_at = NOTSENT_LOWAT, float("-inf")
        # frames waiting for the transport to drain: (loop time taken, frame, payload, tag, droppable)
        self._queue: collections.deque[tuple[float, bytes, bytes | memoryview, Any, bool]] = collections.deque()
        self._queued_bytes = 0
        self._cork: list[bytes] = []        # frames written in this loop pass (module doc)
        self._cork_bytes = 0
        self._pass_open = False             # the cork's end of pass is scheduled
        self._loop = asyncio.get_running_loop()

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
        self.last_rx = self._loop.time()
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
    @property
    def held(self) -> int:
        """Frames waiting in the link's queue for the transport to drain."""
        return len(self._queue)

    def offer(self, frame: bytes, payload: bytes | memoryview = b"", tag: Any = None) -> bool:
        """Write ``frame`` (then ``payload``, unjoined: no copy) if the link is open and within
        its bound, or queue it while the peer is not keeping up (module doc); otherwise drop
        it, count it in ``dropped`` and return False. ``tag`` goes to ``on_drop`` if the frame
        is dropped later."""
        t = self.transport
        n = len(frame) + len(payload)
        if self.closed.is_set() or t.is_closing():
            self.dropped += 1
            return False
        if self._fit_sock is not None:
            now = self._loop.time()
            if now - self._fitted_at >= FIT_EVERY:
                self._fit_unsent(now)
        waiting = self.waiting
        if self._queue or waiting > self._high:
            if self._enqueue(frame, payload, n, tag, True, self.max_buffer):
                return True
        elif not waiting or waiting + n <= self.max_buffer:
            self._write(frame, payload)
            return True
        self.dropped += 1
        return False

    def send(self, frame: bytes, payload: bytes | memoryview = b"") -> None:
        """Write a frame that must not be lost (queued behind earlier frames while the peer is not
        keeping up, never dropped). Raises :class:`Unavailable` on a closed link and
        :class:`LinkFull` (counted in ``refused``) past ``hard_buffer``."""
        t = self.transport
        if self.closed.is_set() or t.is_closing():
            raise Unavailable(f"the link to {self.name} is closed")
        n = len(frame) + len(payload)
        waiting = self.waiting
        if self._queue:
            if self._enqueue(frame, payload, n, None, False, self.hard_buffer):
                return
        elif not waiting or waiting + n <= self.hard_buffer:
            self._write(frame, payload)
            return
        self.refused += 1
        raise LinkFull(f"the link to {self.name} is saturated: {waiting + self._queued_bytes} bytes wait "
                       f"unread (bound {self.hard_buffer} bytes)")

    def _enqueue(self, frame: bytes, payload: bytes | memoryview, nbytes: int, tag: Any, droppable: bool,
                 bound: int) -> bool:
        """Queue one frame behind the others, making room by dropping the oldest offered frames
        (and those past ``max_delay``); False if there is no room for it even so."""
        self._flush()                     # the transport may have drained below its mark already
        q = self._queue
        if not q and self.waiting <= self._high:
            self._write(frame, payload)
            return True
        now = self._loop.time()
        if self.max_delay is not None:
            while q and q[0][4] and now - q[0][0] > self.max_delay:
                self._drop(q.popleft(), expired=True)
        room = bound - self.waiting
        if self._queued_bytes + nbytes > room:
            if self._queued_bytes - self._droppable_bytes() + nbytes > room:
                return False
            i = 0
            while self._queued_bytes + nbytes > room:
                if q[i][4]:
                    self._drop(q[i], expired=False)
                    del q[i]
                else:
                    i += 1
        q.append((now, frame, payload, tag, droppable))
        self._queued_bytes += nbytes
        return True

    def _fit_unsent(self, now: float) -> None:
        """Let the kernel and the transport each hold what this data link sends in :data:`UNSENT_S`
        at its delivery rate, within their bounds (module doc); a rate measured while the link had
        nothing more to send (app-limited) says nothing of the path and is not used."""
        self._fitted_at = now
        info = link_sample(self._fit_sock)
        if info is None or info[1] <= 0 or info[2]:
            return
        want = int(info[1] * UNSENT_S)
        lowat = max(MIN_UNSENT, min(NOTSENT_LOWAT, want))
        if abs(lowat - self._lowat) > self._lowat // 4 and not self._set_lowat(lowat):
            return
        high = max(MIN_UNSENT, min(self._high_max, want))
        if high != self._high:
            self.transport.set_write_buffer_limits(high=high)
            self._high = high

    def _set_lowat(self, lowat: int) -> bool:
        try:
            self._fit_sock.setsockopt(socket.IPPROTO_TCP, TCP_NOTSENT_LOWAT, lowat)
        except OSError:
            self._fit_sock = None            # closed under us, or a kernel without the option
            return False
        self._lowat = lowat
        return True

    def queued(self, which: Callable[[bytes], bool]) -> list[bytes]:
        """The headers of the offered frames waiting in the link's queue that ``which`` accepts, in
        order; nothing is taken."""
        return [e[1] for e in self._queue if e[4] and which(e[1])]

    def take_back(self, which: Callable[[bytes], bool]) -> list[tuple[bytes, bytes | memoryview, Any]]:
        """Take the offered frames still waiting in the link's queue whose header ``which`` accepts
        out of it, unsent and not counted as dropped, in order: ``(frame, payload, tag)`` each, for
        a sender that sends them elsewhere now. What the cork, the transport or the kernel took has
        left for good."""
        taken, kept = [], collections.deque()
        for entry in self._queue:
            if entry[4] and which(entry[1]):
                taken.append((entry[1], entry[2], entry[3]))
                self._queued_bytes -= len(entry[1]) + len(entry[2])
            else:
                kept.append(entry)
        self._queue = kept
        return taken

    def _droppable_bytes(self) -> int:
        return sum(len(f) + len(p) for _t, f, p, _tag, d in self._queue if d)

    def _drop(self, entry: tuple, expired: bool) -> None:
        """An offered frame leaves the queue unsent (the caller takes it out of the deque)."""
        self._queued_bytes -= len(entry[1]) + len(entry[2])
        self.dropped += 1
        self.expired += expired
        if self.on_drop is not None:
            try:
                self.on_drop(entry[3])
            except Exception as e:
                log.error("on_drop handler failed", link=self.name, exc_info=e)

    def _flush(self) -> None:
        """Move queued frames to the transport, in order, in one ``writelines``, while it is below its
        high-water mark; offered frames past ``max_delay`` are dropped on the way."""
        t, q = self.transport, self._queue
        if not q or self.closed.is_set() or t.is_closing():
            return
        now = self._loop.time()
        self.uncork()                     # what the cork holds was written before the queue's frames
        # until the queue is empty or the transport is above its mark (then its resume_writing calls
        # again): a batch the socket takes at once leaves the transport below it, with no such call
        while q and t.get_write_buffer_size() <= self._high:
            batch: list[bytes | memoryview] = []
            size = t.get_write_buffer_size()
            while q and size <= self._high:
                entry = q.popleft()
                if entry[4] and self.max_delay is not None and now - entry[0] > self.max_delay:
                    self._drop(entry, expired=True)
                    continue
                n = len(entry[1]) + len(entry[2])
                self._queued_bytes -= n
                size += n
                batch.append(entry[1])
                if entry[2]:
                    batch.append(entry[2])
            if batch:
                t.writelines(batch)       # one system call for what the link held

    @property
    def waiting(self) -> int:
        """Bytes written and not yet taken by the socket: in the transport's buffer and in the cork."""
        return self.transport.get_write_buffer_size() + self._cork_bytes

    def _write(self, frame: bytes, payload: bytes | memoryview) -> None:
        """One frame into the cork, which goes out at the end of the loop pass (module doc). A small
        payload is joined to its header (a copy of at most :data:`JOIN_MAX` bytes costs less than a
        second ``write``); a large one follows it unjoined, uncopied, after what the cork holds."""
        if len(payload) > JOIN_MAX:
            self.uncork()
            self.transport.write(frame)
            self.transport.write(payload)
            return
        data = frame + payload if payload else frame
        if not self._pass_open:
            self._pass_open = True
            self._loop.call_soon(self._end_pass)
        self._cork.append(data)
        self._cork_bytes += len(data)
        if self._cork_bytes >= CORK_MAX:
            self.uncork()

    def uncork(self) -> None:
        """Write what the cork holds now, in one ``writelines`` (it is done at the end of each loop
        pass by itself)."""
        if self._cork:
            cork, self._cork, self._cork_bytes = self._cork, [], 0
            if not self.transport.is_closing():
                self.transport.writelines(cork)

    def _end_pass(self) -> None:
        self._pass_open = False
        self.uncork()
        if self._queue:                   # frames queued behind the cork's: they follow while there is room
            self._flush()

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
        self.uncork()                     # written before the close: the transport sends them first
        while self._queue:                # what waited for a peer that is gone
            entry = self._queue.popleft()
            if entry[4]:
                self._drop(entry, expired=False)
        self._queued_bytes = 0
        try:
            self.writer.close()
        except (RuntimeError, OSError):     # the loop is closing
            pass
        if self.on_close is not None:
            try:
                self.on_close(self)
            except Exception as e:
                log.error("on_close handler failed", link=self.name, exc_info=e)


class _Receiver(asyncio.BufferedProtocol):
    """A started :class:`FramedLink`'s protocol (asyncio ``BufferedProtocol``): the transport
    receives into :meth:`rce.transport.framing.FrameDecoder.get_buffer`, a large frame straight into its
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
        self.link._flush()              # may pause the stream again: after its resume, never before


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


def settle_reply(calls: PendingCalls, frame: framing.DataFrame) -> bool:
    """Complete call ``f.call_id`` of ``calls`` from a ``SRV_RESP`` (result: the response bytes)
    or ``SRV_ERR`` frame (error: :class:`RequestError` with the remote reason). False when no
    such call waits (late, or unknown)."""
    if frame.op == framing.SRV_RESP:
        return calls.settle(frame.call_id, bytes(frame.payload))
    return calls.fail(frame.call_id, RequestError(bytes(frame.payload).decode(errors="replace")))


def nodelay(writer: asyncio.StreamWriter, *, data: bool = False) -> None:
    """Turn Nagle's algorithm off on a TCP stream (small frames go at once); no-op otherwise.
    ``data``: a data link's, whose kernel send queue also keeps at most :data:`NOTSENT_LOWAT`
    bytes not yet sent (:func:`data_socket`)."""
    sock = writer.get_extra_info("socket")
    if sock is not None:
        (data_socket if data else _nodelay)(sock)


def _nodelay(sock: socket.socket) -> None:
    if sock.family in (socket.AF_INET, socket.AF_INET6):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


def data_socket(sock: socket.socket) -> None:
    """A data link's TCP socket: no Nagle, and at most :data:`NOTSENT_LOWAT` bytes waiting unsent
    in the kernel (``TCP_NOTSENT_LOWAT``, tcp(7)). Without that bound Linux keeps megabytes
    (``tcp_wmem``) for a peer that is not reading, out of the link's reach: with it the rest
    waits in the link's queue, where the oldest messages give way to the newest (module doc).
    A backed-up :class:`FramedLink` made with ``data=True`` lowers the bound to its measured rate.
    No-op for other sockets."""
    _nodelay(sock)
    if sock.family in (socket.AF_INET, socket.AF_INET6) and TCP_NOTSENT_LOWAT is not None:
        sock.setsockopt(socket.IPPROTO_TCP, TCP_NOTSENT_LOWAT, NOTSENT_LOWAT)
