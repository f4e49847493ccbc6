"""node -> bus, on a node's link to its container's bus (docs/INTERNALS.md, "Processes and links"):
served by :data:`rce.bus.server.BUS_OPS`, sent by :mod:`rce.node.runtime` and the ROS relays'
bus nodes (:mod:`rce_container.relay_base`). Topic and service data travel as DATA frames beside
these ops."""
from __future__ import annotations

from typing import Any

from rce.contract.base import OpArgs


# -- before the node is admitted ---------------------------------------------------------------------
class BusHello(OpArgs):
    """The node ``name`` (process ``pid``, in container ``container``) joins with the bus ``token``
    (``RCE_BUS_TOKEN``); ``direct``: it takes direct links. ``{bus, fd_key?}``. A missing or wrong
    token (of any type) is the bus's to refuse and count, so it is not typed here."""
    OP = "hello"
    name: str | None = None
    pid: int | None = None
    container: str | None = None
    token: Any = None
    direct: bool = False


class BusFdChannel(OpArgs):
    """(a notification, the only frame of a node's second connection) This connection is the fd channel
    of the session whose hello got ``fd_key`` = ``key`` (an unknown key of any type: refused, counted)."""
    OP = "fd_channel"
    key: Any = None


# -- the node's graph -----------------------------------------------------------------------------------
class BusAdvertise(OpArgs):
    """Publish on ``topic`` (class ``type``); the publisher's handle."""
    OP = "advertise"
    topic: str
    type: str


class BusUnadvertise(OpArgs):
    OP = "unadvertise"
    handle: int


class BusSubscribe(OpArgs):
    """BusSubscribe to ``topic`` (class ``type``) with a queue of ``queue_size`` messages; ``handle``: the
    one the node chose (so frames may come before the reply), else the bus picks one."""
    OP = "subscribe"
    topic: str
    type: str
    queue_size: int = 100
    handle: int | None = None


class BusUnsubscribe(OpArgs):
    OP = "unsubscribe"
    handle: int


class BusAdvertiseService(OpArgs):
    """Serve ``service`` (class ``type``) under ``handle`` (as for :class:`BusSubscribe`)."""
    OP = "advertise_service"
    service: str
    type: str
    handle: int | None = None


class BusUnadvertiseService(OpArgs):
    OP = "unadvertise_service"
    handle: int


class BusResolveService(OpArgs):
    """``{handle, type}`` to call ``service`` with."""
    OP = "resolve_service"
    service: str


class BusHandoff(OpArgs):
    """(a notification) The node hands its state over when its container moves."""
    OP = "handoff"


class BusUndecodable(OpArgs):
    """(a notification) A message for ``where`` did not deserialize (``error``): counted."""
    OP = "undecodable"
    where: str = ""
    error: str = ""


class BusDirectClosed(OpArgs):
    """(a notification) The node's direct link ``link`` ended."""
    OP = "direct_closed"
    link: int


class BusDirectFence(OpArgs):
    """(a notification) A fence ``fence`` of ``src -> dst`` came on one of the node's direct links."""
    OP = "direct_fence"
    fence: int
    src: int
    dst: int


# -- parameters -------------------------------------------------------------------------------------------
class BusGetParam(OpArgs):
    OP = "get_param"
    name: str


class BusSetParam(OpArgs):
    OP = "set_param"
    name: str
    value: Any = None


class BusDeleteParam(OpArgs):
    OP = "delete_param"
    name: str


class BusDescribe(OpArgs):
    """The bus's topics, services, parameters and nodes."""
    OP = "describe"
