"""What waits to go to a peer, by lane, sans I/O (docs/lanes.md "Scheduling").

:class:`LaneQueues` holds one :class:`~rce.protocol.outbox.Outbox` per :class:`~rce.interfaces.lanes.Lane`
(the one outbox policy in each: control items are never dropped, data items keep each key's newest) and
takes the next item by strict priority, control before state before bulk, with a minimum share for the
lower lanes: a lane that has waited while ``starve_after`` items of higher lanes went out gets the next
turn, so it never starves (one in ``starve_after + 1`` items at least; Fast DDS's
priority-with-reservation flow controller and Zenoh's priority queues do the same job).

It also keeps each lane's counters (:class:`LaneStats`): messages and bytes sent, drops, and the queue
delay (the time from put to take, s), which the endpoint shows per lane in Prometheus and the
session's stats.
"""
from __future__ import annotations

from bisect import bisect_left
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

from rce.interfaces.lanes import Lane
from rce.protocol.outbox import Outbox

T = TypeVar("T")

STARVE_AFTER = 7            # items of higher lanes before a waiting lower lane's turn: bulk gets >= 1/8 of the turns
DELAY_BOUNDS = (0.001, 0.005, 0.01, 0.05, 0.1, 0.5, 1.0, 5.0)     # s: queue-delay histogram buckets (upper bounds)
ALL_LANES: tuple[Lane, ...] = tuple(sorted(Lane, key=lambda lane: lane.rank))    # every lane, in priority order
_RANK_OF = {lane: lane.rank for lane in ALL_LANES}      # ALL_LANES[rank] is the lane


@dataclass
class LaneStats:
    """One lane's counters: ``taken`` messages that left the queue, ``sent`` of them written whole
    (goodput in whole messages, as the owner reports with :meth:`LaneQueues.sent`), ``bytes`` of
    those, ``delay_sum``/``delay_max`` s of queue delay (put to take) and ``delay_buckets`` (counts per
    :data:`DELAY_BOUNDS` upper bound, the last for larger ones). Drops are the lane's
    :class:`~rce.protocol.outbox.Outbox`'s."""
    taken: int = 0
    sent: int = 0
    bytes: int = 0
    delay_sum: float = 0.0
    delay_max: float = 0.0
    delay_buckets: list[int] = field(default_factory=lambda: [0] * (len(DELAY_BOUNDS) + 1))

    def took(self, delay: float) -> None:
        """An item left after waiting ``delay`` s."""
        self.taken += 1
        self.delay_sum += delay
        if delay > self.delay_max:
            self.delay_max = delay
        self.delay_buckets[bisect_left(DELAY_BOUNDS, delay)] += 1     # the first bound >= delay


@dataclass(slots=True)
class _LaneItem:
    item: Any
    since: float | None          # s when put; None: not timed (its queue delay counts as 0)


_RANKS = {lanes: tuple(lane.rank for lane in lanes) for lanes in
          (ALL_LANES, (Lane.CONTROL, Lane.STATE), (Lane.CONTROL,), (Lane.STATE,), (Lane.BULK,))}


def _ranks(lanes: tuple[Lane, ...]) -> tuple[int, ...]:
    """The ranks of ``lanes``, in priority order."""
    ranks = _RANKS.get(lanes)
    return ranks if ranks is not None else tuple(sorted(lane.rank for lane in lanes))


