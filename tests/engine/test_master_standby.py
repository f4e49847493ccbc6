"""Several masters on etcd. Real processes on loopback: a real etcd
(tests/etcd_server.py), two ``rce-master --store etcd://...`` (the first leads, the second stands
by), a robot task set and a container host registered with the leader.

- Login works on both masters; the standby refuses a task set's ``register`` naming the leader's
  control address, and an admin change with 503 and the leader's URL; rce-console given a list
  of masters takes the change to the leader.
- The state built through the leader (a user, a robot's container with a node, a parameter,
  interfaces and connections) shows in the standby's admin API.
- kill -9 the leader: the standby leads within 5 s, with the state intact; its task sets are
  absent (login answers 503 with Retry-After) until they re-register with it, as after a restart.
  The returning robot task set here is a control-plane client speaking the contract of
  docs/INTERNALS.md.
- The same with the real task sets, each given both masters' control addresses: a robot echoes
  numbered messages at 10 Hz through a converter to the Test package's stringEcho.py; kill -9
  the leader: the standby leads within 5 s, no echo is lost and the robot's websocket stays
  open, a CN sent meanwhile waits for the new leader, rce-robot and rce-container re-register
  with it on their own (following its redirect while it stands by), and a new container echoes.
- A leader that is paused past its lease (SIGSTOP, as a long stall or a partition) is replaced,
  and exits when it resumes, without writing.
"""
from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from types import SimpleNamespace

import pytest

from rce.transport import rpc
from rce.tools.admin_client import LEADER_HEADER, AdminClient
from rce.plumbing.errors import NotLeader
from rce.tools.launch import Engine, command, start_engine
from rce.transport.masterlink import BACKOFF_CAP
from test_master_away import RATE, Robot, echo_container, echoing
from test_master_restart import ECHO, LISTS, FakeRobotTaskSet, http_error
from wsclient import RawRobot, login

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from etcd_server import EtcdServer  # noqa: E402

TAKEOVER_BOUND = 5.0     # s, the promise: a standby leads within 5 s of the leader's kill -9
WAIT = 20.0              # s, the most a test waits for what takes well under a second
LOGIN = "?userID=alice&version=20130902"
AFTER_KILL = 2.5         # s the stream is watched after the kill (the 2-3 s after it: the takeover)
REREGISTER_BOUND = BACKOFF_CAP + 1.0   # s from the standby leading to both task sets registered with it: the
                         # links back off to at most BACKOFF_CAP between rounds, then one dial and one register on
                         # loopback (a round tries the dead leader, refused at once, and the standby)
MAX_GAP = 1.0            # s, the longest the echo may pause (10 Hz: 0.1 s apart; the master's absence lasts about
                         # LEASE_TTL = 2 s; a loaded machine may delay a few)
SETTLE = 10.0            # s for the last echoes to come back


@pytest.fixture
def etcd(tmp_path: Path):
    with EtcdServer(tmp_path / "etcd") as e:
        yield e


@pytest.fixture
def engine(tmp_path: Path, etcd: EtcdServer):
    """An engine whose master (the leader: it starts first) keeps its state in ``etcd``."""
    e = start_engine(tmp_path / "engine", master_args=("--store", etcd.url))
    yield e
    e.stop()


def start_standby(e: Engine, etcd: EtcdServer, name: str = "master-b") -> tuple[subprocess.Popen, str, int]:
    """Another rce-master on ``etcd``; returns it, its URL and its control port once it stands by."""
    ready = e.workdir / f"{name}.ready"
    p, info = e.spawn(name, [*command("rce-master"), "--dev", "--port", "0", "--control-port", "0",
                             "--store", etcd.url, "--ready-file", str(ready)], ready)
    assert info["leading"] is False
    return p, f"http://127.0.0.1:{info['http_port']}/", info["control_port"]


