"""The master's users, managed by an admin of a running ``rce-fleet serve`` through the fleet's HTTP API.

==================================  ==========================================================================
``GET /api/users``                  ``{"users": [{"name", "role"}]}``, the master's users (the fleet's internal
                                    user is none of them)
``POST /api/users``                 ``{"name", "password", "role"?}`` -> 201 ``{"name", "role", "revoked": 0}``;
                                    409 when the user exists
``PATCH /api/users/NAME``           ``{"role"?, "password"?}`` -> ``{"name", "role", "revoked"}``: the user's
                                    tokens end, and with them its page sessions (it logs in again, with the new
                                    role); 404 no such user; 409 the last admin would be none, or (a password)
                                    the user has robots connected
``DELETE /api/users/NAME``          -> ``{"name", "role": "", "revoked"}``; 404, 409 as above
==================================  ==========================================================================

Every route needs an admin (:mod:`rce_fleet.operations.api_auth`). Passwords are 8 characters at least. The fleet's
internal user is refused with 403 on every route. Changes are made one at a time (a lock), each checked first
against the master's list (so that a name in a path is a user's, and the last admin stays one).

:class:`MasterUsers` speaks the master's admin API (``rce_master.http.admin``) with the fleet's admin token: the
password check behind every login of the fleet's doors, and ``/api/users`` there. The master keeps the users in
its state and its users file (the work directory's ``engine/users.json``; ``--users FILE`` is only read at
start). A new password is set by removing the user's record and adding it again with its role: the master's
admin API has no route for a password, and a user with robots connected cannot be removed (409, named).
"""
from __future__ import annotations

import asyncio
import hashlib
from urllib.parse import quote

from aiohttp import web

from rce.plumbing.errors import RCEError
from rce.protocol.limits import short_repr

from .api_body import read_model
from .api_errors import ApiRefusal
from .api_models import UserAdd, UserChange, UserChanged, UserList

__all__ = ["MasterUsers", "add_user_routes"]


class MasterUsers:
    """The master's users through its admin API: ``client``, an :class:`rce.tools.admin_client.AdminClient`
    holding the master's admin token. Calling it checks a password (the ``PasswordCheck`` of
    :class:`~rce_fleet.operations.http_api.ApiAuth`); :attr:`lock` is held by whoever changes users.
    Every method raises the :class:`~rce.plumbing.errors.RCEError` of the master's refusal (its ``status``
    set)."""

    def __init__(self, client):
        self.client = client
        self.lock = asyncio.Lock()

    async def __call__(self, user: str, password: str, addr: str) -> str:
        """The role of ``user`` if ``password`` is right, from client address ``addr`` (the master's login
        guard backs off per user and address)."""
        digest = hashlib.sha256(password.encode()).hexdigest()        # what a robot sends (DESIGN 3.2)
        answer = await self.client.arequest("POST", "/api/auth", {"user": user, "password": digest, "addr": addr})
        return str(answer["role"])

    async def users(self) -> dict[str, str]:
        """name -> role, every user of the master."""
        return {u["name"]: u["role"] for u in await self.client.arequest("GET", "/api/users")}

    async def robots_of(self, name: str) -> int:
        """How many robots of ``name`` are connected."""
        return sum(1 for r in await self.client.arequest("GET", "/api/robots") if r.get("user") == name)

    async def add(self, name: str, password: str, role: str) -> None:
        """Add user ``name`` with ``password`` and ``role``."""
        await self.client.arequest("POST", "/api/users", {"name": name, "password": password, "role": role})

    async def set_role(self, name: str, role: str) -> None:
        """Give ``name`` ``role``."""
        await self.client.arequest("POST", f"/api/users/{quote(name, safe='')}", {"role": role})

    async def remove(self, name: str) -> None:
        """Remove ``name``."""
        await self.client.arequest("DELETE", f"/api/users/{quote(name, safe='')}")

    async def set_password(self, name: str, password: str, role: str) -> None:
        """Give ``name`` ``password`` (and ``role``): its record removed and added again."""
        await self.remove(name)
        await self.add(name, password, role)


