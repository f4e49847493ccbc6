"""Message and service class names in ROS 1's and ROS 2's forms, sans typestores.

A class named ``pkg/Type`` is a ROS 1 type (ROS 1 serialization on the wire); one named
``pkg/msg/Type``, ``pkg/srv/Type`` or ``pkg/action/Type`` (an action's parts:
``pkg/action/Type_SendGoal``...) is a ROS 2 type (CDR). Two classes that name the same package and
type in the two forms are the same type to a connection (:func:`same_type`): the end that sends
converts (:mod:`rce.messages.convert`), as ros1_bridge pairs ``std_msgs/String`` with
``std_msgs/msg/String``.
"""
from __future__ import annotations

import re
from typing import Callable, NamedTuple

Convert = Callable[[bytes | memoryview], bytes]


class Conversion(NamedTuple):
    """How an interface's bytes become its peer's where one end is ROS 1 and the other ROS 2
    (:mod:`rce.messages.convert`): ``out`` converts a message or a request to the peer's encoding,
    ``back`` (services) the peer's response to this end's."""
    out: Convert
    back: Convert | None = None

_ROS2_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*/(msg|srv|action)/[A-Za-z][A-Za-z0-9_]*")


def is_ros2_name(cls: object) -> bool:
    """Is ``cls`` a class name in ROS 2's form (``pkg/msg/T``, ``pkg/srv/T``, ``pkg/action/T``)?"""
    return isinstance(cls, str) and _ROS2_NAME.fullmatch(cls.strip("/")) is not None


def plain_name(cls: str) -> str:
    """``pkg/Type`` for a class in either form (``std_msgs/msg/String`` -> ``std_msgs/String``; an
    action's part keeps its ``action``: it has no ROS 1 twin)."""
    parts = cls.strip("/").split("/")
    return f"{parts[0]}/{parts[2]}" if len(parts) == 3 and parts[1] in ("msg", "srv") else "/".join(parts)


def same_type(a: str, b: str) -> bool:
    """Do classes ``a`` and ``b`` name the same type, each in ROS 1's or ROS 2's form
    (``std_msgs/String`` and ``std_msgs/msg/String``; ``Test/Echo`` and ``Test/srv/Echo``)?"""
    return a == b or (isinstance(a, str) and isinstance(b, str) and plain_name(a) == plain_name(b))
