"""Control never waits behind data (docs/lanes.md): a cancel's round trip idle and under a saturating
camera, on a 10 Mbit/s link, with lanes, without lanes and with ROS 1, in network namespaces this
bench makes and removes (root).

Topology: the cloud (the real engine: rce-master, rce-robot ``--bulk-rate``, rce-container) in the
root namespace; the robot in namespace R, joined by one veth pair. Each end shapes what it sends to
10 Mbit/s with HTB (R's end: the uplink, the cloud's end: the downlink), in one of two bottlenecks:

- ``dscp``: a class per DSCP mark (u32 ``tos`` filters): EF 3 Mbit/s assured, best effort 5 Mbit/s, CS1
  2 Mbit/s, each borrowing up to 10 Mbit/s, EF first; a 1000-packet FIFO under each;
- ``fifo``: one 10 Mbit/s class, one 1000-packet FIFO, marks ignored.

The robot (a process in R): a camera of ``--camera-rate`` bytes/s (``sensor_msgs/Image`` frames of
``--frame`` bytes through a forwarder into a container, where ``benchecho/ack.py`` acks each frame with
its age) and a ``std_msgs/String`` cancel at 10 Hz through a converter, echoed by the Test package's
``stringEcho.py``. Each system runs an idle phase (the cancel only) and a camera phase (both):

- ``rce-lanes``: ``rce_client`` with lanes, the bulk link paced to ``--pace`` x the link (configured);
- ``rce-auto``: ``rce_client`` with lanes, the bulk link paced under the rate it estimates for the path
  (no rate configured: ``bulk_rate="auto"``, docs/lanes.md "Pacing");
- ``rce``: ``rce_client`` on one link (lanes off: today's shape for a 2013 client);
- ``ros1``: rospy over TCPROS (Debian ros-comm): rosmaster, the echo and the ack in the cloud, the robot
  node in R (``bench/ros1/lanes_peer.py``), when ROS 1 is installed.

It reports the cancel's p50/p99/max idle and under the camera and how many were lost, the camera's
goodput (frames acked x frame size / s, the phase's first second left out, and as a share of the link)
and frame age; JSON and a PNG in
``bench/results/``. Usage::

    sudo .venv/bin/python bench/lanes.py [--idle 8] [--camera 15] [--setups dscp,fifo]
                                         [--systems rce-lanes,rce-auto,rce,ros1]
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parent
sys.path.insert(0, str(BENCH))

LINK = 10_000_000 / 8           # bytes/s: the link's rate, both ways
CANCEL_HZ = 10.0
DRAIN = 5.0                     # s after a phase for late echoes before a cancel counts as lost
TRACE_EVERY = 0.02              # s between samples of the uplink's pacing (rate, estimate, queue) in the camera phase
WARMUP = 1.0                    # s at the start of a phase the camera's goodput leaves out (its first frames)
SYS_PY = "/usr/bin/python3"


# -- the robot: runs in namespace R --------------------------------------------------------------
def frame_bytes(size: int) -> bytearray:
    """A serialized ``sensor_msgs/Image`` of about ``size`` bytes (mono8, one row); header.seq at
    bytes 0-3, header.stamp at 4-11 (patched per frame)."""
    import numpy as np
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS1_NOETIC)
    t = ts.types
    img = t["sensor_msgs/msg/Image"](
        header=t["std_msgs/msg/Header"](seq=0, stamp=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0),
                                        frame_id="cam"),
        height=1, width=size, encoding="mono8", is_bigendian=0, step=size, data=np.zeros(size, dtype=np.uint8))
    return bytearray(ts.serialize_ros1(img, "sensor_msgs/msg/Image"))


def stamp(frame: bytearray, seq: int) -> bytes:
    now = time.time()
    frame[0:12] = seq.to_bytes(4, "little") + int(now).to_bytes(4, "little") + \
        int((now % 1) * 1e9).to_bytes(4, "little")
    return bytes(frame)


class Probe:
    """The cancel's round trips and the camera's acks of one phase."""

    def __init__(self, phase: str):
        self.phase = phase
        self.sent: dict[int, float] = {}
        self.rtt: dict[int, float] = {}
        self.acks: list[tuple[int, float, float]] = []     # (seq, age s, arrival monotonic)
        self.frames = 0

    def echo(self, data: str) -> None:
        phase, _, n = data.partition(":")
        if phase == self.phase and n.isdigit() and int(n) in self.sent and int(n) not in self.rtt:
            self.rtt[int(n)] = time.monotonic() - self.sent[int(n)]

    def ack(self, data: str) -> None:
        a = json.loads(data)
        self.acks.append((a["seq"], a["age"], time.monotonic()))

    def result(self, seconds: float, frame: int, end: float) -> dict:
        """The phase's numbers; the camera's are steady state: frames acked in the phase's last
        ``seconds - WARMUP`` s before ``end`` (monotonic s)."""
        ms = sorted(v * 1000 for v in self.rtt.values())
        seconds = max(seconds - WARMUP, 1e-9)
        acks = [(seq, age) for seq, age, t in self.acks if end - seconds <= t <= end]
        ages = sorted(age * 1000 for _, age in acks)
        return {"phase": self.phase, "cancels": len(self.sent), "lost": len(self.sent) - len(self.rtt),
                "p50_ms": _pct(ms, 50), "p99_ms": _pct(ms, 99), "max_ms": ms[-1] if ms else None,
                "frames_sent": self.frames, "frames_acked": len(acks),
                "goodput_Bps": round(len(acks) * frame / seconds), "goodput_share": round(
                    len(acks) * frame / seconds / LINK, 3),
                "frame_age_p50_ms": _pct(ages, 50), "frame_age_p99_ms": _pct(ages, 99),
                "rtt_series": self.series()}

    def series(self) -> list[tuple[float, float | None]]:
        """Each cancel's (s since the phase's first, round trip ms; None: lost), for a look at when the
        slow ones went."""
        t0 = min(self.sent.values(), default=0.0)
        return [(round(t - t0, 3), round(self.rtt[n] * 1000, 2) if n in self.rtt else None)
                for n, t in sorted(self.sent.items())]


def _pct(xs: list[float], q: float) -> float | None:
    if not xs:
        return None
    return round(xs[min(len(xs) - 1, int(round(q / 100 * (len(xs) - 1))))], 3)


async def run_phase(probe: Probe, seconds: float, cancel, camera, frame: bytearray | None, fps: float) -> float:
    """The cancel at 10 Hz (``await cancel(text)``) and, with ``frame``, the camera at ``fps``
    (``await camera(bytes)``) for ``seconds``; then :data:`DRAIN` s for late echoes. Returns when the
    phase ended (monotonic s)."""
    end = time.monotonic() + seconds

    async def cancels() -> None:
        i = 0
        while time.monotonic() < end:
            probe.sent[i] = time.monotonic()
            await cancel(f"{probe.phase}:{i}")
            i += 1
            await asyncio.sleep(max(0.0, probe.sent[i - 1] + 1 / CANCEL_HZ - time.monotonic()))   # the rate

    async def frames() -> None:
        n = 0
        t0 = time.monotonic()
        while time.monotonic() < end:
            await camera(stamp(frame, n))
            n += 1
            probe.frames = n
            await asyncio.sleep(max(0.0, t0 + n / fps - time.monotonic()))           # the camera's rate

    await asyncio.gather(cancels(), *([frames()] if frame is not None else []))
    ended = time.monotonic()
    deadline = time.monotonic() + DRAIN
    while len(probe.rtt) < len(probe.sent) and time.monotonic() < deadline:
        await asyncio.sleep(0.05)            # waiting out late echoes, bounded
    return ended


async def robot_rce(a: argparse.Namespace) -> dict:
    from rce_client.connection import Connection
    lanes = a.system in ("rce-lanes", "rce-auto")
    conn = await Connection.connect(a.master, "testUser", "testUser", f"lanes{a.tag}", allow_reconnect=True,
                                    lanes=lanes, bulk_rate=a.pace * LINK if a.system == "rce-lanes" else "auto")
    rid, c = conn.robot_id, f"lanesC{a.tag}"
    await conn.create_container(c)
    await conn.add_node(c, "echo", "Test", "stringEcho.py")
    await conn.add_node(c, "ack", "benchecho", "ack.py")
    for t, itype, cls, addr in (("req", "PublisherInterface", "std_msgs/String", "/stringEchoReq"),
                                ("resp", "SubscriberInterface", "std_msgs/String", "/stringEchoResp"),
                                ("cam", "PublisherInterface", "sensor_msgs/Image", "/camera"),
                                ("ack", "SubscriberInterface", "std_msgs/String", "/camera_ack")):
        await conn.add_interface(c, t, itype, cls, addr)
    await conn.add_interface(rid, "req", "SubscriberConverter", "std_msgs/String")       # control (std_msgs)
    await conn.add_interface(rid, "resp", "PublisherConverter", "std_msgs/String")
    await conn.add_interface(rid, "cam", "SubscriberForwarder", "sensor_msgs/Image")     # bulk (sensor_msgs/Image)
    await conn.add_interface(rid, "ack", "PublisherConverter", "std_msgs/String")
    for t in ("req", "resp", "cam", "ack"):
        await conn.connect(f"{c}/{t}", f"{rid}/{t}")
    await conn.wait_interfaces_up(["req", "resp", "cam", "ack"], timeout=120)
    if lanes:
        await conn.bulk.wait_up(30)
    probe = Probe("warm")
    conn.subscriber("resp", "std_msgs/String", lambda m: probe.echo(m["data"]))
    conn.subscriber("ack", "std_msgs/String", lambda m: probe.ack(m["data"]))
    req, cam = conn.publisher("req", "std_msgs/String"), conn.publisher("cam", "sensor_msgs/Image")

    async def cancel(text: str) -> None:
        await req.publish({"data": text})
    for i in range(600):                       # the echo node may subscribe after the interfaces are up
        probe.sent[i] = time.monotonic()
        await cancel(f"warm:{i}")
        await asyncio.sleep(0.1)
        if probe.rtt:
            break
    trace: list[tuple] = []
    out = await phases(a, cancel, cam.publish, probe, trace_pacing(conn, trace) if lanes else None)
    out["pacing_trace"] = trace
    out["bulk"] = {"sent": conn.bulk.sent, "dropped": conn.bulk.dropped, "pacing": conn.bulk.pacing()} if lanes \
        else None
    await conn.close()
    return out


async def trace_pacing(conn, trace: list[tuple]) -> None:
    """Every :data:`TRACE_EVERY` s until cancelled, the uplink's pacing into ``trace``: (s since the
    camera phase began, the pacer's rate, the estimate (None until known), the estimator's mode, the
    bulk socket's smoothed RTT above its least (ms), its bytes acked and not sent (None without a
    sample)), rates as a share of the link."""
    from rce.transport.lane_socket import socket_of, tcp_sample
    t0 = time.monotonic()
    while True:
        pacer, sock = conn.bulk.pacer, socket_of(conn.bulk.ws) if conn.bulk.ws is not None else None
        s = tcp_sample(sock, 0.0, 0.0) if sock is not None else None
        est = pacer.estimator
        trace.append((round(time.monotonic() - t0, 3), round(pacer.rate / LINK, 4),
                      None if est is None or est.estimate is None else round(est.estimate / LINK, 4),
                      est.mode.value if est is not None else "configured",
                      None if s is None else round((s.rtt - s.min_rtt) * 1000, 2),
                      None if s is None else s.acked, None if s is None else s.notsent))
        await asyncio.sleep(TRACE_EVERY)


async def phases(a: argparse.Namespace, cancel, camera, first: Probe, tracer=None) -> dict:
    """The idle phase, then the camera phase (``tracer``, a coroutine, runs through the camera phase)."""
    frame = frame_bytes(a.frame)
    res = {}
    for name, with_camera, seconds in (("idle", False, a.idle), ("camera", True, a.camera)):
        probe = Probe(name)
        first.echo, first.ack = probe.echo, probe.ack          # the handlers feed the current phase
        traced = asyncio.ensure_future(tracer) if with_camera and tracer is not None else None
        try:
            ended = await run_phase(probe, seconds, cancel, camera, frame if with_camera else None,
                                    a.camera_rate / a.frame)
        finally:
            if traced is not None:
                traced.cancel()
        res[name] = probe.result(seconds, a.frame, ended)
    return res


# -- the cloud side: namespaces, shaping, the systems ---------------------------------------------
def robot_process(lab, argv: list[str], timeout: float) -> dict:
    r = subprocess.run(lab.wrap("r", argv), capture_output=True, text=True, timeout=timeout)
    if r.returncode != 0:
        raise RuntimeError(f"robot failed ({r.returncode}): {r.stderr[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--idle", type=float, default=8.0, help="s of the idle phase")
    p.add_argument("--camera", type=float, default=15.0, help="s of the camera phase")
    p.add_argument("--camera-rate", type=float, default=5e6, help="camera bytes/s (default 5 MB/s)")
    p.add_argument("--frame", type=int, default=500_000, help="bytes per camera frame")
    p.add_argument("--pace", type=float, default=0.88, help="the bulk link's rate as a share of the link")
    p.add_argument("--setups", default="dscp,fifo")
    p.add_argument("--systems", default="rce-lanes,rce-auto,rce,ros1")
    p.add_argument("--out", type=Path, default=BENCH / "results" / "lanes.json")
    # the robot's role (run by the bench in namespace R)
    p.add_argument("--role", choices=("bench", "robot"), default="bench", help=argparse.SUPPRESS)
    p.add_argument("--system", default="rce-lanes", help=argparse.SUPPRESS)
    p.add_argument("--master", help=argparse.SUPPRESS)
    p.add_argument("--tag", default="", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.role == "robot":
        print(json.dumps(asyncio.run(robot_rce(a))), flush=True)
        return 0
    return bench(a)


def bench(a: argparse.Namespace) -> int:
    from common import ensure_ros1, git_head, pyplot, write_json
    from rce.tools.launch import start_engine
    from rce.tools.netlab import NetLab
    if os.geteuid() != 0:
        print("lanes: needs root (network namespaces, tc)", file=sys.stderr)
        return 2
    systems = [s for s in a.systems.split(",") if s]
    if "ros1" in systems:
        ok, why = ensure_ros1(log=lambda m: print(f"lanes: {m}", flush=True))
        if not ok:
            print(f"lanes: ROS 1 left out: {why}", flush=True)
            systems.remove("ros1")
    results: dict = {"load_before": os.getloadavg(), "link_Bps": LINK, "camera_Bps": a.camera_rate,
                     "frame": a.frame, "pace": a.pace, "cancel_hz": CANCEL_HZ, "git": git_head(), "runs": []}
    with NetLab("lnb") as lab:
        lab.namespace("r")
        link = lab.link(None, "r", 1)
        lab.route("r", "default", link.a_ip)
        os.environ["RCE_PACKAGE_PATH"] = str(BENCH / "packages")
        e = start_engine(Path(tempfile.mkdtemp(prefix="rce-lanes-")), master_args=("--bind", "0.0.0.0"),
                         robot_args=("--bind", "0.0.0.0", "--advertise-host", link.a_ip,
                                     "--bulk-rate", str(a.pace * LINK)))
        try:
            master = f"http://{link.a_ip}:{e.http_port}/"
            n = 0
            for setup in [s for s in a.setups.split(",") if s]:
                lab.shape(link, "b", "10mbit", dscp=setup == "dscp")      # the uplink
                lab.shape(link, "a", "10mbit", dscp=setup == "dscp")      # the downlink
                for system in systems:
                    n += 1
                    print(f"lanes: {setup} bottleneck, {system}: idle {a.idle:g} s, camera {a.camera:g} s ...",
                          flush=True)
                    if system == "ros1":
                        r = ros1_run(lab, link, a)
                    else:
                        r = robot_process(lab, [sys.executable, __file__, "--role", "robot", "--system", system,
                                                "--master", master, "--tag", str(n), "--idle", str(a.idle),
                                                "--camera", str(a.camera), "--camera-rate", str(a.camera_rate),
                                                "--frame", str(a.frame), "--pace", str(a.pace)],
                                          timeout=300 + a.idle + a.camera)
                    r.update(setup=setup, system=system)
                    results["runs"].append(r)
                    print("   " + summary(r), flush=True)
        finally:
            e.stop()
    results["load_after"] = os.getloadavg()
    write_json(a.out, results)
    plot(results, a.out.with_suffix(".png"), pyplot())
    print(f"lanes: {a.out} and {a.out.with_suffix('.png')}")
    return 0


def ros1_run(lab, link, a: argparse.Namespace) -> dict:
    """ROS 1 on the same link: rosmaster, the echo and the ack in the cloud (root namespace), the robot
    node in R (``bench/ros1/lanes_peer.py``)."""
    port = 11411
    home = tempfile.mkdtemp(prefix="rce-lanes-ros1-")
    env = dict(os.environ, ROS_MASTER_URI=f"http://{link.a_ip}:{port}", ROS_IP=link.a_ip, ROS_HOME=home)
    peer = str(BENCH / "ros1" / "lanes_peer.py")
    master = subprocess.Popen(["rosmaster", "--core", "-p", str(port)], env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    cloud = subprocess.Popen([SYS_PY, peer, "cloud"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        renv = dict(env, ROS_IP=link.b_ip)
        r = subprocess.run(lab.wrap("r", ["env", *[f"{k}={v}" for k, v in renv.items() if k.startswith("ROS")],
                                          SYS_PY, peer, "robot", "--idle", str(a.idle), "--camera", str(a.camera),
                                          "--camera-rate", str(a.camera_rate), "--frame", str(a.frame)]),
                           capture_output=True, text=True, timeout=300 + a.idle + a.camera)
        if r.returncode != 0:
            raise RuntimeError(f"ROS 1 robot failed: {r.stderr[-2000:]}")
        return json.loads(r.stdout.strip().splitlines()[-1])
    finally:
        for proc in (cloud, master):
            proc.terminate()
            proc.wait()


def summary(r: dict) -> str:
    i, c = r["idle"], r["camera"]
    pacing = (r.get("bulk") or {}).get("pacing") or {}
    est = f"; uplink estimated {pacing['rate_estimate'] / LINK:.0%} of the link" \
        if pacing.get("rate_estimate") else ""
    return (f"cancel idle p50 {i['p50_ms']} p99 {i['p99_ms']} max {i['max_ms']} ms; under camera p50 "
            f"{c['p50_ms']} p99 {c['p99_ms']} max {c['max_ms']} ms, lost {i['lost'] + c['lost']}; camera "
            f"{c['goodput_Bps'] / 1e6:.2f} MB/s ({c['goodput_share']:.0%} of the link), age p50 "
            f"{c['frame_age_p50_ms']} ms{est}")


def plot(results: dict, path: Path, plt) -> None:
    """Left: the cancel's round trips per run; right: the camera's goodput; below, for each run whose
    rate was estimated: the estimate and the pacer's rate against time in the camera phase, with each
    cancel's round trip."""
    runs = results["runs"]
    traced = [r for r in runs if r["system"] == "rce-auto" and r.get("pacing_trace")]
    fig = plt.figure(figsize=(12, 4.5 + 3.5 * bool(traced)))
    grid = fig.add_gridspec(1 + bool(traced), max(2, len(traced)))
    ax1, ax2 = fig.add_subplot(grid[0, : grid.ncols // 2]), fig.add_subplot(grid[0, grid.ncols // 2:])
    labels = [f"{r['system']}\n{r['setup']}" for r in runs]
    x = range(len(runs))
    for k, (phase, key) in enumerate((("idle", "p99_ms"), ("camera", "p50_ms"), ("camera", "p99_ms"))):
        vals = [r[phase][key] or 0 for r in runs]
        ax1.bar([i + (k - 1) * 0.27 for i in x], vals, 0.27, label=f"{phase} {key.split('_')[0]}")
    ax1.set_yscale("log")
    ax1.set_xticks(list(x), labels, fontsize=8)
    ax1.set_ylabel("cancel round trip, ms (log)")
    ax1.set_title("10 Hz cancel, 10 Mbit/s link, 5 MB/s camera")
    ax1.legend(fontsize=8)
    ax2.bar(list(x), [r["camera"]["goodput_share"] * 100 for r in runs])
    ax2.axhline(85, color="grey", ls="--", lw=1)
    ax2.set_xticks(list(x), labels, fontsize=8)
    ax2.set_ylabel("camera goodput, % of the link")
    for k, r in enumerate(traced):
        ax = fig.add_subplot(grid[1, k])
        t = [p[0] for p in r["pacing_trace"]]
        ax.plot(t, [p[1] * 100 for p in r["pacing_trace"]], lw=0.8, label="pacer's rate")
        ax.plot(t, [None if p[2] is None else p[2] * 100 for p in r["pacing_trace"]], lw=1.2, label="estimate")
        ax.set_ylim(0, 200)
        ax.set_xlabel("s into the camera phase")
        ax.set_ylabel("% of the link")
        ax.set_title(f"rate estimated, {r['setup']} bottleneck", fontsize=9)
        rt = ax.twinx()
        series = [(t_, ms) for t_, ms in r["camera"]["rtt_series"] if ms is not None]
        rt.plot([p[0] for p in series], [p[1] for p in series], ".", ms=3, color="C3", label="cancel round trip")
        rt.set_ylabel("cancel round trip, ms", color="C3")
        ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)

if __name__ == "__main__":
    sys.exit(main())
