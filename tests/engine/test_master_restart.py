"""The master's state survives the master. Real processes on loopback: a robot
builds a container with nodes, a parameter, interfaces and connections; the master is killed
with SIGKILL and a new one started on the same SQLite file and ports has it all back. Its task
sets are absent (login answers 503 with Retry-After) until they re-register. The real rce-robot,
held (SIGSTOP) while the test looks at the absent state, re-registers by itself once let go and
keeps its robot, whose websocket stayed open all along; the container host, killed with the
master, never comes back, so its container is lost after the grace and the robot is told, on
that same websocket. New ids go on after the old ones.

:class:`FakeRobotTaskSet`, a control-plane client speaking the contract of docs/INTERNALS.md
("Master state and restart"), is shared with test_master_standby."""
from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import time
import urllib.error
import urllib.request
from pathlib import Path
from urllib.parse import urlsplit

import pytest

from rce.transport import rpc
from rce.tools.launch import Engine, command, start_engine
from rce.transport.masterlink import BACKOFF_CAP
from wsclient import RawRobot

pytestmark = pytest.mark.asyncio
GRACE = 8.0              # s, --reconcile-grace of the restarted masters: long enough for a new rce-robot to start
                         # and a robot to log in through it on a loaded machine (robot_returns_through_a_new_endpoint)
REREGISTER_BOUND = BACKOFF_CAP + 1.0   # s for a task set to re-register once it can: one backoff delay at most,
                                       # then a dial and a register on loopback
NOTICE_TIMEOUT = 20.0    # s to wait for a notice the master sends after the grace
LISTS = ("users", "robots", "containers", "nodes", "parameters", "interfaces", "connections")
ECHO = {"pkg": "Test", "exe": "stringEcho.py"}


@pytest.fixture
def engine(tmp_path: Path):
    """An engine whose master keeps its state in a file of this test (named ``engine`` so that
    a failing test's report carries the process logs)."""
    state = tmp_path / "state" / "master.sqlite3"
    e = start_engine(tmp_path / "engine", master_args=("--state", str(state), "--reconcile-grace", str(GRACE)))
    e.state_path = state
    yield e
    e.stop()


def start_master(e: Engine, name: str, grace: float | None = GRACE) -> subprocess.Popen:
    """Start another rce-master on the engine's ports and state file, with ``--reconcile-grace
    grace`` (None: the default); returns it once listening."""
    ready = e.workdir / f"{name}.ready"
    argv = [*command("rce-master"), "--dev", "--port", str(urlsplit(e.master_url).port), "--control-port",
            str(e.control_port), "--ready-file", str(ready), "--state", str(e.state_path)]
    return e.spawn(name, argv + (["--reconcile-grace", str(grace)] if grace is not None else []), ready)[0]


def proc(e: Engine, name: str, nth: int = 0) -> subprocess.Popen:
    """The ``nth`` process of the engine running ``name`` (rce-robot, rce-container)."""
    return [p for p in e.procs if name in str(p.args[0])][nth]


async def registered(e: Engine, tids: dict[int, bool], timeout: float) -> float:
    """Poll the admin API until each task set of ``tids`` (tid -> absent?) is as given; the
    seconds it took. A master that is still starting counts as not yet."""
    t0 = time.monotonic()
    while True:
        try:
            ts = {t["tid"]: t["absent"] for t in e.admin("/api/state")["tasksets"]}
        except OSError:
            ts = {}
        if all(ts.get(tid) == absent for tid, absent in tids.items()):
            return time.monotonic() - t0
        assert time.monotonic() - t0 < timeout, f"task sets not as {tids} within {timeout} s: {ts}"
        await asyncio.sleep(0.02)


def http_error(url: str, token: str | None = None) -> urllib.error.HTTPError:
    """The HTTP error GET ``url`` answers (fails the test when it answers 2xx)."""
    req = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"} if token else {})
    with pytest.raises(urllib.error.HTTPError) as ei:
        urllib.request.urlopen(req, timeout=10)
    return ei.value


async def build(e: Engine, r: RawRobot) -> dict:
    """Robot r1 of alice (connected as ``r``) gets container c1 with a node, a parameter,
    container- and robot-side interfaces and two connections; returns the admin state."""
    await r.send("CC", {"containerTag": "c1", "containerData": {"group": "g1", "memory": 256}})
    await r.cn(addNodes=[{"containerTag": "c1", "nodeTag": "echo", **ECHO}],
               setParam=[{"containerTag": "c1", "name": "/speed", "value": {"max": 0.5}}],
               addInterfaces=[
                   {"endpointTag": "c1", "interfaceTag": "req", "interfaceType": "PublisherInterface",
                    "className": "std_msgs/String", "addr": "/stringEchoReq"},
                   {"endpointTag": "c1", "interfaceTag": "resp", "interfaceType": "SubscriberInterface",
                    "className": "std_msgs/String", "addr": "/stringEchoResp"},
                   {"endpointTag": "r1", "interfaceTag": "req", "interfaceType": "SubscriberConverter",
                    "className": "std_msgs/String"},
                   {"endpointTag": "r1", "interfaceTag": "resp", "interfaceType": "PublisherConverter",
                    "className": "std_msgs/String"}])
    await r.send("CX", {"connect": [{"tagA": "c1/req", "tagB": "r1/req"}, {"tagA": "c1/resp", "tagB": "r1/resp"}]})
    await r.wait_up("req", "resp")
    return e.admin("/api/state")


