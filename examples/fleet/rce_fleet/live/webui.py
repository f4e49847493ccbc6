"""The operator's web page for ``rce-fleet demo`` / ``rce-fleet serve``.

:class:`WebUI` serves ``rce_fleet/live/web/`` (index.html, fleet.js, style.css) and the engine's
``rce/web/rce.js`` on its own
HTTP port, next to two generated files:

* ``map.png``: the map image (browsers do not show PGM), drawn by the page under the grid;
* ``config.json``: where the page logs in (the master's URL, or ``door``: the page's RCE session through
  this server, :mod:`rce_fleet.live.page_door`), the fleet container's tag, the user to prefill (never a
  password), the mission topic and the named places (for the task form);
* ``relays.json`` (given ``relays``): ``{"relays": {follower: relay}}``, the robots whose link to the
  cloud goes through another robot's relay, as the master knows it (docs/relays.md); the page draws
  a line from each follower to its relay;
* ``placement.json`` (given ``placement``): ``{"containers": [{ctag, runs, best, move, pinned, misses,
  node_ms, why}], "moves": [...]}``, where each placed container runs, where the master's placer
  would put it and why, and its last moves (docs/placement.md); the page shows them in a table.

Given the fleet manager's :class:`~rce_fleet.operations.tasks_client.TaskChannel` (``tasks``), it also
serves the JSON task API and ``/metrics`` (:mod:`rce_fleet.operations.http_api`).

Who may: the page itself (``index.html`` and its scripts and styles) is open, so that it can show its
login form; ``config.json``, ``map.png``, ``relays.json`` and ``placement.json`` need a viewer's credential, as the task
API does (``auth``, :class:`~rce_fleet.operations.http_api.ApiAuth`). The page logs in with
``POST /api/login`` and sends the token with its own calls; with the task API its RCE session goes through
this server (``GET /rce/ws``, as the fleet's internal user, the frames checked for the person's role), else
(a replay's page) it logs in at the master. It listens on ``bind`` (default 127.0.0.1), over TLS given
``ssl_context``; every answer carries the headers of :mod:`rce_fleet.operations.web_headers`, and every error
is the API's JSON error (:mod:`rce_fleet.operations.api_errors`), the page's files' too.

The page is served from another origin than the master's: its login ``GET /?userID=..`` is a
cross-origin request, allowed by the master's ``Access-Control-Allow-Origin: *``, and its
websocket goes to the robot endpoint the login names. (``rce-master --static /ui=DIR`` serves
the same page same-origin; then give it ``?container=CTAG&map=URL``.)

:class:`MissionRunner` is the random mission the page starts and stops: an RCE client
(robotID ``fleetMission``) that listens on ``/fleet/mission`` (``std_msgs/String``, ``start``
or ``stop``) in the fleet container, watches ``/fleet/state`` and sends ``/fleet/goal``: on
``start`` every robot gets a random free cell of its connected part of the grid (distinct from
the others' goals), and a new one each time it arrives, until ``stop`` drops every goal.
"""
from __future__ import annotations

import io
import json
import random
import socket
from pathlib import Path
from typing import Callable

from aiohttp import web

import rce

from rce.plumbing.errors import RCEError, Unavailable
from rce.plumbing.log import get_logger
from rce_client.connection import Connection

from ..maps.geometry import GridGeometry, components
from ..operations.api_errors import MAX_BODY, json_errors
from ..operations.web_headers import add_security_headers

log = get_logger("fleet.web")

WEB_DIR = Path(__file__).parent / "web"
#: The engine's browser client, rce.js (the page imports it as ./rce.js): it ships with the engine.
RCE_JS = Path(rce.__file__).parent / "web" / "rce.js"
MISSION_TOPIC = "/fleet/mission"
MISSION_ID = "fleetMission"
DEFAULT_PORT = 8000
SETUP_TIMEOUT_S = 30.0   # s for the mission runner's interfaces to come up
CLOSE_TIMEOUT_S = 5.0    # s the cloud gets to confirm the removal of the mission runner's interfaces


