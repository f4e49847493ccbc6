"""Bulk data paced below the link's rate and cut into small frames, sans I/O (docs/lanes.md "Pacing").

A queue at a bottleneck that ignores DSCP marks (one FIFO) fills up with whatever is sent faster than
the link drains it; a control message behind it waits for all of it. Sending bulk data a little below
the link's rate keeps that queue short, whatever the bottleneck does.

- :class:`Pacer`: a token bucket in bytes (``rate`` bytes/s, ``burst`` bytes; RFC 2697's
  committed-rate bucket, one colour): :meth:`Pacer.delay` says how long the next ``n`` bytes wait.
- :func:`chunks`: a message's bytes cut into frames of at most :data:`~rce.interfaces.lanes.BULK_SIZE`,
  so the pacer works at fine grain (RFC 6455 section 5.4: the fragments of one message cannot be
  interleaved with another's on one websocket, which is why control has its own connection).
- :func:`parse_rate`: a rate given as bytes/s (``1250000``, ``1.25MB``) or bits/s (``10Mbit``);
  :func:`parse_pacing` also takes ``auto`` (the rate estimated, :mod:`rce.interfaces.rate_estimator`) and
  ``off``; :func:`new_pacer` makes the pacer a setting asks for.
"""
from __future__ import annotations

import argparse
import re
from collections.abc import Iterator

from rce.interfaces.lanes import BULK_SIZE
from rce.interfaces.rate_estimator import PathSample, RateEstimator

DEFAULT_BURST = 2 * BULK_SIZE       # bytes the pacer lets out at once after an idle spell (26 ms at 10 Mbit/s)
_UNITS = {"": 1, "b": 1, "kb": 1e3, "mb": 1e6, "gb": 1e9, "kib": 1024, "mib": 1024 ** 2,
          "bit": 1 / 8, "kbit": 1e3 / 8, "mbit": 1e6 / 8, "gbit": 1e9 / 8}
AUTO, OFF = "auto", "off"         # a bulk link's pacing: its rate estimated, or not paced
Pacing = float | str              # bytes/s, AUTO or OFF
_RATE = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*([a-zA-Z]*)(?:/s|ps)?\s*$")


def parse_rate(text: str) -> float:
    """Bytes/s of ``text``: a number of bytes/s, or a number with a unit: ``B``, ``kB``, ``MB``, ``GB``,
    ``KiB``, ``MiB`` (bytes) or ``bit``, ``kbit``, ``Mbit``, ``Gbit`` (bits; ``/s`` or ``ps`` may follow).
    Raises ValueError naming the value for anything else, or a rate that is not > 0."""
    m = _RATE.match(str(text))
    unit = m.group(2).lower() if m else None
    if m is None or unit not in _UNITS:
        raise ValueError(f"rate {text!r}: expected bytes/s, or a number with a unit (e.g. 1.25MB, 10Mbit)")
    rate = float(m.group(1)) * _UNITS[unit]
    if rate <= 0:
        raise ValueError(f"rate {text!r} must be > 0")
    return rate


def parse_pacing(text: str) -> Pacing:
    """A bulk link's pacing: ``auto`` (:data:`AUTO`: the path's rate estimated), ``off`` (:data:`OFF`:
    not paced), or a rate (:func:`parse_rate`, bytes/s). Raises ValueError as :func:`parse_rate`."""
    word = str(text).strip().lower()
    return word if word in (AUTO, OFF) else parse_rate(text)


def rate_arg(text: str) -> Pacing:
    """An argparse type: :func:`parse_pacing`, its refusal as argparse's error (``--bulk-rate``,
    ``--uplink-rate``)."""
    try:
        return parse_pacing(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def new_pacer(pacing: Pacing | None) -> "Pacer | None":
    """The pacer of a bulk link paced as ``pacing`` says: bytes/s (a configured rate), :data:`AUTO` or
    None (the rate estimated: a :class:`Pacer` driven by a :class:`RateEstimator`), :data:`OFF` (None: not
    paced). Raises ValueError for a rate that is not > 0 or another word."""
    if pacing == OFF:
        return None
    if pacing is None or pacing == AUTO:
        est = RateEstimator()
        return Pacer(est.rate, estimator=est)
    if isinstance(pacing, str):
        raise ValueError(f"pacing {pacing!r}: expected a rate in bytes/s, {AUTO!r} or {OFF!r}")
    return Pacer(pacing)


class Pacer:
    """``rate`` bytes/s on average, at most ``burst`` bytes at once; starts full. With ``estimator`` the
    rate is not configured but follows the path (:meth:`observe`). Raises ValueError for a rate or burst
    that is not > 0."""

    def __init__(self, rate: float, burst: int = DEFAULT_BURST, estimator: RateEstimator | None = None):
        if rate <= 0 or burst <= 0:
            raise ValueError(f"a pacer needs a rate and a burst > 0, got {rate!r} bytes/s, {burst!r} bytes")
        self.rate, self.burst = float(rate), float(burst)
        self.estimator = estimator
        self.tokens = self.burst
        self.last: float | None = None
        self.paced = 0.0                # s waited in all
        self._observed = 0.0            # :attr:`paced` at the last :meth:`observe`

    def _fill(self, now: float) -> None:
        if self.last is not None:
            self.tokens = min(self.burst, self.tokens + (now - self.last) * self.rate)
        self.last = now

    def delay(self, n: int, now: float) -> float:
        """s until ``n`` bytes may go at ``now`` (s, monotonic); 0: now. ``n`` larger than the burst waits
        for as many tokens as the burst holds, then goes into debt (the next bytes wait for it)."""
        self._fill(now)
        need = min(float(n), self.burst)
        return 0.0 if self.tokens >= need else (need - self.tokens) / self.rate

    def spend(self, n: int, now: float) -> None:
        """``n`` bytes went out at ``now`` (s): spend them (the bucket may go below 0, a debt)."""
        self._fill(now)
        self.tokens -= n

    def waited(self, s: float) -> None:
        """The sender waited ``s`` s for the pacer (counted in :attr:`paced`)."""
        self.paced += s

    def held(self) -> float:
        """s the sender waited for this pacer since the last :meth:`observe` (:meth:`waited`)."""
        return self.paced - self._observed

    def observe(self, sample: PathSample, now: float) -> None:
        """(with an estimator) The path's state at ``now`` (s; its ``waited``: :meth:`held`): fed to the
        estimator, whose rate becomes this pacer's from ``now`` on. Bytes the kernel holds unsent
        (``notsent``) count as let out but not yet gone: past a burst they are this pacer's debt, so no
        more goes until the kernel has sent them (a rate that fell, after startup's overshoot, would
        otherwise leave a backlog the kernel sends at its own, higher pace)."""
        if self.estimator is None:
            return
        self._fill(now)
        self._observed = self.paced
        self.estimator.sample(sample)
        self.rate = self.estimator.rate
        self.tokens = min(self.tokens, self.burst - sample.notsent)

    def stats(self) -> dict:
        """``rate_source`` (configured, estimated), ``rate`` (bytes/s); with an estimator also its
        :meth:`RateEstimator.stats` (the estimate, the mode, back-offs and probes)."""
        if self.estimator is None:
            return {"rate_source": "configured", "rate": round(self.rate)}
        return {"rate_source": "estimated", **self.estimator.stats()}


def chunks(data: bytes | memoryview, size: int = BULK_SIZE) -> Iterator[memoryview]:
    """``data`` in frames of at most ``size`` bytes, in order (one empty frame for empty data)."""
    view = memoryview(data)
    if not len(view):
        yield view
        return
    for i in range(0, len(view), size):
        yield view[i:i + size]
