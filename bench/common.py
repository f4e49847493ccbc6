"""Shared helpers of the bench scripts: paths, engine start, peers (ROS 1, anchors),
statistics, a raw robot client, CPU and network counters, console and plotting.

Imported as ``from common import ...`` by the scripts in ``bench/`` (run them as
``.venv/bin/python bench/NAME.py``; the script's directory is on ``sys.path``).
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Iterable, Iterator

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"
RESULTS = BENCH / "results"
SHARED = (ROOT / ".." / "shared").resolve()
ANCHORS = SHARED / "anchors"
VENV_PY = sys.executable
SYS_PY = "/usr/bin/python3"          # Debian's python3: the one that has rospy
ROS1_DEBS = ("python3-rospy", "python3-rosmaster", "python3-std-msgs", "python3-sensor-msgs")
ROS1_MODULES = ("rospy", "rosmaster", "std_msgs.msg", "sensor_msgs.msg")

sys.path.insert(0, str(ROOT / "tests"))           # wsclient.py
from rce.tools.launch import Engine, start_engine  # noqa: E402
from wsclient import RawRobot, login  # noqa: E402,F401  (re-exported)

USER, PASSWORD = "testUser", "testUser"            # the master's --dev user


# -- sizes, stats ------------------------------------------------------------------------------

def anchor_sizes() -> list[int]:
    """The payload sizes of the original engine's measurement suite (shared/anchors/sizes.py)."""
    ns: dict = {}
    exec((ANCHORS / "sizes.py").read_text(), ns)
    return list(ns["SIZES"])


def percentile(xs: Iterable[float], q: float) -> float:
    """``q``-th percentile (0..100, linear interpolation) of the finite values; NaN if none."""
    v = sorted(x for x in xs if x is not None and math.isfinite(x))
    if not v:
        return float("nan")
    k = (len(v) - 1) * q / 100.0
    lo, hi = math.floor(k), math.ceil(k)
    return v[lo] + (v[hi] - v[lo]) * (k - lo)


def median(xs: Iterable[float]) -> float:
    return percentile(xs, 50)


def ratio(a: float | None, b: float | None) -> float:
    if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)) or b <= 0:
        return float("nan")
    return a / b


def geomean(xs: Iterable[float]) -> float:
    v = [x for x in xs if x is not None and math.isfinite(x) and x > 0]
    return math.exp(sum(map(math.log, v)) / len(v)) if v else float("nan")


