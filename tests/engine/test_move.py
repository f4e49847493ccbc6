"""Moving a running container, make-before-break, against a real engine on loopback: a master, a
robot task set, a cloud container host and robot ``mover``'s own computer (``--zone robot:mover``).
The robot sends numbered ``std_msgs/String`` at 20 Hz through converters to ``stringEcho.py`` in
its container and reads the echoes.

- pinned to the robot, the container moves there while the stream runs; pinned to the cloud, back:
  every message echoed exactly once and in order, the old copy destroyed, the robot told;
- a move that fails part way (its node's package exists only in the cloud) leaves the container
  running where it was, the stream undisturbed;
- a node that hands its state over (``Node.handoff``: a counter of the messages it handled) goes on
  counting on the new host from where the old copy stopped: every count once, in order;
- each container's results are timed by the engine from input to output, against its deadline;
- a container with ``ordered_moves`` keeps its echoes in order though its old copy has a backlog
  (a node of 40 ms an input, sent a burst) when the move begins.

Prints each move's longest gap between echoes (``pytest -s``).
"""
from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from rce.tools.launch import start_engine
from test_dataflow import _echo_container
from wsclient import RawRobot

pytestmark = pytest.mark.asyncio

RATE = 20.0      # Hz
WAIT = 30.0


COUNTER = """#!/usr/bin/env python3
import rce.node


async def main(node):
    count = [0]
    pub = await node.publisher("stringEchoResp", "std_msgs/String", queue_size=100)

    def handle(msg):
        count[0] += 1
        pub.publish_nowait({"data": f"{count[0]}:{msg.data}"})
    node.handoff(lambda: str(count[0]).encode(), lambda state: count.__setitem__(0, int(state)))
    await node.subscriber("stringEchoReq", "std_msgs/String", handle, queue_size=100)
    await node.service("stringEchoService", "Test/StringEcho", lambda req: {"data": req.data})
    await node.spin()

rce.node.run(main, "stringEcho")
"""


SLOW = """#!/usr/bin/env python3
import time

import rce.node


async def main(node):
    pub = await node.publisher("stringEchoResp", "std_msgs/String", queue_size=200)

    def handle(msg):
        time.sleep(0.04)                  # 40 ms of work an input: a burst leaves a backlog
        pub.publish_nowait({"data": msg.data})
    await node.subscriber("stringEchoReq", "std_msgs/String", handle, queue_size=200)
    await node.service("stringEchoService", "Test/StringEcho", lambda req: {"data": req.data})
    await node.spin()

rce.node.run(main, "stringEcho")
"""


def _package(d: Path, code: str) -> Path:
    """Package directory ``d`` with ``code`` as its executable ``stringEcho.py``."""
    d.mkdir(parents=True)
    (d / "stringEcho.py").write_text(code)
    os.chmod(d / "stringEcho.py", 0o755)
    return d


@pytest.fixture(scope="module")
def eng(tmp_path_factory):
    work = tmp_path_factory.mktemp("move")
    src = Path(__import__("rce").__file__).parent / "packages" / "Test" / "stringEcho.py"
    pkg = _package(work / "pkgs" / "CloudEcho", src.read_text())      # a package only the cloud host has
    both = _package(work / "pkgs-both" / "Counting", COUNTER)          # a node with state, on both hosts
    _package(work / "pkgs-both" / "SlowEcho", SLOW)                    # 40 ms an input, on both hosts
    e = start_engine(work / "engine", container_hosts=0)
    plain = dict(e.env)
    e.env["RCE_PACKAGE_PATH"] = f"{pkg.parent}:{both.parent}"
    e.add_container_host("--name", "dc1")
    e.env = {**plain, "RCE_PACKAGE_PATH": str(both.parent)}
    e.add_container_host("--zone", "robot:mover", "--user", "testUser", "--name", "mover-computer")
    e.env = plain
    yield e
    e.stop()


