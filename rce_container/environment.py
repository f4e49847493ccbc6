"""The environment process: the ROS-like master of one container group of one user.

Run by the container task set as ``python -m rce_container.environment --control SOCK
--env-id N ...``. It owns

- one :class:`~rce.bus.core.Bus` shared by the group's containers, served to each container
  on its own Unix socket (``RUNTIME/c<cid>/bus.sock``, one :class:`~rce.bus.server.BusServer`
  per container, all on the same bus) — a container's nodes get only their own socket;
- one :class:`~rce.transport.dataplane.DataPlane` (its address is the group's ``data_addr``);
- per container: a sandbox, a node :class:`~rce_container.launcher.Launcher` and its
  container-side interfaces.

It dials its task set's control socket, says ``hello {env_id, pid, data_addr}``, then serves
the ops the task set relays (docs/INTERNALS.md, "Master -> container task set") plus
``data_key`` (its data-plane key, :mod:`rce.transport.cluster_auth`), ``add_container``, ``remove_container``,
``shutdown``, ``stats`` and ``logs``. It sends
``node_status`` notifications up the same link and exits (killing its nodes) when the link
closes or on SIGTERM/SIGINT.
"""
from __future__ import annotations

import argparse
import asyncio
import os
import secrets
import shutil
import signal
import socket
import sys
import time
from pathlib import Path
from typing import Any

from rce.plumbing.process import run_loop
from rce.contract import environment as ops
from rce.contract import node as to_node
from rce.transport import framing
from rce.transport import rpc
from rce.bus.core import Bus
from rce.bus.server import BusServer, NodeSession
from rce.transport.cluster_auth import token_of
from rce.transport.dataplane import DataPlane
from rce.plumbing.errors import MessageError, NotFound, RCEError, RequestError
from rce.plumbing.log import get_logger, setup_logging
from rce.messages import MessageRegistry, default_registry, wire_name
from rce.interfaces.naming import resolve
from rce.transport.op_table import OpTable
from rce.node.package_path import load_package_types
from rce.node.results import ResultStats
from rce_container import sandbox as sandboxes
from rce_container.direct_routes import DirectRoutes
from rce_container.env_layout import BUS_CALL_TIMEOUT, MAX_SOCKET_PATH, container_paths
from rce_container.interfaces import BusInterface, make_interface
from rce_container.launcher import LOG_LINES, Launcher
from rce_container.ros1_graph import Ros1Graph
from rce_container.ros1_plan import bridged
from rce_container.ros2_graph import Ros2Graph
from rce_container.usage import CpuRate, measure
from rce_container.zygote_client import ZygoteTemplate

log = get_logger("rce.container.env")

MAX_SAMPLE = 10000        # messages, bound of one bus_sample
MAX_SAMPLE_TIMEOUT = 300  # s, the longest a bus_sample may wait
BUS_SAMPLE_TIMEOUT = 5.0  # s a bus_sample waits for messages when the request gives no timeout
BUS_TOKEN_BYTES = 32      # random bytes of a container's bus token (64 hex chars, 256 bits)
RESULTS_TIMEOUT = 1.0     # s a node has to hand over its result samples
STATE_TIMEOUT = 10.0      # s a node has to hand its state out, or take it in (rce.node.Node.handoff)

#: The ops the task set sends an environment (the module doc): those it relays from the master, and its own.
ENV_OPS = OpTable("container task set -> environment")


