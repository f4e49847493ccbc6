"""Lanes end to end on loopback (docs/lanes.md): a client with lanes joins a bulk link to its session,
bulk data goes on it both ways while control stays on the session's link, the sockets carry their
DSCP marks, the endpoint counts each lane, a cut bulk link joins again on its own, and a join with a
bad token or lane is refused. Real processes, real websockets."""
from __future__ import annotations

import asyncio
import struct
import urllib.request

import pytest

from rce.transport.lane_socket import marks, socket_of
from rce_client.connection import Connection
from rce_client.dial import HandshakeRefused, dial, with_query

pytestmark = pytest.mark.asyncio
STEP = 30.0          # s any one step may take on a loaded machine


@pytest.fixture(scope="module")
def eng(shared_engine):
    return shared_engine


def _string(data: bytes) -> bytes:
    """A ROS 1 serialized std_msgs/String."""
    return struct.pack("<I", len(data)) + data


def _metrics(port: int) -> str:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as resp:
        return resp.read().decode()


def _metric(text: str, name: str) -> float:
    return float(next(x for x in text.splitlines() if x.startswith(name + " ")).split()[1])


async def _echo_container(conn: Connection, ctag: str) -> None:
    """stringEcho in ``ctag``; robot-side: a control pair (converters, std_msgs default: control) and a
    bulk pair (forwarders, ``lane: bulk``) on the same echo topics."""
    rid = conn.robot_id
    await conn.create_container(ctag)
    await conn.add_node(ctag, "echo", "Test", "stringEcho.py")
    for t, itype, addr in (("req", "PublisherInterface", "/stringEchoReq"),
                           ("resp", "SubscriberInterface", "/stringEchoResp"),
                           ("breq", "PublisherInterface", "/stringEchoReq"),
                           ("bresp", "SubscriberInterface", "/stringEchoResp")):
        await conn.add_interface(ctag, t, itype, "std_msgs/String", addr)
    await conn.add_interface(rid, "req", "SubscriberConverter", "std_msgs/String")
    await conn.add_interface(rid, "resp", "PublisherConverter", "std_msgs/String")
    await conn.add_interface(rid, "breq", "SubscriberForwarder", "std_msgs/String", lane="bulk")
    await conn.add_interface(rid, "bresp", "PublisherForwarder", "std_msgs/String", lane="bulk")
    for t in ("req", "resp", "breq", "bresp"):
        await conn.connect(f"{ctag}/{t}", f"{rid}/{t}")
    await conn.wait_interfaces_up(["req", "resp", "breq", "bresp"], timeout=STEP)


async def _echo(pub, got: asyncio.Queue, msg, want) -> None:
    """Publish ``msg`` until ``want(received)`` arrives (the node may subscribe after the interfaces are up)."""
    async def until() -> None:
        while True:
            await pub.publish(msg)
            try:
                while not want(await asyncio.wait_for(got.get(), 0.5)):
                    pass
                return
            except asyncio.TimeoutError:
                continue
    await asyncio.wait_for(until(), STEP)


async def test_bulk_goes_on_its_own_link_control_on_the_sessions_and_a_cut_bulk_link_joins_again(engine_ws_impls):
    eng = engine_ws_impls
    conn = await Connection.connect(eng.master_url, "testUser", "testUser", "lanesR", allow_reconnect=True,
                                    lanes=True, bulk_rate=50e6)
    lanes_status: asyncio.Queue = asyncio.Queue()
    conn.on_status(lambda st: lanes_status.put_nowait(st) if st.get("topic") == "lanes" else None)
    try:
        await conn.bulk.wait_up(STEP)
        assert marks(socket_of(conn.bulk.ws)) == 0x20 and marks(socket_of(conn.ws)) == 0xB8    # CS1, EF
        await _echo_container(conn, "lanesC")
        control, bulk = asyncio.Queue(), asyncio.Queue()
        conn.subscriber("resp", "std_msgs/String", lambda m: control.put_nowait(m["data"]))
        conn.subscriber("bresp", "std_msgs/String", lambda m: bulk.put_nowait(bytes(m)))
        image = b"x" * 200_000                        # cut into 16 KiB frames, both ways
        await _echo(conn.publisher("breq", "std_msgs/String", lane="bulk"), bulk, _string(image),
                    lambda m: m == _string(image))
        await _echo(conn.publisher("req", "std_msgs/String"), control, {"data": "stop"}, lambda m: m == "stop")
        assert conn.bulk.sent >= 1 and conn.bulk.received >= 1       # both ways on the bulk link
        text = _metrics(eng.robot_ready[0]["metrics_port"])
        assert _metric(text, 'rce_robot_lane_messages_sent_total{lane="bulk"}') >= 1
        assert _metric(text, 'rce_robot_lane_messages_sent_total{lane="control"}') >= 1
        assert 'rce_robot_lane_queue_delay_seconds_bucket{lane="bulk",le="0.001"}' in text
        # the endpoint paces the robot's bulk link under the rate it estimates (no --bulk-rate: auto)
        assert _metric(text, 'rce_robot_lane_pacing_rate_bytes{lane="bulk",robot="lanesR",user="testUser"}') > 0
        bulk_st = (await asyncio.wait_for(lanes_status.get(), STEP))["lanes"]["bulk"]
        assert bulk_st["rate_source"] == "estimated" and bulk_st["rate"] > 0 and bulk_st["rate_mode"] in {
            "startup", "cruise", "probe", "drain"}
        assert conn.bulk.pacing() == {"rate_source": "configured", "rate": 50_000_000}

        conn.bulk.ws.transport.abort()                # the bulk link is cut: it joins again on its own
        await conn.bulk.wait_up(STEP, joins=2)
        await _echo(conn.publisher("breq", "std_msgs/String", lane="bulk"), bulk, _string(b"again"),
                    lambda m: m == _string(b"again"))
        assert conn.connected and conn.resumes == 0   # the session's link never dropped
    finally:
        await conn.close()


async def test_a_bulk_join_needs_the_sessions_token_and_names_the_bulk_lane(engine_ws_impls):
    eng = engine_ws_impls
    conn = await Connection.connect(eng.master_url, "testUser", "testUser", "lanesR2", allow_reconnect=True)
    try:
        await asyncio.wait_for(_live(conn), STEP)
        base = with_query(conn.ws_url, userID="testUser", robotID="lanesR2")
        for query, status, says in (({"session": "0" * 64, "lane": "bulk"}, 401, "wrong or expired session token"),
                                    ({"session": conn.session.token, "lane": "control"}, 400, "lane must be 'bulk'")):
            with pytest.raises(HandshakeRefused) as ei:
                await dial(with_query(base, **query), STEP)
            assert ei.value.status == status and says in ei.value.reason
        assert conn.connected
    finally:
        await conn.close()


async def _live(conn: Connection) -> None:
    while conn.session.state != "live":
        await conn._session_changed()
