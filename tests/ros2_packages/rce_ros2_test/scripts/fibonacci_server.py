#!/usr/bin/env python3
"""A plain rclpy action server (``test_msgs/action/Fibonacci`` at ``fibonacci``), as the ROS 2
tutorials write one: one feedback per step of 0.1 s, cancelable between steps."""
import time

import rclpy
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from test_msgs.action import Fibonacci


class FibonacciServer(Node):
    def __init__(self):
        super().__init__("fibonacci_server")
        ActionServer(self, Fibonacci, "fibonacci", execute_callback=self.execute,
                     goal_callback=lambda _goal: GoalResponse.ACCEPT,
                     cancel_callback=lambda _handle: CancelResponse.ACCEPT, callback_group=ReentrantCallbackGroup())

    def execute(self, handle):
        feedback = Fibonacci.Feedback(sequence=[0, 1])
        for i in range(1, handle.request.order):
            if handle.is_cancel_requested:
                handle.canceled()
                return Fibonacci.Result(sequence=feedback.sequence)
            feedback.sequence.append(feedback.sequence[i] + feedback.sequence[i - 1])
            handle.publish_feedback(feedback)
            time.sleep(0.1)
        handle.succeed()
        return Fibonacci.Result(sequence=feedback.sequence)


def main():
    rclpy.init()
    executor = MultiThreadedExecutor()
    executor.add_node(FibonacciServer())
    executor.spin()


if __name__ == "__main__":
    main()
