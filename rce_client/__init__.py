"""The robot side of rce: the client library (:mod:`rce_client.connection`), ``rce-ros``
(:mod:`rce_client.rce_ros`) and the bus tools ``rce-topic``/``rce-service``
(:mod:`rce_client.tools`)."""
from rce_client.connection import Connection, hash_password, login

__all__ = ["Connection", "hash_password", "login"]
