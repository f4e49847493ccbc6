"""Finding ROS 1 (Debian's ros-comm) from rce's own Python environment.

rce runs in a virtual environment; Debian installs rospy, rosgraph, genpy and the message
packages (``python3-rospy``, ``python3-rosmaster``, ``python3-std-msgs`` ...) as pure-Python
packages under ``/usr/lib/python3/dist-packages``. :func:`import_rospy` makes them importable
by *appending* that directory to ``sys.path`` (so every package the virtual environment has
still wins), and only when ``rospy`` is not importable already (a ROS install on ``PYTHONPATH``,
or a robot's own catkin workspace, is used as it is).

ROS 2 installs message packages under the same names (``std_msgs``, ``rosgraph_msgs``...: the
``ros2`` extra puts them in the virtual environment), and one process holds one module per name. A
process that imports rospy is a ROS 1 process: :func:`import_rospy` then puts a finder first on
``sys.meta_path`` that takes the ROS 1 message packages (a package with a genpy ``msg`` or ``srv``
module) from :func:`ros1_paths`, and forgets ROS 2 modules of those names imported before
(:func:`forget_ros1` undoes both, for a process that goes on with ROS 2, such as a test run).
"""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import os
import sys
from pathlib import Path
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


def ros1_message_packages(paths: list[str]) -> frozenset[str]:
    """The top-level Python packages under ``paths`` that are ROS 1 message packages (they hold a
    genpy-generated ``msg`` or ``srv`` module)."""
    names = set()
    for base in paths:
        try:
            entries = list(Path(base).iterdir())
        except OSError:
            continue
        names.update(d.name for d in entries if (d / "msg" / "__init__.py").is_file()
                     or (d / "srv" / "__init__.py").is_file())
    return frozenset(names)


class Ros1First(importlib.abc.MetaPathFinder):
    """Finds the ROS 1 message packages ``names`` in ``paths`` before anything else on ``sys.path``
    (their submodules follow their package's ``__path__``)."""

    def __init__(self, names: frozenset[str], paths: list[str]):
        self.names, self.paths = names, paths

    def find_spec(self, fullname, path=None, target=None):
        if fullname not in self.names:
            return None
        return importlib.machinery.PathFinder.find_spec(fullname, self.paths)


def _ros1_first() -> Ros1First | None:
    return next((f for f in sys.meta_path if isinstance(f, Ros1First)), None)


def _evict(names: frozenset[str], keep_under: list[str] | None) -> dict[str, ModuleType]:
    """Forget the modules of packages ``names`` (all, or those not under ``keep_under``); returns them."""
    gone = {}
    for mod_name, mod in list(sys.modules.items()):
        if mod_name.partition(".")[0] not in names:
            continue
        where = getattr(mod, "__file__", None) or ""
        if keep_under is not None and any(where.startswith(p.rstrip("/") + "/") for p in keep_under):
            continue
        gone[mod_name] = sys.modules.pop(mod_name)
    return gone


def forget_ros1() -> None:
    """Undo :func:`import_rospy`'s claim on the message packages' names: the finder goes, and the ROS 1
    modules of those names are forgotten (a later import finds the virtual environment's, ROS 2's)."""
    finder = _ros1_first()
    if finder is not None:
        sys.meta_path.remove(finder)
        _evict(finder.names, None)


def import_rospy() -> ModuleType:
    """Import and return ``rospy``, appending :func:`ros1_paths` to ``sys.path`` if needed, with ROS 1's
    message packages first (:class:`Ros1First`; ROS 2 modules of their names imported before are forgotten).

    Raises:
        ConfigError: rospy is not installed (the message names the Debian packages to install).
    """
    paths = ros1_paths()
    if _ros1_first() is None:
        names = ros1_message_packages(paths)
        if names:
            _evict(names, paths)
            sys.meta_path.insert(0, Ros1First(names, paths))
    try:
        return importlib.import_module("rospy")
    except ImportError:
        pass
    for path in paths:
        if path not in sys.path:
            sys.path.append(path)
    try:
        return importlib.import_module("rospy")
    except ImportError as exc:
        raise ConfigError(f"ROS 1 (rospy) is not installed: {exc}; on Debian: "
                          f"apt-get install {DEBIAN_PACKAGES}") from exc
