"""A robot's disconnect names the session it ends (rce_master.server.Master's robot_connected and
robot_disconnected ops, in process): an old session's late end leaves the robot's newer login."""
from __future__ import annotations

import pytest

from rce.transport.cluster_auth import ClusterKey
from rce_master.server import ROBOT_SET_OPS, Master

ENDPOINT = 5      # the robot endpoint's task set id


@pytest.mark.asyncio
async def test_an_old_sessions_late_disconnect_leaves_the_new_login():
    m = Master(admin_token="t", cluster_key=ClusterKey.generate())
    ops = ROBOT_SET_OPS.handlers(m, context=ENDPOINT)       # as the endpoint's link serves them
    await ops["robot_connected"]({"user": "u", "robot": "r", "session": "a"})
    await ops["robot_disconnected"]({"user": "u", "robot": "r", "session": "a"})
    assert m.state.robot("u", "r") is None, "a session's own end ends it"
    await ops["robot_connected"]({"user": "u", "robot": "r", "session": "b"})
    await ops["robot_disconnected"]({"user": "u", "robot": "r", "session": "a"})     # a's end, late
    assert m.state.robot("u", "r") is not None, "the new login keeps its namespace"
    await ops["robot_disconnected"]({"user": "u", "robot": "r"})     # an older endpoint names none
    assert m.state.robot("u", "r") is None