def map_png(occ) -> bytes:
    """PNG bytes of an :class:`rce_fleet.maps.occupancy.OccupancyMap`: its own image when it has one
    (PGM/PNG as map_server reads it), else grey levels as ``map_saver`` writes them."""
    from PIL import Image
    import numpy as np
    img = None
    if getattr(occ, "image", None) and Path(occ.image).is_file():
        try:
            img = Image.open(occ.image)
            img = img.convert("LA" if img.mode in ("LA", "PA", "RGBA") else "L")
        except OSError:
            img = None
    if img is None:
        o = occ.occupancy
        a = np.full(o.shape, 205, dtype=np.uint8)
        a[(o >= 0) & (o < 50)] = 254
        a[o >= 50] = 0
        img = Image.fromarray(a, mode="L")
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return buf.getvalue()


class MissionRunner:
    """The random mission behind the page's start/stop buttons (see the module docstring)."""

    def __init__(self, master_url: str, geo: GridGeometry, robots: list[str], *, user: str, password: str,
                 ctag: str, robot_id: str = MISSION_ID, seed: int | None = None):
        self.master_url, self.geo, self.robots = master_url, geo, list(robots)
        self.user, self.password, self.ctag, self.robot_id = user, password, ctag, robot_id
        self.rng = random.Random(seed)
        self.comp = {c: i for i, part in enumerate(components(geo)) for c in sorted(part)}   # cell -> its part
        self.conn: Connection | None = None
        self.running = False
        self.goals: dict[str, int] = {}          # robot -> goal this mission gave it
        self.missions = 0
        self.goals_sent = 0
        self._goal_pub = None
        self._state: dict | None = None

    async def start(self, timeout: float = SETUP_TIMEOUT_S) -> None:
        """Log in as ``fleetMission`` and connect the mission topics; returns when they are up
        (within ``timeout`` s). Raises :class:`RCEError` with the cloud's reason."""
        c = self.conn = await Connection.connect(self.master_url, self.user, self.password, self.robot_id,
                                                 allow_reconnect=True)
        c.on_error(lambda reason: log.warning("mission: error from the cloud", reason=reason))
        links = [("missionCmd", "SubscriberInterface", "PublisherConverter", "std_msgs/String", MISSION_TOPIC),
                 ("missionState", "SubscriberInterface", "PublisherConverter", "fleet/FleetState", "/fleet/state"),
                 ("missionGoal", "PublisherInterface", "SubscriberConverter", "fleet/RobotGoal", "/fleet/goal")]
        adds = []
        for tag, ctype, rtype, cls, topic in links:
            adds += [{"endpointTag": self.ctag, "interfaceTag": tag, "interfaceType": ctype, "className": cls,
                      "addr": topic},
                     {"endpointTag": self.robot_id, "interfaceTag": tag, "interfaceType": rtype, "className": cls}]
        c.subscriber("missionCmd", "std_msgs/String", self._on_cmd)
        c.subscriber("missionState", "fleet/FleetState", self._on_state)
        self._goal_pub = c.publisher("missionGoal", "fleet/RobotGoal")
        errors: list[str] = []
        c.on_error(errors.append)
        await c.configure({"addInterfaces": adds})
        await c.send("CX", {"connect": [{"tagA": f"{self.ctag}/{t}", "tagB": f"{self.robot_id}/{t}"}
                                        for t, *_ in links]})
        await c.barrier(timeout)
        if errors:
            raise Unavailable(f"mission runner setup refused: {errors[0]}")
        await c.wait_interfaces_up([t for t, *_ in links], timeout)
        log.info("mission runner up", topic=MISSION_TOPIC)

    async def close(self) -> None:
        """Remove the mission's interfaces from the fleet container and log out."""
        if self.conn is not None and not self.conn.closed:
            try:
                await self.conn.configure({"removeInterfaces": [
                    {"endpointTag": self.ctag, "interfaceTag": t}
                    for t in ("missionCmd", "missionState", "missionGoal")]})
                await self.conn.barrier(CLOSE_TIMEOUT_S)
            except RCEError:
                pass
            await self.conn.close()

    # -- logic ---------------------------------------------------------------------------------
    async def _on_cmd(self, msg) -> None:
        cmd = str((msg or {}).get("data", "")).strip().lower()
        if cmd == "start":
            self.running = True
            self.missions += 1
            self.goals.clear()
            log.info("random mission started", n=self.missions)
            await self._assign(self.robots)
        elif cmd == "stop":
            self.running = False
            log.info("random mission stopped")
            for r in self.robots:
                await self._send(r, -1)
            self.goals.clear()
        else:
            log.warning("mission: unknown command (start | stop)", command=cmd)

    async def _on_state(self, msg) -> None:
        if not isinstance(msg, dict):
            return
        self._state = msg
        if not self.running:
            return
        again = [r["robot"] for r in msg.get("robots", [])
                 if r["robot"] in self.goals and r.get("goal") == self.goals[r["robot"]]
                 and (r.get("state") == "arrived" or (r.get("state") == "unreachable" and r.get("error_permanent")))]
        if again:
            await self._assign(again)

    async def _assign(self, robots: list[str]) -> None:
        st = {r["robot"]: r for r in (self._state or {}).get("robots", [])}
        blocked = set((self._state or {}).get("blocked", []))
        taken = {g for r, g in self.goals.items() if r not in robots}
        for r in robots:
            here = st.get(r, {}).get("cell", -1)
            part = self.comp.get(here)
            cands = [c for c, p in self.comp.items()
                     if (part is None or p == part) and c != here and c not in taken and c not in blocked]
            if not cands:
                continue
            g = self.rng.choice(cands)
            taken.add(g)
            self.goals[r] = g
            await self._send(r, g)

    async def _send(self, robot: str, cell: int) -> None:
        await self._goal_pub.publish({"robot": robot, "cell": int(cell)})
        self.goals_sent += 1


