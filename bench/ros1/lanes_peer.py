#!/usr/bin/python3
"""ROS 1 (Debian ros-comm, rospy over TCPROS) peer of bench/lanes.py: the same cancel and camera on the
same link.

    lanes_peer.py cloud                 # the echo (/req -> /resp) and the camera's ack (/camera -> /camera_ack)
    lanes_peer.py robot [--idle S] [--camera S] [--camera-rate B/s] [--frame BYTES]

The robot node publishes the cancel (``std_msgs/String`` ``phase:n`` at 10 Hz, ``tcp_nodelay``) and the
camera (``sensor_msgs/Image``, ``queue_size`` 1: a ROS publisher keeps its newest), times each cancel's
echo and collects the acks (``{"seq", "age"}``: the frame's age on arrival). It prints one JSON line in
bench/lanes.py's form. Environment: ROS_MASTER_URI, ROS_IP as usual (the robot runs in namespace R).
"""
import argparse
import json
import sys
import threading
import time

CANCEL_HZ = 10.0
DRAIN = 5.0                 # s after a phase for late echoes
WARMUP = 1.0                # s at the start of a phase the camera's goodput leaves out
LINK = 10_000_000 / 8       # bytes/s


def cloud():
    import rospy
    from sensor_msgs.msg import Image
    from std_msgs.msg import String
    rospy.init_node("lanes_cloud", disable_signals=True)
    echo = rospy.Publisher("/resp", String, queue_size=100, tcp_nodelay=True)
    ack = rospy.Publisher("/camera_ack", String, queue_size=100, tcp_nodelay=True)
    rospy.Subscriber("/req", String, lambda m: echo.publish(m), tcp_nodelay=True)

    def on_frame(m):
        age = time.time() - m.header.stamp.to_sec()
        ack.publish(String(data=json.dumps({"seq": m.header.seq, "age": round(age, 6)})))
    rospy.Subscriber("/camera", Image, on_frame, queue_size=2, buff_size=2 ** 24)
    rospy.spin()


def pct(xs, q):
    return round(xs[min(len(xs) - 1, int(round(q / 100 * (len(xs) - 1))))], 3) if xs else None


def robot(a):
    import rospy
    from sensor_msgs.msg import Image
    from std_msgs.msg import String
    rospy.init_node("lanes_robot", disable_signals=True)
    lock = threading.Lock()
    state = {"phase": "warm", "sent": {}, "rtt": {}, "acks": []}

    def on_echo(m):
        phase, _, n = m.data.partition(":")
        with lock:
            if phase == state["phase"] and n.isdigit() and int(n) in state["sent"]:
                state["rtt"].setdefault(int(n), time.monotonic() - state["sent"][int(n)])

    def on_ack(m):
        with lock:
            state["acks"].append((json.loads(m.data), time.monotonic()))
    rospy.Subscriber("/resp", String, on_echo, tcp_nodelay=True)
    rospy.Subscriber("/camera_ack", String, on_ack, tcp_nodelay=True)
    req = rospy.Publisher("/req", String, queue_size=100, tcp_nodelay=True)
    cam = rospy.Publisher("/camera", Image, queue_size=1)
    deadline = time.monotonic() + 60
    i = 0
    while not state["rtt"] and time.monotonic() < deadline:      # wiring: until one echo comes back
        state["sent"][i] = time.monotonic()
        req.publish(String(data=f"warm:{i}"))
        i += 1
        time.sleep(0.1)
    frame = Image(height=1, width=a.frame, encoding="mono8", step=a.frame, data=bytes(a.frame))
    frame.header.frame_id = "cam"
    out = {}
    for phase, seconds, with_camera in (("idle", a.idle, False), ("camera", a.camera, True)):
        with lock:
            state.update(phase=phase, sent={}, rtt={}, acks=[])
        end = time.monotonic() + seconds
        frames = [0]

        def camera():
            t0 = time.monotonic()
            while time.monotonic() < end:
                frame.header.seq = frames[0]
                frame.header.stamp = rospy.Time.from_sec(time.time())
                cam.publish(frame)
                frames[0] += 1
                time.sleep(max(0.0, t0 + frames[0] * a.frame / a.camera_rate - time.monotonic()))
        t = threading.Thread(target=camera) if with_camera else None
        if t:
            t.start()
        n = 0
        while time.monotonic() < end:
            t_send = time.monotonic()
            with lock:
                state["sent"][n] = t_send
            req.publish(String(data=f"{phase}:{n}"))
            n += 1
            time.sleep(max(0.0, t_send + 1 / CANCEL_HZ - time.monotonic()))
        if t:
            t.join()
        ended = time.monotonic()
        drain = time.monotonic() + DRAIN
        while len(state["rtt"]) < len(state["sent"]) and time.monotonic() < drain:
            time.sleep(0.05)
        with lock:
            ms = sorted(v * 1000 for v in state["rtt"].values())
            window = max(seconds - WARMUP, 1e-9)       # steady state: the phase's first second left out
            acks = [x for x, t_ack in state["acks"] if ended - window <= t_ack <= ended]
            ages = sorted(x["age"] * 1000 for x in acks)
            acked = len(acks)
            out[phase] = {"phase": phase, "cancels": len(state["sent"]), "lost": len(state["sent"]) - len(ms),
                          "p50_ms": pct(ms, 50), "p99_ms": pct(ms, 99), "max_ms": ms[-1] if ms else None,
                          "frames_sent": frames[0], "frames_acked": acked,
                          "goodput_Bps": round(acked * a.frame / window),
                          "goodput_share": round(acked * a.frame / window / LINK, 3),
                          "frame_age_p50_ms": pct(ages, 50), "frame_age_p99_ms": pct(ages, 99)}
    print(json.dumps(out), flush=True)
    rospy.signal_shutdown("done")


def main():
    p = argparse.ArgumentParser(prog="lanes_peer.py")
    p.add_argument("role", choices=("cloud", "robot"))
    p.add_argument("--idle", type=float, default=8.0)
    p.add_argument("--camera", type=float, default=15.0)
    p.add_argument("--camera-rate", type=float, default=5e6)
    p.add_argument("--frame", type=int, default=500_000)
    a = p.parse_args()
    if a.role == "cloud":
        cloud()
    else:
        robot(a)
    return 0


if __name__ == "__main__":
    sys.exit(main())
