"""Multipath TCP (docs/lanes.md "Multipath TCP") in network namespaces the test makes (root; deleted
after, also on failure): the cloud (the real engine, ``rce-robot --mptcp``) in the root namespace; a
robot namespace R with two veth paths to it, P1 (its route to the cloud) and P2 (an MPTCP ``subflow``
endpoint, with a source route through P2). ``rce-ros --mptcp`` in R echoes a numbered 20 Hz stream
through a container's stringEcho.py. Mid-stream P1 goes dark (R's end down: what R sends on it is lost
without an error): the stream goes on over P2 with no reconnect and no session resume, and every message
arrives once, in order."""
from __future__ import annotations

import asyncio
import json
import subprocess
import time

import pytest

import rce.node
from rce.tools.launch import start_engine
from rce.tools.netlab import NetLab
from nsrobot import WAIT, RosRun, echo_config

pytestmark = pytest.mark.asyncio
RATE = 20.0                  # Hz of the numbered stream
BEFORE, AFTER = 20, 40       # messages echoed before P1 goes down, and sent after


@pytest.fixture
def lab():
    with NetLab("mpt") as lab:
        lab.namespace("r")
        p1, p2 = lab.link(None, "r", 1), lab.link(None, "r", 2)
        lab.route("r", "default", p1.a_ip)
        r = lab.full("r")
        lab.ip("-n", r, "rule", "add", "from", p2.b_ip, "table", "102")          # P2's source goes out on P2
        lab.ip("-n", r, "route", "add", "default", "via", p2.a_ip, "dev", p2.b_dev, "table", "102")
        lab.ip("-n", r, "mptcp", "limits", "set", "subflows", "2", "add_addr_accepted", "2")
        lab.ip("-n", r, "mptcp", "endpoint", "add", p2.b_ip, "dev", p2.b_dev, "subflow")
        subprocess.run(lab.wrap("r", ["sysctl", "-qw", "net.mptcp.stale_loss_cnt=1"]), check=True)   # one lost RTO
        yield lab, p1, p2


@pytest.fixture
def cloud(lab, tmp_path):
    _, p1, _ = lab
    e = start_engine(tmp_path / "engine", master_args=("--bind", "0.0.0.0"),
                     robot_args=("--bind", "0.0.0.0", "--advertise-host", p1.a_ip, "--mptcp"))
    yield e
    e.stop()


def robot_config(url: str) -> dict:
    return echo_config(url, "M")


def mptcp_sockets(lab: NetLab, port: int) -> list[str]:
    """R's established MPTCP sockets to the cloud's websocket ``port`` (``ss -M``)."""
    out = subprocess.run(lab.wrap("r", ["ss", "-HMn", "state", "established", f"( dport = :{port} )"]),
                         capture_output=True, text=True, check=True).stdout
    return [line for line in out.splitlines() if line.strip()]


async def test_a_path_that_goes_down_mid_stream_costs_no_reconnect_and_no_message(lab, cloud, tmp_path):
    netlab, p1, p2 = lab
    robot = await RosRun.start(netlab, "r", robot_config(f"http://{p1.a_ip}:{cloud.http_port}/"), tmp_path,
                               "--mptcp", "--max-lag", "0")     # never shed on a loaded machine: all must arrive
    node = None
    try:
        await robot.wait_line("rce-ros: ready")
        assert mptcp_sockets(netlab, cloud.robot_ready[0]["ws_port"]), "the session's link is not MPTCP"
        node = await rce.node.init_node("tester", bus=str(robot.bus), argv=[])
        got: asyncio.Queue = asyncio.Queue()
        arrived: list[tuple[int, float]] = []
        # the echoes held up behind the dark path arrive in one burst (up to ~15 of them): the queue holds the
        # whole stream, so a drop would be the link's, not this subscriber's (ROS's queue_size drops the oldest)
        sub = await node.subscriber("/resp", "std_msgs/String", lambda m: got.put_nowait(m.data),
                                    queue_size=2 * (BEFORE + AFTER))
        pub = await node.publisher("/req", "std_msgs/String")
        async with asyncio.timeout(WAIT):            # the first messages may precede the subscription's path
            while True:
                await pub.publish({"data": "warm-up"})
                try:
                    await asyncio.wait_for(got.get(), 1.0)
                    break
                except asyncio.TimeoutError:
                    continue

        async def stream() -> None:
            for i in range(BEFORE + AFTER):
                await pub.publish({"data": json.dumps(i)})
                if i == BEFORE:
                    netlab.set_up(p1, False, side="b")     # P1 goes dark mid-stream
                await asyncio.sleep(1 / RATE)              # the stream's rate, a timer

        async def collect() -> None:
            while len(arrived) < BEFORE + AFTER:
                data = await got.get()
                if data != "warm-up":
                    arrived.append((json.loads(data), time.monotonic()))

        async with asyncio.timeout(WAIT):
            await asyncio.gather(stream(), collect())
        assert [i for i, _ in arrived] == list(range(BEFORE + AFTER))      # each once, in order
        assert sub.dropped == 0
        gap = max(b - a for (_, a), (_, b) in zip(arrived, arrived[1:], strict=False))
        print(f"longest gap between echoes across the path change: {gap * 1000:.0f} ms")   # reported, not a bound
        assert not any("link to the cloud lost" in line or "session resumed" in line for line in robot.lines)
    finally:
        if node is not None:
            await node.close()
        await robot.stop()
