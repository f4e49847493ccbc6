"""Containers outlive their host. Real processes on loopback: a master, a robot
task set and two container hosts; a robot echoes ``std_msgs/String`` at 10 Hz through converters
to the Test package's ``stringEcho.py`` in its container.

- kill -9 of the container's host: the robot sees ST lost, then running (the container
  re-created on the other host with its node, parameter, interfaces and connections) within
  10 s of the kill, and the echo resumes; the messages lost all fall in the gap.
- kill -9 of the container's environment process: reported (ST lost, an ER naming the signal,
  ``iu false``), re-created on its own host, the echo resumes.
- a silent host (SIGSTOP): the master's keepalive marks it lost, and the container runs on the
  other host within 10 s of that verdict; the host, woken, re-registers and its stale copy is
  dropped.

Each test prints its figures (``pytest -s``): kill -> running, kill -> first echo, messages lost.
"""
from __future__ import annotations

import asyncio
import os
import signal
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager, suppress
from pathlib import Path
from typing import Any

import psutil
import pytest

from rce.tools.launch import Engine, start_engine
from test_dataflow import _echo_container
from wsclient import RawRobot

pytestmark = pytest.mark.asyncio

RATE = 10.0             # Hz, the robot's echo requests (the rate of the faults bench)
RECREATE_BOUND = 10.0   # s, the promise: running again within 10 s of the loss being seen
SILENCE_BOUND = 6.0     # s, the keepalive verdict on a silent host: rce.transport.rpc.KEEPALIVE_TIMEOUT (4 s),
                        # checked every KEEPALIVE_INTERVAL (1 s), plus scheduling on a busy machine
WAIT = 30.0             # s, the most a test waits for a step that normally takes well under that
STEADY = 10             # echoes before the fault: the node is subscribed, messages flow
IN_FLIGHT = 0.5         # s before the fault: a message sent then may still be lost with the host
CTAG = "echoC"


@pytest.fixture
def engine(tmp_path: Path):
    """Master, robot task set, two container hosts."""
    e = start_engine(tmp_path / "engine", container_hosts=2)
    yield e
    e.stop()


class EchoRobot:
    """A robot whose container echoes what it sends: ``run()`` sends ``DM req`` with a sequence
    number at :data:`RATE` and keeps every frame it receives, stamped (monotonic s)."""

    def __init__(self, r: RawRobot):
        self.r = r
        self.sent: dict[int, float] = {}          # seq -> when sent
        self.echoed: dict[int, float] = {}        # seq -> when its echo came back
        self.events: list[tuple[float, str, Any]] = []     # (t, type, data) of every ST and ER
        self._changed = asyncio.Event()

    async def build(self) -> None:
        """The container with stringEcho and converters, connected (as in test_dataflow), and a parameter."""
        await _echo_container(self.r, CTAG, "Converter")
        await self.r.cn(setParam=[{"containerTag": CTAG, "name": "echoParam", "value": 42}])

    async def run(self) -> None:
        """Send at RATE and read everything, until cancelled."""
        async with asyncio.TaskGroup() as tg:
            tg.create_task(self._send())
            tg.create_task(self._read())

    async def _send(self) -> None:
        seq = 0
        while True:
            await self.r.send("DM", {"iTag": "req", "type": "std_msgs/String", "msgID": "", "msg": {"data": str(seq)}})
            self.sent[seq] = time.monotonic()
            seq += 1
            await asyncio.sleep(1 / RATE)          # the rate, not a wait for something to happen

    async def _read(self) -> None:
        while True:
            m = await self.r.recv(timeout=3600)
            if not isinstance(m, dict):
                continue
            now = time.monotonic()
            if m["type"] == "DM" and m["data"]["iTag"] == "resp":
                self.echoed.setdefault(int(m["data"]["msg"]["data"]), now)
            elif m["type"] in ("ST", "ER"):
                self.events.append((now, m["type"], m["data"]))
            self._changed.set()

    async def until(self, what: str, pred: Callable[[], Any], timeout: float = WAIT) -> Any:
        """Wait until ``pred()`` is true (checked on every frame received); returns its value."""
        deadline = time.monotonic() + timeout
        while not (got := pred()):
            self._changed.clear()
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"not within {timeout:g} s: {what}; events: {self.events}")
            try:
                await asyncio.wait_for(self._changed.wait(), left)
            except TimeoutError:
                pass
        return got

    def event(self, type_: str, pred: Callable[[Any], bool], after: float) -> tuple[float, Any] | None:
        """The first ST/ER of ``type_`` after ``after`` (monotonic s) whose data satisfies ``pred``."""
        return next(((t, d) for t, ty, d in self.events if ty == type_ and t > after and pred(d)), None)

    def container_event(self, status: str, after: float):
        return self.event("ST", lambda d: d.get("topic") == "container" and d.get("status") == status, after)

    def iu(self, itag: str, up: bool, after: float):
        return self.event("ST", lambda d: d.get("topic") == "iu" and d["iTag"] == itag and d["status"] is up, after)

    def first_echo_sent_after(self, t: float) -> float | None:
        """When the first echo of a message sent after ``t`` came back."""
        return min((at for seq, at in self.echoed.items() if self.sent[seq] > t), default=None)


