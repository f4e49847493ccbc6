"""Lanes over a real bottleneck (docs/lanes.md), in network namespaces the test makes (root; deleted after,
also on failure): the cloud (the real engine) in the root namespace, the robot in namespace R; R's uplink
shaped to 10 Mbit/s by HTB with a class per DSCP mark (EF, best effort, CS1). ``rce-ros --lanes
--uplink-rate 9Mbit`` in R bridges a camera (``sensor_msgs/Image`` forwarder into a container) and a
cancel (``std_msgs/String`` converter echoed by stringEcho.py). Under a camera far faster than the
link, every cancel comes back once and in order, the session's link crosses the bottleneck in the EF
class and the camera in the CS1 class, and the bulk link joined.

With one FIFO that ignores the marks and no rate given (``rce-ros --lanes``: the uplink's rate is
estimated from the bulk socket), the estimate comes to the link's rate and the FIFO never holds more than
a fraction of one camera frame: a cancel does not wait behind a bulk backlog."""
from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

import rce.node
from rce.tools.launch import start_engine
from rce.tools.netlab import NetLab, qdisc_backlog
from nsrobot import WAIT, RosRun, echo_config

pytestmark = pytest.mark.asyncio
CANCELS = 30                 # at 10 Hz, under the camera
FRAME = 200_000              # bytes of a camera frame; 20 frames a second: 4 MB/s into a 1.25 MB/s link


LINK = 10e6 / 8             # bytes/s of the uplink


@pytest.fixture
def lab(request):
    """R and its uplink; ``dscp`` (the fixture's parameter, default True): a class per DSCP mark, else one
    FIFO that ignores the marks."""
    with NetLab("lnt") as lab:
        lab.namespace("r")
        link = lab.link(None, "r", 1)
        lab.route("r", "default", link.a_ip)
        lab.shape(link, "b", "10mbit", dscp=getattr(request, "param", True))        # the uplink
        yield lab, link


@pytest.fixture
def cloud(lab, tmp_path):
    _, link = lab
    e = start_engine(tmp_path / "engine", master_args=("--bind", "0.0.0.0"),
                     robot_args=("--bind", "0.0.0.0", "--advertise-host", link.a_ip))
    yield e
    e.stop()


def robot_config(url: str) -> dict:
    return echo_config(url, "L", camera=True)


def image(seq: int):
    t = get_typestore(Stores.ROS1_NOETIC).types
    return t["sensor_msgs/msg/Image"](
        header=t["std_msgs/msg/Header"](seq=seq, stamp=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0),
                                        frame_id="cam"),
        height=1, width=FRAME, encoding="mono8", is_bigendian=0, step=FRAME, data=np.zeros(FRAME, dtype=np.uint8))


class Robot:
    """``rce-ros --lanes ARGS`` in R, and a tester node on its bus: a cancel publisher with its echo, a
    camera publisher."""

    def __init__(self, run: RosRun, node, pub, cam, got: asyncio.Queue):
        self.run, self.node, self.pub, self.cam, self.got = run, node, pub, cam, got
        self.done = asyncio.Event()
        self.camera_task: asyncio.Task | None = None

    @classmethod
    async def start(cls, netlab: NetLab, link, cloud, tmp_path, *args: str) -> "Robot":
        run = await RosRun.start(netlab, "r", robot_config(f"http://{link.a_ip}:{cloud.http_port}/"), tmp_path,
                                 "--lanes", *args)
        try:
            await run.wait_line("rce-ros: ready")
            await run.wait_line("bulk link joined")
            node = await rce.node.init_node("tester", bus=str(run.bus), argv=[])
        except BaseException:
            await run.stop()
            raise
        got: asyncio.Queue = asyncio.Queue()
        await node.subscriber("/resp", "std_msgs/String", lambda m: got.put_nowait(m.data))
        robot = cls(run, node, await node.publisher("/req", "std_msgs/String"),
                    await node.publisher("/camera", "sensor_msgs/Image"), got)
        async with asyncio.timeout(WAIT):            # the first messages may precede the subscription's path
            while True:
                await robot.pub.publish({"data": "warm-up"})
                try:
                    await asyncio.wait_for(got.get(), 1.0)
                    break
                except asyncio.TimeoutError:
                    continue
        return robot

    def start_camera(self) -> None:
        async def camera() -> None:
            n = 0
            while not self.done.is_set():
                await self.cam.publish(image(n))
                n += 1
                await asyncio.sleep(0.05)            # the camera's rate (20 Hz), a timer
        self.camera_task = asyncio.create_task(camera())

    async def cancels(self) -> list[str]:
        """:data:`CANCELS` cancels at 10 Hz; their echoes."""
        echoed = []
        async with asyncio.timeout(WAIT):
            for i in range(CANCELS):
                await self.pub.publish({"data": f"cancel {i}"})
                await asyncio.sleep(0.1)             # the cancel's rate (10 Hz), a timer
            while len(echoed) < CANCELS:
                data = await self.got.get()
                if data != "warm-up":
                    echoed.append(data)
        return echoed

    async def stop(self) -> None:
        self.done.set()
        if self.camera_task is not None:
            await self.camera_task
        await self.node.close()
        await self.run.stop()


