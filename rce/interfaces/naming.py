"""ROS graph names (ROS wiki "Names"): global ``/a/b``, relative ``b`` (resolved in the
node's namespace) and private ``~b`` (resolved under the node's own name)."""
from __future__ import annotations

import re

from rce.plumbing.errors import RequestError

_VALID = re.compile(r"^[~/]?([A-Za-z_][A-Za-z0-9_]*)?(/[A-Za-z_][A-Za-z0-9_]*)*/?$")


def validate_name(name: str, what: str = "name") -> str:
    """Return ``name`` if it is a legal ROS graph name, else raise :class:`RequestError`."""
    if not isinstance(name, str) or not name or not _VALID.match(name) or "//" in name:
        raise RequestError(f"illegal {what} {name!r}: ROS names are [~/]word(/word)* with words [A-Za-z_][A-Za-z0-9_]*")
    return name


def join(ns: str, name: str) -> str:
    """Join namespace and name into a normalised global name (``/ns/name``)."""
    parts = [p for p in (ns + "/" + name).split("/") if p]
    return "/" + "/".join(parts)


def resolve(name: str, namespace: str = "/", node_name: str | None = None) -> str:
    """Resolve ``name`` as ROS does for a node named ``node_name`` in ``namespace``.

    ``resolve("b", "/ns")`` -> ``/ns/b``; ``resolve("~p", "/ns", "n")`` -> ``/ns/n/p``;
    ``resolve("/g", "/ns")`` -> ``/g``. Raises :class:`RequestError` for an illegal name,
    or a private name without a node."""
    validate_name(name)
    if name.startswith("/"):
        return join("/", name)
    if name.startswith("~"):
        if not node_name:
            raise RequestError(f"private name {name!r} needs a node")
        return join(join(namespace, node_name), name[1:])
    return join(namespace or "/", name)
