"""Fixtures the message and node tests share."""
from __future__ import annotations

import asyncio

import pytest
from memlink import pipe
from rosbags.typesys import Stores, get_typestore

import rce.node
from rce.bus.core import Bus
from rce.bus.server import BusServer
from rce.messages import MessageRegistry


@pytest.fixture(scope="module")
def reg() -> MessageRegistry:
    """A registry shared by the read-only tests of a module."""
    return MessageRegistry()


@pytest.fixture(scope="module")
def ts():
    """rosbags' own typestore, independent of the registry, as the reference serializer."""
    return get_typestore(Stores.ROS1_NOETIC)


@pytest.fixture
async def bus(monkeypatch):
    """A bus and its server; ``rce.node.init_node(bus="mem")`` connects to it."""
    b = Bus("mem-bus")
    server = BusServer(b)

    async def open_unix_connection(path, limit=None):
        (ra, wa), (rb, wb) = pipe()
        await server._accept(rb, wb)           # what the server's listener does with a new connection
        return ra, wa
    monkeypatch.setattr(asyncio, "open_unix_connection", open_unix_connection)
    nodes = []

    async def node(name: str) -> rce.node.Node:
        n = await rce.node.init_node(name, bus="mem", argv=[])
        nodes.append(n)
        return n
    yield b, server, node
    for n in nodes:
        await n.close()
    await server.close()
