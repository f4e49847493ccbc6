"""The Python module of the rce_ros2_test package, where ament_python keeps it (beside package.xml):
rce puts the package's directory on its nodes' PYTHONPATH."""
import json


def seen_report(me: str, heard: set, nodes: list) -> str:
    """What ``chatter.py`` reports on ``seen``: JSON ``{me, heard, nodes}`` (names sorted)."""
    return json.dumps({"me": me, "heard": sorted(heard - {me}), "nodes": sorted(nodes)})
