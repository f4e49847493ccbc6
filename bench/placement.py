"""Where a node with a deadline serves best while the robot's link and battery change: the placer
(docs/placement.md) against the two static placements, in network namespaces this bench makes and
removes (root; also after a failure: rce/tools/netlab.py).

Topology: the cloud (the real engine: rce-master, a cloud container host ``cloud-dc1`` and a shared
robot endpoint) in the root namespace; the robot in namespace R, joined to it by one veth pair: the
robot's own process (an ``rce_client`` connection) and its own computer, with a ``robot:`` container
host (``rce-container --zone robot:ROBOT --user USER``) whose CPU is capped at :data:`ROBOT_CPU`
cores by a cgroup the bench makes for it (v2 ``cpu.max``, or v1 ``cpu.cfs_quota_us`` where the cpu
controller is v1) and a robot endpoint of its own (``rce-robot --zone robot:ROBOT --user USER``,
which the master hands the robot's logins to): a container on the robot's computer is reached
without crossing the link, and the link the placer weighs is that endpoint's uplink.
``--endpoint cloud`` leaves the robot to the cloud's endpoint instead (the link is then measured on
the robot's websocket, and a container on the robot's computer is reached through the cloud: its
messages cross the link twice).

The link: each end shapes what it sends with HTB (one class, a ``pfifo`` of :data:`QUEUE` packets;
with ``--dscp`` an EF class for the engine's control links served first beside it), and a delay line
in the middle (``rce.tools.delayline``: this kernel has no ``netem``) holds every frame a one-way
delay each way: :data:`GOOD_RATE` and :data:`GOOD_DELAY_MS` ms while good, :data:`BAD_RATE` and
:data:`BAD_DELAY_MS` ms while bad (a 100 ms round trip: the cloud cannot answer within the deadline
however fast it computes). The kernel's TCP_INFO shows the placer the round trip and the rate (module
``rce_robot.link_report``).

The node (``bench/packages/benchcostmap/costmap.py``): a costmap from each ``sensor_msgs/LaserScan``
of :data:`SCAN_POINTS` beams (a 270-degree scanner at 0.25 degrees, ~4.4 kB, 10 Hz: 0.35 Mbit/s,
which the bad link carries: the cloud's results keep coming there, late), answered
with a ``geometry_msgs/PointStamped`` carrying the scan's header; deadline :data:`DEADLINE_MS` ms
from the scan's stamp to its result back at the robot. Its work grows with the scan's finite returns:
most scans are sparse (:data:`LIGHT_FRACTION` of the beams return), one in :data:`HEAVY_EVERY` is
cluttered (every beam returns, ~10x the work), so that the robot's capped CPU meets the deadline on
the sparse scans and misses it on the cluttered ones.

Script (``--phase-s`` s per phase, default 30): good link (the node belongs in the cloud); the link
falls to :data:`BAD_RATE` and :data:`BAD_DELAY_MS` ms (it belongs on the robot); the link returns;
the robot's battery falls to :data:`BATTERY_LOW_PCT` % (``POST /api/robots/{user}/{robot}/battery``:
saving the robot's energy wins). The same script three ways: ``cloud`` (containerData ``placement: cloud``), ``robot``
(``placement: robot``), ``placer`` (``placement: auto`` with ``deadline_ms``, ``robot``,
``consumes`` and ``spare``: a made copy waits on the host it would move to next, so that a move
there only switches; ``--no-spare``: each move makes its new copy first).

Per system it reports deadline misses per phase (a result later than the deadline after its scan's
stamp, or never; a scan the robot could not send within one period counts as missed), results lost
and duplicated (by the scans' header.seq), the robot's modelled energy (the placer's
:class:`~rce_master.placement.placer.EnergyModel`: W per core x the container's CPU seconds while on the
robot's computer, plus J per byte x the bytes across the link, both ways, from the veth's counters),
each move (its time, hosts, its gap: the longest time without a result while the results pass from
the old copy to the new one, :func:`handover_gap`; the longest around it, the copies' own gaps
included; the placer's reason) and the placer's word as ``GET /api/placement`` gave it, sampled
every :data:`POLL` s. JSON in ``bench/results/placement.json`` and a PNG timeline beside it::

    sudo .venv/bin/python bench/placement.py [--phase-s 30] [--systems cloud,robot,placer]
                                             [--endpoint robot|cloud] [--bad-rate 1mbit] [--bad-delay-ms 50]
                                             [--scan-points 1081] [--dscp] [--ordered-moves] [--out FILE]

``--scan-points 10000 --bad-delay-ms 0`` is the link starved by rate instead (a 40 kB scan, 3.2 Mbit/s
into 1 Mbit/s, no delay): there the cloud's results stop rather than come late.
"""
from __future__ import annotations

import argparse
import asyncio
import contextlib
import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parent
sys.path.insert(0, str(BENCH))

USER, PASSWORD = "testUser", "testUser"
ROBOT = "rover"                 # the robot's ID (its computer's zone: robot:rover)
CTAG = "costmap"
RATE_HZ = 10.0                  # scans per second
DEADLINE_MS = 100.0             # from a scan's stamp to its result back at the robot
CALIBRATION_SPREAD = (0.6, 0.8, 1.0, 1.2, 1.4)    # sample counts the calibration times, as shares of its guess
SCAN_POINTS = 1_081             # beams per scan (270 degrees at 0.25 degrees): 4.3 kB of float32 ranges
LIGHT_FRACTION = 0.1            # share of a sparse scan's beams that return
HEAVY_EVERY = 10                # one scan in this many is cluttered (every beam returns)
CELLS, PASSES = 160, 4          # the node's grid (cells a side) and inflation passes
NODE_ARGS = f"--cells {CELLS} --passes {PASSES} --queue 100"     # and --samples, from calibrate()
ROBOT_HEAVY_MS = 150.0          # ms a cluttered scan takes on the robot's computer (calibrate_on_robot()): it misses
                                # there, and the sparse scan behind it (~20 ms there) still meets its deadline
ROBOT_CPU = 0.3                 # cores of the robot's computer (cgroup CPU quota)
CPU_PERIOD_US = 10_000          # the cap's period: short beside the scans' 100 ms, so that the robot's computer is
                                # slow and not bursty (a 100 ms period locks in phase with the 10 Hz scans: a
                                # cluttered scan met or missed its deadline by where in the period it came)
