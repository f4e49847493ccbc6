"""``rce-master``: the master task set (login on 9000, control plane on 8080)."""
from __future__ import annotations

import argparse
import asyncio
import os
import signal
from pathlib import Path

from rce.process import run, write_ready_file
from rce.log import get_logger
from rce_master import token
from rce_master.server import Master

log = get_logger("rce.master")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rce-master", description="RCE master: robot login, admin API, control plane.")
    p.add_argument("--dev", action="store_true", help="provision user testUser/testUser (development only)")
    p.add_argument("--bind", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=9000, help="HTTP port: login, admin API, /metrics (0 = ephemeral)")
    p.add_argument("--control-port", type=int, default=8080, help="control-plane port for task sets (0 = ephemeral)")
    p.add_argument("--users", type=Path, help="JSON file of hashed user records, kept up to date")
    p.add_argument("--admin-token-file", type=Path, default=None,
                   help="admin API token file (default ~/.config/rce/admin-token, or under $XDG_CONFIG_HOME; "
                        "RCE_ADMIN_TOKEN overrides)")
    p.add_argument("--static", action="append", default=[], metavar="PREFIX=DIR",
                   help="serve DIR under URL PREFIX (e.g. the operator's web page)")
    p.add_argument("--ready-file", type=Path, help="write {http_port, control_port, pid} here once listening")
    return p


async def amain(args: argparse.Namespace) -> None:
    admin_token = token.load_or_create(args.admin_token_file)
    master = Master(users_file=args.users, admin_token=admin_token, dev=args.dev)
    static = {}
    for s in args.static:
        prefix, _, d = s.partition("=")
        static[prefix] = Path(d)
    await master.start(args.bind, args.port, args.control_port, static)
    write_ready_file(args.ready_file, {"http_port": master.http_port, "control_port": master.control_port,
                                   "pid": os.getpid()})
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    await stop.wait()
    log.info("master stopping")
    await master.stop()


def main(argv: list[str] | None = None) -> None:
    run("rce-master", amain, parser().parse_args(argv))
