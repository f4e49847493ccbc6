"""Frames of the robot <-> cloud client protocol (docs/design.md, section 3.3-3.4), sans I/O.

Wire-compatible with the RoboEarth/Rapyuta RCE alpha client: JSON text frames
``{"type": T, "data": {...}}`` with T in CC, DC, CN, CX, DM, ST, ER; a message
field whose key ends in ``*`` holds a 32-hex-char id (or a list of ids) and each
id arrives as a binary frame ``id || bytes``, before or after the JSON frame.

:class:`Assembler` joins JSON frames and binary parts, in either order, and
expires incomplete messages; :func:`encode` does the reverse for outgoing
messages whose values are ``bytes``. The shapes of complete messages are checked
by :mod:`rce.protocol.schema`.
"""
from __future__ import annotations

import itertools
import os
import re
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import orjson

from rce.plumbing.errors import ProtocolError
from rce.protocol import jsontext
from rce.plumbing.text import short_repr
from rce.protocol.limits import MAX_JSON_DEPTH, PartBudget, json_too_deep, truncate

CC, DC, CN, CX, DM, ST, ER = "CC", "DC", "CN", "CX", "DM", "ST", "ER"
ID_LEN = 32                       # chars of a binary part id (hex), the first bytes of its binary frame
_HEX_ID = re.compile(r"[0-9a-fA-F]{32}")
DEFAULT_EXPIRY = 60.0             # s an incomplete message or an orphan part waits (docs/design.md, section 3.4)
DEFAULT_MAX_PENDING_BYTES = 256 * 1024 * 1024   # bytes of binary parts held while waiting for their message
DEFAULT_MAX_PENDING_MESSAGES = 1000             # messages held while waiting for their binary parts
DEFAULT_MAX_PENDING_PARTS = 1000                # binary parts held while waiting for their message (each costs
                                                # its bookkeeping however small: 20,000 cost 32 MB)
QUEUE_SLACK = 1024                              # stale expiry-queue entries tolerated before it is compacted


def is_part_id(ref: Any) -> bool:
    """True for a 32-hex-char binary part id."""
    return isinstance(ref, str) and _HEX_ID.fullmatch(ref) is not None


# -- binary parts ------------------------------------------------------------------------------
_CONTAINERS = (dict, list)
_SCALARS = frozenset((str, int, float, bool, type(None)))    # a value of one of these is not nested: no isinstance


def _binary_refs(obj: dict | list, out: list[str]) -> None:
    """Collect the ids referenced by ``*`` keys anywhere in ``obj`` (parsed JSON: a key is a
    str), depth first; only dicts and lists are descended into."""
    for k, v in (obj.items() if isinstance(obj, dict) else enumerate(obj)):
        if k.__class__ is str and k[-1:] == "*":
            for ref in (v if isinstance(v, list) else (v,)):
                if not is_part_id(ref):
                    raise ProtocolError(f"binary reference under key {short_repr(k)} must be a 32-hex-char id, "
                                        f"got {short_repr(ref)}")
                out.append(ref)
        elif isinstance(v, _CONTAINERS):
            _binary_refs(v, out)


def _resolve(obj: dict | list, parts: dict[str, bytes]) -> dict | list:
    """A copy of parsed JSON ``obj`` with ``key*: id`` replaced by ``key: bytes`` (``key*: [ids]``
    by a list of bytes); only dicts and lists are copied, other values are shared."""
    if isinstance(obj, list):
        return [_resolve(v, parts) if isinstance(v, _CONTAINERS) else v for v in obj]
    out = {}
    for k, v in obj.items():
        if k.__class__ is str and k[-1:] == "*":
            out[k[:-1]] = [parts[r] for r in v] if isinstance(v, list) else parts[v]
        else:
            out[k] = _resolve(v, parts) if isinstance(v, _CONTAINERS) else v
    return out