GOOD_RATE, BAD_RATE = "100mbit", "1mbit"
GOOD_DELAY_MS, BAD_DELAY_MS = 5.0, 50.0     # one way, each way: a 10 ms round trip to a nearby cloud, then 100 ms
QUEUE = 40                      # packets in each end's FIFO (bounded: ~0.5 s at 1 Mbit/s)
BATTERY_START_PCT, BATTERY_LOW_PCT = 80.0, 12.0
PHASES = ("good link", "link 1 Mbit/s", "link back", "battery low")
POLL = 0.5                      # s between looks at the placer's word, the container's host and CPU
CGROUP_EMPTY_WAIT = 10.0        # s for the robot computer's processes to leave its cgroup after it stopped
READY_WAIT = 120.0              # s for the robot's container to answer its first scan
SYSTEMS = {"cloud": "cloud", "robot": "robot", "placer": "auto"}


# -- the robot: runs in namespace R --------------------------------------------------------------
def scan_bytes(points: int, fraction: float) -> bytearray:
    """A serialized ``sensor_msgs/LaserScan`` of ``points`` beams of which ``fraction`` return
    (finite ranges 0.5 - 4.5 m, the rest inf); header.seq at bytes 0-3, header.stamp at 4-11."""
    import numpy as np
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS1_NOETIC)
    t = ts.types
    ranges = scan_ranges(points, fraction)
    scan = t["sensor_msgs/msg/LaserScan"](
        header=t["std_msgs/msg/Header"](seq=0, stamp=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0),
                                        frame_id="laser"),
        angle_min=-np.pi, angle_max=np.pi, angle_increment=2 * np.pi / points, time_increment=0.0, scan_time=0.1,
        range_min=0.1, range_max=30.0, ranges=ranges, intensities=np.zeros(0, np.float32))
    return bytearray(ts.serialize_ros1(scan, "sensor_msgs/msg/LaserScan"))


def scan_ranges(points: int, fraction: float):
    """A scan's ``points`` ranges (m, float32) of which ``fraction`` return (0.5 - 4.5 m), the rest inf."""
    import numpy as np
    rng = np.random.default_rng(7)
    ranges = np.full(points, np.inf, np.float32)
    hit = rng.random(points) < fraction
    ranges[hit] = rng.uniform(0.5, 4.5, int(hit.sum())).astype(np.float32)
    return ranges


def costmap_ms(points: int, fraction: float, samples: int, clock=time.process_time) -> float:
    """ms by ``clock`` (median of 7) the node's own ``costmap`` takes here on a scan of ``points``
    beams of which ``fraction`` return, each cleared at ``samples`` points."""
    import numpy as np
    sys.path.insert(0, str(BENCH / "packages" / "benchcostmap"))
    from costmap import costmap
    ranges, ts = scan_ranges(points, fraction), []
    for _ in range(7):
        t0 = clock()
        costmap(ranges, -np.pi, 2 * np.pi / points, CELLS, PASSES, samples)
        ts.append((clock() - t0) * 1e3)
    return sorted(ts)[3]


