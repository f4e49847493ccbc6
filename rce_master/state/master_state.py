"""The master's command data structure (docs/design.md, section 2.2) and every change to it, sans I/O.

Users, task sets, robots, containers, nodes, parameters, interfaces and connections, with every
rule the master enforces: tags are scoped per user, robot-side interfaces belong to the robot
that asks, container-side ones to a container of the user, connections pair Publisher with
Subscriber and ServiceClient with ServiceProvider of the same class.

Every operation validates before it changes anything and raises :class:`RequestError` (or a
subclass) naming what was wrong; it returns what the asyncio shell (:mod:`rce_master.server`,
:mod:`rce_master.requests`) must tell the task sets. The shell never changes a record itself.
A request the task sets refuse half way is undone by the matching operation (``container_failed``,
``node_failed``, ``interface_refused``, ``connection_failed``), which also removes what was hung
on the half-made record meanwhile.

Each operation is one batch of store changes (:mod:`rce_master.state.store`): applied all or nothing,
and rolled back in memory too when it fails part way; :meth:`MasterState.batch` makes several
operations one batch (the reconciliation of :mod:`rce_master.state.reconcile`). Requests are keyed by
tags, so replaying one (after a reconnect) either succeeds identically or names the duplicate.

Built on a store that holds records, the state is the one a previous master left; its task sets
are then absent (``lost``) until they re-register (:meth:`MasterState.mark_tasksets_absent`).
"""
from __future__ import annotations

import functools
import json
import time
from collections.abc import Collection, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from rce.contract.environment import NodeStatus
from rce.plumbing.errors import AuthError, NotFound, RequestError, Unavailable
from rce.interfaces.classes import same_type
from rce.interfaces.kind import Kind
from rce.protocol import schema
from rce_master.state.index import StateIndex, lost_reason
from rce_master.state.lifecycle import ContainerState, check_move
from rce_master.state.model import (DEFAULT_ROLE, ConnectionRec, ContainerRec, InterfaceRec, NodeRec, Robot, TaskSet,
                              User, check_role, param_key)
from rce_master.state.store import Key, MemoryStore, Store, encode

Pairs = list[tuple[InterfaceRec, InterfaceRec]]     # connections removed: the shell disconnects both ends

# Per-user quotas: what one user may hold at once, so that one user's robots cannot
# exhaust the hosts and the master for the others; rce-master --max-containers/--max-nodes/--max-interfaces.
DEFAULT_MAX_CONTAINERS = 256      # containers per user (a fleet of hundreds of robots, one container each)
DEFAULT_MAX_NODES = 2048          # nodes per user, all containers together
DEFAULT_MAX_INTERFACES = 8192     # interfaces per user, robot-side and container-side together


@dataclass(frozen=True)
class Quotas:
    """Per-user bounds on records: ``containers``, ``nodes`` and ``interfaces`` a user may hold at
    once (0: no bound). A request past one is refused with :class:`QuotaExceeded`."""

    containers: int = DEFAULT_MAX_CONTAINERS
    nodes: int = DEFAULT_MAX_NODES
    interfaces: int = DEFAULT_MAX_INTERFACES

    def check(self, user: str, kind: str, keys: Iterable[tuple]) -> None:
        """Raise :class:`QuotaExceeded` when ``user`` already holds its quota of ``kind`` (``containers``,
        ``nodes``, ``interfaces``); ``keys``: the keys of that table (user first)."""
        limit = getattr(self, kind)
        if limit and sum(1 for k in keys if k[0] == user) >= limit:
            raise QuotaExceeded(f"quota exceeded: user {user!r} already has {limit} {kind}, the most one user "
                                f"may have (rce-master --max-{kind})")


class QuotaExceeded(RequestError):
    """A request would take a user past one of its :class:`Quotas`."""


class TaskSetAbsent(Unavailable):
    """What is asked needs a task set that is not registered now (none started yet, or one the
    master knows from its store that has not re-registered since the master restarted): asking
    again later may work (HTTP answers 503 with ``Retry-After``)."""


def _atomic(op):
    """Run the operation as one batch of store changes (see :meth:`MasterState.batch`)."""
    @functools.wraps(op)
    def run(self: "MasterState", *args, **kwargs):
        with self.batch():
            return op(self, *args, **kwargs)
    return run


