"""Robot session resume (docs/INTERNALS.md "Session resume"), with real
processes on loopback. The robot's link runs through a TCP proxy the test owns (rce/transport/tcpproxy.py):
``cut()`` drops every connection (RST both ways) and refuses new ones until ``restore()``.

- A robot (rce_client, ``allow_reconnect``) echoes numbered messages at 10 Hz through a converter
  to the Test package's stringEcho.py while the cloud publishes its own numbered stream into the
  container (admin API) at 10 Hz; the link is cut for 5 s. The session resumes: every message of
  both streams arrives exactly once and in order, the containers were never destroyed, the robot
  gets ``ST session resumed`` with 0 dropped, and the resume takes less than RESUME_BOUND s from
  the link's return to the first message delivered. A wrong token is refused (401); the right one
  takes over a link the endpoint still holds; a new login ends a detached session.
- With a state stream (lane ``state``) and a command stream (lane ``control``) each way, a 5 s cut
  resends of each state interface only its newest, counted as superseded on the side that dropped the
  others, and every command once, in order.
- With ``rce-robot --grace 2`` a 5 s cut ends the session: the master destroys the containers
  only after the grace, and the robot's resume is refused like a bad password.
- A 2013 client (no opt-in) sees today's protocol: no ST session, no seq; its lost link ends its
  session at once and it logs in again right away.
"""
from __future__ import annotations

import asyncio
import hashlib
import json
import time

import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from rce.tools.launch import start_engine
from rce.transport.tcpproxy import TcpProxy
from echo import echo_interfaces
from rce_client.connection import RECONNECT_WAIT_MAX, Connection
from wsclient import RawRobot

pytestmark = pytest.mark.asyncio

RATE = 10.0                   # Hz of each numbered stream
CUT = 5.0                     # s the link is down
GRACE_SHORT = 2.0             # s, rce-robot --grace of the second test
RESUME_BOUND = RECONNECT_WAIT_MAX + 1.0   # s from the link's return to the first message delivered: one backoff
                                          # step of the client, then a handshake and the resend on loopback
HANDSHAKE_TO_FIRST_BOUND = 0.25   # s from the new link being open to the first message delivered (ST resumed,
                                  # the resend): the protocol's own cost, under 1 ms on loopback, room for load
SETTLE = 20.0                 # s to wait for the streams to drain after the resume


class Echoes:
    """What the robot receives on ``resp``: the numbers of each stream (prefix ``r``: the robot's own,
    ``c``: the cloud's), in order, and when each message arrived."""

    def __init__(self):
        self.got: dict[str, list[int]] = {"r": [], "c": [], "warm": []}
        self.times: list[float] = []
        self.new = asyncio.Event()

    def __call__(self, msg: dict) -> None:
        text = msg["data"]
        kind, _, n = text.partition(":")
        self.got[kind].append(int(n or 0))
        self.times.append(time.monotonic())
        self.new.set()

    async def until(self, pred, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while not pred():
            self.new.clear()
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"timed out; received {({k: len(v) for k, v in self.got.items()})}")
            try:
                await asyncio.wait_for(self.new.wait(), left)
            except asyncio.TimeoutError:
                pass


async def echo_setup(conn: Connection, ctag: str, echoes: Echoes) -> None:
    """Container ``ctag`` with stringEcho.py, robot-side converters ``req`` (to it) and ``resp`` (from it);
    returns once an echo came back (the node subscribes a moment after the interfaces are up)."""
    rid = conn.robot_id
    await conn.create_container(ctag)
    await conn.add_node(ctag, "echo", "Test", "stringEcho.py")
    await conn.configure({"addInterfaces": echo_interfaces(ctag, rid)})
    conn.subscriber("resp", "std_msgs/String", echoes)
    await conn.send("CX", {"connect": [{"tagA": f"{ctag}/{t}", "tagB": f"{rid}/{t}"} for t in ("req", "resp")]})
    await conn.wait_interfaces_up(["req", "resp"])
    pub = conn.publisher("req", "std_msgs/String")
    for _ in range(100):
        await pub.publish({"data": "warm:"})
        try:
            await echoes.until(lambda: echoes.got["warm"], 0.2)
            return
        except AssertionError:
            continue
    raise AssertionError("no echo from stringEcho.py")


