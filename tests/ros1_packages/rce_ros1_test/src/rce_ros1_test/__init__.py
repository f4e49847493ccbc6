"""Python side of the rce_ros1_test ROS 1 package (genpy-generated service classes in srv/)."""
