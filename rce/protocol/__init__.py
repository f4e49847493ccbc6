"""The robot <-> cloud client protocol (docs/design.md, section 3), sans I/O.

- :mod:`rce.protocol.frames`: text frames and binary parts (:class:`Assembler`, :func:`encode`);
- :mod:`rce.protocol.schema`: the one schema of robot -> cloud requests (:func:`validate`),
  whose component models the robot config shares;
- :mod:`rce.protocol.session`: the rules of a robot session, cloud side
  (:mod:`~rce.protocol.robot_session`) and robot side (:mod:`~rce.protocol.client_session`),
  frames in, typed events out (:mod:`rce.protocol.events`); the cloud side composes
  :mod:`~rce.protocol.holdback` (requests and the DMs held back for them) and
  :mod:`~rce.protocol.robot_outbox` (what goes to the robot: :mod:`~rce.protocol.outbox`, the one
  outbox policy, and :mod:`~rce.protocol.error_limits`); :mod:`rce.protocol.resume`: session resume.
- :mod:`rce.protocol.limits`: the bounds a session keeps under hostile input (JSON depth, ER
  text and rate, the endpoint's budget of pending binary parts).
"""
import importlib

#: The package's names and the modules that define them. They load on first use (PEP 562), so a
#: process that needs only a light part (an environment: interface types) does not build the
#: pydantic schema.
_EXPORTS = {**dict.fromkeys(("CC", "CN", "CX", "DC", "DEFAULT_EXPIRY", "DM", "ER", "ID_LEN", "ST", "Assembler",
                             "encode", "is_part_id", "new_id"), "rce.protocol.frames"),
            "split_interface_type": "rce.protocol.schema", "validate": "rce.protocol.schema"}

__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'rce.protocol' has no attribute {name!r}")
    value = getattr(importlib.import_module(_EXPORTS[name]), name)
    globals()[name] = value
    return value