async def robot_stream(conn: Connection, stop: asyncio.Event) -> int:
    """Publish ``r:0``, ``r:1``, ... at RATE until ``stop``; returns how many."""
    pub = conn.publisher("req", "std_msgs/String")
    n = 0
    while not stop.is_set():
        await pub.publish({"data": f"r:{n}"})
        n += 1
        try:
            async with asyncio.timeout(1 / RATE):               # the stream's clock
                await stop.wait()
        except TimeoutError:
            pass
    return n


async def cloud_stream(engine, ctag: str, stop: asyncio.Event) -> int:
    """Publish ``c:0``, ``c:1``, ... into the container's /stringEchoReq at RATE (admin API) until ``stop``."""
    n = 0
    while not stop.is_set():
        await asyncio.to_thread(engine.admin, f"/api/containers/testUser/{ctag}/publish",
                                {"topic": "/stringEchoReq", "type": "std_msgs/String", "msg": {"data": f"c:{n}"}})
        n += 1
        try:
            async with asyncio.timeout(1 / RATE):
                await stop.wait()
        except TimeoutError:
            pass
    return n


def containers(engine) -> dict[str, tuple[int, str]]:
    return {c["ctag"]: (c["cid"], c["state"]) for c in engine.admin("/api/containers")}


async def test_link_cut_for_5s_resumes_with_nothing_lost(engine_ws_impls):
    engine = engine_ws_impls
    proxy = await TcpProxy(engine.robot_ready[0]["ws_port"]).start()
    echoes, resumed, lost_links, reconnected = Echoes(), [], [], []
    conn = await Connection.open(proxy.url, "testUser", "testUser", "resumeBot", allow_reconnect=True)
    conn.on_disconnected(lost_links.append)
    conn.on_reconnected(lambda _url: reconnected.append(time.monotonic()))
    conn.on_resumed(lambda st: resumed.append((time.monotonic(), st)))
    try:
        await echo_setup(conn, "resumeC", echoes)
        assert conn.session.token and len(conn.session.token) >= 32       # >= 128 random bits, as hex
        before = containers(engine)
        assert before["resumeC"][1] == "running"
        stop = asyncio.Event()
        streams = [asyncio.ensure_future(robot_stream(conn, stop)),
                   asyncio.ensure_future(cloud_stream(engine, "resumeC", stop))]
        await echoes.until(lambda: len(echoes.got["r"]) >= RATE and len(echoes.got["c"]) >= RATE, SETTLE)

        proxy.cut()
        cut_at = time.monotonic()
        while time.monotonic() - cut_at < CUT:            # the master never hears of the drop
            assert containers(engine) == before
            await asyncio.sleep(0.5)                       # the cut's clock, and the poll period
        assert not conn.closed and not conn.connected and lost_links
        proxy.restore()
        await echoes.until(lambda: echoes.times and echoes.times[-1] > proxy.restored_at, SETTLE)
        first = next(t for t in echoes.times if t > proxy.restored_at) - proxy.restored_at
        await asyncio.sleep(1.0)                           # the streams run on after the resume
        stop.set()
        sent_r, sent_c = await asyncio.gather(*streams)
        await echoes.until(lambda: len(echoes.got["r"]) >= sent_r and len(echoes.got["c"]) >= sent_c, SETTLE)

        assert echoes.got["r"] == list(range(sent_r)), "robot -> cloud: each message once, in order"
        assert echoes.got["c"] == list(range(sent_c)), "cloud -> robot: each message once, in order"
        assert sent_r >= (CUT + 2) * RATE * 0.8 and sent_c >= (CUT + 2) * RATE * 0.5
        assert len(resumed) == 1 and resumed[0][1]["status"] == "resumed" and resumed[0][1]["dropped"] == 0
        assert containers(engine) == before, "the containers were never destroyed"
        handshake_to_first = first - (reconnected[-1] - proxy.restored_at)
        print(f"\nresume: link back -> first message delivered {first * 1000:.0f} ms (new link open -> first "
              f"message {handshake_to_first * 1000:.1f} ms; the rest is the wait for the client's next dial and "
              f"the handshake); {sent_r} + {sent_c} messages, 0 lost")
        assert first < RESUME_BOUND and handshake_to_first < HANDSHAKE_TO_FIRST_BOUND
        assert "session=" in proxy.requests[-1].decode() and "password" not in proxy.requests[-1].decode()

        # a wrong token is refused like a bad password
        with pytest.raises(InvalidStatus) as ei:
            await connect(f"{proxy.url}?userID=testUser&robotID=resumeBot&session={'0' * 64}&ack=0")
        assert ei.value.response.status_code == 401 and b"wrong or expired" in ei.value.response.body
        # the right token while the endpoint still holds the link (half-open) takes the session over
        q = conn.session.resume_query()
        thief = await connect(f"{proxy.url}?userID=testUser&robotID=resumeBot&session={q['session']}&ack={q['ack']}")
        st = json.loads(await asyncio.wait_for(thief.recv(), 5))
        assert st["type"] == "ST" and st["data"]["status"] == "resumed" and "seq" not in st
        assert "replaced by a resumed link" in await asyncio.wait_for(conn.wait_closed(), 5)
        # a new login with the password while the session is detached ends that session first
        proxy.cut()                                         # the thief's link is lost: detached
        proxy.restore()
        async with ProxiedRobot(proxy.url, "resumeBot") as r:
            await r.probe()
            assert "resumeC" not in containers(engine)
    finally:
        await conn.close()
        await proxy.close()


