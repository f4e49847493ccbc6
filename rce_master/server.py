"""rce-master's asyncio shell around :class:`~rce_master.state.master_state.MasterState`.

- Control plane (TCP, default 8080): task sets register and exchange the ops of
  docs/INTERNALS.md; robot requests go to their handlers (:mod:`rce_master.requests`).
- HTTP (default 9000): robot login ``GET /?userID=U&version=V`` (docs/design.md, section 3.1), the
  JSON admin API under ``/api/`` (:mod:`rce_master.http.admin`, Bearer token), Prometheus ``/metrics``.

No data flows through the master, and the shell changes no state itself: it asks
:class:`MasterState`, and tells the task sets what that returns (:class:`~rce_master.control.Control`).

On a store a previous master left, the state comes back with every task set absent; each one
that re-registers is reconciled (:mod:`rce_master.state.reconcile`), and those still absent after the
reconciliation grace are dropped as if their link had closed (docs/INTERNALS.md, "Master state
and restart"). A robot task set whose link closes is absent in the same way, for the same grace, and
its robots may move to another endpoint meanwhile (docs/INTERNALS.md, "Moving to another endpoint").
A container lost with its host or environment is re-created elsewhere (:mod:`rce_master.failover`,
docs/INTERNALS.md, "Container failover").

Several masters on etcd (docs/INTERNALS.md, "Several masters"): a master that stands by (its
``office`` does not lead, :mod:`rce_master.leadership.office`) serves login and admin reads from the state it
follows, and refuses ``register`` and admin writes with :class:`~rce.plumbing.errors.NotLeader` naming the
leader; once elected, :meth:`Master.take_office` makes it the master that restarted on the state.
Every answer that follows a change waits until the store has it (:meth:`Store.flush`).
"""
from __future__ import annotations

import asyncio
import math
import ssl
from collections import defaultdict
from pathlib import Path

from aiohttp import web
from prometheus_client import CollectorRegistry, Counter, Gauge, generate_latest, CONTENT_TYPE_LATEST
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

from rce.contract import environment as to_env
from rce.contract import host as to_host
from rce.contract import master as ops
from rce.tools.admin_client import LEADER_HEADER
from rce.transport.cluster_auth import ClusterKey, Gate
from rce.plumbing.errors import AuthError, NotFound, NotLeader, RCEError, RequestError, Throttled, Timeout, Unavailable
from rce.plumbing.log import get_logger
from rce.transport import lane_socket
from rce.transport.op_table import OpTable
from rce.transport.rpc import RpcPeer
from rce.interfaces.lanes import Lane
from rce.plumbing.tasks import Tasks
from rce_master.state import reconcile
from rce_master.http.admin import AdminApi
from rce_master.control import Control
from rce_master.failover import Failover
from rce_master.auth.login_guard import LoginGuard, PasswordCheck
from rce_master.state.lifecycle import ContainerState
from rce_master.state.model import ContainerRec, Robot, TaskSet
from rce_master.leadership.office import RETRY_AFTER_NO_LEADER, Alone, Office, require_leader
from rce_master.placement.mover import Mover
from rce_master.placement.advice import Placement
from rce_master.requests import Request, handle
from rce_master.state.master_state import MasterState, Quotas, TaskSetAbsent
from rce_master.state.store import Store
from rce_master.auth.users import UsersFile

log = get_logger("rce.master")

CLIENT_VERSION = "20130902"                        # the RCE alpha client's version string
SUPPORTED_VERSIONS = {"20130902", "20130210"}
MAX_HTTP_BODY = 16 * 1024 * 1024                   # bytes, an admin API request body
HTTP_STATUS = ((AuthError, 401), (NotFound, 404), (Timeout, 504), (Throttled, 429), (Unavailable, 503), (RCEError, 400))
RETRY_AFTER = 5                                    # s, Retry-After of a 503 for an absent task set (login, admin
#                                                    API): about a reconnecting task set's backoff

#: What a task set sends the master first, and alone until it is registered (served with its link).
MASTER_OPS = OpTable("task set -> master")
#: What a registered robot task set sends the master (served with its tid).
ROBOT_SET_OPS = OpTable("robot task set -> master")
#: What a registered container task set sends the master (served with its tid).
HOST_SET_OPS = OpTable("container task set -> master")