def jsonable(x):
    """NaN/inf -> None, recursively (strict JSON)."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    return x


def write_json(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(jsonable(data), indent=1) + "\n")


def fmt_ms(x: float | None) -> str:
    if x is None or not math.isfinite(x):
        return "-"
    return f"{x:.3f}" if x < 1 else f"{x:.2f}" if x < 100 else f"{x:.0f}"


def fmt_ratio(x: float | None) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.2f}"


def fmt_size(n: int) -> str:
    return f"{n} B" if n < 1000 else f"{n / 1e3:.1f} kB" if n < 1e6 else f"{n / 1e6:.1f} MB"


def git_head() -> str:
    """``git log -1 --oneline`` of the checkout, with ``(+N files changed)`` when the work tree differs
    from that commit; ``"unknown"`` outside git."""
    try:
        head = subprocess.run(["git", "log", "-1", "--oneline"], cwd=ROOT, capture_output=True, text=True,
                              timeout=10).stdout.strip()
        changed = subprocess.run(["git", "status", "--porcelain"], cwd=ROOT, capture_output=True, text=True,
                                 timeout=10).stdout.splitlines()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return (head or "unknown") + (f" (+{len(changed)} files changed)" if changed else "")


# -- console, plots ----------------------------------------------------------------------------

def console():
    from rich.console import Console
    return Console(stderr=False, width=max(140, shutil.get_terminal_size((140, 40)).columns))


def progress(con=None):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn
    return Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TimeElapsedColumn(), console=con, transient=False)


def pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


# -- engine ------------------------------------------------------------------------------------

def add_ws_impl_argument(p) -> None:
    """``--ws-impl``: the websocket library rce-robot serves robots with (``rce-robot --ws-impl``), so a run can
    set the two side by side."""
    from rce_robot.ws_link import DEFAULT_IMPL, IMPLS
    p.add_argument("--ws-impl", choices=IMPLS, default=DEFAULT_IMPL,
                   help=f"rce-robot's websocket library (default {DEFAULT_IMPL})")


@contextlib.contextmanager
def engine(workdir: Path | None = None, env: dict | None = None, **kw) -> Iterator[Engine]:
    """The real engine as processes (:mod:`rce.tools.launch`). ``env`` is added to ``os.environ`` while it
    starts (start_engine passes os.environ on to every process it spawns)."""
    saved = {k: os.environ.get(k) for k in (env or {})}
    os.environ.update(env or {})
    try:
        e = start_engine(workdir or Path(tempfile.mkdtemp(prefix="rce-bench-")), **kw)
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    try:
        yield e
    finally:
        e.stop()


class WsRobot(RawRobot):
    """A RawRobot that connects to a known websocket URL (no HTTP login: the login may have been
    done elsewhere, e.g. by a server that can reach the master when the robot cannot)."""

    def __init__(self, ws_url: str, robot: str, user: str = USER, password: str = PASSWORD):
        super().__init__("", robot, user, password)
        self.ws_url = ws_url

    async def __aenter__(self) -> "WsRobot":
        from websockets.asyncio.client import connect
        pw = hashlib.sha256(self.password.encode()).hexdigest()
        self.ws = await connect(f"{self.ws_url}?userID={self.user}&robotID={self.robot}&password={pw}",
                                max_size=None, compression=None, ping_interval=None)
        return self


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


# -- ROS 1 (Debian's rospy) --------------------------------------------------------------------

def ros1_available() -> bool:
    if not os.path.exists(SYS_PY):
        return False
    r = subprocess.run([SYS_PY, "-c", "import " + ", ".join(ROS1_MODULES)], capture_output=True)
    return r.returncode == 0 and shutil.which("rosmaster") is not None


def ensure_ros1(install: bool = True, log=print) -> tuple[bool, str]:
    """Make Debian's ROS 1 (rospy, rosmaster, std_msgs, sensor_msgs) available; installs the
    packages with apt-get when missing and running as root. Returns (ok, reason)."""
    if ros1_available():
        return True, "ok"
    if not install:
        return False, "ROS 1 (Debian python3-rospy) not installed"
    if os.geteuid() != 0 or not shutil.which("apt-get"):
        return False, f"ROS 1 missing and not root (install {' '.join(ROS1_DEBS)})"
    log(f"installing Debian {' '.join(ROS1_DEBS)} (apt-get update first) ...")
    env = dict(os.environ, DEBIAN_FRONTEND="noninteractive")
    for argv in (["apt-get", "update", "-qq"],
                 ["apt-get", "install", "-y", "-qq", "--no-install-recommends", *ROS1_DEBS]):
        r = subprocess.run(argv, env=env, capture_output=True, text=True)
        if r.returncode != 0:
            return False, f"{' '.join(argv[:2])} failed: {(r.stderr or r.stdout).strip()[-300:]}"
    return (True, "installed") if ros1_available() else (False, "installed, but rospy still not importable")


def run_anchor(script: str, python: str, reps: int, env: dict | None = None, timeout: float = 900) -> dict:
    """Run an anchor script of shared/anchors; returns its ``{"peer", "rtt_ms": {size: ms}}``
    with integer sizes (NaN where it gave none)."""
    e = dict(os.environ, REPS=str(reps), **(env or {}))
    r = subprocess.run([python, str(ANCHORS / script)], env=e, capture_output=True, text=True, timeout=timeout,
                       cwd=tempfile.gettempdir())
    return peer_result(r, script)


def peer_result(r: subprocess.CompletedProcess, script: str) -> dict:
    """The last JSON line ``{"peer", "rtt_ms": {size: ms}, ...}`` a peer script printed, sizes as
    integers, NaN where it gave none. Raises RuntimeError (with its stderr's end) when there is none."""
    for line in reversed(r.stdout.splitlines()):
        if line.startswith("{"):
            d = json.loads(line)
            d["rtt_ms"] = {int(k): (float(v) if v is not None else float("nan")) for k, v in d["rtt_ms"].items()}
            return d
    raise RuntimeError(f"{script} gave no result (exit {r.returncode}): {r.stderr.strip()[-800:]}")


# -- CPU ---------------------------------------------------------------------------------------

def proc_tree(pids: Iterable[int], include_roots: bool = True) -> list:
    """psutil.Process objects of ``pids`` and all their descendants (those alive now)."""
    import psutil
    out, seen = [], set()
    for pid in pids:
        try:
            p = psutil.Process(pid)
            kids = p.children(recursive=True)
        except psutil.Error:
            continue
        for q in ([p] if include_roots else []) + kids:
            if q.pid not in seen:
                seen.add(q.pid)
                out.append(q)
    return out


def proc_label(p) -> str:
    """Short name of a process for CPU breakdowns: the script, entry point or module it runs."""
    try:
        cmd = p.cmdline()
    except Exception:
        return "?"
    for a in cmd:
        b = os.path.basename(a)
        if b.startswith(("rce-", "rosmaster")) or b.endswith(".py"):
            return b
    if "-m" in cmd and cmd.index("-m") + 1 < len(cmd):
        return cmd[cmd.index("-m") + 1]
    return os.path.basename(cmd[0]) if cmd else "?"


def process_cpu_s(p) -> float:
    """CPU time of the process ``p`` (a psutil.Process or a pid) in s: user + system of all its
    threads, those that exited too, at nanosecond resolution. It reads the kernel's CPU clock of the
    process (``clock_gettime`` on the clock id ``clock_getcpuclockid(3)`` gives,
    ``MAKE_PROCESS_CPUCLOCK(pid, CPUCLOCK_SCHED)`` = ``(~pid << 3) | 2`` in Linux's
    include/linux/posix-timers.h), not /proc/PID/stat's user and system times, which come in ticks of
    10 ms: a process that works a few ms in a window of a few seconds reads 0 there. Raises
    psutil.NoSuchProcess when the process is gone."""
    import psutil
    pid = p if isinstance(p, int) else p.pid
    try:
        return time.clock_gettime((~pid << 3) | 2)
    except OSError:
        raise psutil.NoSuchProcess(pid) from None


class CpuMeter:
    """CPU time (user + system, :func:`process_cpu_s`) of a fixed set of processes between :meth:`start` and
    :meth:`stop`. Processes that exit between the two are not counted (so keep them alive)."""

    def __init__(self, procs: list):
        self.procs = procs
        self.t0: dict[int, float] = {}
        self.t1: dict[int, float] = {}
        self.wall = 0.0

    @staticmethod
    def _cpu(p) -> float | None:
        try:
            return process_cpu_s(p)
        except Exception:
            return None

    def start(self) -> None:
        self.labels = {p.pid: proc_label(p) for p in self.procs}
        self.w0 = time.monotonic()
        self.t0 = {p.pid: self._cpu(p) for p in self.procs}

    def stop(self) -> None:
        self.wall = time.monotonic() - self.w0
        self.t1 = {p.pid: self._cpu(p) for p in self.procs}

    def seconds(self) -> dict[int, float]:
        return {pid: self.t1[pid] - self.t0[pid] for pid in self.t0
                if self.t0[pid] is not None and self.t1.get(pid) is not None}

    def percent(self) -> float:
        """CPU % of one core over the wall time (may exceed 100 with several processes)."""
        return 100.0 * sum(self.seconds().values()) / self.wall if self.wall > 0 else float("nan")

    def by_label(self) -> dict[str, float]:
        out: dict[str, float] = {}
        secs = self.seconds()
        for p in self.procs:
            if p.pid in secs:
                k = self.labels.get(p.pid) or proc_label(p)
                out[k] = out.get(k, 0.0) + 100.0 * secs[p.pid] / self.wall
        return {k: round(v, 2) for k, v in sorted(out.items(), key=lambda kv: -kv[1])}


class ForeignLoad:
    """How busy the machine was with work that is not ours over a phase: machine-wide busy CPU
    (psutil.cpu_times, all cores) minus our own CPU (this process, its reaped children, and its
    live descendants with their reaped children). ``stop()`` returns cores: ``other_cores`` near
    0 means the phase ran on an otherwise quiet machine; 1.0 = one core taken by someone else."""

    @staticmethod
    def _busy() -> float:
        import psutil
        t = psutil.cpu_times()
        return sum(t) - t.idle - getattr(t, "iowait", 0.0) - getattr(t, "guest", 0.0) - getattr(t, "guest_nice", 0.0)

    @staticmethod
    def _mine() -> float:
        import resource

        import psutil
        s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
        total = s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime
        for p in psutil.Process().children(recursive=True):
            try:
                t = p.cpu_times()
                total += t.user + t.system + t.children_user + t.children_system
            except psutil.Error:
                pass
        return total

    def start(self) -> "ForeignLoad":
        self.w0, self.b0, self.m0 = time.monotonic(), self._busy(), self._mine()
        return self

    def stop(self) -> dict:
        wall = time.monotonic() - self.w0
        busy, mine = self._busy() - self.b0, self._mine() - self.m0
        return {"wall_s": round(wall, 2), "machine_busy_cores": round(busy / wall, 2),
                "own_cores": round(mine / wall, 2), "other_cores": round(max(0.0, busy - mine) / wall, 2)}


def set_nice(n: int | None, log=print) -> None:
    """Run this bench and every process it starts (peers, engine, nodes) at niceness ``n``
    (negative needs root): on a shared machine, the measured processes then get the CPU before
    other work, which brings the numbers closer to a dedicated machine's. Both systems alike."""
    if n is None:
        return
    try:
        os.setpriority(os.PRIO_PROCESS, 0, n)
        log(f"running at niceness {n}")
    except OSError as e:
        log(f"cannot set niceness {n}: {e.strerror}")


def wait_quiet(max_wait: float, threshold: float = 0.3, window: float = 3.0, log=print) -> dict | None:
    """Wait (at most ``max_wait`` s) until other processes use less than ``threshold`` cores over a
    ``window``; returns the last :class:`ForeignLoad` reading (None if ``max_wait`` <= 0)."""
    if max_wait <= 0:
        return None
    deadline = time.monotonic() + max_wait
    while True:
        fl = ForeignLoad().start()
        time.sleep(window)
        r = fl.stop()
        if r["other_cores"] < threshold or time.monotonic() >= deadline:
            log(f"machine load before measuring: other processes use {r['other_cores']:.2f} cores"
                + ("" if r["other_cores"] < threshold else f" (still >= {threshold} after {max_wait:.0f} s; going on)"))
            return r
        log(f"waiting for a quieter machine: other processes use {r['other_cores']:.2f} cores")


# -- network: two namespaces joined by a veth pair ---------------------------------------------

class NetLab:
    """A server namespace and a client namespace joined by one veth pair, so the bytes between a
    system's server side and its client side are counted by the server end's interface counters
    (``ip -s link``: every frame with its Ethernet/IP/TCP headers, as a NIC would count them).
    Traffic inside one side (e.g. rce-master <-> rce-robot <-> environments) stays on that
    namespace's own loopback and is not counted, as on the paper's Machine 1.

    Needs root and iproute2; :attr:`ok` is False (with :attr:`reason`) otherwise, and then
    :meth:`wrap_srv`/:meth:`wrap_cli` run commands unwrapped on loopback and nothing is counted.
    Addresses live only in the two namespaces made here (10.213.77.0/30) and are removed with them."""

    SRV_IP, CLI_IP = "10.213.77.1", "10.213.77.2"

    def __init__(self, tag: str | None = None):
        tag = tag or str(os.getpid())           # names stay within IFNAMSIZ (15) for pids < 10**10
        self.srv, self.cli = f"rceb{tag}s", f"rceb{tag}c"
        self.vs, self.vc = f"vb{tag}s", f"vb{tag}c"
        self.ok, self.reason = False, ""

    def _ip(self, *args: str) -> None:
        subprocess.run(["ip", *args], check=True, capture_output=True, text=True)

    def __enter__(self) -> "NetLab":
        if os.geteuid() != 0 or not shutil.which("ip"):
            self.reason = "network namespaces need root and iproute2: network bytes not counted"
            return self
        self._reap_stale()
        try:
            self._ip("netns", "add", self.srv)
            self._ip("netns", "add", self.cli)
            self._ip("link", "add", self.vs, "type", "veth", "peer", "name", self.vc)
            self._ip("link", "set", self.vs, "netns", self.srv)
            self._ip("link", "set", self.vc, "netns", self.cli)
            for ns, dev, ip in ((self.srv, self.vs, self.SRV_IP), (self.cli, self.vc, self.CLI_IP)):
                self._ip("-n", ns, "addr", "add", f"{ip}/30", "dev", dev)
                self._ip("-n", ns, "link", "set", dev, "up")
                self._ip("-n", ns, "link", "set", "lo", "up")
            self.ok = True
        except (subprocess.CalledProcessError, OSError) as e:
            self.reason = f"cannot make network namespaces ({getattr(e, 'stderr', '') or e}): network bytes not counted"
            self.__exit__()
        return self

    @staticmethod
    def _reap_stale() -> None:
        """Delete namespaces this class made in a bench run that was killed (its pid is gone)."""
        import re
        r = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True)
        for line in r.stdout.splitlines():
            m = re.match(r"(rceb(\d+)[sc])\b", line)
            if m and not os.path.exists(f"/proc/{m.group(2)}"):
                subprocess.run(["ip", "netns", "del", m.group(1)], capture_output=True)

    def __exit__(self, *exc) -> None:
        for ns in (self.srv, self.cli):   # deleting a namespace deletes its end of the veth pair, and so the pair
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)

    @property
    def srv_ip(self) -> str:
        return self.SRV_IP if self.ok else "127.0.0.1"

    @property
    def cli_ip(self) -> str:
        return self.CLI_IP if self.ok else "127.0.0.1"

    def wrap_srv(self, argv: list[str]) -> list[str]:
        return ["ip", "netns", "exec", self.srv, *argv] if self.ok else list(argv)

    def wrap_cli(self, argv: list[str]) -> list[str]:
        return ["ip", "netns", "exec", self.cli, *argv] if self.ok else list(argv)

    def counters(self) -> dict | None:
        """``{rx_bytes, tx_bytes, rx_packets, tx_packets}`` of the server end (rx = client -> server)."""
        if not self.ok:
            return None
        r = subprocess.run(["ip", "-j", "-s", "-n", self.srv, "link", "show", self.vs],
                           capture_output=True, text=True, check=True)
        st = json.loads(r.stdout)[0]["stats64"]
        return {"rx_bytes": st["rx"]["bytes"], "tx_bytes": st["tx"]["bytes"],
                "rx_packets": st["rx"]["packets"], "tx_packets": st["tx"]["packets"]}