def echo_pair(ctag: str, rid: str, req: str, resp: str, lane: str | None) -> list[dict]:
    """CN ``addInterfaces``: container ``ctag``'s stringEcho.py topics and robot ``rid``'s converters ``req``
    and ``resp`` (``lane``: theirs; None: from the class, std_msgs: control)."""
    itfs = [{"endpointTag": ctag, "interfaceTag": req, "interfaceType": "PublisherInterface",
             "className": "std_msgs/String", "addr": "/stringEchoReq"},
            {"endpointTag": ctag, "interfaceTag": resp, "interfaceType": "SubscriberInterface",
             "className": "std_msgs/String", "addr": "/stringEchoResp"},
            {"endpointTag": rid, "interfaceTag": req, "interfaceType": "SubscriberConverter",
             "className": "std_msgs/String"},
            {"endpointTag": rid, "interfaceTag": resp, "interfaceType": "PublisherConverter",
             "className": "std_msgs/String"}]
    for i in itfs[2:]:
        if lane is not None:
            i["lane"] = lane
    return itfs


async def test_a_cut_resends_each_states_newest_and_every_command_once(engine):
    proxy = await TcpProxy(engine.robot_ready[0]["ws_port"]).start()
    conn = await Connection.open(proxy.url, "testUser", "testUser", "newestBot", allow_reconnect=True)
    states, commands, resumed = Echoes(), Echoes(), []
    sent = {"r": 0, "c": 0, "k": 0, "kc": 0}
    at_reconnect: dict[str, int] = {}
    conn.on_reconnected(lambda _url: at_reconnect.update(sent))
    conn.on_resumed(resumed.append)
    try:
        for ctag in ("stateC", "cmdC"):
            await conn.create_container(ctag)
            await conn.add_node(ctag, "echo", "Test", "stringEcho.py")
        await conn.configure({"addInterfaces": echo_pair("stateC", "newestBot", "sreq", "sresp", "state")
                              + echo_pair("cmdC", "newestBot", "creq", "cresp", None)})
        conn.subscriber("sresp", "std_msgs/String", states)
        conn.subscriber("cresp", "std_msgs/String", commands)
        await conn.send("CX", {"connect": [{"tagA": f"{c}/{t}", "tagB": f"newestBot/{t}"}
                                           for c, ts in (("stateC", ("sreq", "sresp")), ("cmdC", ("creq", "cresp")))
                                           for t in ts]})
        await conn.wait_interfaces_up(["sreq", "sresp", "creq", "cresp"])
        pose = conn.publisher("sreq", "std_msgs/String", lane="state")
        cmd = conn.publisher("creq", "std_msgs/String")
        for pub, echoes in ((pose, states), (cmd, commands)):      # both nodes subscribed
            while not echoes.got["warm"]:
                await pub.publish({"data": "warm:"})
                try:
                    await echoes.until(lambda e=echoes: e.got["warm"], 0.2)
                except AssertionError:
                    pass
        stop = asyncio.Event()

        async def robot(pub, kind: str, hz: float) -> None:
            while not stop.is_set():
                await pub.publish({"data": f"r:{sent[kind]}"})
                sent[kind] += 1
                try:
                    async with asyncio.timeout(1 / hz):                   # the stream's clock
                        await stop.wait()
                except TimeoutError:
                    pass

        async def cloud(ctag: str, kind: str, hz: float) -> None:
            while not stop.is_set():
                await asyncio.to_thread(engine.admin, f"/api/containers/testUser/{ctag}/publish",
                                        {"topic": "/stringEchoReq", "type": "std_msgs/String",
                                         "msg": {"data": f"{kind[-1]}:{sent[kind]}"}})
                sent[kind] += 1
                try:
                    async with asyncio.timeout(1 / hz):
                        await stop.wait()
                except TimeoutError:
                    pass

        # states at 10 Hz each way (robot: r, cloud: c); commands at 1 Hz each way (robot: r, cloud: c on cmdC)
        streams = [asyncio.ensure_future(robot(pose, "r", RATE)), asyncio.ensure_future(cloud("stateC", "c", RATE)),
                   asyncio.ensure_future(robot(cmd, "k", 1.0)), asyncio.ensure_future(cloud("cmdC", "kc", 1.0))]
        await states.until(lambda: len(states.got["r"]) >= RATE and len(states.got["c"]) >= RATE, SETTLE)
        proxy.cut()
        before = {k: len(v) for k, v in states.got.items()}
        await asyncio.sleep(CUT)                                    # the cut's clock
        proxy.restore()
        await states.until(lambda: at_reconnect and len(states.got["r"]) > before["r"]
                           and len(states.got["c"]) > before["c"], SETTLE)
        await asyncio.sleep(1.0)                                    # the streams run on after the resume
        stop.set()
        await asyncio.gather(*streams)
        await states.until(lambda: states.got["r"][-1:] == [sent["r"] - 1] and states.got["c"][-1:] == [sent["c"] - 1],
                           SETTLE)
        await commands.until(lambda: len(commands.got["r"]) >= sent["k"] and len(commands.got["c"]) >= sent["kc"],
                             SETTLE)
    finally:
        await conn.close()
        await proxy.close()
    # commands: every one once, in order, both ways
    assert commands.got["r"] == list(range(sent["k"])) and commands.got["c"] == list(range(sent["kc"]))
    assert sent["k"] >= CUT and sent["kc"] >= CUT
    # states: in order, none twice; after the cut, the robot sent its newest and the cloud resent its newest
    for kind in ("r", "c"):
        assert states.got[kind] == sorted(set(states.got[kind])), f"{kind}: in order, once"
    after_r, after_c = states.got["r"][before["r"]:], states.got["c"][before["c"]:]
    # of the robot's states, only the newest at the resume went up (an echo the cloud held may come first)
    assert [n for n in after_r if n < at_reconnect["r"] - 1][1:] == [], after_r[:5]
    assert after_c[0] >= at_reconnect["c"] - 2, after_c[:5]         # the cloud's newest (the admin call's lag)
    # every state missing is counted superseded: the robot's by the client, the cloud's in ST resumed
    missing = sum(len(set(range(sent[k])) - set(states.got[k])) for k in ("r", "c"))
    assert len(resumed) == 1 and resumed[0]["dropped"] == 0
    assert missing == conn.session.superseded + resumed[0]["superseded"] and missing >= CUT * RATE
    assert conn.session.resume_lost == 0
    print(f"\nnewest after a {CUT:g} s cut: {conn.session.superseded} robot states and {resumed[0]['superseded']} "
          f"cloud states superseded; {sent['k']} + {sent['kc']} commands once, in order")