def _master(e: RCEError) -> ApiRefusal:
    """The API's refusal for the master's: its status (a 5xx: 503) and its reason alone."""
    status = getattr(e, "status", 0) or 503
    reason = str(e.message).split(f"HTTP {status}: ", 1)[-1]
    if status >= 500 or status in (401, 403):
        return ApiRefusal(503, "unavailable", f"the master: {reason}")
    return ApiRefusal(status, {404: "not_found", 409: "conflict"}.get(status, "bad_request"), reason)


def add_user_routes(app: web.Application, auth, users: MasterUsers) -> None:
    """Add the routes of the module docstring to ``app``: ``auth`` (the fleet's
    :class:`~rce_fleet.operations.http_api.ApiAuth`) says who may, and ends a changed user's tokens."""

    async def known(name: str) -> tuple[dict[str, str], str]:
        """The users and ``name``'s role; raises 403 (the internal user) or 404."""
        if name in auth.internal:
            raise ApiRefusal(403, "forbidden", f"user {name!r} is the fleet's own, no person's: not managed here")
        every = await users.users()
        if name not in every:
            raise ApiRefusal(404, "not_found", f"no user {short_repr(name)}")
        return every, every[name]

    def keeps_an_admin(every: dict[str, str], name: str, role: str) -> None:
        admins = [n for n, r in every.items() if r == "admin" and n not in auth.internal]
        if admins == [name] and role != "admin":
            raise ApiRefusal(409, "conflict", f"user {name!r} is the last admin: make another admin first")

    async def without_robots(name: str) -> None:
        if n := await users.robots_of(name):
            raise ApiRefusal(409, "conflict", f"user {name!r} has {n} robot(s) connected; disconnect them first")

    async def listing(req: web.Request) -> web.Response:
        await auth.require(req, "admin")
        try:
            every = await users.users()
        except RCEError as e:
            raise _master(e) from None
        return web.json_response(UserList(users=[{"name": n, "role": r} for n, r in sorted(every.items())
                                                 if n not in auth.internal]).model_dump())

    async def add(req: web.Request) -> web.Response:
        await auth.require(req, "admin")
        u = await read_model(req, UserAdd)
        if u.name in auth.internal:
            raise ApiRefusal(403, "forbidden", f"user {u.name!r} is the fleet's own, no person's: not managed here")
        async with users.lock:
            try:
                if u.name in await users.users():
                    raise ApiRefusal(409, "conflict", f"user {u.name!r} exists")
                await users.add(u.name, u.password, u.role)
            except RCEError as e:
                raise _master(e) from None
        return web.json_response(UserChanged(name=u.name, role=u.role, revoked=0).model_dump(), status=201)

    async def change(req: web.Request) -> web.Response:
        await auth.require(req, "admin")
        name = req.match_info["name"]
        c = await read_model(req, UserChange)
        if c.role is None and c.password is None:
            raise ApiRefusal(400, "bad_request", "give a role, a password or both")
        async with users.lock:
            try:
                every, role = await known(name)
                role = c.role or role
                keeps_an_admin(every, name, role)
                if c.password is not None:
                    await without_robots(name)
                    await users.set_password(name, c.password, role)
                else:
                    await users.set_role(name, role)
            except RCEError as e:
                raise _master(e) from None
        return web.json_response(UserChanged(name=name, role=role, revoked=auth.revoke_user(name)).model_dump())

    async def remove(req: web.Request) -> web.Response:
        await auth.require(req, "admin")
        name = req.match_info["name"]
        async with users.lock:
            try:
                every, _ = await known(name)
                keeps_an_admin(every, name, "")
                await without_robots(name)
                await users.remove(name)
            except RCEError as e:
                raise _master(e) from None
        return web.json_response(UserChanged(name=name, role="", revoked=auth.revoke_user(name)).model_dump())

    app.router.add_get("/api/users", listing)
    app.router.add_post("/api/users", add)
    app.router.add_patch("/api/users/{name}", change)
    app.router.add_delete("/api/users/{name}", remove)
