"""The records of the master's command data structure (docs/design.md, section 2.2): users, task sets,
robots, containers, nodes, parameters, interfaces and connections.

Each record class knows its store key (:mod:`rce_master.state.store`) and its JSON form
(``to_record``/``from_record``); :class:`~rce_master.state.master_state.MasterState` holds them and is the
only one that changes them.
"""
from __future__ import annotations

import dataclasses
import hashlib
import hmac
import os
from dataclasses import dataclass, field
from typing import Any

from rce.contract.environment import NodeStatus
from rce.protocol.zones import Zone, parse_zone
from rce_master.state.lifecycle import DOWN, ContainerState
from rce_master.state.store import Key

SCRYPT = {"n": 2**14, "r": 8, "p": 1}     # RFC 7914 cost: ~50 ms of CPU per check, by design
LIMIT_KEYS = ("cpu", "memory", "pids", "size", "bandwidth")   # container limits and sizes (docs/INTERNALS.md)
# what a user may do on the fleet's task API (docs/task-api.md): viewer reads tasks, metrics and the operator page;
# operator also adds and cancels tasks; admin also revokes others' tokens. Robots' logins do not look at it.
ROLES = ("viewer", "operator", "admin")
DEFAULT_ROLE = "operator"   # a record without a role (written before roles existed), and `user add` without --role


def password_digest(password: str) -> str:
    """The hex SHA-256 a client sends for ``password`` (docs/design.md, section 3.2)."""
    return hashlib.sha256(password.encode()).hexdigest()


def _scrypt(digest_hex: str, salt: bytes) -> bytes:
    return hashlib.scrypt(digest_hex.lower().encode(), salt=salt, dklen=32, **SCRYPT)


class _Record:
    """JSON form of a record dataclass: its fields, less those in ``DERIVED`` (recomputed on load); a
    field with a default may be absent from a record (one written before the field existed)."""

    DERIVED: tuple[str, ...] = ()

    def to_record(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in self.DERIVED}

    @classmethod
    def from_record(cls, record: dict):
        return cls(**{f.name: record[f.name] for f in dataclasses.fields(cls) if f.name not in cls.DERIVED
                      and (f.name in record or f.default is dataclasses.MISSING)})


@dataclass
class User:
    """A user; the password is kept only as scrypt(sha256_hex(password), salt); ``role``: one of
    :data:`ROLES`.

    Record (also the users file's): ``{"name", "salt": hex, "scrypt": hex, "role"}``; a record without
    ``role`` is :data:`DEFAULT_ROLE`'s."""
    name: str
    salt: bytes
    key: bytes
    role: str = DEFAULT_ROLE

    @classmethod
    def create(cls, name: str, password: str, role: str = DEFAULT_ROLE) -> "User":
        salt = os.urandom(16)
        return cls(name, salt, _scrypt(password_digest(password), salt), check_role(role))

    def check(self, digest_hex: str) -> bool:
        """True if ``digest_hex`` (hex SHA-256 of the password) matches."""
        return hmac.compare_digest(_scrypt(digest_hex, self.salt), self.key)

    @property
    def store_key(self) -> Key:
        return ("user", self.name)

    def to_record(self) -> dict:
        return {"name": self.name, "salt": self.salt.hex(), "scrypt": self.key.hex(), "role": self.role}

    @classmethod
    def from_record(cls, record: dict) -> "User":
        """Raises KeyError/ValueError/TypeError for a malformed record (ValueError: an unknown role)."""
        return cls(record["name"], bytes.fromhex(record["salt"]), bytes.fromhex(record["scrypt"]),
                   check_role(record.get("role", DEFAULT_ROLE)))


def check_role(role: Any) -> str:
    """``role`` when it is one of :data:`ROLES`; else raises ValueError naming them."""
    if role not in ROLES:
        raise ValueError(f"unknown role {role!r} (roles: {', '.join(ROLES)})")
    return role


@dataclass
class TaskSet(_Record):
    """A robot task set (endpoints) or container task set (host). ``info``: its ``register`` args.

    ``lost``: absent, i.e. known from the store a previous master left but not re-registered
    since this master started (no placement on it, no calls to it)."""
    tid: int
    kind: str                 # "robot" | "container"
    name: str
    host: str
    info: dict = field(default_factory=dict)
    lost: bool = False
    # derived from the robots and containers on it (kept up to date by MasterState, not stored)
    robots: int = 0
    cpu_load: float = 0.0     # sum of cpu requested by its containers (cores), lost ones left out
    mem_load: float = 0.0     # MiB requested
    containers: int = 0
    DERIVED = ("robots", "cpu_load", "mem_load", "containers")

    @property
    def zone(self) -> Zone:
        """Where this container host stands (:mod:`rce.protocol.zones`; ``cloud`` if it said nothing)."""
        return parse_zone(self.info.get("zone") or "cloud", self.info.get("zone_user"))

    @property
    def store_key(self) -> Key:
        return ("taskset", str(self.tid))


