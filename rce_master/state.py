"""The master's command data structure (DESIGN section 1), sans I/O.

Users, task sets, robots, containers, nodes, parameters, interfaces and
connections, with every rule the master enforces: tags are scoped per user,
robot-side interfaces belong to the robot that asks, container-side ones to a
container of the user, connections pair Publisher with Subscriber and
ServiceClient with ServiceProvider of the same class. Every method validates
before it changes anything and raises :class:`RequestError` (or a subclass)
naming what was wrong; the asyncio shell (:mod:`rce_master.server`) performs
the I/O the state asks for.

Requests are keyed by tags, so replaying one (after a reconnect) either
succeeds identically or names the duplicate.
"""
from __future__ import annotations

import hashlib
import hmac
import itertools
import os
import time
from dataclasses import dataclass, field
from typing import Any

from rce.errors import AuthError, NotFound, RequestError, Unavailable
from rce.interfaces import PAIRS
from rce.protocol import split_interface_type

SCRYPT = {"n": 2**14, "r": 8, "p": 1}


def password_digest(password: str) -> str:
    """The hex SHA-256 a client sends for ``password`` (DESIGN section 3.2)."""
    return hashlib.sha256(password.encode()).hexdigest()


def _scrypt(digest_hex: str, salt: bytes) -> bytes:
    return hashlib.scrypt(digest_hex.lower().encode(), salt=salt, dklen=32, **SCRYPT)


@dataclass
class User:
    """A user; the password is kept only as scrypt(sha256_hex(password), salt)."""
    name: str
    salt: bytes
    key: bytes

    @classmethod
    def create(cls, name: str, password: str) -> "User":
        salt = os.urandom(16)
        return cls(name, salt, _scrypt(password_digest(password), salt))

    def check(self, digest_hex: str) -> bool:
        """True if ``digest_hex`` (hex SHA-256 of the password) matches."""
        return hmac.compare_digest(_scrypt(digest_hex, self.salt), self.key)

    def to_record(self) -> dict:
        return {"name": self.name, "salt": self.salt.hex(), "scrypt": self.key.hex()}

    @classmethod
    def from_record(cls, r: dict) -> "User":
        return cls(r["name"], bytes.fromhex(r["salt"]), bytes.fromhex(r["scrypt"]))


@dataclass
class TaskSet:
    """A robot task set (endpoints) or container task set (host)."""
    tid: int
    kind: str                 # "robot" | "container"
    name: str
    host: str
    info: dict = field(default_factory=dict)
    robots: int = 0
    cpu_load: float = 0.0     # sum of cpu requested by its containers (cores)
    mem_load: float = 0.0     # MiB requested
    containers: int = 0
    lost: bool = False


@dataclass
class Robot:
    user: str
    robot: str
    tid: int
    since: float


@dataclass
class Container:
    cid: int
    user: str
    ctag: str
    owner: str                # robotID that created it
    tid: int                  # container host
    group: str | None
    data: dict
    state: str = "starting"   # starting | running | lost | stopping
    data_addr: str = ""
    sandbox: str = ""


@dataclass
class NodeRec:
    user: str
    ctag: str
    ntag: str
    spec: dict
    status: str = "starting"
    detail: dict = field(default_factory=dict)


@dataclass
class InterfaceRec:
    iid: int
    user: str
    etag: str
    itag: str
    itype: str
    kind: str                 # Publisher | Subscriber | ServiceClient | ServiceProvider
    side: str                 # Interface | Converter | Forwarder
    cls: str
    addr: str | None
    location: int             # cid (container side) or robot task set tid (robot side)

    @property
    def tag(self) -> str:
        return f"{self.etag}/{self.itag}"

    @property
    def robot_side(self) -> bool:
        return self.side != "Interface"


@dataclass(frozen=True)
class ConnectionRec:
    user: str
    a: int                    # iid
    b: int


