"""The one message registry: ROS 1 (Noetic) types from the rosbags typestore, plus
the ``.msg``/``.srv`` files node packages bring, and the JSON <-> message codec.

Names: on the wire a message class is ``pkg/Name`` (``std_msgs/String``), a
service class ``pkg/Name`` (``Test/StringEcho``); in the typestore they are
``pkg/msg/Name`` and the service halves ``pkg/msg/NameRequest`` /
``pkg/msg/NameResponse`` (ROS 1 names its generated halves ``NameRequest`` and
``NameResponse``).

Internal format: ROS 1 serialization (``serialize_ros1``), the bytes every
internal hop carries.

JSON form (converters, ``rce-topic pub``): a message is an object with one key
per field; ``time``/``duration`` are ``{"secs", "nsecs"}`` (``{"sec",
"nanosec"}`` is accepted too); ``uint8[]``/``char[]`` arrays are base64 strings
on output; non-finite floats (NaN, +-inf, e.g. lidar ranges) are ``null`` on output and
``null`` reads back as NaN and a base64 string or a list of ints on input (the rosbridge v2
convention); missing fields take their ROS default (0, "", empty).
"""
from __future__ import annotations

import base64
import math
import threading
from pathlib import Path
from typing import Any, Callable

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.base import Nodetype

from rce.errors import MessageError

_INT_RANGES = {
    "bool": None, "byte": (0, 255), "char": (0, 255),
    "int8": (-2**7, 2**7 - 1), "uint8": (0, 2**8 - 1), "int16": (-2**15, 2**15 - 1), "uint16": (0, 2**16 - 1),
    "int32": (-2**31, 2**31 - 1), "uint32": (0, 2**32 - 1), "int64": (-2**63, 2**63 - 1), "uint64": (0, 2**64 - 1),
}
_FLOATS = {"float32", "float64"}
_NP_DTYPES = {"bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8, "uint8": np.uint8,
              "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32,
              "int64": np.int64, "uint64": np.uint64, "float32": np.float32, "float64": np.float64}
_TIME_TYPES = {"builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration"}

Encoder = Callable[[Any, str], Any]   # (json value, field path) -> typestore value
Decoder = Callable[[Any], Any]        # typestore value -> json value


def store_name(wire: str) -> str:
    """``std_msgs/String`` -> ``std_msgs/msg/String`` (names already in store form pass through).

    Raises :class:`MessageError` for a name that is not ``pkg/Name``."""
    if not isinstance(wire, str):
        raise MessageError(f"message class must be a string like 'std_msgs/String', got {wire!r}")
    parts = wire.strip("/").split("/")
    if len(parts) == 2 and all(parts):
        return f"{parts[0]}/msg/{parts[1]}"
    if len(parts) == 3 and parts[1] in ("msg", "srv") and parts[0] and parts[2]:
        return f"{parts[0]}/msg/{parts[2]}"
    raise MessageError(f"malformed message class {wire!r}: expected 'pkg/Name'")


def wire_name(store: str) -> str:
    """``std_msgs/msg/String`` -> ``std_msgs/String``."""
    pkg, _, name = store.split("/")
    return f"{pkg}/{name}"


