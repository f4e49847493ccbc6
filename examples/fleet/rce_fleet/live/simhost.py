"""The fleet simulator host: one :class:`rce_fleet.sim.SimWorld`, and per simulated robot
the rce-ros bridge IN-PROCESS (:class:`rce_client.rce_ros.RobotBridge`, the code
``rce-ros CONFIG`` runs, without a socket: one local :class:`rce.bus.core.Bus` per robot).

Each robot, on its own local bus, like a TurtleBot running ``amcl`` and ``move_base``:

* publishes ``/amcl_pose`` (geometry_msgs/PoseWithCovarianceStamped, the localisation
  stand-in with its covariance, 5 Hz sim time), ``/obstacles`` (geometry_msgs/PoseArray:
  lidar hits the static map does not explain, within 2 m, 1 Hz, only when there are
  some), and ``/odom`` (nav_msgs/Odometry, 10 Hz) and ``/scan`` (sensor_msgs/LaserScan,
  5 Hz) when something on its bus subscribes to them;
* publishes ``/battery`` (sensor_msgs/BatteryState, 1 Hz sim time) when the host simulates
  batteries (``battery``: :class:`rce_fleet.operations.battery.BatteryParams`): it drains by the metres
  driven and the seconds passed, and charges while the robot stands still in a charger cell
  (``chargers``); a flat battery stops the robot;
* drives to the goals it gets on ``/move_base_simple/goal`` (geometry_msgs/PoseStamped)
  with its own local planner (:class:`rce_fleet.sim.LocalNavigator`: DWA with obstacle
  avoidance) and stops on ``/move_base/cancel`` (actionlib_msgs/GoalID).

Its robot config (:func:`rce_fleet.configs.robot_config`) bridges these to the fleet
container. Simulated time runs ``speedup`` times faster than wall time: every tick
advances the world by ``dt`` s of sim time and waits until ``dt / speedup`` s of wall time
have passed (when the host cannot keep up, sim time simply runs slower; publish rates
are in sim time). Cells the operator blocks (from ``/fleet/state``, :meth:`set_blocked`)
become box obstacles, placed as soon as no robot is inside the box's footprint.

Ground truth for tests and reports, checked every physics substep: the smallest distance
between two robots, every cell each robot's centre entered and when, its driven path.

With ``ros2`` (:class:`rce_fleet.live.ros2_robots.Ros2Robots`, ``rce-fleet demo --ros2``) each robot is
a ROS 2 robot instead: the same topics in ROS 2's classes (:data:`TOPICS`, :data:`COMMANDS`; the
messages CDR) on a ROS 2 graph of its own, bridged by an ``rce-ros --ros2`` process.
"""
from __future__ import annotations

import asyncio
import heapq
import itertools
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from rce.protocol.config import parse_config
from rce.plumbing.log import get_logger
from rce.messages import MessageRegistry
from rce.plumbing.tasks import Tasks
from rce_client.rce_ros import RobotBridge

from ..configs import ros2_class
from ..operations.battery import BATTERY_TOPIC, T_BATTERY, Battery, BatteryParams
from ..maps.geometry import GridGeometry, quaternion_from_yaw
from .points_wire import PointsWire
from ..sim.local_nav import LocalNavigator
from ..sim.obstacles import ObstacleDetector
from ..sim.world import SimWorld

log = get_logger("fleet.sim")

OWNER = "/simulator"
T_POSE, T_OBST = "geometry_msgs/PoseWithCovarianceStamped", "geometry_msgs/PoseArray"
T_ODOM, T_SCAN = "nav_msgs/Odometry", "sensor_msgs/LaserScan"
T_GOAL, T_CANCEL = "geometry_msgs/PoseStamped", "actionlib_msgs/GoalID"
#: what a robot publishes: (name, topic, ROS 1 class); a ROS 2 robot's classes are their ROS 2 forms
TOPICS = (("pose", "/amcl_pose", T_POSE), ("obstacles", "/obstacles", T_OBST), ("odom", "/odom", T_ODOM),
          ("scan", "/scan", T_SCAN), ("battery", BATTERY_TOPIC, T_BATTERY))