def _file(path: Path):
    async def handler(_req):
        return web.FileResponse(path)
    return handler


class WebUI:
    """Serve the operator's page for a running fleet; ``await start()`` returns the page's URL.
    ``tasks``: the fleet manager's TaskChannel (the HTTP API and /metrics; None: none);
    ``places``: the fleet's :class:`~rce_fleet.operations.places.Places` (the page's task form);
    ``relays()``: follower -> relay robot now (``relays.json``; None: no relays); ``placement()``: the
    placer's rows and moves (``placement.json``; None: not shown); ``auth``: who may
    (:class:`~rce_fleet.operations.http_api.ApiAuth`; None: no credential asked, only for a page without
    the task API, such as a replay's: with ``tasks`` it raises ValueError); ``ssl_context``: serve HTTPS
    (:func:`rce.transport.tls.server_context`). ``user``/``password``: the fleet container's owner (the fleet's
    internal user: the mission runner's and the page sessions' login); ``login_user``: the user the page
    prefills (default ``user``)."""

    def __init__(self, master_url: str, occ, geo: GridGeometry, robots: list[str], *, ctag: str, user: str,
                 password: str, auth=None, bind: str = "127.0.0.1", port: int = DEFAULT_PORT, mission: bool = True,
                 title: str = "rce fleet", tasks=None, places=None,
                 relays: Callable[[], dict[str, str]] | None = None, ssl_context=None,
                 placement: Callable[[], dict] | None = None, login_user: str | None = None):
        self.master_url, self.occ, self.geo, self.robots = master_url, occ, geo, list(robots)
        self.ctag, self.user, self.password = ctag, user, password
        self.login_user = user if login_user is None else login_user
        self.bind, self.port, self.title = bind, port, title
        self.mission = MissionRunner(master_url, geo, robots, user=user, password=password, ctag=ctag) \
            if mission else None
        self.tasks, self.places, self.relays, self.placement = tasks, places, relays, placement
        if tasks is not None and auth is None:
            raise ValueError("the task API needs auth (an ApiAuth): who may call it")
        self.auth, self.ssl_context = auth, ssl_context
        self.url = ""
        self._runner: web.AppRunner | None = None

    def config(self) -> dict:
        """The page's ``config.json`` (no password in it)."""
        return {"master": self.master_url, "user": self.login_user, "container": self.ctag, "map": "map.png",
                "door": "rce/ws" if self.tasks is not None else None,
                "missionTopic": MISSION_TOPIC if self.mission else None, "title": self.title,
                "robots": self.robots, "tasks": self.tasks is not None,
                "places": self.places.to_param() if self.places is not None else [],
                "relays": self.relays is not None, "placement": self.placement is not None}

    async def start(self) -> str:
        """Start the mission runner and the HTTP server (on ``port``, or any free port when it
        is taken); returns the page's URL."""
        png = map_png(self.occ)
        cfg = json.dumps(self.config())
        nocache = {"Cache-Control": "no-store"}

        async def index(_req):
            return web.FileResponse(WEB_DIR / "index.html", headers=nocache)

        async def viewer(req):
            if self.auth is not None:
                await self.auth.require(req, "viewer")

        async def config(req):
            await viewer(req)
            return web.Response(text=cfg, content_type="application/json", headers=nocache)

        async def mapimg(req):
            await viewer(req)
            return web.Response(body=png, content_type="image/png", headers=nocache)

        async def relays(req):
            await viewer(req)
            return web.json_response({"relays": self.relays()}, headers=nocache)

        async def placement(req):
            await viewer(req)
            return web.json_response(self.placement(), headers=nocache)

        app = web.Application(middlewares=[json_errors], client_max_size=MAX_BODY)
        add_security_headers(app, tls=self.ssl_context is not None)
        app.router.add_get("/", index)
        if self.relays is not None:
            app.router.add_get("/relays.json", relays)
        if self.placement is not None:
            app.router.add_get("/placement.json", placement)
        app.router.add_get("/config.json", config)
        app.router.add_get("/map.png", mapimg)
        if self.tasks is not None:
            from ..operations.http_api import add_routes
            from .page_door import PageDoor
            add_routes(app, self.tasks, self.auth)
            self.door = PageDoor(self.master_url, self.user, self.password, self.auth, self.ctag)
            self.door.add_routes(app)
        for f in [*sorted(WEB_DIR.iterdir()), RCE_JS]:   # the page's files, each its own route: any other path
            if f.is_file():                                # is a 404 (or a 405 for a route of another method)
                app.router.add_get(f"/{f.name}", _file(f))
        if self.mission is not None:
            await self.mission.start()
        self._runner = web.AppRunner(app, access_log=None)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.bind, self.port, ssl_context=self.ssl_context)
        try:
            await site.start()
        except OSError:
            if not self.port:
                raise
            log.warning("web port in use, taking a free one", port=self.port)
            site = web.TCPSite(self._runner, self.bind, 0, ssl_context=self.ssl_context)
            await site.start()
        port = site._server.sockets[0].getsockname()[1]
        host = self.bind if self.bind not in ("0.0.0.0", "::", "") else socket.gethostname()
        host = f"[{host}]" if ":" in host else host
        # 127.0.0.1/localhost are secure contexts (crypto.subtle); rce.js has a fallback elsewhere
        self.url = f"{'https' if self.ssl_context else 'http'}://{host}:{port}/" + \
            (f"?user={self.login_user}" if self.login_user else "")
        log.info("operator page up", url=self.url)
        return self.url

    async def stop(self) -> None:
        """Stop the mission runner and the HTTP server."""
        if self.mission is not None:
            await self.mission.close()
        if self._runner is not None:
            await self._runner.cleanup()
