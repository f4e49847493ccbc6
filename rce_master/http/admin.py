"""The master's JSON admin API (what rce-console, rce-topic --container and the launcher use,
through :mod:`rce.tools.admin_client`).

All routes need ``Authorization: Bearer TOKEN`` (the master's admin token). Refusals are HTTP
errors with a one-line reason (:mod:`rce_master.server`).

| route | result |
|---|---|
| ``GET /api/state`` | everything (:meth:`MasterState.snapshot`) |
| ``GET /api/{users,robots,containers,nodes,parameters,interfaces,connections,tasksets}`` | one list |
| ``POST /api/users`` ``{name, password, role?}`` / ``DELETE /api/users/{name}`` | add / delete a user |
| ``POST /api/users/{name}`` ``{role}`` | give a user a role (``viewer``, ``operator``, ``admin``) |
| ``POST /api/auth`` ``{user, password, addr}`` | ``{user, role}`` if the password (hex SHA-256) is right; 401, 429 |
| ``GET /api/containers/{user}/{ctag}/bus`` | the container's bus: topics, services, params, nodes |
| ``POST /api/containers/{user}/{ctag}/publish`` ``{topic, type, msg}`` | publish on its bus |
| ``POST /api/containers/{user}/{ctag}/call`` ``{service, request, timeout}`` | call a service on its bus |
| ``POST /api/containers/{user}/{ctag}/sample`` ``{topic, count, timeout}`` | up to count messages |
| ``GET /api/containers/{user}/{ctag}/stats`` | the container's counters from its host |
| ``POST /api/containers/{user}/{ctag}/resize`` ``{cpu?, memory?, pids?, size?, bandwidth?}`` | new limits |
| ``GET /api/containers/{user}/{ctag}/logs/{ntag}`` | a node's kept stdout/stderr |
| ``GET /api/placement`` | per container: where it runs, where the placer would put it and why |
| ``POST /api/placement/{user}/{ctag}`` ``{pin}`` | pin it to ``cloud``, ``edge``, ``robot`` (moved there); ``auto`` |
| ``GET /api/placement/moves`` | the last moves (``{t, user, ctag, from, to, make_s, ...}``, mover.py) |
| ``POST /api/containers/{user}/{ctag}/move`` ``{host, why?, drain_max_s?}`` | move it there, make-before-break |
| ``POST /api/robots/{user}/{robot}/battery`` ``{percent}`` | a robot's charge, for the placer |
| ``GET /api/leader`` | ``{leading, leader, self}``: whether this master leads, the leader's and its own addresses |

``POST /api/auth`` is the robots' password check (:mod:`rce_master.auth.login_guard`: the same back-off per
user and ``addr``, the address the user logs in from, and the same scrypt pool) for another front door
that holds the admin token: the fleet's task API (docs/task-api.md).

A master that stands by (several masters on etcd) answers ``GET /api/state``, the lists and
``/api/leader`` from the state it follows; everything else needs the leader (a change, or a call
on a container's host, whose link only the leader holds) and is refused with 503 and the
leader's URL in the ``X-RCE-Leader`` header (:mod:`rce_master.leadership.office`). A change is answered
once the store has it.
"""
from __future__ import annotations

import hmac

from aiohttp import web

from rce.contract import environment as to_env
from rce.contract import host as to_host
from rce.contract.base import OpArgs, parse
from rce.plumbing.errors import AuthError, RequestError
from rce.protocol import schema
from rce_master.control import Control
from rce_master.state.lifecycle import ContainerState
from rce_master.state.model import DEFAULT_ROLE
from rce_master.auth.login_guard import PasswordCheck
from rce_master.leadership.office import Alone, Office, require_leader
from rce_master.placement.advice import Placement
from rce_master.requests import Request, ResizeContainer
from rce_master.state.master_state import MasterState
from rce_master.auth.users import UsersFile

