"""A follower with one relay and no other way to the cloud (docs/relays.md), in network namespaces the
test makes (root; deleted after, also on failure): the cloud (the real engine) in the root namespace,
leader L1 (``rce-ros --relay-port``) with an uplink to it, follower F (``rce-ros --relays L1``) with a link
only to L1, a 10 Hz numbered stream through converters to a container's stringEcho.py.

Three faults, one after the other, each ending with F's session resumed through L1 and every message of
the stream echoed exactly once and in order:

- L1's uplink down for 5 s and up again (F's relay answers 504 meanwhile: the endpoint lives, F keeps
  resuming the same session instead of counting it dead);
- L1's process killed -9 and a new one started;
- the F - L1 link down for 5 s and up again (F's packets vanish without an error).
"""
from __future__ import annotations

import asyncio
import os
import signal

import pytest

import rce.node
from rce.tools.launch import start_engine
from rce.tools.netlab import NetLab, RelayTopology
from rce_client.reconnect import _reason
from nsrobot import RosRun, echo_config
from test_relay import RELAY_PORT, Stream, leader_config, master_url, robot_row, wait_until

pytestmark = pytest.mark.asyncio

DARK = 5.0                   # s a link stays down: longer than the ping timeout, shorter than the resume grace


@pytest.fixture
def topo():
    with NetLab("rls") as lab:
        yield RelayTopology.make(lab)


@pytest.fixture
def cloud(topo, tmp_path):
    e = start_engine(tmp_path / "engine", master_args=("--bind", "0.0.0.0"),
                     robot_args=("--bind", "0.0.0.0", "--advertise-host", topo.cloud_ip))
    yield e
    e.stop()


async def start_leader(topo, cloud, tmp_path) -> RosRun:
    l1 = await RosRun.start(topo.lab, "l1", leader_config(master_url(cloud, topo), "L1"), tmp_path,
                            "--relay-port", str(RELAY_PORT))
    await l1.wait_line("relaying for nearby robots")
    return l1


async def survives(f: RosRun, stream: Stream, fault, heal) -> None:
    """Cause ``fault()``, wait until F has noticed, keep the link dark for :data:`DARK` s, ``heal()``;
    then F's session resumes through L1 and the stream goes on."""
    mark = len(f.lines)
    await fault()
    await f.wait_line("link to the cloud lost; resuming", after=mark)
    await asyncio.sleep(DARK)               # the outage's length, a timer: what the test is about
    await heal()
    assert "through relay L1" in await f.wait_line("rce-ros: session resumed", after=mark)
    n = len(stream.got)
    await stream.wait_count(n + 10)


async def test_follower_resumes_through_its_only_relay(topo, cloud, tmp_path):
    l1 = await start_leader(topo, cloud, tmp_path)
    f = await RosRun.start(topo.lab, "f", echo_config(master_url(cloud, topo), "F"), tmp_path,
                           "--relays", f"{topo.f_l1.a_ip}:{RELAY_PORT}")
    leaders = [l1]
    node = None
    try:
        await f.wait_line("rce-ros: ready")
        node = await rce.node.init_node("tester", bus=str(f.bus), argv=[])
        cid = next(c["cid"] for c in cloud.admin("/api/containers") if c["ctag"] == "cF")
        stream = Stream(node)
        await stream.start()
        await stream.wait_count(1)
        first = stream.got[0]               # messages before the interfaces' path was whole are not echoed
        await stream.wait_count(10)
        assert robot_row(cloud, "F")["relay"] == "L1"

        async def uplink_down():
            topo.lab.set_up(topo.up1, False, side="b")

        async def uplink_up():
            topo.lab.set_up(topo.up1, True, side="b")
            topo.lab.route("l1", "default", topo.up1.a_ip)      # the link's down took its routes

        await survives(f, stream, uplink_down, uplink_up)
        assert any("HTTP 504" in line for line in f.lines), "the relay said its uplink is cut"

        async def kill_relay():
            os.kill(leaders[-1].proc.pid, signal.SIGKILL)
            await leaders[-1].proc.wait()

        async def restart_relay():
            leaders.append(await start_leader(topo, cloud, tmp_path))

        await survives(f, stream, kill_relay, restart_relay)

        async def hop_down():
            topo.lab.set_up(topo.f_l1, False, side="a")

        async def hop_up():
            topo.lab.set_up(topo.f_l1, True, side="a")

        await survives(f, stream, hop_down, hop_up)
        await wait_until(lambda: (robot_row(cloud, "F") or {}).get("relay") == "L1", "the master sees F through L1")

        await stream.stop()
        await stream.wait_count(stream.sent - first)
        assert stream.got == list(range(first, stream.sent)), "every message echoed once, in order"
        assert [c["cid"] for c in cloud.admin("/api/containers") if c["ctag"] == "cF"] == [cid]
        assert not [line for line in f.lines if "moved" in line or "connection closed" in line]
        gaps = "\n".join(f.lines).split("link to the cloud lost; resuming")[1:]
        assert len(gaps) == 3
        for gap in gaps:
            fails = [_reason(line.split("reason", 1)[1]) for line in gap.splitlines()
                     if "reconnect attempt failed" in line]
            assert fails and len(fails) == len(set(fails)), "each reason a retry failed for is said once per gap"
    finally:
        if node is not None:
            await node.close()
        for r in (f, *leaders):
            await r.stop()
