"""The robot task set: the websocket server robots connect to (docs/design.md, section 3), one
:class:`~rce_robot.namespace.RobotNamespace` per robot, the robot-side interfaces and
this process's data-plane endpoint."""
from __future__ import annotations

import asyncio
import hashlib
import hmac
import secrets
import socket
import ssl
from collections import Counter
from http import HTTPStatus
from typing import Any
from urllib.parse import parse_qs, urlsplit

from prometheus_client import CollectorRegistry, Gauge, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily

from rce.contract import master as to_master
from rce.contract import robot as ops
from rce.transport.cluster_auth import ClusterKey, token_of
from rce.transport.dataplane import DataPlane
from rce.plumbing.errors import AuthError, NotFound, ProtocolError, RCEError, RequestError, Throttled
from rce.interfaces.kind import InterfaceType
from rce.protocol.zones import CLOUD, Zone
from rce.interfaces.lanes import Lane
from rce.protocol.lane_queue import DELAY_BOUNDS
from rce.interfaces.pacer import Pacing, new_pacer
from rce.transport.lane_socket import mptcp_socket
from rce.plumbing.log import get_logger
from rce.plumbing.metrics_http import MetricsServer
from rce.transport.masterlink import MASTER_WAIT, Address, MasterLink
from rce.messages import default_registry
from rce.transport.op_table import OpTable
from rce.node.package_path import load_package_types
from rce.protocol.frames import DEFAULT_EXPIRY, ER, encode
from rce.protocol.limits import DEFAULT_MAX_PENDING_TOTAL, PartBudget, parse_max_lag
from rce.protocol.resume import DEFAULT_GRACE, DEFAULT_RESUME_BUFFER
from rce.protocol.session import (DEFAULT_MAX_LAG, DEFAULT_MAX_MESSAGE, DEFAULT_QUEUE_SIZE, ResumeOptions, RobotSession,
                                  SessionLimits)
from rce_robot.front_door import master_away, peer_address, refuse_in_band, relay_name, throttled
from rce_robot.interfaces import RobotInterface
from rce_robot.namespace import CLOSE_POLICY, RobotNamespace
from rce_robot.parse_pool import ParsePool
from rce_robot.rosbridge.endpoint import SESSION_COUNTERS as ROSBRIDGE_COUNTERS
from rce_robot.rosbridge.endpoint import RosbridgeServer
from rce_robot.rosbridge.session import RosbridgeSession
from rce_robot import link_report, ws_link
from rce_robot.link_report import LinkReports, Uplink, crosses_uplink, websocket_link

log = get_logger("rce.robot")
PING_INTERVAL = 20.0     # s between websocket pings to a robot
PING_TIMEOUT = 60.0      # s a robot may leave a ping unanswered before its link counts as lost (slow links)
WS_MAX_QUEUE = 64        # frames the websocket reads ahead of the session
SESSION_OPEN_WAIT = 5.0  # s a master op for a robot whose login was accepted waits for its websocket to open (a robot
                         # that moved here: the master installs its interfaces right after robot_connected)
PROBE_TIMEOUT = 5.0      # s an uplink probe's answers may take (a slower link gives no sample)
STOP_REPORT_S = 1.0      # s a stopping endpoint waits for the master to take a robot's disconnect

#: The ops the master sends a robot task set.
ROBOT_OPS = OpTable("master -> robot task set")


def normalise_password(p: str) -> str:
    """The hex SHA-256 digest from the ``password`` query value. The RCE alpha client sent the raw
    32-byte digest (URL-encoded); docs/design.md, section 3.2, sends its hex form. Both are accepted."""
    if len(p) == 64 and all(c in "0123456789abcdefABCDEF" for c in p):
        return p.lower()
    raw = p.encode("latin-1", errors="replace")
    return raw.hex() if len(raw) == 32 else hashlib.sha256(b"\0invalid").hexdigest()


# RobotSession counter -> (Prometheus counter, help), summed over the sessions, live and ended
SESSION_COUNTERS = {"msgs_in": ("rce_robot_messages_in", "Messages from robots"),
                    "msgs_out": ("rce_robot_messages_out", "Messages to robots"),
                    "dropped": ("rce_robot_dropped", "Messages to robots dropped (queue full)"),
                    "dropped_in": ("rce_robot_dropped_in", "Messages from robots refused (queue full)"),
                    "shed": ("rce_robot_shed", "Topic messages from robots dropped while the endpoint lagged "
                                               "behind them (max_lag)"),
                    "errors": ("rce_robot_errors", "ER messages sent to robots"),
                    "errors_dropped": ("rce_robot_errors_dropped", "ER messages to robots dropped (rate limit, "
                                                                   "or unread)"),
                    "resumes": ("rce_robot_resumes", "Robot sessions resumed on a new link"),
                    "resent": ("rce_robot_resent", "Messages resent to robots after a resume"),
                    "resume_lost": ("rce_robot_resume_lost", "Messages to robots lost from a full resume buffer"),
                    "superseded": ("rce_robot_superseded", "State and bulk topic messages to detached robots "
                                                           "dropped for a newer one of their interface"),
                    "duplicates": ("rce_robot_duplicates", "Messages resent by robots and dropped as duplicates"),
                    "resume_gaps": ("rce_robot_resume_gaps", "Messages from robots lost from their full resume "
                                                             "buffer (numbers skipped at a resume)")}


