"""Issue 10, part 1: the master's state survives the master. Real processes on loopback: a robot
builds a container with nodes, a parameter, interfaces and connections; the master is killed
with SIGKILL and a new one started on the same SQLite file and ports has it all back. Its task
sets are absent (login answers 503 with Retry-After) until they re-register: a robot task set
that comes back with its robot keeps it, and the container whose host never came back is lost
after the grace (its robot is told). New ids go on after the old ones.

Today rce-robot and rce-container exit when their master dies (making them reconnect is the
next step), so the returning robot task set here is a control-plane client speaking the
contract of docs/INTERNALS.md ("Master state and restart")."""
from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import time
import urllib.error
import urllib.request
from pathlib import Path
from urllib.parse import urlsplit

import pytest

from rce import rpc
from rce.launch import Engine, command, start_engine
from wsclient import RawRobot

pytestmark = pytest.mark.asyncio
GRACE = 2.0              # s, --reconcile-grace of the restarted masters
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


def start_master(e: Engine, name: str) -> subprocess.Popen:
    """Start another rce-master on the engine's ports and state file; returns it once listening."""
    ready = e.workdir / f"{name}.ready"
    argv = [*command("rce-master"), "--dev", "--port", str(urlsplit(e.master_url).port), "--control-port",
            str(e.control_port), "--ready-file", str(ready), "--state", str(e.state_path),
            "--reconcile-grace", str(GRACE)]
    return e.spawn(name, argv, ready)[0]


def http_error(url: str, token: str | None = None) -> urllib.error.HTTPError:
    """The HTTP error GET ``url`` answers (fails the test when it answers 2xx)."""
    req = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"} if token else {})
    with pytest.raises(urllib.error.HTTPError) as ei:
        urllib.request.urlopen(req, timeout=10)
    return ei.value


async def build(e: Engine) -> dict:
    """A user alice whose robot r1 has container c1 with a node, a parameter, container- and
    robot-side interfaces and two connections; returns the admin state."""
    e.admin("/api/users", {"name": "alice", "password": "pw"})
    async with RawRobot(e.master_url, "r1", user="alice", password="pw") as r:
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
        state = e.admin("/api/state")
        # the master dies under the robot's feet: kill -9, then its task sets exit (today)
        e.procs[0].send_signal(signal.SIGKILL)
        assert e.procs[0].wait(10) == -signal.SIGKILL
        for p in e.procs[1:]:
            p.wait(30)
    return state


class FakeRobotTaskSet:
    """A robot task set that comes back (the contract's robot side): it re-registers with its tid,
    robots and interfaces, and records every op the master sends it."""

    def __init__(self) -> None:
        self.ops: asyncio.Queue = asyncio.Queue()
        self.seen: list[tuple[str, dict]] = []        # every op received, in order
        self.peer: rpc.RpcPeer | None = None

    async def register(self, control_port: int, **report) -> dict:
        handlers = {op: self._recorder(op) for op in
                    ("notify", "connect", "disconnect", "add_interface", "remove_interface", "close_robot")}
        self.peer = await rpc.connect("127.0.0.1", control_port, handlers, name="returning robot task set")
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
    before = await build(engine)
    old_tids = {t["kind"]: t["tid"] for t in before["tasksets"]}
    restarted_at = time.monotonic()
    master2 = start_master(engine, "master2")
    after = engine.admin("/api/state")
    for name in LISTS:
        assert after[name] == before[name], name
    assert [{**t, "absent": False} for t in after["tasksets"]] == before["tasksets"]
    assert all(t["absent"] for t in after["tasksets"])
    with urllib.request.urlopen(f"{engine.master_url}metrics", timeout=10) as resp:
        assert "rce_master_tasksets_absent 2.0" in resp.read().decode()
    # the robot task set is absent: login says when to ask again, and so do admin routes that need a host
    err = http_error(f"{engine.master_url}?userID=alice&version=20130902")
    assert (err.code, err.headers["Retry-After"]) == (503, "5") and "rce-robot" in err.read().decode()
    err = http_error(f"{engine.master_url}api/containers/alice/c1/bus", engine.admin_token)
    assert (err.code, err.headers["Retry-After"]) == (503, "5") and "re-registered" in err.read().decode()
    # a second master on the same file refuses to start
    other = subprocess.run([*command("rce-master"), "--port", "0", "--control-port", "0", "--state",
                            str(engine.state_path)], capture_output=True, text=True, timeout=60, env=engine.env)
    assert other.returncode == 1 and f"pid {master2.pid}" in other.stderr and "in use" in other.stderr

    # the robot task set comes back with its robot and interfaces; the container host never does
    robot_ts = FakeRobotTaskSet()
    r1_iids = [i["iid"] for i in before["interfaces"] if i["tag"].startswith("r1/")]
    answer = await robot_ts.register(engine.control_port, tid=old_tids["robot"], interfaces=r1_iids,
                                     robots=[{"user": "alice", "robot": "r1"}])
    try:
        assert answer == {"tid": old_tids["robot"], "resumed": True, "drop_containers": [], "drop_nodes": [],
                          "drop_interfaces": [], "close_robots": []}
        with urllib.request.urlopen(f"{engine.master_url}?userID=alice&version=20130902", timeout=10) as resp:
            assert json.loads(resp.read()) == {"url": "ws://127.0.0.1:9/"}
        st = await robot_ts.expect("notify", lambda a: a["type"] == "ST")
        lost_after = time.monotonic() - restarted_at
        er = await robot_ts.expect("notify", lambda a: a["type"] == "ER")
        assert st == {"user": "alice", "robot": "r1", "type": "ST",
                      "data": {"topic": "container", "cTag": "c1", "status": "lost"}}
        assert "container 'c1' was lost" in er["data"] and f"within {GRACE:g} s" in er["data"]
        assert GRACE <= lost_after < GRACE + 10
        # the robot-side ends of the lost container's connections were told first
        assert sorted(a["iid"] for op, a in robot_ts.seen if op == "disconnect") == sorted(r1_iids)
        s = engine.admin("/api/state")
        assert [(c["ctag"], c["state"]) for c in s["containers"]] == [("c1", "lost")]
        assert [i["tag"] for i in s["interfaces"]] == ["r1/req", "r1/resp"] and s["connections"] == []
        assert s["robots"] == [{**r, "endpoint": "re-back"} for r in before["robots"]]     # its new name
        assert [(t["tid"], t["absent"]) for t in s["tasksets"]] == [(old_tids["robot"], False)]
        await new_ids_go_on(engine, robot_ts, before)
        await graceful_restart_keeps_the_state(engine, master2)
    finally:
        await robot_ts.peer.close()


