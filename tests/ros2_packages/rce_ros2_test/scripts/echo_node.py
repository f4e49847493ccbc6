#!/usr/bin/env python3
"""A plain ROS 2 node, written for rclpy and nothing else (no rce import).

- declares the parameter ``prefix`` (default ""), read again for every message and call;
- subscribes ``in`` (``std_msgs/msg/String``) and republishes each message on ``out`` with the
  prefix in front;
- serves ``set_flag`` (``std_srvs/srv/SetBool``): answers ``success = data`` and the message
  ``<prefix><data>@<its full name>``, so a test can tell the answer came from this node;
- publishes ``latched`` (``std_msgs/msg/String``, transient local, depth 1) once as it starts,
  like a map server its map;
- subscribes ``strict`` asking for a deadline of 1 s, a QoS a plain publisher does not offer.
"""
import rclpy
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile
from std_msgs.msg import String
from std_srvs.srv import SetBool


class Echo(Node):
    def __init__(self):
        super().__init__("echo_node")
        self.declare_parameter("prefix", "")
        latched = self.create_publisher(String, "latched",
                                        QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        latched.publish(String(data="published once, at the start"))
        self.out = self.create_publisher(String, "out", 10)
        self.create_subscription(String, "in", self.on_message, 10)
        self.create_service(SetBool, "set_flag", self.on_call)
        self.create_subscription(String, "strict", lambda _m: None, QoSProfile(depth=10, deadline=Duration(seconds=1)))
        self.get_logger().info("echo_node ready")

    def prefix(self):
        return self.get_parameter("prefix").value

    def on_message(self, msg):
        self.out.publish(String(data=self.prefix() + msg.data))

    def on_call(self, request, response):
        response.success = request.data
        response.message = f"{self.prefix()}{request.data}@{self.get_fully_qualified_name()}"
        return response


def main():
    rclpy.init()
    rclpy.spin(Echo())


if __name__ == "__main__":
    main()
