"""``rce-console``: the operator's CLI onto the master's admin API.

::

    rce-console [--master URL[,URL...]] robots|containers|nodes|interfaces|connections|tasksets|parameters|users
    rce-console user add NAME [--password-stdin] [--role viewer|operator|admin]   # prompts twice without stdin
    rce-console user role NAME --role viewer|operator|admin   # what the user may do on the fleet's task API
    rce-console user del NAME
    rce-console logs USER CTAG NTAG                   # a node's kept stdout/stderr
    rce-console container resize USER CTAG [--cpu CORES] [--memory MIB] [--pids N] [--size N]
    rce-console container move USER CTAG --to HOST     # make-before-break, nothing lost
    rce-console top [--interval S] [--once]           # per-container CPU, memory, processes, traffic
    rce-console user add NAME --file users.json       # offline: add a hashed record to a --users file
    rce-console leader                                # which master leads (several masters on etcd)
    rce-console placement                             # per container: where it runs, where it would serve best, why
    rce-console placement pin USER CTAG cloud|edge|robot|auto    # pin it (moved there now; auto: the placer decides)
    rce-console placement moves                       # the last moves: when, from, to, the switch, why

With several masters (``--master`` repeated, or URLs separated by commas) a request goes to one
that answers, and a change to the leader (:mod:`rce.tools.admin_client`).

The admin token comes from ``--admin-token``, ``RCE_ADMIN_TOKEN``, ``--admin-token-file`` or the
token file the master created (``~/.config/rce/admin-token``); see :mod:`rce.tools.admin_client`.
"""
from __future__ import annotations

import argparse
import getpass
import json
import sys
import time
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.live import Live
from rich.table import Table

from rce.tools.admin_client import AdminClient
from rce.plumbing.errors import RCEError, RequestError
from rce_master.state.model import DEFAULT_ROLE, ROLES

DEFAULT_MASTER = "http://127.0.0.1:9000/"
COLUMNS = {
    "users": ["name", "role"],
    "robots": ["user", "robot", "endpoint", "since", "relay", "relay_since"],
    "containers": ["user", "ctag", "owner", "host", "group", "state", "sandbox", "data"],
    "nodes": ["user", "ctag", "ntag", "pkg", "exe", "status", "code", "signal"],
    "parameters": ["user", "ctag", "name", "value"],
    "interfaces": ["user", "tag", "type", "class", "addr", "connections"],
    "connections": ["user", "tagA", "tagB"],
    "tasksets": ["tid", "kind", "name", "host", "zone", "capacity", "absent", "robots", "containers", "cpu_load",
                 "mem_load", "sandbox"],
}


PLACEMENT_COLUMNS = ["user", "ctag", "runs", "best", "move", "pinned", "spare", "misses", "node_ms", "why"]
MOVE_COLUMNS = ["when", "user", "ctag", "from", "to", "spare", "switch_s", "drain_s", "why"]

def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float) and value > 1e9:   # timestamps
        return time.strftime("%H:%M:%S", time.localtime(value))
    if isinstance(value, (dict, list)):
        return json.dumps(value, separators=(",", ":"))
    return str(value)


def table(title: str, rows: list[dict], columns: list[str]) -> Table:
    t = Table(title=f"{title} ({len(rows)})", title_justify="left")
    for c in columns:
        t.add_column(c)
    for r in rows:
        t.add_row(*(_cell(r.get(c)) for c in columns))
    return t


TOP_COLUMNS = ["container", "node", "state", "cpu_percent", "rss_mib", "processes", "msgs_in", "msgs_out",
               "bytes_in", "bytes_out", "dropped", "restarts", "limits"]


def top_rows(client: AdminClient) -> list[dict]:
    """One row per container (its whole use: every process, interface traffic) followed by one
    row per node (its process tree, its bus traffic: in = published by the node)."""
    rows = []
    for c in client.request("GET", "/api/containers"):
        name = f"{c['user']}/{c['ctag']}"
        if c["state"] != "running":
            rows.append({"container": name, "state": c["state"]})
            continue
        try:
            s = client.request("GET", f"/api/containers/{c['user']}/{c['ctag']}/stats")
        except RCEError as e:
            rows.append({"container": name, "state": str(e)})
            continue
        limits = s.get("limits") or {}
        rows.append({"container": name, "state": s.get("sandbox") or c["state"], **_flatten_stats(s),
                     "restarts": (s.get("nodes") or {}).get("restarts"),
                     "limits": " ".join(f"{k}={v:g}" for k, v in sorted(limits.items())
                                        if isinstance(v, (int, float)))})
        for ntag, n in sorted((s.get("per_node") or {}).items()):
            if n.get("running"):
                state = "running"
            else:
                ex = n.get("last_exit") or {}
                state = "exited" + (f" signal {ex['signal']}" if ex.get("signal") else
                                    f" code {ex['code']}" if ex.get("code") is not None else "")
            rows.append({"container": "", "node": ntag, "state": state, **_flatten_stats(n),
                         "restarts": n.get("restarts")})
    return rows


