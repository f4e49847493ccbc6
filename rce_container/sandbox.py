"""The isolation seam: how a container's node processes are started, measured and torn down.

A :class:`Sandbox` is created per container by its environment and owns every process it
spawns for that container. Two kinds exist; :func:`select` (``--sandbox auto``) takes the
strongest one the host can run:

- :class:`NamespaceSandbox` (``namespaced``, needs root and util-linux ``unshare``,
  ``nsenter``, ``setsid``, ``setpriv``): the container gets an init process in new PID,
  mount, IPC, UTS and network namespaces and its own cgroup with the requested limits
  (:mod:`rce_container.cgroups`); every node is entered into those namespaces and that
  cgroup. A node runs as the container's own unprivileged uid (:mod:`rce_container.node_uid`)
  with no capabilities at all (empty bounding, permitted, effective, inheritable and ambient
  sets, ``no_new_privs``), so it cannot undo any of this. It sees only its container's
  processes, only ``lo`` (no route to the host or anything else), a private ``/tmp`` and
  ``/dev/shm``, of the task set's runtime directories only its own container's workdir and
  bus socket, and a read-only rest of the filesystem (:mod:`rce_container.mounts`): its
  workdir is the only host directory it can write.
- :class:`ProcessGroupSandbox` (``unconfined``): each node in its own session/process group;
  teardown signals the whole group. It isolates nothing and enforces no limit.

Both stop a node with SIGTERM to its process group, then SIGKILL after ``grace`` seconds,
so the children a node forks die with it.

A new kind is one subclass with its own ``kind``, ``priority`` and :meth:`Sandbox.available`;
the registry below picks it up.
"""
from __future__ import annotations

import asyncio
import functools
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from operator import attrgetter
from pathlib import Path
from typing import ClassVar

from rce.plumbing.errors import ConfigError, RCEError
from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks
from rce_container import cgroups, mounts, node_uid, usage

log = get_logger("rce.container.sandbox")

DEFAULT_GRACE = 3.0          # s between SIGTERM and SIGKILL when a node is stopped (its chance to clean up)

#: kind -> sandbox class; filled by :meth:`Sandbox.__init_subclass__`.
REGISTRY: dict[str, type["Sandbox"]] = {}


def host_scope(name: str, pid: int | None = None) -> str:
    """The per-task-set scope of sandbox resources (cgroup directory ``rce/<name>-<pid>``)."""
    safe = re.sub(r"[^A-Za-z0-9_.-]", "_", name)[:64] or "host"
    return f"rce/{safe}-{pid or os.getpid()}"


