"""The fleet's simulated robots as ROS 2 robots (``rce-fleet demo --ros2``, ``rce-fleet serve --ros2``).

Each robot of the :class:`~rce_fleet.live.simhost.SimHost` gets a ROS 2 graph of its own: a domain id
leased for the run (:func:`rce_container.ros2_graph.lease_domain`: held by no other robot, container or
test of this machine) with discovery on this host only (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``). On
it run two nodes:

- ``/simulator``, the simulated robot: an rclpy node in the simulator's process, in a context of its
  own on the robot's domain, spun by a thread (:class:`rce_client.ros2_spin.Spinner`). It publishes
  ``/amcl_pose`` (``geometry_msgs/msg/PoseWithCovarianceStamped``; reliable, transient local, depth 1,
  as Nav2's amcl), ``/obstacles`` (``geometry_msgs/msg/PoseArray``), ``/battery``
  (``sensor_msgs/msg/BatteryState``, with batteries), and while something subscribes ``/odom``
  (``nav_msgs/msg/Odometry``) and ``/scan`` (``sensor_msgs/msg/LaserScan``; best effort, depth 5: the
  sensor-data QoS of lidar drivers). It takes goals on ``/move_base_simple/goal``
  (``geometry_msgs/msg/PoseStamped``) and cancels on ``/move_base/cancel`` (``actionlib_msgs/msg/GoalID``).
  The messages are CDR built by rce's registry (:meth:`rce.messages.MessageRegistry.json_to_bytes`) and
  published as bytes; what it takes reaches the simulator's loop through a bounded handoff per topic
  (:class:`rce_client.ros1_bridge.Handoff`: 100 in flight, more dropped and counted).
- ``/RobotN``, its bridge to the cloud: ``rce-ros CONFIG --ros2``, a process of its own (tied to this
  one: it ends when this process does), with the robot's config whose robot-side interfaces name ROS 2
  classes (:func:`rce_fleet.configs.ros2_config`). The cloud's ends keep their ROS 1 classes; the engine
  converts between the two, at the sending end. Its output goes to ``RobotN.log`` in the work
  directory's ``ros2/``; the counts per interface it prints at its stop are kept (:meth:`Ros2Robots.summary`).

The fleet's own messages (``fleet/Clearance``, ``fleet/MoveProgress``, ``fleet/FleetState``...) never
reach a robot: they stay ROS 1, between the cloud's nodes and the operators.

rcl takes ``ROS_AUTOMATIC_DISCOVERY_RANGE`` from the environment only, so :class:`Ros2Robots` sets it in
this process (and ``ROS_LOG_DIR``, unless set, to the run's ``ros2/log``).
"""
from __future__ import annotations

import asyncio
import collections
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

from rce.interfaces.qos import parse_qos
from rce.plumbing.errors import MessageError
from rce.plumbing.log import get_logger
from rce.plumbing.process import popen_tied
from rce.plumbing.tasks import Tasks

from ..configs import ros2_config

log = get_logger("fleet.ros2")

NODE = "simulator"           # the simulated robot's node on each robot's graph
RANGE = "LOCALHOST"          # ROS_AUTOMATIC_DISCOVERY_RANGE of every robot's graph
HANDOFF_LIMIT = 100          # messages per topic on their way from rclpy's thread to the loop
BRIDGE_GRACE_S = 5.0         # s beyond rce-ros's own --timeout that its "ready" may take (its start-up)
OUTPUT_LINES = 30            # last lines of each rce-ros kept for the reason of a failure
LINE_LIMIT = 1 << 20         # bytes in one line of rce-ros's output (a longer one is cut)
CLOSE_TIMEOUT_S = 5.0        # s a node's executor gets to stop
#: QoS profiles (:data:`rce.interfaces.qos.PROFILES`) of the simulated robot's publishers, as a TurtleBot's ROS 2
#: drivers have them: Nav2's amcl keeps the last pose for late subscribers (reliable, transient local, depth 1:
#: ``map``), lidar drivers publish sensor data (best effort, depth 5). Not named: rclpy's default (reliable,
#: volatile, depth 10), the subscriptions' too.
QOS = {"pose": "map", "scan": "sensor_data"}
COUNTS = re.compile(r"rce-ros: ROS 2 (\S+): (\d+) from ROS 2, (\d+) to ROS 2, (\d+) dropped, (\d+) failed"
                    r"(?:, (\d+) lost on the robot's graph)?")
