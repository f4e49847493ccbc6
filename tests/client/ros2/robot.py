"""A robot's own ROS 2 programs, plain rclpy (nothing of rce): what tests/client/test_ros2_bridge.py
runs beside ``rce-ros --ros2``. One mode per run, printing what it saw, one line each; exit 0 when
done, 1 (with the reason) when a step did not happen within ``DEADLINE`` s.

    robot.py talk OUT BACK TEXT...     publish each TEXT on OUT (std_msgs/msg/String), print each that comes
                                       back on BACK
    robot.py bad TOPIC                 publish bytes that are no std_msgs/msg/String CDR on TOPIC (raw)
    robot.py latched IN LATCHED TEXT   publish TEXT on IN; once it is on LATCHED, a transient-local subscriber
                                       joining late gets it too
    robot.py reliable TOPIC            a reliable subscription on TOPIC: print its incompatible-QoS event
    robot.py serve NAME ACTION         a std_srvs/srv/SetBool server NAME and a test_msgs/action/Fibonacci server
                                       ACTION, until stdin closes
    robot.py call NAME                 call SetBool NAME with data true
    robot.py goals ACTION              a goal to its end (feedback, result), then one cancelled on its way
    robot.py flood TOPIC               publish on TOPIC as amcl publishes /amcl_pose (reliable, transient local,
                                       depth 1) every PERIOD s, printing each thousandth, until stdin closes
"""
from __future__ import annotations

import sys
import threading
import time

import rclpy
from rclpy.duration import Duration
from rclpy.action import ActionClient, ActionServer, CancelResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import MultiThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from std_srvs.srv import SetBool
from test_msgs.action import Fibonacci

DEADLINE = 60.0      # s for each step (a loaded 2-core machine)
STEP = 0.1           # s between the Fibonacci server's feedbacks
PERIOD = 0.001       # s between the flood's messages


def say(*words: object) -> None:
    print(*words, flush=True)


def spin_until(node, cond, what: str) -> None:
    """Spin ``node`` until ``cond()``; exit 1 naming ``what`` after DEADLINE s."""
    end = time.monotonic() + DEADLINE
    while not cond():
        if time.monotonic() > end:
            say(f"timeout: {what}")
            sys.exit(1)
        rclpy.spin_once(node, timeout_sec=0.05)


def talk(node, out: str, back: str, *texts: str) -> None:
    got: list[str] = []
    sub = node.create_subscription(String, back, lambda m: (got.append(m.data), say(f"back: {m.data}")), 10)
    pub = node.create_publisher(String, out, 10)
    spin_until(node, lambda: pub.get_subscription_count() > 0 and sub.get_publisher_count() > 0,
               f"the bridge on {out} and {back}")
    for text in texts:
        pub.publish(String(data=text))
        spin_until(node, lambda t=text: t in got, f"{text!r} back on {back}")


def bad(node, topic: str) -> None:
    pub = node.create_publisher(String, topic, 10)
    spin_until(node, lambda: pub.get_subscription_count() > 0, f"the bridge on {topic}")
    pub.publish(b"\x00\x01\x00\x00\xff\x00\x00\x00ab")      # CDR header, a string of 255 bytes, then 2 bytes
    # a reliable writer that exits before the bridge's reader acknowledged the sample loses it
    if not pub.wait_for_all_acked(Duration(seconds=DEADLINE)):
        say(f"timeout: the bridge's acknowledgement on {topic}")
        sys.exit(1)
    say("published bad bytes")


def latched(node, topic_in: str, topic_latched: str, text: str) -> None:
    tl = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    early: list[str] = []
    node.create_subscription(String, topic_latched, lambda m: early.append(m.data), tl)
    pub = node.create_publisher(String, topic_in, 10)
    spin_until(node, lambda: pub.get_subscription_count() > 0, f"the bridge on {topic_in}")
    pub.publish(String(data=text))
    spin_until(node, lambda: text in early, f"{text!r} on {topic_latched}")
    say(f"early: {early[-1]}")
    late = rclpy.create_node("late_joiner")
    got: list[str] = []
    late.create_subscription(String, topic_latched, lambda m: got.append(m.data), tl)
    spin_until(late, lambda: got, f"a late joiner's message on {topic_latched}")
    say(f"late: {got}")