async def new_ids_go_on(engine: Engine, robot_ts: FakeRobotTaskSet, before: dict) -> None:
    """A new host, container and interface get ids after every old one."""
    await asyncio.to_thread(engine.add_container_host)          # the returning robot task set keeps answering
    s = engine.admin("/api/state")
    assert max(t["tid"] for t in s["tasksets"]) > max(t["tid"] for t in before["tasksets"])
    await robot_ts.peer.call("robot_request", user="alice", robot="r1", type="CC", data={"containerTag": "c2"},
                             timeout=60)
    await robot_ts.peer.call("robot_request", user="alice", robot="r1", type="CN", data={"addInterfaces": [
        {"endpointTag": "c2", "interfaceTag": "i", "interfaceType": "PublisherInterface",
         "className": "std_msgs/String", "addr": "/x"}]})
    s = engine.admin("/api/state")
    c2 = next(c for c in s["containers"] if c["ctag"] == "c2")
    assert c2["state"] == "running" and c2["cid"] > max(c["cid"] for c in before["containers"])
    assert next(i for i in s["interfaces"] if i["tag"] == "c2/i")["iid"] > max(i["iid"] for i in before["interfaces"])


async def graceful_restart_keeps_the_state(engine: Engine, master: subprocess.Popen) -> None:
    """A master stopped with SIGTERM leaves its task sets in the store (absent next time), not dropped."""
    before = engine.admin("/api/state")
    master.send_signal(signal.SIGTERM)
    assert master.wait(30) == 0
    start_master(engine, "master3")
    after = engine.admin("/api/state")
    for name in LISTS:
        assert after[name] == before[name], name
    assert [(t["tid"], t["absent"]) for t in after["tasksets"]] == [(t["tid"], True) for t in before["tasksets"]]
    await robot_returns_through_a_new_endpoint(engine)


async def robot_returns_through_a_new_endpoint(engine: Engine) -> None:
    """A robot the master has on an absent endpoint connects through a new one: its old session is
    over (forgotten as on a disconnect: the containers it owned go), the new one is recorded."""
    info = engine.add_robot_taskset()
    async with RawRobot(engine.master_url, "r1", user="alice", password="pw") as r:
        await r.probe()
        s = engine.admin("/api/state")
        new = next(t for t in s["tasksets"] if t.get("ws_url", "").endswith(f":{info['ws_port']}/"))
        assert [(x["robot"], x["endpoint"]) for x in s["robots"]] == [("r1", new["name"])]
        assert s["containers"] == [] and s["interfaces"] == [] and s["nodes"] == [] and s["parameters"] == []