def top_table(client: AdminClient) -> Table:
    return table("containers", top_rows(client), TOP_COLUMNS)


def _flatten_stats(stats: dict) -> dict:
    out = {}
    for k in ("cpu_percent", "rss_mib", "processes", "msgs_in", "msgs_out", "bytes_in", "bytes_out", "dropped"):
        v = stats.get(k)
        if isinstance(v, dict):           # dropped: {interfaces, bus}
            v = sum(x for x in v.values() if isinstance(x, (int, float)))
        if isinstance(v, float):
            v = round(v, 1)
        out[k] = v
    return out


def _read_password(from_stdin: bool) -> str:
    if from_stdin:
        pw = sys.stdin.readline().rstrip("\n")
    else:
        pw = getpass.getpass("password: ")
        if getpass.getpass("again: ") != pw:
            raise RequestError("the passwords differ")
    if not pw:
        raise RequestError("the password must not be empty")
    return pw


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="rce-console", description="Inspect and manage an rce master.")
    p.add_argument("--master", action="append", default=None, metavar="URL[,URL...]",
                   help=f"master URL; repeat it (or separate URLs by commas) for several masters "
                        f"(default {DEFAULT_MASTER})")
    p.add_argument("--admin-token", default=None, help="admin token (default: RCE_ADMIN_TOKEN or the token file)")
    p.add_argument("--admin-token-file", type=Path, default=None,
                   help="the master's admin token file (default ~/.config/rce/admin-token)")
    p.add_argument("--json", action="store_true", help="print JSON instead of tables")
    sub = p.add_subparsers(dest="cmd", required=True)
    for name in COLUMNS:
        sub.add_parser(name, help=f"list {name}")
    sub.add_parser("leader", help="which master leads, and the one that answered")
    u = sub.add_parser("user", help="add or delete a user, or give one a role")
    u.add_argument("action", choices=["add", "del", "role"])
    u.add_argument("name")
    u.add_argument("--role", choices=ROLES, default=None,
                   help=f"viewer: reads the fleet's tasks, metrics and page; operator: also adds and cancels tasks; "
                        f"admin: also revokes others' tokens (default for add: {DEFAULT_ROLE})")
    u.add_argument("--password-stdin", action="store_true", help="read the password from stdin")
    u.add_argument("--file", type=Path, help="offline: edit this --users file instead of asking the master")
    lg = sub.add_parser("logs", help="a node's kept stdout and stderr")
    lg.add_argument("user")
    lg.add_argument("ctag")
    lg.add_argument("ntag")
    c = sub.add_parser("container", help="container operations")
    c.add_argument("action", choices=["resize", "move"])
    c.add_argument("user")
    c.add_argument("ctag")
    c.add_argument("--cpu", type=float, help="cores (may be fractional)")
    c.add_argument("--memory", type=float, help="MiB")
    c.add_argument("--pids", type=int, help="the most tasks (processes and threads), pids.max")
    c.add_argument("--size", type=float, help="size class in slots (the original RCE's; recorded only)")
    c.add_argument("--to", metavar="HOST", help="move: the container host (name or tid), make-before-break")
    pl = sub.add_parser("placement", help="where each container runs, where the placer would put it and why; "
                                          "pin one")
    pl.add_argument("action", nargs="?", choices=["pin", "moves"], help="pin USER CTAG ZONE; moves: the last moves")
    pl.add_argument("pin_args", nargs="*", metavar="USER CTAG ZONE")
    t = sub.add_parser("top", help="per-container resource use, refreshing")
    t.add_argument("--interval", type=float, default=2.0, help="seconds between refreshes")
    t.add_argument("--once", action="store_true", help="print one table and exit")
    return p