async def frames_until(r: RawRobot, pred, timeout: float = NOTICE_TIMEOUT) -> list[dict]:
    """Every JSON frame the robot gets up to the first for which ``pred(frame)`` holds (included)."""
    out = []
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not out or not pred(out[-1]):
        m = await r.recv(max(0.01, deadline - loop.time()))
        if isinstance(m, dict):
            out.append(m)
    return out


class FakeRobotTaskSet:
    """A robot task set that comes back (the contract's robot side): it re-registers with its tid,
    robots and interfaces, and records every op the master sends it. It proves ``cluster_key``
    (the engine's) to the master, as rce-robot does."""

    def __init__(self, cluster_key) -> None:
        self.cluster_key = cluster_key
        self.ops: asyncio.Queue = asyncio.Queue()
        self.seen: list[tuple[str, dict]] = []        # every op received, in order
        self.peer: rpc.RpcPeer | None = None

    async def register(self, control_port: int, **report) -> dict:
        handlers = {op: self._recorder(op) for op in
                    ("notify", "connect", "disconnect", "add_interface", "remove_interface", "close_robot")}
        self.peer = await rpc.connect("127.0.0.1", control_port, handlers, name="returning robot task set",
                                      cluster_key=self.cluster_key)
        self.peer.keepalive()
        return await self.peer.call("register", kind="robot", name="re-back", host="127.0.0.1",
                                    ws_url="ws://127.0.0.1:9/", data_addr="tcp://127.0.0.1:9", **report)

    def _recorder(self, op: str):
        async def record(args: dict) -> dict:
            self.seen.append((op, args))
            self.ops.put_nowait((op, args))
            return {}
        return record

    async def expect(self, op: str, pred=lambda a: True) -> dict:
        """The next op ``op`` whose args satisfy ``pred`` (others are skipped)."""
        while True:
            got, args = await asyncio.wait_for(self.ops.get(), NOTICE_TIMEOUT)
            if got == op and pred(args):
                return args


async def test_state_survives_kill_9_and_is_reconciled(engine):
    robot_ts, host = proc(engine, "rce-robot"), proc(engine, "rce-container")
    engine.admin("/api/users", {"name": "alice", "password": "pw"})
    async with RawRobot(engine.master_url, "r1", user="alice", password="pw") as r:
        before = await build(engine, r)
        old_tids = {t["kind"]: t["tid"] for t in before["tasksets"]}
        os.kill(robot_ts.pid, signal.SIGSTOP)       # held: it re-registers only once the test has seen it absent
        try:
            for p in (engine.procs[0], host):        # the master dies, and the container host never comes back
                p.send_signal(signal.SIGKILL)
                assert p.wait(10) == -signal.SIGKILL
            restarted_at = time.monotonic()
            master2 = start_master(engine, "master2")
            the_restored_state_is_absent(engine, before, master2)
        finally:
            os.kill(robot_ts.pid, signal.SIGCONT)
        took = await registered(engine, {old_tids["robot"]: False}, REREGISTER_BOUND + 5)
        assert took < REREGISTER_BOUND
        with urllib.request.urlopen(f"{engine.master_url}?userID=alice&version=20130902", timeout=10) as resp:
            assert json.loads(resp.read())["url"].endswith(f":{engine.robot_ready[0]['ws_port']}/")
        # the robot, still connected: the ends of the lost container's connections go down, then it is lost
        frames = await frames_until(r, lambda m: m["type"] == "ER" and "container 'c1' was lost" in m["data"])
        lost_after = time.monotonic() - restarted_at
        sts = [(m["data"].get("topic"), m["data"].get("iTag") or m["data"].get("cTag"), m["data"]["status"])
               for m in frames if m["type"] == "ST"]
        assert sts[-1] == ("container", "c1", "lost") and sorted(sts[:-1]) == [("iu", "req", False),
                                                                               ("iu", "resp", False)]
        assert f"within {GRACE:g} s" in frames[-1]["data"] and GRACE <= lost_after < GRACE + 10
        s = engine.admin("/api/state")
        assert [(c["ctag"], c["state"]) for c in s["containers"]] == [("c1", "lost")]
        assert {"r1/req", "r1/resp"} <= {i["tag"] for i in s["interfaces"]}
        assert s["robots"] == before["robots"]
        assert [(t["tid"], t["absent"]) for t in s["tasksets"]] == [(old_tids["robot"], False)]
        await r.send("DC", {"containerTag": "c1"})              # the robot can always destroy a lost container
        await r.send("DC", {"containerTag": "noSuchC"})         # a marker: once its ER is back, DC is done
        await r.expect("ER", pred=lambda d: "noSuchC" in d)
        s = engine.admin("/api/state")
        assert s["containers"] == [] and s["connections"] == []
        assert [i["tag"] for i in s["interfaces"]] == ["r1/req", "r1/resp"]
        await new_ids_go_on(engine, r, before)
        await graceful_restart_keeps_the_state(engine, master2, robot_ts)