def reliable(node, topic: str) -> None:
    events: list[str] = []

    def on_event(e) -> None:
        events.append(e.last_policy_kind.name)
        say(f"incompatible QoS: {e.last_policy_kind.name}")
    reliable_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(String, topic, lambda m: None, reliable_qos,
                             event_callbacks=SubscriptionEventCallbacks(incompatible_qos=on_event))
    spin_until(node, lambda: events, f"an incompatible-QoS event on {topic}")


def serve(node, name: str, action: str) -> None:
    group = ReentrantCallbackGroup()

    def set_bool(req, resp):
        resp.success, resp.message = req.data, f"robot got {req.data}"
        return resp

    def execute(goal):
        seq = [0, 1]
        for _ in range(goal.request.order - 1):
            if goal.is_cancel_requested:
                goal.canceled()
                say(f"goal canceled after {len(seq)}")
                return Fibonacci.Result(sequence=seq)
            seq.append(seq[-1] + seq[-2])
            goal.publish_feedback(Fibonacci.Feedback(sequence=seq))
            time.sleep(STEP)
        goal.succeed()
        say(f"goal succeeded: {seq}")
        return Fibonacci.Result(sequence=seq)
    node.create_service(SetBool, name, set_bool, callback_group=group)
    ActionServer(node, Fibonacci, action, execute, callback_group=group,
                 cancel_callback=lambda _req: CancelResponse.ACCEPT)
    ex = MultiThreadedExecutor(4)
    ex.add_node(node)
    spinning = threading.Thread(target=ex.spin, daemon=True)
    spinning.start()
    say("serving")
    sys.stdin.read()            # until the test closes stdin
    ex.shutdown()               # then a clean exit: DDS's shared-memory segments go with it
    spinning.join(DEADLINE)


def call(node, name: str) -> None:
    cli = node.create_client(SetBool, name)
    if not cli.wait_for_service(timeout_sec=DEADLINE):
        say(f"timeout: service {name}")
        sys.exit(1)
    fut = cli.call_async(SetBool.Request(data=True))
    spin_until(node, fut.done, f"the answer of {name}")
    say(f"answer: success={fut.result().success} message={fut.result().message}")


def goals(node, action: str) -> None:
    cli = ActionClient(node, Fibonacci, action)
    if not cli.wait_for_server(timeout_sec=DEADLINE):
        say(f"timeout: action server {action}")
        sys.exit(1)
    feedback: list[list[int]] = []
    for order, cancel in ((5, False), (45, True)):      # fib(45) still fits the result's int32
        feedback.clear()
        sent = cli.send_goal_async(Fibonacci.Goal(order=order),
                                   feedback_callback=lambda f: feedback.append(list(f.feedback.sequence)))
        spin_until(node, sent.done, "the goal's answer")
        handle = sent.result()
        say(f"goal order={order} accepted={handle.accepted}")
        if cancel:
            spin_until(node, lambda: len(feedback) >= 2, "two feedbacks")
            canceling = handle.cancel_goal_async()
            spin_until(node, canceling.done, "the cancel's answer")
            r = canceling.result()
            say(f"cancel: return_code={r.return_code} canceling={len(r.goals_canceling)}")
        result = handle.get_result_async()
        spin_until(node, result.done, "the result")
        res = result.result()
        tail = f"feedbacks>=2={len(feedback) >= 2}" if cancel else f"feedback={feedback}"
        say(f"result: status={res.status} sequence={list(res.result.sequence)[:7]} {tail}")


def flood(node, topic: str) -> None:
    pub = node.create_publisher(String, topic, QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    spin_until(node, lambda: pub.get_subscription_count() > 0, f"the bridge on {topic}")
    say("matched")
    closed = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), closed.set()), daemon=True).start()
    n = 0
    while not closed.wait(PERIOD):
        n += 1
        pub.publish(String(data=f"pose {n}"))
        if n % 1000 == 0:
            say(f"published {n}")


MODES = {"talk": talk, "bad": bad, "latched": latched, "reliable": reliable, "serve": serve, "call": call,
         "goals": goals, "flood": flood}

if __name__ == "__main__":
    rclpy.init()
    mode = sys.argv[1]
    node = rclpy.create_node(f"robot_{mode}")
    try:
        MODES[mode](node, *sys.argv[2:])
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
