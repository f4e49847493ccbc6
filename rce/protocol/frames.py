"""Frames of the robot <-> cloud client protocol (DESIGN section 3.3-3.4), sans I/O.

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

import json
import re
import uuid
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

from rce.errors import ProtocolError

CC, DC, CN, CX, DM, ST, ER = "CC", "DC", "CN", "CX", "DM", "ST", "ER"
ID_LEN = 32                       # chars of a binary part id (hex), the first bytes of its binary frame
_HEX_ID = re.compile(r"[0-9a-fA-F]{32}")
DEFAULT_EXPIRY = 60.0             # s an incomplete message or an orphan part waits (DESIGN section 3.4)
DEFAULT_MAX_PENDING_BYTES = 256 * 1024 * 1024   # bytes of binary parts held while waiting for their message
DEFAULT_MAX_PENDING_MESSAGES = 1000             # messages held while waiting for their binary parts


def is_part_id(ref: Any) -> bool:
    """True for a 32-hex-char binary part id."""
    return isinstance(ref, str) and _HEX_ID.fullmatch(ref) is not None


# -- binary parts ------------------------------------------------------------------------------
def _binary_refs(obj: Any, out: list[str]) -> None:
    """Collect the ids referenced by ``*`` keys anywhere in ``obj``."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            if isinstance(k, str) and k.endswith("*"):
                for ref in (v if isinstance(v, list) else [v]):
                    if not is_part_id(ref):
                        raise ProtocolError(f"binary reference under key '{k}' must be a 32-hex-char id, got {ref!r}")
                    out.append(ref)
            else:
                _binary_refs(v, out)
    elif isinstance(obj, list):
        for v in obj:
            _binary_refs(v, out)


