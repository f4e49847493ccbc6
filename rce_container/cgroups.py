"""Control groups for containers: find the host's cgroup hierarchies (v1 or v2), create one
cgroup per container, write its limits, read its usage, kill what is left in it, remove it.

Layout (``scope`` is ``rce/<host name>-<host pid>``, one per container task set):

- **v1** (one hierarchy per controller, e.g. ``/sys/fs/cgroup/memory``): per controller
  ``MOUNT/<own cgroup>/<scope>/c<cid>``, where ``<own cgroup>`` is the container task set's
  own cgroup in that hierarchy (so a host that was itself given a cgroup stays inside it).
  Controllers used: ``memory`` (required), ``cpu``, ``cpuacct`` and ``pids`` when mounted.
- **v2** (one unified hierarchy): ``MOUNT/<scope>/c<cid>`` at the root of the hierarchy (v2
  forbids controllers below a cgroup that holds processes, which the host's own cgroup
  does); ``+cpu +memory +pids`` are enabled on the way down. Needs ``memory`` and ``cpu`` in
  the root's ``cgroup.controllers``.

Limits (what ``containerData`` asks; 0 or absent = no limit):

- ``cpu`` cores (fractional): v1 ``cpu.cfs_quota_us`` = cores x ``cpu.cfs_period_us``
  (100 ms); v2 ``cpu.max`` = ``"QUOTA 100000"``. The cores are also the container's CPU weight
  under contention (as a Kubernetes CPU request): v1 ``cpu.shares`` = cores x 1024, v2
  ``cpu.weight`` = cores x 100, at least one process's weight (1024, 100), which is what a
  container without ``cpu`` weighs. The master already reserves those cores on the host when it
  places the container; the weight lets the container use them when every core is busy.
- ``memory`` MiB: v1 ``memory.limit_in_bytes`` and ``memory.memsw.limit_in_bytes`` (no
  swapping past it); v2 ``memory.max``, ``memory.swap.max 0``.
- ``pids`` tasks (processes and threads): ``pids.max`` (v1 and v2).

``size`` is not a limit: the original RCE's container size class (its client always sends
``size: 1``), recorded and left alone here.

Parsing (:func:`parse_mountinfo`, :func:`parse_proc_cgroup`, :func:`detect`) is pure; the
file I/O is in :class:`CgroupSet`, which takes any root so tests can point it at a fake tree.
"""
from __future__ import annotations

import errno
import os
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path

from rce.plumbing.errors import RCEError, RequestError
from rce.plumbing.log import get_logger

log = get_logger("rce.container.cgroups")

CFS_PERIOD_US = 100_000
KILL_TIMEOUT = 5.0      # s to empty a cgroup tree with SIGKILL (only a process stuck in the kernel takes long)
POLL = 0.01             # s between looks at a cgroup that is emptying
MIN_QUOTA_US = 1_000        # the kernel refuses quotas below 1 ms
V1_CONTROLLERS = ("cpu", "cpuacct", "memory", "pids")
V2_CONTROLLERS = ("cpu", "memory", "pids")


@dataclass(frozen=True)
class Mount:
    """One cgroup mount: ``version`` 1 or 2, ``path`` (mount point), ``root`` (the hierarchy
    path mounted there) and, for v1, its ``controllers``."""
    version: int
    path: str
    root: str
    controllers: frozenset = frozenset()


def parse_mountinfo(text: str) -> list[Mount]:
    """The cgroup mounts listed in a ``/proc/self/mountinfo`` text."""
    out = []
    for line in text.splitlines():
        left, sep, right = line.partition(" - ")
        if not sep:
            continue
        f, r = left.split(), right.split()
        if len(f) < 5 or len(r) < 3:
            continue
        fstype, opts = r[0], r[2].split(",")
        if fstype == "cgroup":
            ctrls = frozenset(o for o in opts if o in V1_CONTROLLERS)
            if ctrls:
                out.append(Mount(1, _unescape(f[4]), f[3], ctrls))
        elif fstype == "cgroup2":
            out.append(Mount(2, _unescape(f[4]), f[3]))
    return out


