"""Finding ROS 1 (Debian's ros-comm) from rce's own Python environment.

rce runs in a virtual environment; Debian installs rospy, rosgraph, genpy and the message
packages (``python3-rospy``, ``python3-rosmaster``, ``python3-std-msgs`` ...) as pure-Python
packages under ``/usr/lib/python3/dist-packages``. :func:`import_rospy` makes them importable
by *appending* that directory to ``sys.path`` (so every package the virtual environment has
still wins), and only when ``rospy`` is not importable already (a ROS install on ``PYTHONPATH``,
or a robot's own catkin workspace, is used as it is).
"""
from __future__ import annotations

import importlib
import os
import sys
from types import ModuleType

from rce.plumbing.errors import ConfigError

#: Where Debian's python3-* ROS 1 packages live; ``RCE_ROS1_PYTHONPATH`` (os.pathsep-separated)
#: overrides it, for a ROS install elsewhere.
DEBIAN_DIST_PACKAGES = "/usr/lib/python3/dist-packages"

#: The Debian packages that give ROS 1's Python side (named in the error when it is missing).
DEBIAN_PACKAGES = "python3-rospy python3-rosmaster python3-std-msgs python3-rostopic python3-rosservice"


def ros1_paths() -> list[str]:
    """The directories searched for ROS 1's Python packages, in order."""
    override = os.environ.get("RCE_ROS1_PYTHONPATH")
    return [p for p in (override.split(os.pathsep) if override else [DEBIAN_DIST_PACKAGES]) if p]


def import_rospy() -> ModuleType:
    """Import and return ``rospy``, appending :func:`ros1_paths` to ``sys.path`` if needed.

    Raises:
        ConfigError: rospy is not installed (the message names the Debian packages to install).
    """
    try:
        return importlib.import_module("rospy")
    except ImportError:
        pass
    for path in ros1_paths():
        if path not in sys.path:
            sys.path.append(path)
    try:
        return importlib.import_module("rospy")
    except ImportError as exc:
        raise ConfigError(f"ROS 1 (rospy) is not installed: {exc}; on Debian: "
                          f"apt-get install {DEBIAN_PACKAGES}") from exc
