"""Round-trip time of a ROS 2 robot through rce to a ROS 2 node in a container, against payload size,
with its peers in the same run.

The robot is an rclpy node (``bench/ros2/ping.py``: ``std_msgs/msg/String`` on ``/req``, its answer
timed on ``/resp``, raw CDR); the cloud's node is an unchanged rclpy echo (the ament package
``bench/packages/benchecho_ros2``). Series:

- ``direct``: ping and echo in one ROS 2 graph (Fast DDS, shared memory between the processes):
  the ROS 2 floor.
- ``floor``: the topology's own floor: ping -> a plain rclpy relay -> a plain websocket -> a plain
  rclpy relay -> echo and back (``bench/ros2/relay.py``), the robot's and the cloud's graphs apart
  (two ``ROS_DOMAIN_ID``), nothing of rce between them: the DDS hops and the websocket rce's path has.
- ``rce_forwarder``: ping -> ``rce-ros --ros2`` (SubscriberForwarder/PublisherForwarder: the CDR
  bytes untouched) -> rce-robot -> the container's ROS 2 relay -> echo in the container and back.
- ``rce_converter``: the same with converters: the robot's CDR becomes JSON on the websocket and CDR
  again in the cloud (rce's registry, rosbags' CDR).

Per size, the median and p90 of ``reps`` round trips; ratios to ``floor`` (target: within 1.2x) and
to ``direct``; CPU per round trip of ``rce-ros --ros2`` beside rclpy's own processes (the ping's and the
echo's). Results in ``bench/results/rtt_ros2.json`` and ``.png``.

Usage::

    .venv/bin/python bench/rtt_ros2.py [--sizes 3,1623,...] [--reps N] [--series direct,floor,forwarder,converter]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import psutil

from common import (BENCH, RESULTS, USER, PASSWORD, anchor_sizes, console, engine, fmt_ms, fmt_ratio, fmt_size,
                    free_port, git_head, median, percentile, proc_label, proc_tree, process_cpu_s, pyplot, write_json)

PING = BENCH / "ros2" / "ping.py"
RELAY = BENCH / "ros2" / "relay.py"
PACKAGES = BENCH / "packages"
ECHO = PACKAGES / "benchecho_ros2" / "scripts" / "echo.py"
SERIES = ("direct", "floor", "forwarder", "converter")
SIZES = (3, 1623, 127_427, 1_128_837, 10_000_000)   # bytes: five of the anchors' sizes (shared/anchors/sizes.py)
READY_S = 120.0          # s a process may take to say it is ready


def reps_for(size: int, reps: int) -> int:
    """``reps`` per size, a quarter (at least 5) from 1 MB up, as the anchors."""
    return reps if size < 1_000_000 else max(5, reps // 4)


def domain_env(domain: int) -> dict:
    """One ROS 2 graph of this run: its domain, discovery on this host only, logs out of ~/.ros."""
    return dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                ROS_LOG_DIR=str(RESULTS / "ros2-logs"))


def wait_line(proc: subprocess.Popen, prefix: str, timeout: float = READY_S) -> str:
    """The first line of ``proc``'s stdout that starts with ``prefix``; RuntimeError if it ends first."""
    end = time.monotonic() + timeout
    for line in proc.stdout:
        if line.startswith(prefix):
            return line
        if time.monotonic() > end:
            break
    raise RuntimeError(f"{proc.args[:3]} did not print {prefix!r} (exit {proc.poll()})")


