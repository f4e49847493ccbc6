"""ROS messages: the one message registry and JSON codec (:mod:`.registry`), its ROS 1 codec
compiled per class (:mod:`.compiled`), the JSON forms of times, images and byte arrays
(:mod:`.forms`), the structure check forwarders use (:mod:`.structure`), ROS strings as bytes
(:mod:`.ros_strings`) and ROS 1 type identities (:mod:`.ros1_types`)."""
from rce.messages.registry import (MessageRegistry, default_registry, store_name,
                                   takes_binary_message, wire_name)
from rce.messages.forms import JsonForms

__all__ = ["JsonForms", "MessageRegistry", "default_registry", "store_name", "takes_binary_message", "wire_name"]
