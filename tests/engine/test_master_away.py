"""While the master is away, nothing stops. Real processes on loopback: a robot
echoes numbered messages at 10 Hz through a converter to the Test package's stringEcho.py;
rce-master is killed with SIGKILL and, AWAY s later, started again on the same state file and
ports.

- Meanwhile rce-robot and rce-container keep running, every echo arrives (0 lost, by the
  numbers in the payload), the robot's websocket stays open, a CN gets the ER "the master is
  unavailable" after ``--master-wait``, and a new robot's handshake gets 503 with Retry-After.
- After the restart both task sets re-register on their own with their tids, within
  REREGISTER_BOUND s; a new container (CC, CN, CX) echoes too, and the echo through the first
  container never stopped (no gap longer than MAX_GAP s).
"""
from __future__ import annotations

import asyncio
import itertools
import json
import signal
import time
import urllib.request
from pathlib import Path

import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from rce.tools.launch import start_engine
from rce.transport.masterlink import BACKOFF_CAP
from test_master_restart import ECHO, proc, registered, start_master
from wsclient import RawRobot, login

pytestmark = pytest.mark.asyncio

RATE = 10.0               # Hz of the robot's numbered stream
AWAY = 3.0                # s the master stays dead
MASTER_WAIT = 1.0         # s, rce-robot --master-wait: a request's wait for the absent master
REREGISTER_BOUND = BACKOFF_CAP + 1.0   # s from the restarted master's ready file to both task sets registered:
                                       # one backoff delay at most, then a dial and a register on loopback
MAX_GAP = 1.0             # s, the longest the echo through the first container may pause (10 Hz: 0.1 s apart;
                          # a stop would last AWAY s; a loaded machine may delay a few)
SETTLE = 10.0             # s for the last echoes to come back
HELD_BACK = 1.0           # s the container host is kept from re-registering (SIGSTOP) while a request waits for it


@pytest.fixture
def engine(tmp_path: Path):
    """An engine whose master keeps its state in a file of this test; the robot task set's
    requests wait MASTER_WAIT s for an absent master."""
    state = tmp_path / "state" / "master.sqlite3"
    e = start_engine(tmp_path / "engine", master_args=("--state", str(state)),
                     robot_args=("--master-wait", str(MASTER_WAIT)))
    e.state_path = state
    yield e
    e.stop()


class Robot:
    """The one reader of a robot's websocket: echoes (``DM`` on ``resp*``: ``"<stream> <n>"``) are
    recorded with their arrival time; every other frame goes to ``frames``."""

    def __init__(self, raw: RawRobot):
        self.raw = raw
        self.echoes: dict[str, dict[int, float]] = {}      # stream -> n -> arrival (monotonic s)
        self.frames: asyncio.Queue = asyncio.Queue()
        self.sent: dict[str, list[int]] = {}

    async def read(self) -> None:
        async for m in self.raw.ws:
            d = json.loads(m) if isinstance(m, str) else m
            if isinstance(d, dict) and d.get("type") == "DM" and d["data"]["iTag"].startswith("resp"):
                stream, n = d["data"]["msg"]["data"].split()
                self.echoes.setdefault(stream, {})[int(n)] = time.monotonic()
            else:
                self.frames.put_nowait(d)

    async def expect(self, type_: str, pred=lambda d: True, timeout: float = 20.0):
        deadline = time.monotonic() + timeout
        while True:
            d = await asyncio.wait_for(self.frames.get(), max(0.01, deadline - time.monotonic()))
            if isinstance(d, dict) and d.get("type") == type_ and pred(d["data"]):
                return d["data"]

    async def stream(self, name: str, itag: str, stop: asyncio.Event) -> None:
        """Send ``"<name> <n>"`` on ``itag`` at RATE Hz until ``stop``."""
        sent = self.sent.setdefault(name, [])
        for n in itertools.count():
            if stop.is_set():
                return
            await self.raw.send("DM", {"iTag": itag, "type": "std_msgs/String", "msgID": "",
                                       "msg": {"data": f"{name} {n}"}})
            sent.append(n)
            try:
                async with asyncio.timeout(1 / RATE):               # the stream's clock
                    await stop.wait()
            except TimeoutError:
                pass

    def lost(self, name: str) -> list[int]:
        return sorted(set(self.sent.get(name, [])) - set(self.echoes.get(name, {})))

    def max_gap(self, name: str) -> tuple[float, float]:
        """The longest pause between two echoes of stream ``name``, s, and when it began (monotonic s)."""
        t = sorted(self.echoes[name].values())
        return max((b - a, a) for a, b in zip(t, t[1:], strict=False))


