"""Bulk data paced below the link's rate and cut into small frames, sans I/O (docs/lanes.md "Pacing").

A queue at a bottleneck that ignores DSCP marks (one FIFO) fills up with whatever is sent faster than
the link drains it; a control message behind it waits for all of it. Sending bulk data a little below
the link's rate keeps that queue short, whatever the bottleneck does.

- :class:`Pacer`: a token bucket in bytes (``rate`` bytes/s, ``burst`` bytes; RFC 2697's
  committed-rate bucket, one colour): :meth:`Pacer.delay` says how long the next ``n`` bytes wait.
- :func:`chunks`: a message's bytes cut into frames of at most :data:`~rce.protocol.lanes.BULK_SIZE`,
  so the pacer works at fine grain (RFC 6455 section 5.4: the fragments of one message cannot be
  interleaved with another's on one websocket, which is why control has its own connection).
- :func:`parse_rate`: a rate given as bytes/s (``1250000``, ``1.25MB``) or bits/s (``10Mbit``).
"""
from __future__ import annotations

import argparse
import re
from collections.abc import Iterator

from rce.protocol.lanes import BULK_SIZE

DEFAULT_BURST = 2 * BULK_SIZE       # bytes the pacer lets out at once after an idle spell (26 ms at 10 Mbit/s)
_UNITS = {"": 1, "b": 1, "kb": 1e3, "mb": 1e6, "gb": 1e9, "kib": 1024, "mib": 1024 ** 2,
          "bit": 1 / 8, "kbit": 1e3 / 8, "mbit": 1e6 / 8, "gbit": 1e9 / 8}
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


def rate_arg(text: str) -> float:
    """An argparse type: :func:`parse_rate`, its refusal as argparse's error (``--bulk-rate``, ``--uplink-rate``)."""
    try:
        return parse_rate(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


class Pacer:
    """``rate`` bytes/s on average, at most ``burst`` bytes at once; starts full. Raises ValueError for a
    rate or burst that is not > 0."""

    def __init__(self, rate: float, burst: int = DEFAULT_BURST):
        if rate <= 0 or burst <= 0:
            raise ValueError(f"a pacer needs a rate and a burst > 0, got {rate!r} bytes/s, {burst!r} bytes")
        self.rate, self.burst = float(rate), float(burst)
        self.tokens = self.burst
        self.last: float | None = None
        self.paced = 0.0                # s waited in all

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


def chunks(data: bytes | memoryview, size: int = BULK_SIZE) -> Iterator[memoryview]:
    """``data`` in frames of at most ``size`` bytes, in order (one empty frame for empty data)."""
    view = memoryview(data)
    if not len(view):
        yield view
        return
    for i in range(0, len(view), size):
        yield view[i:i + size]
