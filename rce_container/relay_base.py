"""What the relays of a container (:mod:`rce_container.ros1_relay`, :mod:`rce_container.ros2_relay`)
share: their bus node, which moves serialized bytes without decoding them, the loop that looks at
both graphs every :data:`POLL_INTERVAL` s and whenever its ``sync`` service is called, and the
process around them (``python -m rce_container.rosN_relay --cid N``).
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import sys
from typing import Any, Awaitable, Callable, Protocol

from rce.contract import bus as to_bus
from rce.messages import default_registry
from rce.node import Node, Publisher
from rce.plumbing.errors import ConfigError, RCEError, Unavailable
from rce.plumbing.log import get_logger, setup_logging
from rce.plumbing.process import run_loop

log = get_logger("rce.container.relay")

POLL_INTERVAL = 0.5      # s between two looks at both graphs (ros1_bridge's dynamic_bridge polls every 1 s)
QUEUE_SIZE = 1000        # messages a relay's bus subscription holds for it
SYNC_TYPE = "std_srvs/Empty"   # the type a relay's own services are announced with on the bus (bytes in, JSON out)


class _Sink:
    """A bus subscription's receiver of raw bytes (the duck type :class:`rce.node.Node` delivers to)."""

    def __init__(self, push):
        self._push = push


class RawNode(Node):
    """A bus node that publishes, subscribes and serves serialized bytes, never decoding them."""

    def _encode(self, typename: str, msg: Any) -> bytes:
        return bytes(msg)

    async def _serve(self, handle: int, payload: bytes) -> bytes:
        return await self._services[handle][0](payload)

    async def raw_publisher(self, topic: str, wire: str) -> Publisher:
        """Advertise ``topic`` with class ``wire`` (``pkg/Name``, not checked against a registry)."""
        return Publisher(self, topic, wire, await self._peer.ask(to_bus.BusAdvertise(topic=topic, type=wire)))

    async def raw_subscriber(self, topic: str, wire: str, push, queue_size: int = QUEUE_SIZE) -> int:
        """Subscribe ``push(payload)`` to ``topic``; returns the handle for :meth:`unsubscribe`."""
        h = next(self._ids)
        self._subs[h] = _Sink(push)
        await self._peer.ask(to_bus.BusSubscribe(topic=topic, type=wire, queue_size=queue_size, handle=h))
        return h

    async def unsubscribe(self, handle: int) -> None:
        self._subs.pop(handle, None)
        await self._peer.ask(to_bus.BusUnsubscribe(handle=handle))

    async def raw_service(self, name: str, wire: str, handler) -> int:
        """Provide ``name``: ``await handler(request bytes)`` -> response bytes. Returns its handle."""
        h = next(self._ids)
        self._services[h] = (handler, wire, wire)
        await self._peer.ask(to_bus.BusAdvertiseService(service=name, type=wire, handle=h))
        return h

    async def unadvertise_service(self, handle: int) -> None:
        self._services.pop(handle, None)
        await self._peer.ask(to_bus.BusUnadvertiseService(handle=handle))

    async def raw_call(self, name: str, payload: bytes, timeout: float) -> bytes:
        """Call bus service ``name`` with request bytes; the response bytes."""
        r = await self._peer.ask(to_bus.BusResolveService(service=name))
        return await self._call(r["handle"], payload, timeout)


class RelayLike(Protocol):
    """What :func:`serve` and :func:`run` ask of a relay: its name on both graphs, a ``stopping``
    event, ``sync()`` (look at both graphs now, return its stats) and ``stats()``."""
    me: str
    stopping: asyncio.Event

    async def sync(self) -> dict: ...

    def stats(self) -> dict: ...


async def run(relay: RelayLike, bus: RawNode) -> None:
    """Serve ``<me>/sync`` (sync now, answer the stats as JSON) and ``<me>/stats`` (the stats) on
    ``bus``, and sync every :data:`POLL_INTERVAL` s until ``relay.stopping`` or the bus goes."""
    async def on_sync(_payload: bytes) -> bytes:
        return json.dumps(await relay.sync()).encode()

    async def on_stats(_payload: bytes) -> bytes:
        return json.dumps(relay.stats()).encode()
    await bus.raw_service(f"{relay.me}/stats", SYNC_TYPE, on_stats)
    await bus.raw_service(f"{relay.me}/sync", SYNC_TYPE, on_sync)
    while not relay.stopping.is_set() and not bus.is_shutdown:
        try:
            await relay.sync()
        except (OSError, RCEError) as e:      # the other graph or the bus busy or going: next round
            log.warning("sync failed", relay=relay.me, reason=str(e))
        try:
            async with asyncio.timeout(POLL_INTERVAL):
                await relay.stopping.wait()
        except TimeoutError:
            pass


async def serve(me: str, make: Callable[[RawNode], Awaitable[RelayLike]], cleanup: Callable[[], None] | None = None,
                **about: Any) -> None:
    """Connect the bus node ``me`` (``RCE_BUS``, ``RCE_BUS_TOKEN``), make the relay on it, and relay
    until SIGTERM/SIGINT or the bus closes; then run ``cleanup`` (what exiting does not undo) and exit
    the process at once (0). ``about``: logged with the relay's start."""
    bus = RawNode(me.lstrip("/"), "/", os.environ["RCE_BUS"], default_registry(), os.environ.get("RCE_BUS_TOKEN"))
    await bus._connect()
    relay = await make(bus)
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, relay.stopping.set)
    log.info("relay ready", name=me, **about)
    try:
        await run(relay, bus)
    finally:
        await bus.close()
        if cleanup is not None:
            cleanup()
    # Exit at once, without the ROS client library's shutdown or waiting for its threads: that
    # would unregister from a graph stopped next anyway and wait out its poll loops (~1.5 s for
    # rospy, more than a sandbox's grace); exiting closes every socket.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def main(prog: str, graph: str, serve_cid: Callable[[int], Awaitable[None]], argv: list[str] | None = None) -> None:
    """The command line of a relay (``--cid N``): run ``serve_cid(N)``; a relay that cannot start
    (:class:`ConfigError`, :class:`Unavailable`) says why on stderr and exits 1. ``graph``: ``ROS 1``..."""
    p = argparse.ArgumentParser(prog=f"python -m {prog}", description=f"relay between a container's bus and its "
                                                                     f"{graph} graph (started by the container's "
                                                                     f"environment)")
    p.add_argument("--cid", type=int, required=True, help="the container id (names the relay)")
    args = p.parse_args(argv)
    setup_logging()
    try:
        run_loop(serve_cid(args.cid))
    except (ConfigError, Unavailable) as e:
        log.error(f"{graph} relay cannot start", reason=e.message)
        print(f"{prog.rsplit('.', 1)[-1]}: {e.message}", file=sys.stderr)
        sys.exit(1)
