"""``rce-robot MASTER[,MASTER...]``: the robot task set (websocket on 9010, rosbridge v2 on 9090, data
plane on 10030).

It outlives its master: when the master goes away it keeps its robots and data-plane links,
dials the masters again with backoff and re-registers (:mod:`rce.transport.masterlink`)."""
from __future__ import annotations

import argparse
import asyncio
import os
import signal
import socket
from pathlib import Path

from rce.transport import cluster_auth

from rce.transport import tls
from rce.plumbing.log import get_logger
from rce.transport.masterlink import MASTER_PORT, MASTER_WAIT, parse_masters, unless_stopped
from rce.plumbing.process import run, write_ready_file
from rce.protocol.frames import DEFAULT_EXPIRY
from rce.protocol.limits import DEFAULT_MAX_PENDING_TOTAL
from rce.interfaces.pacer import rate_arg
from rce.protocol.resume import DEFAULT_GRACE, DEFAULT_RESUME_BUFFER
from rce.protocol.zones import parse_zone
from rce.protocol.session import DEFAULT_MAX_LAG, DEFAULT_MAX_MESSAGE, DEFAULT_QUEUE_SIZE
from rce_robot.endpoint import RobotEndpoint
from rce_robot import ws_link
from rce_robot.rosbridge.endpoint import ROSBRIDGE_PORT

log = get_logger("rce.robot")



def _at_least_one(text: str) -> int:
    """An argparse type: an integer >= 1."""
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}")
    return n


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rce-robot", description="RCE robot task set: robot endpoints.")
    p.add_argument("master_ip", metavar="MASTER",
                   help="rce-master's control address: HOST or HOST:PORT; several masters: comma-separated")
    p.add_argument("--master-port", type=int, default=MASTER_PORT,
                   help=f"rce-master control port of addresses that give none (default {MASTER_PORT})")
    p.add_argument("--master-wait", type=float, default=MASTER_WAIT, metavar="S",
                   help="seconds a robot's request (CC, DC, CN, CX) waits for an absent master before it gets "
                        f"an ER (default {MASTER_WAIT:g})")
    p.add_argument("--bind", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=9010, help="websocket port for robots (0 = ephemeral)")
    p.add_argument("--data-port", type=int, default=10030, help="data-plane port (0 = ephemeral)")
    p.add_argument("--rosbridge-port", type=int, default=ROSBRIDGE_PORT,
                   help=f"websocket port for rosbridge v2 clients (roslibpy, roslibjs; 0 = ephemeral, "
                        f"-1 = off; default {ROSBRIDGE_PORT})")
    p.add_argument("--foxglove-port", type=int, default=-1, metavar="PORT",
                   help="websocket port for Foxglove and Lichtblick (the Foxglove WebSocket protocol on a container's "
                        "graph, rce_robot.foxglove; needs the rosbridge endpoint; 0 = ephemeral; default -1 = off)")
    p.add_argument("--metrics-port", type=int, default=None, help="serve Prometheus /metrics on this port")
    p.add_argument("--advertise-host", default=None, metavar="HOST",
                   help="address robots and environments reach this host by (default: --bind)")
    p.add_argument("--name", default=None, help="task set name (default: hostname:port)")
    p.add_argument("--max-message", type=int, default=DEFAULT_MAX_MESSAGE,
                   help="largest websocket frame taken, bytes (larger: ER)")
    p.add_argument("--queue-size", type=_at_least_one, default=DEFAULT_QUEUE_SIZE,
                   help="messages that may wait per robot in each queue (data to it, requests, early DMs, calls; "
                        f">= 1; default {DEFAULT_QUEUE_SIZE}); past it topic data to the robot drops its oldest")
    p.add_argument("--expiry", type=float, default=DEFAULT_EXPIRY,
                   help="seconds an incomplete message waits for binary parts")
    p.add_argument("--max-lag", type=float, default=DEFAULT_MAX_LAG, metavar="S",
                   help="seconds the endpoint may stay behind a robot's frames before it sheds that robot's topic "
                        f"messages, oldest first, until it has caught up (0 = never; default {DEFAULT_MAX_LAG:g})")
    p.add_argument("--grace", type=float, default=DEFAULT_GRACE, metavar="S",
                   help="seconds the session of a robot that opted in to resume is kept after its link is lost, "
                        f"before its containers are destroyed (default {DEFAULT_GRACE:g})")
    p.add_argument("--resume-buffer", type=int, default=DEFAULT_RESUME_BUFFER, metavar="N",
                   help="messages kept per robot until it acks them, to resend after a resume; past it the oldest "
                        f"are dropped, counted and reported to the robot (default {DEFAULT_RESUME_BUFFER})")
    p.add_argument("--max-pending-binary", type=int, default=DEFAULT_MAX_PENDING_TOTAL, metavar="BYTES",
                   help="bytes of binary parts waiting for their message, all robots together; past it a part "
                        f"gets an ER (default {DEFAULT_MAX_PENDING_TOTAL}; each robot also has its own cap)")
    p.add_argument("--bulk-rate", type=rate_arg, default="auto", metavar="RATE",
                   help="pace each robot's bulk link (images, clouds, scans, maps to the robot) to RATE: bytes/s, or "
                        "with a unit (1.25MB, 10Mbit), a little below the robots' downlink; 'auto' (the default): "
                        "under the rate estimated for each link's path; 'off': not paced (docs/lanes.md)")
    p.add_argument("--mptcp", action="store_true",
                   help="accept robots over Multipath TCP where the kernel offers it (net.mptcp.enabled), else TCP")
    p.add_argument("--ws-impl", choices=ws_link.IMPLS, default=ws_link.DEFAULT_IMPL,
                   help="the websocket library that serves robots and rosbridge clients (default "
                        f"{ws_link.DEFAULT_IMPL}; docs/INTERNALS.md \"The robot endpoint's websocket\")")
    p.add_argument("--zone", default="cloud", metavar="ZONE",
                   help="where this endpoint stands: cloud (default), edge, or robot:ROBOT_ID (that robot's own "
                        "computer: it serves that robot alone, the master hands it that robot's logins, and the "
                        "robot's link is measured on its uplink; docs/placement.md)")
    p.add_argument("--user", default=None, metavar="NAME", help="with --zone robot:ROBOT_ID: the robot's user")
    p.add_argument("--ready-file", type=Path, help="write {ws_port, data_addr, pid} here once registered")
    p.add_argument("--cluster-key-file", type=Path, default=None, metavar="PATH", help=cluster_auth.KEY_FLAG_HELP)
    tls.add_server_arguments(p, "serve wss:// to robots and rosbridge clients (and https:// /metrics)")
    return p