def run(args: argparse.Namespace, out: Console) -> None:
    if args.cmd == "user" and args.file:
        _user_file(args)
        return
    client = AdminClient.from_options(args.master or DEFAULT_MASTER, args.admin_token, args.admin_token_file)
    if args.cmd == "leader":
        answer = client.request("GET", "/api/leader")
        if args.json:
            print(json.dumps(answer, indent=1))
        else:
            leader = answer.get("leader") or {}
            if answer.get("leading") and not leader:
                out.print(f"{client.base} leads: it is the only master")
                return
            out.print(f"leader: {leader.get('http', '(none elected now)')} (control {leader.get('control', '-')}); "
                      f"asked {client.base}, which {'leads' if answer.get('leading') else 'stands by'}")
    elif args.cmd in COLUMNS:
        rows = client.request("GET", f"/api/{args.cmd}")
        if args.json:
            print(json.dumps(rows, indent=1))
        else:
            out.print(table(args.cmd, rows, COLUMNS[args.cmd]))
    elif args.cmd == "user":
        _user(args, client, out)
    elif args.cmd == "logs":
        logs = client.request("GET", f"/api/containers/{args.user}/{args.ctag}/logs/{args.ntag}")
        for stream in ("stdout", "stderr"):
            for line in logs.get(stream, []):
                print(f"{stream}: {line}")
    elif args.cmd == "container" and args.action == "move":
        if not args.to:
            raise RequestError("container move USER CTAG --to HOST")
        host = int(args.to) if args.to.isdigit() else args.to
        m = client.request("POST", f"/api/containers/{args.user}/{args.ctag}/move", {"host": host})
        out.print(f"container {args.ctag!r} moved from {m['from']} to {m['to']}: built in {m['make_s']:.2f} s, "
                  f"switched in {m['switch_s'] * 1e3:.1f} ms, old copy drained in {m['drain_s']:.2f} s")
    elif args.cmd == "container":
        limits = {k: getattr(args, k) for k in ("cpu", "memory", "pids", "size") if getattr(args, k) is not None}
        if not limits:
            raise RequestError("give at least one of --cpu, --memory, --pids, --size")
        res = client.request("POST", f"/api/containers/{args.user}/{args.ctag}/resize", limits)
        out.print(f"container {args.ctag!r} resized: {json.dumps(res)}")
    elif args.cmd == "placement":
        if args.action == "pin":
            if len(args.pin_args) != 3:
                raise RequestError("placement pin USER CTAG ZONE (ZONE: cloud, edge, robot or auto)")
            user, ctag, zone = args.pin_args
            res = client.request("POST", f"/api/placement/{user}/{ctag}", {"pin": zone})
            out.print(f"container {user}/{ctag}: " + (f"pinned to {res['pinned']}" if res.get("pinned")
                                                      else "unpinned; the placer decides"))
            if res.get("moved"):
                m = res["moved"]
                out.print(f"moved from {m['from']} to {m['to']} (switched in {m['switch_s'] * 1e3:.1f} ms)")
            return
        if args.action == "moves":
            rows = client.request("GET", "/api/placement/moves")
            if args.json:
                print(json.dumps(rows, indent=1))
            else:
                for m in rows:
                    m["when"] = time.strftime("%H:%M:%S", time.localtime(m["t"]))
                out.print(table("moves", rows, MOVE_COLUMNS))
            return
        rows = client.request("GET", "/api/placement")
        if args.json:
            print(json.dumps(rows, indent=1))
        else:
            out.print(table("placement", rows, PLACEMENT_COLUMNS))
    elif args.cmd == "top":
        if args.once:
            if args.json:
                print(json.dumps(top_rows(client), indent=1))
            else:
                out.print(top_table(client))
            return
        with Live(top_table(client), console=out, refresh_per_second=4) as live:
            while True:
                time.sleep(args.interval)
                live.update(top_table(client))


def _user(args: argparse.Namespace, client: AdminClient, out: Console) -> None:
    """``user add|role|del NAME`` on the master."""
    if args.action == "add":
        u = client.request("POST", "/api/users", {"name": args.name, "role": args.role or DEFAULT_ROLE,
                                                  "password": _read_password(args.password_stdin)})
        out.print(f"user {args.name!r} added, is {u['role']}")
    elif args.action == "role":
        u = client.request("POST", f"/api/users/{args.name}", {"role": _role_given(args)})
        out.print(f"user {args.name!r} is now {u['role']}")
    else:
        client.request("DELETE", f"/api/users/{args.name}")
        out.print(f"user {args.name!r} deleted")


def _user_file(args: argparse.Namespace) -> None:
    """Offline: add or delete a user in a ``--users`` file, by the master's own rules (imported here:
    the master's state and the protocol's models, which the other commands do not load)."""
    from rce_master.state.master_state import MasterState
    from rce_master.auth.users import UsersFile
    users, state = UsersFile(args.file), MasterState()
    users.load(state)
    if args.action == "add" and args.name in state.users:      # before asking for the password
        raise RequestError(f"{args.file}: user {args.name!r} already exists")
    try:
        if args.action == "add":
            state.add_user(args.name, _read_password(args.password_stdin), args.role or DEFAULT_ROLE)
        elif args.action == "role":
            state.set_user_role(args.name, _role_given(args))
        else:
            state.del_user(args.name)
    except RCEError as e:
        raise RequestError(f"{args.file}: {e}") from None
    users.save(state)
    done = "deleted" if args.action == "del" else f"is {state.users[args.name].role}"
    print(f"{args.file}: user {args.name!r} {'added, ' if args.action == 'add' else ''}{done}")


def _role_given(args: argparse.Namespace) -> str:
    if not args.role:
        raise RequestError(f"user role {args.name}: give --role ({', '.join(ROLES)})")
    return args.role


def main(argv: list[str] | None = None) -> None:
    args = parser().parse_args(argv)
    try:
        run(args, Console(width=None if sys.stdout.isatty() else 240))
    except RCEError as e:
        print(f"rce-console: {e}", file=sys.stderr)
        sys.exit(1)
    except KeyboardInterrupt:
        pass
