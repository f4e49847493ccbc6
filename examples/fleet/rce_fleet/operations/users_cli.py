"""``rce-fleet users``: an admin manages the master's users of a running ``rce-fleet serve``.

It speaks the fleet's HTTP API (``/api/users``, :mod:`rce_fleet.operations.api_users`) at ``--api URL`` (or
``$RCE_FLEET_API``: serve's page URL) as ``--user`` (default ``$RCE_USER``, else ``admin``, the first admin),
with ``--password`` (or ``$RCE_PASSWORD``) or ``--token`` (or ``$RCE_FLEET_TOKEN``); ``--ca-file`` (or
``$RCE_CA_FILE``) trusts an https:// API's CA::

    rce-fleet users [list] [--json]
    rce-fleet users add NAME [--role viewer|operator|admin] [--new-password-stdin]
    rce-fleet users role NAME --role viewer|operator|admin
    rce-fleet users password NAME [--new-password-stdin]
    rce-fleet users remove NAME

The new password of ``add`` and ``password`` is the first line of stdin with ``--new-password-stdin``, else it
is asked twice on the terminal. A new role or password, and a removal, end the user's tokens and page
sessions: the user logs in again. Exit codes: 0 done, 1 refused (the reason on stderr: a role below admin,
no such user, the last admin, ...), 2 bad flags, 3 the API cannot be reached.
"""
from __future__ import annotations

import argparse
import asyncio
import getpass
import json
import os
import sys

from .api_client import ApiRefused, ApiUnreachable, Caller, call, part, report
from .api_models import MIN_PASSWORD

__all__ = ["add_users_parser", "run_users"]

ROLES = ("viewer", "operator", "admin")
EXIT_OK, EXIT_USAGE = 0, 2
PROG = "rce-fleet users"


def add_users_parser(sub) -> None:
    """Add the ``users`` sub-command to ``rce-fleet``'s sub-parsers ``sub``."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--api", default=os.environ.get("RCE_FLEET_API"), metavar="URL",
                        help="rce-fleet serve's page URL (default $RCE_FLEET_API)")
    common.add_argument("--user", default=os.environ.get("RCE_USER", "admin"),
                        help="an admin (default $RCE_USER, else admin)")
    common.add_argument("--password", default=os.environ.get("RCE_PASSWORD"),
                        help="its password (default $RCE_PASSWORD)")
    common.add_argument("--token", default=os.environ.get("RCE_FLEET_TOKEN"),
                        help="a bearer token of POST /api/login instead (default $RCE_FLEET_TOKEN)")
    common.add_argument("--ca-file", default=None, metavar="FILE",
                        help="with an https:// --api: the CA that signed its certificate (default $RCE_CA_FILE)")
    common.add_argument("--json", action="store_true", help="print JSON")
    common.add_argument("--timeout", type=float, default=30.0, metavar="S", help="wall s for the whole exchange")
    u = sub.add_parser("users", parents=[common], help="list, add, change or remove the users of a running "
                                                       "rce-fleet serve (an admin's, through its HTTP API)")
    us = u.add_subparsers(dest="action")     # none: list (an action's flags go after it)
    u.set_defaults(action="list")
    us.add_parser("list", parents=[common], help="the users and their roles")
    a = us.add_parser("add", parents=[common], help="add a user (its password asked, or from stdin)")
    a.add_argument("name")
    a.add_argument("--role", choices=ROLES, default="operator", help="its role (default operator)")
    a.add_argument("--new-password-stdin", action="store_true", help="read its password from stdin's first line")
    r = us.add_parser("role", parents=[common], help="give a user a role (its tokens end)")
    r.add_argument("name")
    r.add_argument("--role", choices=ROLES, required=True)
    p = us.add_parser("password", parents=[common], help="give a user a new password (its tokens end)")
    p.add_argument("name")
    p.add_argument("--new-password-stdin", action="store_true", help="read it from stdin's first line")
    d = us.add_parser("remove", parents=[common], help="remove a user (its tokens end)")
    d.add_argument("name")


def _new_password(args) -> str:
    if args.new_password_stdin:
        return sys.stdin.readline().rstrip("\r\n")
    pw = getpass.getpass(f"password for {args.name}: ")
    if getpass.getpass("again: ") != pw:
        raise ValueError("the two passwords differ")
    return pw


def _request(args) -> tuple[str, str, dict | None]:
    if args.action == "list":
        return "GET", "api/users", None
    path = f"api/users/{part(args.name)}"
    if args.action == "add":
        return "POST", "api/users", {"name": args.name, "password": _new_password(args), "role": args.role}
    if args.action == "role":
        return "PATCH", path, {"role": args.role}
    if args.action == "password":
        return "PATCH", path, {"password": _new_password(args)}
    return "DELETE", path, None


def _print(args, out: dict) -> None:
    if args.json:
        print(json.dumps(out, indent=1))
    elif args.action == "list":
        for u in out.get("users", []):
            print(f"{u['name']:<24} {u['role']}")
    else:
        did = {"add": f"added, is {out.get('role')}", "role": f"is now {out.get('role')}",
               "password": "has a new password", "remove": "removed"}[args.action]
        ended = f"; {out['revoked']} token(s) ended" if out.get("revoked") else ""
        print(f"user {out.get('name')!r} {did}{ended}")


def run_users(args) -> int:
    """Run ``rce-fleet users ...`` (module docstring); returns the exit code."""
    if not args.api:
        print(f"{PROG}: give --api URL (rce-fleet serve's page URL) or set $RCE_FLEET_API", file=sys.stderr)
        return EXIT_USAGE
    if not (args.token or args.password):
        print(f"{PROG}: give --password, $RCE_PASSWORD or --token for {args.user!r}", file=sys.stderr)
        return EXIT_USAGE
    try:
        method, path, body = _request(args)
    except (ValueError, EOFError) as e:
        print(f"{PROG}: {e or 'no password given'}", file=sys.stderr)
        return EXIT_USAGE
    if body and "password" in body and len(body["password"]) < MIN_PASSWORD:
        print(f"{PROG}: a password has {MIN_PASSWORD} characters at least", file=sys.stderr)
        return EXIT_USAGE
    who = Caller(args.api, args.user, args.password, args.token, args.ca_file, args.timeout)
    try:
        out = asyncio.run(call(who, method, path, body))
    except (ApiRefused, ApiUnreachable) as e:
        return report(PROG, e)
    _print(args, out)
    return EXIT_OK
