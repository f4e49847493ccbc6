"""A robot namespace: the websocket shell of one robot's session.

The rules live in :class:`rce.protocol.session.RobotSession` (frames, binary parts,
validation, ordering, the bounded outbox, error accounting, resume); this shell moves frames
between a websocket and the session and does what the session's events ask: a request goes
to the master (one at a time), a DM to its interface, a service call runs in a task. Every
task is kept (:class:`rce.plumbing.tasks.Tasks`).

A session may outlive its link (docs/INTERNALS.md "Session resume"): :meth:`RobotNamespace.serve`
serves one link. When the link of a robot that opted in is lost, the namespace keeps its
interfaces, connections, requests and calls, detached, for ``grace`` s; what the cloud sends
the robot meanwhile is kept by the session. A resume serves the next link. The session ends
(``on_gone``: the endpoint forgets it and tells the master) when the grace passes, when the
robot closes its link itself, when a robot that did not opt in loses its link, or on
:meth:`RobotNamespace.close`.
"""
from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import Any

from websockets.exceptions import ConnectionClosed

from rce.contract import master as to_master
from rce.plumbing.errors import ProtocolError, RCEError
from rce.plumbing.log import get_logger
from rce.messages.forms import JsonForms
from rce.protocol.limits import LOG_BURST, LOG_RATE, TokenBucket, truncate
from rce.protocol.events import (CaughtUp, CloseLink, Deliver, Lagging, RequestReady, RobotEvent, ServiceCall,
                                 unhandled)
from rce.protocol.schema import RequestData
from rce.protocol.session import RobotSession
from rce.transport.masterlink import MasterLink
from rce.plumbing.tasks import Tasks
from rce_robot.interfaces import RobotInterface
from rce_robot import ws_link
from rce.interfaces.lanes import BULK_SIZE, Lane
from rce.interfaces.pacer import Pacer
from rce.transport import lane_socket
from rce.transport.lane_socket import PacedLink, fragments, socket_of
from rce_robot.parse_pool import ParsePool

log = get_logger("rce.robot")

# s a robot's request (CC, DC, CN, CX) waits for the master: creating a container (an environment
# process, its sandbox, its nodes) can take tens of seconds on a loaded host
REQUEST_TIMEOUT = 120.0
# s between two expiry checks at most (half the expiry when that is shorter)
EXPIRY_CHECK = 5.0
# s between two ticks of a resumable session at most, as a fraction of its ack delay: its AKs go out on time
ACK_TICK_FRACTION = 0.5
CLOSE_POLICY = 1008       # websocket close code when the cloud ends a session (policy violation)
CLOSE_REASON_MAX = 120    # chars of a close reason (a close frame holds 123 bytes)
CLEAN_CLOSE = (1000, 1001)  # close codes of a robot that ends its session itself (normal, going away)


LAG_LOG = TokenBucket(LOG_RATE, LOG_BURST)     # "lags behind" warnings of all this endpoint's robots

