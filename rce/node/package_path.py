"""Node packages: where ``pkg``/``exe`` of an addNodes request are found.

Search order (like ``ROS_PACKAGE_PATH``): every directory on ``RCE_PACKAGE_PATH``
(``:``-separated; a directory is either a package itself, named after it, or
holds packages as subdirectories), then packages installed with the project:
the built-in ``rce/packages`` directory and every ``rce.packages`` entry point
(value: a directory path string, e.g. ``rce_fleet.packages:PACKAGE_DIR``).

A package is a directory with executables (Python scripts or any executable
file) and optional ``msg/*.msg`` and ``srv/*.srv`` definitions, which are
registered into the message registry when the package is loaded.
"""
from __future__ import annotations

import os
from importlib import metadata
from pathlib import Path

from rce.plumbing.errors import NotFound, RequestError
from rce.messages import MessageRegistry

BUILTIN_DIR = Path(__file__).parents[1] / "packages"


def search_path(env: dict | None = None) -> list[Path]:
    """Directories searched for packages, in order."""
    env = os.environ if env is None else env
    dirs = [Path(p) for p in env.get("RCE_PACKAGE_PATH", "").split(os.pathsep) if p]
    dirs.append(BUILTIN_DIR)
    for ep in metadata.entry_points(group="rce.packages"):
        try:
            dirs.append(Path(ep.load()).parent)
        except Exception:   # a broken plug-in never hides the others
            continue
    return dirs


def find_package(pkg: str, env: dict | None = None) -> Path:
    """Directory of package ``pkg``; raises :class:`NotFound` listing where it looked."""
    if not pkg or "/" in pkg or pkg.startswith("."):
        raise RequestError(f"illegal package name {pkg!r}")
    dirs = search_path(env)
    for d in dirs:
        if d.name == pkg and d.is_dir():
            return d
        cand = d / pkg
        if cand.is_dir():
            return cand
    raise NotFound(f"package {pkg!r} not found on the package path ({', '.join(map(str, dirs))})")


def find_executable(pkg: str, exe: str, env: dict | None = None) -> Path:
    """Path of executable ``exe`` in package ``pkg``; :class:`NotFound` if missing."""
    if not exe or "/" in exe or exe.startswith("."):
        raise RequestError(f"illegal executable name {exe!r}")
    d = find_package(pkg, env)
    for cand in (d / exe, d / "scripts" / exe, d / "nodes" / exe):
        if cand.is_file():
            return cand
    raise NotFound(f"executable {exe!r} not found in package {pkg!r} ({d})")


def load_package_types(registry: MessageRegistry, env: dict | None = None) -> list[str]:
    """Register the ``.msg``/``.srv`` files of every package on the path; returns their names."""
    names = []
    seen = set()
    for d in search_path(env):
        cands = [d] + (sorted(p for p in d.iterdir() if p.is_dir()) if d.is_dir() else [])
        for p in cands:
            if p in seen or not ((p / "msg").is_dir() or (p / "srv").is_dir()):
                continue
            seen.add(p)
            names += registry.load_definitions(p.name, p)
    return names
