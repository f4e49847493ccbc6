#!/usr/bin/env python3
"""Echo: every std_msgs/msg/String on ``req`` is published unchanged on ``resp`` (raw CDR, no decoding).
On SIGINT/SIGTERM it prints ``{"msgs": n, "cpu_s": s}`` on stderr."""
import json
import signal
import sys
import time

import rclpy
from rclpy.executors import ExternalShutdownException
from std_msgs.msg import String

rclpy.init(args=sys.argv)
node = rclpy.create_node("echo")
pub = node.create_publisher(String, "resp", 10)
count = [0]


def echo(raw: bytes) -> None:
    count[0] += 1
    pub.publish(raw)


node.create_subscription(String, "req", echo, 10, raw=True)
signal.signal(signal.SIGTERM, lambda *_: rclpy.try_shutdown())
c0 = time.process_time()
try:
    rclpy.spin(node)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
print(json.dumps({"msgs": count[0], "cpu_s": time.process_time() - c0}), file=sys.stderr, flush=True)
