#!/usr/bin/env python3
"""benchecho/ack.py: the camera's receiver of bench/lanes.py.

    ack.py [--topic /camera] [--ack /camera_ack]

Subscribes to TOPIC (``sensor_msgs/Image``) and, for each frame, publishes on ACK a
``std_msgs/String`` ``{"seq": header.seq, "age": s}``: ``age`` is the time from the frame's
``header.stamp`` (wall clock of its sender, the same machine) to its arrival here, s."""
import argparse
import json
import time

import rce.node


async def main(node: rce.node.Node) -> None:
    p = argparse.ArgumentParser(prog="ack.py")
    p.add_argument("--topic", default="/camera")
    p.add_argument("--ack", default="/camera_ack")
    a = p.parse_args(rce.node.node_argv())
    pub = await node.publisher(a.ack, "std_msgs/String", queue_size=100)

    def on_frame(m) -> None:
        age = time.time() - (m.header.stamp.sec + m.header.stamp.nanosec * 1e-9)
        pub.publish_nowait({"data": json.dumps({"seq": m.header.seq, "age": round(age, 6)})})
    await node.subscriber(a.topic, "sensor_msgs/Image", on_frame, queue_size=2)
    await node.spin()


if __name__ == "__main__":
    rce.node.run(main, "benchack")
