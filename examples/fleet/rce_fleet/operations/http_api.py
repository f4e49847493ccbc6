"""The fleet's JSON HTTP API and Prometheus metrics, on ``rce-fleet serve``'s web server.

Routes (the fleet manager's :class:`~rce_fleet.operations.tasks_client.TaskChannel` does the work; the
role each needs in brackets, :mod:`rce_fleet.operations.api_auth`; the models and the OpenAPI document:
:mod:`rce_fleet.operations.api_models`):

==============================  =====================================================================
``POST /api/login``             ``{"user", "password", "ttl_s"?}`` -> ``{"token", "token_type":
                                "Bearer", "expires_in", "user", "role", "survives_restart": false}``;
                                401 wrong user or password (and the fleet's own internal user, never
                                a person's login), 429 (``Retry-After``) after repeated failures [anyone]
``POST /api/logout``            revoke the bearer token the request carries [viewer]
``DELETE /api/tokens/USER``     revoke every token of USER -> ``{"revoked": n}``, and end its page
                                sessions [admin]
``/api/users[/NAME]``           the master's users: list, add, a role or password, remove
                                (:mod:`rce_fleet.operations.api_users`) [admin]
``POST /api/tasks``             body ``{"errands": ["pick1", "42"], "priority": 0, "earliest_start_s": 0,
                                "deadline_s": 0, "id": ""}`` -> 201 and the task, its ``source``
                                ``http:USER``; 400 (bad request), 409 (the id exists); a field not
                                listed here is a 400 [operator]
``GET /api/tasks``              the task list: ``tasks`` (open, then recently closed), ``robots`` (each
                                robot's task, activity, battery), counts and times [viewer]
``GET /api/tasks/ID``           one task, 404 when the fleet does not know it [viewer]
``DELETE /api/tasks/ID``        cancel it -> 200 and the task, its ``cancelled_by`` ``http:USER``; 404
                                unknown, 409 already closed [operator]
``GET /api/openapi.json``       the OpenAPI 3.1 document; its server is ``/`` (relative: the ``Host``
                                header names nothing in it) [anyone]
``GET /metrics``                Prometheus text: tasks by state, queue length, task times, per-robot
                                utilisation, battery and tasks done [viewer; anyone with
                                ``metrics_public``]
==============================  =====================================================================

A credential is ``Authorization: Bearer TOKEN`` (from ``POST /api/login``) or ``Authorization: Basic``
(a user and password of the master, over TLS only: in clear HTTP it is refused). No credential, or a
wrong, expired or revoked one: 401 with ``WWW-Authenticate``; a role below the route's: 403. Every
refusal is ``{"error", "code"}`` (:mod:`rce_fleet.operations.api_errors`: aiohttp's own 404, 405, 413 and any
500 too), and quotes no more than a short prefix of anything the client sent. A body is JSON within the
engine's bounds (:mod:`rce_fleet.operations.api_body`: 64 levels, UTF-8 without lone surrogates, numbers
that fit a double), else a 400 naming what was wrong. Passwords are checked by the master (``POST /api/auth``
of its admin API), which throttles repeated failures per user and client address as it does robots' logins.

A task is ``{"id", "errands", "cells", "priority", "state", "robot", "next_errand", "reason",
"source", "cancelled_by", "created", "earliest_start", "deadline", "assigned", "active", "finished",
"reached"}`` (times in fleet seconds, 0: not reached; ``reached``: the time each errand was reached, in
order). A request the fleet does not answer within 10 s is a 504.
"""
from __future__ import annotations

import time
from typing import Awaitable, Callable

from aiohttp import web

from rce.plumbing.errors import AuthError, RCEError, RequestError, Throttled
from rce.protocol.limits import short_repr

from .api_auth import DEFAULT_TTL_S, Identity, TokenBook, allows, parse_authorization
from .api_body import read_model
from .api_errors import ApiRefusal, error_response
from .api_users import MasterUsers, add_user_routes
from .api_models import LoginAnswer, LoginRequest, TaskRequest, openapi_document
from .tasks_client import TaskChannel, TaskRefused

