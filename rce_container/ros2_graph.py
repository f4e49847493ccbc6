"""A container's ROS 2 graph: its relay, started with its first ROS 2 node and stopped with its
last, and what a ROS 2 node is started with (docs/INTERNALS.md, "ROS 2 nodes in containers").

- A node is a ROS 2 node when its package's ``package.xml`` depends on rclpy or rclcpp
  (:func:`rce_container.ros2_plan.is_ros2_package`): an ament package runs unchanged from a plain
  ``addNodes`` entry.
- Isolation: each container's graph is its own. The namespaced sandbox gives the container a
  network namespace with only ``lo`` and a private ``/dev/shm``, so DDS discovery (UDP) and Fast
  DDS's shared-memory transport reach nothing outside it; every node and the relay also get
  ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (no multicast, no other host) and a domain id of
  the container's own (:func:`rce_container.ros2_plan.domain_of`). The unconfined sandbox has no
  namespace: there the domain id is what keeps containers apart, leased per machine
  (:func:`lease_domain`, never the host's own ``ROS_DOMAIN_ID``), on loopback only.
- A ROS 2 node gets, beside the usual node environment (:func:`rce_container.node_env.node_env`),
  ``RMW_IMPLEMENTATION=rmw_fastrtps_cpp``, ``AMENT_PREFIX_PATH`` (the engine's prefix, where the
  ROS 2 wheels keep ``share/``), ``ROS_DOMAIN_ID``, ``ROS_AUTOMATIC_DISCOVERY_RANGE``, ``ROS_HOME``
  and ``ROS_LOG_DIR`` (in the container's workdir), ``PYTHONPATH`` with its package's directory
  when it holds the package's Python module (ament_python's layout), and the arguments ``ros2
  launch`` passes (:func:`rce_container.ros2_plan.node_args`), with a parameter file of the
  bus's parameters.
- The relay (:mod:`rce_container.ros2_relay`) runs in the sandbox like a node. While it runs its
  stats are read every :data:`WATCH_INTERVAL` s, and what it cannot bridge is told to the robot
  per interface (``interface_status``).
"""
from __future__ import annotations

import asyncio
import collections
import json
import os
import re
import sys
from pathlib import Path
from typing import Any, Callable

from rce.bus.core import Bus
from rce.interfaces.naming import join
from rce.node.package_path import find_package
from rce.plumbing.errors import RCEError
from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks
from rce_container.launcher import LOG_LINES, Launcher, _pump
from rce_container.node_env import node_env
from rce_container.ros1_graph import provided_or_exited
from rce.ros2.domains import DomainLease, lease_domain
from rce_container.ros2_plan import (domain_of, interface_statuses, is_ros2_package, node_args,
                                     params_yaml, relay_name, ros2_parameters, status_changes)

log = get_logger("rce.container.ros2")

START_TIMEOUT = 30.0       # s for the relay to be ready (it imports rclpy, joins both graphs, syncs once)
SYNC_TIMEOUT = 10.0        # s the environment waits for one sync of the relay
WATCH_INTERVAL = 1.0       # s between two readings of the relay's stats (what it cannot bridge)
RMW = "rmw_fastrtps_cpp"   # the middleware of the ROS 2 wheels installed with rce

#: ``report(iid, tag, status, reason)``: tell the robot how a container interface is bridged.
Report = Callable[[int, str, str, str], None]