class GroupContainer:
    """One container of the group: its bus socket and server, sandbox, launcher, interfaces."""

    def __init__(self, env: "Environment", cid: int, ctag: str, user: str, group: str | None, limits: dict,
                 deadline_ms: float | None = None, handoff: bool = False):
        self.env, self.cid, self.ctag, self.user, self.group = env, cid, ctag, user, group
        self.limits = limits
        self.results = ResultStats(deadline_ms)
        self.workdir, socket = container_paths(env.runtime_dir, env.socket_dir, cid)
        self.socket = str(socket)
        token = secrets.token_hex(BUS_TOKEN_BYTES)     # only this container's nodes get it (RCE_BUS_TOKEN)
        self.server = BusServer(env.bus, token=token, direct=env.direct is not None)
        if env.direct is not None:
            self.server.on_direct_closed.append(env.direct.link_closed)
        self.server.on_direct_fence.append(env.plane.fence_arrived)
        self.sandbox = env.sandbox_cls(cid, ctag, limits, self.workdir, grace=env.grace, bus_socket=self.socket,
                                       scope=env.scope)
        self.launcher = Launcher(self.sandbox, self.socket, ctag, self._status, bus_token=token,
                                 template=env.template)
        if handoff:
            self.launcher.extra_env["RCE_STATE_IN"] = "1"
        self.ros1 = Ros1Graph(self.launcher, cid, env.bus)     # rosmaster and relay, while it has ROS 1 nodes
        # its ROS 2 relay, while it has ROS 2 nodes; it tells the robot what it cannot bridge
        self.ros2 = Ros2Graph(self.launcher, cid, env.bus, lambda: self.interfaces,
                              lambda iid, tag, status, reason: env.notify_interface(cid, iid, tag, status, reason))
        self.interfaces: dict[int, BusInterface] = {}

    def _status(self, ntag: str, status: str, **fields: Any) -> None:
        self.env.notify_status(self.cid, ntag, status, **fields)

    async def start(self) -> None:
        if len(self.socket.encode()) > MAX_SOCKET_PATH:
            raise RCEError(f"bus socket path {self.socket!r} is too long for a Unix socket; "
                           "use a shorter --runtime-dir")
        self.workdir.mkdir(parents=True, exist_ok=True)
        Path(self.socket).parent.mkdir(parents=True, exist_ok=True)
        await self.sandbox.setup()          # before the socket exists: its directory is bind-mounted
        if self.sandbox.node_uid is not None:     # the socket is the node uid's, and only it may connect
            self.server.owner, self.server.uids = self.sandbox.node_uid, frozenset({self.sandbox.node_uid})
        await self.server.listen(self.socket)
        self.launcher.warm_up()             # the zygote imports the node runtime while the nodes are asked for

    async def close(self) -> None:
        """Kill the nodes, drop the interfaces, close the socket, remove the workdir."""
        await self.launcher.close()
        await self.ros1.close()
        await self.ros2.close()
        await self.sandbox.close()
        for iface in list(self.interfaces.values()):
            await self.env.drop_interface(iface)
        await self.server.close()
        shutil.rmtree(self.workdir, ignore_errors=True)
        shutil.rmtree(Path(self.socket).parent, ignore_errors=True)

    def usage(self) -> tuple[dict, dict]:
        """(container-level use, {ntag: per-node use}): CPU %, resident memory, processes, and
        per node its bus traffic. The container level comes from the sandbox's cgroup when it
        has one (every process of the container, its init included), else from the sum of the
        nodes' process trees."""
        rates = self.env.rates
        sessions = {s.node: s for s in self.server.sessions if s.node}
        per_node, total = {}, {"cpu_seconds": 0.0, "rss_bytes": 0, "processes": 0}
        for n in self.launcher.nodes.values():
            m = measure(self.sandbox.node_pids(n.proc))
            for k in total:
                total[k] += m[k]
            pid = n.pid
            sess = sessions.get(n.full_name)
            bus = sess.stats() if sess else {"msgs_in": 0, "bytes_in": 0, "msgs_out": 0, "bytes_out": 0, "dropped": 0,
                                             "undecodable": 0}
            info = n.info()
            info.pop("argv")
            per_node[n.ntag] = {
                **info,
                "cpu_percent": round(rates.percent(("node", self.cid, n.ntag, pid), m["cpu_seconds"], n.started), 1)
                if pid else 0.0,
                "rss_mib": round(m["rss_bytes"] / 2**20, 2), "processes": m["processes"],
                "connected": sess is not None, **{k: bus[k] for k in ("msgs_in", "msgs_out", "bytes_in", "bytes_out",
                                                                     "dropped", "undecodable")}}
        box = self.sandbox.usage()
        if "pids" in box:
            m = measure(box["pids"])
            cpu = box["cpu_seconds"] if box.get("cpu_seconds") is not None else m["cpu_seconds"]
            total = {"cpu_seconds": cpu, "rss_bytes": m["rss_bytes"], "processes": m["processes"]}
        out = {"cpu_percent": round(rates.percent(("container", self.cid), total["cpu_seconds"],
                                                  self.sandbox.started), 1),
               "rss_mib": round(total["rss_bytes"] / 2**20, 2), "processes": total["processes"],
               "cpu_seconds": round(total["cpu_seconds"], 4)}
        if box.get("cpu"):
            out["cpu"] = {**box["cpu"], "throttled_s": round(box["cpu"]["throttled_s"], 3)}
        mem = box.get("memory") or {}
        if "usage_bytes" in mem:
            limit = mem.get("limit_bytes")
            out["memory"] = {"usage_mib": round(mem["usage_bytes"] / 2**20, 2),
                             "limit_mib": None if limit is None else round(limit / 2**20, 2),
                             "oom_kills": mem.get("oom_kills", 0), "failcnt": mem.get("failcnt", 0)}
        return out, per_node

    def sessions(self) -> list[NodeSession]:
        """The node sessions of this container that have said hello."""
        return [s for s in self.server.sessions if s.node]

    async def collect_results(self) -> None:
        """Add what each node timed since the last collect (:mod:`rce.node.results`); a node whose
        runtime does not time results (ROS 1 nodes, older runtimes) is skipped."""
        for s in self.sessions():
            try:
                self.results.add(await s.peer.ask(to_node.NodeResults(), RESULTS_TIMEOUT), time.monotonic())
            except RCEError:
                continue

    def stats(self) -> dict:
        """Per-container counters; see :meth:`Environment.op_stats`."""
        ifs = [i.stats() for i in self.interfaces.values()]
        node_subs = [s for sess in self.server.sessions for s in sess.subs.values()]
        iface_subs = [i.sub for i in self.interfaces.values() if getattr(i, "sub", None) is not None]
        nodes = [n.info() for n in self.launcher.nodes.values()]
        use, per_node = self.usage()
        return {
            "cid": self.cid, "user": self.user, "ctag": self.ctag, "group": self.group,
            "sandbox": self.sandbox.status, "limits": dict(self.sandbox.limits), **use,
            "nodes": {"count": len(nodes), "running": sum(n["running"] for n in nodes),
                      "starts": self.launcher.starts, "forked": self.launcher.forks,
                      "restarts": sum(n["restarts"] for n in nodes)},
            "per_node": per_node,
            "results": self.results.stats(time.monotonic()),
            "msgs_in": sum(i["msgs_in"] for i in ifs), "msgs_out": sum(i["msgs_out"] for i in ifs),
            "bytes_in": sum(i["bytes_in"] for i in ifs), "bytes_out": sum(i["bytes_out"] for i in ifs),
            "dropped": {"interfaces": sum(i["dropped"] for i in ifs),
                        "bus": sum(s.dropped for s in node_subs + iface_subs)},
            "interfaces": ifs,
        }