#: what a robot takes: (name, topic, ROS 1 class)
COMMANDS = (("goal", "/move_base_simple/goal", T_GOAL), ("cancel", "/move_base/cancel", T_CANCEL))

#: s a robot's bridge may take to log in and bring its node and interfaces up (the bridge's
#: own setup timeout; :meth:`SimHost.connect` waits ``BRIDGE_GRACE_S`` longer, so the
#: bridge's own reason is the one reported).
CONNECT_TIMEOUT_S = 60.0
BRIDGE_GRACE_S = 5.0
#: s the bridges get at :meth:`SimHost.stop` to remove their nodes and interfaces before
#: they are cancelled.
STOP_TIMEOUT_S = 10.0
#: wall s the sim loop may fall behind its schedule before it re-anchors (sim time then runs
#: slower; it never bursts to catch up).
MAX_LAG_S = 0.5
#: lidar points per ``/obstacles`` message; further points are dropped (counted in
#: ``SimHost.obstacle_points_dropped``).
MAX_OBSTACLE_POINTS = 120
#: m/s above which a robot counts as moving (its motion starts are kept for goal -> motion delays)
MOVING_M = 0.02


class BusPort:
    """A robot's topic on its local bus: :meth:`publish` a message's bytes; :meth:`wanted`: does
    anything subscribe to it?"""

    __slots__ = ("bus", "topic")

    def __init__(self, bus, topic):
        self.bus, self.topic = bus, topic

    def publish(self, payload: bytes) -> None:
        self.bus.publish(self.topic, payload)

    def wanted(self) -> bool:
        return bool(self.topic.subscriptions)


def _stamp(sim_time: float) -> dict:
    return {"secs": int(sim_time), "nsecs": int(round((sim_time % 1.0) * 1e9)) % 1_000_000_000}


@dataclass
class SimBot:
    """One simulated robot: the physics body, its navigator, its bridge and ground truth. ``ports``:
    name (:data:`TOPICS`) -> where it publishes (a :class:`BusPort`, or a ROS 2 publisher's port);
    ``live``: it publishes (its bridge is up; a ROS 2 robot, once its node is); ``task`` ends when its
    bridge does; ``bridge``: the in-process bridge (None for a ROS 2 robot, whose bridge is a process:
    ``ros2``, a :class:`rce_fleet.live.ros2_robots.Ros2Robot`)."""
    rid: str
    robot: object
    nav: LocalNavigator
    start_cell: int
    bridge: RobotBridge | None = None
    task: asyncio.Task | None = None
    ports: dict = field(default_factory=dict)
    live: bool = False
    ros2: object | None = None
    last_scan: tuple | None = None
    goals_received: int = 0
    cancels_received: int = 0
    cells: list[tuple[float, int]] = field(default_factory=list)    # (sim time, cell entered)
    trace: list[tuple[float, float, float]] = field(default_factory=list)   # (t, x, y)
    distance: float = 0.0
    last_goal: tuple[float, float] | None = None
    battery: Battery | None = None
    last_xy: tuple[float, float] | None = None
    moving: bool = False
    motion_starts: list[float] = field(default_factory=list)         # sim times it began to move from standing
    motion_stops: list[float] = field(default_factory=list)          # sim times it came to a stand