async def amain(args: argparse.Namespace) -> None:
    masters = parse_masters(args.master_ip, args.master_port)
    zone = parse_zone(args.zone, args.user)                                # exit 2 for a bad zone
    ep = RobotEndpoint(name=args.name or f"{socket.gethostname()}-robot-{os.getpid()}",
                       cluster_key=cluster_auth.ClusterKey.load(args.cluster_key_file),
                       advertise_host=args.advertise_host or args.bind, max_message=args.max_message,
                       queue_size=args.queue_size, expiry=args.expiry, master_wait=args.master_wait,
                       grace=args.grace, resume_buffer=args.resume_buffer,
                       max_pending_total=args.max_pending_binary, ssl_context=tls.server_context_from(args),
                       max_lag=args.max_lag or None, bulk_rate=args.bulk_rate, mptcp=args.mptcp,
                       ws_impl=args.ws_impl, zone=zone)
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, ep.stopped.set)
    foxglove = None
    try:
        await unless_stopped(ep.start(masters, args.bind, args.port, args.data_port, args.metrics_port,
                                      None if args.rosbridge_port < 0 else args.rosbridge_port), ep.stopped)
        if args.foxglove_port >= 0 and ep.rosbridge is not None and not ep.stopped.is_set():
            from rce_robot.foxglove import RobotFoxglove
            foxglove = RobotFoxglove(ep.rosbridge)
            await foxglove.start(args.bind, args.foxglove_port, ep.ssl_context)
        if not ep.stopped.is_set():
            write_ready_file(args.ready_file, {"ws_port": ep.ws_port, "data_addr": ep.plane.addr, "pid": os.getpid(),
                                               "metrics_port": ep.metrics_port,
                                               "rosbridge_port": ep.rosbridge.port if ep.rosbridge else None,
                                               "foxglove_port": foxglove.port if foxglove else None,
                                               "tid": ep.master.tid})
            await ep.stopped.wait()
    finally:
        log.info("robot endpoint stopping")
        if foxglove is not None:
            await foxglove.stop()
        await ep.stop()


def main(argv: list[str] | None = None) -> None:
    run("rce-robot", amain, parser().parse_args(argv))