def _resolve_msg(msg: dict, data: dict, part: bytes) -> dict | None:
    """:func:`_resolve` of ``msg`` whose one binary reference is ``data.msg*`` (``data`` is ``msg["data"]``)
    and whose other values, and ``data``'s, are not dicts or lists (a forwarder's DM; so no other key is
    a binary reference: one would be in ``refs``): copies of ``msg`` and ``data``, ``msg*`` replaced by
    ``msg: part`` in its place. None for any other message: the walk takes it."""
    return _flat_swap(msg, data, "msg*", "msg", part, _CONTAINERS)


def _flat_swap(msg: dict, data: dict, key: str, new_key: str, value, nested: tuple) -> dict | None:
    """A copy of ``msg`` whose ``data`` (``msg``'s value that is ``data``) is copied with ``key``
    replaced by ``new_key: value`` in its place; None when any other value of either is an
    instance of ``nested``. The flat path of a forwarder's DM, read (:func:`_resolve_msg`) and
    written (:func:`_flat_dm`); a scalar's class is checked by one set lookup."""
    out = {}
    for k, v in data.items():
        if k == key:
            out[new_key] = value
        elif v.__class__ in _SCALARS or not isinstance(v, nested):
            out[k] = v
        else:
            return None
    top = {}
    for k, v in msg.items():
        if v is data:
            top[k] = out
        elif v.__class__ in _SCALARS or not isinstance(v, nested):
            top[k] = v
        else:
            return None
    return top


def parse_text(text: str | bytes) -> dict:
    """Parse one JSON text frame into its message object (a dict). Nesting deeper than
    :data:`~rce.protocol.limits.MAX_JSON_DEPTH` is refused before parsing. Raises
    :class:`ProtocolError` for malformed or too deeply nested JSON, or a message that is not an object."""
    try:
        if isinstance(text, (bytes, bytearray)):
            text = bytes(text).decode("utf-8")
        if json_too_deep(text):
            raise ProtocolError(f"JSON nested deeper than the limit of {MAX_JSON_DEPTH} levels; dropped")
        msg = jsontext.loads(text)
    except (ValueError, UnicodeDecodeError, RecursionError) as e:
        raise ProtocolError(f"malformed JSON: {truncate(str(e), 200)}") from None
    if not isinstance(msg, dict):
        raise ProtocolError(f"message must be a JSON object, got {type(msg).__name__}")
    return msg


def parse_frame(text: str | bytes) -> tuple[dict, list[str]]:
    """Parse one JSON text frame (:func:`parse_text`) and find the binary part ids its ``*`` keys
    reference, depth first (a frame without ``*"`` holds no such key: no walk). A pure function: the
    robot endpoint runs it in a worker process for big frames. Raises :class:`ProtocolError` as
    :func:`parse_text`, and for a reference that is not a 32-hex-char id."""
    msg = parse_text(text)
    refs: list[str] = []
    star = (b"*", b'*"', b"\\") if isinstance(text, (bytes, bytearray)) else ("*", '*"', "\\")
    if star[0] in text and star[1] in text:            # the one-char search is a memchr: fast
        ref = _lone_msg_part(msg, text, star)
        if ref is not None:
            refs.append(ref)
        else:
            _binary_refs(msg, refs)
    return msg, refs


def _lone_msg_part(msg: dict, text: str | bytes, star: tuple) -> str | None:
    """The id under ``data.msg*`` when that is the frame's one ``*`` key (a forwarder's DM): the text
    has no escape and one ``*"``, which every key ending in ``*`` writes. None otherwise (bad id
    included): the walk then finds the ids, or names the bad one."""
    data = msg.get("data")
    if data.__class__ is dict and (ref := data.get("msg*")).__class__ is str and is_part_id(ref) \
            and star[2] not in text and text.count(star[1]) == 1:
        return ref
    return None


@dataclass
class _Pending:
    msg: dict
    refs: list[str]
    missing: set[str]
    since: float