async def until(pred, timeout: float = WAIT, what: str = "condition") -> float:
    """Poll ``pred()`` every 20 ms until it holds; the seconds it took."""
    t0 = time.monotonic()
    while not pred():
        assert time.monotonic() - t0 < timeout, f"{what} not met within {timeout} s"
        await asyncio.sleep(0.02)
    return time.monotonic() - t0


def leading(url: str, token: str) -> bool:
    return AdminClient(url, token).request("GET", "/api/leader")["leading"]


async def build(r: RawRobot) -> None:
    """Robot r1 of alice builds container c1 with a node, a parameter, container- and robot-side
    interfaces and their connections."""
    await r.send("CC", {"containerTag": "c1", "containerData": {"group": "g1"}})
    await r.cn(addNodes=[{"containerTag": "c1", "nodeTag": "echo", **ECHO}],
               setParam=[{"containerTag": "c1", "name": "/speed", "value": 0.5}],
               addInterfaces=[{"endpointTag": "c1", "interfaceTag": "req", "interfaceType": "PublisherInterface",
                               "className": "std_msgs/String", "addr": "/stringEchoReq"},
                              {"endpointTag": "r1", "interfaceTag": "req", "interfaceType": "SubscriberConverter",
                               "className": "std_msgs/String"}])
    await r.send("CX", {"connect": [{"tagA": "c1/req", "tagB": "r1/req"}]})
    await r.wait_up("req")


async def test_the_standby_follows_the_leader_and_takes_over_within_5_s(engine, etcd):
    a_url, token = engine.master_url, engine.admin_token
    b_proc, b_url, b_control = start_standby(engine, etcd)
    ws_url = login(a_url)["url"]
    assert login(b_url) == {"url": ws_url}                           # login works on any master
    # the standby sends a task set to the leader, and admin changes too
    peer = await rpc.connect("127.0.0.1", b_control, name="task set at the standby", cluster_key=engine.cluster_key)
    with pytest.raises(NotLeader, match=f"the leader is at control 127.0.0.1:{engine.control_port}") as ei:
        await peer.call("register", kind="robot", name="x", host="127.0.0.1")
    assert ei.value.leader == {"control": f"127.0.0.1:{engine.control_port}", "http": a_url}
    await peer.close()
    err = http_error(f"{b_url}api/containers/testUser/nope/bus", token)
    assert (err.code, err.headers[LEADER_HEADER]) == (503, a_url) and "stands by" in err.read().decode()
    # rce-console with a list of masters: the first cannot be reached, the standby sends it on to the leader
    console = [*command("rce-console"), "--master", "http://127.0.0.1:9/", "--master", f"{b_url},{a_url}"]
    added = subprocess.run([*console, "user", "add", "alice", "--password-stdin"], input="pw\n", env=engine.env,
                           capture_output=True, text=True, timeout=60)
    assert added.returncode == 0 and "user 'alice' added" in added.stdout, added.stderr
    shown = subprocess.run([*console, "--json", "leader"], env=engine.env, capture_output=True, text=True, timeout=60)
    assert json.loads(shown.stdout)["leader"]["http"] == a_url and not json.loads(shown.stdout)["leading"]
    client = AdminClient(["http://127.0.0.1:9/", b_url, a_url], token)
    assert [u["name"] for u in client.request("GET", "/api/users")] == ["alice", "testUser"] and client.base == b_url
    standby = AdminClient(b_url, token)
    async with RawRobot(b_url, "r1", user="alice", password="pw") as r:  # logged in through the standby
        await build(r)
        before = engine.admin("/api/state")
        assert [c["state"] for c in before["containers"]] == ["running"] and len(before["connections"]) == 1
        await until(lambda: standby.request("GET", "/api/state") == before, what="the standby has the leader's state")
        assert standby.request("GET", "/api/parameters") == before["parameters"]
        engine.procs[0].send_signal(signal.SIGKILL)
        took = await until(lambda: leading(b_url, token), TAKEOVER_BOUND + 1, "the standby leads")
    print(f"failover after kill -9 of the leader: {took:.2f} s")
    assert engine.procs[0].wait(10) == -signal.SIGKILL and took < TAKEOVER_BOUND
    after = standby.request("GET", "/api/state")
    for name in LISTS:
        assert after[name] == before[name], name
    assert [{**t, "absent": False} for t in after["tasksets"]] == before["tasksets"]
    assert all(t["absent"] for t in after["tasksets"])
    await the_new_leader_serves(engine, b_url, b_control, before)