class Metrics:
    """The endpoint's Prometheus metrics: session counters (those of ended sessions are kept in
    ``ended``), connections, interfaces, the data plane, the outgoing queue depth."""

    def __init__(self, ep: "RobotEndpoint"):
        self.ep = ep
        self.ended: Counter[str] = Counter()
        self.ended_lanes: dict[Lane, Counter] = {lane: Counter() for lane in Lane}     # per lane, ended sessions
        self.registry = r = CollectorRegistry()
        r.register(self)
        Gauge("rce_robot_connections", "Connected robots", registry=r).set_function(lambda: len(ep.namespaces))
        Gauge("rce_robot_interfaces", "Robot-side interfaces", registry=r).set_function(
            lambda: sum(len(n.interfaces) for n in ep.namespaces.values()))
        for k in ("msgs_in", "msgs_out", "bytes_in", "bytes_out", "dropped", "refused", "unauthenticated",
                  "moved_unsent"):
            Gauge(f"rce_robot_dataplane_{k}", f"Data plane {k}", registry=r).set_function(
                lambda k=k: getattr(ep.plane, k))
        Gauge("rce_robot_queue_depth", "Data messages waiting to go to robots", registry=r).set_function(
            lambda: sum(n.session.out_data for n in ep.namespaces.values()))
        Gauge("rce_robot_detached", "Robot sessions kept without a link, waiting for a resume",
              registry=r).set_function(lambda: sum(bool(getattr(n, "detached", False)) for n in ep.namespaces.values()))
        Gauge("rce_robot_pending_binary_bytes", "Bytes of binary parts waiting for their message, all robots",
              registry=r).set_function(lambda: ep.budget.held)
        Gauge("rce_robot_pending_binary_refused", "Binary parts refused for the endpoint's pending-bytes cap",
              registry=r).set_function(lambda: ep.budget.refused)
        Gauge("rce_robot_big_frames_parsed", "Big text frames parsed in a worker process",
              registry=r).set_function(lambda: ep.parser.parsed)
        Gauge("rce_robot_master_available", "1 while registered with a master, 0 while it is away",
              registry=r).set_function(lambda: int(ep.master is not None and ep.master.available))
        Gauge("rce_robot_rosbridge_sessions", "Connected rosbridge v2 clients", registry=r).set_function(
            lambda: len(ep.rosbridge.sessions) if ep.rosbridge is not None else 0)

    def session_ended(self, session: RobotSession) -> None:
        stats = session.stats()
        self.ended.update({k: stats[k] for k in SESSION_COUNTERS})
        for lane, counts in _lane_counts(session).items():
            self.ended_lanes[lane].update(counts)

    def collect(self):
        """(prometheus_client collector) The session counters."""
        live = [n.session.stats() for n in self.ep.namespaces.values()]
        for key, (name, doc) in SESSION_COUNTERS.items():
            yield CounterMetricFamily(name, doc, value=self.ended[key] + sum(s[key] for s in live))
        rosbridge = self.ep.rosbridge.stats() if self.ep.rosbridge is not None else {}
        for key, (name, doc) in ROSBRIDGE_COUNTERS.items():
            yield CounterMetricFamily(name, doc, value=rosbridge.get(key, 0))
        yield CounterMetricFamily("rce_robot_rosbridge_sessions_accepted", "rosbridge v2 clients accepted",
                                  value=rosbridge.get("sessions_total", 0))
        yield from self._lanes()

    def _lanes(self):
        """Per lane (label ``lane``): messages sent whole and their bytes (goodput), drops, and the queue
        delay as a histogram (docs/lanes.md "Metrics")."""
        totals = {lane: Counter(c) for lane, c in self.ended_lanes.items()}
        for ns in self.ep.namespaces.values():
            for lane, counts in _lane_counts(ns.session).items():
                totals[lane].update(counts)
        families = {k: CounterMetricFamily(f"rce_robot_lane_{k}", doc, labels=["lane"])
                    for k, doc in LANE_COUNTERS.items()}
        delay = HistogramMetricFamily("rce_robot_lane_queue_delay_seconds", "Time messages to robots waited in "
                                      "their lane's queue", labels=["lane"])
        for lane, c in totals.items():
            for k, fam in families.items():
                fam.add_metric([lane.value], c[k])
            cum, buckets = 0, []
            for i, bound in enumerate((*DELAY_BOUNDS, float("inf"))):
                cum += c[f"b{i}"]
                buckets.append((str(bound) if bound != float("inf") else "+Inf", cum))
            delay.add_metric([lane.value], buckets, c["delay_sum"])
        yield from families.values()
        yield delay
        yield from self._pacing()

    def _pacing(self):
        """Per session with a paced bulk link (labels ``lane``, ``user``, ``robot``): the rate its bulk
        link is paced to, and the path's rate estimated (docs/lanes.md "Pacing")."""
        rate = GaugeMetricFamily("rce_robot_lane_pacing_rate_bytes", "Bytes/s a robot's bulk link is paced to "
                                 "(configured or estimated)", labels=["lane", "user", "robot"])
        estimate = GaugeMetricFamily("rce_robot_lane_rate_estimate_bytes", "Bytes/s estimated for the path of a "
                                     "robot's bulk link (set once a queue showed it)", labels=["lane", "user", "robot"])
        for (user, robot), ns in self.ep.namespaces.items():
            pacer = ns.session.bulk_pacer
            if pacer is None:
                continue
            labels = [Lane.BULK.value, user, robot]
            rate.add_metric(labels, pacer.rate)
            if pacer.estimator is not None and pacer.estimator.estimate is not None:
                estimate.add_metric(labels, pacer.estimator.estimate)
        yield rate
        yield estimate


