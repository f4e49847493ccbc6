"""rclpy's classes and QoS profiles of rce's names (this module imports rclpy).

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
"""
from __future__ import annotations

import importlib
from typing import Any

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from rce.interfaces.qos import QoS
from rce.messages.ros2 import split_name
from rce.plumbing.errors import MessageError

#: Suffixes of an action's part classes -> the attribute path of their rclpy class under the action's class.
ACTION_PARTS = {
    "_SendGoal": ("Impl", "SendGoalService"),
    "_GetResult": ("Impl", "GetResultService"),
    "_FeedbackMessage": ("Impl", "FeedbackMessage"),
    "_Goal": ("Goal",),
    "_Result": ("Result",),
    "_Feedback": ("Feedback",),
}


def rclpy_class(cls: str) -> Any:
    """The rclpy message or service class of ROS 2 class ``cls`` (the table above). Raises
    :class:`MessageError` (``no rclpy class: ...``) when it is not in ROS 2's form, its package's
    Python module is not installed, or the module has no such class."""
    pkg, sub, name = split_name(cls)
    attrs: tuple[str, ...] = (name,)
    if sub == "action":
        for suffix, path in ACTION_PARTS.items():
            if name.endswith(suffix) and len(name) > len(suffix):
                attrs = (name[:-len(suffix)], *path)
                break
    try:
        obj: Any = importlib.import_module(f"{pkg}.{sub}")
    except ImportError as e:
        raise MessageError(f"no rclpy class: the Python module {pkg}.{sub} is not installed ({e}); install the "
                           f"package's ROS 2 interfaces (e.g. ros-jazzy-{pkg.replace('_', '-')})") from None
    for i, attr in enumerate(attrs):
        obj = getattr(obj, attr, None)
        if obj is None:
            raise MessageError(f"no rclpy class: {pkg}.{sub} has no {'.'.join(attrs[:i + 1])}")
    return obj


def qos_profile(qos: QoS | None) -> QoSProfile:
    """rclpy's ``QoSProfile`` of a :class:`~rce.interfaces.qos.QoS` (None: rclpy's default, reliable,
    volatile, keep last 10, which is also ``qos_profile_services_default``; deadline, lifespan and
    liveliness: DDS's defaults)."""
    q = qos or QoS()
    return QoSProfile(depth=q.depth, reliability=ReliabilityPolicy[q.reliability.upper()],
                      durability=DurabilityPolicy[q.durability.upper()], history=HistoryPolicy[q.history.upper()])
