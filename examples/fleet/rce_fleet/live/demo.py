"""``rce-fleet demo`` / ``rce-fleet serve``: the whole fleet system on one machine.

1. The engine as processes on 127.0.0.1 with ephemeral ports (:mod:`rce.tools.launch`):
   rce-master ``--dev``, rce-robot, rce-container.
2. The fleet manager (:mod:`rce_fleet.live.manager`, robotID ``fleetManager``): the fleet
   container ``cTag_01``, the grid parameter and the ``global_planner`` node.
3. N simulated robots in one :class:`rce_fleet.live.simhost.SimHost`, each connected as an
   rce-ros client with its own robot config (:func:`rce_fleet.configs.robot_config`),
   which starts its ``move_client`` in the fleet container.
4. The mission (``demo``): goals (``--goal RobotN=CELL`` or random free cells from
   ``--seed``), optional cell blocks (``--block CELL@SECONDS``, sim seconds after the
   goals were sent) and unannounced obstacles (``--obstacle CELL@SECONDS``: a box only the
   robots' lidars can find); a live table; a PNG of the driven paths (``--plot``); a JSON
   report (``--report``); a ROS 1 bag of the fleet topics (``--bag``: every robot's
   ``amcl_pose``, ``goalNodesList`` and ``cancelGoal`` and ``/fleet/state``, recorded from the
   fleet container through forwarders of the client ``fleetRecorder``, :mod:`rce_client.bag`,
   from when the robots are ready until the end); faults (``--fault master@T``: kill -9 rce-master
   and restart it on its ``--state`` file; ``--fault link:RobotN@T+S``: cut a robot's link for S s;
   :mod:`rce_fleet.live.faults`), which the mission rides out: the demo's clients resume their sessions;
   robots out of the access point's coverage (``--out-of-coverage Robot2,Robot5``), which reach the
   cloud only through relays on the other robots within ``--radio-range`` m (:mod:`rce_fleet.live.radio`).
   Exit 0 when every robot has reached its goal (and every fault was recovered from); otherwise
   non-zero with the reason (1 failure or timeout, 2 bad arguments, 3 an unreachable goal).

The master keeps its state in ``engine/master.sqlite3`` of the work directory (``--state``), so a
master that is killed comes back with it.

``serve`` runs the same system without a mission until Ctrl-C (or ``--timeout``).

The fleet runs as its own internal user, with a password made for the run; people log in to the
operator's page, the task API and the Foxglove port with the master's users and their roles (``--users
FILE``, ``--admin-password-file FILE``, or on loopback a first admin's password made for the run and
written to a 0600 file; :mod:`rce_fleet.live.access`). The page, the task API and the Foxglove port listen
on ``--web-bind`` (127.0.0.1), over TLS with ``--tls-cert``/``--tls-key`` (:class:`WebAccess`,
docs/task-api.md, docs/SECURITY.md).

Tasks. The fleet takes operators' tasks in every mode (:mod:`rce_fleet.operations.tasks_api`): named
places come from ``--places FILE`` or are generated for the map and written to
``places.yaml`` in the work directory (:mod:`rce_fleet.operations.places`). ``demo --lifelong`` runs the
fleet on a generated task stream (``--task-rate R`` per simulated minute, pick-up then
drop-off) for ``--duration S`` simulated seconds, with batteries (``--battery``) and idle
robots parking (``--block``, ``--obstacle`` and faults timed from its start, as a mission's),
and writes the report's ``tasks`` section and per-robot utilisation, distance,
lowest battery level and charges (:mod:`rce_fleet.live.task_stream`); it exits 0 when the duration
was reached and no robot ran flat.
"""
from __future__ import annotations

import asyncio
import json
import math
import random
import shutil
import signal
import sys
import tempfile
import time
from collections import deque
from pathlib import Path

from rce.plumbing.errors import RCEError
from rce.tools.launch import Engine, start_engine
from rce.plumbing.log import get_logger, setup_logging
from rce.messages import default_registry
from rce.node.package_path import load_package_types
from rce.plumbing.process import run_loop
from rce.plumbing.tasks import Tasks

from ..operations.battery import battery_links
from ..configs import FLEET_CTAG, robot_config
from .access import prepare_access
from .demo_output import (EXIT_FAIL, EXIT_OK, EXIT_UNREACHABLE, EXIT_USAGE, activities, blocked_by, progress_line,
                          table, write_outputs)
from .faults import FaultInjector
from .fleet_bag import FleetBag
from ..maps.geometry import GRID_PARAM, GridGeometry, components
from ..maps.grid import fleet_grid
from ..maps.lab_map import write_lab_map
from .manager import FleetManager
from ..maps.occupancy import MapError, load_map
from .task_stream import TaskStream
from ..operations.places import PlaceError, Places, generate_places
from .radio import Radio, default_range
from .options import (Options, UsageError, WebAccess, check_robots, parse_battery, parse_cell_at,  # noqa: F401
                      parse_faults, parse_robot_cell, web_access)
