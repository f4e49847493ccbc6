"""Session resume, sans I/O: sequence numbers, acks and the bounded buffer of messages kept
until the peer acks them (docs/INTERNALS.md, "Session resume"; the model is MQTT's persistent
sessions and NATS reconnects).

Both sides of an opted-in robot session use the same two pieces:

- :class:`Outgoing` numbers the messages one side sends (``"seq": n`` in the JSON envelope)
  and keeps their frames until the peer acks them, in a buffer bounded in messages and bytes
  (past the bound the oldest is forgotten and counted); after a resume it gives back the
  frames the peer has not got, with how many were lost.
- While the link is down (:meth:`Outgoing.cut`), a message kept with a key (``newest_of``: the
  interface of a state or bulk topic message) supersedes the kept message of the same key that the
  peer has not got; at the resume only each key's newest is resent, and the resent messages are
  numbered again from the peer's ack, so the peer sees no gap for them (docs/INTERNALS.md
  "Newest only while no path exists").
- :class:`Incoming` takes each numbered message once (a resent duplicate is dropped and
  counted) and says when an ``AK`` is due: after ``ack_every`` messages, or ``ack_delay`` s
  after the first message not yet acked (an idle link is acked too).

Link-level messages are not numbered, never kept and never resent: ``ST {"topic": "session"}``
(the cloud's answer to the opt-in and to a resume) and ``AK {"seq": n}`` (every message up
to ``n`` was taken)."""
from __future__ import annotations

import json
import secrets
from collections import deque
from dataclasses import dataclass
from typing import Any

from rce.plumbing.errors import ProtocolError
from rce.protocol.frames import encode

AK = "AK"                                    # the ack message type (link-level)
SESSION_TOPIC = "session"                    # the ST topic of the session's own statuses (link-level)
DEFAULT_GRACE = 30.0                         # s a robot endpoint keeps a detached session for its robot
DEFAULT_RESUME_BUFFER = 1000                 # messages kept per direction until acked (each side's bound)
DEFAULT_RESUME_BYTES = 64 * 1024 * 1024      # bytes of frames kept per direction until acked
ACK_EVERY = 16                               # messages taken before an AK goes out at once
ACK_DELAY = 0.2                              # s after the first message not yet acked before an AK goes out:
                                             # short, so that a drop finds little unacked; cheap (one small frame)
TOKEN_BYTES = 32                             # random bytes of a session token (64 hex chars, 256 bits)

Frame = str | bytes


def new_token() -> str:
    """A fresh session token: :data:`TOKEN_BYTES` random bytes from :mod:`secrets`, as hex."""
    return secrets.token_hex(TOKEN_BYTES)


def ack_frame(n: int) -> str:
    """The text frame ``{"type": "AK", "data": {"seq": n}}``."""
    return json.dumps({"type": AK, "data": {"seq": n}}, separators=(",", ":"))


def read_seq(msg: dict) -> int | None:
    """The ``seq`` of a message's envelope, or None when it has none. Raises :class:`ProtocolError`
    for one that is not a positive integer."""
    if "seq" not in msg:
        return None
    seq = msg["seq"]
    if isinstance(seq, bool) or not isinstance(seq, int) or seq < 1:
        raise ProtocolError(f"message.seq must be a positive integer, got {seq!r}")
    return seq


def read_ack(data: Any) -> int:
    """The ``n`` of an AK's data ``{"seq": n}``. Raises :class:`ProtocolError` naming what is wrong."""
    seq = data.get("seq") if isinstance(data, dict) else None
    if isinstance(seq, bool) or not isinstance(seq, int) or seq < 0:
        raise ProtocolError(f"AK.data.seq must be a non-negative integer, got {data!r}")
    return seq


def is_session_status(msg: dict) -> bool:
    """Is ``msg`` an ``ST {"topic": "session", ...}`` (link-level)?"""
    data = msg.get("data")
    return msg.get("type") == "ST" and isinstance(data, dict) and data.get("topic") == SESSION_TOPIC


@dataclass(slots=True, eq=False)
class _Kept:
    """A message kept until acked."""
    seq: int
    frames: list[Frame] | None      # None: superseded while the link was down (nothing is resent for it)
    size: int                       # bytes of its frames
    newest_of: str | None           # its key: a newer message of the same key supersedes it; None: never


