"""What both sides of a robot session share, sans I/O (:mod:`rce.protocol.session`): frames in
(binary parts and expiry, :class:`~rce.protocol.frames.Assembler`), time in, typed events out
(:mod:`rce.protocol.events`), and resume's numbering, acks and duplicates (:mod:`rce.protocol.resume`)."""
from __future__ import annotations


from rce.plumbing.errors import ProtocolError
from rce.protocol.events import Event
from rce.protocol.frames import DEFAULT_MAX_PENDING_PARTS, Assembler
from rce.protocol.limits import PartBudget
from rce.protocol.resume import AK, Incoming, Outgoing, read_ack, read_seq


class SessionCore:
    """What both sides share: binary parts and expiry, events. A subclass takes complete messages
    (``_on_message``) and says what becomes of bad input (``_bad_input``: an ER, or a drop)."""

    max_message: int | None = None      # bytes (text: chars) of the largest frame taken; None: any

    def __init__(self, expiry: float, max_pending_bytes: int, resume: bool, resume_buffer: int, resume_bytes: int,
                 ack_every: int, ack_delay: float, max_pending_parts: int = DEFAULT_MAX_PENDING_PARTS,
                 budget: PartBudget | None = None):
        self.assembler = Assembler(expiry=expiry, max_pending_bytes=max_pending_bytes,
                                   max_pending_parts=max_pending_parts, budget=budget)
        # a bulk link's binary parts (docs/lanes.md): its messages are whole on it, never split across links
        self.bulk_assembler = Assembler(expiry=expiry, max_pending_bytes=max_pending_bytes,
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
        for reason in self.bulk_assembler.expire(now):
            self._bad_input(f"bulk link: {reason}")
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

    def _bulk_messages(self, frame: str | bytes, now: float) -> list[dict]:
        """A frame from the bulk link (docs/lanes.md) at ``now`` (s), through its own assembler: the messages
        it completes; a frame too big or refused is bad input (``bulk link: ...``)."""
        self._now = now
        if self.too_big(frame):
            self._bad_input(f"bulk link: frame of {len(frame)} bytes exceeds the limit of {self.max_message} bytes")
            return []
        try:
            return (self.bulk_assembler.feed_text(frame, now) if isinstance(frame, str)
                    else self.bulk_assembler.feed_binary(frame, now))
        except ProtocolError as e:
            self._bad_input(f"bulk link: {e.message}")
            return []

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
