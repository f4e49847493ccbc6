"""The rules of a robot session, sans I/O, in the manner of the ``websockets`` library's
``Protocol``: frames in (:meth:`receive_text`, :meth:`receive_binary`), time in
(:meth:`tick`), and out come the frames to send (:meth:`data_to_send`) and typed events
for the application (:meth:`events_received`; :mod:`rce.protocol.events`). No sockets and no tasks: the robot endpoint
(:mod:`rce_robot.namespace`) and the client library (:mod:`rce_client.connection`) are
shells that move frames and run what the events ask for.

- :class:`RobotSession` is the cloud side of one connected robot: binary parts and expiry,
  the one schema (:func:`rce.protocol.schema.validate`), requests to the master one at a
  time and in order, the DM ordering rule, the bounded outbox, error accounting.
- :class:`ClientSession` is the robot side: pending calls and barriers (one
  :class:`~rce.pending.PendingCalls` table keyed by msgID or token), the interface status
  table, ER attribution. Its rules are those of ``tests/vectors/README.md``, which the
  browser client (``rce.js``) follows too; ``tests/vectors/session.json`` checks both.

Either side may opt in to session resume (``resume=True``; docs/INTERNALS.md "Session
resume"): messages are numbered and kept until acked (:mod:`rce.protocol.resume`), a lost link
detaches the session (:meth:`RobotSession.detach`, :meth:`ClientSession.detach`) and a new one
resumes it (:meth:`RobotSession.attach`, :meth:`ClientSession.attach`). Without it nothing
changes: no ``seq``, no ``AK``, no ``ST session``.
"""
from __future__ import annotations

import json
import uuid
from dataclasses import dataclass
from typing import Any

from rce.errors import ProtocolError, RequestError, Unavailable
from rce.messages import takes_binary_message
from rce.pending import PendingCalls
from rce.protocol.events import (BarrierFailed, BarrierPassed, CallFailed, CaughtUp, CloseLink, Deliver, Detached,
                                 Dropped, ErrorReceived, Event, InterfaceChanged, Lagging, MessageReceived,
                                 RequestReady, ResponseReceived, ServiceCall, SessionStatus, StatusReceived)
from rce.protocol.frames import (CX, DEFAULT_EXPIRY, DEFAULT_MAX_PENDING_BYTES, DEFAULT_MAX_PENDING_PARTS, DM, ER,
                                 ST, Assembler, encode)
from rce.protocol.holdback import HoldBack
from rce.protocol.limits import DEFAULT_MAX_LAG, ER_BURST, ER_RATE, LagGate, PartBudget
from rce.protocol.robot_outbox import RobotOutbox, dm
from rce.protocol.resume import (ACK_DELAY, ACK_EVERY, AK, DEFAULT_GRACE, DEFAULT_RESUME_BUFFER, DEFAULT_RESUME_BYTES,
                                 SESSION_TOPIC, Frame, Incoming, Outgoing, ack_frame, is_session_status, new_token,
                                 read_ack, read_seq)
from rce.protocol.schema import split_interface_type, validate

DEFAULT_QUEUE_SIZE = 1000                   # messages per robot in each bounded queue (like a ROS queue_size)
DEFAULT_MAX_MESSAGE = 32 * 1024 * 1024      # bytes (chars for text) of the largest frame a robot endpoint takes
LAG_TOPIC = "lag"                           # ST topic: the endpoint sheds the robot's topic messages, or caught up
BARRIER_PREFIX = "rcesync"                  # barrier tokens: interfaces named so cannot exist


