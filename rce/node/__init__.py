"""The node API, in the spirit of rospy (:mod:`.runtime`): ``import rce.node``, then
``rce.node.run(main, "talker")``; graph names (:mod:`.naming`), node packages
(:mod:`.package_path`), direct links between nodes (:mod:`.links`) and ROS 1 from Debian
(:mod:`.ros1`).

The runtime (and with it the message registry) is imported on the first use of one of its names,
so that a process that only needs :mod:`.naming` (the master) does not load it."""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rce.node.runtime import (Node, Publisher, ServiceProxy, Subscriber, init_node, load_types, node_argv,
                                  run)

__all__ = ["Node", "Publisher", "ServiceProxy", "Subscriber", "init_node", "load_types", "node_argv", "run"]


def __getattr__(name: str):
    """``rce.node.Node`` (...): the names of :mod:`.runtime`, which is imported then."""
    if name in __all__:
        return getattr(importlib.import_module("rce.node.runtime"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