class MasterState(StateIndex):
    """All master state on ``store`` (default: a new :class:`MemoryStore`); a store that holds
    records is loaded, so the state a previous master left comes back. ``quotas``: per-user bounds
    (default :class:`Quotas`)."""

    def __init__(self, store: Store | None = None, quotas: Quotas | None = None) -> None:
        super().__init__()
        self.quotas = quotas if quotas is not None else Quotas()
        self.store = store if store is not None else MemoryStore()
        self._batch: list[tuple[Key, dict | None, dict | None]] | None = None
        self._latest: dict[Key, dict | None] = {}
        self.load(self.store)

    # -- the one way to change: records in batches ----------------------------------------------------
    @contextmanager
    def batch(self) -> Iterator[None]:
        """One batch: commit its changes to the store at the end, or, when the operation or the
        store fails, put the view back as it was. Nested operations (and batches) join the outer one."""
        if self._batch is not None:
            yield
            return
        self._batch, self._latest = [], {}
        try:
            yield
            if self._batch:
                self.store.commit([(key, new) for key, _, new in self._batch])
        except BaseException:
            for key, old, new in reversed(self._batch):
                self.apply(key, new, old)
            raise
        finally:
            self._batch, self._latest = None, {}
            self._removed.clear()

    def followed(self, key: Key, old: dict | None, new: dict | None) -> None:
        """A change another master made to the store (a standby follows the leader's writes in
        etcd, :mod:`rce_master.state.etcd_store`): make the view follow it. Never inside a batch."""
        if self._batch is not None:
            raise RuntimeError("a followed change arrived inside an operation")
        self.apply(key, old, new)
        self._removed.clear()

    def _write(self, key: Key, new: dict | None) -> None:
        if self._batch is None:
            raise RuntimeError("MasterState changes only inside an operation")
        if new is not None:
            new = json.loads(encode(key, new))                # a copy, and JSON before anything changes
        old = self._latest[key] if key in self._latest else self.store.get(key)
        self._batch.append((key, old, new))
        self._latest[key] = new
        self.apply(key, old, new)

    def _put(self, obj: Any, **changes: Any) -> None:
        self._write(obj.store_key, {**obj.to_record(), **changes})

    def _move(self, rec: ContainerRec | NodeRec, to: ContainerState | NodeStatus, **changes: Any) -> None:
        """Move record ``rec`` (a container or a node) to state ``to``, with ``changes``, as its lifecycle
        allows (:func:`~rce_master.state.lifecycle.check_move`: raises
        :class:`~rce_master.state.lifecycle.IllegalMove` for a move its table does not have). Every
        change of a container's state or a node's status goes through here."""
        if isinstance(rec, ContainerRec):
            self._put(rec, state=check_move(ContainerState, f"container {rec.ctag!r}", rec.state, to), **changes)
        else:
            self._put(rec, status=check_move(NodeStatus, f"node {rec.ntag!r} in container {rec.ctag!r}", rec.status,
                                             to), **changes)

    def _delete(self, obj: Any) -> None:
        self._write(obj.store_key, None)

    def _next_id(self, name: str) -> int:
        n = self.counters.get(name, 1)
        self._write(("counter", name), {"next": n + 1})
        return n

    # -- users -------------------------------------------------------------------------------------------
    @_atomic
    def add_user(self, name: str, password: str, role: str = DEFAULT_ROLE) -> User:
        """Add a user with ``role`` (:data:`~rce_master.state.model.ROLES`). Raises :class:`RequestError` for an
        illegal/duplicate name, an empty password or an unknown role."""
        _check_user_name(name)
        if name in self.users:
            raise RequestError(f"user {name!r} already exists")
        if not password:
            raise RequestError("the password must not be empty")
        u = User.create(name, password, _role(role))
        self._write(u.store_key, u.to_record())
        return self.users[name]

    @_atomic
    def set_user_role(self, name: str, role: str) -> User:
        """Give user ``name`` ``role``. Raises :class:`NotFound` or :class:`RequestError` (unknown role)."""
        if name not in self.users:
            raise NotFound(f"no user {name!r}")
        u = self.users[name]
        self._write(u.store_key, {**u.to_record(), "role": _role(role)})
        return self.users[name]

    @_atomic
    def del_user(self, name: str) -> None:
        """Delete a user. Raises :class:`NotFound`, or :class:`RequestError` while it has robots."""
        if name not in self.users:
            raise NotFound(f"no user {name!r}")
        if any(r.user == name for r in self.robots.values()):
            raise RequestError(f"user {name!r} has connected robots; disconnect them first")
        self._delete(self.users[name])

    @_atomic
    def load_users(self, records: list) -> None:
        """Add (or replace) users from hashed records (a users file's ``users`` list).
        Raises :class:`RequestError` naming the first bad record; then none is loaded."""
        for i, r in enumerate(records, 1):
            try:
                u = User.from_record(r)
                _check_user_name(u.name)
            except (KeyError, ValueError, TypeError, RequestError) as e:
                raise RequestError(f"user record {i}: {e}") from None
            self._write(u.store_key, u.to_record())

    def user_records(self) -> list[dict]:
        """The hashed records of every user (what a users file keeps)."""
        return [self.users[n].to_record() for n in sorted(self.users)]

    def authenticate(self, user: str, digest_hex: str) -> None:
        """Raise :class:`AuthError` unless ``digest_hex`` is the user's password digest."""
        u = self.users.get(user)
        if u is None or not isinstance(digest_hex, str) or not u.check(digest_hex):
            raise AuthError(f"invalid user ID or password for user {user!r}")

    # -- task sets ---------------------------------------------------------------------------------------
    @_atomic
    def register_taskset(self, kind: str, name: str, host: str, info: dict) -> TaskSet:
        """Record a task set that registered (``info``: its register args). Raises :class:`RequestError`."""
        if kind not in ("robot", "container"):
            raise RequestError(f"unknown task set kind {kind!r}")
        ts = TaskSet(self._next_id("tid"), kind, name, host, dict(info))
        self._write(ts.store_key, ts.to_record())
        return self.tasksets[ts.tid]

    @_atomic
    def taskset_back(self, tid: int, name: str, host: str, info: dict) -> TaskSet:
        """An absent task set re-registered (same ``tid``, its new name, host and register args).
        Raises :class:`RequestError` when ``tid`` is not an absent task set."""
        ts = self.tasksets.get(tid)
        if ts is None or not ts.lost:
            raise RequestError(f"task set {tid} is not absent: it is " + ("unknown" if ts is None else "registered"))
        self._put(ts, name=name, host=host, info=dict(info), lost=False)
        return ts

    @_atomic
    def mark_tasksets_absent(self) -> list[TaskSet]:
        """On start on a store a previous master left: every task set in it is absent (``lost``:
        no placement, no calls) until it re-registers or the reconciliation grace ends. Returns them."""
        for ts in self.tasksets.values():
            if not ts.lost:
                self._put(ts, lost=True)
        return sorted(self.tasksets.values(), key=lambda t: t.tid)

    @_atomic
    def taskset_absent(self, tid: int) -> TaskSet | None:
        """Robot task set ``tid`` lost its link (its rce-robot died, or the link broke): it is absent,
        as after a master restart, until it re-registers or the grace ends; its robots stay, with
        their containers (docs/INTERNALS.md "Session resume", "Moving to another endpoint")."""
        ts = self.tasksets.get(tid)
        if ts is not None and not ts.lost:
            self._put(ts, lost=True)
        return ts

    def absent_tasksets(self) -> list[TaskSet]:
        """The task sets still absent, container hosts first (their containers are lost before
        the robots of absent robot task sets leave), then by tid."""
        return sorted((t for t in self.tasksets.values() if t.lost), key=lambda t: (t.kind != "container", t.tid))

    @_atomic
    def drop_taskset(self, tid: int) -> tuple[list[ContainerRec], list[Robot]]:
        """Remove a task set that went away. Returns its containers (now ``lost``: the shell tells
        their robots and re-creates them, :mod:`rce_master.failover`) and its robots (the shell
        disconnects them)."""
        ts = self.tasksets.get(tid)
        if ts is None:
            return [], []
        lost = [c for c in self.containers.values() if c.tid == tid and c.state != ContainerState.LOST]
        for c in lost:
            self.container_lost(c)
        robots = [r for r in self.robots.values() if r.tid == tid]
        self._delete(ts)
        return lost, robots

    def pick_robot_taskset(self, user: str | None = None, robot: str | None = None) -> TaskSet:
        """The robot endpoint for ``user``'s robot ``robot``: the one on that robot's own computer
        (zone ``robot:ROBOT``, :mod:`rce.protocol.zones`) when it is up, else the least loaded shared
        one (an endpoint on a robot's computer serves that robot alone). Raises
        :class:`TaskSetAbsent` if none may take it."""
        up = [t for t in self.tasksets.values() if t.kind == "robot" and not t.lost]
        own = [t for t in up if t.zone.kind == "robot" and robot and t.zone.serves(user or "", robot)]
        cands = own or [t for t in up if t.zone.kind != "robot"]
        if not cands:
            raise TaskSetAbsent("no robot endpoint is available; start rce-robot")
        return min(cands, key=lambda t: (t.robots, t.tid))

    def pick_container_host(self, data: dict, user: str = "", exclude: Collection[int] = (),
                            prefer: int | None = None) -> TaskSet:
        """The container host for a container of ``user`` with containerData ``data``: among the
        hosts its placement allows (:func:`placement_tiers`, tier by tier), the one with the lowest
        load after adding this container's cpu/memory request (relative to its capacity), leaving
        out the tids in ``exclude``; host ``prefer`` whenever it fits (an environment that died is
        re-created on its own host). A ``robot:`` host takes only its user's containers that serve
        its robot. Raises :class:`Unavailable` if none fits, naming the zones it looked in."""
        cpu = float(data.get("cpu") or 0)
        mem = float(data.get("memory") or 0)
        tiers = placement_tiers(data)
        for kinds in tiers:
            best, best_key = None, None
            for t in self.tasksets.values():
                if t.kind != "container" or t.lost or t.tid in exclude:
                    continue
                zone = t.zone
                if zone.kind not in kinds or not zone.serves(user, data.get("robot")):
                    continue
                cap = t.info.get("capacity") or {}
                cap_cpu, cap_mem = float(cap.get("cpu") or 0), float(cap.get("memory") or 0)
                if cap_mem and t.mem_load + mem > cap_mem:
                    continue
                load = max((t.cpu_load + cpu) / cap_cpu if cap_cpu else 0.0,
                           (t.mem_load + mem) / cap_mem if cap_mem else 0.0)
                key = (t.tid != prefer, load, t.containers, t.tid)
                if best_key is None or key < best_key:
                    best, best_key = t, key
            if best is not None:
                return best
        robot = data.get("robot")
        where = "" if tiers == [("cloud", "edge")] else " in zone " + " or ".join(
            "/".join(f"robot:{robot}" if k == "robot" else k for k in kinds) for kinds in tiers)
        raise Unavailable(f"no container host{where} can take this container "
                          f"(cpu {cpu:g} cores, memory {mem:g} MiB); start rce-container"
                          + (f" --zone robot:{robot} --user {user} on the robot" if tiers == [("robot",)] else ""))

    # -- robots ------------------------------------------------------------------------------------------
    @_atomic
    def robot_connect(self, user: str, robot: str, tid: int) -> Robot:
        """Record a connected robot. Raises :class:`RequestError` for a duplicate robotID or one
        that clashes with a container tag of the user."""
        if (user, robot) in self.robots:
            raise RequestError(f"robot {robot!r} of user {user!r} is already connected")
        if (user, robot) in self.containers:
            raise RequestError(f"robot ID {robot!r} is already used as a container tag")
        r = Robot(user, robot, tid, time.time())
        self._write(r.store_key, r.to_record())
        return self.robots[(user, robot)]

    @_atomic
    def robot_relay(self, user: str, robot: str, tid: int, relay: str) -> Robot | None:
        """Robot ``user/robot`` on task set ``tid`` reaches the cloud through robot ``relay`` ("" for its
        own path) from now on. Returns it, or None when it is not (or no longer) on ``tid``."""
        r = self.robots.get((user, robot))
        if r is None or r.tid != tid:
            return None
        if r.relay != relay:
            self._put(r, relay=relay, relay_since=time.time())
        return self.robots[(user, robot)]

    @_atomic
    def robot_moved(self, user: str, robot: str, tid: int) -> list[InterfaceRec]:
        """Robot ``user/robot``, stored on an absent robot task set, connected through task set
        ``tid``: it is on ``tid`` now, with its robot-side interfaces (same iids; their connections
        stay). Returns those interfaces (the shell installs them there and re-connects them).
        Raises :class:`NotFound` when the robot is not stored."""
        r = self.robots.get((user, robot))
        if r is None:
            raise NotFound(f"robot {robot!r} of user {user!r} is not connected")
        recs = self.interfaces_of(user, robot, robot_side=True)
        self._put(r, tid=tid)
        for rec in recs:
            self._put(rec, location=tid)
        return [self.interfaces[(rec.user, rec.etag, rec.itag)] for rec in recs]

    @_atomic
    def robot_disconnect(self, user: str, robot: str) -> tuple[Pairs, list[ContainerRec]]:
        """Forget a robot with its interfaces (and their connections). Returns the connections
        removed and the containers it owns (the shell destroys them)."""
        r = self.robots.get((user, robot))
        if r is None:
            return [], []
        pairs = self.forget_interfaces(self.interfaces_of(user, robot, robot_side=True))
        owned = [c for c in self.containers.values() if c.user == user and c.owner == robot]
        self._delete(r)
        return pairs, owned

    # -- containers --------------------------------------------------------------------------------------
    @_atomic
    def add_container(self, user: str, owner: str, ctag: str, data: dict | None) -> tuple[ContainerRec, TaskSet]:
        """Reserve a new container (state ``starting``) on the chosen host; returns it and the host."""
        old = self.containers.get((user, ctag))
        if old is not None and old.down:
            raise RequestError(f"{lost_reason(old)}; DC it first to create it afresh")
        if old is not None:
            raise RequestError(f"container {ctag!r} already exists")
        if (user, ctag) in self.robots:
            raise RequestError(f"container tag {ctag!r} is already used as a robot ID")
        self.quotas.check(user, "containers", self.containers)
        data = dict(data or {})
        host = self.pick_container_host(data, user)
        c = ContainerRec(self._next_id("cid"), user, ctag, owner, host.tid, data.get("group") or None, data)
        self._write(c.store_key, c.to_record())
        return self.containers[(user, ctag)], host

    @_atomic
    def container_ready(self, container: ContainerRec, data_addr: str, sandbox: str) -> None:
        """The host created (or re-created) ``c``: ``running``. Raises :class:`Unavailable` when it
        was removed or lost meanwhile."""
        if not _current(self.containers, (container.user, container.ctag), container) \
                or container.state == ContainerState.LOST:
            raise Unavailable(f"container {container.ctag!r} was removed or lost while it was created")
        self._move(container, ContainerState.RUNNING, data_addr=data_addr, sandbox=sandbox)

    @_atomic
    def container_lost(self, container: ContainerRec) -> None:
        """``c`` is gone with its host or environment (or its host re-registered without it):
        ``lost``. Its nodes, parameters, interfaces and connections stay, for its re-creation
        (:meth:`container_recovering`) or until its robot destroys it (DC) or leaves."""
        self._move(container, ContainerState.LOST)

    @_atomic
    def container_recovering(self, container: ContainerRec, tid: int, cid: int | None = None) -> None:
        """Re-create lost container ``c`` on host ``tid``: it gets a new ``cid`` (a copy its old
        host may still hold keeps the old one, and is dropped when that host re-registers), or
        ``cid``, its spare's, its container-side interfaces move with it, its nodes are ``starting``
        again. Raises :class:`RequestError` unless ``c`` is the user's current, lost container."""
        if not _current(self.containers, (container.user, container.ctag), container) \
                or container.state != ContainerState.LOST:
            raise RequestError(f"container {container.ctag!r} is not lost: it is {container.state} (or gone)")
        old = container.cid
        self._move(container, ContainerState.RECOVERING, cid=self._next_id("cid") if cid is None else cid, tid=tid)
        for rec in self.interfaces_of(container.user, container.ctag, robot_side=False):
            if rec.location == old:
                self._put(rec, location=container.cid)
        for n in self.nodes_of(container):
            self._move(n, NodeStatus.STARTING, detail={})

    @_atomic
    def reserve_cid(self) -> int:
        """A new container id (for the copy a move makes)."""
        return self._next_id("cid")

    @_atomic
    def container_moved(self, container: ContainerRec, tid: int, cid: int, data_addr: str, sandbox: str) -> None:
        """Running container ``c`` runs as ``cid`` on host ``tid`` at ``data_addr`` from now on (a
        move's switch, :mod:`rce_master.placement.mover`): its container-side interfaces move with it. Raises
        :class:`RequestError` unless ``c`` is the user's current, running container."""
        if not _current(self.containers, (container.user, container.ctag), container) \
                or container.state != ContainerState.RUNNING:
            raise RequestError(f"container {container.ctag!r} is not running: it is {container.state} (or gone)")
        old = container.cid
        self._put(container, cid=cid, tid=tid, data_addr=data_addr, sandbox=sandbox)
        for rec in self.interfaces_of(container.user, container.ctag, robot_side=False):
            if rec.location == old:
                self._put(rec, location=cid)

    @_atomic
    def interrupted_recoveries(self) -> list[ContainerRec]:
        """On taking office on a store a previous master left: a container it was re-creating is
        ``lost`` again (that work died with it). Returns every lost container that ever ran,
        by cid: the ones to re-create once hosts register."""
        for c in self.containers.values():
            if c.state == ContainerState.RECOVERING:
                self._move(c, ContainerState.LOST)
        return sorted((c for c in self.containers.values() if c.state == ContainerState.LOST and c.data_addr),
                      key=lambda c: c.cid)

    @_atomic
    def container_found(self, container: ContainerRec, tid: int, data_addr: str, sandbox: str) -> None:
        """Host ``tid`` reported ``c`` running when it re-registered: ``running`` there, at ``data_addr``."""
        self._move(container, ContainerState.RUNNING, tid=tid, data_addr=data_addr, sandbox=sandbox)

    @_atomic
    def container_failed(self, container: ContainerRec) -> Pairs:
        """Undo a container its host did not create (nothing when it is already gone)."""
        if not _current(self.containers, (container.user, container.ctag), container):
            return []
        return self._forget_container(container)

    @_atomic
    def remove_container(self, user: str, ctag: str) -> tuple[ContainerRec, Pairs]:
        """Forget a container with its nodes, parameters and interfaces; returns the container
        and the connections removed (the shell disconnects their peers). Raises :class:`NotFound`."""
        c = self.containers.get((user, ctag))
        if c is None:
            raise NotFound(f"container {ctag!r} does not exist")
        return c, self._forget_container(c)

    def _forget_container(self, container: ContainerRec) -> Pairs:
        for n in self.nodes_of(container):
            self._delete(n)
        for k in [k for k in self.params if k[:2] == (container.user, container.ctag)]:
            self._write(param_key(*k), None)
        pairs = self.forget_interfaces(self.interfaces_of(container.user, container.ctag))
        self._delete(container)
        return pairs

    @_atomic
    def set_container_data(self, container: ContainerRec, data: dict) -> None:
        """Replace a container's containerData record (a user's placement pin)."""
        self._put(container, data=dict(data))

    @_atomic
    def resize(self, user: str, ctag: str, limits: dict) -> ContainerRec:
        """Record new limits of a container its host applied (host load follows)."""
        c = self.container(user, ctag)
        self._put(c, data={**c.data, **limits})
        return c

    # -- nodes and parameters ----------------------------------------------------------------------------
    @_atomic
    def add_node(self, user: str, spec: schema.NodeComponent) -> tuple[ContainerRec, NodeRec]:
        """Reserve node ``spec`` (an addNodes entry; status ``starting``); its record keeps the entry
        as the wire has it. Raises :class:`RequestError`."""
        c = self.container(user, spec.cTag)
        key = (user, c.ctag, spec.nTag)
        if key in self.nodes:
            raise RequestError(f"node {spec.nTag!r} already exists in container {c.ctag!r}")
        self.quotas.check(user, "nodes", self.nodes)
        n = NodeRec(user, c.ctag, spec.nTag, spec.wire())
        self._write(n.store_key, n.to_record())
        return c, self.nodes[key]

    @_atomic
    def node_running(self, node: NodeRec) -> None:
        """The host launched ``n``: ``running``, unless a status report came first."""
        if _current(self.nodes, (node.user, node.ctag, node.ntag), node) and node.status == NodeStatus.STARTING:
            self._move(node, NodeStatus.RUNNING)

    @_atomic
    def node_failed(self, node: NodeRec) -> None:
        """Undo a node the host did not launch (nothing when it is already gone)."""
        if _current(self.nodes, (node.user, node.ctag, node.ntag), node):
            self._delete(node)

    @_atomic
    def remove_node(self, user: str, ctag: str, ntag: str) -> ContainerRec:
        """Forget a node; returns its container. Raises :class:`NotFound`."""
        c = self.container(user, ctag)
        n = self.nodes.get((user, ctag, ntag))
        if n is None:
            raise NotFound(f"node {ntag!r} does not exist in container {ctag!r}")
        self._delete(n)
        return c

    @_atomic
    def node_status(self, cid: int, ntag: str, status: NodeStatus, detail: dict) -> NodeRec | None:
        """A host's report on node ``ntag`` of container ``cid``; None for a node not known. Raises
        :class:`~rce_master.state.lifecycle.IllegalMove` for a status its node cannot take now."""
        c = self.container_by_cid(cid)
        n = self.nodes.get((c.user, c.ctag, ntag)) if c else None
        if n is not None:
            self._move(n, status, detail=dict(detail))
        return n

    @_atomic
    def set_param(self, user: str, ctag: str, name: str, value: Any) -> ContainerRec:
        """Record a parameter the container's bus has set. Raises :class:`NotFound`/:class:`RequestError`."""
        c = self.container(user, ctag)
        self._write(param_key(user, ctag, name), {"user": user, "ctag": ctag, "name": name, "value": value})
        return c

    @_atomic
    def delete_param(self, user: str, ctag: str, name: str) -> ContainerRec:
        """Forget a parameter; returns its container. Raises :class:`NotFound`."""
        c = self.container(user, ctag)
        if (user, ctag, name) not in self.params:
            raise NotFound(f"parameter {name!r} is not set in container {ctag!r}")
        self._write(param_key(user, ctag, name), None)
        return c

    # -- interfaces and connections ----------------------------------------------------------------------
    @_atomic
    def add_interface(self, user: str, robot: str, spec: schema.InterfaceComponent) -> InterfaceRec:
        """Add interface ``spec`` (an addInterfaces entry) for the robot ``robot`` of ``user`` asking.

        Robot-side kinds (Converter/Forwarder) must name the asking robot as endpoint; container
        kinds (Interface) a container of the user. Raises :class:`RequestError`/:class:`NotFound`."""
        etag, itag, itype = spec.eTag, spec.iTag, spec.iType
        if "/" in itag:
            raise RequestError(f"interface tag {itag!r} must not contain '/'")
        if not itype.robot_side:
            location = self.container(user, etag).cid
        else:
            if etag != robot:
                raise RequestError(f"a {itype} is created on the robot's own endpoint: endpointTag must be "
                                   f"{robot!r}, got {etag!r}")
            r = self.robots.get((user, robot))
            if r is None:
                raise NotFound(f"robot {robot!r} is not connected")
            location = r.tid
        if (user, etag, itag) in self.interfaces:
            raise RequestError(f"interface {etag}/{itag} already exists")
        self.quotas.check(user, "interfaces", self.interfaces)
        rec = InterfaceRec(self._next_id("iid"), user, etag, itag, itype.value, itype.kind.value, itype.side.value,
                           spec.iCls.strip("/"), spec.addr, location, spec.lane.value if spec.lane else None)
        self._write(rec.store_key, rec.to_record())
        return self.interfaces[(user, etag, itag)]

    @_atomic
    def interface_refused(self, rec: InterfaceRec) -> Pairs:
        """Undo an interface its endpoint refused (nothing when it is already gone)."""
        if not _current(self.interfaces, (rec.user, rec.etag, rec.itag), rec):
            return []
        return self.forget_interfaces([rec])

    @_atomic
    def remove_interface(self, user: str, etag: str, itag: str) -> tuple[InterfaceRec, Pairs]:
        """Forget an interface; returns it and the connections removed with it. Raises :class:`NotFound`."""
        rec = self.interfaces.get((user, etag, itag))
        if rec is None:
            raise NotFound(f"interface {etag}/{itag} does not exist")
        return rec, self.forget_interfaces([rec])

    @_atomic
    def forget_interfaces(self, recs: list[InterfaceRec]) -> Pairs:
        """Remove interfaces (one removed, a robot left, a container destroyed, a refused add) with
        their connections; returns the removed connections as pairs of records. O(their connections)."""
        out: Pairs = []
        for rec in recs:
            for conn in list(self._links.get(rec.iid, ())):
                a, b = self._by_iid.get(conn.a), self._by_iid.get(conn.b)
                self._delete(conn)
                if a is not None and b is not None:
                    out.append((a, b))
            self._delete(rec)
        return out

    @_atomic
    def connect(self, user: str, tag_a: str, tag_b: str) -> tuple[InterfaceRec, InterfaceRec]:
        """Connect two interfaces. Raises :class:`RequestError` if they cannot be paired
        (kinds, classes, same endpoint side rules) or are already connected."""
        a, b = self.interface(user, tag_a), self.interface(user, tag_b)
        if Kind(a.kind).peer != b.kind:
            raise RequestError(f"cannot connect {a.tag} ({a.itype}) with {b.tag} ({b.itype}): a {a.kind} pairs "
                               f"only with a {Kind(a.kind).peer}")
        if not same_type(a.cls, b.cls):
            raise RequestError(f"cannot connect {a.tag} ({a.cls}) with {b.tag} ({b.cls}): classes differ")
        if a.robot_side and b.robot_side:
            raise RequestError(f"cannot connect two robot-side interfaces ({a.tag}, {b.tag}); "
                               "connect each to a container interface")
        for x in (a, b):
            if not x.robot_side:
                c = self.container_by_cid(x.location)
                if c is None or c.state != ContainerState.RUNNING:
                    raise Unavailable(f"container {x.etag!r} of interface {x.tag} is not running")
        conn = ConnectionRec(user, min(a.iid, b.iid), max(a.iid, b.iid))
        if conn in self.connections:
            raise RequestError(f"{a.tag} and {b.tag} are already connected")
        self._write(conn.store_key, conn.to_record())
        return a, b

    @_atomic
    def disconnect(self, user: str, tag_a: str, tag_b: str) -> tuple[InterfaceRec, InterfaceRec]:
        """Remove the connection of two interfaces. Raises :class:`NotFound`."""
        a, b = self.interface(user, tag_a), self.interface(user, tag_b)
        conn = ConnectionRec(user, min(a.iid, b.iid), max(a.iid, b.iid))
        if conn not in self.connections:
            raise NotFound(f"{a.tag} and {b.tag} are not connected")
        self._delete(conn)
        return a, b

    @_atomic
    def connection_failed(self, a: InterfaceRec, b: InterfaceRec) -> None:
        """Undo a connection an endpoint refused (nothing when it is already gone)."""
        conn = ConnectionRec(a.user, min(a.iid, b.iid), max(a.iid, b.iid))
        if conn in self.connections:
            self._delete(conn)