class _SessionCore:
    """What both sides share: binary parts and expiry, events. A subclass takes complete messages
    (``_on_message``) and says what becomes of bad input (``_bad_input``: an ER, or a drop)."""

    max_message: int | None = None      # bytes (text: chars) of the largest frame taken; None: any

    def __init__(self, expiry: float, max_pending_bytes: int, resume: bool, resume_buffer: int, resume_bytes: int,
                 ack_every: int, ack_delay: float, max_pending_parts: int = DEFAULT_MAX_PENDING_PARTS,
                 budget: PartBudget | None = None):
        self.assembler = Assembler(expiry=expiry, max_pending_bytes=max_pending_bytes,
                                   max_pending_parts=max_pending_parts, budget=budget)
        self._events: list[Event] = []
        self._now = 0.0                                            # s, the last time given
        # with resume: what this side sent, numbered and kept until acked; what it took from the peer
        self.outgoing = Outgoing(resume_buffer, resume_bytes) if resume else None
        self.incoming = Incoming(ack_every, ack_delay) if resume else None

    def _emit(self, event: Event) -> None:
        self._events.append(event)

    def events_received(self) -> list[Event]:
        """The events produced since the last call, in order."""
        events, self._events = self._events, []
        return events

    def receive_text(self, text: str, now: float) -> None:
        """A text frame from the peer, at time ``now`` (s)."""
        self._receive(text, now)

    def receive_binary(self, data: bytes, now: float) -> None:
        """A binary frame ``id || bytes`` from the peer, at time ``now`` (s)."""
        self._receive(data, now)

    def receive_parsed(self, parsed: tuple[dict, list[str]] | ProtocolError, now: float) -> None:
        """A text frame from the peer that the shell parsed itself with :func:`~rce.protocol.frames.parse_frame`
        (a big one, in a worker process), at time ``now`` (s): its message and binary part ids, or the error
        that parsing raised."""
        self._now = now
        if isinstance(parsed, ProtocolError):
            self._bad_input(parsed.message)
            return
        self._take(lambda: self.assembler.feed_parsed(*parsed, now))

    def too_big(self, frame: str | bytes) -> bool:
        """Is ``frame`` longer than :attr:`max_message` (it is refused, whoever parses it)?"""
        return self.max_message is not None and len(frame) > self.max_message

    def tick(self, now: float) -> None:
        """Time is ``now`` (s): incomplete messages and orphan parts past their expiry are bad input;
        with resume on a live link, an AK that is due goes out."""
        self._now = now
        for reason in self.assembler.expire(now):
            self._bad_input(reason)
        if self.incoming is not None and self._linked():
            self._ack_if_due()

    def _receive(self, frame: str | bytes, now: float) -> None:
        self._now = now
        if self.too_big(frame):
            kind = "text" if isinstance(frame, str) else "binary"
            self._bad_input(f"{kind} frame of {len(frame)} bytes exceeds the limit of {self.max_message} bytes; "
                            f"dropped")
            return
        self._take(lambda: self.assembler.feed_text(frame, now) if isinstance(frame, str)
                   else self.assembler.feed_binary(frame, now))

    def _take(self, feed) -> None:
        """Feed the assembler (``feed()``); its complete messages go on, its refusal is bad input."""
        try:
            done = feed()
        except ProtocolError as e:
            self._bad_input(e.message)
            return
        for msg in done:
            self._on_message(msg)

    def _on_message(self, msg: dict) -> None:
        raise NotImplementedError

    def _bad_input(self, reason: str) -> None:
        raise NotImplementedError

    # -- resume (both sides) ------------------------------------------------------------------------
    def _linked(self) -> bool:
        """Is the session on a live link (with resume: AKs can go out)?"""
        raise NotImplementedError

    def _send_ack(self, n: int) -> None:
        raise NotImplementedError

    def _take_numbered(self, msg: dict) -> bool:
        """Resume's rules for a complete message from the peer: an AK acks what this side kept; a
        numbered message is taken once (a resent duplicate is dropped). True: the application's."""
        if msg.get("type") == AK:
            try:
                self.outgoing.ack(read_ack(msg.get("data")))
            except ProtocolError as e:
                self._bad_input(e.message)
            return False
        try:
            seq = read_seq(msg)
        except ProtocolError as e:
            self._bad_input(e.message)
            return False
        if not self.incoming.take(seq, self._now):
            return False
        self._ack_if_due()
        return True

    def _ack_if_due(self) -> None:
        n = self.incoming.ack_due(self._now)
        if n is not None:
            self._send_ack(n)