__all__ = ["ApiAuth", "add_routes", "master_password_check", "prometheus_text"]

STATUS = {"bad_request": 400, "not_found": 404, "conflict": 409, "timeout": 504}
REALM = 'realm="rce fleet"'

# (user, password, client address) -> the user's role; raises AuthError (wrong) or Throttled (backing off)
PasswordCheck = Callable[[str, str, str], Awaitable[str]]


def master_password_check(client) -> MasterUsers:
    """The :data:`PasswordCheck` of a master: ``POST /api/auth`` through ``client``, an
    :class:`rce.tools.admin_client.AdminClient` holding the master's admin token. It is a
    :class:`~rce_fleet.operations.api_users.MasterUsers`, so an :class:`ApiAuth` made with it also lets an admin
    manage the master's users (``/api/users``)."""
    return MasterUsers(client)


class ApiAuth:
    """Who a request comes from and whether its role is enough: bearer tokens of a
    :class:`~rce_fleet.operations.api_auth.TokenBook` (lifetime ``ttl_s``), else HTTP Basic over TLS,
    checked by ``check_password``; ``metrics_public``: ``/metrics`` needs no credential; ``internal``: user
    names that are never a person's login (the fleet's own user): refused as a wrong password is, unasked;
    ``users``: the master's users for an admin to manage (``/api/users``; by default ``check_password`` when it
    is a :class:`~rce_fleet.operations.api_users.MasterUsers`, else none). ``on_revoke``: callables given a
    user whose tokens were all revoked (the page's door ends that user's sessions)."""

    def __init__(self, check_password: PasswordCheck, *, ttl_s: float = DEFAULT_TTL_S, metrics_public: bool = False,
                 clock: Callable[[], float] = time.monotonic, internal: frozenset[str] = frozenset(),
                 users: MasterUsers | None = None):
        self.check_password, self.metrics_public, self.clock = check_password, metrics_public, clock
        self.internal = frozenset(internal)
        self.book = TokenBook(ttl_s)
        self.users = users if users is not None else check_password if isinstance(check_password, MasterUsers) \
            else None
        self.on_revoke: list[Callable[[str], None]] = []

    def revoke_user(self, user: str) -> int:
        """End every token of ``user`` and tell :attr:`on_revoke`; returns how many tokens ended."""
        n = self.book.revoke_user(user)
        for tell in self.on_revoke:
            tell(user)
        return n

    def bearer(self, token: str, needed: str) -> Identity:
        """The identity of bearer ``token`` when its role allows ``needed`` (another door's check, e.g. the
        Foxglove port's); raises :class:`~rce.plumbing.errors.AuthError` (unknown, expired or revoked) or
        :class:`~rce.plumbing.errors.RequestError` (a lower role)."""
        who = self.book.check(token, self.clock()) if token else None
        if who is None:
            raise AuthError("a bearer token from POST /api/login is needed (unknown, expired or revoked)")
        if not allows(who.role, needed):
            raise RequestError(f"user {who.user!r} is {who.role}: this needs {needed} or above")
        return who

    def _unauthorized(self, req: web.Request, text: str) -> ApiRefusal:
        schemes = f"Bearer {REALM}" + (f", Basic {REALM}" if req.secure else "")
        return ApiRefusal(401, "unauthorized", text, {"WWW-Authenticate": schemes})

    async def password(self, req: web.Request, user: str, password: str) -> str:
        """The role of ``user`` if ``password`` is right (the master checks it); raises :class:`ApiRefusal`
        401 (wrong), 429 (backing off) or 503 (the master cannot be asked)."""
        if user in self.internal:
            raise self._unauthorized(req, "invalid user or password")
        try:
            return await self.check_password(user, password, req.remote or "")
        except Throttled as e:
            raise ApiRefusal(429, "throttled", f"too many failed logins; retry after {e.retry_after:g} s",
                          {"Retry-After": str(max(1, round(e.retry_after)))}) from None
        except AuthError:
            raise self._unauthorized(req, "invalid user or password") from None
        except RCEError as e:
            raise ApiRefusal(503, "unavailable", f"cannot check the password at the master: {e.message}") from None

    async def require(self, req: web.Request, role: str) -> Identity:
        """The identity of ``req`` when its role allows ``role``; raises :class:`ApiRefusal` 401 (no,
        malformed, wrong, expired or revoked credential; Basic without TLS) or 403 (a lower role)."""
        try:
            cred = parse_authorization(req.headers.get("Authorization", ""))
        except ValueError as e:
            raise self._unauthorized(req, str(e)) from None
        if cred is None:
            raise self._unauthorized(req, "a credential is needed: Authorization: Bearer TOKEN (POST /api/login)"
                                          + (" or Basic" if req.secure else ""))
        kind, a, b = cred
        if kind == "bearer":
            who = self.book.check(a, self.clock())
            if who is None:
                raise self._unauthorized(req, "the token is unknown, expired or revoked; log in again")
        elif not req.secure:
            raise self._unauthorized(req, "HTTP Basic only over TLS (https://); over http:// log in with "
                                          "POST /api/login and send the token")
        else:
            who = Identity(a, await self.password(req, a, b), "basic")
        if not allows(who.role, role):
            raise ApiRefusal(403, "forbidden", f"user {who.user!r} is {who.role}: this needs {role} or above")
        return who