from .simhost import SimHost

log = get_logger("fleet.demo")

REACH_TOL = 0.25       # m between the robot's true centre and its goal cell's centre
STUCK_S = 30.0         # wall s every robot still on its way may stay unplannable before the run fails
SETUP_TIMEOUT_S = 60.0     # wall s for the fleet manager's setup, and for each robot's connection
MIN_STEP_TIMEOUT_S = 0.1   # wall s a set-up step gets even when the run's --timeout is (nearly) used up
MIN_READY_WAIT_S = 1.0     # wall s the wait for every robot and move_client to report gets at least
CONNECTING_AT_ONCE = 4     # robots connecting at the same time (each sets up its node and interfaces)
WATCH_PERIOD_S = 0.25      # wall s between checks of the run (mission end, engine, Ctrl-C)
TIMELINE_MAX = 100_000     # samples of a run by tasks kept for its PNG (one per sim s: 27 h; the oldest go first)
CHARGE_TRIPS_MAX = 100     # trips to a charger kept per robot for the report (the newest)
PROGRESS_EVERY_S = 5.0     # wall s between plain progress lines (no live table)
RELAYS_EVERY_S = 1.0       # wall s between asks for the followers' relays at the master (--out-of-coverage)
TEARDOWN_TIMEOUT_S = 10.0  # wall s the web page and the fleet manager each get to close before they are left
SIM_STOP_TIMEOUT_S = 5.0   # wall s the robots' bridges get to remove their nodes and interfaces


def choose_cells(geo: GridGeometry, robots: list[str], seed: int, starts: dict[str, int],
                 goals: dict[str, int], mission: bool) -> tuple[dict[str, int], dict[str, int]]:
    """Starts and goals: the given ones, the others random distinct free cells (seeded) of the
    largest connected part of the grid. Raises UsageError for a given start that is not free."""
    rng = random.Random(seed)
    comps = components(geo)
    if not comps:
        raise UsageError("the grid has no free cell (try another --grid/--cell)")
    pool = sorted(comps[0])
    for r, c in starts.items():
        if not geo.is_free(c):
            raise UsageError(f"--start {r}={c}: cell {c} is not a free cell of the grid")
    if len(set(starts.values())) != len(starts):
        raise UsageError("--start: two robots in one cell")
    need = len(robots) - len(starts)
    free_starts = [c for c in pool if c not in starts.values()]
    if need > len(free_starts):
        raise UsageError(f"{len(robots)} robots do not fit in the {len(pool)} connected free cells of the grid")
    picked = rng.sample(free_starts, need)
    st = dict(starts)
    for r in robots:
        if r not in st:
            st[r] = picked.pop()
    gl = dict(goals)
    if mission:
        taken = set(gl.values())
        for r in robots:
            if r in gl:
                continue
            cands = [c for c in pool if c != st[r] and c not in taken]
            if not cands:
                raise UsageError("not enough free cells for distinct goals")
            gl[r] = rng.choice(cands)
            taken.add(gl[r])
    return st, gl