def ping(env: dict, sizes: list[int], reps: int, meter: list[psutil.Process] = ()) -> dict:
    """Run the ping node in ``env``'s graph; returns its result, with ``cpu_ms_procs``: CPU per round trip
    (ms) of each process in ``meter`` and its descendants (a container host's environments, relay and nodes)
    over the whole measurement, by process name."""
    spec = {"sizes": sizes, "reps": {str(s): reps_for(s, reps) for s in sizes}, "wait_s": READY_S}
    meter = proc_tree([p.pid for p in meter])
    cpu0 = {p.pid: _cpu(p) for p in meter}
    r = subprocess.run([sys.executable, str(PING)], input=json.dumps(spec) + "\n", env=env, capture_output=True,
                       text=True, timeout=3600)
    if r.returncode != 0 or not r.stdout.strip():
        raise RuntimeError(f"ping failed ({r.returncode}): {r.stderr[-2000:]}")
    out = json.loads(r.stdout.strip().splitlines()[-1])
    n = sum(spec["reps"].values()) + len(sizes)
    out["cpu_ms_procs"] = {}
    for p in meter:
        used = _cpu(p)
        if used is not None and cpu0[p.pid] is not None:
            label = proc_label(p)
            out["cpu_ms_procs"][label] = out["cpu_ms_procs"].get(label, 0.0) + (used - cpu0[p.pid]) * 1e3 / n
    out["cpu_ms_procs"]["ping (rclpy)"] = out["cpu_ms"]
    return out


def _cpu(p: psutil.Process) -> float | None:
    """User + system CPU s of ``p``; None once it is gone."""
    try:
        return process_cpu_s(p)
    except psutil.Error:
        return None


def stop(*procs: subprocess.Popen) -> None:
    for p in procs:
        if p.poll() is None:
            p.terminate()
    for p in procs:
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()


