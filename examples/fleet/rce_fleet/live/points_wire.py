"""The simulated robots' ``obstacles`` messages (``geometry_msgs/PoseArray`` of lidar points)
straight to ROS 1 bytes.

The simulator host publishes, once a simulated second per robot, the lidar points the map
does not explain (up to 120). Built as JSON, a dict per point, and converted through the
message registry (:meth:`rce.messages.MessageRegistry.json_to_bytes`) such a message cost
about 230 us for 60 points; packed from the detector's array, 3 us. The layout (ROS 1
serialisation, https://wiki.ros.org/msg#Serialization): the header (uint32 seq, the stamp as
int32 secs and uint32 nsecs as the registry's time, ``frame_id`` as its uint32 length and
bytes), the array's uint32 length, then 7 little-endian float64 per pose (position x, y, z,
orientation x, y, z, w). ``tests/fleet/test_sim.py`` checks the bytes against the registry's.
"""
from __future__ import annotations

import struct

import numpy as np

__all__ = ["PointsWire"]


class PointsWire:
    """Packs ``geometry_msgs/PoseArray`` messages of points in frame ``frame_id`` (header seq 0;
    each pose at z 0 without rotation)."""

    def __init__(self, frame_id: str = "map") -> None:
        frame = frame_id.encode()
        self._frame = struct.pack("<I", len(frame)) + frame
        self._stamp = struct.Struct("<IiI")       # seq, secs, nsecs
        self._count = struct.Struct("<I")

    def pack(self, secs: int, nsecs: int, xy: np.ndarray) -> bytes:
        """The message stamped ``secs``/``nsecs`` for the points ``xy`` ((N, 2) float, m). Raises
        :class:`struct.error` for a stamp outside int32 secs / uint32 nsecs."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        poses = np.zeros((len(xy), 7), dtype="<f8")
        poses[:, :2] = xy
        poses[:, 6] = 1.0
        return b"".join((self._stamp.pack(0, secs, nsecs), self._frame, self._count.pack(len(xy)), poses.tobytes()))
