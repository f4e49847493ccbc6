"""The cost of the fleet's Foxglove WebSocket server beside the operator page's own websocket, per pose
forwarded, at 100 robots, in the same run on the same engine.

A source client publishes ``fleet/FleetState`` messages of ``--robots`` robots (5 Hz by default, as the
global planner does) into the fleet container's ``/fleet/state``. Two ways of watching them take turns
(``--rounds`` times each, ``--phase`` s each):

- **page**: a client connected as the operator page is (container ``SubscriberInterface`` ->
  ``PublisherConverter``): rce-robot turns each state into JSON and sends it on the client's websocket;
- **foxglove**: :class:`rce_fleet.live.foxglove.FleetFoxglove` in a process of its own (as in
  ``rce-fleet serve --foxglove-port``), fed through a forwarder, and one Foxglove client subscribed to every
  robot's ``/RobotN/pose``: each state becomes ``--robots`` ``geometry_msgs/PoseStamped`` messages, each a
  binary ``MESSAGE_DATA`` frame.

CPU (user + system) of the serving side: rce-robot, the container host (its environment forwards the
state either way) and, for foxglove, the Foxglove server's process; divided by the poses the client
received. The clients run in this process and are not counted. Reported: µs of CPU per pose each way, by
process, and their ratio (foxglove / page).

Usage::

    .venv/bin/python bench/foxglove.py [--robots 100] [--rate 5] [--phase 10] [--rounds 2]

Writes ``bench/results/foxglove.json`` and ``bench/results/foxglove.png``.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import RESULTS, USER, PASSWORD, CpuMeter, engine, git_head, median, proc_tree, pyplot, write_json

from rce.messages import default_registry
from rce.node.package_path import load_package_types
from rce_client.connection import Connection

CTAG = "cTag_01"
SOURCE_ID, PAGE_ID = "benchStateSource", "benchPage"
SETUP_TIMEOUT_S = 60.0
SERVER_START_S = 60.0


def fleet_state(reg, robots: int, seq: int) -> bytes:
    """A ``fleet/FleetState`` of ``robots`` robots on a 10 x 10 grid, positions moving with ``seq``."""
    t = seq * 0.2
    rs = [{"robot": f"Robot{i + 1}", "cell": i % 64, "goal": (i * 7) % 64, "x": (i % 10) + 0.01 * seq,
           "y": -(i // 10) - 0.5, "yaw": 0.1 * i, "path": [i % 64, (i + 1) % 64, (i + 2) % 64], "plan": 1,
           "cleared": 1, "state": "moving", "client_state": "driving", "distance_left": 3.0} for i in range(robots)]
    return reg.json_to_bytes("fleet/msg/FleetState", {
        "header": {"frame_id": "map", "stamp": {"secs": int(t), "nsecs": int((t % 1) * 1e9)}}, "seq": seq,
        "rows": 8, "cols": 8, "cell_w": 1.0, "cell_h": 1.0, "free": "1" * 64, "robots": rs})


async def wire(c: Connection, tag: str, container_type: str, robot_type: str) -> None:
    """Connect the container's ``/fleet/state`` (``container_type``) to ``c``'s ``robot_type`` interface ``tag``."""
    await c.configure({"addInterfaces": [
        {"endpointTag": CTAG, "interfaceTag": tag, "interfaceType": container_type,
         "className": "fleet/FleetState", "addr": "/fleet/state"},
        {"endpointTag": c.robot_id, "interfaceTag": tag, "interfaceType": robot_type,
         "className": "fleet/FleetState"}]})
    await c.send("CX", {"connect": [{"tagA": f"{CTAG}/{tag}", "tagB": f"{c.robot_id}/{tag}"}]})
    await c.barrier(SETUP_TIMEOUT_S)
    await c.wait_interfaces_up([tag], SETUP_TIMEOUT_S)


async def connect_source(master_url: str) -> tuple[Connection, object]:
    """The state source: creates the container and a forwarder into its /fleet/state."""
    c = await Connection.connect(master_url, USER, PASSWORD, SOURCE_ID)
    await c.create_container(CTAG)
    await wire(c, "srcState", "PublisherInterface", "SubscriberForwarder")
    return c, c.publisher("srcState", "fleet/FleetState")


async def connect_page(master_url: str, counts: dict) -> Connection:
    """A client as the operator page is: the fleet state as JSON through a PublisherConverter."""
    c = await Connection.connect(master_url, USER, PASSWORD, PAGE_ID)

    def on_state(msg) -> None:
        counts["states"] += 1
        counts["poses"] += len(msg["robots"])
    c.subscriber("pageState", "fleet/FleetState", on_state)
    await wire(c, "pageState", "SubscriberInterface", "PublisherConverter")
    return c


async def connect_foxglove(port: int, robots: int, counts: dict):
    """A Foxglove client subscribed to every ``/RobotN/pose``; returns the websocket and its reader task."""
    from websockets.asyncio.client import connect
    import hashlib
    import orjson
    pw = hashlib.sha256(PASSWORD.encode()).hexdigest()
    ws = await connect(f"ws://127.0.0.1:{port}/?userID={USER}&password={pw}", subprotocols=["foxglove.websocket.v1"],
                       max_size=None, compression=None)
    channels: dict[str, int] = {}
    while len(channels) < robots:
        msg = orjson.loads(await ws.recv())
        if msg["op"] == "advertise":
            channels.update({c["topic"]: c["id"] for c in msg["channels"] if c["topic"].endswith("/pose")})
    await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": i, "channelId": cid} for i, cid
                                                                   in enumerate(channels.values())]}))

    async def read() -> None:
        async for m in ws:
            if isinstance(m, bytes) and m[0] == 1:
                counts["poses"] += 1
    return ws, asyncio.create_task(read())


def start_server(master_url: str, robots: int, workdir: Path) -> tuple[subprocess.Popen, int]:
    """This script with ``--serve``: FleetFoxglove in a process of its own; returns it and its port."""
    port_file = workdir / "foxglove.port"
    p = subprocess.Popen([sys.executable, __file__, "--serve", master_url, "--robots", str(robots),
                          "--port-file", str(port_file)], stdout=open(workdir / "foxglove.log", "wb"),
                         stderr=subprocess.STDOUT, env=dict(os.environ, RCE_LOG_JSON="1"))
    deadline = time.monotonic() + SERVER_START_S
    while time.monotonic() < deadline:
        if port_file.exists() and port_file.read_text().strip():
            return p, int(port_file.read_text())
        if p.poll() is not None:
            break
        time.sleep(0.1)
    p.kill()
    raise RuntimeError(f"the Foxglove server did not start:\n{(workdir / 'foxglove.log').read_text()[-2000:]}")


async def serve(master_url: str, robots: int, port_file: Path) -> None:
    """``--serve``: FleetFoxglove on the lab map until killed."""
    from rce_fleet.live.fleet_scene import FleetScene
    from rce_fleet.live.foxglove import FleetFoxglove
    from rce_fleet.maps.geometry import GridGeometry
    from rce_fleet.maps.grid import fleet_grid
    from rce_fleet.maps.lab_map import write_lab_map
    from rce_fleet.maps.occupancy import load_map
    reg = default_registry()
    load_package_types(reg)
    occ = load_map(write_lab_map(tempfile.mkdtemp(prefix="rce-bench-map-")))
    geo = GridGeometry.from_cellgrid(fleet_grid(occ, (8, 8), None)[0])
    fox = FleetFoxglove(master_url, FleetScene(geo, occ, None, reg), [f"Robot{i + 1}" for i in range(robots)],
                        user=USER, password=PASSWORD, ctag=CTAG)
    await fox.start()
    port_file.write_text(str(fox.port))
    await asyncio.Event().wait()


async def measure(procs: list, counts: dict, seconds: float) -> dict:
    """CPU of ``procs`` over ``seconds`` s and the poses received meanwhile."""
    meter = CpuMeter(procs)
    p0 = counts["poses"]
    meter.start()
    await asyncio.sleep(seconds)          # the measuring window itself
    meter.stop()
    poses = counts["poses"] - p0
    secs = meter.seconds()
    by = {}
    for p in procs:
        if p.pid in secs:
            by[meter.labels[p.pid]] = by.get(meter.labels[p.pid], 0.0) + secs[p.pid]
    total = sum(secs.values())
    return {"poses": poses, "cpu_s": total, "us_per_pose": 1e6 * total / poses if poses else math.nan,
            "us_per_pose_by_process": {k: round(1e6 * v / poses, 2) if poses else None for k, v in by.items()},
            "wall_s": meter.wall}


async def run(args) -> dict:
    reg = default_registry()
    load_package_types(reg)
    workdir = Path(tempfile.mkdtemp(prefix="rce-bench-foxglove-"))
    with engine(workdir / "engine") as e:
        source, pub = await connect_source(e.master_url)
        # after the container is made: its environment is one of the container host's processes
        serving = proc_tree([p.pid for p in e.procs if "rce-master" not in str(p.args[0])])
        stop = asyncio.Event()

        async def publish() -> None:
            seq = 0
            t0 = time.monotonic()
            while not stop.is_set():
                seq += 1
                await pub.publish(fleet_state(reg, args.robots, seq))
                await asyncio.sleep(max(0.0, t0 + seq / args.rate - time.monotonic()))   # the source's pace
        pacer = asyncio.create_task(publish())
        server, port = start_server(e.master_url, args.robots, workdir)
        rows: dict[str, list[dict]] = {"page": [], "foxglove": []}
        try:
            for _ in range(args.rounds):
                counts = {"states": 0, "poses": 0}
                page = await connect_page(e.master_url, counts)
                while counts["states"] < 2:
                    await asyncio.sleep(0.05)
                rows["page"].append(await measure(serving, counts, args.phase))
                await page.configure({"removeInterfaces": [{"endpointTag": CTAG, "interfaceTag": "pageState"}]})
                await page.close()
                counts = {"poses": 0}
                ws, reader = await connect_foxglove(port, args.robots, counts)
                while counts["poses"] < 2 * args.robots:
                    await asyncio.sleep(0.05)
                rows["foxglove"].append(await measure(serving + proc_tree([server.pid]), counts, args.phase))
                await ws.close()
                reader.cancel()
        finally:
            stop.set()
            await pacer
            server.kill()
            server.wait()
            await source.close()
    page_us = median(r["us_per_pose"] for r in rows["page"])
    fox_us = median(r["us_per_pose"] for r in rows["foxglove"])
    return {"robots": args.robots, "rate_hz": args.rate, "phase_s": args.phase, "rounds": args.rounds,
            "page_us_per_pose": page_us, "foxglove_us_per_pose": fox_us, "ratio_foxglove_to_page": fox_us / page_us,
            "rows": rows, "git": git_head()}


def plot(res: dict, path: Path) -> None:
    """Stacked bars: CPU µs per pose by serving process, each way (the last round)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    names = {"foxglove.py": "Foxglove server", "rce_container.environment": "fleet container"}
    colours = {"rce-robot": "tab:blue", "fleet container": "tab:green", "Foxglove server": "tab:orange"}
    shown = set()
    for i, way in enumerate(("page", "foxglove")):
        bottom = 0.0
        for name, us in res["rows"][way][-1]["us_per_pose_by_process"].items():
            label = names.get(name, name)
            if not us or label not in colours:
                continue
            ax.bar(i, us, bottom=bottom, color=colours[label], label=None if label in shown else label)
            shown.add(label)
            bottom += us
    ax.set_xticks([0, 1], ["operator page's websocket", "Foxglove WebSocket server"])
    ax.set_ylabel("CPU µs per pose delivered")
    ax.set_title(f"{res['robots']} robots, {res['rate_hz']:g} Hz: foxglove / page = "
                 f"{res['ratio_foxglove_to_page']:.2f}x")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--robots", type=int, default=100)
    p.add_argument("--rate", type=float, default=5.0, help="fleet states per second (default 5)")
    p.add_argument("--phase", type=float, default=10.0, help="s of each measurement (default 10)")
    p.add_argument("--rounds", type=int, default=2, help="measurements of each way, alternating (default 2)")
    p.add_argument("--serve", metavar="MASTER_URL", help=argparse.SUPPRESS)
    p.add_argument("--port-file", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.serve:
        from rce.plumbing.process import run_loop
        run_loop(serve(args.serve, args.robots, args.port_file))
        return 0
    res = asyncio.run(run(args))
    RESULTS.mkdir(parents=True, exist_ok=True)
    write_json(RESULTS / "foxglove.json", res)
    plot(res, RESULTS / "foxglove.png")
    print(f"{res['robots']} robots at {res['rate_hz']:g} Hz: CPU per pose delivered: operator page's websocket "
          f"{res['page_us_per_pose']:.1f} µs, Foxglove WebSocket server {res['foxglove_us_per_pose']:.1f} µs "
          f"({res['ratio_foxglove_to_page']:.2f}x); by process: page "
          f"{res['rows']['page'][-1]['us_per_pose_by_process']}, foxglove "
          f"{res['rows']['foxglove'][-1]['us_per_pose_by_process']}")
    print(f"wrote {RESULTS / 'foxglove.json'} and {RESULTS / 'foxglove.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
