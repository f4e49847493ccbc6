"""rce-master's asyncio shell around :class:`~rce_master.state.MasterState`.

- Control plane (TCP, default 8080): task sets register and exchange the ops of
  docs/INTERNALS.md.
- HTTP (default 9000): robot login ``GET /?userID=U&version=V`` (DESIGN 3.1), the
  JSON admin API under ``/api/`` (Bearer token), Prometheus ``/metrics``.

No data flows through the master.
"""
from __future__ import annotations

import asyncio
import json
import os
from collections import defaultdict
from pathlib import Path
from typing import Any

from aiohttp import web
from prometheus_client import CollectorRegistry, Counter, Gauge, generate_latest, CONTENT_TYPE_LATEST

from rce.errors import AuthError, NotFound, RCEError, RequestError, Unavailable
from rce.log import get_logger
from rce.rpc import RpcPeer, nodelay
from rce_master.state import Container, InterfaceRec, MasterState, User

log = get_logger("rce.master")

CLIENT_VERSION = "20130902"                        # the RCE alpha client's version string
SUPPORTED_VERSIONS = {"20130902", "20130210"}
CREATE_TIMEOUT = 60.0                              # s, container creation


class Metrics:
    """Prometheus metrics of the master."""

    def __init__(self, master: "Master"):
        self.registry = CollectorRegistry()
        r = self.registry
        self.logins = Counter("rce_master_logins", "Robot logins over HTTP", ["result"], registry=r)
        self.requests = Counter("rce_master_requests", "Robot requests (CC, DC, CN, CX)", ["type", "result"], registry=r)
        for name, help_, fn in [
            ("rce_master_robots", "Connected robots", lambda: len(master.state.robots)),
            ("rce_master_containers", "Containers", lambda: len(master.state.containers)),
            ("rce_master_interfaces", "Interfaces", lambda: len(master.state.interfaces)),
            ("rce_master_connections", "Connections", lambda: len(master.state.connections)),
            ("rce_master_tasksets", "Registered task sets", lambda: len(master.state.tasksets)),
        ]:
            Gauge(name, help_, registry=r).set_function(fn)


