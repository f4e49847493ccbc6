"""Lanes: which of a robot session's connections a message travels on, sans I/O (docs/lanes.md).

Every interface has a :class:`Lane`:

- ``control``: services, action goals and cancels, small commands (``std_msgs`` scalars,
  ``geometry_msgs/Twist``): never dropped, never waits behind data;
- ``state``: poses, odometry, transforms, joint states: each interface keeps its newest;
- ``bulk``: images, point clouds, laser scans, maps: cut into small frames and paced below the
  link's rate; each interface keeps its newest.

The lane is set per interface (``"lane"`` in a CN ``addInterfaces`` component, in a robot config,
in a rosbridge op), or comes from the message type (:func:`default_lane`). A message of an
interface whose lane was not set and that is larger than :data:`BULK_SIZE` travels bulk whatever
its type (:func:`message_lane`): a big string must not hold a cancel up.
"""
from __future__ import annotations

from enum import StrEnum
from typing import Any

from rce.plumbing.errors import ProtocolError
from rce.plumbing.text import short_repr

BULK_SIZE = 16 * 1024      # bytes: a message of a default-laned interface above this travels bulk; also
                           # the largest frame a bulk lane writes (docs/lanes.md "Frames")


class Lane(StrEnum):
    """A lane, in priority order: control before state before bulk."""
    CONTROL = "control"
    STATE = "state"
    BULK = "bulk"

    @property
    def rank(self) -> int:
        """0 (control, first) to 2 (bulk, last)."""
        return _RANK[self]


_RANK = {Lane.CONTROL: 0, Lane.STATE: 1, Lane.BULK: 2}

# message types by package and name (ROS 1 names, "pkg/Name"); the first match wins
_BY_TYPE: dict[str, Lane] = {
    # bulk: sensor data and maps
    "sensor_msgs/Image": Lane.BULK, "sensor_msgs/CompressedImage": Lane.BULK,
    "sensor_msgs/PointCloud": Lane.BULK, "sensor_msgs/PointCloud2": Lane.BULK,
    "sensor_msgs/LaserScan": Lane.BULK, "sensor_msgs/MultiEchoLaserScan": Lane.BULK,
    "stereo_msgs/DisparityImage": Lane.BULK, "nav_msgs/OccupancyGrid": Lane.BULK,
    "nav_msgs/GetMap": Lane.BULK, "map_msgs/OccupancyGridUpdate": Lane.BULK,
    "theora_image_transport/Packet": Lane.BULK, "audio_common_msgs/AudioData": Lane.BULK,
    # state: where the robot is and how it moves
    "nav_msgs/Odometry": Lane.STATE, "nav_msgs/Path": Lane.STATE, "tf/tfMessage": Lane.STATE,
    "tf2_msgs/TFMessage": Lane.STATE, "sensor_msgs/Imu": Lane.STATE, "sensor_msgs/NavSatFix": Lane.STATE,
    "sensor_msgs/JointState": Lane.STATE, "sensor_msgs/BatteryState": Lane.STATE,
    "sensor_msgs/CameraInfo": Lane.STATE, "sensor_msgs/Range": Lane.STATE,
    # control: commands a teleoperator or a planner sends
    "geometry_msgs/Twist": Lane.CONTROL, "geometry_msgs/TwistStamped": Lane.CONTROL,
    "actionlib_msgs/GoalID": Lane.CONTROL,
}
# by package, when the type is not listed: geometry_msgs (poses, transforms, vectors) is state;
# std_msgs (scalars, strings, small arrays) and actionlib_msgs are control
_BY_PACKAGE: dict[str, Lane] = {"geometry_msgs": Lane.STATE, "std_msgs": Lane.CONTROL,
                                "actionlib_msgs": Lane.CONTROL}
# by name suffix (actionlib: goals and cancels are control, feedback is state, results are control)
_BY_SUFFIX: tuple[tuple[str, Lane], ...] = (("ActionGoal", Lane.CONTROL), ("ActionResult", Lane.CONTROL),
                                            ("ActionFeedback", Lane.STATE))


def parse_lane(value: Any, where: str = "lane") -> Lane:
    """The lane named ``value`` (``"control"``, ``"state"`` or ``"bulk"``, any case). Raises
    :class:`ProtocolError` naming ``where`` (e.g. ``interfaces[2].lane``; empty: not named) and the
    lanes there are."""
    if isinstance(value, Lane):
        return value
    lane = Lane._value2member_map_.get(value.lower()) if isinstance(value, str) else None
    if lane is None:
        raise ProtocolError(f"{where + ': ' if where else ''}unknown lane {short_repr(value)}: expected one of "
                            f"{', '.join(repr(x.value) for x in Lane)}")
    return lane


def default_lane(cls: str, service: bool = False) -> Lane:
    """The lane of an interface that did not set one: from its message or service class ``cls``
    (ROS name ``pkg/Name``; a leading ``/`` or ``pkg/msg/Name`` form is taken too) and whether it is
    a service (``service``: services are control, a map service is bulk)."""
    pkg, _, name = cls.strip("/").replace("/msg/", "/").replace("/srv/", "/").partition("/")
    full = f"{pkg}/{name}"
    if full in _BY_TYPE:
        return _BY_TYPE[full]
    if service:
        return Lane.CONTROL
    for suffix, lane in _BY_SUFFIX:
        if name.endswith(suffix):
            return lane
    return _BY_PACKAGE.get(pkg, Lane.STATE)


def interface_lane(cls: str, service: bool, lane: Any = None, where: str = "lane") -> Lane:
    """The lane of an interface: ``lane`` when set (parsed, :func:`parse_lane`), else
    :func:`default_lane`. Raises :class:`ProtocolError` for a bad ``lane``."""
    return default_lane(cls, service) if lane is None else parse_lane(lane, where)


def message_lane(lane: Lane, explicit: bool, size: int) -> Lane:
    """The lane one message of ``size`` bytes takes on an interface of lane ``lane``: a message
    larger than :data:`BULK_SIZE` travels bulk unless the interface set its lane (``explicit``)."""
    if not explicit and size > BULK_SIZE and lane is not Lane.BULK:
        return Lane.BULK
    return lane
