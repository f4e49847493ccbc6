"""ROS 1 <-> ROS 2 conversion of serialized messages, field by field, as ros1_bridge maps a pair of
types with the same package and name (ros2/ros1_bridge, "Type mapping": fields are paired by name).

A connection may join a ROS 1 end (``std_msgs/String``, ROS 1 serialization) and a ROS 2 end
(``std_msgs/msg/String``, CDR) of the same type (:func:`rce.messages.registry.same_type`); the end
that sends converts (:meth:`rce.transport.interface.Interface.send_message`). The message is
decoded with its own typestore (rosbags), rebuilt as the other side's class and encoded again:

- fields both sides have are copied (nested messages converted in turn, arrays of numbers as they are);
- a field only the source has is dropped (ROS 1's ``Header.seq``);
- a field only the destination has takes its default.

:func:`converter` raises :class:`MessageError` when either type is unknown; the converter it returns
raises :class:`MessageError` when the bytes do not decode.
"""
from __future__ import annotations

from typing import Any, Callable

from rosbags.typesys.base import Nodetype

from rce.interfaces.classes import Conversion, same_type
from rce.messages.registry import ROS2_PREFIX, MessageRegistry
from rce.plumbing.errors import MessageError

Build = Callable[[Any], Any]


def _half(registry: MessageRegistry, typename: str) -> tuple[MessageRegistry, str]:
    """The registry half that holds ``typename`` and its name there."""
    if typename.startswith(ROS2_PREFIX):
        return registry.ros2, typename[len(ROS2_PREFIX):]
    return registry, typename


def _builder(src: MessageRegistry, dst: MessageRegistry, src_t: str, dst_t: str, cache: dict) -> Build:
    """A function from an instance of ``src_t`` (``src``'s store) to one of ``dst_t`` (``dst``'s)."""
    key = (src_t, dst_t)
    if key in cache:
        return cache[key]
    cache[key] = lambda msg: build(msg)       # a type that contains itself refers to its own builder
    src_fields = dict(src.store.fielddefs[src_t][1])
    default = dst.from_json(dst_t, {})
    cls = dst.store.types[dst_t]
    steps: list[tuple[str, Callable[[Any], Any] | None, Any]] = []
    for name, (nt, arg) in dst.store.fielddefs[dst_t][1]:
        if name not in src_fields:
            steps.append((name, None, getattr(default, name)))
            continue
        s_nt, s_arg = src_fields[name]
        if nt == Nodetype.NAME and s_nt == Nodetype.NAME:
            steps.append((name, _builder(src, dst, s_arg, arg, cache), None))
        elif (nt in (Nodetype.ARRAY, Nodetype.SEQUENCE) and arg[0][0] == Nodetype.NAME
              and s_nt in (Nodetype.ARRAY, Nodetype.SEQUENCE) and s_arg[0][0] == Nodetype.NAME):
            sub = _builder(src, dst, s_arg[0][1], arg[0][1], cache)
            steps.append((name, lambda v, _sub=sub: [_sub(x) for x in v], None))
        else:
            steps.append((name, _same, None))

    def build(msg: Any) -> Any:
        return cls(**{name: (fixed if conv is None else conv(getattr(msg, name))) for name, conv, fixed in steps})
    cache[key] = build
    return build


def _same(value: Any) -> Any:
    return value


def converter(registry: MessageRegistry, src_t: str, dst_t: str) -> Callable[[bytes | memoryview], bytes]:
    """The function that turns serialized ``src_t`` into serialized ``dst_t`` (registry type names:
    one ROS 1, one ``ros2:``). Made once per pair and kept by the registry. Raises
    :class:`MessageError` if either type is unknown."""
    key = (src_t, dst_t)
    conv = registry.converters.get(key)
    if conv is not None:
        return conv
    (s_reg, s_t), (d_reg, d_t) = _half(registry, src_t), _half(registry, dst_t)
    for reg, t in ((s_reg, s_t), (d_reg, d_t)):
        if t not in reg.store.fielddefs:
            raise MessageError(f"cannot convert {src_t} to {dst_t}: {t} is unknown")
    build = _builder(s_reg, d_reg, s_t, d_t, {})

    def convert(payload: bytes | memoryview) -> bytes:
        try:
            return d_reg.serialize(d_t, build(s_reg.deserialize(s_t, bytes(payload))))
        except MessageError as e:
            raise MessageError(f"cannot convert {s_t} to {d_t}: {e.message}") from None
        except Exception as e:        # a value the other side's type cannot hold
            raise MessageError(f"cannot convert {s_t} to {d_t}: {e}") from None
    registry.converters[key] = convert
    return convert


def conversion(registry: MessageRegistry, kind: str, cls: str, peer_cls: str) -> Conversion:
    """How an interface of ``kind`` (Subscriber, ServiceProvider: the kinds that send) and class ``cls``
    converts for a peer of ``peer_cls``, the same type in the other ROS. Raises :class:`MessageError`
    when either class is unknown here, or they are not the same type."""
    if not same_type(cls, peer_cls):
        raise MessageError(f"{cls} and {peer_cls} are not the same type")
    if kind in ("ServiceProvider", "ServiceClient"):
        (req, resp), (peer_req, peer_resp) = registry.srv_types(cls), registry.srv_types(peer_cls)
        return Conversion(converter(registry, req, peer_req), converter(registry, peer_resp, resp))
    return Conversion(converter(registry, registry.msg_type(cls), registry.msg_type(peer_cls)))