class MessageRegistry:
    """Message and service classes by name, and their JSON codec and ROS 1 serialization.

    Thread-safe for registration; lookups are lock-free dict reads. One instance per
    process is the normal use (:func:`default_registry`)."""

    def __init__(self) -> None:
        self.store = get_typestore(Stores.ROS1_NOETIC)
        self._lock = threading.Lock()
        self._encoders: dict[str, Encoder] = {}
        self._decoders: dict[str, Decoder] = {}
        self._services: set[str] = set()   # wire names of registered services

    # -- registration -----------------------------------------------------------------------
    def register_msg(self, wire: str, text: str) -> None:
        """Register message class ``wire`` (``pkg/Name``) from ``.msg`` definition ``text``.

        Raises :class:`MessageError` if the definition does not parse or names unknown types."""
        types = self._parse_msg(wire, text)
        self._check_resolvable(types)
        self._register(wire, types)

    def _parse_msg(self, wire: str, text: str) -> dict:
        try:
            return get_types_from_msg(text, store_name(wire))
        except MessageError:
            raise
        except Exception as e:  # rosbags raises several parser error types
            raise MessageError(f"cannot register message class {wire!r}: {e}") from e

    def _register(self, wire: str, types: dict) -> None:
        try:
            with self._lock:
                self.store.register(types)
        except Exception as e:
            raise MessageError(f"cannot register message class {wire!r}: {e}") from e

    def register_srv(self, wire: str, text: str) -> None:
        """Register service class ``wire`` from ``.srv`` text (request ``---`` response)."""
        lines = text.splitlines()
        try:
            cut = next(i for i, ln in enumerate(lines) if ln.strip() == "---")
        except StopIteration:
            raise MessageError(f"service definition {wire!r} has no '---' separator") from None
        req, resp = "\n".join(lines[:cut]), "\n".join(lines[cut + 1:])
        self.register_msg(wire + "Request", req)
        self.register_msg(wire + "Response", resp)
        self._services.add(wire.strip("/"))

    def load_definitions(self, pkg: str, pkg_dir: Path) -> list[str]:
        """Register every ``msg/*.msg`` and ``srv/*.srv`` of package ``pkg`` at ``pkg_dir``.

        Returns the wire names registered. Raises :class:`MessageError` naming the file on error.
        The package's messages are checked together (they may refer to each other in any order)
        and registered only if all of them are good."""
        msgs = []
        for f in sorted((pkg_dir / "msg").glob("*.msg")):
            try:
                msgs.append((f, f"{pkg}/{f.stem}", self._parse_msg(f"{pkg}/{f.stem}", f.read_text())))
            except MessageError as e:
                raise MessageError(f"{f}: {e.message}") from e
        own = {name: t for _, _, types in msgs for name, t in types.items()}
        for f, _, types in msgs:
            try:
                self._check_resolvable(types, own)
            except MessageError as e:
                raise MessageError(f"{f}: {e.message}") from e
        for f, wire, types in msgs:
            try:
                self._register(wire, types)
            except MessageError as e:
                raise MessageError(f"{f}: {e.message}") from e
        done = [wire for _, wire, _ in msgs]
        for f in sorted((pkg_dir / "srv").glob("*.srv")):
            wire = f"{pkg}/{f.stem}"
            try:
                self.register_srv(wire, f.read_text())
            except MessageError as e:
                raise MessageError(f"{f}: {e.message}") from e
            done.append(wire)
        return done

    def _check_resolvable(self, types: dict, also_known: dict | None = None) -> None:
        """Raise :class:`MessageError` if a field of ``types`` names a type that is neither in the
        store, nor in ``types``, nor in ``also_known``."""
        for name, (_, fields) in types.items():
            for _, (nt, arg) in fields:
                sub = arg[0] if nt in (Nodetype.ARRAY, Nodetype.SEQUENCE) else (nt, arg)
                if (sub[0] == Nodetype.NAME and sub[1] not in self.store.fielddefs and sub[1] not in types
                        and sub[1] not in (also_known or {})):
                    raise MessageError(f"message class {wire_name(name)!r} uses unknown type {wire_name(sub[1])!r}")

    # -- lookup -----------------------------------------------------------------------------
    def msg_type(self, wire: str) -> str:
        """Store name of message class ``wire``; raises :class:`MessageError` if unknown."""
        name = store_name(wire)
        if name not in self.store.fielddefs:
            raise MessageError(f"unknown message class {wire!r}")
        return name

    def srv_types(self, wire: str) -> tuple[str, str]:
        """(request, response) store names of service class ``wire``; :class:`MessageError` if unknown."""
        base = store_name(wire)
        req, resp = base + "Request", base + "Response"
        if req not in self.store.fielddefs or resp not in self.store.fielddefs:
            raise MessageError(f"unknown service class {wire!r}")
        return req, resp

    def is_service(self, wire: str) -> bool:
        """True if ``wire`` names a registered service class."""
        try:
            self.srv_types(wire)
            return True
        except MessageError:
            return False

    # -- serialization ----------------------------------------------------------------------
    def serialize(self, typename: str, msg: Any) -> bytes:
        """ROS 1 serialize typestore instance ``msg`` of store type ``typename``."""
        try:
            return bytes(self.store.serialize_ros1(msg, typename))
        except Exception as e:
            raise MessageError(f"cannot serialize {wire_name(typename)}: {e}") from e

    def deserialize(self, typename: str, data: bytes) -> Any:
        """Inverse of :meth:`serialize`; :class:`MessageError` if ``data`` does not fit the type."""
        try:
            return self.store.deserialize_ros1(data, typename)
        except Exception as e:
            raise MessageError(f"{len(data)} bytes do not deserialize as {wire_name(typename)}: {e}") from e

    def from_json(self, typename: str, obj: Any) -> Any:
        """Build a typestore instance of ``typename`` from JSON ``obj``.

        Raises :class:`MessageError` naming the class and the field path (``pose.pose.position.x``)."""
        if not isinstance(obj, dict):
            raise MessageError(f"{wire_name(typename)}: message must be a JSON object, got {type(obj).__name__}")
        try:
            return self._encoder(typename)(obj, "")
        except MessageError as e:   # nested encoders name their own class; name the outer one
            raise MessageError(f"{wire_name(typename)}: {e.message.split(': ', 1)[-1]}") from None

    def to_json(self, typename: str, msg: Any) -> dict:
        """JSON-ready dict of typestore instance ``msg`` of ``typename``."""
        return self._decoder(typename)(msg)

    def json_to_bytes(self, typename: str, obj: Any) -> bytes:
        """JSON -> ROS 1 serialized bytes (what a converter does with a robot's message)."""
        return self.serialize(typename, self.from_json(typename, obj))

    def bytes_to_json(self, typename: str, data: bytes) -> dict:
        """ROS 1 serialized bytes -> JSON dict (what a converter sends to a robot)."""
        return self.to_json(typename, self.deserialize(typename, data))

    # -- codec compilation --------------------------------------------------------------------
    def _encoder(self, typename: str) -> Encoder:
        enc = self._encoders.get(typename)
        if enc is None:
            enc = self._encoders[typename] = self._compile_encoder(typename)
        return enc

    def _decoder(self, typename: str) -> Decoder:
        dec = self._decoders.get(typename)
        if dec is None:
            dec = self._decoders[typename] = self._compile_decoder(typename)
        return dec

    def _compile_encoder(self, typename: str) -> Encoder:
        cls = self.store.types[typename]
        wire = wire_name(typename)
        fields = [(fname, self._field_encoder(ftype, wire)) for fname, ftype in self.store.fielddefs[typename][1]]
        names = {f for f, _ in fields}
        is_time = typename in _TIME_TYPES

        def encode(obj: Any, path: str) -> Any:
            if not isinstance(obj, dict):
                raise MessageError(f"{wire}: field '{path or '.'}' must be an object, got {type(obj).__name__}")
            shown = None   # time/duration: field -> the JSON key the client used (for error paths)
            if is_time:
                extra = set(obj) - {"secs", "nsecs", "sec", "nanosec"}
                shown = {"sec": "sec" if "sec" in obj and "secs" not in obj else "secs",
                         "nanosec": "nanosec" if "nanosec" in obj and "nsecs" not in obj else "nsecs"}
                obj = {"sec": obj.get("secs", obj.get("sec", _MISSING)),
                       "nanosec": obj.get("nsecs", obj.get("nanosec", _MISSING))}
            else:
                extra = set(obj) - names
            if extra:
                raise MessageError(f"{wire}: unknown field '{_join(path, sorted(extra)[0])}'")
            kwargs = {}
            for fname, fenc in fields:
                kwargs[fname] = fenc(obj.get(fname, _MISSING), _join(path, shown[fname] if shown else fname))
            return cls(**kwargs)

        return encode

    def _field_encoder(self, ftype: tuple, owner: str) -> Encoder:
        nt, arg = ftype
        if nt == Nodetype.BASE:
            return _base_encoder(arg[0], owner)
        if nt == Nodetype.NAME:
            sub_name = arg
            def enc_name(v: Any, path: str, _n=sub_name) -> Any:
                return self._encoder(_n)({} if v is _MISSING else v, path)
            return enc_name
        (sub_nt, sub_arg), length = arg
        fixed = length if nt == Nodetype.ARRAY else None
        if sub_nt == Nodetype.BASE and sub_arg[0] in _NP_DTYPES:
            return _numeric_array_encoder(sub_arg[0], fixed, owner)
        item = self._field_encoder((sub_nt, sub_arg), owner)

        def enc_list(v: Any, path: str) -> list:
            if v is _MISSING:
                v = []
            if not isinstance(v, list):
                raise MessageError(f"{owner}: field '{path}' must be a list, got {type(v).__name__}")
            if fixed is not None and len(v) != fixed:
                if v:
                    raise MessageError(f"{owner}: field '{path}' must have {fixed} items, got {len(v)}")
                v = [_MISSING] * fixed
            return [item(x, f"{path}[{i}]") for i, x in enumerate(v)]
        return enc_list

    def _compile_decoder(self, typename: str) -> Decoder:
        if typename in _TIME_TYPES:
            return lambda m: {"secs": int(m.sec), "nsecs": int(m.nanosec)}
        fields = [(fname, self._field_decoder(ftype)) for fname, ftype in self.store.fielddefs[typename][1]]

        def decode(m: Any) -> dict:
            return {fname: fdec(getattr(m, fname)) for fname, fdec in fields}
        return decode

    def _field_decoder(self, ftype: tuple) -> Decoder:
        nt, arg = ftype
        if nt == Nodetype.BASE:
            return _base_decoder(arg[0])
        if nt == Nodetype.NAME:
            return lambda v, _n=arg: self._decoder(_n)(v)
        (sub_nt, sub_arg), _ = arg
        if sub_nt == Nodetype.BASE and sub_arg[0] in ("uint8", "char", "byte"):
            return lambda v: base64.b64encode(bytes(np.asarray(v, dtype=np.uint8))).decode()
        if sub_nt == Nodetype.BASE and sub_arg[0] in _NP_DTYPES:
            conv = _base_decoder(sub_arg[0])
            return lambda v: [conv(x) for x in np.asarray(v).tolist()]
        item = self._field_decoder((sub_nt, sub_arg))
        return lambda v: [item(x) for x in v]


