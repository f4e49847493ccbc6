#!/usr/bin/env python3
"""A plain rclpy node that says its name on ``chatter`` every 0.1 s and, every 0.5 s, reports on
``seen`` (``std_msgs/msg/String``, JSON) whose names it heard there and which other nodes its
graph shows (with its package's own Python module, ament_python's layout)."""
import rclpy
from rce_ros2_test import seen_report
from std_msgs.msg import String


def main():
    rclpy.init()
    node = rclpy.create_node("chatter")
    me = node.get_fully_qualified_name()
    heard = set()
    chatter = node.create_publisher(String, "chatter", 10)
    seen = node.create_publisher(String, "seen", 10)
    node.create_subscription(String, "chatter", lambda m: heard.add(m.data), 10)
    node.create_timer(0.1, lambda: chatter.publish(String(data=me)))

    def report():
        nodes = [n for n in node.get_node_names() if n != node.get_name() and not n.startswith("rce_ros2_relay")]
        seen.publish(String(data=seen_report(me, heard, nodes)))
    node.create_timer(0.5, report)
    rclpy.spin(node)


if __name__ == "__main__":
    main()
