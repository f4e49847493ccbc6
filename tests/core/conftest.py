"""Fixtures the message tests share."""
from __future__ import annotations

import pytest
from rosbags.typesys import Stores, get_typestore

from rce.messages import MessageRegistry


@pytest.fixture(scope="module")
def reg() -> MessageRegistry:
    """A registry shared by the read-only tests of a module."""
    return MessageRegistry()


@pytest.fixture(scope="module")
def ts():
    """rosbags' own typestore, independent of the registry, as the reference serializer."""
    return get_typestore(Stores.ROS1_NOETIC)