class _RelayCollector:
    """``rce_master_robot_relay{user, robot, relay}``: 1 for each robot whose link to the cloud goes through
    robot ``relay`` now (docs/relays.md), the topology as Prometheus sees it."""

    def __init__(self, state: MasterState):
        self.state = state

    def collect(self):
        g = GaugeMetricFamily("rce_master_robot_relay", "1 for each robot whose link to the cloud goes through "
                              "robot `relay`", labels=["user", "robot", "relay"])
        for b in self.state.robots.values():
            if b.relay:
                g.add_metric([b.user, b.robot, b.relay], 1.0)
        yield g


class _HostCollector:
    """Per container host, labelled by ``host`` (its name) and ``zone``: ``rce_master_host_capacity_cpu``
    (cores), ``rce_master_host_load_cpu`` (cores its containers requested) and
    ``rce_master_host_containers``."""

    def __init__(self, state: MasterState):
        self.state = state

    def collect(self):
        fams = [GaugeMetricFamily("rce_master_host_capacity_cpu", "A container host's cores", labels=["host", "zone"]),
                GaugeMetricFamily("rce_master_host_load_cpu", "Cores the containers on a host requested",
                                  labels=["host", "zone"]),
                GaugeMetricFamily("rce_master_host_containers", "Containers on a host", labels=["host", "zone"])]
        for t in self.state.tasksets.values():
            if t.kind != "container" or t.lost:
                continue
            labels = [t.name, str(t.zone)]
            fams[0].add_metric(labels, float((t.info.get("capacity") or {}).get("cpu") or 0))
            fams[1].add_metric(labels, t.cpu_load)
            fams[2].add_metric(labels, t.containers)
        yield from fams


class _PlacementCollector:
    """Per container that asks for a placement, labelled ``user``, ``ctag`` (and ``host``, where it
    runs): ``rce_master_container_results`` and ``rce_master_container_deadline_misses`` (its nodes'
    results timed by the engine, and those late, on the copy that runs now: a move starts them
    again); and the placer's ``rce_master_container_moves_total`` / ``_move_failures_total`` /
    ``_move_fence_timeouts_total`` (moves whose old copy went before all was fenced: after the
    mover's ``DRAIN_MAX``, or a peer that could not be switched)."""

    def __init__(self, state: MasterState, placement: Placement, mover: Mover):
        self.state, self.placement, self.mover = state, placement, mover

    def collect(self):
        res = GaugeMetricFamily("rce_master_container_results", "Results a container's nodes gave, timed from "
                                "their inputs (its copy that runs now)", labels=["user", "ctag", "host"])
        late = GaugeMetricFamily("rce_master_container_deadline_misses", "Of those, results later than the "
                                 "container's deadline_ms", labels=["user", "ctag", "host"])
        for (user, ctag), u in list(self.placement.use.items()):
            c = self.state.containers.get((user, ctag))
            host = self.state.tasksets.get(c.tid) if c is not None else None
            labels = [user, ctag, host.name if host is not None else ""]
            res.add_metric(labels, float(u.results))
            late.add_metric(labels, float(u.misses))
        yield res
        yield late
        yield CounterMetricFamily("rce_master_container_moves", "Containers moved, make-before-break",
                                  value=self.mover.moves)
        yield CounterMetricFamily("rce_master_container_move_failures", "Moves that failed (the container ran "
                                  "on where it was)", value=self.mover.failed)
        yield CounterMetricFamily("rce_master_container_move_fence_timeouts", "Moves whose old copy went before "
                                  "every fence, input and output was accounted for", value=self.mover.fence_timeouts)
        yield GaugeMetricFamily("rce_master_container_spares", "Spare copies of containers, made and fed nothing "
                                "(docs/placement.md, Spares)", value=sum(self.mover.spare_of(*k) is not None
                                                                         for k in list(self.mover.spares)))
        yield CounterMetricFamily("rce_master_container_spares_taken", "Moves that took a spare (switch and break "
                                  "only)", value=self.mover.spares_taken)


