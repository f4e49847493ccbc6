"""Sans-I/O rules of a container's ROS 1 graph: which packages hold ROS 1 nodes, and what the
relay (:mod:`rce_container.ros1_relay`) bridges between the container's bus and its rosmaster.

- A package holds ROS 1 nodes when its ``package.xml`` (catkin, REP 127 format 1 / REP 140
  format 2 / REP 149 format 3) depends on ``rospy`` or ``roscpp`` (:func:`is_ros1_package`).
- A topic is bridged in one direction when the source graph has a publisher and the other
  graph a subscriber, neither of them the relay itself: the rule of ros1_bridge's
  ``dynamic_bridge`` (ros2/ros1_bridge, ``src/dynamic_bridge.cpp``), so nothing flows that
  nobody reads, and the relay never feeds its own output back (:func:`plan`).
- A service provided in one graph (by a node other than the relay) and not in the other is
  provided in the other by the relay (not a ROS 1 node's own logger services, :data:`NODE_SERVICES`).
- Parameters go one way, bus -> rosmaster: what the bus has is set, what the relay set before
  and the bus no longer has is deleted (:func:`param_changes`).
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rce.plumbing.errors import RequestError

#: Dependencies that make a catkin package a ROS 1 package (its nodes talk to a rosmaster).
ROS1_CLIENT_LIBS = ("rospy", "roscpp")
#: package.xml tags that name a run-time dependency (formats 1, 2 and 3).
DEPEND_TAGS = ("depend", "run_depend", "exec_depend", "build_export_depend")
#: Bus and ROS 1 names of the relays start with this; relays never bridge them.
RELAY_PREFIX = "/rce_ros1_relay"
#: Services every rospy/roscpp node provides about itself (wiki.ros.org/roscpp/Overview/Logging):
#: they stay in the ROS 1 graph.
NODE_SERVICES = ("/get_loggers", "/set_logger_level")


def relay_name(cid: int) -> str:
    """Global name of container ``cid``'s relay, the same on its bus and in its ROS 1 graph
    (the bus is shared by a container group: one relay per container needs its own name)."""
    return f"{RELAY_PREFIX}_c{cid}"


def is_ros1_package(pkg_dir: Path) -> bool:
    """True when ``pkg_dir/package.xml`` depends on :data:`ROS1_CLIENT_LIBS`.

    Raises :class:`RequestError` naming the file for a package.xml that is not well-formed XML."""
    return depends_on(pkg_dir, ROS1_CLIENT_LIBS)


def depends_on(pkg_dir: Path, libs: tuple[str, ...]) -> bool:
    """True when ``pkg_dir/package.xml`` (formats 1 - 3) has a run-time dependency (:data:`DEPEND_TAGS`)
    on one of ``libs``; False without a package.xml.

    Raises :class:`RequestError` naming the file for a package.xml that is not well-formed XML."""
    path = Path(pkg_dir) / "package.xml"
    if not path.is_file():
        return False
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as e:
        raise RequestError(f"{path}: cannot read the ROS package manifest: {e}") from None
    return any((el.text or "").strip() in libs for tag in DEPEND_TAGS for el in root.iter(tag))


@dataclass
class GraphView:
    """One side's view: ``publishers``/``subscribers``: topic -> set of node names,
    ``types``: topic -> ``pkg/Name``, ``services``: service -> provider node name,
    ``service_types``: service -> ``pkg/Name`` (where known)."""
    publishers: dict[str, set[str]] = field(default_factory=dict)
    subscribers: dict[str, set[str]] = field(default_factory=dict)
    types: dict[str, str] = field(default_factory=dict)
    services: dict[str, str] = field(default_factory=dict)
    service_types: dict[str, str] = field(default_factory=dict)


def bus_graph(describe: dict) -> GraphView:
    """A :class:`GraphView` from the bus's ``describe`` (:meth:`rce.bus.core.Bus.describe`)."""
    g = GraphView()
    for t in describe.get("topics", []):
        g.publishers[t["name"]] = set(t["publishers"])
        g.subscribers[t["name"]] = set(t["subscribers"])
        g.types[t["name"]] = t["type"]
    for s in describe.get("services", []):
        g.services[s["name"]] = s["provider"]
        g.service_types[s["name"]] = s["type"]
    return g


