"""``rce-fleet task add|list|get|cancel``: the operators' task API from a shell.

With ``--api URL`` (or ``$RCE_FLEET_API``) it speaks the fleet's HTTP task API
(:mod:`rce_fleet.operations.http_api`) as the user ``--user``: with ``--token`` (or
``$RCE_FLEET_TOKEN``), else it logs in with ``--password`` (or ``$RCE_PASSWORD``) for a short-lived
token and logs out after; the user's role decides (a viewer may list and get, an operator also add
and cancel), and the task records ``http:USER``. ``--ca-file`` (or ``$RCE_CA_FILE``) trusts an
https:// API's CA.

Without it, it logs in at the master as an RCE client of the fleet container's own user (robotID
``taskCli-XXXXXX``, like the page), attaches a :class:`rce_fleet.operations.tasks_client.TaskChannel`
to the fleet container, sends one request, prints the answer and leaves (removing the interfaces it
added)::

    rce-fleet task add pick1 drop1 --priority 2 --api http://127.0.0.1:8000/ --user alice
    rce-fleet task add pick1 drop1 --priority 2 --master http://127.0.0.1:PORT/
    rce-fleet task list [--json]
    rce-fleet task get T3
    rce-fleet task cancel T3

Exit codes: 0 done, 1 the fleet refused the request (its reason on stderr; also a wrong
credential or a role below the request's), 2 bad flags, 3 the fleet cannot be reached (login,
container, no answer).
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import secrets
import sys

from ..configs import FLEET_CTAG, PASSWORD, USER

__all__ = ["add_task_parser", "run_task"]

EXIT_OK, EXIT_REFUSED, EXIT_USAGE, EXIT_UNREACHABLE = 0, 1, 2, 3
DEFAULT_MASTER = "http://127.0.0.1:9000/"


def add_task_parser(sub) -> None:
    """Add the ``task`` sub-command to ``rce-fleet``'s sub-parsers ``sub``."""
    t = sub.add_parser("task", help="add, list, get or cancel the fleet's tasks (logs in as an RCE client)")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--master", default=os.environ.get("RCE_MASTER", DEFAULT_MASTER), metavar="URL",
                        help="the master's login URL (default $RCE_MASTER or %(default)s; rce-fleet serve prints it)")
    common.add_argument("--api", default=os.environ.get("RCE_FLEET_API"), metavar="URL",
                        help="the fleet's HTTP task API (rce-fleet serve's page URL; default $RCE_FLEET_API); "
                             "without it: an RCE client at --master")
    common.add_argument("--user", default=os.environ.get("RCE_USER", USER),
                        help=f"user (default $RCE_USER, else {USER})")
    common.add_argument("--password", default=os.environ.get("RCE_PASSWORD", PASSWORD),
                        help="password (default $RCE_PASSWORD, else rce-master --dev's)")
    common.add_argument("--token", default=os.environ.get("RCE_FLEET_TOKEN"),
                        help="with --api: a bearer token from POST /api/login instead of the password "
                             "(default $RCE_FLEET_TOKEN)")
    common.add_argument("--ca-file", default=None, metavar="FILE",
                        help="with an https:// --api: the CA that signed its certificate (default $RCE_CA_FILE)")
    common.add_argument("--container", default=FLEET_CTAG, metavar="CTAG",
                        help=f"fleet container (default {FLEET_CTAG})")
    common.add_argument("--json", action="store_true", help="print JSON")
    common.add_argument("--timeout", type=float, default=30.0, metavar="S", help="wall s for login and answer")
    ts = t.add_subparsers(dest="action", required=True)
    a = ts.add_parser("add", parents=[common], help="queue a task: errands in order (cell numbers or place names)")
    a.add_argument("errands", nargs="+", metavar="ERRAND")
    a.add_argument("--priority", type=float, default=0.0, help="higher first (default 0)")
    a.add_argument("--start-in", type=float, default=0.0, metavar="S",
                   help="earliest start, fleet time: simulated s from now (--speedup of them a wall second)")
    a.add_argument("--deadline-in", type=float, default=0.0, metavar="S",
                   help="deadline, fleet time: simulated s from now (0: none; --speedup of them a wall second)")
    a.add_argument("--id", default="", help="task id (default: the fleet names it)")
    ts.add_parser("list", parents=[common], help="the open tasks and the most recently closed ones")
    g = ts.add_parser("get", parents=[common], help="one task")
    g.add_argument("id")
    c = ts.add_parser("cancel", parents=[common], help="cancel a queued, assigned or active task")
    c.add_argument("id")