class Environment:
    """The environment of one container group (see the module doc).

    ``env_id``: the task set's id for it; ``runtime_dir``: where container dirs and sockets go;
    ``bind``/``advertise_host``: data-plane listener and the address peers dial; ``sandbox``:
    sandbox kind (:func:`rce_container.sandbox.select`); ``grace``: s between SIGTERM and
    SIGKILL when nodes are stopped; ``direct``: give nodes direct links
    (:mod:`rce_container.direct_routes`; off: ``RCE_DIRECT_LINKS=0``)."""

    def __init__(self, env_id: int, runtime_dir: str | Path, *, socket_dir: str | Path | None = None,
                 bind: str = "127.0.0.1",
                 advertise_host: str | None = None, sandbox: str = "auto",
                 max_frame: int = framing.DEFAULT_MAX_FRAME, grace: float = sandboxes.DEFAULT_GRACE,
                 registry: MessageRegistry | None = None, scope: str | None = None, direct: bool = True,
                 zygote_template: socket.socket | None = None):
        self.env_id = env_id
        self.runtime_dir = Path(runtime_dir)
        self.socket_dir = Path(socket_dir or runtime_dir)
        self.bind, self.advertise_host = bind, advertise_host or bind
        self.sandbox_cls = sandboxes.select(sandbox, check=False)    # the task set has checked it
        self.scope = scope or sandboxes.host_scope("env")
        self.rates = CpuRate()
        self.max_frame, self.grace = max_frame, grace
        self.registry = registry or default_registry()
        self.bus = Bus(f"env{env_id}")
        self.plane = DataPlane(f"env{env_id}", max_frame=max_frame)
        self.containers: dict[int, GroupContainer] = {}
        self.interfaces: dict[int, BusInterface] = {}
        self.direct = DirectRoutes(self) if direct else None
        self.peer: rpc.RpcPeer | None = None
        self.done = asyncio.Event()
        self.t0 = time.monotonic()
        self._closed = False
        # containers' zygotes fork from it (itself forked from the task set's, or exec'd)
        self.template = ZygoteTemplate.for_nodes(self.runtime_dir, zygote_template)

    # -- lifecycle -----------------------------------------------------------------------------
    async def start(self, control_path: str) -> None:
        """Listen on the data plane, dial the task set at ``control_path`` and say hello."""
        try:
            load_package_types(self.registry)
        except MessageError as e:   # one broken package must not take every container down
            log.warning("cannot load the message types of a package", reason=e.message)
        await self.plane.listen(self.bind, 0, self.advertise_host)
        if self.direct is not None:
            self.direct.start()
        self.template.start_soon()
        await self.template.wait_started()      # a spare environment is warm once its template is
        self.peer = await rpc.connect_unix(control_path, ENV_OPS.handlers(self), name="container task set",
                                           on_close=lambda _p: self.done.set(), max_frame=self.max_frame)
        await self.peer.ask(ops.EnvHello(env_id=self.env_id, pid=os.getpid(), data_addr=self.plane.addr))
        log.info("environment ready", env=self.env_id, data_addr=self.plane.addr,
                 sandbox=self.sandbox_cls.kind)

    async def close(self) -> None:
        """Destroy every container (killing their nodes) and close the data plane. Idempotent."""
        if self._closed:
            return
        self._closed = True
        await self._close_containers()
        if self.direct is not None:
            await self.direct.close()
        await self.template.close()
        await self.plane.close()
        if self.peer:
            await self.peer.close()

    def notify_status(self, cid: int, ntag: str, status: str, **fields: Any) -> None:
        """Send ``node_status {cid, ntag, status, ...}`` to the task set."""
        if self.peer:
            self.peer.tell(ops.NodeStatusReport(cid=cid, ntag=ntag, status=status, **fields))

    def notify_interface(self, cid: int, iid: int, tag: str, status: str, reason: str) -> None:
        """Send ``interface_status {cid, iid, tag, status, reason}`` to the task set: how a container
        interface is bridged into its ROS 2 graph (:mod:`rce_container.ros2_graph`)."""
        if self.peer:
            self.peer.tell(ops.InterfaceStatus(cid=cid, iid=iid, tag=tag, status=status, reason=reason))

    def _container(self, cid: int) -> GroupContainer:
        c = self.containers.get(cid)
        if c is None:
            raise NotFound(f"container {cid!r} is not in this environment")
        return c

    def _touch(self) -> None:
        if self.direct is not None:
            self.direct.touch()

    async def drop_interface(self, iface: BusInterface) -> None:
        self.interfaces.pop(iface.iid, None)
        c = self.containers.get(iface.cid)
        if c:
            c.interfaces.pop(iface.iid, None)
        await iface.stop()

    # -- containers ----------------------------------------------------------------------------
    @ENV_OPS.op("add_container", args=ops.EnvAddContainer)
    async def op_add_container(self, args: ops.EnvAddContainer) -> dict:
        """``{cid, ctag, user, group, limits}`` -> ``{data_addr, sandbox, socket}``."""
        cid = args.cid
        c = self.containers.get(cid)
        if c is None:
            deadline = args.deadline_ms
            c = GroupContainer(self, cid, args.ctag or f"c{cid}", args.user, args.group, args.limits or {},
                               deadline if deadline is not None and deadline > 0 else None, args.handoff)
            self.containers[cid] = c
            try:
                await c.start()
            except BaseException:
                self.containers.pop(cid, None)
                await c.close()
                raise
            log.info("container added", env=self.env_id, cid=cid, ctag=c.ctag, socket=c.socket)
        return {"data_addr": self.plane.addr, "sandbox": c.sandbox.status, "socket": c.socket}

    @ENV_OPS.op("remove_container", args=ops.EnvRemoveContainer)
    async def op_remove_container(self, args: ops.EnvRemoveContainer) -> dict:
        """``{cid}``: kill the container's nodes, drop its interfaces and socket."""
        c = self._container(args.cid)
        del self.containers[c.cid]
        await c.close()
        log.info("container removed", env=self.env_id, cid=c.cid, ctag=c.ctag)
        return {}

    @ENV_OPS.op("shutdown", args=ops.EnvShutdown)
    async def op_shutdown(self, args: ops.EnvShutdown) -> dict:
        """Destroy every container; the task set closes the link afterwards."""
        await self._close_containers()
        return {}

    async def _close_containers(self) -> None:
        """Close every container at once; one that fails to close is logged, the others go on."""
        cs = list(self.containers.values())
        results = await asyncio.gather(*(c.close() for c in cs), return_exceptions=True)
        self.containers.clear()
        for c, r in zip(cs, results, strict=True):
            if isinstance(r, Exception):
                log.error("container did not close cleanly", env=self.env_id, cid=c.cid, exc_info=r)

    @ENV_OPS.op("resize_container", args=ops.EnvResizeContainer)
    async def op_resize_container(self, args: ops.EnvResizeContainer) -> dict:
        """``{cid, limits: {cpu, memory, size, bandwidth}}`` -> ``{sandbox, limits, cgroup?}``:
        new limits for the container's sandbox, written into its cgroup while its nodes keep
        running (recorded only by the unconfined sandbox); 0 removes a limit. ``cgroup``: the
        limit files as the kernel now reports them."""
        c = self._container(args.cid)
        await c.sandbox.resize(args.limits or {})
        log.info("container resized", cid=c.cid, ctag=c.ctag, limits=c.sandbox.limits)
        info = c.sandbox.info()
        return {"sandbox": c.sandbox.status, "limits": c.sandbox.limits,
                **({"cgroup": info["cgroup"]["files"]} if "cgroup" in info else {})}

    # -- nodes ---------------------------------------------------------------------------------
    @ENV_OPS.op("add_node", args=ops.EnvAddNode)
    async def op_add_node(self, args: ops.EnvAddNode) -> dict:
        """``{cid, ntag, pkg, exe, args, name, namespace, respawn}`` -> ``{ntag, pid}``. A node of a
        ROS 1 package first gets its container's ROS 1 graph (:mod:`rce_container.ros1_graph`), one of
        a ROS 2 package its ROS 2 graph (:mod:`rce_container.ros2_graph`). The launcher and the graphs
        keep the node's spec as the wire has it (a repeated identical spec is no new node)."""
        c = self._container(args.cid)
        spec = args.wire()
        graph = c.ros1
        kind = await c.ros1.prepare(spec)
        if kind is None:
            graph, kind = c.ros2, await c.ros2.prepare(spec)
        try:
            return await c.launcher.add(spec, kind)
        finally:
            if kind is not None and args.ntag not in c.launcher.nodes:
                await graph.node_gone(args.ntag)

    @ENV_OPS.op("remove_node", args=ops.EnvRemoveNode)
    async def op_remove_node(self, args: ops.EnvRemoveNode) -> dict:
        """``{cid, ntag}``: stop the node (SIGTERM, then SIGKILL after the grace period)."""
        c = self._container(args.cid)
        await c.launcher.remove(args.ntag)
        await c.ros1.node_gone(args.ntag)
        await c.ros2.node_gone(args.ntag)
        return {}

    @ENV_OPS.op("logs", args=ops.EnvLogs)
    async def op_logs(self, args: ops.EnvLogs) -> dict:
        """``{cid, ntag, lines?}`` -> ``{stdout: [line...], stderr: [line...]}`` (last lines)."""
        return self._container(args.cid).launcher.logs(args.ntag, LOG_LINES if args.lines is None else args.lines)

    # -- parameters ----------------------------------------------------------------------------
    @ENV_OPS.op("set_param", args=ops.EnvSetParam)
    async def op_set_param(self, args: ops.EnvSetParam) -> dict:
        """``{cid, name, value}``: set a parameter (global name) on the group's bus."""
        self._container(args.cid)
        self.bus.set_param(resolve(args.name, "/"), args.value)
        await self._sync_graphs()
        return {}

    @ENV_OPS.op("delete_param", args=ops.EnvDeleteParam)
    async def op_delete_param(self, args: ops.EnvDeleteParam) -> dict:
        """``{cid, name}``: delete a parameter (and its subtree). NotFound if not set."""
        self._container(args.cid)
        self.bus.delete_param(resolve(args.name, "/"))
        await self._sync_graphs()
        return {}

    async def _sync_graphs(self) -> None:
        """Copy the bus's parameters into the ROS 1 graphs of the group's containers, and set them
        on the running nodes of their ROS 2 graphs, now."""
        await asyncio.gather(*(g.sync() for c in self.containers.values() for g in (c.ros1, c.ros2)))

    @ENV_OPS.op("get_param", args=ops.EnvGetParam)
    async def op_get_param(self, args: ops.EnvGetParam) -> dict:
        """``{cid, name}`` -> ``{value}``: a parameter's value (a subtree as an object), for a
        rosbridge client's ``/rosapi/get_param``. NotFound if not set."""
        self._container(args.cid)
        return {"value": self.bus.get_param(resolve(args.name, "/"))}

    # -- interfaces ----------------------------------------------------------------------------
    @ENV_OPS.op("add_interface", args=ops.EnvAddInterface)
    async def op_add_interface(self, args: ops.EnvAddInterface) -> dict:
        """``{cid, iid, tag, itype, cls, addr?}`` -> ``{iid, addr}``: create and start a
        container-side interface. Idempotent for the same spec; MessageError for an unknown class."""
        c = self._container(args.cid)
        iid = args.iid
        old = self.interfaces.get(iid)
        iface = make_interface(self.plane, self.bus, c.cid, iid, args.tag, args.itype, args.cls, args.addr,
                               self.registry)
        if old is not None:
            if (old.cid, old.kind, old.cls, old.addr) == (c.cid, iface.kind, iface.cls, iface.addr):
                return {"iid": iid, "addr": old.addr}
            raise RequestError(f"interface id {iid} is already in use by {old.tag!r}")
        await iface.start()
        self.interfaces[iid] = c.interfaces[iid] = iface
        log.info("interface added", cid=c.cid, iid=iid, tag=iface.tag, kind=iface.kind, cls=iface.cls,
                 addr=iface.addr)
        return {"iid": iid, "addr": iface.addr}

    def _interface(self, cid: int, iid: int) -> BusInterface:
        c = self._container(cid)
        iface = c.interfaces.get(iid)
        if iface is None:
            raise NotFound(f"interface {iid!r} does not exist in container {c.ctag!r}")
        return iface

    @ENV_OPS.op("remove_interface", args=ops.EnvRemoveInterface)
    async def op_remove_interface(self, args: ops.EnvRemoveInterface) -> dict:
        """``{cid, iid}``: stop and drop an interface (its connections go with it)."""
        await self.drop_interface(self._interface(args.cid, args.iid))
        return {}

    @ENV_OPS.op("data_key", args=ops.EnvDataKey)
    async def op_data_key(self, args: ops.EnvDataKey) -> dict:
        """``{key}`` (hex; from the task set, once, right after ``hello``): this environment's data
        key, derived from the cluster key and its data address (:mod:`rce.transport.cluster_auth`); peers'
        grants are checked with it."""
        if self.plane.data_key is not None:
            raise RequestError("this environment has its data key already")
        try:
            self.plane.data_key = bytes.fromhex(args.key)
        except ValueError:
            raise RequestError("data_key: 'key' must be hex digits") from None
        return {}

    @ENV_OPS.op("connect", args=ops.EnvConnect)
    async def op_connect(self, args: ops.EnvConnect) -> dict:
        """``{cid, iid, peer_iid, peer_addr, token, fence?, peer_cls?}`` -> ``{fenced}``: connect an
        interface to a peer interface (``token``: the master's credential for sending to it); a
        connection pointed at a moved container's new copy fences its old one with ``fence`` (the
        move's id), ``fenced`` fences sent (:meth:`rce.transport.interface.Interface.connect`);
        ``peer_cls``: the peer's class (one of the other ROS: this end converts what it sends).
        A ROS relay of the container that has not bridged the interface's name yet looks at its
        graphs first: a node's endpoint that came up since its last poll is bridged before the
        connection carries anything (an action's feedback wired before its goal, the goal sent as
        soon as it is wired, finds its bridge made)."""
        iface = self._interface(args.cid, args.iid)
        c = self._container(args.cid)
        for graph in (c.ros1, c.ros2):
            if graph.running and not bridged(graph.relay_stats, iface.addr):
                await graph.sync()
        fenced = iface.connect(args.peer_iid, args.peer_addr, token_of(args.token), args.fence, args.peer_cls)
        self._touch()
        return {"fenced": fenced}

    @ENV_OPS.op("disconnect", args=ops.EnvDisconnect)
    async def op_disconnect(self, args: ops.EnvDisconnect) -> dict:
        """``{cid, iid, peer_iid}``: drop one connection (no error if absent)."""
        self._interface(args.cid, args.iid).disconnect(args.peer_iid)
        self._touch()
        return {}

    # -- bus tools -----------------------------------------------------------------------------
    @ENV_OPS.op("describe", args=ops.EnvDescribe)
    async def op_describe(self, args: ops.EnvDescribe) -> dict:
        """``{cid}`` -> :meth:`Bus.describe` of the group's bus, plus ``launched``: the
        container's nodes as the launcher sees them (``ntag, pid, running, restarts, argv``), and
        ``handoff``: the names of its nodes that hand their state over when it moves."""
        c = self._container(args.cid)
        return {**self.bus.describe(), "launched": [n.info() for n in c.launcher.nodes.values()],
                "handoff": sorted(s.node for s in c.sessions() if s.handoff)}

    @ENV_OPS.op("bus_publish", args=ops.EnvBusPublish)
    async def op_bus_publish(self, args: ops.EnvBusPublish) -> dict:
        """``{cid, topic, type, msg}`` -> ``{delivered}``: publish a JSON message once."""
        self._container(args.cid)
        topic = resolve(args.topic, "/")
        typename = self.registry.msg_type(args.type)
        payload = self.registry.json_to_bytes(typename, args.msg or {})
        owner = "admin:bus_publish"
        t = self.bus.advertise(topic, wire_name(typename), owner)
        try:
            return {"delivered": self.bus.publish(t, payload)}
        finally:
            self.bus.unadvertise(topic, owner)

    @ENV_OPS.op("bus_call", args=ops.EnvBusCall)
    async def op_bus_call(self, args: ops.EnvBusCall) -> Any:
        """``{cid, service, request, timeout}`` -> the JSON response. NotFound for an absent
        service, Timeout after ``timeout`` s (default :data:`BUS_CALL_TIMEOUT`), the provider's
        error otherwise."""
        self._container(args.cid)
        name = resolve(args.service, "/")
        s = self.bus.services.get(name)
        if s is None:
            raise NotFound(f"service {name!r} is not provided in container {args.cid}")
        req_t, resp_t = self.registry.srv_types(s.type)
        payload = self.registry.json_to_bytes(req_t, args.request or {})
        resp = await self.bus.call_service(name, payload, None, args.timeout or BUS_CALL_TIMEOUT)
        return self.registry.bytes_to_json(resp_t, resp)

    @ENV_OPS.op("bus_sample", args=ops.EnvBusSample)
    async def op_bus_sample(self, args: ops.EnvBusSample) -> list:
        """``{cid, topic, count, timeout, type?}`` -> up to ``count`` JSON messages received on
        ``topic`` within ``timeout`` s. The type comes from the topic (or ``type``); NotFound
        if neither is known."""
        self._container(args.cid)
        topic = resolve(args.topic, "/")
        t = self.bus.topics.get(topic)
        wire = t.type if t is not None else args.type
        if not wire:
            raise NotFound(f"topic {topic!r} does not exist; give its 'type' to wait for it")
        typename = self.registry.msg_type(wire)
        count = max(1, min(args.count or 1, MAX_SAMPLE))
        timeout = max(0.0, min(args.timeout or BUS_SAMPLE_TIMEOUT, MAX_SAMPLE_TIMEOUT))
        got: list[bytes] = []
        full = asyncio.Event()

        def deliver(payload: bytes) -> bool:
            if len(got) < count:
                got.append(bytes(payload))
                if len(got) >= count:
                    full.set()
            return True
        sub = self.bus.subscribe(topic, wire_name(typename), deliver, "admin:bus_sample", count)
        try:
            async with asyncio.timeout(timeout):
                await full.wait()
        except TimeoutError:
            pass
        finally:
            self.bus.unsubscribe(sub)
        return [self.registry.bytes_to_json(typename, p) for p in got]

    # -- status --------------------------------------------------------------------------------
    @ENV_OPS.op("state_out", args=ops.EnvStateOut)
    async def op_state_out(self, args: ops.EnvStateOut) -> dict:
        """``{cid}`` -> ``{states: {node name: base64 | None}}``: each node's state, from the nodes
        that hand theirs over (:meth:`rce.node.Node.handoff`; None: no hook, or it failed: logged).
        Each node hands it out once its inputs so far are handled."""
        c = self._container(args.cid)
        states: dict[str, str | None] = {}
        for s in c.sessions():
            try:
                r = await s.peer.ask(to_node.NodeStateOut(), STATE_TIMEOUT)
            except RCEError as e:
                log.warning("node's state not handed out", cid=c.cid, node=s.node, reason=str(e))
                r = None
            states[s.node] = r.get("state") if isinstance(r, dict) else None
        return {"states": states}

    @ENV_OPS.op("drain", args=ops.EnvDrain)
    async def op_drain(self, args: ops.EnvDrain) -> dict:
        """``{cid, fence, expect: [[src, dst, n]...], timeout}`` -> ``{complete, missing, unsettled,
        unflushed, waited_s}``: a moved container's old copy finishes (:mod:`rce_master.placement.mover`). It waits
        until ``n`` fences ``fence`` of each connection ``src -> dst`` came (nothing more is on its
        way to it), its nodes handled every input that came before them (``settle``), and each peer
        its interfaces send to acknowledged the end of their stream (every output reached it);
        at most ``timeout`` s (s) in all, then it says what did not happen: ``missing`` fences
        ``[[src, dst, n]...]``, ``unsettled`` nodes, ``unflushed`` peer addresses."""
        c = self._container(args.cid)
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        end = t0 + max(0.0, args.timeout or 0.0)
        fid = args.fence
        expect = {(a, b): n for a, b, n in args.expect if n > 0}
        missing = await self.plane.wait_fences(fid, expect, end - loop.time())
        unsettled = []
        for s in c.sessions():
            try:
                left = max(0.05, end - loop.time())
                r = await s.peer.ask(to_node.NodeSettle(timeout=left), left + 1.0)
                if isinstance(r, dict) and r.get("unflushed"):
                    unsettled.append(s.node)
            except RCEError as e:
                log.warning("node not settled before its copy goes", cid=c.cid, node=s.node, reason=str(e))
                unsettled.append(s.node)
        addrs = {a for iface in c.interfaces.values() for a in iface.peers.values()}
        unflushed = await self.plane.flush(addrs, max(0.05, end - loop.time()))
        self.plane.fences.pop(fid, None)
        return {"complete": not (missing or unsettled or unflushed),
                "missing": [[a, b, n] for (a, b), n in missing.items()], "unsettled": unsettled,
                "unflushed": sorted(unflushed), "waited_s": round(loop.time() - t0, 3)}

    @ENV_OPS.op("state_in", args=ops.EnvStateIn)
    async def op_state_in(self, args: ops.EnvStateIn) -> dict:
        """``{cid, states: {node name: base64 | None}}``: each node of a move's new copy takes its
        state (or starts fresh) and then the inputs it held; ``{nodes: [names that took a state]}``."""
        c = self._container(args.cid)
        states = args.states or {}
        took = []
        for s in c.sessions():
            try:
                r = await s.peer.ask(to_node.NodeStateIn(state=states.get(s.node)), STATE_TIMEOUT)
            except RCEError as e:
                log.warning("node did not take its state", cid=c.cid, node=s.node, reason=str(e))
                continue
            if isinstance(r, dict) and r.get("took"):
                took.append(s.node)
        return {"nodes": took}

    @ENV_OPS.op("stats", args=ops.EnvStats)
    async def op_stats(self, args: ops.EnvStats) -> dict:
        """``{cid}`` -> counters of the container and of its group::

            {cid, user, ctag, group, sandbox, limits: {cpu?, memory?, size?, bandwidth?},
             cpu_percent, cpu_seconds, rss_mib, processes,     # every process of the container (cpu s: all time)
             memory?: {usage_mib, limit_mib, oom_kills, failcnt},   # its memory cgroup, when it has one
             cpu?: {periods, throttled, throttled_s},          # CPU-limit enforcement periods, how many hit it
             nodes: {count, running, starts, forked (of the starts, by the zygote), restarts},
             per_node: {ntag: {ntag, name, pid, running, restarts, last_exit, cpu_percent, rss_mib,
                               processes, connected, msgs_in, msgs_out, bytes_in, bytes_out, dropped}},
             results: {results, misses, deadline_ms, p50_ms, p99_ms, max_ms, recent_p90_ms, unseen},
                                   # its nodes' outputs timed from the inputs that caused them (rce.node.results)
             msgs_in, msgs_out, bytes_in, bytes_out,          # over the container's interfaces
             dropped: {interfaces, bus},                       # refused by peer links / bus subscriptions
             interfaces: [{iid, tag, kind, cls, addr, peers, msgs_in, msgs_out, bytes_in, bytes_out, dropped}],
             sandbox_info: {kind, limits, init_pid?, namespaces?, uid?, cgroup?: {version, dirs, files}},
             environment: {env_id, pid, rss_mib, cpu_percent, containers, data_addr,
                           bus: {topics, services, refused, nodes, messages, bytes, dropped},
                                 # refused: connections to the group's bus sockets turned away
                           dataplane: {msgs_in, msgs_out, bytes_in, bytes_out, dropped, links},
                           zygote_template: {pid, forked, running}},   # forked: from the task set's
             ros1?: {master_uri, running, nodes, pids, relay},  # while it has ROS 1 nodes (Ros1Graph.info)
             ros2?: {domain_id, running, nodes, pids, relay}}   # while it has ROS 2 nodes (Ros2Graph.info)
        """
        c = self._container(args.cid)
        await c.ros1.sync()
        await c.ros2.sync("stats")
        if self.direct is not None:
            await self.direct.collect()
        await c.collect_results()
        topics = self.bus.topics.values()
        env_mem = measure([os.getpid()])
        return {**c.stats(), "sandbox_info": c.sandbox.info(), "environment": {
            "rss_mib": round(env_mem["rss_bytes"] / 2**20, 2),
            "cpu_percent": round(self.rates.percent("environment", env_mem["cpu_seconds"], self.t0), 1),
            "env_id": self.env_id, "pid": os.getpid(), "containers": len(self.containers),
            "data_addr": self.plane.addr,
            "bus": {"topics": len(self.bus.topics), "services": len(self.bus.services),
                    "refused": sum(c.server.refused for c in self.containers.values()),
                    "nodes": len(self.bus.nodes), "messages": sum(t.messages for t in topics),
                    "bytes": sum(t.bytes for t in topics), "dropped": sum(t.dropped for t in topics)},
            "dataplane": self.plane.stats(),
            "direct": self.direct.stats() if self.direct is not None else {"enabled": False},
            "zygote_template": {"pid": self.template.pid, "forked": self.template.forked,
                                "running": self.template.alive}},
            **({"ros1": c.ros1.info()} if c.ros1.ntags else {}),
            **({"ros2": c.ros2.info()} if c.ros2.ntags else {})}