class Sandbox:
    """Base class: spawns and kills the node processes of one container.

    ``cid``/``ctag``: the container; ``limits``: ``{cpu, memory, pids, size, bandwidth}`` as the
    master sent them (cpu in cores, memory in MiB, pids in tasks; size, the original RCE's
    container size class, and bandwidth in bytes/s are recorded only; any may be absent, 0 means
    no limit); ``workdir``: the container's private directory (node cwd);
    ``bus_socket``: the container's bus socket path; ``scope``: the task set's
    :func:`host_scope`; ``grace``: seconds between SIGTERM and SIGKILL on teardown.

    Subclasses set ``kind`` (the name reported in status and accepted by ``--sandbox``) and
    ``priority`` (higher wins in :func:`select`), and implement :meth:`spawn` and :meth:`kill`.
    """

    kind: ClassVar[str] = ""
    priority: ClassVar[int] = 0

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        if cls.kind:
            REGISTRY[cls.kind] = cls

    def __init__(self, cid: int, ctag: str, limits: dict | None, workdir: Path, *, grace: float = DEFAULT_GRACE,
                 bus_socket: str | Path | None = None, scope: str | None = None):
        self.cid, self.ctag = cid, ctag
        self.limits = {k: v for k, v in (limits or {}).items() if v is not None}
        self.workdir = Path(workdir)
        self.bus_socket = Path(bus_socket) if bus_socket else self.workdir / "bus.sock"
        self.scope = scope or host_scope("host")
        self.grace = grace
        self.procs: set[asyncio.subprocess.Process] = set()
        self.started = time.monotonic()
        self.node_uid: int | None = None     # the uid the nodes run as, when the sandbox sets one

    @classmethod
    def available(cls) -> bool:
        """True if this kind of sandbox can work on this host (e.g. needs root)."""
        return True

    # -- host-wide hooks (called by the container task set) ------------------------------------
    @classmethod
    def prepare_host(cls, scope: str) -> str:
        """Called once by the task set before its first environment starts; returns a line
        describing what the sandbox will use (logged)."""
        return cls.kind

    @classmethod
    def cleanup_container(cls, scope: str, cid: int) -> None:
        """Remove what container ``cid`` may have left behind when its environment could not
        clean up (crashed): processes and kernel objects. Default: nothing."""

    @classmethod
    def cleanup_host(cls, scope: str) -> None:
        """Remove everything left under ``scope`` (task set shutdown). Default: nothing."""

    @property
    def status(self) -> str:
        """What isolation the container really has (reported in ``create_container``)."""
        return self.kind

    async def setup(self) -> None:
        """Prepare the sandbox before the first spawn (cgroups, namespaces...). Default: nothing."""

    async def resize(self, limits: dict) -> dict:
        """Apply new limits (keys as in the constructor; absent keys keep their value); returns
        the limits now recorded. The base class only records them."""
        cgroups.limits_of(limits)          # same validation everywhere
        for k, v in limits.items():
            if v is None:
                continue
            if v == 0:
                self.limits.pop(k, None)
            else:
                self.limits[k] = v
        return dict(self.limits)

    async def spawn(self, argv: list[str], env: dict[str, str], cwd: str | Path | None = None,
                    pass_fds: tuple[int, ...] = ()) -> asyncio.subprocess.Process:
        """Start ``argv`` with environment ``env`` in ``cwd`` (default: the workdir), stdout and
        stderr piped; ``pass_fds``: descriptors it inherits (e.g. the zygote's control socket).
        Raises :class:`OSError` if it cannot be started."""
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

    def enter_spec(self) -> dict:
        """How a running process joins this sandbox in-process (:mod:`rce_container.sandbox_enter`,
        for the container's zygote): ``{cwd, init_pid?, uid?, procs_files?}``. Here: its own
        session in the workdir."""
        return {"cwd": str(self.workdir)}

    # -- observation ---------------------------------------------------------------------------
    def node_pids(self, proc: asyncio.subprocess.Process) -> list[int]:
        """Host pids of the processes of the node started as ``proc`` (it and its descendants)."""
        if proc is None or proc.returncode is not None:
            return []
        return usage.tree(proc.pid)

    def usage(self) -> dict:
        """Container-wide use the sandbox can account for itself: ``{pids?, cpu_seconds?,
        memory?}``; empty when only the nodes' process trees are known (the caller sums them)."""
        return {}

    def exit_reason(self, proc: asyncio.subprocess.Process, code: int) -> str | None:
        """Why the node's process ended with ``code`` when the sandbox knows better than the
        code (e.g. the kernel's OOM killer); None otherwise."""
        return None

    def info(self) -> dict:
        """Sandbox details for status: ``{kind, limits, ...}``."""
        return {"kind": self.status, "limits": dict(self.limits)}


class ProcessGroupSandbox(Sandbox):
    """Each node in its own session and process group (``start_new_session=True``); no
    namespaces, no resource limits. Teardown: SIGTERM to the group, SIGKILL after ``grace`` s."""

    kind = "unconfined"
    priority = 0

    async def spawn(self, argv, env, cwd=None, pass_fds=()):
        proc = await asyncio.create_subprocess_exec(
            *argv, env=env, cwd=str(cwd or self.workdir), stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, start_new_session=True, pass_fds=pass_fds)
        self.procs.add(proc)
        return proc

    async def kill(self, proc):
        try:
            if proc.returncode is None:
                _signal_group(proc.pid, signal.SIGTERM)
                try:
                    async with asyncio.timeout(self.grace):
                        await proc.wait()
                except TimeoutError:
                    log.warning("node ignored SIGTERM, killing", cid=self.cid, pid=proc.pid)
            # SIGKILL the group even when the leader is gone: its children may still be there.
            _signal_group(proc.pid, signal.SIGKILL)
            await proc.wait()
        finally:
            self.procs.discard(proc)