class Ros2Graph:
    """The ROS 2 graph of one container (see the module doc): ``launcher`` is the container's (its
    sandbox, bus socket, token and cTag are the relay's too), ``cid`` names the relay, ``bus`` is
    the group's bus; ``interfaces()`` gives the container's interfaces now (``{iid: interface}``,
    each with ``addr`` and ``tag``) and ``report`` tells the robot about one."""

    def __init__(self, launcher: Launcher, cid: int, bus: Bus, interfaces: Callable[[], dict[int, Any]],
                 report: Report):
        self.launcher, self.cid, self.bus = launcher, cid, bus
        self.sandbox = launcher.sandbox
        self.interfaces, self.report = interfaces, report
        self.ntags: set[str] = set()
        self.relay: Any = None
        self.output: collections.deque = collections.deque(maxlen=LOG_LINES)
        self.lease: DomainLease | None = None
        self.relay_stats: dict = {}
        self.told: dict[int, tuple[str, str]] = {}       # iid -> the status the robot was told last
        self.tasks = Tasks(f"ROS 2 graph of {launcher.ctag}")
        self._lock = asyncio.Lock()

    @property
    def running(self) -> bool:
        return self.relay is not None and self.relay.returncode is None

    @property
    def home(self) -> Path:
        """The nodes' ``ROS_HOME`` (logs, the parameter files), in the container's workdir."""
        return self.sandbox.workdir / "ros2"

    # -- nodes ---------------------------------------------------------------------------------
    async def prepare(self, spec: dict) -> dict | None:
        """For an ``add_node`` spec of a ROS 2 package: start the relay if needed, write the node's
        parameter file and return ``{"env": {...}, "args": [...]}`` to add to the node's; None for
        any other node (or a package that cannot be found: the launcher names that error)."""
        ntag = spec.get("ntag")
        try:
            pkg_dir = find_package(spec.get("pkg") or "")
        except RCEError:
            return None
        if not isinstance(ntag, str) or not ntag or not is_ros2_package(pkg_dir):
            return None
        async with self._lock:
            if not self.running:
                await self._stop()
                await self._start()
        self.ntags.add(ntag)
        name, namespace = spec.get("name") or ntag, join("/", spec.get("namespace") or "/")
        env = self._ros_env()
        if (pkg_dir / pkg_dir.name / "__init__.py").is_file():      # ament_python: the module beside package.xml
            env["PYTHONPATH"] = os.pathsep.join([str(pkg_dir), *filter(None, [env.get("PYTHONPATH")])])
        return {"env": env, "args": node_args(name, namespace, str(self._params_file(ntag, join(namespace, name))))}

    def _params_file(self, ntag: str, node: str) -> Path:
        """Write the bus's parameters as node ``node``'s parameter file; those ROS 2 cannot hold are logged."""
        params, skipped = ros2_parameters(self.bus.params)
        if skipped:
            log.warning("parameters left out of a ROS 2 node's", container=self.launcher.ctag, node=node,
                        skipped=skipped)
        path = self.home / "params" / (re.sub(r"[^A-Za-z0-9_.-]", "_", ntag) + ".yaml")
        self._own_dir(path.parent)
        path.write_text(params_yaml(params, node))
        self._own(path, 0o600)
        return path

    def _own_dir(self, d: Path) -> None:
        for p in (self.home, d):
            p.mkdir(exist_ok=True)
            self._own(p, 0o700)

    def _own(self, path: Path, mode: int) -> None:
        """The container's own uid owns ``path`` (its nodes write their logs beside it)."""
        uid = self.sandbox.node_uid
        if uid is not None:
            os.chown(path, uid, uid)
        os.chmod(path, mode)

    async def node_gone(self, ntag: str) -> None:
        """Node ``ntag`` was removed (or did not start): stop the relay after the last ROS 2 node."""
        self.ntags.discard(ntag)
        if not self.ntags:
            async with self._lock:
                await self._stop()

    async def sync(self, what: str = "sync") -> None:
        """Have the relay look at both graphs and set changed parameters now (``what="sync"``; a
        parameter set with CN ``setParam`` then reaches the running nodes before the CN is
        answered), or only read its stats (``"stats"``); then tell the robot what changed. A relay
        that does not answer is logged; it syncs on its own."""
        if not self.running:
            return
        try:
            raw = await self.bus.call_service(f"{relay_name(self.cid)}/{what}", b"", timeout=SYNC_TIMEOUT)
            self.relay_stats = json.loads(raw)
        except (RCEError, ValueError) as e:
            if self.running:           # (not one stopped meanwhile)
                log.warning("ROS 2 relay did not answer", container=self.launcher.ctag, reason=str(e))
            return
        self._tell()

    def _tell(self) -> None:
        """Tell the robot each interface whose bridging status changed (:func:`status_changes`)."""
        ifaces = self.interfaces()
        now = interface_statuses({iid: i.addr for iid, i in ifaces.items()}, self.relay_stats)
        for iid, (status, reason) in status_changes(self.told, now).items():
            if iid in ifaces:
                self.report(iid, ifaces[iid].tag, status, reason)
        self.told = now

    async def _watch(self) -> None:
        relay = self.relay
        while self.relay is relay and self.running:
            await asyncio.sleep(WATCH_INTERVAL)
            await self.sync("stats")

    async def close(self) -> None:
        """Stop the relay (the container is going away)."""
        self.ntags.clear()
        async with self._lock:
            await self._stop()
        await self.tasks.cancel_all()

    def info(self) -> dict:
        """``{domain_id, running, nodes, pids: {relay}, relay: relay stats of the last reading}``."""
        return {"domain_id": self.lease.domain if self.lease else None, "running": self.running,
                "nodes": sorted(self.ntags), "pids": {"relay": self.relay.pid} if self.running else {},
                "relay": self.relay_stats}

    # -- the relay -----------------------------------------------------------------------------
    def _ros_env(self) -> dict[str, str]:
        return {"RMW_IMPLEMENTATION": RMW, "AMENT_PREFIX_PATH": sys.prefix, "ROS_DOMAIN_ID": str(self.lease.domain),
                "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_HOME": str(self.home),
                "ROS_LOG_DIR": str(self.home / "log")}

    async def _start(self) -> None:
        own_net = bool(getattr(self.sandbox, "ns", {}).get("net"))
        self.lease = DomainLease(domain_of(self.cid)) if own_net else await asyncio.to_thread(lease_domain)
        self._own_dir(self.home / "log")
        lc, me = self.launcher, relay_name(self.cid)
        env = node_env(bus=lc.bus_path, token=lc.bus_token, ctag=lc.ctag, name=me.lstrip("/"), namespace="/",
                       home=self.sandbox.workdir, extra=self._ros_env())
        self.relay = await self.sandbox.spawn([sys.executable, "-m", "rce_container.ros2_relay", "--cid",
                                               str(self.cid)], env)
        self.output.clear()
        for stream in (self.relay.stdout, self.relay.stderr):
            self.tasks.spawn(_pump(stream, self.output), name=f"output of the ROS 2 relay of {lc.ctag}")
        if not await provided_or_exited(self.bus, f"{me}/sync", [self.relay], START_TIMEOUT):
            why = " / ".join(list(self.output)[-3:]) or "no output"
            await self._stop()
            raise RCEError(f"container {lc.ctag!r}: its ROS 2 relay did not start within {START_TIMEOUT:g} s: {why}")
        log.info("ROS 2 graph started", container=lc.ctag, domain=self.lease.domain, relay=self.relay.pid)
        await self.sync()
        self.tasks.spawn(self._watch(), name=f"ROS 2 relay of {lc.ctag}")

    async def _stop(self) -> None:
        """Stop the relay (SIGTERM, then SIGKILL after the sandbox's grace), give its domain back."""
        relay, self.relay = self.relay, None
        if relay is not None:
            await self.sandbox.kill(relay)
            log.info("ROS 2 graph stopped", container=self.launcher.ctag)
        if self.lease is not None:
            self.lease.release()
            self.lease = None
        self.relay_stats = {}
        self.told = {}
