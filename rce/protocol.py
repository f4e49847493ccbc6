"""The robot <-> cloud client protocol (DESIGN section 3), sans I/O.

Wire-compatible with the RoboEarth/Rapyuta RCE alpha client: JSON text frames
``{"type": T, "data": {...}}`` with T in CC, DC, CN, CX, DM, ST, ER; a message
field whose key ends in ``*`` holds a 32-hex-char id (or a list of ids) and each
id arrives as a binary frame ``id || bytes``, before or after the JSON frame.

:class:`Assembler` joins JSON frames and binary parts, in either order, and
expires incomplete messages; :func:`encode` does the reverse for outgoing
messages whose values are ``bytes``. :func:`validate` checks a complete message
against the shapes of DESIGN section 3 and raises :class:`ProtocolError` naming
the type and the key path.
"""
from __future__ import annotations

import json
import re
import uuid
from dataclasses import dataclass, field
from typing import Any

from rce.errors import ProtocolError

CC, DC, CN, CX, DM, ST, ER = "CC", "DC", "CN", "CX", "DM", "ST", "ER"
ROBOT_TO_CLOUD = {CC, DC, CN, CX, DM}
ID_LEN = 32
_HEX_ID = re.compile(r"^[0-9a-fA-F]{32}$")
DEFAULT_EXPIRY = 60.0   # s

INTERFACE_PREFIXES = ("ServiceClient", "ServiceProvider", "Publisher", "Subscriber")
INTERFACE_SUFFIXES = ("Interface", "Converter", "Forwarder")
# Names the RCE alpha client used for the service-client kinds.
LEGACY_INTERFACE_NAMES = {"ServiceInterface": "ServiceClientInterface",
                          "ServiceConverter": "ServiceClientConverter",
                          "ServiceForwarder": "ServiceClientForwarder"}
CN_KEYS = ("addNodes", "removeNodes", "setParam", "deleteParam", "addInterfaces", "removeInterfaces",
           "resizeContainer")


def split_interface_type(itype: str) -> tuple[str, str]:
    """``"PublisherConverter"`` -> ``("Publisher", "Converter")``; legacy names are mapped.

    Raises :class:`ProtocolError` for an unknown interface type."""
    itype = LEGACY_INTERFACE_NAMES.get(itype, itype)
    for p in INTERFACE_PREFIXES:
        if itype.startswith(p) and itype[len(p):] in INTERFACE_SUFFIXES:
            return p, itype[len(p):]
    raise ProtocolError(f"unknown interface type {itype!r}: expected one of "
                        f"{{{', '.join(INTERFACE_PREFIXES)}}} x {{{', '.join(INTERFACE_SUFFIXES)}}}")


# -- validation --------------------------------------------------------------------------------
def _req(d: dict, key: str, where: str, kind: type | tuple = str) -> Any:
    if key not in d:
        raise ProtocolError(f"{where}: missing key '{key}'")
    v = d[key]
    if not isinstance(v, kind) or (kind is str and not v):
        tname = kind.__name__ if isinstance(kind, type) else "/".join(k.__name__ for k in kind)
        raise ProtocolError(f"{where}: key '{key}' must be a non-empty {tname}, got {v!r}")
    return v


def _opt(d: dict, key: str, where: str, kind: type | tuple = str) -> Any:
    if key not in d or d[key] is None:
        return None
    v = d[key]
    if not isinstance(v, kind):
        tname = kind.__name__ if isinstance(kind, type) else "/".join(k.__name__ for k in kind)
        raise ProtocolError(f"{where}: key '{key}' must be a {tname}, got {v!r}")
    return v


def _obj(v: Any, where: str) -> dict:
    if not isinstance(v, dict):
        raise ProtocolError(f"{where}: must be a JSON object, got {type(v).__name__}")
    return v


def _list(d: dict, key: str, where: str) -> list:
    v = d.get(key, [])
    if not isinstance(v, list):
        raise ProtocolError(f"{where}: '{key}' must be a list, got {type(v).__name__}")
    return v


