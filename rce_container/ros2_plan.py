"""Sans-I/O rules of a container's ROS 2 graph: which packages hold ROS 2 nodes, what a ROS 2 node
is started with, and what the relay (:mod:`rce_container.ros2_relay`) bridges between the
container's bus and its ROS 2 graph, with which QoS.

- A package holds ROS 2 nodes when its ``package.xml`` (REP 140/149, as ament packages have it)
  depends on ``rclpy`` or ``rclcpp`` (:func:`is_ros2_package`).
- A node starts with the arguments ``ros2 launch`` gives it (:func:`node_args`): ``--ros-args -r
  __node:=NAME -r __ns:=NS --params-file FILE``, FILE holding the bus's parameters
  (:func:`params_yaml`).
- What is bridged follows the rule of ROS 1's relay (ros1_bridge's ``dynamic_bridge``;
  :func:`rce_container.ros1_plan.plan`): a topic one way where one side publishes and the other
  subscribes, a service where one side provides it and the other does not. Every ROS 2 node's own
  parameter and type-description services (:data:`NODE_SERVICES`) stay in ROS 2; hidden names
  (an action's ``NAME/_action/...`` parts) are bridged like any other, so actions are carried as
  their five parts.
- QoS (:func:`request_for`, :func:`offer_for`), the way rosbag2 (``adapt_request_to_offers``) and
  zenoh-bridge-ros2dds pick theirs: the relay's subscription takes what every publisher in the
  container offers (reliable only when all are, transient local only when all are); its publisher
  offers what the subscriptions need (reliable when one asks for it, transient local when one does,
  then keeping the last message for late subscribers, as ROS 1 latching does). DDS does not tell a
  remote endpoint's history depth, so the depths are the relay's own (:data:`SUB_DEPTH`,
  :data:`PUB_DEPTH`, :data:`LATCHED_DEPTH`). Deadline, lifespan and liveliness stay DDS's defaults:
  a node that asks for them from a bridged topic is an incompatible pair, reported.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from rce.ros2.domains import DOMAIN_IDS   # the ids a container is given (rce.ros2.domains)
from rce.interfaces.classes import is_ros2_name
from rce.interfaces.qos import QoS
from rce.interfaces.naming import join
from rce_container.ros1_plan import GraphView, depends_on
from rce_container.ros1_plan import plan as bridge_plan

#: Dependencies that make a package a ROS 2 package (its nodes join the container's ROS 2 graph).
ROS2_CLIENT_LIBS = ("rclpy", "rclcpp")
#: Bus and ROS 2 names of the relays start with this; relays never bridge them.
RELAY_PREFIX = "/rce_ros2_relay"
#: Services every rclpy/rclcpp node provides about itself (parameters, type descriptions, logger
#: levels, https://docs.ros.org/en/jazzy/Concepts/Basic/About-Parameters.html): they stay in ROS 2.
NODE_SERVICES = tuple(f"/{s}" for s in (
    "describe_parameters", "get_parameter_types", "get_parameters", "list_parameters", "set_parameters",
    "set_parameters_atomically", "get_type_description", "get_logger_levels", "set_logger_levels"))
SUB_DEPTH = 100       # messages the relay's subscriptions hold for its executor (DDS drops beyond)
PUB_DEPTH = 10        # messages the relay's volatile publishers keep for reliable resends (ROS 2's default)
LATCHED_DEPTH = 1     # messages its transient-local publishers keep for late subscribers (ROS 1 latching)
INT64 = (-2**63, 2**63 - 1)
_PARAM_WORD = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def relay_name(cid: int) -> str:
    """Global name of container ``cid``'s ROS 2 relay, the same on its bus and in its ROS 2 graph
    (a container group shares one bus: one relay per container needs its own name)."""
    return f"{RELAY_PREFIX}_c{cid}"


def is_ros2_package(pkg_dir: Path) -> bool:
    """True when ``pkg_dir/package.xml`` depends on :data:`ROS2_CLIENT_LIBS`.

    Raises :class:`~rce.plumbing.errors.RequestError` naming the file for a package.xml that is not
    well-formed XML."""
    return depends_on(pkg_dir, ROS2_CLIENT_LIBS)


def domain_of(cid: int) -> int:
    """The ROS 2 domain id of container ``cid`` when it has its own network namespace (nothing
    else can reach its graph there; a per-container id is one more wall)."""
    return DOMAIN_IDS[cid % len(DOMAIN_IDS)]


def node_args(name: str, namespace: str, params_file: str | None) -> list[str]:
    """The ROS 2 arguments of a node named ``name`` in ``namespace`` (absolute) reading its
    parameters from ``params_file`` (None: none), as ``ros2 launch`` passes them."""
    args = ["--ros-args", "-r", f"__node:={name}", "-r", f"__ns:={join('/', namespace)}"]
    return args + (["--params-file", params_file] if params_file else [])


# -- parameters --------------------------------------------------------------------------------
def _param_value(value: Any) -> Any:
    """``value`` as a ROS 2 parameter holds it; ValueError saying why it cannot."""
    if isinstance(value, bool | str):
        return value
    if isinstance(value, int):
        if not INT64[0] <= value <= INT64[1]:
            raise ValueError("an integer beyond 64 bits")
        return value
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError("not a finite number")
        return value
    if not isinstance(value, list):
        raise ValueError(f"a {type(value).__name__}, which no ROS 2 parameter type holds")
    if not value:
        raise ValueError("an empty list (ROS 2 cannot tell its type)")
    if all(isinstance(v, bool) for v in value) or all(isinstance(v, str) for v in value):
        return list(value)
    numbers = [v for v in value if isinstance(v, int | float) and not isinstance(v, bool)]
    if len(numbers) != len(value):
        raise ValueError("a list that is not all booleans, all numbers or all strings")
    if all(isinstance(v, int) for v in value):
        return [_param_value(v) for v in value]
    return [float(_param_value(v)) for v in value]     # numbers with a float among them: a double array


def ros2_parameters(params: dict[str, Any]) -> tuple[dict[str, Any], dict[str, str]]:
    """The bus's parameters (``{"/a/b": value}``, :attr:`rce.bus.core.Bus.params`) as ROS 2
    parameters: ``({"a.b": value}, {bus name: why not})``. ``/a/b`` becomes ``a.b`` (ROS 2's
    nesting); a name that is not ROS 2's (words ``[A-Za-z_][A-Za-z0-9_]*``) or a value no ROS 2
    parameter type holds (an empty, mixed or nested list, an object, null) is left out, with why."""
    out, skipped = {}, {}
    for bus_name, value in params.items():
        words = bus_name.strip("/").split("/")
        if not all(_PARAM_WORD.fullmatch(w) for w in words):
            skipped[bus_name] = "not a ROS 2 parameter name (words of letters, digits and _)"
            continue
        try:
            out[".".join(words)] = _param_value(value)
        except ValueError as e:
            skipped[bus_name] = str(e)
    return out, skipped


def _nest(params: dict[str, Any]) -> dict[str, Any]:
    tree: dict[str, Any] = {}
    for name, value in params.items():
        *path, leaf = name.split(".")
        d = tree
        for w in path:
            d = d.setdefault(w, {})
        d[leaf] = value
    return tree


def params_yaml(params: dict[str, Any], node: str) -> str:
    """A ROS 2 parameter file (``--params-file``) giving every node ``params`` (``{a.b: value}``,
    :func:`ros2_parameters`) under ``/**``, and node ``node`` (its full name) those under its own
    name without it (``/ns/talker/rate`` -> ``rate``, as ROS 1's ``~rate`` is ``/ns/talker/rate``)."""
    doc: dict[str, Any] = {"/**": {"ros__parameters": _nest(params)}}
    own = ".".join(node.strip("/").split("/")) + "."
    mine = {k[len(own):]: v for k, v in params.items() if k.startswith(own)}
    if mine:
        doc[node] = {"ros__parameters": _nest(mine)}
    return yaml.safe_dump(doc, default_flow_style=False, sort_keys=True)


# -- the graph and the plan --------------------------------------------------------------------
@dataclass(frozen=True)
class Endpoint:
    """A publisher or subscription in the ROS 2 graph: its node's full name, its QoS and, for a
    subscription, what it asks for beyond reliability and durability (``"a deadline of 1 s"``;
    empty: nothing), which the relay's publishers do not offer."""
    node: str
    qos: QoS
    limits: str = ""


@dataclass
class Ros2View:
    """The ROS 2 graph as the relay reads it: ``publishers``/``subscribers``: topic -> endpoints,
    ``types``: topic -> ``pkg/msg/T``, ``services``: service -> provider node, ``service_types``:
    service -> ``pkg/srv/T``."""
    publishers: dict[str, list[Endpoint]] = field(default_factory=dict)
    subscribers: dict[str, list[Endpoint]] = field(default_factory=dict)
    types: dict[str, str] = field(default_factory=dict)
    services: dict[str, str] = field(default_factory=dict)
    service_types: dict[str, str] = field(default_factory=dict)

    def view(self) -> GraphView:
        """The same graph as the bridging rule reads it (node names only)."""
        return GraphView({t: {e.node for e in es} for t, es in self.publishers.items()},
                         {t: {e.node for e in es} for t, es in self.subscribers.items()},
                         dict(self.types), dict(self.services), dict(self.service_types))


@dataclass
class Ros2Plan:
    """What the relay should bridge: ``to_ros``/``to_bus``: topic -> (type, the QoS of the relay's
    publisher in ROS 2 / of its subscription there), ``services_to_bus``/``services_to_ros``:
    service -> type, ``conflicts``: name -> why it is left alone, ``incompatible``: topic -> which
    subscriptions the relay's publisher cannot match (bridged all the same: the others get it)."""
    to_ros: dict[str, tuple[str, QoS]] = field(default_factory=dict)
    to_bus: dict[str, tuple[str, QoS]] = field(default_factory=dict)
    services_to_bus: dict[str, str] = field(default_factory=dict)
    services_to_ros: dict[str, str] = field(default_factory=dict)
    conflicts: dict[str, str] = field(default_factory=dict)
    incompatible: dict[str, str] = field(default_factory=dict)


def request_for(offers: list[QoS]) -> QoS:
    """The QoS of a subscription that matches every publisher offering ``offers`` (rosbag2's
    ``adapt_request_to_offers``): reliable only when all are, transient local only when all are."""
    return QoS(reliability="reliable" if offers and all(q.reliability == "reliable" for q in offers) else "best_effort",
               durability="transient_local" if offers and all(q.durability == "transient_local" for q in offers)
               else "volatile", depth=SUB_DEPTH)


def offer_for(requests: list[QoS]) -> QoS:
    """The QoS of a publisher every subscription requesting ``requests`` matches: reliable when
    one asks for it, transient local (keeping the last :data:`LATCHED_DEPTH`) when one does."""
    latched = any(q.durability == "transient_local" for q in requests)
    return QoS(reliability="reliable" if any(q.reliability == "reliable" for q in requests) else "best_effort",
               durability="transient_local" if latched else "volatile", depth=LATCHED_DEPTH if latched else PUB_DEPTH)


def plan(bus: GraphView, ros: Ros2View, me: str) -> Ros2Plan:
    """The bridges the relay named ``me`` (on both graphs) should have now (module doc). A bus
    service of a ROS 1 class is not offered in ROS 2 (a ROS 1 relay of the same container serves it)."""
    base = bridge_plan(bus, ros.view(), me, relay_prefix=RELAY_PREFIX, node_services=NODE_SERVICES, graph="ROS 2")
    p = Ros2Plan(conflicts=dict(base.conflicts))
    for topic, t in base.to_ros.items():
        subs = [e for e in ros.subscribers.get(topic, []) if e.node != me]
        p.to_ros[topic] = (t, offer_for([e.qos for e in subs]))
        unmet = [f"{e.node} asks for {e.limits}" for e in subs if e.limits]
        if unmet:
            p.incompatible[topic] = "; ".join(sorted(set(unmet))) + ", which the relay's publisher does not offer"
    for topic, t in base.to_bus.items():
        p.to_bus[topic] = (t, request_for([e.qos for e in ros.publishers.get(topic, []) if e.node != me]))
    for name in base.services_to_bus:
        if ros.service_types.get(name):
            p.services_to_bus[name] = ros.service_types[name]
    p.services_to_ros = {n: t for n, t in base.services_to_ros.items() if is_ros2_name(t)}
    return p


# -- what the robot is told --------------------------------------------------------------------
def interface_statuses(addrs: dict[int, str], stats: dict) -> dict[int, tuple[str, str]]:
    """``{iid: (status, reason)}`` for the container interfaces (``addrs``: iid -> topic or
    service) whose name the relay could not bridge as asked, from its :meth:`stats
    <rce_container.ros2_relay.Ros2Relay.stats>`: ``incompatible_qos`` (``incompatible``) before
    ``not_bridged`` (``problems``: a type conflict, a type without Python support...)."""
    out = {}
    incompatible, problems = stats.get("incompatible") or {}, stats.get("problems") or {}
    for iid, addr in addrs.items():
        if addr in incompatible:
            out[iid] = ("incompatible_qos", f"ROS 2 {addr}: {incompatible[addr]}")
        elif addr in problems:
            out[iid] = ("not_bridged", f"ROS 2 {addr}: {problems[addr]}")
    return out


def status_changes(old: dict[int, tuple[str, str]], new: dict[int, tuple[str, str]]) -> dict[int, tuple[str, str]]:
    """What to tell the robot going from statuses ``old`` to ``new`` (:func:`interface_statuses`):
    each new or changed one, and ``("ok", "")`` for each that cleared."""
    changes = {iid: s for iid, s in new.items() if old.get(iid) != s}
    changes.update({iid: ("ok", "") for iid in old if iid not in new})
    return changes
