"""The robot side of a session, sans I/O (:mod:`rce.protocol.session`): pending calls and barriers,
the interface status table, ER attribution, resume. Its rules are those of ``tests/vectors/README.md``,
which the browser client (``rce.js``) follows too. The client library (:mod:`rce_client.connection`)
is its shell."""
from __future__ import annotations

import json
import uuid
from dataclasses import dataclass
from typing import Any

from rce.plumbing.errors import ProtocolError, RequestError, Unavailable
from rce.plumbing.pending import PendingCalls
from rce.protocol.events import (BarrierFailed, BarrierPassed, CallFailed, Detached,
                                 Dropped, ErrorReceived, InterfaceChanged, MessageReceived,
                                 ResponseReceived, SessionStatus, StatusReceived)
from rce.protocol.frames import (CX, DEFAULT_EXPIRY, DEFAULT_MAX_PENDING_BYTES, DM, ER,
                                 ST, encode)
from rce.protocol.resume import (ACK_DELAY, ACK_EVERY, DEFAULT_RESUME_BUFFER, DEFAULT_RESUME_BYTES,
                                 Frame, ack_frame, is_session_status, read_ack)
from rce.protocol.session_core import SessionCore

BARRIER_PREFIX = "rcesync"                  # barrier tokens: interfaces named so cannot exist


@dataclass
class _Waiting:
    kind: str               # "call" or "barrier"
    itag: str | None        # a call's interface
    done: bool = False


class ClientSession(SessionCore):
    """The robot side of a session: what the cloud sends becomes events; calls and barriers wait in
    :attr:`pending` (a :class:`PendingCalls` keyed by msgID or token: the shell awaits
    ``pending.wait(key, timeout)``; a call's result is the response's ``msg``, a failure
    :class:`RequestError` (an ER) or :class:`Unavailable` (the link closed)). Opening a call
    needs a running asyncio loop (the table's futures); nothing else here does.

    ``expiry``: s an incomplete message waits for its binary parts. :attr:`interfaces`: iTag ->
    last ``iu`` status; :attr:`dropped`: malformed frames, expired parts, unexpected messages;
    :attr:`resume_lost`: messages to the cloud lost at resumes (the resume buffer forgot them before
    the cloud acked them: a link down for longer than the buffer holds); :attr:`superseded`: state and
    bulk topic messages to the cloud dropped while no link was up, for a newer one of their interface.

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
        self.resume_lost = 0
        self._frames: list[str | bytes] = []
        # resume: off | asked -> live <-> detached -> resuming -> live
        self.state = "asked" if resume else "off"
        self.token: str | None = None
        self.grace: float | None = None
        self.bulk_in = 0                                   # DMs taken on the bulk link

    # -- frames out ---------------------------------------------------------------------------------
    def data_to_send(self) -> list[str | bytes]:
        """The frames to send, in order (each message's text frame, then its binary parts)."""
        frames, self._frames = self._frames, []
        return frames

    @property
    def outbox(self) -> int:
        """Frames waiting to be taken by :meth:`data_to_send`."""
        return len(self._frames)

    def send(self, type_: str, data: Any, ids: list[str] | None = None, newest_of: str | None = None) -> None:
        """Send ``{"type": type_, "data": data}``; ``bytes`` values become binary parts (with the
        given ``ids``, default fresh ones). With resume it is numbered and kept until acked; while
        detached or resuming it waits for the resume. ``newest_of``: the interface of a state or bulk
        topic message: while no link is up, the interface's newest alone waits (the older ones are
        dropped, counted in :attr:`superseded`); None (requests, calls, answers, control topics): every
        one waits. Raises the table's error once the link closed."""
        if self.pending.closed is not None:
            raise type(self.pending.closed)(self.pending.closed.message)
        if self.outgoing is None:
            text, parts = encode({"type": type_, "data": data}, ids)
            frames: list[Frame] = [text, *parts]
        else:
            frames = self.outgoing.numbered({"type": type_, "data": data}, ids, newest_of)
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

    def _on_message(self, message: dict) -> None:
        if self.state != "off" and not self._resume_rules(message):
            return
        t, data = message.get("type"), message.get("data")
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

    def receive_bulk(self, frame: str | bytes, now: float) -> None:
        """A frame from the bulk link at ``now`` (s): unnumbered DMs with their own binary parts
        (docs/lanes.md); anything else is dropped and counted."""
        for m in self._bulk_messages(frame, now):
            data = m.get("data")
            if m.get("type") != DM or "seq" in m or not isinstance(data, dict):
                self._bad_input(f"bulk link: unexpected message from the cloud: type {m.get('type')!r}")
                continue
            self.bulk_in += 1
            self._on_dm(data)

    def bulk_frames(self, itag: str, type_: str, msg: Any) -> list[Frame]:
        """The frames of topic ``DM {iTag, type, msg}`` for the bulk link: unnumbered, never kept (bulk
        data keeps its newest; what a dropped bulk link loses is gone). Raises the table's error once the
        link closed."""
        if self.pending.closed is not None:
            raise type(self.pending.closed)(self.pending.closed.message)
        text, parts = encode({"type": DM, "data": {"iTag": itag, "type": type_, "msg": msg}})
        return [text, *parts]

    # -- resume ------------------------------------------------------------------------------------
    def _linked(self) -> bool:
        return self.state == "live"

    def _send_ack(self, n: int) -> None:
        self._frames.append(ack_frame(n))

    def _resume_rules(self, message: dict) -> bool:
        """The session's own messages: True when ``m`` is the application's."""
        data = message.get("data")
        if self.state == "asked":                       # the cloud's first message decides
            if is_session_status(message) and data.get("status") == "started" and isinstance(data.get("session"), str):
                self.state, self.token, self.grace = "live", data["session"], data.get("grace")
                self._emit(SessionStatus(data))
                return False
            self.state = "off"                          # the cloud does not offer resume
            self.outgoing = self.incoming = None
            return True
        if is_session_status(message):
            if self.state == "resuming" and data.get("status") == "resumed":
                self._resumed(data)
            self._emit(SessionStatus(data))
            return False
        return self._take_numbered(message)

    def _resumed(self, data: dict) -> None:
        """The cloud's ST resumed: resend what it did not take, then the link is live."""
        try:
            frames, lost = self.outgoing.resend_after(read_ack({"seq": data.get("ack")}))
        except ProtocolError as e:                      # a cloud that does not say: resend all that is kept
            self._bad_input(f"ST session resumed: {e.message}")
            frames, lost = self.outgoing.resend_after(self.outgoing.acked, newest=False)
        self.state = "live"
        for f in frames:
            self._frames.extend(f)
        if lost:
            self.resume_lost += lost
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
        self.outgoing.cut()
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

    @property
    def superseded(self) -> int:
        """State and bulk topic messages to the cloud dropped while no link was up: a newer one of the same
        interface took their place (:meth:`send` ``newest_of``); never counted as lost."""
        return self.outgoing.superseded if self.outgoing is not None else 0

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