async def echo_container(engine, robot: Robot, ctag: str, suffix: str) -> None:
    """Container ``ctag`` with stringEcho, wired to robot-side converters ``req<suffix>``/``resp<suffix>``."""
    rid = robot.raw.robot
    await robot.raw.send("CC", {"containerTag": ctag})
    await robot.raw.cn(addNodes=[{"containerTag": ctag, "nodeTag": "echo", **ECHO}], addInterfaces=[
        {"endpointTag": ctag, "interfaceTag": "req", "interfaceType": "PublisherInterface",
         "className": "std_msgs/String", "addr": "/stringEchoReq"},
        {"endpointTag": ctag, "interfaceTag": "resp", "interfaceType": "SubscriberInterface",
         "className": "std_msgs/String", "addr": "/stringEchoResp"},
        {"endpointTag": rid, "interfaceTag": f"req{suffix}", "interfaceType": "SubscriberConverter",
         "className": "std_msgs/String"},
        {"endpointTag": rid, "interfaceTag": f"resp{suffix}", "interfaceType": "PublisherConverter",
         "className": "std_msgs/String"}])
    await robot.raw.send("CX", {"connect": [{"tagA": f"{ctag}/req", "tagB": f"{rid}/req{suffix}"},
                                            {"tagA": f"{ctag}/resp", "tagB": f"{rid}/resp{suffix}"}]})
    up = set()
    while up != {f"req{suffix}", f"resp{suffix}"}:
        up.add((await robot.expect("ST", lambda d: d.get("topic") == "iu" and d.get("status") is True))["iTag"])
    # the interfaces are up before the master has answered the CX; the robot sends its requests
    # one at a time, so once a later CN is done the CX is answered (a kill now loses no answer)
    await robot.raw.cn(setParam=[{"containerTag": ctag, "name": "wired", "value": 1}])
    deadline = time.monotonic() + 30
    while not any(p["ctag"] == ctag and p["name"] == "wired" for p in engine.admin("/api/parameters")):
        assert time.monotonic() < deadline, f"container {ctag}: the CN after its CX was not done"
        await asyncio.sleep(0.02)


async def echoing(robot: Robot, name: str, timeout: float = 30.0) -> None:
    """Wait until stream ``name``'s echoes come back (the node subscribes a moment after the
    interfaces are up: the first few may be lost; they are not counted)."""
    deadline = time.monotonic() + timeout
    while not robot.echoes.get(name):
        assert time.monotonic() < deadline, f"no echo of stream {name!r}"
        await asyncio.sleep(0.05)
    first = min(robot.echoes[name])
    robot.sent[name][:] = [n for n in robot.sent[name] if n >= first]


def metric(port: int, name: str) -> float:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as resp:
        line = next(x for x in resp.read().decode().splitlines() if x.startswith(name + " "))
    return float(line.split()[1])


