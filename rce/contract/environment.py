"""container task set <-> environment, over the environment's Unix socket (docs/INTERNALS.md,
"Control ops"): the ops an environment serves (:data:`rce_container.environment.ENV_OPS`; most
of them come from the master, each naming its container's ``cid``, and its host relays them
unchanged, :data:`rce_container.host.HOST_OPS`), and what an environment tells its host
(``hello``, and the ``node_status`` and ``interface_status`` the host passes on to the master)."""
from __future__ import annotations

from enum import StrEnum
from typing import Any

from rce.contract.base import IType, OpArgs
from rce.contract.robot import EndpointConnect, EndpointDisconnect


class NodeStatus(StrEnum):
    """A node's status: ``starting`` (asked for), ``running`` (its launch answered), then what its
    environment's launcher reports: ``started`` (a process is up), ``respawning`` (it exited and is
    started again), ``exited`` (for good). The master's records move between them as
    :data:`rce_master.state.lifecycle.NODE_TRANSITIONS` allows."""
    STARTING = "starting"
    RUNNING = "running"
    STARTED = "started"
    RESPAWNING = "respawning"
    EXITED = "exited"


# -- environment -> container task set --------------------------------------------------------------
class EnvHello(OpArgs):
    """The first op of environment ``env_id`` (process ``pid``): it serves data at ``data_addr``."""
    OP = "hello"
    env_id: int
    pid: int | None = None
    data_addr: str


class NodeStatusReport(OpArgs):
    """(a notification) Node ``ntag`` of container ``cid`` is ``status``: ``pid`` once started,
    ``restarts`` when respawning, ``code``, ``signal`` and ``reason`` when it exited. Its host passes
    it on to the master unchanged (:mod:`rce.contract.master`)."""
    OP = "node_status"
    cid: int
    ntag: str
    status: NodeStatus
    pid: int | None = None
    restarts: int | None = None
    code: int | None = None
    signal: int | None = None
    reason: str | None = None


class InterfaceStatus(OpArgs):
    """(a notification) How container interface ``iid`` (tag ``tag``) of container ``cid`` is bridged
    into the container's ROS 2 graph: ``status`` ``ok``, or what could not be bridged, and
    ``reason``. Its host passes it on to the master unchanged."""
    OP = "interface_status"
    cid: int
    iid: int
    tag: str = ""
    status: str
    reason: str = ""


# -- container task set -> environment: containers ------------------------------------------------------
class ContainerSetup(OpArgs):
    """Container ``cid`` (tag ``ctag``) of ``user`` in ``group`` (None: a group of its own), with
    ``limits`` (``cpu`` cores, ``memory`` MiB, ``pids``, ``size``, ``bandwidth``; absent or 0: none),
    ``deadline_ms`` (its results' due time, ms) and ``handoff`` (a move's new copy: its nodes wait for
    their state)."""
    cid: int
    ctag: str | None = None
    user: str = ""
    group: str | None = None
    limits: dict[str, Any] | None = None
    deadline_ms: float | None = None
    handoff: bool = False


class EnvAddContainer(ContainerSetup):
    """Serve container ``cid`` in this environment: ``{data_addr, sandbox, socket}``."""
    OP = "add_container"


class OnContainer(OpArgs):
    """An op on container ``cid`` of this environment (NotFound for another)."""
    cid: int


class EnvRemoveContainer(OnContainer):
    """Kill the container's nodes, drop its interfaces and socket."""
    OP = "remove_container"


class EnvShutdown(OpArgs):
    """Destroy every container; the task set closes the link afterwards."""
    OP = "shutdown"


class EnvResizeContainer(OnContainer):
    """New ``limits`` for the container's sandbox, its nodes running on: ``{sandbox, limits, cgroup?}``."""
    OP = "resize_container"
    limits: dict[str, Any] | None = None


class EnvDataKey(OpArgs):
    """This environment's data key (hex), from its host, once, right after ``hello``."""
    OP = "data_key"
    key: str


