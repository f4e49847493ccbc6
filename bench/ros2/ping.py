"""The robot's side of bench/rtt_ros2.py: an rclpy node that publishes ``std_msgs/msg/String`` on
``/req`` and times each answer on ``/resp`` (raw CDR both ways: no (de)serialization in the loop).

Reads one JSON object on stdin: ``{"sizes": [bytes...], "reps": {size: n}, "wait_s": s}``; waits until
``/req`` has a subscriber and ``/resp`` a publisher (at most ``wait_s``), sends one unmeasured message
per size, then ``reps`` timed round trips; prints one JSON line
``{"rtt_ms": {size: [ms...]}, "cpu_ms": {size: ms per round trip}, "lost": {size: n}}``.
"""
from __future__ import annotations

import json
import sys
import time

import rclpy
from rclpy.serialization import serialize_message
from std_msgs.msg import String

TIMEOUT = 10.0     # s an answer may take before the round trip counts as lost


def main() -> int:
    spec = json.loads(sys.stdin.readline())
    rclpy.init()
    node = rclpy.create_node("rtt_ping")
    pub = node.create_publisher(String, "/req", 10)
    got: list[bytes] = []
    node.create_subscription(String, "/resp", got.append, 10, raw=True)
    deadline = time.monotonic() + spec.get("wait_s", 60)
    while (pub.get_subscription_count() == 0 or node.count_publishers("/resp") == 0) and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    out: dict = {"rtt_ms": {}, "cpu_ms": {}, "lost": {}}

    def once(payload: bytes) -> float | None:
        got.clear()
        t0 = time.perf_counter()
        pub.publish(payload)
        end = t0 + TIMEOUT
        while not got and time.perf_counter() < end:
            rclpy.spin_once(node, timeout_sec=0.5)
        return (time.perf_counter() - t0) * 1e3 if got else None

    for size in spec["sizes"]:
        payload = serialize_message(String(data="x" * size))
        once(payload)                                   # unmeasured: every hop is hot
        n = int(spec["reps"][str(size)])
        rtts, lost = [], 0
        c0 = time.process_time()
        for _ in range(n):
            ms = once(payload)
            if ms is None:
                lost += 1
            else:
                rtts.append(ms)
        out["rtt_ms"][size], out["lost"][size] = rtts, lost
        out["cpu_ms"][size] = (time.process_time() - c0) * 1e3 / max(1, n)
        print(json.dumps({"progress": size}), file=sys.stderr, flush=True)
    print(json.dumps(out), flush=True)
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
