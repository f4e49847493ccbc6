"""The rosapi services rosbridge clients use to look at the graph and its parameters (roslibpy's
``Ros.get_topics``, ``get_services``, ``get_topic_type``, ``get_service_type``, ``get_params``,
``Param``; roslibjs' ``getTopics``, ``getParams``, ``ROSLIB.Param``...), answered from a
container's bus. Request and response fields are those of the ``rosapi`` package's ``.srv``
files (rosbridge_suite): ``GetParam {name, default} -> {value}`` and ``SetParam {name, value}``
carry values as JSON text, as rosapi's ``params.py`` does (a missing parameter answers
``default`` parsed as JSON, or the text itself when it is not JSON; without a default, ``null``).
Types are answered as the graph names them: ``std_msgs/msg/String`` for a ROS 2 topic, as the ROS 2
rosapi does. ``action_servers`` (ROS 2 rosapi's ``GetActionServers``) lists the actions the graph serves: the
names ``NAME`` whose ``NAME/_action/send_goal`` service is on it (:mod:`rce.interfaces.actions`).
"""
from __future__ import annotations

import json
from typing import Any, Protocol

from rce.plumbing.errors import NotFound, ProtocolError
from rce.interfaces.naming import resolve


class Graph(Protocol):
    """What rosapi needs of a session (:class:`rce_robot.rosbridge.session.RosbridgeSession`)."""

    async def describe(self) -> dict:
        """The container's bus, :meth:`rce.bus.core.Bus.describe`."""

    async def get_param(self, name: str) -> Any:
        """A parameter's JSON value; NotFound if not set."""

    async def set_param(self, name: str, value: Any) -> None:
        """Set a parameter (through the master, as a robot's CN ``setParam``)."""

    async def delete_param(self, name: str) -> None:
        """Delete a parameter (as a robot's CN ``deleteParam``)."""


def _name(args: dict, key: str = "name") -> str:
    v = args.get(key)
    if not isinstance(v, str) or not v:
        raise ProtocolError(f"rosapi: {key!r} must be a non-empty string, got {v!r}")
    return resolve(v, "/")


def _json_arg(args: dict, key: str) -> Any:
    text = args.get(key)
    if not isinstance(text, str):
        raise ProtocolError(f"rosapi: {key!r} must be JSON text (a string), got {text!r}")
    try:
        return json.loads(text)
    except ValueError:
        raise ProtocolError(f"rosapi: {key!r} must be JSON text (rosapi's SetParam takes the value as JSON), "
                            f"got {text!r}") from None


async def _topics(graph: Graph, args: dict) -> dict:
    entries = (await graph.describe()).get("topics", [])
    return {"topics": [t["name"] for t in entries], "types": [t.get("type", "") for t in entries]}


async def _services(graph: Graph, args: dict) -> dict:
    return {"services": [s["name"] for s in (await graph.describe()).get("services", [])]}


def _type_of(kind: str, key: str):
    async def answer(graph: Graph, args: dict) -> dict:
        name = args.get(key)
        for entry in (await graph.describe()).get(kind, []):
            if entry.get("name") == name:
                return {"type": entry.get("type", "")}
        return {"type": ""}            # rosapi answers an empty type for a name it does not know
    return answer


async def _action_servers(graph: Graph, args: dict) -> dict:
    suffix = "/_action/send_goal"
    return {"action_servers": sorted(s["name"][:-len(suffix)] for s in (await graph.describe()).get("services", [])
                                     if s["name"].endswith(suffix))}


async def _get_param(graph: Graph, args: dict) -> dict:
    name, default = _name(args), args.get("default") or ""
    try:
        value = await graph.get_param(name)
    except NotFound:
        try:
            value = json.loads(default) if default else None
        except ValueError:
            value = default
    return {"value": json.dumps(value)}


async def _set_param(graph: Graph, args: dict) -> dict:
    await graph.set_param(_name(args), _json_arg(args, "value"))
    return {}


async def _param_names(graph: Graph, args: dict) -> dict:
    return {"names": list((await graph.describe()).get("params", []))}


async def _has_param(graph: Graph, args: dict) -> dict:
    name = _name(args).rstrip("/")
    names = (await graph.describe()).get("params", [])
    return {"exists": any(n == name or n.startswith(name + "/") for n in names)}


async def _delete_param(graph: Graph, args: dict) -> dict:
    await graph.delete_param(_name(args))
    return {}


# service name -> answer(graph, request args) -> response values
ROSAPI = {"/rosapi/topics": _topics, "/rosapi/services": _services,
          "/rosapi/topic_type": _type_of("topics", "topic"), "/rosapi/service_type": _type_of("services", "service"),
          "/rosapi/get_param": _get_param, "/rosapi/set_param": _set_param,
          "/rosapi/get_param_names": _param_names, "/rosapi/has_param": _has_param,
          "/rosapi/delete_param": _delete_param, "/rosapi/action_servers": _action_servers}


async def rosapi_answer(service: str, args: Any, graph: Graph) -> dict:
    """The response values of rosapi service ``service`` (a key of :data:`ROSAPI`) for request
    ``args`` (a dict) on ``graph``. Raises :class:`ProtocolError` for another service or bad
    args, and what ``graph`` raises (NotFound, a refused request...)."""
    answer = ROSAPI.get(service)
    if answer is None:
        raise ProtocolError(f"rosapi service {service!r} is not served; served: {', '.join(ROSAPI)}")
    if not isinstance(args, dict):
        raise ProtocolError(f"call_service {service!r}: args must be an object, got {args!r}")
    return await answer(graph, args)