def the_restored_state_is_absent(engine: Engine, before: dict, master2: subprocess.Popen) -> None:
    """The restarted master has the whole state back, with every task set absent: login says when
    to ask again, and so do admin routes that need a host; a second master on the file refuses."""
    after = engine.admin("/api/state")
    for name in LISTS:
        assert after[name] == before[name], name
    assert [{**t, "absent": False} for t in after["tasksets"]] == before["tasksets"]
    assert all(t["absent"] for t in after["tasksets"])
    with urllib.request.urlopen(f"{engine.master_url}metrics", timeout=10) as resp:
        assert "rce_master_tasksets_absent 2.0" in resp.read().decode()
    err = http_error(f"{engine.master_url}?userID=alice&version=20130902")
    assert (err.code, err.headers["Retry-After"]) == (503, "5") and "rce-robot" in err.read().decode()
    err = http_error(f"{engine.master_url}api/containers/alice/c1/bus", engine.admin_token)
    assert (err.code, err.headers["Retry-After"]) == (503, "5") and "re-registered" in err.read().decode()
    other = subprocess.run([*command("rce-master"), "--port", "0", "--control-port", "0", "--state",
                            str(engine.state_path)], capture_output=True, text=True, timeout=60, env=engine.env)
    assert other.returncode == 1 and f"pid {master2.pid}" in other.stderr and "in use" in other.stderr


async def new_ids_go_on(engine: Engine, r: RawRobot, before: dict) -> None:
    """A new host, container and interface get ids after every old one."""
    await asyncio.to_thread(engine.add_container_host)
    s = engine.admin("/api/state")
    assert max(t["tid"] for t in s["tasksets"]) > max(t["tid"] for t in before["tasksets"])
    await r.send("CC", {"containerTag": "c2"})
    await r.cn(addInterfaces=[{"endpointTag": "c2", "interfaceTag": "i", "interfaceType": "PublisherInterface",
                               "className": "std_msgs/String", "addr": "/x"}])
    await r.send("DC", {"containerTag": "noSuchC2"})         # a marker: once its ER is back, CC and CN are done
    await r.expect("ER", pred=lambda d: "noSuchC2" in d)
    s = engine.admin("/api/state")
    c2 = next(c for c in s["containers"] if c["ctag"] == "c2")
    assert c2["state"] == "running" and c2["cid"] > max(c["cid"] for c in before["containers"])
    assert next(i for i in s["interfaces"] if i["tag"] == "c2/i")["iid"] > max(i["iid"] for i in before["interfaces"])


async def graceful_restart_keeps_the_state(engine: Engine, master: subprocess.Popen,
                                           robot_ts: subprocess.Popen) -> None:
    """A master stopped with SIGTERM leaves its task sets in the store (absent next time), not
    dropped. The host comes back and keeps its container; the robot task set does not."""
    host2 = proc(engine, "rce-container", 1)
    before = engine.admin("/api/state")
    for p in (robot_ts, host2):
        os.kill(p.pid, signal.SIGSTOP)
    try:
        master.send_signal(signal.SIGTERM)
        assert master.wait(30) == 0
        start_master(engine, "master3")
        after = engine.admin("/api/state")
        for name in LISTS:
            assert after[name] == before[name], name
        assert [(t["tid"], t["absent"]) for t in after["tasksets"]] == [(t["tid"], True) for t in before["tasksets"]]
    finally:
        robot_ts.send_signal(signal.SIGKILL)                     # the robot's websocket goes with it
        os.kill(host2.pid, signal.SIGCONT)
    host_tid = next(t["tid"] for t in before["tasksets"] if t["kind"] == "container")
    await registered(engine, {host_tid: False}, REREGISTER_BOUND + 5)
    assert any(c["ctag"] == "c2" and c["state"] == "running" for c in engine.admin("/api/state")["containers"])
    await robot_returns_through_a_new_endpoint(engine)


async def robot_returns_through_a_new_endpoint(engine: Engine) -> None:
    """A robot the master has on an absent endpoint connects through a new one: it takes its namespace
    over there (docs/INTERNALS.md "Moving to another endpoint"): the containers it owns, their nodes and
    parameters and its interfaces stay, and the robot is recorded on the new endpoint."""
    before = engine.admin("/api/state")
    info = engine.add_robot_taskset()
    async with RawRobot(engine.master_url, "r1", user="alice", password="pw") as r:
        await r.probe()
        s = engine.admin("/api/state")
        new = next(t for t in s["tasksets"] if t.get("ws_url", "").endswith(f":{info['ws_port']}/"))
        assert [(x["robot"], x["endpoint"]) for x in s["robots"]] == [("r1", new["name"])]
        for name in ("containers", "interfaces", "nodes", "parameters", "connections"):
            assert s[name] == before[name], name
        assert [c["ctag"] for c in s["containers"]] == ["c2"]
