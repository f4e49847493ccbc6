"""The simulated robots' ``amcl_pose`` messages straight to ROS 1 bytes.

The simulator host publishes a ``geometry_msgs/PoseWithCovarianceStamped`` per robot five
times a simulated second; building each as JSON and converting it through the message
registry (:meth:`rce.messages.MessageRegistry.json_to_bytes`: JSON -> message object ->
bytes) cost more than the rest of its publication. The message has a fixed layout but for
the header's ``frame_id``, so one :class:`struct.Struct` packs it (ROS 1 serialisation:
little-endian, a string as its uint32 length and bytes, a fixed-size array without a length;
https://wiki.ros.org/msg#Serialization). ``tests/fleet/test_sim.py`` checks the bytes against
the registry's.
"""
from __future__ import annotations

import math
import struct

__all__ = ["PoseWire"]


class PoseWire:
    """Packs ``geometry_msgs/PoseWithCovarianceStamped`` messages of frame ``frame_id`` (header
    seq 0, the pose in the plane: z 0, a rotation about z)."""

    def __init__(self, frame_id: str = "map") -> None:
        frame = frame_id.encode()
        self._head = struct.pack("<I", 0)
        self._frame = struct.pack("<I", len(frame)) + frame
        self._stamp = struct.Struct("<iI")        # as the registry's time: int32 secs, uint32 nsecs
        self._body = struct.Struct("<7d36d")

    def pack(self, secs: int, nsecs: int, x: float, y: float, yaw: float, covariance: list[float]) -> bytes:
        """The message at ``secs``/``nsecs`` (the stamp) for the pose (x m, y m, yaw rad) with its
        6 x 6 row-major ``covariance`` (36 floats). Raises :class:`struct.error` for a stamp
        outside int32 secs / uint32 nsecs or a covariance of another length."""
        return b"".join((self._head, self._stamp.pack(secs, nsecs), self._frame,
                         self._body.pack(x, y, 0.0, 0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0), *covariance)))
