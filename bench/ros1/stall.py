#!/usr/bin/python3
"""ROS 1 (Debian ros-comm, rospy) peer of ``bench/stall.py``: a stream into an echo node that is
frozen for a while.

A ``rosmaster --core``, the echo node of ``bench/ros1_peer.py`` (``/req`` -> ``/resp``,
``std_msgs/String``, ``tcp_nodelay``, publisher ``queue_size`` 10) in its own process, and this
client node: it publishes ``/req`` (``queue_size`` 10, as the anchors) at ``--rate`` Hz with
``--size``-byte payloads that start with the message's sequence number, and takes ``/resp``.
After ``--warmup`` s it stops the echo node (SIGSTOP) for ``--stall`` s, continues it (SIGCONT)
and publishes ``--after`` s more, then waits ``--drain`` s for the last echoes.

Run with the system python3 that has rospy::

    /usr/bin/python3 bench/ros1/stall.py [--size B] [--rate HZ] [--warmup S] [--stall S] [--after S]

Environment: ``ROS1_PORT`` (master port, default 11498), ``ROS_HOME`` (default a fresh
temporary directory). Prints one JSON line: ``{"peer": "ros1-rospy", "sent": [[seq, t], ...],
"echoes": [[seq, t], ...], "t_stop": t, "t_cont": t}``, times from ``time.monotonic()`` (s).
"""
import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
PEER = os.path.join(HERE, "..", "ros1_peer.py")
sys.path.insert(0, os.path.dirname(HERE))
from ros1_peer import wait_master  # noqa: E402  (bench/ros1_peer.py: the round-trip peer)

WIRING_WAIT_S = 30.0        # s: the echo node must be wired both ways within this
SEQ_DIGITS = 10             # the payload's first characters: the sequence number


def client(a, echo_pid):
    import rospy
    from std_msgs.msg import String
    rospy.init_node("stall_client", disable_signals=True)
    echoes, lock, first = [], threading.Lock(), threading.Event()

    def cb(m):
        t = time.monotonic()
        with lock:
            echoes.append((int(m.data[:SEQ_DIGITS]), t))
        first.set()
    rospy.Subscriber("/resp", String, cb, tcp_nodelay=True)
    pub = rospy.Publisher("/req", String, queue_size=10)
    filler = "a" * max(0, a.size - SEQ_DIGITS)
    deadline = time.monotonic() + WIRING_WAIT_S
    while not first.is_set():                      # until the echo node is wired both ways
        if time.monotonic() > deadline:
            raise RuntimeError(f"no echo within {WIRING_WAIT_S:g} s")
        pub.publish(String(data=f"{0:0{SEQ_DIGITS}d}"))
        first.wait(0.2)
    time.sleep(0.5)                                # the wiring echoes are in
    with lock:
        echoes.clear()
    sent, period = [], 1.0 / a.rate
    t0 = time.monotonic()
    t_stop = t0 + a.warmup
    t_cont = t_stop + a.stall
    t_end = t_cont + a.after
    stopped = continued = False
    seq = 1
    while True:
        now = time.monotonic()
        if not stopped and now >= t_stop:
            os.kill(echo_pid, signal.SIGSTOP)
            stopped, t_stop = True, time.monotonic()
        if stopped and not continued and now >= t_cont:
            os.kill(echo_pid, signal.SIGCONT)
            continued, t_cont = True, time.monotonic()
        if now >= t_end:
            break
        sent.append((seq, time.monotonic()))
        pub.publish(String(data=f"{seq:0{SEQ_DIGITS}d}" + filler))
        seq += 1
        time.sleep(max(0.0, t0 + (seq - 1) * period - time.monotonic()))
    time.sleep(a.drain)
    with lock:
        got = list(echoes)
    print(json.dumps({"peer": "ros1-rospy", "sent": sent, "echoes": got, "t_stop": t_stop, "t_cont": t_cont}),
          flush=True)
    rospy.signal_shutdown("done")


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", type=int, default=1_000_000, help="payload bytes (default 1 MB)")
    p.add_argument("--rate", type=float, default=30.0, help="messages per second (default 30)")
    p.add_argument("--warmup", type=float, default=2.0, help="s of streaming before the stall (default 2)")
    p.add_argument("--stall", type=float, default=3.0, help="s the echo node is stopped (default 3)")
    p.add_argument("--after", type=float, default=4.0, help="s of streaming after it is continued (default 4)")
    p.add_argument("--drain", type=float, default=3.0, help="s to wait for the last echoes (default 3)")
    a = p.parse_args()
    port = int(os.environ.get("ROS1_PORT", "11498"))
    os.environ["ROS1_PORT"] = str(port)                # the echo node (ros1_peer.py) reads it
    os.environ["ROS_MASTER_URI"] = f"http://127.0.0.1:{port}"
    os.environ["ROS_HOSTNAME"] = "127.0.0.1"
    os.environ.setdefault("ROS_HOME", tempfile.mkdtemp(prefix="ros1stall-"))
    master = subprocess.Popen(["rosmaster", "--core", "-p", str(port)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    echo = None
    try:
        wait_master(port)
        echo = subprocess.Popen([sys.executable, PEER, "echo"], stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        client(a, echo.pid)
    finally:
        for q in (echo, master):
            if q is not None:
                try:
                    q.send_signal(signal.SIGCONT)
                except ProcessLookupError:
                    pass
                q.terminate()
                q.wait()


if __name__ == "__main__":
    main()
