"""What waits to go to a peer that may not keep up, sans I/O: one bounded outbox with one policy
(docs/INTERNALS.md "A peer that does not keep up"), used by the RCE robot session
(:class:`~rce.protocol.robot_session.RobotSession`) and the rosbridge session
(:mod:`rce_robot.rosbridge.outbox`).

- Control items (statuses, answers, errors) are never dropped here; the owner bounds them.
- Data items (topic messages) are keyed by their interface (or topic) and keep each key's newest,
  as a ROS publisher's queue does: past ``queue_size`` waiting data items, the oldest of the key
  with the most waiting is dropped for the new one; and a data item that has waited longer than
  ``max_lag`` s when its turn comes (:meth:`Outbox.take` with ``now``) is dropped if a newer one
  of its key waits behind it. Both are counted in :attr:`Outbox.dropped` (the second also in
  :attr:`Outbox.expired`). So the newest item of every key goes out, however late.

A dropped data item keeps its place, marked gone, until ``queue_size`` such wait; then the queue is
rebuilt without them: a peer that never reads costs at most twice the bound, in amortized O(1) per item.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

T = TypeVar("T")


@dataclass(slots=True)
class _Queued:
    item: Any
    key: Any = None                 # a data item's key (its interface or topic); None: a control item
    since: float = 0.0              # s: when a data item was queued (its age counts from it)
    gone: bool = False              # a data item given up while it waited: nothing goes out for it


class Outbox(Generic[T]):
    """Items of type ``T`` waiting for a peer, in order. ``queue_size`` (>= 1): data items waiting
    before the busiest key drops its oldest; ``max_lag``: s a data item may wait while a newer one of
    its key waits behind it (None: no age limit).

    Counters: :attr:`dropped` (data items dropped, for the bound or their age), :attr:`expired` (of
    those, for their age), :attr:`data` (data items waiting), :attr:`control` (control items waiting)."""

    def __init__(self, queue_size: int, max_lag: float | None = None):
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        self.queue_size, self.max_lag = queue_size, max_lag
        self._entries: deque[_Queued] = deque()
        self._by_key: dict[Any, deque[_Queued]] = {}    # key -> its data items waiting, oldest first
        self._gone = 0                                  # entries given up, still in _entries
        self.data = self.control = 0
        self.dropped = self.expired = 0

    def __len__(self) -> int:
        """Items waiting (data items dropped not counted)."""
        return len(self._entries) - self._gone

    @property
    def places(self) -> int:
        """Places held in the queue, dropped data items waiting to be reclaimed included."""
        return len(self._entries)

    def put(self, item: T) -> None:
        """Queue control item ``item`` (never dropped here)."""
        self.control += 1
        self._entries.append(_Queued(item))

    def put_data(self, key: Any, item: T, now: float) -> None:
        """Queue data item ``item`` of key ``key`` at time ``now`` (s); when ``queue_size`` data items
        already wait, the oldest of the key with the most waiting is dropped (counted)."""
        if self.data >= self.queue_size:
            busiest = max(self._by_key, key=lambda k: len(self._by_key[k]))
            self._give_up(self._oldest_of(busiest))
        e = _Queued(item, key, now)
        self.data += 1
        self._by_key.setdefault(key, deque()).append(e)
        self._entries.append(e)

    def take(self, now: float | None = None) -> T | None:
        """The next item to send (None when none waits). ``now`` (s): a data item older than ``max_lag``
        with a newer one of its key behind it is dropped instead (counted); None: none is."""
        stale = None if now is None or self.max_lag is None else now - self.max_lag
        while self._entries:
            e = self._entries.popleft()
            if e.gone:
                self._gone -= 1
                continue
            if e.key is not None:
                self._oldest_of(e.key)              # e: its key's oldest data item still waiting
                self.data -= 1
                if stale is not None and e.since < stale and e.key in self._by_key:     # a newer one waits
                    self.dropped += 1
                    self.expired += 1
                    continue
            else:
                self.control -= 1
            return e.item
        return None

    def drain(self) -> list[T]:
        """Every item waiting, in order, taken off the queue (the link is lost; nothing is counted)."""
        items = [e.item for e in self._entries if not e.gone]
        self._entries.clear()
        self._by_key.clear()
        self._gone = self.data = self.control = 0
        return items

    def _oldest_of(self, key: Any) -> _Queued:
        """The oldest waiting data item of ``key``, taken off its key's queue."""
        q = self._by_key[key]
        e = q.popleft()
        if not q:
            del self._by_key[key]
        return e

    def _give_up(self, e: _Queued) -> None:
        e.gone, e.item = True, None
        self.data -= 1
        self._gone += 1
        self.dropped += 1
        if self._gone > self.queue_size:
            self._entries = deque(x for x in self._entries if not x.gone)
            self._gone = 0