#: setpriv(1) options that make a node an unprivileged process: no capability in any set
#: (``--reuid``/``--regid`` to a non-root uid clear the permitted and effective sets), no
#: supplementary groups, and no way back through a setuid binary (``no_new_privs``).
DROP_PRIVILEGES = ("--clear-groups", "--inh-caps=-all", "--ambient-caps=-all", "--bounding-set=-all",
                   "--no-new-privs")
WORKDIR_MODE = 0o700         # a container's own directory: its node uid only
NSINIT = Path(__file__).with_name("nsinit.py")
TOOLS = ("unshare", "nsenter", "setsid", "setpriv")
#: sh prologue: write our pid into each cgroup.procs file given before "--", then exec the rest.
JOIN_CGROUPS = 'while [ "$1" != -- ]; do echo $$ > "$1" || exit 126; shift; done; shift; exec "$@"'
INIT_TIMEOUT = 15.0          # s for a container's init to report ready
INIT_ERROR_TIMEOUT = 1.0     # s to read the reason a failed init wrote on stderr
INIT_EXIT_TIMEOUT = 2.0      # s for the init to exit once its stdin is closed, before it is killed
PROBE_TIMEOUT = 10.0         # s for the one-off ``unshare`` probe of :meth:`NamespaceSandbox.available`
STALE_CGROUP_TIMEOUT = 1.0   # s to empty and remove the cgroups of a task set that is gone
LEADER_TIMEOUT = 5.0         # s to find a node's program under its nsenter (it forks at once)
LEADER_POLL = 0.002          # s between looks for it
_layouts: dict[str, cgroups.Layout | None] = {}


def _layout(scope: str) -> cgroups.Layout | None:
    if scope not in _layouts:
        _layouts[scope] = cgroups.host_layout(scope)
    return _layouts[scope]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
        return True
    except ProcessLookupError:
        return False
    except PermissionError:
        return True


def _children(pid: int) -> list[int]:
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as f:
            return [int(x) for x in f.read().split()]
    except (OSError, ValueError):
        return []


