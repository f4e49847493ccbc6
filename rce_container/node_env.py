"""The environment a node process starts with: minimal and explicit, never the host's.

A container host runs with secrets in its environment (``RCE_ADMIN_TOKEN``, a cluster key,
cloud credentials...). None of that reaches a node: :func:`node_env` builds the node's
environment from scratch, and ``$(env X)`` in node args reads only that environment and only
the names in :data:`ENV_DIRECTIVE_ALLOWED` (:func:`rce_container.launcher.build_args`).

What a node gets (every key, nothing else):

- ``PATH`` (:data:`NODE_PATH` with this interpreter's ``bin`` first), ``HOME`` (the
  container's own directory), ``LANG`` (:data:`NODE_LANG`), ``PYTHONUNBUFFERED=1``,
  ``PYTHONPATH`` (the directory holding the engine's node runtime, :mod:`rce.node`);
- ``RCE_BUS`` (the container's bus socket), ``RCE_BUS_TOKEN`` (the container's bus token,
  checked by :class:`rce.bus.server.BusServer` on ``hello``), ``RCE_CONTAINER`` (cTag),
  ``RCE_NODE_NAME``, ``RCE_NAMESPACE``;
- the host's values of :data:`PASSED_THROUGH` when set (package search paths, log format);
- ``RCE_STATE_IN=1`` for the nodes of a move's new copy: they hold their inputs until their state
  arrives (:meth:`rce.node.Node.handoff`);
- ``extra``: what a node kind adds on purpose (e.g. ``ROS_*`` for ROS 1 nodes): one
  function builds every node's environment, so every addition is visible here.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import rce

#: ``PATH`` of a node after the interpreter's own ``bin`` directory (Debian's usual system path).
NODE_PATH = "/usr/local/bin:/usr/bin:/bin"
#: ``LANG`` of a node: UTF-8 without depending on the host's locale settings.
NODE_LANG = "C.UTF-8"
#: Host variables a node sees unchanged when the host has them: where packages and their
#: message types are found (rce's and ROS 1's search paths), the engine's log format, and where
#: the ROS 2 wheels' shared libraries are (``LD_LIBRARY_PATH``, with the wheels' mark that it is set:
#: without it, their ``ros_wheels_bootstrapper.pth`` re-executes every Python of the venv to set it,
#: which a sandboxed node may not do).
PASSED_THROUGH = ("RCE_PACKAGE_PATH", "ROS_PACKAGE_PATH", "RCE_LOG_JSON", "RCE_LOG_LEVEL", "LD_LIBRARY_PATH",
                  "_ROS_WHEELS_BOOTSTRAP_COMPLETE")
#: The only names ``$(env X)`` / ``$(optenv X)`` in node args may read (from the node's own
#: environment above; the bus token and everything of the host's are not readable this way).
ENV_DIRECTIVE_ALLOWED = frozenset({
    "HOME", "PATH", "LANG", "RCE_CONTAINER", "RCE_NODE_NAME", "RCE_NAMESPACE", "RCE_PACKAGE_PATH",
    "ROS_PACKAGE_PATH", "ROS_MASTER_URI", "ROS_HOSTNAME", "ROS_IP", "ROS_NAMESPACE", "ROS_DISTRO",
    "ROS_ROOT", "ROS_ETC_DIR", "ROS_LOG_DIR", "ROS_HOME"})
#: The directory that holds the ``rce`` package (the node runtime a node imports).
RUNTIME_ROOT = Path(rce.__file__).resolve().parent.parent


def node_env(*, bus: str, token: str, ctag: str, name: str, namespace: str, home: str | Path,
             extra: dict[str, str] | None = None, host: dict[str, str] | None = None) -> dict[str, str]:
    """The whole environment of one node process (see the module doc for the keys).

    ``bus``: bus socket path; ``token``: the container's bus token; ``ctag``: container tag;
    ``name``/``namespace``: the node's base name and absolute namespace; ``home``: the
    container's own directory; ``extra``: further variables a node kind needs (they win);
    ``host``: where :data:`PASSED_THROUGH` is read (default :data:`os.environ`)."""
    host = os.environ if host is None else host
    env = {k: host[k] for k in PASSED_THROUGH if host.get(k)}
    env.update(PATH=f"{Path(sys.executable).parent}:{NODE_PATH}", HOME=str(home), LANG=NODE_LANG,
               PYTHONUNBUFFERED="1", PYTHONPATH=str(RUNTIME_ROOT), RCE_BUS=str(bus), RCE_BUS_TOKEN=token,
               RCE_CONTAINER=ctag, RCE_NODE_NAME=name, RCE_NAMESPACE=namespace)
    env.update(extra or {})
    return env


def directive_env(env: dict[str, str]) -> dict[str, str]:
    """The part of a node's environment that ``$(env X)`` may read: :data:`ENV_DIRECTIVE_ALLOWED`."""
    return {k: v for k, v in env.items() if k in ENV_DIRECTIVE_ALLOWED}
