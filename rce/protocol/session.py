"""The rules of a robot session, sans I/O, in the manner of the ``websockets`` library's
``Protocol``: frames in (:meth:`receive_text`, :meth:`receive_binary`), time in
(:meth:`tick`), and out come the frames to send (:meth:`data_to_send`) and typed events for the
application (:meth:`events_received`; :mod:`rce.protocol.events`). No sockets and no tasks: the robot
endpoint (:mod:`rce_robot.namespace`) and the client library (:mod:`rce_client.connection`) are
shells that move frames and run what the events ask for. Both share
:class:`~rce.protocol.session_core.SessionCore`; this module gathers their public names.

- :class:`RobotSession` (:mod:`rce.protocol.robot_session`) is the cloud side of one connected
  robot: binary parts and expiry, the one schema (:func:`rce.protocol.schema.validate`), requests
  to the master one at a time and in order, the DM ordering rule, the bounded outbox, error accounting.
- :class:`ClientSession` (:mod:`rce.protocol.client_session`) is the robot side: pending calls and
  barriers (one :class:`~rce.plumbing.pending.PendingCalls` table keyed by msgID or token), the interface
  status table, ER attribution. Its rules are those of ``tests/vectors/README.md``, which the
  browser client (``rce.js``) follows too; ``tests/vectors/session.json`` checks both.

Either side may opt in to session resume (``resume=True``; docs/INTERNALS.md "Session
resume"): messages are numbered and kept until acked (:mod:`rce.protocol.resume`), a lost link
detaches the session (:meth:`RobotSession.detach`, :meth:`ClientSession.detach`) and a new one
resumes it (:meth:`RobotSession.attach`, :meth:`ClientSession.attach`). Without it nothing
changes: no ``seq``, no ``AK``, no ``ST session``.
"""
from __future__ import annotations

from rce.protocol.client_session import BARRIER_PREFIX, ClientSession
from rce.protocol.events import Event
from rce.protocol.limits import DEFAULT_MAX_LAG
from rce.protocol.robot_session import (DEFAULT_MAX_MESSAGE, DEFAULT_QUEUE_SIZE, LAG_TOPIC, ResumeOptions,
                                        RobotSession, SessionLimits, robot_interface_type)

__all__ = ["BARRIER_PREFIX", "DEFAULT_MAX_LAG", "DEFAULT_MAX_MESSAGE", "DEFAULT_QUEUE_SIZE", "LAG_TOPIC",
           "ClientSession", "Event", "ResumeOptions", "RobotSession", "SessionLimits", "robot_interface_type"]