def run_direct(sizes: list[int], reps: int, domain: int) -> dict:
    env = domain_env(domain)
    echo = subprocess.Popen([sys.executable, str(ECHO)], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        return ping(env, sizes, reps, [psutil.Process(echo.pid)])
    finally:
        stop(echo)


def run_floor(sizes: list[int], reps: int, robot_domain: int, cloud_domain: int) -> dict:
    port = free_port()
    cloud, robot = domain_env(cloud_domain), domain_env(robot_domain)
    echo = subprocess.Popen([sys.executable, str(ECHO)], env=cloud, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    server = subprocess.Popen([sys.executable, str(RELAY), "server", str(port)], env=cloud, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    client = None
    try:
        wait_line(server, "ready")
        client = subprocess.Popen([sys.executable, str(RELAY), "client", f"ws://127.0.0.1:{port}/"], env=robot,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        wait_line(client, "ready")
        return ping(robot, sizes, reps, [psutil.Process(p.pid) for p in (client, server, echo)])
    finally:
        stop(*(p for p in (client, server, echo) if p is not None))


def robot_config(master_url: str, side: str) -> dict:
    """The robot's config: a container running the echo node, its /req and /resp wired to the robot's."""
    cls = "std_msgs/msg/String"
    return {
        "url": master_url, "userID": USER, "password": PASSWORD, "robotID": "rttRobot",
        "containers": [{"cTag": "rtt"}],
        "nodes": [{"cTag": "rtt", "nTag": "echo", "pkg": "benchecho_ros2", "exe": "echo.py"}],
        "interfaces": [
            {"eTag": "rtt", "iTag": "req", "iType": "PublisherInterface", "iCls": cls, "addr": "/req"},
            {"eTag": "rtt", "iTag": "resp", "iType": "SubscriberInterface", "iCls": cls, "addr": "/resp"},
            {"eTag": "rttRobot", "iTag": "req", "iType": f"Subscriber{side}", "iCls": cls, "addr": "/req"},
            {"eTag": "rttRobot", "iTag": "resp", "iType": f"Publisher{side}", "iCls": cls, "addr": "/resp"}],
        "connections": [{"tagA": "rtt/req", "tagB": "rttRobot/req"}, {"tagA": "rtt/resp", "tagB": "rttRobot/resp"}],
    }


def run_rce(sizes: list[int], reps: int, side: str, robot_domain: int, workdir: Path) -> dict:
    env = domain_env(robot_domain)
    with engine(workdir / side, env={"RCE_PACKAGE_PATH": str(PACKAGES)}) as e:
        cfg = workdir / f"{side}.config"
        cfg.write_text(json.dumps(robot_config(e.master_url, side.capitalize())))
        ros = subprocess.Popen([str(Path(sys.executable).parent / "rce-ros"), str(cfg), "--ros2"], env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            wait_line(ros, "rce-ros: ready")
            procs = [psutil.Process(ros.pid)] + [psutil.Process(p.pid) for p in e.procs]
            return ping(env, sizes, reps, procs)
        finally:
            stop(ros)


def summarize(raw: dict) -> dict:
    return {str(s): {"median_ms": median(v), "p90_ms": percentile(v, 90), "n": len(v),
                     "lost": raw["lost"].get(str(s), raw["lost"].get(s, 0))}
            for s, v in ((int(k), v) for k, v in raw["rtt_ms"].items())}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", default=",".join(map(str, SIZES)),
                   help="payload sizes in bytes (default: five of the anchors' sizes, 3 B to 10 MB; 'all': every one)")
    p.add_argument("--reps", type=int, default=int(os.environ.get("REPS", "40")))
    p.add_argument("--series", default=",".join(SERIES))
    p.add_argument("--json", type=Path, default=RESULTS / "rtt_ros2.json")
    p.add_argument("--plot", type=Path, default=RESULTS / "rtt_ros2.png")
    args = p.parse_args(argv)
    sizes = anchor_sizes() if args.sizes == "all" else [int(s) for s in args.sizes.split(",")]
    series = args.series.split(",")
    con = console()
    RESULTS.mkdir(parents=True, exist_ok=True)
    base = 10 + os.getpid() % 80           # three graphs of this run: robot, cloud, direct
    workdir = Path(os.environ.get("TMPDIR", "/tmp")) / f"rce-rtt-ros2-{os.getpid()}"
    workdir.mkdir(parents=True, exist_ok=True)
    res: dict = {"date": time.strftime("%Y-%m-%d"), "commit": git_head(), "sizes": sizes, "series": {}}
    runs = {"direct": lambda: run_direct(sizes, args.reps, base + 2),
            "floor": lambda: run_floor(sizes, args.reps, base, base + 1),
            "forwarder": lambda: run_rce(sizes, args.reps, "forwarder", base, workdir),
            "converter": lambda: run_rce(sizes, args.reps, "converter", base, workdir)}
    for name in series:
        con.print(f"[bold]{name}[/bold] ...")
        raw = runs[name]()
        res["series"][name] = {"rtt": summarize(raw), "cpu_ms_ping": raw["cpu_ms"], "cpu_ms_procs": raw["cpu_ms_procs"],
                               "raw_ms": raw["rtt_ms"]}
    write_json(args.json, res)
    print_table(con, res)
    plot(res, args.plot)
    con.print(f"results: {args.json}, {args.plot}")
    return 0


def print_table(con, res: dict) -> None:
    from rich.table import Table
    t = Table(title=f"ROS 2 round trip, median ms ({res['date']}, {res['commit']})")
    t.add_column("size")
    names = list(res["series"])
    for n in names:
        t.add_column(n, justify="right")
    for n in ("forwarder", "converter"):
        if n in names:
            t.add_column(f"{n} / floor", justify="right")
            t.add_column(f"{n} / direct", justify="right")
    for s in res["sizes"]:
        med = {n: res["series"][n]["rtt"][str(s)]["median_ms"] for n in names}
        row = [fmt_size(s)] + [fmt_ms(med[n]) for n in names]
        for n in ("forwarder", "converter"):
            if n in names:
                row += [fmt_ratio(med[n] / med["floor"]) if "floor" in med else "-",
                        fmt_ratio(med[n] / med["direct"]) if "direct" in med else "-"]
        t.add_row(*row)
    con.print(t)
    for n in names:
        cpu = res["series"][n]["cpu_ms_procs"]
        con.print(f"CPU per round trip, {n}: " + ", ".join(
            f"{k} {v:.3f} ms" if isinstance(v, float) else f"{k} " + "/".join(f"{x:.2f}" for x in v.values()) + " ms"
            for k, v in cpu.items() if not isinstance(v, float) or v >= 0.005))


def plot(res: dict, path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 5))
    for n, d in res["series"].items():
        xs = res["sizes"]
        ax.plot(xs, [d["rtt"][str(s)]["median_ms"] for s in xs], marker="o", label=n)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("payload (bytes)")
    ax.set_ylabel("round trip, median (ms)")
    ax.set_title(f"ROS 2 robot -> cloud node -> robot ({res['date']})")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    sys.exit(main())
