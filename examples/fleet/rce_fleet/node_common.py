"""What the fleet's container nodes share: the :class:`Out` items their sans-I/O cores
return, publishing them, and waiting for the grid parameter."""
from __future__ import annotations

import asyncio
from typing import Any, Iterable, NamedTuple

from rce.plumbing.errors import Unavailable

from .geometry import GRID_PARAM, GridGeometry

__all__ = ["Out", "wait_param", "load_geometry", "Publishers", "PARAM_TIMEOUT_S", "PARAM_POLL_S"]

#: s a node waits for a parameter (the fleet manager sets ``/fleet/grid`` before it starts
#: the nodes; a node started by hand may come first) before it gives up.
PARAM_TIMEOUT_S = 30.0
#: s between two reads of a parameter that is not set yet.
PARAM_POLL_S = 0.1


class Out(NamedTuple):
    """One message a node's core wants published: ``topic``, message class ``type`` (wire
    name), JSON-form ``msg``."""
    topic: str
    type: str
    msg: dict


async def wait_param(node, name: str, timeout: float = PARAM_TIMEOUT_S, interval: float = PARAM_POLL_S) -> Any:
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


async def load_geometry(node, timeout: float = PARAM_TIMEOUT_S) -> GridGeometry:
    """The grid from ``/fleet/grid``; raises Unavailable when it is not set within
    ``timeout`` s or is not a grid."""
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
        """Create the publisher of ``topic`` (message class ``typename``) unless there is one."""
        if topic not in self.pubs:
            self.pubs[topic] = await self.node.publisher(topic, typename, queue_size=queue_size)

    def send(self, outs: Iterable[Out]) -> None:
        """Publish ``outs`` in order; raises KeyError for a topic without a publisher."""
        for o in outs:
            pub = self.pubs.get(o.topic)
            if pub is None:
                raise KeyError(f"no publisher for {o.topic}")
            pub.publish_nowait(o.msg)