class MasterMetrics:
    """Prometheus metrics of the master."""

    def __init__(self, state: MasterState, office: Office, failover: Failover):
        self.registry = CollectorRegistry()
        r = self.registry
        self.logins = Counter("rce_master_logins", "Robot logins over HTTP", ["result"], registry=r)
        self.requests = Counter("rce_master_requests", "Robot requests (CC, DC, CN, CX)", ["type", "result"],
                                registry=r)
        self.control_refused = Counter("rce_master_control_refused", "Control-plane connections refused: no proof "
                                       "of the cluster key (rce.transport.cluster_auth.Gate)", ["reason"], registry=r)
        for name, help_, table in [
            ("rce_master_robots", "Connected robots", state.robots),
            ("rce_master_containers", "Containers", state.containers),
            ("rce_master_interfaces", "Interfaces", state.interfaces),
            ("rce_master_connections", "Connections", state.connections),
            ("rce_master_tasksets", "Registered task sets", state.tasksets),
        ]:
            Gauge(name, help_, registry=r).set_function(table.__len__)
        Gauge("rce_master_tasksets_absent", "Task sets from the stored state that have not re-registered",
              registry=r).set_function(lambda: sum(t.lost for t in state.tasksets.values()))
        Gauge("rce_master_leader", "1 while this master leads (always, alone; one of several on etcd)",
              registry=r).set_function(lambda: int(office.leading))
        Gauge("rce_master_containers_down", "Containers lost with their host or environment, or being re-created",
              registry=r).set_function(lambda: sum(c.down for c in state.containers.values()))
        Gauge("rce_master_containers_recovered", "Lost containers re-created since the master started",
              registry=r).set_function(lambda: failover.recovered)
        Gauge("rce_master_containers_given_up", "Lost containers the master gave up re-creating since it started",
              registry=r).set_function(lambda: failover.gave_up)
        Gauge("rce_master_robots_relayed", "Connected robots whose link to the cloud goes through another robot",
              registry=r).set_function(lambda: sum(bool(b.relay) for b in state.robots.values()))
        Gauge("rce_master_robots_relaying", "Robots that carry the link of at least one other robot",
              registry=r).set_function(lambda: len({(b.user, b.relay) for b in state.robots.values() if b.relay}))
        r.register(_RelayCollector(state))
        r.register(_HostCollector(state))
        Gauge("rce_master_store_pending", "Changes of the state not yet written to the store (etcd)",
              registry=r).set_function(lambda: getattr(state.store, "pending", 0))


PLACEMENT_STATS_S = 5.0    # s the placer waits for a container's counters