def calibrate(target_ms: float, points: int = SCAN_POINTS) -> dict:
    """The node's ``--samples`` for which a cluttered scan of ``points`` beams takes ``target_ms`` ms
    of wall time where this process runs (inside the robot computer's cgroup:
    :func:`calibrate_on_robot`). The work is linear in the samples, but under a CPU cap one timing
    (:func:`costmap_ms`, itself a median of 7) may be off by half: two sample counts give a first
    guess, then a least-squares line through timings at :data:`CALIBRATION_SPREAD` times that guess,
    each taken twice, gives the answer. Returns ``{samples, node_args, heavy_ms, light_ms}`` (wall
    ms at those samples, ``heavy_ms`` by the line)."""
    import numpy as np
    clock = time.perf_counter
    first = max(20, 1_000_000 // points)              # ~the same work a scan whatever its beams
    lo, hi = costmap_ms(points, 1.0, first, clock), costmap_ms(points, 1.0, 3 * first, clock)
    slope = (hi - lo) / (2 * first)
    guess = int(round(3 * first + (target_ms - hi) / slope)) if slope > 0 else 3 * first
    guess = max(20, min(100 * first, guess))
    xs = [max(20, int(guess * f)) for f in CALIBRATION_SPREAD for _ in range(2)]
    ys = [costmap_ms(points, 1.0, x, clock) for x in xs]
    a, b = np.polyfit(xs, ys, 1)
    samples = max(20, min(100 * first, int(round((target_ms - b) / a)) if a > 0 else guess))
    return {"samples": samples, "node_args": f"{NODE_ARGS} --samples {samples}",
            "heavy_ms": round(float(a * samples + b), 2),
            "light_ms": round(costmap_ms(points, LIGHT_FRACTION, samples, clock), 2)}


def calibrate_on_robot(cap: CpuCap, target_ms: float = ROBOT_HEAVY_MS, points: int = SCAN_POINTS) -> dict:
    """The node's work set on the robot's computer itself: :func:`calibrate` run inside ``cap`` by the
    wall clock, so that a cluttered scan takes ``target_ms`` there (its cap's throttling and
    whatever else loads this machine at the time included), then timed here, uncapped, in CPU time
    for the record. Returns ``{samples, node_args, robot_heavy_ms, robot_light_ms, heavy_ms,
    light_ms}``. Raises RuntimeError when the calibration in the cgroup fails."""
    out = subprocess.run(cap.wrap([sys.executable, str(Path(__file__).resolve()), "--role", "calibrate",
                                   "--heavy-ms", str(target_ms), "--scan-points", str(points)]),
                       capture_output=True, text=True, timeout=300)
    if out.returncode != 0:
        raise RuntimeError(f"placement: calibration on the robot's computer failed: {out.stderr.strip()[-500:]}")
    robot = json.loads(out.stdout.strip().splitlines()[-1])
    return {"samples": robot["samples"], "node_args": robot["node_args"], "robot_heavy_ms": robot["heavy_ms"],
            "robot_light_ms": robot["light_ms"], "heavy_ms": round(costmap_ms(points, 1.0, robot["samples"]), 2),
            "light_ms": round(costmap_ms(points, LIGHT_FRACTION, robot["samples"]), 2)}


def drain_s(phase_s: float) -> float:
    """s the robot waits for the last results after its last scan."""
    return min(5.0, max(2.0, phase_s))


def stamped(template: bytearray, seq: int, wall: float) -> bytes:
    """``template`` with header.seq ``seq`` and header.stamp ``wall`` (s)."""
    template[0:12] = seq.to_bytes(4, "little") + int(wall).to_bytes(4, "little") + \
        int((wall % 1) * 1e9).to_bytes(4, "little")
    return bytes(template)


async def robot_main(a: argparse.Namespace) -> dict:
    """Set the container up, send the scans for the whole script, collect the results. Prints
    ``ready T0`` (monotonic s) once the first result is back; returns the record."""
    from rce_client.connection import Connection
    conn = await Connection.login_connect(a.master, USER, PASSWORD, ROBOT, allow_reconnect=True)
    data = {"placement": SYSTEMS[a.system], "deadline_ms": DEADLINE_MS, "robot": ROBOT, "consumes": ["scan"],
            **({"ordered_moves": True} if a.ordered_moves else {}),
            **({"spare": True} if a.spare and SYSTEMS[a.system] == "auto" else {})}
    await conn.create_container(CTAG, **data)
    await conn.add_node(CTAG, "costmap", "benchcostmap", "costmap.py", args=a.node_args)
    for tag, itype, cls, addr in (("scan", "PublisherInterface", "sensor_msgs/LaserScan", "/scan"),
                                  ("done", "SubscriberInterface", "geometry_msgs/PointStamped", "/costmap_done")):
        await conn.add_interface(CTAG, tag, itype, cls, addr)
    await conn.add_interface(ROBOT, "scan", "SubscriberForwarder", "sensor_msgs/LaserScan")
    await conn.add_interface(ROBOT, "done", "PublisherConverter", "geometry_msgs/PointStamped")
    for tag in ("scan", "done"):
        await conn.connect_interfaces(f"{CTAG}/{tag}", f"{ROBOT}/{tag}")
    await conn.wait_interfaces_up(["scan", "done"], timeout=READY_WAIT)
    light, heavy = scan_bytes(a.scan_points, LIGHT_FRACTION), scan_bytes(a.scan_points, 1.0)
    sent: dict[int, float] = {}                       # seq -> monotonic s at its stamp
    skipped: list[float] = []                         # ticks whose scan could not be sent in time
    got: list[tuple[int, float, float, str]] = []     # (seq, arrival monotonic s, node CPU ms, the node copy's ID)
    first = asyncio.Event()
    failed: list[int] = []                            # scans whose send the connection refused
    node_dropped = [0]                                # scans the node's queue dropped (its copies' largest count)

    def on_result(m: dict) -> None:
        tags = dict(kv.partition("=")[::2] for kv in str(m["header"].get("frame_id", "")).split(";"))
        got.append((int(m["header"]["seq"]), time.monotonic(), float(m["point"]["z"]), tags.get("copy", "")))
        node_dropped[0] = max(node_dropped[0], int(tags.get("dropped") or 0))
        first.set()
    conn.subscriber("done", "geometry_msgs/PointStamped", on_result)
    errors: list[str] = []
    conn.on_error(lambda *err: errors.append(f"{time.monotonic():.3f} {err}"))
    pub = conn.publisher("scan", "sensor_msgs/LaserScan")
    end = [float("inf")]
    pending: list[asyncio.Task] = []

    async def scans() -> None:
        seq, t_next = 0, time.monotonic()
        while t_next < end[0]:
            if pending and not pending[0].done():
                skipped.append(t_next)                # the link has not taken the last one yet
            else:
                if pending and pending.pop().exception() is not None:
                    failed.append(seq)                # refused (e.g. the link to the cloud was lost meanwhile)
                seq += 1
                sent[seq] = time.monotonic()
                frame = stamped(heavy if seq % HEAVY_EVERY == 0 else light, seq, time.time())
                pending.append(asyncio.ensure_future(pub.publish(frame)))
            t_next += 1 / RATE_HZ
            await asyncio.sleep(max(0.0, t_next - time.monotonic()))      # the sensor's period

    sender = asyncio.ensure_future(scans())
    await asyncio.wait_for(first.wait(), READY_WAIT)
    t0 = time.monotonic()
    print(f"ready {t0}", flush=True)
    end[0] = t0 + 4 * a.phase_s
    await sender
    await asyncio.sleep(drain_s(a.phase_s))                        # the last results on their way
    with contextlib.suppress(Exception):
        await conn.close()
    return {"t0": t0, "sent": [[s, t] for s, t in sent.items() if t >= t0], "skipped": [t for t in skipped if t >= t0],
            "got": [list(g) for g in got], "node_dropped": node_dropped[0],
            "send_failed": failed, "errors": errors[-20:]}


# -- the cloud side: namespaces, shaping, cgroup, the engine -------------------------------------
def shape(lab, link, rate: str, dscp: bool = False) -> None:
    """Both ends of ``link`` send at most ``rate`` with HTB, through ``QUEUE``-packet FIFOs: one class
    (marks ignored), or with ``dscp`` an EF class (``tos`` 0xb8: the engine's control links) served
    first, 30 % of ``rate`` assured, beside the rest, each borrowing up to ``rate``. Made on the first
    call; later calls change the classes' rates in place (``tc class change``), so that what waits in
    the queues stays there, as it does in a radio whose rate falls: taking the qdisc down and up again
    would drop it all, control packets too, and their retransmission timeouts (0.2 s and more) would
    be the bench's, not the link's."""
    classes = ((10, 0.7, 1), (20, 0.3, 0)) if dscp else ((10, 1.0, 0),)
    bits = _bits(rate)
    for ns, dev in ((link.a, link.a_dev), (link.b, link.b_dev)):
        tc = [*(("ip", "netns", "exec", ns) if ns else ()), "tc"]
        verb = "change" if (ns, dev) in _SHAPED else "add"
        cmds = [("class", verb, "dev", dev, "parent", "1:", "classid", "1:1", "htb", "rate", rate, "ceil", rate,
                 "burst", "15k")]
        for cid, share, prio in classes:
            cmds.append(("class", verb, "dev", dev, "parent", "1:1", "classid", f"1:{cid}", "htb", "rate",
                         f"{int(bits * share)}bit", "ceil", rate, "burst", "15k", "prio", str(prio)))
        if verb == "add":
            # one packet a segment: HTB lets a whole segmentation-offload packet (up to 64 kB) through at
            # once and pays it back after, which no radio does (a 48 kB probe crossed "1 Mbit/s" at once)
            subprocess.run([*tc[:-1], "ip", "link", "set", "dev", dev, "gso_max_segs", "1"], check=True,
                           capture_output=True)
            subprocess.run([*tc, "qdisc", "del", "dev", dev, "root"], capture_output=True)
            cmds.insert(0, ("qdisc", "add", "dev", dev, "root", "handle", "1:", "htb", "default", "10"))
            cmds += [("qdisc", "add", "dev", dev, "parent", f"1:{cid}", "pfifo", "limit", str(QUEUE))
                     for cid, _, _ in classes]
            if dscp:
                cmds.append(("filter", "add", "dev", dev, "parent", "1:", "protocol", "ip", "prio", "1", "u32",
                             "match", "ip", "tos", "0xb8", "0xfc", "flowid", "1:20"))
        for args in cmds:
            subprocess.run([*tc, *args], check=True, capture_output=True, text=True)
        _SHAPED.add((ns, dev))


_SHAPED: set[tuple[str | None, str]] = set()    # link ends shaped so far (a system's run makes its link anew)


def _bits(rate: str) -> int:
    """Bits/s of a tc rate such as ``1mbit``."""
    from rce.tools.netlab import _tc_bits
    return _tc_bits(rate)


def link_bytes(dev: str) -> int:
    """Bytes the root end ``dev`` of the link sent and received."""
    base = Path("/sys/class/net") / dev / "statistics"
    return int((base / "tx_bytes").read_text()) + int((base / "rx_bytes").read_text())


class CpuCap:
    """A cgroup capping what runs in it at ``cores`` (v2 ``cpu.max``, else v1 ``cpu.cfs_quota_us``);
    :meth:`wrap` runs a command in it; removed by :meth:`close`."""

    def __init__(self, name: str, cores: float):
        v2 = Path("/sys/fs/cgroup")
        if "cpu" in ((v2 / "cgroup.controllers").read_text().split() if (v2 / "cgroup.controllers").exists() else []):
            subtree = (v2 / "cgroup.subtree_control").read_text().split()
            if "cpu" not in subtree:
                (v2 / "cgroup.subtree_control").write_text("+cpu")
            self.dir = v2 / name
            self.dir.mkdir(exist_ok=True)
            (self.dir / "cpu.max").write_text(f"{int(cores * CPU_PERIOD_US)} {CPU_PERIOD_US}")
            self.how = f"cgroup v2 {self.dir}/cpu.max {int(cores * CPU_PERIOD_US)} {CPU_PERIOD_US}"
        else:
            self.dir = Path("/sys/fs/cgroup/cpu") / name
            self.dir.mkdir(exist_ok=True)
            (self.dir / "cpu.cfs_period_us").write_text(str(CPU_PERIOD_US))
            (self.dir / "cpu.cfs_quota_us").write_text(str(int(cores * CPU_PERIOD_US)))
            self.how = f"cgroup v1 {self.dir}/cpu.cfs_quota_us {int(cores * CPU_PERIOD_US)} per {CPU_PERIOD_US}"

    def wrap(self, argv: list[str]) -> list[str]:
        """``argv`` started inside this cgroup (its shell joins it, then execs it)."""
        return ["sh", "-c", f'echo $$ > {self.dir}/cgroup.procs && exec "$@"', "sh", *argv]

    def close(self) -> None:
        """Remove the cgroup and whatever cgroups a host left under it, once the processes the bench
        started in it have exited (at most :data:`CGROUP_EMPTY_WAIT` s)."""
        if not self.dir.exists():
            return
        end = time.monotonic() + CGROUP_EMPTY_WAIT
        while time.monotonic() < end and any((d / "cgroup.procs").read_text().strip()
                                             for d in [self.dir, *self.dir.rglob("*")] if d.is_dir()):
            time.sleep(0.1)              # the stopped host's last processes exiting
        for d in sorted((p for p in self.dir.rglob("*") if p.is_dir()), key=lambda p: len(p.parts), reverse=True):
            try:
                d.rmdir()
            except OSError:
                pass
        try:
            self.dir.rmdir()
        except OSError as e:
            print(f"placement: cgroup {self.dir} not removed: {e}", file=sys.stderr)


def start(lab, link, work: Path, cap: CpuCap, endpoint: str):
    """The engine for one system: master, cloud host and a shared robot endpoint in the root namespace,
    the robot's computer in R under ``cap`` (with the robot's own endpoint when ``endpoint`` is
    ``"robot"``). Returns it (stop it with ``stop()``)."""
    from rce.tools.launch import command, start_engine
    e = start_engine(work, robot_tasksets=1, container_hosts=1,
                     master_args=("--bind", "0.0.0.0"),
                     robot_args=("--bind", "0.0.0.0", "--advertise-host", link.a_ip),
                     container_args=("--bind", "0.0.0.0", "--advertise-host", link.a_ip, "--name", "cloud-dc1"),
                     env={"RCE_PACKAGE_PATH": str(BENCH / "packages")})
    ctl = f"{link.a_ip}:{e.control_port}"
    try:
        if endpoint == "robot":
            ready = work / "robot-endpoint.ready"
            _, info = e.spawn("robot-endpoint", lab.wrap("r", [
                *command("rce-robot"), ctl, "--zone", f"robot:{ROBOT}", "--user", USER, "--port", "0",
                "--data-port", "0", "--metrics-port", "0", "--rosbridge-port", "0", "--bind", "0.0.0.0",
                "--advertise-host", link.b_ip, "--ready-file", str(ready)]), ready)
            e.robot_ready.insert(0, dict(info, host=link.b_ip))   # the robot's; /metrics from the root namespace
        ready = work / "robot-computer.ready"
        # nsenter, not `ip netns exec`: that mounts a sysfs of its own over /sys, without the cgroup
        # mounts, and the robot's computer could not read its CPU cap (it would register every core)
        e.spawn("robot-computer", cap.wrap([
            "nsenter", f"--net=/run/netns/{lab.full('r')}", *command("rce-container"), ctl, "--zone",
            f"robot:{ROBOT}", "--user", USER, "--name", "robot-computer", "--bind", link.b_ip, "--advertise-host",
            link.b_ip, "--runtime-dir", str(work / "rt-robot"), "--ready-file", str(ready)]), ready)
    except Exception:
        e.stop()
        raise
    return e


async def run_system(system: str, lab, link, work: Path, cap: CpuCap, a: argparse.Namespace) -> dict:
    """One system through the script: the robot's record, the bench's samples, the moves."""
    shape(lab, link, GOOD_RATE, a.dscp)
    lab.set_delay(link, GOOD_DELAY_MS)
    e = start(lab, link, work, cap, a.endpoint)
    try:
        return await drive(system, lab, link, e, work, a)
    finally:
        e.stop()


async def drive(system: str, lab, link, e, work: Path, a: argparse.Namespace) -> dict:
    master = f"http://{link.a_ip}:{e.http_port}/"

    def admin(path: str, body: dict | None = None):
        return asyncio.to_thread(e.admin, path, body)
    await admin(f"/api/robots/{USER}/{ROBOT}/battery", {"percent": BATTERY_START_PCT})
    hosts = [{k: t.get(k) for k in ("name", "zone", "capacity")} for t in await admin("/api/tasksets")
             if t["kind"] == "container"]
    log = open(work / "robot.log", "wb")
    proc = await asyncio.create_subprocess_exec(
        *lab.wrap("r", [sys.executable, __file__, "--role", "robot", "--system", system, "--master", master,
                        "--phase-s", str(a.phase_s), "--node-args", a.node_args, "--scan-points", str(a.scan_points),
                        *(["--ordered-moves"] if a.ordered_moves else []), *([] if a.spare else ["--no-spare"])]),
        stdout=asyncio.subprocess.PIPE, stderr=log, limit=2**26)
    scripted: asyncio.Future | None = None
    try:
        line = b""
        async with asyncio.timeout(READY_WAIT + 30):
            while not line.startswith(b"ready"):
                line = await proc.stdout.readline()
                if not line:
                    raise RuntimeError(f"robot exited before it was ready:\n{(work / 'robot.log').read_text()[-3000:]}")
        t0 = float(line.split()[1])
        wall0 = time.time() - (time.monotonic() - t0)        # wall clock at t0
        samples, words = [], []
        dropped: list[tuple[float, float]] = []       # (s, messages the robot endpoint dropped and counted so far)
        last: tuple[list, dict] = ([], {})          # the last /api/placement rows and container stats seen
        bytes0 = link_bytes(link.a_dev)
        end = t0 + 4 * a.phase_s
        changes: list[float] = []                   # s at which each change of the script took effect

        async def script() -> None:
            """Each phase's change at its start (not at the next sample), timed when it took effect."""
            for k, change in ((1, lambda: (shape(lab, link, a.bad_rate, a.dscp), lab.set_delay(link, a.bad_delay_ms))),
                              (2, lambda: (shape(lab, link, GOOD_RATE, a.dscp), lab.set_delay(link, GOOD_DELAY_MS))),
                              (3, lambda: e.admin(f"/api/robots/{USER}/{ROBOT}/battery",
                                                  {"percent": BATTERY_LOW_PCT}))):
                await asyncio.sleep(max(0.0, t0 + k * a.phase_s - time.monotonic()))   # the script's clock
                await asyncio.to_thread(change)
                changes.append(round(time.monotonic() - t0, 3))
        scripted = asyncio.ensure_future(script())
        while (now := time.monotonic()) < end:
            try:
                rows = await admin("/api/placement")
                cs = await admin("/api/containers")
                st = await admin(f"/api/containers/{USER}/{CTAG}/stats")
            except Exception as err:          # noqa: BLE001 (a look that failed mid-move: the next one counts)
                print(f"placement: a look failed: {err}", flush=True)
                await asyncio.sleep(POLL)
                continue
            last = (rows, st)
            t = time.monotonic() - t0
            host = next((c["host"] for c in cs if c["ctag"] == CTAG), None)
            samples.append((round(t, 3), host, float(st.get("cpu_seconds") or 0.0), link_bytes(link.a_dev) - bytes0))
            dropped.append((round(t, 3), await asyncio.to_thread(counted_drops, e)))
            row = next((r for r in rows if r["ctag"] == CTAG), None)
            if row is not None:
                word = {"t_s": round(t, 2), "runs": row["runs"], "best": row["best"], "move": row["move"],
                        "why": row["why"]}
                if not words or any(words[-1][k] != word[k] for k in ("runs", "best", "move")):
                    words.append(word)
            await asyncio.sleep(max(0.0, POLL - (time.monotonic() - now)))     # the sampling period
        await scripted
        out, _ = await asyncio.wait_for(proc.communicate(), 60 + a.phase_s)
        if proc.returncode != 0:
            raise RuntimeError(f"robot failed ({proc.returncode}):\n{(work / 'robot.log').read_text()[-3000:]}")
        rec = json.loads(out.decode().strip().splitlines()[-1])
        moves = [dict(m, t_s=round(m["t"] - wall0, 3)) for m in await admin("/api/placement/moves")
                 if m["ctag"] == CTAG and m["t"] >= wall0]
        final, stats = last
        drops = {"container (its last copy)": {k: stats.get(k) for k in ("msgs_in", "msgs_out", "dropped")},
                 "node (its last copy)": {k: (stats.get("per_node") or {}).get("costmap", {}).get(k)
                                          for k in ("msgs_in", "msgs_out", "dropped")}}
        drops["node queue (largest count of a copy)"] = rec["node_dropped"]
        drops.update({name: await asyncio.to_thread(endpoint_counter, e, name)
                      for name in ("rce_robot_dropped", "rce_robot_shed", "rce_robot_superseded",
                                   "rce_robot_resume_lost", "rce_robot_duplicates", "rce_robot_lane_dropped",
                                   "rce_robot_dataplane_dropped")})
        total_bytes = link_bytes(link.a_dev) - bytes0
    finally:
        if scripted is not None and not scripted.done():
            scripted.cancel()
        if proc.returncode is None:
            proc.terminate()
            await proc.wait()
    return {"robot": rec, "samples": samples, "words": words, "moves": moves, "link_bytes": total_bytes,
            "counted_drops": dropped, "changes": changes,
            "hosts": hosts, "drops": drops,
            "placement_final": [r for r in final if r["ctag"] == CTAG],
            "master_log": [ln for ln in (work / "master.log").read_text(errors="replace").splitlines()
                           if '"placement' in ln or "container mov" in ln]}


def counted_drops(e) -> float:
    """Messages the robot endpoint dropped and counted so far (its data plane's links: a peer that
    does not keep up, :mod:`rce.transport.link`; its lanes)."""
    return sum(endpoint_counter(e, name) for name in ("rce_robot_dataplane_dropped", "rce_robot_lane_dropped"))


def endpoint_counter(e, name: str) -> float:
    """The sum of the robot endpoint's metric ``name`` over its samples (all labels; 0 if absent)."""
    import urllib.request
    info = e.robot_ready[0]
    host = info.get("host") or "127.0.0.1"
    url = f"http://{host if host != '0.0.0.0' else '127.0.0.1'}:{info['metrics_port']}/metrics"
    try:
        with urllib.request.urlopen(url, timeout=10) as resp:
            text = resp.read().decode()
    except OSError:
        return float("nan")
    return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines()
               if line.startswith(name) and not line.startswith(f"{name}_created"))


