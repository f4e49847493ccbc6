"""A container's ROS 1 graph: its own rosmaster and relay, started when its first ROS 1 node is
added and stopped with its last (docs/INTERNALS.md, "ROS 1 nodes in containers").

- A node is a ROS 1 node when its package's ``package.xml`` depends on rospy or roscpp
  (:func:`rce_container.ros1_plan.is_ros1_package`): a catkin package runs unchanged, and a
  2013 client's plain ``addNodes`` entry needs no new key.
- The graph is two processes in the container's sandbox, children of it like its nodes (they
  die with it): Debian's ``rosmaster --core`` on the container's loopback (port
  :data:`ROS1_MASTER_PORT` when the sandbox gives the container its own network namespace, else
  a free loopback port), and the relay (:mod:`rce_container.ros1_relay`), which bridges the
  container's bus and that graph with raw bytes and copies the bus's parameters to rosmaster.
- A ROS 1 node gets, beside the usual node environment (:func:`rce_container.node_env.node_env`),
  ``ROS_MASTER_URI``, ``ROS_IP=127.0.0.1`` (rospy and rosmaster then listen on loopback only),
  ``ROS_HOME`` (in the container's workdir), ``ROS_NAMESPACE`` (the node's namespace, as
  roslaunch sets it), ``PYTHONPATH`` (the package's ``src`` directory, where catkin keeps a
  package's Python modules, then Debian's ROS 1 packages, :func:`rce.messages.debian_ros1.ros1_paths`), and the
  argument ``__name:=NAME`` (the node's name, as roslaunch passes it).
"""
from __future__ import annotations

import asyncio
import collections
import json
import os
import shutil
import socket
import sys
from typing import Any

from rce.bus.core import Bus
from rce.plumbing.errors import ConfigError, RCEError
from rce.plumbing.log import get_logger
from rce.interfaces.naming import join
from rce.node.package_path import find_package
from rce.messages.debian_ros1 import DEBIAN_PACKAGES, ros1_paths
from rce.plumbing.tasks import Tasks
from rce_container.launcher import LOG_LINES, Launcher, _pump
from rce_container.node_env import NODE_PATH, node_env
from rce_container.ros1_plan import is_ros1_package, relay_name

log = get_logger("rce.container.ros1")

ROS1_MASTER_PORT = 11311   # rosmaster's port in a container with its own network namespace (ROS's default)
START_TIMEOUT = 30.0       # s for rosmaster and the relay to be ready (the relay imports rospy, registers, syncs once)
SYNC_TIMEOUT = 10.0        # s the environment waits for one sync of the relay
LOOPBACK = "127.0.0.1"     # where the graph listens (ROS_IP): nothing of it is reachable from off the host


async def provided_or_exited(bus: Bus, service: str, procs: list[Any], timeout: float) -> bool:
    """True once ``service`` is provided on ``bus`` (a relay is ready); False when one of ``procs``
    exits first, or after ``timeout`` s."""
    waits = [asyncio.ensure_future(bus.wait_for_service(service, timeout)),
             *(asyncio.ensure_future(p.wait()) for p in procs)]
    try:
        await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
        return waits[0].done() and waits[0].result() is not None
    finally:
        for w in waits:
            w.cancel()


def free_loopback_port() -> int:
    """A TCP port free on the loopback now (for rosmaster in a container that shares the host's
    network; another process may still take it before rosmaster binds it)."""
    with socket.socket() as s:
        s.bind((LOOPBACK, 0))
        return s.getsockname()[1]