async def test_under_a_saturating_camera_every_cancel_comes_back_and_each_lane_takes_its_class(lab, cloud, tmp_path):
    netlab, link = lab
    robot = await Robot.start(netlab, link, cloud, tmp_path, "--uplink-rate", "9Mbit")
    try:
        before = netlab.class_bytes(link, "b")
        robot.start_camera()
        echoed = await robot.cancels()
        assert echoed == [f"cancel {i}" for i in range(CANCELS)]        # 0 control lost, in order
        after = netlab.class_bytes(link, "b")
        sent = {c: after[c] - before.get(c, 0) for c in ("1:10", "1:20", "1:30")}
        assert sent["1:30"] > 1_000_000, sent        # the camera went CS1 (about a second of the link at least)
        assert 0 < sent["1:10"] < sent["1:30"], sent    # the cancels and acks went EF
    finally:
        await robot.stop()


def estimates(lines: list[str]) -> list[dict]:
    """rce-ros's "uplink rate estimated" lines (JSON log lines)."""
    out = []
    for line in lines:
        if "uplink rate estimated" in line:
            out.append(json.loads(line))
    return out


@pytest.mark.parametrize("lab", [False], indirect=True, ids=["fifo"])
async def test_with_the_uplink_rate_estimated_a_fifo_bottleneck_holds_no_bulk_backlog(lab, cloud, tmp_path):
    netlab, link = lab
    robot = await Robot.start(netlab, link, cloud, tmp_path)        # no rate: estimated
    try:
        robot.start_camera()
        await robot.run.wait_line('"rate_mode": "cruise"')      # estimated, and the pacer cruising under it
        backlog: list[int] = []
        sampling = asyncio.Event()

        async def sample_backlog() -> None:
            while not sampling.is_set():
                proc = await asyncio.create_subprocess_exec(*netlab.backlog_argv(link, "b"),
                                                            stdout=asyncio.subprocess.PIPE)
                out, _ = await proc.communicate()
                backlog.append(qdisc_backlog(out.decode()))
                await asyncio.sleep(0.02)            # the sampling's period, a timer

        sampler = asyncio.create_task(sample_backlog())
        echoed = await robot.cancels()
        sampling.set()
        await sampler
        assert echoed == [f"cancel {i}" for i in range(CANCELS)]        # 0 control lost, in order
        last = estimates(robot.run.lines)[-1]
        print(f"uplink estimate {last['rate_estimate']} B/s ({last['rate_estimate'] / LINK:.0%} of the link), "
              f"FIFO backlog max {max(backlog)} B, median {sorted(backlog)[len(backlog) // 2]} B "
              f"over {len(backlog)} samples")                        # reported, not a bound
        assert last["rate_source"] == "estimated"
        assert 0.6 * LINK <= last["rate_estimate"] <= 1.2 * LINK, last      # the link's rate, in a generous band
        assert len(backlog) >= 10
        assert max(backlog) < FRAME / 2, backlog        # never a camera frame's worth waiting in front of a cancel
    finally:
        await robot.stop()
