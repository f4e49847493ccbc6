"""A move's fence across a thin, shaped link, in network namespaces the test makes (root; deleted
after, also on failure): the cloud (master, robot endpoint, cloud host ``fc1``) in the root
namespace; robot ``F``'s own computer (``rce-container --zone robot:F``, its data plane on R's
address) in namespace R, joined by one veth pair shaped with HTB (no ``netem`` here).

- moved from the robot's computer to the cloud and back while bursts of 8 kB messages cross the
  2 Mbit/s link (each burst takes ~0.3 s to pass, so the old copy still has messages on their way
  when the switch comes): every message echoed exactly once, and each move fenced (the old copy
  went only after its fences, its node and the endpoint's acknowledgement);
- a fence that cannot arrive (the cloud's links to the old copy squeezed to 8 kbit/s behind 80 kB
  of messages; the master's control link left alone) does not hang the move: the old copy goes
  after the move's ``drain_max_s``, the move says it was not fenced, the master counts it, and the
  container answers from its new host.
"""
from __future__ import annotations

import asyncio
import subprocess
import time
import urllib.request

import pytest

from rce.tools.launch import command, start_engine
from rce.tools.netlab import NetLab
from test_dataflow import _echo_container
from wsclient import RawRobot

pytestmark = pytest.mark.asyncio
ROBOT = "F"
WAIT = 60.0           # s any one step may take on a loaded machine
PAD = 8000            # bytes of padding per message (std_msgs/String)
BURST, EVERY = 10, 0.5    # messages per burst, s between bursts: 1.3 Mbit/s each way on a 2 Mbit/s link


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fence")
    with NetLab("mfn") as lab:
        lab.namespace("r")
        link = lab.link(None, "r", 1)
        lab.route("r", "default", link.a_ip)
        e = start_engine(tmp / "engine", container_hosts=0, master_args=("--bind", "0.0.0.0"),
                         robot_args=("--bind", "0.0.0.0", "--advertise-host", link.a_ip))
        try:
            e.add_container_host("--name", "fc1")
            control_port = e.masters[0].rsplit(":", 1)[1]
            ready = tmp / "robot-computer.ready"
            e.spawn("robot-computer", lab.wrap("r", [
                *command("rce-container"), f"{link.a_ip}:{control_port}", "--bind", "0.0.0.0",
                "--advertise-host", link.b_ip, "--zone", f"robot:{ROBOT}", "--user", "testUser",
                "--name", "f-computer", "--runtime-dir", str(tmp / "rt-robot"), "--ready-file", str(ready)]), ready)
            yield lab, link, e
        finally:
            e.stop()


class Bursts:
    """Numbered, padded messages in bursts, and their echoes (numbers, in arrival order)."""

    def __init__(self, r: RawRobot):
        self.r, self.sent, self.echoes = r, 0, []

    async def send(self, n: int) -> None:
        for _ in range(n):
            await self.r.send("DM", {"iTag": "req", "type": "std_msgs/String", "msgID": "",
                                     "msg": {"data": f"{self.sent}:{'x' * PAD}"}})
            self.sent += 1

    async def run(self) -> None:
        while True:
            await self.send(BURST)
            await asyncio.sleep(EVERY)         # the sensor's period

    async def read(self) -> None:
        while True:
            m = await self.r.recv(WAIT)
            if isinstance(m, dict) and m.get("type") == "DM" and m["data"]["iTag"] == "resp":
                self.echoes.append(int(m["data"]["msg"]["data"].split(":", 1)[0]))

    async def until(self, n: int) -> None:
        end = time.monotonic() + WAIT
        while len(self.echoes) < n:
            assert time.monotonic() < end, f"{len(self.echoes)} echoes of {n}"
            await asyncio.sleep(0.02)

    async def first_echo(self) -> None:
        """One message a sensor's period until the first echo (the node may subscribe a moment after
        the interfaces are up)."""
        end = time.monotonic() + WAIT
        while not self.echoes:
            assert time.monotonic() < end, "no echo"
            await self.send(1)
            await asyncio.sleep(0.2)                           # the sensor's period

    async def all_back(self) -> None:
        """Until every message sent so far came back (or WAIT passes)."""
        end = time.monotonic() + WAIT
        while set(range(self.sent)) - set(self.echoes) and time.monotonic() < end:
            await asyncio.sleep(0.05)


