"""The ERs one robot session sends, sans I/O: cut to :data:`~rce.protocol.limits.MAX_ER_TEXT` bytes,
those for bad input at most ``rate`` per s and ``burst`` at once (a token bucket), and at most
``queue_size`` waiting unread. What is dropped is counted, and the next ER that goes out (or one of its
own, :meth:`ErrorLimits.due`) says how many (docs/SECURITY.md "Limits")."""
from __future__ import annotations

from rce.protocol.limits import TokenBucket, truncate


class ErrorLimits:
    """ER accounting of robot ``robot``'s session. Counters: :attr:`sent` (ERs queued),
    :attr:`dropped` (ERs dropped: rate, or unread); :attr:`waiting`: ERs in the outbox, kept by the
    session (up when it queues one on a link, down when it sends one)."""

    def __init__(self, robot: str, queue_size: int, rate: float, burst: int):
        self.robot, self.queue_size = robot, queue_size
        self.bucket = TokenBucket(rate, burst)
        self.sent = self.dropped = self.waiting = 0
        self._untold = 0                         # dropped and not yet told to the robot

    def admit(self, answer: bool, now: float, attached: bool) -> bool:
        """May an ER go out at ``now`` (s)? ``answer``: it answers a request or call (not rate-limited);
        ``attached``: the robot is on a link (while detached, unread ERs are not bounded here). A refusal
        is counted."""
        if (not answer and not self.bucket.take(now)) or (attached and self.waiting >= self.queue_size):
            self.dropped += 1
            self._untold += 1
            return False
        return True

    def text(self, reason: str) -> str:
        """The text of an admitted ER for ``reason``: cut short, with the note of those dropped before
        it; it counts as queued."""
        return self._queued(truncate(reason) + self._note())

    def due(self, now: float, attached: bool) -> str | None:
        """At a tick: the text of an ER of its own saying how many were dropped, when some were and the
        robot reads again (queued); else None."""
        if self._untold and attached and self.waiting < self.queue_size and self.bucket.take(now):
            return self._queued(self._note().strip(" ()"))
        return None

    def _queued(self, text: str) -> str:
        self.sent += 1
        return text

    def _note(self) -> str:
        """What an ER adds when ERs were dropped since the last one went out ("" when none were)."""
        if not self._untold:
            return ""
        n, self._untold = self._untold, 0
        return (f" ({n} error message(s) to robot {self.robot!r} before this one were dropped: more than "
                f"{self.bucket.rate:g} per s, {self.bucket.burst} at once, or {self.queue_size} unread)")
