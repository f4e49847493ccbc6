"""The master's state as seen in memory: the store's records (:mod:`rce_master.state.store`) held as
record objects (:mod:`rce_master.state.model`) in dicts by key, with the indexes and per-host
accounting the rules need, and the read-only queries and JSON view (admin API) over them.

:meth:`StateIndex.apply` is the one way the view changes: applying a store change
``(key, old record, new record)``. Loading a store, every change an operation writes and the
rollback of a failed operation all go through it, so the view always equals its records.
Existing record objects are updated in place, and a rolled-back removal puts the same object
back: whoever holds one sees the change.
"""
from __future__ import annotations

import dataclasses
from operator import attrgetter
from typing import Any, Callable

from rce.plumbing.errors import NotFound, Unavailable
from rce_master.state.lifecycle import ContainerState
from rce_master.state.model import ConnectionRec, ContainerRec, InterfaceRec, NodeRec, Robot, TaskSet, User
from rce_master.state.store import Key, Store


class StateIndex:
    """Users, task sets, robots, containers, nodes, parameters, interfaces and connections.

    The dicts are keyed like their store keys without the kind (``containers[(user, ctag)]``,
    ``tasksets[tid]``); ``params`` maps ``(user, ctag, name)`` to the value. Read them freely;
    only :meth:`apply` writes them."""

    def __init__(self) -> None:
        self.users: dict[str, User] = {}
        self.tasksets: dict[int, TaskSet] = {}
        self.robots: dict[tuple[str, str], Robot] = {}
        self.containers: dict[tuple[str, str], ContainerRec] = {}
        self.nodes: dict[tuple[str, str, str], NodeRec] = {}
        self.params: dict[tuple[str, str, str], Any] = {}
        self.interfaces: dict[tuple[str, str, str], InterfaceRec] = {}
        self.connections: set[ConnectionRec] = set()
        self.counters: dict[str, int] = {}                   # next id: "tid", "cid", "iid"
        # indexes: a robot leaving with many interfaces costs O(its connections)
        self._by_cid: dict[int, ContainerRec] = {}
        self._by_iid: dict[int, InterfaceRec] = {}
        self._links: dict[int, set[ConnectionRec]] = {}      # iid -> its connections
        # objects removed by the current batch: a rollback puts the same objects back
        self._removed: dict[tuple[int, Any], Any] = {}
        self._appliers: dict[str, Callable[[Key, dict | None, dict | None], None]] = {
            "user": self._apply_user, "counter": self._apply_counter, "taskset": self._apply_taskset,
            "robot": self._apply_robot, "container": self._apply_container, "node": self._apply_node,
            "param": self._apply_param, "interface": self._apply_interface, "connection": self._apply_connection}

    def load(self, store: Store) -> None:
        """Apply every record of ``store`` (on start: the whole state comes back from the store)."""
        for key, record in store.items():
            self.apply(key, None, record)

    def apply(self, key: Key, old: dict | None, new: dict | None) -> None:
        """Make the view follow the store change at ``key`` from record ``old`` to ``new``
        (None: absent). Raises KeyError for an unknown kind of record."""
        self._appliers[key[0]](key, old, new)

    # -- appliers, one per kind of record ----------------------------------------------------------
    def _apply_user(self, key: Key, old: dict | None, new: dict | None) -> None:
        if new is None:
            self.users.pop(key[1], None)
        else:
            self.users[key[1]] = User.from_record(new)

    def _apply_counter(self, key: Key, old: dict | None, new: dict | None) -> None:
        if new is None:
            self.counters.pop(key[1], None)
        else:
            self.counters[key[1]] = int(new["next"])

    def _apply_taskset(self, key: Key, old: dict | None, new: dict | None) -> None:
        tid = int(key[1])
        known = self.tasksets.get(tid)
        ts = self._upsert(self.tasksets, tid, TaskSet, new)
        if ts is not None and known is None:              # (re)created: count what runs on it
            ts.robots = sum(r.tid == tid for r in self.robots.values())
            on_it = [c for c in self.containers.values() if c.tid == tid and c.state != ContainerState.LOST]
            ts.containers = len(on_it)
            ts.cpu_load = sum(c.load()[0] for c in on_it)
            ts.mem_load = sum(c.load()[1] for c in on_it)

    def _apply_robot(self, key: Key, old: dict | None, new: dict | None) -> None:
        for rec, sign in ((old, -1), (new, 1)):
            if rec is not None and rec["tid"] in self.tasksets:
                self.tasksets[rec["tid"]].robots += sign
        self._upsert(self.robots, key[1:], Robot, new)

    def _apply_container(self, key: Key, old: dict | None, new: dict | None) -> None:
        for rec, sign in ((old, -1), (new, 1)):
            # a host carries what runs (or starts) on it; a lost container weighs on none
            running = rec is not None and rec.get("state") != ContainerState.LOST
            host = self.tasksets.get(rec["tid"]) if running else None
            if host is not None:
                data = rec["data"]
                host.containers += sign
                host.cpu_load += sign * float(data.get("cpu") or 0)
                host.mem_load += sign * float(data.get("memory") or 0)
        if old is not None:
            self._by_cid.pop(old["cid"], None)
        c = self._upsert(self.containers, key[1:], ContainerRec, new)
        if c is not None:
            self._by_cid[c.cid] = c

    def _apply_node(self, key: Key, old: dict | None, new: dict | None) -> None:
        self._upsert(self.nodes, key[1:], NodeRec, new)

    def _apply_param(self, key: Key, old: dict | None, new: dict | None) -> None:
        if new is None:
            self.params.pop(key[1:], None)
        else:
            self.params[key[1:]] = new["value"]

    def _apply_interface(self, key: Key, old: dict | None, new: dict | None) -> None:
        if old is not None:
            self._by_iid.pop(old["iid"], None)
        rec = self._upsert(self.interfaces, key[1:], InterfaceRec, new)
        if rec is not None:
            self._by_iid[rec.iid] = rec

    def _apply_connection(self, key: Key, old: dict | None, new: dict | None) -> None:
        conn = ConnectionRec.from_record(new if new is not None else old)
        if new is None:
            self.connections.discard(conn)
            for iid in (conn.a, conn.b):
                links = self._links.get(iid)
                if links is not None:
                    links.discard(conn)
                    if not links:
                        del self._links[iid]
        else:
            self.connections.add(conn)
            self._links.setdefault(conn.a, set()).add(conn)
            self._links.setdefault(conn.b, set()).add(conn)

    def _upsert(self, table: dict, key: Any, cls: type, new: dict | None) -> Any:
        """Put record ``new`` (None: remove) into ``table[k]`` as a ``cls``; an object already there
        (or removed earlier in this batch) is updated in place, its derived fields kept. Returns
        the object, or None when removed."""
        if new is None:
            obj = table.pop(key, None)
            if obj is not None:
                self._removed[(id(table), key)] = obj
            return None
        fresh = cls.from_record(new)
        obj = table.get(key)
        if obj is None:
            obj = self._removed.pop((id(table), key), None)
            if obj is None:
                table[key] = fresh
                return fresh
            table[key] = obj
        for f in dataclasses.fields(cls):
            if f.name not in cls.DERIVED:
                setattr(obj, f.name, getattr(fresh, f.name))
        return obj

    # -- queries --------------------------------------------------------------------------------------
    def container(self, user: str, ctag: str) -> ContainerRec:
        """The user's container ``ctag``. Raises :class:`NotFound`, or :class:`Unavailable` while it
        is lost or being re-created (:func:`lost_reason`)."""
        c = self.containers.get((user, ctag))
        if c is None:
            raise NotFound(f"container {ctag!r} does not exist")
        if c.down:
            raise Unavailable(f"{lost_reason(c)}; try again once it runs (ST status running), or DC it")
        return c

    def container_by_cid(self, cid: int) -> ContainerRec | None:
        return self._by_cid.get(cid)

    def nodes_of(self, container: ContainerRec) -> list[NodeRec]:
        """The nodes of ``container``, by nTag."""
        return sorted((n for k, n in self.nodes.items() if k[:2] == (container.user, container.ctag)),
                      key=attrgetter("ntag"))

    def params_of(self, container: ContainerRec) -> list[tuple[str, Any]]:
        """The parameters set in ``container``: ``(name, value)`` by name."""
        return sorted((k[2], v) for k, v in self.params.items() if k[:2] == (container.user, container.ctag))

    def robot(self, user: str, robot: str) -> Robot | None:
        """The connected ``robot`` of ``user``, or None."""
        return self.robots.get((user, robot))

    def interface(self, user: str, tag: str) -> InterfaceRec:
        """Look up ``endpointTag/interfaceTag``. Raises :class:`NotFound`."""
        etag, _, itag = tag.partition("/")
        rec = self.interfaces.get((user, etag, itag))
        if rec is None:
            raise NotFound(f"interface {tag!r} does not exist")
        return rec

    def interfaces_of(self, user: str, etag: str, robot_side: bool | None = None) -> list[InterfaceRec]:
        """The interfaces on endpoint ``etag`` (a robot or container) of ``user``."""
        return [i for i in self.interfaces.values()
                if i.user == user and i.etag == etag and robot_side in (None, i.robot_side)]

    def connections_of(self, iid: int) -> list[tuple[InterfaceRec, InterfaceRec]]:
        """The connections of interface ``iid``, each as (that interface, its peer)."""
        out = []
        for conn in self._links.get(iid, ()):
            me, peer = self._by_iid.get(iid), self._by_iid.get(conn.b if conn.a == iid else conn.a)
            if me is not None and peer is not None:
                out.append((me, peer))
        return sorted(out, key=lambda pair: pair[1].iid)

    def connection_count(self, iid: int) -> int:
        """How many connections interface ``iid`` has."""
        return len(self._links.get(iid, ()))

    def data_addr(self, rec: InterfaceRec) -> str:
        """Data-plane address of the endpoint holding interface ``rec``. Raises :class:`Unavailable`."""
        if rec.robot_side:
            ts = self.tasksets.get(rec.location)
            if ts is None:
                raise Unavailable(f"the robot endpoint of {rec.tag} is gone")
            return ts.info["data_addr"]
        c = self._by_cid.get(rec.location)
        if c is None or not c.data_addr:
            raise Unavailable(f"container {rec.etag!r} of {rec.tag} is not running")
        return c.data_addr

    def snapshot(self) -> dict:
        """JSON view of everything (admin API and rce-console)."""
        ts = self.tasksets
        by_iid = self._by_iid
        return {
            "users": [{"name": n, "role": u.role} for n, u in sorted(self.users.items())],
            "tasksets": [{"tid": t.tid, "kind": t.kind, "name": t.name, "host": t.host, "absent": t.lost,
                          "robots": t.robots, "containers": t.containers, "cpu_load": t.cpu_load,
                          "mem_load": t.mem_load,
                          **{k: v for k, v in t.info.items()
                             if k in ("ws_url", "data_addr", "sandbox", "capacity", "zone")}}
                         for t in sorted(ts.values(), key=attrgetter("tid"))],
            "robots": [{"user": r.user, "robot": r.robot, "endpoint": ts[r.tid].name if r.tid in ts else "?",
                        "since": r.since, "relay": r.relay, "relay_since": r.relay_since or None}
                       for r in sorted(self.robots.values(), key=attrgetter("user", "robot"))],
            "containers": [{"user": c.user, "ctag": c.ctag, "owner": c.owner, "cid": c.cid,
                            "host": ts[c.tid].name if c.tid in ts else "(lost)", "group": c.group, "state": c.state,
                            "sandbox": c.sandbox, "data": c.data}
                           for c in sorted(self.containers.values(), key=attrgetter("cid"))],
            "nodes": [{"user": n.user, "ctag": n.ctag, "ntag": n.ntag, "pkg": n.spec.get("pkg"),
                       "exe": n.spec.get("exe"), "status": n.status, **n.detail}
                      for n in sorted(self.nodes.values(), key=attrgetter("user", "ctag", "ntag"))],
            "parameters": [{"user": u, "ctag": c, "name": n, "value": v}
                           for (u, c, n), v in sorted(self.params.items())],
            "interfaces": [{"user": i.user, "tag": i.tag, "type": i.itype, "class": i.cls, "addr": i.addr,
                            "iid": i.iid, "connections": self.connection_count(i.iid)}
                           for i in sorted(self.interfaces.values(), key=attrgetter("iid"))],
            "connections": [{"user": c.user, "tagA": by_iid[c.a].tag, "tagB": by_iid[c.b].tag}
                            for c in sorted(self.connections, key=attrgetter("a", "b"))
                            if c.a in by_iid and c.b in by_iid],
        }


def lost_reason(container: ContainerRec) -> str:
    """What became of lost (or recovering) ``container``, for the refusals that name it."""
    if container.state == ContainerState.RECOVERING:
        return f"container {container.ctag!r} was lost with its host and is being re-created on another host"
    return f"container {container.ctag!r} was lost with its host and waits for a container host to be re-created on"