def _line(t: dict) -> str:
    errands = " -> ".join(t.get("errands", []))
    robot = t.get("robot") or "-"
    why = f"  ({t['reason']})" if t.get("reason") else ""
    return f"{t['id']:<10} {t['state']:<10} {robot:<9} prio {t.get('priority', 0):g}  {errands}{why}"


async def _run(args) -> int:
    from rce.plumbing.errors import RCEError
    from rce_client.connection import Connection

    from .tasks_client import TaskChannel, TaskRefused
    robot_id = f"taskCli-{secrets.token_hex(3)}"
    try:
        async with asyncio.timeout(args.timeout):
            conn = await Connection.connect(args.master, args.user, args.password, robot_id, max_lag=0)
    except (RCEError, OSError, TimeoutError) as e:
        why = str(getattr(e, "message", e) or type(e).__name__)
        # the connection's own errors already name the master's URL
        print(f"rce-fleet task: {why}" if args.master in why else
              f"rce-fleet task: cannot log in at {args.master}: {why}", file=sys.stderr)
        return EXIT_UNREACHABLE
    ch = TaskChannel(conn, robot_id, args.container, source=f"cli:{args.user}")
    try:
        try:
            await ch.attach(args.timeout)
        except RCEError as e:
            print(f"rce-fleet task: {e.message}", file=sys.stderr)
            return EXIT_UNREACHABLE
        try:
            if args.action == "add":
                out = await ch.add(args.errands, priority=args.priority, earliest_start_s=args.start_in,
                                   deadline_s=args.deadline_in, task_id=args.id, timeout=args.timeout)
            elif args.action == "cancel":
                out = await ch.cancel(args.id, timeout=args.timeout)
            elif args.action == "get":
                out = ch.get(args.id)
                if out is None:
                    print(f"rce-fleet task: no task {args.id!r} among the fleet's open and recent tasks",
                          file=sys.stderr)
                    return EXIT_REFUSED
            else:
                out = ch.latest
        except TaskRefused as e:
            print(f"rce-fleet task: refused ({e.code}): {e.reason}", file=sys.stderr)
            return EXIT_UNREACHABLE if e.code == "timeout" else EXIT_REFUSED
        _print(args, out)
        return EXIT_OK
    finally:
        await ch.detach()
        await conn.close()


def _print(args, out: dict) -> None:
    if args.json:
        print(json.dumps(out, indent=1))
    elif args.action == "list":
        print(f"queued {out.get('queued', 0)}  done {out.get('done', 0)}  failed {out.get('failed', 0)}  "
              f"cancelled {out.get('cancelled', 0)}")
        for t in out.get("tasks", []):
            print(_line(t))
    else:
        print(_line(out))


async def _run_http(args) -> int:
    """``rce-fleet task`` against the HTTP task API (module docstring)."""
    from .api_client import ApiRefused, ApiUnreachable, Caller, call, part, report
    if args.action == "add":
        method, path, body = "POST", "api/tasks", {"errands": args.errands, "priority": args.priority,
                                                   "earliest_start_s": args.start_in, "deadline_s": args.deadline_in,
                                                   "id": args.id}
    elif args.action == "list":
        method, path, body = "GET", "api/tasks", None
    else:
        method, path, body = "GET" if args.action == "get" else "DELETE", f"api/tasks/{part(args.id)}", None
    who = Caller(args.api, args.user, args.password, args.token, args.ca_file, args.timeout)
    try:
        out = await call(who, method, path, body)
    except (ApiRefused, ApiUnreachable) as e:
        return report("rce-fleet task", e)
    _print(args, out)
    return EXIT_OK


def run_task(args) -> int:
    """Run ``rce-fleet task ...`` (module docstring); returns the exit code."""
    from rce.plumbing.log import setup_logging
    setup_logging()
    import logging
    logging.getLogger("rce.client").setLevel(logging.WARNING)
    return asyncio.run(_run_http(args) if args.api else _run(args))
