#!/usr/bin/python3
"""ROS 1 (rospy) server node of bench/paper_experiments.py, the peer of bench/packages/benchecho.

    echo.py --type sensor_msgs/LaserScan [--back] [--suffix _echo] [--report 0.2] TOPIC...

Subscribes to every TOPIC (tcp_nodelay, as the anchors); with --back publishes each message
again on TOPIC + suffix; without, only counts (``rostopic echo`` minus the printing). Prints one
JSON line {"counts": {topic: n}} every --report seconds (cumulative).
Environment: ROS_MASTER_URI, ROS_HOSTNAME as usual."""
import argparse
import importlib
import json
import sys
import threading
import time

import rospy


def msg_class(name):
    pkg, cls = name.split("/")
    return getattr(importlib.import_module(pkg + ".msg"), cls)


def main():
    p = argparse.ArgumentParser(prog="echo.py")
    p.add_argument("--type", required=True)
    p.add_argument("--back", action="store_true")
    p.add_argument("--suffix", default="_echo")
    p.add_argument("--report", type=float, default=0.2)
    p.add_argument("--queue", type=int, default=100)
    p.add_argument("topics", nargs="+")
    a = p.parse_args(rospy.myargv()[1:])
    cls = msg_class(a.type)
    rospy.init_node("benchecho", disable_signals=True)
    counts = {t: 0 for t in a.topics}
    lock = threading.Lock()

    def make_cb(t, pub):
        def cb(m):
            with lock:
                counts[t] += 1
            if pub is not None:
                pub.publish(m)
        return cb
    for t in a.topics:
        pub = rospy.Publisher(t + a.suffix, cls, queue_size=a.queue) if a.back else None
        rospy.Subscriber(t, cls, make_cb(t, pub), queue_size=a.queue, tcp_nodelay=True)
    try:
        while True:
            with lock:
                line = json.dumps({"t": time.time(), "counts": dict(counts)})
            print(line, flush=True)
            time.sleep(a.report)
    except KeyboardInterrupt:
        pass
    finally:
        rospy.signal_shutdown("done")


if __name__ == "__main__":
    sys.exit(main())