class Stream:
    """Numbered messages at RATE and their echoes, each stamped (monotonic s)."""

    def __init__(self, r: RawRobot, parse=int, rate: float = RATE):
        self.r, self.sent, self.echoes, self.other, self.parse, self.rate = r, 0, [], [], parse, rate

    async def run(self) -> None:
        async with asyncio.TaskGroup() as tg:
            tg.create_task(self._send())
            tg.create_task(self._read())

    async def _send(self) -> None:
        while True:
            await self.send()
            await asyncio.sleep(1 / self.rate)

    async def send(self) -> None:
        """The next numbered message (numbered before it is sent: a burst may interleave)."""
        k, self.sent = self.sent, self.sent + 1
        await self.r.send("DM", {"iTag": "req", "type": "std_msgs/String", "msgID": "", "msg": {"data": str(k)}})

    async def _read(self) -> None:
        while True:
            m = await self.r.recv(60)
            if isinstance(m, dict) and m.get("type") == "DM" and m["data"]["iTag"] == "resp":
                self.echoes.append((time.monotonic(), self.parse(m["data"]["msg"]["data"])))
            elif isinstance(m, dict):
                self.other.append(m)

    async def until(self, n: int) -> None:
        end = time.monotonic() + WAIT
        while len(self.echoes) < n:
            assert time.monotonic() < end, f"{len(self.echoes)} echoes of {n}"
            await asyncio.sleep(0.02)

    def gap(self, t0: float, t1: float) -> float:
        ts = [t for t, _ in self.echoes if t0 <= t <= t1]
        return max((b - a for a, b in zip(ts, ts[1:], strict=False)), default=float("inf"))


def host_of(eng, ctag: str) -> str:
    return next(c["host"] for c in eng.admin("/api/containers") if c["ctag"] == ctag)


async def test_moves_to_the_robot_and_back_lose_nothing(eng):
    # never shed, even on a loaded machine (maxLag=0): every message must come back
    async with RawRobot(eng.master_url, "mover", query="&maxLag=0") as r:
        await _echo_container(r, "echoM", "Converter", {"placement": "auto", "robot": "mover", "deadline_ms": 1000})
        assert host_of(eng, "echoM") == "dc1"
        s = Stream(r)
        task = asyncio.create_task(s.run())
        try:
            # the node subscribes a moment after the interfaces are up: the first echo is the start
            await s.until(1)
            first = s.echoes[0][1]
            await s.until(10)
            gaps = []
            for zone, where in (("robot", "mover-computer"), ("cloud", "dc1")):
                t0 = time.monotonic()
                res = await asyncio.to_thread(eng.admin, "/api/placement/testUser/echoM", {"pin": zone})
                t1 = time.monotonic()
                assert res["moved"] and res["moved"]["to"].endswith(f"({where})"), res
                assert host_of(eng, "echoM") == where
                before = (await asyncio.to_thread(eng.admin, "/api/containers/testUser/echoM/stats"))["msgs_in"]
                n = len(s.echoes)
                await s.until(n + 20)
                after = (await asyncio.to_thread(eng.admin, "/api/containers/testUser/echoM/stats"))["msgs_in"]
                assert after - before >= 10, f"the stream goes through the copy on {where}"
                gaps.append((zone, s.gap(t0 - 0.5, t1 + 0.5), res["moved"]))
            sent_before_stop = s.sent
            await s.until(sent_before_stop - first - 2)
        finally:
            task.cancel()
        seqs = [q for _, q in s.echoes]
        assert seqs == sorted(seqs), "echoes in order"
        assert len(seqs) == len(set(seqs)), "no echo twice"
        missing = sorted(set(range(first, seqs[-1] + 1)) - set(seqs))
        assert not missing, f"lost across the moves: {missing}"
        moved = [m for m in s.other if m.get("type") == "ST" and m["data"].get("moved")]
        assert len(moved) == 2, "the robot is told of each move"
        for zone, gap, rec in gaps:
            print(f"move to {zone}: longest gap between echoes {gap * 1e3:.0f} ms at {RATE:g} Hz; "
                  f"built {rec['make_s']:.2f} s, switched {rec['switch_s'] * 1e3:.1f} ms, "
                  f"drained {rec['drain_s']:.2f} s")
        assert [m["to"].split(" ")[0] for m in eng.admin("/api/placement/moves")][-2:] == ["robot:mover", "cloud"]
        shown = subprocess.run([str(Path(sys.executable).parent / "rce-console"), "--master", eng.master_url,
                                "placement", "moves"], capture_output=True, text=True, env=eng.env, timeout=60)
        assert shown.returncode == 0 and "robot:mover" in shown.stdout and "pinned to robot" in shown.stdout, shown
        ts = {t["name"]: t for t in eng.admin("/api/tasksets") if t["kind"] == "container"}
        assert ts["mover-computer"]["containers"] == 0 and ts["dc1"]["containers"] == 1
        with urllib.request.urlopen(eng.master_url + "metrics", timeout=10) as resp:
            metrics = resp.read().decode()
        assert "rce_master_container_moves_total 2.0" in metrics, "the two moves, counted"
        assert 'rce_master_container_results{ctag="echoM",host="dc1",user="testUser"}' in metrics
        res = eng.admin("/api/containers/testUser/echoM/stats")["results"]
        assert res["results"] >= 20 and res["deadline_ms"] == 1000, res     # timed on the copy it runs on now
        assert 0 <= res["p50_ms"] <= res["max_ms"] and res["misses"] <= res["results"], res


