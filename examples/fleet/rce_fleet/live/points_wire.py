"""The simulated robots' ``obstacles`` messages (``geometry_msgs/PoseArray`` of lidar points)
straight to ROS 1 bytes, or to CDR for a ROS 2 robot (``geometry_msgs/msg/PoseArray``).

The simulator host publishes, once a simulated second per robot, the lidar points the map
does not explain (up to 120). Built as JSON, a dict per point, and converted through the
message registry (:meth:`rce.messages.MessageRegistry.json_to_bytes`) such a message cost
about 230 us for 60 points; packed from the detector's array, 3 us. The layout (ROS 1
serialisation, https://wiki.ros.org/msg#Serialization): the header (uint32 seq, the stamp as
int32 secs and uint32 nsecs as the registry's time, ``frame_id`` as its uint32 length and
bytes), the array's uint32 length, then 7 little-endian float64 per pose (position x, y, z,
orientation x, y, z, w). ``tests/fleet/test_sim.py`` checks the bytes against the registry's.

The CDR form (``ros2=True``; XCDR1 little endian as rclpy's ``serialize_message`` writes it, OMG
DDS-XTypes 1.3 section 7.4.3): the encapsulation header ``00 01 00 00``, the stamp as int32 sec and
uint32 nanosec (ROS 2's Header has no seq), ``frame_id`` as its uint32 length counting a NUL and the
bytes with the NUL, zeros up to a multiple of 4 for the array's uint32 length, zeros up to a multiple
of 8 (offsets count from after the encapsulation header), then the float64s as above.
``tests/fleet/test_fleet_ros2.py`` checks them against the registry's and rclpy's.
"""
from __future__ import annotations

import struct

import numpy as np

__all__ = ["PointsWire"]


class PointsWire:
    """Packs ``geometry_msgs/PoseArray`` messages of points in frame ``frame_id`` (header seq 0;
    each pose at z 0 without rotation); ``ros2``: as CDR (``geometry_msgs/msg/PoseArray``)."""

    def __init__(self, frame_id: str = "map", ros2: bool = False) -> None:
        frame = frame_id.encode()
        self._count = struct.Struct("<I")
        self._ros2 = ros2
        if ros2:
            frame += b"\0"
            body = 8 + 4 + len(frame)                  # sec, nanosec, frame_id; the count at a multiple of 4
            pad4 = -body % 4
            self._frame = struct.pack("<I", len(frame)) + frame + bytes(pad4)
            self._pad8 = bytes(-(body + pad4 + 4) % 8)  # the float64s at a multiple of 8
            self._stamp = struct.Struct("<4siI")       # encapsulation header, sec, nanosec
        else:
            self._frame = struct.pack("<I", len(frame)) + frame
            self._pad8 = b""
            self._stamp = struct.Struct("<IiI")        # seq, secs, nsecs

    def pack(self, secs: int, nsecs: int, xy: np.ndarray) -> bytes:
        """The message stamped ``secs``/``nsecs`` for the points ``xy`` ((N, 2) float, m). Raises
        :class:`struct.error` for a stamp outside int32 secs / uint32 nsecs."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        poses = np.zeros((len(xy), 7), dtype="<f8")
        poses[:, :2] = xy
        poses[:, 6] = 1.0
        head = self._stamp.pack(b"\x00\x01\x00\x00" if self._ros2 else 0, secs, nsecs)
        return b"".join((head, self._frame, self._count.pack(len(xy)), self._pad8 if len(xy) else b"",
                         poses.tobytes()))
