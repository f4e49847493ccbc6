"""The container task set: registers with the master and runs its containers' environments.

Links (docs/INTERNALS.md): this process dials the master's control port and registers
``{kind: "container", name, host, sandbox, capacity}``. When the master goes away, everything
here keeps running; the link dials again and re-registers with its ``tid`` and a report of its
containers and their nodes (:class:`rce.transport.masterlink.MasterLink`; node statuses meanwhile wait in
its bounded backlog). It listens on a Unix control socket
(``RUNTIME/host.sock``) that its environment processes dial. The master never talks to an
environment: every container op arrives here, names its ``cid``, and is relayed to the
environment that serves the container's group. ``node_status`` and ``interface_status`` (what
a container's ROS 2 relay cannot bridge) notifications travel the other way (environment -> here
-> master).

Groups: containers of one user created with the same ``group`` share one environment (one
bus); a container without a group gets an environment of its own. An environment is spawned
on the group's first ``create_container`` and stopped with its last container. An environment
that dies takes its containers with it: each is reported to the master (``container_lost``),
which creates it again, under a new cid, on this host if it can (docs/INTERNALS.md, "Container
failover").
"""
from __future__ import annotations

import asyncio
import hashlib
import itertools
import json
import os
import shutil
import signal
import socket
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import psutil
from prometheus_client import generate_latest

from rce.contract import environment as env_ops
from rce.contract import host as ops
from rce.contract.base import OpArgs
from rce.transport import framing

from rce.transport import rpc
from rce.transport.cluster_auth import ClusterKey, peer_pid
from rce.plumbing.errors import NotFound, RCEError, RequestError, Timeout, Unavailable
from rce.transport.link import STREAM_LIMIT
from rce.plumbing.log import get_logger
from rce.plumbing.metrics_http import MetricsServer
from rce.contract import master as to_master
from rce.transport.masterlink import MASTER_PORT, MasterLink, parse_masters
from rce.transport.op_table import OpTable
from rce.plumbing.pending import PendingCalls
from rce.protocol.zones import CLOUD, Zone
from rce_container.cgroups import host_cpus
from rce.plumbing.tasks import Tasks
from rce_container import metrics
from rce_container import sandbox as sandboxes
from rce_container.env_template_client import EnvTemplate
from rce_container.env_layout import BUS_CALL_TIMEOUT, MAX_SOCKET_PATH, container_paths
from rce_container.usage import measure
from rce_container.zygote_client import ForkedChild, ZygoteTemplate

log = get_logger("rce.container")
ENV_TIMEOUT = 30.0         # s a new environment has to say hello (start Python, load packages, listen)
RELAY_TIMEOUT = 30.0       # s an op relayed to an environment waits for its answer
REPLY_MARGIN = 10.0        # s on top of an op's own time limit (a bus_call's timeout, the grace period of
                           # stopping nodes) for the environment to answer it
SMALL_HOST_CPU = 1.0       # cores below which a host starts a spare only while it runs no container: a start
                           # (an interpreter and its imports, ~0.5 core-s) on a robot's computer capped at 0.3
                           # cores takes the CPU of the container its last spare went to for seconds
EXIT_MARGIN = 5.0          # s on top of the grace period for an environment to exit before it is killed

CONTROL_SOCKET = "host.sock"

#: The ops the master sends a container task set: its own, and those relayed, unchanged, to the
#: environment that serves the op's ``cid`` (each of them an op of ``rce_container.environment.ENV_OPS``).
HOST_OPS = OpTable("master -> container task set")
#: What an environment tells its container task set.
FROM_ENV_OPS = OpTable("environment -> container task set")


def socket_dir_for(runtime_dir: Path) -> Path:
    """Where the Unix sockets go: ``runtime_dir`` itself, or, when its path is too long for a
    socket path (``c<cid>/bus.sock`` must fit in 107 bytes), a short directory in the system
    temp dir derived from it."""
    if len(str(runtime_dir / "c0000000000" / "bus.sock").encode()) <= MAX_SOCKET_PATH:
        return runtime_dir
    digest = hashlib.sha1(str(runtime_dir.resolve()).encode()).hexdigest()[:12]
    return Path(tempfile.gettempdir()) / f"rce-{digest}"


