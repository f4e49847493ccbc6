"""Where a container host or a robot endpoint stands: its zone (docs/design.md, section 9.1).

- ``cloud``: a machine in the data centre, shared by every user;
- ``edge``: a machine near the robots (on the site's network), shared by every user;
- ``robot:ROBOT_ID``: the robot's own computer; it serves that robot's user alone
  (``rce-container --zone robot:r1 --user alice``).

A host registers its zone with the master (``register`` args ``zone`` and ``zone_user``); the
master places a container on a ``robot:`` host only for that user and that robot, and hands a
``robot:`` endpoint (``rce-robot --zone robot:r1 --user alice``) only that robot's logins.
"""
from __future__ import annotations

from dataclasses import dataclass

from rce.plumbing.errors import RequestError

__all__ = ["CLOUD", "KINDS", "Zone", "parse_zone"]

KINDS = ("cloud", "edge", "robot")


@dataclass(frozen=True)
class Zone:
    """A parsed zone: ``kind`` one of :data:`KINDS`; ``robot`` and ``user`` only for ``robot``."""
    kind: str
    robot: str = ""
    user: str = ""

    def __str__(self) -> str:
        return f"robot:{self.robot}" if self.kind == "robot" else self.kind

    def serves(self, user: str, robot: str | None) -> bool:
        """Whether a container of ``user`` serving robot ``robot`` (None: no robot named) may run here."""
        return self.kind != "robot" or (user == self.user and robot == self.robot)


CLOUD = Zone("cloud")


def parse_zone(text: str, user: str | None = None) -> Zone:
    """``"cloud"``, ``"edge"`` or ``"robot:ROBOT_ID"`` (with ``user``, the robot's user) as a :class:`Zone`.

    Raises :class:`RequestError` naming what is wrong: an unknown kind, a ``robot:`` zone without
    a robot ID or without its user, a user given for a shared zone."""
    kind, _, robot = str(text).partition(":")
    if kind not in KINDS:
        raise RequestError(f"zone {text!r}: must be 'cloud', 'edge' or 'robot:ROBOT_ID'")
    if kind != "robot":
        if robot:
            raise RequestError(f"zone {text!r}: only a robot zone names something after ':'")
        if user:
            raise RequestError(f"zone {text!r} is shared by every user; a user is given only with robot:ROBOT_ID")
        return Zone(kind)
    if not robot:
        raise RequestError(f"zone {text!r}: give the robot's ID, e.g. robot:r1")
    if not user:
        raise RequestError(f"zone {text!r} serves one user: give the robot's user (--user NAME)")
    return Zone("robot", robot, user)