async def test_a_node_hands_its_state_over(eng):
    async with RawRobot(eng.master_url, "mover") as r:
        await _echo_container(r, "counter", "Converter", {"placement": "auto", "robot": "mover"}, pkg="Counting")
        s = Stream(r, parse=lambda d: tuple(int(x) for x in d.split(":")))
        task = asyncio.create_task(s.run())
        try:
            await s.until(10)
            for where in ("mover-computer", "dc1"):
                moved = await asyncio.to_thread(eng.admin, "/api/containers/testUser/counter/move", {"host": where})
                assert moved["states"] == 1, moved
                n = len(s.echoes)
                await s.until(n + 10)
        finally:
            task.cancel()
        counts = [c for _, (c, _) in s.echoes]
        seqs = [q for _, (_, q) in s.echoes]
        assert counts == list(range(counts[0], counts[0] + len(counts))), "the count goes on across both moves"
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "every message handled once, in order"


async def test_a_move_that_fails_part_way_leaves_it_running_where_it_was(eng):
    async with RawRobot(eng.master_url, "mover") as r:
        await _echo_container(r, "cloudOnly", "Converter", {"placement": "auto", "robot": "mover"}, pkg="CloudEcho")
        s = Stream(r)
        task = asyncio.create_task(s.run())
        try:
            await s.until(5)
            with pytest.raises(Exception) as err:
                await asyncio.to_thread(eng.admin, "/api/containers/testUser/cloudOnly/move",
                                        {"host": "mover-computer"})
            assert "runs where it was" in str(err.value) and "CloudEcho" in str(err.value)
            assert host_of(eng, "cloudOnly") == "dc1"
            n = len(s.echoes)
            await s.until(n + 20)
        finally:
            task.cancel()
        seqs = [q for _, q in s.echoes]
        assert seqs == sorted(seqs) and len(seqs) == len(set(seqs))
        assert not sorted(set(range(seqs[0], seqs[-1] + 1)) - set(seqs)), "the stream went on undisturbed"
        ts = {t["name"]: t for t in eng.admin("/api/tasksets") if t["kind"] == "container"}
        assert ts["mover-computer"]["containers"] == 0


async def test_a_container_with_ordered_moves_keeps_its_results_in_order_across_a_backlog(eng):
    """The old copy still has 60 inputs to handle (2.4 s of work) when the move begins; without
    ``ordered_moves`` the new copy's first echoes would overtake them."""
    async with RawRobot(eng.master_url, "mover", query="&maxLag=0") as r:
        await _echo_container(r, "ordered", "Converter", {"placement": "auto", "robot": "mover",
                                                            "ordered_moves": True}, pkg="SlowEcho")
        assert host_of(eng, "ordered") == "dc1"
        s = Stream(r, rate=10.0)
        task = asyncio.create_task(s.run())
        try:
            await s.until(1)
            first = s.echoes[0][1]
            await s.until(5)
            for _ in range(60):
                await s.send()
            moved = await asyncio.to_thread(eng.admin, "/api/containers/testUser/ordered/move",
                                            {"host": "mover-computer"})
            assert moved["states"] == 0 and moved["fenced"], moved
            assert host_of(eng, "ordered") == "mover-computer"
            n = s.sent
            await s.until(n - first + 10)
        finally:
            task.cancel()
        seqs = [q for _, q in s.echoes]
        assert len(seqs) == len(set(seqs)), "no echo twice"
        overtaken = [(a, b) for a, b in zip(seqs, seqs[1:], strict=False) if b < a]
        assert not overtaken, f"echoes in order: {overtaken[:5]}"
        assert not sorted(set(range(first, seqs[-1] + 1)) - set(seqs)), "none lost"