@dataclass
class Robot(_Record):
    """A connected robot: on robot task set ``tid`` since ``since`` (Unix time, s); ``relay``: the robot
    (of the same user) its link to the cloud goes through, "" for its own path, since ``relay_since``
    (Unix time, s; docs/relays.md)."""
    user: str
    robot: str
    tid: int
    since: float
    relay: str = ""
    relay_since: float = 0.0

    @property
    def store_key(self) -> Key:
        return ("robot", self.user, self.robot)


@dataclass
class ContainerRec(_Record):
    """A container of ``user`` created by robot ``owner`` on container host ``tid``.

    ``state``: ``starting`` (its CC runs), ``running``, ``lost`` (its host or environment went
    away; ``tid`` still names that host) or ``recovering`` (being re-created on host ``tid``
    under a new ``cid``, see :mod:`rce_master.failover`), moving as
    :data:`~rce_master.state.lifecycle.CONTAINER_TRANSITIONS` allows. ``data_addr`` stays the last
    address it ran at while it is lost or recovering ("" only before it first ran)."""
    cid: int
    user: str
    ctag: str
    owner: str                # robotID that created it
    tid: int                  # container host
    group: str | None
    data: dict                # containerData, with the limits as last resized
    state: ContainerState = ContainerState.STARTING
    data_addr: str = ""
    sandbox: str = ""

    def __post_init__(self) -> None:
        self.state = ContainerState(self.state)       # a stored record has its str

    @property
    def store_key(self) -> Key:
        return ("container", self.user, self.ctag)

    @property
    def down(self) -> bool:
        """Lost, or being re-created: no container serves it now."""
        return self.state in DOWN

    def load(self) -> tuple[float, float]:
        """(cpu cores, memory MiB) it asked of its host."""
        return float(self.data.get("cpu") or 0), float(self.data.get("memory") or 0)




@dataclass
class NodeRec(_Record):
    """A node in container ``ctag``; ``spec``: its addNodes entry; ``status``: where it is in its life
    (:data:`~rce_master.state.lifecycle.NODE_TRANSITIONS`); ``detail``: code/signal/reason."""
    user: str
    ctag: str
    ntag: str
    spec: dict
    status: NodeStatus = NodeStatus.STARTING
    detail: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.status = NodeStatus(self.status)         # a stored record has its str

    @property
    def store_key(self) -> Key:
        return ("node", self.user, self.ctag, self.ntag)


@dataclass
class InterfaceRec(_Record):
    """An interface ``etag/itag``; ``location`` is the cid (container side) or the robot task
    set's tid (robot side)."""
    iid: int
    user: str
    etag: str
    itag: str
    itype: str
    kind: str                 # Publisher | Subscriber | ServiceClient | ServiceProvider
    side: str                 # Interface | Converter | Forwarder
    cls: str
    addr: str | None
    location: int
    lane: str | None = None   # control | state | bulk as the robot set it; None: from cls (rce.interfaces.lanes)

    @property
    def tag(self) -> str:
        return f"{self.etag}/{self.itag}"

    @property
    def robot_side(self) -> bool:
        return self.side != "Interface"

    @property
    def store_key(self) -> Key:
        return ("interface", self.user, self.etag, self.itag)


@dataclass(frozen=True)
class ConnectionRec(_Record):
    """A connection between interfaces ``a`` < ``b`` (iids) of ``user``."""
    user: str
    a: int
    b: int

    @property
    def store_key(self) -> Key:
        return ("connection", self.user, str(self.a), str(self.b))


def param_key(user: str, ctag: str, name: str) -> Key:
    """Store key of a parameter; its record is ``{"user", "ctag", "name", "value"}``."""
    return ("param", user, ctag, name)


def limits_of(spec: dict) -> dict[str, Any]:
    """The limits (``cpu``, ``memory``, ``size``, ``bandwidth``) given in ``spec``, None ones left out."""
    return {k: spec[k] for k in LIMIT_KEYS if spec.get(k) is not None}
