#!/usr/bin/env python3
"""A plain rclpy action client of ``fibonacci`` (``test_msgs/action/Fibonacci``): one goal to its
end, then one canceled after two feedbacks. What happened goes out as JSON on ``report``
(``std_msgs/msg/String``, transient local: a late subscriber still gets every report); its
``feedback`` counts the goal's feedback messages, those that come after its result too."""
import json
import time

import rclpy
from action_msgs.msg import GoalStatus
from rclpy.action import ActionClient
from rclpy.qos import DurabilityPolicy, QoSProfile
from std_msgs.msg import String
from test_msgs.action import Fibonacci

LATE_FEEDBACK = 5.0   # s a feedback may come after its goal's result


def main():
    rclpy.init()
    node = rclpy.create_node("fibonacci_client")
    report = node.create_publisher(String, "report", QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    client = ActionClient(node, Fibonacci, "fibonacci")
    while not client.wait_for_server(timeout_sec=1.0):
        node.get_logger().info("waiting for the fibonacci server")

    def run(order, cancel_after=None):
        feedback = []
        sent = client.send_goal_async(Fibonacci.Goal(order=order),
                                      feedback_callback=lambda f: feedback.append(list(f.feedback.sequence)))
        rclpy.spin_until_future_complete(node, sent)
        handle = sent.result()
        out = {"order": order, "accepted": handle.accepted}
        if cancel_after:
            while len(feedback) < cancel_after:
                rclpy.spin_once(node, timeout_sec=0.1)
            canceling = handle.cancel_goal_async()
            rclpy.spin_until_future_complete(node, canceling)
            out["canceling"] = len(canceling.result().goals_canceling)
        result = handle.get_result_async()
        rclpy.spin_until_future_complete(node, result)
        names = {GoalStatus.STATUS_SUCCEEDED: "succeeded", GoalStatus.STATUS_CANCELED: "canceled"}
        sequence = list(result.result().result.sequence)
        # feedback and result travel apart (two DDS topics, no order between them): a feedback
        # sent before the result may come after it (each feedback adds one to the server's [0, 1])
        late = time.monotonic() + LATE_FEEDBACK
        while len(feedback) < len(sequence) - 2 and time.monotonic() < late:
            rclpy.spin_once(node, timeout_sec=0.05)
        out.update(status=names.get(result.result().status, str(result.result().status)),
                   sequence=sequence, feedback=len(feedback))
        report.publish(String(data=json.dumps(out)))

    run(6)
    run(60, cancel_after=2)
    rclpy.spin(node)


if __name__ == "__main__":
    main()
