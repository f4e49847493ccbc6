"""Fleet load: N lightweight robots (no physics) on one fleet container, N = 10, 100, 300, 1000.

What runs (a fresh engine per N, processes on loopback, :mod:`common`'s ``engine``):

- rce-master ``--dev`` (user testUser; ``--max-interfaces`` raised to what N robots need),
  ``--robot-tasksets`` rce-robot task sets (default one per core: the master places each robot on
  the least loaded), one rce-container host;
- the fleet manager (:class:`rce_fleet.live.manager.FleetManager`, robotID ``fleetManager``, in
  this orchestrating process): the fleet container ``cTag_01`` with the real
  ``fleet/global_planner`` node (``--no-lidar-blocking``), the ``/fleet/grid`` and
  ``/fleet/robots`` parameters and the operator interfaces (its ``/fleet/state`` at 5 Hz
  comes back here through a PublisherConverter, as on the operator's page);
- in the same container, a pose echo node: ``benchecho/echo.py`` (``bench/packages``)
  subscribed to every ``/RobotN/amcl_pose`` (the planner's own subscription topic), which
  publishes each pose back unchanged on ``/RobotN/amcl_pose_echo``;
- N robots ``Robot1..RobotN`` (distinct robot IDs, the same user), each its own websocket
  and login, spread over ``--clients`` worker processes (default 1; uvloop, the raw wire protocol;
  one timer per worker drives all its robots and each pose goes out in one corked write,
  :mod:`rce_robot.ws_cork`, so the clients stay cheap on the cores they share with the engine).

Each robot wires, through its own CN/CX requests, what a fleet robot wires
(``rce_fleet.configs.robot_config``): its pose ``/amcl_pose`` -> robot-side
``amclPoseSender_N`` (SubscriberForwarder, or SubscriberConverter with ``--converter``) ->
container ``amclPoseReceiver_N`` (PublisherInterface ``/RobotN/amcl_pose``, where the
global planner listens). Back to the robot, through robot-side Publisher Forwarders
(Converters): the planner's ``/RobotN/goalNodesList``, ``/RobotN/cancelGoal`` and
``/RobotN/clearance`` (a lightweight robot has no move_client: it takes the planner's
output itself; one move_client process per robot would not fit 1000 robots), and the echo
``/RobotN/amcl_pose_echo``.

Load: every robot publishes ``geometry_msgs/PoseWithCovarianceStamped`` at ``--rate`` Hz
(10), phases spread evenly, standing in its own grid cell (an all-free grid, 1 m cells,
2 cells per robot). After warm-up every robot gets a goal (the neighbouring cell) through
``/fleet/goal``: the planner then sends each robot its path, a clearance, and repeats them
(paths every 2 s, clearances every 0.5 s) for the whole run. A topic may drop messages under
overload (an endpoint that lags sheds them, docs/INTERNALS.md "A peer that does not keep up"),
so the manager sends the goal of each robot that has no path yet again every 5 s.

Measured, over a window of ``--duration`` s after warm-up:

- latency: ``header.stamp`` is the robot's wall clock just before it sends pose ``seq``;
  latency = the same robot's clock when the echo of that pose (same ``header.seq``, same
  stamp) has fully arrived (JSON frame and binary part) minus the stamp. The path measured:
  robot websocket -> rce-robot (forwarder checks the message) -> data plane -> environment
  -> container bus ``/RobotN/amcl_pose`` (fanned out to the planner and the echo node) ->
  echo node (deserialise, serialise) -> bus ``/RobotN/amcl_pose_echo`` -> SubscriberInterface
  -> data plane -> rce-robot -> websocket -> robot. p50/p99 over all echoes of poses sent
  in the window. The echo is its own node process, so the planner's own processing is not in
  this number (the planner view age below covers it).
- lost: per robot, poses sent in the window (``header.seq`` is 0, 1, 2, ... per robot) minus
  distinct seqs echoed back within ``--drain`` s after the window (an echo later than that
  counts as lost). Also reported: drops the engine counted (rce-robot's per-robot queue, the
  container's bus subscriptions, interface links, data plane) over the window.
- planner view age: the planner's ``/fleet/state`` carries each robot's last pose; the robot
  encodes its send time (ms mod 100 s, 1e-6 m per ms) in ``position.y``, so for each state
  received here, age = now - send time of the newest pose the planner had processed (includes
  up to one pose period, 100 ms at 10 Hz, plus the state's own trip). Shows whether the
  planner itself keeps up (its subscriber queues drop silently when it does not).
- CPU % (of one core; the machine has ``os.cpu_count()``) of each process over the window
  (psutil CPU times): master, robot task set, container host, environment, planner node,
  echo node, client workers, this orchestrator; peak RSS (psutil, sampled every 0.5 s for
  the whole N, setup included); ``cpu_share``: cores of the engine, the load clients, the
  orchestrator and foreign load; ``cpu_us_per_pose``; per robot task set its CPU and robots.
- memory: rce-robot's RSS and USS (all task sets) before the robots connect and at the end of the
  window, and the growth per connected robot (``robot_memory``, KiB per robot).
- bytes on the wire per robot per second, counted at the websocket by the clients: every
  frame's payload plus its websocket header (2..14 bytes, the client's 4-byte mask
  included), up (robot -> cloud) and down; TCP/IP headers not included.
- the transport floor (``floor``, before each N; ``--no-floor`` skips it): the same robots,
  setup, warm-up and window against :mod:`fleet_floor`, as many processes as robot task sets
  that only echo each pose straight back over the robot's own websocket (websockets on uvloop,
  as rce-robot). Its latency, losses and CPU are what this machine carries at N robots with one
  websocket hop each way and nothing else: the engine's path has the same two hops, plus the
  container and the planner. A target the floor misses, the engine cannot meet here.
  ``engine_over_floor``: the engine's CPU per pose (master, robot task sets, the fleet container's
  processes) over the floor servers' at the same N, the two measured in the same run.
- setup (not part of the latency): engine start, fleet container + planner, echo node,
  robots (login, websocket with the master's scrypt check, CN 10 interfaces, CX 5
  connections, all interfaces up; ``--setup-concurrency`` robots at a time), warm-up (every
  robot's pose echoed and seen by the planner) and goals (every robot has its path).

The run stops at the first N whose p99 passes ``--max-p99`` ms (100) or that loses anything,
and says so; an engine process that exits (e.g. a task set dropped by the control plane's
keepalive under overload) ends it too, with the engine's warnings. Other processes on the
machine are not ours to stop: their load over each window is reported (``other load``).
Results: a table on stdout, ``--json`` (bench/results/fleet_load.json),
``--plot`` (bench/results/fleet_load.png: p50/p99 and CPU against N).

Usage::

    .venv/bin/python bench/fleet_load.py [--robots 10,100,300,1000] [--duration 10] [--rate 10]
        [--converter] [--container-cpu CORES] [--clients 1] [--robot-tasksets K] [--setup-concurrency 16]
        [--drain 3] [--max-p99 100] [--no-stop] [--no-floor] [--relay-floor] [--profile S] [--profile-labels L]
        [--wait-quiet S] [--raw DIR] [--json PATH] [--plot PATH]

``--profile S``: after each window, with the load still on, record the two hottest processes
(or those of ``--profile-labels``, e.g. ``planner,echo node``) for S s each with py-spy (when
installed: ``pip install py-spy``; not a project dependency) and list their top functions.
``--no-stop`` runs every N even past the first failure (which is still the one reported).
``--raw DIR`` writes every echo as CSV. The clients, the engine and the nodes all share the
machine's cores: a client worker near 100 % of a core, or a send rate below ``--rate``, is
reported.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import math
import multiprocessing as mp
import os
import random
import shutil
import struct
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections import defaultdict
from pathlib import Path
from typing import Callable

from rce_robot import ws_cork

from common import (BENCH, PASSWORD, RESULTS, USER, ForeignLoad, add_ws_impl_argument, console, engine, fmt_ms,
                    free_port, median, percentile, process_cpu_s, pyplot, set_nice, wait_quiet, write_json)
from fleet_floor import echo_main, floor_main
from fleet_wiring import CTAG, DOWN, ECHO_SUFFIX, POSE, robot_wiring

Y_MS_SCALE = 1e-6          # m of position.y per ms of the send time (mod Y_MS_MOD)
Y_MS_MOD = 100_000         # ms
DEFAULT_ROBOTS = "10,100,300,1000"
MAX_DEFAULT_TASKSETS = 4   # robot task sets by default: one per core, up to this many
DEFAULT_TASKSETS = max(1, min(os.cpu_count() or 1, MAX_DEFAULT_TASKSETS))
DEFAULT_CLIENTS = 1        # client worker processes: one event loop drives all the robots (they share the cores)
PACKAGES = BENCH / "packages"
INTERFACES_PER_ROBOT = 2 * (2 + len(DOWN))   # both ends of the pose, echo and DOWN links (robot_wiring)
INTERFACE_HEADROOM = 1000  # interfaces the fleet manager and its container take, with room to spare
GOAL_RESEND = 5.0          # s: goals of robots that have no path yet are sent again this often


# == the robots' plan (shared by the orchestrator and the workers) ==============================

def grid_for(n: int):
    """An all-free map with a grid of 1 m cells, two cells per robot: (GridGeometry, rows, cols)."""
    import numpy as np
    from rce_fleet.maps.geometry import GridGeometry
    from rce_fleet.maps.grid import make_grid
    from rce_fleet.maps.occupancy import FREE, OccupancyMap
    rows = max(2, math.ceil(math.sqrt(n)))
    cols = 2 * rows
    occ = np.full((rows * 10, cols * 10), FREE, dtype=np.int8)
    geo = GridGeometry.from_cellgrid(make_grid(OccupancyMap(occupancy=occ, resolution=0.1, origin=(0.0, 0.0, 0.0)),
                                               (rows, cols)))
    return geo, rows, cols


def placements(n: int, cols: int) -> list[tuple[int, int]]:
    """(start cell, goal cell) of robot i (0-based): starts in even columns, goal to the east."""
    half = cols // 2
    return [((i // half) * cols + 2 * (i % half), (i // half) * cols + 2 * (i % half) + 1) for i in range(n)]


def interface_quota(n: int) -> int:
    """The master's per-user interface quota (``--max-interfaces``) a run of ``n`` robots needs: all
    its robots are one user's (testUser), so the default quota (8192) would stop it at ~800."""
    return INTERFACES_PER_ROBOT * n + INTERFACE_HEADROOM