def placement_tiers(data: dict) -> list[tuple[str, ...]]:
    """The zone kinds a container with containerData ``data`` may be placed in, tier by tier
    (the first tier with a host that fits wins). Without any placement key: any shared host
    (cloud or edge) as the original engine did; ``cloud``, ``edge``, ``robot``: that zone only
    (``pinned``, a user's pin, overrides ``placement``); ``auto`` before the placer has measured
    anything: the cloud, then the edge, then the robot's own computer."""
    placement = data.get("pinned") or data.get("placement")
    if placement is None and any(k in data for k in NEED_KEYS):
        placement = "auto"
    if placement is None:
        return [("cloud", "edge")]
    if placement == "auto":
        return [("cloud",), ("edge",), ("robot",)]
    return [(placement,)]


NEED_KEYS = ("deadline_ms", "robot", "consumes")


def _role(role: Any) -> str:
    try:
        return check_role(role)
    except ValueError as e:
        raise RequestError(str(e)) from None


def _check_user_name(name: Any) -> None:
    if not isinstance(name, str) or not name or not name.replace("_", "").replace("-", "").replace(".", "").isalnum():
        raise RequestError(f"illegal user name {name!r}: use letters, digits, '_', '-', '.'")


def _current(table: dict, k: Any, obj: Any) -> bool:
    """True while ``obj`` is still the record at ``table[k]`` (not removed, nor replaced meanwhile)."""
    return table.get(k) is obj