async def test_nothing_stops_while_the_master_is_away(engine):
    ws_url = login(engine.master_url)["url"]
    metrics_port = engine.robot_ready[0]["metrics_port"]
    async with RawRobot(engine.master_url, "awayBot") as raw:
        robot = Robot(raw)
        stop = asyncio.Event()
        reader = asyncio.ensure_future(robot.read())
        await echo_container(engine, robot, "awayC1", "1")
        streams = [asyncio.ensure_future(robot.stream("a", "req1", stop))]
        await echoing(robot, "a")
        tids = {t["kind"]: t["tid"] for t in engine.admin("/api/state")["tasksets"]}
        try:
            # -- the master dies --------------------------------------------------------------------------
            engine.procs[0].send_signal(signal.SIGKILL)
            assert engine.procs[0].wait(10) == -signal.SIGKILL
            killed = time.monotonic()
            await raw.cn(addNodes=[{"containerTag": "awayC1", "nodeTag": "late", **ECHO}])
            er = await robot.expect("ER", lambda d: "master" in d)
            waited = time.monotonic() - killed
            assert er == f"CN: the master is unavailable (waited {MASTER_WAIT:g} s)"
            assert MASTER_WAIT <= waited < MASTER_WAIT + 2
            with pytest.raises(InvalidStatus) as ei:                 # a new robot cannot be authenticated
                await connect(f"{ws_url}?userID=testUser&robotID=newBot&password={'0' * 64}")
            assert ei.value.response.status_code == 503 and ei.value.response.headers["Retry-After"] == "5"
            assert metric(metrics_port, "rce_robot_master_available") == 0
            await asyncio.sleep(AWAY - (time.monotonic() - killed))  # the master stays away AWAY s (the fault)
            away_sent = [n for n in robot.sent["a"] if n <= robot.sent["a"][-1] - RATE]    # all but the last 1 s
            assert not [n for n in away_sent if n not in robot.echoes["a"]], "echoes lost while the master was away"
            assert [p.args[0] for p in engine.procs[1:] if p.poll() is not None] == []
            await raw.send("DM", {"iTag": "noSuchProbe", "type": "std_msgs/String", "msgID": "", "msg": {"data": ""}})
            await robot.expect("ER", lambda d: "noSuchProbe" in d)   # the robot's session still answers
            # -- the master comes back on the same state file and ports ----------------------------------------
            back = time.monotonic()
            await asyncio.to_thread(start_master, engine, "master2", None)     # the streams go on meanwhile
            took = await registered(engine, {tid: False for tid in tids.values()}, REREGISTER_BOUND + 5)
            print(f"CN refused after {waited:.2f} s; master restarted after {AWAY:g} s; task sets re-registered "
                  f"{took:.2f} s after it was ready ({time.monotonic() - back:.2f} s after it was started)")
            assert took < REREGISTER_BOUND
            for _ in range(int(REREGISTER_BOUND / 0.02)):           # the answer obeyed: polling, a condition
                if metric(metrics_port, "rce_robot_master_available") == 1:
                    break
                await asyncio.sleep(0.02)
            assert metric(metrics_port, "rce_robot_master_available") == 1
            await echo_container(engine, robot, "awayC2", "2")               # CC, CN, CX work again
            streams.append(asyncio.ensure_future(robot.stream("b", "req2", stop)))
            await echoing(robot, "b")
            await asyncio.sleep(1.0)                                 # both streams run together a while
        finally:
            stop.set()
            await asyncio.gather(*streams)
        deadline = time.monotonic() + SETTLE
        while (robot.lost("a") or robot.lost("b")) and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        reader.cancel()
        # read while the robot is still connected: its disconnect destroys the containers
        states = {c["ctag"]: c["state"] for c in engine.admin("/api/state")["containers"]}
    assert robot.lost("a") == [] and robot.lost("b") == []
    during = [n for n, t in robot.echoes["a"].items() if killed <= t < back]
    gap, at = robot.max_gap("a")
    print(f"echoes through the first container: {len(robot.sent['a'])} sent and received, 0 lost, {len(during)} of "
          f"them while the master was away; longest gap {gap:.3f} s, {at - killed:+.2f} s after the kill; through "
          f"the second: {len(robot.sent['b'])}, 0 lost")
    assert len(during) >= AWAY * RATE * 0.8 and gap < MAX_GAP
    assert states == {"awayC1": "running", "awayC2": "running"}


async def test_a_request_waits_for_a_host_that_has_not_re_registered_yet(engine):
    """After a restart (or a standby's takeover) the robot task set may re-register before the
    container host: a robot's request that needs the host waits for it (up to
    ``rce_master.control.ABSENT_WAIT``) instead of being refused. The host is held back with
    SIGSTOP, so the order is certain."""
    async with RawRobot(engine.master_url, "waitBot") as raw:
        robot = Robot(raw)
        reader = asyncio.ensure_future(robot.read())
        await echo_container(engine, robot, "waitC", "1")
        tids = {t["kind"]: t["tid"] for t in engine.admin("/api/state")["tasksets"]}
        host = proc(engine, "rce-container")
        engine.procs[0].send_signal(signal.SIGKILL)
        assert engine.procs[0].wait(10) == -signal.SIGKILL
        host.send_signal(signal.SIGSTOP)
        try:
            await asyncio.to_thread(start_master, engine, "master2", None)
            await registered(engine, {tids["robot"]: False, tids["container"]: True}, REREGISTER_BOUND + 5)
            sent = time.monotonic()
            await raw.cn(setParam=[{"containerTag": "waitC", "name": "late", "value": 7}])
            await asyncio.sleep(HELD_BACK)                           # the fault: the host stays away a while
        finally:
            host.send_signal(signal.SIGCONT)
        deadline = time.monotonic() + REREGISTER_BOUND + 5
        params: dict = {}
        while "late" not in params:
            assert time.monotonic() < deadline, "the CN was not done once the host was back"
            params = {p["name"]: p["value"] for p in engine.admin("/api/parameters") if p["ctag"] == "waitC"}
            await asyncio.sleep(0.02)
        done = time.monotonic() - sent
        reader.cancel()
    errors = []
    while not robot.frames.empty():
        d = robot.frames.get_nowait()
        if isinstance(d, dict) and d.get("type") == "ER":
            errors.append(d["data"])
    print(f"CN sent while the host was absent; done {done:.2f} s later (the host was held back {HELD_BACK:g} s)")
    assert params["late"] == 7 and errors == [] and HELD_BACK <= done < HELD_BACK + REREGISTER_BOUND + 1
