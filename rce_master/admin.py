"""The master's JSON admin API (what rce-console and rce-topic --container use).

All routes need ``Authorization: Bearer TOKEN`` (the master's admin token).

| route | result |
|---|---|
| ``GET /api/state`` | everything (:meth:`MasterState.snapshot`) |
| ``GET /api/{users,robots,containers,nodes,parameters,interfaces,connections,tasksets}`` | one list |
| ``POST /api/users`` ``{name, password}`` / ``DELETE /api/users/{name}`` | add / delete a user |
| ``GET /api/containers/{user}/{ctag}/bus`` | the container's bus: topics, services, params, nodes |
| ``POST /api/containers/{user}/{ctag}/publish`` ``{topic, type, msg}`` | publish on its bus |
| ``POST /api/containers/{user}/{ctag}/call`` ``{service, request, timeout}`` | call a service on its bus |
| ``POST /api/containers/{user}/{ctag}/sample`` ``{topic, count, timeout}`` | up to count messages |
| ``GET /api/containers/{user}/{ctag}/stats`` | the container's counters from its host |
| ``POST /api/containers/{user}/{ctag}/resize`` ``{cpu?, memory?, size?}`` | new limits, nodes keep running |
| ``GET /api/containers/{user}/{ctag}/logs/{ntag}`` | a node's kept stdout/stderr |
"""
from __future__ import annotations

import hmac
from typing import TYPE_CHECKING

from aiohttp import web

from rce.errors import AuthError, RequestError

if TYPE_CHECKING:
    from rce_master.server import Master

LISTS = ("users", "robots", "containers", "nodes", "parameters", "interfaces", "connections", "tasksets")


def routes(master: "Master", app: web.Application) -> None:
    """Add the admin routes of ``master`` to ``app``."""

    def check(request: web.Request) -> None:
        auth = request.headers.get("Authorization", "")
        if not auth.startswith("Bearer ") or not hmac.compare_digest(auth[7:].strip(), master.admin_token):
            raise AuthError("admin API: missing or wrong bearer token (see --admin-token-file)")

    async def body(request: web.Request) -> dict:
        try:
            d = await request.json()
        except ValueError:
            raise RequestError("request body must be a JSON object") from None
        if not isinstance(d, dict):
            raise RequestError("request body must be a JSON object")
        return d

    async def state(request: web.Request) -> web.Response:
        check(request)
        return web.json_response(master.state.snapshot())

    def one_list(name: str):
        async def handler(request: web.Request) -> web.Response:
            check(request)
            return web.json_response(master.state.snapshot()[name])
        return handler

    async def add_user(request: web.Request) -> web.Response:
        check(request)
        d = await body(request)
        master.state.add_user(str(d.get("name", "")), str(d.get("password", "")))
        master._save_users()
        return web.json_response({"name": d["name"]}, status=201)

    async def del_user(request: web.Request) -> web.Response:
        check(request)
        master.state.del_user(request.match_info["name"])
        master._save_users()
        return web.json_response({})

    def container_op(op: str, method: str):
        async def handler(request: web.Request) -> web.Response:
            check(request)
            c = master.state.container(request.match_info["user"], request.match_info["ctag"])
            args = await body(request) if method == "POST" else {}
            if "ntag" in request.match_info:
                args["ntag"] = request.match_info["ntag"]
            timeout = float(args.get("timeout") or 10) + 5
            peer = master.peers.get(c.tid)
            if peer is None:
                raise RequestError(f"the host of container {c.ctag!r} is gone")
            if op == "resize_container":
                limits = {k: args[k] for k in ("cpu", "memory", "size") if args.get(k) is not None}
                res = await peer.call(op, cid=c.cid, limits=limits)
                c.data.update(limits)
            else:
                res = await peer.request(op, {"cid": c.cid, **args}, timeout)
            return web.json_response(res)
        return handler

    app.router.add_get("/api/state", state)
    for name in LISTS:
        app.router.add_get(f"/api/{name}", one_list(name))
    app.router.add_post("/api/users", add_user)
    app.router.add_delete("/api/users/{name}", del_user)
    base = "/api/containers/{user}/{ctag}"
    app.router.add_get(base + "/bus", container_op("describe", "GET"))
    app.router.add_post(base + "/publish", container_op("bus_publish", "POST"))
    app.router.add_post(base + "/call", container_op("bus_call", "POST"))
    app.router.add_post(base + "/sample", container_op("bus_sample", "POST"))
    app.router.add_get(base + "/stats", container_op("stats", "GET"))
    app.router.add_post(base + "/resize", container_op("resize_container", "POST"))
    app.router.add_get(base + "/logs/{ntag}", container_op("logs", "GET"))
