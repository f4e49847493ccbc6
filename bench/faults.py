"""Faults benchmark: what survives what, how fast the robot is served again,
and how many messages are lost, for rce and, in the same run, ROS 1.

A robot echoes a ``std_msgs/String`` at 10 Hz through a converter to the Test package's
``stringEcho.py`` in a container (``bench/rtt.py``'s ``rce_converter`` path), the payload being
the message's sequence number. The bench injects one fault and measures:

- **served again after** (s): from the fault to the first echo, back at the robot, of a message
  the robot generated after the fault (a robot never interrupted is served again one period
  later; ``max_gap_s`` tells whether it was);
- **lost**: messages generated from the start of the measurement (the first echo) to the end of
  sending whose echo never came back, exact by sequence number. A message the robot could not
  send because it had no link counts as lost (``not_sent``).

rce faults (``--faults``), each on a fresh engine (``rce.tools.launch``, real processes on loopback):

- ``master``: kill -9 of rce-master, restarted after ``restart`` s on the same ``--state`` file;
  also when login works again and when a new request (a CN adding interfaces and a CX connecting
  them, from a second robot) works again (its robot-side interface comes up);
- ``leader``: two masters on a real etcd (``tests/etcd_server.py``), kill -9 of the leader; also
  when the standby leads, when login works on it and when a new request works;
- ``link``: the robot's websocket runs through a TCP proxy on loopback (``rce.transport.tcpproxy``), which
  resets every connection (RST both ways, as a wireless drop) and refuses new ones for ``cut`` s;
- ``robot``: two robot endpoints, kill -9 of the robot's; the robot reconnects (above), logging
  in again to reach the other one;
- ``host``: two container hosts, kill -9 of the one running the robot's container;
- ``environment``: kill -9 of the environment process running the robot's container.

The robot is an ``rce_client.Connection``. When that library reconnects by itself
(``allow_reconnect=True``: it dials the same robot endpoint again and resumes the session,
docs/INTERNALS.md "Session resume") the bench lets it. When the library gives up (the grace has
passed), or cannot reconnect at all (an rce_client without ``allow_reconnect``), the bench
reconnects as an application would: it logs in again (or reopens the proxy's URL) with backoff
and, its session being gone, re-creates its container, node, interfaces and connections (each
request alone; "already exists" ERs are fine). The bench never re-creates a container that the
engine reports lost: that is the engine's job (containers outlive their host).

ROS 1 (Debian's ros-comm, rospy; ``--no-ros1`` skips it), where ROS 1 has the fault: the robot
is a rospy node publishing ``/faultReq`` at 10 Hz, ``bench/ros1/echo.py`` echoes it on
``/faultReq_echo``:

- ``master``: kill -9 of rosmaster, restarted on the same port: do the existing topics keep
  flowing, and does a new subscriber find the old publisher after the restart (and before the
  fault, for comparison)?
- ``link``: the TCP link from the robot's publisher to the echo node's subscriber runs through the
  same proxy (the robot tells subscribers the proxy's port in its ``requestTopic`` answer), cut
  as for rce.

Every wait is bounded (``Timing``); every process the bench starts, and their descendants, are
killed at the end, also on Ctrl-C or an error (``Reaper``). Traffic stays on 127.0.0.1.

Usage::

    .venv/bin/python bench/faults.py [--quick] [--faults master,leader,link,robot,host,environment]
        [--no-ros1] [--json PATH] [--plot PATH]

Results: ``bench/results/faults.json`` and ``bench/results/faults.png`` by default; the
processes' logs stay in the work directory printed at the start.
"""
from __future__ import annotations

import argparse
import asyncio
import contextlib
import datetime
import inspect
import json
import logging
import math
import os
import shlex
import signal
import subprocess
import sys
import tempfile
import time
import traceback
import urllib.error
import urllib.request
import xmlrpc.client
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Awaitable, Callable
from urllib.parse import urlsplit

from common import (BENCH, PASSWORD, RESULTS, ROOT, SYS_PY, USER, ForeignLoad, console, ensure_ros1, free_port,
                    git_head, proc_tree, progress, pyplot, write_json)
from etcd_server import EtcdServer
from rce.plumbing.errors import RCEError, Unavailable
from rce.tools.launch import Engine, command, start_engine
from rce.plumbing.tasks import Tasks
from rce.transport.tcpproxy import TcpProxy
from rce_client.connection import Connection, login

FAULTS = ("master", "leader", "link", "robot", "host", "environment")
ROS1_FAULTS = ("master", "link")
DESCRIPTION = {
    ("master", "rce"): "kill -9 rce-master, restart on the same --state file",
    ("leader", "rce"): "kill -9 the leading rce-master (etcd), a standby takes over",
    ("link", "rce"): "robot's TCP link reset and cut",
    ("robot", "rce"): "kill -9 rce-robot, a second robot endpoint",
    ("host", "rce"): "kill -9 rce-container, a second host",
    ("environment", "rce"): "kill -9 the container's environment",
    ("master", "ros1"): "kill -9 rosmaster, restart on the same port",
    ("link", "ros1"): "TCP link publisher -> subscriber reset and cut",
}
FIELDS = ("fault", "system", "description", "survived", "served_again_s", "lost", "lost_seqs", "measured",
          "echoed", "not_sent", "duplicates", "max_gap_s", "notes", "extra", "events", "commands", "timeline")
STRING = "std_msgs/String"
ROBOT, CTAG, PROBE_ROBOT = "faultBot", "faultC", "faultProbe"
ROS1_TOPIC = "/faultReq"
RATE_HZ = 10.0           # messages per second the robot echoes (the rate of the fault tests)

SEND_TIMEOUT = 2.0       # s one publish may take before its message counts as not sent (a dead link may block)
BACKOFF_FIRST = 0.1      # s, the bench's first delay between reconnect attempts ...
BACKOFF_CAP = 1.0        # s ... doubled after each failure up to this (an application's usual backoff)
REBUILD_WAIT = 10.0      # s the bench waits for re-created interfaces to come up before it sends the requests again
RESUME_WAIT = 1.0        # s after a library reconnect for its "resumed" callback, else the bench re-creates
PROBE_WAIT = 10.0        # s one new-request probe waits for its interface to come up before the next probe
PROBE_RETRY = 0.5        # s between a failed probe and the next
POLL = 0.05              # s between polls (an echo, a leader, a login, a process exit)
HTTP_TIMEOUT = 2.0       # s, one polling HTTP request (login, /api/leader, rosmaster)
CLOSE_TIMEOUT = 10.0     # s a robot's connection may take to close at the end (a dead link: the client's own bound)
NODE_EXIT = 5.0          # s a ROS 1 node has to exit after EXIT before it is killed


@dataclass(frozen=True)
class Timing:
    """The bench's waits, s. ``pre``: steady echo before the fault; ``bound``: the longest wait after
    the fault for the robot to be served again (and for a new request, a login, a leader);
    ``post``: echo after the robot is served again; ``drain``: the longest wait for the last
    echoes once sending stops; ``cut``: how long a link is cut; ``restart``: from the kill of a
    master (rosmaster) to its restart; ``listen``: the longest wait for a new ROS 1 subscriber's
    first message; ``setup``: the longest wait for a container to echo."""
    pre: float
    bound: float
    post: float
    drain: float
    cut: float
    restart: float
    listen: float
    setup: float


# bound: past the engine's 30 s defaults (a request waiting on an absent master, a robot's resume
# grace, the master's reconcile grace), so what they allow is seen
FULL = Timing(pre=3.0, bound=45.0, post=3.0, drain=3.0, cut=5.0, restart=1.0, listen=10.0, setup=90.0)
# --quick (the smoke test): what the engine does within seconds is seen, the rest is "not within"
QUICK = Timing(pre=1.5, bound=10.0, post=1.0, drain=1.5, cut=2.0, restart=0.5, listen=3.0, setup=90.0)


