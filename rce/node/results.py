"""A node's result latency, measured where it happens: from an input message's arrival at the
node to the output it causes (sans I/O; the node runtime feeds it, :mod:`rce.node.runtime`).

An output is caused by an input when

1. it is published while the node's subscriber callback for that input runs (a sync callback,
   or an async one and everything it awaits): the usual ``callback -> compute -> publish``;
2. else, when the output carries a ``header.stamp`` that an input carried (a node that publishes
   from a timer what it computed from a stamped input, as ROS nodes stamp their results with their
   sources' time: ``message_filters``, costmaps, scan matchers).

An output that neither rule ties to an input is not a result and is not timed. The latency is the
node's own (queueing in the node and compute); the placer adds the links around it
(:mod:`rce_master.placement.placer`). The environment asks each node for its samples (``node_results``) and
counts them against the container's deadline (:class:`ResultStats`).
"""
from __future__ import annotations

import contextvars
from collections import OrderedDict, deque

__all__ = ["INPUT_ARRIVAL", "MAX_SAMPLES", "MAX_STAMPS", "ResultClock", "ResultStats", "stamp_of"]

#: ``[arrival, running]`` of the input whose callback runs in this context: its arrival (monotonic s) and
#: whether its callback still runs (a task the callback started outlives it, and is no longer its result)
INPUT_ARRIVAL: contextvars.ContextVar[list | None] = contextvars.ContextVar("rce_input_arrival", default=None)
MAX_SAMPLES = 4096     # samples a node keeps between two asks; more are counted in ``overflow``
MAX_STAMPS = 256       # input stamps a node remembers for rule 2
KEPT = 512             # latencies a container keeps for its percentiles
RECENT_S = 2.0         # s of latencies in ``recent_p50_ms`` and ``recent_p90_ms``: what the placer reacts to
LATE_S = 10.0          # s of results in ``late_results`` and ``late_misses``: the share late where it runs


def stamp_of(msg) -> tuple[int, int] | None:
    """``(sec, nanosec)`` of ``msg.header.stamp`` (a typestore instance or a JSON-form dict), or None
    without one."""
    if isinstance(msg, dict):                 # a JSON-form message (rce.messages.forms)
        stamp = (msg.get("header") or {}).get("stamp") if isinstance(msg.get("header"), dict) else None
        if not isinstance(stamp, dict):
            return None
        sec = stamp.get("secs", stamp.get("sec"))
        return None if sec is None else (sec, stamp.get("nsecs", stamp.get("nanosec", 0)))
    header = getattr(msg, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None:
        return None
    sec = getattr(stamp, "sec", None)
    return None if sec is None else (sec, getattr(stamp, "nanosec", 0))


class ResultClock:
    """One node's samples: :meth:`arrived` for each stamped input, :meth:`published` for each
    output; :meth:`take` hands the latencies (ms) gathered since the last take."""

    def __init__(self) -> None:
        self.samples: list[float] = []
        self.results = 0
        self.overflow = 0
        self._stamps: OrderedDict[tuple[int, int], float] = OrderedDict()

    def arrived(self, stamp: tuple[int, int] | None, t: float) -> None:
        """A stamped input arrived at monotonic ``t`` s (rule 2 of the module doc)."""
        if stamp is None or stamp in self._stamps:
            return
        self._stamps[stamp] = t
        if len(self._stamps) > MAX_STAMPS:
            self._stamps.popitem(last=False)

    def published(self, msg, now: float) -> None:
        """An output ``msg`` published at monotonic ``now`` s: a result if the module doc's rules
        tie it to an input."""
        h = INPUT_ARRIVAL.get()
        t_in = h[0] if h is not None and h[1] else None
        if t_in is None:
            stamp = stamp_of(msg) if self._stamps else None
            t_in = self._stamps.get(stamp) if stamp is not None else None
            if t_in is None:
                return
        self.results += 1
        if len(self.samples) < MAX_SAMPLES:
            self.samples.append(1e3 * max(0.0, now - t_in))
        else:
            self.overflow += 1

    def take(self) -> dict:
        """``{results, samples: [ms...], overflow}``: every result so far, the latencies since the
        last take, and how many of those were not kept (more than :data:`MAX_SAMPLES`)."""
        out = {"results": self.results, "samples": [round(s, 3) for s in self.samples], "overflow": self.overflow}
        self.samples, self.overflow = [], 0
        return out


class ResultStats:
    """A container's results over its nodes, against its deadline ``deadline_ms`` (None: none):
    ``results`` and ``misses`` since it started, percentiles over the last :data:`KEPT`."""

    def __init__(self, deadline_ms: float | None = None):
        self.deadline_ms = deadline_ms
        self.results = self.misses = self.unseen = 0
        self.recent: deque[tuple[float, float]] = deque(maxlen=KEPT)     # (added: monotonic s, ms)

    def add(self, report: dict, now: float) -> None:
        """Add one node's :meth:`ResultClock.take`, collected at monotonic ``now`` s; ignores a
        malformed report."""
        samples = report.get("samples") if isinstance(report, dict) else None
        if not isinstance(samples, list):
            return
        ms = [float(s) for s in samples if isinstance(s, (int, float))]
        self.results += len(ms) + int(report.get("overflow") or 0)
        self.unseen += int(report.get("overflow") or 0)
        self.recent.extend((now, m) for m in ms)
        if self.deadline_ms is not None:
            self.misses += sum(1 for s in ms if s > self.deadline_ms)

    def stats(self, now: float) -> dict:
        """``{results, misses, deadline_ms, p50_ms, p99_ms, max_ms, recent_p50_ms, recent_p90_ms,
        late_results, late_misses, unseen}`` at monotonic ``now`` s: percentiles over the last
        :data:`KEPT` results (None before the first); ``recent_*`` over those of the last
        :data:`RECENT_S` s (None without any); ``late_*``: the results of the last :data:`LATE_S` s
        and how many of them missed the deadline (what the placer reacts to); ``unseen``: results a
        node could not keep a sample of."""
        r = sorted(m for _, m in self.recent)
        fresh = sorted(m for t, m in self.recent if now - t <= RECENT_S)

        def pct(xs: list[float], q: float) -> float | None:
            return round(xs[min(len(xs) - 1, int(q * len(xs)))], 3) if xs else None
        window = [m for t, m in self.recent if now - t <= LATE_S]
        late = sum(1 for m in window if self.deadline_ms is not None and m > self.deadline_ms)
        return {"results": self.results, "misses": self.misses, "deadline_ms": self.deadline_ms,
                "p50_ms": pct(r, 0.5), "p99_ms": pct(r, 0.99), "max_ms": round(r[-1], 3) if r else None,
                "recent_p50_ms": pct(fresh, 0.5), "recent_p90_ms": pct(fresh, 0.9),
                "late_results": len(window), "late_misses": late, "unseen": self.unseen}