# -- the cloud side -------------------------------------------------------------------------------
class RobotSession(_SessionCore):
    """The cloud side of robot ``robot``'s session.

    ``max_message``: largest frame taken (bytes; text: chars), larger ones get an ER;
    ``queue_size``: bound of each queue (data DMs waiting to go out, requests waiting for
    the master, DMs waiting for earlier requests, service calls in flight), beyond which
    messages are dropped, counted, and (inbound ones) refused with an ER; ``expiry``: s
    an incomplete message waits for its binary parts.

    Every bad input gets an ER naming what was wrong; the session goes on. ERs are cut short and
    those for bad input rate-limited (``er_rate`` per s, ``er_burst`` at once), dropped and counted past
    it (:class:`~rce.protocol.error_limits.ErrorLimits`). ``max_pending_parts``: binary parts waiting for
    their message; ``budget``: the endpoint's :class:`~rce.protocol.limits.PartBudget`, shared by its
    sessions (:meth:`end` gives back).

    ``resume``: the robot opted in (docs/INTERNALS.md "Session resume"): the session opens with
    ``ST {"topic": "session", "status": "started", "session": token, "grace": grace}`` (``token``:
    default a fresh :func:`~rce.protocol.resume.new_token`; ``grace``: s the endpoint keeps it
    detached), numbers what it sends and keeps it until acked (``resume_buffer`` messages,
    ``resume_bytes`` bytes; past them the oldest is forgotten, counted), takes each numbered
    message once and acks every ``ack_every`` messages or ``ack_delay`` s.

    ``max_lag``: s the endpoint may stay behind this robot (received frames waiting for the
    session, as the shell tells with :meth:`backlog`) before it sheds the robot's topic messages:
    while it has been behind for longer, a DM for a topic interface is dropped and counted
    (``shed``) instead of delivered, until the shell has caught up, unless that interface has
    delivered nothing for ``max_lag`` s (so a stream still reaches the cloud at least that often
    while the endpoint stays behind). So an overloaded endpoint hands the cloud the robot's
    newest messages, not ever older ones, as a ROS subscriber's ``queue_size`` drops the oldest.
    Requests, service calls and answers are never shed. None: never shed. The robot is told:
    ``ST {"topic": "lag", "status": "shedding", "behind_s", "max_lag_s"}`` when shedding starts,
    ``ST {"topic": "lag", "status": "caught_up", "shed": n}`` when it ends.

    The other way, to a robot that does not keep up, each interface's topic data keeps its newest
    messages, as a ROS publisher's queue does (:class:`~rce.protocol.outbox.Outbox`; ``max_lag`` ages
    them too); drops are counted in ``dropped`` (for their age also in ``expired``).

    The jobs live in their modules and this class composes them: requests and the DMs held back for
    them (:class:`~rce.protocol.holdback.HoldBack`), what goes to the robot (outbox, ERs, resume's
    numbering: :class:`~rce.protocol.robot_outbox.RobotOutbox`), lag shedding
    (:class:`~rce.protocol.limits.LagGate`), resume (:mod:`rce.protocol.resume`)."""

    def __init__(self, robot: str, *, max_message: int = DEFAULT_MAX_MESSAGE, queue_size: int = DEFAULT_QUEUE_SIZE,
                 expiry: float = DEFAULT_EXPIRY, max_pending_bytes: int = DEFAULT_MAX_PENDING_BYTES,
                 max_pending_parts: int = DEFAULT_MAX_PENDING_PARTS, budget: PartBudget | None = None,
                 resume: bool = False, token: str | None = None, grace: float = DEFAULT_GRACE,
                 resume_buffer: int = DEFAULT_RESUME_BUFFER, resume_bytes: int = DEFAULT_RESUME_BYTES,
                 ack_every: int = ACK_EVERY, ack_delay: float = ACK_DELAY, er_rate: float = ER_RATE,
                 er_burst: int = ER_BURST, max_lag: float | None = DEFAULT_MAX_LAG):
        super().__init__(expiry, max_pending_bytes, resume, resume_buffer, resume_bytes, ack_every, ack_delay,
                         max_pending_parts, budget)
        # what waits for the robot (ValueError for a queue_size < 1)
        self.out = RobotOutbox(robot, queue_size, max_lag, er_rate, er_burst, self.outgoing,
                               lambda reason: self._emit(CloseLink(reason)))
        self.robot, self.max_message, self.queue_size = robot, max_message, queue_size
        self.lag = LagGate(max_lag)                               # sheds topic DMs while the shell lags
        self.requests = HoldBack(queue_size)                      # requests to the master, DMs held for them
        self.interfaces: dict[str, tuple[str, str, str]] = {}     # iTag -> (kind, side, cls)
        self.calls = 0                                            # service calls in flight
        self.msgs_in = self.dropped_in = 0
        self.token = (token or new_token()) if resume else None
        self.grace = grace
        self.resumes = self.resume_lost = 0
        if resume:
            self.out.link_message(ST, {"topic": SESSION_TOPIC, "status": "started", "session": self.token,
                                       "grace": grace})

    @property
    def attached(self) -> bool:
        """Is the robot on a live link (always, without resume)?"""
        return self.out.attached

    @property
    def dropped(self) -> int:
        """Data DMs to the robot dropped (the queue bound, or their age; :class:`~rce.protocol.outbox.Outbox`)."""
        return self.out.queue.dropped

    @property
    def expired(self) -> int:
        """Data DMs to the robot dropped for their age (``max_lag``)."""
        return self.out.queue.expired

    @property
    def out_data(self) -> int:
        """Data DMs waiting to go to the robot."""
        return self.out.queue.data

    # -- frames in --------------------------------------------------------------------------------
    def _bad_input(self, reason: str) -> None:
        self.send_error(reason)

    def _on_message(self, msg: dict) -> None:
        if self.incoming is not None and not self._take_numbered(msg):
            return
        self.msgs_in += 1
        try:
            t, data = validate(msg)
        except ProtocolError as e:
            self.send_error(e.message)
            return
        if t == DM:
            self._on_dm(data)
        elif self.requests.full:
            self.dropped_in += 1
            self.send_error(f"{t}: refused: {len(self.requests.requests)} requests already wait for the master")
        else:
            self.requests.add(t, data)
            self._next_request()

    def backlog(self, frames: int, now: float) -> None:
        """The shell has ``frames`` more frames (or bytes) of this robot received and not yet given
        to the session, at time ``now`` (s): 0 when it has caught up with all the robot sent so far,
        in its own buffers and the kernel's. Call it before each frame it gives (``max_lag`` above;
        :class:`~rce.protocol.limits.LagGate`)."""
        shed = self.lag.backlog(frames, now)
        if shed:
            self._emit(CaughtUp(shed))
            self.send_status({"topic": LAG_TOPIC, "status": "caught_up", "shed": shed})

    # -- requests, one at a time and in order -------------------------------------------------------
    def _next_request(self) -> None:
        nxt = self.requests.next()
        if nxt is not None:
            self._emit(RequestReady(*nxt))

    def request_done(self, error: str | None = None) -> None:
        """The master answered the request of the last :class:`~rce.protocol.events.RequestReady`;
        ``error``: its refusal. DMs that waited for it are routed, then the next request goes out.
        Raises :class:`ProtocolError` when no request is in flight."""
        type_, released = self.requests.done()
        if error is not None:
            self.send_error(f"{type_}: {error}", answer=True)
        for data in released:
            self._route(data)
        self._next_request()

    # -- DMs ----------------------------------------------------------------------------------------
    def _on_dm(self, data: dict) -> None:
        if not self.requests.must_hold(data["iTag"] in self.interfaces):
            self._route(data)
        elif not self.requests.hold(data):
            self.dropped_in += 1
            self.send_error(f"DM for interface {data['iTag']!r} dropped: {self.requests.held} messages already "
                            f"wait for earlier requests")

    def _route(self, data: dict) -> None:
        itag = data["iTag"]
        itf = self.interfaces.get(itag)
        if itf is None:
            self.send_error(f"DM: no interface {itag!r} on robot {self.robot!r}")
            return
        kind, side, cls = itf
        refusal = _refusal(itag, kind, side, cls, data)
        if refusal:
            self.send_error(refusal)
        elif kind != "ServiceProvider":
            if not self.lag.admit(itag, self._now):
                if self.lag.episode == 1:
                    behind = round(self.lag.behind(self._now), 3)
                    self._emit(Lagging(behind))
                    self.send_status({"topic": LAG_TOPIC, "status": "shedding", "behind_s": behind,
                                      "max_lag_s": self.lag.max_lag})
                return
            self._emit(Deliver(itag, data))
        elif self.calls >= self.queue_size:
            self.dropped_in += 1
            self.send_error(f"service call {data.get('msgID')!r} on {itag!r} refused: {self.calls} calls in flight")
        else:
            self.calls += 1
            self._emit(ServiceCall(itag, data))

    def answer_call(self, call: dict, msg: Any) -> None:
        """The service of a :class:`~rce.protocol.events.ServiceCall` (its ``data``: ``call``) answered
        ``msg``: the response goes to the robot with the call's msgID (never dropped)."""
        self.calls -= 1
        itag = call["iTag"]
        self.send_dm(itag, self.interfaces.get(itag, ("", "", call["type"]))[2], call.get("msgID") or "", msg)

    def fail_call(self, call: dict, reason: str) -> None:
        """The service of a :class:`~rce.protocol.events.ServiceCall` (its ``data``: ``call``) failed: an
        ER naming the call's msgID and interface."""
        self.calls -= 1
        self.send_error(f"service call {call.get('msgID')!r} on {call['iTag']!r} failed: {reason}", answer=True)

    # -- the interface table ------------------------------------------------------------------------
    def add_interface(self, itag: str, itype: str, cls: str) -> None:
        """A robot-side interface ``itag`` of type ``itype`` and class ``cls`` now exists.
        Raises as :func:`robot_interface_type`."""
        kind, side = robot_interface_type(itype)
        self.interfaces[itag] = (kind, side, cls)

    def remove_interface(self, itag: str) -> None:
        """Robot-side interface ``itag`` is gone."""
        self.interfaces.pop(itag, None)
        self.lag.forget(itag)

    # -- frames out ---------------------------------------------------------------------------------
    def send_dm(self, itag: str, cls: str, msg_id: Any, msg: Any, data: bool = False,
                now: float | None = None) -> bool:
        """Queue ``DM {iTag, type, msgID, msg}`` for the robot at time ``now`` (s; default the last
        time given). ``data=True`` marks topic data: when ``queue_size`` data DMs already wait, the
        oldest of the busiest interface is dropped (:class:`~rce.protocol.outbox.Outbox`). Returns True."""
        self.out.dm(dm(itag, cls, msg_id, msg), data, self._now if now is None else now)
        return True

    def send_status(self, data: dict) -> None:
        """Queue ``ST data`` for the robot (never dropped)."""
        self.out.control({"type": ST, "data": data})

    def send_error(self, reason: str, answer: bool = False) -> bool:
        """Queue ``ER reason`` for the robot (:class:`~rce.protocol.error_limits.ErrorLimits`: cut short,
        counted). ``answer``: it answers a request or call of the robot (not rate-limited). Returns False
        when it was dropped (rate limit, or ``queue_size`` ERs unread; counted in ``errors_dropped``)."""
        return self.out.error(reason, answer, self._now)

    def tick(self, now: float) -> None:
        """As :meth:`_SessionCore.tick`; then, when ERs were dropped and the robot reads again, an ER
        saying how many."""
        super().tick(now)
        self.out.tick(now)

    def end(self) -> None:
        """The session ended: what waited for binary parts is forgotten (its bytes go back to the budget)."""
        self.assembler.clear()

    @property
    def outbox(self) -> int:
        """Messages waiting to be sent."""
        return len(self.out)

    def data_to_send(self, max_messages: int | None = None, now: float | None = None) -> list[str | bytes]:
        """Frames of up to ``max_messages`` waiting messages (all by default), each message's JSON
        text frame followed by its binary parts; they count as sent (with resume: numbered and kept
        until acked). ``now`` (s): a data DM that has waited longer than ``max_lag`` while a newer one
        of its interface waits is dropped instead (counted in ``dropped`` and ``expired``); None: none
        is."""
        return self.out.data_to_send(max_messages, now)

    # -- resume -------------------------------------------------------------------------------------
    def _linked(self) -> bool:
        return self.attached

    def _send_ack(self, n: int) -> None:
        self.out.ack(n)

    def detach(self) -> None:
        """(resume) The robot's link is lost: what waits for it is numbered and kept, and so is what
        comes until :meth:`attach`; link-level messages are gone with the link."""
        if self.outgoing is None:
            raise ProtocolError("detach: the robot did not opt in to resume")
        self.out.detach()

    def can_resume(self, ack: int) -> bool:
        """Can a resume whose robot took every message up to ``ack`` be served?"""
        return self.outgoing is not None and 0 <= ack <= self.outgoing.last

    def attach(self, ack: int) -> None:
        """(resume) A new link resumes the session (from a detached session, or taking over a link the
        endpoint still holds); the robot took every message up to ``ack``. Queues ``ST {"topic":
        "session", "status": "resumed", "session", "grace", "ack", "dropped"}`` (``ack``: the last robot
        message taken; ``dropped``: messages to the robot the buffer lost), then the kept messages after
        ``ack``, as first numbered. Incomplete messages of the old link are dropped: the robot resends
        them whole. Raises :class:`ProtocolError` when :meth:`can_resume` is false."""
        if not self.can_resume(ack):
            raise ProtocolError(f"resume: ack {ack} is not a message sent to robot {self.robot!r} "
                                f"(the last is {self.outgoing.last if self.outgoing else 0})")
        if self.attached:
            self.detach()
        frames, lost = self.outgoing.resend_after(ack)
        self.assembler = self.assembler.fresh()
        self.incoming.reported()
        self.resumes += 1
        self.resume_lost += lost
        self.out.resume({"topic": SESSION_TOPIC, "status": "resumed", "session": self.token, "grace": self.grace,
                         "ack": self.incoming.last, "dropped": lost}, frames)

    def stats(self) -> dict:
        """Counters: messages in and out, drops out (data DMs: the oldest past the queue bound, or older
        than ``max_lag``, those also in ``expired``) and in (refused for a full queue), ERs sent and
        dropped, messages and parts waiting for binary parts and their bytes, queue depths; ``shed``:
        topic DMs from the robot dropped while the endpoint lagged (``max_lag``);
        resume: resumes, messages resent, lost at a resume (``resume_lost``), kept until acked
        (``kept``, ``kept_bytes``), forgotten past the bound (``resume_forgotten``), duplicates from the
        robot dropped."""
        out, inc = self.outgoing, self.incoming
        return {"interfaces": len(self.interfaces), "msgs_in": self.msgs_in, "msgs_out": self.out.msgs_out,
                "dropped": self.dropped, "dropped_in": self.dropped_in, "shed": self.lag.shed,
                "errors": self.out.er.sent, "errors_dropped": self.out.er.dropped,
                "pending_binary": self.assembler.pending, "pending_binary_bytes": self.assembler.pending_bytes,
                "outbox": self.outbox, "expired": self.expired, "requests_waiting": self.requests.waiting,
                "held": self.requests.held, "calls": self.calls, "resumes": self.resumes, "resent": self.out.resent,
                "resume_lost": self.resume_lost, "kept": len(out) if out else 0, "kept_bytes": out.bytes if out else 0,
                "resume_forgotten": out.forgotten if out else 0, "duplicates": inc.duplicates if inc else 0}