async def move(e, ctag: str, where: str, **more) -> dict:
    return await asyncio.to_thread(e.admin, f"/api/containers/testUser/{ctag}/move", {"host": where, **more})


def host_of(e, ctag: str) -> str:
    return next(c["host"] for c in e.admin("/api/containers") if c["ctag"] == ctag)


def tc(link, side: str, *args: str) -> None:
    ns = link.a if side == "a" else link.b
    subprocess.run([*(("ip", "netns", "exec", ns) if ns else ()), "tc", *args], check=True, capture_output=True,
                   text=True)


async def test_moves_across_a_thin_link_lose_nothing(world):
    lab, link, e = world
    for side in ("a", "b"):
        lab.shape(link, side, "2mbit")
    # never shed, even on a loaded machine (maxLag=0): every message must come back
    async with RawRobot(e.master_url, ROBOT, query="&maxLag=0") as r:
        await _echo_container(r, "thin", "Converter", {"placement": "robot", "robot": ROBOT})
        assert host_of(e, "thin") == "f-computer"
        b = Bursts(r)
        tasks = [asyncio.create_task(b.read()), asyncio.create_task(b.run())]
        try:
            await b.until(BURST)
            for where in ("fc1", "f-computer", "fc1"):
                await asyncio.sleep(EVERY / 2 + 0.05)          # mid-burst: messages still crossing the link
                moved = await move(e, "thin", where)
                assert moved["to"].endswith(f"({where})") and host_of(e, "thin") == where
                assert moved["fenced"] is True, moved
                n = len(b.echoes)
                await b.until(n + 2 * BURST)
            tasks.pop().cancel()                               # no more sending
            await b.all_back()
        finally:
            for t in tasks:
                t.cancel()
    first = min(b.echoes)
    assert sorted(b.echoes) == list(range(first, b.sent)), \
        f"lost {sorted(set(range(first, b.sent)) - set(b.echoes))[:20]}"
    assert len(b.echoes) == len(set(b.echoes)), "nothing echoed twice"


async def test_a_fence_that_cannot_arrive_does_not_hang_the_move(world):
    lab, link, e = world
    for side in ("a", "b"):
        lab.shape(link, side, "100mbit")
    async with RawRobot(e.master_url, ROBOT) as r:
        await _echo_container(r, "stuck", "Converter", {"placement": "robot", "robot": ROBOT})
        b = Bursts(r)
        reader = asyncio.create_task(b.read())
        try:
            await b.first_echo()
            # all the cloud sends to the robot's computer at 8 kbit/s (its messages, by the environment's
            # data port or a node's direct link), but the master's control link to its host
            control_port = e.masters[0].rsplit(":", 1)[1]
            tc(link, "a", "qdisc", "del", "dev", link.a_dev, "root")
            tc(link, "a", "qdisc", "add", "dev", link.a_dev, "root", "handle", "1:", "htb", "default", "20")
            tc(link, "a", "class", "add", "dev", link.a_dev, "parent", "1:", "classid", "1:10", "htb", "rate",
               "100mbit")
            tc(link, "a", "class", "add", "dev", link.a_dev, "parent", "1:", "classid", "1:20", "htb", "rate", "8kbit",
               "ceil", "8kbit")
            tc(link, "a", "filter", "add", "dev", link.a_dev, "parent", "1:", "protocol", "ip", "prio", "1", "u32",
               "match", "ip", "sport", control_port, "0xffff", "flowid", "1:10")
            await b.send(BURST)                                # 80 kB behind which the fence waits: 80 s at 8 kbit/s
            t0 = time.monotonic()
            moved = await move(e, "stuck", "fc1", drain_max_s=2)
            took = time.monotonic() - t0
            assert moved["fenced"] is False and "missing" in moved["unfenced"], moved
            assert took < 2 + 10, f"the move took {took:.1f} s with a 2 s bound"
            assert host_of(e, "stuck") == "fc1"
            n = len(b.echoes)
            await b.send(3)
            await b.until(n + 3)                               # it answers from its new host
        finally:
            reader.cancel()
    with urllib.request.urlopen(e.master_url + "metrics", timeout=10) as resp:
        text = resp.read().decode()
    assert any(line.startswith("rce_master_container_move_fence_timeouts_total") and float(line.split()[-1]) >= 1
               for line in text.splitlines()), "the fall-back is counted"