# -- processes -------------------------------------------------------------------------------------

class Reaper:
    """Every process the bench starts and their descendants as last seen; :meth:`kill_all` sends
    SIGKILL to whichever still runs, matched by pid and start time (never a reused pid)."""

    def __init__(self) -> None:
        self.roots: list[int] = []
        self.seen: dict[int, float] = {}

    def add(self, pid: int) -> None:
        self.roots.append(pid)
        self.snapshot()

    def snapshot(self) -> None:
        """Remember the live descendants of every root (before a kill orphans them)."""
        for p in proc_tree(self.roots):
            with contextlib.suppress(Exception):
                self.seen.setdefault(p.pid, p.create_time())

    def kill_all(self) -> int:
        """SIGKILL every remembered process still running; returns how many there were."""
        import psutil
        self.snapshot()
        n = 0
        for pid, created in self.seen.items():
            try:
                p = psutil.Process(pid)
                if p.create_time() == created:
                    p.kill()
                    n += 1
            except psutil.Error:
                pass
        return n


@dataclass
class Ctx:
    """One bench run: its waits, work directory, reaper, a status line, and what still needs
    stopping (``stoppers``: callables, run on the way out even after Ctrl-C)."""
    t: Timing
    workdir: Path
    reaper: Reaper
    status: Callable[[str], None]
    stoppers: list[Callable[[], None]] = field(default_factory=list)


def kill9(pid: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGKILL)


class ProcWatch:
    """Notes in ``events`` when one of ``procs`` ({name: Popen}) exits, polling every :data:`POLL` s;
    snapshots the reaper as it goes (a process about to die may orphan children)."""

    def __init__(self, procs: dict[str, subprocess.Popen], events: "EchoLog", reaper: Reaper):
        self.procs, self.log, self.reaper = procs, events, reaper
        self.exited: dict[str, tuple[float, int, int]] = {}       # name -> (when, exit code, pid)

    async def run(self) -> None:
        while True:
            for name, p in list(self.procs.items()):
                if name not in self.exited and p.poll() is not None:
                    self.exited[name] = (time.monotonic(), p.returncode, p.pid)
                    self.log.event(f"{name} exited ({p.returncode})")
            self.reaper.snapshot()
            await asyncio.sleep(POLL)


# -- what a robot sent and got back ----------------------------------------------------------------

@dataclass
class EchoLog:
    """One robot's messages: ``sent`` seq -> monotonic time (s) it was generated, ``echoed`` seq ->
    its first echo's arrival, ``not_sent`` (generated with no link), ``duplicates`` (echoes after
    the first), ``events`` [(time, text)]; ``t_start``: when the measurement began (the first echo)."""
    sent: dict[int, float] = field(default_factory=dict)
    echoed: dict[int, float] = field(default_factory=dict)
    not_sent: set[int] = field(default_factory=set)
    duplicates: int = 0
    events: list[tuple[float, str]] = field(default_factory=list)
    t_start: float | None = None

    def echo(self, seq: int, t: float) -> None:
        if seq in self.echoed:
            self.duplicates += 1
        else:
            self.echoed[seq] = t
            if self.t_start is None:
                self.t_start = t

    def event(self, text: str, t: float | None = None) -> None:
        self.events.append((time.monotonic() if t is None else t, text))

    def measured(self) -> list[int]:
        """Sequence numbers generated since the measurement began."""
        if self.t_start is None:
            return []
        return sorted(s for s, t in self.sent.items() if t >= self.t_start)

    def served_after(self, t0: float) -> float | None:
        """s from ``t0`` to the first echo of a message generated at or after ``t0``; None: none yet."""
        arrivals = [self.echoed[s] for s, t in self.sent.items() if t >= t0 and s in self.echoed]
        return min(arrivals) - t0 if arrivals else None

    def missing(self) -> int:
        """Measured messages that were sent and whose echo has not come (yet)."""
        return sum(1 for s in self.measured() if s not in self.echoed and s not in self.not_sent)


def ranges(seqs: list[int]) -> str:
    """``[3, 4, 5, 9]`` -> ``"3-5, 9"``."""
    runs: list[list[int]] = []
    for s in seqs:
        if runs and s == runs[-1][1] + 1:
            runs[-1][1] = s
        else:
            runs.append([s, s])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


def summarize(log: EchoLog, t0: float, t_end: float) -> dict:
    """The measured figures of one run around a fault at ``t0`` (see the module's definitions);
    ``t_end``: when the observation ended (for a gap still open)."""
    seqs = log.measured()
    lost = [s for s in seqs if s not in log.echoed]
    arrivals = sorted(log.echoed[s] for s in seqs if s in log.echoed)
    before = [a for a in arrivals if a < t0]
    after = [a for a in arrivals if a >= t0]
    marks = ([before[-1]] if before else [t0]) + after
    gaps = [b - a for a, b in zip(marks, marks[1:], strict=False)]
    if not after:
        gaps.append(t_end - marks[-1])
    served = log.served_after(t0)
    timeline = [[round(log.sent[s] - t0, 3),
                 round((log.echoed[s] - log.sent[s]) * 1000, 2) if s in log.echoed else None] for s in seqs]
    return {"survived": served is not None, "served_again_s": None if served is None else round(served, 3),
            "lost": len(lost), "lost_seqs": ranges(lost), "measured": len(seqs), "echoed": len(seqs) - len(lost),
            "not_sent": len([s for s in seqs if s in log.not_sent]), "duplicates": log.duplicates,
            "max_gap_s": round(max(gaps), 3) if gaps else None, "timeline": timeline,
            "events": [[round(t - t0, 3), text] for t, text in log.events]}


async def wait_served(log: EchoLog, t0: float, bound: float, status: Callable[[str], None], what: str) -> float | None:
    """Poll until the robot is served again after ``t0`` (s, see :meth:`EchoLog.served_after`) or ``bound`` s pass."""
    while (s := log.served_after(t0)) is None:
        elapsed = time.monotonic() - t0
        if elapsed >= bound:
            return None
        status(f"{what}: fault at 0 s, waiting for an echo ({elapsed:.1f} of {bound:g} s)")
        await asyncio.sleep(POLL)
    return s


async def drain(log: EchoLog, timeout: float) -> None:
    """Wait (at most ``timeout`` s) until every measured message that was sent has its echo."""
    deadline = time.monotonic() + timeout
    while log.missing() and time.monotonic() < deadline:
        await asyncio.sleep(POLL)


# -- the rce robot -------------------------------------------------------------------------------------

def library_keywords() -> dict[str, bool]:
    """``{"allow_reconnect": True}`` when this rce_client reconnects by itself and resumes
    (``Connection.open(..., allow_reconnect=True)``, docs/INTERNALS.md "Session resume"); else empty."""
    return {"allow_reconnect": True} if "allow_reconnect" in inspect.signature(Connection.open).parameters else {}