class NamespaceSandbox(Sandbox):
    """Namespaces and a cgroup per container (see the module doc).

    ``setup`` creates the cgroup(s), writes the limits and starts the container's init with
    ``unshare --pid --fork --mount --ipc --uts --net --mount-proc --kill-child`` (the init is
    :mod:`rce_container.nsinit`, itself in the cgroup). A node runs as
    ``sh`` (joins the cgroup) -> ``nsenter -t INIT -p -m -i -u -n`` (enters the namespaces,
    forks and waits, passing the exit status on) -> ``setsid`` (the node leads its own process
    group) -> ``setpriv --bounding-set`` (drops capabilities) -> ``env --chdir`` (the workdir, as
    the container sees it) -> the node's program. The
    process the launcher watches is the ``nsenter``; signals go to the node's process group.
    Python nodes are usually forked by the container's zygote instead, which enters the same
    way in-process (:meth:`enter_spec`, :mod:`rce_container.sandbox_enter`).
    When the init exits (teardown, or its environment dies: its stdin closes) the kernel kills
    every process left in the PID namespace; the cgroup is then emptied and removed.
    """

    kind = "namespaced"
    priority = 10
    _available: ClassVar[bool | None] = None

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        layout = _layout(self.scope)
        self.cg = cgroups.CgroupSet(layout, f"c{self.cid}") if layout else None
        self.init: asyncio.subprocess.Process | None = None
        self.init_pid: int | None = None
        self.ns: dict[str, str] = {}
        self._leaders: dict[asyncio.subprocess.Process, int] = {}
        self._tasks = Tasks(f"sandbox of {self.ctag}")
        self._ooms = 0
        self._uid: node_uid.NodeUid | None = None

    @classmethod
    def available(cls) -> bool:
        """Root, the util-linux tools, and a kernel that lets us create the namespaces."""
        if cls._available is None:
            ok = os.geteuid() == 0 and all(shutil.which(t) for t in TOOLS)
            if ok:
                try:
                    ok = subprocess.run(["unshare", "--pid", "--fork", "--mount", "--ipc", "--uts", "--net",
                                         "--mount-proc", "true"], capture_output=True,
                                        timeout=PROBE_TIMEOUT).returncode == 0
                except (OSError, subprocess.TimeoutExpired):
                    ok = False
            cls._available = ok
        return cls._available

    @classmethod
    def prepare_host(cls, scope: str) -> str:
        """Describe the cgroup layout, and remove the scopes of task sets that died without
        cleaning up (``rce/<name>-<pid>`` whose pid no longer runs and that hold no process)."""
        layout = _layout(scope)
        if layout is not None:
            for base in dict.fromkeys(layout.bases.values()):
                parent = Path(base).parent
                for d in (parent.iterdir() if parent.is_dir() else ()):
                    m = re.fullmatch(r".+-(\d+)", d.name)
                    if d.is_dir() and m and str(d) != base and not _alive(int(m.group(1))):
                        if cgroups.tree_pids([d]):     # never kill anything here: it may not be ours
                            log.warning("cgroups of a gone task set still hold processes; left alone", dir=str(d))
                            continue
                        log.info("removing the cgroups of a task set that is gone", dir=str(d))
                        cgroups.remove_tree([d], timeout=STALE_CGROUP_TIMEOUT)
        if layout is None:
            log.warning("no usable cgroup hierarchy: containers get namespaces but no resource limits")
            return "namespaces, no cgroup"
        return "namespaces, " + layout.describe()

    @classmethod
    def cleanup_container(cls, scope: str, cid: int) -> None:
        layout = _layout(scope)
        if layout:
            left = cgroups.CgroupSet(layout, f"c{cid}").remove()
            if left:
                log.warning("cgroup directories left behind", dirs=[str(d) for d in left])

    @classmethod
    def cleanup_host(cls, scope: str) -> None:
        layout = _layout(scope)
        if layout is None:
            return
        bases = [Path(b) for b in dict.fromkeys(layout.bases.values())]
        left = cgroups.remove_tree(bases)
        if left:
            log.warning("cgroup directories left behind", dirs=[str(d) for d in left])
        for b in bases:          # the shared "rce" parent, if no other task set uses it
            try:
                b.parent.rmdir()
            except OSError:
                pass

    @property
    def status(self) -> str:
        return self.kind if self.cg else f"{self.kind} (no cgroup: limits not enforced)"

    # -- setup ---------------------------------------------------------------------------------
    def _joined(self, argv: list[str]) -> list[str]:
        if self.cg is None:
            return argv
        return ["/bin/sh", "-c", JOIN_CGROUPS, "sh", *self.cg.procs_files, "--", *argv]

    def _own_dirs(self) -> None:
        """Lease the container's node uid and give it the workdir and bus socket directory."""
        self._uid = node_uid.lease(self.cid)
        self.node_uid = self._uid.uid
        for d in dict.fromkeys((self.workdir, self.bus_socket.parent)):
            os.chown(d, self.node_uid, self.node_uid)
            os.chmod(d, WORKDIR_MODE)

    async def setup(self) -> None:
        """Lease the node uid, create and limit the cgroup, start the init in its new namespaces.

        Raises :class:`RCEError` naming what failed (a refused limit, an init that did not start)."""
        try:
            self._own_dirs()
        except BaseException:
            self._release_uid()
            raise
        if self.cg is not None:
            await asyncio.to_thread(self.cg.create)
            try:
                in_force = self.cg.apply({k: self.limits.get(k) for k in cgroups.LIMITS})
            except RCEError:
                await asyncio.to_thread(self.cg.remove)
                self._release_uid()
                raise
            self._ooms = self.cg.oom_kills()
            log.debug("cgroup ready", cid=self.cid, limits=in_force, dirs=[str(d) for d in self.cg.unique_dirs])
        hostname = re.sub(r"[^A-Za-z0-9-]", "-", self.ctag)[:63].strip("-") or f"c{self.cid}"
        spec = json.dumps({"hostname": hostname, **mounts.plan(self.workdir, self.bus_socket.parent, _readable())})
        argv = ["unshare", "--pid", "--fork", "--mount", "--ipc", "--uts", "--net", "--mount-proc",
                "--kill-child", sys.executable, "-I", "-S", str(NSINIT), spec]
        try:
            self.init = await asyncio.create_subprocess_exec(
                *self._joined(argv), stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
                stderr=asyncio.subprocess.PIPE, start_new_session=True, cwd="/")
            try:
                async with asyncio.timeout(INIT_TIMEOUT):
                    line = await self.init.stdout.readline()
            except TimeoutError:
                line = b"error: no answer within %d s" % INIT_TIMEOUT
            if line.strip() != b"ready":
                err = b""
                if self.init.returncode is not None or line.startswith(b"error"):
                    try:
                        async with asyncio.timeout(INIT_ERROR_TIMEOUT):
                            err = await self.init.stderr.read(4096)
                    except TimeoutError:
                        pass
                why = (line.decode(errors="replace").strip() or "init exited") + \
                      (f" ({err.decode(errors='replace').strip()})" if err.strip() else "")
                raise RCEError(f"container {self.ctag!r}: cannot start its namespaces: {why}")
            kids = _children(self.init.pid)
            if not kids:
                raise RCEError(f"container {self.ctag!r}: its init is gone")
            self.init_pid = kids[0]
            self.ns = {n: os.readlink(f"/proc/{self.init_pid}/ns/{n}") for n in ("pid", "mnt", "ipc", "uts", "net")}
        except BaseException:
            await self._stop_init()
            if self.cg is not None:
                await asyncio.to_thread(self.cg.remove)
            self._release_uid()
            raise
        log.debug("container namespaces ready", cid=self.cid, init=self.init_pid, uid=self.node_uid)

    def _release_uid(self) -> None:
        if self._uid is not None:
            self._uid.release()
            self._uid = None

    # -- nodes ---------------------------------------------------------------------------------
    async def spawn(self, argv, env, cwd=None, pass_fds=()):
        if self.init_pid is None:
            raise OSError(f"the namespaces of container {self.ctag!r} are not set up")
        # the working directory is entered last, in the container's mount namespace (nsenter's
        # --wd would open it in the host's, where ".." leads out of the container's view)
        inner = ["nsenter", "-t", str(self.init_pid), "-p", "-m", "-i", "-u", "-n",
                 "--", "setsid", "setpriv", f"--reuid={self.node_uid}", f"--regid={self.node_uid}",
                 *DROP_PRIVILEGES, "--", "env", f"--chdir={cwd or self.workdir}", "--", *argv]
        proc = await asyncio.create_subprocess_exec(
            *self._joined(inner), env=env, cwd="/", stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE, start_new_session=True, pass_fds=pass_fds)
        self.procs.add(proc)
        self._tasks.spawn(self._find_leader(proc), name=f"leader of {proc.pid}")
        return proc

    async def _find_leader(self, proc: asyncio.subprocess.Process) -> int | None:
        """The host pid of the node's program (nsenter's child, its own process group leader);
        remembered so its group can be signalled after nsenter is gone."""
        if proc in self._leaders:
            return self._leaders[proc]
        deadline = time.monotonic() + LEADER_TIMEOUT
        while proc.returncode is None and time.monotonic() < deadline:
            kids = _children(proc.pid)
            if kids:
                self._leaders[proc] = kids[0]
                return kids[0]
            await asyncio.sleep(LEADER_POLL)
        return self._leaders.get(proc)

    async def kill(self, proc):
        try:
            leader = self._leaders.get(proc)
            if leader is None and proc.returncode is None:
                kids = _children(proc.pid)
                leader = self._leaders[proc] = kids[0] if kids else None
            if proc.returncode is None:
                # TERM the node's own group: nsenter waits for it and passes its exit status on
                _signal_group(leader or proc.pid, signal.SIGTERM)
                try:
                    async with asyncio.timeout(self.grace):
                        await proc.wait()
                except TimeoutError:
                    log.warning("node ignored SIGTERM, killing", cid=self.cid, pid=proc.pid)
            if leader:
                _signal_group(leader, signal.SIGKILL)
            _signal_group(proc.pid, signal.SIGKILL)
            await proc.wait()
        finally:
            self.procs.discard(proc)
            self._leaders.pop(proc, None)

    async def _stop_init(self) -> None:
        if self.init is None:
            return
        if self.init.returncode is None:
            try:
                self.init.stdin.close()          # the init exits; the kernel kills its namespace
                async with asyncio.timeout(INIT_EXIT_TIMEOUT):
                    await self.init.wait()
            except (TimeoutError, OSError):
                _signal_group(self.init.pid, signal.SIGKILL)     # unshare --kill-child takes the init along
                await self.init.wait()

    async def close(self) -> None:
        await self.kill_all()
        await self._tasks.cancel_all()
        await self._stop_init()
        if self.cg is not None:
            left = await asyncio.to_thread(self.cg.remove)
            if left:
                log.warning("cgroup directories left behind", cid=self.cid, dirs=[str(d) for d in left])
        self._release_uid()        # every process of the container is gone: the uid is free again

    async def resize(self, limits: dict) -> dict:
        """Write the new limits into the cgroup (running nodes keep running). Raises
        :class:`RCEError` when the kernel refuses one (e.g. memory below what is in use)."""
        if self.cg is not None:
            await asyncio.to_thread(self.cg.apply, {k: v for k, v in limits.items()
                                                    if k in cgroups.LIMITS and v is not None})
        return await super().resize(limits)

    def enter_spec(self) -> dict:
        """The cgroup, the init's namespaces and the node uid: what ``spawn``'s sh/nsenter/setsid/
        setpriv chain applies. Raises :class:`OSError` before :meth:`setup`."""
        if self.init_pid is None:
            raise OSError(f"the namespaces of container {self.ctag!r} are not set up")
        return {"cwd": str(self.workdir), "init_pid": self.init_pid, "uid": self.node_uid,
                "procs_files": [str(f) for f in self.cg.procs_files] if self.cg is not None else []}

    # -- observation ---------------------------------------------------------------------------
    def node_pids(self, proc):
        if proc is None or proc.returncode is not None:
            return []
        return usage.tree(proc.pid)

    def usage(self) -> dict:
        if self.cg is None:
            return {}
        return {"pids": self.cg.pids(), "cpu_seconds": self.cg.cpu_seconds(), "memory": self.cg.memory(),
                "cpu": self.cg.throttling()}

    def exit_reason(self, proc, code):
        if self.cg is None or code != -signal.SIGKILL:
            return None
        n = self.cg.oom_kills()
        if n <= self._ooms:
            return None
        self._ooms = n
        mib = self.limits.get("memory")
        return "killed: out of memory" + (f" (limit {mib:g} MiB)" if mib else "")

    def info(self) -> dict:
        out = super().info()
        out.update(init_pid=self.init_pid, namespaces=self.ns, uid=self.node_uid)
        if self.cg is not None:
            out["cgroup"] = {"version": self.cg.layout.version, "dirs": [str(d) for d in self.cg.unique_dirs],
                             "files": self.cg.files()}
        return out


@functools.cache
def _readable() -> list[str]:
    """:func:`mounts.runtime_paths` of this process (computed once: they do not change)."""
    return mounts.runtime_paths()


def _signal_group(pgid: int, sig: int) -> None:
    try:
        os.killpg(pgid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def select(kind: str = "auto", check: bool = True) -> type[Sandbox]:
    """The sandbox class for ``kind``: a registered kind, or ``"auto"`` for the available one
    with the highest priority. Raises :class:`ConfigError` for an unknown or (with ``check``)
    unavailable kind."""
    if kind == "auto":
        usable = [c for c in REGISTRY.values() if c.available()]
        return max(usable, key=attrgetter("priority"))
    cls = REGISTRY.get(kind)
    if cls is None:
        raise ConfigError(f"unknown sandbox {kind!r}: expected auto or one of {', '.join(sorted(REGISTRY))}")
    if check and not cls.available():
        raise ConfigError(f"sandbox {kind!r} is not available on this host"
                          + (" (it needs root)" if os.geteuid() != 0 else ""))
    return cls