async def test_gap_longer_than_the_grace_ends_the_session(tmp_path):
    engine = start_engine(tmp_path / "engine", robot_args=("--grace", str(GRACE_SHORT)))
    proxy = await TcpProxy(engine.robot_ready[0]["ws_port"]).start()
    echoes = Echoes()
    conn = await Connection.open(proxy.url, "testUser", "testUser", "graceBot", allow_reconnect=True)
    try:
        await echo_setup(conn, "graceC", echoes)
        token = conn.session.token
        proxy.cut()
        cut_at = time.monotonic()
        while "graceC" in containers(engine):
            assert time.monotonic() - cut_at < GRACE_SHORT + 10, "the containers outlived the grace"
            await asyncio.sleep(0.1)                       # the poll period
        gone_after = time.monotonic() - cut_at
        assert gone_after >= GRACE_SHORT, f"the master destroyed the containers {gone_after:.2f} s after the drop"
        await asyncio.sleep(max(0.0, CUT - gone_after))    # the cut's clock
        proxy.restore()
        reason = await asyncio.wait_for(conn.wait_closed(), SETTLE)
        assert "resume" in reason
        with pytest.raises(InvalidStatus) as ei:            # the token died with the session
            await connect(f"{proxy.url}?userID=testUser&robotID=graceBot&session={token}&ack=0")
        assert ei.value.response.status_code == 401
        print(f"\ngrace {GRACE_SHORT:g} s: containers destroyed {gone_after:.2f} s after the drop; client: {reason}")
    finally:
        await conn.close()
        await proxy.close()
        engine.stop()


