"""The filesystem view of a namespaced container's nodes: what is hidden, what stays
readable, what is writable. Pure planning here; :mod:`rce_container.nsinit` carries the
plan out in the container's mount namespace.

The plan (:func:`plan`):

- :data:`SCRATCH_DIRS` (``/tmp``, ``/dev/shm``) become private tmpfs of the container
  (mode 1777, :data:`SCRATCH_SIZE` each, in its memory cgroup, gone with it): no other
  container's or the host's files there are visible.
- :data:`HIDDEN_DIRS` (``/var/tmp``, ``/run``) and the task set's runtime and socket
  directories are hidden under an empty tmpfs; of the latter only this container's own
  directory is bound back.
- What nodes need to start (the interpreter's prefixes and site-packages, the engine's
  code, the package search paths: :func:`runtime_paths`) stays visible, read-only: when it lies
  under a hidden directory or under a directory other users cannot enter (``/root``, mode
  0700), that directory is hidden and the path alone bound back.
- Every mount is then remounted read-only except the container's own directory and its
  scratch tmpfs (``writable``).

Docker and bubblewrap build the same view (``--tmpfs /tmp``, ``--ro-bind``); see
docs/containers.md, "Isolation", for why rce does it in its own init.
"""
from __future__ import annotations

import os
import site
import stat
import sys
from pathlib import Path
from typing import Callable

from rce_container.node_env import RUNTIME_ROOT

SCRATCH_DIRS = ("/tmp", "/dev/shm")
HIDDEN_DIRS = ("/var/tmp", "/run")
SCRATCH_SIZE = "64m"       # tmpfs size of each private scratch dir (counted in the container's memory)
SKELETON_SIZE = "64k"      # tmpfs size of a hiding directory (it only holds the mount points bound back)
SCRATCH_OPTS = f"mode=1777,size={SCRATCH_SIZE}"
SKELETON_OPTS = f"mode=0755,size={SKELETON_SIZE}"
PATH_VARS = ("RCE_PACKAGE_PATH", "ROS_PACKAGE_PATH")   # search paths whose directories nodes read


def runtime_paths(env: dict[str, str] | None = None) -> list[str]:
    """Absolute, existing directories a node needs to read: this interpreter's prefixes and
    site-packages, the engine's code (:data:`RUNTIME_ROOT`) and the directories on
    :data:`PATH_VARS` of ``env`` (default :data:`os.environ`). Not ``sys.path`` as such: its
    first entry may be the host's working directory."""
    env = os.environ if env is None else env
    cands = [sys.prefix, sys.base_prefix, sys.exec_prefix, str(RUNTIME_ROOT), *site.getsitepackages()]
    for var in PATH_VARS:
        cands += env.get(var, "").split(os.pathsep)
    out: list[str] = []
    for c in cands:
        if c and os.path.isabs(c) and os.path.isdir(c):
            p = os.path.realpath(c)
            if p not in out:
                out.append(p)
    return out


def _inside(path: str, parent: str) -> bool:
    return path != parent and path.startswith(parent.rstrip("/") + "/")


def closed_ancestor(path: str, mode_of: Callable[[str], int] | None = None) -> str | None:
    """The highest proper ancestor of ``path`` that other users cannot enter (no ``o+x``), or None."""
    mode_of = mode_of or (lambda path: os.stat(path).st_mode)
    parts = Path(path).parts
    for i in range(1, len(parts) - 1):
        d = str(Path(*parts[:i + 1]))
        try:
            if not mode_of(d) & stat.S_IXOTH:
                return d
        except OSError:
            return None
    return None


def plan(workdir: str | Path, socket_dir: str | Path, readable: list[str],
         mode_of: Callable[[str], int] | None = None) -> dict:
    """The mount plan of one container: ``{"masks": [[dir, [keep...], tmpfs_opts], ...],
    "writable": [path...]}``. ``masks`` are in the order to apply (outer first); each hides
    ``dir`` under a tmpfs and binds each ``keep`` back. ``workdir``: the container's own
    directory (writable); ``socket_dir``: the directory of its bus socket; ``readable``:
    :func:`runtime_paths`; ``mode_of(path)``: ``st_mode`` (tests pass their own)."""
    workdir, socket_dir = str(workdir), str(socket_dir)
    opts = {d: SCRATCH_OPTS for d in SCRATCH_DIRS}
    opts.update({d: SKELETON_OPTS for d in HIDDEN_DIRS})
    for own in (workdir, socket_dir):
        opts.setdefault(str(Path(own).parent), SKELETON_OPTS)
    for p in readable:
        closed = closed_ancestor(p, mode_of)
        if closed:
            opts.setdefault(closed, SKELETON_OPTS)
    keeps = [workdir, socket_dir, *readable]
    masks: dict[str, list[str]] = {}
    for d in sorted(opts, key=lambda target: (len(Path(target).parts), target)):
        outer = next((m for m in masks if _inside(d, m)), None)
        if outer is not None and not any(k == d or _inside(d, k) for k in masks[outer]):
            continue                          # already hidden by the outer mask
        masks[d] = [k for k in keeps if _inside(k, d)]
    for d, ks in masks.items():               # a keep inside another keep comes along with it
        masks[d] = [k for k in dict.fromkeys(ks) if not any(_inside(k, o) for o in ks)]
    return {"masks": [[d, ks, opts[d]] for d, ks in masks.items()],
            "writable": [workdir, *SCRATCH_DIRS]}
