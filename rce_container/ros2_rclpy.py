"""What the ROS 2 relay (:mod:`rce_container.ros2_relay`) asks of rclpy: type classes by name,
QoS both ways, a reading of the graph, and the parameters of running nodes.

Kept apart from the relay's bridging so that each stays small; everything here runs in the
relay's process (rclpy imported), never in the environment.
"""
from __future__ import annotations

import asyncio
from typing import Any, Callable

from rclpy.duration import Infinite
from rclpy.node import Node as RclpyNode
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, LivelinessPolicy, ReliabilityPolicy
from rclpy.task import Future

from rce.interfaces.qos import QoS
from rce.interfaces.naming import join
from rce_container.ros2_plan import Endpoint, Ros2View

FOREVER_S = 2**31      # s: DDS's "infinite" durations (2^31 - 1 s and more) count as none
SERVICE_POLL = 0.01    # s between two looks at whether a service's server is matched yet


def _finite(duration: Any) -> float | None:
    ns = duration.nanoseconds
    return ns / 1e9 if 0 < ns < Infinite.nanoseconds and ns < FOREVER_S * 10**9 else None


def endpoint(info: Any) -> Endpoint:
    """An :class:`Endpoint` of rclpy's ``TopicEndpointInfo``: its node, its reliability and
    durability, and what it asks beyond them (a deadline, a manual or leased liveliness), which
    the relay's endpoints never offer."""
    p = info.qos_profile
    limits = []
    if (d := _finite(p.deadline)) is not None:
        limits.append(f"a deadline of {d:g} s")
    if p.liveliness == LivelinessPolicy.MANUAL_BY_TOPIC:
        limits.append("manual liveliness")
    if (lease := _finite(p.liveliness_lease_duration)) is not None:
        limits.append(f"a liveliness lease of {lease:g} s")
    q = QoS(reliability="best_effort" if p.reliability == ReliabilityPolicy.BEST_EFFORT else "reliable",
            durability="transient_local" if p.durability == DurabilityPolicy.TRANSIENT_LOCAL else "volatile",
            depth=max(1, p.depth))
    return Endpoint(join(info.node_namespace, info.node_name), q, " and ".join(limits))


def read_graph(node: RclpyNode, me: str) -> Ros2View:
    """The ROS 2 graph as ``node`` (the relay, named ``me``) sees it. A node gone while it is read
    is left out. A service provided by the relay and by another node counts as the other's."""
    v = Ros2View()
    for topic, types in node.get_topic_names_and_types():
        v.types[topic] = types[0] if len(types) == 1 else "*"
        v.publishers[topic] = [endpoint(i) for i in node.get_publishers_info_by_topic(topic)]
        v.subscribers[topic] = [endpoint(i) for i in node.get_subscriptions_info_by_topic(topic)]
    for name, ns in node.get_node_names_and_namespaces():
        full = join(ns, name)
        try:
            services = node.get_service_names_and_types_by_node(name, ns)
        except Exception:        # the node went away between the two calls
            continue
        for service, types in services:
            if v.services.get(service) in (None, me):
                v.services[service], v.service_types[service] = full, types[0]
    return v


async def call(client: Any, request: Any, wait: float) -> Any:
    """``client``'s call with ``request``, awaited on this asyncio loop (the response comes in the
    relay's executor thread). Waits up to ``wait`` s for the server to be matched first (a request
    sent before would be lost). The caller bounds the whole call; cancelled, it is forgotten."""
    loop = asyncio.get_running_loop()
    if not await holds_within(client.service_is_ready, wait):
        raise TimeoutError(f"no server matched within {wait:g} s")
    fut: Future = client.call_async(request)
    done = loop.create_future()

    def settle(f: Future) -> None:
        if done.done():
            return
        if f.cancelled():
            done.cancel()
        elif f.exception() is not None:
            done.set_exception(f.exception())
        else:
            done.set_result(f.result())
    fut.add_done_callback(lambda f: loop.call_soon_threadsafe(settle, f))
    try:
        return await done
    finally:
        if not fut.done():
            client.remove_pending_request(fut)


async def holds_within(ready: Callable[[], bool], wait: float) -> bool:
    """Whether ``ready()`` (a look at DDS's matching, from this asyncio loop) holds within ``wait`` s,
    looked at every :data:`SERVICE_POLL` s."""
    try:
        async with asyncio.timeout(wait):
            while not ready():
                await asyncio.sleep(SERVICE_POLL)
    except TimeoutError:
        return False
    return True


async def set_parameters(node: RclpyNode, target: str, params: dict[str, Any], wait: float) -> dict[str, str]:
    """Set those of ``params`` (``{name: value}``) that node ``target`` (full name) has declared,
    through its ``list_parameters``, ``get_parameter_types`` and ``set_parameters`` services; an
    integer is given as a double where the node declared a double. Returns ``{name: why not}``
    for those the node refused. ``wait``: s for each call."""
    from rcl_interfaces.srv import GetParameterTypes, ListParameters, SetParameters
    clients = {t: node.create_client(t, f"{target}/{n}") for t, n in (
        (ListParameters, "list_parameters"), (GetParameterTypes, "get_parameter_types"),
        (SetParameters, "set_parameters"))}
    try:
        async with asyncio.timeout(wait * 3):
            declared = set((await call(clients[ListParameters], ListParameters.Request(), wait)).result.names)
            names = sorted(set(params) & declared)
            if not names:
                return {}
            types = (await call(clients[GetParameterTypes], GetParameterTypes.Request(names=names), wait)).types
            msgs = [_as_declared(n, params[n], t).to_parameter_msg() for n, t in zip(names, types, strict=True)]
            results = (await call(clients[SetParameters], SetParameters.Request(parameters=msgs), wait)).results
        return {n: r.reason or "refused" for n, r in zip(names, results, strict=True) if not r.successful}
    finally:
        for c in clients.values():
            node.destroy_client(c)


def _as_declared(name: str, value: Any, declared: int) -> Parameter:
    """``value`` as a parameter, an integer (array) widened where the node declared a double (array)."""
    if declared == Parameter.Type.DOUBLE.value and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    elif declared == Parameter.Type.DOUBLE_ARRAY.value and isinstance(value, list):
        value = [float(v) for v in value]
    return Parameter(name, value=value)
