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
