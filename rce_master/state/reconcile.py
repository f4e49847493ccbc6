"""A task set's ``register``, and the reconciliation of what the master stored with what a task
set that comes back reports (docs/INTERNALS.md, "Master state and restart"), sans I/O.

A task set that registers with the ``tid`` its previous ``register`` got asks to *resume*: it
reports what it holds (a robot task set its ``robots`` and robot-side ``interfaces``, a container
host its ``containers`` with their ``nodes``), and :func:`register` makes the master's records
agree with that report in one batch (:meth:`MasterState.batch`):

- kept: what both sides have (a container's host ``tid``, ``data_addr`` and ``sandbox`` and a
  node's status follow the report);
- lost or forgotten: what only the master had (a container becomes ``lost``, a node, a robot
  or an interface is forgotten, as when a robot disconnects);
- dropped: what only the task set has; the answer lists it and the task set removes it.

It returns a :class:`Reconciled`: the answer, and what the shell must tell others
(:meth:`rce_master.control.Control.reconciled`). A ``register`` without ``tid`` (a task set's
first start, or one that predates this contract) registers a new task set, as always.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from rce.contract.environment import NodeStatus
from rce.plumbing.errors import RequestError
from rce.protocol.zones import parse_zone
from rce_master.state.lifecycle import ContainerState
from rce_master.state.model import ContainerRec, NodeRec, Robot, TaskSet
from rce_master.state.master_state import MasterState, Pairs

# s after a master starts on a store: task sets still absent then are dropped (their containers lost, their
# robots gone). Task sets reconnect with backoff: long enough for several tries, short enough for robots to wait
RECONCILE_GRACE = 30.0
REPORT_FIELDS = ("tid", "robots", "interfaces", "containers")     # register fields that are a report, not info


@dataclass
class ContainerReport:
    """One entry of a host's ``containers``: ``nodes`` maps ntag -> status (None: not reported)."""
    cid: int
    data_addr: str
    sandbox: str | None = None
    nodes: dict[str, NodeStatus] | None = None


@dataclass
class Report:
    """What a returning task set says it holds (the report fields of its ``register``)."""
    tid: int | None = None
    robots: list[tuple[str, str]] = field(default_factory=list)        # (user, robot)
    interfaces: set[int] | None = None                                 # robot-side iids; None: not reported
    containers: dict[int, ContainerReport] = field(default_factory=dict)

    @classmethod
    def parse(cls, args: dict) -> "Report":
        """The report in ``register`` args. Raises :class:`RequestError` naming the bad field."""
        tid = args.get("tid")
        if tid is not None:
            _check_int(tid, "tid")
        robots = [(_str(r, "user", f"robots[{i}]"), _str(r, "robot", f"robots[{i}]"))
                  for i, r in enumerate(_list(args, "robots"))]
        interfaces = None
        if args.get("interfaces") is not None:
            interfaces = {_check_int(iid, f"interfaces[{i}]") for i, iid in enumerate(_list(args, "interfaces"))}
        containers = {}
        for i, c in enumerate(_list(args, "containers")):
            where = f"containers[{i}]"
            nodes = None
            if _dict(c, where).get("nodes") is not None:
                nodes = {_str(n, "ntag", f"{where}.nodes[{j}]"): _status(n, f"{where}.nodes[{j}]")
                         for j, n in enumerate(_list(c, "nodes", where))}
            sandbox = _str(c, "sandbox", where) if c.get("sandbox") is not None else None
            cid = _check_int(c.get("cid"), f"{where}.cid")
            containers[cid] = ContainerReport(cid, _str(c, "data_addr", where), sandbox, nodes)
        return cls(tid, robots, interfaces, containers)


@dataclass
class Reconciled:
    """The outcome of a ``register``: the task set, the answer's lists, and what the shell tells others."""
    taskset: TaskSet
    resuming: bool = False                   # the register carried a tid: answer with the lists below
    resumed: bool = False                    # ... and it was the absent task set of that tid
    drop_containers: list[int] = field(default_factory=list)
    drop_nodes: list[dict] = field(default_factory=list)           # {cid, ntag}
    drop_interfaces: list[int] = field(default_factory=list)
    close_robots: list[dict] = field(default_factory=list)         # {user, robot}
    lost: list[ContainerRec] = field(default_factory=list)            # now lost: tell their robots
    nodes_lost: list[tuple[ContainerRec, str]] = field(default_factory=list)
    readdressed: list[ContainerRec] = field(default_factory=list)     # new data_addr: tell their peers
    pairs: Pairs = field(default_factory=list)                     # connections of forgotten interfaces
    kept: list[Robot] = field(default_factory=list)                # robots it reported that the master kept
    gone: list[Robot] = field(default_factory=list)                # robots it did not report: forget them

    def answer(self) -> dict[str, Any]:
        """The ``register`` answer: ``{tid}``, plus the lists when the task set asked to resume."""
        if not self.resuming:
            return {"tid": self.taskset.tid}
        return {"tid": self.taskset.tid, "resumed": self.resumed, "drop_containers": self.drop_containers,
                "drop_nodes": self.drop_nodes, "drop_interfaces": self.drop_interfaces,
                "close_robots": self.close_robots}


