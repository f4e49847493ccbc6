"""The node launcher of one container: starts node packages' executables in the container's
sandbox, keeps their output, watches their exits and respawns them on request.

A node spec is the ``add_node`` op (docs/INTERNALS.md): ``{ntag, pkg, exe, args, name,
namespace, respawn}``.

- ``pkg``/``exe`` are found with :func:`rce.node.package_path.find_executable`; a ``.py`` executable
  runs with this interpreter, anything else is executed directly.
- ``args`` is a list of strings, or a string split like a shell (:mod:`shlex`) after the RCE
  alpha / roslaunch directives ``$(find PKG)`` (package directory), ``$(env VAR)`` (must be
  set) and ``$(optenv VAR [default])`` are expanded. ``VAR`` is read from the node's own
  environment and must be one of :data:`rce_container.node_env.ENV_DIRECTIVE_ALLOWED` (never
  a host variable; ``$(optenv)`` of another name gives its default).
- The node's environment is :func:`rce_container.node_env.node_env` (minimal; nothing of the
  host's). ``name`` (default: the nTag) and ``namespace`` reach :mod:`rce.node` as
  ``RCE_NODE_NAME`` and ``RCE_NAMESPACE``; ``RCE_BUS`` is the container's bus socket,
  ``RCE_BUS_TOKEN`` its bus token, ``RCE_CONTAINER`` its cTag.
- ``respawn``: ``true`` or ``{"delay": s, "limit": n}`` (roslaunch's respawn/respawn_delay;
  ``limit`` counts restarts, absent = unlimited).

Statuses are reported through ``on_status(ntag, status, **fields)`` with status ``started``
(``pid``), ``respawning`` (``code``/``signal`` of the exit, ``restarts``) or ``exited``
(``code``/``signal``, ``reason``).

Python nodes (not ROS 1 ones) are forked by the container's warm launcher
(:mod:`rce_container.zygote`, started with :meth:`Launcher.warm_up` when the container is
created) instead of starting a new interpreter each: same sandbox, environment, cwd and argv,
without the ~150-250 ms of interpreter start and imports. When it cannot (not started, failed,
the node's interpreter settings differ, a request too large), the node is exec'd as before.
"""
from __future__ import annotations

import asyncio
import collections
import os
import re
import shlex
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from rce.plumbing.errors import NotFound, RCEError, RequestError
from rce.plumbing.log import get_logger
from rce.interfaces.naming import join, validate_name
from rce.node.package_path import find_executable, find_package
from rce.plumbing.tasks import Tasks
from rce_container.node_env import ENV_DIRECTIVE_ALLOWED, directive_env, node_env
from rce_container.sandbox import Sandbox
from rce_container.zygote_client import ZygoteChild, ZygoteClient, ZygoteTemplate

log = get_logger("rce.container.launcher")

LOG_LINES = 1000            # lines of stdout and of stderr kept per node
DEFAULT_RESPAWN_DELAY = 1.0  # s, when ``respawn`` is just ``true``
PIPE_DRAIN_TIMEOUT = 1.0     # s to read what is left in a dead node's stdout/stderr (a process it left
                             # behind may hold the pipes open: then its output is no longer read)

StatusCallback = Callable[..., None]   # on_status(ntag, status, **fields)

_DIRECTIVE = re.compile(r"\$\((\w+)((?:\s+[^()\s]+)*)\s*\)")


