"""``rce-container MASTER[,MASTER...]``: the container task set of one host (see :mod:`rce_container.host`).

It outlives its master: when the master goes away its containers keep running, and it dials the
masters again with backoff and re-registers (:mod:`rce.transport.masterlink`).

Exit codes: 0 after SIGINT/SIGTERM (every container destroyed), 1 when the master refuses to
register it, 2 for bad arguments.
"""
from __future__ import annotations

import argparse
import asyncio
import os
import signal
import socket
import sys
import tempfile

from rce.plumbing.process import exit_process, run_loop
from rce.protocol.zones import parse_zone
from rce.transport import cluster_auth
from rce.transport import framing
from rce.plumbing.errors import RCEError
from rce.plumbing.log import get_logger, setup_logging
from rce.transport.masterlink import MASTER_PORT, unless_stopped
from rce_container import sandbox as sandboxes
from rce_container.host import ContainerHost, write_ready_file

log = get_logger("rce.container")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rce-container", description="rce container task set: runs the "
                                "containers (environments and their nodes) the master places on this host")
    p.add_argument("master", metavar="MASTER",
                   help="rce-master's control address: HOST or HOST:PORT; several masters: comma-separated")
    p.add_argument("--master-port", type=int, default=MASTER_PORT,
                   help=f"rce-master control port of addresses that give none (default {MASTER_PORT})")
    p.add_argument("--bind", default="127.0.0.1",
                   help="address environments' data-plane listeners bind to (default 127.0.0.1)")
    p.add_argument("--advertise-host", default=None, metavar="HOST",
                   help="address other hosts reach this host's environments by (default: --bind)")
    p.add_argument("--name", default=None, help="task set name (default: the hostname)")
    p.add_argument("--runtime-dir", default=None,
                   help="sockets and per-container dirs (default: a fresh dir under $XDG_RUNTIME_DIR or /tmp, "
                        "removed on exit)")
    p.add_argument("--ready-file", default=None, metavar="PATH",
                   help='write {"tid": ..., "pid": ...} as JSON here once registered with the master')
    p.add_argument("--cluster-key-file", type=str, default=None, metavar="PATH", help=cluster_auth.KEY_FLAG_HELP)
    p.add_argument("--max-frame", type=int, default=framing.DEFAULT_MAX_FRAME,
                   help=f"largest frame accepted on any link, bytes (default {framing.DEFAULT_MAX_FRAME})")
    p.add_argument("--sandbox", default="auto", choices=["auto", *sorted(sandboxes.REGISTRY)],
                   help="node isolation (default auto: 'namespaced' -- namespaces and a cgroup per "
                        "container -- when running as root, else 'unconfined')")
    p.add_argument("--warm", type=int, default=1,
                   help="idle environments kept started for fast container creation (default 1; 0 = none)")
    p.add_argument("--grace", type=float, default=sandboxes.DEFAULT_GRACE,
                   help="seconds between SIGTERM and SIGKILL when stopping nodes "
                        f"(default {sandboxes.DEFAULT_GRACE:g})")
    p.add_argument("--zone", default="cloud", metavar="ZONE",
                   help="where this host stands: cloud (default), edge (near the robots, shared) or "
                        "robot:ROBOT_ID (that robot's own computer; serves its --user alone)")
    p.add_argument("--user", default=None, metavar="NAME",
                   help="with --zone robot:ROBOT_ID: the user whose robot this is")
    p.add_argument("--metrics-port", type=int, default=None, metavar="PORT",
                   help="serve Prometheus /metrics on --bind at this port (0: ephemeral, written to the "
                        "ready file; default: off)")
    return p


async def amain(args: argparse.Namespace) -> int:
    zone = parse_zone(args.zone, args.user)                                # exit 2 for a bad zone
    cluster_key = cluster_auth.ClusterKey.load(args.cluster_key_file)     # before anything is made: exit 2 if none
    own = args.runtime_dir is None
    runtime_dir = args.runtime_dir or tempfile.mkdtemp(
        prefix="rce-container-", dir=os.environ.get("XDG_RUNTIME_DIR") or None)
    host = ContainerHost(args.master, args.master_port, name=args.name or socket.gethostname(), bind=args.bind,
                         cluster_key=cluster_key,
                         advertise_host=args.advertise_host, runtime_dir=runtime_dir, own_runtime_dir=own,
                         sandbox=args.sandbox, max_frame=args.max_frame, grace=args.grace, warm=args.warm,
                         metrics_port=args.metrics_port, zone=zone)
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, host.stop)
    try:
        tid = await unless_stopped(host.start(), host.stopped)
    except (OSError, RCEError) as e:
        log.error("cannot register with the master", master=args.master, reason=str(e))
        await host.close()
        return 1
    if host.stopped.is_set():
        return await host.run()
    if args.ready_file:
        write_ready_file(args.ready_file, tid, metrics_port=host.metrics_port, sandbox=host.sandbox_cls.kind)
    return await host.run()


def main(argv: list[str] | None = None) -> None:
    args = parser().parse_args(argv)
    setup_logging()
    try:
        code = run_loop(amain(args))
    except RCEError as e:        # configuration errors (e.g. an unavailable sandbox)
        print(f"rce-container: {e}", file=sys.stderr)
        sys.exit(2)
    exit_process(code)


if __name__ == "__main__":
    main()
