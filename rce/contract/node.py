"""environment -> node, on the node's bus link: a node's direct links (docs/INTERNALS.md, "Direct
links"; served by :data:`rce.node.links.DIRECT_OPS`, sent by :mod:`rce_container.direct_routes`)
and its results and state across a move (served by :data:`rce.node.runtime.NODE_OPS`, sent by
:mod:`rce_container.environment`)."""
from __future__ import annotations

from rce.contract.base import OpArgs

#: ``[link id, grant frame]``: a data-plane grant (:func:`rce.transport.cluster_auth.grant_frame`) the node
#: sends on its link ``link id`` before the first message it sends there for that connection.
Grant = tuple[int, dict]


# -- direct links ---------------------------------------------------------------------------------------
class DirectLink(OpArgs):
    """Take the socket of direct link ``link`` from the fd channel (``name``: its far plane's address)."""
    OP = "direct_link"
    link: int
    name: str = "?"


class DirectPublish(OpArgs):
    """Publisher ``handle``'s route ``version``: each message goes to each ``[link, dst, src]`` of
    ``targets``, and to the bus too when ``local``; ``hold``: keep them until ``direct_go``."""
    OP = "direct_publish"
    handle: int
    version: int
    targets: list[tuple[int, int, int]] = []
    local: bool = False
    hold: bool = False
    grants: list[Grant] = []


class DirectGo(OpArgs):
    """(a notification) What publisher ``handle`` sent by the bus before its route ``version`` has
    been handed on at the far ends: the route's held messages go."""
    OP = "direct_go"
    handle: int
    version: int


class DirectSubscribe(OpArgs):
    """Claim interface ``iid`` on ``link`` for the subscriber ``handles``, as member of generation
    ``gen`` of ``size`` members; ``peers``: the interfaces that send to ``iid``; ``at``: where the
    far end sends ``iid``'s messages otherwise (only then does it take the claim)."""
    OP = "direct_subscribe"
    link: int
    iid: int
    peers: list[int]
    handles: list[int]
    gen: int = 0
    size: int = 1
    at: str | None = None
    grants: list[Grant] = []


class DirectUnsubscribe(OpArgs):
    """Release the claim of interface ``iid`` on ``link``."""
    OP = "direct_unsubscribe"
    link: int
    iid: int


class DirectSwitch(OpArgs):
    """(a notification, behind the messages the bus carried for ``iid``) The bus path's switch
    marker ``id``: what was held behind the direct marker ``id`` goes on."""
    OP = "direct_switch"
    iid: int
    id: int


class DirectCounts(OpArgs):
    """``{iid: [messages, bytes, dropped]}`` the node sent and received on its direct links."""
    OP = "direct_counts"


# -- results and handoff ---------------------------------------------------------------------------------
class NodeResults(OpArgs):
    """The node's outputs timed from their inputs since the last ask (:mod:`rce.node.results`)."""
    OP = "node_results"


class NodeStateOut(OpArgs):
    """``{state: base64 | None}`` of the node's handoff hook, once its inputs so far are handled."""
    OP = "state_out"


class NodeSettle(OpArgs):
    """``{unflushed: [link ids]}`` once the inputs so far are handled and what they caused reached the
    far ends of its direct links, within ``timeout`` s (None: the node's default)."""
    OP = "settle"
    timeout: float | None = None


class NodeStateIn(OpArgs):
    """Take ``state`` (base64; None: start fresh) through the handoff hook, then the held inputs;
    ``{took}``."""
    OP = "state_in"
    state: str | None = None