def _unescape(text: str) -> str:
    return text.replace("\\040", " ").replace("\\011", "\t").replace("\\012", "\n").replace("\\134", "\\")


def parse_proc_cgroup(text: str) -> dict[str, str]:
    """``/proc/self/cgroup`` -> {controller: path} for v1 and {"": path} for v2."""
    out = {}
    for line in text.splitlines():
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, ctrls, path = parts
        if ctrls == "":
            out[""] = path
        for c in ctrls.split(","):
            if c:
                out[c] = path
    return out


@dataclass(frozen=True)
class Layout:
    """Where a container task set's cgroups go: ``version`` and ``bases`` (controller ->
    directory holding the per-container cgroups; for v2 the key is ``""``)."""
    version: int
    bases: dict = field(default_factory=dict)
    v2_root: str = ""           # v2: the mount point (controllers are enabled from here down)

    @property
    def controllers(self) -> set[str]:
        return set(self.bases) if self.version == 1 else set(V2_CONTROLLERS)

    def describe(self) -> str:
        return f"cgroup v{self.version}: " + ", ".join(f"{k or 'unified'}={v}" for k, v in sorted(self.bases.items()))


def detect(scope: str, mountinfo: str, proc_cgroup: str, v2_controllers: str | None = None) -> Layout | None:
    """The :class:`Layout` for ``scope`` on a host with these ``/proc/self/mountinfo`` and
    ``/proc/self/cgroup`` texts, or None when no usable hierarchy exists. v1 wins when its
    memory controller is mounted; else v2 when ``v2_controllers`` (the root's
    ``cgroup.controllers``) lists memory and cpu."""
    mounts = parse_mountinfo(mountinfo)
    own = parse_proc_cgroup(proc_cgroup)
    v1 = {}
    for m in mounts:
        if m.version != 1:
            continue
        for c in m.controllers:
            if c in v1:
                continue
            path = own.get(c, "/")
            rel = path[len(m.root):] if m.root != "/" and path.startswith(m.root) else path
            v1[c] = str(Path(m.path) / rel.lstrip("/") / scope)
    if "memory" in v1:
        return Layout(1, v1)
    v2 = next((m for m in mounts if m.version == 2), None)
    if v2 is not None and v2_controllers is not None and {"memory", "cpu"} <= set(v2_controllers.split()):
        return Layout(2, {"": str(Path(v2.path) / scope)}, v2_root=v2.path)
    return None


def host_layout(scope: str) -> Layout | None:
    """:func:`detect` on this host (reads /proc and the v2 root's ``cgroup.controllers``)."""
    try:
        mountinfo = Path("/proc/self/mountinfo").read_text()
        proc_cgroup = Path("/proc/self/cgroup").read_text()
    except OSError:
        return None
    v2_ctrls = None
    for m in parse_mountinfo(mountinfo):
        if m.version == 2:
            try:
                v2_ctrls = (Path(m.path) / "cgroup.controllers").read_text()
            except OSError:
                pass
            break
    return detect(scope, mountinfo, proc_cgroup, v2_ctrls)


def cpu_max_cores(text: str) -> float | None:
    """A v2 ``cpu.max`` text (``"QUOTA PERIOD"`` or ``"max PERIOD"``) as cores (None: no limit)."""
    parts = text.split()
    if len(parts) != 2 or parts[0] == "max":
        return None
    try:
        return int(parts[0]) / int(parts[1])
    except (ValueError, ZeroDivisionError):
        return None


def cfs_quota_cores(quota: str, period: str) -> float | None:
    """v1 ``cpu.cfs_quota_us`` and ``cpu.cfs_period_us`` texts as cores (None: no limit, quota -1)."""
    try:
        q, p = int(quota), int(period)
    except ValueError:
        return None
    return q / p if q > 0 and p > 0 else None


