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
per field; missing fields take their ROS default (0, "", empty); non-finite floats (NaN,
+-inf, e.g. lidar ranges) are ``null`` on output and ``null`` reads back as NaN (the rosbridge
v2 convention). ``time``/``duration``, ``sensor_msgs/Image`` and ``uint8[]``/``char[]``
arrays have several forms (:mod:`rce.messages.forms`): every form is accepted on input
(time ``{"secs", "nsecs"}``, ``{"sec", "nanosec"}`` or ISO 8601; duration those or float
seconds; an image an object or a PNG/JPEG binary part, i.e. a ``bytes`` value; a byte array
base64, a list of ints or ``bytes``), and the output takes the forms a :class:`JsonForms`
names (default: rce's, ``{"secs", "nsecs"}``, objects, base64). A client's session passes its
own :class:`JsonForms` to :meth:`MessageRegistry.json_to_bytes` and
:meth:`MessageRegistry.bytes_to_json` and so gets back the forms it used.

Forwarders do not convert: :meth:`MessageRegistry.check_structure` checks that serialized
bytes fit their class without decoding them (:mod:`rce.messages.structure`).

ROS 2: a class in ROS 2's form (``std_msgs/msg/String``, ``std_srvs/srv/Trigger``, an action's
parts) is a ROS 2 type, serialized as CDR by the registry's ROS 2 half (:mod:`rce.messages.ros2`,
:attr:`MessageRegistry.ros2`). Its type names carry :data:`ROS2_PREFIX` here
(``ros2:std_msgs/msg/String``), so that every method takes either kind and the two typestores'
names never meet.
"""
from __future__ import annotations

import base64
import functools
import math
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.base import Nodetype

from rce.interfaces.classes import is_ros2_name
from rce.plumbing.errors import MessageError
from rce.messages.forms import (RCE_FORMS, JsonForms, duration_to_seconds, image_from_bytes, image_to_bytes,
                               iso_to_time, seconds_to_duration, time_to_iso)
from rce.messages.structure import Short, Walker, compile_walker
from rce.messages import ros_strings

if TYPE_CHECKING:     # both loaded by the first converter that needs them: a process that only routes never does
    import numpy as np
    from rce.messages.compiled import Codec, JsonReader

ros_strings.install()       # ROS strings carry any bytes, as in rospy (rce.messages.ros_strings)

_INT_RANGES = {
    "bool": None, "byte": (0, 255), "char": (0, 255),
    "int8": (-2**7, 2**7 - 1), "uint8": (0, 2**8 - 1), "int16": (-2**15, 2**15 - 1), "uint16": (0, 2**16 - 1),
    "int32": (-2**31, 2**31 - 1), "uint32": (0, 2**32 - 1), "int64": (-2**63, 2**63 - 1), "uint64": (0, 2**64 - 1),
}
_FLOATS = {"float32", "float64"}
_EXACT_FLOAT_INT = 2 ** 53      # the largest magnitude up to which every integer is a float exactly (IEEE 754 double)
_NP_DTYPES = {"bool": "bool", "byte": "uint8", "char": "uint8", "int8": "int8", "uint8": "uint8",   # numpy dtype names
              "int16": "int16", "uint16": "uint16", "int32": "int32", "uint32": "uint32",
              "int64": "int64", "uint64": "uint64", "float32": "float32", "float64": "float64"}
_TIME, _DURATION = "builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration"
_TIME_TYPES = {_TIME, _DURATION}
IMAGE = "sensor_msgs/msg/Image"        # the class whose messages may travel as PNG/JPEG binary parts
_BINARY = (bytes, bytearray, memoryview)

Encoder = Callable[[Any, str, JsonForms], Any]   # (json value, field path, the client's forms) -> typestore value
Decoder = Callable[[Any], Any]                   # typestore value -> json value
FormsKey = tuple[str, str, str, str]             # JsonForms.key: what a decoder's output depends on


#: The prefix of a ROS 2 type's name in the registry (the name after it is the ROS 2 typestore's).
ROS2_PREFIX = "ros2:"
_ros2_factory: Callable[[], Any] | None = None


def set_ros2_factory(factory: Callable[[], Any]) -> None:
    """Set what makes a registry's ROS 2 half (:class:`rce.messages.ros2.Ros2Registry`, which sets
    itself when ``rce.messages`` is imported)."""
    global _ros2_factory
    _ros2_factory = factory


def _or_ros2(method: Callable) -> Callable:
    """A registry method of a type name that hands ROS 2 names (:data:`ROS2_PREFIX`) to the ROS 2 half."""
    name = method.__name__

    @functools.wraps(method)
    def dispatch(self: "MessageRegistry", typename: str, *args: Any, **kwargs: Any) -> Any:
        if typename.__class__ is str and typename.startswith(ROS2_PREFIX):
            return getattr(self.ros2, name)(typename[len(ROS2_PREFIX):], *args, **kwargs)
        return method(self, typename, *args, **kwargs)
    return dispatch


def takes_binary_message(cls: str) -> bool:
    """Can a converter of message class ``cls`` (``pkg/Name``) take a whole message as one binary
    part? True for ``sensor_msgs/Image`` (a PNG or JPEG file, as the original RCE's image converter)."""
    try:
        return store_name(cls) == IMAGE
    except MessageError:
        return False


def store_name(wire: str) -> str:
    """``std_msgs/String`` -> ``std_msgs/msg/String`` (the ROS 1 typestore's name); a ROS 2 name
    ``std_msgs/msg/String`` -> ``ros2:std_msgs/msg/String``.

    Raises :class:`MessageError` for a name in neither form."""
    if not isinstance(wire, str):
        raise MessageError(f"message class must be a string like 'std_msgs/String', got {wire!r}")
    if is_ros2_name(wire):
        return ROS2_PREFIX + wire.strip("/")
    parts = wire.strip("/").split("/")
    if len(parts) == 2 and all(parts):
        return f"{parts[0]}/msg/{parts[1]}"
    raise MessageError(f"malformed message class {wire!r}: expected 'pkg/Name' (ROS 1) or 'pkg/msg/Name' (ROS 2)")


def wire_name(store: str) -> str:
    """``std_msgs/msg/String`` -> ``std_msgs/String``; ``ros2:std_msgs/msg/String`` -> ``std_msgs/msg/String``."""
    if store.startswith(ROS2_PREFIX):
        return store[len(ROS2_PREFIX):]
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
        self._decoders: dict[tuple[str, FormsKey], Decoder] = {}
        self._walkers: dict[str, Walker] = {}
        self._codecs: dict[str, Codec | None] = {}   # store type -> its compiled codec (rce.messages.compiled)
        self._readers: dict[tuple, JsonReader | None] = {}   # (store type, forms key) -> its compiled JSON reader
        self._services: set[str] = set()   # wire names of registered services
        self._ros2: MessageRegistry | None = None
        #: (source, destination) type names -> their ROS 1 <-> ROS 2 converter (rce.messages.convert)
        self.converters: dict[tuple[str, str], Callable[[bytes | memoryview], bytes]] = {}

    @property
    def ros2(self) -> "MessageRegistry":
        """The ROS 2 half (:class:`rce.messages.ros2.Ros2Registry`), made on first use."""
        if self._ros2 is None:
            if _ros2_factory is None:
                raise MessageError("ROS 2 types are not available in this process (rce.messages.ros2 not loaded)")
            self._ros2 = _ros2_factory()
        return self._ros2

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
                self._codecs.clear()
                self._readers.clear()
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
        if is_ros2_name(wire):
            return ROS2_PREFIX + self.ros2.msg_type(wire)
        name = store_name(wire)
        if name not in self.store.fielddefs:
            raise MessageError(f"unknown message class {wire!r}")
        return name

    def srv_types(self, wire: str) -> tuple[str, str]:
        """(request, response) store names of service class ``wire``; :class:`MessageError` if unknown."""
        if is_ros2_name(wire):
            return tuple(ROS2_PREFIX + t for t in self.ros2.srv_types(wire))
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
    @_or_ros2
    def codec(self, typename: str) -> Codec | None:
        """The compiled codec of store type ``typename`` (:mod:`rce.messages.compiled`), or None for
        a class it does not handle (rosbags' functions then do all the work)."""
        try:
            return self._codecs[typename]
        except KeyError:
            pass
        if typename not in self.store.fielddefs:
            return None
        from rce.messages.compiled import compile_codec
        return compile_codec(self.store.fielddefs, self.store.types, typename, self.store.max_sequence_length,
                             self._codecs)

    @_or_ros2
    def serialize(self, typename: str, msg: Any) -> bytes:
        """ROS 1 serialize typestore instance ``msg`` of store type ``typename`` (the compiled
        codec, or rosbags' serializer for what it does not take). Raises :class:`MessageError`."""
        codec = self.codec(typename)
        if codec is not None:
            try:
                return codec.serialize(msg)
            except Exception:       # not an input the fast path takes: rosbags' says what it makes of it
                pass
        try:
            return bytes(self.store.serialize_ros1(msg, typename))
        except Exception as e:
            raise MessageError(f"cannot serialize {wire_name(typename)}: {e}") from e

    @_or_ros2
    def deserialize(self, typename: str, data: bytes) -> Any:
        """Inverse of :meth:`serialize`; :class:`MessageError` if ``data`` does not fit the type."""
        codec = self.codec(typename)
        if codec is not None:
            try:
                return codec.deserialize(data)
            except Exception:       # does not fit: rosbags' deserializer names why
                pass
        try:
            return self.store.deserialize_ros1(data, typename)
        except Exception as e:
            raise MessageError(f"{len(data)} bytes do not deserialize as {wire_name(typename)}: {e}") from e

    @_or_ros2
    def check_structure(self, typename: str, payload: bytes | memoryview) -> None:
        """Check that ROS 1 serialized ``payload`` fits store type ``typename`` without decoding it
        (what a forwarder does: strings are not decoded, numbers not read; :mod:`rce.messages.structure`).
        Raises :class:`MessageError` naming the class, the field and the offset where it does not fit."""
        walk = self._walkers.get(typename)
        if walk is None:
            walk = compile_walker(self.store.fielddefs, typename, self._walkers)
        buf = memoryview(payload)
        try:
            end = walk(buf, 0, len(buf))
        except Short as e:
            raise MessageError(f"{len(buf)} bytes do not fit {wire_name(typename)}: field '{e.path}' {e.why}") from None
        if end != len(buf):
            raise MessageError(f"{len(buf)} bytes do not fit {wire_name(typename)}: {len(buf) - end} byte(s) "
                               f"left after the last field")

    @_or_ros2
    def from_json(self, typename: str, obj: Any, forms: JsonForms | None = None) -> Any:
        """Build a typestore instance of ``typename`` from JSON ``obj`` (an object; for
        ``sensor_msgs/Image`` also a PNG or JPEG file as ``bytes``). ``forms``: the sending client's
        :class:`JsonForms`, told the forms it used (default: none told).

        Raises :class:`MessageError` naming the class and the field path (``pose.pose.position.x``)."""
        if not isinstance(obj, dict) and not (typename == IMAGE and isinstance(obj, _BINARY)):
            raise MessageError(f"{wire_name(typename)}: message must be a JSON object, got {type(obj).__name__}")
        try:
            return self._encoder(typename)(obj, "", forms or RCE_FORMS)
        except MessageError as e:   # nested encoders name their own class; name the outer one
            raise MessageError(f"{wire_name(typename)}: {e.message.split(': ', 1)[-1]}") from None

    @_or_ros2
    def to_json(self, typename: str, msg: Any, forms: JsonForms | None = None) -> Any:
        """JSON-ready form of typestore instance ``msg`` of ``typename``, in ``forms`` (default rce's):
        a dict, or ``bytes`` (a binary part) for an image in the ``png``/``jpeg`` form. Raises
        :class:`MessageError` when the message has no such form (an image encoding PNG cannot hold)."""
        return self._decoder(typename, (forms or RCE_FORMS).key)(msg)

    @_or_ros2
    def json_to_bytes(self, typename: str, obj: Any, forms: JsonForms | None = None) -> bytes:
        """JSON -> ROS 1 serialized bytes (what a converter does with a robot's message; a node that
        publishes a dict). The same bytes and errors as :meth:`serialize` of :meth:`from_json`; a
        message in the canonical forms is written without building the instance
        (:mod:`rce.messages.compiled`)."""
        codec = self.codec(typename)
        if codec is not None and codec.serialize_json is not None:
            try:
                return codec.serialize_json(obj, forms or RCE_FORMS)
            except Exception:       # another form, a missing field, bad input: the general path decides
                pass
        return self.serialize(typename, self.from_json(typename, obj, forms))

    @_or_ros2
    def bytes_to_json(self, typename: str, data: bytes, forms: JsonForms | None = None) -> Any:
        """ROS 1 serialized bytes -> JSON (what a converter sends to a robot), in ``forms``: the same
        value and errors as :meth:`to_json` of :meth:`deserialize`, read straight from the bytes where
        :mod:`rce.messages.compiled` has a reader for the class in these forms."""
        key = (forms or RCE_FORMS).key
        reader = self._readers.get((typename, key), False)
        if reader is False:
            from rce.messages.compiled import compile_json_reader
            reader = (compile_json_reader(self.store.fielddefs, self.store.types, typename, key,
                                          self.store.max_sequence_length, self._readers)
                      if typename in self.store.fielddefs else None)
        if reader is not None:
            try:
                return reader.to_json(data)
            except Exception:       # does not fit: the general path says why
                pass
        return self.to_json(typename, self.deserialize(typename, data), forms)

    # -- codec compilation --------------------------------------------------------------------
    def _encoder(self, typename: str) -> Encoder:
        enc = self._encoders.get(typename)
        if enc is None:
            enc = self._encoders[typename] = self._compile_encoder(typename)
        return enc

    def _decoder(self, typename: str, key: FormsKey) -> Decoder:
        dec = self._decoders.get((typename, key))
        if dec is None:
            dec = self._decoders[(typename, key)] = self._compile_decoder(typename, key)
        return dec

    def _compile_encoder(self, typename: str) -> Encoder:
        if typename in _TIME_TYPES:
            return _time_encoder(typename == _DURATION, self.store.types[typename])
        cls = self.store.types[typename]
        wire = wire_name(typename)
        fields = [(fname, self._field_encoder(ftype, wire)) for fname, ftype in self.store.fielddefs[typename][1]]
        names = {f for f, _ in fields}
        image = self._image_encoder(cls) if typename == IMAGE else None

        def encode(obj: Any, path: str, forms: JsonForms) -> Any:
            if obj is _MISSING:
                obj = {}
            elif image is not None:
                if isinstance(obj, _BINARY):
                    return image(obj, path, forms)
                forms.saw("images", "json")
            if not isinstance(obj, dict):
                raise MessageError(f"{wire}: field '{path or '.'}' must be an object, got {type(obj).__name__}")
            extra = set(obj) - names
            if extra:
                raise MessageError(f"{wire}: unknown field '{_join(path, sorted(extra)[0])}'")
            return cls(**{fname: fenc(obj.get(fname, _MISSING), _join(path, fname), forms) for fname, fenc in fields})

        return encode

    def _image_encoder(self, cls: Any) -> Encoder:
        """``sensor_msgs/Image`` from a PNG or JPEG file (header left at its default: the file has none)."""
        header = self._encoder("std_msgs/msg/Header")

        def encode(data: Any, path: str, forms: JsonForms) -> Any:
            try:
                fields, fmt = image_from_bytes(bytes(data))
            except ValueError as e:
                raise MessageError(f"sensor_msgs/Image: field '{path or '.'}': {e}") from None
            forms.saw("images", fmt)
            return cls(header=header(_MISSING, _join(path, "header"), forms), **fields)
        return encode

    def _field_encoder(self, ftype: tuple, owner: str) -> Encoder:
        nt, arg = ftype
        if nt == Nodetype.BASE:
            return _base_encoder(arg[0], owner)
        if nt == Nodetype.NAME:
            sub_name = arg
            def enc_name(value: Any, path: str, forms: JsonForms, _n=sub_name) -> Any:
                return self._encoder(_n)(value, path, forms)
            return enc_name
        (sub_nt, sub_arg), length = arg
        fixed = length if nt == Nodetype.ARRAY else None
        if sub_nt == Nodetype.BASE and sub_arg[0] in _NP_DTYPES:
            return _numeric_array_encoder(sub_arg[0], fixed, owner)
        item = self._field_encoder((sub_nt, sub_arg), owner)

        def enc_list(value: Any, path: str, forms: JsonForms) -> list:
            if value is _MISSING:
                value = []
            if not isinstance(value, list):
                raise MessageError(f"{owner}: field '{path}' must be a list, got {type(value).__name__}")
            if fixed is not None and len(value) != fixed:
                if value:
                    raise MessageError(f"{owner}: field '{path}' must have {fixed} items, got {len(value)}")
                value = [_MISSING] * fixed
            return [item(x, f"{path}[{i}]", forms) for i, x in enumerate(value)]
        return enc_list

    def _compile_decoder(self, typename: str, key: FormsKey) -> Decoder:
        time_form, duration_form, image_form, _ = key
        if typename == _TIME:
            return _time_decoder(time_form)
        if typename == _DURATION:
            return _time_decoder(duration_form)
        if typename == IMAGE and image_form != "json":
            def encode_image(msg: Any) -> bytes:
                try:
                    return image_to_bytes(msg, image_form)
                except ValueError as e:
                    raise MessageError(f"sensor_msgs/Image: {e}") from None
            return encode_image
        fields = [(fname, self._field_decoder(ftype, key)) for fname, ftype in self.store.fielddefs[typename][1]]

        def decode(msg: Any) -> dict:
            return {fname: fdec(getattr(msg, fname)) for fname, fdec in fields}
        return decode

    def _field_decoder(self, ftype: tuple, key: FormsKey) -> Decoder:
        nt, arg = ftype
        if nt == Nodetype.BASE:
            return _base_decoder(arg[0])
        if nt == Nodetype.NAME:
            return lambda value, _n=arg: self._decoder(_n, key)(value)
        (sub_nt, sub_arg), _ = arg
        if sub_nt == Nodetype.BASE and sub_arg[0] in ("uint8", "char", "byte"):
            import numpy as np
            if key[3] == "binary":
                return lambda value: bytes(np.asarray(value, dtype=np.uint8))
            return lambda value: base64.b64encode(bytes(np.asarray(value, dtype=np.uint8))).decode()
        if sub_nt == Nodetype.BASE and sub_arg[0] in _NP_DTYPES:
            return _numeric_array_decoder(sub_arg[0] in _FLOATS)
        item = self._field_decoder((sub_nt, sub_arg), key)
        return lambda value: [item(x) for x in value]


class _Missing:
    def __repr__(self) -> str:
        return "<missing>"


_MISSING = _Missing()


def _join(path: str, name: str) -> str:
    return f"{path}.{name}" if path else name


# -- time and duration: every form in, the client's form out (rce.messages.forms) ---------------------------
_TIME_KEYS = {"secs", "nsecs", "sec", "nanosec"}


def _time_encoder(duration: bool, cls: Any) -> Encoder:
    """Time (or ``duration``) class ``cls`` from any of its JSON forms; tells ``forms`` which one."""
    owner = "builtin_interfaces/Duration" if duration else "builtin_interfaces/Time"
    sec_enc, ns_enc = _base_encoder("int32", owner), _base_encoder("uint32", owner)
    other = "seconds (a number)" if duration else "an ISO 8601 string"

    def encode(value: Any, path: str, forms: JsonForms) -> Any:
        if value is _MISSING:
            return cls(sec=0, nanosec=0)
        if isinstance(value, dict):
            extra = set(value) - _TIME_KEYS
            if extra:
                raise MessageError(f"{owner}: unknown field '{_join(path, sorted(extra)[0])}'")
            sk = "sec" if "sec" in value and "secs" not in value else "secs"
            nk = "nanosec" if "nanosec" in value and "nsecs" not in value else "nsecs"
            if value:
                forms.saw("time", "sec" if sk == "sec" and nk == "nanosec" else "secs")
            return cls(sec=sec_enc(value.get(sk, _MISSING), _join(path, sk), forms),
                       nanosec=ns_enc(value.get(nk, _MISSING), _join(path, nk), forms))
        try:
            if duration and not isinstance(value, (dict, list)):
                sec, ns = seconds_to_duration(value)
                sec_enc(sec, path, forms)
                forms.saw("time", "float")
                return cls(sec=sec, nanosec=ns)
            if not duration and isinstance(value, str):
                sec, ns = iso_to_time(value)
                sec_enc(sec, path, forms)
                forms.saw("time", "iso")
                return cls(sec=sec, nanosec=ns)
        except ValueError as e:
            raise MessageError(f"{owner}: field '{path or '.'}': {e}") from None
        raise MessageError(f"{owner}: field '{path or '.'}' must be an object {{secs, nsecs}} or {other}, "
                           f"got {type(value).__name__}")
    return encode


def _time_decoder(form: str) -> Decoder:
    if form == "sec":
        return lambda msg: {"sec": int(msg.sec), "nanosec": int(msg.nanosec)}
    if form == "iso":
        return lambda msg: time_to_iso(msg.sec, msg.nanosec)
    if form == "float":
        return lambda msg: duration_to_seconds(msg.sec, msg.nanosec)
    return lambda msg: {"secs": int(msg.sec), "nsecs": int(msg.nanosec)}


def _base_decoder(base_type: str) -> Decoder:
    if base_type in _FLOATS:
        # JSON has no NaN or Infinity: non-finite values go out as null, as rosbridge sends them
        return lambda value: float(value) if math.isfinite(value) else None
    if base_type == "bool":
        return bool
    if base_type == "string":
        return ros_strings.to_text
    return int


def _base_encoder(base_type: str, owner: str) -> Encoder:
    if base_type == "string":
        def enc_str(value: Any, path: str, forms: JsonForms) -> str:
            if value is _MISSING:
                return ""
            if not isinstance(value, str):
                raise MessageError(f"{owner}: field '{path}' must be a string, got {type(value).__name__}")
            return value
        return enc_str
    if base_type == "bool":
        def enc_bool(value: Any, path: str, forms: JsonForms) -> bool:
            if value is _MISSING:
                return False
            if not isinstance(value, bool):
                raise MessageError(f"{owner}: field '{path}' must be true or false, got {value!r}")
            return value
        return enc_bool
    if base_type in _FLOATS:
        def enc_float(value: Any, path: str, forms: JsonForms) -> float:
            if value is _MISSING:
                return 0.0
            if value is None:
                return float("nan")
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise MessageError(f"{owner}: field '{path}' must be a number, got {type(value).__name__}")
            try:
                return float(value)
            except OverflowError:       # an integer past a double's range
                raise MessageError(f"{owner}: field '{path}' must be a number a {base_type} holds, got an integer "
                                   f"of {value.bit_length()} bits") from None
        return enc_float
    lo, hi = _INT_RANGES[base_type]

    def enc_int(value: Any, path: str, forms: JsonForms) -> int:
        if value is _MISSING:
            return 0
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer() and abs(value) <= _EXACT_FLOAT_INT:
                value = int(value)
            else:       # past 2**53 a float is no exact integer (an integer past 64 bits is read as one)
                raise MessageError(f"{owner}: field '{path}' must be an integer ({base_type}), got {value!r}")
        if not lo <= value <= hi:
            raise MessageError(f"{owner}: field '{path}' value {value} is out of range for {base_type}")
        return value
    return enc_int


def _numeric_array_encoder(base_type: str, fixed: int | None, owner: str) -> Encoder:
    import numpy as np
    dtype = _NP_DTYPES[base_type]
    is_bytes = base_type in ("uint8", "char", "byte")
    item = _base_encoder(base_type, owner)
    whole = _whole_array(base_type, dtype)

    def enc(value: Any, path: str, forms: JsonForms) -> np.ndarray:
        if value is _MISSING:
            return np.zeros(fixed or 0, dtype=dtype)
        if is_bytes and isinstance(value, _BINARY):
            arr = np.frombuffer(bytes(value), dtype=np.uint8).copy()
            forms.saw("byte_arrays", "binary")
        elif is_bytes and isinstance(value, str):
            try:
                arr = np.frombuffer(base64.b64decode(value, validate=True), dtype=np.uint8)
            except ValueError:
                raise MessageError(f"{owner}: field '{path}' is not valid base64") from None
            forms.saw("byte_arrays", "base64")
        elif isinstance(value, list):
            arr = whole(value)
            if arr is None:     # something to refuse (or null: NaN): item by item, for the error's field path
                arr = np.array([item(x, f"{path}[{i}]", forms) for i, x in enumerate(value)], dtype=dtype)
        else:
            what = " or base64 string (or a binary part)" if is_bytes else ""
            raise MessageError(f"{owner}: field '{path}' must be a list{what}, got {type(value).__name__}")
        if fixed is not None and len(arr) != fixed:
            raise MessageError(f"{owner}: field '{path}' must have {fixed} items, got {len(arr)}")
        return arr
    return enc


def _whole_array(base_type: str, dtype: Any) -> Callable[[list], np.ndarray | None]:
    """The fast path of a JSON list -> numeric array of ROS type ``base_type``: the whole list at C speed
    when every item is what the item encoder (:func:`_base_encoder`) takes as it is (numbers, not
    bools, for floats; in-range integers for integers; bools for bools); ``None`` otherwise (the
    caller then goes item by item, which refuses what does not fit, naming the item)."""
    import numpy as np
    kinds = {float, int} if base_type in _FLOATS else {bool} if base_type == "bool" else {int}
    lo, hi = _INT_RANGES[base_type] if kinds == {int} else (None, None)

    def whole(value: list) -> np.ndarray | None:
        if not value or not set(map(type, value)) <= kinds:
            return None
        if lo is not None and not lo <= min(value) <= max(value) <= hi:
            return None
        try:
            return np.array(value, dtype=dtype)
        except (OverflowError, ValueError):     # an integer too large for a float: item by item says so
            return None
    return whole


def _numeric_array_decoder(floats: bool) -> Decoder:
    """Numeric array (numpy, as rosbags gives it) -> JSON list of Python numbers; non-finite
    floats become ``null`` (as :func:`_base_decoder`, as rosbridge sends them)."""
    import numpy as np
    if not floats:
        return lambda value: np.asarray(value).tolist()

    def dec(value: Any) -> list:
        out = np.asarray(value).tolist()
        if all(map(math.isfinite, out)):
            return out
        return [x if math.isfinite(x) else None for x in out]
    return dec


_DEFAULT: MessageRegistry | None = None


def default_registry() -> MessageRegistry:
    """The process-wide registry (created on first use)."""
    global _DEFAULT
    if _DEFAULT is None:
        _DEFAULT = MessageRegistry()
    return _DEFAULT
