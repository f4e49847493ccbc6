"""The node API, in the spirit of rospy (:mod:`.runtime`): ``import rce.node``, then
``rce.node.run(main, "talker")``; graph names (:mod:`.naming`), node packages
(:mod:`.package_path`), direct links between nodes (:mod:`.links`) and ROS 1 from Debian
(:mod:`.ros1`)."""
from rce.node.runtime import (Node, Publisher, ServiceProxy, Subscriber, init_node, load_types, node_argv,
                              run)

__all__ = ["Node", "Publisher", "ServiceProxy", "Subscriber", "init_node", "load_types", "node_argv", "run"]