def endpoint_metric(e, name: str) -> float:
    """The cloud robot endpoint's counter ``name`` (its /metrics)."""
    with urllib.request.urlopen(f"http://127.0.0.1:{e.robot_ready[0]['metrics_port']}/metrics", timeout=10) as resp:
        return float(next(x for x in resp.read().decode().splitlines() if x.startswith(name + " ")).split()[1])


async def test_what_had_not_left_for_the_old_copy_goes_to_the_new_one(world):
    """A stream the 1 Mbit/s link to the robot's computer cannot carry (8 kB every 40 ms, 1.6 Mbit/s)
    backs up in the endpoint's link to the container there; when the container moves to the cloud,
    what waits in that link's queue goes to the new copy instead. Every message is echoed once, or
    was dropped by the endpoint for waiting past its 1 s and counted: none is lost by the move."""
    lab, link, e = world
    lab.shape(link, "a", "1mbit", queue=40, one_segment=True)     # the cloud -> the robot's computer
    lab.shape(link, "b", "100mbit")
    async with RawRobot(e.master_url, ROBOT, query="&maxLag=0") as r:
        await _echo_container(r, "unsent", "Converter", {"placement": "robot", "robot": ROBOT})
        b = Bursts(r)
        reader = asyncio.create_task(b.read())
        try:
            await b.first_echo()
            await b.all_back()
            first, dropped0 = b.sent, endpoint_metric(e, "rce_robot_dataplane_dropped")
            moved0 = endpoint_metric(e, "rce_robot_dataplane_moved_unsent")

            async def stream() -> None:
                while True:
                    await b.send(1)
                    await asyncio.sleep(0.04)
            sender = asyncio.create_task(stream())
            await asyncio.sleep(1.5)                           # the link backs up
            moved = await move(e, "unsent", "fc1")
            assert host_of(e, "unsent") == "fc1" and moved["fenced"] is True, moved
            await asyncio.sleep(0.5)
            sender.cancel()

            def accounted() -> tuple[int, float]:
                return (len({n for n in b.echoes if n >= first}),
                        endpoint_metric(e, "rce_robot_dataplane_dropped") - dropped0)
            end = time.monotonic() + WAIT                      # each echoed, or dropped and counted
            while sum(await asyncio.to_thread(accounted)) < b.sent - first and time.monotonic() < end:
                await asyncio.sleep(0.1)
            _, dropped = await asyncio.to_thread(accounted)
            taken = endpoint_metric(e, "rce_robot_dataplane_moved_unsent") - moved0
        finally:
            reader.cancel()
    echoed = [n for n in b.echoes if n >= first]
    assert len(echoed) == len(set(echoed)), "nothing echoed twice"
    assert taken > 0, "messages waiting for the old copy's link went to the new copy"
    assert b.sent - first == len(echoed) + dropped, \
        f"{b.sent - first} sent, {len(echoed)} echoed, {dropped:.0f} dropped and counted: the rest was lost"