class RobotLink:
    """A robot's ``rce_client.Connection``: opened at ``ws_url`` (a proxy), else by logging in at
    the first of ``masters`` (HTTP URLs) that answers; reopened with backoff when it closes. ER and
    ST (container, node, session) go to ``log``'s events."""

    def __init__(self, robot: str, log: EchoLog, masters: list[str], ws_url: str | None, keywords: dict):
        self.robot, self.log, self.masters, self.ws_url, self.keywords = robot, log, masters, ws_url, keywords
        self.conn: Connection | None = None
        self.tasks = Tasks(f"faults {robot}")
        self.resumed = asyncio.Event()
        self.reconnected = asyncio.Event()

    async def open(self) -> Connection:
        """One attempt. Raises :class:`RCEError` (Unavailable, AuthError) when it fails."""
        if self.ws_url:
            conn = await Connection.open(self.ws_url, USER, PASSWORD, self.robot, **self.keywords)
        else:
            last: RCEError = Unavailable("no master URL")
            for url in self.masters:
                try:
                    conn = await Connection.login_connect(url, USER, PASSWORD, self.robot, **self.keywords)
                    break
                except RCEError as e:
                    last = e
            else:
                raise last
        self.conn = conn
        self.wire(conn)
        return conn

    def wire(self, conn: Connection) -> None:
        conn.on_error(lambda reason: self.log.event(f"{self.robot} ER {reason[:160]}"))
        conn.on_status(self._status)
        if self.keywords:
            conn.on_disconnected(lambda reason: self.log.event(f"{self.robot} disconnected ({reason}); the library "
                                                               "reconnects"))
            conn.on_reconnected(lambda url: (self.reconnected.set(), self.log.event(f"{self.robot} reconnected to "
                                                                                    f"{url} (library)")))
            conn.on_resumed(lambda st: (self.resumed.set(), self.log.event(f"{self.robot} resumed: {st}")))

    def _status(self, data: dict) -> None:
        if data.get("topic") != "iu":
            self.log.event(f"{self.robot} ST {data}")

    async def reopen(self, deadline: float | None = None) -> bool:
        """Reconnect, with backoff, until it works (True) or ``deadline`` (monotonic s) passes."""
        delay, said = BACKOFF_FIRST, None
        while deadline is None or time.monotonic() < deadline:
            try:
                again = self.conn is not None
                await self.open()
                self.log.event(f"{self.robot} {'reconnected' if again else 'connected'} to {self.conn.ws_url}")
                return True
            except RCEError as e:
                if e.message != said:
                    said = e.message
                    self.log.event(f"{self.robot} cannot reconnect: {e.message[:200]}")
            await asyncio.sleep(delay)
            delay = min(BACKOFF_CAP, delay * 2)
        return False

    async def close(self) -> None:
        await self.tasks.cancel_all()
        if self.conn is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self.conn.close(), CLOSE_TIMEOUT)


class EchoRobot(RobotLink):
    """The measured robot: container ``CTAG`` with Test/stringEcho.py, converters ``req``/``resp``;
    a ticker generates message ``seq`` every 1/RATE_HZ s (recorded in ``log``) and publishes it
    when it can. When its connection closes it reconnects, and re-creates what its session lost
    (:meth:`build`) unless the library resumed the session."""

    def __init__(self, log: EchoLog, masters: list[str], ws_url: str | None = None, keywords: dict | None = None):
        super().__init__(ROBOT, log, masters, ws_url, library_keywords() if keywords is None else keywords)
        self.library = bool(self.keywords)
        self.ready = False
        self.sending = True
        self.seq = 0

    def wire(self, conn: Connection) -> None:
        super().wire(conn)
        conn.subscriber("resp", STRING, lambda msg: self._echo(msg))
        self.pub = conn.publisher("req", STRING)

    def _echo(self, msg: Any) -> None:
        with contextlib.suppress(KeyError, TypeError, ValueError):
            self.log.echo(int(msg["data"]), time.monotonic())

    async def start(self, timeout: float) -> None:
        """Connect, build, start sending and wait for the first echo (all within ``timeout`` s).
        Raises :class:`RCEError` or :class:`TimeoutError`."""
        deadline = time.monotonic() + timeout
        if not await self.reopen(deadline):
            raise Unavailable(f"robot {self.robot} could not connect within {timeout:g} s")
        await self.build(deadline - time.monotonic())
        self.tasks.spawn(self._tick(), name="ticker")
        while self.log.t_start is None:
            if time.monotonic() > deadline:
                raise TimeoutError(f"no echo within {timeout:g} s of the robot's start")
            await asyncio.sleep(POLL)
        self.tasks.spawn(self._supervise(), name="supervisor")

    async def build(self, timeout: float) -> None:
        """CC, CN (node, 4 interfaces), CX, each alone; wait until both robot-side interfaces are up."""
        c, r = self.conn, self.robot
        self.ready = False
        await c.create_container(CTAG)
        await c.add_node(CTAG, "echo", "Test", "stringEcho.py")
        for etag, itag, kind, addr in ((CTAG, "req", "PublisherInterface", "/stringEchoReq"),
                                       (CTAG, "resp", "SubscriberInterface", "/stringEchoResp"),
                                       (r, "req", "SubscriberConverter", None),
                                       (r, "resp", "PublisherConverter", None)):
            await c.add_interface(etag, itag, kind, STRING, addr)
        for itag in ("req", "resp"):
            await c.connect(f"{CTAG}/{itag}", f"{r}/{itag}")
        await c.wait_interfaces_up(["req", "resp"], timeout=max(0.1, timeout))
        self.ready = True

    async def _tick(self) -> None:
        period, t0, n = 1.0 / RATE_HZ, time.monotonic(), 0
        while self.sending:
            n += 1
            await asyncio.sleep(max(0.0, t0 + n * period - time.monotonic()))
            self.seq += 1
            seq = self.seq
            self.log.sent[seq] = time.monotonic()
            if not (self.library or self.ready) or self.conn.closed:
                self.log.not_sent.add(seq)
                continue
            try:
                async with asyncio.timeout(SEND_TIMEOUT):
                    await self.pub.publish({"data": str(seq)})
            except (RCEError, TimeoutError):
                self.log.not_sent.add(seq)

    async def _supervise(self) -> None:
        while True:
            if self.library:
                await self._follow_library()
            reason = await self.conn.wait_closed()
            self.ready = False
            self.log.event(f"{self.robot} " + (f"connection closed, the library gave up ({reason})" if self.library
                                               else f"disconnected ({reason})"))
            await self.reopen()
            await self.rebuild()

    async def _follow_library(self) -> None:
        """The library reconnects by itself: re-create only when a reconnect did not resume."""
        while not self.conn.closed:
            closed = self.tasks.spawn(self.conn.wait_closed(), name="closed")
            back = self.tasks.spawn(self.reconnected.wait(), name="reconnected")
            await asyncio.wait([closed, back], return_when=asyncio.FIRST_COMPLETED)
            closed.cancel()
            back.cancel()
            if not self.reconnected.is_set():
                return
            self.reconnected.clear()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(RESUME_WAIT):
                    await self.resumed.wait()
            if not self.resumed.is_set():
                await self.rebuild()
            self.resumed.clear()

    async def rebuild(self) -> None:
        """Re-create the session's container, node, interfaces and connections until they are up
        or the connection closes."""
        while not self.conn.closed:
            try:
                await self.build(REBUILD_WAIT)
                self.log.event(f"{self.robot} re-created its container, interfaces and connections")
                return
            except RCEError as e:
                self.log.event(f"{self.robot} re-creating: {e.message[:200]}")

    def stop_sending(self) -> None:
        """The ticker generates no more messages."""
        self.sending = False


