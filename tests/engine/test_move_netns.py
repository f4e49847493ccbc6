"""Moves between the cloud and a robot's own computer across a real link, in network namespaces the
test makes (root; deleted after, also on failure): the cloud (master, robot endpoint, a cloud
container host) in the root namespace; robot ``N`` in namespace R with its own computer
(``rce-container --zone robot:N --user testUser``, its data plane on R's address) and ``rce-ros``
bridging its local bus, joined to the cloud by one veth pair.

- pinned to the robot and back to the cloud, a container echoing a 20 Hz stream moves twice while
  the stream runs: every message echoed exactly once, in order;
- a move that fails part way (its package exists only in the cloud) leaves it running where it was;
- a node that hands its state over (``Node.handoff``) goes on counting across both moves;
- another user's container asking for robot N's computer is refused; the session lives on.
"""
from __future__ import annotations

import asyncio
import json
import os
import time
from pathlib import Path

import pytest

import rce.node
from rce.tools.launch import command, start_engine
from rce.tools.netlab import NetLab
from nsrobot import WAIT, RosRun
from test_move import COUNTER
from wsclient import RawRobot

pytestmark = pytest.mark.asyncio
RATE = 20.0       # Hz of each stream
ROBOT = "N"
#: container -> (package, its placement data); the robot's /in_<c> goes to it, /out_<c> comes back
CONTAINERS = {"echo": ("Test", {"placement": "auto", "robot": ROBOT, "deadline_ms": 500}),
              "count": ("Counting", {"placement": "auto", "robot": ROBOT}),
              "only": ("CloudEcho", {"placement": "auto", "robot": ROBOT})}


def robot_config(url: str) -> dict:
    """rce-ros config: each container of :data:`CONTAINERS` runs ``stringEcho.py`` of its package."""
    cfg = {"url": url, "userID": "testUser", "password": "testUser", "robotID": ROBOT,
           "containers": [{"cTag": c, **data} for c, (_, data) in CONTAINERS.items()],
           "nodes": [{"cTag": c, "nTag": "echo", "pkg": pkg, "exe": "stringEcho.py"}
                     for c, (pkg, _) in CONTAINERS.items()],
           "interfaces": [], "connections": []}
    for c in CONTAINERS:
        cfg["interfaces"] += [
            {"eTag": c, "iTag": "req", "iType": "PublisherInterface", "iCls": "std_msgs/String",
             "addr": "/stringEchoReq"},
            {"eTag": c, "iTag": "resp", "iType": "SubscriberInterface", "iCls": "std_msgs/String",
             "addr": "/stringEchoResp"},
            {"eTag": ROBOT, "iTag": f"req_{c}", "iType": "SubscriberConverter", "iCls": "std_msgs/String",
             "addr": f"/in_{c}"},
            {"eTag": ROBOT, "iTag": f"resp_{c}", "iType": "PublisherConverter", "iCls": "std_msgs/String",
             "addr": f"/out_{c}"}]
        cfg["connections"] += [{"tagA": f"{c}/req", "tagB": f"{ROBOT}/req_{c}"},
                               {"tagA": f"{c}/resp", "tagB": f"{ROBOT}/resp_{c}"}]
    return cfg


def package(root: Path, name: str, text: str) -> None:
    d = root / name
    d.mkdir(parents=True)
    (d / "stringEcho.py").write_text(text)
    os.chmod(d / "stringEcho.py", 0o755)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("movens")
    echo = (Path(rce.__file__).parent / "packages" / "Test" / "stringEcho.py").read_text()
    package(tmp / "cloud-pkgs", "CloudEcho", echo)           # only the cloud has it
    package(tmp / "cloud-pkgs", "Counting", COUNTER)
    package(tmp / "robot-pkgs", "Counting", COUNTER)
    with NetLab("mvn") as lab:
        lab.namespace("r")
        link = lab.link(None, "r", 1)
        lab.route("r", "default", link.a_ip)
        e = start_engine(tmp / "engine", container_hosts=0, master_args=("--bind", "0.0.0.0"),
                         robot_args=("--bind", "0.0.0.0", "--advertise-host", link.a_ip))
        try:
            plain = dict(e.env)
            e.env["RCE_PACKAGE_PATH"] = str(tmp / "cloud-pkgs")
            e.add_container_host("--name", "dc1")
            e.env["RCE_PACKAGE_PATH"] = str(tmp / "robot-pkgs")
            control_port = e.masters[0].rsplit(":", 1)[1]
            ready = tmp / "robot-computer.ready"
            e.spawn("robot-computer", lab.wrap("r", [
                *command("rce-container"), f"{link.a_ip}:{control_port}", "--bind", "0.0.0.0",
                "--advertise-host", link.b_ip, "--zone", f"robot:{ROBOT}", "--user", "testUser",
                "--name", "n-computer", "--runtime-dir", str(tmp / "rt-robot"), "--ready-file", str(ready)]), ready)
            e.env = plain
            yield lab, link, e, tmp
        finally:
            e.stop()


