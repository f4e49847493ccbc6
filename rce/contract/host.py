"""master -> container task set (docs/INTERNALS.md, "Control ops"): the ops a container host
serves itself (:data:`rce_container.host.HOST_OPS`); every other container op it takes is an
environment's (:mod:`rce.contract.environment`), relayed unchanged to the environment serving
its ``cid``. Sent by :class:`rce_master.control.Control`."""
from __future__ import annotations

from rce.contract.base import OpArgs
from rce.contract.environment import ContainerSetup


class CreateContainer(ContainerSetup):
    """Create container ``cid`` (a new environment, or its group's): ``{data_addr, sandbox,
    startup_ms}`` once its environment serves it. Idempotent for a repeated cid with the same tag."""
    OP = "create_container"


class DestroyContainer(OpArgs):
    """Kill every node of container ``cid``, drop its interfaces and socket; its environment stops
    with its group's last container."""
    OP = "destroy_container"
    cid: int


class HostStats(OpArgs):
    """Container ``cid``'s counters; without a cid, the host's with every container's."""
    OP = "stats"
    cid: int | None = None
