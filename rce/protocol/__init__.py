"""The robot <-> cloud client protocol (DESIGN section 3), sans I/O.

- :mod:`rce.protocol.frames`: text frames and binary parts (:class:`Assembler`, :func:`encode`);
- :mod:`rce.protocol.schema`: the one schema of robot -> cloud requests (:func:`validate`),
  whose component models the robot config shares;
- :mod:`rce.protocol.session`: the rules of a robot session, cloud side
  (:class:`RobotSession`) and robot side (:class:`ClientSession`), frames in, events out.
- :mod:`rce.protocol.limits`: the bounds a session keeps under hostile input (JSON depth, ER
  text and rate, the endpoint's budget of pending binary parts).
"""
from rce.protocol.frames import (CC, CN, CX, DC, DEFAULT_EXPIRY, DM, ER, ID_LEN, ST, Assembler, encode,
                                 is_part_id, new_id)
from rce.protocol.schema import split_interface_type, validate

__all__ = ["CC", "CN", "CX", "DC", "DEFAULT_EXPIRY", "DM", "ER", "ID_LEN", "ST", "Assembler", "encode",
           "is_part_id", "new_id", "split_interface_type", "validate"]