class SimHost:
    """See the module docstring. ``occ_map``: the :class:`rce_fleet.maps.occupancy.OccupancyMap`;
    ``geometry``: the grid; ``registry``: one message registry shared by all bridges; ``ros2``: the
    robots are ROS 2 robots (:class:`rce_fleet.live.ros2_robots.Ros2Robots`), None: on local buses."""

    def __init__(self, occ_map, geometry: GridGeometry, registry: MessageRegistry, *, seed: int = 0,
                 speedup: float = 1.0, dt: float = 0.1, scan_every: int = 2, pose_every: int = 2,
                 obstacles_every: int = 10, box_margin: float = 0.1, obstacle_range: float = 2.0,
                 publish_obstacles: bool = True, battery: BatteryParams | None = None,
                 chargers: list[int] = (), battery_every: int = 10, ros2=None):
        if speedup <= 0:
            raise ValueError("speedup must be > 0")
        self.map, self.geo, self.registry = occ_map, geometry, registry
        self.world = SimWorld(occ_map, seed=seed)
        self.detector = ObstacleDetector(occ_map)
        self.rng = np.random.default_rng(seed)
        self.speedup, self.dt = float(speedup), float(dt)
        self.scan_every, self.pose_every, self.obstacles_every = scan_every, pose_every, obstacles_every
        self.box_margin, self.obstacle_range = box_margin, obstacle_range
        self.publish_obstacles = publish_obstacles
        self.battery, self.chargers, self.battery_every = battery, set(chargers), battery_every
        self.bots: dict[str, SimBot] = {}
        self.ticks = 0
        self.min_pair = math.inf
        self.min_pair_at: tuple[float, str, str] | None = None
        self.boxes: dict[int, str] = {}          # cell -> box id, placed
        self.pending_boxes: set[int] = set()     # wanted, not yet placed (a robot is there)
        self.wall_per_sim: list[float] = []
        self.lag_resets = 0
        self._timers: list = []
        self.tick_hooks: list[Callable[[], None]] = []     # called after every tick (e.g. the radio links)
        self._timer_ids = itertools.count()
        self.obstacle_points_dropped = 0
        self.tasks = Tasks("fleet-sim")          # the sim loop, the bridges
        self._task: asyncio.Task | None = None
        self._stopping = False
        self.radius = self.world.robot_params.radius
        self.ros2 = ros2
        self._points_wire = PointsWire("map", ros2=ros2 is not None)
        form = ros2_class if ros2 is not None else str
        #: name (TOPICS, COMMANDS) -> the robots' class there and its registry type
        self.classes = {name: form(cls) for name, _, cls in TOPICS + COMMANDS}
        self._types = {name: registry.msg_type(cls) for name, cls in self.classes.items()}

    @property
    def time(self) -> float:
        """Simulated time, s."""
        return self.world.time

    # -- robots ----------------------------------------------------------------------------------
    def spawn(self, rid: str, cell: int, yaw: float | None = None) -> SimBot:
        """Put robot ``rid`` at the centre of ``cell`` (random heading unless ``yaw``)."""
        x, y = self.geo.center(cell)
        yaw = float(self.rng.uniform(-math.pi, math.pi)) if yaw is None else yaw
        robot = self.world.add_robot(rid, x, y, yaw)
        bot = SimBot(rid, robot, LocalNavigator(obstacle_detector=self.detector), cell)
        if self.battery is not None:
            level = self.battery.initial - self.battery.initial_spread * float(self.rng.uniform())
            bot.battery = Battery(self.battery, wh=level * self.battery.capacity_wh)
        bot.last_xy = (x, y)
        bot.cells.append((self.time, cell))
        bot.trace.append((self.time, x, y))
        self.bots[rid] = bot
        return bot

    async def connect(self, rid: str, config: dict, master_url: str, timeout: float = CONNECT_TIMEOUT_S,
                      **bridge_kw) -> None:
        """Connect robot ``rid`` to the cloud with ``config`` (its robot config dict) through an
        in-process rce-ros bridge (``bridge_kw``: more :class:`~rce_client.rce_ros.RobotBridge` keywords,
        e.g. its relay or routes); returns when its interfaces are up. Raises RuntimeError
        with the bridge's reason when it fails. A ROS 2 robot (``ros2``) is connected by its
        :meth:`~rce_fleet.live.ros2_robots.Ros2Robots.connect` (no ``bridge_kw``)."""
        bot = self.bots[rid]
        if self.ros2 is not None:
            if bridge_kw:
                raise ValueError(f"{rid}: a ROS 2 robot's bridge is an rce-ros process: no {', '.join(bridge_kw)}")
            await self.ros2.connect(bot, config, master_url, timeout, self._topics(), self._commands(bot))
            return
        source = f"<{rid} config>"
        errors: list[str] = []

        def err(line: str) -> None:
            errors.append(line)
            log.warning("bridge", robot=rid, line=line)

        bridge = RobotBridge(parse_config(config, source), source, None, timeout=timeout, url=master_url,
                             registry=self.registry, out=lambda line: log.debug("bridge", robot=rid, line=line),
                             err=err, **bridge_kw)
        bot.bridge = bridge
        bus = bridge.bus
        bot.ports = {name: BusPort(bus, bus.advertise(topic, cls, OWNER)) for name, topic, cls in self._topics()}
        for topic, cls, handler in self._commands(bot):
            bus.subscribe(topic, cls, handler, OWNER, 100)
        bot.task = self.tasks.spawn(bridge.run(), name=f"bridge-{rid}")
        ready = self.tasks.spawn(bridge.ready.wait(), name=f"ready-{rid}")
        done, _ = await asyncio.wait({ready, bot.task}, timeout=timeout + BRIDGE_GRACE_S,
                                     return_when=asyncio.FIRST_COMPLETED)
        if ready not in done:
            ready.cancel()
            why = errors[-1] if errors else f"interfaces not up within {timeout:g} s"
            raise RuntimeError(f"{rid}: cannot connect to the cloud: {why}")
        bot.live = True

    def _topics(self) -> list[tuple[str, str, str]]:
        """What every robot publishes: (name, topic, class) (:data:`TOPICS`, in the robots' form)."""
        return [(name, topic, self.classes[name]) for name, topic, _ in TOPICS]

    def _commands(self, bot: SimBot) -> list[tuple[str, str, Callable[[bytes], bool]]]:
        """What ``bot`` takes: (topic, class, handler of a message's bytes) (:data:`COMMANDS`). A handler
        raises :class:`rce.plumbing.errors.MessageError` for bytes that are not its class."""
        reg, goal_t, cancel_t = self.registry, self._types["goal"], self._types["cancel"]

        def on_goal(payload: bytes) -> bool:
            m = reg.deserialize(goal_t, payload)
            p = m.pose.position
            bot.goals_received += 1
            bot.last_goal = (float(p.x), float(p.y))
            bot.nav.set_goal(float(p.x), float(p.y))
            return True

        def on_cancel(payload: bytes) -> bool:
            reg.deserialize(cancel_t, payload)
            bot.cancels_received += 1
            bot.nav.cancel()
            bot.robot.cmd_vel(0.0, 0.0)
            return True
        handlers = {"goal": on_goal, "cancel": on_cancel}
        return [(topic, self.classes[name], handlers[name]) for name, topic, _ in COMMANDS]

    # -- blocked cells ---------------------------------------------------------------------------
    def set_blocked(self, blocked: dict[int, str]) -> None:
        """The fleet's blocked cells (cell -> source). Cells blocked by the operator (any source
        but ``lidar:...``, which is an obstacle already there) get a box; unblocked ones lose it."""
        want = {int(c) for c, src in blocked.items() if not str(src).startswith("lidar")}
        for c in list(self.boxes):
            if c not in want:
                self.world.remove_box(self.boxes.pop(c))
        self.pending_boxes = {c for c in want if c not in self.boxes}
        self._place_boxes()

    def _box(self, cell: int) -> tuple[float, float, float, float]:
        x, y = self.geo.center(cell)
        m = self.box_margin
        return x, y, max(self.geo.cell_w_m - 2 * m, 0.1), max(self.geo.cell_h_m - 2 * m, 0.1)

    def _place_boxes(self) -> None:
        for c in sorted(self.pending_boxes):
            x, y, w, h = self._box(c)
            r = self.radius + 0.02
            clear = True
            for bot in self.bots.values():
                px, py, _ = bot.robot.pose()
                if abs(px - x) < w / 2 + r and abs(py - y) < h / 2 + r:
                    clear = False
                    break
            if clear:
                box_id = f"cell{c}"
                self.world.add_box(box_id, x, y, w, h)
                self.boxes[c] = box_id
                self.pending_boxes.discard(c)
                log.info("box placed", cell=c, t=round(self.time, 2))

    # -- time ------------------------------------------------------------------------------------
    def at(self, sim_time: float, callback: Callable[[], None]) -> None:
        """Run ``callback()`` in the sim loop once sim time reaches ``sim_time`` s."""
        heapq.heappush(self._timers, (sim_time, next(self._timer_ids), callback))

    def start(self) -> None:
        """Start the sim loop (a task on the running event loop)."""
        if self._task is None:
            self._task = self.tasks.spawn(self._run(), name="sim-loop")

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        wall0, sim0 = loop.time(), self.time
        while not self._stopping:
            t0 = loop.time()
            self._tick()
            self.wall_per_sim.append(loop.time() - t0)
            if len(self.wall_per_sim) > 200:
                del self.wall_per_sim[:100]
            target = wall0 + (self.time - sim0) / self.speedup
            now = loop.time()
            if now - target > MAX_LAG_S:           # cannot keep up: re-anchor, never burst to catch up
                wall0, sim0 = now, self.time
                self.lag_resets += 1
                await asyncio.sleep(0)
            else:
                await asyncio.sleep(max(0.0, target - now))

    def _tick(self) -> None:
        k = self.ticks
        dt = self.dt
        bots = list(self.bots.values())
        for bot in bots:
            r = bot.robot
            est = r.localisation()
            pose = est[:3]
            driving = bot.nav.state in ("driving", "blocked")
            scan = None
            if k % self.scan_every == 0 and (driving or k % self.obstacles_every == 0
                                             or "scan" in bot.ports and bot.ports["scan"].wanted()):
                scan = r.scan()
                bot.last_scan = (scan, pose, k)
            v, w = bot.nav.update(pose, dt, scan)
            if bot.battery is not None and bot.battery.flat:
                v, w = 0.0, 0.0                       # a flat battery: it cannot move
            r.cmd_vel(v, w)
        # physics, with the ground-truth distance check every substep
        sub = self.world.substep
        n = max(1, int(round(dt / sub)))
        for _ in range(n):
            self.world.step(sub)
            if len(bots) > 1:
                d = self.world.min_pair_distance()
                if d < self.min_pair:
                    self.min_pair = d
                    self.min_pair_at = (self.time, *self._closest_pair())
        t = self.time
        for bot in bots:
            x, y, _ = bot.robot.pose()
            lt, lx, ly = bot.trace[-1]
            step = math.hypot(x - lx, y - ly)
            if step > 0.05 or t - lt > 1.0:
                bot.distance += step
                bot.trace.append((t, x, y))
            c = self.geo.cell_of(x, y)
            if c is not None and c != bot.cells[-1][1]:
                bot.cells.append((t, c))
            lx, ly = bot.last_xy
            moved = math.hypot(x - lx, y - ly)
            bot.last_xy = (x, y)
            now_moving = moved > MOVING_M * dt
            if now_moving != bot.moving:
                (bot.motion_starts if now_moving else bot.motion_stops).append(t)
            bot.moving = now_moving
            if bot.battery is not None:
                bot.battery.step(dt, moved, c in self.chargers)
        if self.pending_boxes:
            self._place_boxes()
        self._publish(k)
        for hook in self.tick_hooks:
            hook()
        while self._timers and self._timers[0][0] <= t + 1e-9:
            _, _, cb = heapq.heappop(self._timers)
            try:
                cb()
            except Exception:
                log.exception("sim timer callback failed")
        self.ticks += 1

    def _closest_pair(self) -> tuple[str, str]:
        best, pair = math.inf, ("", "")
        items = list(self.bots.items())
        for i, (a, ba) in enumerate(items):
            pa = ba.robot.body.position
            for b, bb in items[i + 1:]:
                pb = bb.robot.body.position
                d = math.hypot(pa.x - pb.x, pa.y - pb.y)
                if d < best:
                    best, pair = d, (a, b)
        return pair

    # -- publishing --------------------------------------------------------------------------------
    def _publish(self, tick: int) -> None:
        reg, ty = self.registry, self._types
        t = self.time
        for bot in self.bots.values():
            if not bot.live:
                continue
            tp = bot.ports
            if tick % self.pose_every == 0:
                x, y, yaw, cov = bot.robot.localisation()
                msg = {"header": {"stamp": _stamp(t), "frame_id": "map"},
                       "pose": {"pose": {"position": {"x": x, "y": y, "z": 0.0},
                                         "orientation": quaternion_from_yaw(yaw)},
                                "covariance": cov}}
                tp["pose"].publish(reg.json_to_bytes(ty["pose"], msg))
            if tp["odom"].wanted():
                ox, oy, oyaw, v, w = bot.robot.odom()
                msg = {"header": {"stamp": _stamp(t), "frame_id": "odom"}, "child_frame_id": "base_footprint",
                       "pose": {"pose": {"position": {"x": ox, "y": oy}, "orientation": quaternion_from_yaw(oyaw)}},
                       "twist": {"twist": {"linear": {"x": v}, "angular": {"z": w}}}}
                tp["odom"].publish(reg.json_to_bytes(ty["odom"], msg))
            if bot.last_scan is not None and bot.last_scan[2] == tick and tp["scan"].wanted():
                p = bot.robot.lidar.params
                msg = {"header": {"stamp": _stamp(t), "frame_id": "base_scan"}, "angle_min": p.angle_min,
                       "angle_max": p.angle_max, "angle_increment": p.angle_increment, "scan_time": 1.0 / p.rate_hz,
                       "range_min": p.range_min, "range_max": p.range_max,
                       "ranges": [float(v) for v in bot.last_scan[0]]}
                tp["scan"].publish(reg.json_to_bytes(ty["scan"], msg))
            if bot.battery is not None and tick % self.battery_every == 0:
                tp["battery"].publish(reg.json_to_bytes(ty["battery"], bot.battery.message(_stamp(t))))
            if self.publish_obstacles and tick % self.obstacles_every == 0 and bot.last_scan is not None:
                scan, pose, _ = bot.last_scan
                pts = self.detector.detect_points(scan, pose)
                pts = pts[np.hypot(pts[:, 0] - pose[0], pts[:, 1] - pose[1]) <= self.obstacle_range]
                if len(pts):
                    self.obstacle_points_dropped += max(0, len(pts) - MAX_OBSTACLE_POINTS)
                    stamp = _stamp(t)
                    tp["obstacles"].publish(self._points_wire.pack(stamp["secs"], stamp["nsecs"],
                                                                   pts[:MAX_OBSTACLE_POINTS]))

    # -- teardown ----------------------------------------------------------------------------------
    async def stop(self, timeout: float = STOP_TIMEOUT_S, first: list[str] = ()) -> None:
        """Stop the loop and every bridge (each removes its node and interfaces from the cloud
        within ``timeout`` s, or is cancelled): the robots ``first`` (e.g. those whose link goes
        through the others' relays) before the others."""
        self._stopping = True
        if self._task is not None:
            await asyncio.gather(self._task, return_exceptions=True)
        if self.ros2 is not None:
            await self.ros2.stop(timeout)
        for group in ([r for r in self.bots if r in first], [r for r in self.bots if r not in first]):
            tasks = []
            for bot in (self.bots[r] for r in group):
                if bot.bridge is not None and bot.task is not None and not bot.task.done():
                    bot.bridge.stop.set()
                    tasks.append(bot.task)
            if tasks:
                await asyncio.wait(tasks, timeout=timeout)
        await self.tasks.cancel_all()

    # -- ground truth --------------------------------------------------------------------------------
    def entries_after(self, cell: int, sim_time: float) -> list[tuple[str, float]]:
        """(robot, time) of every entry of a robot's centre into ``cell`` at or after sim time ``sim_time``."""
        out = []
        for rid, bot in self.bots.items():
            for tc, c in bot.cells:
                if c == cell and tc >= sim_time:
                    out.append((rid, tc))
        return out

    def positions(self) -> dict[str, tuple[float, float]]:
        """Every robot's true position (x, y), m."""
        return {rid: tuple(bot.robot.pose()[:2]) for rid, bot in self.bots.items()}

    def effective_speedup(self) -> float:
        """Sim seconds per wall second the loop manages (ticks' own cost only)."""
        if not self.wall_per_sim:
            return math.inf
        busy = sum(self.wall_per_sim) / len(self.wall_per_sim)
        return self.dt / busy if busy > 0 else math.inf