NOT_SENT = re.compile(r"rce-ros: (\S+): (\d+) message\(s\) not sent to the cloud")


def rce_ros_command() -> list[str]:
    """argv prefix of ``rce-ros``: the script beside this interpreter, else ``python -m``."""
    script = Path(sys.executable).parent / "rce-ros"
    return [str(script)] if script.is_file() else [sys.executable, "-m", "rce_client.rce_ros"]


def _qos(name: str) -> Any:
    """rclpy's QoS profile of the robot's topic ``name`` (:data:`QOS`)."""
    from rce.ros2.classes import qos_profile
    return qos_profile(parse_qos(QOS[name]) if name in QOS else None)


class Ros2Port:
    """A topic the simulated robot publishes on its ROS 2 graph: :meth:`publish` CDR bytes;
    :meth:`wanted`: does a subscription on the graph match it? ``sent`` counts what was published."""

    __slots__ = ("pub", "sent")

    def __init__(self, pub: Any):
        self.pub, self.sent = pub, 0

    def publish(self, payload: bytes) -> None:
        self.pub.publish(payload)
        self.sent += 1

    def wanted(self) -> bool:
        return self.pub.get_subscription_count() > 0


class Ros2Robot:
    """One ROS 2 robot: its domain lease, its ``/simulator`` node (:attr:`spinner`), its publishers
    (:attr:`ports`), what it took (:attr:`counts`, topic -> :class:`rce_client.ros1_bridge.Counts`;
    ``bad``: bytes that were not their class) and its rce-ros process (:attr:`proc`, the counts it printed
    at its stop in :attr:`bridged`: iTag -> (from ROS 2, to ROS 2, dropped, failed, lost on the robot's
    graph))."""

    def __init__(self, rid: str, lease: Any):
        self.rid, self.lease = rid, lease
        self.domain: int = lease.domain
        self.spinner: Any = None
        self.ports: dict[str, Ros2Port] = {}
        self.counts: dict[str, Any] = {}
        self.proc: subprocess.Popen | None = None
        self.reader: asyncio.Task | None = None      # reads its output; ends with it (its exit code)
        self.ready = asyncio.Event()
        self.output: collections.deque[str] = collections.deque(maxlen=OUTPUT_LINES)
        self.bridged: dict[str, tuple[int, int, int, int]] = {}
        self.not_sent: dict[str, int] = {}             # iTag -> messages rce-ros did not send (before its link was up)
        self.started = time.monotonic()                # its rce-ros's start (monotonic s)
        self.node_s = 0.0                              # wall s its node took to start

    def start_node(self, topics: list[tuple[str, str, str]],
                   commands: list[tuple[str, str, Callable[[bytes], bool]]], loop: asyncio.AbstractEventLoop) -> None:
        """Blocking (call it in a thread): the node on the robot's domain, a publisher per topic
        (name, topic, class), a raw subscription per command (topic, class, handler run in ``loop``)."""
        from rce_client.ros1_bridge import Counts, Handoff
        from rce_client.ros2_spin import Spinner
        from rce_client.ros2_types import rclpy_class
        self.spinner = Spinner(NODE, domain_id=self.domain)
        self.spinner.start()
        node = self.spinner.node
        for name, topic, cls in topics:
            self.ports[name] = Ros2Port(node.create_publisher(rclpy_class(name, cls), topic, _qos(name)))
        for topic, cls, handler in commands:
            counts = self.counts[topic] = Counts()
            hand = Handoff(loop, self._taker(topic, cls, handler, counts), counts, HANDOFF_LIMIT)
            node.create_subscription(rclpy_class(topic, cls), topic, hand.offer, _qos(topic), raw=True,
                                     callback_group=self.spinner.group)

    def _taker(self, topic: str, cls: str, handler: Callable[[bytes], bool], counts: Any) -> Callable[[bytes], None]:
        def take(payload: bytes) -> None:
            try:
                handler(payload)
            except MessageError as e:
                counts.add(bad=1)
                log.warning("message refused", robot=self.rid, topic=topic, cls=cls, reason=str(e))
        return take

    def close(self) -> None:
        """Blocking: destroy the node, shut its context down, give the domain back."""
        try:
            if self.spinner is not None:
                self.spinner.close(CLOSE_TIMEOUT_S)
        finally:
            self.lease.release()


