#!/usr/bin/python3
"""ROS 1 (rospy) simulated robot of bench/paper_experiments.py, the peer of its rce robot.

    robot.py --name robot0 --topic /robot0/scan --kind scan|image --rate HZ --duration S [--back]

Publishes sensor_msgs/LaserScan (360 beams) or sensor_msgs/Image (640x480 rgb8) at a fixed rate.
Stdio protocol with the bench: prints READY once the server subscribed (with --back: once the
first echo came back), waits for GO on stdin, publishes for --duration s, waits for late echoes,
prints ``DONE {json}``, then waits for EXIT (or end of stdin) so its CPU time can still be read."""
import argparse
import json
import math
import os
import random
import statistics
import sys
import threading
import time

import rospy
from sensor_msgs.msg import Image, LaserScan


def make_msg(kind):
    if kind == "scan":
        m = LaserScan()
        m.header.frame_id = "base_scan"
        m.angle_min, m.angle_max = -math.pi, math.pi
        m.angle_increment = 2 * math.pi / 360
        m.time_increment, m.scan_time = 0.0, 0.1
        m.range_min, m.range_max = 0.12, 3.5
        rnd = random.Random(1)
        m.ranges = [rnd.uniform(0.2, 3.5) for _ in range(360)]
        m.intensities = []
        return m
    m = Image()
    m.header.frame_id = "camera"
    m.height, m.width, m.encoding, m.is_bigendian, m.step = 480, 640, "rgb8", 0, 640 * 3
    m.data = bytes(i % 251 for i in range(640 * 480 * 3))
    return m


def main():
    p = argparse.ArgumentParser(prog="robot.py")
    p.add_argument("--name", required=True)
    p.add_argument("--topic", required=True)
    p.add_argument("--kind", choices=("scan", "image"), required=True)
    p.add_argument("--rate", type=float, required=True)
    p.add_argument("--duration", type=float, required=True)
    p.add_argument("--back", action="store_true")
    p.add_argument("--suffix", default="_echo")
    p.add_argument("--queue", type=int, default=10)
    a = p.parse_args(rospy.myargv()[1:])
    cls = LaserScan if a.kind == "scan" else Image
    rospy.init_node(a.name, disable_signals=True)
    msg = make_msg(a.kind)
    lat, state = [], {"echoes": 0, "measuring": False}
    got = threading.Event()

    def on_echo(m):
        got.set()
        if state["measuring"]:
            state["echoes"] += 1
            lat.append((time.time() - m.header.stamp.to_sec()) * 1000)
    if a.back:
        rospy.Subscriber(a.topic + a.suffix, cls, on_echo, queue_size=100, tcp_nodelay=True)
    pub = rospy.Publisher(a.topic, cls, queue_size=a.queue, tcp_nodelay=True)
    deadline = time.time() + 60
    while pub.get_num_connections() == 0:
        if time.time() > deadline:
            print("FAIL no subscriber", flush=True)
            return 1
        time.sleep(0.05)
    if a.back:                 # warm up: until the first echo comes back (bounded)
        for _ in range(120):
            msg.header.stamp = rospy.Time.from_sec(time.time())
            pub.publish(msg)
            if got.wait(0.5):
                break
        else:
            print("FAIL no echo", flush=True)
            return 1
        time.sleep(0.3)
    else:
        time.sleep(0.3)        # the subscriber's connection is up on both ends
    print("READY", flush=True)
    if sys.stdin.readline().strip() != "GO":
        return 1
    state["measuring"] = True
    period, sent = 1.0 / a.rate, 0
    t0 = base = time.monotonic()
    while base + sent * period - t0 < a.duration - 1e-6:
        slot, now = base + sent * period, time.monotonic()
        if now < slot:
            time.sleep(slot - now)
        elif now > slot + period:          # behind by more than a period: no burst to catch up (as rospy.Rate)
            base = now - sent * period
        msg.header.seq = sent
        msg.header.stamp = rospy.Time.from_sec(time.time())
        pub.publish(msg)
        sent += 1
    elapsed = a.duration
    end = time.monotonic() + 2.0
    while a.back and state["echoes"] < sent and time.monotonic() < end:
        time.sleep(0.02)
    time.sleep(0.3)
    state["measuring"] = False
    res = {"sent": sent, "elapsed_s": elapsed, "rate_hz": sent / elapsed if elapsed else 0.0,
           "echoes": state["echoes"] if a.back else None,
           "latency_ms_median": statistics.median(lat) if lat else None,
           "latency_ms_p90": sorted(lat)[int(0.9 * (len(lat) - 1))] if lat else None}
    print("DONE " + json.dumps(res), flush=True)
    sys.stdin.readline()
    sys.stdout.flush()
    os._exit(0)            # rospy's orderly shutdown takes seconds and there is nothing to keep


if __name__ == "__main__":
    sys.exit(main())