async def the_new_leader_serves(engine: Engine, b_url: str, b_control: int, before: dict) -> None:
    """The new leader: login waits for a robot task set; one that re-registers with its tid is
    reconciled (the hook for rce-robot's reconnection); admin changes work."""
    err = http_error(b_url + LOGIN)
    assert (err.code, err.headers["Retry-After"]) == (503, "5")
    old_tid = next(t["tid"] for t in before["tasksets"] if t["kind"] == "robot")
    r1_iids = [i["iid"] for i in before["interfaces"] if i["tag"].startswith("r1/")]
    robot_ts = FakeRobotTaskSet(engine.cluster_key)
    answer = await robot_ts.register(b_control, tid=old_tid, interfaces=r1_iids,
                                     robots=[{"user": "alice", "robot": "r1"}])
    try:
        assert answer["tid"] == old_tid and answer["resumed"] is True and answer["close_robots"] == []
        with urllib.request.urlopen(b_url + LOGIN, timeout=10) as resp:
            assert json.loads(resp.read()) == {"url": "ws://127.0.0.1:9/"}
        AdminClient(b_url, engine.admin_token).request("POST", "/api/users", {"name": "bob", "password": "pw"})
        assert [u["name"] for u in AdminClient(b_url, engine.admin_token).request("GET", "/api/users")] == \
            ["alice", "bob", "testUser"]
    finally:
        await robot_ts.peer.close()


async def test_a_paused_leader_is_replaced_and_exits_when_it_resumes(tmp_path, etcd):
    e = start_engine(tmp_path / "engine", robot_tasksets=0, container_hosts=0, master_args=("--store", etcd.url))
    try:
        a = e.procs[0]
        b_proc, b_url, _ = start_standby(e, etcd)
        a.send_signal(signal.SIGSTOP)                  # a stall: it renews nothing, and does not know it
        try:
            took = await until(lambda: leading(b_url, e.admin_token), TAKEOVER_BOUND + 1, "the standby leads")
        finally:
            a.send_signal(signal.SIGCONT)
        assert took < TAKEOVER_BOUND
        assert await asyncio.to_thread(a.wait, WAIT) == 1
        log = (e.workdir / "master.log").read_text()
        assert "stopped leading" in log, log[-2000:]
        assert leading(b_url, e.admin_token) and b_proc.poll() is None
        AdminClient(b_url, e.admin_token).request("POST", "/api/users", {"name": "carol", "password": "pw"})
    finally:
        e.stop()


def two_masters(tmp_path: Path, etcd: EtcdServer) -> tuple[Engine, str, int]:
    """An engine on ``etcd`` whose leader is its first master, and a standby; its robot task set
    and container host are given both masters' control addresses. Returns it, the standby's URL
    and control port."""
    e = start_engine(tmp_path / "engine", robot_tasksets=0, container_hosts=0, master_args=("--store", etcd.url))
    try:
        _, b_url, b_control = start_standby(e, etcd)
        e.masters.append(f"127.0.0.1:{b_control}")
        e.add_robot_taskset()
        e.add_container_host()
    except BaseException:
        e.stop()
        raise
    return e, b_url, b_control