class Prober(RobotLink):
    """New requests after a fault, from a second robot: each probe adds a container-side
    PublisherInterface on ``CTAG`` and a robot-side SubscriberConverter (two CN) and connects them
    (CX); the request works when that robot-side interface comes up (ST iu true). A request that
    waits on an absent master may come up after later probes were sent: any probe counts."""

    def __init__(self, log: EchoLog, masters: list[str]):
        super().__init__(PROBE_ROBOT, log, masters, None, {})
        self.n = 0
        self.up: dict[int, float] = {}          # probe number -> when it came up
        self.changed = asyncio.Event()
        self.refused = False                    # an ER came since the last probe was sent

    def wire(self, conn: Connection) -> None:
        super().wire(conn)
        conn.on_status(self._iu)
        conn.on_error(self._er)

    def _er(self, reason: str) -> None:
        self.refused = True
        self.changed.set()

    def _iu(self, data: dict) -> None:
        tag = str(data.get("iTag", ""))
        if data.get("topic") == "iu" and data.get("status") is True and tag.startswith("probe"):
            self.up.setdefault(int(tag[5:]), time.monotonic())
            self.changed.set()

    async def probe(self, timeout: float, since: int | None = None) -> bool:
        """Send one probe and wait up to ``timeout`` s for it (or any probe from number ``since`` on)
        to come up; False at once when an ER comes (one of its requests was refused)."""
        self.n += 1
        n, c, first = self.n, self.conn, self.n if since is None else since
        self.refused = False
        await c.add_interface(CTAG, f"probe{n}", "PublisherInterface", STRING, f"/faultProbe{n}")
        await c.add_interface(self.robot, f"probe{n}", "SubscriberConverter", STRING)
        await c.connect(f"{CTAG}/probe{n}", f"{self.robot}/probe{n}")
        deadline = time.monotonic() + timeout
        while not any(k >= first for k in self.up) and time.monotonic() < deadline and not c.closed \
                and not self.refused:
            self.changed.clear()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(max(0.01, deadline - time.monotonic())):
                    await self.changed.wait()
        return any(k >= first for k in self.up)

    async def start(self, timeout: float) -> float:
        """Connect and make one probe work before the fault; returns the s it took."""
        t0 = time.monotonic()
        if not await self.reopen(t0 + timeout) or not await self.probe(timeout):
            raise Unavailable(f"the new-request probe did not work before the fault (within {timeout:g} s)")
        return time.monotonic() - t0

    async def first_success(self, t0: float, bound: float) -> float | None:
        """s from ``t0`` until a probe sent after ``t0`` works (reconnecting as needed); None: not within ``bound``."""
        first, deadline = self.n + 1, t0 + bound
        while time.monotonic() < deadline:
            if self.conn.closed and not await self.reopen(deadline):
                break
            try:
                await self.probe(min(PROBE_WAIT, deadline - time.monotonic()), first)
            except RCEError as e:
                self.log.event(f"{self.robot} probe: {e.message[:200]}")
            done = [t for k, t in self.up.items() if k >= first]
            if done:
                return min(done) - t0
            await asyncio.sleep(PROBE_RETRY)
        return None


async def first_login(urls: list[str], t0: float, bound: float) -> float | None:
    """s from ``t0`` until login at one of ``urls`` answers a robot endpoint; None: not within ``bound``."""
    while time.monotonic() < t0 + bound:
        for url in urls:
            with contextlib.suppress(RCEError):
                await login(url, USER, timeout=HTTP_TIMEOUT)
                return time.monotonic() - t0
        await asyncio.sleep(POLL)
    return None


def leading(url: str, token: str) -> bool:
    """Does the master at ``url`` lead (``GET /api/leader``)? False when it does not answer."""
    req = urllib.request.Request(url + "api/leader", headers={"Authorization": f"Bearer {token}"})
    try:
        with urllib.request.urlopen(req, timeout=HTTP_TIMEOUT) as r:
            return bool(json.loads(r.read()).get("leading"))
    except (OSError, ValueError, urllib.error.URLError):
        return False


async def first_true(pred: Callable[[], bool], t0: float, bound: float) -> float | None:
    """s from ``t0`` until ``pred()`` (run in a thread) holds; None: not within ``bound``."""
    while time.monotonic() < t0 + bound:
        if await asyncio.to_thread(pred):
            return time.monotonic() - t0
        await asyncio.sleep(POLL)
    return None


async def collect(measures: dict[str, asyncio.Task], deadline: float) -> dict:
    """The results of the measuring tasks, waiting until ``deadline`` (monotonic s) at most; a task
    not done by then (or failed) gives None. Seconds are rounded to ms."""
    pending = [t for t in measures.values() if not t.done()]
    if pending:
        await asyncio.wait(pending, timeout=max(0.0, deadline - time.monotonic()))
    out = {}
    for name, task in measures.items():
        value = None
        if task.done() and not task.cancelled() and task.exception() is None:
            value = task.result()
        else:
            task.cancel()
        out[name] = round(value, 3) if isinstance(value, float) else value
    return out


async def observe(ctx: Ctx, log: EchoLog, t0: float, measures: dict[str, asyncio.Task], what: str) -> dict:
    """After the fault at ``t0``: wait until the robot is served again (at most the bound), let it echo
    ``post`` s more, and return the measuring tasks' results (:func:`collect`)."""
    if await wait_served(log, t0, ctx.t.bound, ctx.status, what) is not None:
        await asyncio.sleep(ctx.t.post)                # echo after the fault (a timer)
    return await collect(measures, t0 + ctx.t.bound)


async def finish(ctx: Ctx, log: EchoLog, t0: float, stop_sending: Callable[[], Any]) -> dict:
    """The observation ends: the robot stops sending, the last echoes come (at most ``drain`` s);
    returns :func:`summarize`'s figures."""
    t_end = time.monotonic()
    stop_sending()
    await drain(log, ctx.t.drain)
    return summarize(log, t0, t_end)


def failed(ctx: Ctx, res: dict, e: Exception) -> None:
    """One fault's run failed: say why in its result, the traceback in the work directory."""
    res["error"] = f"{type(e).__name__}: {e}"
    (ctx.workdir / f"{res['system']}-{res['fault']}-error.txt").write_text(traceback.format_exc())


# -- rce: the engine of one fault ----------------------------------------------------------------------

class Rig:
    """The processes of one rce fault: an engine (:mod:`rce.tools.launch`) and what the fault adds (a
    standby master on etcd, a proxy). ``masters``: the login URLs; ``ws_url``: the robot's websocket
    URL when it must not log in (the proxy's)."""

    def __init__(self, ctx: Ctx, fault: str):
        self.ctx, self.fault = ctx, fault
        self.workdir = ctx.workdir / f"rce-{fault}"
        self.engine: Engine | None = None
        self.etcd: EtcdServer | None = None
        self.proxy: TcpProxy | None = None
        self.masters: list[str] = []
        self.ws_url: str | None = None
        self.standby_url = ""
        self.state: Path | None = None
        self.hosts: dict[str, subprocess.Popen] = {}

    def start(self) -> None:
        """Start the engine of this fault (blocking: nothing else runs yet)."""
        SETUP[self.fault](self)
        self.masters = self.masters or [self.engine.master_url]

    async def start_proxy(self) -> None:
        ws_port = self.engine.robot_ready[0]["ws_port"]
        self.proxy = await TcpProxy(ws_port).start()
        self.ws_url = self.proxy.url

    def procs(self) -> dict[str, subprocess.Popen]:
        """The engine's processes by the name of their log (master, robot0, container0, ...)."""
        e = self.engine
        return {log.stem: p for log, p in zip(e.logs, e.procs, strict=False)} if e else {}

    def commands(self) -> list[str]:
        cmds = [shlex.join(str(a) for a in p.args) for p in self.procs().values()]
        if self.etcd is not None and self.etcd.proc is not None:
            cmds.insert(0, shlex.join(str(a) for a in self.etcd.proc.args))
        return cmds

    def start_master_again(self) -> None:
        """A new rce-master on the killed one's ports and ``--state`` file (as tests/engine/test_master_restart.py)."""
        e = self.engine
        ready = e.workdir / "master-restarted.ready"
        e.spawn("master-restarted", [*command("rce-master"), "--dev", "--port", str(urlsplit(e.master_url).port),
                                     "--control-port", str(e.control_port), "--ready-file", str(ready),
                                     "--state", str(self.state)], ready)

    def stop(self) -> None:
        """Stop everything (SIGTERM, then SIGKILL); idempotent, blocking."""
        if self.engine is not None:
            self.engine.stop()
        if self.etcd is not None:
            self.etcd.stop()