class Ros2Robots:
    """The simulator's robots as ROS 2 robots (see the module doc): :meth:`connect` each, :meth:`stop`
    all. ``workdir``: where the bridges' configs and output go (made 0700: the configs hold the fleet's
    password); ``out(line)``: prints a robot's domain once its bridge is up; ``lease``: leases a
    domain (default :func:`rce_container.ros2_graph.lease_domain`)."""

    def __init__(self, workdir: Path, out: Callable[[str], None] = lambda line: print(line, flush=True),
                 lease: Callable[[], Any] | None = None):
        self.dir = Path(workdir)
        self.dir.mkdir(mode=0o700, parents=True, exist_ok=True)
        self.out = out
        if lease is None:
            from rce.ros2.domains import lease_domain as lease
        self._lease = lease
        self.robots: dict[str, Ros2Robot] = {}
        self.tasks = Tasks("fleet-ros2")
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = RANGE       # rcl reads it from the environment only
        os.environ.setdefault("ROS_LOG_DIR", str(self.dir / "log"))

    async def connect(self, bot: Any, config: dict, master_url: str, timeout: float,
                      topics: list[tuple[str, str, str]], commands: list[tuple[str, str, Callable[[bytes], bool]]]
                      ) -> Ros2Robot:
        """Make ``bot`` (a :class:`~rce_fleet.live.simhost.SimBot`) a ROS 2 robot: lease its domain, start
        its node (it publishes from now on: ``bot.ports``, ``bot.live``), then its ``rce-ros --ros2`` with
        ``config`` (its robot config, made ROS 2 here) logging in at ``master_url``; returns when the
        bridge's interfaces are up (within ``timeout`` s, its ``--timeout``). ``bot.task`` ends when the
        bridge's process does. Raises RuntimeError with rce-ros's reason when it fails."""
        rid = bot.rid
        lease = await asyncio.to_thread(self._lease)
        robot = self.robots[rid] = Ros2Robot(rid, lease)
        bot.ros2 = robot
        t0 = time.monotonic()
        await asyncio.to_thread(robot.start_node, topics, commands, asyncio.get_running_loop())
        robot.node_s = time.monotonic() - t0
        bot.ports, bot.live = robot.ports, True
        path = self.dir / f"{rid.lower()}.config"
        path.touch(mode=0o600)
        path.write_text(json.dumps(ros2_config(config) | {"url": master_url}, indent=2))
        env = dict(os.environ, ROS_DOMAIN_ID=str(robot.domain), ROS_AUTOMATIC_DISCOVERY_RANGE=RANGE)
        logfile = open(self.dir / f"{rid}.log", "wb")
        try:
            robot.proc = await asyncio.to_thread(
                popen_tied, [*rce_ros_command(), str(path), "--ros2", "--timeout", f"{timeout:g}"],
                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, start_new_session=True)
        except OSError:
            logfile.close()
            raise
        robot.started = time.monotonic()
        bot.task = robot.reader = self.tasks.spawn(self._read(robot, logfile), name=f"rce-ros-{rid}")
        ready = self.tasks.spawn(robot.ready.wait(), name=f"ready-{rid}")
        done, _ = await asyncio.wait({ready, bot.task}, timeout=timeout + BRIDGE_GRACE_S,
                                     return_when=asyncio.FIRST_COMPLETED)
        if ready not in done:
            ready.cancel()
            said = [ln for ln in robot.output if ln.startswith("rce-ros:")]
            how = f"exited with {robot.proc.poll()}" if bot.task.done() else f"not ready within {timeout:g} s"
            raise RuntimeError(f"{rid}: cannot connect to the cloud: rce-ros --ros2 {how}"
                               f"{': ' + said[-1] if said else ''} (see {self.dir / (rid + '.log')})")
        self.out(f"rce-fleet: {rid}: a ROS 2 robot on domain {robot.domain} (ROS_DOMAIN_ID={robot.domain} "
                 f"ROS_AUTOMATIC_DISCOVERY_RANGE={RANGE}): /{NODE} and its bridge rce-ros --ros2 "
                 f"(pid {robot.proc.pid})")
        return robot

    async def _read(self, robot: Ros2Robot, logfile) -> int:
        """Tee rce-ros's output to its log, note its ready line and its counts; its exit code at the end."""
        loop = asyncio.get_running_loop()
        reader = asyncio.StreamReader(limit=LINE_LIMIT)
        transport, _ = await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), robot.proc.stdout)
        try:
            while True:
                try:
                    raw = await reader.readline()
                except ValueError:                     # a line over LINE_LIMIT: its start is gone, go on
                    raw = b"(a line too long to keep)\n"
                if not raw:
                    break
                logfile.write(raw)
                line = raw.decode(errors="replace").rstrip()
                robot.output.append(line)
                if line.startswith("rce-ros: ready"):
                    robot.ready.set()
                    log.info("ROS 2 robot up", robot=robot.rid, domain=robot.domain, node_s=round(robot.node_s, 2),
                             bridge_s=round(time.monotonic() - robot.started, 2))
                elif (m := COUNTS.match(line)) is not None:
                    robot.bridged[m.group(1)] = tuple(int(x or 0) for x in m.groups()[1:])
                elif (m := NOT_SENT.match(line)) is not None:
                    robot.not_sent[m.group(1)] = int(m.group(2))
        finally:
            transport.close()
            logfile.close()
        return await asyncio.to_thread(robot.proc.wait)

    async def stop(self, timeout: float) -> None:
        """Stop every bridge (SIGTERM: rce-ros removes its interfaces and prints its counts; SIGKILL after
        ``timeout`` s), then every node, and give the domains back."""
        procs = [r.proc for r in self.robots.values() if r.proc is not None and r.proc.poll() is None]
        for p in procs:
            p.send_signal(signal.SIGTERM)
        readers = [r.reader for r in self.robots.values() if r.reader is not None and not r.reader.done()]
        if procs:
            await asyncio.to_thread(_wait_all, procs, timeout)
        if readers:
            await asyncio.wait(readers, timeout=timeout)
        for r in self.robots.values():
            await asyncio.to_thread(r.close)
        await self.tasks.cancel_all()
        if self.robots:
            self.out(self.summary())

    def summary(self) -> str:
        """One line: the robots' domains, what their bridges carried each way, dropped and failed (and the
        messages they took from ROS 2 before their interfaces were connected: not sent on; and those the
        robots' middleware reported lost before the bridges took them), and what
        the simulated robots published and took (their messages' counts)."""
        rows = [v for r in self.robots.values() for v in r.bridged.values()]
        from_ros, to_ros, dropped, failed, lost = (sum(col) for col in zip(*rows, (0,) * 5, strict=True))
        not_sent = sum(n for r in self.robots.values() for n in r.not_sent.values())
        sent = sum(p.sent for r in self.robots.values() for p in r.ports.values())
        took = sum(c.from_ros for r in self.robots.values() for c in r.counts.values())
        refused = sum(c.dropped + c.bad for r in self.robots.values() for c in r.counts.values())
        domains = ", ".join(f"{rid} {r.domain}" for rid, r in self.robots.items())
        return (f"rce-fleet: ROS 2 robots (domains {domains}): their rce-ros --ros2 carried {from_ros} messages from "
                f"ROS 2 to the cloud ({not_sent} of them before their interfaces were connected: not sent on) and "
                f"{to_ros} to ROS 2, {dropped} dropped, {failed} failed ({lost} lost on the robots' graphs, their "
                f"QoS keeping the newest); the robots published {sent} and took {took} ({refused} dropped or refused)")


def _wait_all(procs: list[subprocess.Popen], timeout: float) -> None:
    """Wait for ``procs`` to end, together within ``timeout`` s; SIGKILL (the process group) those that do not."""
    deadline = time.monotonic() + timeout
    for p in procs:
        try:
            p.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            log.warning("rce-ros did not stop in time: killed", pid=p.pid)
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()

