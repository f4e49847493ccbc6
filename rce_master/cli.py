"""``rce-master``: the master task set (login on 9000, control plane on 8080), its state in a
SQLite file (``--state``, default :func:`default_state_path`; with ``--dev`` one per port,
:func:`dev_state_path`), in memory (``--state :memory:``),
or in etcd shared with other masters (``--store etcd://HOST:PORT[,HOST:PORT...][/PREFIX/]``: one
leads, the others stand by; :mod:`rce_master.leadership.elected`)."""
from __future__ import annotations

import argparse
import asyncio
import functools
import os
import signal
import socket
import sys
from pathlib import Path

from rce.plumbing.errors import ConfigError
from rce.plumbing.process import run, write_ready_file
from rce.plumbing.log import get_logger
from rce.transport import cluster_auth
from rce.transport import tls
from rce_master.auth import login_guard, token
from rce_master.leadership import elected as leadership
from rce_master.state.reconcile import RECONCILE_GRACE
from rce_master.server import Master
from rce_master.state.master_state import DEFAULT_MAX_CONTAINERS, DEFAULT_MAX_INTERFACES, DEFAULT_MAX_NODES, Quotas
from rce_master.state.sqlite_store import SqliteStore
from rce_master.state.store import MemoryStore, Store

log = get_logger("rce.master")
MEMORY = ":memory:"          # --state value for a state kept in memory only (lost when the master exits)


def default_state_path() -> Path:
    """``$XDG_STATE_HOME/rce/master.sqlite3``, else ``~/.local/state/rce/master.sqlite3`` (XDG Base
    Directory specification: state that persists between restarts)."""
    base = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(base) / "rce" / "master.sqlite3"


def dev_state_path(port: int) -> Path | None:
    """The state file of ``rce-master --dev`` on HTTP port ``port``, beside the default one:
    ``dev-master-PORT.sqlite3``, so a development master never reads or writes the user's default
    state, nor another port's. None (state in memory) for an ephemeral port (``--port 0``)."""
    return default_state_path().with_name(f"dev-master-{port}.sqlite3") if port else None


def state_of(args: argparse.Namespace) -> str:
    """The ``--state`` a master runs on: the one given, else :func:`dev_state_path` with ``--dev``,
    else :func:`default_state_path`."""
    if args.state:
        return args.state
    if args.dev:
        path = dev_state_path(args.port)
        return str(path) if path else MEMORY
    return str(default_state_path())


def open_store(state: str | None) -> Store:
    """The store for ``--state``: :data:`MEMORY` gives a :class:`MemoryStore`, a path (default
    :func:`default_state_path`) a :class:`SqliteStore`. Raises :class:`ConfigError` when the file
    is held by another master or is not a state file."""
    if state == MEMORY:
        return MemoryStore()
    return SqliteStore(Path(state) if state else default_state_path())