class Outgoing:
    """The numbered messages one side sent, kept until acked.

    ``max_messages`` and ``max_bytes`` bound what is kept; past either the oldest kept message
    is forgotten and counted in :attr:`forgotten` (it is lost only if the link drops before the
    peer got it). :attr:`last` is the number of the last message numbered (0: none yet).

    While the link is down (from :meth:`cut` to :meth:`resend_after`), a message kept with a key
    (``newest_of``) supersedes the one of the same key numbered since the cut (never sent); at the
    resume each key's newest alone is resent (those the cut caught in flight too). Each message
    superseded is counted in :attr:`superseded`, never as lost: the resent messages are numbered
    again, after the peer's ack and the gap of those lost, so the peer waits for none of them."""

    def __init__(self, max_messages: int = DEFAULT_RESUME_BUFFER, max_bytes: int = DEFAULT_RESUME_BYTES):
        self.max_messages, self.max_bytes = max_messages, max_bytes
        self.last = 0
        self.acked = 0
        self.forgotten = 0
        self.superseded = 0
        self._kept: deque[_Kept] = deque()              # oldest first, superseded ones included
        self._bytes = 0
        self._live = 0                                  # kept messages not superseded
        self._newest: dict[str, _Kept] = {}             # key -> its newest kept message
        self._cut: int | None = None                    # the last number sent before the link was lost
        self._gone = 0                                  # superseded ones still in _kept
        self._removed = 0                               # superseded ones numbered since the cut, no longer in _kept

    def __len__(self) -> int:
        return self._live

    @property
    def bytes(self) -> int:
        """Bytes of the frames kept."""
        return self._bytes

    def number(self) -> int:
        """The number of the next message."""
        self.last += 1
        return self.last

    def numbered(self, msg: dict, ids: list[str] | None = None, newest_of: str | None = None) -> list[Frame]:
        """Number ``msg`` (``{"type", "data"}``; ``seq`` goes in its envelope), encode it (``bytes``
        values become binary parts with ``ids``, :func:`~rce.protocol.frames.encode`) and keep its
        frames until acked (``newest_of``: its key, :meth:`keep`); returns them."""
        seq = self.last + 1
        text, parts = encode({"type": msg["type"], "seq": seq, "data": msg["data"]}, ids)
        self.number()
        frames: list[Frame] = [text, *parts]
        self.keep(seq, frames, newest_of)
        return frames

    def keep(self, seq: int, frames: list[Frame], newest_of: str | None = None) -> None:
        """Keep message ``seq``'s frames (its JSON text frame, then its binary parts) until acked.
        ``newest_of``: its key (a state or bulk topic message's interface): while the link is down it
        supersedes the message of the same key kept since the cut (counted in :attr:`superseded`)."""
        size = sum(len(f) for f in frames)
        e = _Kept(seq, frames, size, newest_of)
        if newest_of is not None:
            older = self._newest.get(newest_of)
            self._newest[newest_of] = e
            if older is not None and self._cut is not None and older.seq > self._cut and older.frames is not None:
                self._supersede(older)
        self._kept.append(e)
        self._bytes += size
        self._live += 1
        while self._live > self.max_messages or (self._bytes > self.max_bytes and self._live > 1):
            f = self._kept.popleft()
            if f.frames is None:
                self._gone -= 1
                self._removed += 1
                continue
            self._forget(f)
            self.forgotten += 1
        if self._gone > self.max_messages:              # reclaim their places: amortized O(1) per message
            self._kept = deque(x for x in self._kept if x.frames is not None)
            self._removed += self._gone
            self._gone = 0

    def _supersede(self, e: _Kept) -> None:
        self._bytes -= e.size
        self._live -= 1
        e.frames, e.size = None, 0
        self._gone += 1
        self.superseded += 1

    def _forget(self, e: _Kept) -> None:
        """``e`` left the buffer (acked or forgotten)."""
        self._bytes -= e.size
        self._live -= 1
        if e.newest_of is not None and self._newest.get(e.newest_of) is e:
            del self._newest[e.newest_of]

    def cut(self) -> None:
        """The link is lost: until the resume, what is kept with a key supersedes its key's older ones."""
        if self._cut is None:
            self._cut = self.last

    def ack(self, n: int) -> None:
        """The peer took every message up to ``n``: forget them. Raises :class:`ProtocolError` for
        a number never sent."""
        if n > self.last:
            raise ProtocolError(f"AK: seq {n} was never sent (the last message sent is {self.last})")
        while self._kept and self._kept[0].seq <= n:
            e = self._kept.popleft()
            if e.frames is None:
                self._gone -= 1
            else:
                self._forget(e)
        self.acked = max(self.acked, n)

    def resend_after(self, n: int, newest: bool = True) -> tuple[list[list[Frame]], int]:
        """A resume: the peer took every message up to ``n``. Returns the kept messages after ``n``
        (each one's frames), in order, and how many messages after ``n`` are lost (forgotten past the
        bound). ``newest``: of each key only the newest is resent (the others are superseded, counted),
        numbered again after ``n`` and the lost ones; False (the peer's ``n`` is a guess): all, with
        their first numbers. Raises :class:`ProtocolError` for a number never sent."""
        self.ack(n)
        lost = max(0, self.last - self.acked - len(self._kept) - self._removed)
        if newest:
            keep = []
            for e in self._kept:
                if e.frames is not None and e.newest_of is not None and self._newest.get(e.newest_of) is not e:
                    self._supersede(e)                  # caught in flight by the cut; a newer one is kept
                elif e.frames is not None:
                    keep.append(e)
            seq = self.acked + lost
            for e in keep:
                seq += 1
                if e.seq != seq:
                    e.frames[0] = _renumbered(e.frames[0], e.seq, seq)
                    e.seq = seq
            self._kept = deque(keep)
            self.last = seq
        else:
            self._kept = deque(e for e in self._kept if e.frames is not None)
        self._cut, self._gone, self._removed = None, 0, 0
        return [e.frames for e in self._kept], lost

    def clear(self) -> None:
        """Keep nothing more (the peer does not resume)."""
        self._kept.clear()
        self._newest.clear()
        self._bytes = self._live = self._gone = self._removed = 0


