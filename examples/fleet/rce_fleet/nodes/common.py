"""What the fleet's container nodes share: the :class:`Out` items their sans-I/O cores
return, publishing them, waiting for the grid parameter, and reading a robot's planar pose
from its ``amcl_pose`` bytes."""
from __future__ import annotations

import asyncio
import struct
from typing import Any, Iterable, NamedTuple

from rce.plumbing.errors import MessageError, Unavailable

from ..maps.geometry import GRID_PARAM, GridGeometry, quaternion_yaw

__all__ = ["Out", "PlanarPose", "planar_pose", "wait_param", "load_geometry", "Publishers", "PARAM_TIMEOUT_S",
           "PARAM_POLL_S"]

#: s a node waits for a parameter (the fleet manager sets ``/fleet/grid`` before it starts
#: the nodes; a node started by hand may come first) before it gives up.
PARAM_TIMEOUT_S = 30.0
#: s between two reads of a parameter that is not set yet.
PARAM_POLL_S = 0.1


class Out(NamedTuple):
    """One message a node's core wants published: ``topic``, message class ``type`` (wire
    name), JSON-form ``msg``."""
    topic: str
    type: str
    msg: dict


class PlanarPose(NamedTuple):
    """What the fleet's nodes read of a ``geometry_msgs/PoseWithCovarianceStamped``: ``x``, ``y``
    (m), ``yaw`` (rad, :func:`rce_fleet.maps.geometry.quaternion_yaw`) and ``stamp`` (s, the
    header stamp)."""
    x: float
    y: float
    yaw: float
    stamp: float


_HEAD = struct.Struct("<IiII")        # header.seq, header.stamp.sec, header.stamp.nanosec, len(frame_id)
_POSE = struct.Struct("<7d")          # pose.pose.position x y z, pose.pose.orientation x y z w
_POSE_REST = _POSE.size + 36 * 8      # and pose.covariance (float64[36])


def planar_pose(data: bytes) -> PlanarPose:
    """The :class:`PlanarPose` of a ROS 1 serialized ``geometry_msgs/PoseWithCovarianceStamped``
    (wire format: ROS 1 serialization, little-endian, a string as a uint32 length and its bytes),
    read without building the message (``frame_id`` and the covariance are skipped). ``data`` is
    held to the rule of :meth:`rce.messages.MessageRegistry.deserialize`: exactly the message's
    length (a string may hold any bytes, :mod:`rce.messages.ros_strings`), or :class:`MessageError`."""
    try:
        _seq, sec, nanosec, n = _HEAD.unpack_from(data)
        if len(data) != _HEAD.size + n + _POSE_REST:
            raise ValueError(f"the message is {len(data)} bytes, its frame_id of {n} bytes makes it "
                             f"{_HEAD.size + n + _POSE_REST}")
        x, y, _z, qx, qy, qz, qw = _POSE.unpack_from(data, _HEAD.size + n)
    except (struct.error, ValueError) as e:
        raise MessageError(f"{len(data)} bytes do not deserialize as geometry_msgs/PoseWithCovarianceStamped: "
                           f"{e}") from None
    return PlanarPose(x, y, quaternion_yaw(qx, qy, qz, qw), sec + nanosec * 1e-9)


async def wait_param(node, name: str, timeout: float = PARAM_TIMEOUT_S, interval: float = PARAM_POLL_S) -> Any:
    """The value of parameter ``name`` once set (the fleet manager sets it before it starts
    the nodes; a node started by hand may come first). Raises Unavailable after ``timeout`` s."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while True:
        v = await node.get_param(name, None)
        if v is not None:
            return v
        if loop.time() > deadline:
            raise Unavailable(f"parameter {name} is not set (the fleet manager sets it; waited {timeout:g} s)")
        await asyncio.sleep(interval)


async def load_geometry(node, timeout: float = PARAM_TIMEOUT_S) -> GridGeometry:
    """The grid from ``/fleet/grid``; raises Unavailable when it is not set within
    ``timeout`` s or is not a grid."""
    p = await wait_param(node, GRID_PARAM, timeout)
    try:
        return GridGeometry.from_param(p)
    except ValueError as e:
        raise Unavailable(f"{GRID_PARAM}: {e}") from None


class Publishers:
    """Publishers by topic, created up front; :meth:`send` publishes Out items in order."""

    def __init__(self, node):
        self.node = node
        self.pubs: dict[str, Any] = {}

    async def add(self, topic: str, typename: str, queue_size: int = 10) -> None:
        """Create the publisher of ``topic`` (message class ``typename``) unless there is one."""
        if topic not in self.pubs:
            self.pubs[topic] = await self.node.publisher(topic, typename, queue_size=queue_size)

    def send(self, outs: Iterable[Out]) -> None:
        """Publish ``outs`` in order; raises KeyError for a topic without a publisher."""
        for o in outs:
            pub = self.pubs.get(o.topic)
            if pub is None:
                raise KeyError(f"no publisher for {o.topic}")
            pub.publish_nowait(o.msg)