def _resolve(obj: Any, parts: dict[str, bytes]) -> Any:
    """Replace ``key*: id`` by ``key: bytes`` (``key*: [ids]`` by a list of bytes)."""
    if isinstance(obj, dict):
        out = {}
        for k, v in obj.items():
            if isinstance(k, str) and k.endswith("*"):
                out[k[:-1]] = [parts[r] for r in v] if isinstance(v, list) else parts[v]
            else:
                out[k] = _resolve(v, parts)
        return out
    if isinstance(obj, list):
        return [_resolve(v, parts) for v in obj]
    return obj


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
    what waited longer than ``expiry`` seconds and returns one reason per drop.
    ``max_pending_bytes`` bounds the binary parts held while waiting, ``max_pending_messages``
    the messages held while waiting for their parts (beyond either: :class:`ProtocolError`)."""

    expiry: float = DEFAULT_EXPIRY
    max_pending_bytes: int = DEFAULT_MAX_PENDING_BYTES
    max_pending_messages: int = DEFAULT_MAX_PENDING_MESSAGES
    _pending: list[_Pending] = field(default_factory=list)
    _parts: dict[str, tuple[bytes, float]] = field(default_factory=dict)
    _bytes: int = 0
    dropped: int = 0

    def feed_text(self, text: str | bytes, now: float) -> list[dict]:
        """Parse one text frame. Raises :class:`ProtocolError` for malformed JSON or bad ids."""
        try:
            msg = json.loads(text)
        except (ValueError, UnicodeDecodeError) as e:
            raise ProtocolError(f"malformed JSON: {e}") from None
        if not isinstance(msg, dict):
            raise ProtocolError(f"message must be a JSON object, got {type(msg).__name__}")
        refs: list[str] = []
        _binary_refs(msg, refs)
        if not refs:
            return [msg]
        missing = {r for r in refs if r not in self._parts}
        if not missing:
            return [self._complete(msg, refs)]
        if len(self._pending) >= self.max_pending_messages:
            raise ProtocolError(f"{len(self._pending)} messages already wait for their binary parts "
                                f"(the limit); dropped")
        self._pending.append(_Pending(msg, refs, missing, now))
        return []

    def feed_binary(self, data: bytes, now: float) -> list[dict]:
        """Take one binary frame ``id || bytes``. Raises :class:`ProtocolError` for a bad id."""
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
        held = self._bytes - (len(old[0]) if old else 0)   # the same part sent again replaces the first copy
        if held + len(payload) > self.max_pending_bytes:
            raise ProtocolError(f"binary parts waiting for their message exceed {self.max_pending_bytes} bytes")
        self._parts[ref] = (payload, now)
        self._bytes = held + len(payload)
        # the first message waiting for this id takes it (an id reused by a client is consumed once per message)
        p = next((p for p in self._pending if ref in p.missing), None)
        if p is not None:
            p.missing.discard(ref)
            if not p.missing:
                self._pending.remove(p)
                return [self._complete(p.msg, p.refs)]
        return []

    def _complete(self, msg: dict, refs: list[str]) -> dict:
        parts = {r: self._parts[r][0] for r in refs}
        for r in set(refs):
            self._bytes -= len(self._parts.pop(r)[0])
        for p in self._pending:   # messages that reuse a consumed id wait for it again
            p.missing.update(r for r in p.refs if r in parts)
        return _resolve(msg, parts)

    def expire(self, now: float) -> list[str]:
        """Drop incomplete messages and orphan parts older than ``expiry``; return reasons."""
        reasons = []
        for p in list(self._pending):
            if now - p.since > self.expiry:
                self._pending.remove(p)
                self.dropped += 1
                data = p.msg.get("data") if isinstance(p.msg.get("data"), dict) else {}
                reasons.append(f"message {p.msg.get('type')} for interface {data.get('iTag')!r} expired after "
                               f"{self.expiry:g} s waiting for {len(p.missing)} binary part(s)")
        waiting = {r for p in self._pending for r in p.refs}
        for ref, (payload, since) in list(self._parts.items()):
            if now - since > self.expiry and ref not in waiting:
                del self._parts[ref]
                self._bytes -= len(payload)
                self.dropped += 1
                reasons.append(f"binary part {ref} expired after {self.expiry:g} s with no message referring to it")
        return reasons

    @property
    def pending(self) -> int:
        """Messages waiting for binary parts, plus parts waiting for their message."""
        return len(self._pending) + len(self._parts)


def new_id() -> str:
    """A fresh 32-hex-char binary part id."""
    return uuid.uuid4().hex


def encode(msg: dict, ids: Iterable[str] | None = None) -> tuple[str, list[bytes]]:
    """Encode an outgoing message: every ``bytes`` value under key ``k`` becomes ``k*: id``
    and a binary frame ``id || bytes``; a list of ``bytes`` becomes ``k*: [ids]``. Parts are
    numbered depth first, keys in insertion order; ``ids`` gives their ids in that order
    (default: fresh :func:`new_id` ones). Returns ``(json_text, binary_frames)``, frames in
    the same order. Raises :class:`ProtocolError` when ``ids`` runs out or holds a bad id."""
    frames: list[bytes] = []
    given: Iterator[str] | None = iter(ids) if ids is not None else None

    def part(v: bytes | bytearray | memoryview) -> str:
        ref = new_id() if given is None else next(given, None)
        if not is_part_id(ref):
            raise ProtocolError(f"binary part {len(frames)}: needs a 32-hex-char id, got {ref!r}")
        frames.append(ref.encode() + bytes(v))
        return ref

    def walk(obj: Any) -> Any:
        if isinstance(obj, dict):
            out = {}
            for k, v in obj.items():
                if isinstance(v, (bytes, bytearray, memoryview)):
                    out[k + "*"] = part(v)
                elif isinstance(v, list) and v and all(isinstance(x, (bytes, bytearray, memoryview)) for x in v):
                    out[k + "*"] = [part(x) for x in v]
                else:
                    out[k] = walk(v)
            return out
        if isinstance(obj, list):
            return [walk(v) for v in obj]
        return obj

    return json.dumps(walk(msg), separators=(",", ":")), frames
