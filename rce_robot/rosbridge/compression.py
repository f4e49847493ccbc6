"""rosbridge v2 ``compression`` of what a subscription sends (``ROSBRIDGE_PROTOCOL.md``,
"Subscribe", and rosbridge_library's ``capabilities/subscribe.py``):

- ``png``: the ``publish`` op's JSON text packed into the RGB pixels of a PNG image (rosbridge's
  ``internal/pngcompression.py``: width ``floor(sqrt(n / 3))``, height ``ceil(n / 3 / width)``,
  padded with ``\\n``), sent as ``{op: "png", data: BASE64}``; roslibjs draws it on a canvas and
  reads the pixels back. The JSON is ASCII (``\\u`` escapes), since roslibjs maps each byte to a
  character.
- ``cbor``: the ``publish`` op as one binary websocket message in CBOR (RFC 8949, ``cbor2``), with
  rosbridge's ``internal/cbor_conversion.py`` rules: ``uint8[]``/``char[]`` as byte strings,
  numeric arrays as little-endian typed arrays (RFC 8746 tags, :data:`TYPED_ARRAY_TAGS`), time
  and duration as the JSON has them (``{secs, nsecs}``; ``{sec, nanosec}`` for ROS 2 types).
- ``cbor-raw``: ``{op: "publish", topic, msg: {secs, nsecs, bytes}}`` in CBOR: ``bytes`` the ROS 1
  serialization (CDR for a ROS 2 type, as rosbridge_suite's ROS 2 server sends), ``secs``/``nsecs`` the time
  the endpoint received it.
"""
from __future__ import annotations

import base64
import io
import math
from typing import Any

import cbor2
from rosbags.interfaces import Nodetype

from rce.messages import MessageRegistry
from rce.messages.registry import ROS2_PREFIX

COMPRESSIONS = ("none", "png", "cbor", "cbor-raw")
# ROS array item type -> (RFC 8746 tag, little-endian numpy dtype); rosbridge's TAGGED_ARRAY_FORMATS
TYPED_ARRAY_TAGS = {"uint16": (69, "<u2"), "uint32": (70, "<u4"), "uint64": (71, "<u8"), "byte": (72, "i1"),
                    "int8": (72, "i1"), "int16": (77, "<i2"), "int32": (78, "<i4"), "int64": (79, "<i8"),
                    "float32": (85, "<f4"), "float64": (86, "<f8")}
BYTE_STREAMS = ("uint8", "char")       # arrays sent as CBOR byte strings (rosbridge's BYTESTREAM_TYPES)
TIME_TYPES = ("builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration")   # already in their JSON form


def png_op(text: str) -> dict:
    """The ``png`` op carrying ``text`` (an op's JSON, ASCII) as rosbridge's ``pngcompression.encode``."""
    from PIL import Image       # only a session that asks for png pays its import (~60 ms of CPU)
    raw = text.encode("ascii")
    width = max(1, math.floor(math.sqrt(len(raw) / 3.0)))
    height = max(1, math.ceil(len(raw) / 3.0 / width))
    raw += b"\n" * (width * height * 3 - len(raw))
    buf = io.BytesIO()
    Image.frombytes("RGB", (width, height), raw).save(buf, "png")
    return {"op": "png", "data": base64.b64encode(buf.getvalue()).decode("ascii")}


def cbor_publish(registry: MessageRegistry, typename: str, topic: str, msg: Any) -> bytes:
    """The ``publish`` op of ``msg`` (a message of ``typename`` in rosbridge's JSON form, as a
    converter gives it) in CBOR, typed as rosbridge's ``extract_cbor_values``."""
    if typename.startswith(ROS2_PREFIX):         # the ROS 2 half's own names
        registry, typename = registry.ros2, typename[len(ROS2_PREFIX):]
    return cbor2.dumps({"op": "publish", "topic": topic, "msg": _values(registry, typename, msg)})


def cbor_raw_publish(registry: MessageRegistry, typename: str, topic: str, msg: Any, received: float) -> bytes:
    """The ``cbor-raw`` ``publish`` op: ``msg`` as its ROS 1 bytes (CDR for a ROS 2 ``typename``), ``received``
    (Unix s) as secs/nsecs."""
    secs = math.floor(received)
    raw = registry.json_to_bytes(typename, msg)
    return cbor2.dumps({"op": "publish", "topic": topic,
                        "msg": {"secs": secs, "nsecs": int((received - secs) * 1e9), "bytes": raw}})


def _values(registry: MessageRegistry, typename: str, msg: Any) -> Any:
    if typename in TIME_TYPES or not isinstance(msg, dict):
        return msg
    return {name: _field(registry, ftype, msg.get(name)) for name, ftype in registry.store.fielddefs[typename][1]
            if name in msg}


def _field(registry: MessageRegistry, ftype: tuple, value: Any) -> Any:
    nt, arg = ftype
    if nt == Nodetype.BASE:
        return value
    if nt == Nodetype.NAME:
        return _values(registry, arg, value)
    (sub_nt, sub_arg), _ = arg
    if sub_nt == Nodetype.NAME:
        return [_values(registry, sub_arg, x) for x in value]
    item = sub_arg[0]
    if item in BYTE_STREAMS and isinstance(value, str):           # rosbridge's JSON form: base64
        return base64.b64decode(value)
    if item in TYPED_ARRAY_TAGS and isinstance(value, list):
        tag, dtype = TYPED_ARRAY_TAGS[item]
        floats = dtype[-2] == "f"
        data = [math.nan if x is None and floats else x for x in value]     # JSON null is a non-finite float
        import numpy as np      # loaded by the first cbor typed array, as PIL by the first png op
        return cbor2.CBORTag(tag, np.asarray(data, dtype=dtype).tobytes())
    if item == "byte" and isinstance(value, str):
        return cbor2.CBORTag(72, base64.b64decode(value))
    return value