@dataclass
class Assembler:
    """Joins JSON frames and their binary parts, which may arrive in either order.

    ``feed_text`` and ``feed_binary`` return the messages completed by that frame
    (binary values resolved to ``bytes``, keys without ``*``). ``expire(now)`` drops
    what waited longer than ``expiry`` seconds and returns one reason per drop, in O(dropped):
    messages and parts wait in one queue in arrival order (``now`` never goes back).
    Bounds (beyond each: :class:`ProtocolError`, the frame is dropped): ``max_pending_bytes`` of
    binary parts held while waiting, ``max_pending_parts`` parts, ``max_pending_messages`` messages
    waiting for their parts, and ``budget``, the bytes held by every session of the endpoint."""

    expiry: float = DEFAULT_EXPIRY
    max_pending_bytes: int = DEFAULT_MAX_PENDING_BYTES
    max_pending_messages: int = DEFAULT_MAX_PENDING_MESSAGES
    max_pending_parts: int = DEFAULT_MAX_PENDING_PARTS
    budget: PartBudget | None = None
    _pending: dict[int, _Pending] = field(default_factory=dict)     # key -> message, in arrival order
    _users: dict[str, dict[int, None]] = field(default_factory=dict)  # part id -> keys of messages naming it
    _parts: dict[str, tuple[bytes, float]] = field(default_factory=dict)
    _queue: deque = field(default_factory=deque)    # (since, key or part id), arrival order; stale entries skipped
    _bytes: int = 0
    _key: int = 0
    dropped: int = 0

    def feed_text(self, text: str | bytes, now: float) -> list[dict]:
        """Parse one text frame (:func:`parse_frame`) and take its message (:meth:`feed_parsed`)."""
        msg, refs = parse_frame(text)
        return self.feed_parsed(msg, refs, now)

    def feed_parsed(self, msg: dict, refs: list[str], now: float) -> list[dict]:
        """Take one message and its binary part ids as :func:`parse_frame` gives them. Raises
        :class:`ProtocolError` when too many messages wait for their parts."""
        if not refs:
            return [msg]
        missing = {r for r in refs if r not in self._parts}
        if not missing:
            return [self._complete(None, msg, refs)]
        if len(self._pending) >= self.max_pending_messages:
            raise ProtocolError(f"{len(self._pending)} messages already wait for their binary parts "
                                f"(the limit); dropped")
        self._key += 1
        self._pending[self._key] = _Pending(msg, refs, missing, now)
        for r in refs:
            self._users.setdefault(r, {})[self._key] = None
        self._enqueue(now, self._key)
        return []

    def feed_binary(self, data: bytes, now: float) -> list[dict]:
        """Take one binary frame ``id || bytes``. Raises :class:`ProtocolError` for a bad id or a
        part past a bound."""
        if len(data) < ID_LEN:
            raise ProtocolError(f"binary frame of {len(data)} bytes is shorter than its {ID_LEN}-char id")
        try:
            ref = bytes(data[:ID_LEN]).decode("ascii")
        except UnicodeDecodeError:
            ref = ""
        if not is_part_id(ref):
            raise ProtocolError("binary frame does not start with a 32-hex-char id")
        payload = bytes(data[ID_LEN:])
        old = self._parts.get(ref)
        if old is None and len(self._parts) >= self.max_pending_parts:
            raise ProtocolError(f"{len(self._parts)} binary parts already wait for their message (the limit); "
                                f"part {ref} dropped")
        held = self._bytes - (len(old[0]) if old else 0)   # the same part sent again replaces the first copy
        if held + len(payload) > self.max_pending_bytes:
            raise ProtocolError(f"binary parts waiting for their message exceed {self.max_pending_bytes} bytes")
        if self.budget is not None and not self.budget.take(len(payload)):
            raise ProtocolError(f"binary parts waiting for their message on this endpoint exceed "
                                f"{self.budget.max_bytes} bytes; part {ref} dropped")
        if old is None and (done := self._completes(ref)) is not None:    # the usual case: not held at all
            self._release(len(payload))
            return [self._complete(done, self._pending[done].msg, [ref], {ref: payload})]
        if old is not None:
            self._release(len(old[0]))
        self._parts[ref] = (payload, now)
        self._bytes = held + len(payload)
        self._enqueue(now, ref)
        # the first message waiting for this id takes it (an id reused by a client is consumed once per message)
        for key in self._users.get(ref, ()):
            p = self._pending[key]
            if ref in p.missing:
                p.missing.discard(ref)
                return [self._complete(key, p.msg, p.refs)] if not p.missing else []
        return []

    def _enqueue(self, now: float, item: int | str) -> None:
        self._queue.append((now, item))
        if len(self._queue) > 2 * (len(self._pending) + len(self._parts)) + QUEUE_SLACK:   # drop stale entries
            self._queue = deque(e for e in self._queue if self._live(e))

    def _live(self, entry: tuple[float, int | str]) -> bool:
        since, item = entry
        if isinstance(item, int):
            return item in self._pending
        part = self._parts.get(item)
        return part is not None and part[1] == since

    def _release(self, n: int) -> None:
        if self.budget is not None:
            self.budget.give(n)

    def _forget(self, key: int) -> _Pending:
        p = self._pending.pop(key)
        for r in set(p.refs):
            users = self._users[r]
            users.pop(key, None)
            if not users:
                del self._users[r]
        return p

    def _drop_part(self, ref: str) -> None:
        n = len(self._parts.pop(ref)[0])
        self._bytes -= n
        self._release(n)

    def _complete(self, key: int | None, msg: dict, refs: list[str], given: dict[str, bytes] | None = None) -> dict:
        """Message ``msg`` (``key``: waiting, None: not) has all its parts: those held and ``given``
        (never held) are taken."""
        if key is not None:
            self._forget(key)
        parts = {r: self._parts[r][0] for r in refs if given is None or r not in given}
        for r in set(parts):
            self._drop_part(r)
            for k in self._users.get(r, ()):     # messages that reuse a consumed id wait for it again
                self._pending[k].missing.add(r)
        if given:
            parts.update(given)
        if len(refs) == 1 and (data := msg.get("data")).__class__ is dict and data.get("msg*") == refs[0] \
                and (flat := _resolve_msg(msg, data, parts[refs[0]])) is not None:
            return flat                                         # a forwarder's DM: no walk
        return _resolve(msg, parts)

    def _completes(self, ref: str) -> int | None:
        """The key of the first message waiting for part ``ref`` whose one part it is, else None
        (the part is then held as usual)."""
        for key in self._users.get(ref, ()):
            p = self._pending[key]
            return key if p.refs == [ref] else None
        return None

    def expire(self, now: float) -> list[str]:
        """Drop incomplete messages and orphan parts older than ``expiry``; return reasons."""
        reasons = []
        while self._queue and now - self._queue[0][0] > self.expiry:
            entry = self._queue.popleft()
            if not self._live(entry):
                continue
            item = entry[1]
            if isinstance(item, int):
                p = self._forget(item)
                self.dropped += 1
                data = p.msg.get("data") if isinstance(p.msg.get("data"), dict) else {}
                reasons.append(f"message {truncate(str(p.msg.get('type')), 40)} for interface "
                               f"{short_repr(data.get('iTag'))} expired after {self.expiry:g} s waiting "
                               f"for {len(p.missing)} binary part(s)")
                # its parts that waited past their own expiry only for it go too
                reasons.extend(self._expire_part(r, now) for r in set(p.refs) if self._orphan(r, now))
            elif self._orphan(item, now):
                reasons.append(self._expire_part(item, now))
        return reasons

    def _orphan(self, ref: str, now: float) -> bool:
        part = self._parts.get(ref)
        return part is not None and ref not in self._users and now - part[1] > self.expiry

    def _expire_part(self, ref: str, now: float) -> str:
        self._drop_part(ref)
        self.dropped += 1
        return f"binary part {ref} expired after {self.expiry:g} s with no message referring to it"

    def clear(self) -> None:
        """Forget every waiting message and part (the session ended, or its link was replaced);
        their bytes go back to the budget."""
        self._release(self._bytes)
        self._pending.clear()
        self._users.clear()
        self._parts.clear()
        self._queue.clear()
        self._bytes = 0

    def fresh(self) -> "Assembler":
        """An empty assembler with the same bounds and budget; this one is cleared (:meth:`clear`)."""
        self.clear()
        return Assembler(expiry=self.expiry, max_pending_bytes=self.max_pending_bytes,
                         max_pending_messages=self.max_pending_messages, max_pending_parts=self.max_pending_parts,
                         budget=self.budget)

    @property
    def pending(self) -> int:
        """Messages waiting for binary parts, plus parts waiting for their message."""
        return len(self._pending) + len(self._parts)

    @property
    def pending_bytes(self) -> int:
        """Bytes of binary parts waiting for their message."""
        return self._bytes


