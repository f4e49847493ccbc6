"""The cloud side of a robot session, sans I/O (:mod:`rce.protocol.session`): one connected robot's
frames in, requests to the master one at a time and in order, the DM ordering rule, lag shedding,
what goes to the robot, and resume. The robot endpoint (:mod:`rce_robot.namespace`) is its shell."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from rce.plumbing.errors import ProtocolError
from rce.interfaces.kind import InterfaceType, Kind, Side
from rce.messages import takes_binary_message
from rce.protocol.events import CaughtUp, CloseLink, Deliver, Lagging, RequestReady, ServiceCall
from rce.protocol.frames import DEFAULT_EXPIRY, DEFAULT_MAX_PENDING_BYTES, DEFAULT_MAX_PENDING_PARTS, DM, ST
from rce.protocol.holdback import HoldBack
from rce.interfaces.lanes import Lane, interface_lane, message_lane
from rce.interfaces.pacer import Pacer
from rce.plumbing.text import short_repr
from rce.protocol.limits import DEFAULT_MAX_LAG, ER_BURST, ER_RATE, LagGate, PartBudget
from rce.protocol.robot_outbox import RobotOutbox, dm
from rce.protocol.resume import (ACK_DELAY, ACK_EVERY, DEFAULT_GRACE, DEFAULT_RESUME_BUFFER, DEFAULT_RESUME_BYTES,
                                 SESSION_TOPIC, new_token)
from rce.protocol.schema import dm_data, validate
from rce.protocol.session_core import SessionCore

DEFAULT_QUEUE_SIZE = 1000                   # messages per robot in each bounded queue (like a ROS queue_size)
DEFAULT_MAX_MESSAGE = 32 * 1024 * 1024      # bytes (chars for text) of the largest frame a robot endpoint takes
LAG_TOPIC = "lag"                           # ST topic: the endpoint sheds the robot's topic messages, or caught up
LANES_TOPIC = "lanes"                       # ST topic: the per-lane counters, to a robot with a bulk link
LANES_STATUS_EVERY = 5.0                    # s between two ST lanes


@dataclass(frozen=True)
class SessionLimits:
    """The bounds of one robot's session (each a ValueError when out of range, where it is used).

    ``max_message``: largest frame taken (bytes; text: chars), larger ones get an ER.
    ``queue_size``: bound of each queue (data DMs waiting to go out, requests waiting for the master,
    DMs waiting for earlier requests, service calls in flight), beyond which messages are dropped,
    counted, and (inbound ones) refused with an ER; at least 1.
    ``expiry``: s an incomplete message waits for its binary parts; ``max_pending_bytes`` and
    ``max_pending_parts``: binary parts waiting for their message.
    ``er_rate`` per s and ``er_burst`` at once: ERs for bad input, dropped and counted past them
    (:class:`~rce.protocol.error_limits.ErrorLimits`).
    ``max_lag``: s the endpoint may stay behind the robot before it sheds the robot's topic messages
    (:class:`RobotSession`); None: never shed."""

    max_message: int = DEFAULT_MAX_MESSAGE
    queue_size: int = DEFAULT_QUEUE_SIZE
    expiry: float = DEFAULT_EXPIRY
    max_pending_bytes: int = DEFAULT_MAX_PENDING_BYTES
    max_pending_parts: int = DEFAULT_MAX_PENDING_PARTS
    er_rate: float = ER_RATE
    er_burst: int = ER_BURST
    max_lag: float | None = DEFAULT_MAX_LAG


@dataclass(frozen=True)
class ResumeOptions:
    """A session the robot may resume (docs/INTERNALS.md "Session resume").

    ``token``: the session's (None: a fresh :func:`~rce.protocol.resume.new_token`); ``grace``: s the
    endpoint keeps it detached; ``buffer`` messages and ``bytes`` kept until acked (past them the
    oldest is forgotten, counted); an AK every ``ack_every`` messages taken or ``ack_delay`` s."""

    token: str | None = None
    grace: float = DEFAULT_GRACE
    buffer: int = DEFAULT_RESUME_BUFFER
    bytes: int = DEFAULT_RESUME_BYTES
    ack_every: int = ACK_EVERY
    ack_delay: float = ACK_DELAY


class RobotSession(SessionCore):
    """The cloud side of robot ``robot``'s session, within ``limits`` (:class:`SessionLimits`).

    Every bad input gets an ER naming what was wrong; the session goes on. ERs are cut short and
    those for bad input rate-limited. ``budget``: the endpoint's :class:`~rce.protocol.limits.PartBudget`
    of binary parts, shared by its sessions (:meth:`end` gives back).

    ``resume`` (:class:`ResumeOptions`): the robot opted in. The session opens with
    ``ST {"topic": "session", "status": "started", "session": token, "grace": grace}``, numbers what
    it sends and keeps it until acked, and takes each numbered message once.

    Lag shedding: while the endpoint has been behind this robot (received frames waiting for the
    session, as the shell tells with :meth:`backlog`) for longer than ``limits.max_lag``, a DM for a
    topic interface is dropped and counted (``shed``) instead of delivered, until the shell has caught
    up, unless that interface has delivered nothing for ``max_lag`` s (so a stream still reaches the
    cloud at least that often). So an overloaded endpoint hands the cloud the robot's newest
    messages, as a ROS subscriber's ``queue_size`` drops the oldest. Requests, service calls and
    answers are never shed. The robot is told: ``ST {"topic": "lag", "status": "shedding", "behind_s",
    "max_lag_s"}`` when shedding starts, ``ST {"topic": "lag", "status": "caught_up", "shed": n}`` when
    it ends.

    The other way, to a robot that does not keep up, each interface's topic data keeps its newest
    messages, as a ROS publisher's queue does (:class:`~rce.protocol.outbox.Outbox`; ``max_lag`` ages
    them too); drops are counted in ``dropped`` (for their age also in ``expired``).

    The jobs live in their modules and this class composes them: requests and the DMs held back for
    them (:class:`~rce.protocol.holdback.HoldBack`), what goes to the robot (outbox, ERs, resume's
    numbering: :class:`~rce.protocol.robot_outbox.RobotOutbox`), lag shedding
    (:class:`~rce.protocol.limits.LagGate`), resume (:mod:`rce.protocol.resume`)."""

    def __init__(self, robot: str, limits: SessionLimits = SessionLimits(), resume: ResumeOptions | None = None,
                 budget: PartBudget | None = None):
        r = resume or ResumeOptions()
        super().__init__(limits.expiry, limits.max_pending_bytes, resume is not None, r.buffer, r.bytes,
                         r.ack_every, r.ack_delay, limits.max_pending_parts, budget)
        # what waits for the robot (ValueError for a queue_size < 1)
        self.out = RobotOutbox(robot, limits.queue_size, limits.max_lag, limits.er_rate, limits.er_burst,
                               self.outgoing, lambda reason: self._emit(CloseLink(reason)))
        self.robot, self.max_message, self.queue_size = robot, limits.max_message, limits.queue_size
        self.lag = LagGate(limits.max_lag)                        # sheds topic DMs while the shell lags
        self.requests = HoldBack(limits.queue_size)               # requests to the master, DMs held for them
        self.interfaces: dict[str, tuple[InterfaceType, str]] = {}     # iTag -> (its type, its class)
        self.lanes: dict[str, tuple[Lane, bool]] = {}             # iTag -> (its lane, set by the robot)
        self.calls = 0                                            # service calls in flight
        self.msgs_in = self.dropped_in = 0
        self.token = (r.token or new_token()) if resume is not None else None
        self.grace = r.grace
        self.resumes = self.resume_lost = 0
        self._superseded_at_detach = 0              # resume: superseded before the link was lost (for ST resumed)
        self.bulk_links = self.bulk_in = 0          # bulk links joined; DMs the robot sent on them
        self.bulk_pacer: Pacer | None = None        # the bulk link's, while one is there
        self._lanes_status = float("-inf")          # s: when the last ST lanes went out
        if resume is not None:
            self.out.link_message(ST, {"topic": SESSION_TOPIC, "status": "started", "session": self.token,
                                       "grace": self.grace})

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
            if type(msg) is dict and msg.get("type") == DM:      # its data travels on as its dict (schema.dm_data)
                data, request = dm_data(msg), None
            else:
                data, (t, request) = None, validate(msg)
        except ProtocolError as e:
            self.send_error(e.message)
            return
        if request is None:
            self._on_dm(data)
        elif self.requests.full:
            self.dropped_in += 1
            self.send_error(f"{t}: refused: {len(self.requests.requests)} requests already wait for the master")
        else:
            self.requests.add(t, request)
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
        itype, cls = itf
        refusal = _refusal(itag, itype, cls, data)
        if refusal:
            self.send_error(refusal)
        elif itype.kind is not Kind.SERVICE_PROVIDER:
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
        self.send_dm(itag, self.interfaces.get(itag, (None, call["type"]))[1], call.get("msgID") or "", msg)

    def fail_call(self, call: dict, reason: str) -> None:
        """The service of a :class:`~rce.protocol.events.ServiceCall` (its ``data``: ``call``) failed: an
        ER naming the call's msgID and interface."""
        self.calls -= 1
        self.send_error(f"service call {call.get('msgID')!r} on {call['iTag']!r} failed: {reason}", answer=True)

    # -- the interface table ------------------------------------------------------------------------
    def add_interface(self, itag: str, itype: str, cls: str, lane: Lane | None = None) -> None:
        """A robot-side interface ``itag`` of type ``itype`` and class ``cls`` now exists; ``lane``: the
        lane the robot set for it (None: from ``cls``, :func:`~rce.interfaces.lanes.default_lane`).
        Raises as :func:`robot_interface_type`."""
        parsed = robot_interface_type(itype)
        self.interfaces[itag] = (parsed, cls)
        self.lanes[itag] = (interface_lane(cls, parsed.kind.service, lane), lane is not None)

    def remove_interface(self, itag: str) -> None:
        """Robot-side interface ``itag`` is gone."""
        self.interfaces.pop(itag, None)
        self.lanes.pop(itag, None)
        self.lag.forget(itag)

    def lane_of(self, itag: str, msg: Any = None) -> Lane:
        """The lane a topic DM of interface ``itag`` with message ``msg`` takes
        (:func:`~rce.interfaces.lanes.message_lane`: a serialized message, bytes, larger than
        :data:`~rce.interfaces.lanes.BULK_SIZE` goes bulk unless the robot set the lane); an unknown
        interface's: state."""
        lane, explicit = self.lanes.get(itag, (Lane.STATE, False))
        return message_lane(lane, explicit, len(msg) if isinstance(msg, (bytes, bytearray, memoryview)) else 0)

    # -- frames out ---------------------------------------------------------------------------------
    def send_dm(self, itag: str, cls: str, msg_id: Any, msg: Any, data: bool = False,
                now: float | None = None) -> bool:
        """Queue ``DM {iTag, type, msgID, msg}`` for the robot at time ``now`` (s; default the last
        time given). ``data=True`` marks topic data: when ``queue_size`` data DMs already wait, the
        oldest of the busiest interface is dropped (:class:`~rce.protocol.outbox.Outbox`). Returns True."""
        self.out.dm(dm(itag, cls, msg_id, msg), data, self._now if now is None else now, self.lane_of(itag, msg))
        return True

    def data_now(self, itag: str, cls: str, msg_id: Any, msg: Any, now: float) -> list[str | bytes] | None:
        """Topic data ``DM {iTag, type, msgID, msg}`` at ``now`` (s): its frames, to write to the robot's link
        at once, when nothing waits for the robot (counted as :meth:`send_dm` with ``data=True`` and
        :meth:`data_to_send`, without the queue); else it is queued as :meth:`send_dm` does and None
        returned (:meth:`RobotOutbox.data_now`). Call it only when the link takes the frames now."""
        return self.out.data_now(dm(itag, cls, msg_id, msg), now, self.lane_of(itag, msg))

    def send_status(self, data: dict) -> None:
        """Queue ``ST data`` for the robot (never dropped)."""
        self.out.control({"type": ST, "data": data})

    def send_error(self, reason: str, answer: bool = False) -> bool:
        """Queue ``ER reason`` for the robot (:class:`~rce.protocol.error_limits.ErrorLimits`: cut short,
        counted). ``answer``: it answers a request or call of the robot (not rate-limited). Returns False
        when it was dropped (rate limit, or ``queue_size`` ERs unread; counted in ``errors_dropped``)."""
        return self.out.error(reason, answer, self._now)

    def tick(self, now: float) -> None:
        """As :meth:`SessionCore.tick`; then, when ERs were dropped and the robot reads again, an ER
        saying how many; and to a robot with a bulk link, every :data:`LANES_STATUS_EVERY` s, ``ST {"topic":
        "lanes", "lanes": {lane: counters}}`` (:meth:`~rce.protocol.lane_queue.LaneQueues.lane_stats`)."""
        super().tick(now)
        self.out.tick(now)
        if self.out.bulk_linked and self.attached and now - self._lanes_status >= LANES_STATUS_EVERY:
            self._lanes_status = now
            self.send_status({"topic": LANES_TOPIC, "lanes": self.lane_stats()})

    def end(self) -> None:
        """The session ended: what waited for binary parts is forgotten (its bytes go back to the budget)."""
        self.assembler.clear()
        self.bulk_assembler.clear()

    # -- the bulk link (docs/lanes.md) --------------------------------------------------------------
    def attach_bulk(self, pacer: Pacer | None = None) -> None:
        """A bulk link joined the session: from now on the bulk lane's topic DMs go on it
        (:meth:`bulk_to_send`), unnumbered; the robot's DMs on it come in through :meth:`receive_bulk`.
        ``pacer``: the link's (None: not paced); its rate is in the bulk lane's stats (:meth:`lane_stats`)."""
        self.bulk_pacer = pacer
        self.out.bulk_linked = True
        self.bulk_links += 1
        self.bulk_assembler = self.bulk_assembler.fresh()

    def detach_bulk(self) -> None:
        """The bulk link is gone: the bulk lane goes on the session's own link again; what waited for
        binary parts on it is forgotten (the robot resends nothing there: bulk data keeps its newest)."""
        self.out.bulk_linked = False
        self.bulk_pacer = None
        self.bulk_assembler = self.bulk_assembler.fresh()

    def bulk_to_send(self, now: float | None = None) -> list[str | bytes] | None:
        """(a bulk link) The frames of the next bulk topic DM (:meth:`RobotOutbox.bulk_to_send`), or None."""
        return self.out.bulk_to_send(now) if self.out.bulk_linked else None

    def receive_bulk(self, frame: str | bytes, now: float) -> None:
        """A frame from the robot's bulk link at ``now`` (s): it carries DMs only, unnumbered, with their
        own binary parts; anything else gets an ER."""
        for msg in self._bulk_messages(frame, now):
            if msg.get("type") != DM or "seq" in msg:
                self.send_error(f"bulk link: carries unnumbered DMs only, got a {short_repr(msg.get('type'))}"
                                f"{' with seq' if 'seq' in msg else ''}; send it on the session's link")
                continue
            self.msgs_in += 1
            try:
                data = dm_data(msg)
            except ProtocolError as e:
                self.send_error(e.message)
                continue
            self.bulk_in += 1
            self._on_dm(data)

    @property
    def outbox(self) -> int:
        """Messages waiting for the session's own link (with a bulk link, the bulk lane's topic data is
        not: :attr:`bulk_outbox`)."""
        return self.out.waiting()

    @property
    def bulk_outbox(self) -> int:
        """Bulk topic DMs waiting for the bulk link (0 without one)."""
        return self.out.queue.waiting((Lane.BULK,)) if self.out.bulk_linked else 0

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
        self._superseded_at_detach = self.outgoing.superseded
        self.out.detach()

    def can_resume(self, ack: int) -> bool:
        """Can a resume whose robot took every message up to ``ack`` be served?"""
        return self.outgoing is not None and 0 <= ack <= self.outgoing.last

    def attach(self, ack: int) -> None:
        """(resume) A new link resumes the session (from a detached session, or taking over a link the
        endpoint still holds); the robot took every message up to ``ack``. Queues ``ST {"topic":
        "session", "status": "resumed", "session", "grace", "ack", "dropped", "superseded"}`` (``ack``: the
        last robot message taken; ``dropped``: messages to the robot the buffer lost; ``superseded``: state
        and bulk topic messages to it dropped while it was away, for a newer one of their interface), then
        the kept messages after ``ack`` (of each such interface only the newest), numbered on from ``ack``
        and the lost ones (:meth:`~rce.protocol.resume.Outgoing.resend_after`).
        Incomplete messages of the old link are dropped: the robot resends
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
                         "ack": self.incoming.last, "dropped": lost,
                         "superseded": self.outgoing.superseded - self._superseded_at_detach}, frames)

    def stats(self) -> dict:
        """Counters: messages in and out, drops out (data DMs: the oldest past the queue bound, or older
        than ``max_lag``, those also in ``expired``) and in (refused for a full queue), ERs sent and
        dropped, messages and parts waiting for binary parts and their bytes, queue depths; ``shed``:
        topic DMs from the robot dropped while the endpoint lagged (``max_lag``);
        resume: resumes, messages resent, lost at a resume (``resume_lost``), state and bulk topic messages
        to the robot dropped while it was detached for a newer one of their interface (``superseded``; not
        lost: the robot waits for none of them), kept until acked
        (``kept``, ``kept_bytes``), forgotten past the bound (``resume_forgotten``), duplicates from the
        robot dropped, messages from the robot its resume buffer lost (``resume_gaps``: numbers skipped);
        ``bulk_links`` joined, ``bulk_in`` DMs the robot sent on them; ``lanes``: per lane
        (:meth:`LaneQueues.lane_stats`: messages taken and sent whole, bytes, drops, waiting, queue delay)."""
        out, inc = self.outgoing, self.incoming
        return {"interfaces": len(self.interfaces), "msgs_in": self.msgs_in, "msgs_out": self.out.msgs_out,
                "dropped": self.dropped, "dropped_in": self.dropped_in, "shed": self.lag.shed,
                "errors": self.out.er.sent, "errors_dropped": self.out.er.dropped,
                "pending_binary": self.assembler.pending, "pending_binary_bytes": self.assembler.pending_bytes,
                "outbox": self.outbox, "expired": self.expired, "requests_waiting": self.requests.waiting,
                "held": self.requests.held, "calls": self.calls, "resumes": self.resumes, "resent": self.out.resent,
                "resume_lost": self.resume_lost, "superseded": out.superseded if out else 0,
                "kept": len(out) if out else 0, "kept_bytes": out.bytes if out else 0,
                "resume_forgotten": out.forgotten if out else 0, "duplicates": inc.duplicates if inc else 0,
                "resume_gaps": inc.gaps if inc else 0,
                "bulk_links": self.bulk_links, "bulk_in": self.bulk_in, "lanes": self.lane_stats()}

    def lane_stats(self) -> dict[str, dict]:
        """Per lane, :meth:`LaneQueues.lane_stats`; the bulk lane's, while a paced bulk link is there, also
        its pacing (:meth:`Pacer.stats`: ``rate_source``, ``rate`` bytes/s, and when estimated
        ``rate_estimate`` bytes/s, ``rate_mode``, ``rate_backoffs``, ``rate_probes``)."""
        stats = self.out.queue.lane_stats()
        if self.bulk_pacer is not None:
            stats[Lane.BULK.value].update(self.bulk_pacer.stats())
        return stats


def robot_interface_type(itype: str | InterfaceType) -> InterfaceType:
    """A robot-side interface type (a Converter or Forwarder), parsed. Raises :class:`ProtocolError`
    for an unknown type, :class:`RequestError` for a container-side one."""
    return InterfaceType.parse(itype, robot_side=True)


def _refusal(itag: str, itype: InterfaceType, cls: str, data: dict) -> str | None:
    """Why interface ``itag`` (of type ``itype``, class ``cls``) cannot take this DM, or None."""
    if str(data["type"]).strip("/") != cls:
        return f"DM: interface {itag!r} carries {cls!r}, not {data['type']!r}"
    if itype.kind is Kind.PUBLISHER:
        return (f"{itype} {itag!r} sends messages to the robot; it does not take messages from it "
                f"(use a SubscriberConverter)")
    binary = isinstance(data.get("msg"), (bytes, bytearray))
    if itype.side is Side.CONVERTER and binary and not takes_binary_message(cls):
        return f"{itype} {itag!r} takes JSON messages; use a {itype.kind}Forwarder for serialized binary messages"
    if itype.side is Side.FORWARDER and not binary:
        return f"{itype} {itag!r} takes the serialized message as binary part 'msg*'"
    return None
