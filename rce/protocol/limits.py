"""Bounds of a robot session under hostile input, sans I/O: the JSON depth
limit, the ER text cap, the per-session ER token bucket and the endpoint-wide budget of binary
parts waiting for their message. docs/SECURITY.md "Limits" lists them with their defaults.

- :func:`json_too_deep`: a bracket-depth scan that skips strings (C-speed regular expressions),
  run before ``json.loads`` so that a deep frame costs neither a RecursionError nor a deep walk.
- :func:`rce.plumbing.text.short_repr` (the layers below use it too): a value quoted in an error, cut
  short before it is formatted.
- :func:`truncate`: the first :data:`MAX_ER_TEXT` bytes of a text (UTF-8), with a marker.
- :class:`TokenBucket`: ``rate`` tokens per s up to ``burst`` (the classic token bucket, as
  in RFC 2697's committed-burst bucket, one colour).
- :class:`PartBudget`: bytes of binary parts held by all the sessions of one robot endpoint.
- :class:`LagGate`: sheds a client's topic messages while the endpoint has been behind it for
  longer than ``max_lag`` (docs/INTERNALS.md "A peer that does not keep up").
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from itertools import accumulate

from rce.plumbing.text import SHORT_REPR, short_repr  # noqa: F401 (a session's limits quote values with it)

MAX_JSON_DEPTH = 64             # nesting of JSON arrays and objects in a frame; ROS messages nest a few levels,
                                # and Python's json and the walks after it recurse (a 1000-deep frame raised)
MAX_ER_TEXT = 512               # bytes (UTF-8) of an ER's text: an ER names what was wrong, it never echoes a value
TRUNCATED = " ... [{n} more bytes]"   # the marker after a truncated text
ER_RATE = 20.0                  # ERs per s a session sends a robot for its bad input, on average ...
ER_BURST = 50                   # ... and at most this many at once (token bucket); the rest are dropped and counted
LOG_RATE = 2.0                  # log lines per s a session writes about its robot's bad input, on average ...
LOG_BURST = 10                  # ... and at most this many at once; the rest are counted in the next line
DEFAULT_MAX_PENDING_TOTAL = 512 * 1024 * 1024   # bytes of binary parts waiting for their message, all the robots
                                                # of one endpoint together (each also has its own cap)
DEFAULT_MAX_LAG = 1.0           # s an endpoint may stay behind a client's frames before it sheds the client's topic
                                # messages (LagGate)

_STRING = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"')     # a JSON string (RFC 8259 section 7), unrolled
_NOT_BRACKET = re.compile(r"[^\[\]{}]+")
_STEP = {"[": 1, "{": 1, "]": -1, "}": -1}


def json_too_deep(text: str, limit: int = MAX_JSON_DEPTH) -> bool:
    """True when JSON ``text`` nests arrays and objects deeper than ``limit``. Linear in the length
    of ``text`` and cheap when it holds few brackets; malformed text is left to the parser."""
    if text.count("[") + text.count("{") <= limit:
        return False
    brackets = _NOT_BRACKET.sub("", _STRING.sub("", text))
    return max(accumulate(map(_STEP.__getitem__, brackets)), default=0) > limit


def truncate(text: str, limit: int = MAX_ER_TEXT) -> str:
    """``text`` cut to ``limit`` bytes of UTF-8 (never inside a character), with a marker saying
    how many bytes were cut; shorter texts unchanged."""
    if len(text) <= limit // 4:                     # at most 4 bytes a character: surely short enough
        return text
    raw = text.encode("utf-8", "replace")
    if len(raw) <= limit:
        return text
    return raw[:limit].decode("utf-8", "ignore") + TRUNCATED.format(n=len(raw) - limit)


@dataclass
class TokenBucket:
    """``rate`` tokens per s, at most ``burst`` held; starts full. :meth:`take` at time ``now`` (s,
    monotonic) spends one token, or says there is none."""

    rate: float
    burst: int
    tokens: float = -1.0
    last: float | None = None

    def take(self, now: float) -> bool:
        """Spend a token at ``now`` (s); False when the bucket is empty."""
        if self.last is None:
            self.tokens = float(self.burst)
        else:
            self.tokens = min(float(self.burst), self.tokens + max(0.0, now - self.last) * self.rate)
        self.last = now
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True


@dataclass
class PartBudget:
    """Bytes of binary parts waiting for their message, summed over every session of one endpoint:
    at most ``max_bytes``. :attr:`held` now; :attr:`refused`: parts refused for the budget."""

    max_bytes: int = DEFAULT_MAX_PENDING_TOTAL
    held: int = 0
    refused: int = 0

    def take(self, n: int) -> bool:
        """Hold ``n`` more bytes; False (and counted) when that would pass the budget."""
        if self.held + n > self.max_bytes:
            self.refused += 1
            return False
        self.held += n
        return True

    def give(self, n: int) -> None:
        """``n`` held bytes are released (consumed, expired, replaced, or their session ended)."""
        self.held -= n


class LagGate:
    """Which of a client's topic messages an endpoint that lags behind the client takes.

    The shell tells :meth:`backlog` before each frame it takes how much more of the client's it
    has received and not yet taken (frames in its library's queue, else bytes in the kernel's).
    Once something has waited without a break for longer than ``max_lag`` s, :meth:`admit` says
    no to a topic message, unless its topic (``key``) has had nothing admitted for ``max_lag`` s
    (so a stream still gets through at least that often), until the shell has caught up. So an
    overloaded endpoint passes on the client's newest messages, not ever older ones, as a ROS
    subscriber's ``queue_size`` drops the oldest. ``max_lag`` None: admit everything.

    ``shed``: messages refused; ``episode``: of them, since the shell last caught up."""

    def __init__(self, max_lag: float | None = DEFAULT_MAX_LAG):
        self.max_lag = max_lag
        self.shed = self.episode = 0
        self._since: float | None = None                 # s: since when frames have waited unbroken
        self._admitted: dict[object, float] = {}         # key -> s: its last message admitted

    def backlog(self, waiting: int, now: float) -> int:
        """``waiting`` frames (or bytes) of the client's are still behind the one taken at ``now``
        (s). Returns how many messages were shed if this ends a lag (the shell caught up), else 0."""
        if waiting:
            if self._since is None:
                self._since = now
            return 0
        self._since = None
        ended, self.episode = self.episode, 0
        return ended

    def behind(self, now: float) -> float:
        """s the shell has been behind the client at ``now`` (0 when it is not)."""
        return 0.0 if self._since is None else now - self._since

    def admit(self, key: object, now: float) -> bool:
        """May topic ``key``'s message go on at ``now`` (s)? A refusal is counted."""
        lag = self.max_lag
        if lag is not None and self._since is not None and now - self._since > lag \
                and now - self._admitted.get(key, -math.inf) <= lag:
            self.shed += 1
            self.episode += 1
            return False
        self._admitted[key] = now
        return True

    def forget(self, key: object) -> None:
        """Topic ``key`` is gone (its interface removed)."""
        self._admitted.pop(key, None)


def parse_max_lag(text: str) -> float | None:
    """A ``maxLag`` query value: s >= 0, 0 for never (None). Raises :class:`ValueError` naming it."""
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not v >= 0 or v == float("inf"):
        raise ValueError(f"maxLag must be a number of seconds >= 0 (0: never shed); got {text[:40]!r}")
    return v or None