def expand_directives(text: str, env: dict[str, str] | None = None,
                      allowed: frozenset[str] | None = None) -> str:
    """Expand ``$(find PKG)``, ``$(env VAR)`` and ``$(optenv VAR [default])`` in ``text``;
    ``VAR`` is read from ``env`` and, when ``allowed`` is given, must be one of its names
    (``$(optenv VAR default)`` of another name is its default, as for an unset variable).

    Raises :class:`NotFound` for an unknown package, :class:`RequestError` for an unset
    ``$(env VAR)``, a ``VAR`` not in ``allowed``, an unknown directive or a wrong number of
    arguments."""
    env = os.environ if env is None else env

    def sub(match: re.Match) -> str:
        kind, args = match.group(1), match.group(2).split()
        if kind == "optenv" and args and allowed is not None and args[0] not in allowed:
            return " ".join(args[1:])          # a variable it may not read is, to it, not set
        if kind == "env" and len(args) == 1 and allowed is not None and args[0] not in allowed:
            raise RequestError(f"{match.group(0)}: node args may not read {args[0]!r}; $(env X) and $(optenv X) "
                               f"read only the node's own variables {', '.join(sorted(allowed))}")
        if kind == "find" and len(args) == 1:
            return str(find_package(args[0], env))
        if kind == "env" and len(args) == 1:
            if args[0] not in env:
                raise RequestError(f"$(env {args[0]}): environment variable {args[0]!r} is not set")
            return env[args[0]]
        if kind == "optenv" and len(args) >= 1:
            return env.get(args[0], " ".join(args[1:]))
        raise RequestError(f"unsupported substitution {match.group(0)!r}: expected $(find PKG), "
                           "$(env VAR) or $(optenv VAR [default])")
    return _DIRECTIVE.sub(sub, text)


def build_args(args: str | list | None, env: dict[str, str] | None = None,
               allowed: frozenset[str] | None = None) -> list[str]:
    """Node arguments as a list: a string is split like a shell, directives expanded in each
    word (so an expanded path with spaces stays one argument; a word that is only a directive
    expanding to nothing is dropped, as roslaunch does); a list is taken item by item.
    ``env``/``allowed``: as in :func:`expand_directives`.

    Raises :class:`RequestError` for unbalanced quotes or a non-string item."""
    if args is None or args == "":
        return []
    if isinstance(args, list):
        if not all(isinstance(a, (str, int, float)) for a in args):
            raise RequestError(f"node args must be a string or a list of strings, got {args!r}")
        return [expand_directives(str(a), env, allowed) for a in args]
    if not isinstance(args, str):
        raise RequestError(f"node args must be a string or a list of strings, got {args!r}")
    # Protect directives (which contain spaces) from the shell split, then expand per word.
    found: list[str] = []

    def hide(match: re.Match) -> str:
        found.append(match.group(0))
        return f"\x00{len(found) - 1}\x00"
    hidden = _DIRECTIVE.sub(hide, args)
    try:
        words = shlex.split(hidden)
    except ValueError as e:
        raise RequestError(f"cannot split node args {args!r}: {e}") from None
    restore = re.compile("\x00(\\d+)\x00")
    out = []
    for w in words:
        value = expand_directives(restore.sub(lambda match: found[int(match.group(1))], w), env, allowed)
        if value or not restore.fullmatch(w):    # a lone directive that expands to "" is no argument
            out.append(value)
    return out


def parse_respawn(spec: Any) -> tuple[bool, float, int | None]:
    """``respawn`` of a node spec -> ``(enabled, delay s, limit or None)``.

    Raises :class:`RequestError` for a malformed value."""
    if spec in (None, False):
        return False, 0.0, None
    if spec is True:
        return True, DEFAULT_RESPAWN_DELAY, None
    if isinstance(spec, dict):
        unknown = set(spec) - {"delay", "limit"}
        delay, limit = spec.get("delay", DEFAULT_RESPAWN_DELAY), spec.get("limit")
        if unknown or isinstance(delay, bool) or not isinstance(delay, (int, float)) or delay < 0 or \
                (limit is not None and (isinstance(limit, bool) or not isinstance(limit, int) or limit < 0)):
            raise RequestError(f"respawn must be true or {{\"delay\": seconds >= 0, \"limit\": int >= 0}}, "
                               f"got {spec!r}")
        return True, float(delay), limit
    raise RequestError(f"respawn must be true, false or an object, got {spec!r}")


def _python_shebang(path: Path) -> bool:
    """True for a script whose first line is a Python shebang (``#!/usr/bin/env python3``):
    like a ``.py`` file it runs with this interpreter, so it sees the packages installed with
    rce (rosrun-style executables without a suffix)."""
    try:
        with open(path, "rb") as f:
            first = f.readline(200)
    except OSError:
        return False
    return first.startswith(b"#!") and b"python" in first