class Streams:
    """On the robot's bus: numbered messages at RATE to each container, and their echoes (monotonic s)."""

    def __init__(self, node):
        self.node, self.sent = node, {c: 0 for c in CONTAINERS}
        self.got: dict[str, list[tuple[float, str]]] = {c: [] for c in CONTAINERS}
        self.pubs: dict = {}

    async def start(self) -> None:
        for c in CONTAINERS:
            self.pubs[c] = await self.node.publisher(f"/in_{c}", "std_msgs/String")
            await self.node.subscriber(f"/out_{c}", "std_msgs/String",
                                       lambda m, c=c: self.got[c].append((time.monotonic(), m.data)))

    async def run(self) -> None:
        while True:
            for c, pub in self.pubs.items():
                await pub.publish({"data": str(self.sent[c])})
                self.sent[c] += 1
            await asyncio.sleep(1 / RATE)

    async def until(self, c: str, n: int) -> None:
        async with asyncio.timeout(WAIT):
            while len(self.got[c]) < n:
                await asyncio.sleep(0.02)


async def move(e, c: str, where: str) -> dict:
    return await asyncio.to_thread(e.admin, f"/api/containers/testUser/{c}/move", {"host": where})


def host_of(e, ctag: str) -> str:
    return next(c["host"] for c in e.admin("/api/containers") if c["ctag"] == ctag)


async def test_moves_across_the_robots_link(world):
    lab, link, e, tmp = world
    # never shed, even on a loaded machine (--max-lag 0): every message must come back
    run = await RosRun.start(lab, "r", robot_config(f"http://{link.a_ip}:{e.http_port}/"), tmp, "--max-lag", "0")
    node = None
    try:
        await run.wait_line("rce-ros: ready")
        connected = [json.loads(line) for log in e.logs if log.exists() for line in log.read_text().splitlines()
                     if '"robot connected"' in line and f'"robot": "{ROBOT}"' in line]
        assert connected and connected[-1]["max_lag"] == 0, connected   # the endpoint took rce-ros's --max-lag
        node = await rce.node.init_node("tester", bus=str(run.bus), argv=[])
        s = Streams(node)
        await s.start()
        task = asyncio.create_task(s.run())
        try:
            for c in CONTAINERS:
                await s.until(c, 10)
                assert host_of(e, c) == "dc1", "auto starts in the cloud"
            for where in ("n-computer", "dc1"):               # make-before-break, both ways, state carried
                for c in ("echo", "count"):
                    moved = await move(e, c, where)
                    assert moved["to"].endswith(f"({where})"), moved
                    assert host_of(e, c) == where
                    if c == "count":
                        assert moved["states"] == 1, moved
                    n = len(s.got[c])
                    await s.until(c, n + 10)
            with pytest.raises(Exception) as err:            # its package is not on the robot's computer
                await move(e, "only", "n-computer")
            assert "runs where it was" in str(err.value)
            assert host_of(e, "only") == "dc1"
            n = len(s.got["only"])
            await s.until("only", n + 10)
        finally:
            task.cancel()
        echoes = [int(d) for _, d in s.got["echo"]]
        assert echoes == list(range(echoes[0], echoes[0] + len(echoes))), "echo: each message once, in order"
        counted = [tuple(int(x) for x in d.split(":")) for _, d in s.got["count"]]
        counts = [k for k, _ in counted]
        seqs = [q for _, q in counted]
        assert counts == list(range(counts[0], counts[0] + len(counts))), "the count goes on across both moves"
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
        only = [int(d) for _, d in s.got["only"]]
        assert only == list(range(only[0], only[0] + len(only))), "the failed move disturbed nothing"
        ts = {t["name"]: t for t in e.admin("/api/tasksets") if t["kind"] == "container"}
        assert ts["n-computer"]["containers"] == 0 and ts["dc1"]["containers"] == 3
        assert ts["n-computer"]["zone"] == f"robot:{ROBOT}"
    finally:
        if node is not None:
            await node.close()
        await run.stop()


async def test_a_robots_computer_refuses_another_users_container(world):
    _, link, e, _ = world
    e.admin("/api/users", {"name": "bob", "password": "bob-password"})
    async with RawRobot(e.master_url, ROBOT, user="bob", password="bob-password") as b:
        await b.send("CC", {"containerTag": "sneak", "containerData": {"placement": "robot", "robot": ROBOT}})
        err = await b.expect("ER", pred=lambda d: "sneak" in d or f"robot:{ROBOT}" in d)
        assert f"no container host in zone robot:{ROBOT}" in err
        await b.probe()                                  # the session lives on
    ts = {t["name"]: t for t in e.admin("/api/tasksets") if t["kind"] == "container"}
    assert ts["n-computer"]["containers"] == 0
