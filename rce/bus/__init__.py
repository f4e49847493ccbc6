"""A container's bus: topics, services and parameters of its nodes, sans I/O (:mod:`.core`), and
the server nodes connect to (:mod:`.server`)."""
from rce.bus.core import Bus
from rce.bus.server import BusServer

__all__ = ["Bus", "BusServer"]