@dataclass(eq=False)
class NodeProcess:
    """One launched node: its spec, current process, output tails and counters."""
    ntag: str
    argv: list[str]
    env: dict[str, str]
    forkable: bool                       # a Python node the zygote may fork (not a ROS 1 or other program)
    respawn: bool
    delay: float
    limit: int | None
    proc: asyncio.subprocess.Process | ZygoteChild | None = None
    restarts: int = 0
    stopping: bool = False
    stdout: collections.deque = field(default_factory=lambda: collections.deque(maxlen=LOG_LINES))
    stderr: collections.deque = field(default_factory=lambda: collections.deque(maxlen=LOG_LINES))
    task: asyncio.Task | None = None
    stop_event: asyncio.Event = field(default_factory=asyncio.Event)
    spec: dict = field(default_factory=dict)
    started: float = 0.0                 # monotonic s, the current process's start
    last_exit: dict | None = None        # {code|signal, reason?} of the last exit

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc and self.proc.returncode is None else None

    @property
    def full_name(self) -> str:
        """The node's name on the bus (``RCE_NAMESPACE`` joined with ``RCE_NODE_NAME``)."""
        return join(self.env.get("RCE_NAMESPACE", "/"), self.env.get("RCE_NODE_NAME", self.ntag))

    def info(self) -> dict:
        """``{ntag, name, pid, running, restarts, last_exit, argv}`` for status and ``describe``."""
        return {"ntag": self.ntag, "name": self.full_name, "pid": self.pid, "running": self.pid is not None,
                "restarts": self.restarts, "last_exit": self.last_exit, "argv": self.argv}