def add_routes(app: web.Application, channel: TaskChannel, auth: ApiAuth) -> None:
    """Add the task API, the login and ``/metrics`` (module docstring) to ``app``; ``auth`` says who may."""

    async def login(req: web.Request) -> web.Response:
        lr = await read_model(req, LoginRequest)
        role = await auth.password(req, lr.user, lr.password)
        token, life = auth.book.issue(lr.user, role, auth.clock(), lr.ttl_s)
        return web.json_response(LoginAnswer(token=token, expires_in=life, user=lr.user, role=role).model_dump(),
                                 headers={"Cache-Control": "no-store"})

    async def logout(req: web.Request) -> web.Response:
        who = await auth.require(req, "viewer")
        revoked = who.via == "bearer" and auth.book.revoke(req.headers["Authorization"].split(None, 1)[1].strip())
        return web.json_response({"revoked": int(revoked)})

    async def revoke_user(req: web.Request) -> web.Response:
        await auth.require(req, "admin")
        return web.json_response({"revoked": auth.revoke_user(req.match_info["user"])})

    async def post(req: web.Request) -> web.Response:
        who = await auth.require(req, "operator")
        t = await read_model(req, TaskRequest)
        try:
            task = await channel.add(t.errands, priority=t.priority, earliest_start_s=t.earliest_start_s,
                                     deadline_s=t.deadline_s, task_id=t.id, source=f"http:{who.user}")
        except TaskRefused as e:
            return error_response(STATUS.get(e.code, 400), e.reason)
        return web.json_response(task, status=201, headers={"Location": f"/api/tasks/{task['id']}"})

    async def listing(req: web.Request) -> web.Response:
        await auth.require(req, "viewer")
        return web.json_response(_public(channel.latest))

    async def one(req: web.Request) -> web.Response:
        await auth.require(req, "viewer")
        t = channel.get(req.match_info["id"])
        if t is None:
            return error_response(404, f"no task {short_repr(req.match_info['id'])} among the open and recent tasks")
        return web.json_response(t)

    async def delete(req: web.Request) -> web.Response:
        who = await auth.require(req, "operator")
        try:
            return web.json_response(await channel.cancel(req.match_info["id"], source=f"http:{who.user}"))
        except TaskRefused as e:
            return error_response(STATUS.get(e.code, 400), e.reason)

    async def openapi(req: web.Request) -> web.Response:
        return web.json_response(openapi_document("/", auth.metrics_public))

    async def metrics(req: web.Request) -> web.Response:
        if not auth.metrics_public:
            await auth.require(req, "viewer")
        return web.Response(text=prometheus_text(channel.latest), content_type="text/plain", charset="utf-8",
                            headers={"Cache-Control": "no-store"})

    app.router.add_post("/api/login", login)
    app.router.add_post("/api/logout", logout)
    app.router.add_delete("/api/tokens/{user}", revoke_user)
    app.router.add_post("/api/tasks", post)
    app.router.add_get("/api/tasks", listing)
    app.router.add_get("/api/tasks/{id}", one)
    app.router.add_delete("/api/tasks/{id}", delete)
    app.router.add_get("/api/openapi.json", openapi)
    app.router.add_get("/metrics", metrics)
    if auth.users is not None:
        add_user_routes(app, auth, auth.users)


