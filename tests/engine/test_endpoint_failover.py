"""Kill -9 of rce-robot, with the robot moving to another robot endpoint
(docs/INTERNALS.md "Session resume", "Moving to another endpoint"), with real processes on loopback.

An engine with two robot task sets. A robot (rce_client, logged in with ``allow_reconnect``) echoes
numbered messages at 10 Hz through a converter to the Test package's stringEcho.py. The test finds
its endpoint in the admin API and kills that rce-robot with SIGKILL. The client finds the endpoint
dead (its dials refused), logs in again and opens a fresh session on the other endpoint; the
master moves the robot there with its interfaces and connections (the robot repeats no CN/CX).
The echoes come back through the other endpoint within SERVED_BOUND s, the container was never
destroyed (same cid), and the messages lost in the gap are counted.
"""
from __future__ import annotations

import asyncio
import time
from urllib.parse import urlsplit

import pytest

from rce.tools.launch import start_engine
from rce_client.connection import Connection
from test_resume import RATE, SETTLE, Echoes, containers, echo_setup, robot_stream

pytestmark = pytest.mark.asyncio

SERVED_BOUND = 5.0     # s from the kill to the first echo through the other endpoint: the client's dials refused
                       # ENDPOINT_GONE_AFTER times (~0.75 s of backoff), a login, a handshake, the interfaces moved
RUN_ON = 1.0           # s the stream runs on after the robot is served again


def endpoint_of(engine, robot: str) -> tuple[str, int]:
    """The name and websocket port of the robot endpoint that robot ``robot`` of testUser is on (admin API)."""
    name = next(r["endpoint"] for r in engine.admin("/api/robots") if r["robot"] == robot)
    ts = next(t for t in engine.admin("/api/tasksets") if t["name"] == name)
    return name, urlsplit(ts["ws_url"]).port


async def test_robot_endpoint_killed_robot_served_through_the_other(tmp_path):
    engine = start_engine(tmp_path / "engine", robot_tasksets=2)
    echoes, moved, lost_links = Echoes(), [], []
    conn = await Connection.connect(engine.master_url, "testUser", "testUser", "moveBot", allow_reconnect=True)
    conn.on_disconnected(lost_links.append)
    conn.on_moved(lambda info: moved.append((time.monotonic(), info)))
    try:
        await echo_setup(conn, "moveC", echoes)
        before = containers(engine)
        assert before["moveC"][1] == "running"
        name, port = endpoint_of(engine, "moveBot")
        i = next(i for i, info in enumerate(engine.robot_ready) if info["ws_port"] == port)
        proc = next(p for p in engine.procs if any(str(a).endswith(f"robot{i}.ready") for a in p.args))
        stop = asyncio.Event()
        stream = asyncio.ensure_future(robot_stream(conn, stop))
        await echoes.until(lambda: len(echoes.got["r"]) >= RATE, SETTLE)

        proc.kill()
        killed_at = time.monotonic()
        proc.wait()
        await echoes.until(lambda: echoes.times[-1] > killed_at, SERVED_BOUND + SETTLE)
        served = next(t for t in echoes.times if t > killed_at) - killed_at
        await asyncio.sleep(RUN_ON)                          # the stream runs on through the other endpoint
        stop.set()
        sent = await stream
        await echoes.until(lambda: echoes.got["r"][-1] == sent - 1, SETTLE)

        got = echoes.got["r"]
        assert got == sorted(set(got)), "each message at most once, in order"
        lost = sent - len(got)
        assert lost_links and len(moved) == 1 and conn.moves == 1 and conn.resumes == 0
        assert urlsplit(moved[0][1]["ws_url"]).port == engine.robot_ready[1 - i]["ws_port"]
        new_name, new_port = endpoint_of(engine, "moveBot")
        assert new_name != name and new_port == engine.robot_ready[1 - i]["ws_port"]
        assert containers(engine) == before, "the container was never destroyed (same cid, running)"
        assert conn.interfaces == {"req": True, "resp": True} and not conn.closed
        assert not [r for r in engine.admin("/api/robots") if r["robot"] != "moveBot"]
        print(f"\nendpoint failover: kill -9 -> first echo through the other endpoint {served * 1000:.0f} ms; "
              f"{sent} messages sent, {lost} lost in the gap ({conn.moved_lost} in flight or sent during the "
              f"gap, lost with the dead endpoint)")
        assert served < SERVED_BOUND
        assert lost <= (served + 1.0) * RATE, "only the messages of the gap are lost"
    finally:
        await conn.close()
        engine.stop()