@dataclass(eq=False)
class EnvHandle:
    """The task set's view of one environment process."""
    env_id: int
    key: tuple | None              # the group it serves; None while it is a warm spare
    proc: asyncio.subprocess.Process | ForkedChild | None = None   # exec'd, or forked by the template
    peer: rpc.RpcPeer | None = None
    data_addr: str = ""
    cids: set[int] = field(default_factory=set)
    stopping: bool = False
    exit_code: int | None = None
    started: float = 0.0          # monotonic s, spawn time

    @property
    def alive(self) -> bool:
        return self.exit_code is None and self.peer is not None and not self.peer.closed.is_set()


@dataclass(eq=False)
class ContainerRecord:
    """A container this task set hosts: ids, its environment and its known nodes (nTag -> pid,
    and nTag -> last status reported: ``starting``, ``started``, ``exited``, ``respawning``)."""
    cid: int
    user: str
    ctag: str
    group: str | None
    env: EnvHandle
    result: dict
    nodes: dict[str, int | None] = field(default_factory=dict)
    statuses: dict[str, env_ops.NodeStatus] = field(default_factory=dict)


class ContainerHost:
    """The container task set (``rce-container``).

    ``master``: the master's control address, or several (``HOST[:PORT][,HOST[:PORT]...]``, see
    :func:`rce.transport.masterlink.parse_masters`; ``master_port`` where none is given); ``name``: this task
    set's name;
    ``bind``: where environments' data planes listen; ``advertise_host``: the address peers
    reach them by; ``runtime_dir``: sockets and per-container dirs (created if missing;
    removed on exit only if ``own_runtime_dir``); ``sandbox``: sandbox kind or ``"auto"``;
    ``env_timeout``: s to wait for a new environment's hello; ``grace``: s between SIGTERM
    and SIGKILL for nodes; ``warm``: idle environments kept started, so that a new group's
    ``create_container`` does not wait for a Python process to start (one taken is replaced at
    once; on a host of less than :data:`SMALL_HOST_CPU` cores only once it runs no container);
    ``metrics_port``: serve
    Prometheus ``/metrics`` on ``bind`` at this port (0: an ephemeral one, read back from
    ``self.metrics_port``; None: no metrics server); ``cluster_key``: proved to the master on every
    link (:mod:`rce.transport.cluster_auth`); each environment gets only its own data key derived from it;
    ``zone``: where this host stands (:mod:`rce.protocol.zones`), told to the master on registration."""

    def __init__(self, master: str | list[str], master_port: int = MASTER_PORT, *, name: str | None = None,
                 bind: str = "127.0.0.1", advertise_host: str | None = None, runtime_dir: str | Path,
                 own_runtime_dir: bool = False, sandbox: str = "auto",
                 max_frame: int = framing.DEFAULT_MAX_FRAME, env_timeout: float = ENV_TIMEOUT,
                 grace: float = sandboxes.DEFAULT_GRACE,
                 warm: int = 1, metrics_port: int | None = None, cluster_key: ClusterKey,
                 zone: Zone = CLOUD):
        self.masters = parse_masters(master, master_port)
        self.cluster_key = cluster_key
        self.zone = zone
        self.name = name or socket.gethostname()
        self.bind, self.advertise_host = bind, advertise_host or bind
        self.runtime_dir = Path(runtime_dir)
        self.own_runtime_dir = own_runtime_dir
        self.sandbox_cls = sandboxes.select(sandbox)
        self.scope = sandboxes.host_scope(self.name)
        self.metrics_port = metrics_port
        self._http: MetricsServer | None = None
        self.max_frame, self.env_timeout, self.grace = max_frame, env_timeout, grace
        self.warm = max(0, warm)
        self.spares: list[EnvHandle] = []
        self.env_template = EnvTemplate()      # environments fork from it (exec'd when it cannot)
        # environments' zygote templates fork from it (an environment execs its own when it cannot)
        self.zygote_template = ZygoteTemplate.for_nodes(self.runtime_dir)
        self._spare_tasks: list[asyncio.Task] = []
        self.capacity = host_cpus()            # cores this host may use
        self.socket_dir = socket_dir_for(self.runtime_dir)
        self.control_path = str(self.socket_dir / CONTROL_SOCKET)
        self.master: MasterLink | None = None
        self.containers: dict[int, ContainerRecord] = {}
        self.groups: dict[tuple, EnvHandle] = {}
        self.envs: set[EnvHandle] = set()
        self.stopped = asyncio.Event()
        self.exit_code = 0
        self._server: asyncio.AbstractServer | None = None
        self._env_ids = itertools.count(1)
        self._hellos = PendingCalls("new environments")     # env_id -> (peer, hello args)
        self._group_locks: dict[tuple, asyncio.Lock] = {}
        self.tasks = Tasks("container task set")
        self._closing = False

    @property
    def tid(self) -> Any:
        """This task set's id at the master (None before the first registration)."""
        return self.master.tid if self.master else None

    # -- lifecycle -----------------------------------------------------------------------------
    async def start(self) -> Any:
        """Listen for environments, dial the master and register (retried with backoff until a
        master takes this task set); returns the ``tid``. Raises :class:`RCEError` if the master
        refuses this task set."""
        self.runtime_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
        self.socket_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
        if os.path.exists(self.control_path):
            os.unlink(self.control_path)
        self._server = await asyncio.start_unix_server(self._accept_env, self.control_path, limit=STREAM_LIMIT)
        os.chmod(self.control_path, 0o600)
        self.env_template.start_soon()        # imports while the task set registers; spares fork from it
        self.zygote_template.start_soon()
        how = await asyncio.to_thread(self.sandbox_cls.prepare_host, self.scope)
        log.info("sandbox", kind=self.sandbox_cls.kind, uses=how, scope=self.scope)
        if self.metrics_port is not None:
            await self._start_metrics()
        info = {"kind": "container", "name": self.name, "host": self.advertise_host, "sandbox": self.sandbox_cls.kind,
                "capacity": {"cpu": round(self.capacity, 3), "memory": psutil.virtual_memory().total // 2**20},
                "zone": str(self.zone), "zone_user": self.zone.user}
        self.master = MasterLink(self.masters, HOST_OPS.handlers(self), info, report=self._report,
                                 on_registered=self._obey, max_frame=self.max_frame, cluster_key=self.cluster_key)
        await self.master.start()
        log.info("container task set up", tid=self.tid, name=self.name, sandbox=self.sandbox_cls.kind,
                 runtime_dir=str(self.runtime_dir))
        self._refill_spares()
        return self.tid

    def stop(self, code: int = 0) -> None:
        """Ask :meth:`run` to shut down with exit ``code``."""
        self.exit_code = self.exit_code or code
        self.stopped.set()

    async def close(self) -> None:
        """Destroy every container (killing every node), close the links, remove the sockets."""
        if self._closing:
            return
        self._closing = True
        envs = list(self.envs)
        for env, r in zip(envs, await asyncio.gather(*(self._stop_env(e) for e in envs), return_exceptions=True),
                          strict=True):
            if isinstance(r, Exception):
                log.error("environment did not stop cleanly", env=env.env_id, exc_info=r)
        self.containers.clear()
        await self.env_template.close()
        await self.zygote_template.close()
        await asyncio.to_thread(self.sandbox_cls.cleanup_host, self.scope)   # anything a crash left behind
        if self._http is not None:
            await self._http.close()
        if self.master:
            await self.master.close()
        if self._server:
            self._server.close()
        try:
            os.unlink(self.control_path)
        except FileNotFoundError:
            pass
        if self.socket_dir != self.runtime_dir:
            shutil.rmtree(self.socket_dir, ignore_errors=True)
        if self.own_runtime_dir:
            shutil.rmtree(self.runtime_dir, ignore_errors=True)
        await self.tasks.cancel_all()
        log.info("container task set stopped", name=self.name)

    async def run(self) -> int:
        """Serve until :meth:`stop`, then :meth:`close`; the exit code."""
        await self.stopped.wait()
        await self.close()
        return self.exit_code

    # -- environments --------------------------------------------------------------------------
    async def _accept_env(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = rpc.RpcPeer(reader, writer, name="environment", max_frame=self.max_frame)
        peer.handlers.update(FROM_ENV_OPS.handlers(self, context=peer))
        peer.start()

    @FROM_ENV_OPS.op("hello", args=env_ops.EnvHello)
    async def _op_env_hello(self, peer: rpc.RpcPeer, args: env_ops.EnvHello) -> dict:
        """An environment this task set started is ready (:meth:`_spawn_env` waits for it)."""
        if not self._hellos.settle(args.env_id, (peer, args)):
            raise RequestError(f"unexpected environment {args.env_id!r}")
        return {}

    @FROM_ENV_OPS.op("node_status", args=env_ops.NodeStatusReport)
    async def _op_env_node_status(self, _peer: rpc.RpcPeer, args: env_ops.NodeStatusReport) -> None:
        """A node's status: kept for the report of a re-registration, and passed on to the master."""
        c = self.containers.get(args.cid)
        if c is not None:
            if args.status == env_ops.NodeStatus.STARTED:
                c.nodes[args.ntag] = args.pid
            elif args.status in (env_ops.NodeStatus.EXITED, env_ops.NodeStatus.RESPAWNING) and args.ntag in c.nodes:
                c.nodes[args.ntag] = None           # (not a node removed meanwhile)
            if args.ntag in c.nodes:
                c.statuses[args.ntag] = args.status
        self._to_master(args)

    @FROM_ENV_OPS.op("interface_status", args=env_ops.InterfaceStatus)
    async def _op_env_interface_status(self, _peer: rpc.RpcPeer, args: env_ops.InterfaceStatus) -> None:
        """How an interface is bridged into its container's ROS 2 graph: passed on to the master."""
        self._to_master(args)

    def _refill_spares(self) -> None:
        """Start environments in the background until ``warm`` spares are ready or starting."""
        while not self._closing and len(self.spares) + len(self._spare_tasks) < self.warm:
            t = self.tasks.spawn(self._start_spare(), name="spare environment")
            self._spare_tasks.append(t)
            t.add_done_callback(self._spare_tasks.remove)

    def _refill_after_take(self) -> None:
        """A spare was taken: refill at once, but on a small host only once it runs no container
        (``op_destroy_container``); a create_container meanwhile that finds no spare starts its
        environment itself, as without spares."""
        if self.capacity >= SMALL_HOST_CPU:
            self._refill_spares()

    async def _start_spare(self) -> None:
        try:
            env = await self._spawn_env(None)
        except RCEError as e:
            log.warning("could not start a spare environment", reason=e.message)
            return
        if self._closing:
            await self._stop_env(env)
        else:
            self.spares.append(env)

    async def _take_spare(self) -> EnvHandle | None:
        """A ready spare environment, waiting for one that is starting (it started earlier than
        a new one would); None if there is none."""
        while True:
            while self.spares:
                env = self.spares.pop(0)
                if env.alive:
                    return env
            if not self._spare_tasks:
                return None
            await asyncio.wait([self._spare_tasks[0]])

    async def _fork_zygote_template(self) -> socket.socket | None:
        """A new environment's zygote template, forked from the task set's (the environment's end
        of its socket); None when it is not running: the environment then execs its own, and a
        dead one is started again for the next environment."""
        template = self.zygote_template
        if await template.wait_started():
            try:
                return template.fork_template()
            except OSError as e:
                log.warning("the zygote template did not fork", reason=str(e))
        if template.lost and template is self.zygote_template and not self._closing:
            self.zygote_template = ZygoteTemplate.for_nodes(self.runtime_dir)
            self.zygote_template.start_soon()
            self.tasks.spawn(template.close(), name="dead zygote template")
        return None

    async def _spawn_env(self, key: tuple | None) -> EnvHandle:
        env = EnvHandle(next(self._env_ids), key, started=time.monotonic())
        self._hellos.open(key=env.env_id)
        args = ["--control", self.control_path, "--env-id", str(env.env_id), "--runtime-dir", str(self.runtime_dir),
                "--socket-dir", str(self.socket_dir), "--bind", self.bind,
                "--advertise-host", self.advertise_host, "--sandbox", self.sandbox_cls.kind,
                "--max-frame", str(self.max_frame), "--grace", str(self.grace), "--scope", self.scope]
        zygote_template = await self._fork_zygote_template()
        try:
            env.proc = await self.env_template.spawn(args, zygote_template) or await asyncio.create_subprocess_exec(
                sys.executable, "-m", "rce_container.environment", *args,
                *(["--zygote-template-fd", str(zygote_template.fileno())] if zygote_template else []),
                stdin=asyncio.subprocess.DEVNULL, start_new_session=True,
                pass_fds=[zygote_template.fileno()] if zygote_template else [])
            early_exit = self.tasks.spawn(self._exit_before_hello(env), name=f"environment {env.env_id} start")
            try:
                env.peer, info = await self._hellos.wait(env.env_id, self.env_timeout)
            except Timeout:
                await self._kill_env_proc(env)
                raise Timeout(f"environment process did not report ready within {self.env_timeout:g} s") from None
            finally:
                early_exit.cancel()
        finally:
            self._hellos.forget(env.env_id)
            if zygote_template is not None:
                zygote_template.close()            # the environment has its own descriptor of it
        env.peer.name = f"environment {env.env_id}"
        env.peer.on_close = lambda _p, e=env: self._env_link_closed(e)
        env.data_addr = info.data_addr
        await self._give_data_key(env)
        self.envs.add(env)
        self.tasks.spawn(self._watch_env(env), name=f"environment {env.env_id}")
        log.info("environment started", env=env.env_id, pid=env.proc.pid, data_addr=env.data_addr,
                 ms=round((time.monotonic() - env.started) * 1000, 1))
        return env

    async def _give_data_key(self, env: EnvHandle) -> None:
        """Hand the environment that said hello its data key (:mod:`rce.transport.cluster_auth`), once the
        kernel confirms the hello came from the process this task set started. Raises
        :class:`Unavailable` (the environment is killed) otherwise."""
        pid = peer_pid(env.peer.link.writer)
        try:
            if pid != env.proc.pid:
                raise Unavailable(f"environment {env.env_id}'s hello came from pid {pid}, not {env.proc.pid}")
            await env.peer.ask(env_ops.EnvDataKey(key=self.cluster_key.data_key(env.data_addr).hex()))
        except RCEError:
            await self._kill_env_proc(env)
            raise

    async def _exit_before_hello(self, env: EnvHandle) -> None:
        code = await env.proc.wait()
        self._hellos.fail(env.env_id, Unavailable(f"environment process exited with code {code} "
                                                  "before it was ready (see its log)"))

    def _env_link_closed(self, env: EnvHandle) -> None:
        if not env.stopping:
            log.error("control link to an environment lost", env=env.env_id, containers=sorted(env.cids))

    async def _watch_env(self, env: EnvHandle) -> None:
        env.exit_code = await env.proc.wait()
        if env.stopping:
            return
        if env.key is None:                  # a spare: just forget it
            log.warning("a spare environment exited", env=env.env_id, code=env.exit_code)
            self.envs.discard(env)
            if env in self.spares:
                self.spares.remove(env)
            return
        await self._env_died(env)

    async def _env_died(self, env: EnvHandle) -> None:
        """An environment serving containers died: their nodes are killed and reported exited,
        their sandboxes cleaned up, and each container is reported to the master as
        ``container_lost {cid, reason}``: it destroys the dead one here and re-creates it under a
        new cid (docs/INTERNALS.md, "Container failover"). Until then an op on it is refused
        (:class:`Unavailable`); the group's next container gets a new environment."""
        why = exit_reason(env.exit_code)
        log.error("environment exited unexpectedly", env=env.env_id, reason=why, containers=sorted(env.cids))
        if env.peer:
            await env.peer.close()
        for cid in sorted(env.cids):
            c = self.containers.get(cid)
            if c is None:
                continue
            for ntag, pid in list(c.nodes.items()):
                if pid:
                    _kill_group(pid)
                self._to_master(env_ops.NodeStatusReport(cid=cid, ntag=ntag, status=env_ops.NodeStatus.EXITED,
                                                         reason=f"environment exited with code {env.exit_code}"))
                c.nodes[ntag] = None
                c.statuses[ntag] = env_ops.NodeStatus.EXITED
            self._to_master(to_master.ContainerLost(cid=cid, reason=f"its environment {why}"))
            await asyncio.to_thread(self.sandbox_cls.cleanup_container, self.scope, cid)

    async def _stop_env(self, env: EnvHandle) -> None:
        """Ask the environment to destroy its containers, close its link, reap it (SIGKILL after
        a timeout), and kill any node process group it left behind."""
        env.stopping = True
        self.envs.discard(env)
        if env in self.spares:
            self.spares.remove(env)
        if self.groups.get(env.key) is env:
            del self.groups[env.key]
        clean = False
        if env.alive:
            try:
                await env.peer.ask(env_ops.EnvShutdown(), self.grace + REPLY_MARGIN)
                clean = True
            except RCEError as e:
                log.warning("environment did not shut down cleanly", env=env.env_id, reason=e.message)
        if env.peer:
            await env.peer.close()
        await self._kill_env_proc(env)
        if not clean:       # the environment could not clean up: kill its nodes, remove the dirs
            for cid in env.cids:
                c = self.containers.get(cid)
                for pid in (c.nodes.values() if c else ()):
                    if pid:
                        _kill_group(pid)
                await self._remove_dirs(cid)

    async def _remove_dirs(self, cid: int) -> None:
        """Remove what container ``cid`` left: its sandbox's processes and cgroups, its dirs."""
        await asyncio.to_thread(self.sandbox_cls.cleanup_container, self.scope, cid)
        workdir, sock = container_paths(self.runtime_dir, self.socket_dir, cid)
        shutil.rmtree(workdir, ignore_errors=True)
        shutil.rmtree(sock.parent, ignore_errors=True)

    async def _kill_env_proc(self, env: EnvHandle) -> None:
        if env.proc is None:
            return
        try:
            async with asyncio.timeout(self.grace + EXIT_MARGIN):
                await env.proc.wait()
        except TimeoutError:
            log.warning("environment did not exit, killing it", env=env.env_id, pid=env.proc.pid)
            _kill_group(env.proc.pid)
            await env.proc.wait()

    # -- master ops ----------------------------------------------------------------------------
    def _to_master(self, msg: OpArgs) -> None:
        """A notification the master must get: while it is away it waits in the link's backlog."""
        if self.master:
            self.master.tell(msg, keep=True)

    def _report(self) -> dict:
        """What this host holds, for re-registering: every container whose environment runs,
        with its data address, sandbox, and nodes with their last status."""
        return {"containers": [
            {"cid": c.cid, "data_addr": c.result["data_addr"], "sandbox": c.result["sandbox"],
             "nodes": [{"ntag": ntag, "status": c.statuses.get(ntag, env_ops.NodeStatus.STARTING)}
                       for ntag in sorted(c.nodes)]}
            for c in self.containers.values() if c.env.alive]}

    async def _obey(self, answer: dict) -> None:
        """A register answer: destroy the containers and remove the nodes the master does not have."""
        for cid in answer.get("drop_containers") or []:
            log.warning("the master does not have this container: destroying it", cid=cid)
            try:
                await self.op_destroy_container(ops.DestroyContainer(cid=cid))
            except RCEError as e:
                log.warning("could not destroy a container the master dropped", cid=cid, reason=e.message)
        for n in answer.get("drop_nodes") or []:
            log.warning("the master does not have this node: removing it", cid=n.get("cid"), ntag=n.get("ntag"))
            try:
                await self.relay("remove_node", HOST_OPS.parse("remove_node", n))
            except RCEError as e:
                log.warning("could not remove a node the master dropped", reason=e.message, **n)

    def _record(self, cid: int) -> ContainerRecord:
        c = self.containers.get(cid)
        if c is None:
            raise NotFound(f"container {cid!r} does not exist on container host {self.name!r}")
        if not c.env.alive:
            raise Unavailable(f"the environment of container {c.ctag!r} is gone"
                              + (f" (exit code {c.env.exit_code})" if c.env.exit_code is not None else ""))
        return c

    @HOST_OPS.op("create_container", args=ops.CreateContainer)
    async def op_create_container(self, args: ops.CreateContainer) -> dict:
        """``{cid, user, ctag, group, limits, deadline_ms?, handoff?}`` -> ``{data_addr, sandbox,
        startup_ms}`` once the environment serves the container (``deadline_ms``: its results'
        due time, counted in its stats; ``handoff``: it is a move's new copy, its nodes wait for
        their state, :meth:`rce_container.environment.Environment.op_state_in`). Idempotent for a
        repeated cid with the same tag.

        Raises :class:`RequestError` for a cid reused with another tag, :class:`Unavailable`
        if the environment exits before it is ready, :class:`Timeout` if it does not get
        ready within ``env_timeout`` s."""
        cid, user, ctag, group = args.cid, args.user, args.ctag, args.group or None
        old = self.containers.get(cid)
        if old is not None:
            if (old.user, old.ctag) == (user, ctag):
                return old.result
            raise RequestError(f"container id {cid} is already in use by {old.ctag!r}")
        t0 = time.monotonic()
        key = ("group", user, group) if group else ("solo", cid)
        lock = self._group_locks.setdefault(key, asyncio.Lock())
        async with lock:
            old = self.containers.get(cid)
            if old is not None:      # a concurrent replay of the same request won the race
                if (old.user, old.ctag) == (user, ctag):
                    return old.result
                raise RequestError(f"container id {cid} is already in use by {old.ctag!r}")
            env = self.groups.get(key)
            if env is None or not env.alive:
                env = await self._take_spare()
                if env is not None:
                    env.key = key
                else:
                    env = await self._spawn_env(key)
                self.groups[key] = env
                self._refill_after_take()
            env.cids.add(cid)
            try:
                res = await env.peer.ask(env_ops.EnvAddContainer(cid=cid, ctag=ctag, user=user, group=group,
                                                              limits=args.limits or {}, deadline_ms=args.deadline_ms,
                                                              handoff=args.handoff), self.env_timeout)
            except BaseException:
                env.cids.discard(cid)
                if not env.cids:
                    await self._stop_env(env)
                raise
            result = {"data_addr": res["data_addr"], "sandbox": res["sandbox"],
                      "startup_ms": round((time.monotonic() - t0) * 1000, 1)}
            self.containers[cid] = ContainerRecord(cid, user, ctag, group, env, result)
        log.info("container created", cid=cid, user=user, ctag=ctag, group=group, env=env.env_id,
                 data_addr=result["data_addr"], startup_ms=result["startup_ms"])
        return result

    @HOST_OPS.op("destroy_container", args=ops.DestroyContainer)
    async def op_destroy_container(self, args: ops.DestroyContainer) -> dict:
        """``{cid}``: kill every node of the container, drop its interfaces and socket; stop its
        environment if it was the group's last container. Raises :class:`NotFound`."""
        c = self.containers.get(args.cid)
        if c is None:
            raise NotFound(f"container {args.cid!r} does not exist on container host {self.name!r}")
        env = c.env
        async with self._group_locks.setdefault(env.key, asyncio.Lock()):
            del self.containers[c.cid]
            env.cids.discard(c.cid)
            clean = False
            if env.alive:
                try:
                    await env.peer.ask(env_ops.EnvRemoveContainer(cid=c.cid), self.grace + REPLY_MARGIN)
                    clean = True
                except RCEError as e:
                    log.warning("environment failed to remove a container", cid=c.cid, reason=e.message)
            if not clean:   # the environment could not clean up: kill the nodes, remove the dirs
                for pid in c.nodes.values():
                    if pid:
                        _kill_group(pid)
                await self._remove_dirs(c.cid)
            if not env.cids:
                await self._stop_env(env)
                self._group_locks.pop(env.key, None)
        if not self.containers and self.capacity < SMALL_HOST_CPU:
            self._refill_spares()         # a small host's spare, held back while it ran containers
        log.info("container destroyed", cid=c.cid, ctag=c.ctag)
        return {}

    @HOST_OPS.relay(env_ops.EnvAddNode, env_ops.EnvRemoveNode, env_ops.EnvSetParam, env_ops.EnvDeleteParam,
                    env_ops.EnvGetParam, env_ops.EnvAddInterface, env_ops.EnvRemoveInterface, env_ops.EnvConnect,
                    env_ops.EnvDisconnect, env_ops.EnvDescribe, env_ops.EnvBusPublish, env_ops.EnvBusCall,
                    env_ops.EnvBusSample, env_ops.EnvLogs, env_ops.EnvResizeContainer, env_ops.EnvStateOut,
                    env_ops.EnvStateIn, env_ops.EnvDrain)
    async def relay(self, op: str, args: env_ops.OnContainer) -> Any:
        """Relay ``op`` (one of :data:`HOST_OPS`' relayed ops, an environment's) to the environment of
        the op's ``cid``; its answer. Raises :class:`NotFound` for an unknown cid, :class:`Unavailable`
        when its environment is gone, and what the environment raises."""
        c = self._record(args.cid)
        timeout = RELAY_TIMEOUT
        if isinstance(args, (env_ops.EnvBusCall, env_ops.EnvBusSample)):
            timeout = (args.timeout or BUS_CALL_TIMEOUT) + REPLY_MARGIN
        elif isinstance(args, env_ops.EnvRemoveNode):
            timeout = self.grace + REPLY_MARGIN
        elif isinstance(args, env_ops.EnvDrain):
            timeout = (args.timeout or 0.0) + REPLY_MARGIN
        result = await c.env.peer.ask(args, timeout)
        if isinstance(args, env_ops.EnvAddNode):
            c.nodes.setdefault(args.ntag, (result or {}).get("pid"))
            c.statuses.setdefault(args.ntag, env_ops.NodeStatus.STARTING)
        elif isinstance(args, env_ops.EnvRemoveNode):
            c.nodes.pop(args.ntag, None)
            c.statuses.pop(args.ntag, None)
        return result

    @HOST_OPS.op("stats", args=ops.HostStats)
    async def op_stats(self, args: ops.HostStats) -> dict:
        """``{cid}`` -> the container's counters (see ``Environment.op_stats``); without a cid,
        ``{name, tid, sandbox, environments, containers: [per-container stats...]}``."""
        if args.cid is not None:
            c = self._record(args.cid)
            return await c.env.peer.ask(env_ops.EnvStats(cid=c.cid))
        out = []
        for c in list(self.containers.values()):
            if c.env.alive:
                try:
                    out.append(await c.env.peer.ask(env_ops.EnvStats(cid=c.cid)))
                except RCEError as e:
                    out.append({"cid": c.cid, "ctag": c.ctag, "error": e.message})
            else:
                out.append({"cid": c.cid, "ctag": c.ctag, "error": "environment gone"})
        envs = {}
        for e in list(self.envs):
            if e.proc is not None and e.proc.returncode is None:
                envs[e.env_id] = measure([e.proc.pid])["rss_bytes"]
        return {"name": self.name, "tid": self.tid, "sandbox": self.sandbox_cls.kind, "scope": self.scope,
                "environments": len(self.envs), "spares": len(self.spares),
                "environment_rss_mib": {str(k): round(v / 2**20, 2) for k, v in envs.items()},
                "containers": out}

    # -- Prometheus ----------------------------------------------------------------------------
    async def _start_metrics(self) -> None:
        self._http = MetricsServer(self._metrics)
        self.metrics_port = await self._http.start(self.bind, self.metrics_port)
        log.info("metrics served", url=f"http://{self.bind}:{self.metrics_port}/metrics")

    async def _metrics(self) -> bytes:
        return generate_latest(metrics.snapshot_registry(await self.op_stats(ops.HostStats())))



def exit_reason(code: int | None) -> str:
    """How a process ended, from its return code (negative: the signal that killed it)."""
    if code is not None and code < 0:
        try:
            return f"was killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"was killed by signal {-code}"
    return f"exited with code {code}"


def _kill_group(pgid: int) -> None:
    try:
        os.killpg(pgid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


def write_ready_file(path: str | Path, tid: Any, **extra: Any) -> None:
    """Write ``{"tid", "pid", **extra}`` to ``path`` atomically (tests wait for it)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps({"tid": tid, "pid": os.getpid(), **extra}))
    os.replace(tmp, path)