def setup_master(rig: Rig) -> None:
    rig.state = rig.workdir / "master.sqlite3"
    rig.engine = start_engine(rig.workdir / "engine", master_args=("--state", str(rig.state)))


def setup_leader(rig: Rig) -> None:
    rig.etcd = EtcdServer(rig.workdir / "etcd").start()
    e = rig.engine = start_engine(rig.workdir / "engine", robot_tasksets=0, container_hosts=0,
                                  master_args=("--store", rig.etcd.url))
    ready = e.workdir / "standby.ready"
    _, info = e.spawn("standby", [*command("rce-master"), "--dev", "--port", "0", "--control-port", "0",
                                  "--store", rig.etcd.url, "--ready-file", str(ready)], ready)
    rig.standby_url = f"http://127.0.0.1:{info['http_port']}/"
    if hasattr(e, "masters"):          # task sets that take a list of masters (standby masters)
        e.masters.append(f"127.0.0.1:{info['control_port']}")
    e.add_robot_taskset()
    e.add_container_host()
    rig.masters = [e.master_url, rig.standby_url]


def setup_plain(rig: Rig) -> None:
    rig.engine = start_engine(rig.workdir / "engine")


def setup_robot(rig: Rig) -> None:
    rig.engine = start_engine(rig.workdir / "engine", robot_tasksets=2)


def setup_host(rig: Rig) -> None:
    e = rig.engine = start_engine(rig.workdir / "engine", container_hosts=0)
    for name in ("hostA", "hostB"):
        rig.hosts[name] = e.add_container_host("--name", name)


SETUP = {"master": setup_master, "leader": setup_leader, "link": setup_plain, "robot": setup_robot,
         "host": setup_host, "environment": setup_plain}

# -- rce: arming a fault: what to kill, found before the fault; fire(t0) kills it and returns what to measure

Fire = Callable[[float], dict[str, Awaitable]]


async def restart_master(rig: Rig, t0: float) -> float:
    await asyncio.sleep(max(0.0, t0 + rig.ctx.t.restart - time.monotonic()))
    await asyncio.to_thread(rig.start_master_again)
    return time.monotonic() - t0


async def arm_master(rig: Rig, robot: EchoRobot) -> tuple[str, Fire]:
    pid, bound = rig.engine.procs[0].pid, rig.ctx.t.bound

    def fire(t0: float) -> dict[str, Awaitable]:
        kill9(pid)
        return {"master_restarted_s": restart_master(rig, t0), "login_s": first_login(rig.masters, t0, bound)}
    return f"rce-master (pid {pid})", fire


async def arm_leader(rig: Rig, robot: EchoRobot) -> tuple[str, Fire]:
    pid, token, bound = rig.engine.procs[0].pid, rig.engine.admin_token, rig.ctx.t.bound
    if not await asyncio.to_thread(leading, rig.engine.master_url, token):
        raise RuntimeError("the first master does not lead")

    def fire(t0: float) -> dict[str, Awaitable]:
        kill9(pid)
        return {"leader_s": first_true(lambda: leading(rig.standby_url, token), t0, bound),
                "login_s": first_login([rig.standby_url], t0, bound)}
    return f"the leading rce-master (pid {pid})", fire


async def arm_link(rig: Rig, robot: EchoRobot) -> tuple[str, Fire]:
    def fire(t0: float) -> dict[str, Awaitable]:
        rig.proxy.cut(refuse_s=rig.ctx.t.cut)
        return {}
    return f"cut for {rig.ctx.t.cut:g} s: the robot's link through the proxy 127.0.0.1:{rig.proxy.port}", fire


async def arm_robot(rig: Rig, robot: EchoRobot) -> tuple[str, Fire]:
    port = urlsplit(robot.conn.ws_url).port
    k, info = next((k, i) for k, i in enumerate(rig.engine.robot_ready) if i["ws_port"] == port)
    pid = info["pid"]

    def fire(t0: float) -> dict[str, Awaitable]:
        kill9(pid)
        return {}
    return f"rce-robot robot{k} (pid {pid}, the robot's endpoint, port {port})", fire


async def arm_host(rig: Rig, robot: EchoRobot) -> tuple[str, Fire]:
    containers = await asyncio.to_thread(rig.engine.admin, "/api/containers")
    host = next(c["host"] for c in containers if c["ctag"] == CTAG)
    pid = rig.hosts[host].pid

    def fire(t0: float) -> dict[str, Awaitable]:
        kill9(pid)
        return {}
    return f"rce-container {host} (pid {pid}, the container's host)", fire


async def arm_environment(rig: Rig, robot: EchoRobot) -> tuple[str, Fire]:
    import psutil
    stats = await asyncio.to_thread(rig.engine.admin, f"/api/containers/{USER}/{CTAG}/stats")
    pid = (stats.get("environment") or {}).get("pid")
    hosts = {p.pid for name, p in rig.procs().items() if name.startswith("container")}
    try:
        if not pid or not hosts & {q.pid for q in psutil.Process(pid).parents()}:
            raise RuntimeError(f"the container's environment (pid {pid}) is not a process of its host")
    except psutil.Error as e:
        raise RuntimeError(f"the container's environment (pid {pid}) is not running: {e}") from None

    def fire(t0: float) -> dict[str, Awaitable]:
        kill9(pid)
        return {}
    return f"the environment (pid {pid}) running container {CTAG}", fire


ARM = {"master": arm_master, "leader": arm_leader, "link": arm_link, "robot": arm_robot, "host": arm_host,
       "environment": arm_environment}


async def run_rce(ctx: Ctx, fault: str) -> dict:
    """One rce fault on a fresh engine; returns its result (see :data:`FIELDS`)."""
    rig, log, tasks = Rig(ctx, fault), EchoLog(), Tasks(f"faults {fault}")
    ctx.stoppers.append(rig.stop)
    res: dict = {"fault": fault, "system": "rce"}
    robot = probe = None
    try:
        ctx.status(f"{fault} (rce): starting the engine")
        rig.start()
        if fault == "link":
            await rig.start_proxy()
        res["commands"] = rig.commands()
        ctx.status(f"{fault} (rce): the robot builds its container and echoes")
        robot = EchoRobot(log, rig.masters, rig.ws_url)
        await robot.start(ctx.t.setup)
        extra: dict = {"client": "rce_client.Connection reconnects by itself: " + ", ".join(robot.keywords)
                       if robot.library else "rce_client.Connection; the bench reconnects and re-creates"}
        if fault in ("master", "leader"):
            probe = Prober(log, rig.masters)
            extra["new_request_before_s"] = round(await probe.start(ctx.t.setup), 3)
        target, fire = await ARM[fault](rig, robot)
        await asyncio.sleep(ctx.t.pre)                 # steady echo before the fault (a timer)
        watch = ProcWatch(rig.procs(), log, ctx.reaper)
        tasks.spawn(watch.run(), name="watch")
        t0 = time.monotonic()
        log.event(f"fault: {target}", t0)
        measures = {k: tasks.spawn(aw, name=k) for k, aw in fire(t0).items()}
        if probe is not None:
            measures["new_request_s"] = tasks.spawn(probe.first_success(t0, ctx.t.bound), name="probe")
        extra.update(await observe(ctx, log, t0, measures, f"{fault} (rce)"))
        extra["exited"] = {n: [round(t - t0, 3), code, pid] for n, (t, code, pid) in watch.exited.items()}
        extra.update({"proxy": rig.proxy.stats()} if rig.proxy else {})
        res.update(await finish(ctx, log, t0, robot.stop_sending), extra=extra)
    except Exception as e:              # one fault's failure is reported, the others still run
        failed(ctx, res, e)
    finally:
        await tasks.cancel_all()
        for r in (robot, probe):
            if r is not None:
                await r.close()
        if rig.proxy is not None:
            await rig.proxy.close()
        res["commands"] = rig.commands()
        rig.stop()
    return res