def _public(task_list: dict | None) -> dict:
    tl = dict(task_list or {})
    tl.pop("answers", None)
    tl.pop("header", None)
    return tl


def prometheus_text(task_list: dict | None) -> str:
    """The Prometheus exposition text of a ``fleet/TaskList`` (JSON form); empty metrics
    before the first one."""
    tl = task_list or {}
    lines = []

    def metric(name: str, kind: str, help_: str, samples: list[tuple[str, float]]) -> None:
        lines.append(f"# HELP {name} {help_}")
        lines.append(f"# TYPE {name} {kind}")
        lines.extend(f"{name}{labels} {value:g}" for labels, value in samples)

    metric("rce_fleet_tasks_total", "counter", "Tasks closed, by final state.",
           [(f'{{state="{s}"}}', float(tl.get(s, 0))) for s in ("done", "failed", "cancelled")])
    states = {}
    for t in tl.get("tasks", []):
        if t["state"] in ("queued", "assigned", "active"):
            states[t["state"]] = states.get(t["state"], 0) + 1
    metric("rce_fleet_tasks_open", "gauge", "Open tasks, by state.",
           [(f'{{state="{s}"}}', float(states.get(s, 0))) for s in ("queued", "assigned", "active")])
    metric("rce_fleet_tasks_deadline_missed_total", "counter", "Tasks that missed their deadline.",
           [("", float(tl.get("deadline_missed", 0)))])
    metric("rce_fleet_task_seconds", "gauge", "Seconds from creation to done over done tasks (mean, p95).",
           [('{stat="mean"}', float(tl.get("mean_s", 0.0))), ('{stat="p95"}', float(tl.get("p95_s", 0.0)))])
    robots = tl.get("robots", [])
    metric("rce_fleet_robot_utilisation", "gauge", "Share of a robot's time on a task.",
           [(f'{{robot="{r["robot"]}"}}', r["busy_s"] / r["since_s"] if r.get("since_s") else 0.0) for r in robots])
    metric("rce_fleet_robot_battery_percent", "gauge", "A robot's battery level (-1: not reported).",
           [(f'{{robot="{r["robot"]}"}}', float(r.get("battery_pct", -1.0))) for r in robots])
    metric("rce_fleet_robot_tasks_done_total", "counter", "Tasks a robot finished.",
           [(f'{{robot="{r["robot"]}"}}', float(r.get("tasks_done", 0))) for r in robots])
    metric("rce_fleet_robot_charges_total", "counter", "Charging sessions a robot began.",
           [(f'{{robot="{r["robot"]}"}}', float(r.get("charges", 0))) for r in robots])
    metric("rce_fleet_robot_stalled_seconds", "gauge",
           "Fleet seconds a robot holding work has made no progress (0: it moves; an alert from 60 s).",
           [(f'{{robot="{r["robot"]}"}}', float(r.get("stalled_s", 0.0))) for r in robots])
    metric("rce_fleet_robot_stalls_total", "counter", "Times a robot holding work was found stalled.",
           [(f'{{robot="{r["robot"]}"}}', float(r.get("stalls", 0))) for r in robots])
    return "\n".join(lines) + "\n"