_ID_PREFIX = os.urandom(8).hex()        # this process's: 16 random hex chars
_ID_SEQ = itertools.count()


def _new_id_prefix() -> None:
    """A forked child draws its own prefix: its ids never repeat its parent's."""
    global _ID_PREFIX, _ID_SEQ
    _ID_PREFIX, _ID_SEQ = os.urandom(8).hex(), itertools.count()


os.register_at_fork(after_in_child=_new_id_prefix)


def new_id() -> str:
    """A fresh 32-hex-char binary part id: the process's random 64-bit prefix, then a 64-bit
    sequence number. Unique within the process (and unlike a uuid4 it costs no system call: ids
    are made for every binary part sent); an id only has to be unique among one link's parts in
    flight."""
    return f"{_ID_PREFIX}{next(_ID_SEQ):016x}"


_BINARY = (bytes, bytearray, memoryview)   # the values that become binary parts


def encode(msg: dict, ids: Iterable[str] | None = None) -> tuple[str, list[bytes]]:
    """Encode an outgoing message: every ``bytes`` value under key ``k`` becomes ``k*: id``
    and a binary frame ``id || bytes``; a list of ``bytes`` becomes ``k*: [ids]``. Parts are
    numbered depth first, keys in insertion order; ``ids`` gives their ids in that order
    (default: fresh :func:`new_id` ones). Returns ``(json_text, binary_frames)``, frames in
    the same order. Raises :class:`ProtocolError` when ``ids`` runs out or holds a bad id.

    A message without binary values (most: every converter's) is one ``orjson.dumps``; it
    refuses the first bytes-like value it meets, and only then the message is walked. A
    forwarder's DM (``data.msg`` bytes-like) is walked at once: a refused encode and its
    exception cost more than the walk of so small a message."""
    data = msg.get("data")
    if not (isinstance(data, dict) and isinstance(data.get("msg"), _BINARY)):
        try:
            return orjson.dumps(msg).decode(), []
        except TypeError:       # a bytes-like value (or what only the stdlib encodes: dumps after the walk)
            pass
    elif ids is None and (flat := _flat_dm(msg, data)) is not None:
        return flat
    frames: list[bytes] = []
    given: Iterator[str] | None = iter(ids) if ids is not None else None

    def part(v: bytes | bytearray | memoryview) -> str:
        if given is None:
            ref = new_id()
        elif not is_part_id(ref := next(given, None)):
            raise ProtocolError(f"binary part {len(frames)}: needs a 32-hex-char id, got {ref!r}")
        frames.append(b"".join((ref.encode(), v)))      # one copy, whatever kind of buffer ``v`` is
        return ref

    def walk(obj: Any) -> Any:
        if isinstance(obj, dict):
            out = {}
            for k, v in obj.items():
                if isinstance(v, _BINARY):
                    out[k + "*"] = part(v)
                elif isinstance(v, list) and v and all(isinstance(x, _BINARY) for x in v):
                    out[k + "*"] = [part(x) for x in v]
                else:
                    out[k] = walk(v) if isinstance(v, _CONTAINERS) else v
            return out
        return [walk(v) if isinstance(v, _CONTAINERS) else v for v in obj]

    return jsontext.dumps(walk(msg)), frames


_NESTED = (dict, list, bytes, bytearray, memoryview)


def _flat_dm(msg: dict, data: dict) -> tuple[str, list[bytes]] | None:
    """:func:`encode` of a forwarder's DM whose one binary value is ``data.msg`` and whose other
    values are scalars (``iTag``, ``type``, ``msgID``, resume's ``seq``): the same text and part as
    the walk, without it. None when a value is nested: the walk then takes the message."""
    ref = new_id()
    top = _flat_swap(msg, data, "msg", "msg*", ref, _NESTED)
    return None if top is None else (jsontext.dumps(top), [b"".join((ref.encode(), data["msg"]))])