class ProxiedRobot(RawRobot):
    """A 2013-style client (no resume) that connects through the proxy."""

    def __init__(self, url: str, robot: str):
        super().__init__("", robot)
        self.url = url

    async def __aenter__(self) -> "ProxiedRobot":
        pw = hashlib.sha256(self.password.encode()).hexdigest()
        self.ws = await connect(f"{self.url}?userID={self.user}&robotID={self.robot}&password={pw}",
                                max_size=None, compression=None)
        return self

    async def __aexit__(self, *exc) -> None:
        try:
            await self.ws.close()
        except Exception:
            pass


async def test_a_2013_client_sees_todays_protocol(engine_ws_impls):
    engine = engine_ws_impls
    proxy = await TcpProxy(engine.robot_ready[0]["ws_port"]).start()
    try:
        async with ProxiedRobot(proxy.url, "oldBot") as r:
            await r.send("CC", {"containerTag": "oldC"})
            await r.send("DC", {"containerTag": "noSuchC"})
            frames = [await r.recv()]
            while not (frames[-1]["type"] == "ER" and "noSuchC" in frames[-1]["data"]):
                frames.append(await r.recv())
            assert frames[0]["type"] == "ST" and frames[0]["data"]["topic"] == "container"    # no ST session first
            assert all(set(f) == {"type", "data"} for f in frames), "no seq, no other envelope keys"
            assert containers(engine)["oldC"][1] == "running"
            await r.send("AK", {"seq": 1})                 # not a message type of the 2013 protocol
            assert "unknown type 'AK'" in await r.expect("ER")
            proxy.cut()
            cut_at = time.monotonic()
            while "oldC" in containers(engine):            # its session ends with its link, as today
                assert time.monotonic() - cut_at < 5, "the 2013 robot's containers outlived its link"
                await asyncio.sleep(0.05)                   # the poll period
            proxy.restore()
        async with ProxiedRobot(proxy.url, "oldBot") as r:  # and it logs in again at once (no 409)
            await r.probe()
    finally:
        await proxy.close()