class Launcher:
    """Starts, watches and stops the nodes of one container.

    ``sandbox``: where processes run; ``bus_path``: the container's bus socket; ``ctag``: the
    container tag (``RCE_CONTAINER``); ``on_status(ntag, status, **fields)``: status reports;
    ``bus_token``: the container's bus token (``RCE_BUS_TOKEN``); ``zygote``: fork Python nodes
    from a warm launcher in the sandbox (False: exec every node); ``template``: the environment's
    warm template the zygote is forked from (None: the zygote is spawned like a node)."""

    def __init__(self, sandbox: Sandbox, bus_path: str, ctag: str, on_status: StatusCallback, bus_token: str = "",
                 zygote: bool = True, template: ZygoteTemplate | None = None):
        self.sandbox, self.bus_path, self.ctag, self.bus_token = sandbox, bus_path, ctag, bus_token
        self.on_status = on_status
        self.nodes: dict[str, NodeProcess] = {}
        self.extra_env: dict[str, str] = {}     # every node of the container gets these (after its kind's)
        self.starts = 0   # processes started, respawns included
        self.forks = 0    # of which forked by the zygote
        self.tasks = Tasks(f"launcher of {ctag}")
        self.use_zygote, self.template = zygote, template
        self.zygote: ZygoteClient | None = None
        self._zygote_start: asyncio.Task | None = None

    def warm_up(self) -> None:
        """Start the zygote in the background (once the sandbox is set up), so the first
        nodes find it ready."""
        if self.use_zygote and self._zygote_start is None:
            self._zygote_start = self.tasks.spawn(self._start_zygote(), name=f"zygote of {self.ctag}")

    async def _start_zygote(self) -> None:
        env = node_env(bus=self.bus_path, token=self.bus_token, ctag=self.ctag, name="zygote", namespace="/",
                       home=self.sandbox.workdir)
        self.zygote = ZygoteClient(self.sandbox, env, self.ctag)
        try:
            await self.zygote.start(self.template)
        except (OSError, RuntimeError) as e:
            log.warning("no zygote: nodes are exec'd", container=self.ctag, reason=str(e),
                        output=list(self.zygote.output)[-5:])
            zygote, self.zygote = self.zygote, None
            await zygote.close()

    async def _fork(self, node: NodeProcess) -> ZygoteChild | None:
        """``node`` forked by the zygote, or None (then it is exec'd)."""
        if not (node.forkable and self.use_zygote):
            return None
        self.warm_up()
        await asyncio.shield(self._zygote_start)
        if self.zygote is None or not self.zygote.fits(node.env):
            return None
        return await self.zygote.spawn(node.argv, node.env, str(self.sandbox.workdir))

    async def _kill(self, proc: asyncio.subprocess.Process | ZygoteChild) -> None:
        if isinstance(proc, ZygoteChild):
            await self.zygote.kill(proc, self.sandbox.grace)
        else:
            await self.sandbox.kill(proc)

    def _prepare(self, spec: dict, kind: dict | None = None) -> NodeProcess:
        ntag = spec.get("ntag")
        if not isinstance(ntag, str) or not ntag:
            raise RequestError("add_node needs a non-empty 'ntag'")
        pkg, exe = spec.get("pkg"), spec.get("exe")
        try:
            path = find_executable(pkg, exe)
        except RCEError as e:
            raise NotFound(f"node {ntag!r}: cannot find executable {exe!r} of package {pkg!r}: {e.message}") from None
        name = spec.get("name") or ntag
        namespace = spec.get("namespace") or "/"
        validate_name(name, "node name")
        validate_name(namespace, "node namespace")
        if name.startswith(("/", "~")) or "/" in name.strip("/"):
            raise RequestError(f"node name {name!r} must be a base name (use 'namespace' to place it)")
        enabled, delay, limit = parse_respawn(spec.get("respawn"))
        env = node_env(bus=self.bus_path, token=self.bus_token, ctag=self.ctag, name=name,
                       namespace=join("/", namespace), home=self.sandbox.workdir,
                       extra={**((kind or {}).get("env") or {}), **self.extra_env})
        args = build_args(spec.get("args"), directive_env(env), ENV_DIRECTIVE_ALLOWED) + (kind or {}).get("args", [])
        python = path.suffix == ".py" or _python_shebang(path)
        argv = ([sys.executable, str(path)] if python else [str(path)]) + args
        if not python and not os.access(path, os.X_OK):
            raise RequestError(f"node {ntag!r}: {path} is not executable (and not a .py script)")
        return NodeProcess(ntag, argv, env, python and kind is None, enabled, delay, limit, spec=dict(spec))

    async def add(self, spec: dict, kind: dict | None = None) -> dict:
        """Launch the node of ``spec``; returns ``{ntag, pid}`` once the process is started.
        ``kind``: ``{env: {...}, args: [...]}`` a node kind adds to the node's environment and
        arguments (ROS 1 nodes: :meth:`rce_container.ros1_graph.Ros1Graph.prepare`).

        Idempotent for a repeated identical spec. Raises :class:`NotFound` naming ``pkg`` and
        ``exe`` when the executable is unknown, :class:`RequestError` for a duplicate nTag with
        another spec or a malformed spec, :class:`RCEError` if the process cannot start."""
        ntag = spec.get("ntag")
        old = self.nodes.get(ntag)
        if old is not None:
            if {k: v for k, v in old.spec.items() if k != "cid"} == {k: v for k, v in spec.items() if k != "cid"}:
                return {"ntag": ntag, "pid": old.pid}
            raise RequestError(f"node {ntag!r} already exists in container {self.ctag!r}")
        node = self._prepare(spec, kind)
        self.nodes[ntag] = node
        try:
            await self._start(node)
        except BaseException:
            self.nodes.pop(ntag, None)
            raise
        node.task = self.tasks.spawn(self._watch(node), name=f"node {ntag}")
        return {"ntag": ntag, "pid": node.pid}

    async def _start(self, node: NodeProcess) -> None:
        try:
            node.proc = await self._fork(node) or await self.sandbox.spawn(node.argv, node.env)
        except OSError as e:
            raise RCEError(f"node {node.ntag!r}: cannot start {node.argv[0]}: {e.strerror or e}") from None
        self.starts += 1
        self.forks += isinstance(node.proc, ZygoteChild)
        node.started = time.monotonic()
        log.info("node started", container=self.ctag, ntag=node.ntag, pid=node.proc.pid)
        self.on_status(node.ntag, "started", pid=node.proc.pid)

    async def _watch(self, node: NodeProcess) -> None:
        while True:
            proc = node.proc
            readers = [self.tasks.spawn(_pump(proc.stdout, node.stdout), name=f"stdout of {node.ntag}"),
                       self.tasks.spawn(_pump(proc.stderr, node.stderr), name=f"stderr of {node.ntag}")]
            code = await proc.wait()
            await self._kill(proc)    # the node's own children go with it
            _, hung = await asyncio.wait(readers, timeout=PIPE_DRAIN_TIMEOUT)   # pipes inherited by escaped processes
            for t in hung:
                t.cancel()
            if isinstance(proc, ZygoteChild):
                proc.close_pipes()
            if node.stopping:
                return
            fields: dict[str, Any] = {"signal": -code} if code < 0 else {"code": code}
            why = self.sandbox.exit_reason(proc, code) or getattr(proc, "error", None)   # OOM killer, uncaught
            if why:
                fields["reason"] = why
            node.last_exit = dict(fields)
            if not node.respawn or (node.limit is not None and node.restarts >= node.limit):
                if node.respawn:
                    fields["reason"] = f"{why}; respawn limit reached" if why else "respawn limit reached"
                log.info("node exited", container=self.ctag, ntag=node.ntag, **fields)
                self.on_status(node.ntag, "exited", **fields)
                return
            node.restarts += 1
            log.info("node respawning", container=self.ctag, ntag=node.ntag, restarts=node.restarts, **fields)
            self.on_status(node.ntag, "respawning", restarts=node.restarts, **fields)
            try:
                async with asyncio.timeout(node.delay):
                    await node.stop_event.wait()
                return                       # removed while waiting to respawn
            except TimeoutError:
                pass
            try:
                await self._start(node)
            except RCEError as e:
                self.on_status(node.ntag, "exited", reason=e.message, **fields)
                return
            if node.stopping:                # removed while starting
                await self._kill(node.proc)
                return

    async def remove(self, ntag: str, reason: str | None = "removed") -> None:
        """Stop node ``ntag`` (and its children); reports ``exited`` with ``reason`` unless None.

        Raises :class:`NotFound` for an unknown nTag."""
        node = self.nodes.pop(ntag, None)
        if node is None:
            raise NotFound(f"node {ntag!r} does not exist in container {self.ctag!r}")
        node.stopping = True
        node.stop_event.set()
        was_running = node.pid is not None
        if node.proc is not None:
            await self._kill(node.proc)
        if node.task:
            await node.task
        if reason is not None and was_running:
            code = node.proc.returncode
            self.on_status(ntag, "exited", reason=reason, **({"signal": -code} if code < 0 else {"code": code}))

    async def close(self) -> None:
        """Stop every node without status reports (the container is going away)."""
        await asyncio.gather(*(self.remove(t, None) for t in list(self.nodes)), return_exceptions=True)
        if self._zygote_start is not None:
            self._zygote_start.cancel()
            await asyncio.gather(self._zygote_start, return_exceptions=True)
        if self.zygote is not None:
            await self.zygote.close()
        await self.sandbox.kill_all()
        await self.tasks.cancel_all()

    def logs(self, ntag: str, lines: int = LOG_LINES) -> dict:
        """The last ``lines`` lines of stdout and stderr of node ``ntag``: ``{stdout: [...], stderr: [...]}``.

        Raises :class:`NotFound` for an unknown nTag."""
        node = self.nodes.get(ntag)
        if node is None:
            raise NotFound(f"node {ntag!r} does not exist in container {self.ctag!r}")
        lines = max(0, int(lines))
        return {"stdout": list(node.stdout)[-lines:] if lines else [],
                "stderr": list(node.stderr)[-lines:] if lines else []}


async def _pump(stream: asyncio.StreamReader | None, sink: collections.deque) -> None:
    """Copy lines of ``stream`` into the bounded ``sink`` until EOF."""
    if stream is None:
        return
    while True:
        try:
            line = await stream.readline()
        except ValueError:               # a line longer than the stream limit (64 KiB) was discarded
            sink.append("<line longer than 64 KiB dropped>")
            continue
        if not line:
            return
        sink.append(line.decode(errors="replace").rstrip("\n"))
