#!/usr/bin/env python3
"""A plain ROS 1 node, written for rospy and nothing else (no rce import).

- subscribes ``in`` (``std_msgs/String``) and republishes each message on ``out`` with the
  parameter ``/echo_prefix`` (``rospy.get_param``, default "") in front;
- serves ``echo`` (``rce_ros1_test/Echo``): answers the request's data with the same prefix
  and the node's own name after it, so a test can tell the answer came from this node.
"""
import rospy
from rce_ros1_test.srv import Echo, EchoResponse
from std_msgs.msg import String


def main():
    rospy.init_node("echo_node")
    pub = rospy.Publisher("out", String, queue_size=10)

    def on_message(msg):
        pub.publish(String(data=rospy.get_param("/echo_prefix", "") + msg.data))

    def on_call(req):
        return EchoResponse(data=rospy.get_param("/echo_prefix", "") + req.data + "@" + rospy.get_name())

    rospy.Subscriber("in", String, on_message, queue_size=10)
    rospy.Service("echo", Echo, on_call)
    rospy.loginfo("echo_node ready")
    rospy.spin()


if __name__ == "__main__":
    main()
