"""rclpy's classes, QoS profiles and node names for the robot-side interfaces of ``rce-ros --ros2``.

An interface's class is named in ROS 2's form (:func:`rce.interfaces.classes.is_ros2_name`); the
rclpy class of that name is the generated Python class of its package (``std_msgs/msg/String`` ->
``std_msgs.msg.String``, as ``rosidl_runtime_py.utilities.get_interface`` finds it). An action's
parts (:mod:`rce.interfaces.actions`) are the classes rosidl generates inside the action's class:

=====================================  ==================================================
rce class                              rclpy class
=====================================  ==================================================
``pkg/action/T_SendGoal``              ``pkg.action.T.Impl.SendGoalService``
``pkg/action/T_GetResult``             ``pkg.action.T.Impl.GetResultService``
``pkg/action/T_FeedbackMessage``       ``pkg.action.T.Impl.FeedbackMessage``
``pkg/action/T_Goal`` (``_Result``,    ``pkg.action.T.Goal`` (``.Result``, ``.Feedback``)
``_Feedback``)
``action_msgs/srv/CancelGoal``,        plain: ``action_msgs.srv.CancelGoal``,
``action_msgs/msg/GoalStatusArray``    ``action_msgs.msg.GoalStatusArray``
=====================================  ==================================================

A class in ROS 1's form (``std_msgs/String``) is refused on a ``--ros2`` bridge: its bytes would be
ROS 1 serialized, which no rclpy node reads (:func:`check_ros2_class`).
"""
from __future__ import annotations

import importlib
import re
from typing import Any

from rce.interfaces.classes import is_ros2_name
from rce.interfaces.qos import QoS
from rce.plumbing.errors import ConfigError

#: Suffixes of an action's part classes -> the attribute path of their rclpy class under the action's class.
ACTION_PARTS = {
    "_SendGoal": ("Impl", "SendGoalService"),
    "_GetResult": ("Impl", "GetResultService"),
    "_FeedbackMessage": ("Impl", "FeedbackMessage"),
    "_Goal": ("Goal",),
    "_Result": ("Result",),
    "_Feedback": ("Feedback",),
}


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
    """The rclpy message or service class of ROS 2 class ``cls`` (the table above) for interface
    ``itag``. Raises :class:`ConfigError` naming the interface and the class when it is not in ROS 2's
    form, its package's Python module is not installed, or the module has no such class."""
    check_ros2_class(itag, cls)
    pkg, sub, name = cls.strip("/").split("/")
    attrs: tuple[str, ...] = (name,)
    if sub == "action":
        for suffix, path in ACTION_PARTS.items():
            if name.endswith(suffix) and len(name) > len(suffix):
                attrs = (name[:-len(suffix)], *path)
                break
    where = f"interface {itag} ({cls})"
    try:
        obj: Any = importlib.import_module(f"{pkg}.{sub}")
    except ImportError as e:
        raise ConfigError(f"{where}: no rclpy class: the Python module {pkg}.{sub} is not installed ({e}); "
                          f"install the package's ROS 2 interfaces (e.g. ros-jazzy-{pkg.replace('_', '-')})") from None
    for i, attr in enumerate(attrs):
        obj = getattr(obj, attr, None)
        if obj is None:
            raise ConfigError(f"{where}: no rclpy class: {pkg}.{sub} has no {'.'.join(attrs[:i + 1])}")
    return obj


def is_service_class(rclpy_cls: Any) -> bool:
    """Is ``rclpy_cls`` a service class (one with ``Request`` and ``Response``)?"""
    return hasattr(rclpy_cls, "Request") and hasattr(rclpy_cls, "Response")


def qos_profile(qos: QoS | None) -> Any:
    """rclpy's ``QoSProfile`` of a config's :class:`~rce.interfaces.qos.QoS` (None: rclpy's default,
    reliable, volatile, keep last 10, which is also ``qos_profile_services_default``)."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    q = qos or QoS()
    return QoSProfile(depth=q.depth, reliability=ReliabilityPolicy[q.reliability.upper()],
                      durability=DurabilityPolicy[q.durability.upper()], history=HistoryPolicy[q.history.upper()])


def describe_qos(qos: QoS | None) -> str:
    """``reliable, volatile, keep_last 10``: a profile as a log line says it."""
    q = qos or QoS()
    return f"{q.reliability}, {q.durability}, {q.history}" + (f" {q.depth}" if q.history == "keep_last" else "")


def node_name(robot_id: str) -> str:
    """A valid ROS 2 node name after ``robot_id``: runs of characters other than letters and digits
    become one ``_``, and one that does not start with a letter or ``_`` gets ``rce_`` before it."""
    name = re.sub(r"[^A-Za-z0-9]+", "_", robot_id)
    return name if re.match(r"[A-Za-z_]", name) else f"rce_{name}"