def robot_interface_type(itype: str) -> tuple[str, str]:
    """``(kind, side)`` of a robot-side interface type (a Converter or Forwarder). Raises
    :class:`ProtocolError` for an unknown type, :class:`RequestError` for a container-side one."""
    kind, side = split_interface_type(itype)
    if side == "Interface":
        raise RequestError(f"{itype} is a container interface, not a robot-side one")
    return kind, side


def _refusal(itag: str, kind: str, side: str, cls: str, data: dict) -> str | None:
    """Why interface ``itag`` cannot take this DM, or None."""
    if str(data["type"]).strip("/") != cls:
        return f"DM: interface {itag!r} carries {cls!r}, not {data['type']!r}"
    itype = kind + side
    if kind == "Publisher":
        return (f"{itype} {itag!r} sends messages to the robot; it does not take messages from it "
                f"(use a SubscriberConverter)")
    binary = isinstance(data.get("msg"), (bytes, bytearray))
    if side == "Converter" and binary and not takes_binary_message(cls):
        return f"{itype} {itag!r} takes JSON messages; use a {kind}Forwarder for serialized binary messages"
    if side == "Forwarder" and not binary:
        return f"{itype} {itag!r} takes the serialized message as binary part 'msg*'"
    return None


# -- the robot side -------------------------------------------------------------------------------
@dataclass
class _Waiting:
    kind: str               # "call" or "barrier"
    itag: str | None        # a call's interface
    done: bool = False