class LaneQueues(Generic[T]):
    """Items of type ``T`` for a peer, one :class:`~rce.protocol.outbox.Outbox` per lane (each bounded
    by ``queue_size`` data items, ``max_lag`` s; see there), taken by strict priority with the
    ``starve_after`` rule (module docstring).

    It counts what waits per lane and in all as items come and go (:meth:`waiting` and an empty
    :meth:`take` cost no walk over the lanes), and works per message on lists indexed by the lane's
    rank; :attr:`lanes` and :attr:`stats` are the same outboxes and counters by lane, for reports."""

    def __init__(self, queue_size: int, max_lag: float | None = None, starve_after: int = STARVE_AFTER):
        if starve_after < 1:
            raise ValueError(f"starve_after must be >= 1, got {starve_after}")
        self.queue_size, self.starve_after = queue_size, starve_after
        self.lanes: dict[Lane, Outbox[_LaneItem]] = {lane: Outbox(queue_size, max_lag) for lane in Lane}
        self.stats: dict[Lane, LaneStats] = {lane: LaneStats() for lane in Lane}
        self._q = [self.lanes[lane] for lane in ALL_LANES]        # by rank
        self._st = [self.stats[lane] for lane in ALL_LANES]
        self._n = [0] * len(ALL_LANES)                            # items waiting, by rank
        self._total = 0                                           # items waiting, all lanes
        self._passed = [0] * len(ALL_LANES)     # by rank: items of higher lanes taken while this one waited

    def __len__(self) -> int:
        return self._total

    def waiting(self, lanes: tuple[Lane, ...] = ALL_LANES) -> int:
        """Items waiting in ``lanes``."""
        if lanes is ALL_LANES:
            return self._total
        n = self._n
        return sum(n[r] for r in _ranks(lanes))

    def _count(self, rank: int) -> None:
        """Lane ``rank``'s outbox changed: its count (and the total) again."""
        q = self._q[rank]
        n = q.data + q.control
        self._total += n - self._n[rank]
        self._n[rank] = n

    @property
    def places(self) -> int:
        """Places held (:attr:`Outbox.places`), all lanes."""
        return sum(q.places for q in self._q)

    @property
    def data(self) -> int:
        """Data items waiting, all lanes."""
        return sum(q.data for q in self._q)

    @property
    def control(self) -> int:
        """Control items (never dropped) waiting, all lanes."""
        return sum(q.control for q in self._q)

    @property
    def dropped(self) -> int:
        """Data items dropped, all lanes."""
        return sum(q.dropped for q in self._q)

    @property
    def expired(self) -> int:
        """Data items dropped for their age, all lanes."""
        return sum(q.expired for q in self._q)

    def put(self, item: T, now: float | None = None, lane: Lane = Lane.CONTROL) -> None:
        """Queue ``item`` in ``lane`` at ``now`` (s; None: not timed), never to be dropped here."""
        rank = _RANK_OF[lane]
        self._q[rank].put(_LaneItem(item, now))
        self._n[rank] += 1
        self._total += 1

    def put_data(self, key: Any, item: T, now: float, lane: Lane = Lane.STATE) -> None:
        """Queue data item ``item`` of ``key`` in ``lane`` at ``now`` (s): the lane's outbox keeps each
        key's newest (:meth:`Outbox.put_data`)."""
        rank = _RANK_OF[lane]
        self._q[rank].put_data(key, _LaneItem(item, now), now)
        self._count(rank)

    def take(self, now: float | None = None, lanes: tuple[Lane, ...] = ALL_LANES) -> tuple[Lane, T] | None:
        """The next item of ``lanes`` and its lane (None when none waits): the first lane in priority
        order that waits, unless a lower one has waited through ``starve_after`` turns. ``now`` (s):
        as :meth:`Outbox.take` (stale data dropped); also the end of the item's queue delay."""
        if not self._total:
            return None
        order = _ranks(lanes)
        n, passed = self._n, self._passed
        while True:
            waiting = [r for r in order if n[r]]
            if not waiting:
                return None
            rank = waiting[0]
            for r in reversed(waiting[1:]):          # the lowest starved lane gets the turn
                if passed[r] >= self.starve_after:
                    rank = r
                    break
            entry = self._q[rank].take(now)
            self._count(rank)
            if entry is not None:
                break                               # else everything left in it was stale: look again
        for r in order:
            passed[r] = passed[r] + 1 if r > rank and r in waiting else 0
        timed = now is not None and entry.since is not None
        self._st[rank].took(max(0.0, now - entry.since) if timed else 0.0)
        return ALL_LANES[rank], entry.item

    def through(self, lane: Lane, n: int) -> None:
        """An item of ``lane`` went out whole (``n`` bytes) without waiting, while nothing waited: counted
        as :meth:`put`, :meth:`take` at once (no queue delay) and :meth:`sent`. Raises ValueError when
        items wait (they go first)."""
        if self._total:
            raise ValueError(f"{self._total} items wait: an item cannot go past them")
        self._st[_RANK_OF[lane]].took(0.0)
        self.sent(lane, n)

    def sent(self, lane: Lane, n: int) -> None:
        """A message of ``lane`` went out whole, ``n`` bytes (the owner knows once it is written)."""
        st = self.stats[lane]
        st.sent += 1
        st.bytes += n

    def drain(self) -> list[T]:
        """Every item waiting, control lane first, taken off the queues (nothing counted)."""
        items = [e.item for q in self._q for e in q.drain()]
        self._passed = [0] * len(ALL_LANES)
        self._n = [0] * len(ALL_LANES)
        self._total = 0
        return items

    def lane_stats(self) -> dict[str, dict]:
        """Per lane: ``taken``, ``sent`` (whole messages), ``bytes``, ``dropped``, ``waiting``,
        ``delay_avg_s``, ``delay_max_s`` (the session's stats)."""
        out = {}
        for lane, s in self.stats.items():
            q = self.lanes[lane]
            out[lane.value] = {"taken": s.taken, "sent": s.sent, "bytes": s.bytes, "dropped": q.dropped,
                               "waiting": len(q), "delay_avg_s": round(s.delay_sum / s.taken, 6) if s.taken else 0.0,
                               "delay_max_s": round(s.delay_max, 6)}
        return out
