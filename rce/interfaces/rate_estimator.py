"""The bulk lane's path rate, estimated from the sender's TCP state, sans I/O (docs/lanes.md "Pacing").

When no rate is configured, a bulk link's :class:`~rce.interfaces.pacer.Pacer` follows a
:class:`RateEstimator`: the transport reads the bulk socket's Linux ``TCP_INFO`` as it writes
(:class:`rce.transport.lane_socket.PacedLink`) and feeds it here as :class:`PathSample`\\ s; the
estimator says the rate to pace at (:attr:`RateEstimator.rate`) and what it believes the path's
bottleneck rate is (:attr:`RateEstimator.estimate`).

The signals are those BBR reads from the kernel (Cardwell, Cheng, Gunn, Hassas Yeganeh, Jacobson, "BBR:
Congestion-Based Congestion Control", ACM Queue 14(5), 2016): a bottleneck drains at its rate whatever
is sent into it, and the round-trip time grows only once a queue stands in front of it. The reaction
to queueing delay is LEDBAT's (RFC 6817): a sender of bulk data backs off as soon as the delay it adds to
the path passes a small target, so that the path's other traffic (here: the session's control lane,
behind the same FIFO where a bottleneck ignores DSCP) does not wait behind it.

In intervals of at least :data:`MIN_INTERVAL` s and two minimum round trips:

- **Held back**: the pacer made the sender wait for at least :data:`HELD_SHARE` of the interval, or
  the kernel holds more than :data:`NOTSENT_LIMIT` bytes written but not sent (``tcpi_notsent_bytes``):
  the application has more to send than goes out. Only such intervals say something about the path;
  in the others the estimate stays.
- **Congested**: the path did not take what was sent: the smoothed RTT (``tcpi_rtt``) is more than the
  queue target above the path's minimum (``tcpi_min_rtt``) while less than :data:`TAKEN_SHARE` of the
  pacer's rate was acked (``tcpi_bytes_acked``), or it is :data:`QUEUE_HIGH` targets above whatever
  was acked. The bottleneck was busy, so the bytes acked per second over the interval are its rate:
  that is the estimate (lowered by :data:`STEP_DOWN` at most per interval, against one noisy RTT). The
  pacer then drains the queue at :data:`DRAIN_GAIN` x the estimate until the RTT shows it gone (the path
  acking more than the drain's rate only says it is draining). If the RTT still shows one after
  :data:`MAX_DRAIN` intervals, what was acked over the last :data:`RATE_WINDOW` s (on a loaded host acks
  come in bursts: one interval's count is noise) says why: less than the drain's rate, the path is
  slower yet, and that is the estimate; about the drain's rate, there is no queue of ours to drain
  (the RTT is noisy, or the queue another flow's), and the pacer cruises; more, it is still draining.
- **Cruise**: the pacer runs at :data:`CRUISE_GAIN` x the estimate, under the link, so the
  bottleneck's queue stays empty.
- **Probe**: after :data:`PROBE_EVERY` cruise intervals held back, one interval at :data:`PROBE_GAIN` x
  the estimate (BBR probes at 1.25 for a round trip; a FIFO shared with control holds less at 1.1): if
  the path takes it without a queue, the estimate rises to what was acked, and while it rises by
  :data:`PROBE_ROOM` or more the probing goes on.
- **Startup**: from :data:`INITIAL_RATE` the rate doubles every interval held back (BBR's startup,
  gain 2), but to twice what the path acked over the last :data:`RATE_WINDOW` s at most (the pacer's
  rate can run ahead of what the path takes: about x1.5 an interval while the path takes it all, twice
  the path's rate at most once it takes no more; never down), until the first sample that shows a
  queue of :data:`STARTUP_QUEUE_TARGET` (half an interval in, at the earliest; the smoothed RTT shows
  the doubling's queue late: a smaller target than cruise's, intervals of :data:`MIN_INTERVAL`), or
  until a doubling raised what the path acked by less than :data:`FULL_GROWTH` (BBR's full pipe; with
  :data:`FULL_BYTES` acked in the window at least, against the acks' noise). The first estimate is what
  was acked over the last :data:`RATE_WINDOW` s (not one interval: on a loaded host acks come in
  bursts), and the queue the doubling left drains at :data:`STARTUP_DRAIN_GAIN` x the estimate; then it
  probes at once (as BBR's drain leads to probing), the estimate having been read over a ramp.
- An interval with no byte acked (a stalled path) changes nothing; one longer than
  :data:`MAX_INTERVAL` (an idle spell) is not judged.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import Enum

INITIAL_RATE = 125_000.0    # bytes/s the pacer starts at (1 Mbit/s), doubling each interval until a queue shows
MIN_RATE = 12_500.0         # bytes/s, the lowest estimate (100 kbit/s)
MIN_INTERVAL = 0.08         # s, the shortest interval the estimator judges (also at least 2 minimum RTTs)
MAX_INTERVAL = 1.0          # s; a longer gap between samples is an idle spell: the interval starts again
QUEUE_TARGET = 0.010        # s of queueing delay that counts as a queue (RFC 6817's TARGET, scaled to control)
STARTUP_QUEUE_TARGET = 0.003   # s, the same in startup: the smoothed RTT shows the doubling's queue late
TARGET_PACKETS = 4          # ... at least the time of this many full packets at the rate (delayed ACKs on a slow path)
PACKET = 1500               # bytes of a full packet
NOTSENT_LIMIT = 64 * 1024   # bytes the kernel holds unsent past which the sender counts as held back
HELD_SHARE = 0.5            # share of an interval the pacer made the sender wait, for the interval to count
TAKEN_SHARE = 0.95          # a queue with at least this share of the pacer's rate acked is noise, not the path's
QUEUE_HIGH = 3              # queue targets past which a queue counts whatever was acked
STARTUP_GAIN = 2.0
CRUISE_GAIN = 0.9           # the pacer's rate in cruise, as a share of the estimate: under the link
DRAIN_GAIN = 0.75
STARTUP_DRAIN_GAIN = 0.5    # after startup's overshoot (BBR drains at 1/2.89 after a startup at 2.89)
PROBE_GAIN = 1.1            # BBR probes at 1.25; a FIFO bottleneck shared with control holds less at 1.1
PROBE_EVERY = 16            # cruise intervals (held back) between probes
PROBE_ROOM = 1.05           # a probe that raised the estimate by this factor or more is followed by another
MAX_DRAIN = 4               # drain intervals that still show a queue after which the estimate is taken again
STEP_DOWN = 0.9             # the most one congested interval lowers the estimate by (a queue that stays: more)
FULL_GROWTH = 1.25          # startup ends when a doubling raised what the path acked by less (BBR's full pipe)
FULL_BYTES = 128 * 1024     # ... over a window of at least these bytes acked (fewer: the acks' noise)
RATE_WINDOW = 0.16          # s: the least span a path's rate is read over at the end of startup or a drain


class Mode(str, Enum):
    """What the estimator is doing (module doc): finding the path's rate, cruising under it, probing
    above it, or draining a queue it saw."""
    STARTUP = "startup"
    CRUISE = "cruise"
    PROBE = "probe"
    DRAIN = "drain"


@dataclass(frozen=True)
class PathSample:
    """One reading of a bulk link's TCP state (Linux ``TCP_INFO``) at ``t`` (s, monotonic):
    ``acked``: bytes acked since the connection began (``tcpi_bytes_acked``); ``rtt``: the smoothed
    round trip (``tcpi_rtt``, s); ``min_rtt``: the least round trip seen (``tcpi_min_rtt``, s);
    ``notsent``: bytes written but not yet sent (``tcpi_notsent_bytes``); ``waited``: s the pacer made
    the sender wait since the previous sample (the application had more to send than the rate)."""
    t: float
    acked: int
    rtt: float
    min_rtt: float
    notsent: int
    waited: float


class RateEstimator:
    """A bulk link's bottleneck rate and the rate to pace at, from :class:`PathSample`\\ s (module doc).

    :attr:`rate`: bytes/s to pace at (starts at ``initial``); :attr:`estimate`: the path's rate in
    bytes/s (None until a first queue showed it); :attr:`mode`. Counters: :attr:`samples`,
    :attr:`intervals` (judged), :attr:`backoffs` (congested intervals), :attr:`probes`. Raises
    ValueError for an ``initial`` rate that is not > 0."""

    def __init__(self, initial: float = INITIAL_RATE):
        if initial <= 0:
            raise ValueError(f"a rate estimator needs an initial rate > 0, got {initial!r} bytes/s")
        self.mode = Mode.STARTUP
        self.rate = float(initial)
        self.estimate: float | None = None
        self.samples = self.intervals = self.backoffs = self.probes = 0
        self._start: PathSample | None = None     # the sample that began the current interval
        self._waited = 0.0                        # s the pacer held the sender back in the current interval
        self._cruised = 0                         # cruise intervals with data held back since the last probe
        self._drained = 0                         # drain intervals that still showed a queue
        self._ramp: float | None = None           # bytes/s acked over the window when startup last doubled
        self._first_drain = False                 # draining what startup left
        self._ends: deque[PathSample] = deque(maxlen=16)     # the samples that ended the last judged intervals

    def sample(self, s: PathSample) -> None:
        """Take sample ``s`` (samples come in time order; one older than the last is ignored). When it
        ends an interval, the interval is judged and :attr:`rate` may change."""
        start = self._start
        if start is not None and s.t < start.t:
            return
        self.samples += 1
        if start is None or s.t - start.t > MAX_INTERVAL or s.acked < start.acked:
            self._begin(s)          # the first, after an idle spell, or a new connection's counters
            return
        self._waited += s.waited
        dt = s.t - start.t
        queue = max(0.0, s.rtt - s.min_rtt)
        startup = self.mode is Mode.STARTUP
        shortest = max(MIN_INTERVAL, 2 * s.min_rtt)
        if dt < shortest and not (startup and dt >= shortest / 2 and queue > self.target()):
            return                  # (startup ends at the first sample that shows a queue)
        self._ends.append(start)
        self._judge(delivered=(s.acked - start.acked) / dt, queue=queue,
                    held=self._waited >= HELD_SHARE * dt or s.notsent > NOTSENT_LIMIT, now=s)
        self._begin(s)

    def _windowed(self, now: PathSample) -> float:
        """bytes/s acked up to ``now`` since the latest interval boundary at least :data:`RATE_WINDOW` s
        before it (or the earliest kept): one interval's rate is noisy where acks come in bursts."""
        return self._window(now)[0]

    def _window(self, now: PathSample) -> tuple[float, int]:
        """(bytes/s, bytes) acked over :meth:`_windowed`'s window."""
        first = self._ends[0]
        for s in reversed(self._ends):
            if now.t - s.t >= RATE_WINDOW:
                first = s
                break
        acked = now.acked - first.acked
        return (acked / (now.t - first.t) if now.t > first.t else 0.0), acked

    def _begin(self, s: PathSample) -> None:
        self._start, self._waited = s, 0.0

    def target(self) -> float:
        """s of queueing delay that counts as a queue at the current rate: :data:`QUEUE_TARGET`
        (:data:`STARTUP_QUEUE_TARGET` in startup), or the time of :data:`TARGET_PACKETS` full packets at
        :attr:`rate` if longer."""
        least = STARTUP_QUEUE_TARGET if self.mode is Mode.STARTUP else QUEUE_TARGET
        return max(least, TARGET_PACKETS * PACKET / self.rate)

    def _judge(self, delivered: float, queue: float, held: bool, now: PathSample) -> None:
        self.intervals += 1
        target = self.target()
        congested = (queue > target and delivered < TAKEN_SHARE * self.rate) or queue > QUEUE_HIGH * target
        if self.mode is Mode.DRAIN:
            if queue <= target:
                self._drained_out()    # the queue is gone (not merely draining: the path taking the rate)
            else:
                self._drained += 1
                windowed = self._windowed(now)
                if self._drained < MAX_DRAIN or windowed <= 0:
                    return
                if windowed < TAKEN_SHARE * self.rate:      # still a queue: the path is slower yet
                    self._set(max(windowed, MIN_RATE), Mode.DRAIN)
                    self._drained = 0
                elif windowed * TAKEN_SHARE <= self.rate:    # it acks what is sent, no more: no queue of ours
                    self._drained_out()    # to drain (the round trip is noisy, or another flow's queue)
            return
        if not held or delivered <= 0:
            return                     # the application sent less than the rate, or nothing was acked
        if congested:
            self.backoffs += 1
            self._drained = 0
            if self.estimate is None:  # the end of startup: the pipe filled in the last intervals
                self._end_startup(self._windowed(now))
            else:                      # one interval moves it by STEP_DOWN at most; a queue that stays, more
                self._set(min(self.estimate, max(delivered, STEP_DOWN * self.estimate)), Mode.DRAIN)
            return
        if self.mode is Mode.STARTUP:
            windowed, acked = self._window(now)
            if acked < FULL_BYTES:
                self._ramp = None      # too few bytes to tell the path's rate from the acks' noise
            elif self._ramp is not None and windowed < FULL_GROWTH * self._ramp:
                self.backoffs += 1     # the rate doubled and the path acked hardly more: the pipe is full
                self._end_startup(windowed)
                return
            else:
                self._ramp = windowed
            # twice what the path acked, not twice what the pacer let out (never less than now)
            self.rate = max(self.rate, min(STARTUP_GAIN * self.rate, STARTUP_GAIN * windowed))
        elif self.mode is Mode.PROBE:
            before = self.estimate
            self.estimate = max(before, min(delivered, self.rate))
            if self.estimate >= PROBE_ROOM * before:
                self._probe()          # the path took more: probe on from the new estimate
            else:
                self._cruise()
        else:
            self._cruised += 1
            if self._cruised >= PROBE_EVERY:
                self._probe()

    def _end_startup(self, estimate: float) -> None:
        """Startup found the path's rate: drain the queue its doubling left, then probe from there."""
        self._set(max(estimate, MIN_RATE), Mode.DRAIN)
        self.rate = STARTUP_DRAIN_GAIN * self.estimate
        self._first_drain = True

    def _drained_out(self) -> None:
        """The drain is over: after startup's, probe at once (its estimate read a ramp, and may be low);
        after another, cruise."""
        if self._first_drain:
            self._first_drain = False
            self._probe()
        else:
            self._cruise()

    def _set(self, estimate: float, mode: Mode) -> None:
        self.estimate, self.mode = estimate, mode
        self.rate = DRAIN_GAIN * estimate

    def _cruise(self) -> None:
        self.mode, self._cruised = Mode.CRUISE, 0
        self.rate = CRUISE_GAIN * self.estimate

    def _probe(self) -> None:
        self.mode = Mode.PROBE
        self.probes += 1
        self.rate = PROBE_GAIN * self.estimate

    def stats(self) -> dict:
        """``rate`` and ``rate_estimate`` (bytes/s, rounded; the estimate None until known), ``rate_mode``
        (startup, cruise, probe, drain), ``rate_backoffs``, ``rate_probes``."""
        return {"rate": round(self.rate), "rate_estimate": None if self.estimate is None else round(self.estimate),
                "rate_mode": self.mode.value, "rate_backoffs": self.backoffs, "rate_probes": self.probes}
