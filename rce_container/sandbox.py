"""The isolation seam: how a container's node processes are started and torn down.

A :class:`Sandbox` is created per container by its environment and owns every
process it spawns for that container. :class:`ProcessGroupSandbox` is the
portable one: each node runs in its own session/process group, and teardown
signals the whole group (SIGTERM, then SIGKILL after a grace period), so
grandchildren a node forks die with it. It isolates nothing else and reports
``status == "unconfined"``.

Stronger sandboxes (PID/mount/IPC/UTS/network namespaces plus a cgroup with the
container's limits, DESIGN section 5) slot in by adding a subclass with its own
``kind``, a higher ``priority`` and an :meth:`Sandbox.available` check: the
registry below picks it up, :func:`select` prefers it where it is available, and
nothing else changes.
"""
from __future__ import annotations

import asyncio
import os
import signal
from pathlib import Path
from typing import ClassVar

from rce.errors import ConfigError
from rce.log import get_logger

log = get_logger("rce.container.sandbox")

#: kind -> sandbox class; filled by :meth:`Sandbox.__init_subclass__`.
REGISTRY: dict[str, type["Sandbox"]] = {}


class Sandbox:
    """Base class: spawns and kills the node processes of one container.

    ``cid``/``ctag``: the container; ``limits``: ``{cpu, memory, size, bandwidth}`` as the
    master sent them (cpu in cores, memory and size in MiB, bandwidth in bytes/s; any may be
    absent); ``workdir``: the container's private directory (node cwd, bus socket);
    ``grace``: seconds between SIGTERM and SIGKILL on teardown.

    Subclasses set ``kind`` (the name reported in status and accepted by ``--sandbox``) and
    ``priority`` (higher wins in :func:`select`), and implement :meth:`spawn` and :meth:`kill`.
    """

    kind: ClassVar[str] = ""
    priority: ClassVar[int] = 0

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        if cls.kind:
            REGISTRY[cls.kind] = cls

    def __init__(self, cid: int, ctag: str, limits: dict | None, workdir: Path, *, grace: float = 3.0):
        self.cid, self.ctag = cid, ctag
        self.limits = {k: v for k, v in (limits or {}).items() if v is not None}
        self.workdir = Path(workdir)
        self.grace = grace
        self.procs: set[asyncio.subprocess.Process] = set()

    @classmethod
    def available(cls) -> bool:
        """True if this kind of sandbox can work on this host (e.g. needs root)."""
        return True

    @property
    def status(self) -> str:
        """What isolation the container really has (reported in ``create_container``)."""
        return self.kind

    async def setup(self) -> None:
        """Prepare the sandbox before the first spawn (cgroups, mounts...). Default: nothing."""

    async def resize(self, limits: dict) -> None:
        """Apply new limits (keys as in the constructor; absent keys keep their value).
        The base class only records them."""
        self.limits.update({k: v for k, v in limits.items() if v is not None})

    async def spawn(self, argv: list[str], env: dict[str, str], cwd: str | Path | None = None
                    ) -> asyncio.subprocess.Process:
        """Start ``argv`` with environment ``env`` in ``cwd`` (default: the workdir), stdout and
        stderr piped. Raises :class:`OSError` if it cannot be started."""
        raise NotImplementedError

    async def kill(self, proc: asyncio.subprocess.Process) -> None:
        """Stop ``proc`` and everything it started; returns once it has been reaped."""
        raise NotImplementedError

    async def kill_all(self) -> None:
        """Stop every process of this container (concurrently); returns when all are reaped."""
        await asyncio.gather(*(self.kill(p) for p in list(self.procs)), return_exceptions=True)

    async def close(self) -> None:
        """Kill everything and release the sandbox's resources."""
        await self.kill_all()


class ProcessGroupSandbox(Sandbox):
    """Each node in its own session and process group (``start_new_session=True``); no
    namespaces, no resource limits. Teardown: SIGTERM to the group, SIGKILL after ``grace`` s."""

    kind = "unconfined"
    priority = 0

    async def spawn(self, argv, env, cwd=None):
        proc = await asyncio.create_subprocess_exec(
            *argv, env=env, cwd=str(cwd or self.workdir), stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, start_new_session=True)
        self.procs.add(proc)
        return proc

    async def kill(self, proc):
        try:
            if proc.returncode is None:
                _signal_group(proc.pid, signal.SIGTERM)
                try:
                    await asyncio.wait_for(proc.wait(), self.grace)
                except asyncio.TimeoutError:
                    log.warning("node ignored SIGTERM, killing", cid=self.cid, pid=proc.pid)
            # SIGKILL the group even when the leader is gone: its children may still be there.
            _signal_group(proc.pid, signal.SIGKILL)
            await proc.wait()
        finally:
            self.procs.discard(proc)


def _signal_group(pgid: int, sig: int) -> None:
    try:
        os.killpg(pgid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def select(kind: str = "auto") -> type[Sandbox]:
    """The sandbox class for ``kind``: a registered kind, or ``"auto"`` for the available one
    with the highest priority. Raises :class:`ConfigError` for an unknown or unavailable kind."""
    if kind == "auto":
        usable = [c for c in REGISTRY.values() if c.available()]
        return max(usable, key=lambda c: c.priority)
    cls = REGISTRY.get(kind)
    if cls is None:
        raise ConfigError(f"unknown sandbox {kind!r}: expected auto or one of {', '.join(sorted(REGISTRY))}")
    if not cls.available():
        raise ConfigError(f"sandbox {kind!r} is not available on this host")
    return cls
