"""Lanes over a real bottleneck (docs/lanes.md), in network namespaces the test makes (root; deleted after,
also on failure): the cloud (the real engine) in the root namespace, the robot in namespace R; R's uplink
shaped to 10 Mbit/s by HTB with a class per DSCP mark (EF, best effort, CS1). ``rce-ros --lanes
--uplink-rate 9Mbit`` in R bridges a camera (``sensor_msgs/Image`` forwarder into a container) and a
cancel (``std_msgs/String`` converter echoed by stringEcho.py). Under a camera far faster than the
link, every cancel comes back once and in order, the session's link crosses the bottleneck in the EF
class and the camera in the CS1 class, and the bulk link joined."""
from __future__ import annotations

import asyncio

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

import rce.node
from rce.tools.launch import start_engine
from rce.tools.netlab import NetLab
from nsrobot import WAIT, RosRun, echo_config

pytestmark = pytest.mark.asyncio
CANCELS = 30                 # at 10 Hz, under the camera
FRAME = 200_000              # bytes of a camera frame; 20 frames a second: 4 MB/s into a 1.25 MB/s link


@pytest.fixture
def lab():
    with NetLab("lnt") as lab:
        lab.namespace("r")
        link = lab.link(None, "r", 1)
        lab.route("r", "default", link.a_ip)
        lab.shape(link, "b", "10mbit", dscp=True)        # the uplink
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


async def test_under_a_saturating_camera_every_cancel_comes_back_and_each_lane_takes_its_class(lab, cloud, tmp_path):
    netlab, link = lab
    robot = await RosRun.start(netlab, "r", robot_config(f"http://{link.a_ip}:{cloud.http_port}/"), tmp_path,
                               "--lanes", "--uplink-rate", "9Mbit")
    node = None
    try:
        await robot.wait_line("rce-ros: ready")
        await robot.wait_line("bulk link joined")
        node = await rce.node.init_node("tester", bus=str(robot.bus), argv=[])
        got: asyncio.Queue = asyncio.Queue()
        await node.subscriber("/resp", "std_msgs/String", lambda m: got.put_nowait(m.data))
        pub = await node.publisher("/req", "std_msgs/String")
        cam = await node.publisher("/camera", "sensor_msgs/Image")
        async with asyncio.timeout(WAIT):            # the first messages may precede the subscription's path
            while True:
                await pub.publish({"data": "warm-up"})
                try:
                    await asyncio.wait_for(got.get(), 1.0)
                    break
                except asyncio.TimeoutError:
                    continue
        before = netlab.class_bytes(link, "b")
        done = asyncio.Event()

        async def camera() -> None:
            n = 0
            while not done.is_set():
                await cam.publish(image(n))
                n += 1
                await asyncio.sleep(0.05)            # the camera's rate (20 Hz), a timer

        async def cancels() -> list[str]:
            echoed = []
            for i in range(CANCELS):
                await pub.publish({"data": f"cancel {i}"})
                await asyncio.sleep(0.1)             # the cancel's rate (10 Hz), a timer
            while len(echoed) < CANCELS:
                data = await got.get()
                if data != "warm-up":
                    echoed.append(data)
            return echoed

        cam_task = asyncio.create_task(camera())
        async with asyncio.timeout(WAIT):
            echoed = await cancels()
        done.set()
        await cam_task
        assert echoed == [f"cancel {i}" for i in range(CANCELS)]        # 0 control lost, in order
        after = netlab.class_bytes(link, "b")
        sent = {c: after[c] - before.get(c, 0) for c in ("1:10", "1:20", "1:30")}
        assert sent["1:30"] > 1_000_000, sent        # the camera went CS1 (about a second of the link at least)
        assert 0 < sent["1:10"] < sent["1:30"], sent    # the cancels and acks went EF
    finally:
        if node is not None:
            await node.close()
        await robot.stop()
