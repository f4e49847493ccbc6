"""ROS 2 actions as interfaces: one config entry, five parts on the engine's services and topics.

A ROS 2 action ``NAME`` of type ``pkg/action/T`` is, on the wire of DDS, three services and two
topics (design article "Actions", https://design.ros2.org/articles/actions.html; rcl_action's
names in ``rcl_action/src/rcl_action/names.c``):

=============  =======================================  =================================  =========
part           ROS 2 name                               type                               direction
=============  =======================================  =================================  =========
send_goal      ``NAME/_action/send_goal``               ``pkg/action/T_SendGoal``          service
get_result     ``NAME/_action/get_result``              ``pkg/action/T_GetResult``         service
cancel_goal    ``NAME/_action/cancel_goal``             ``action_msgs/srv/CancelGoal``     service
feedback       ``NAME/_action/feedback``                ``pkg/action/T_FeedbackMessage``   server -> client
status         ``NAME/_action/status``                  ``action_msgs/msg/GoalStatusArray``  server -> client
=============  =======================================  =================================  =========

rce carries an action the same way (as zenoh-bridge-ros2dds does): a config's
``ActionProvider*`` (provides the action server to its local side: a robot's Nav2-style client
sends goals into the cloud) or ``ActionClient*`` (sends the goals it gets to its local side's
action server) becomes, in :func:`expand_interface`, five interfaces tagged ``iTag.part`` (``nav.send_goal``):
ServiceProvider/ServiceClient for the services, Publisher/Subscriber for the topics; a connection
of two actions becomes the five connections of their parts (:func:`expand_connection`). Each part
is an ordinary interface to the engine (routes, lanes, ST, converters and forwarders alike), and
an unchanged rclpy ``ActionClient`` or ``ActionServer`` sees an action at ``NAME``.

A ``get_result`` call lasts as long as its goal runs: its call timeout is
:data:`RESULT_TIMEOUT` (:func:`call_timeout`), not a service's.
"""
from __future__ import annotations

from dataclasses import dataclass

from rce.interfaces.qos import ACTION_STATUS, QoS

ACTION_KINDS = ("ActionProvider", "ActionClient")
SIDES = ("Interface", "Converter", "Forwarder")
#: Every action interface type a config takes: ActionProvider/ActionClient x Interface/Converter/Forwarder.
ACTION_TYPES = tuple(k + s for k in ACTION_KINDS for s in SIDES)
SERVICE_TIMEOUT = 30.0      # s a forwarded service call waits for its response
RESULT_TIMEOUT = 24 * 3600.0   # s a get_result call may wait: the goal's whole run (a day bounds a lost one)
CANCEL = "action_msgs/srv/CancelGoal"
STATUS = "action_msgs/msg/GoalStatusArray"


@dataclass(frozen=True, slots=True)
class Part:
    """One part of an action: ``name`` (``send_goal`` ...), the service or topic ``kind`` on the
    provider's side and on the client's side, its class for action type ``pkg/action/T``
    (``{T}`` stands for the type) and its QoS (None: the interface's own)."""
    name: str
    provider_kind: str
    client_kind: str
    cls: str
    qos: QoS | None = None

    @property
    def is_service(self) -> bool:
        """Is the part one of the action's services (else one of its topics)?"""
        return self.provider_kind.startswith("Service")

    def class_for(self, action_cls: str) -> str:
        """The part's class for action class ``action_cls`` (``pkg/action/T``)."""
        return self.cls.replace("{T}", action_cls)


PARTS = (
    Part("send_goal", "ServiceProvider", "ServiceClient", "{T}_SendGoal"),
    Part("get_result", "ServiceProvider", "ServiceClient", "{T}_GetResult"),
    Part("cancel_goal", "ServiceProvider", "ServiceClient", CANCEL),
    Part("feedback", "Publisher", "Subscriber", "{T}_FeedbackMessage"),
    Part("status", "Publisher", "Subscriber", STATUS, ACTION_STATUS),
)


def is_action_type(itype: object) -> bool:
    """Is ``itype`` (an iType string) one of :data:`ACTION_TYPES`?"""
    return itype in ACTION_TYPES


def check_action_class(cls: str) -> str:
    """``cls`` if it names a ROS 2 action (``pkg/action/T``); else :class:`ValueError`."""
    parts = cls.strip("/").split("/") if isinstance(cls, str) else []
    if len(parts) != 3 or parts[1] != "action" or not parts[0] or not parts[2]:
        raise ValueError(f"an action interface's class must be a ROS 2 action type 'pkg/action/Type', got {cls!r}")
    return cls.strip("/")


def part_addr(addr: str, part: Part) -> str:
    """The ROS 2 name of ``part`` of the action at ``addr``."""
    return f"{addr.rstrip('/')}/_action/{part.name}"


def expand_interface(entry: dict) -> list[dict]:
    """The five interface entries (config keys ``eTag``, ``iTag``, ``iType``, ``iCls``, ``addr``,
    ``qos``, and any other keys copied) of one action entry. ``addr`` defaults to ``/iTag``.
    Raises :class:`ValueError` for a class that is not an action type."""
    action_kind, side = entry["iType"][:-len(_side(entry["iType"]))], _side(entry["iType"])
    cls = check_action_class(entry["iCls"])
    addr = entry.get("addr") or "/" + entry["iTag"]
    out = []
    for part in PARTS:
        kind = part.provider_kind if action_kind == "ActionProvider" else part.client_kind
        e = {**entry, "iTag": f"{entry['iTag']}.{part.name}", "iType": kind + side, "iCls": part.class_for(cls),
             "addr": part_addr(addr, part)}
        if part.qos is not None:
            e["qos"] = part.qos.as_dict()
        out.append(e)
    return out


def _side(itype: str) -> str:
    return next(s for s in SIDES if itype.endswith(s))


def expand_connection(tag_a: str, tag_b: str) -> list[tuple[str, str]]:
    """The five connections between the parts of actions ``tag_a`` and ``tag_b``
    (``endpointTag/interfaceTag`` each), the topics first: a goal sent as soon as its service is
    wired then finds its feedback and status wired already, and misses none of them."""
    ordered = sorted(PARTS, key=lambda p: p.is_service)
    return [(f"{tag_a}.{p.name}", f"{tag_b}.{p.name}") for p in ordered]


def goal_topics(service: str) -> tuple[str, ...]:
    """The ROS 2 names of the feedback and status topics of the action whose ``send_goal`` service
    is ``service`` (``NAME/_action/send_goal``); ``()`` for any other service. A goal should go to
    its server only once these are matched (rcl_action's ``rcl_action_server_is_available`` asks the
    same of an action client): DDS drops a volatile message its reader was not matched for yet, and
    a goal's first feedback would be lost."""
    suffix = "/_action/send_goal"
    if not isinstance(service, str) or not service.endswith(suffix):
        return ()
    addr = service[:-len(suffix)]
    return tuple(part_addr(addr, p) for p in PARTS if not p.is_service)


def call_timeout(cls: str) -> float:
    """s a call of service class ``cls`` may wait for its response: :data:`RESULT_TIMEOUT` for an
    action's ``get_result`` (``pkg/action/T_GetResult``), else :data:`SERVICE_TIMEOUT`."""
    return RESULT_TIMEOUT if isinstance(cls, str) and "/action/" in cls and cls.endswith("_GetResult") \
        else SERVICE_TIMEOUT