def validate(msg: Any) -> tuple[str, dict]:
    """Check a complete robot -> cloud message; return ``(type, data)``.

    Raises :class:`ProtocolError` naming the type and key path of the first problem."""
    msg = _obj(msg, "message")
    t = msg.get("type")
    if not isinstance(t, str) or t not in ROBOT_TO_CLOUD:
        if "type" not in msg:
            raise ProtocolError("message: missing key 'type'")
        raise ProtocolError(f"message: unknown type {t!r} (expected one of CC, DC, CN, CX, DM)")
    if "data" not in msg:
        raise ProtocolError(f"{t}: missing key 'data'")
    data = _obj(msg["data"], f"{t}.data")
    w = f"{t}.data"
    if t in (CC, DC):
        _req(data, "containerTag", w)
        if t == CC and data.get("containerData") is not None:
            _validate_container_data(_obj(data["containerData"], f"{w}.containerData"), f"{w}.containerData")
    elif t == CN:
        unknown = set(data) - set(CN_KEYS)
        if unknown:
            raise ProtocolError(f"{w}: unknown key '{sorted(unknown)[0]}' (expected {', '.join(CN_KEYS)})")
        for key in CN_KEYS:
            for i, item in enumerate(_list(data, key, w)):
                _validate_component(key, _obj(item, f"{w}.{key}[{i}]"), f"{w}.{key}[{i}]")
    elif t == CX:
        unknown = set(data) - {"connect", "disconnect"}
        if unknown:
            raise ProtocolError(f"{w}: unknown key '{sorted(unknown)[0]}' (expected connect, disconnect)")
        for key in ("connect", "disconnect"):
            for i, item in enumerate(_list(data, key, w)):
                where = f"{w}.{key}[{i}]"
                item = _obj(item, where)
                for tk in ("tagA", "tagB"):
                    tag = _req(item, tk, where)
                    if tag.count("/") != 1 or tag.startswith("/") or tag.endswith("/"):
                        raise ProtocolError(f"{where}.{tk}: {tag!r} must be 'endpointTag/interfaceTag'")
    elif t == DM:
        _req(data, "iTag", w)
        _req(data, "type", w)
        if "msg" not in data and "msg*" not in data:
            raise ProtocolError(f"{w}: missing key 'msg'")
        _opt(data, "msgID", w, (str, int))
    return t, data


def _validate_container_data(cd: dict, where: str) -> None:
    for key in ("cpu", "memory", "size", "bandwidth"):
        v = cd.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0):
            raise ProtocolError(f"{where}.{key}: must be a non-negative number, got {v!r}")
    _opt(cd, "group", where)
    _opt(cd, "groupIp", where)
    _opt(cd, "specialFeatures", where, list)


def _validate_component(key: str, item: dict, where: str) -> None:
    if key == "addNodes":
        for k in ("containerTag", "nodeTag", "pkg", "exe"):
            _req(item, k, where)
        for k in ("args", "name", "namespace"):
            _opt(item, k, where, (str, list) if k == "args" else str)
        _opt(item, "respawn", where, (bool, dict))
    elif key == "removeNodes":
        _req(item, "containerTag", where)
        _req(item, "nodeTag", where)
    elif key == "setParam":
        _req(item, "containerTag", where)
        _req(item, "name", where)
        if "value" not in item:
            raise ProtocolError(f"{where}: missing key 'value'")
    elif key == "deleteParam":
        _req(item, "containerTag", where)
        _req(item, "name", where)
    elif key == "addInterfaces":
        for k in ("endpointTag", "interfaceTag", "interfaceType", "className"):
            _req(item, k, where)
        try:
            split_interface_type(item["interfaceType"])
        except ProtocolError as e:
            raise ProtocolError(f"{where}.interfaceType: {e.message}") from None
        _opt(item, "addr", where)
    elif key == "removeInterfaces":
        _req(item, "endpointTag", where)
        _req(item, "interfaceTag", where)
    elif key == "resizeContainer":
        _req(item, "containerTag", where)
        _validate_container_data(item, where)


# -- binary parts ------------------------------------------------------------------------------
def _binary_refs(obj: Any, out: list[str]) -> None:
    """Collect the ids referenced by ``*`` keys anywhere in ``obj``."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            if isinstance(k, str) and k.endswith("*"):
                for ref in (v if isinstance(v, list) else [v]):
                    if not isinstance(ref, str) or not _HEX_ID.match(ref):
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
    ``max_pending_bytes`` bounds the binary parts held while waiting."""

    expiry: float = DEFAULT_EXPIRY
    max_pending_bytes: int = 256 * 1024 * 1024
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
        if not _HEX_ID.match(ref):
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


def encode(msg: dict) -> tuple[str, list[bytes]]:
    """Encode an outgoing message: every ``bytes`` value under key ``k`` becomes ``k*: id``
    and a binary frame ``id || bytes``; a list of ``bytes`` becomes ``k*: [ids]``.
    Returns ``(json_text, binary_frames)``."""
    frames: list[bytes] = []

    def part(v: bytes | bytearray | memoryview) -> str:
        ref = new_id()
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
