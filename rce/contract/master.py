"""task set -> master (docs/INTERNALS.md, "Control ops"): what rce-robot and rce-container send
rce-master, served by the master's tables (:mod:`rce_master.server`: ``register`` first, then the
ops of the task set's kind), sent through :class:`rce.transport.masterlink.MasterLink`."""
from __future__ import annotations

from typing import Any, Literal

from pydantic import ConfigDict

from rce.contract.base import OpArgs
# an environment's word on a node and on an interface's bridge into ROS 2, which its host passes on unchanged
from rce.contract.environment import InterfaceStatus as InterfaceStatus
from rce.contract.environment import NodeStatusReport as NodeStatusReport


# -- every task set ------------------------------------------------------------------------------------
class Register(OpArgs):
    """The first op on a link: a task set of ``kind`` named ``name`` on ``host``, with what else it
    tells about itself (``ws_url``, ``data_addr``, ``sandbox``, ``capacity``, ``zone``...: kept as its
    info, so those keys are open). With ``tid`` it re-registers, reporting what it holds
    (``robots``, ``interfaces`` or ``containers``), which :class:`rce_master.state.reconcile.Report`
    checks field by field (docs/INTERNALS.md, "Re-registering")."""
    model_config = ConfigDict(extra="allow")
    OP = "register"
    kind: Literal["robot", "container"]
    name: str | None = None
    host: str | None = None
    tid: Any = None
    robots: Any = None
    interfaces: Any = None
    containers: Any = None


# -- robot task set -> master --------------------------------------------------------------------------
class Auth(OpArgs):
    """Check ``user``'s ``password`` (hex SHA-256) for a login of ``robot`` from ``addr`` (a robot's or
    rosbridge client's address, for the login guard's back-off). Answer ``{}`` or an ``auth`` error."""
    OP = "auth"
    user: str
    robot: str = ""
    password: str = ""
    addr: str = ""


class _RobotSession(OpArgs):
    """Robot ``robot`` of ``user``, and ``session``, the endpoint's id of one of its logins."""
    user: str
    robot: str
    session: str | None = None


class RobotConnected(_RobotSession):
    """A login of ``robot`` was accepted; ``session`` names it, so only the disconnect of that session
    ends the robot's namespace."""
    OP = "robot_connected"


class RobotDisconnected(_RobotSession):
    """The robot's session ``session`` ended (none named: an older endpoint, any session)."""
    OP = "robot_disconnected"


class RobotRelayChanged(OpArgs):
    """The robot's link to the cloud goes through robot ``relay`` from now on ("" for its own path)."""
    OP = "robot_relay"
    user: str
    robot: str
    relay: str = ""


class RobotLinkReport(OpArgs):
    """(a notification) The endpoint's measure of a robot's link: round trip ``rtt_ms`` (ms) and ``rate``
    (bytes/s), for the placer (:mod:`rce_robot.link_report`)."""
    OP = "robot_link"
    user: str
    robot: str
    rtt_ms: float
    rate: float


class RobotBattery(OpArgs):
    """(a notification) A robot's charge, ``percent`` of full (0-100), for the placer."""
    OP = "robot_battery"
    user: str
    robot: str
    percent: float


class LinkProbe(OpArgs):
    """A probe of the endpoint's uplink: answered at once with ``{bytes}``, the length of ``pad``."""
    OP = "link_probe"
    pad: str = ""


class RobotRequest(OpArgs):
    """A robot's request ``type`` (CC, DC, CN, CX) with its ``data`` as the schema has it
    (:func:`rce.protocol.schema.validate`, which the master runs on it again: one parse, into its
    model). A robot's requests are sent one at a time, in order."""
    OP = "robot_request"
    user: str
    robot: str
    type: str
    data: dict | None = None


class ContainerBus(OpArgs):
    """(a rosbridge session) The bus of ``user``'s container ``ctag``, as its host describes it."""
    OP = "container_bus"
    user: str
    ctag: str


class ContainerParam(OpArgs):
    """(a rosbridge client's ``/rosapi/get_param``) ``{value}`` of parameter ``name`` on the bus of
    ``user``'s container ``ctag``."""
    OP = "container_param"
    user: str
    ctag: str
    name: str = ""


# -- container task set -> master (notifications; also node_status and interface_status, above) ----------
class ContainerLost(OpArgs):
    """Container ``cid``'s environment died (``reason``, e.g. ``its environment was killed by SIGKILL``)."""
    OP = "container_lost"
    cid: int
    reason: str | None = None
