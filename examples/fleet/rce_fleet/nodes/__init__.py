"""rce_fleet.nodes: what runs in the fleet's containers: the global planner and move_client nodes,
their sans-I/O cores and what they share, and the ROS package (``packages/fleet``) that launches them.

- :mod:`.global_planner_core`, :mod:`.move_client_core`: the nodes' logic, sans-I/O.
- :mod:`.tracking`: which cell a robot is in, obstacle filtering, sans-I/O.
- :mod:`.common`: the :class:`~rce_fleet.nodes.common.Out` items the cores return, poses and publishers.
- :mod:`.global_planner_node`, :mod:`.move_client_node`: the nodes' I/O shells (``rce.node``).

May import :mod:`rce_fleet.maps`, :mod:`rce_fleet.planning`, :mod:`rce_fleet.lifelong`,
:mod:`rce_fleet.operations` (the dispatcher and task book), :mod:`rce_fleet.sim` (the local navigator's
parameters) and ``rce.node``; never the demo
(:mod:`rce_fleet.live`) or the CLI. The cores import no sockets or asyncio.

:data:`PACKAGE_DIR`: where the node package (``pkg: fleet``) is installed, registered as the
``rce.packages`` entry point ``fleet`` so container hosts find it without ``RCE_PACKAGE_PATH``."""
from pathlib import Path

PACKAGE_DIR = str(Path(__file__).parent / "packages" / "fleet")