class Master:
    """The running master. ``users_file``: JSON file of hashed user records (read and kept up to date)."""

    def __init__(self, *, users_file: Path | None = None, admin_token: str, dev: bool = False):
        self.state = MasterState()
        self.users_file = users_file
        self.admin_token = admin_token
        self.peers: dict[int, RpcPeer] = {}
        self.robot_locks: dict[tuple[str, str], asyncio.Lock] = defaultdict(asyncio.Lock)
        self.metrics = Metrics(self)
        self._control: asyncio.AbstractServer | None = None
        self._runner: web.AppRunner | None = None
        self.http_port = self.control_port = 0
        if users_file and users_file.exists():
            self._load_users()
        if dev and "testUser" not in self.state.users:
            self.state.add_user("testUser", "testUser")
            log.warning("DEV MODE: user 'testUser' with password 'testUser' is provisioned; never use --dev on a "
                        "reachable network")

    # -- users file ----------------------------------------------------------------------------
    def _load_users(self) -> None:
        try:
            records = json.loads(self.users_file.read_text()).get("users", [])
            for r in records:
                self.state.users[r["name"]] = User.from_record(r)
        except (OSError, ValueError, KeyError) as e:
            raise RequestError(f"{self.users_file}: cannot load users: {e}") from None

    def _save_users(self) -> None:
        if not self.users_file:
            return
        tmp = self.users_file.with_suffix(".tmp")
        tmp.write_text(json.dumps({"users": [u.to_record() for u in self.state.users.values()]}, indent=1))
        os.chmod(tmp, 0o600)
        tmp.replace(self.users_file)

    # -- lifecycle -----------------------------------------------------------------------------
    async def start(self, bind: str, http_port: int, control_port: int, static_dirs: dict[str, Path] | None = None) -> None:
        self._control = await asyncio.start_server(self._accept, bind, control_port, limit=2**20)
        self.control_port = self._control.sockets[0].getsockname()[1]
        app = self._app(static_dirs or {})
        self._runner = web.AppRunner(app, access_log=None)
        await self._runner.setup()
        site = web.TCPSite(self._runner, bind, http_port)
        await site.start()
        self.http_port = site._server.sockets[0].getsockname()[1]
        log.info("master up", http_port=self.http_port, control_port=self.control_port, bind=bind)

    async def stop(self) -> None:
        if self._control:
            self._control.close()
        for p in list(self.peers.values()):
            await p.close()
        if self._runner:
            await self._runner.cleanup()

    # -- control plane -------------------------------------------------------------------------
    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        nodelay(writer)
        peer = RpcPeer(reader, writer, name="taskset", on_close=self._peer_closed)
        peer.handlers["register"] = lambda a, p=peer: self._register(p, a)
        peer.start()

    async def _register(self, peer: RpcPeer, a: dict) -> dict:
        if "tid" in peer.info:
            raise RequestError("this task set is already registered")
        ts = self.state.register_taskset(a.get("kind", ""), a.get("name") or peer.peername,
                                         a.get("host") or "127.0.0.1", a)
        peer.info["tid"] = ts.tid
        peer.name = f"{ts.kind}:{ts.name}"
        self.peers[ts.tid] = peer
        peer.keepalive()      # a host gone silent is lost within 4 s (its containers marked lost)
        if ts.kind == "robot":
            peer.handlers.update({
                "auth": self._auth, "robot_connected": lambda x, t=ts.tid: self._robot_connected(t, x),
                "robot_disconnected": self._robot_disconnected, "robot_request": self._robot_request})
        else:
            peer.handlers.update({"node_status": self._node_status})
        log.info("task set registered", tid=ts.tid, kind=ts.kind, name=ts.name, host=ts.host)
        return {"tid": ts.tid}

    def _peer_closed(self, peer: RpcPeer) -> None:
        tid = peer.info.get("tid")
        if tid is None:
            return
        self.peers.pop(tid, None)
        ts = self.state.tasksets.get(tid)
        lost, robots = self.state.drop_taskset(tid)
        log.warning("task set gone", tid=tid, kind=ts.kind if ts else "?", containers=len(lost), robots=len(robots))
        asyncio.create_task(self._after_taskset_loss(lost, robots))

    async def _after_taskset_loss(self, lost: list[Container], robots: list) -> None:
        for r in robots:
            await self._cleanup_robot(r.user, r.robot)
        for c in lost:
            ifaces = [i for i in self.state.interfaces.values() if i.user == c.user and i.etag == c.ctag]
            for a, b in self.state.forget_interfaces(ifaces):
                await self._tell_disconnect(a, b)
            self._notify_robot(c.user, c.owner, "ST", {"topic": "container", "cTag": c.ctag, "status": "lost"})
            self._notify_robot(c.user, c.owner, "ER", f"container {c.ctag!r} was lost: its host went away")

    # -- robot endpoint ops --------------------------------------------------------------------
    async def _auth(self, a: dict) -> dict:
        # scrypt costs ~50 ms of CPU by design: run it off the event loop so logins never stall
        # the control plane (keepalives, other robots' requests)
        await asyncio.to_thread(self.state.authenticate, a.get("user", ""), a.get("password", ""))
        return {}

    async def _robot_connected(self, tid: int, a: dict) -> dict:
        self.state.robot_connect(a["user"], a["robot"], tid)
        log.info("robot connected", user=a["user"], robot=a["robot"])
        return {}

    async def _robot_disconnected(self, a: dict) -> dict:
        async with self.robot_locks[(a["user"], a["robot"])]:
            await self._cleanup_robot(a["user"], a["robot"])
        self.robot_locks.pop((a["user"], a["robot"]), None)
        log.info("robot disconnected", user=a["user"], robot=a["robot"])
        return {}

    async def _cleanup_robot(self, user: str, robot: str) -> None:
        ifaces, owned = self.state.robot_disconnect(user, robot)
        for a, b in self.state.forget_interfaces(ifaces):
            await self._tell_disconnect(a, b)
        for c in owned:
            await self._destroy_container(c.user, c.ctag)

    async def _robot_request(self, a: dict) -> dict:
        user, robot, t, data = a["user"], a["robot"], a["type"], a.get("data") or {}
        async with self.robot_locks[(user, robot)]:
            try:
                if t == "CC":
                    await self._create_container(user, robot, data["containerTag"], data.get("containerData"))
                elif t == "DC":
                    self.state.container(user, data["containerTag"])
                    await self._destroy_container(user, data["containerTag"])
                elif t == "CN":
                    await self._configure(user, robot, data)
                elif t == "CX":
                    await self._connections(user, data)
                else:
                    raise RequestError(f"unknown request type {t!r}")
            except RCEError:
                self.metrics.requests.labels(t, "error").inc()
                raise
        self.metrics.requests.labels(t, "ok").inc()
        return {}

    async def _node_status(self, a: dict) -> None:
        detail = {k: a[k] for k in ("code", "signal", "reason") if a.get(k) is not None}
        n = self.state.node_status(a["cid"], a["ntag"], a["status"], detail)
        c = self.state.container_by_cid(a["cid"])
        if n and c:
            self._notify_robot(c.user, c.owner, "ST", {"topic": "node", "cTag": c.ctag, "nTag": n.ntag,
                                                       "status": a["status"], **detail})
            if a["status"] in ("exited", "failed") and (detail.get("code") or detail.get("signal")):
                how = f"code {detail['code']}" if detail.get("code") is not None else f"signal {detail.get('signal')}"
                self._notify_robot(c.user, c.owner, "ER", f"node {n.ntag!r} in container {c.ctag!r} exited with {how}"
                                   + (f": {detail['reason']}" if detail.get("reason") else ""))

    def _notify_robot(self, user: str, robot: str, type_: str, data: Any) -> None:
        r = self.state.robots.get((user, robot))
        peer = self.peers.get(r.tid) if r else None
        if peer:
            peer.notify("notify", user=user, robot=robot, type=type_, data=data)

    # -- request handlers ----------------------------------------------------------------------
    async def _create_container(self, user: str, robot: str, ctag: str, data: dict | None) -> None:
        c, host = self.state.add_container(user, robot, ctag, data)
        limits = {k: (data or {}).get(k) for k in ("cpu", "memory", "size", "bandwidth")}
        try:
            res = await self.peers[host.tid].call("create_container", timeout=CREATE_TIMEOUT, cid=c.cid, user=user,
                                                  ctag=ctag, group=c.group, limits=limits)
        except RCEError:
            self.state.remove_container(user, ctag)
            raise
        self.state.container_ready(c, res["data_addr"], res.get("sandbox", ""))
        log.info("container created", user=user, ctag=ctag, cid=c.cid, host=host.name, sandbox=c.sandbox)
        # the robot learns what isolation its container got ("namespaced", or "unconfined" on a host without root)
        self._notify_robot(user, robot, "ST", {"topic": "container", "cTag": ctag, "status": "running",
                                               "sandbox": c.sandbox})

    async def _destroy_container(self, user: str, ctag: str) -> None:
        c, ifaces = self.state.remove_container(user, ctag)
        for a, b in self.state.forget_interfaces(ifaces):
            await self._tell_disconnect(a, b)
        peer = self.peers.get(c.tid)
        if peer and c.state != "lost":
            try:
                await peer.call("destroy_container", cid=c.cid)
            except RCEError as e:
                log.warning("destroy failed", ctag=ctag, reason=str(e))
        log.info("container destroyed", user=user, ctag=ctag, cid=c.cid)

    async def _host_call(self, c: Container, op: str, **args) -> Any:
        peer = self.peers.get(c.tid)
        if peer is None:
            raise Unavailable(f"the host of container {c.ctag!r} is gone")
        return await peer.call(op, cid=c.cid, **args)

    async def _endpoint_call(self, rec: InterfaceRec, op: str, **args) -> Any:
        if rec.robot_side:
            peer = self.peers.get(rec.location)
            if peer is None:
                raise Unavailable(f"the robot endpoint of {rec.tag} is gone")
            return await peer.call(op, **args)
        c = self.state.container_by_cid(rec.location)
        if c is None:
            raise Unavailable(f"container {rec.etag!r} is gone")
        return await self._host_call(c, op, **args)

    async def _configure(self, user: str, robot: str, data: dict) -> None:
        errors: list[str] = []

        async def each(items: list, fn) -> None:
            for item in items or []:
                try:
                    await fn(item)
                except RCEError as e:
                    errors.append(e.message)

        async def add_node(spec: dict) -> None:
            c, n = self.state.add_node(user, spec)
            try:
                await self._host_call(c, "add_node", ntag=n.ntag, pkg=spec["pkg"], exe=spec["exe"],
                                      args=spec.get("args", ""), name=spec.get("name"),
                                      namespace=spec.get("namespace"), respawn=spec.get("respawn"))
                n.status = "running"
            except RCEError:
                self.state.nodes.pop((user, c.ctag, n.ntag), None)
                raise

        async def remove_node(spec: dict) -> None:
            c = self.state.remove_node(user, spec["containerTag"], spec["nodeTag"])
            await self._host_call(c, "remove_node", ntag=spec["nodeTag"])

        async def set_param(spec: dict) -> None:
            c = self.state.container(user, spec["containerTag"])
            await self._host_call(c, "set_param", name=spec["name"], value=spec["value"])
            self.state.set_param(user, c.ctag, spec["name"], spec["value"])

        async def delete_param(spec: dict) -> None:
            c = self.state.delete_param(user, spec["containerTag"], spec["name"])
            await self._host_call(c, "delete_param", name=spec["name"])

        async def add_interface(spec: dict) -> None:
            rec = self.state.add_interface(user, robot, spec)
            try:
                if rec.robot_side:
                    await self._endpoint_call(rec, "add_interface", user=user, robot=rec.etag, iid=rec.iid,
                                              itag=rec.itag, itype=rec.itype, cls=rec.cls)
                else:
                    await self._endpoint_call(rec, "add_interface", iid=rec.iid, tag=rec.tag, itype=rec.itype,
                                              cls=rec.cls, addr=rec.addr)
            except RCEError:
                self.state.forget_interfaces([rec])
                raise

        async def remove_interface(spec: dict) -> None:
            rec, conns = self.state.remove_interface(user, spec["endpointTag"], spec["interfaceTag"])
            for a, b in conns:
                other = b if a.iid == rec.iid else a
                await self._quiet(self._endpoint_call(other, "disconnect", iid=other.iid, peer_iid=rec.iid))
            await self._quiet(self._endpoint_call(rec, "remove_interface", iid=rec.iid))

        async def resize(spec: dict) -> None:
            c = self.state.container(user, spec["containerTag"])
            limits = {k: spec.get(k) for k in ("cpu", "memory", "size", "bandwidth") if spec.get(k) is not None}
            await self._host_call(c, "resize_container", limits=limits)
            c.data.update(limits)

        await each(data.get("addNodes"), add_node)
        await each(data.get("removeNodes"), remove_node)
        await each(data.get("setParam"), set_param)
        await each(data.get("deleteParam"), delete_param)
        await each(data.get("addInterfaces"), add_interface)
        await each(data.get("removeInterfaces"), remove_interface)
        await each(data.get("resizeContainer"), resize)
        if errors:
            raise RequestError("; ".join(errors))

    async def _connections(self, user: str, data: dict) -> None:
        errors: list[str] = []
        for item in data.get("connect") or []:
            try:
                a, b = self.state.connect(user, item["tagA"], item["tagB"])
                try:
                    await self._tell_connect(a, b)
                except RCEError:
                    self.state.disconnect(user, item["tagA"], item["tagB"])
                    await self._tell_disconnect(a, b)
                    raise
            except RCEError as e:
                errors.append(e.message)
        for item in data.get("disconnect") or []:
            try:
                a, b = self.state.disconnect(user, item["tagA"], item["tagB"])
                await self._tell_disconnect(a, b)
            except RCEError as e:
                errors.append(e.message)
        if errors:
            raise RequestError("; ".join(errors))

    async def _tell_connect(self, a: InterfaceRec, b: InterfaceRec) -> None:
        addr_a, addr_b = self.state.data_addr(a), self.state.data_addr(b)
        await self._endpoint_call(a, "connect", iid=a.iid, peer_iid=b.iid, peer_addr=addr_b)
        await self._endpoint_call(b, "connect", iid=b.iid, peer_iid=a.iid, peer_addr=addr_a)

    async def _tell_disconnect(self, a: InterfaceRec, b: InterfaceRec) -> None:
        await self._quiet(self._endpoint_call(a, "disconnect", iid=a.iid, peer_iid=b.iid))
        await self._quiet(self._endpoint_call(b, "disconnect", iid=b.iid, peer_iid=a.iid))

    @staticmethod
    async def _quiet(coro) -> None:
        try:
            await coro
        except RCEError as e:
            log.debug("ignored on teardown", reason=str(e))

    # -- HTTP ------------------------------------------------------------------------------------
    def _app(self, static_dirs: dict[str, Path]) -> web.Application:
        app = web.Application(middlewares=[self._errors_mw], client_max_size=16 * 1024 * 1024)
        from rce_master.admin import routes
        app.router.add_get("/", self._login)
        app.router.add_get("/metrics", self._metrics)
        routes(self, app)
        for prefix, d in static_dirs.items():
            app.router.add_static(prefix, d, show_index=False)
        return app

    @web.middleware
    async def _errors_mw(self, request: web.Request, handler):
        try:
            resp = await handler(request)
        except AuthError as e:
            resp = web.Response(status=401, text=e.message + "\n")
        except NotFound as e:
            resp = web.Response(status=404, text=e.message + "\n")
        except Unavailable as e:
            resp = web.Response(status=503, text=e.message + "\n")
        except RCEError as e:
            resp = web.Response(status=400, text=e.message + "\n")
        if request.path.startswith("/api/") or request.path == "/":
            # the operator's web page may be served from another origin (rce-fleet); login and the
            # read-only parts are safe to share, the admin API itself still needs its token
            resp.headers["Access-Control-Allow-Origin"] = "*"
            resp.headers["Access-Control-Allow-Headers"] = "Authorization, Content-Type"
        return resp

    async def _login(self, request: web.Request) -> web.Response:
        """``GET /?userID=U&version=V`` -> ``{"url": ws_url, "current"?: V'}`` (DESIGN section 3.1)."""
        q = request.query
        user, version = q.get("userID"), q.get("version")
        if not user:
            self.metrics.logins.labels("bad_request").inc()
            raise RequestError("missing query parameter 'userID'")
        if not version:
            self.metrics.logins.labels("bad_request").inc()
            raise RequestError("missing query parameter 'version'")
        if user not in self.state.users:
            self.metrics.logins.labels("unknown_user").inc()
            raise AuthError(f"unknown user {user!r}")
        if version not in SUPPORTED_VERSIONS and version > CLIENT_VERSION:
            self.metrics.logins.labels("bad_version").inc()
            raise RequestError(f"client version {version!r} is not supported (this master speaks {CLIENT_VERSION})")
        ts = self.state.pick_robot_taskset()
        body = {"url": ts.info["ws_url"]}
        if version < CLIENT_VERSION:
            body["current"] = CLIENT_VERSION
        self.metrics.logins.labels("ok").inc()
        return web.json_response(body)

    async def _metrics(self, request: web.Request) -> web.Response:
        return web.Response(body=generate_latest(self.metrics.registry),
                            headers={"Content-Type": CONTENT_TYPE_LATEST})