class ClientSession(_SessionCore):
    """The robot side of a session: what the cloud sends becomes events; calls and barriers wait in
    :attr:`pending` (a :class:`PendingCalls` keyed by msgID or token: the shell awaits
    ``pending.wait(key, timeout)``; a call's result is the response's ``msg``, a failure
    :class:`RequestError` (an ER) or :class:`Unavailable` (the link closed)). Opening a call
    needs a running asyncio loop (the table's futures); nothing else here does.

    ``expiry``: s an incomplete message waits for its binary parts. :attr:`interfaces`: iTag ->
    last ``iu`` status; :attr:`dropped`: malformed frames, expired parts, unexpected messages.

    ``resume``: ask for session resume (the shell adds ``resume=1`` to the connect query; docs/INTERNALS.md
    "Session resume"): messages are numbered from the first and kept until acked (``resume_buffer``
    messages, ``resume_bytes`` bytes); the first message from the cloud decides: ``ST session started``
    turns resume on (:attr:`state` ``live``, :attr:`token`, :attr:`grace`), anything else turns it off
    (a cloud that does not offer it: the 2013 protocol from then on). Numbered messages from the cloud
    are taken once and acked every ``ack_every`` messages or ``ack_delay`` s."""

    def __init__(self, *, expiry: float = DEFAULT_EXPIRY, max_pending_bytes: int = DEFAULT_MAX_PENDING_BYTES,
                 resume: bool = False, resume_buffer: int = DEFAULT_RESUME_BUFFER,
                 resume_bytes: int = DEFAULT_RESUME_BYTES, ack_every: int = ACK_EVERY, ack_delay: float = ACK_DELAY):
        super().__init__(expiry, max_pending_bytes, resume, resume_buffer, resume_bytes, ack_every, ack_delay)
        self.pending = PendingCalls("the cloud")
        self.interfaces: dict[str, bool] = {}
        self.dropped = 0
        self._frames: list[str | bytes] = []
        # resume: off | asked -> live <-> detached -> resuming -> live
        self.state = "asked" if resume else "off"
        self.token: str | None = None
        self.grace: float | None = None

    # -- frames out ---------------------------------------------------------------------------------
    def data_to_send(self) -> list[str | bytes]:
        """The frames to send, in order (each message's text frame, then its binary parts)."""
        frames, self._frames = self._frames, []
        return frames

    @property
    def outbox(self) -> int:
        """Frames waiting to be taken by :meth:`data_to_send`."""
        return len(self._frames)

    def send(self, type_: str, data: Any, ids: list[str] | None = None) -> None:
        """Send ``{"type": type_, "data": data}``; ``bytes`` values become binary parts (with the
        given ``ids``, default fresh ones). With resume it is numbered and kept until acked; while
        detached or resuming it waits for the resume. Raises the table's error once the link closed."""
        if self.pending.closed is not None:
            raise type(self.pending.closed)(self.pending.closed.message)
        if self.outgoing is None:
            text, parts = encode({"type": type_, "data": data}, ids)
            frames: list[Frame] = [text, *parts]
        else:
            frames = self.outgoing.numbered({"type": type_, "data": data}, ids)
        if self.state not in ("detached", "resuming"):
            self._frames.extend(frames)

    def call(self, itag: str, type_: str, msg: Any, msg_id: str | None = None, ids: list[str] | None = None) -> str:
        """Start a service call through robot-side interface ``itag`` of service class ``type_``:
        sends ``DM {iTag, type, msgID, msg}``; returns the msgID (default a fresh 32-hex-char one)."""
        msg_id = self.pending.open(msg_id or uuid.uuid4().hex, _Waiting("call", itag))
        try:
            self.send(DM, {"iTag": itag, "type": type_, "msgID": msg_id, "msg": msg}, ids)
        except BaseException:
            self.pending.forget(msg_id)
            raise
        return msg_id

    def barrier(self, token: str | None = None) -> str:
        """Start a barrier: a CX between two interfaces that cannot exist, ``TOKEN/a`` and
        ``TOKEN/b``; the ER naming them means every request sent before was handled. Returns the token."""
        token = self.pending.open(token or f"{BARRIER_PREFIX}{uuid.uuid4().hex[:12]}", _Waiting("barrier", None))
        self.send(CX, {"connect": [{"tagA": f"{token}/a", "tagB": f"{token}/b"}]})
        return token

    # -- frames in ----------------------------------------------------------------------------------
    def _bad_input(self, reason: str) -> None:
        self.dropped += 1
        self._emit(Dropped(reason))

    def _on_message(self, m: dict) -> None:
        if self.state != "off" and not self._resume_rules(m):
            return
        t, data = m.get("type"), m.get("data")
        if t == DM and isinstance(data, dict):
            self._on_dm(data)
        elif t == ST and isinstance(data, dict):
            if data.get("topic") == "iu" and isinstance(data.get("iTag"), str):
                self.interfaces[data["iTag"]] = up = bool(data.get("status"))
                self._emit(InterfaceChanged(data["iTag"], up))
            self._emit(StatusReceived(data))
        elif t == ER:
            self._on_er(data if isinstance(data, str) else json.dumps(data, separators=(",", ":"), ensure_ascii=False))
        else:
            self._bad_input(f"unexpected message from the cloud: type {t!r}")

    # -- resume ------------------------------------------------------------------------------------
    def _linked(self) -> bool:
        return self.state == "live"

    def _send_ack(self, n: int) -> None:
        self._frames.append(ack_frame(n))

    def _resume_rules(self, m: dict) -> bool:
        """The session's own messages: True when ``m`` is the application's."""
        data = m.get("data")
        if self.state == "asked":                       # the cloud's first message decides
            if is_session_status(m) and data.get("status") == "started" and isinstance(data.get("session"), str):
                self.state, self.token, self.grace = "live", data["session"], data.get("grace")
                self._emit(SessionStatus(data))
                return False
            self.state = "off"                          # the cloud does not offer resume
            self.outgoing = self.incoming = None
            return True
        if is_session_status(m):
            if self.state == "resuming" and data.get("status") == "resumed":
                self._resumed(data)
            self._emit(SessionStatus(data))
            return False
        return self._take_numbered(m)

    def _resumed(self, data: dict) -> None:
        """The cloud's ST resumed: resend what it did not take, then the link is live."""
        try:
            frames, lost = self.outgoing.resend_after(read_ack({"seq": data.get("ack")}))
        except ProtocolError as e:                      # a cloud that does not say: resend all that is kept
            self._bad_input(f"ST session resumed: {e.message}")
            frames, lost = self.outgoing.resend_after(self.outgoing.acked)
        self.state = "live"
        for f in frames:
            self._frames.extend(f)
        if lost:
            self._bad_input(f"{lost} message(s) to the cloud were lost: the resume buffer "
                            f"({self.outgoing.max_messages} messages) forgot them before the cloud acked them")

    def detach(self, reason: str) -> bool:
        """The link is lost. A live resumable session is kept for a resume (:meth:`attach`): pending calls
        and barriers wait, sends are kept; event ``detached {session, ack}`` (the resume query) and True.
        Otherwise it is :meth:`close` (``reason``) and False."""
        if self.state not in ("live", "resuming"):
            self.close(reason)
            return False
        self.state = "detached"
        self._frames.clear()                            # AKs; numbered messages are kept
        self.assembler = self.assembler.fresh()
        self._emit(Detached(self.token, self.incoming.last))
        return True

    def attach(self) -> None:
        """A new link is open with the resume query (:meth:`resume_query`); nothing new goes out until
        the cloud's ``ST session resumed``. Raises :class:`ProtocolError` unless detached."""
        if self.state != "detached":
            raise ProtocolError(f"attach: the session is {self.state}, not detached")
        self.state = "resuming"
        self.incoming.reported()

    def resume_query(self) -> dict[str, str]:
        """The query values of a resume: ``{"session": token, "ack": last taken}``."""
        return {"session": self.token or "", "ack": str(self.incoming.last if self.incoming else 0)}

    def close(self, reason: str) -> None:
        """The link closed: every pending call and barrier fails, in the order they were started,
        and later calls, barriers and sends raise :class:`Unavailable`."""
        self.state = "off"
        if self.outgoing is not None:
            self.outgoing.clear()
        error = f"connection to the cloud closed: {reason}"
        for key, w in self.pending.items():
            if not w.done:
                self._finish(key, w, Unavailable(error))
                self._emit(CallFailed(key, error) if w.kind == "call" else BarrierFailed(key, error))
        self.pending.fail_all(Unavailable(error))

    def _finish(self, key: str, w: _Waiting, error: Exception | None = None, result: Any = None) -> None:
        w.done = True
        if error is None:
            self.pending.settle(key, result)
        else:
            self.pending.fail(key, error)

    def _waiting(self, kind: str) -> list[tuple[str, _Waiting]]:
        return [(k, w) for k, w in self.pending.items() if w.kind == kind and not w.done]

    def _on_dm(self, data: dict) -> None:
        itag, msg_id = data.get("iTag"), data.get("msgID")
        if msg_id is not None:
            key = str(msg_id)
            w = self.pending.info(key)
            if w is not None and w.kind == "call" and not w.done and w.itag == itag:
                self._finish(key, w, result=data.get("msg"))
                self._emit(ResponseReceived(key, data.get("msg")))
                return
        self._emit(MessageReceived(itag, data.get("type"), msg_id, data.get("msg")))

    def _on_er(self, reason: str) -> None:
        for token, w in self._waiting("barrier"):
            if token in reason:
                self._finish(token, w)
                self._emit(BarrierPassed(token))
                return
        calls = self._waiting("call")
        named = [(k, w) for k, w in calls if k in reason]
        if not named:
            named = [(k, w) for k, w in calls if _names(reason, w.itag)
                     and sum(1 for _, o in calls if o.itag == w.itag) == 1]
        if named:
            key, w = named[0]
            self._finish(key, w, RequestError(reason))
            self._emit(CallFailed(key, reason))
            return
        self._emit(ErrorReceived(reason))


def _names(reason: str, itag: str | None) -> bool:
    """Does an ER's text name interface ``itag`` (as ``'iTag'``, ``"iTag"`` or ``/iTag``)?"""
    return bool(itag) and (f"'{itag}'" in reason or f'"{itag}"' in reason or f"/{itag}" in reason)