class _Missing:
    def __repr__(self) -> str:
        return "<missing>"


_MISSING = _Missing()


def _join(path: str, name: str) -> str:
    return f"{path}.{name}" if path else name


def _base_decoder(t: str) -> Decoder:
    if t in _FLOATS:
        # JSON has no NaN or Infinity: non-finite values go out as null, as rosbridge sends them
        return lambda v: float(v) if math.isfinite(v) else None
    if t == "bool":
        return bool
    if t == "string":
        return str
    return int


def _base_encoder(t: str, owner: str) -> Encoder:
    if t == "string":
        def enc_str(v: Any, path: str) -> str:
            if v is _MISSING:
                return ""
            if not isinstance(v, str):
                raise MessageError(f"{owner}: field '{path}' must be a string, got {type(v).__name__}")
            return v
        return enc_str
    if t == "bool":
        def enc_bool(v: Any, path: str) -> bool:
            if v is _MISSING:
                return False
            if not isinstance(v, bool):
                raise MessageError(f"{owner}: field '{path}' must be true or false, got {v!r}")
            return v
        return enc_bool
    if t in _FLOATS:
        def enc_float(v: Any, path: str) -> float:
            if v is _MISSING:
                return 0.0
            if v is None:
                return float("nan")
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise MessageError(f"{owner}: field '{path}' must be a number, got {type(v).__name__}")
            return float(v)
        return enc_float
    lo, hi = _INT_RANGES[t]

    def enc_int(v: Any, path: str) -> int:
        if v is _MISSING:
            return 0
        if isinstance(v, bool) or not isinstance(v, int):
            if isinstance(v, float) and v.is_integer():
                v = int(v)
            else:
                raise MessageError(f"{owner}: field '{path}' must be an integer ({t}), got {v!r}")
        if not lo <= v <= hi:
            raise MessageError(f"{owner}: field '{path}' value {v} is out of range for {t}")
        return v
    return enc_int