# -- ROS 1 -----------------------------------------------------------------------------------------------

ROS1_NODE = '''\
#!/usr/bin/python3
"""ROS 1 (rospy) peer of bench/faults.py, written out by it; stdout lines are read by the bench.

    node.py robot TOPIC RATE_HZ [TCPROS_PORT ADVERTISE_PORT]
        Publishes std_msgs/String str(seq) on TOPIC at RATE_HZ and subscribes TOPIC_echo; prints
        "S seq t" for each message published and "E seq t" for each echo, t = time.monotonic()
        (the machine's CLOCK_MONOTONIC, as the bench's). stdin "STOP": stop publishing; "EXIT" or
        end of stdin: exit. With ADVERTISE_PORT its TCPROS server listens on TCPROS_PORT and tells
        subscribers (requestTopic) to connect to ADVERTISE_PORT: a proxy to it.
    node.py listen TOPIC
        A new subscriber of TOPIC: prints "E seq t" for each message; end of stdin: exit.
"""
import os
import sys
import threading
import time

import rospy
from std_msgs.msg import String

LOCK = threading.Lock()


def emit(*fields):
    with LOCK:
        sys.stdout.write(" ".join(str(f) for f in fields) + "\\n")
        sys.stdout.flush()


def control(stop):
    for line in sys.stdin:
        if line.strip() == "STOP":
            stop.set()
        elif line.strip() == "EXIT":
            break
    os._exit(0)


def main():
    role, topic = sys.argv[1], sys.argv[2]
    tcpros = int(sys.argv[4]) if len(sys.argv) > 4 else 0
    if len(sys.argv) > 5:
        import rospy.impl.tcpros_pubsub as tcpros_pubsub
        real, advertised = tcpros_pubsub.get_tcpros_server_address, int(sys.argv[5])
        tcpros_pubsub.get_tcpros_server_address = lambda: (real()[0], advertised)
    rospy.init_node("faults_" + role, anonymous=True, disable_signals=True, tcpros_port=tcpros)
    stop = threading.Event()
    threading.Thread(target=control, args=(stop,), daemon=True).start()

    def on_message(m):
        emit("E", m.data, time.monotonic())
    if role == "listen":
        rospy.Subscriber(topic, String, on_message, queue_size=100, tcp_nodelay=True)
        threading.Event().wait()
    rospy.Subscriber(topic + "_echo", String, on_message, queue_size=100, tcp_nodelay=True)
    pub = rospy.Publisher(topic, String, queue_size=100, tcp_nodelay=True)
    period, seq, base = 1.0 / float(sys.argv[3]), 0, time.monotonic()
    while not stop.is_set():
        seq += 1
        slot, now = base + seq * period, time.monotonic()
        if now > slot + period:                 # behind by more than a period: no burst to catch up
            base = now - seq * period
        time.sleep(max(0.0, base + seq * period - now))
        t = time.monotonic()
        pub.publish(String(data=str(seq)))
        emit("S", seq, t)
    threading.Event().wait()


if __name__ == "__main__":
    main()
'''


def rosmaster_up(port: int) -> bool:
    """Does rosmaster answer ``getUri`` on ``port``?"""
    body = xmlrpc.client.dumps(("/faults_bench",), "getUri").encode()
    req = urllib.request.Request(f"http://127.0.0.1:{port}/", data=body, headers={"Content-Type": "text/xml"})
    try:
        with urllib.request.urlopen(req, timeout=HTTP_TIMEOUT) as r:
            return xmlrpc.client.loads(r.read())[0][0][0] == 1
    except (OSError, ValueError, xmlrpc.client.Error):
        return False


class Ros1Rig:
    """rosmaster on a free loopback port and the ROS 1 nodes (Debian's python3) of one fault;
    ``commands``: every argv started. :meth:`stop` ends them all."""

    def __init__(self, ctx: Ctx, fault: str):
        self.ctx = ctx
        self.dir = ctx.workdir / f"ros1-{fault}"
        self.dir.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self.env = dict(os.environ, ROS_MASTER_URI=f"http://127.0.0.1:{self.port}", ROS_HOSTNAME="127.0.0.1",
                        ROS_HOME=str(self.dir), ROS_LOG_DIR=str(self.dir / "log"), PYTHONUNBUFFERED="1")
        self.node = self.dir / "faults_node.py"
        self.node.write_text(ROS1_NODE)
        self.procs: dict[str, asyncio.subprocess.Process] = {}
        self.commands: list[str] = []

    async def spawn(self, name: str, argv: list[str], pipes: bool = False) -> asyncio.subprocess.Process:
        """Start ``argv`` (stdout and stderr to ``NAME.log``, or stdin/stdout piped with ``pipes``)."""
        log = open(self.dir / f"{name}.log", "wb")
        pipe = asyncio.subprocess.PIPE
        p = await asyncio.create_subprocess_exec(*argv, stdin=pipe if pipes else subprocess.DEVNULL,
                                                 stdout=pipe if pipes else log, stderr=log, env=self.env,
                                                 start_new_session=True)
        log.close()
        self.procs[name] = p
        self.commands.append(shlex.join(argv))
        return p

    async def start_master(self, name: str = "rosmaster") -> None:
        await self.spawn(name, ["rosmaster", "--core", "-p", str(self.port)])
        deadline = time.monotonic() + self.ctx.t.setup
        while not await asyncio.to_thread(rosmaster_up, self.port):
            if time.monotonic() > deadline or self.procs[name].returncode is not None:
                raise RuntimeError(f"rosmaster did not answer on port {self.port} (see {self.dir / name}.log)")
            await asyncio.sleep(POLL)

    async def stop(self) -> None:
        for p in self.procs.values():
            if p.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    p.terminate()
        for p in self.procs.values():
            try:
                await asyncio.wait_for(p.wait(), NODE_EXIT)
            except asyncio.TimeoutError:
                kill9(p.pid)
                await p.wait()

    def kill(self) -> None:
        """SIGKILL every node still running (the way out after Ctrl-C)."""
        for p in self.procs.values():
            if p.returncode is None:
                kill9(p.pid)


async def read_node(proc: asyncio.subprocess.Process, log: EchoLog) -> None:
    """Fill ``log`` from a ROS 1 node's ``S seq t`` and ``E seq t`` lines."""
    while line := await proc.stdout.readline():
        f = line.split()
        with contextlib.suppress(ValueError, IndexError):
            if f[0] == b"S":
                log.sent[int(f[1])] = float(f[2])
            elif f[0] == b"E":
                log.echo(int(f[1]), float(f[2]))


async def listen(rig: Ros1Rig, name: str, bound: float) -> float | None:
    """A new subscriber of the echo topic: s from its start to its first message; None: none within ``bound``."""
    log, tasks = EchoLog(), Tasks(f"faults {name}")
    t0 = time.monotonic()
    p = await rig.spawn(name, [SYS_PY, str(rig.node), "listen", f"{ROS1_TOPIC}_echo"], pipes=True)
    tasks.spawn(read_node(p, log), name="reader")
    try:
        while not log.echoed and time.monotonic() < t0 + bound:
            await asyncio.sleep(POLL)
    finally:
        await tasks.cancel_all()
        kill9(p.pid)
        await p.wait()
    return min(log.echoed.values()) - t0 if log.echoed else None


async def restart_rosmaster(rig: Ros1Rig, t0: float) -> float:
    await asyncio.sleep(max(0.0, t0 + rig.ctx.t.restart - time.monotonic()))
    await rig.start_master("rosmaster-restarted")
    return time.monotonic() - t0