def host_of(engine: Engine, ctag: str = CTAG) -> tuple[psutil.Process, psutil.Process]:
    """(the container host process, the environment process) serving ``ctag``, found through the
    admin API's stats (the environment's pid) and its ancestors (the host, or the host's
    environment template, whose parent is the host)."""
    env = psutil.Process(engine.admin(f"/api/containers/testUser/{ctag}/stats")["environment"]["pid"])
    host = next(p for p in env.parents() if any("rce-container" in a for a in p.cmdline()))
    return host, env


@asynccontextmanager
async def echoing(engine: Engine, robot: str) -> AsyncIterator[EchoRobot]:
    """Robot ``robot`` connected, its container built, its echo flowing (:class:`EchoRobot`)."""
    async with RawRobot(engine.master_url, robot) as r:
        echo = EchoRobot(r)
        await echo.build()
        task = asyncio.get_running_loop().create_task(echo.run())
        try:
            await echo.until(f"{STEADY} echoes", lambda: len(echo.echoed) >= STEADY)
            yield echo
        finally:
            task.cancel()
            with suppress(asyncio.CancelledError):
                await task


async def lost_and_back(echo: EchoRobot, t_fault: float, why: str) -> tuple[float, float, float]:
    """After a fault at ``t_fault`` (monotonic s): ST lost, an ER saying ``why``, each robot-side
    interface down and up again, ST running within RECREATE_BOUND s of the loss, and the echo
    again. Returns when the robot saw the loss, saw it running, and got the first echo again."""
    t_lost, _ = await echo.until("ST lost", lambda: echo.container_event("lost", t_fault))
    t_running, st = await echo.until("ST running", lambda: echo.container_event("running", t_lost))
    t_echo = await echo.until("the echo again", lambda: echo.first_echo_sent_after(t_lost))
    assert t_running - t_lost < RECREATE_BOUND and st["sandbox"] in ("namespaced", "unconfined")
    er = echo.event("ER", lambda d: CTAG in d, t_fault)[1]
    assert er == f"container '{CTAG}' was lost: {why}; it is being re-created"
    for itag in ("req", "resp"):
        down = echo.iu(itag, False, t_fault)
        assert down and echo.iu(itag, True, down[0]), f"{itag}: iu false, then true"
    return t_lost, t_running, t_echo