# -- nodes ---------------------------------------------------------------------------------------------
class EnvAddNode(OnContainer):
    """Launch node ``ntag`` (an addNodes entry: ``pkg``, ``exe``, ``args``, ``name``, ``namespace``,
    ``respawn``): ``{ntag, pid}``."""
    OP = "add_node"
    ntag: str
    pkg: str
    exe: str
    args: str | list[str] = ""
    name: str | None = None
    namespace: str | None = None
    respawn: bool | dict | None = None


class EnvRemoveNode(OnContainer):
    """Stop node ``ntag`` (SIGTERM, then SIGKILL after the grace period)."""
    OP = "remove_node"
    ntag: str


class EnvLogs(OnContainer):
    """The last ``lines`` lines of node ``ntag``'s output: ``{stdout: [...], stderr: [...]}``."""
    OP = "logs"
    ntag: str
    lines: int | None = None


# -- parameters -----------------------------------------------------------------------------------------
class EnvSetParam(OnContainer):
    """Set parameter ``name`` (a global name) to ``value`` (JSON) on the container's bus."""
    OP = "set_param"
    name: str
    value: Any = None


class EnvDeleteParam(OnContainer):
    OP = "delete_param"
    name: str


class EnvGetParam(OnContainer):
    """``{value}`` of parameter ``name`` (NotFound if not set)."""
    OP = "get_param"
    name: str


# -- interfaces -----------------------------------------------------------------------------------------
class EnvAddInterface(OnContainer):
    """Container-side interface ``iid`` (tag ``tag``, ``itype``, class ``cls``) for the bus name
    ``addr`` (default: ``/`` + the interface tag): ``{iid, addr}``."""
    OP = "add_interface"
    iid: int
    tag: str | None = None
    itype: IType
    cls: str
    addr: str | None = None


class EnvRemoveInterface(OnContainer):
    OP = "remove_interface"
    iid: int


class EnvConnect(OnContainer, EndpointConnect):
    """:class:`rce.contract.robot.EndpointConnect` for a container-side interface of container ``cid``:
    ``{fenced}``."""
    OP = "connect"


class EnvDisconnect(OnContainer, EndpointDisconnect):
    """:class:`rce.contract.robot.EndpointDisconnect` for a container-side interface of container ``cid``."""
    OP = "disconnect"


# -- the bus and a move ----------------------------------------------------------------------------------
class EnvDescribe(OnContainer):
    """The bus (topics, services, params, nodes), the container's ``launched`` nodes and those that
    ``handoff`` their state."""
    OP = "describe"


class EnvBusPublish(OnContainer):
    """Publish JSON message ``msg`` of class ``type`` on ``topic`` once: ``{delivered}``."""
    OP = "bus_publish"
    topic: str
    type: str
    msg: dict | None = None


class EnvBusCall(OnContainer):
    """Call ``service`` with JSON ``request``, within ``timeout`` s: the JSON response."""
    OP = "bus_call"
    service: str
    request: dict | None = None
    timeout: float | None = None


class EnvBusSample(OnContainer):
    """Up to ``count`` JSON messages on ``topic`` (class from the topic, else ``type``) within ``timeout`` s."""
    OP = "bus_sample"
    topic: str
    count: int | None = None
    timeout: float | None = None
    type: str | None = None


class EnvStateOut(OnContainer):
    """``{states: {node name: base64 | None}}`` from the nodes that hand their state over."""
    OP = "state_out"


class EnvDrain(OnContainer):
    """A moved container's old copy finishes: ``expect`` fences ``fence`` of each ``[src, dst, n]``,
    its nodes settled, its peers flushed, within ``timeout`` s."""
    OP = "drain"
    fence: int
    expect: list[tuple[int, int, int]] = []
    timeout: float | None = None


class EnvStateIn(OnContainer):
    """Each node of a move's new copy takes its state of ``states`` (node name -> base64 | None):
    ``{nodes: [names that took one]}``."""
    OP = "state_in"
    states: dict[str, str | None] | None = None


class EnvStats(OnContainer):
    """The container's counters and its group's (:meth:`rce_container.environment.Environment.op_stats`)."""
    OP = "stats"
