"""ROS messages: the one message registry and JSON codec (:mod:`.registry`), its ROS 1 codec
compiled per class (:mod:`.compiled`), the JSON forms of times, images and byte arrays
(:mod:`.forms`), the structure check forwarders use (:mod:`.structure`), ROS strings as bytes
(:mod:`.ros_strings`), ROS 1 type identities (:mod:`.ros1_types`) and ROS 2 types and CDR
(:mod:`.ros2`)."""
from rce.interfaces.classes import is_ros2_name, same_type
from rce.messages.registry import MessageRegistry, default_registry, store_name, takes_binary_message, wire_name
from rce.messages.forms import JsonForms
from rce.messages import ros2     # the registry's ROS 2 half (it sets itself as the registry's ROS 2 factory)

__all__ = ["JsonForms", "MessageRegistry", "default_registry", "is_ros2_name", "ros2", "same_type", "store_name",
           "takes_binary_message", "wire_name"]