LANE_COUNTERS = {"messages_sent": "Messages to robots sent whole, per lane (goodput in messages)",
                 "bytes_sent": "Bytes of messages to robots sent whole, per lane",
                 "dropped": "Topic messages to robots dropped, per lane (each interface keeps its newest)"}


def _lane_counts(session: RobotSession) -> dict[Lane, Counter]:
    """A session's per-lane counters for :class:`Metrics` (queue-delay buckets as ``b0``..)."""
    q = session.out.queue
    out = {}
    for lane, st in q.stats.items():
        c = Counter({"messages_sent": st.sent, "bytes_sent": st.bytes, "dropped": q.lanes[lane].dropped,
                     "delay_sum": st.delay_sum})
        c.update({f"b{i}": n for i, n in enumerate(st.delay_buckets)})
        out[lane] = c
    return out


class RobotEndpoint:
    """One robot task set. ``max_message``: largest websocket frame taken (bytes; larger ones get
    an ER); ``queue_size``: bound of each of a robot's queues (:class:`RobotSession`); ``expiry``: s for
    binary parts; ``master_wait``: s a robot's request waits for an absent master before its ER
    (:class:`~rce.transport.masterlink.MasterLink`); ``grace``: s the session of a robot that opted in to resume
    is kept after its link is lost; ``resume_buffer``: messages kept per robot until it acks them
    (docs/INTERNALS.md "Session resume"); ``max_pending_total``: bytes of binary parts waiting for their
    message, all robots together (:class:`~rce.protocol.limits.PartBudget`); ``ssl_context``: serve wss://
    (and https:// metrics) with it (:func:`rce.transport.tls.server_context`), and tell the master so: the URL it
    registers is ``wss://``;
    ``cluster_key``: proved to the master on every link (:mod:`rce.transport.cluster_auth`), and the source of
    this endpoint's data key; ``max_lag``: s the endpoint may stay behind a robot's frames before it
    sheds that robot's topic messages (:class:`RobotSession`; None: never); ``bulk_rate``: how each
    robot's bulk link is paced (docs/lanes.md "Pacing"): bytes/s, ``"auto"`` or None (the rate estimated
    per link from its socket), ``"off"`` (not paced); ``mptcp``: listen on an MPTCP socket
    where the kernel offers it (:func:`rce.transport.lane_socket.mptcp_socket`); ``ws_impl``: the websocket
    library that serves robots and rosbridge clients (:data:`rce_robot.ws_link.IMPLS`)."""

    def __init__(self, *, name: str, advertise_host: str, max_message: int = DEFAULT_MAX_MESSAGE,
                 queue_size: int = DEFAULT_QUEUE_SIZE, expiry: float = DEFAULT_EXPIRY,
                 master_wait: float = MASTER_WAIT, grace: float = DEFAULT_GRACE,
                 resume_buffer: int = DEFAULT_RESUME_BUFFER, max_pending_total: int = DEFAULT_MAX_PENDING_TOTAL,
                 ssl_context: ssl.SSLContext | None = None, max_lag: float | None = DEFAULT_MAX_LAG,
                 cluster_key: ClusterKey, bulk_rate: Pacing | None = None, mptcp: bool = False,
                 ws_impl: str = ws_link.DEFAULT_IMPL, zone: Zone = CLOUD):
        if ws_impl not in ws_link.IMPLS:
            raise ValueError(f"ws_impl must be one of {', '.join(ws_link.IMPLS)}; got {ws_impl!r}")
        self.ws_impl = ws_impl
        self.zone = zone
        self.name, self.advertise_host = name, advertise_host
        self.ssl_context = ssl_context
        self.cluster_key = cluster_key
        self.max_message, self.queue_size, self.expiry = max_message, queue_size, expiry
        self.grace, self.resume_buffer, self.max_lag = grace, resume_buffer, max_lag
        self.bulk_rate, self.mptcp = bulk_rate, mptcp
        self.listening_mptcp = False            # the websocket server's socket is MPTCP
        self.budget = PartBudget(max_pending_total)      # binary parts waiting, all robots together
        self.parser = ParsePool()                        # big text frames are parsed off the loop
        self.master_wait = master_wait
        self.registry = default_registry()
        load_package_types(self.registry)
        self.plane = DataPlane(f"robot:{name}")
        self.stopping = False             # stop() began: the master is asked a moment only
        self.namespaces: dict[tuple[str, str], RobotNamespace] = {}
        self.by_iid: dict[int, RobotInterface] = {}
        self.opening: dict[tuple[str, str], asyncio.Event] = {}     # logins accepted, websocket not open yet
        self.master: MasterLink | None = None
        self.metrics = Metrics(self)
        self.ws_port = 0
        self.metrics_port = 0
        self._ws_server = None
        self._http: MetricsServer | None = None
        self.rosbridge: RosbridgeServer | None = None
        self.stopped = asyncio.Event()
        self.relays: dict[tuple[str, str], str] = {}      # (user, robot) -> the relay its link goes through now
        self.link_reports = LinkReports(self._tell_link)
        self.uplink = Uplink(self._master_socket,     # on a robot's computer: its link
                             lambda: [s for s in self.plane.link_sockets() if crosses_uplink(s)])
        self._link_task: asyncio.Task | None = None
        self._ping_task: asyncio.Task | None = None
        self._probed_at = float("-inf")   # monotonic s of the last uplink probe
        self._probe_ok = True             # the master answers link probes

    async def start(self, masters: list[Address], bind: str, port: int, data_port: int,
                    metrics_port: int | None = None, rosbridge_port: int | None = None) -> None:
        """Listen (data plane, websocket), then register with one of ``masters`` (control
        addresses; retried with backoff until one takes this task set), then serve metrics and
        rosbridge v2 clients (:mod:`rce_robot.rosbridge.endpoint`; ``rosbridge_port`` None: not served).
        Raises :class:`RCEError` when the master refuses this task set."""
        await self.plane.listen(bind, data_port, self.advertise_host)
        self.plane.data_key = self.cluster_key.data_key(self.plane.addr)
        # frames up to twice the limit are read and refused with an ER; beyond that the socket closes
        sock = self._listen_socket(bind, port) if self.mptcp else None
        self._ws_server = await ws_link.serve(self.ws_impl, self._session, None if sock else bind,
                                              None if sock else port, sock=sock, process_request=self._handshake,
                                              max_size=2 * self.max_message + 1024, ping_interval=PING_INTERVAL,
                                              ping_timeout=PING_TIMEOUT, max_queue=WS_MAX_QUEUE,
                                              ssl_context=self.ssl_context)
        self.ws_port = self._ws_server.sockets[0].getsockname()[1]
        host = f"[{self.advertise_host}]" if ":" in self.advertise_host else self.advertise_host
        scheme = "wss" if self.ssl_context else "ws"
        info = {"kind": "robot", "name": self.name, "host": self.advertise_host, "ws_url": f"{scheme}://{host}:{self.ws_port}/",
                "data_addr": self.plane.addr, "zone": str(self.zone), "zone_user": self.zone.user}
        self.master = MasterLink(masters, ROBOT_OPS.handlers(self), info, report=self._report, on_registered=self._obey,
                                 master_wait=self.master_wait, cluster_key=self.cluster_key)
        await self.master.start()
        if rosbridge_port is not None:
            self.rosbridge = RosbridgeServer(self.master, self.by_iid, self.max_lag, self.ws_impl)
            await self.rosbridge.start(bind, rosbridge_port, self.ssl_context)
        if metrics_port is not None:
            self._http = MetricsServer(self._metrics)
            self.metrics_port = await self._http.start(bind, metrics_port, self.ssl_context)
        self._link_task = asyncio.create_task(self._watch_links(), name="robot-links")
        log.info("robot endpoint up", ws_port=self.ws_port, data_addr=self.plane.addr)

    async def _watch_links(self) -> None:
        """Every :data:`~rce_robot.link_report.EVERY` s, :meth:`_look` at the robots' links. A look
        that fails is logged and the next one goes on: the placer never loses the reports for good."""
        loop = asyncio.get_running_loop()
        while True:
            await asyncio.sleep(link_report.EVERY)
            try:
                self._look(loop.time())
            except Exception:
                log.exception("a look at the robots' links failed; the next one goes on")

    def _look(self, now: float) -> None:
        """Tell the master each robot's measured link (:mod:`rce_robot.link_report`) and its charge
        (read from the ``sensor_msgs/BatteryState`` it publishes) when it moved by
        :data:`~rce_robot.link_report.BATTERY_STEP` points. A charge the master was not there to hear
        is told at the next look, and every charge again after each registration (:meth:`_obey`: a
        master that restarted or took over keeps no charges)."""
        if self.zone.kind == "robot":       # its robot's websocket is local: the robot's link is the uplink
            up = self.uplink.measure(now)
            # its round trip: a ping a look (not behind a probe: it would time the probe's bytes),
            # and after it, when one is due, a probe of its rate (link_report.Uplink.probe_due)
            if up is not None and self.namespaces and (self._ping_task is None or self._ping_task.done()):
                self._ping_task = asyncio.create_task(self._ping_and_probe(), name="uplink ping")
            robots = [(u, r, up) for (u, r) in self.namespaces]
        else:
            robots = [(u, r, websocket_link(ns.ws)) for (u, r), ns in self.namespaces.items()]
        self.link_reports.sample(now, robots)
        for (user, robot), ns in list(self.namespaces.items()):
            if ns.battery is not None and (ns.battery_told is None
                                           or abs(ns.battery - ns.battery_told) >= link_report.BATTERY_STEP):
                if self.master.tell(to_master.RobotBattery(user=user, robot=robot, percent=round(ns.battery, 2))):
                    ns.battery_told = ns.battery

    async def _probe(self) -> None:
        """Probe the uplink's rate (:func:`~rce_robot.link_report.probe_rate`): a ``link_probe`` request
        of :data:`~rce_robot.link_report.PROBE_DRAIN_BYTES` to the master and one of
        :data:`~rce_robot.link_report.PROBE_BYTES` right behind it; a master without the op (older) is
        not probed again."""
        loop = asyncio.get_running_loop()
        done: dict[str, float] = {}

        async def one(name: str, pad: str) -> None:
            await self.master.ask(to_master.LinkProbe(pad=pad), PROBE_TIMEOUT)
            done[name] = loop.time()
        try:
            await asyncio.gather(one("first", "x" * link_report.PROBE_DRAIN_BYTES),
                                 one("second", "x" * link_report.PROBE_BYTES))
        except (ProtocolError, RequestError) as e:     # an older master: unknown op
            self._probe_ok = False
            log.info("the master takes no link probes: the uplink's rate is measured on busy data links only",
                     reason=str(e))
            return
        except RCEError:
            return                        # no master now, or a link too slow for the timeout: no sample
        self.uplink.probed(loop.time(), link_report.probe_rate(done["first"], done["second"]))

    async def _ping_and_probe(self) -> None:
        """Time a ``ping`` request to the master (its round trip: :meth:`Uplink.pinged
        <rce_robot.link_report.Uplink.pinged>`; no sample when it fails or takes over
        :data:`PROBE_TIMEOUT` s), then probe the uplink's rate if a probe is due
        (:meth:`Uplink.probe_due <rce_robot.link_report.Uplink.probe_due>`)."""
        peer = self.master.peer if self.master is not None else None
        if peer is None:
            return                        # no master now: nothing to time
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        try:
            await peer.request("ping", {}, PROBE_TIMEOUT)
        except RCEError:
            return
        self.uplink.pinged(loop.time(), loop.time() - t0)
        if self._probe_ok and self.uplink.probe_due(loop.time(), self._probed_at):
            self._probed_at = loop.time()
            await self._probe()

    def _master_socket(self) -> Any:
        peer = self.master.peer if self.master is not None else None
        return peer.link.writer.get_extra_info("socket") if peer is not None else None


    def _tell_link(self, user: str, robot: str, rtt_ms: float, rate: float) -> None:
        self.master.tell(to_master.RobotLinkReport(user=user, robot=robot, rtt_ms=round(rtt_ms, 3), rate=rate))

    def _listen_socket(self, bind: str, port: int) -> socket.socket:
        """(``mptcp``) The websocket server's listening socket: MPTCP where the kernel offers it, else TCP."""
        family = socket.AF_INET6 if ":" in bind else socket.AF_INET
        sock, self.listening_mptcp = mptcp_socket(family)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((bind, port))
        sock.setblocking(False)
        return sock

    async def stop(self) -> None:
        self.stopping = True
        if self._link_task is not None:
            self._link_task.cancel()
        if self.master and not self.master.available:
            await self.master.close()         # sessions that end now need not wait for an absent master
        # resumable sessions end here, detached ones too (their robots see 1008: nothing to resume); the
        # others end as before, with the server's close (1001)
        await asyncio.gather(*(ns.close("the robot endpoint is stopping") for ns in list(self.namespaces.values())
                               if ns.resumable))
        if self.rosbridge:
            await self.rosbridge.stop()
        if self._ws_server:
            self._ws_server.close()
            await self._ws_server.wait_closed()
        if self.master:
            await self.master.close()
        await self.plane.close()
        self.parser.close()
        if self._http:
            await self._http.close()

    async def _metrics(self) -> bytes:
        return generate_latest(self.metrics.registry)

    # -- websocket -------------------------------------------------------------------------------
    async def _handshake(self, connection, request):
        """Authenticate ``?userID=U&robotID=R&password=P[&resume=1][&maxLag=S]`` before the websocket
        opens, or a resume ``?userID=U&robotID=R&session=TOKEN&ack=N`` (docs/INTERNALS.md "Session
        resume"). ``maxLag``: this connection's ``max_lag`` (s, 0: never shed; :class:`RobotSession`),
        instead of the endpoint's; a value that is not a number of seconds >= 0 is a 400."""
        q = {k: v[0] for k, v in parse_qs(urlsplit(request.path).query, encoding="latin-1").items()}
        connection.rce_lane = None
        if "session" in q:         # a resume (or a bulk link joining) needs no master: the session and token are here
            return self._resume(connection, q)
        if (away := master_away(connection, self.master)) is not None:
            return away
        missing = [k for k in ("userID", "robotID", "password") if not q.get(k)]
        if missing:
            return connection.respond(HTTPStatus.BAD_REQUEST, f"missing query parameter(s): {', '.join(missing)}\n")
        try:
            max_lag = self.max_lag if "maxLag" not in q else parse_max_lag(q["maxLag"])
        except ValueError as e:
            return connection.respond(HTTPStatus.BAD_REQUEST, f"{e}\n")
        user, robot = q["userID"], q["robotID"]
        if not self.zone.serves(user, robot):
            return connection.respond(HTTPStatus.FORBIDDEN, f"this endpoint runs on robot {self.zone.robot}'s "
                                      f"computer and serves that robot alone (zone {self.zone})\n")
        try:
            await self.master.ask(to_master.Auth(user=user, robot=robot, password=normalise_password(q["password"]),
                                                 addr=peer_address(connection)))
        except (AuthError, Throttled) as e:
            if refuse_in_band(q):           # a 2013 client: one ER, then close (_session)
                connection.rce_refused = e.message
                return None
            if isinstance(e, Throttled):
                return throttled(connection, e)
            return connection.respond(HTTPStatus.UNAUTHORIZED, e.message + "\n")
        except RCEError as e:
            return connection.respond(HTTPStatus.SERVICE_UNAVAILABLE, e.message + "\n")
        old = self.namespaces.get((user, robot))
        if old is not None and old.detached:      # a new login (no token) ends the detached session first
            await old.close("a new login replaced this session")
        try:
            login = secrets.token_hex(8)      # names this login's session in robot_disconnected
            await self.master.ask(to_master.RobotConnected(user=user, robot=robot, session=login))
        except RCEError as e:
            return connection.respond(HTTPStatus.CONFLICT, e.message + "\n")
        connection.rce_login = login
        connection.rce_identity, connection.rce_resume = (user, robot), q.get("resume") == "1"
        connection.rce_ack, connection.rce_max_lag, connection.rce_relay = None, max_lag, relay_name(q)
        self.opening.setdefault((user, robot), asyncio.Event())
        return None

    def _resume(self, connection, q: dict):
        """A resume's handshake: the robot's session, its token (else 401, as a bad password) and an
        ``ack`` it can serve (else 400). With ``lane=bulk``, a bulk link joining the session instead (no
        ``ack``: nothing on it is numbered; docs/lanes.md); another lane is a 400."""
        user, robot, token = q.get("userID", ""), q.get("robotID", ""), q["session"]
        ns = self.namespaces.get((user, robot))
        if ns is None or ns.ended or not ns.session.token or \
                not hmac.compare_digest(ns.session.token.encode(), token.encode("utf-8", "replace")):
            return connection.respond(HTTPStatus.UNAUTHORIZED, f"no session to resume for robot {robot!r} of user "
                                                               f"{user!r} (wrong or expired session token)\n")
        if "lane" in q:
            if q["lane"] != Lane.BULK:
                return connection.respond(HTTPStatus.BAD_REQUEST, f"lane must be 'bulk' (the session's own link is "
                                                                  f"its control lane), got {q['lane']!r}\n")
            connection.rce_identity, connection.rce_resume, connection.rce_ack = (user, robot), True, None
            connection.rce_lane = Lane.BULK
            return None
        try:
            ack = int(q.get("ack", "0"))
        except ValueError:
            ack = -1
        if not ns.session.can_resume(ack):
            return connection.respond(HTTPStatus.BAD_REQUEST, f"ack must be the number of the last message the robot "
                                                              f"took, 0 to {ns.session.outgoing.last}; got "
                                                              f"{q.get('ack')!r}\n")
        connection.rce_identity, connection.rce_resume, connection.rce_ack = (user, robot), True, ack
        connection.rce_relay = relay_name(q)
        return None

    async def _session(self, ws) -> None:
        if (refused := getattr(ws, "rce_refused", None)) is not None:
            await self._refuse(ws, refused)
            return
        user, robot = ws.rce_identity
        if ws.rce_lane is not None:            # a bulk link joins the session
            ns = self.namespaces.get((user, robot))
            if ns is None or ns.ended:
                await ws.close(CLOSE_POLICY, "the session to join has ended")
                return
            log.info("bulk link joined", user=user, robot=robot, peer=str(ws.remote_address))
            await ns.serve_bulk(ws, new_pacer(self.bulk_rate))
            return
        if ws.rce_ack is not None:             # a resume
            ns = self.namespaces.get((user, robot))
            if ns is None or ns.ended:         # it ended between the handshake and now
                await ws.close(CLOSE_POLICY, "the session to resume has ended")
                return
            log.info("robot resumed", user=user, robot=robot, ack=ws.rce_ack, peer=str(ws.remote_address),
                     relay=ws.rce_relay or None)
            self._relayed(ns, ws.rce_relay)
            await ns.serve(ws, ws.rce_ack)
            return
        limits = SessionLimits(max_message=self.max_message, queue_size=self.queue_size, expiry=self.expiry,
                               max_lag=ws.rce_max_lag)
        resume = ResumeOptions(grace=self.grace, buffer=self.resume_buffer) if ws.rce_resume else None
        session = RobotSession(robot, limits, resume, budget=self.budget)
        ns = RobotNamespace(user, robot, self.master, session, on_gone=self._session_gone, parser=self.parser)
        ns.login = getattr(ws, "rce_login", None)
        self.namespaces[(user, robot)] = ns
        if (opened := self.opening.pop((user, robot), None)) is not None:
            opened.set()
        log.info("robot connected", user=user, robot=robot, peer=str(ws.remote_address), resume=ws.rce_resume,
                 relay=ws.rce_relay or None, max_lag=ws.rce_max_lag or 0)     # s; 0: never shed
        self._relayed(ns, ws.rce_relay)
        await ns.serve(ws)

    def _relayed(self, ns: RobotNamespace, relay: str) -> None:
        """Tell the master when robot ``ns``'s link goes through another relay (or its own path) than
        before (docs/relays.md): ``robot_relay``."""
        if self.relays.get((ns.user, ns.robot), "") == relay:
            return
        self.relays[(ns.user, ns.robot)] = relay

        async def report() -> None:
            try:
                await self.master.ask(to_master.RobotRelayChanged(user=ns.user, robot=ns.robot, relay=relay))
            except RCEError as e:
                log.warning("could not report the robot's relay", robot=ns.robot, relay=relay, reason=str(e))
        ns.tasks.spawn(report(), name="robot-relay")

    @staticmethod
    async def _refuse(ws, reason: str) -> None:
        """A 2013 client's refused login (:func:`~rce_robot.front_door.refuse_in_band`): the one ER
        it shows, naming the failure, then close 1008 (policy violation)."""
        log.info("login refused in band", peer=str(ws.remote_address), reason=reason)
        text, _ = encode({"type": ER, "data": f"login refused: {reason}"})
        await ws.send(text)
        await ws.close(CLOSE_POLICY, "login refused")

    async def _session_gone(self, ns: RobotNamespace) -> None:
        """A robot's session ended (:class:`RobotNamespace`): forget it and tell the master."""
        user, robot = ns.user, ns.robot
        if self.namespaces.get((user, robot)) is ns:
            del self.namespaces[(user, robot)]
            self.relays.pop((user, robot), None)
        self.metrics.session_ended(ns.session)
        for iid in [i for i, itf in self.by_iid.items() if itf.link is ns]:
            del self.by_iid[iid]
        if not self.master.available:      # stopping, or the master is away: its registration learns it
            log.info("robot disconnected; the master is away and learns it when this task set registers",
                     user=user, robot=robot)
            return
        try:
            # a stopping endpoint waits for the master a moment only: the master may be stopping with it (its
            # parent killed: both get SIGTERM), and a lost task set's robots are gone for the master anyway
            async with asyncio.timeout(STOP_REPORT_S if self.stopping else None):
                await self.master.ask(to_master.RobotDisconnected(user=user, robot=robot, session=ns.login))
        except (RCEError, TimeoutError) as e:
            log.warning("could not report disconnect", robot=robot, reason=str(e) or type(e).__name__)
        log.info("robot disconnected", user=user, robot=robot)

    # -- the master link ---------------------------------------------------------------------------
    def _report(self) -> dict:
        """What this task set holds, for re-registering: its robots (rosbridge clients too, marked with
        their ``rosbridge`` container) and robot-side interfaces."""
        bridged = [{"user": u, "robot": r, "rosbridge": s.ctag}
                   for (u, r), s in (self.rosbridge.sessions.items() if self.rosbridge is not None else ())]
        return {"robots": [{"user": u, "robot": r} for u, r in self.namespaces] + bridged,
                "interfaces": sorted(self.by_iid)}

    async def _obey(self, answer: dict) -> None:
        """A register answer: remove the interfaces and close the robots the master does not have; the
        robots' links and charges are told again at the next look (a master that restarted or took over
        keeps neither)."""
        self.link_reports.last.clear()
        for ns in self.namespaces.values():
            ns.battery_told = None
        for iid in answer.get("drop_interfaces") or []:
            await self._op_remove_interface(ops.EndpointRemoveInterface(iid=iid))
        closing = [self._find(r.get("user"), r.get("robot")) for r in answer.get("close_robots") or []]
        await asyncio.gather(*(ns.close("the master does not know this session (it restarted without it); "
                                        "connect again") for ns in closing if ns is not None))

    # -- master ops --------------------------------------------------------------------------------
    def _find(self, user: str, robot: str) -> RobotNamespace | RosbridgeSession | None:
        """Robot ``robot`` of ``user``: an RCE robot's namespace or a rosbridge client's session."""
        ns = self.namespaces.get((user, robot))
        if ns is None and self.rosbridge is not None:
            return self.rosbridge.sessions.get((user, robot))
        return ns

    def _ns(self, user: str, robot: str) -> RobotNamespace | RosbridgeSession:
        ns = self._find(user, robot)
        if ns is None:
            raise NotFound(f"robot {robot!r} is not connected to this endpoint")
        return ns

    def _iface(self, iid: int) -> RobotInterface:
        iface = self.by_iid.get(iid)
        if iface is None:
            raise NotFound(f"no robot-side interface with id {iid}")
        return iface

    @ROBOT_OPS.op("add_interface", args=ops.EndpointAddInterface)
    async def _op_add_interface(self, args: ops.EndpointAddInterface) -> dict:
        key = (args.user, args.robot)
        opening = self.opening.get(key)
        if opening is not None and key not in self.namespaces:
            try:
                async with asyncio.timeout(SESSION_OPEN_WAIT):
                    await opening.wait()
            except TimeoutError:        # its websocket never opened: the login was abandoned
                self.opening.pop(key, None)
        ns = self._ns(args.user, args.robot)
        itype = InterfaceType.parse(args.itype, robot_side=True)
        iface = RobotInterface(ns, self.plane, self.registry, args.iid, args.itag, itype, args.cls, lane=args.lane)
        await iface.start()
        ns.add_interface(iface)
        self.by_iid[iface.iid] = iface
        return {}

    @ROBOT_OPS.op("remove_interface", args=ops.EndpointRemoveInterface)
    async def _op_remove_interface(self, args: ops.EndpointRemoveInterface) -> dict:
        iface = self.by_iid.pop(args.iid, None)
        if iface:
            iface.link.remove_interface(iface)
            await iface.stop()
            iface.on_peers_changed()
        return {}

    @ROBOT_OPS.op("connect", args=ops.EndpointConnect)
    async def _op_connect(self, args: ops.EndpointConnect) -> dict:
        return {"fenced": self._iface(args.iid).connect(args.peer_iid, args.peer_addr, token_of(args.token),
                                                        args.fence, args.peer_cls)}

    @ROBOT_OPS.op("disconnect", args=ops.EndpointDisconnect)
    async def _op_disconnect(self, args: ops.EndpointDisconnect) -> dict:
        iface = self.by_iid.get(args.iid)
        if iface:
            iface.disconnect(args.peer_iid)
        return {}

    @ROBOT_OPS.op("notify", args=ops.EndpointNotify)
    async def _op_notify(self, args: ops.EndpointNotify) -> None:
        ns = self._find(args.user, args.robot)
        if ns is None:
            return
        if args.type == "ER":
            ns.send_error(str(args.data))
        else:
            ns.send_status(args.data)

    @ROBOT_OPS.op("close_robot", args=ops.EndpointCloseRobot)
    async def _op_close_robot(self, args: ops.EndpointCloseRobot) -> dict:
        await self._ns(args.user, args.robot).close(args.reason)
        return {}
