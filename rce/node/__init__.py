"""The node API, in the spirit of rospy (:mod:`.runtime`): ``import rce.node``, then
``rce.node.run(main, "talker")``; node packages (:mod:`.package_path`), direct links between nodes
(:mod:`.links`) and each output timed from its input (:mod:`.results`). Graph names are
:mod:`rce.interfaces.naming` (the master and the bus use them, and are no nodes)."""
from rce.node.runtime import Node, Publisher, ServiceProxy, Subscriber, init_node, load_types, node_argv, run

__all__ = ["Node", "Publisher", "ServiceProxy", "Subscriber", "init_node", "load_types", "node_argv", "run"]
