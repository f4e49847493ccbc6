"""rosbridge v2 fragments (``ROSBRIDGE_PROTOCOL.md``, "Fragmentation"; rosbridge_library's
``fragmentation.py`` and ``capabilities/defragmentation.py``): a message longer than a client's
``fragment_size`` goes as ``fragment`` ops ``{op, id, data, num, total}`` whose ``data`` joined in
``num`` order (0 to ``total`` - 1) is the message's JSON text; a client may send its own messages
the same way. Sans-I/O: :func:`fragment` splits, :class:`Defragmenter` reassembles with bounds.
"""
from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from rce.plumbing.errors import ProtocolError

FRAGMENT_EXPIRY = 60.0        # s a partly received message waits for its missing fragments (rosbridge's
                              # fragment_timeout is 600 s; a client sends its fragments back to back)
MAX_PENDING_MESSAGES = 16     # fragmented messages one session reassembles at once (distinct ids)
MAX_PENDING_CHARS = 16 * 1024 * 1024   # characters of fragment data one session holds at once (the
                                       # largest websocket message, rce_robot.rosbridge.endpoint.MAX_MESSAGE)
MAX_FRAGMENTS = 65536         # most fragments one message may have (``total``)
FRAGMENT_COST = 64            # characters each held fragment counts for on top of its data (its entry)
MIN_FRAGMENT_SIZE = 64        # characters: the least fragment_size taken (smaller ones would send one op per few bytes)


def fragment_size_of(op: dict) -> int | None:
    """An op's ``fragment_size`` (characters; None when absent). ProtocolError below :data:`MIN_FRAGMENT_SIZE`."""
    size = op.get("fragment_size")
    if size is None:
        return None
    if not isinstance(size, int) or isinstance(size, bool) or size < MIN_FRAGMENT_SIZE:
        raise ProtocolError(f"op {op.get('op')!r}: fragment_size must be an integer >= {MIN_FRAGMENT_SIZE} "
                            f"(characters), got {size!r}")
    return size


def fragment(text: str, size: int, mid: str) -> list[str]:
    """The ``fragment`` ops (JSON text) carrying ``text`` in pieces of ``size`` characters (>= 1)
    under id ``mid``, as rosbridge's ``Fragmentation._fragment_generator``; ``[text]`` itself
    when it is not longer than ``size``."""
    if len(text) <= size:
        return [text]
    total = (len(text) + size - 1) // size
    return [json.dumps({"op": "fragment", "id": mid, "data": text[i * size:(i + 1) * size], "num": i, "total": total})
            for i in range(total)]


@dataclass
class _Partial:
    total: int
    started: float                       # monotonic s of its first fragment
    parts: dict[int, str] = field(default_factory=dict)
    chars: int = 0                       # what it counts for in Defragmenter.held


class Defragmenter:
    """One session's reassembly of ``fragment`` ops. Bounds: ``max_messages`` ids at once,
    ``max_chars`` characters held (each fragment counts its data plus :data:`FRAGMENT_COST`),
    ``expiry`` s for a message's fragments to arrive. Counters: :attr:`fragments` (taken),
    :attr:`messages` (reassembled), :attr:`dropped` (fragments thrown away: overflow, expiry,
    inconsistent ``total``)."""

    def __init__(self, max_messages: int = MAX_PENDING_MESSAGES, max_chars: int = MAX_PENDING_CHARS,
                 expiry: float = FRAGMENT_EXPIRY, clock: Callable[[], float] = time.monotonic):
        self.max_messages, self.max_chars, self.expiry, self.clock = max_messages, max_chars, expiry, clock
        self.pending: dict[str, _Partial] = {}
        self.held = self.fragments = self.messages = self.dropped = 0

    def expire(self) -> list[str]:
        """Drop the messages whose fragments have waited over ``expiry`` s; their ids."""
        now = self.clock()
        old = [mid for mid, p in self.pending.items() if now - p.started > self.expiry]
        for mid in old:
            self._drop(mid)
        return old

    def _drop(self, mid: str, extra: int = 0) -> int:
        p = self.pending.pop(mid, None)
        n = extra + (len(p.parts) if p else 0)
        if p is not None:
            self.held -= p.chars
        self.dropped += n
        return n

    def add(self, op: dict) -> str | None:
        """Take one ``fragment`` op; the whole message's text once its last fragment is in, else
        None. Raises :class:`ProtocolError` (naming the field or bound) for a malformed fragment
        or one past a bound; the message it belongs to is then dropped (counted)."""
        mid, data, num, total = op.get("id"), op.get("data"), op.get("num"), op.get("total")
        if not isinstance(mid, (str, int)) or isinstance(mid, bool) or not isinstance(data, str):
            raise ProtocolError(f"fragment: 'id' must be a string and 'data' a string, got {mid!r}, "
                                f"{type(data).__name__}")
        mid = str(mid)
        if not _count(total) or not 1 <= total <= MAX_FRAGMENTS or not _count(num) or num >= total:
            self._drop(mid, 1)
            raise ProtocolError(f"fragment {mid!r}: 'total' must be an integer 1..{MAX_FRAGMENTS} and 'num' "
                                f"0..total-1, got num={num!r}, total={total!r}; message dropped")
        self.fragments += 1
        p = self.pending.get(mid)
        if p is not None and p.total != total:
            self._drop(mid, 1)
            raise ProtocolError(f"fragment {mid!r}: 'total' changed from {p.total} to {total}; message dropped")
        if p is None:
            if len(self.pending) >= self.max_messages:
                self.dropped += 1
                raise ProtocolError(f"fragment {mid!r}: {self.max_messages} fragmented messages are already "
                                    "being reassembled; fragment dropped")
            p = self.pending[mid] = _Partial(total, self.clock())
        cost = len(data) + FRAGMENT_COST - (len(p.parts[num]) + FRAGMENT_COST if num in p.parts else 0)
        if self.held + cost > self.max_chars:
            self._drop(mid, 1)
            raise ProtocolError(f"fragment {mid!r}: fragments held would exceed {self.max_chars} characters; "
                                "message dropped")
        p.parts[num] = data
        p.chars += cost
        self.held += cost
        if len(p.parts) < total:
            return None
        del self.pending[mid]
        self.held -= p.chars
        self.messages += 1
        return "".join(p.parts[i] for i in range(total))


def _count(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0