def given_socket(fd: int | None) -> socket.socket | None:
    """The socket on descriptor ``fd`` the task set gave (not inherited by what this process execs)."""
    if fd is None:
        return None
    os.set_inheritable(fd, False)
    return socket.socket(fileno=fd)


async def run(args: argparse.Namespace) -> int:
    """Start the environment, serve until the link closes or a signal; returns the exit code."""
    env = Environment(args.env_id, args.runtime_dir, socket_dir=args.socket_dir, bind=args.bind,
                      advertise_host=args.advertise_host, sandbox=args.sandbox, max_frame=args.max_frame,
                      grace=args.grace, scope=args.scope, direct=os.environ.get("RCE_DIRECT_LINKS", "1") != "0",
                      zygote_template=given_socket(args.zygote_template_fd))
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, env.done.set)
    t0 = time.monotonic()
    try:
        await env.start(args.control)
    except (OSError, RCEError) as e:
        log.error("environment failed to start", env=args.env_id, reason=str(e))
        await env.close()
        return 1
    log.debug("environment started", env=args.env_id, ms=round((time.monotonic() - t0) * 1000, 1))
    await env.done.wait()
    log.info("environment stopping", env=args.env_id)
    await env.close()
    return 0


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m rce_container.environment",
                                description="rce environment of one container group (started by rce-container)")
    p.add_argument("--control", required=True, help="Unix socket of the container task set")
    p.add_argument("--env-id", type=int, required=True)
    p.add_argument("--runtime-dir", required=True)
    p.add_argument("--socket-dir", default=None, help="where bus sockets go (default: --runtime-dir)")
    p.add_argument("--bind", default="127.0.0.1")
    p.add_argument("--advertise-host", default=None)
    p.add_argument("--sandbox", default="auto")
    p.add_argument("--scope", default=None, help="the task set's sandbox scope (cgroup directory rce/NAME-PID)")
    p.add_argument("--max-frame", type=int, default=framing.DEFAULT_MAX_FRAME)
    p.add_argument("--grace", type=float, default=sandboxes.DEFAULT_GRACE,
                   help="s between SIGTERM and SIGKILL for nodes")
    p.add_argument("--zygote-template-fd", type=int, default=None,
                   help="descriptor of this environment's zygote template, forked by the task set's "
                        "(default: exec one)")
    args = p.parse_args(argv)
    setup_logging()
    sys.exit(run_loop(run(args)))


if __name__ == "__main__":
    main()