async def test_real_task_sets_follow_the_standby_and_nothing_stops(tmp_path, etcd):
    e, b_url, _ = two_masters(tmp_path, etcd)
    standby = AdminClient(b_url, e.admin_token)
    try:
        async with RawRobot(e.master_url, "standbyBot") as raw:       # logged in through the leader
            robot = Robot(raw)
            stop = asyncio.Event()
            reader = asyncio.ensure_future(robot.read())
            await echo_container(e, robot, "sbC1", "1")
            streams = [asyncio.ensure_future(robot.stream("a", "req1", stop))]
            await echoing(robot, "a")
            tids = sorted(t["tid"] for t in e.admin("/api/state")["tasksets"])
            assert len(tids) == 2
            try:
                e.procs[0].send_signal(signal.SIGKILL)                # -- the leader dies ---------------------
                killed = time.monotonic()
                assert await asyncio.to_thread(e.procs[0].wait, 10) == -signal.SIGKILL
                # a request that needs the master waits for the new leader (rce-robot --master-wait 30 s). It
                # needs only the robot's task set, which sends it once registered: a request that needs the
                # container host too is refused while that host has not re-registered (docs/INTERNALS.md)
                await raw.cn(addInterfaces=[{"endpointTag": "standbyBot", "interfaceTag": "late",
                                             "interfaceType": "SubscriberConverter", "className": "std_msgs/String"}])
                await until(lambda: leading(b_url, e.admin_token), TAKEOVER_BOUND + 1, "the standby leads")
                took = time.monotonic() - killed
                back = await until(lambda: [t["tid"] for t in standby.request("GET", "/api/tasksets")
                                            if not t["absent"]] == tids,
                                   REREGISTER_BOUND + 5, "both task sets registered with the new leader")
                await asyncio.sleep(max(0.0, AFTER_KILL - (time.monotonic() - killed)))   # the stream goes on
                watched = [n for n in robot.sent["a"] if n <= robot.sent["a"][-1] - RATE]  # all but the last 1 s
                assert not [n for n in watched if n not in robot.echoes["a"]], "echoes lost after the kill"
                assert e.alive() == [str(e.procs[0].args[0])]      # only the leader has exited
                assert raw.ws.state.name == "OPEN"
                await until(lambda: "standbyBot/late" in [i["tag"] for i in standby.request("GET", "/api/interfaces")],
                            what="the CN that waited for the new leader done")
                new_leader = SimpleNamespace(admin=lambda path: standby.request("GET", path))
                await echo_container(new_leader, robot, "sbC2", "2")  # CC, CN, CX through the new leader
                streams.append(asyncio.ensure_future(robot.stream("b", "req2", stop)))
                await echoing(robot, "b")
                await until(lambda: len(robot.echoes["b"]) >= RATE / 2, what="both streams echo together")
            finally:
                stop.set()
                await asyncio.gather(*streams)
            await until(lambda: not robot.lost("a") and not robot.lost("b"), SETTLE, "every echo back (0 lost)")
            assert not reader.done() and raw.ws.state.name == "OPEN"     # the websocket never closed
            # asked while the robot is connected: when it leaves, its containers are destroyed one by one
            states = {c["ctag"]: c["state"] for c in standby.request("GET", "/api/containers")}
            reader.cancel()
        gap, at = robot.max_gap("a")
        during = [n for n, t in robot.echoes["a"].items() if t >= killed]
        print(f"kill -9 of the leader: the standby led after {took:.2f} s; both task sets re-registered "
              f"{back:.2f} s after that ({took + back:.2f} s after the kill); echoes through the first container: "
              f"{len(robot.sent['a'])} sent and received, 0 lost, {len(during)} after the kill, longest gap "
              f"{gap:.3f} s ({at - killed:+.2f} s after the kill); through the second: {len(robot.sent['b'])}, 0 lost")
        assert took < TAKEOVER_BOUND and back < REREGISTER_BOUND and gap < MAX_GAP
        assert states == {"sbC1": "running", "sbC2": "running"}
    except BaseException:
        print(e.log_text())
        raise
    finally:
        e.stop()