def ros1_graph(system_state: list, topic_types: list) -> GraphView:
    """A :class:`GraphView` from rosmaster's ``getSystemState`` (``[publishers, subscribers,
    services]``, each ``[[name, [node...]]...]``) and ``getTopicTypes`` (``[[name, type]...]``),
    ROS Master API (wiki.ros.org/ROS/Master_API)."""
    pubs, subs, srvs = system_state
    g = GraphView(publishers={n: set(ns) for n, ns in pubs}, subscribers={n: set(ns) for n, ns in subs},
              types={n: t for n, t in topic_types})
    g.services = {n: sorted(ns)[0] for n, ns in srvs if ns}
    return g


@dataclass
class Ros1Plan:
    """What the relay should bridge: ``to_ros``/``to_bus``: topic -> type (bus -> ROS 1 and
    ROS 1 -> bus), ``services_to_bus``: ROS 1 services the relay provides on the bus,
    ``services_to_ros``: bus services (-> type) it provides in the ROS 1 graph."""
    to_ros: dict[str, str] = field(default_factory=dict)
    to_bus: dict[str, str] = field(default_factory=dict)
    services_to_bus: set[str] = field(default_factory=set)
    services_to_ros: dict[str, str] = field(default_factory=dict)
    conflicts: dict[str, str] = field(default_factory=dict)   # topic -> why it is left alone (the types differ)


def _others(names: set[str] | None, me: str) -> bool:
    return bool(names and names - {me})


def plan(bus: GraphView, ros: GraphView, me: str, *, relay_prefix: str = RELAY_PREFIX,
         node_services: tuple[str, ...] = NODE_SERVICES, graph: str = "ROS 1") -> Ros1Plan:
    """The bridges the relay named ``me`` (on both graphs) should have now (module doc).
    ``relay_prefix``, ``node_services`` and ``graph`` (its name in messages) describe the ROS graph
    (:mod:`rce_container.ros2_plan` uses the same rule for ROS 2)."""
    p = Ros1Plan()
    for topic in set(bus.publishers) | set(ros.publishers):
        if topic.startswith(relay_prefix):
            continue
        bus_t, ros_t = bus.types.get(topic), ros.types.get(topic)
        if bus_t and ros_t and bus_t != ros_t and ros_t != "*":
            p.conflicts[topic] = f"type conflict: {bus_t} on the bus, {ros_t} in {graph}"
            continue
        if _others(bus.publishers.get(topic), me) and _others(ros.subscribers.get(topic), me):
            p.to_ros[topic] = bus_t
        if _others(ros.publishers.get(topic), me) and _others(bus.subscribers.get(topic), me) and ros_t:
            p.to_bus[topic] = ros_t
    for name, provider in ros.services.items():
        if provider != me and not name.startswith(relay_prefix) and not name.endswith(node_services) \
                and bus.services.get(name, me) == me:
            p.services_to_bus.add(name)
    for name, provider in bus.services.items():
        if provider != me and not name.startswith(relay_prefix) and ros.services.get(name, me) == me:
            p.services_to_ros[name] = bus.service_types[name]
    return p


def bridged(stats: dict, name: str) -> bool:
    """Is topic or service ``name`` bridged, either way, by a relay whose last stats
    (``topics_to_ros``, ``topics_to_bus``, ``services_to_bus``, ``services_to_ros``, as both relays
    give them) are ``stats``?"""
    return any(name in (stats.get(k) or ()) for k in ("topics_to_ros", "topics_to_bus", "services_to_bus",
                                                       "services_to_ros"))


def flatten_params(tree: Any, prefix: str = "/") -> dict[str, Any]:
    """Leaves of a parameter tree (``get_param('/')``) as ``{global name: value}``; an empty
    dict is kept as a leaf (the parameter exists with that value)."""
    if not isinstance(tree, dict) or (not tree and prefix != "/"):
        return {prefix.rstrip("/") or "/": tree}
    out: dict[str, Any] = {}
    for k, v in tree.items():
        out.update(flatten_params(v, f"{prefix}{k}/"))
    return out


def param_changes(bus: dict[str, Any], pushed: dict[str, Any]) -> tuple[dict[str, Any], list[str]]:
    """(to set, to delete) on rosmaster so that what the relay ``pushed`` before becomes ``bus``
    (both ``{global name: value}``); parameters rosmaster got from elsewhere are left alone."""
    to_set = {k: v for k, v in bus.items() if k not in pushed or pushed[k] != v}
    return to_set, sorted(k for k in pushed if k not in bus)
