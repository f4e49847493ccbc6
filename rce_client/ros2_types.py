"""rclpy's classes and node names for the robot-side interfaces of ``rce-ros --ros2``.

The rclpy class of an interface's class, with an action's parts, is :func:`rce.ros2.classes.rclpy_class`'s
(the table of names there); here it is refused naming the interface.

A class in ROS 1's form (``std_msgs/String``) is refused on a ``--ros2`` bridge: its bytes would be
ROS 1 serialized, which no rclpy node reads (:func:`check_ros2_class`).
"""
from __future__ import annotations

import re
from typing import Any

from rce.interfaces.classes import is_ros2_name
from rce.interfaces.qos import QoS
from rce.plumbing.errors import ConfigError, MessageError
from rce.ros2 import classes

def check_ros2_class(itag: str, cls: str) -> None:
    """Refuse a class not in ROS 2's form for interface ``itag``: :class:`ConfigError` that says so
    and names the ROS 2 form to use (a ROS 1 peer in the cloud is converted by the engine)."""
    if is_ros2_name(cls):
        return
    parts = cls.strip("/").split("/")
    hint = (f" (its ROS 2 name is e.g. {parts[0]}/msg/{parts[1]} or {parts[0]}/srv/{parts[1]})"
            if len(parts) == 2 else "")
    raise ConfigError(f"interface {itag} ({cls}): --ros2 bridges ROS 2 classes only, named pkg/msg/Type, "
                      f"pkg/srv/Type or pkg/action/Type{hint}; a ROS 1 interface in the cloud connects to it "
                      f"and the engine converts")


def rclpy_class(itag: str, cls: str) -> Any:
    """The rclpy message or service class of ROS 2 class ``cls`` (:func:`rce.ros2.classes.rclpy_class`)
    for interface ``itag``. Raises :class:`ConfigError` naming the interface and the class when it is not
    in ROS 2's form, its package's Python module is not installed, or the module has no such class."""
    check_ros2_class(itag, cls)
    try:
        return classes.rclpy_class(cls)
    except MessageError as e:
        raise ConfigError(f"interface {itag} ({cls}): {e.message}") from None


def is_service_class(rclpy_cls: Any) -> bool:
    """Is ``rclpy_cls`` a service class (one with ``Request`` and ``Response``)?"""
    return hasattr(rclpy_cls, "Request") and hasattr(rclpy_cls, "Response")


def describe_qos(qos: QoS | None) -> str:
    """``reliable, volatile, keep_last 10``: a profile as a log line says it."""
    q = qos or QoS()
    return f"{q.reliability}, {q.durability}, {q.history}" + (f" {q.depth}" if q.history == "keep_last" else "")


def node_name(robot_id: str) -> str:
    """A valid ROS 2 node name after ``robot_id``: runs of characters other than letters and digits
    become one ``_``, and one that does not start with a letter or ``_`` gets ``rce_`` before it."""
    name = re.sub(r"[^A-Za-z0-9]+", "_", robot_id)
    return name if re.match(r"[A-Za-z_]", name) else f"rce_{name}"