def _numeric_array_encoder(t: str, fixed: int | None, owner: str) -> Encoder:
    dtype = _NP_DTYPES[t]
    is_bytes = t in ("uint8", "char", "byte")
    item = _base_encoder(t, owner)

    def enc(v: Any, path: str) -> np.ndarray:
        if v is _MISSING:
            return np.zeros(fixed or 0, dtype=dtype)
        if is_bytes and isinstance(v, str):
            try:
                arr = np.frombuffer(base64.b64decode(v, validate=True), dtype=np.uint8)
            except ValueError:
                raise MessageError(f"{owner}: field '{path}' is not valid base64") from None
        elif isinstance(v, list):
            arr = np.array([item(x, f"{path}[{i}]") for i, x in enumerate(v)], dtype=dtype)
        else:
            raise MessageError(f"{owner}: field '{path}' must be a list{' or base64 string' if is_bytes else ''}, "
                               f"got {type(v).__name__}")
        if fixed is not None and len(arr) != fixed:
            raise MessageError(f"{owner}: field '{path}' must have {fixed} items, got {len(arr)}")
        return arr
    return enc


_DEFAULT: MessageRegistry | None = None


def default_registry() -> MessageRegistry:
    """The process-wide registry (created on first use)."""
    global _DEFAULT
    if _DEFAULT is None:
        _DEFAULT = MessageRegistry()
    return _DEFAULT