class Run:
    """One demo/serve run (see the module docstring)."""

    def __init__(self, opts: Options):
        self.o = opts
        self.robots = [f"Robot{i}" for i in range(1, opts.robots + 1)]
        self.engine: Engine | None = None
        self.manager: FleetManager | None = None
        self.sim: SimHost | None = None
        self.state: dict | None = None
        self.t_mission: float | None = None       # sim time the goals were sent
        self.wall_mission: float | None = None
        self.cpu_mission = 0.0                    # this process's CPU s (the simulator, the bridges) then
        self.reached: dict[str, float] = {}       # robot -> sim time
        self.block_log: list[dict] = []
        self.obstacle_log: list[dict] = []
        self.result: tuple[int, str] | None = None
        self.events: deque[str] = deque(maxlen=6)
        self.bag: FleetBag | None = None          # --bag
        self.record: FleetBag | None = None       # --record
        self.foxglove = None                      # --foxglove-port: rce_fleet.live.foxglove.FleetFoxglove
        self.grid_note = ""
        self.faults: FaultInjector | None = None
        self._stuck_since: float | None = None
        self._stop = asyncio.Event()
        self.tasks = Tasks("fleet-demo")           # operator requests sent from sim timers
        self.task_list: dict | None = None         # the newest /fleet/tasks
        self.generated = 0                         # tasks the lifelong stream sent
        self.first_done: float | None = None       # sim s from the start to the first task done
        self.refused: list[str] = []               # why the fleet refused generated tasks
        self.radio: Radio | None = None            # --out-of-coverage: the radio links to the relays
        self.master_relays: dict[str, dict] = {}   # follower -> the master's relay and relay_since (asked every 1 s)
        self.placement: dict = {}                  # --edge-hosts: the placer's rows and moves at the end
        # a run by tasks, sampled each sim second: (sim s, tasks done, {robot: activity}); bounded
        self.timeline: deque[tuple[float, int, dict[str, str]]] = deque(maxlen=TIMELINE_MAX)
        self.timeline_dropped = 0                  # samples the bound dropped (the report says how many)
        self.charge_trips: dict[str, deque] = {}   # robot -> (sim s, battery %) of each trip to a charger

    # -- set-up ---------------------------------------------------------------------------------
    def prepare(self) -> None:
        """Check the options, load the map, cut the grid, choose starts and goals; raises
        UsageError naming the bad flag."""
        o = self.o
        check_robots(o)
        self.workdir = Path(o.workdir).resolve() if o.workdir else Path(tempfile.mkdtemp(prefix="rce-fleet-"))
        self.workdir.mkdir(parents=True, exist_ok=True)
        map_path = o.map or str(write_lab_map(self.workdir / "map"))
        self.map_path = map_path
        try:
            self.occ = load_map(map_path)
        except (MapError, OSError) as e:
            raise UsageError(f"--map: {e}") from None
        try:
            grid, self.grid_note = fleet_grid(self.occ, o.grid, o.cell)
        except ValueError as e:
            raise UsageError(f"--grid/--cell: {e}") from None
        self.geo = GridGeometry.from_cellgrid(grid)
        if o.out_of_coverage and o.radio_range is None:     # the default: rce_fleet.live.radio.default_range
            o.radio_range = default_range(self.occ.width_m, self.occ.height_m)
        for r, c in o.goals.items():
            if not self.geo.valid(c):
                raise UsageError(f"--goal {r}={c}: cell outside the {self.geo.rows}x{self.geo.cols} grid")
        for c, _ in o.blocks + o.obstacles:
            if not self.geo.valid(c):
                raise UsageError(f"cell {c} is outside the {self.geo.rows}x{self.geo.cols} grid")
        self.starts, self.goals = choose_cells(self.geo, self.robots, o.seed, o.starts, o.goals, o.mission)
        try:
            self.places = Places.load(o.places, self.geo) if o.places else \
                generate_places(self.geo, o.robots, paired=o.stations == "paired")
        except PlaceError as e:
            if o.places or o.lifelong:
                raise UsageError(f"--places: {e}") from None
            self.places = Places([], self.geo)      # a grid too small for places: tasks name cells
            log.info("no places generated", reason=str(e))
        if not o.places and len(self.places):
            self.places.dump(self.workdir / "places.yaml", f"places generated for {Path(self.map_path).name}, "
                             f"grid {self.geo.rows}x{self.geo.cols} (rce-fleet --places)")
        if o.lifelong:
            if not o.duration > 0:
                raise UsageError("--duration must be > 0")
            try:
                self.stream = TaskStream(self.places, o.task_rate, o.seed, backlog=o.backlog,
                                         nearest_drop=o.stations == "paired").times_and_errands(o.duration)
            except ValueError as e:
                raise UsageError(f"--task-rate/--places: {e}") from None
        if self.grid_note:
            log.info(self.grid_note)
            self.events.append(self.grid_note)
        self.access = prepare_access(o.web, self.workdir, page=not o.headless)

    # -- run --------------------------------------------------------------------------------------
    async def run(self) -> int:
        """Start everything, run the mission (or serve), write the outputs, tear down;
        returns the exit code."""
        o = self.o
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                loop.add_signal_handler(sig, self._interrupt)
            except (NotImplementedError, RuntimeError):
                pass
        wall0 = time.monotonic()
        self.deadline = wall0 + o.timeout
        try:
            code, reason = await self._run()
        except RCEError as e:
            code, reason = EXIT_FAIL, e.message
        except (RuntimeError, TimeoutError, OSError) as e:
            code, reason = EXIT_FAIL, str(e)
        self.result = (code, reason)
        self.wall_total = time.monotonic() - wall0
        if self.radio is not None:
            await self._ask_master_relays()
        if o.edge_hosts and self.engine is not None:
            await self._ask_placement()
        try:
            for rec in (self.bag, self.record):     # before the report, which gives the bag's counts
                if rec is not None:
                    await rec.stop(TEARDOWN_TIMEOUT_S)
        except (asyncio.TimeoutError, RCEError, OSError) as e:
            log.warning("the bag recorder did not disconnect", reason=str(e))
        try:
            write_outputs(self, code, reason)
        finally:
            await self._teardown()
        return code

    def _interrupt(self) -> None:
        self.events.append("interrupted")
        self._stop.set()

    async def _run(self) -> tuple[int, str]:
        o = self.o
        state = self.workdir / "engine" / "master.sqlite3"
        users = ("--no-dev-user", "--users", str(self.access.users_file))
        self.engine = await asyncio.to_thread(start_engine, self.workdir / "engine",
                                              master_args=("--state", str(state), *users),
                                              admin_token=f"fleet-{random.getrandbits(64):016x}")
        log.info("engine up", master=self.engine.master_url, workdir=str(self.workdir))
        if o.edge_hosts:
            await self._bounded(self._robot_computers(), "the robots' computers")
        self.faults = FaultInjector(o.faults, self.engine, self.tasks, self.access.user, self.mission_t)
        print(f"rce-fleet: master {self.engine.master_url}  (the engine: the fleet's own user; people use the page)",
              flush=True)
        args = " ".join(a for a, on in (("--no-lidar-blocking", not o.lidar_blocking), ("--park-idle", o.lifelong))
                        if on)
        self.manager = FleetManager(self.engine.master_url, self.geo, self.robots, planner_args=args,
                                    user=self.access.user, password=self.access.password,
                                    on_state=self._on_state, places=self.places, battery=o.battery,
                                    on_tasks=self._on_tasks, on_alert=self._on_alert)
        await self._bounded(self.manager.start(timeout=SETUP_TIMEOUT_S), "fleet manager setup")
        reg = default_registry()
        load_package_types(reg)
        ros2 = None
        if o.ros2:                      # ROS 2 robots, each with an rce-ros --ros2 process
            from .ros2_robots import Ros2Robots
            ros2 = Ros2Robots(self.workdir / "ros2")
        self.sim = SimHost(self.occ, self.geo, reg, seed=o.seed, speedup=o.speedup, battery=o.battery,
                           chargers=self.places.cells("charger"), ros2=ros2)
        for r in self.robots:
            self.sim.spawn(r, self.starts[r])
        self.sim.start()
        await self._connect_robots()
        log.info("robots connected", robots=len(self.robots),
                 t_wall=round(time.monotonic() - (self.deadline - o.timeout), 1))

        def ready(st: dict) -> bool:
            rs = {x["robot"]: x for x in st.get("robots", [])}
            return all(r in rs and rs[r]["cell"] >= 0 and rs[r]["client_state"] not in ("", "no_pose")
                       for r in self.robots)
        await self._bounded(self.manager.wait_state(ready, max(MIN_READY_WAIT_S, self.deadline - time.monotonic())),
                            "robots and move_clients reporting")
        if not o.headless:
            await self._start_web()
        if o.bag:
            self.bag = FleetBag(o.bag, self.robots)
            await self._bounded(self.bag.start(self.engine.master_url, reg, SETUP_TIMEOUT_S, self.access.user,
                                               self.access.password), "bag recorder setup")
            self.events.append(f"recording the fleet topics to {o.bag}")
            log.info("recording", bag=o.bag, topics=len(self.bag.topics()))
        if o.record:
            from .fleet_scene import FleetScene
            self.record = FleetBag(o.record, self.robots, recorder_id="fleetMcapRecorder",
                                   scene=FleetScene(self.geo, self.occ, self.places, reg))
            await self._bounded(self.record.start(self.engine.master_url, reg, SETUP_TIMEOUT_S, self.access.user,
                                                  self.access.password), "recorder setup")
            self.events.append(f"recording the fleet topics to {o.record}")
        if o.foxglove_port is not None:
            await self._start_foxglove(reg)
        if o.lifelong:
            return await self._lifelong()
        if not o.mission:
            log.info("serving", robots=len(self.robots), note="Ctrl-C to stop")
            await self._watch(mission=False)
            return EXIT_OK, "stopped"
        # the mission
        self._start_clock()
        for r in self.robots:
            await self.manager.set_goal(r, self.goals[r])
        log.info("mission started", goals=self.goals, starts=self.starts, t_sim=round(self.t_mission, 2))
        return await self._watch(mission=True)

    def _start_clock(self) -> None:
        """The mission (or lifelong run) starts now: blocks, obstacles and faults are timed from here."""
        o = self.o
        self.t_mission = self.sim.time
        self.wall_mission = time.monotonic()
        self.cpu_mission = time.process_time()
        for c, at in o.blocks:
            self.sim.at(self.t_mission + at, lambda cell=c, at=at: self._do_block(cell, at))
        for c, at in o.obstacles:
            self.sim.at(self.t_mission + at, lambda cell=c, at=at: self._do_obstacle(cell, at))
        self.faults.schedule(self.sim.at, self.t_mission)

    async def _lifelong(self) -> tuple[int, str]:
        """The generated task stream for ``--duration`` sim s (module docstring)."""
        self._start_clock()
        for at, errands in self.stream:
            self.sim.at(self.t_mission + at, lambda e=errands: self.tasks.spawn(self._add_task(e), name="task"))
        log.info("lifelong run started", tasks=len(self.stream), duration=self.o.duration, rate=self.o.task_rate)
        code, reason = await self._watch(mission=False)
        flat = [r for r, b in self.sim.bots.items() if b.battery is not None and b.battery.flat]
        if code == EXIT_OK and flat:
            return EXIT_FAIL, f"battery ran flat: {', '.join(flat)}"
        return code, reason

    async def _add_task(self, errands: list[str]) -> None:
        self.generated += 1
        try:
            await self.manager.tasks.add(errands, timeout=SETUP_TIMEOUT_S)
        except RCEError as e:
            self.refused.append(e.message)
            log.warning("generated task refused", errands=errands, reason=e.message)

    def _on_tasks(self, task_list: dict) -> None:
        self.task_list = task_list
        if self.first_done is None and task_list.get("done") and self.t_mission is not None:
            done = [t["finished"] for t in task_list.get("tasks", []) if t.get("state") == "done"]
            self.first_done = (min(done) if done else self.sim.time) - self.t_mission

    def _on_alert(self, robot: str, text: str) -> None:
        """A robot's stall alert (the fleet manager logged it): on the console too."""
        self.events.append(f"t={self.mission_t():.0f}s ALERT {text}")

    async def _robot_computers(self) -> None:
        """``--edge-hosts``: a container host per robot, in zone ``robot:RobotN``, serving the fleet's
        user alone (a robot's own computer, here a process on this machine)."""
        for r in self.robots:
            await asyncio.to_thread(self.engine.add_container_host, "--zone", f"robot:{r}", "--user", self.access.user,
                                    "--name", f"{r}-computer", "--warm", "0")
        self.events.append(f"{len(self.robots)} robots' computers (zone robot:RobotN); the placer places move_clients")
        self.tasks.spawn(self._watch_placement(), name="placement")

    def _move_client_placement(self, robot: str) -> str | None:
        """Where ``robot``'s move_client runs: None (the fleet container) without ``--edge-hosts``;
        else on board for a robot out of coverage, where the placer says for the others."""
        if not self.o.edge_hosts:
            return None
        return "robot" if robot in self.o.out_of_coverage else "auto"

    async def _connect_robots(self) -> None:
        """Write the robots' configs and connect them, a few at a time (each sets up its node and
        interfaces); a robot whose link a fault cuts logs in through its proxy's login relay."""
        cfgs = {r: robot_config(int(r[5:]), self.engine.master_url, self.access.user, self.access.password,
                                placement=self._move_client_placement(r),
                                params={GRID_PARAM: self.geo.to_param()}) for r in self.robots}
        if self.o.battery is not None:
            for r, cfg in cfgs.items():
                ifaces, links = battery_links(int(r[5:]), FLEET_CTAG)
                cfg["interfaces"] += ifaces
                cfg["connections"] += links
        (self.workdir / "configs").mkdir(mode=0o700, exist_ok=True)      # they hold the internal user's password
        for r, cfg in cfgs.items():
            path = self.workdir / "configs" / f"robot{r[5:]}.config"
            path.touch(mode=0o600)
            path.write_text(json.dumps(cfg, indent=2))
        logins = await self.faults.start_links()
        sem = asyncio.Semaphore(CONNECTING_AT_ONCE)
        followers = [r for r in self.robots if r in self.o.out_of_coverage]
        relays = {"relay_port": 0, "relay_bind": "127.0.0.1"} if followers else {}

        async def connect(robot: str, **kw) -> None:
            async with sem:
                await self.sim.connect(robot, cfgs[robot], logins.get(robot, self.engine.master_url),
                                       timeout=SETUP_TIMEOUT_S, **kw)
            if robot in logins:
                self.faults.watch(robot, self.sim.bots[robot].bridge.conn)
        await self._bounded(asyncio.gather(*(connect(r, **relays) for r in self.robots if r not in followers)),
                            "robots connecting")
        if followers:
            await self._connect_followers(followers, connect)

    async def _connect_followers(self, followers: list[str], connect) -> None:
        """Start the radio links from ``followers`` to every other robot's relay, and connect the
        followers through them (the relays are connected)."""
        ports = {r: b.bridge.relay.port for r, b in self.sim.bots.items() if r not in followers}
        self.radio = Radio(self.o.radio_range, followers, ports, self.sim.positions)
        await self.radio.start()
        self.sim.tick_hooks.append(self.radio.update)
        self.tasks.spawn(self._watch_relays(), name="relays")
        self.events.append(f"out of coverage: {', '.join(followers)} (radio range {self.o.radio_range:g} m)")
        log.info("out of coverage: reaching the cloud through relays", followers=followers,
                 radio_range_m=self.o.radio_range)

        async def follower(robot: str) -> None:
            await connect(robot, routes=self.radio.routes(robot))
            self.radio.follow(robot, self.sim.bots[robot].bridge.conn, self.mission_t)
        await self._bounded(asyncio.gather(*(follower(r) for r in followers)), "robots out of coverage connecting")

    async def _ask_master_relays(self) -> None:
        """Keep what the master says of each follower's relay (the admin API's ``/api/robots``)."""
        try:
            rows = await asyncio.to_thread(self.engine.admin, "/api/robots")
        except (RCEError, OSError) as e:
            log.warning("could not ask the master for the robots' relays", reason=str(e))
            return
        self.master_relays = {r["robot"]: {"relay": r.get("relay"), "relay_since": r.get("relay_since")}
                              for r in rows if r["robot"] in self.o.out_of_coverage}

    async def _ask_placement(self) -> None:
        """Keep where each move_client ran at the end, the placer's word on it, and the moves made."""
        try:
            rows = await asyncio.to_thread(self.engine.admin, "/api/placement")
            moves = await asyncio.to_thread(self.engine.admin, "/api/placement/moves")
        except (RCEError, OSError) as e:
            log.warning("could not ask the master for the placement", reason=str(e))
            return
        self.placement = {"containers": [{k: r.get(k) for k in ("ctag", "runs", "best", "move", "pinned", "why",
                                                                "results", "misses", "node_ms", "battery")}
                                         for r in rows if r["ctag"].startswith("mc_")],
                          "moves": [m for m in moves if m["ctag"].startswith("mc_")]}

    async def _watch_placement(self) -> None:
        """Ask the master's placer every :data:`RELAYS_EVERY_S` s (the web page's placement table)."""
        while True:
            await self._ask_placement()
            await asyncio.sleep(RELAYS_EVERY_S)     # the period, a timer

    async def _watch_relays(self) -> None:
        """Ask the master for the followers' relays every :data:`RELAYS_EVERY_S` s (the web page's lines)."""
        while True:
            await self._ask_master_relays()
            await asyncio.sleep(RELAYS_EVERY_S)     # the period, a timer

    def _relay_lines(self) -> dict[str, str]:
        """Follower -> the relay its link goes through now, as the master last said."""
        return {r: v["relay"] for r, v in self.master_relays.items() if v["relay"]}

    async def _bounded(self, aw, what: str):
        left = self.deadline - time.monotonic()
        try:
            async with asyncio.timeout(max(left, MIN_STEP_TIMEOUT_S)):
                return await aw
        except TimeoutError:
            raise TimeoutError(f"timeout ({self.o.timeout:g} s wall) during {what}") from None

    def _on_state(self, st: dict) -> None:
        self.state = st
        if self.faults is not None:
            self.faults.on_state()
        for rec in self.block_log:      # the planner's time for the re-plan the block caused
            if "replan_ms" not in rec and rec["cell"] in st.get("blocked", []):
                rec["replan_ms"] = round(st.get("last_plan_ms", 0.0), 3)
        if self.sim is not None:
            self.sim.set_blocked(blocked_by(st))

    def _do_block(self, cell: int, at: float) -> None:
        paths = {x["robot"]: x["path"] for x in (self.state or {}).get("robots", [])}
        rec = {"cell": cell, "at_s": at, "sent_sim_s": round(self.sim.time - self.t_mission, 3),
               "sent_t": self.sim.time,
               "paths_crossed": sorted(r for r, p in paths.items() if cell in p[1:]),
               "robot_cells": {r: b.cells[-1][1] for r, b in self.sim.bots.items()}}
        self.block_log.append(rec)
        crossed = ", ".join(rec["paths_crossed"]) or "none"
        self.events.append(f"t={at:g}s: block cell {cell} (paths crossing it: {crossed})")
        log.info("blocking cell", cell=cell, t=at, paths_crossed=rec["paths_crossed"])
        self.tasks.spawn(self.manager.block(cell, True, "operator"), name=f"block-{cell}")

    def _do_obstacle(self, cell: int, at: float) -> None:
        x, y, w, h = self.sim._box(cell)
        self.sim.world.add_box(f"obstacle{cell}", x, y, w, h)
        self.obstacle_log.append({"cell": cell, "at_s": at, "sent_t": self.sim.time})
        self.events.append(f"t={at:g}s: unannounced obstacle in cell {cell}")
        log.info("obstacle placed (only the lidars can tell)", cell=cell, t=at)

    # -- watching ------------------------------------------------------------------------------
    def robot_states(self) -> dict[str, dict]:
        return {x["robot"]: x for x in (self.state or {}).get("robots", [])}

    def _check(self) -> tuple[int, str] | None:
        """The mission's end, if reached: (exit code, reason)."""
        st = self.robot_states()
        for r in self.robots:
            s = st.get(r)
            if s is None:
                continue
            if s["state"] == "unreachable" and s.get("error_permanent"):
                return EXIT_UNREACHABLE, f"{r}: goal cell {self.goals[r]} unreachable: {s['error']}"
            if r not in self.reached and s["state"] == "arrived" and s["client_state"] == "arrived" \
                    and s["goal"] == self.goals[r]:
                x, y, _ = self.sim.bots[r].robot.pose()
                gx, gy = self.geo.center(self.goals[r])
                if math.hypot(x - gx, y - gy) <= REACH_TOL:
                    self.reached[r] = self.sim.time
                    self.events.append(f"{r} reached cell {self.goals[r]} at t={self.sim.time - self.t_mission:.1f}s")
                    log.info("goal reached", robot=r, goal=self.goals[r], t=round(self.sim.time - self.t_mission, 2))
        if len(self.reached) == len(self.robots) and not self.faults.busy:
            return EXIT_OK, "every robot reached its goal"
        # no plan for anybody still on the way (the planner retries every second): give up after a while
        left = [r for r in self.robots if r not in self.reached]
        if left and all(st.get(r, {}).get("state") == "unreachable" for r in left):
            if self._stuck_since is None:
                self._stuck_since = time.monotonic()
            elif time.monotonic() - self._stuck_since > STUCK_S:
                why = "; ".join(f"{r}: {st[r]['error']}" for r in left)
                return EXIT_UNREACHABLE, f"no collision-free plan for {len(left)} robot(s) for {STUCK_S:g} s: {why}"
        else:
            self._stuck_since = None
        return None

    def _engine_problem(self) -> str | None:
        if self.faults is not None and self.faults.error:
            return self.faults.error
        dead = self.engine.alive() if self.engine else []
        if dead:
            return f"engine process exited: {', '.join(dead)}"
        if self.sim is not None:
            for r, b in self.sim.bots.items():
                if b.task is not None and b.task.done():
                    return f"{r}: its rce-ros bridge stopped"
        if self.manager is not None and self.manager.conn is not None and self.manager.conn.closed:
            return "the fleet manager lost its connection"
        return None

    async def _watch(self, mission: bool) -> tuple[int, str]:
        live = self.o.live if self.o.live is not None else sys.stdout.isatty()
        if live:
            from rich.live import Live
            with Live(table(self), refresh_per_second=4, redirect_stderr=True, redirect_stdout=True) as lv:
                setup_logging()         # logs go above the table
                _quiet_libraries()
                end = await self._loop(mission, lambda: lv.update(table(self)))
            setup_logging()
            _quiet_libraries()
            print(flush=True)
            return end
        last = [0.0]

        def plain() -> None:
            if time.monotonic() - last[0] >= PROGRESS_EVERY_S:
                last[0] = time.monotonic()
                print(progress_line(self), flush=True)
        return await self._loop(mission, plain)

    async def _loop(self, mission: bool, show) -> tuple[int, str]:
        while True:
            show()
            if self.o.lifelong and self.t_mission is not None:
                self._sample()
            if self._stop.is_set():
                return (EXIT_FAIL, "interrupted") if mission else (EXIT_OK, "stopped")
            prob = self._engine_problem()
            if prob:
                return EXIT_FAIL, prob
            if mission:
                end = self._check()
                if end is not None:
                    show()
                    return end
            if self.o.lifelong and self.t_mission is not None and self.mission_t() >= self.o.duration:
                return EXIT_OK, f"{self.o.duration:g} s simulated"
            if time.monotonic() > self.deadline:
                if self.o.lifelong:
                    return EXIT_FAIL, (f"timeout after {self.o.timeout:g} s wall at {self.mission_t():.0f} of "
                                       f"{self.o.duration:g} s simulated")
                if not mission:
                    return EXIT_OK, "timeout reached (serve)"
                missing = [r for r in self.robots if r not in self.reached]
                st = self.robot_states()
                detail = "; ".join(f"{r} in cell {st.get(r, {}).get('cell')} ({st.get(r, {}).get('state')}, "
                                   f"goal {self.goals[r]})" for r in missing)
                return EXIT_FAIL, f"timeout after {self.o.timeout:g} s wall: not at their goals: {detail}"
            try:
                async with asyncio.timeout(WATCH_PERIOD_S):
                    await self._stop.wait()
            except TimeoutError:
                pass

    def _sample(self) -> None:
        """One timeline sample per sim second of a run by tasks (tasks done, each robot's activity)."""
        t = self.mission_t()
        if self.timeline and t - self.timeline[-1][0] < 1.0:
            return
        self.timeline_dropped += len(self.timeline) == TIMELINE_MAX
        acts = activities(self)
        before = self.timeline[-1][2] if self.timeline else {}
        for r, a in acts.items():          # each trip to a charger: when, and the battery then (simulator's)
            b = self.sim.bots[r].battery
            if a == "to charger" and before.get(r) != a and b is not None:
                trips = self.charge_trips.setdefault(r, deque(maxlen=CHARGE_TRIPS_MAX))
                trips.append((round(t, 1), round(100.0 * b.fraction, 1)))
        self.timeline.append((t, int((self.task_list or {}).get("done", 0)), acts))

    # -- display ---------------------------------------------------------------------------------
    def mission_t(self) -> float:
        """Sim seconds since the goals were sent (since the simulator started when serving)."""
        if self.sim is None:
            return 0.0
        return self.sim.time - (self.t_mission if self.t_mission is not None else 0.0)

    # -- the operator's web page (rce_fleet.live.webui, owned by the web page's code) ----------------
    async def _start_web(self) -> None:
        from rce.tools.admin_client import AdminClient
        from rce.transport.tls import server_context

        from ..operations.api_auth import DEFAULT_TTL_S
        from ..operations.http_api import ApiAuth, master_password_check
        from .access import is_loopback
        from .webui import WebUI
        w, acc = self.o.web, self.access
        self.admin_client = AdminClient(self.engine.master_url, self.engine.admin_token)
        self.api_auth = ApiAuth(master_password_check(self.admin_client), ttl_s=w.token_ttl or DEFAULT_TTL_S,
                                metrics_public=w.metrics_public, internal=frozenset({acc.user}))
        self.ssl_context = server_context(w.tls_cert, w.tls_key) if w.tls_cert else None
        if self.ssl_context is None and not is_loopback(w.bind):
            log.warning("the page, the task API and the Foxglove port listen beyond loopback without TLS: "
                        "passwords and tokens travel in clear (give --tls-cert and --tls-key)", bind=w.bind)
        self.web = WebUI(self.engine.master_url, self.occ, self.geo, self.robots, ctag=FLEET_CTAG, user=acc.user,
                         password=acc.password, auth=self.api_auth, bind=w.bind, port=self.o.web_port,
                         tasks=self.manager.tasks, places=self.places,
                         relays=self._relay_lines if self.radio is not None else None,
                         ssl_context=self.ssl_context, login_user=acc.admin_user,
                         placement=(lambda: self.placement) if self.o.edge_hosts else None)
        url = await self._bounded(self.web.start(), "web page setup")
        self.events.append(f"operator page: {url}")
        print(f"rce-fleet: operator page: {url}  ({acc.admin_note})" if acc.admin_note else
              f"rce-fleet: operator page: {url}", flush=True)

    async def _start_foxglove(self, reg) -> None:
        from .fleet_scene import FleetScene
        from .foxglove import FleetFoxglove
        w = self.o.web
        self.foxglove = FleetFoxglove(self.engine.master_url, FleetScene(self.geo, self.occ, self.places, reg),
                                      self.robots, user=self.access.user, password=self.access.password,
                                      auth=self.api_auth, bind=w.bind, port=self.o.foxglove_port,
                                      ssl_context=self.ssl_context)
        url = await self._bounded(self.foxglove.start(), "Foxglove server setup")
        self.events.append(f"Foxglove: {url}")
        print(f"rce-fleet: Foxglove WebSocket: {url}  (TOKEN: a token of the page's POST /api/login)", flush=True)

    async def _teardown(self) -> None:
        t0 = time.monotonic()
        try:
            await self.tasks.cancel_all()
            for rec in (self.bag, self.record):
                if rec is not None:
                    await rec.stop(TEARDOWN_TIMEOUT_S)
            if self.foxglove is not None:
                async with asyncio.timeout(TEARDOWN_TIMEOUT_S):
                    await self.foxglove.close()
            if getattr(self, "web", None) is not None:
                async with asyncio.timeout(TEARDOWN_TIMEOUT_S):
                    await self.web.stop()
                    await self.admin_client.aclose()
            if self.sim is not None:
                await self.sim.stop(timeout=SIM_STOP_TIMEOUT_S, first=self.o.out_of_coverage)
            if self.radio is not None:
                await self.radio.close()
            if self.manager is not None:
                async with asyncio.timeout(TEARDOWN_TIMEOUT_S):
                    await self.manager.close()
            if self.faults is not None:
                async with asyncio.timeout(TEARDOWN_TIMEOUT_S):
                    await self.faults.close()
        except (TimeoutError, RCEError, OSError) as e:
            log.warning("teardown incomplete", reason=str(e))
        finally:
            t1 = time.monotonic()
            if self.engine is not None:
                await asyncio.to_thread(self.engine.stop)
            if not self.o.keep and not self.o.workdir:
                shutil.rmtree(self.workdir, ignore_errors=True)
            log.info("stopped", clients_s=round(t1 - t0, 2), engine_s=round(time.monotonic() - t1, 2))


def _quiet_libraries() -> None:
    import logging
    for name in ("rce.ros", "rce.client"):
        logging.getLogger(name).setLevel(logging.WARNING)


def run(opts: Options) -> int:
    """Run the demo (or ``serve`` when ``opts.mission`` is False); returns the exit code."""
    setup_logging()
    _quiet_libraries()
    r = Run(opts)
    try:
        r.prepare()
    except UsageError as e:
        print(f"rce-fleet: {e}", file=sys.stderr)
        return EXIT_USAGE
    return run_loop(r.run())