def report(name: str, echo: EchoRobot, t_fault: float, t_seen: float, t_running: float, t_echo: float) -> int:
    """Print the figures; return how many messages were lost (from the first echoed one to the
    last), after checking they all fall in the gap: sent between IN_FLIGHT s before the fault
    and the first echo after it."""
    first, last = min(echo.echoed), max(echo.echoed)
    lost = [seq for seq in echo.sent if first <= seq <= last and seq not in echo.echoed]
    print(f"\n{name}: loss seen after {t_seen - t_fault:.2f} s, running again after {t_running - t_fault:.2f} s "
          f"({t_running - t_seen:.2f} s after the loss was seen), echo after {t_echo - t_fault:.2f} s; "
          f"{len(lost)} of {last - first + 1} messages lost")
    outside = [seq for seq in lost if not t_fault - IN_FLIGHT <= echo.sent[seq] <= t_echo]
    assert outside == [], f"messages lost outside the gap: {outside}"
    assert len(lost) <= (t_echo - t_fault + IN_FLIGHT) * RATE + 1
    return len(lost)


async def test_kill_9_of_the_host_re_creates_the_container_on_the_other_host(engine):
    async with echoing(engine, "failBot") as echo:
        host, _ = host_of(engine)
        before = next(c for c in engine.admin("/api/containers") if c["ctag"] == CTAG)
        t_kill = time.monotonic()
        os.kill(host.pid, signal.SIGKILL)
        t_lost, t_running, t_echo = await lost_and_back(echo, t_kill, "its host went away")
        assert t_running - t_kill < RECREATE_BOUND
        report("kill -9 of the container host", echo, t_kill, t_lost, t_running, t_echo)
        new_host, _ = host_of(engine)
        assert new_host.pid != host.pid
        s = engine.admin("/api/state")
        c = next(c for c in s["containers"] if c["ctag"] == CTAG)
        assert c["state"] == "running" and c["cid"] > before["cid"]
        assert [p["value"] for p in s["parameters"] if p["ctag"] == CTAG] == [42]
        assert [n["status"] for n in s["nodes"] if n["ctag"] == CTAG] in (["running"], ["started"])
        assert len([x for x in s["connections"] if x["tagA"].startswith(CTAG) or x["tagB"].startswith(CTAG)]) == 3


async def test_kill_9_of_the_environment_re_creates_it_on_its_own_host(engine):
    async with echoing(engine, "envBot") as echo:
        host, env = host_of(engine)
        t_kill = time.monotonic()
        env.kill()
        t_lost, t_running, t_echo = await lost_and_back(echo, t_kill, "its environment was killed by SIGKILL")
        assert t_running - t_kill < RECREATE_BOUND
        report("kill -9 of the environment", echo, t_kill, t_lost, t_running, t_echo)
        same_host, new_env = host_of(engine)
        assert same_host.pid == host.pid and new_env.pid != env.pid


async def test_a_silent_host_s_container_runs_on_the_other_host(engine):
    async with echoing(engine, "quietBot") as echo:
        host, _ = host_of(engine)
        t_stop = time.monotonic()
        host.suspend()                               # SIGSTOP: the socket stays open, nothing is sent
        try:
            t_lost, t_running, t_echo = await lost_and_back(echo, t_stop, "its host went away")
        finally:
            host.resume()
        assert t_lost - t_stop < SILENCE_BOUND
        report("a silent host (SIGSTOP)", echo, t_stop, t_lost, t_running, t_echo)
        assert host_of(engine)[0].pid != host.pid
        # the host, woken, registers again and drops its stale copy; the echo goes on meanwhile
        log = engine.workdir / f"container{_index(engine, host.pid)}.log"
        await echo.until("the woken host drops its copy",
                         lambda: "the master does not have this container: destroying it" in log.read_text(),
                         timeout=WAIT)
        n = len(echo.echoed)
        await echo.until("more echoes", lambda: len(echo.echoed) >= n + 5)
        hosts = [t for t in engine.admin("/api/tasksets") if t["kind"] == "container"]
        assert len(hosts) == 2 and not any(t["absent"] for t in hosts)
        assert [c["state"] for c in engine.admin("/api/containers")] == ["running"]


def _index(engine: Engine, pid: int) -> int:
    """The n of the ``container{n}`` log of the host process ``pid``."""
    hosts = [p for p in engine.procs if any("rce-container" in str(a) or "rce_container" in str(a) for a in p.args[:3])]
    return next(i for i, p in enumerate(hosts) if p.pid == pid)
