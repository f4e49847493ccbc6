#!/usr/bin/python3
"""ROS 1 (Debian ros-comm, rospy) topic round trip on loopback, with silence before each round trip:
the peer of ``bench/rtt.py --gap S``.

The same topology and message as ``shared/anchors/ros1_rtt.py`` (which has no gap option): a
``rosmaster --core``, an echo node (``/req`` -> ``/resp``, ``std_msgs/String``, ``tcp_nodelay``)
and a client node, each its own process; the client times from just before ``publish`` to its
subscriber callback. With ``--gap S`` the client sleeps S s before each timed round trip (one
unmeasured round trip per size first, as the anchor's hot loop has none to warm).

Run with the system python3 that has rospy::

    /usr/bin/python3 bench/ros1_peer.py [--gap S] [--sizes 3,1623,...] [--reps N]

Environment: ``ROS1_PORT`` (master port, default 11499), ``REPS`` (default 20; a quarter, at least
3, from 1 MB up, as the anchor), ``ROS_HOME`` (default a fresh temporary directory).
Prints one JSON line: ``{"peer": "ros1-rospy", "gap_s": S, "rtt_ms": {size: median_ms},
"samples_ms": {size: [ms, ...]}}``.
"""
import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time

ANCHORS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "anchors")
MASTER_WAIT_S = 10.0        # s: rosmaster must accept connections within this (it takes ~1 s to start)
WIRING_SETTLE_S = 1.0       # s: after the first subscriber connects, as the anchor waits
ECHO_TIMEOUT_S = 10.0       # s: one round trip taking longer counts as lost (NaN), as the anchor


def default_sizes():
    """The payload sizes of shared/anchors/sizes.py (the anchors' sweep)."""
    ns = {}
    with open(os.path.join(ANCHORS, "sizes.py")) as f:
        exec(f.read(), ns)
    return list(ns["SIZES"])


def reps_for(size, reps):
    """As the anchors: REPS per size, a quarter (at least 3) from 1 MB up."""
    return reps if size < 1_000_000 else max(3, reps // 4)


def echo():
    """The echo node: every /req message published again on /resp."""
    import rospy
    from std_msgs.msg import String
    rospy.init_node("echo", disable_signals=True)
    pub = rospy.Publisher("/resp", String, queue_size=10)
    rospy.Subscriber("/req", String, lambda m: pub.publish(m), tcp_nodelay=True)
    rospy.spin()


def client(sizes, reps, gap):
    """The client node: per size one unmeasured round trip, then ``reps`` timed ones, each after
    ``gap`` s of silence; prints the JSON result line."""
    import rospy
    from std_msgs.msg import String
    rospy.init_node("client", disable_signals=True)
    got, box = threading.Event(), {}

    def cb(m):
        box["t"] = time.perf_counter()
        box["n"] = len(m.data)
        got.set()
    rospy.Subscriber("/resp", String, cb, tcp_nodelay=True)
    pub = rospy.Publisher("/req", String, queue_size=10)
    while pub.get_num_connections() == 0:
        time.sleep(0.05)
    time.sleep(WIRING_SETTLE_S)

    def one(payload):
        got.clear()
        t0 = time.perf_counter()
        pub.publish(String(data=payload))
        if not got.wait(ECHO_TIMEOUT_S) or box["n"] != len(payload):
            return float("nan")
        return (box["t"] - t0) * 1000
    out, samples = {}, {}
    for size in sizes:
        payload = "a" * size
        one(payload)
        xs = samples[size] = []
        for _ in range(reps_for(size, reps)):
            if gap > 0:
                time.sleep(gap)
            xs.append(one(payload))
        fin = [x for x in xs if x == x]
        out[size] = statistics.median(fin) if fin else None
    print(json.dumps({"peer": "ros1-rospy", "gap_s": gap, "rtt_ms": out, "samples_ms": samples}), flush=True)
    rospy.signal_shutdown("done")


def wait_master(port):
    deadline = time.monotonic() + MASTER_WAIT_S
    while time.monotonic() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return
        except OSError:
            time.sleep(0.05)
    raise RuntimeError(f"rosmaster on port {port} did not start within {MASTER_WAIT_S} s")


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("role", nargs="?", choices=("echo", "client"), help=argparse.SUPPRESS)
    p.add_argument("--gap", type=float, default=0.0, help="seconds of silence before each round trip (default 0)")
    p.add_argument("--sizes", help="comma-separated sizes in bytes (default shared/anchors/sizes.py)")
    p.add_argument("--reps", type=int, default=int(os.environ.get("REPS", "20")))
    a = p.parse_args()
    port = int(os.environ.get("ROS1_PORT", "11499"))
    os.environ["ROS_MASTER_URI"] = f"http://127.0.0.1:{port}"
    os.environ["ROS_HOSTNAME"] = "127.0.0.1"
    os.environ.setdefault("ROS_HOME", tempfile.mkdtemp(prefix="ros1peer-"))
    sizes = [int(s) for s in a.sizes.split(",")] if a.sizes else default_sizes()
    if a.role == "echo":
        return echo()
    if a.role == "client":
        return client(sizes, a.reps, a.gap)
    master = subprocess.Popen(["rosmaster", "--core", "-p", str(port)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    e = None
    try:
        wait_master(port)
        e = subprocess.Popen([sys.executable, __file__, "echo"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        subprocess.run([sys.executable, __file__, "client", "--gap", str(a.gap), "--reps", str(a.reps),
                        "--sizes", ",".join(map(str, sizes))], timeout=3600, check=False)
    finally:
        for q in (e, master):
            if q is not None:
                q.terminate()
                q.wait()


if __name__ == "__main__":
    sys.exit(main())
