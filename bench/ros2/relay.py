"""The topology's floor of bench/rtt_ros2.py: two plain rclpy relay nodes joined by a plain websocket,
with nothing of rce between them. ``relay.py server PORT`` (the cloud's side: what arrives on the
websocket is published on ``/req``, ``/resp`` goes back on it) and ``relay.py client URL`` (the robot's
side: ``/req`` goes out on the websocket, what comes back is published on ``/resp``). Each is in its own
ROS 2 graph (``ROS_DOMAIN_ID``), as a robot and a container are.

Raw CDR both ways, an executor spinning in a thread and the messages handed to the asyncio loop with
``call_soon_threadsafe`` (the pattern an asyncio bridge uses), websockets' binary frames. Prints
``ready`` on stdout once its websocket is up; on SIGTERM, ``{"msgs": n, "cpu_s": s}`` on stderr.
"""
from __future__ import annotations

import asyncio
import json
import signal
import sys
import threading
import time

import rclpy
import websockets
from rclpy.executors import SingleThreadedExecutor
from std_msgs.msg import String

MAX = 64 * 1024 * 1024     # bytes: the largest frame (10 MB messages and more)


async def run(role: str, where: str) -> None:
    loop = asyncio.get_running_loop()
    rclpy.init(signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    node = rclpy.create_node(f"relay_{role}")
    out_topic, in_topic = ("/req", "/resp") if role == "server" else ("/resp", "/req")
    pub = node.create_publisher(String, out_topic, 10)
    inbox: asyncio.Queue[bytes] = asyncio.Queue(maxsize=1000)
    count = [0]
    node.create_subscription(String, in_topic, lambda raw: loop.call_soon_threadsafe(inbox.put_nowait, raw), 10,
                             raw=True)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True, name="rclpy").start()
    stop = loop.create_future()
    loop.add_signal_handler(signal.SIGTERM, stop.set_result, None)

    async def pump(ws) -> None:
        async def outgoing() -> None:
            while True:
                await ws.send(await inbox.get())

        sender = asyncio.ensure_future(outgoing())
        try:
            async for frame in ws:
                count[0] += 1
                pub.publish(frame)
        finally:
            sender.cancel()

    c0 = time.process_time()
    if role == "server":
        async with websockets.serve(pump, "127.0.0.1", int(where), max_size=MAX, compression=None):
            print("ready", flush=True)
            await stop
    else:
        async with websockets.connect(where, max_size=MAX, compression=None) as ws:
            print("ready", flush=True)
            task = asyncio.ensure_future(pump(ws))
            await stop
            task.cancel()
    print(json.dumps({"msgs": count[0], "cpu_s": time.process_time() - c0}), file=sys.stderr, flush=True)
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    asyncio.run(run(sys.argv[1], sys.argv[2]))