async def ros1_robot(rig: Ros1Rig, log: EchoLog, tasks: Tasks, proxy: TcpProxy | None,
                     tcpros: int) -> asyncio.subprocess.Process:
    """Start the robot node and the echo node; returns the robot once its first echo is back."""
    ports = [str(tcpros), str(proxy.port)] if proxy else []
    robot = await rig.spawn("robot", [SYS_PY, str(rig.node), "robot", ROS1_TOPIC, f"{RATE_HZ:g}", *ports], pipes=True)
    tasks.spawn(read_node(robot, log), name="robot reader")
    await rig.spawn("echo", [SYS_PY, str(BENCH / "ros1" / "echo.py"), "--type", STRING, "--back", "--report", "60",
                             ROS1_TOPIC])
    deadline = time.monotonic() + rig.ctx.t.setup
    while log.t_start is None:
        if time.monotonic() > deadline or robot.returncode is not None:
            raise RuntimeError(f"no ROS 1 echo within {rig.ctx.t.setup:g} s (see {rig.dir})")
        await asyncio.sleep(POLL)
    return robot


async def run_ros1(ctx: Ctx, fault: str) -> dict:
    """One ROS 1 fault (rosmaster kill -9 and restart, or a cut link); returns its result."""
    rig, log, tasks = Ros1Rig(ctx, fault), EchoLog(), Tasks(f"faults ros1 {fault}")
    ctx.stoppers.append(rig.kill)
    res: dict = {"fault": fault, "system": "ros1"}
    proxy, tcpros, extra = None, free_port(), {}
    try:
        ctx.status(f"{fault} (ROS 1): rosmaster, the robot and the echo node")
        await rig.start_master()
        if fault == "link":
            proxy = await TcpProxy(tcpros).start()
        robot = await ros1_robot(rig, log, tasks, proxy, tcpros)
        if fault == "master":
            ctx.status(f"{fault} (ROS 1): a new subscriber before the fault")
            extra["new_subscriber_before_s"] = await listen(rig, "listen-before", ctx.t.listen)
        await asyncio.sleep(ctx.t.pre)                 # steady echo before the fault (a timer)
        t0 = time.monotonic()
        measures = {}
        if fault == "master":
            kill9(rig.procs["rosmaster"].pid)
            log.event(f"fault: rosmaster (pid {rig.procs['rosmaster'].pid})", t0)
            measures["master_restarted_s"] = tasks.spawn(restart_rosmaster(rig, t0), name="restart")
        else:
            proxy.cut(refuse_s=ctx.t.cut)
            log.event(f"fault: cut for {ctx.t.cut:g} s: the link robot -> echo node through the proxy "
                      f"127.0.0.1:{proxy.port}", t0)
        extra.update(await observe(ctx, log, t0, measures, f"{fault} (ROS 1)"))
        if fault == "master":
            ctx.status(f"{fault} (ROS 1): a new subscriber after the restart")
            extra["new_subscriber_after_s"] = await listen(rig, "listen-after", ctx.t.listen)
        extra.update({"proxy": proxy.stats()} if proxy else {})
        res.update(await finish(ctx, log, t0, lambda: robot.stdin.write(b"STOP\n")), extra=extra)
    except Exception as e:              # one fault's failure is reported, the others still run
        failed(ctx, res, e)
    finally:
        await tasks.cancel_all()
        if proxy is not None:
            await proxy.close()
        await rig.stop()
        res["commands"] = rig.commands
    return res


# -- results: notes, table, plot -------------------------------------------------------------------------

