"""The rosapi services rosbridge clients use to look at the graph (roslibpy's ``Ros.get_topics``,
``get_services``, ``get_topic_type``, ``get_service_type``; roslibjs' ``getTopics``...), answered
from a container's bus as :meth:`rce.bus.core.Bus.describe` gives it. Request and response
fields are those of the ``rosapi`` package's ``.srv`` files (rosbridge_suite)."""
from __future__ import annotations

from typing import Any

from rce.errors import ProtocolError


def _topics(graph: dict, args: dict) -> dict:
    entries = graph.get("topics", [])
    return {"topics": [t["name"] for t in entries], "types": [t.get("type", "") for t in entries]}


def _services(graph: dict, args: dict) -> dict:
    return {"services": [s["name"] for s in graph.get("services", [])]}


def _type_of(kind: str, key: str):
    def answer(graph: dict, args: dict) -> dict:
        name = args.get(key)
        for entry in graph.get(kind, []):
            if entry.get("name") == name:
                return {"type": entry.get("type", "")}
        return {"type": ""}            # rosapi answers an empty type for a name it does not know
    return answer


# service name -> answer(graph, request args) -> response values
ROSAPI = {"/rosapi/topics": _topics, "/rosapi/services": _services,
          "/rosapi/topic_type": _type_of("topics", "topic"), "/rosapi/service_type": _type_of("services", "service")}


def rosapi_answer(service: str, args: Any, graph: dict) -> dict:
    """The response values of rosapi service ``service`` (a key of :data:`ROSAPI`) for request
    ``args`` (a dict) on ``graph`` (a bus describe). Raises :class:`ProtocolError` for another
    service or args that are not an object."""
    answer = ROSAPI.get(service)
    if answer is None:
        raise ProtocolError(f"rosapi service {service!r} is not served; served: {', '.join(ROSAPI)}")
    if not isinstance(args, dict):
        raise ProtocolError(f"call_service {service!r}: args must be an object, got {args!r}")
    return answer(graph, args)
