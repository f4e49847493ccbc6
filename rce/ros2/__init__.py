"""What every rce process that joins a ROS 2 graph shares (``rce-ros --ros2``, a container's ROS 2 relay,
the fleet's ROS 2 robots): rclpy's classes and QoS profiles of rce's names (:mod:`.classes`, which imports
rclpy) and the ROS 2 domain ids this machine leases to graphs that must stay apart (:mod:`.domains`)."""