def _renumbered(text: Frame, old: int, new: int) -> str:
    """Message text frame ``text`` numbered ``old`` (``{"type": T, "seq": old, ...}``, as :meth:`Outgoing.numbered`
    encodes it) with ``new`` instead."""
    head = f'"seq":{old},'
    at = text.find(head) if isinstance(text, str) else -1
    if at < 0:
        raise ProtocolError(f"resume: kept message {old} has no envelope seq to renumber")
    return f'{text[:at]}"seq":{new},{text[at + len(head):]}'


class Incoming:
    """Numbered messages taken from the peer: each once, and an AK when due.

    :attr:`last`: the number of the last message taken (what a resume reports as taken);
    :attr:`duplicates`: resent messages dropped; :attr:`gaps`: numbers skipped (messages the
    peer's buffer lost)."""

    def __init__(self, ack_every: int = ACK_EVERY, ack_delay: float = ACK_DELAY):
        self.ack_every, self.ack_delay = ack_every, ack_delay
        self.last = 0
        self.acked = 0
        self.duplicates = 0
        self.gaps = 0
        self._unacked = 0                        # messages taken since the last AK
        self._since: float | None = None         # when the first of them was taken

    def take(self, seq: int | None, now: float) -> bool:
        """Message ``seq`` (None: the next one) arrived complete at ``now`` (s). False: a duplicate."""
        if seq is None:
            seq = self.last + 1
        if seq <= self.last:
            self.duplicates += 1
            return False
        self.gaps += seq - self.last - 1
        self.last = seq
        self._unacked += 1
        if self._since is None:
            self._since = now
        return True

    def ack_due(self, now: float) -> int | None:
        """The number to ack now (and count it acked), or None: ``ack_every`` messages are unacked,
        or the oldest unacked one came ``ack_delay`` s ago."""
        if not self._unacked or (self._unacked < self.ack_every and now - self._since < self.ack_delay):
            return None
        self.reported()
        return self.last

    def reported(self) -> None:
        """The peer learnt :attr:`last` (an AK, a resume's query or ST): nothing is unacked."""
        self.acked, self._unacked, self._since = self.last, 0, None
