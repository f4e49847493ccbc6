"""What the fleet's container nodes share: waiting for the grid parameter, publishing the
core's :class:`Out` items, logging."""
from __future__ import annotations

import asyncio
from typing import Any, Iterable

from rce.errors import Unavailable

from .geometry import GRID_PARAM, GridGeometry

__all__ = ["wait_param", "load_geometry", "Publishers"]


async def wait_param(node, name: str, timeout: float = 30.0, interval: float = 0.1) -> Any:
    """The value of parameter ``name`` once set (the fleet manager sets it before it starts
    the nodes; a node started by hand may come first). Raises Unavailable after ``timeout`` s."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while True:
        v = await node.get_param(name, None)
        if v is not None:
            return v
        if loop.time() > deadline:
            raise Unavailable(f"parameter {name} is not set (the fleet manager sets it; waited {timeout:g} s)")
        await asyncio.sleep(interval)


async def load_geometry(node, timeout: float = 30.0) -> GridGeometry:
    """The grid from ``/fleet/grid``."""
    p = await wait_param(node, GRID_PARAM, timeout)
    try:
        return GridGeometry.from_param(p)
    except ValueError as e:
        raise Unavailable(f"{GRID_PARAM}: {e}") from None


class Publishers:
    """Publishers by topic, created up front; :meth:`send` publishes Out items in order."""

    def __init__(self, node):
        self.node = node
        self.pubs: dict[str, Any] = {}

    async def add(self, topic: str, typename: str, queue_size: int = 10) -> None:
        if topic not in self.pubs:
            self.pubs[topic] = await self.node.publisher(topic, typename, queue_size=queue_size)

    def send(self, outs: Iterable) -> None:
        for o in outs:
            pub = self.pubs.get(o.topic)
            if pub is None:
                raise KeyError(f"no publisher for {o.topic}")
            pub.publish_nowait(o.msg)