def secs(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


EXTRA_NOTES = (  # key in "extra": what it says when measured, when not ({}: seconds, {bound}: its bound)
    ("master_restarted_s", "master restarted at {} s", "master not restarted"),
    ("leader_s", "the standby leads at {} s", "no standby leads within {bound} s"),
    ("login_s", "login works at {} s", "no login within {bound} s"),
    ("new_request_s", "a new request works at {} s", "no new request works within {bound} s"),
    ("new_subscriber_before_s", "before the fault a new subscriber gets the old publisher's messages in {} s",
     "before the fault a new subscriber gets nothing within {listen} s"),
    ("new_subscriber_after_s", "after the restart a new subscriber gets the old publisher's messages in {} s",
     "after the restart a new subscriber gets nothing within {listen} s (the new master does not know the old "
     "publisher: rospy nodes do not register again)"))
EVENT_NOTES = (("disconnected", "robot disconnected"), ("cannot reconnect", "reconnect refused"),
               ("reconnected", "reconnected"), ("resumed", "resumed"), ("gave up", "the library gave up"),
               ("re-created its container", "robot re-created its session"),
               ("'status': 'exited'", "ST node exited"), ("'status': 'lost'", "ST container lost"),
               ("'status': 'running'", "ST container running"), (" ER ", "first ER"))


def first_event(res: dict, text: str) -> tuple[float, str] | None:
    """The first event at or after the fault whose text has ``text``: (s from the fault, its text)."""
    return next(((t, what) for t, what in res.get("events") or [] if text in what and t >= 0), None)


def notes(res: dict, t: Timing) -> str:
    """One line on what happened: interrupted or not, the extra times, processes that exited, the robot's events."""
    if res.get("error"):
        return f"the bench could not run it: {res['error']}"
    if res.get("skipped"):
        return res["skipped"]
    e, parts = res.get("extra") or {}, []
    gap = res.get("max_gap_s")
    if not res.get("survived"):
        parts.append(f"not served again within {t.bound:g} s")
    elif gap is not None and gap <= 3 / RATE_HZ:
        parts.append(f"never interrupted (longest gap {gap:.2f} s)")
    else:
        parts.append(f"longest gap {secs(gap)} s")
    for key, found, missing in EXTRA_NOTES:
        if key in e:
            parts.append(found.format(secs(e[key])) if e[key] is not None
                         else missing.format(bound=f"{t.bound:g}", listen=f"{t.listen:g}"))
    fault = next((what for at, what in res.get("events") or [] if what.startswith("fault:")), "")
    for name, (at, code, pid) in (e.get("exited") or {}).items():
        if f"(pid {pid}" not in fault:             # the killed process exits as it should
            parts.append(f"{name} exited ({code}) at {at:.2f} s")
    for text, label in EVENT_NOTES:
        ev = first_event(res, text)
        if ev is not None:
            said = f" ({ev[1].split(text, 1)[1][:90]})" if text == " ER " else ""
            parts.append(f"{label} at {ev[0]:.2f} s{said}")
    if res.get("not_sent"):
        parts.append(f"{res['not_sent']} not sent (no link)")
    if res["system"] == "ros1" and res["fault"] == "link" and not res.get("survived"):
        parts.append("rospy's subscriber drops a reset TCPROS connection for good (TransportTerminated) and "
                     "connects again only when the master sends it a publisher update")
    return "; ".join(parts)


def complete(res: dict, t: Timing) -> dict:
    """Every field of :data:`FIELDS` (None where not measured), and the notes."""
    res.setdefault("description", DESCRIPTION[(res["fault"], res["system"])])
    for k in FIELDS:
        res.setdefault(k, None)
    res["notes"] = notes(res, t)
    return res


def served_text(res: dict, t: Timing) -> str:
    if res.get("error"):
        return "error"
    if res.get("skipped"):
        return "skipped"
    return secs(res["served_again_s"]) if res["survived"] else f"not within {t.bound:g}"


def print_table(con, results: list[dict], t: Timing, head: str) -> None:
    from rich.table import Table
    table = Table(title=f"faults: a robot echoing at {RATE_HZ:g} Hz ({head})", show_lines=True)
    table.add_column("fault")
    table.add_column("system")
    table.add_column("served again after (s)", justify="right")
    table.add_column("lost", justify="right")
    table.add_column("notes", overflow="fold")
    for r in results:
        lost = "-" if r["lost"] is None else f"{r['lost']} of {r['measured']}"
        table.add_row(f"{r['fault']}: {r['description']}", r["system"], served_text(r, t), lost, r["notes"])
    con.print(table)


def plot(results: list[dict], path: Path, t: Timing) -> None:
    """For each fault, the echo RTT of every message against when it was generated (0 = the fault),
    rce and ROS 1; lost messages as crosses at the bottom."""
    plt = pyplot()
    from matplotlib.ticker import FuncFormatter
    from matplotlib.transforms import blended_transform_factory
    faults = list(dict.fromkeys(r["fault"] for r in results))
    cols = 2 if len(faults) > 1 else 1
    rows = math.ceil(len(faults) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(7 * cols, 3.2 * rows), squeeze=False)
    colors = {"rce": "tab:blue", "ros1": "tab:orange"}
    for ax, fault in zip(axes.flat, faults, strict=False):
        trans = blended_transform_factory(ax.transData, ax.transAxes)
        for r in (r for r in results if r["fault"] == fault and r.get("timeline")):
            ok = [(x, y) for x, y in r["timeline"] if y is not None and y > 0]
            lost = [x for x, y in r["timeline"] if y is None]
            name = "ROS 1" if r["system"] == "ros1" else "rce"
            served = f"served again after {secs(r['served_again_s'])} s" if r["survived"] else \
                f"not served again within {t.bound:g} s"
            label = f"{name}: {served}, lost {r['lost']} of {r['measured']}"
            if ok:
                ax.plot(*zip(*ok, strict=True), ".", ms=3, color=colors[r["system"]], label=label)
            else:
                ax.plot([], [], ".", color=colors[r["system"]], label=label)
            if lost:
                ax.plot(lost, [0.04 if r["system"] == "rce" else 0.1] * len(lost), "x", ms=4,
                        color=colors[r["system"]], transform=trans)
        ax.axvline(0, color="red", lw=1)
        if fault == "link":
            ax.axvspan(0, t.cut, color="red", alpha=0.08)
        ax.set_yscale("log")
        lo, hi = ax.get_ylim()
        every = hi / lo < 10                          # less than a decade: label every minor tick
        ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, _, every=every: f"{v:g}" if every or f"{v:g}"[0] in "25"
                                                   else ""))
        ax.tick_params(axis="y", which="both", labelsize=7)
        ax.set_title(f"{fault}: {DESCRIPTION[(fault, 'rce')]}", fontsize=9)
        ax.set_xlabel("message generated at, s from the fault (x at the bottom: lost)", fontsize=8)
        ax.set_ylabel("echo RTT, ms", fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
    for ax in list(axes.flat)[len(faults):]:
        ax.set_visible(False)
    fig.suptitle(f"faults: a robot echoing at {RATE_HZ:g} Hz", fontsize=11)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


# -- main --------------------------------------------------------------------------------------------------

DEFINITIONS = {
    "served_again_s": "s from the fault to the first echo, back at the robot, of a message generated after the fault "
                      "(None: not within the bound)",
    "lost": "messages generated from the first echo to the end of sending whose echo never came (exact, by seq)",
    "not_sent": "lost messages generated while the robot had no link (it could not send them)",
    "max_gap_s": "the longest time without an echo, from the last echo before the fault on",
    "timeline": "[s from the fault the message was generated, echo RTT ms or None if lost] per message",
    "events": "[s from the fault, what happened]: the fault, process exits, disconnects, ER and ST the robot got",
    "survived": "served again within the bound",
}


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="short waits (the smoke test): " + str(QUICK))
    p.add_argument("--faults", default=",".join(FAULTS), help=f"comma list, a subset of {','.join(FAULTS)}")
    p.add_argument("--no-ros1", action="store_true", help="skip ROS 1 (no apt-get)")
    p.add_argument("--json", type=Path, default=RESULTS / "faults.json", help="default bench/results/faults.json")
    p.add_argument("--plot", type=Path, default=RESULTS / "faults.png", help="default bench/results/faults.png")
    return p.parse_args(argv)


def client_logging(path: Path) -> None:
    """The engine's client library logs (reconnects, ERs) go to ``path``, not over the progress display."""
    handler = logging.FileHandler(path)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    lg = logging.getLogger("rce")
    lg.addHandler(handler)
    lg.setLevel(logging.INFO)
    lg.propagate = False


def on_sigterm(signum, frame):
    raise KeyboardInterrupt          # the same way out as Ctrl-C: every process stopped


def run_all(ctx: Ctx, runs: list[tuple[str, str]], ros1: tuple[bool, str], prog, task) -> list[dict]:
    results = []
    for fault, system in runs:
        if system == "ros1" and not ros1[0]:
            results.append(complete({"fault": fault, "system": system, "skipped": f"ROS 1 skipped: {ros1[1]}"}, ctx.t))
            prog.advance(task)
            continue
        load = ForeignLoad().start()
        res = asyncio.run((run_rce if system == "rce" else run_ros1)(ctx, fault))
        res["machine_load"] = load.stop()
        results.append(complete(res, ctx.t))
        prog.advance(task)
        served = f"served again after {served_text(res, ctx.t)} s" if res["survived"] else "not served again"
        prog.console.print(f"{fault} ({system}): {served}, lost {res['lost']}; {res['notes']}")
    return results


def main(argv=None) -> int:
    args = parse_args(argv)
    faults = [f for f in args.faults.split(",") if f]
    con = console()
    if not faults or any(f not in FAULTS for f in faults):
        con.print(f"[red]--faults: unknown {[f for f in faults if f not in FAULTS]}; known: {', '.join(FAULTS)}")
        return 2
    t = QUICK if args.quick else FULL
    workdir = Path(tempfile.mkdtemp(prefix="rce-faults-"))
    client_logging(workdir / "client.log")
    con.print(f"work directory (process logs): {workdir}")
    ros1 = (False, "--no-ros1") if args.no_ros1 else ensure_ros1(log=con.print)
    runs = [(f, "rce") for f in faults] + [(f, "ros1") for f in faults if f in ROS1_FAULTS]
    ctx = Ctx(t, workdir, Reaper(), lambda s: None)
    old = signal.signal(signal.SIGTERM, on_sigterm)
    started = datetime.datetime.now(datetime.timezone.utc)
    try:
        with progress(con) as prog:
            task = prog.add_task("faults", total=len(runs))
            ctx.status = lambda s: prog.update(task, description=s)
            results = run_all(ctx, runs, ros1, prog, task)
    except KeyboardInterrupt:
        con.print("[red]interrupted: every process the bench started is stopped; no results written")
        return 130
    finally:
        for stop in reversed(ctx.stoppers):
            with contextlib.suppress(Exception):
                stop()
        left = ctx.reaper.kill_all()
        signal.signal(signal.SIGTERM, old)
    head = git_head()
    data = {"date": started.isoformat(timespec="seconds"), "commit": head, "command": shlex.join(sys.argv),
            "cwd": str(ROOT), "quick": args.quick, "timing": asdict(t), "rate_hz": RATE_HZ,
            "ros1": {"ok": ros1[0], "reason": ros1[1]}, "workdir": str(workdir), "definitions": DEFINITIONS,
            "machine_load": {f"{r['fault']}/{r['system']}": r.pop("machine_load", None) for r in results},
            "processes_killed_at_exit": left, "results": results}
    write_json(args.json, data)
    print_table(con, results, t, f"{head}; {'--quick' if args.quick else 'full'} run")
    plot(results, args.plot, t)
    con.print(f"results: {args.json}  plot: {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
