"""master -> robot task set (docs/INTERNALS.md, "Control ops"): the ops rce-master sends an
rce-robot, served by :data:`rce_robot.endpoint.ROBOT_OPS`, sent by :class:`rce_master.control.Control`
and :mod:`rce_master.placement.mover`."""
from __future__ import annotations

from typing import Any, Literal

from rce.contract.base import IType, OpArgs
from rce.interfaces.lanes import Lane


class EndpointAddInterface(OpArgs):
    """Robot ``robot`` of ``user`` gets robot-side interface ``iid`` (tag ``itag``, a converter or
    forwarder of ``itype`` for class ``cls``), on ``lane`` (None: from the class)."""
    OP = "add_interface"
    user: str
    robot: str
    iid: int
    itag: str
    itype: IType
    cls: str
    lane: Lane | None = None


class EndpointRemoveInterface(OpArgs):
    """Interface ``iid`` goes, with its data-plane connections (an unknown one: nothing to do)."""
    OP = "remove_interface"
    iid: int


class EndpointConnect(OpArgs):
    """Interface ``iid`` is connected to ``peer_iid`` at data address ``peer_addr``; ``token``: the
    credential that lets ``iid`` send there (64 hex digits, :mod:`rce.transport.cluster_auth`);
    ``peer_cls``: the peer's class, where it differs from this end's (the sender converts);
    ``fence``: a move's fence id (:mod:`rce_master.placement.mover`). A connect for a connection that
    exists replaces its address. Answer ``{fenced}``."""
    OP = "connect"
    iid: int
    peer_iid: int
    peer_addr: str
    token: str = ""             # rce.transport.cluster_auth.token_of checks it, naming what is wrong
    peer_cls: str | None = None
    fence: int | None = None


class EndpointDisconnect(OpArgs):
    """The connection of ``iid`` to ``peer_iid`` is gone."""
    OP = "disconnect"
    iid: int
    peer_iid: int


class EndpointNotify(OpArgs):
    """A status (``ST``) or error (``ER``) for the robot, ``data`` as the robot gets it (a
    notification: a robot that is not here any more is no error)."""
    OP = "notify"
    user: str
    robot: str
    type: Literal["ST", "ER"]
    data: Any = None


class EndpointCloseRobot(OpArgs):
    """Close the robot's session (it logs in again), telling it ``reason``."""
    OP = "close_robot"
    user: str
    robot: str
    reason: str = "closed by the master"