class _OldSpelling(argparse.Action):
    """A flag's former name, kept so that existing command lines work: stores its value as the
    flag ``new`` does and says on stderr which name to use."""

    def __init__(self, *args, new: str, **kwargs):
        super().__init__(*args, **kwargs)
        self.new = new

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"{parser.prog}: {option_string} is deprecated; use {self.new}", file=sys.stderr)
        setattr(namespace, self.dest, values)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rce-master", description="RCE master: robot login, admin API, control plane.")
    p.add_argument("--dev", action="store_true", help="provision user testUser/testUser (development only)")
    p.add_argument("--no-dev-user", action="store_true",
                   help="with --dev, provision no testUser: the users come from --users alone (rce-fleet serve "
                        "gives its own, so that no well-known login exists)")
    p.add_argument("--bind", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=9000, help="HTTP port: login, admin API, /metrics (0 = ephemeral)")
    p.add_argument("--control-port", type=int, default=8080, help="control-plane port for task sets (0 = ephemeral)")
    p.add_argument("--users", type=Path, help="JSON file of hashed user records, kept up to date")
    p.add_argument("--state", default=None, metavar="PATH",
                   help="SQLite file of the master's state, restored on start (default $XDG_STATE_HOME/rce/"
                        "master.sqlite3, else ~/.local/state/rce/master.sqlite3; with --dev dev-master-PORT.sqlite3 "
                        f"there, in memory with --port 0); {MEMORY} keeps it in memory")
    p.add_argument("--store", default=None, metavar="etcd://HOST:PORT[,HOST:PORT...][/PREFIX/]",
                   help="keep the state in etcd, shared with other masters: one leads, the others stand by "
                        "(key prefix default /rce/; instead of --state)")
    p.add_argument("--advertise-host", default=None, metavar="HOST",
                   help="host name other masters and task sets reach this one at (default: --bind, or this "
                        "machine's name when --bind is a wildcard); with --store")
    p.add_argument("--advertise", dest="advertise_host", action=_OldSpelling, new="--advertise-host",
                   help=argparse.SUPPRESS)
    p.add_argument("--reconcile-grace", type=float, default=RECONCILE_GRACE, metavar="S",
                   help=f"s task sets found in the state may take to re-register before their containers are "
                        f"lost and their robots gone (default {RECONCILE_GRACE:g})")
    for kind, default in (("containers", DEFAULT_MAX_CONTAINERS), ("nodes", DEFAULT_MAX_NODES),
                          ("interfaces", DEFAULT_MAX_INTERFACES)):
        p.add_argument(f"--max-{kind}", type=int, default=default, metavar="N",
                       help=f"{kind} one user may have at once; past it a request gets an ER naming the quota "
                            f"(default {default}; 0 = no limit)")
    p.add_argument("--admin-token-file", type=Path, default=None,
                   help="admin API token file (default ~/.config/rce/admin-token, or under $XDG_CONFIG_HOME; "
                        "RCE_ADMIN_TOKEN overrides)")
    p.add_argument("--static", action="append", default=[], metavar="PREFIX=DIR",
                   help="serve DIR under URL PREFIX (e.g. the operator's web page)")
    p.add_argument("--ready-file", type=Path, help="write {http_port, control_port, pid} here once listening")
    p.add_argument("--cluster-key-file", type=Path, default=None, metavar="PATH", help=cluster_auth.KEY_FLAG_HELP)
    tls.add_server_arguments(p, "serve HTTPS (login, admin API, web page, /metrics)")
    g = p.add_argument_group("login throttling (docs/SECURITY.md)")
    g.add_argument("--login-failures-per-user", type=int, default=login_guard.FAILURES_PER_USER, metavar="N",
                   help="failed logins of one user from one address before it backs off with HTTP 429 "
                        f"(default {login_guard.FAILURES_PER_USER})")
    g.add_argument("--login-failures-per-address", type=int, default=login_guard.FAILURES_PER_ADDRESS, metavar="N",
                   help="failed logins from one address (any user names) before it backs off "
                        f"(default {login_guard.FAILURES_PER_ADDRESS})")
    g.add_argument("--login-backoff-max", type=float, default=login_guard.BACKOFF_MAX, metavar="S",
                   help="longest back-off, s; it starts at 1 s and doubles with each further failure "
                        f"(default {login_guard.BACKOFF_MAX:g})")
    return p



async def amain(args: argparse.Namespace) -> None:
    admin_token = token.load_or_create(args.admin_token_file)
    guard = login_guard.LoginGuard(per_user=args.login_failures_per_user, per_address=args.login_failures_per_address,
                                   backoff_max=args.login_backoff_max)
    cluster_key = cluster_auth.ClusterKey.load_or_create(args.cluster_key_file)
    make = functools.partial(Master, users_file=args.users, admin_token=admin_token,
                             dev=args.dev and not args.no_dev_user, cluster_key=cluster_key,
                             reconcile_grace=args.reconcile_grace, login_guard=guard,
                             quotas=Quotas(args.max_containers, args.max_nodes, args.max_interfaces))
    stop = stop_event()
    if args.store:
        if args.state:
            raise ConfigError("give --state (one master, SQLite or memory) or --store (etcd), not both")
        await leadership.run(args.store, lambda store, office: make(store=store, office=office),
                             functools.partial(start, args), functools.partial(ready, args), stop)
        return
    with open_store(state_of(args)) as store:
        master = make(store=store)
        await start(args, master)
        ready(args, master)
        await stop.wait()
        log.info("master stopping")
        await master.stop()


def stop_event() -> asyncio.Event:
    """An event set on SIGINT or SIGTERM."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    return stop


async def start(args: argparse.Namespace, master: Master) -> dict:
    """Start ``master`` listening; returns its addresses as other masters and task sets reach them
    (``{"control": "HOST:PORT", "http": "http://HOST:PORT/", "name", "pid"}``)."""
    static = {}
    for s in args.static:
        prefix, _, d = s.partition("=")
        static[prefix] = Path(d)
    ssl_context = tls.server_context_from(args)
    await master.start(args.bind, args.port, args.control_port, static, ssl_context)
    host = args.advertise_host or (socket.getfqdn() if args.bind in ("0.0.0.0", "::", "") else args.bind)
    host = f"[{host}]" if ":" in host else host
    scheme = "https" if ssl_context else "http"
    return {"control": f"{host}:{master.control_port}", "http": f"{scheme}://{host}:{master.http_port}/",
            "name": socket.gethostname(), "pid": os.getpid()}


def ready(args: argparse.Namespace, master: Master) -> None:
    """Write the ready file: ``{http_port, control_port, pid, leading, tls}`` (several masters: once this
    one leads or knows it stands by)."""
    write_ready_file(args.ready_file, {"http_port": master.http_port, "control_port": master.control_port,
                                       "pid": os.getpid(), "leading": master.office.leading,
                                       "tls": args.tls_cert is not None})


def main(argv: list[str] | None = None) -> None:
    run("rce-master", amain, parser().parse_args(argv))