def register(state: MasterState, kind: str, name: str, host: str, args: dict) -> Reconciled:
    """Register a task set of ``kind`` with its ``register`` ``args``; resume and reconcile when
    they carry a ``tid`` (see the module doc). One batch. Raises :class:`RequestError` for a bad
    report, a tid of another kind, or the tid of a task set that is registered now."""
    report = Report.parse(args)
    info = {k: v for k, v in args.items() if k not in REPORT_FIELDS}
    if kind == "container":
        zone = parse_zone(info.get("zone") or "cloud", info.get("zone_user"))
        info["zone"] = str(zone)
        info.pop("zone_user", None)
        if zone.user:
            info["zone_user"] = zone.user
    with state.batch():
        old = state.tasksets.get(report.tid) if report.tid is not None else None
        if old is not None and old.kind != kind:
            raise RequestError(f"register: task set {old.tid} was a {old.kind} task set, not a {kind!r} one")
        if old is not None and not old.lost:
            raise RequestError(f"register: task set {old.tid} is registered already, on another link")
        if old is not None:
            out = Reconciled(state.taskset_back(old.tid, name, host, info), resuming=True, resumed=True)
        else:
            out = Reconciled(state.register_taskset(kind, name, host, info), resuming=report.tid is not None)
        if out.resuming and kind == "robot":
            _robots(state, out, report)
        elif out.resuming:
            _containers(state, out, report)
    return out


def _robots(state: MasterState, out: Reconciled, report: Report) -> None:
    """Keep the reported robots stored on this task set, close the others; forget its robots it
    did not report and, when ``interfaces`` is reported, its kept robots' interfaces it lacks."""
    tid = out.taskset.tid
    for user, robot in report.robots:
        r = state.robots.get((user, robot))
        if r is not None and r.tid == tid:
            out.kept.append(r)
        else:
            out.close_robots.append({"user": user, "robot": robot})
    reported = set(report.robots)
    out.gone = [r for r in state.robots.values() if r.tid == tid and (r.user, r.robot) not in reported]
    if report.interfaces is None:
        return
    mine = [i for i in state.interfaces.values() if i.robot_side and i.location == tid]
    kept = {(r.user, r.robot) for r in out.kept}
    out.pairs += state.forget_interfaces([i for i in mine if i.iid not in report.interfaces
                                          and (i.user, i.etag) in kept])
    out.drop_interfaces = sorted(report.interfaces - {i.iid for i in mine})


def _containers(state: MasterState, out: Reconciled, report: Report) -> None:
    """Keep the reported containers the master has (not lost, not on another registered host);
    mark lost its containers the host did not report (the failover re-creates them); drop the rest
    (one that is lost or being re-created is re-created under a new cid: the copy reported goes)."""
    tid = out.taskset.tid
    nodes: dict[int, list[NodeRec]] = {}
    for n in state.nodes.values():
        c = state.containers.get((n.user, n.ctag))
        if c is not None:
            nodes.setdefault(c.cid, []).append(n)
    for cid, rep in sorted(report.containers.items()):
        c = state.container_by_cid(cid)
        host = state.tasksets.get(c.tid) if c is not None else None
        if c is None or c.down or (c.tid != tid and host is not None and not host.lost):
            out.drop_containers.append(cid)
            continue
        if c.data_addr and c.data_addr != rep.data_addr:
            out.readdressed.append(c)
        state.container_found(c, tid, rep.data_addr, rep.sandbox if rep.sandbox is not None else c.sandbox)
        if rep.nodes is not None:
            _nodes(state, out, c, nodes.get(cid, []), rep.nodes)
    for c in [c for c in state.containers.values()
              if c.tid == tid and c.state != ContainerState.LOST and c.cid not in report.containers]:
        state.container_lost(c)
        out.lost.append(c)


def _nodes(state: MasterState, out: Reconciled, container: ContainerRec, stored: list[NodeRec], reported: dict) -> None:
    by_ntag = {n.ntag: n for n in stored}
    for ntag, status in sorted(reported.items()):
        n = by_ntag.get(ntag)
        if n is None:
            out.drop_nodes.append({"cid": container.cid, "ntag": ntag})
        elif n.status != status:
            state.node_status(container.cid, ntag, status, {})
    for ntag in sorted(set(by_ntag) - set(reported)):
        state.remove_node(container.user, container.ctag, ntag)
        out.nodes_lost.append((container, ntag))


# -- checks of the report's fields ---------------------------------------------------------------------------
def _list(record: dict, key: str, where: str = "") -> list:
    v = record.get(key)
    if v is None:
        return []
    if not isinstance(v, list):
        raise RequestError(f"register: {where + '.' if where else ''}{key} must be a list, got {type(v).__name__}")
    return v


def _dict(value: Any, where: str) -> dict:
    if not isinstance(value, dict):
        raise RequestError(f"register: {where} must be an object, got {type(value).__name__}")
    return value


def _str(record: Any, key: str, where: str) -> str:
    v = _dict(record, where).get(key)
    if not isinstance(v, str) or not v:
        raise RequestError(f"register: {where}.{key} must be a non-empty string, got {v!r}")
    return v


def _status(record: Any, where: str) -> NodeStatus:
    v = _str(record, "status", where)
    if v not in NodeStatus._value2member_map_:
        raise RequestError(f"register: {where}.status must be one of {', '.join(NodeStatus)}, got {v!r}")
    return NodeStatus(v)


def _check_int(value: Any, where: str) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value < 1:
        raise RequestError(f"register: {where} must be a positive integer, got {value!r}")
    return value