class MasterState:
    """All master state; methods validate, mutate, and return what the shell must do."""

    def __init__(self) -> None:
        self.users: dict[str, User] = {}
        self.tasksets: dict[int, TaskSet] = {}
        self.robots: dict[tuple[str, str], Robot] = {}
        self.containers: dict[tuple[str, str], Container] = {}
        self.nodes: dict[tuple[str, str, str], NodeRec] = {}
        self.params: dict[tuple[str, str, str], Any] = {}
        self.interfaces: dict[tuple[str, str, str], InterfaceRec] = {}
        self.connections: set[ConnectionRec] = set()
        # indexes, so that a robot leaving with many interfaces costs O(its connections)
        self._by_iid: dict[int, InterfaceRec] = {}
        self._links: dict[int, set[ConnectionRec]] = {}     # iid -> its connections
        self._tids = itertools.count(1)
        self._cids = itertools.count(1)
        self._iids = itertools.count(1)

    # -- users ---------------------------------------------------------------------------------
    def add_user(self, name: str, password: str) -> User:
        """Add a user. Raises :class:`RequestError` for an empty/duplicate name or empty password."""
        if not name or not name.replace("_", "").replace("-", "").replace(".", "").isalnum():
            raise RequestError(f"illegal user name {name!r}: use letters, digits, '_', '-', '.'")
        if name in self.users:
            raise RequestError(f"user {name!r} already exists")
        if not password:
            raise RequestError("the password must not be empty")
        u = self.users[name] = User.create(name, password)
        return u

    def del_user(self, name: str) -> None:
        if name not in self.users:
            raise NotFound(f"no user {name!r}")
        if any(r.user == name for r in self.robots.values()):
            raise RequestError(f"user {name!r} has connected robots; disconnect them first")
        del self.users[name]

    def authenticate(self, user: str, digest_hex: str) -> None:
        """Raise :class:`AuthError` unless ``digest_hex`` is the user's password digest."""
        u = self.users.get(user)
        if u is None or not isinstance(digest_hex, str) or not u.check(digest_hex):
            raise AuthError(f"invalid user ID or password for user {user!r}")

    # -- task sets -----------------------------------------------------------------------------
    def register_taskset(self, kind: str, name: str, host: str, info: dict) -> TaskSet:
        if kind not in ("robot", "container"):
            raise RequestError(f"unknown task set kind {kind!r}")
        ts = TaskSet(next(self._tids), kind, name, host, info)
        self.tasksets[ts.tid] = ts
        return ts

    def drop_taskset(self, tid: int) -> tuple[list[Container], list[Robot]]:
        """Remove a task set that went away. Returns its containers (now ``lost``) and robots."""
        ts = self.tasksets.pop(tid, None)
        if ts is None:
            return [], []
        lost = [c for c in self.containers.values() if c.tid == tid]
        for c in lost:
            c.state = "lost"
        robots = [r for r in self.robots.values() if r.tid == tid]
        return lost, robots

    def pick_robot_taskset(self) -> TaskSet:
        """The least loaded robot task set. Raises :class:`Unavailable` if there is none."""
        cands = [t for t in self.tasksets.values() if t.kind == "robot" and not t.lost]
        if not cands:
            raise Unavailable("no robot endpoint is available; start rce-robot")
        return min(cands, key=lambda t: (t.robots, t.tid))

    def pick_container_host(self, data: dict) -> TaskSet:
        """The container host with the lowest load after adding this container's cpu/memory
        request (relative to its capacity). Raises :class:`Unavailable` if none fits."""
        cpu = float(data.get("cpu") or 0)
        mem = float(data.get("memory") or 0)
        best, best_key = None, None
        for t in self.tasksets.values():
            if t.kind != "container" or t.lost:
                continue
            cap = t.info.get("capacity") or {}
            cap_cpu, cap_mem = float(cap.get("cpu") or 0), float(cap.get("memory") or 0)
            if cap_mem and t.mem_load + mem > cap_mem:
                continue
            load = max((t.cpu_load + cpu) / cap_cpu if cap_cpu else 0.0,
                       (t.mem_load + mem) / cap_mem if cap_mem else 0.0)
            key = (load, t.containers, t.tid)
            if best_key is None or key < best_key:
                best, best_key = t, key
        if best is None:
            raise Unavailable("no container host can take this container "
                              f"(cpu {cpu:g} cores, memory {mem:g} MiB); start rce-container")
        return best

    # -- robots --------------------------------------------------------------------------------
    def robot_connect(self, user: str, robot: str, tid: int) -> Robot:
        """Record a connected robot. Raises :class:`RequestError` for a duplicate robotID or one
        that clashes with a container tag of the user."""
        if (user, robot) in self.robots:
            raise RequestError(f"robot {robot!r} of user {user!r} is already connected")
        if (user, robot) in self.containers:
            raise RequestError(f"robot ID {robot!r} is already used as a container tag")
        r = self.robots[(user, robot)] = Robot(user, robot, tid, time.time())
        if tid in self.tasksets:
            self.tasksets[tid].robots += 1
        return r

    def robot_disconnect(self, user: str, robot: str) -> tuple[list[InterfaceRec], list[Container]]:
        """Forget a robot: removes its interfaces (and their connections); returns those
        interfaces and the containers it owns (the shell destroys them)."""
        r = self.robots.pop((user, robot), None)
        if r is None:
            return [], []
        if r.tid in self.tasksets:
            self.tasksets[r.tid].robots -= 1
        ifaces = [i for i in self.interfaces.values() if i.user == user and i.etag == robot and i.robot_side]
        owned = [c for c in self.containers.values() if c.user == user and c.owner == robot]
        return ifaces, owned

    # -- containers ----------------------------------------------------------------------------
    def add_container(self, user: str, owner: str, ctag: str, data: dict | None) -> tuple[Container, TaskSet]:
        """Reserve a new container (state ``starting``) on the chosen host."""
        if (user, ctag) in self.containers:
            raise RequestError(f"container {ctag!r} already exists")
        if (user, ctag) in self.robots:
            raise RequestError(f"container tag {ctag!r} is already used as a robot ID")
        data = dict(data or {})
        host = self.pick_container_host(data)
        c = Container(next(self._cids), user, ctag, owner, host.tid, data.get("group") or None, data)
        self.containers[(user, ctag)] = c
        host.containers += 1
        host.cpu_load += float(data.get("cpu") or 0)
        host.mem_load += float(data.get("memory") or 0)
        return c, host

    def container_ready(self, c: Container, data_addr: str, sandbox: str) -> None:
        c.state, c.data_addr, c.sandbox = "running", data_addr, sandbox

    def container(self, user: str, ctag: str) -> Container:
        """The user's container ``ctag``. Raises :class:`NotFound`, or :class:`Unavailable` if lost."""
        c = self.containers.get((user, ctag))
        if c is None:
            raise NotFound(f"container {ctag!r} does not exist")
        if c.state == "lost":
            raise Unavailable(f"container {ctag!r} was lost with its host")
        return c

    def remove_container(self, user: str, ctag: str) -> tuple[Container, list[InterfaceRec]]:
        """Forget a container with its nodes, parameters and interfaces; returns the container
        and its interfaces (the shell disconnects their peers)."""
        c = self.containers.get((user, ctag))
        if c is None:
            raise NotFound(f"container {ctag!r} does not exist")
        del self.containers[(user, ctag)]
        host = self.tasksets.get(c.tid)
        if host:
            host.containers -= 1
            host.cpu_load -= float(c.data.get("cpu") or 0)
            host.mem_load -= float(c.data.get("memory") or 0)
        for k in [k for k in self.nodes if k[:2] == (user, ctag)]:
            del self.nodes[k]
        for k in [k for k in self.params if k[:2] == (user, ctag)]:
            del self.params[k]
        ifaces = [i for i in self.interfaces.values() if i.user == user and i.etag == ctag]
        return c, ifaces

    # -- nodes and parameters --------------------------------------------------------------------
    def add_node(self, user: str, spec: dict) -> tuple[Container, NodeRec]:
        c = self.container(user, spec["containerTag"])
        key = (user, c.ctag, spec["nodeTag"])
        if key in self.nodes:
            raise RequestError(f"node {spec['nodeTag']!r} already exists in container {c.ctag!r}")
        n = self.nodes[key] = NodeRec(user, c.ctag, spec["nodeTag"], dict(spec))
        return c, n

    def remove_node(self, user: str, ctag: str, ntag: str) -> Container:
        c = self.container(user, ctag)
        if self.nodes.pop((user, ctag, ntag), None) is None:
            raise NotFound(f"node {ntag!r} does not exist in container {ctag!r}")
        return c

    def node_status(self, cid: int, ntag: str, status: str, detail: dict) -> NodeRec | None:
        c = next((c for c in self.containers.values() if c.cid == cid), None)
        n = self.nodes.get((c.user, c.ctag, ntag)) if c else None
        if n:
            n.status, n.detail = status, detail
        return n

    def set_param(self, user: str, ctag: str, name: str, value: Any) -> Container:
        c = self.container(user, ctag)
        self.params[(user, ctag, name)] = value
        return c

    def delete_param(self, user: str, ctag: str, name: str) -> Container:
        c = self.container(user, ctag)
        if self.params.pop((user, ctag, name), _NONE) is _NONE:
            raise NotFound(f"parameter {name!r} is not set in container {ctag!r}")
        return c

    # -- interfaces and connections --------------------------------------------------------------
    def add_interface(self, user: str, robot: str, spec: dict, cls_known: bool = True) -> InterfaceRec:
        """Add an interface for the robot ``robot`` of ``user`` asking.

        Robot-side kinds (Converter/Forwarder) must name the asking robot as endpoint; container
        kinds (Interface) a container of the user. Raises :class:`RequestError`/:class:`NotFound`."""
        etag, itag = spec["endpointTag"], spec["interfaceTag"]
        itype = spec["interfaceType"]
        kind, side = split_interface_type(itype)
        if "/" in itag:
            raise RequestError(f"interface tag {itag!r} must not contain '/'")
        if side == "Interface":
            c = self.container(user, etag)
            location = c.cid
        else:
            if etag != robot:
                raise RequestError(f"a {itype} is created on the robot's own endpoint: endpointTag must be "
                                   f"{robot!r}, got {etag!r}")
            r = self.robots.get((user, robot))
            if r is None:
                raise NotFound(f"robot {robot!r} is not connected")
            location = r.tid
        key = (user, etag, itag)
        if key in self.interfaces:
            raise RequestError(f"interface {etag}/{itag} already exists")
        rec = InterfaceRec(next(self._iids), user, etag, itag, f"{kind}{side}", kind, side,
                           spec["className"].strip("/"), spec.get("addr"), location)
        self.interfaces[key] = rec
        self._by_iid[rec.iid] = rec
        return rec

    def interface(self, user: str, tag: str) -> InterfaceRec:
        """Look up ``endpointTag/interfaceTag``. Raises :class:`NotFound`."""
        etag, _, itag = tag.partition("/")
        rec = self.interfaces.get((user, etag, itag))
        if rec is None:
            raise NotFound(f"interface {tag!r} does not exist")
        return rec

    def remove_interface(self, user: str, etag: str, itag: str) -> tuple[InterfaceRec, list[tuple[InterfaceRec, InterfaceRec]]]:
        """Forget an interface; returns it and the connections removed with it (pairs of records)."""
        rec = self.interfaces.get((user, etag, itag))
        if rec is None:
            raise NotFound(f"interface {etag}/{itag} does not exist")
        return rec, self.forget_interfaces([rec])

    def _add_link(self, conn: ConnectionRec) -> None:
        self.connections.add(conn)
        self._links.setdefault(conn.a, set()).add(conn)
        self._links.setdefault(conn.b, set()).add(conn)

    def _drop_link(self, conn: ConnectionRec) -> None:
        self.connections.discard(conn)
        for iid in (conn.a, conn.b):
            links = self._links.get(iid)
            if links is not None:
                links.discard(conn)
                if not links:
                    del self._links[iid]

    def forget_interfaces(self, recs: list[InterfaceRec]) -> list[tuple[InterfaceRec, InterfaceRec]]:
        """Remove interfaces (one removed, a robot left, a container destroyed, a failed add) with
        their connections; returns the removed connections as pairs of records. O(their connections)."""
        out = []
        for rec in recs:
            self.interfaces.pop((rec.user, rec.etag, rec.itag), None)
            self._by_iid.pop(rec.iid, None)
            for conn in list(self._links.get(rec.iid, ())):
                self._drop_link(conn)
                other = self._by_iid.get(conn.b if conn.a == rec.iid else conn.a)
                if other is None:
                    other = next((r for r in recs if r.iid in (conn.a, conn.b) and r is not rec), None)
                if other is not None:
                    out.append((rec, other) if conn.a == rec.iid else (other, rec))
        return out

    def connection_count(self, iid: int) -> int:
        """How many connections interface ``iid`` has."""
        return len(self._links.get(iid, ()))

    def connect(self, user: str, tag_a: str, tag_b: str) -> tuple[InterfaceRec, InterfaceRec]:
        """Connect two interfaces. Raises :class:`RequestError` if they cannot be paired
        (kinds, classes, same endpoint side rules) or are already connected."""
        a, b = self.interface(user, tag_a), self.interface(user, tag_b)
        if PAIRS[a.kind] != b.kind:
            raise RequestError(f"cannot connect {a.tag} ({a.itype}) with {b.tag} ({b.itype}): a {a.kind} pairs "
                               f"only with a {PAIRS[a.kind]}")
        if a.cls != b.cls:
            raise RequestError(f"cannot connect {a.tag} ({a.cls}) with {b.tag} ({b.cls}): classes differ")
        if a.robot_side and b.robot_side:
            raise RequestError(f"cannot connect two robot-side interfaces ({a.tag}, {b.tag}); "
                               "connect each to a container interface")
        for x in (a, b):
            if not x.robot_side:
                c = next((c for c in self.containers.values() if c.cid == x.location), None)
                if c is None or c.state != "running":
                    raise Unavailable(f"container {x.etag!r} of interface {x.tag} is not running")
        conn = ConnectionRec(user, min(a.iid, b.iid), max(a.iid, b.iid))
        if conn in self.connections:
            raise RequestError(f"{a.tag} and {b.tag} are already connected")
        self._add_link(conn)
        return a, b

    def disconnect(self, user: str, tag_a: str, tag_b: str) -> tuple[InterfaceRec, InterfaceRec]:
        a, b = self.interface(user, tag_a), self.interface(user, tag_b)
        conn = ConnectionRec(user, min(a.iid, b.iid), max(a.iid, b.iid))
        if conn not in self.connections:
            raise NotFound(f"{a.tag} and {b.tag} are not connected")
        self._drop_link(conn)
        return a, b

    def data_addr(self, rec: InterfaceRec) -> str:
        """Data-plane address of the endpoint holding interface ``rec``."""
        if rec.robot_side:
            ts = self.tasksets.get(rec.location)
            if ts is None:
                raise Unavailable(f"the robot endpoint of {rec.tag} is gone")
            return ts.info["data_addr"]
        c = next((c for c in self.containers.values() if c.cid == rec.location), None)
        if c is None or not c.data_addr:
            raise Unavailable(f"container {rec.etag!r} of {rec.tag} is not running")
        return c.data_addr

    def container_by_cid(self, cid: int) -> Container | None:
        return next((c for c in self.containers.values() if c.cid == cid), None)

    # -- views (admin API) -----------------------------------------------------------------------
    def snapshot(self) -> dict:
        """JSON view of everything (admin API and rce-console)."""
        ts = self.tasksets
        by_iid = {i.iid: i for i in self.interfaces.values()}
        return {
            "users": [{"name": u} for u in sorted(self.users)],
            "tasksets": [{"tid": t.tid, "kind": t.kind, "name": t.name, "host": t.host, "robots": t.robots,
                          "containers": t.containers, "cpu_load": t.cpu_load, "mem_load": t.mem_load,
                          **{k: v for k, v in t.info.items() if k in ("ws_url", "data_addr", "sandbox", "capacity")}}
                         for t in sorted(ts.values(), key=lambda t: t.tid)],
            "robots": [{"user": r.user, "robot": r.robot, "endpoint": ts[r.tid].name if r.tid in ts else "?",
                        "since": r.since} for r in sorted(self.robots.values(), key=lambda r: (r.user, r.robot))],
            "containers": [{"user": c.user, "ctag": c.ctag, "owner": c.owner, "cid": c.cid,
                            "host": ts[c.tid].name if c.tid in ts else "(lost)", "group": c.group, "state": c.state,
                            "sandbox": c.sandbox, "data": c.data}
                           for c in sorted(self.containers.values(), key=lambda c: c.cid)],
            "nodes": [{"user": n.user, "ctag": n.ctag, "ntag": n.ntag, "pkg": n.spec.get("pkg"),
                       "exe": n.spec.get("exe"), "status": n.status, **n.detail}
                      for n in sorted(self.nodes.values(), key=lambda n: (n.user, n.ctag, n.ntag))],
            "parameters": [{"user": u, "ctag": c, "name": n, "value": v} for (u, c, n), v in sorted(self.params.items())],
            "interfaces": [{"user": i.user, "tag": i.tag, "type": i.itype, "class": i.cls, "addr": i.addr,
                            "iid": i.iid, "connections": self.connection_count(i.iid)}
                           for i in sorted(self.interfaces.values(), key=lambda i: i.iid)],
            "connections": [{"user": c.user, "tagA": by_iid[c.a].tag, "tagB": by_iid[c.b].tag}
                            for c in sorted(self.connections, key=lambda c: (c.a, c.b))
                            if c.a in by_iid and c.b in by_iid],
        }


_NONE = object()