class Master:
    """The running master. ``users_file``: JSON file of hashed user records (read and kept up to
    date); ``store``: where the state is kept (default: in memory); ``reconcile_grace`` (s): how
    long task sets found in the store may take to re-register; ``office``: whether it leads
    (default: alone, it always does; on etcd its election); ``cluster_key``: what every task set
    must prove it holds before its link is served (:mod:`rce.transport.cluster_auth`), and what the data-plane
    credentials handed out with ``connect`` derive from; ``quotas``: per-user bounds on containers, nodes
    and interfaces (default :class:`~rce_master.state.master_state.Quotas`); ``login_guard``: the back-off of failed
    logins (default :class:`~rce_master.auth.login_guard.LoginGuard`'s defaults)."""

    def __init__(self, *, users_file: Path | None = None, admin_token: str, dev: bool = False,
                 store: Store | None = None, reconcile_grace: float = reconcile.RECONCILE_GRACE,
                 office: Office | None = None, login_guard: LoginGuard | None = None,
                 cluster_key: ClusterKey, quotas: Quotas | None = None):
        self.office = office if office is not None else Alone()
        self.state = MasterState(store, quotas)
        self.reconcile_grace = reconcile_grace
        self.dev = dev
        self.restored: list[TaskSet] = []          # the task sets a previous master knew
        self.restored_absent: set[int] = set()     # ... the tids of those not back since this master leads
        self.control = Control(self.state, cluster_key)
        self.gate = Gate(cluster_key, "rce-master control",
                         on_refused=lambda reason: self.metrics.control_refused.labels(reason).inc())
        self.users = UsersFile(users_file) if users_file else None
        self.mover = Mover(self.state, self.control)
        self.placement = Placement(self.state, self._container_stats, mover=self.mover)
        self.passwords = PasswordCheck(login_guard)     # the auth op's throttling and scrypt pool (login_guard.py)
        self.admin = AdminApi(self.state, self.control, admin_token, self.users, self.office, self.placement,
                              self.passwords)
        self.robot_locks: dict[tuple[str, str], asyncio.Lock] = defaultdict(asyncio.Lock)
        self.robot_logins: dict[tuple[str, str], tuple[int, str]] = {}   # robot -> (endpoint tid, its login's session)
        self.tasks = Tasks("rce-master")
        self.failover = Failover(self.state, self.control, self.tasks, spares=self.mover.claim_spare)
        self.metrics = MasterMetrics(self.state, self.office, self.failover)
        self.metrics.registry.register(self.passwords)
        self.metrics.registry.register(_PlacementCollector(self.state, self.placement, self.mover))
        self._control: asyncio.AbstractServer | None = None
        self._runner: web.AppRunner | None = None
        self.http_port = self.control_port = 0
        self._stopping = False
        if self.office.leading:
            self._office_duties()

    def _office_duties(self) -> None:
        """What a master does as it starts to lead on its store: the task sets there are absent
        until they re-register; the users file is loaded; ``--dev`` provisions testUser."""
        self.restored = self.state.mark_tasksets_absent()
        self.restored_absent = {ts.tid for ts in self.restored}
        if self.users:
            self.users.load(self.state)
        if self.dev and "testUser" not in self.state.users:
            self.state.add_user("testUser", "testUser", role="admin")
            log.warning("DEV MODE: user 'testUser' with password 'testUser' is provisioned; never use --dev on a "
                        "reachable network")

    def take_office(self) -> None:
        """This master has just been elected (several masters on etcd) and its store holds the
        state as the last leader left it: take it over as a master restarted on it would (its
        task sets absent until they re-register, dropped after the reconciliation grace)."""
        self._office_duties()
        log.info("master leads", restored_tasksets=len(self.restored), containers=len(self.state.containers))
        self.failover.resume()
        if self.restored:
            self.tasks.spawn(self._end_grace(), name="reconcile-grace")

    # -- lifecycle -----------------------------------------------------------------------------
    async def start(self, bind: str, http_port: int, control_port: int,
                    static_dirs: dict[str, Path] | None = None, ssl_context: ssl.SSLContext | None = None) -> None:
        """Listen: the control plane on ``control_port``, HTTP on ``http_port`` (HTTPS with
        ``ssl_context``, :func:`rce.transport.tls.server_context`; 0: ephemeral ports, then in the attributes)."""
        self._control = await asyncio.start_server(self._accept, bind, control_port, limit=2**20)
        self.control_port = self._control.sockets[0].getsockname()[1]
        self._runner = web.AppRunner(self._app(static_dirs or {}), access_log=None)
        await self._runner.setup()
        site = web.TCPSite(self._runner, bind, http_port, ssl_context=ssl_context)
        await site.start()
        self.http_port = site._server.sockets[0].getsockname()[1]
        log.info("master up", http_port=self.http_port, control_port=self.control_port, bind=bind,
                 leading=self.office.leading, restored_tasksets=len(self.restored),
                 containers=len(self.state.containers))
        self.tasks.spawn(self.placement.run(asyncio.Event()), name="placement")
        if self.office.leading:
            self.failover.resume()
        if self.office.leading and self.restored:
            self.tasks.spawn(self._end_grace(), name="reconcile-grace")

    async def _end_grace(self, tid: int | None = None) -> None:
        """After the reconciliation grace, drop the task sets that did not come back (a timer): every
        absent one after a restart (``tid`` None), else robot task set ``tid`` that lost its link."""
        await asyncio.sleep(self.reconcile_grace)
        why = (f"its host did not re-register within {self.reconcile_grace:g} s after the master restarted"
               if tid is None else f"its robot endpoint did not come back within {self.reconcile_grace:g} s")
        lost, robots = [], []
        for ts in self.state.absent_tasksets():
            if tid not in (None, ts.tid):
                continue
            got, gone = self.state.drop_taskset(ts.tid)
            self.mover.host_lost(ts.tid)
            self.restored_absent.discard(ts.tid)
            log.warning("task set did not come back", tid=ts.tid, name=ts.name, containers=len(got),
                        robots=len(gone))
            lost += got
            robots += gone
        # every robot that left goes first, with its containers: only the lost containers of robots
        # still here are re-created (Failover.lost forgets those whose robot is gone)
        await self.failover.taskset_lost(lost, robots, why)
        await self.state.store.flush()

    async def stop(self) -> None:
        """Close every link and server. The task sets stay in the store as they were (a master
        started on it later reconciles with them), rather than being dropped as they would be
        if they left."""
        self._stopping = True
        if self._control:
            self._control.close()
        for p in list(self.control.peers.values()):
            await p.close()
        await self.tasks.cancel_all()
        if self._runner:
            await self._runner.cleanup()
        self.passwords.close()

    # -- control plane -------------------------------------------------------------------------
    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        lane_socket.mark(writer.get_extra_info("socket"), Lane.CONTROL)   # ahead of data on a robot's link
        if not await self.gate.admit(reader, writer):       # refused, logged and counted
            return
        peer = RpcPeer(reader, writer, name="taskset", on_close=self._peer_closed)
        peer.handlers.update(MASTER_OPS.handlers(self, context=peer))
        peer.start()

    async def _container_stats(self, c: ContainerRec) -> dict:
        """``stats`` of container ``c`` from its host, for the placer (an absent host: refused at once)."""
        return await self.control.host_ask(c, to_host.HostStats(cid=c.cid), PLACEMENT_STATS_S, wait=False)

    @MASTER_OPS.op("register", args=ops.Register)
    async def _op_register(self, peer: RpcPeer, args: ops.Register) -> dict:
        """A task set registers (or re-registers, reporting what it holds: :mod:`rce_master.state.reconcile`);
        its link then serves the ops of its kind."""
        require_leader(self.office, "register")
        if "tid" in peer.info:
            raise RequestError("this task set is already registered")
        out = reconcile.register(self.state, args.kind, args.name or peer.peername, args.host or "127.0.0.1",
                                 args.model_dump(exclude_unset=True))
        ts = out.taskset
        self.restored_absent.discard(ts.tid)
        peer.info["tid"] = ts.tid
        peer.name = f"{ts.kind}:{ts.name}"
        self.control.attach(ts.tid, peer)
        peer.keepalive()      # silent for rce.transport.rpc.KEEPALIVE_TIMEOUT (4 s): lost, its containers marked lost
        peer.handlers.update((ROBOT_SET_OPS if ts.kind == "robot" else HOST_SET_OPS).handlers(self, context=ts.tid))
        log.info("task set registered", tid=ts.tid, kind=ts.kind, name=ts.name, host=ts.host, resumed=out.resumed,
                 lost=len(out.lost), dropped=len(out.drop_containers) + len(out.drop_interfaces),
                 robots_gone=len(out.gone))
        self.tasks.spawn(self._reconciled(out), name=f"taskset-{ts.tid}-reconciled")
        await self.state.store.flush()
        return out.answer()

    async def _reconciled(self, out: reconcile.Reconciled) -> None:
        """Tell others what a ``register`` changed; a new container host may take lost containers."""
        await self.control.reconciled(out)
        await self.failover.lost(out.lost, "its host re-registered without it after the master restarted")
        if out.taskset.kind == "container":
            self.failover.host_registered()

    def _peer_closed(self, peer: RpcPeer) -> None:
        tid = peer.info.get("tid")
        if tid is None or self._stopping:
            return
        self.control.peers.pop(tid, None)
        ts = self.state.tasksets.get(tid)
        if ts is not None and ts.kind == "robot":
            # its robots may come back through another endpoint and take their sessions over: absent
            # until it re-registers, dropped after the grace (docs/INTERNALS.md "Session resume")
            self.state.taskset_absent(tid)
            log.warning("robot task set absent", tid=tid, name=peer.name, grace=self.reconcile_grace,
                        robots=sum(r.tid == tid for r in self.state.robots.values()))
            self.tasks.spawn(self._end_grace(tid), name=f"taskset-{tid}-grace")
            return
        lost, robots = self.state.drop_taskset(tid)
        self.mover.host_lost(tid)
        log.warning("task set gone", tid=tid, name=peer.name, containers=len(lost), robots=len(robots))
        self.tasks.spawn(self.failover.taskset_lost(lost, robots), name=f"taskset-{tid}-lost")

    # -- robot endpoint ops --------------------------------------------------------------------
    @ROBOT_SET_OPS.op("auth", args=ops.Auth)
    async def _op_auth(self, _tid: int, args: ops.Auth) -> dict:
        """``auth {user, password, addr}`` (``addr``: the address the robot or rosbridge client logs in
        from): raises AuthError, or Throttled (429) while the user or address backs off (login_guard.py)."""
        await self.passwords.authenticate(self.state.users, args.user, args.password, args.addr)
        return {}

    @ROBOT_SET_OPS.op("robot_connected", args=ops.RobotConnected)
    async def _op_robot_connected(self, tid: int, args: ops.RobotConnected) -> dict:
        """``robot_connected {user, robot, session?}``: a login of the robot was accepted on endpoint
        ``tid``; ``session`` names it (an endpoint's own id of the login), so that only the
        disconnect of that session ends the robot's namespace (:meth:`_op_robot_disconnected`)."""
        user, robot = args.user, args.robot
        old = self.state.robot(user, robot)
        host = self.state.tasksets.get(old.tid) if old is not None else None
        if old is not None and old.tid in self.restored_absent and not self._namespace_up(old):
            # its endpoint has not come back since the master restarted, nor have the hosts of what its
            # namespace uses (a full stop, or every process killed): that session is over, and so are
            # its containers; this login opens a new one
            log.info("robot's previous session ended", user=user, robot=robot, old_tid=old.tid,
                     reason="neither its robot endpoint nor its containers' hosts came back since the master "
                            "restarted")
            async with self.robot_locks[(user, robot)]:
                await self.control.robot_gone(user, robot)
        elif old is not None and old.tid != tid and host is not None and host.lost:
            # its old endpoint is absent (it died, or has not come back since the master restarted): the
            # robot takes its namespace over here, once its session is open on this endpoint
            recs = self.state.robot_moved(user, robot, tid)
            await self.state.store.flush()
            log.info("robot moved", user=user, robot=robot, old_tid=old.tid, tid=tid, interfaces=len(recs))
            self.tasks.spawn(self._robot_moved(user, robot, recs), name=f"robot-{user}/{robot}-moved")
            self._logged_in(tid, args)
            return {}
        self.state.robot_connect(user, robot, tid)
        await self.state.store.flush()
        self._logged_in(tid, args)
        log.info("robot connected", user=user, robot=robot)
        return {}

    def _logged_in(self, tid: int, args: ops.RobotConnected) -> None:
        """Remember the session a robot's accepted login opened on endpoint ``tid`` (none named: an
        older endpoint, whose disconnects end the namespace whichever session they end)."""
        key = (args.user, args.robot)
        if args.session is not None:
            self.robot_logins[key] = (tid, args.session)
        else:
            self.robot_logins.pop(key, None)

    @ROBOT_SET_OPS.op("robot_relay", args=ops.RobotRelayChanged)
    async def _op_robot_relay(self, tid: int, args: ops.RobotRelayChanged) -> dict:
        """``robot_relay {user, robot, relay}``: the robot's link to the cloud goes through robot ``relay``
        ("" for its own path) from now on (docs/relays.md)."""
        r = self.state.robot_relay(args.user, args.robot, tid, args.relay)
        if r is not None:
            await self.state.store.flush()
            log.info("robot's path to the cloud", user=r.user, robot=r.robot, relay=r.relay or "(direct)")
        return {}

    def _namespace_up(self, robot: Robot) -> bool:
        """Every container ``robot`` owns, and every container its interfaces are connected to, runs
        on a host registered now: a namespace worth taking over on a new endpoint."""
        peers = self.control.peers
        used = [c for c in self.state.containers.values() if c.user == robot.user and c.owner == robot.robot]
        for rec in self.state.interfaces_of(robot.user, robot.robot, robot_side=True):
            for _, peer in self.state.connections_of(rec.iid):
                c = None if peer.robot_side else self.state.container_by_cid(peer.location)
                if c is not None:
                    used.append(c)
        return all(c.state == ContainerState.RUNNING and c.tid in peers for c in used)

    async def _robot_moved(self, user: str, robot: str, recs: list) -> None:
        """Install a moved robot's interfaces on its new endpoint and connect them again, before its
        next request (its requests run one at a time, :meth:`_robot_request`)."""
        async with self.robot_locks[(user, robot)]:
            await self.control.robot_moved(recs)
            await self.state.store.flush()

    @ROBOT_SET_OPS.op("robot_disconnected", args=ops.RobotDisconnected)
    async def _op_robot_disconnected(self, tid: int, args: ops.RobotDisconnected) -> dict:
        """``robot_disconnected {user, robot, session?}``: the robot's session on endpoint ``tid``
        ended; its namespace goes unless it is no longer on that endpoint, or the disconnect names
        another session than the robot's last login (an old session's late end, after a new login
        of the same robot: the new one keeps its interfaces)."""
        key = (args.user, args.robot)
        r = self.state.robot(*key)
        if r is None or r.tid != tid:          # not (or no longer) on this endpoint: nothing to forget
            return {}
        session, last = args.session, self.robot_logins.get(key)
        if session is not None and last is not None and last != (tid, session):
            log.info("an old session's end ignored: the robot logged in again since", user=key[0], robot=key[1],
                     session=session)
            return {}
        self.robot_logins.pop(key, None)
        async with self.robot_locks[key]:
            await self.control.robot_gone(*key)
        self.robot_locks.pop(key, None)
        await self.state.store.flush()
        log.info("robot disconnected", user=args.user, robot=args.robot)
        return {}

    @ROBOT_SET_OPS.op("container_bus", args=ops.ContainerBus)
    async def _op_container_bus(self, _tid: int, args: ops.ContainerBus) -> dict:
        """``container_bus {user, ctag}`` (a rosbridge session, :mod:`rce_robot.rosbridge.endpoint`): the bus of
        the user's container ``ctag`` as its host describes it. Raises NotFound unless the user has it."""
        c = self.state.container(args.user, args.ctag)
        return await self.control.host_ask(c, to_env.EnvDescribe(cid=c.cid), wait=False)

    @ROBOT_SET_OPS.op("container_param", args=ops.ContainerParam)
    async def _op_container_param(self, _tid: int, args: ops.ContainerParam) -> dict:
        """``container_param {user, ctag, name}`` (a rosbridge client's ``/rosapi/get_param``):
        ``{value}`` of parameter ``name`` on the bus of the user's container ``ctag``. Raises
        NotFound unless the user has the container and the parameter is set."""
        c = self.state.container(args.user, args.ctag)
        return await self.control.host_ask(c, to_env.EnvGetParam(cid=c.cid, name=args.name), wait=False)

    @ROBOT_SET_OPS.op("robot_request", args=ops.RobotRequest)
    async def _op_robot_request(self, _tid: int, args: ops.RobotRequest) -> dict:
        """``robot_request {user, robot, type, data}``: one robot's requests run one at a time, in order."""
        user, robot, t = args.user, args.robot, args.type
        async with self.robot_locks[(user, robot)]:
            try:
                await handle(Request(user, robot, self.state, self.control), t, args.data or {})
                await self.state.store.flush()
            except RCEError:
                self.metrics.requests.labels(t, "error").inc()
                raise
        self.metrics.requests.labels(t, "ok").inc()
        return {}

    @HOST_SET_OPS.op("container_lost", args=ops.ContainerLost)
    async def _op_container_lost(self, tid: int, args: ops.ContainerLost) -> None:
        """``container_lost {cid, reason}`` from host ``tid``: the container's environment died."""
        reason = args.reason or "its environment exited"
        if self.mover.spare_lost(tid, args.cid):
            return
        log.warning("container lost with its environment", tid=tid, cid=args.cid, reason=reason)
        await self.failover.environment_lost(tid, args.cid, reason)
        await self.state.store.flush()

    @ROBOT_SET_OPS.op("robot_battery", args=ops.RobotBattery)
    async def _op_robot_battery(self, _tid: int, args: ops.RobotBattery) -> None:
        """A robot endpoint's reading of a robot's charge (its ``sensor_msgs/BatteryState``), for the placer."""
        try:
            self.placement.robot_battery(args.user, args.robot, args.percent)
        except RequestError as e:
            log.warning("robot battery not taken", reason=str(e))

    @ROBOT_SET_OPS.op("robot_link", args=ops.RobotLinkReport)
    async def _op_robot_link(self, _tid: int, args: ops.RobotLinkReport) -> None:
        """A robot endpoint's measure of a robot's link (:mod:`rce_robot.link_report`), for the placer."""
        self.placement.robot_link(args.user, args.robot, args.rtt_ms, args.rate)

    @ROBOT_SET_OPS.op("link_probe", args=ops.LinkProbe)
    async def _op_link_probe(self, _tid: int, args: ops.LinkProbe) -> dict:
        """A robot endpoint's probe of its uplink (:func:`rce_robot.link_report.probe_rate`): answered
        at once, with the bytes of its ``pad``; nothing else is done with it."""
        return {"bytes": len(args.pad)}

    @HOST_SET_OPS.op("node_status", args=ops.NodeStatusReport)
    async def _op_node_status(self, _tid: int, args: ops.NodeStatusReport) -> None:
        """A node's status, as its environment reported it: recorded, and its container's owner told."""
        detail = {k: v for k in ("code", "signal", "reason") if (v := getattr(args, k)) is not None}
        n = self.state.node_status(args.cid, args.ntag, args.status, detail)
        c = self.state.container_by_cid(args.cid)
        if n and c:
            self.control.tell_node_status(c, n, args.status, detail)

    @HOST_SET_OPS.op("interface_status", args=ops.InterfaceStatus)
    async def _op_interface_status(self, _tid: int, args: ops.InterfaceStatus) -> None:
        """A host's word on how a container interface is bridged into its container's ROS 2 graph
        (:mod:`rce_container.ros2_graph`): the owner gets ``ST {topic: interface, cTag, iTag, status,
        reason}``, and an ER with the reason unless the status is ``ok``. Nothing is recorded."""
        c = self.state.container_by_cid(args.cid)
        rec = next((r for r in self.state.interfaces_of(c.user, c.ctag, robot_side=False)
                    if r.iid == args.iid), None) if c else None
        status, reason = args.status, args.reason
        if rec is None:
            return
        self.control.notify_robot(c.user, c.owner, "ST", {"topic": "interface", "cTag": c.ctag, "iTag": rec.itag,
                                                          "status": status, "reason": reason})
        if status != "ok":
            self.control.notify_robot(c.user, c.owner, "ER",
                                      f"interface {rec.itag!r} in container {c.ctag!r}: {reason}")

    # -- HTTP ------------------------------------------------------------------------------------
    def _app(self, static_dirs: dict[str, Path]) -> web.Application:
        app = web.Application(middlewares=[self._errors_mw], client_max_size=MAX_HTTP_BODY)
        app.router.add_get("/", self._login)
        app.router.add_get("/metrics", self._metrics)
        app.router.add_get("/endpoints", self._endpoints)
        self.admin.add_routes(app)
        for prefix, d in static_dirs.items():
            app.router.add_static(prefix, d, show_index=False)
        return app

    @web.middleware
    async def _errors_mw(self, request: web.Request, handler):
        """An :class:`RCEError` becomes an HTTP error with its one-line reason (``HTTP_STATUS``)."""
        try:
            resp = await handler(request)
        except RCEError as e:
            status = next(s for cls, s in HTTP_STATUS if isinstance(e, cls))
            resp = web.Response(status=status, text=e.message + "\n")
            if isinstance(e, TaskSetAbsent):
                resp.headers["Retry-After"] = str(RETRY_AFTER)
            elif isinstance(e, Throttled):
                resp.headers["Retry-After"] = str(math.ceil(e.retry_after))
            elif isinstance(e, NotLeader):
                resp.headers[LEADER_HEADER] = (e.leader or {}).get("http") or ""
                if not e.leader:
                    resp.headers["Retry-After"] = str(RETRY_AFTER_NO_LEADER)
        if request.path.startswith("/api/") or request.path == "/":
            # the operator's web page may be served from another origin (rce-fleet); login and the
            # read-only parts are safe to share, the admin API itself still needs its token
            resp.headers["Access-Control-Allow-Origin"] = "*"
            resp.headers["Access-Control-Allow-Headers"] = "Authorization, Content-Type"
            resp.headers["Access-Control-Expose-Headers"] = LEADER_HEADER
        return resp

    async def _login(self, request: web.Request) -> web.Response:
        """``GET /?userID=U&version=V[&robotID=R]`` -> ``{"url": ws_url, "current"?: V'}`` (docs/design.md,
        section 3.1; with ``robotID``, the endpoint on that robot's own computer where one runs). The
        same answer whether user ``U`` exists or not (the password is checked at the robot endpoint, and
        fails there the same way for both): user names cannot be enumerated here."""
        q = request.query
        user, version = q.get("userID"), q.get("version")
        if not user:
            self.metrics.logins.labels("bad_request").inc()
            raise RequestError("missing query parameter 'userID'")
        if not version:
            self.metrics.logins.labels("bad_request").inc()
            raise RequestError("missing query parameter 'version'")
        if version not in SUPPORTED_VERSIONS and version > CLIENT_VERSION:
            self.metrics.logins.labels("bad_version").inc()
            raise RequestError(f"client version {version!r} is not supported (this master speaks {CLIENT_VERSION})")
        ts = self.state.pick_robot_taskset(user, q.get("robotID"))
        body = {"url": ts.info["ws_url"]}
        if version < CLIENT_VERSION:
            body["current"] = CLIENT_VERSION
        self.metrics.logins.labels("ok").inc()
        return web.json_response(body)

    async def _endpoints(self, request: web.Request) -> web.Response:
        """``GET /endpoints`` -> ``{"endpoints": [ws_url, ...]}``: the robot endpoints registered now, those
        a login may name; a relay tunnels to these and the master only (docs/relays.md)."""
        return web.json_response({"endpoints": sorted(t.info["ws_url"] for t in self.state.tasksets.values()
                                                      if t.kind == "robot" and not t.lost and "ws_url" in t.info)})

    async def _metrics(self, request: web.Request) -> web.Response:
        return web.Response(body=generate_latest(self.metrics.registry),
                            headers={"Content-Type": CONTENT_TYPE_LATEST})