LISTS = ("users", "robots", "containers", "nodes", "parameters", "interfaces", "connections", "tasksets")
BUS_TIMEOUT = 10.0          # s, a bus op without its own "timeout" (call, sample), and describe/stats/logs
BUS_TIMEOUT_MARGIN = 5.0    # s, added to the op's own timeout: the host answers only once that has passed
# route -> (the op its container's host is asked, method); the request's body is the op's arguments
HOST_OPS: dict[str, tuple[type[OpArgs], str]] = {
    "bus": (to_env.EnvDescribe, "GET"), "publish": (to_env.EnvBusPublish, "POST"), "call": (to_env.EnvBusCall, "POST"),
    "sample": (to_env.EnvBusSample, "POST"), "stats": (to_host.HostStats, "GET")}


class AdminApi:
    """The admin routes onto ``state`` and the task sets (``control``); ``users``: the users file
    kept up to date on user changes (None: none); ``office``: whether this master leads; ``passwords``:
    the master's password check behind ``POST /api/auth`` (None: its own)."""

    def __init__(self, state: MasterState, control: Control, token: str, users: UsersFile | None = None,
                 office: Office | None = None, placement: Placement | None = None,
                 passwords: PasswordCheck | None = None):
        self.state, self.control, self.token, self.users = state, control, token, users
        self.passwords = passwords if passwords is not None else PasswordCheck()
        self.office = office if office is not None else Alone()
        self.placement = placement

    def add_routes(self, app: web.Application) -> None:
        """Add the admin routes to ``app``."""
        app.router.add_get("/api/state", self._state)
        app.router.add_get("/api/leader", self._leader)
        for name in LISTS:
            app.router.add_get(f"/api/{name}", self._one_list)
        app.router.add_post("/api/users", self._add_user)
        app.router.add_delete("/api/users/{name}", self._del_user)
        app.router.add_post("/api/users/{name}", self._set_role)
        app.router.add_post("/api/auth", self._auth)
        base = "/api/containers/{user}/{ctag}"
        for route, (op, method) in HOST_OPS.items():
            app.router.add_route(method, f"{base}/{route}", self._host_op(op))
        app.router.add_get(base + "/logs/{ntag}", self._host_op(to_env.EnvLogs))
        app.router.add_post(base + "/resize", self._resize)
        if self.placement is not None:
            app.router.add_get("/api/placement", self._advice)
            app.router.add_post("/api/placement/{user}/{ctag}", self._pin)
            app.router.add_get("/api/placement/moves", self._moves)
            app.router.add_post(base + "/move", self._move)
            app.router.add_post("/api/robots/{user}/{robot}/battery", self._battery)

    def _check(self, request: web.Request) -> None:
        auth = request.headers.get("Authorization", "")
        if not auth.startswith("Bearer ") or not hmac.compare_digest(auth[7:].strip(), self.token):
            raise AuthError("admin API: missing or wrong bearer token (see --admin-token-file)")

    async def _body(self, request: web.Request) -> dict:
        """Check the token and that this master leads; the JSON body of a POST (else ``{}``)."""
        self._check(request)
        require_leader(self.office, f"{request.method} {request.path}")
        if request.method != "POST":
            return {}
        try:
            d = await request.json()
        except ValueError:
            raise RequestError("request body must be a JSON object") from None
        if not isinstance(d, dict):
            raise RequestError("request body must be a JSON object")
        return d

    async def _state(self, request: web.Request) -> web.Response:
        self._check(request)
        return web.json_response(self.state.snapshot())

    async def _leader(self, request: web.Request) -> web.Response:
        self._check(request)
        return web.json_response({"leading": self.office.leading, "leader": self.office.leader,
                                  "self": self.office.me or None})

    async def _one_list(self, request: web.Request) -> web.Response:
        self._check(request)
        return web.json_response(self.state.snapshot()[request.path.rsplit("/", 1)[1]])

    async def _add_user(self, request: web.Request) -> web.Response:
        d = await self._body(request)
        u = self.state.add_user(str(d.get("name", "")), str(d.get("password", "")), d.get("role", DEFAULT_ROLE))
        await self.state.store.flush()
        if self.users:
            self.users.save(self.state)
        return web.json_response({"name": u.name, "role": u.role}, status=201)

    async def _set_role(self, request: web.Request) -> web.Response:
        d = await self._body(request)
        u = self.state.set_user_role(request.match_info["name"], d.get("role"))
        await self.state.store.flush()
        if self.users:
            self.users.save(self.state)
        return web.json_response({"name": u.name, "role": u.role})

    async def _auth(self, request: web.Request) -> web.Response:
        self._check(request)
        try:
            d = await request.json()
        except ValueError:
            d = None
        if not isinstance(d, dict) or not all(isinstance(d.get(k), str) for k in ("user", "password", "addr")):
            raise RequestError("auth: the body must be {\"user\", \"password\" (hex SHA-256), \"addr\"}, all strings")
        await self.passwords.authenticate(self.state.users, d["user"], d["password"], d["addr"])
        return web.json_response({"user": d["user"], "role": self.state.users[d["user"]].role})

    async def _del_user(self, request: web.Request) -> web.Response:
        await self._body(request)
        self.state.del_user(request.match_info["name"])
        await self.state.store.flush()
        if self.users:
            self.users.save(self.state)
        return web.json_response({})

    def _host_op(self, op: type[OpArgs]):
        """The handler of a route that asks a container's host op ``op``, with the request's body as its
        arguments (parsed here: a bad one is a 400 naming the key, before any host is asked)."""
        async def handler(request: web.Request) -> web.Response:
            args = await self._body(request)
            c = self.state.container(request.match_info["user"], request.match_info["ctag"])
            msg = parse(op, {**args, **request.match_info, "cid": c.cid}, op=op.OP, link="admin API")
            timeout = (getattr(msg, "timeout", None) or BUS_TIMEOUT) + BUS_TIMEOUT_MARGIN
            return web.json_response(await self.control.host_ask(c, msg, timeout, wait=False))
        return handler

    async def _advice(self, request: web.Request) -> web.Response:
        self._check(request)
        return web.json_response(self.placement.advice())

    async def _pin(self, request: web.Request) -> web.Response:
        d = await self._body(request)
        c = self.placement.pin(request.match_info["user"], request.match_info["ctag"], d.get("pin"))
        await self.state.store.flush()
        moved = None
        here = self.state.tasksets.get(c.tid)
        if c.data.get("pinned") and c.state == ContainerState.RUNNING \
                and (here is None or here.zone.kind != c.data["pinned"]):
            host = self.state.pick_container_host(c.data, c.user, exclude={c.tid})
            moved = await self.placement.move(c, host.tid, f"pinned to {c.data['pinned']}")
            await self.state.store.flush()
        return web.json_response({"user": c.user, "ctag": c.ctag, "pinned": c.data.get("pinned"), "moved": moved})

    async def _move(self, request: web.Request) -> web.Response:
        d = await self._body(request)
        c = self.state.container(request.match_info["user"], request.match_info["ctag"])
        want = d.get("host")
        host = next((t for t in self.state.tasksets.values()
                     if t.kind == "container" and not t.lost and want in (t.name, t.tid)), None)
        if host is None:
            raise RequestError(f"move: 'host' must name a container host that is up (its name or tid), got {want!r}")
        drain = d.get("drain_max_s")
        if drain is not None and (type(drain) not in (int, float) or not 0 < drain <= 60):
            raise RequestError(f"move: 'drain_max_s' must be a number of seconds from 0 to 60, got {drain!r}")
        moved = await self.placement.move(c, host.tid, str(d.get("why") or "moved by the operator"), drain)
        await self.state.store.flush()
        return web.json_response(moved)

    async def _moves(self, request: web.Request) -> web.Response:
        self._check(request)
        return web.json_response(self.placement.moves)

    async def _battery(self, request: web.Request) -> web.Response:
        d = await self._body(request)
        self.placement.robot_battery(request.match_info["user"], request.match_info["robot"], d.get("percent"))
        return web.json_response({})

    async def _resize(self, request: web.Request) -> web.Response:
        args = await self._body(request)
        req = Request(request.match_info["user"], "", self.state, self.control)
        spec = schema.component(schema.ContainerComponent, {**args, "cTag": request.match_info["ctag"]}, "resize")
        answer = await ResizeContainer().run(req, spec)
        await self.state.store.flush()
        return web.json_response(answer)
