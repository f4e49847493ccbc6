"""The robot side of rce: the client library (:mod:`rce_client.connection`), ``rce-ros``
(:mod:`rce_client.rce_ros`) and the bus tools ``rce-topic``/``rce-service``
(:mod:`rce_client.tools`).

The package's names (:class:`~rce_client.connection.Connection`, ``hash_password``, ``login``)
import :mod:`rce_client.connection` on first use, so that a bus tool, which talks to a local bus
and not to the cloud, does not load the websocket client and the robot protocol."""
from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rce_client.connection import Connection, hash_password, login

__all__ = ["Connection", "hash_password", "login"]


def __getattr__(name: str):
    """``rce_client.Connection`` (...): the name from :mod:`rce_client.connection`, imported then."""
    if name in __all__:
        from rce_client import connection
        return getattr(connection, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
