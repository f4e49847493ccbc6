"""The simulated robots' ``amcl_pose`` and ``obstacles`` messages straight to ROS 1 bytes.

The simulator host publishes a ``geometry_msgs/PoseWithCovarianceStamped`` per robot five
times a simulated second, and a ``geometry_msgs/PoseArray`` of up to 120 lidar points once a
second; building each as JSON and converting it through the message registry
(:meth:`rce.messages.MessageRegistry.json_to_bytes`: JSON -> message object -> bytes) cost
more than the rest of its publication. Both have a fixed layout but for the header's
``frame_id`` and the array's length, so :mod:`struct` and numpy pack them (ROS 1
serialisation: little-endian, a string or variable array as its uint32 length and items, a
fixed-size array without a length; https://wiki.ros.org/msg#Serialization).
``tests/fleet/test_sim.py`` checks the bytes against the registry's.
"""
from __future__ import annotations

import math
import struct

import numpy as np

__all__ = ["PoseWire"]


class PoseWire:
    """Packs ``geometry_msgs/PoseWithCovarianceStamped`` and ``geometry_msgs/PoseArray``
    messages of frame ``frame_id`` (header seq 0; poses in the plane: z 0, a rotation about z)."""

    def __init__(self, frame_id: str = "map") -> None:
        frame = frame_id.encode()
        self._head = struct.pack("<I", 0)
        self._frame = struct.pack("<I", len(frame)) + frame
        self._stamp = struct.Struct("<iI")        # as the registry's time: int32 secs, uint32 nsecs
        self._body = struct.Struct("<7d36d")
        self._count = struct.Struct("<I")

    def pack_pose(self, secs: int, nsecs: int, x: float, y: float, yaw: float, covariance: list[float]) -> bytes:
        """The message at ``secs``/``nsecs`` (the stamp) for the pose (x m, y m, yaw rad) with its
        6 x 6 row-major ``covariance`` (36 floats). Raises :class:`struct.error` for a stamp
        outside int32 secs / uint32 nsecs or a covariance of another length."""
        return b"".join((self._head, self._stamp.pack(secs, nsecs), self._frame,
                         self._body.pack(x, y, 0.0, 0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0), *covariance)))

    def pack_points(self, secs: int, nsecs: int, xy: np.ndarray) -> bytes:
        """A ``geometry_msgs/PoseArray`` at ``secs``/``nsecs`` of the points ``xy`` ((N, 2), m),
        each a pose with z 0 and no rotation."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        poses = np.zeros((len(xy), 7), dtype="<f8")
        poses[:, :2] = xy
        poses[:, 6] = 1.0
        return b"".join((self._head, self._stamp.pack(secs, nsecs), self._frame, self._count.pack(len(xy)),
                         poses.tobytes()))