def path_cells(msg) -> list[int]:
    """The cells of a ``std_msgs/Int32MultiArray`` path: JSON form, or a binary part
    (32-byte id + ROS 1 serialization: dims (label, size, stride), data_offset, int32[])."""
    if not isinstance(msg, (bytes, bytearray)):
        return list(msg.get("data", []))
    off = 32
    (ndim,) = struct.unpack_from("<I", msg, off)
    off += 4
    for _ in range(ndim):
        (ln,) = struct.unpack_from("<I", msg, off)
        off += 4 + ln + 8
    off += 4
    (cnt,) = struct.unpack_from("<I", msg, off)
    return list(struct.unpack_from(f"<{cnt}i", msg, off + 4))


def ws_header(n: int, masked: bool) -> int:
    """Bytes of a websocket frame header for an ``n``-byte payload (RFC 6455)."""
    return 2 + (0 if n < 126 else 2 if n < 65536 else 8) + (4 if masked else 0)


# == a lightweight robot (runs in a worker process) ============================================

class Bot:
    """One robot: its websocket, its pose stream and what comes back."""

    def __init__(self, w: "Worker", n: int, x: float, y: float, phase: float, goal: int):
        self.w, self.n, self.rid, self.x, self.y0, self.phase, self.goal = w, n, f"Robot{n}", x, y, phase, goal
        self.adds, self.conns, self.roles = robot_wiring(n, w.side)
        self.role_of = {v: k for k, v in self.roles.items()}
        self.ws = None
        self.up: set[str] = set()
        self.errors: list[str] = []
        self.seq = 0
        self.got: set[int] = set()          # seqs echoed (window ones only)
        self.first_echo: float | None = None
        self.first_path: float | None = None
        self.win_first: int | None = None   # first and last seq sent in the window
        self.win_last: int | None = None
        self.dups = 0
        self.down = defaultdict(int)        # role -> messages received in the window
        self.pending: dict[str, str] = {}   # binary part id -> iTag (forwarder)
        self.setup_s = float("nan")
        self._upd = asyncio.Event()
        self.tasks: list[asyncio.Task] = []
        self.buf = bytearray(w.template) if w.side == "Forwarder" else None
        self.pose_itag = self.roles["pose"]
        self.stopped = False

    # -- setup ---------------------------------------------------------------------------------
    async def setup(self, master_url: str, timeout: float) -> None:
        from rce_client.connection import hash_password, login
        from websockets.asyncio.client import connect
        t0 = time.monotonic()
        last = None
        for attempt in range(4):
            try:
                url = await login(master_url, USER)
                self.ws = await connect(f"{url}?userID={USER}&robotID={self.rid}&password={hash_password(PASSWORD)}",
                                        max_size=None, compression=None, open_timeout=60, ping_interval=None,
                                        max_queue=None)
                break
            except Exception as e:     # a busy master (scrypt per handshake): try again
                last = e
                await asyncio.sleep(0.5 * (attempt + 1) + random.random())
        else:
            raise RuntimeError(f"{self.rid}: cannot connect: {last}")
        self.tasks.append(asyncio.create_task(self._reader()))
        await self.ws.send(json.dumps({"type": "CN", "data": {"addInterfaces": self.adds}}))
        await self.ws.send(json.dumps({"type": "CX", "data": {"connect": self.conns}}))
        want = set(self.roles.values())
        deadline = time.monotonic() + timeout
        while not want <= self.up:
            if self.errors:
                raise RuntimeError(f"{self.rid}: {self.errors[0]}")
            left = deadline - time.monotonic()
            if left <= 0:
                raise RuntimeError(f"{self.rid}: interfaces still down after {timeout:g} s: {sorted(want - self.up)}")
            self._upd.clear()
            try:
                await asyncio.wait_for(self._upd.wait(), left)
            except asyncio.TimeoutError:
                pass
        self.setup_s = time.monotonic() - t0

    # -- receiving -----------------------------------------------------------------------------
    async def _reader(self) -> None:
        from websockets.exceptions import ConnectionClosed
        w = self.w
        try:
            async for frame in self.ws:
                now = time.time_ns()
                if w.counting:
                    w.bytes_down += len(frame) + ws_header(len(frame), False)
                if isinstance(frame, str):
                    m = json.loads(frame)
                    t, data = m.get("type"), m.get("data")
                    if t == "DM":
                        itag = data.get("iTag")
                        ref = data.get("msg*")
                        if ref is not None:
                            self.pending[ref] = itag
                        else:
                            self._on_msg(itag, data.get("msg"), now)
                    elif t == "ST":
                        if data.get("topic") == "iu" and data.get("status"):
                            self.up.add(data["iTag"])
                            self._upd.set()
                    elif t == "ER":
                        self.errors.append(str(data))
                        w.errors += 1
                        self._upd.set()
                else:
                    itag = self.pending.pop(frame[:32].decode(), None)
                    if itag is not None:
                        self._on_msg(itag, frame, now)
        except ConnectionClosed:
            pass

    def _on_msg(self, itag: str, msg, now: int) -> None:
        role = self.role_of.get(itag)
        w = self.w
        if role == "echo":
            if isinstance(msg, (bytes, bytearray)):
                seq, secs, nsecs = struct.unpack_from("<III", msg, 32)
            else:
                h = msg["header"]
                seq, secs, nsecs = h["seq"], h["stamp"]["secs"], h["stamp"]["nsecs"]
            if self.first_echo is None:
                self.first_echo = time.time()
            stamp = secs * 1_000_000_000 + nsecs
            # a window pose sent before this worker took the window command (a starved worker) is in
            # neither count
            if w.win_start_ns <= stamp <= w.win_end_ns and self.win_first is not None and seq >= self.win_first:
                if seq in self.got:
                    self.dups += 1
                    return
                self.got.add(seq)
                w.lat.append((now - stamp) / 1e6)
                if w.raw is not None:
                    w.raw.append((self.n, seq, stamp / 1e9, (now - stamp) / 1e6))
        elif role is not None:
            if role == "goalNodesList" and self.first_path is None and self.goal in path_cells(msg):
                self.first_path = time.time()
            if w.counting:
                self.down[role] += 1

    # -- sending -------------------------------------------------------------------------------
    def publish(self, late: float) -> None:
        """Send the next pose now, ``late`` s after its tick: its frames in one corked write
        (:mod:`rce_robot.ws_cork`), nothing awaited. A link that does not take it now (buffer above
        its high-water mark) skips the tick (counted in ``skipped``); a closed one stops this robot."""
        w = self.w
        if self.ws is None or self.stopped:
            return
        if not ws_cork.writable(self.ws):
            if ws_cork.paused(self.ws):
                w.skipped += 1
            else:
                self.stopped = True       # the connection is gone (its window poses count)
            return
        t_ns = time.time_ns()
        seq = self.seq
        self.seq += 1
        y = self.y0 + ((t_ns // 1_000_000) % Y_MS_MOD) * Y_MS_SCALE
        secs, nsecs = divmod(t_ns, 1_000_000_000)
        if w.side == "Forwarder":
            ref = f"{self.n:08x}{seq:024x}"
            buf = self.buf
            buf[0:32] = ref.encode()
            struct.pack_into("<III", buf, 32, seq, secs, nsecs)
            struct.pack_into("<dd", buf, 32 + w.pos_off, self.x, y)
            frames = (w.text_tpl % (self.pose_itag, ref), bytes(buf))
        else:
            frames = (w.text_tpl % (self.pose_itag, seq, secs, nsecs, self.x, y),)
        n = ws_cork.write(self.ws, frames)
        if w.counting:
            w.bytes_up += n
        if w.win_start_ns <= t_ns <= w.win_end_ns:
            if self.win_first is None:
                self.win_first = seq
            self.win_last = seq
            w.send_late.append(late * 1e3)


class Worker:
    """A client worker process: its share of the robots on one event loop; commands and replies
    (dicts) on the pipe ``conn``."""

    def __init__(self, conn, master_url: str, robots: list[tuple[int, float, float, float, int]], side: str,
                 rate: float, concurrency: int):
        from rce.messages import default_registry
        self.conn, self.master_url, self.side, self.rate, self.concurrency = conn, master_url, side, rate, concurrency
        self.robots_spec = robots
        self.bots: list[Bot] = []
        self.lat: list[float] = []
        self.send_late: list[float] = []
        self.bytes_up = self.bytes_down = 0
        self.errors = 0
        self.skipped = 0                   # pose ticks skipped: the robot's link did not take them (buffer full)
        self.ticker: asyncio.Task | None = None
        self.raw: list | None = None       # (robot, seq, stamp s, latency ms) with --raw
        self.counting = False
        self.win_start_ns = self.win_end_ns = -1
        reg = default_registry()
        cov = [0.0] * 36
        cov[0] = cov[7] = 0.05
        cov[35] = 0.02
        msg = {"header": {"seq": 0, "stamp": {"secs": 0, "nsecs": 0}, "frame_id": "map"},
               "pose": {"pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0},
                                 "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                        "covariance": cov}}
        typ = reg.msg_type(POSE)
        payload = reg.json_to_bytes(typ, msg)
        self.pos_off = 12 + 4 + len(b"map")          # header: seq, stamp, frame_id; then position x, y
        probe = bytearray(payload)
        struct.pack_into("<dd", probe, self.pos_off, 1.25, 2.5)
        p = reg.bytes_to_json(typ, bytes(probe))["pose"]["pose"]["position"]
        assert (p["x"], p["y"]) == (1.25, 2.5), p
        self.template = b"\0" * 32 + payload
        if side == "Forwarder":
            self.text_tpl = '{"type":"DM","data":{"iTag":"%s","type":"' + POSE + '","msgID":"","msg*":"%s"}}'
        else:
            cov_s = json.dumps(cov)
            self.text_tpl = ('{"type":"DM","data":{"iTag":"%s","type":"' + POSE + '","msgID":"","msg":'
                             '{"header":{"seq":%d,"stamp":{"secs":%d,"nsecs":%d},"frame_id":"map"},'
                             '"pose":{"pose":{"position":{"x":%r,"y":%r,"z":0.0},'
                             '"orientation":{"x":0.0,"y":0.0,"z":0.0,"w":1.0}},"covariance":' + cov_s + '}}}}')

    def reply(self, **kw) -> None:
        self.conn.send(kw)

    async def recv(self) -> dict:
        return await asyncio.get_running_loop().run_in_executor(None, self.conn.recv)

    async def main(self) -> None:
        while True:
            cmd = await self.recv()
            op = cmd["op"]
            if op == "setup":
                await self.setup(cmd["timeout"])
            elif op == "publish":
                self.ticker = asyncio.create_task(self.publish_all(cmd["t_start"], 1.0 / self.rate))
                self.reply(ok=True)
            elif op == "status":
                self.reply(echoed=sum(1 for b in self.bots if b.first_echo is not None),
                           pathed={b.rid: b.first_path for b in self.bots if b.first_path is not None},
                           errors=self.errors, last_errors=[e for b in self.bots for e in b.errors][-3:])
            elif op == "window":
                await self.window(cmd["start"], cmd["end"], cmd["drain"], cmd.get("raw", False))
            elif op == "exit":
                self.reply(ok=True)
                return

    async def publish_all(self, t_start: float, period: float) -> None:
        """One timer for all this worker's robots: robot ``b`` publishes at ``t_start + b.phase + k *
        period`` (wall s), in phase order. When the loop falls more than a period behind, the missed
        rounds are skipped for every robot (never a burst); a late tick is sent at once."""
        bots = sorted(self.bots, key=lambda b: b.phase)
        if not bots:
            return
        mono0 = time.monotonic() + (t_start - time.time())
        k = 0
        while True:
            base = mono0 + k * period
            behind = time.monotonic() - (base + period)
            if behind > 0:                      # a whole round late: skip the missed rounds
                k += 1 + int(behind // period)
                continue
            for b in bots:
                due = base + b.phase
                delay = due - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
                b.publish(time.monotonic() - due)
            k += 1

    async def setup(self, timeout: float) -> None:
        sem = asyncio.Semaphore(self.concurrency)
        n_total = len(self.robots_spec)
        self.bots = [Bot(self, *spec) for spec in self.robots_spec]
        failures: list[str] = []

        async def one(b: Bot) -> None:
            async with sem:
                try:
                    await b.setup(self.master_url, timeout)
                except Exception as e:
                    failures.append(str(e))
        t0 = time.monotonic()
        await asyncio.gather(*(one(b) for b in self.bots))
        self.reply(setup_s=[b.setup_s for b in self.bots], wall_s=time.monotonic() - t0, failures=failures[:5],
                   failed=len(failures), robots=n_total)

    async def window(self, start: float, end: float, drain: float, raw: bool = False) -> None:
        self.raw = [] if raw else None
        self.lat.clear()
        self.send_late.clear()
        for b in self.bots:
            b.got.clear()
            b.win_first = b.win_last = None
            b.dups = 0
            b.down.clear()
        self.win_start_ns, self.win_end_ns = int(start * 1e9), int(end * 1e9)
        await asyncio.sleep(max(0.0, start - time.time()))
        self.bytes_up = self.bytes_down = 0
        self.skipped = 0
        self.counting = True
        await asyncio.sleep(max(0.0, end - time.time()))
        self.counting = False
        up, down = self.bytes_up, self.bytes_down
        # every echo of a window pose that is coming comes within ``drain`` s
        deadline = time.time() + drain
        while time.time() < deadline:
            if all(b.win_first is None or len(b.got) >= b.win_last - b.win_first + 1 for b in self.bots):
                break
            await asyncio.sleep(0.05)
        per_robot = {}
        for b in self.bots:
            sent = 0 if b.win_first is None else b.win_last - b.win_first + 1
            per_robot[b.rid] = {"sent": sent, "received": len(b.got), "lost": sent - len(b.got), "dups": b.dups,
                                "down": dict(b.down)}
        self.reply(lat=self.lat, raw=self.raw, send_late=self.send_late, bytes_up=up, bytes_down=down, robots=per_robot,
                   errors=self.errors, skipped=self.skipped)


def worker_main(conn, master_url, robots, side, rate, concurrency) -> None:
    """Entry point of a client worker process."""
    from rce.plumbing.process import run_loop     # uvloop when installed, as the engine's processes
    w = Worker(conn, master_url, robots, side, rate, concurrency)
    try:
        run_loop(w.main())
    except (KeyboardInterrupt, EOFError, BrokenPipeError):
        pass


# == the orchestrator ===========================================================================

class Procs:
    """The processes of one run, labelled: engine task sets, the container's environment and
    nodes, the client workers and this process. :meth:`sample` keeps each label's peak RSS."""

    ORDER = ("master", "robot", "container host", "environment", "planner", "echo node", "sandbox",
             "clients", "orchestrator")

    def __init__(self, eng, workers: list):
        self.eng, self.workers = eng, workers
        self.peak: dict[str, float] = defaultdict(float)     # MiB
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def roots(self) -> list[tuple[int, str]]:
        """(pid, label) of the engine's processes, the client workers and this process. Every robot task
        set is ``robot`` (``--robot-tasksets``; :meth:`robot_pids` tells them apart)."""
        kinds = (("rce-master", "master"), ("rce-robot", "robot"), ("rce-container", "container host"))
        out = []
        for p in self.eng.procs:
            args = " ".join(str(a) for a in p.args[:3])
            lab = next((lab for k, lab in kinds if k in args or k.replace("-", "_") in args), None)
            if lab is not None:
                out.append((p.pid, lab))
        return out + [(os.getpid(), "orchestrator")] + [(w.pid, "clients") for w in self.workers if w.pid]

    def robot_pids(self) -> list[int]:
        """The robot task sets' pids, in the order they were started."""
        return [pid for pid, lab in self.roots() if lab == "robot"]

    def label(self, p, root_label: str, root_pid: int) -> str:
        if root_label != "container host" or p.pid == root_pid:
            return root_label
        try:
            cmd = " ".join(p.cmdline())
        except Exception:
            return "sandbox"
        if "global_planner" in cmd:
            return "planner"
        if "echo.py" in cmd:
            return "echo node"
        if "environment" in cmd:
            return "environment"
        return "sandbox"

    def snapshot(self) -> dict:
        """{pid: (label, process)} of everything alive now."""
        import psutil
        out = {}
        for pid, lab in self.roots():
            try:
                root = psutil.Process(pid)
                kids = root.children(recursive=True) if lab != "orchestrator" else []
            except psutil.Error:
                continue
            for p in [root] + kids:
                out.setdefault(p.pid, (self.label(p, lab, pid), p))
        for p in self.orphan_nodes(out):
            out.setdefault(p.pid, (self.label(p, "container host", -1), p))
        return out

    def orphan_nodes(self, known: dict) -> list:
        """The container's node processes that are not below the container host: a zygote's forks
        (:mod:`rce_container.zygote`) leave its process tree (the sandbox's PID-namespace fork). Found by
        their working directory, under this engine's work directory (the container's runtime dir)."""
        import psutil
        root = str(self.eng.workdir)
        out = []
        for p in psutil.process_iter():
            if p.pid in known:
                continue
            try:
                if p.cwd().startswith(root):
                    out.append(p)
            except psutil.Error:
                continue
        return out

    def robot_memory(self) -> dict:
        """RSS and USS (MiB; psutil ``memory_full_info``: USS is the memory that would be freed if
        the process exited) of each robot task set, and their sums."""
        import psutil
        per = []
        for pid in self.robot_pids():
            try:
                m = psutil.Process(pid).memory_full_info()
            except psutil.Error:
                continue
            per.append({"pid": pid, "rss_mib": round(m.rss / 2**20, 2), "uss_mib": round(m.uss / 2**20, 2)})
        return {"rss_mib": round(sum(x["rss_mib"] for x in per), 2),
                "uss_mib": round(sum(x["uss_mib"] for x in per), 2), "tasksets": per}

    def sample(self) -> None:
        sums: dict[str, float] = defaultdict(float)
        for lab, p in self.snapshot().values():
            try:
                sums[lab] += p.memory_info().rss / 2**20
            except Exception:
                pass
        sums["container (all)"] = sum(v for k, v in sums.items()
                                      if k in ("container host", "environment", "planner", "echo node", "sandbox"))
        for k, v in sums.items():
            self.peak[k] = max(self.peak[k], v)

    def start(self, interval: float = 0.5) -> "Procs":
        def run() -> None:
            while not self._stop.wait(interval):
                self.sample()
        self.sample()
        self._thread = threading.Thread(target=run, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread:
            self._thread.join(5)


class CpuWindow:
    """CPU time per label between :meth:`start` and :meth:`stop` (processes alive at both)."""

    def __init__(self, procs: Procs):
        self.procs = procs

    @staticmethod
    def _times(snap: dict) -> dict:
        out = {}
        for pid, (lab, p) in snap.items():
            try:
                out[pid] = (lab, process_cpu_s(p))
            except Exception:
                pass
        return out

    def start(self) -> None:
        import psutil
        self.t0 = self._times(self.procs.snapshot())
        self.w0 = time.monotonic()
        self.m0 = psutil.cpu_times()

    def stop(self) -> dict:
        import psutil
        t1 = self._times(self.procs.snapshot())
        wall = time.monotonic() - self.w0
        m1 = psutil.cpu_times()
        pct: dict[str, float] = defaultdict(float)
        by_pid = {}
        for pid, (lab, c1) in t1.items():
            if pid in self.t0:
                d = 100.0 * (c1 - self.t0[pid][1]) / wall
                pct[lab] += d
                by_pid[pid] = (lab, d)
        pct["container (all)"] = sum(v for k, v in pct.items()
                                     if k in ("container host", "environment", "planner", "echo node", "sandbox"))
        busy = lambda t: sum(t) - t.idle - getattr(t, "iowait", 0.0)  # noqa: E731
        pct["machine"] = 100.0 * (busy(m1) - busy(self.m0)) / wall
        self.by_pid = by_pid
        return {k: round(v, 1) for k, v in pct.items()}


def engine_drops(eng) -> dict:
    """Drop counters of the engine: the fleet container (bus subscriptions, interfaces, its data
    plane, per node) and the robot task sets (per-robot queues both ways, topic messages shed while
    an endpoint lagged behind its robots, their data planes)."""
    out = {}
    try:
        st = eng.admin(f"api/containers/{USER}/{CTAG}/stats")
        out["container_bus"] = st["dropped"]["bus"]
        out["container_interfaces"] = st["dropped"]["interfaces"]
        out["container_dataplane"] = st["environment"]["dataplane"]["dropped"]
        for ntag, nd in st.get("per_node", {}).items():
            out[f"node_{ntag}"] = nd.get("dropped", 0)
    except Exception as e:       # noqa: BLE001  (reported, not fatal)
        out["container_error"] = str(e)
    for info in eng.robot_ready:          # every robot task set: the sums
        try:
            for name, val in robot_metrics(info).items():
                if name in ("rce_robot_dropped_total", "rce_robot_dropped_in_total", "rce_robot_shed_total",
                            "rce_robot_dataplane_dropped"):
                    key = name.replace("rce_robot_", "robot_").replace("_total", "")
                    out[key] = out.get(key, 0) + int(val)
        except Exception as e:   # noqa: BLE001
            out["robot_error"] = str(e)
    return out


def robot_memory_report(before: dict, at_load: dict, n: int) -> dict:
    """rce-robot's memory (all its task sets) before the robots connect and at full load (MiB), and
    per connected robot (KiB): the growth over ``n`` robots (RSS and USS), and the whole RSS over them."""
    per = lambda k: round((at_load[k] - before[k]) * 1024 / n, 1)  # noqa: E731
    return {"before": before, "at_load": at_load, "rss_per_robot_kib": per("rss_mib"),
            "uss_per_robot_kib": per("uss_mib"), "rss_total_per_robot_kib": round(at_load["rss_mib"] * 1024 / n, 1)}


def taskset_report(eng, procs: Procs, cpu_by_pid: dict) -> list[dict]:
    """Per robot task set: its pid, CPU % of one core over the window, and the robots connected to
    it (its ``rce_robot_connections`` gauge): shows whether the master's placement spreads them."""
    out = []
    for pid, info in zip(procs.robot_pids(), eng.robot_ready, strict=False):
        try:
            robots = int(robot_metrics(info).get("rce_robot_connections", -1))
        except OSError:
            robots = None
        out.append({"pid": pid, "cpu_pct": round(cpu_by_pid.get(pid, ("", float("nan")))[1], 1), "robots": robots})
    return out


def cpu_share(cpu: dict, load: dict) -> dict:
    """Cores (1.0 = one core) over the window: the engine's own (master, robot task sets, the fleet
    container's processes), the load clients (the simulated robots), this orchestrator (the fleet
    manager), everything else on the machine (``other``), and the machine's total."""
    core = lambda *ks: round(sum(cpu.get(k, 0.0) for k in ks) / 100, 2)  # noqa: E731
    return {"engine": core("master", "robot", "container (all)"), "load_clients": core("clients"),
            "orchestrator": core("orchestrator"), "other": load.get("other_cores"), "machine": core("machine")}


def robot_metrics(info: dict) -> dict[str, float]:
    """The Prometheus samples (name -> value, unlabelled ones) of the robot task set whose ready
    info is ``info`` (its ``metrics_port``). Raises OSError when it does not answer."""
    out = {}
    with urllib.request.urlopen(f"http://127.0.0.1:{info['metrics_port']}/metrics", timeout=30) as r:
        for line in r.read().decode().splitlines():
            name, _, val = line.partition(" ")
            if not name.startswith("#") and val:
                out[name] = float(val)
    return out


def engine_events(eng, limit: int = 8) -> list[str]:
    """The engine's warnings and errors (JSON log lines), most recent last: what broke."""
    out = []
    for path in eng.logs:
        try:
            lines = path.read_text(errors="replace").splitlines()
        except OSError:
            continue
        seen = set()
        for line in lines:
            try:
                d = json.loads(line)
            except ValueError:
                continue
            if d.get("level") not in ("warning", "error", "critical") or d.get("msg") in seen:
                continue
            seen.add(d.get("msg"))     # one line per kind of event and process
            extra = {k: v for k, v in d.items() if k not in ("ts", "level", "logger", "msg")}
            out.append((d.get("ts", 0), f"{path.stem}: {d.get('msg')} {json.dumps(extra)[:160]}"))
    return [t for _, t in sorted(out)][-limit:]


def check_engine(eng, what: str) -> None:
    """Raise when an engine process has exited (the run cannot go on), naming what the logs say."""
    dead = eng.alive()
    if dead:
        names = sorted({os.path.basename(d) for d in dead})
        raise RuntimeError(f"engine collapsed during {what}: {', '.join(names)} exited; "
                           + " | ".join(engine_events(eng, 5)))


def diff_drops(a: dict, b: dict) -> dict:
    return {k: b[k] - a.get(k, 0) for k in b if isinstance(b[k], int)}


# leaf frames of a thread waiting in its event loop (asyncio's, or uvloop's C loop under run/Runner.run) or
# in an idle executor thread
WAIT_FRAMES = ("EpollSelector.select", "Runner.run", "run", "_worker", "BaseEventLoop.run_forever",
               "BaseEventLoop._run_once", "BaseEventLoop.run_until_complete")


def pyspy_top(pid: int, seconds: float, out: Path, top: int = 12) -> dict:
    """Record ``pid`` with py-spy for ``seconds`` (100 Hz, idle samples left out); returns the
    share of samples waiting in the event loop (``wait_pct``: the process was runnable in or
    right after ``epoll``, i.e. mostly waiting for a CPU on a busy machine), the functions
    with the most own samples, and the heaviest inclusive ones below the event loop (% of all
    samples)."""
    exe = shutil.which("py-spy") or (str(Path(sys.executable).parent / "py-spy")
                                     if (Path(sys.executable).parent / "py-spy").exists() else None)
    if not exe:
        return {"error": "py-spy not installed"}
    r = subprocess.run([exe, "record", "--pid", str(pid), "--duration", str(int(max(1, seconds))), "--rate", "100",
                        "--format", "raw", "--output", str(out)], capture_output=True, text=True)
    if r.returncode != 0 or not out.exists():
        return {"error": (r.stderr or r.stdout).strip()[-300:]}
    own: dict[str, int] = defaultdict(int)
    incl: dict[str, int] = defaultdict(int)
    total = wait = 0
    for line in out.read_text().splitlines():
        stack, _, cnt = line.rpartition(" ")
        if not stack or not cnt.isdigit():
            continue
        n = int(cnt)
        total += n
        frames = []
        for f in stack.split(";"):        # "func (path/file.py:line)" -> "func (file.py)"
            name, _, where = f.partition(" (")
            frames.append(f"{name} ({os.path.basename(where.split(':')[0])})" if where else name)
        if frames[-1].split(" (")[0] in WAIT_FRAMES:
            wait += n
            continue
        own[frames[-1]] += n
        for f in set(frames):
            if f.split(" (")[0] not in WAIT_FRAMES:
                incl[f] += n
    if not total:
        return {"error": "no samples"}
    def pct(d: dict, skip_above: float) -> list:
        return [(k, round(100.0 * v / total, 1)) for k, v in sorted(d.items(), key=lambda kv: -kv[1])
                if v <= skip_above][:top]
    # inclusive: leave out the frames (nearly) every busy sample has (<module>, main, the loop's run)
    return {"samples": total, "wait_pct": round(100.0 * wait / total, 1), "own": pct(own, total),
            "inclusive": pct(incl, 0.9 * max(incl.values(), default=0))}


class Run:
    """One N: engine, fleet container, echo node, workers, warm-up, goals, window."""

    def __init__(self, n: int, args, con):
        self.n, self.args, self.con = n, args, con
        self.side = "Converter" if args.converter else "Forwarder"
        self.geo, self.rows, self.cols = grid_for(n)
        self.place = placements(n, self.cols)
        self.robots = [f"Robot{i + 1}" for i in range(n)]
        self.res: dict = {"robots": n, "mode": self.side.lower(), "rate_hz": args.rate, "duration_s": args.duration,
                          "grid": f"{self.rows}x{self.cols}", "setup": {}, "notes": []}
        self.ages: list[float] = []
        self.states = self.states_win = 0
        self.planner_seen: set[str] = set()
        self.counting_ages = False

    def log(self, text: str) -> None:
        self.con.print(f"[dim]N={self.n}:[/dim] {text}")

    # -- the fleet state: planner view age ------------------------------------------------------
    def on_state(self, st: dict) -> None:
        self.states += 1
        now_ms = time.time() * 1e3
        for r in st.get("robots", []):
            if r.get("cell", -1) < 0:
                continue
            self.planner_seen.add(r["robot"])
            if not self.counting_ages:
                continue
            if r is st["robots"][0]:
                self.states_win += 1
            i = int(r["robot"][5:]) - 1
            y0 = self.geo.center(self.place[i][0])[1]
            y = r.get("y")
            if y is None or not math.isfinite(y):
                continue
            sent_ms = round((y - y0) / Y_MS_SCALE)
            self.ages.append((now_ms % Y_MS_MOD - sent_ms) % Y_MS_MOD)

    # -- workers ---------------------------------------------------------------------------------
    def start_workers(self, master_url: str) -> None:
        ctx = mp.get_context("spawn")
        k = max(1, min(self.args.clients, self.n))
        per = [[] for _ in range(k)]
        period = 1.0 / self.args.rate
        for i in range(self.n):
            x, y = self.geo.center(self.place[i][0])
            per[i % k].append((i + 1, x, y, period * i / self.n, self.place[i][1]))
        conc = max(1, self.args.setup_concurrency // k)
        self.pipes = []
        for chunk in per:
            a, b = ctx.Pipe()
            p = ctx.Process(target=worker_main, args=(b, master_url, chunk, self.side, self.args.rate, conc),
                            daemon=True)
            p.start()
            self.pipes.append(a)
            self.workers.append(p)

    async def ask_all(self, cmd: dict, timeout: float) -> list[dict]:
        for c in self.pipes:
            c.send(cmd)
        loop = asyncio.get_running_loop()

        def recv(c):
            if not c.poll(timeout):
                raise TimeoutError(f"client worker did not answer {cmd['op']!r} within {timeout:g} s")
            return c.recv()
        return await asyncio.gather(*(loop.run_in_executor(None, recv, c) for c in self.pipes))

    def stop_workers(self) -> None:
        for c in getattr(self, "pipes", []):
            try:
                c.send({"op": "exit"})
            except Exception:
                pass
        for p in getattr(self, "workers", []):
            p.join(5)
            if p.is_alive():
                p.terminate()
                p.join(5)

    # -- the run --------------------------------------------------------------------------------
    async def measure(self, eng, procs: Procs) -> None:
        try:
            await self._measure(eng, procs)
        finally:
            mgr = getattr(self, "mgr", None)
            if mgr is not None:
                try:
                    await asyncio.wait_for(mgr.close(destroy=False), 5)
                except Exception:    # noqa: BLE001  (the engine goes next anyway)
                    pass

    async def _measure(self, eng, procs: Procs) -> None:
        from rce.plumbing.errors import RCEError
        from rce_fleet.live.manager import FleetManager
        a, res, n = self.args, self.res, self.n
        setup = res["setup"]
        t = time.monotonic()
        mgr = FleetManager(eng.master_url, self.geo, self.robots, planner_args="--no-lidar-blocking",
                           on_state=self.on_state, container_cpu=a.container_cpu)
        self.mgr = mgr
        await mgr.start(timeout=120 + n * 0.05)
        # the pose echo, in the fleet container, on the planner's own input topics
        echo_args = ["--type", POSE, "--back", "--suffix", ECHO_SUFFIX, "--report", "5", "--queue", "100"]
        echo_args += [f"/{r}/amcl_pose" for r in self.robots]
        await mgr.conn.add_node(CTAG, "pose_echo", "benchecho", "echo.py", args=echo_args)
        nerr = len(mgr.errors)
        await mgr.conn.barrier(120)
        if len(mgr.errors) > nerr:
            raise RuntimeError(f"echo node refused: {mgr.errors[nerr]}")
        setup["fleet_container_s"] = round(time.monotonic() - t, 2)
        self.log(f"fleet container, planner and echo node up in {setup['fleet_container_s']} s")

        mem0 = await asyncio.to_thread(procs.robot_memory)
        await self._setup_robots(eng.master_url)

        # warm-up: every pose echoed, every robot seen by the planner
        await self._warmup(lambda: check_engine(eng, "warm-up"), planner=True)

        # goals: the neighbouring cell, through /fleet/goal, paced for the planner's goal queue
        t = time.monotonic()
        sent_at: dict[str, float] = {}

        async def send_goals(which: list[str]) -> None:
            try:
                for k, r in enumerate(which):
                    sent_at[r] = time.time()
                    await mgr.set_goal(r, self.place[int(r[5:]) - 1][1])
                    if k % 25 == 24:
                        await asyncio.sleep(0.05)
            except RCEError as e:       # the operator's link is part of the load: say it broke, go on
                res["notes"].append(f"fleet manager could not send goals: {e.message}")
        await send_goals(self.robots)
        deadline = time.monotonic() + 60 + n * 0.05
        resent, last_sent = 0, time.monotonic()
        while True:
            await asyncio.sleep(0.5)
            st = await self.ask_all({"op": "status"}, timeout=60)
            pathed = {r: tp for s in st for r, tp in s["pathed"].items()}
            check_engine(eng, "goals")
            if len(pathed) == n or mgr.conn.closed:
                break
            if time.monotonic() - last_sent > GOAL_RESEND:     # topics may drop under overload: a goal is
                resent += 1                                    # idempotent, so the manager sends it again
                await send_goals([r for r in self.robots if r not in pathed])
                last_sent = time.monotonic()
            if time.monotonic() > deadline:
                errs = (self.mgr.latest or {}).get("errors", [])[-3:]
                res["notes"].append(f"goals: only {len(pathed)}/{n} robots got their path within "
                                    f"{time.monotonic() - t:.0f} s" + (f"; planner errors: {errs}" if errs else ""))
                break
        g2p = [(pathed[r] - sent_at[r]) * 1e3 for r in self.robots if r in pathed]
        setup["goals_s"] = round(time.monotonic() - t, 2)
        res["goal_to_path_ms"] = {"p50": median(g2p), "max": max(g2p, default=float("nan")), "resent": resent,
                                  "robots_with_path": len(pathed)}
        self.log(f"warm-up {setup['warmup_s']} s; {len(pathed)}/{n} robots have their path ({setup['goals_s']} s, "
                 f"goal->path p50 {fmt_ms(median(g2p))} ms)")

        check_engine(eng, "goals")
        # the window
        drops0 = await asyncio.to_thread(engine_drops, eng)
        cpu = await self._window(procs)
        res["robot_memory"] = robot_memory_report(mem0, await asyncio.to_thread(procs.robot_memory), n)
        res["robot_tasksets"] = await asyncio.to_thread(taskset_report, eng, procs, cpu.by_pid)
        reps = await self._replies()
        check_engine(eng, "the measured window")
        drops1 = await asyncio.to_thread(engine_drops, eng)
        res["engine_drops"] = diff_drops(drops0, drops1)
        for k in ("container_error", "robot_error"):
            if k in drops1:
                res["notes"].append(f"engine counters: {drops1[k]}")
        self._summarize(reps, cpu)
        if a.profile > 0:
            prof = {}
            want = [w for w in a.profile_labels.split(",") if w]
            picked = ([x for x in res["cpu_by_process"] if x["label"] in want] if want
                      else res["cpu_by_process"][:2])
            for x in picked:
                self.log(f"py-spy: recording {x['label']} (pid {x['pid']}, {x['pct']} % CPU) for {a.profile:g} s")
                prof[x["label"]] = {"pid": x["pid"], "cpu_pct": x["pct"], **await asyncio.to_thread(
                    pyspy_top, x["pid"], a.profile, Path(tempfile.mkdtemp(prefix="fleetload-spy-")) / "raw.txt")}
            res["profile"] = prof

    async def _setup_robots(self, url: str) -> None:
        """Start the client workers on the login ``url`` and set every robot up (login, websocket,
        CN, CX, interfaces up); raises when one fails."""
        n, setup = self.n, self.res["setup"]
        t = time.monotonic()
        self.start_workers(url)
        reps = await self.ask_all({"op": "setup", "timeout": 120 + n * 0.2}, timeout=600 + n * 2)
        failed = sum(r["failed"] for r in reps)
        per_robot = [s for r in reps for s in r["setup_s"] if s == s]
        setup["robots_s"] = round(time.monotonic() - t, 2)
        setup["per_robot_p50_s"] = round(median(per_robot), 3)
        setup["per_robot_p99_s"] = round(percentile(per_robot, 99), 3)
        setup["robots_failed"] = failed
        if failed:
            first = [f for r in reps for f in r["failures"]][:3]
            raise RuntimeError(f"{failed} of {n} robots failed to set up: {first}")
        self.log(f"{n} robots connected and wired in {setup['robots_s']} s "
                 f"(per robot p50 {setup['per_robot_p50_s']} s, p99 {setup['per_robot_p99_s']} s)")

    async def _warmup(self, check: Callable[[], None], planner: bool) -> None:
        """Start the poses and wait until every robot's pose has been echoed (and, with ``planner``,
        seen by the planner), at least ``--warmup`` s; past ``--warmup-timeout`` go on and say so.
        ``check()`` raises when the server side died."""
        a, res, n = self.args, self.res, self.n
        t = time.monotonic()
        await self.ask_all({"op": "publish", "t_start": time.time() + 0.3}, timeout=60)
        deadline = time.monotonic() + a.warmup_timeout + n * 0.05
        while True:
            await asyncio.sleep(0.5)
            st = await self.ask_all({"op": "status"}, timeout=60)
            echoed = sum(s["echoed"] for s in st)
            check()
            seen = len(self.planner_seen) if planner else n
            if echoed == n and seen == n and time.monotonic() - t >= a.warmup:
                break
            if time.monotonic() > deadline:     # overloaded: measure anyway, and say so
                errs = [e for s in st for e in s["last_errors"]]
                res["notes"].append(f"warm-up incomplete after {time.monotonic() - t:.0f} s: {echoed}/{n} robots "
                                    f"echoed" + (f", planner saw {seen}/{n}" if planner else "")
                                    + (f"; errors: {errs}" if errs else ""))
                break
        res["setup"]["warmup_s"] = round(time.monotonic() - t, 2)
        check()

    async def _window(self, procs) -> "CpuWindow":
        """The measured window: the workers count from ``now + 0.5 s`` for ``--duration`` s; the
        processes' CPU (``procs``: :class:`Procs` or :class:`FloorProcs`) and the machine's load
        over it go into the results. Returns the stopped :class:`CpuWindow`."""
        a, res = self.args, self.res
        start = time.time() + 0.5
        end = start + a.duration
        for c in self.pipes:
            c.send({"op": "window", "start": start, "end": end, "drain": a.drain, "raw": a.raw is not None})
        await asyncio.sleep(max(0.0, start - time.time()))
        cpu = CpuWindow(procs)
        fl = ForeignLoad().start()
        cpu.start()
        self.counting_ages = True
        await asyncio.sleep(max(0.0, end - time.time()))
        res["cpu_pct"] = cpu.stop()
        self.counting_ages = False
        res["machine_load"] = fl.stop()
        res["cpu_share"] = cpu_share(res["cpu_pct"], res["machine_load"])
        return cpu

    async def _replies(self) -> list[dict]:
        """The workers' window reports (they come ``--drain`` s after the window at most)."""
        loop = asyncio.get_running_loop()
        return list(await asyncio.gather(*(loop.run_in_executor(None, c.recv) for c in self.pipes)))

    def _summarize(self, reps: list[dict], cpu: "CpuWindow") -> None:
        """Latency, losses, rates, bytes and CPU per pose of the window from the workers' reports."""
        a, res, n = self.args, self.res, self.n
        lat = [x for r in reps for x in r["lat"]]
        if a.raw is not None:
            a.raw.mkdir(parents=True, exist_ok=True)
            with open(a.raw / f"latency_{n}.csv", "w") as f:
                f.write("robot,seq,stamp_s,latency_ms\n")
                for row in sorted((x for r in reps for x in r["raw"]), key=lambda x: x[2]):
                    f.write("%d,%d,%.6f,%.3f\n" % row)
        late = [x for r in reps for x in r["send_late"]]
        robots = {k: v for r in reps for k, v in r["robots"].items()}
        sent = sum(v["sent"] for v in robots.values())
        lost = sum(v["lost"] for v in robots.values())
        res.update({
            "latency_ms": {"p50": median(lat), "p90": percentile(lat, 90), "p99": percentile(lat, 99),
                           "max": max(lat) if lat else float("nan"), "samples": len(lat)},
            "sent": sent, "received": sum(v["received"] for v in robots.values()), "lost": lost,
            "duplicates": sum(v["dups"] for v in robots.values()),
            "robots_losing": sorted((k for k, v in robots.items() if v["lost"]), key=lambda r: int(r[5:]))[:20],
            "lost_per_robot_max": max((v["lost"] for v in robots.values()), default=0),
            "send_rate_hz": sent / a.duration / n,
            "send_late_ms": {"p50": median(late), "p99": percentile(late, 99)},
            "planner_view_age_ms": {"p50": median(self.ages), "p99": percentile(self.ages, 99),
                                    "samples": len(self.ages)},
            "fleet_states_per_s": self.states_win / a.duration,
            "bytes_per_robot_s": {"up": sum(r["bytes_up"] for r in reps) / a.duration / n,
                                  "down": sum(r["bytes_down"] for r in reps) / a.duration / n},
            "down_msgs_per_robot_s": {role: sum(v["down"].get(role, 0) for v in robots.values()) / a.duration / n
                                      for role in [t for t, _ in DOWN]},
            "client_errors": sum(r["errors"] for r in reps),
            "client_skipped": sum(r.get("skipped", 0) for r in reps),
            # CPU per pose round trip (everything the run's messages cost, paths and states included): less
            # sensitive to a busy machine than latency
            "cpu_us_per_pose": {k: round(v * 1e4 * a.duration / sent, 1) if sent else None
                                for k, v in res["cpu_pct"].items()},
        })
        res["bytes_per_robot_s"]["total"] = res["bytes_per_robot_s"]["up"] + res["bytes_per_robot_s"]["down"]
        res["cpu_by_process"] = [{"pid": pid, "label": lab, "pct": round(p, 1)}
                                 for pid, (lab, p) in sorted(cpu.by_pid.items(), key=lambda kv: -kv[1][1])[:12]]
        hot = res["cpu_by_process"][0] if res["cpu_by_process"] else None
        res["hottest"] = hot
        clients = [x for x in res["cpu_by_process"] if x["label"] == "clients"]
        res["client_saturated"] = any(x["pct"] >= 90 for x in clients)
        if res["send_rate_hz"] < 0.95 * a.rate:
            res["notes"].append(f"the clients sent {res['send_rate_hz']:.2f} Hz per robot, not {a.rate:g} Hz "
                                f"(send lateness p99 {fmt_ms(res['send_late_ms']['p99'])} ms): "
                                "they did not get the CPU")

    def run(self) -> dict:
        a = self.args
        t0 = time.monotonic()
        workdir = Path(tempfile.mkdtemp(prefix=f"rce-fleetload-{self.n}-"))
        procs = None
        try:
            with engine(workdir, env={"RCE_PACKAGE_PATH": str(PACKAGES)}, robot_tasksets=a.robot_tasksets,
                        master_args=("--max-interfaces", str(interface_quota(self.n))),
                        robot_args=("--ws-impl", a.ws_impl)) as eng:
                self.res["setup"]["engine_s"] = round(time.monotonic() - t0, 2)
                self.workers = []
                procs = Procs(eng, self.workers).start()
                try:
                    from rce.plumbing.process import run_loop
                    run_loop(self.measure(eng, procs))
                except Exception as e:      # noqa: BLE001  (the run stops here, with the reason)
                    self.res["error"] = f"{type(e).__name__}: {e}"
                    self.res["engine_dead"] = eng.alive()
                    self.res["engine_events"] = engine_events(eng)
                    for ntag in ("global_planner", "pose_echo"):
                        try:
                            lg = eng.admin(f"api/containers/{USER}/{CTAG}/logs/{ntag}")
                            self.res.setdefault("node_logs", {})[ntag] = lg
                        except Exception as e2:   # noqa: BLE001
                            self.res.setdefault("node_logs", {})[ntag] = f"unavailable: {e2}"
                    st = getattr(getattr(self, "mgr", None), "latest", None) or {}
                    self.res["last_fleet_state"] = {
                        "robots": len(st.get("robots", [])), "errors": st.get("errors", [])[-5:],
                        "states": dict(sorted(__import__("collections").Counter(
                            x.get("state") for x in st.get("robots", [])).items(), key=str)),
                        "fleet_states_received": self.states}
                finally:
                    procs.stop()
                    self.res["peak_rss_mib"] = {k: round(v, 1) for k, v in procs.peak.items()}
        finally:
            self.stop_workers()
            if not a.keep:
                shutil.rmtree(workdir, ignore_errors=True)
            else:
                self.res["workdir"] = str(workdir)
        s = self.res["setup"]
        s["total_s"] = round(sum(s.get(k, 0) for k in ("engine_s", "fleet_container_s", "robots_s", "warmup_s",
                                                          "goals_s")), 2)
        self.res["run_s"] = round(time.monotonic() - t0, 2)
        return self.res


class FloorProcs:
    """The floor run's processes for :class:`CpuWindow`: the floor servers (``floor``), the client
    workers (``clients``) and this process (``orchestrator``)."""

    def __init__(self, servers: list, workers: list):
        self.servers, self.workers = servers, workers

    def snapshot(self) -> dict:
        import psutil
        out = {}
        pids = [(p.pid, "floor") for p in self.servers] + [(p.pid, "clients") for p in self.workers]  # echo: floor
        for pid, lab in pids + [(os.getpid(), "orchestrator")]:
            try:
                out[pid] = (lab, psutil.Process(pid))
            except psutil.Error:
                pass
        return out


class FloorRun(Run):
    """One N on the transport floor (:mod:`fleet_floor`): the same robots, setup, warm-up and window
    as :class:`Run`, served by ``--robot-tasksets`` floor processes that only echo each pose back
    over the robot's own websocket; no engine, no planner, no goals. With ``relay``, the relay
    floor: the floor processes send each pose through one echo process (the node's place) and
    back, the engine's topology with nothing else in it; the echo's CPU counts as the floor's."""

    def __init__(self, n: int, args, con, relay: bool = False):
        super().__init__(n, args, con)
        self.relay = relay

    def run(self) -> dict:
        a = self.args
        t0 = time.monotonic()
        ctx = mp.get_context("spawn")
        port = free_port()
        servers, ready = [], []
        self.workers = []
        relay_port = None
        try:
            if self.relay:
                r, w = ctx.Pipe(duplex=False)
                echo = ctx.Process(target=echo_main, args=(w,), daemon=True)
                echo.start()
                servers.append(echo)
                if not r.poll(60):
                    raise RuntimeError("the relay floor's echo process did not start within 60 s")
                relay_port = r.recv()
            for _ in range(max(1, a.robot_tasksets)):
                r, w = ctx.Pipe(duplex=False)
                proc = ctx.Process(target=floor_main, args=(port, self.side, w, relay_port), daemon=True)
                proc.start()
                servers.append(proc)
                ready.append(r)
            for r in ready:
                if not r.poll(60):
                    raise RuntimeError("a floor process did not start within 60 s")
                r.recv()
            self.res["setup"]["engine_s"] = round(time.monotonic() - t0, 2)
            from rce.plumbing.process import run_loop
            run_loop(self._measure_floor(f"http://127.0.0.1:{port}/", FloorProcs(servers, self.workers), servers))
        except Exception as e:      # noqa: BLE001  (the floor's result says why it has none)
            self.res["error"] = f"{type(e).__name__}: {e}"
        finally:
            self.stop_workers()
            for proc in servers:
                proc.terminate()
                proc.join(5)
        self.res["run_s"] = round(time.monotonic() - t0, 2)
        return self.res

    async def _measure_floor(self, url: str, procs: FloorProcs, servers: list) -> None:
        def check() -> None:
            dead = [p.pid for p in servers if not p.is_alive()]
            if dead:
                raise RuntimeError(f"floor processes {dead} exited")
        await self._setup_robots(url)
        await self._warmup(check, planner=False)
        cpu = await self._window(procs)
        reps = await self._replies()
        check()
        self._summarize(reps, cpu)


# == main =======================================================================================

def engine_over_floor(r: dict, floor: dict) -> float | None:
    """The engine's CPU per pose over the transport floor's at the same N: (master + robot task sets +
    the fleet container's processes) / the floor servers, each in CPU us per pose sent in its own
    window. None when either run has no such number (it failed, or sent nothing)."""
    e, f = r.get("cpu_us_per_pose") or {}, floor.get("cpu_us_per_pose") or {}
    parts = [e.get(k) for k in ("master", "robot", "container (all)")]
    if any(x is None for x in parts) or not f.get("floor"):
        return None
    return round(sum(parts) / f["floor"], 2)


def floor_line(f: dict) -> str:
    """One line of a floor run's result."""
    if f.get("error"):
        return f"failed: {f['error']}"
    L, sh = f["latency_ms"], f["cpu_share"]
    return (f"p50 {fmt_ms(L['p50'])} ms, p99 {fmt_ms(L['p99'])} ms, lost {f['lost']}/{f['sent']}, clients sent "
            f"{f['send_rate_hz']:.2f} Hz; cores: floor {round(f['cpu_pct'].get('floor', 0) / 100, 2)}, "
            f"clients {sh['load_clients']}, other {sh['other']}")


def verdict(r: dict, max_p99: float) -> str | None:
    """Why the run stops at this N (None: go on)."""
    if r.get("error"):
        return f"failed: {r['error']}"
    reasons = []
    p99 = r["latency_ms"]["p99"]
    if not (p99 <= max_p99):
        reasons.append(f"p99 {fmt_ms(p99)} ms > {max_p99:g} ms")
    if r["lost"]:
        reasons.append(f"{r['lost']} of {r['sent']} poses lost ({len(r['robots_losing'])}+ robots)")
    drops = {k: v for k, v in r.get("engine_drops", {}).items() if v}
    if drops:
        reasons.append(f"engine dropped {drops}")
    return "; ".join(reasons) or None


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_ws_impl_argument(p)
    p.add_argument("--robots", default=DEFAULT_ROBOTS, help=f"fleet sizes, in order (default {DEFAULT_ROBOTS})")
    p.add_argument("--duration", type=float, default=10.0, help="measured window per N, s (default 10)")
    p.add_argument("--rate", type=float, default=10.0, help="pose rate per robot, Hz (default 10)")
    p.add_argument("--converter", action="store_true", help="robot-side Converters (JSON) instead of Forwarders")
    p.add_argument("--container-cpu", type=float, default=None, metavar="CORES",
                   help="cores the fleet container asks for (containerData cpu: its quota and its CPU weight under "
                        "contention; default none: the weight of one process)")
    p.add_argument("--clients", type=int, default=DEFAULT_CLIENTS,
                   help=f"client worker processes (default {DEFAULT_CLIENTS})")
    p.add_argument("--robot-tasksets", type=int, default=DEFAULT_TASKSETS,
                   help=f"robot task sets (rce-robot processes) the engine runs; the master places each robot on "
                        f"the least loaded (default: one per core, at most {MAX_DEFAULT_TASKSETS}: {DEFAULT_TASKSETS})")
    p.add_argument("--setup-concurrency", type=int, default=16, help="robots setting up at once (default 16)")
    p.add_argument("--warmup", type=float, default=2.0, help="minimum warm-up, s (default 2)")
    p.add_argument("--warmup-timeout", type=float, default=60.0, help="warm-up limit, s (+0.05 s per robot)")
    p.add_argument("--drain", type=float, default=3.0, help="s after the window an echo may still come (default 3)")
    p.add_argument("--max-p99", type=float, default=100.0, help="stop when p99 passes this, ms (default 100)")
    p.add_argument("--no-stop", action="store_true",
                   help="run every N even after one failed the limits (the first failure is still reported)")
    p.add_argument("--no-floor", action="store_true",
                   help="do not measure the transport floor (bench/fleet_floor.py) before each N")
    p.add_argument("--relay-floor", action="store_true",
                   help="also measure the relay floor (each pose through a relay process and an echo process, "
                        "the engine's topology with nothing else in it) before each N")
    p.add_argument("--profile", type=float, default=0.0, metavar="S",
                   help="after each window, py-spy the two hottest processes for S s (default off)")
    p.add_argument("--profile-labels", default="", metavar="LABELS",
                   help="with --profile: py-spy the processes of these labels instead (comma-separated, "
                        "e.g. planner,robot; one after the other)")
    p.add_argument("--nice", type=int, default=None, metavar="N",
                   help="run the bench and all it starts at niceness N (e.g. -10 as root on a shared machine)")
    p.add_argument("--wait-quiet", type=float, default=0.0, metavar="S",
                   help="before each N, wait up to S s for other processes to use < 0.3 cores (shared machines)")
    p.add_argument("--keep", action="store_true", help="keep the engine's work directories (logs)")
    p.add_argument("--raw", type=Path, default=None, metavar="DIR",
                   help="also write every echo (robot, seq, stamp, latency) to DIR/latency_N.csv")
    p.add_argument("--json", type=Path, default=RESULTS / "fleet_load.json", help="JSON results")
    p.add_argument("--plot", type=Path, default=RESULTS / "fleet_load.png", help="PNG plot")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    con = console()
    try:
        sizes = [int(x) for x in args.robots.split(",") if x.strip()]
        if not sizes or min(sizes) < 1:
            raise ValueError
    except ValueError:
        con.print(f"[red]--robots: expected a comma-separated list of positive integers, got {args.robots!r}")
        return 2
    res = {"robots": sizes, "mode": "converter" if args.converter else "forwarder", "rate_hz": args.rate,
           "robot_tasksets": args.robot_tasksets, "container_cpu": args.container_cpu,
           "duration_s": args.duration, "drain_s": args.drain, "max_p99_ms": args.max_p99, "clients": args.clients,
           "cpu_count": os.cpu_count(), "runs": [], "stopped_at": None, "stop_reason": None,
           "definitions": {
               "latency": "robot wall clock at the echo's arrival minus header.stamp (robot wall clock just before "
                          "sending pose seq): robot -> SubscriberForwarder/Converter -> cTag_01 bus /RobotN/amcl_pose "
                          "(planner + echo node) -> benchecho -> /RobotN/amcl_pose_echo -> Publisher* -> robot",
               "lost": "poses sent in the window minus distinct seqs echoed back within drain_s after it",
               "planner_view_age": "at each /fleet/state received: now - send time of the newest pose of that "
                                   "robot the planner had processed (encoded in position.y)",
               "bytes_per_robot_s": "websocket frames (payload + header) counted by the clients in the window",
               "floor": "the same robots, setup and window against bench/fleet_floor.py, as many processes as "
                        "robot task sets, which echo each pose straight back over the robot's websocket (no "
                        "engine): what this machine's cores carry at N robots with one websocket hop each way",
               "cpu_pct": "user+system CPU of each process over the window, % of one core",
               "peak_rss_mib": "psutil RSS sampled every 0.5 s over the whole N (setup included), summed per label",
               "robot_memory": "rce-robot's RSS and USS (psutil memory_full_info, all robot task sets) before the "
                               "robots connect and at the end of the window; per robot: (at load - before) / N, KiB",
               "cpu_share": "cores over the window: the engine's own processes, the load clients (simulated "
                            "robots), the orchestrator, foreign load (machine busy minus ours), the machine",
               "robot_tasksets": "per rce-robot process: CPU % of one core over the window, robots connected",
               "cpu_us_per_pose": "CPU s of each label over the window / poses sent in it, in us (all the "
                                  "window's traffic: echoes, paths, clearances, fleet states)",
               "engine_over_floor": "the engine's CPU per pose (master + robot task sets + container (all), "
                                    "cpu_us_per_pose) over the floor servers' at the same N, measured in the same "
                                    "run: 1.0 would be an engine that costs no more than one websocket hop each "
                                    "way",
               "engine_over_relay_floor": "the same over the relay floor (--relay-floor: floor processes relaying "
                                          "each pose through an echo process and back, the engine's topology with "
                                          "nothing else in it); relay_floor_over_floor: the relay floor's CPU per "
                                          "pose over the floor's"}}
    set_nice(args.nice, log=con.print)
    res["nice"], res["ws_impl"] = args.nice, args.ws_impl
    for n in sizes:
        con.rule(f"N = {n} robots ({res['mode']})")
        wait_quiet(args.wait_quiet, log=con.print)
        floor = None if args.no_floor else FloorRun(n, args, con).run()
        if floor is not None:
            con.print(f"N={n}: transport floor: {floor_line(floor)}")
        relay = FloorRun(n, args, con, relay=True).run() if args.relay_floor else None
        if relay is not None:
            con.print(f"N={n}: relay floor: {floor_line(relay)}")
        r = Run(n, args, con).run()
        if floor is not None:
            r["floor"] = floor
            r["engine_over_floor"] = engine_over_floor(r, floor)
        if relay is not None:
            r["relay_floor"] = relay
            r["engine_over_relay_floor"] = engine_over_floor(r, relay)
            if floor is not None and relay.get("cpu_us_per_pose", {}).get("floor") and \
                    floor.get("cpu_us_per_pose", {}).get("floor"):
                r["relay_floor_over_floor"] = round(relay["cpu_us_per_pose"]["floor"]
                                                    / floor["cpu_us_per_pose"]["floor"], 2)
            con.print(f"N={n}: relay floor {relay.get('cpu_us_per_pose', {}).get('floor')} us per pose "
                      f"({r.get('relay_floor_over_floor')}x the floor); engine_over_relay_floor "
                      f"{r['engine_over_relay_floor']}")
        res["runs"].append(r)
        why = verdict(r, args.max_p99)
        if r.get("engine_over_floor") is not None:
            us = r["cpu_us_per_pose"]
            con.print(f"N={n}: CPU per pose: engine {us['master'] + us['robot'] + us['container (all)']:.0f} us "
                      f"(rce-robot {us['robot']:.0f}, planner {us.get('planner', 0):.0f}, echo node "
                      f"{us.get('echo node', 0):.0f}, environment {us.get('environment', 0):.0f}), floor "
                      f"{floor['cpu_us_per_pose']['floor']:.0f} us: engine_over_floor {r['engine_over_floor']:.2f}")
        if r.get("latency_ms"):
            con.print(f"N={n}: p50 {fmt_ms(r['latency_ms']['p50'])} ms, p99 {fmt_ms(r['latency_ms']['p99'])} ms, "
                      f"lost {r['lost']}/{r['sent']}, CPU {r['cpu_pct']}")
        r["verdict"] = why
        if why and r.get("error"):
            res["stopped_at"], res["stop_reason"] = n, why
            con.print(f"[bold red]stopping at N={n}: {why}")
            break
        if why and res["stopped_at"] is None:
            res["stopped_at"], res["stop_reason"] = n, why
            if not args.no_stop:
                con.print(f"[bold red]stopping at N={n}: {why}")
                break
            con.print(f"[bold red]N={n} fails ({why}); going on (--no-stop)")
    if res["stopped_at"] is None:
        res["stop_reason"] = f"every N passed (p99 <= {args.max_p99:g} ms, nothing lost)"
    write_json(args.json, res)
    print_table(con, res)
    plot(res, args.plot)
    con.print(f"results: {args.json}  plot: {args.plot}")
    return 0


def print_table(con, res: dict) -> None:
    from rich.table import Table
    f0 = lambda x: "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.0f}"  # noqa: E731
    t = Table(title=f"fleet load: {res['mode']}s, poses at {res['rate_hz']:g} Hz per robot, "
                    f"{res['duration_s']:g} s window per N (latency = pose -> fleet container echo -> robot)")
    for c in ("N", "p50 ms", "p99 ms", "max ms", "lost", "engine drops", "planner view p50/p99 ms",
              "B/robot/s up/down", "setup s (robots)", "goal->path ms", "floor p50/p99 ms",
              "engine/floor CPU per pose"):
        t.add_column(c, justify="right")
    for r in res["runs"]:
        fl = (r.get("floor") or {}).get("latency_ms")
        floor = f"{fmt_ms(fl['p50'])} / {fmt_ms(fl['p99'])}" if fl else "-"
        if not r.get("latency_ms"):
            t.add_row(str(r["robots"]), *["-"] * 7, f"{r['setup'].get('robots_s', '-')}",
                      "-", floor, "-", style="red")
            continue
        L, s = r["latency_ms"], r["setup"]
        drops = sum(v for v in r.get("engine_drops", {}).values())
        pv = r["planner_view_age_ms"]
        b = r["bytes_per_robot_s"]
        t.add_row(str(r["robots"]), fmt_ms(L["p50"]), fmt_ms(L["p99"]), fmt_ms(L["max"]),
                  f"{r['lost']}/{r['sent']}", str(drops), f"{fmt_ms(pv['p50'])} / {fmt_ms(pv['p99'])}",
                  f"{f0(b['up'])} / {f0(b['down'])}",
                  f"{s.get('total_s', '-')} ({s.get('robots_s', '-')})", fmt_ms(r["goal_to_path_ms"]["p50"]), floor,
                  "-" if r.get("engine_over_floor") is None else f"{r['engine_over_floor']:.2f}",
                  style=None if verdict(r, res["max_p99_ms"]) is None else "red")
    con.print(t)
    labels = ("master", "robot", "container host", "environment", "planner", "echo node", "clients", "orchestrator")
    t2 = Table(title="CPU % of one core over the window (peak RSS MiB over the run); "
                     f"the machine has {res['cpu_count']} cores")
    t2.add_column("N", justify="right")
    for c in labels + ("container (all)", "machine busy", "other load"):
        t2.add_column(c, justify="right")
    for r in res["runs"]:
        cpu, rss = r.get("cpu_pct", {}), r.get("peak_rss_mib", {})
        cell = lambda k, cpu=cpu, rss=rss: f"{f0(cpu.get(k))} ({f0(rss.get(k))})"  # noqa: E731
        other = r.get("machine_load", {}).get("other_cores")
        t2.add_row(str(r["robots"]), *[cell(k) for k in labels], cell("container (all)"), f0(cpu.get("machine")),
                   "-" if other is None else f"{other:.2f} cores")
    con.print(t2)
    for r in res["runs"]:
        m, sh = r.get("robot_memory"), r.get("cpu_share")
        if m:
            ts = r.get("robot_tasksets") or []
            con.print(f"N={r['robots']}: rce-robot RSS {m['before']['rss_mib']:.0f} MiB before the robots, "
                      f"{m['at_load']['rss_mib']:.0f} MiB at load: {m['rss_per_robot_kib']:.0f} KiB RSS "
                      f"({m['uss_per_robot_kib']:.0f} KiB USS) per robot; task sets: robots "
                      f"{[t['robots'] for t in ts]}, CPU {[t['cpu_pct'] for t in ts]} %")
        if sh:
            con.print(f"N={r['robots']}: cores: engine {sh['engine']}, load clients {sh['load_clients']}, "
                      f"orchestrator {sh['orchestrator']}, other {sh['other']}, machine {sh['machine']}")
        for n in r.get("notes", []):
            con.print(f"[yellow]N={r['robots']}: {n}")
        if r.get("client_saturated"):
            con.print(f"[yellow]N={r['robots']}: a client worker used >= 90 % of a core: "
                      "the clients may be a bottleneck")
        for lab, p in (r.get("profile") or {}).items():
            if p.get("own"):
                con.print(f"N={r['robots']} py-spy {lab} ({p['cpu_pct']} % CPU; {p['wait_pct']} % of samples "
                          f"waiting in the event loop), own time: " + ", ".join(f"{k} {v}%" for k, v in p["own"][:8]))
    stopped = f"stopped at N={res['stopped_at']}: " if res["stopped_at"] else ""
    con.print(f"[bold]{stopped}{res['stop_reason']}")


def plot(res: dict, path: Path) -> None:
    plt = pyplot()
    runs = [r for r in res["runs"] if r.get("latency_ms") and math.isfinite(r["latency_ms"]["p50"])]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 5))
    if runs:
        xs = [r["robots"] for r in runs]
        ax1.plot(xs, [r["latency_ms"]["p50"] for r in runs], "o-", label="p50")
        ax1.plot(xs, [r["latency_ms"]["p99"] for r in runs], "s-", label="p99")
        ax1.plot(xs, [r["planner_view_age_ms"]["p99"] for r in runs], "^:", label="planner view age p99", alpha=0.6)
        fl = [(r["robots"], r["floor"]["latency_ms"]["p99"]) for r in runs if (r.get("floor") or {}).get("latency_ms")]
        if fl:
            ax1.plot([x for x, _ in fl], [y for _, y in fl], "x--", color="grey",
                     label="transport floor p99 (fleet_floor.py)")
        ax1.axhline(res["max_p99_ms"], color="red", ls="--", lw=0.8, label=f"{res['max_p99_ms']:g} ms limit")
        for lab, style in (("master", "o-"), ("robot", "s-"), ("container (all)", "^-"), ("environment", "v--"),
                           ("planner", "x--"), ("echo node", "+--"), ("clients", "d:"), ("machine", "k-")):
            ys = [r["cpu_pct"].get(lab, float("nan")) for r in runs]
            ax2.plot(xs, ys, style, label=lab if lab != "machine" else "whole machine", markersize=4)
        ax2.axhline(100 * (res.get("cpu_count") or 1), color="red", ls="--", lw=0.8, label="all cores")
    for ax in (ax1, ax2):
        ax.set_xscale("log")
        ax.set_xlabel("robots (N)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    if runs:                      # a log axis needs a positive value
        ax1.set_yscale("log")
    ax1.set_ylabel("ms")
    ax1.set_title(f"pose -> fleet container echo -> robot ({res['mode']})")
    ax2.set_ylabel("CPU % of one core")
    ax2.set_title("CPU per task set over the window")
    if res.get("stopped_at"):
        fig.suptitle(f"stopped at N={res['stopped_at']}: {res['stop_reason']}"[:140], fontsize=9)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