class Ros1Graph:
    """The ROS 1 graph of one container (see the module doc): ``launcher`` is the container's
    (its sandbox, bus socket, token and cTag are the graph's too), ``cid`` names the relay,
    ``bus`` is the group's bus (where the relay's ``sync`` service appears)."""

    def __init__(self, launcher: Launcher, cid: int, bus: Bus):
        self.launcher, self.cid, self.bus = launcher, cid, bus
        self.sandbox = launcher.sandbox
        self.ntags: set[str] = set()
        self.procs: dict[str, Any] = {}          # "rosmaster" / "relay" -> process
        self.output: dict[str, collections.deque] = {}
        self.uri: str | None = None
        self.relay_stats: dict = {}
        self.tasks = Tasks(f"ROS 1 graph of {launcher.ctag}")
        self._lock = asyncio.Lock()

    @property
    def running(self) -> bool:
        return bool(self.procs) and all(p.returncode is None for p in self.procs.values())

    # -- nodes ---------------------------------------------------------------------------------
    async def prepare(self, spec: dict) -> dict | None:
        """For an ``add_node`` spec of a ROS 1 package: start the graph if needed and return
        ``{"env": {...}, "args": [...]}`` to add to the node's; None for any other node (or a
        package that cannot be found: the launcher names that error)."""
        ntag = spec.get("ntag")
        try:
            pkg_dir = find_package(spec.get("pkg") or "")
        except RCEError:
            return None
        if not isinstance(ntag, str) or not ntag:
            return None
        if not is_ros1_package(pkg_dir):
            return None
        async with self._lock:
            if not self.running:
                await self._stop()
                await self._start()
        self.ntags.add(ntag)
        name, namespace = spec.get("name") or ntag, join("/", spec.get("namespace") or "/")
        src = [str(pkg_dir / "src")] if (pkg_dir / "src").is_dir() else []
        return {"env": {**self._ros_env(), "ROS_NAMESPACE": namespace,
                        "PYTHONPATH": os.pathsep.join(src + ros1_paths())},
                "args": [f"__name:={name}"]}

    async def node_gone(self, ntag: str) -> None:
        """Node ``ntag`` was removed (or did not start): stop the graph after its last ROS 1 node."""
        self.ntags.discard(ntag)
        if not self.ntags:
            async with self._lock:
                await self._stop()

    async def sync(self) -> None:
        """Have the relay look at both graphs and copy the parameters now (a parameter set with
        CN ``setParam`` is then in rosmaster when the CN is answered). A relay that does not
        answer is logged; it syncs again on its own."""
        if not self.running:
            return
        try:
            raw = await self.bus.call_service(f"{relay_name(self.cid)}/sync", b"", timeout=SYNC_TIMEOUT)
            self.relay_stats = json.loads(raw)
        except (RCEError, ValueError) as e:
            log.warning("ROS 1 relay did not sync", container=self.launcher.ctag, reason=str(e))

    async def close(self) -> None:
        """Stop rosmaster and the relay (the container is going away)."""
        self.ntags.clear()
        async with self._lock:
            await self._stop()
        await self.tasks.cancel_all()

    def info(self) -> dict:
        """``{master_uri, running, nodes, pids: {rosmaster, relay}, relay: relay stats of the last sync}``."""
        return {"master_uri": self.uri, "running": self.running, "nodes": sorted(self.ntags),
                "pids": {k: p.pid for k, p in self.procs.items() if p.returncode is None},
                "relay": self.relay_stats}

    # -- processes -----------------------------------------------------------------------------
    def _ros_env(self) -> dict[str, str]:
        return {"ROS_MASTER_URI": self.uri, "ROS_IP": LOOPBACK, "ROS_HOME": str(self.sandbox.workdir / "ros")}

    def _env(self, name: str, **extra: str) -> dict[str, str]:
        lc = self.launcher
        return node_env(bus=lc.bus_path, token=lc.bus_token, ctag=lc.ctag, name=name, namespace="/",
                        home=self.sandbox.workdir, extra={**self._ros_env(), **extra})

    async def _spawn(self, what: str, argv: list[str], env: dict[str, str]) -> None:
        proc = await self.sandbox.spawn(argv, env)
        self.procs[what] = proc
        tail = self.output[what] = collections.deque(maxlen=LOG_LINES)
        for stream in (proc.stdout, proc.stderr):
            self.tasks.spawn(_pump(stream, tail), name=f"output of {what} of {self.launcher.ctag}")

    async def _start(self) -> None:
        rosmaster = shutil.which("rosmaster", path=NODE_PATH)
        if rosmaster is None:
            raise ConfigError(f"ROS 1 node in container {self.launcher.ctag!r}: rosmaster is not installed "
                              f"(on Debian: apt-get install {DEBIAN_PACKAGES})")
        own_net = bool(getattr(self.sandbox, "ns", {}).get("net"))
        port = ROS1_MASTER_PORT if own_net else free_loopback_port()
        self.uri = f"http://{LOOPBACK}:{port}/"
        me = relay_name(self.cid)
        await self._spawn("rosmaster", [rosmaster, "--core", "-p", str(port)],
                          self._env("rosmaster", PYTHONPATH=os.pathsep.join(ros1_paths())))
        await self._spawn("relay", [sys.executable, "-m", "rce_container.ros1_relay", "--cid", str(self.cid)],
                          self._env(me.lstrip("/")))
        if not await self._ready(f"{me}/sync"):
            why = " | ".join(f"{k}: {' / '.join(list(v)[-3:])}" for k, v in self.output.items() if v) or "no output"
            await self._stop()
            raise RCEError(f"container {self.launcher.ctag!r}: its ROS 1 graph did not start (rosmaster and "
                           f"relay within {START_TIMEOUT:g} s): {why}")
        log.info("ROS 1 graph started", container=self.launcher.ctag, master_uri=self.uri,
                 pids={k: p.pid for k, p in self.procs.items()})
        await self.sync()

    async def _ready(self, service: str) -> bool:
        """True once the relay provides ``service`` on the bus; False when rosmaster or the relay
        exits first, or after :data:`START_TIMEOUT` s."""
        return await provided_or_exited(self.bus, service, list(self.procs.values()), START_TIMEOUT)

    async def _stop(self) -> None:
        """Stop the relay, then rosmaster (each SIGTERM, then SIGKILL after the sandbox's grace)."""
        for what in ("relay", "rosmaster"):
            proc = self.procs.pop(what, None)
            if proc is not None:
                await self.sandbox.kill(proc)
        if self.uri:
            log.info("ROS 1 graph stopped", container=self.launcher.ctag)
        self.uri, self.relay_stats = None, {}