# -- the numbers ---------------------------------------------------------------------------------
def analyse(raw: dict, phase_s: float) -> dict:
    """The numbers of one system from its raw record (module docstring)."""
    from rce_master.placement.placer import EnergyModel
    rec = raw["robot"]
    t0 = rec["t0"]
    deadline = DEADLINE_MS / 1e3
    sent = {int(s): t - t0 for s, t in rec["sent"]}
    arrivals: dict[int, list[float]] = {}
    cpu_ms: dict[int, float] = {}
    for seq, t, ms, _ in rec["got"]:
        arrivals.setdefault(int(seq), []).append(t - t0)
        cpu_ms[int(seq)] = ms
    by_phase = [0, 0, 0, 0]
    series = []
    for seq, ts in sorted(sent.items()):
        k = min(3, int(ts // phase_s))
        lat = arrivals[seq][0] - ts if seq in arrivals else None
        if lat is None or lat > deadline:
            by_phase[k] += 1
        series.append((round(ts, 3), None if lat is None else round(lat * 1e3, 2)))
    for ts in rec["skipped"]:
        by_phase[min(3, int((ts - t0) // phase_s))] += 1
    not_sent = set(rec["send_failed"])
    lost = sorted(s for s in sent if s not in arrivals and s not in not_sent)
    lost_by_phase = [0, 0, 0, 0]
    for s in lost:
        lost_by_phase[min(3, int(sent[s] // phase_s))] += 1
    dup = sum(len(v) - 1 for v in arrivals.values() if len(v) > 1)
    results = sorted(t for ts in arrivals.values() for t in ts if t >= 0)
    by_arrival = sorted(rec["got"], key=lambda g: g[1])
    order = [int(g[0]) for g in by_arrival]
    reordered_at = [t - t0 for (seq, t, _, _), prev in zip(by_arrival[1:],
                                                         itertools.accumulate(order, max), strict=False) if seq < prev]
    drops = [(t, n) for t, n in raw.get("counted_drops", []) if n == n]      # NaN: a scrape that failed

    def counted(a: float, b: float) -> float:
        """Drops the robot endpoint counted from s ``a`` to ``b`` (its samples, every POLL s)."""
        before = [n for t, n in drops if t <= a]
        after = [n for t, n in drops if t >= b]
        return (after[0] if after else (drops[-1][1] if drops else 0)) - (before[-1] if before else 0)

    def gap_in(a: float, b: float) -> float:
        """The longest time without a result between s ``a`` and ``b`` (a result or a bound at each end)."""
        ts = [a, *(t for t in results if a < t < b), b]
        return max(y - x for x, y in zip(ts, ts[1:], strict=False))
    copies = [(t - t0, copy) for _, t, _, copy in by_arrival if t >= t0]
    moves = []
    for m in raw["moves"]:
        end = m["t_s"]
        begin = end - m["make_s"] - m["switch_s"] - m["drain_s"]
        switch = end - m["drain_s"]
        gaps = [b - a for a, b in zip(results, results[1:], strict=False) if b >= switch - 1.0 and a <= end + 0.5]
        handover = handover_gap(copies, begin, 4 * phase_s + drain_s(phase_s))
        around = [s for s, ts in sent.items() if begin - 1 <= ts <= end + 1]
        before = [t for t in results if t < switch]
        after = [t for t in results if t >= switch]
        lost_here = sum(1 for s in around if s not in arrivals and s not in not_sent)
        dropped = counted(begin - 1, end + 2)
        moves.append({"t_s": round(switch, 3), "from": m["from"], "to": m["to"],
                      "gap_s": None if handover is None else round(handover, 3),
                      # beside the move's own gap: the longest time without a result from 1 s before
                      # the switch to 0.5 s after the move (the copies' own gaps included: a
                      # cluttered scan on the robot's computer), what it is made of: the longest
                      # gap in the s before the move began (the link's own, no move yet), and the
                      # one across the switch (last result before it to the first after)
                      "longest_gap_around_s": round(max(gaps, default=0), 3),
                      "gap_before_move_s": round(gap_in(max(0.0, begin - 1.0), begin), 3),
                      "gap_across_switch_s": round(after[0] - before[-1], 3) if before and after else None,
                      "why": m["why"], "began_s": round(begin, 3), "ended_s": round(end, 3), "make_s": m["make_s"],
                      "switch_s": m["switch_s"], "make_steps": m.get("make_steps"), "spare": m.get("spare"),
                      "drain_s": m["drain_s"], "fenced": m.get("fenced"), "unfenced": m.get("unfenced"),
                      "lost": lost_here,
                      # of those, what the robot endpoint dropped and counted (a link that does not keep
                      # up) around the move; the rest was lost by the move itself
                      "dropped_counted": dropped, "lost_by_the_move": max(0, lost_here - int(dropped)),
                      "reordered": sum(1 for t in reordered_at if begin - 1 <= t <= end + 2),
                      "duplicated": sum(len(arrivals[s]) - 1 for s in around if s in arrivals)})
    robot_cpu = 0.0
    prev = None
    for _, host, cpu, _ in raw["samples"]:
        if prev is not None and host == prev[0] and host == "robot-computer":
            robot_cpu += max(0.0, cpu - prev[1]) if cpu >= prev[1] else cpu
        elif prev is not None and host == "robot-computer" and host != prev[0]:
            robot_cpu += cpu                               # a new copy's CPU since it was built
        prev = (host, cpu)
    em = EnergyModel()
    energy = em.cpu_w * robot_cpu + em.radio_j_per_byte * raw["link_bytes"]
    # the longest time without a result in each phase, moves or not (a copy's own: the robot's cluttered scans)
    gaps_by_phase = [round(max((b - a for a, b in zip(results, results[1:], strict=False)
                                if k * phase_s <= a < (k + 1) * phase_s), default=0.0), 3) for k in range(4)]
    return {"deadline_misses": sum(by_phase), "deadline_misses_by_phase": by_phase,
            "longest_gap_by_phase_s": gaps_by_phase,
            "robot_energy_j": round(energy, 3), "lost": len(lost), "duplicated": dup, "moves": moves,
            # the first result's arrival (s): a move that began before it has no handover to time (gap_s None)
            "first_result_s": round(copies[0][0], 3) if copies else None,
            "reordered": len(reordered_at), "dropped_counted": drops[-1][1] if drops else None,
            "lost_by_phase": lost_by_phase, "drops": raw["drops"],
            "scans": len(sent), "skipped_at_robot": len(rec["skipped"]),
            "skipped_s": [round(t - t0, 3) for t in rec["skipped"]], "send_failed": len(not_sent),
            "robot_errors": rec["errors"],
            "robot_cpu_s": round(robot_cpu, 3), "link_bytes": raw["link_bytes"],
            "energy_model": {"cpu_w": em.cpu_w, "radio_j_per_byte": em.radio_j_per_byte},
            "node_cpu_ms": {"sparse_p50": _p50([v for s, v in cpu_ms.items() if s % HEAVY_EVERY]),
                            "cluttered_p50": _p50([v for s, v in cpu_ms.items() if not s % HEAVY_EVERY])},
            "changes_s": raw["changes"], "placer_word": raw["words"], "placement_final": raw["placement_final"],
            "container_hosts": raw["hosts"], "ran_on": _host_spans(raw["samples"]), "latency_ms": series,
            "master_log": raw["master_log"][-60:]}


def handover_gap(copies: list[tuple[float, str]], begin: float, end: float) -> float | None:
    """A move's gap (s): the longest time without a result while the node's results pass from its
    old copy to its new one. ``copies``: ``(arrival s, copy ID)`` of every result, by arrival; the
    old copy answered last before the move began at ``begin`` s, the new copy is the first other one
    to answer after it. From the result before the first that either copy gave in the handover (the
    new copy's first, or the old copy's last if it came first) to the later of the two, the longest
    time between results (the new copy's first after the old copy's last, where they do not
    overlap). When no new copy answered by ``end`` (s, the record's end): from the old copy's last
    result to ``end``. None when no copy answered before the move."""
    old = next((c for t, c in reversed(copies) if t < begin), None)
    if old is None:
        return None
    new_first, new = next(((t, c) for t, c in copies if t >= begin and c != old), (None, None))
    if new_first is None:
        return end - max(t for t, c in copies if c == old)
    old_last = max(t for t, c in copies if c == old)
    lo, hi = min(new_first, old_last), max(new_first, old_last)
    ts = [t for t, c in copies if lo <= t <= hi and c in (old, new)]
    before = [t for t, _ in copies if t < lo]
    ts = ([before[-1]] if before else []) + ts
    return max((y - x for x, y in zip(ts, ts[1:], strict=False)), default=0.0)


def _p50(xs: list[float]) -> float | None:
    xs = sorted(xs)
    return round(xs[len(xs) // 2], 2) if xs else None


def _host_spans(samples: list) -> list[dict]:
    spans = []
    for t, host, _, _ in samples:
        if not spans or spans[-1]["host"] != host:
            spans.append({"from_s": t, "host": host})
    return spans


def targets(systems: dict, phase_s: float) -> dict:
    """The targets the issue sets, each with whether this run met it (None: not measured here)."""
    out = {}
    if {"cloud", "robot", "placer"} <= set(systems):
        p, c, r = (systems[k]["deadline_misses"] for k in ("placer", "cloud", "robot"))
        worse = max(c, r)
        out["fewer_misses_than_either_static"] = p < c and p < r
        out["5x_fewer_than_the_worse"] = p * 5 <= worse
    moves = [m for s in systems.values() for m in s["moves"]]
    # a move before the script's first scan (while the container was set up) has no handover to time
    timed = [m for m in moves if m["gap_s"] is not None]
    out["move_gap_under_300ms"] = all(m["gap_s"] < 0.3 for m in timed) if timed else None
    out["0_lost_or_duplicated_across_moves"] = all(m["lost"] == 0 and m["duplicated"] == 0 for m in moves) \
        if moves else None
    out["0_lost_by_the_moves_or_duplicated"] = all(m["lost_by_the_move"] == 0 and m["duplicated"] == 0
                                                   for m in moves) if moves else None
    out["moves_fenced"] = all(m["fenced"] for m in moves) if moves else None
    if "placer" in systems:
        from rce_master.placement.placer import Placer
        dwell = Placer().dwell_s
        pm, words = systems["placer"]["moves"], systems["placer"]["placer_word"]
        reactions = []
        took = systems["placer"].get("changes_s") or []
        for k in (1, 2, 3):
            at = took[k - 1] if len(took) >= k else phase_s * k      # when the change took effect
            word = next((w for w in words if w["t_s"] >= at), None)
            # its decision: the first word after the change that says move (a word that only names
            # another best, held back by the hysteresis, decides nothing)
            says_move = next((w for w in words if at <= w["t_s"] < at + phase_s and w["move"]), None)
            move = next((m for m in pm if at - 0.5 <= m["began_s"] < at + phase_s), None)
            changed = None if word is None or word["t_s"] >= at + phase_s else round(word["t_s"] - at, 2)
            moved = None if move is None else round(move["began_s"] - at, 2)
            # the placer's word is sampled every POLL s: a move that began first is its decision
            decided = min((x for x in (None if says_move is None else round(says_move["t_s"] - at, 2), moved)
                           if x is not None), default=None)
            reactions.append({"change": PHASES[k], "at_s": round(at, 3), "word_changed_after_s": changed, "word": word,
                              "moved_after_s": moved, "decided_after_s": decided})
        out["reactions"] = reactions
        seen = [r["decided_after_s"] for r in reactions if r["decided_after_s"] is not None]
        out["decides_within_2s"] = all(x <= 2.0 for x in seen) if seen else None
        out["never_twice_within_hysteresis"] = all(b["began_s"] - a["ended_s"] >= dwell - 0.1
                                                   for a, b in zip(pm, pm[1:], strict=False))
    return out


def plot(res: dict, png: Path) -> None:
    """Per system: each scan's latency against its send time, the deadline, phases, moves."""
    from common import pyplot
    plt = pyplot()
    names = list(res["systems"])
    fig, axes = plt.subplots(len(names), 1, figsize=(12, 2.8 * len(names)), sharex=True, squeeze=False)
    ps = res["phase_s"]
    labels = [*PHASES]
    labels[1] = f"link {res['bad_rate']}, {res['bad_delay_ms']:g} ms each way"
    for ax, name in zip(axes[:, 0], names, strict=False):
        s = res["systems"][name]
        pts = [(t, v) for t, v in s["latency_ms"] if v is not None]
        never = [t for t, v in s["latency_ms"] if v is None]
        ax.scatter([t for t, _ in pts], [v for _, v in pts], s=3, color="C0", label="result latency")
        top = max([v for _, v in pts] + [DEADLINE_MS * 3])
        ax.scatter(never, [top] * len(never), s=6, marker="x", color="C3", label="no result")
        ax.axhline(DEADLINE_MS, color="C3", lw=1, ls="--", label=f"deadline {DEADLINE_MS:g} ms")
        for k in range(4):
            ax.axvspan(k * ps, (k + 1) * ps, color=("white", "0.85", "white", "#fff3cc")[k], zorder=-1)
            ax.text(k * ps + 0.3, 0.97, labels[k], transform=ax.get_xaxis_transform(), fontsize=8, va="top")
        skipped = s.get("skipped_s") or []
        ax.scatter(skipped, [top * 0.6] * len(skipped), s=6, marker="|", color="0.4", label="not sent in time")
        for i, m in enumerate(s["moves"]):
            ax.axvline(m["t_s"], color="C2", lw=1.5)
            gap = f" (gap {m['gap_s'] * 1e3:.0f} ms)" if m["gap_s"] is not None else ""
            ax.text(m["t_s"], (0.88, 0.78, 0.68)[i % 3], f" -> {m['to'].split(' ')[0]}{gap}",
                    transform=ax.get_xaxis_transform(), fontsize=7, color="C2", va="top")
        ax.set_yscale("log")
        ax.set_ylabel("ms")
        ax.set_title(f"{name}: {s['deadline_misses']} misses {s['deadline_misses_by_phase']}, "
                     f"robot energy {s['robot_energy_j']:.1f} J, lost {s['lost']}, dup {s['duplicated']}", fontsize=9)
        ax.legend(loc="upper right", fontsize=7)
    axes[-1, 0].set_xlabel("s since the script began (scan's send time)")
    fig.tight_layout()
    fig.savefig(png, dpi=100)


async def bench(a: argparse.Namespace) -> dict:
    """The three systems' runs (``a.systems``) and the targets; the robot computer's cgroup made for
    them and removed after, whatever happens."""
    cap = CpuCap(f"rce-placement-bench-{os.getpid()}", ROBOT_CPU)
    try:
        res = await _bench_in(a, cap)
    finally:
        cap.close()
    res["targets"] = targets(res["systems"], a.phase_s)
    res["load_after"] = os.getloadavg()
    return res


async def _bench_in(a: argparse.Namespace, cap: CpuCap) -> dict:
    """:func:`bench` with the robot computer's cgroup ``cap`` made (and removed by the caller)."""
    from common import git_head
    from rce.tools.netlab import NetLab
    node = calibrate_on_robot(cap, a.heavy_ms, a.scan_points)
    a.node_args = node["node_args"]
    print(f"placement: node {a.node_args}: a cluttered scan {node['robot_heavy_ms']} ms on the robot's computer "
          f"({node['heavy_ms']} core-ms uncapped), a sparse one {node['robot_light_ms']} ms ({node['light_ms']})",
          flush=True)
    res: dict = {"bench": "placement", "git": git_head(), "phase_s": a.phase_s, "endpoint": a.endpoint,
                 "deadline_ms": DEADLINE_MS, "rate_hz": RATE_HZ, "scan_points": a.scan_points,
                 "light_fraction": LIGHT_FRACTION, "heavy_every": HEAVY_EVERY, "node_args": a.node_args,
                 "robot_cpu": ROBOT_CPU, "good_rate": GOOD_RATE, "bad_rate": a.bad_rate, "dscp": a.dscp,
                 "good_delay_ms": GOOD_DELAY_MS, "bad_delay_ms": a.bad_delay_ms,
                 "ordered_moves": a.ordered_moves, "spare": a.spare, "queue_packets": QUEUE, "node_calibration": node,
                 "battery_pct": [BATTERY_START_PCT, BATTERY_LOW_PCT], "load_before": os.getloadavg(),
                 "systems": {}, "robot_cpu_cap": cap.how}
    root = Path(tempfile.mkdtemp(prefix="rce-placement-"))
    res["logs"] = str(root)
    with NetLab("plb") as lab:
        lab.namespace("r")
        link = lab.link(None, "r", 1, delay=True)
        lab.route("r", "default", link.a_ip)
        for system in a.systems.split(","):
            print(f"placement: {system} ({4 * a.phase_s:g} s) ...", flush=True)
            raw = await run_system(system, lab, link, root / system, cap, a)
            res["systems"][system] = analyse(raw, a.phase_s)
            s = res["systems"][system]
            print(f"   misses {s['deadline_misses']} {s['deadline_misses_by_phase']}, energy "
                  f"{s['robot_energy_j']} J, lost {s['lost']}, dup {s['duplicated']}, moves "
                  f"{[(m['t_s'], m['to'], m['gap_s']) for m in s['moves']]}", flush=True)
    return res


def _interrupt(*_) -> None:
    raise KeyboardInterrupt


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--phase-s", type=float, default=30.0, help="s per phase (4 phases)")
    p.add_argument("--systems", default="cloud,robot,placer")
    p.add_argument("--endpoint", choices=("robot", "cloud"), default="robot",
                   help="the robot's endpoint: on its computer (rce-robot --zone robot:ID, default) or the cloud's")
    p.add_argument("--bad-rate", default=BAD_RATE, help=f"the link's rate in the second phase (tc units; "
                   f"default {BAD_RATE})")
    p.add_argument("--bad-delay-ms", type=float, default=BAD_DELAY_MS,
                   help=f"the link's one-way delay, each way, in the second phase (ms; default {BAD_DELAY_MS:g})")
    p.add_argument("--scan-points", type=int, default=SCAN_POINTS,
                   help=f"beams per scan (4 bytes each; default {SCAN_POINTS}: 0.35 Mbit/s at 10 Hz)")
    p.add_argument("--heavy-ms", type=float, default=ROBOT_HEAVY_MS,
                   help=f"ms a cluttered scan takes on the robot's computer (the node's --samples are set to that "
                        f"there at the start; default {ROBOT_HEAVY_MS:g})")
    p.add_argument("--dscp", action="store_true",
                   help="the link serves DSCP EF (the engine's control links) first; default: one FIFO")
    p.add_argument("--ordered-moves", action="store_true",
                   help="the container asks ordered_moves: its results keep one order across a move, whose gap "
                        "is then the old copy's drain")
    p.add_argument("--no-spare", dest="spare", action="store_false",
                   help="the placer's container asks no spare: each move makes its new copy first (default: a "
                        "spare is kept made on the host it would move to next, and a move there only switches)")
    p.add_argument("--out", type=Path, default=BENCH / "results" / "placement.json")
    p.add_argument("--keep-logs", action="store_true", help="keep the engines' logs (printed path)")
    p.add_argument("--role", choices=("bench", "robot", "calibrate"), default="bench", help=argparse.SUPPRESS)
    p.add_argument("--system", default="placer", help=argparse.SUPPRESS)
    p.add_argument("--node-args", default=f"{NODE_ARGS} --samples 300", help=argparse.SUPPRESS)
    p.add_argument("--master", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.role == "robot":
        print(json.dumps(asyncio.run(robot_main(a))), flush=True)
        return 0
    if a.role == "calibrate":                      # inside the robot computer's cgroup
        print(json.dumps(calibrate(a.heavy_ms, a.scan_points)), flush=True)
        return 0
    if os.geteuid() != 0:
        print("placement: needs root (network namespaces, tc, cgroups)", file=sys.stderr)
        return 2
    from common import write_json
    signal.signal(signal.SIGTERM, _interrupt)          # a kill ends the run through its clean-ups
    res = asyncio.run(bench(a))
    write_json(a.out, res)
    plot(res, a.out.with_suffix(".png"))
    if not a.keep_logs:
        shutil.rmtree(res["logs"], ignore_errors=True)
    print(json.dumps({k: {x: v[x] for x in ("deadline_misses", "deadline_misses_by_phase", "robot_energy_j", "lost",
                                            "duplicated", "moves")} for k, v in res["systems"].items()}, indent=1))
    print(json.dumps(res["targets"]))
    print(f"placement: wrote {a.out} and {a.out.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