class RobotNamespace:
    """Session of robot ``robot`` of user ``user``; ``master``: the control link its requests go
    through; ``grace``: s a resumable session stays detached after its link is lost;
    ``on_gone(namespace)``: called once when the session has ended (interfaces stopped);
    ``parser``: the endpoint's pool that parses big text frames off the loop (None: all on it).
    Its log lines about the robot's errors are cut short and come at most :data:`LOG_RATE` per s
    (:data:`LOG_BURST` at once; the next line counts those left out).
    Implements :class:`rce_robot.interfaces.RobotLink`."""

    def __init__(self, user: str, robot: str, master: MasterLink, session: RobotSession, *,
                 on_gone: Callable[["RobotNamespace"], Awaitable[None]], grace: float | None = None,
                 parser: ParsePool | None = None):
        self.user, self.robot, self.master, self.session = user, robot, master, session
        self.parser = parser
        self._log_bucket = TokenBucket(LOG_RATE, LOG_BURST)
        self.log_suppressed = 0                             # ER log lines left out (rate limit)
        self.grace = session.grace if grace is None else grace
        self.interfaces: dict[str, RobotInterface] = {}
        self.forms = JsonForms(learn=True)   # the JSON forms the robot gets back (docs/INTERNALS.md)
        self.tasks = Tasks(f"robot {user}/{robot}")        # the session's: requests, calls, the grace timer
        self.ws: Any = None                                 # the link being served; None while detached
        self.login: str | None = None                       # the endpoint's name of the login that opened it
        self.ended = False
        self.detached_since: float | None = None            # monotonic s
        self._on_gone = on_gone
        self._gone = False
        self._grace_timer: asyncio.Task | None = None
        self._wake = asyncio.Event()
        self.battery: float | None = None                   # its charge (%), from its BatteryState messages
        self.battery_told: float | None = None              # the charge last told to the master
        self.bulk_ws: Any = None                            # the bulk link, while one has joined (docs/lanes.md)
        self._bulk_wake = asyncio.Event()

    @property
    def resumable(self) -> bool:
        """Did the robot opt in to resume (its session outlives a lost link)?"""
        return self.session.outgoing is not None

    @property
    def detached(self) -> bool:
        """Is the session kept without a link, waiting for a resume?"""
        return self.ws is None and not self.ended and self.detached_since is not None

    # -- the interface table -------------------------------------------------------------------------
    def add_interface(self, iface: RobotInterface) -> None:
        """Robot-side interface ``iface`` now exists (the master's ``add_interface``)."""
        self.session.add_interface(iface.itag, iface.itype, iface.cls, iface.lane)
        self.interfaces[iface.itag] = iface

    def remove_interface(self, iface: RobotInterface) -> None:
        if self.interfaces.get(iface.itag) is iface:
            del self.interfaces[iface.itag]
            self.session.remove_interface(iface.itag)

    # -- to the robot (RobotLink) ----------------------------------------------------------------------
    def send_dm(self, itag: str, cls: str, msg_id: Any, msg: Any, data: bool = False) -> bool:
        """Queue a DM to the robot; ``data=True`` marks droppable topic data (the newest are kept:
        :meth:`RobotSession.send_dm`)."""
        now, ws = time.monotonic(), self.ws
        if data and ws is not None and ws_link.writable(ws):     # nothing waits: its frames go out now
            frames = self.session.data_now(itag, cls, msg_id, msg, now)
            if frames is not None:
                ws_link.write(ws, frames)
                return True
            ok = True                                             # queued behind what waits
        else:
            ok = self.session.send_dm(itag, cls, msg_id, msg, data, now)
        self._pump()
        return ok

    def send_status(self, data: dict) -> None:
        self.session.send_status(data)
        self._pump()

    def battery_seen(self, percent: float) -> None:
        self.battery = percent

    def send_error(self, reason: str) -> None:
        """Queue an ER (:meth:`RobotSession.send_error`: cut short, rate-limited) and log it (rate-limited)."""
        if self.session.send_error(reason):
            self._log_error(reason)
        self._pump()

    def _log_error(self, reason: str) -> None:
        if not self._log_bucket.take(time.monotonic()):
            self.log_suppressed += 1
            return
        extra = {"left_out": self.log_suppressed} if self.log_suppressed else {}
        self.log_suppressed = 0
        log.info("ER to robot", user=self.user, robot=self.robot, reason=truncate(reason), **extra)

    def _flush(self) -> None:
        """Write what waits to the link now, one message at a time, each in one corked write
        (:func:`rce_robot.ws_link.write`), while the link takes it; when it does not (its buffer is
        full, or it is closing) the writer task goes on."""
        ws, now = self.ws, time.monotonic()
        while ws_link.writable(ws):
            frames = self.session.data_to_send(1, now)
            if not frames:          # nothing waits
                return
            ws_link.write(ws, frames)
        if self.session.outbox:
            self._wake.set()

    async def _writer(self, ws: Any) -> None:
        """What :meth:`_flush` cannot write now: after the link drains, or through ``ws.send`` (which
        raises ConnectionClosed on a closed link)."""
        try:
            while True:
                await self._wake.wait()
                self._wake.clear()
                # one message at a time, and only while this link is the session's: the outbox stays the bound
                while self.ws is ws and self.session.outbox:
                    if ws_link.writable(ws):
                        ws_link.write(ws, self.session.data_to_send(1, time.monotonic()))
                    elif ws_link.paused(ws):
                        await ws.drain()
                    else:
                        for f in self.session.data_to_send(1, time.monotonic()):
                            await ws.send(f)
        except (ConnectionClosed, OSError):   # the link is lost (drain raises the transport's error): the reader
            pass                              # sees it too; what was taken is kept for a resume

    # -- a link ----------------------------------------------------------------------------------------
    async def serve(self, ws: Any, ack: int | None = None) -> None:
        """Serve the session over websocket ``ws`` until it closes; ``ack``: a resume whose robot took
        every message up to ``ack`` (:meth:`RobotSession.attach`; a link still held is closed). When
        the link is lost the session is detached (resumable) or ends."""
        if ack is not None:
            try:
                self.session.attach(ack)
            except ProtocolError as e:
                await ws.close(CLOSE_POLICY, e.message[:CLOSE_REASON_MAX])
                return
        old, self.ws, self.detached_since = self.ws, ws, None
        if self.bulk_ws is not None:                # a bulk link is there: this one is the control lane
            lane_socket.mark(socket_of(ws), Lane.CONTROL)
        if self._grace_timer is not None:
            self._grace_timer.cancel()
            self._grace_timer = None
        if old is not None:
            self.tasks.spawn(old.close(CLOSE_POLICY, "replaced by a resumed link"), name="close-old-link")
        link = Tasks(f"robot {self.user}/{self.robot} link")
        link.spawn(self._writer(ws), name="writer")
        link.spawn(self._ticker(), name="ticker")
        self._pump()
        joined = False      # the last frame's message waits for its binary parts: they come in the same turn
        try:
            async for frame in ws:
                if self.ws is not ws:       # a resume took the session over: the robot resends what this link
                    break                   # still brings (the resume's ack says what was taken)
                now = time.monotonic()
                session = self.session
                session.backlog(ws_link.behind(ws), now)
                waiting = session.assembler.pending
                if self._receive(frame, now):       # a big text frame: parsed in the pool first
                    await self._receive_big(frame)
                self._pump()
                # a message and the binary part that follows it are one turn (at most two frames, so a
                # burst is still served among the other robots' frames)
                joined = not joined and session.assembler.pending > waiting
                if not joined:
                    await ws_link.take_turn(ws)
        except ConnectionClosed:
            pass
        finally:
            await link.cancel_all()
        if self.ws is not ws:           # a resume took the session over
            return
        self.ws = None
        if self.ended or not self.resumable or ws_link.closed_by_peer(ws, CLEAN_CLOSE):
            await self._end()
            return
        self.session.detach()
        self.detached_since = time.monotonic()
        log.info("robot link lost; session kept", user=self.user, robot=self.robot, grace=self.grace,
                 code=ws.close_code)
        self._grace_timer = self.tasks.spawn(self._expire(), name="grace")

    def _receive(self, frame: str | bytes, now: float) -> bool:
        """One frame into the session at ``now`` (s), inline; True (and nothing done) for a big text frame,
        which :meth:`_receive_big` takes."""
        if isinstance(frame, str):
            if self.parser is not None and self.parser.takes(frame) and not self.session.too_big(frame):
                return True
            self.session.receive_text(frame, now)
        else:
            self.session.receive_binary(frame, now)
        return False

    async def _receive_big(self, frame: str) -> None:
        """A big text frame, parsed in the pool first (this robot's next frames wait for it, other
        robots' do not)."""
        self.session.receive_parsed(await self.parser.parse(frame), time.monotonic())
        await asyncio.sleep(0)    # other robots' frames between its parse and its conversion

    async def _expire(self) -> None:
        await asyncio.sleep(self.grace)      # a timer: the grace period
        log.info("robot did not resume within the grace period", user=self.user, robot=self.robot, grace=self.grace)
        await self._end()

    async def _ticker(self) -> None:
        period = min(EXPIRY_CHECK, self.session.assembler.expiry / 2)
        if self.session.incoming is not None:
            period = min(period, self.session.incoming.ack_delay * ACK_TICK_FRACTION)
        while True:
            await asyncio.sleep(period)   # a timer
            self.session.tick(time.monotonic())
            self._pump()

    def _pump(self) -> None:
        """Do what the session's events ask; wake the writers when frames wait."""
        while events := self.session.events_received():
            for ev in events:
                self._on_event(ev)
        if self.ws is not None and self.session.outbox:
            self._flush()
        if self.bulk_ws is not None and self.session.bulk_outbox:
            self._bulk_wake.set()

    # -- the bulk link (docs/lanes.md) -------------------------------------------------------------------
    async def serve_bulk(self, ws: Any, pacer: Pacer | None = None) -> None:
        """Serve a bulk link that joined the session (``?session=TOKEN&lane=bulk``) until it closes: the
        bulk lane's topic DMs go on it, unnumbered, in frames of at most
        :data:`~rce.interfaces.lanes.BULK_SIZE` bytes, paced by ``pacer`` (None: as fast as the link takes
        them); the robot's DMs on it come in. It is marked DSCP CS1 and the session's own link becomes the
        control lane (:func:`rce.transport.lane_socket.mark`). A bulk link already there is closed. When it
        closes, the bulk lane goes on the session's link again. The pacer's rate (set, or estimated from the
        socket: :class:`~rce.transport.lane_socket.PacedLink`) is in the session's lane stats."""
        old, self.bulk_ws = self.bulk_ws, ws
        if old is not None:
            self.tasks.spawn(old.close(CLOSE_POLICY, "replaced by a new bulk link"), name="close-old-bulk")
        self.session.attach_bulk(pacer)
        lane_socket.mark(socket_of(ws), Lane.BULK)
        if self.ws is not None:
            lane_socket.mark(socket_of(self.ws), Lane.CONTROL)
        link = Tasks(f"robot {self.user}/{self.robot} bulk link")
        link.spawn(self._bulk_writer(ws, PacedLink(pacer, socket_of(ws)) if pacer is not None else None),
                   name="bulk-writer")
        self._pump()
        try:
            async for frame in ws:
                self.session.receive_bulk(frame, time.monotonic())
                self._pump()
        except ConnectionClosed:
            pass
        finally:
            await link.cancel_all()
        if self.bulk_ws is ws:
            self.bulk_ws = None
            self.session.detach_bulk()
            log.info("bulk link closed; the bulk lane goes on the session's link", user=self.user, robot=self.robot,
                     code=ws.close_code)
            self._pump()

    async def _bulk_writer(self, ws: Any, paced: PacedLink | None) -> None:
        """Write the bulk lane's DMs to ``ws``, one whole message at a time, each frame in fragments of
        at most :data:`BULK_SIZE` paced by ``paced`` (None: as fast as the link takes them)."""
        try:
            while True:
                await self._bulk_wake.wait()
                self._bulk_wake.clear()
                while self.bulk_ws is ws and (frames := self.session.bulk_to_send(time.monotonic())) is not None:
                    for f in frames:
                        if paced is not None:
                            await ws.send(paced.fragments(f))
                        else:
                            await ws.send(fragments(f) if len(f) > BULK_SIZE else f)
                    self.session.out.queue.sent(Lane.BULK, sum(len(f) for f in frames))
        except (ConnectionClosed, OSError):   # the reader sees it too; bulk data keeps its newest, nothing is resent
            pass

    def _on_event(self, ev: RobotEvent) -> None:
        match ev:
            case RequestReady(type=type_, data=data):
                self.tasks.spawn(self._request(type_, data), name="request")
            case Deliver(itag=itag, data=data):
                iface = self.interfaces.get(itag)
                try:
                    if iface is None:
                        raise RCEError(f"DM: no interface {itag!r} on robot {self.robot!r}")
                    iface.from_robot(data)
                except RCEError as e:
                    self.send_error(e.message)
            case ServiceCall(itag=itag, data=data):
                self.tasks.spawn(self._call(itag, data), name="call")
            case Lagging(behind_s=behind_s):
                if LAG_LOG.take(time.monotonic()):     # one endpoint, many robots: a few lines a second at most
                    log.warning("the endpoint lags behind the robot: its topic messages are shed until it catches "
                                "up", user=self.user, robot=self.robot, behind_s=behind_s)
            case CaughtUp(shed=shed):
                log.debug("the endpoint caught up with the robot", user=self.user, robot=self.robot, shed=shed)
            case CloseLink(reason=reason):
                log.warning("closing a robot that does not read", user=self.user, robot=self.robot, reason=reason)
                self.tasks.spawn(self.close(reason), name="close")
            case _:
                unhandled(ev)

    async def _request(self, type_: str, data: RequestData) -> None:
        try:
            await self.master.ask(to_master.RobotRequest(user=self.user, robot=self.robot, type=type_,
                                                         data=data.wire()), REQUEST_TIMEOUT)
        except RCEError as e:
            self.session.request_done(e.message)
        else:
            self.session.request_done()
        self._pump()

    async def _call(self, itag: str, data: dict) -> None:
        iface = self.interfaces.get(itag)
        try:
            if iface is None:
                raise RCEError(f"interface {itag!r} was removed")
            resp = await iface.call_from_robot(data)
        except RCEError as e:
            self.session.fail_call(data, e.message)
        else:
            self.session.answer_call(data, resp)
        self._pump()

    # -- the end ---------------------------------------------------------------------------------------
    async def close(self, reason: str) -> None:
        """End the session: the robot sees a close with ``reason`` (code 1008: do not resume); a
        detached session ends at once."""
        self.ended = True
        if self.ws is not None:
            await self.ws.close(CLOSE_POLICY, reason[:CLOSE_REASON_MAX])      # serve() ends it
        else:
            await self._end()

    async def _end(self) -> None:
        """Stop the session's tasks and interfaces, then ``on_gone`` (once)."""
        if self._gone:
            return
        self._gone = self.ended = True
        self.detached_since = None
        await self.tasks.cancel_all()
        bulk, self.bulk_ws = self.bulk_ws, None
        if bulk is not None:
            await bulk.close(CLOSE_POLICY, "the session ended")
        self.session.end()
        for iface in list(self.interfaces.values()):
            await iface.stop()
        self.interfaces.clear()
        await self._on_gone(self)

    def stats(self) -> dict:
        """This robot's counters (:meth:`RobotSession.stats`) with its user and robot ID."""
        return {"user": self.user, "robot": self.robot, "detached": self.detached, **self.session.stats()}