def host_cpus() -> float:
    """The cores this process may use: the CPUs it may run on (affinity), capped by the CPU quota
    of its own cgroup and every ancestor: v2 ``cpu.max``, or v1 ``cpu.cfs_quota_us`` over
    ``cpu.cfs_period_us`` where the cpu controller is a v1 hierarchy (a robot's computer capped at
    0.3 cores says 0.3)."""
    cores = float(len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
    try:
        mounts = parse_mountinfo(Path("/proc/self/mountinfo").read_text())
        groups = parse_proc_cgroup(Path("/proc/self/cgroup").read_text())
    except OSError:
        return cores
    v1 = next((m for m in mounts if m.version == 1 and "cpu" in m.controllers), None)
    if v1 is not None and groups.get("cpu") is not None:
        def v1_limit(d: Path) -> float | None:
            return cfs_quota_cores((d / "cpu.cfs_quota_us").read_text(), (d / "cpu.cfs_period_us").read_text())
        return min(cores, _ancestors_min(Path(v1.path), groups["cpu"], v1_limit))
    v2 = next((m for m in mounts if m.version == 2), None)
    if v2 is None or groups.get("") is None:
        return cores
    return min(cores, _ancestors_min(Path(v2.path), groups[""], lambda d: cpu_max_cores((d / "cpu.max").read_text())))


def _ancestors_min(root: Path, own: str, limit) -> float:
    """The least ``limit(dir)`` (cores, or None: none) of cgroup ``own`` under mount ``root`` and its
    ancestors up to the mount; inf without any."""
    d, least = root / own.lstrip("/"), float("inf")
    while True:
        try:
            v = limit(d)
        except OSError:
            v = None
        if v is not None:
            least = min(least, v)
        if d == root or root not in d.parents:
            return least
        d = d.parent


def _write(path: Path, value: str) -> None:
    with open(path, "w") as f:
        f.write(value)


def _read(path: Path) -> str:
    with open(path) as f:
        return f.read()


def _keyed(text: str) -> dict[str, int]:
    """``key value`` lines (memory.oom_control, memory.events, cpu.stat) -> dict."""
    out = {}
    for line in text.splitlines():
        k, _, v = line.partition(" ")
        try:
            out[k] = int(v)
        except ValueError:
            pass
    return out


LIMITS = ("cpu", "memory", "pids")      # the limits a cgroup enforces (``size``, ``bandwidth``: recorded only)


def limits_of(limits: dict) -> dict:
    """Normalized limits: cpu (float cores), memory (float MiB), pids (int tasks); 0 or None
    means unlimited (None). Raises :class:`RequestError` for a negative or non-numeric value."""
    out = {}
    for k in LIMITS:
        v = limits.get(k)
        if v is None:
            out[k] = None
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v < 0:
            raise RequestError(f"limit {k!r} must be a non-negative number, got {v!r}")
        out[k] = None if v == 0 else (int(v) if k == "pids" else float(v))
    if out["pids"] is not None and out["pids"] < 1:
        raise RequestError(f"limit 'pids' must be at least 1 task, got {limits['pids']!r}")
    return out


def _children_weight(parent: Path, name: str, unread: int) -> int:
    """The sum of the CPU weights (file ``name``) of ``parent``'s child directories; one whose
    file cannot be read counts ``unread``. Raises OSError when ``parent`` cannot be listed."""
    total = 0
    for child in parent.iterdir():
        if child.is_dir():
            try:
                total += int(_read(child / name))
            except (OSError, ValueError):
                total += unread
    return total


class CgroupSet:
    """The cgroup(s) of one container: one directory per v1 controller, or one v2 directory.

    ``layout``: the host's :class:`Layout`; ``name``: the per-container directory name."""

    def __init__(self, layout: Layout, name: str):
        self.layout = layout
        self.name = name
        self.dirs: dict[str, Path] = {c: Path(b) / name for c, b in layout.bases.items()}

    # -- paths ---------------------------------------------------------------------------------
    def _dir(self, controller: str) -> Path | None:
        if self.layout.version == 2:
            return self.dirs[""]
        return self.dirs.get(controller)

    @property
    def unique_dirs(self) -> list[Path]:
        seen: list[Path] = []
        for d in self.dirs.values():
            if d not in seen:
                seen.append(d)
        return seen

    @property
    def procs_files(self) -> list[str]:
        """The ``cgroup.procs`` files a process writes its pid to, to join this container."""
        return [str(d / "cgroup.procs") for d in self.unique_dirs]

    # -- lifecycle -----------------------------------------------------------------------------
    def create(self) -> None:
        """Make the directories (and, on v2, enable the controllers on the way down), then
        :meth:`rebalance` the CPU weights above them."""
        if self.layout.version == 2:
            root = Path(self.layout.v2_root)
            d = self.dirs[""]
            rel = d.relative_to(root).parts
            cur = root
            for part in rel:
                _enable_v2(cur)
                cur = cur / part
                cur.mkdir(exist_ok=True)
        else:
            for d in self.unique_dirs:
                d.mkdir(parents=True, exist_ok=True)
        self.rebalance()

    def _weight_file(self) -> tuple[int, int, str]:
        """(one process's CPU weight, the kernel's largest, the weight file's name) of this layout."""
        return (100, 10000, "cpu.weight") if self.layout.version == 2 else (1024, 262144, "cpu.shares")

    def rebalance(self) -> None:
        """Give the two directories above the containers (``<scope>`` and ``rce``) the CPU
        weight of what they hold: the sum of their containers' weights (a container weighs one
        process, v1 shares 1024, v2 weight 100, or its ``cpu`` cores' worth, module doc), so under
        contention a container is not squeezed into the single share of a parent that all
        containers (of every task set on the machine) would otherwise divide among themselves."""
        d = self._dir("cpu")
        if d is None:
            return
        one, cap, name = self._weight_file()
        scope, top = d.parent, d.parent.parent
        try:
            _write(scope / name, str(min(cap, max(one, _children_weight(scope, name, one)))))
            _write(top / name, str(min(cap, max(one, _children_weight(top, name, 0)))))
        except OSError as e:
            log.debug("cannot rebalance CPU weights", dir=str(scope), reason=e.strerror)

    def apply(self, limits: dict) -> dict:
        """Write ``limits`` (keys cpu, memory, pids; a missing key is left alone; None or 0 =
        unlimited). Returns the limits now in force, normalized. Raises :class:`RCEError`
        naming the file when the kernel refuses a value (e.g. memory below what is in use)."""
        want = limits_of(limits)
        given = {k for k in LIMITS if k in limits}
        v2 = self.layout.version == 2
        if "cpu" in given and self._dir("cpu"):
            d = self._dir("cpu")
            cores = want["cpu"]
            if v2:
                quota = "max" if cores is None else str(max(MIN_QUOTA_US, int(round(cores * CFS_PERIOD_US))))
                self._set(d / "cpu.max", f"{quota} {CFS_PERIOD_US}")
            else:
                self._set(d / "cpu.cfs_period_us", str(CFS_PERIOD_US))
                self._set(d / "cpu.cfs_quota_us",
                          "-1" if cores is None else str(max(MIN_QUOTA_US, int(round(cores * CFS_PERIOD_US)))))
            one, cap, name = self._weight_file()
            self._set(d / name, str(min(cap, int(round(one * max(1.0, cores or 0.0))))))
            self.rebalance()
        if "memory" in given and self._dir("memory"):
            d = self._dir("memory")
            mib = want["memory"]
            if v2:
                self._set(d / "memory.max", "max" if mib is None else str(int(mib * 2**20)))
                if (d / "memory.swap.max").exists():
                    self._set(d / "memory.swap.max", "max" if mib is None else "0")
            else:
                value = "-1" if mib is None else str(int(mib * 2**20))
                memsw = d / "memory.memsw.limit_in_bytes"
                if memsw.exists():
                    # memsw >= memory at every step: raise memsw first, lower memory first
                    cur = int(_read(d / "memory.limit_in_bytes"))
                    new = (1 << 62) if mib is None else int(mib * 2**20)
                    order = [memsw, d / "memory.limit_in_bytes"] if new >= cur else [d / "memory.limit_in_bytes", memsw]
                    for f in order:
                        self._set(f, value)
                else:
                    self._set(d / "memory.limit_in_bytes", value)
        if "pids" in given and self._dir("pids"):
            n = want["pids"]
            self._set(self._dir("pids") / "pids.max", "max" if n is None else str(n))
        return want

    def _set(self, path: Path, value: str) -> None:
        try:
            _write(path, value)
        except OSError as e:
            why = e.strerror or str(e)
            if e.errno == errno.EBUSY and "memory" in path.name:
                why = "the container uses more than that and it cannot be reclaimed"
            raise RCEError(f"cannot set {path.name} to {value}: {why}") from None

    # -- reading -------------------------------------------------------------------------------
    def pids(self) -> list[int]:
        """Every process in the container's cgroup (host pids)."""
        for d in self.unique_dirs:
            try:
                return [int(x) for x in _read(d / "cgroup.procs").split()]
            except OSError:
                continue
        return []

    def cpu_seconds(self) -> float | None:
        """CPU time used by the container so far (s), or None if not accounted."""
        try:
            if self.layout.version == 2:
                return _keyed(_read(self.dirs[""] / "cpu.stat")).get("usage_usec", 0) / 1e6
            d = self._dir("cpuacct")
            if d is not None:
                return int(_read(d / "cpuacct.usage")) / 1e9
            d = self._dir("cpu")
            if d is not None and (d / "cpuacct.usage").exists():
                return int(_read(d / "cpuacct.usage")) / 1e9
        except (OSError, ValueError):
            pass
        return None

    def throttling(self) -> dict:
        """``{periods, throttled, throttled_s}`` of the CPU controller: enforcement periods, and
        in how many (for how long) the container hit its CPU limit. Empty if not readable."""
        d = self._dir("cpu")
        if d is None:
            return {}
        try:
            st = _keyed(_read(d / "cpu.stat"))
        except OSError:
            return {}
        if self.layout.version == 2:
            return {"periods": st.get("nr_periods", 0), "throttled": st.get("nr_throttled", 0),
                    "throttled_s": st.get("throttled_usec", 0) / 1e6}
        return {"periods": st.get("nr_periods", 0), "throttled": st.get("nr_throttled", 0),
                "throttled_s": st.get("throttled_time", 0) / 1e9}

    def memory(self) -> dict:
        """``{usage_bytes, limit_bytes, oom_kills, failcnt}`` of the memory controller (what
        is readable; an unlimited limit is None)."""
        out: dict = {}
        d = self._dir("memory")
        if d is None:
            return out
        try:
            if self.layout.version == 2:
                out["usage_bytes"] = int(_read(d / "memory.current"))
                lim = _read(d / "memory.max").strip()
                out["limit_bytes"] = None if lim == "max" else int(lim)
                ev = _keyed(_read(d / "memory.events"))
                out["oom_kills"], out["failcnt"] = ev.get("oom_kill", 0), ev.get("max", 0)
            else:
                out["usage_bytes"] = int(_read(d / "memory.usage_in_bytes"))
                lim = int(_read(d / "memory.limit_in_bytes"))
                out["limit_bytes"] = None if lim >= (1 << 62) else lim
                out["oom_kills"] = _keyed(_read(d / "memory.oom_control")).get("oom_kill", 0)
                out["failcnt"] = int(_read(d / "memory.failcnt"))
        except (OSError, ValueError):
            pass
        return out

    def oom_kills(self) -> int:
        return int(self.memory().get("oom_kills") or 0)

    def files(self) -> dict[str, str]:
        """The limit files as the kernel reports them (for status and tests)."""
        names = (["cpu.max", "cpu.weight", "memory.max", "memory.swap.max", "pids.max"] if self.layout.version == 2
                 else ["cpu.cfs_quota_us", "cpu.cfs_period_us", "cpu.shares", "memory.limit_in_bytes",
                       "memory.memsw.limit_in_bytes", "pids.max"])
        out = {}
        for n in names:
            d = self._dir(n.split(".")[0])
            if d is not None:
                try:
                    out[n] = _read(d / n).strip()
                except OSError:
                    pass
        return out

    # -- teardown ------------------------------------------------------------------------------
    def kill_all(self, timeout: float = KILL_TIMEOUT) -> list[int]:
        """SIGKILL every process in the cgroup until it is empty; returns the pids still
        there after ``timeout`` s (none, unless a process is stuck in the kernel)."""
        return kill_tree(self.unique_dirs, timeout)

    def remove(self, timeout: float = KILL_TIMEOUT) -> list[Path]:
        """Kill what is left and remove the directories; returns those that could not be removed."""
        left = remove_tree(self.unique_dirs, timeout)
        self.rebalance()
        return left


def _enable_v2(directory: Path) -> None:
    try:
        have = set(_read(directory / "cgroup.subtree_control").split())
        ctrls = set(_read(directory / "cgroup.controllers").split())
    except OSError:
        return
    add = [c for c in V2_CONTROLLERS if c in ctrls and c not in have]
    if add:
        try:
            _write(directory / "cgroup.subtree_control", " ".join("+" + c for c in add))
        except OSError as e:
            log.warning("cannot enable cgroup controllers", dir=str(directory), controllers=add, reason=e.strerror)


def _tree(directory: Path) -> list[Path]:
    """``directory`` and every cgroup below it, deepest first; [] when ``directory`` is gone (another cleanup,
    e.g. of a crashed environment, may be removing the same tree)."""
    try:
        subs = [p for p in directory.rglob("*") if p.is_dir()] if directory.is_dir() else None
    except OSError:
        subs = None
    if subs is None:
        return []
    return [*sorted(subs, key=lambda path: len(path.parts), reverse=True), directory]


def tree_pids(dirs: list[Path]) -> set[int]:
    """Every process in ``dirs`` and their sub-cgroups."""
    pids = set()
    for d in dirs:
        for sub in _tree(d):
            try:
                pids.update(int(x) for x in _read(sub / "cgroup.procs").split())
            except (OSError, ValueError):
                pass
    return pids


def kill_tree(dirs: list[Path], timeout: float = KILL_TIMEOUT) -> list[int]:
    """SIGKILL every process in ``dirs`` and their sub-cgroups until none is left."""
    deadline = time.monotonic() + timeout
    while True:
        pids = tree_pids(dirs)
        if not pids or time.monotonic() > deadline:
            return sorted(pids)
        kill = dirs[0] / "cgroup.kill"
        if kill.exists():
            try:
                _write(kill, "1")
            except OSError:
                pass
        for p in pids:
            try:
                os.kill(p, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
        time.sleep(POLL)


def remove_tree(dirs: list[Path], timeout: float = KILL_TIMEOUT) -> list[Path]:
    """Kill every process in ``dirs`` (and below) and rmdir them bottom-up. Returns the
    directories left behind."""
    kill_tree(dirs, timeout)
    left = []
    deadline = time.monotonic() + timeout
    for d in dirs:
        for sub in _tree(d):
            while True:
                try:
                    sub.rmdir()
                    break
                except FileNotFoundError:
                    break
                except OSError as e:
                    if e.errno == errno.EBUSY and time.monotonic() < deadline:   # exiting tasks not yet gone
                        time.sleep(POLL)
                        continue
                    left.append(sub)
                    break
    return left
