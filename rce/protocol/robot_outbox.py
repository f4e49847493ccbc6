"""What the cloud sends one robot, sans I/O: the messages of a
:class:`~rce.protocol.robot_session.RobotSession` on their way out, in order.

- Each message waits in its lane (:class:`~rce.protocol.lane_queue.LaneQueues`, docs/lanes.md): STs,
  ERs, AKs and resends in control; DMs in their interface's lane (a service call or answer of a bulk
  interface in state: it is never dropped, so it stays on the session's own link); they go out by
  strict priority with a minimum share for the lower lanes.
- Topic data (data DMs) follows the one outbox policy in its lane (:class:`~rce.protocol.outbox.Outbox`:
  each interface keeps its newest).
- With a bulk link (:attr:`RobotOutbox.bulk_linked`), bulk topic data goes on it, unnumbered
  (:meth:`RobotOutbox.bulk_to_send`); everything else stays on the session's link.
- STs and answers are never dropped; a robot that lets ``CONTROL_BACKLOG`` x ``queue_size`` of them
  wait is closed (``on_overrun``, once).
- ERs are cut short, rate-limited and bounded while unread (:class:`~rce.protocol.error_limits.ErrorLimits`).
- With resume (``outgoing``, :mod:`rce.protocol.resume`): messages are numbered as they go out; while
  the robot is detached they are numbered and kept at once, to go out after a resume, and a state or
  bulk topic message supersedes its interface's older one (:meth:`~rce.protocol.resume.Outgoing.keep`).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rce.protocol.error_limits import ErrorLimits
from rce.protocol.frames import DM, ER, ST, encode
from rce.protocol.lane_queue import ALL_LANES, LaneQueues
from rce.interfaces.lanes import Lane
from rce.protocol.resume import AK, Frame, Outgoing

_CONTROL_STATE = (Lane.CONTROL, Lane.STATE)     # the session's link's lanes while a bulk link takes bulk
CONTROL_BACKLOG = 10        # x queue_size: STs and answers waiting before a robot that does not
                            # read is closed (they are never dropped; ERs are, past queue_size)


@dataclass(slots=True)
class _Out:
    """A message waiting to go to the robot."""
    msg: dict | None                    # None: a kept message resent as it was (``frames``)
    data: bool = False                  # droppable topic data
    link: bool = False                  # link-level (ST session, AK): not numbered, not kept
    frames: list[Frame] | None = None   # a resend: the frames as first numbered
    newest_of: str | None = None        # state or bulk topic data: its interface (only its newest is resent)


class RobotOutbox:
    """The messages to robot ``robot``. ``queue_size`` and ``max_lag`` bound topic data
    (each lane's :class:`~rce.protocol.outbox.Outbox`) and unread ERs; ``er_rate``/``er_burst``: the ER token
    bucket; ``outgoing``: resume's numbering (None without resume); ``on_overrun(reason)``: the robot
    does not read (once). Counters: :attr:`msgs_out` (messages sent, link-level ones not counted),
    :attr:`resent` (kept messages resent after a resume)."""

    def __init__(self, robot: str, queue_size: int, max_lag: float | None, er_rate: float, er_burst: int,
                 outgoing: Outgoing | None, on_overrun: Callable[[str], None]):
        self.robot, self.queue_size, self.outgoing = robot, queue_size, outgoing
        self.queue: LaneQueues[_Out] = LaneQueues(queue_size, max_lag)
        self.bulk_linked = False            # a bulk link takes the bulk lane's topic data
        self.er = ErrorLimits(robot, queue_size, er_rate, er_burst)
        self.attached = True                # on a live link (always, without resume)
        self.msgs_out = self.resent = 0
        self._control = 0                   # STs and answers waiting
        self._overrun = False
        self._on_overrun = on_overrun

    def __len__(self) -> int:
        """Messages waiting to be sent."""
        return len(self.queue)

    # -- in ---------------------------------------------------------------------------------------
    def dm(self, msg: dict, data: bool, now: float, lane: Lane = Lane.STATE) -> None:
        """Queue DM ``msg`` in ``lane``; ``data``: droppable topic data of its interface, queued at ``now``
        (s); else never dropped (in state when ``lane`` is bulk)."""
        newest_of = msg["data"]["iTag"] if data and lane is not Lane.CONTROL else None
        if not self.attached:
            self.outgoing.numbered(msg, newest_of=newest_of)
        elif data:
            self.queue.put_data(msg["data"]["iTag"], _Out(msg, data=True, newest_of=newest_of), now, lane)
        else:
            self.control(msg, now, min(lane, Lane.STATE, key=lambda x: x.rank))

    def control(self, msg: dict, now: float | None = None, lane: Lane = Lane.CONTROL) -> None:
        """Queue an ST or a DM answer (in ``lane``, at ``now`` s): never dropped."""
        if not self.attached:
            self.outgoing.numbered(msg)
            return
        if self._control >= CONTROL_BACKLOG * self.queue_size and not self._overrun:
            self._overrun = True
            self._on_overrun(f"robot {self.robot!r} does not read: {self.queue.places} messages wait for it")
        self._control += 1
        self.queue.put(_Out(msg), now, lane)

    def error(self, reason: str, answer: bool, now: float) -> bool:
        """Queue ER ``reason`` at ``now`` (s) as :class:`~rce.protocol.error_limits.ErrorLimits` admits it
        (``answer``: it answers a request or call, not rate-limited). False: dropped (counted)."""
        if not self.er.admit(answer, now, self.attached):
            return False
        self._error(self.er.text(reason))
        return True

    def tick(self, now: float) -> None:
        """When ERs were dropped and the robot reads again: an ER saying how many."""
        note = self.er.due(now, self.attached)
        if note is not None:
            self._error(note)

    def _error(self, text: str) -> None:
        msg = {"type": ER, "data": text}
        if not self.attached:
            self.outgoing.numbered(msg)
            return
        self.er.waiting += 1
        self.queue.put(_Out(msg))

    def link_message(self, type_: str, data: dict) -> None:
        """Queue a link-level message (``ST session``, ``AK``): not numbered, not kept."""
        self.queue.put(_Out({"type": type_, "data": data}, link=True))

    def ack(self, n: int) -> None:
        """Queue ``AK {"seq": n}``."""
        self.link_message(AK, {"seq": n})

    # -- resume ------------------------------------------------------------------------------------
    def detach(self) -> None:
        """The link is lost: what waits is numbered and kept (link-level messages are gone), and so is
        what comes until :meth:`resume`."""
        self.attached = False
        self.outgoing.cut()
        for o in self.queue.drain():
            if o.msg is not None and not o.link:
                self.outgoing.numbered(o.msg, newest_of=o.newest_of)
        self._control = self.er.waiting = 0

    def resume(self, status: dict, frames: list[list[Frame]]) -> None:
        """A new link: ``ST status`` (session resumed), then the kept messages ``frames`` as first numbered."""
        self.attached = True
        self.link_message(ST, status)
        for f in frames:
            self.queue.put(_Out(None, frames=f))

    # -- out ---------------------------------------------------------------------------------------
    @property
    def link_lanes(self) -> tuple[Lane, ...]:
        """The lanes the session's own link carries: all of them, or control and state while a bulk link
        takes the bulk lane."""
        return _CONTROL_STATE if self.bulk_linked else ALL_LANES

    def waiting(self) -> int:
        """Messages waiting for the session's own link."""
        return self.queue.waiting(_CONTROL_STATE) if self.bulk_linked else len(self.queue)

    def data_to_send(self, max_messages: int | None = None, now: float | None = None) -> list[str | bytes]:
        """Frames of up to ``max_messages`` waiting messages for the session's link (all by default;
        :attr:`link_lanes`, by priority), each message's JSON text frame followed by its binary parts; they
        count as sent (with resume: numbered and kept until acked). ``now`` (s): stale data DMs are dropped
        instead (:meth:`Outbox.take`)."""
        frames: list[str | bytes] = []
        taken = 0
        while max_messages is None or taken < max_messages:
            got = self.queue.take(now, self.link_lanes)
            if got is None:
                break
            lane, o = got
            taken += 1
            if o.frames is not None:
                out = o.frames
                self.resent += 1
            else:
                if o.msg["type"] == ER:
                    self.er.waiting -= 1
                elif not o.link and not o.data:
                    self._control -= 1
                out = self._frames(o.msg, o.link, o.newest_of)
            frames.extend(out)
            self.queue.sent(lane, sum(len(f) for f in out))
        return frames

    def data_now(self, msg: dict, now: float, lane: Lane = Lane.STATE) -> list[str | bytes] | None:
        """The frames of data DM ``msg`` (of ``lane``, at ``now`` s) to write to the session's link at once,
        when nothing waits for the robot: what :meth:`dm` and :meth:`data_to_send` would give, counted the
        same (queued and taken with no delay, sent), without the queue. Otherwise (something waits, the
        robot is detached, or a bulk link takes ``lane``) it is queued as :meth:`dm` does, and None
        returned. Call it only when the link takes the frames now."""
        if len(self.queue) or not self.attached or lane not in self.link_lanes:
            self.dm(msg, True, now, lane)
            return None
        out = self._frames(msg, False, msg["data"]["iTag"] if lane is not Lane.CONTROL else None)
        self.queue.through(lane, sum(len(f) for f in out))
        return out

    def _frames(self, msg: dict, link: bool, newest_of: str | None) -> list[str | bytes]:
        """``msg`` encoded to go out now (with resume, numbered and kept, unless ``link``-level); counted."""
        if link or self.outgoing is None:
            text, parts = encode(msg)
            out = [text, *parts]
        else:
            out = self.outgoing.numbered(msg, newest_of=newest_of)
        self.msgs_out += not link
        return out

    def bulk_to_send(self, now: float | None = None) -> list[str | bytes] | None:
        """(a bulk link) The frames of the next bulk topic DM, unnumbered (the JSON text frame, then its
        binary parts), or None when none waits. The shell reports it written with
        ``queue.sent(Lane.BULK, n)``."""
        got = self.queue.take(now, (Lane.BULK,))
        if got is None:
            return None
        text, parts = encode(got[1].msg)
        self.msgs_out += 1
        return [text, *parts]


def dm(itag: str, cls: str, msg_id: Any, msg: Any) -> dict:
    """The message ``DM {iTag, type, msgID, msg}``."""
    return {"type": DM, "data": {"iTag": itag, "type": cls, "msgID": msg_id, "msg": msg}}
