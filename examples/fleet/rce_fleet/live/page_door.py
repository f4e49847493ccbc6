"""The operator page's RCE session through the fleet's web server: ``GET /rce/ws`` (a websocket).

The page (``rce.js``, with the endpoint ``/rce/ws`` of the page's own origin) opens its RCE session here
with ``userID`` (the person), ``robotID`` (``operator-ID``) and, as its ``password``, its bearer token of
``POST /api/login`` (``rce.js`` sends the hex SHA-256 of it, which is how the token book keeps it:
:meth:`~rce_fleet.operations.api_auth.TokenBook.check_digest`). The server opens the same session at the
robot endpoint as the fleet's internal user and carries the frames both ways, each of the page's read by
:class:`~rce_fleet.operations.page_rules.PageRules` for the person's role; a frame the rules refuse closes
the page's link with 1008 and the reason. A resume (``session``, ``ack``, no password) is let through
for a robotID this server opened, while the token that opened it is live; the robot endpoint checks the
session token. When a user's tokens are revoked (an admin's ``DELETE /api/tokens/USER``, a new role or
password, a removal: :mod:`rce_fleet.operations.api_users`), that user's page sessions are closed with 1008.
So the page works on the page's address, port and TLS alone (the master and the robot
endpoint stay on loopback), and no person ever holds the internal user's password.

Refusals before the websocket opens: 401 (no, an unknown, expired or revoked token; a user that is not
the token's), 400 (a robotID that is not the page's), 503 (over :data:`MAX_SESSIONS`), or the robot
endpoint's own status.
"""
from __future__ import annotations

import asyncio
from collections import OrderedDict

from aiohttp import WSMsgType, web

from rce.plumbing.errors import RCEError
from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks
from rce_client.dial import HandshakeRefused, close_quietly, dial, hash_password, login, with_query
from websockets.exceptions import ConnectionClosed

from ..operations.page_rules import PageRefused, PageRules

log = get_logger("fleet.page_door")

MAX_SESSIONS = 64          # page sessions at once (more: 503)
MAX_FRAME = 1 << 20        # bytes of one frame from the page (the page sends small JSON frames)
DIAL_TIMEOUT_S = 10.0      # s for the robot endpoint's handshake
OPENED_KEPT = 1024         # robotIDs remembered for their resumes (the oldest forgotten first)
PASSED = ("resume", "session", "ack", "maxLag", "refusal")     # query values carried to the robot endpoint
CLOSE_POLICY = 1008
REVOKED = b"the user's tokens were revoked: log in again"     # the close reason then (at most 123 bytes)


class PageDoor:
    """``GET /rce/ws`` (module docstring) onto the robot endpoint of ``master_url``'s ``user`` (the fleet's
    internal user, ``password``), checked against ``auth`` (the page's
    :class:`~rce_fleet.operations.http_api.ApiAuth`); ``ctag``: the fleet container."""

    def __init__(self, master_url: str, user: str, password: str, auth, ctag: str):
        self.master_url, self.user, self.digest, self.auth, self.ctag = (master_url, user, hash_password(password),
                                                                         auth, ctag)
        self.opened: OrderedDict[str, str] = OrderedDict()     # robotID -> the token digest that opened it
        self.sessions = 0
        self.refused = 0           # frames refused (their links closed)
        self.live: dict[str, set[web.WebSocketResponse]] = {}     # user -> its open page sessions
        self.tasks = Tasks("page-door")
        auth.on_revoke.append(self.end_user)

    def end_user(self, user: str) -> None:
        """``user``'s tokens were revoked (a new role or password, a removal, an admin's revocation): close its
        page sessions with 1008; the page logs in again."""
        for ws in list(self.live.get(user, ())):
            self.tasks.spawn(ws.close(code=CLOSE_POLICY, message=REVOKED), name="page-revoked")

    def add_routes(self, app: web.Application) -> None:
        """Add ``GET /rce/ws`` to ``app``."""
        app.router.add_get("/rce/ws", self.handle)

    def _who(self, q) -> tuple:
        rid, digest = q.get("robotID", ""), q.get("password", "").lower()
        if not digest and "session" in q:                # a resume: the token that opened it must still be live
            digest = self.opened.get(rid, "")
        who = self.auth.book.check_digest(digest, self.auth.clock()) if digest else None
        if who is None or who.user != q.get("userID"):
            raise web.HTTPUnauthorized(text="a live token of POST /api/login is needed, as the password, for its "
                                            "own user; log in again")
        try:
            return who, digest, PageRules(who.user, who.role, rid, self.ctag)
        except PageRefused as e:
            raise web.HTTPBadRequest(text=str(e)) from None

    async def handle(self, req: web.Request) -> web.StreamResponse:
        """One page session: check, dial the robot endpoint, carry the frames."""
        who, digest, rules = self._who(req.query)
        if self.sessions >= MAX_SESSIONS:
            raise web.HTTPServiceUnavailable(text=f"over {MAX_SESSIONS} page sessions")
        passed = {k: req.query[k] for k in PASSED if k in req.query}
        try:
            ws_url = await login(self.master_url, self.user, timeout=DIAL_TIMEOUT_S)
            up = await dial(with_query(ws_url, userID=self.user, robotID=rules.robot_id, password=self.digest,
                                       **passed), DIAL_TIMEOUT_S)
        except HandshakeRefused as e:
            raise _status(e.status, e.reason) from None
        except RCEError as e:
            raise web.HTTPServiceUnavailable(text=f"the fleet's robot endpoint: {e.message}") from None
        self.opened[rules.robot_id] = digest
        self.opened.move_to_end(rules.robot_id)
        while len(self.opened) > OPENED_KEPT:
            self.opened.popitem(last=False)
        ws = web.WebSocketResponse(max_msg_size=MAX_FRAME, heartbeat=20.0)
        await ws.prepare(req)
        self.sessions += 1
        self.live.setdefault(who.user, set()).add(ws)
        log.info("page session", user=who.user, role=who.role, robot=rules.robot_id, resume="session" in passed)
        try:
            await _pump(ws, up, rules, self)
        finally:
            self.sessions -= 1
            mine = self.live.get(who.user, set())
            mine.discard(ws)
            if not mine:
                self.live.pop(who.user, None)
            await close_quietly(up)
        return ws


def _status(status: int, reason: str) -> web.HTTPException:
    cls = {401: web.HTTPUnauthorized, 403: web.HTTPForbidden, 404: web.HTTPNotFound, 409: web.HTTPConflict,
           429: web.HTTPTooManyRequests}.get(status, web.HTTPBadGateway)
    return cls(text=reason)


async def _pump(ws: web.WebSocketResponse, up, rules: PageRules, door: PageDoor) -> None:
    """Carry frames both ways until either side closes; a refused frame closes both."""

    async def down() -> None:
        try:
            async for m in up:
                await (ws.send_str(m) if isinstance(m, str) else ws.send_bytes(m))
        except ConnectionClosed:
            pass
        finally:
            if not ws.closed:
                await ws.close(code=up.close_code or 1000, message=(up.close_reason or "").encode()[:120])

    task = asyncio.create_task(down())
    try:
        async for m in ws:
            if m.type == WSMsgType.TEXT:
                await up.send(rules.text(m.data))
            elif m.type == WSMsgType.BINARY:
                rules.binary()
    except PageRefused as e:
        door.refused += 1
        log.warning("page frame refused", user=rules.user, robot=rules.robot_id, reason=str(e))
        await ws.close(code=CLOSE_POLICY, message=f"refused: {e}".encode()[:120])
    except ConnectionClosed:
        pass
    finally:
        await close_quietly(up)
        await task
