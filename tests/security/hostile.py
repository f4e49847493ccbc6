"""What the hostile-input engine tests share (tests/security/test_hostile_input.py, test_fuzz.py):
a victim robot that echoes through its own container, and the robot task set's RSS."""
from __future__ import annotations

import asyncio
import itertools
import time

import psutil

from echo import echo_interfaces
from wsclient import RawRobot


PROBE = "ready? "       # what warm-up probes' data starts with


async def echo_ready(r: RawRobot, ctag: str, timeout: float = 60.0, group: str | None = None) -> None:
    """Give robot ``r`` a container ``ctag`` (in ``group``, if given) running stringEcho.py, its
    ``req``/``resp`` converters connected; return once an echo came back (the node subscribes a
    moment after the interfaces are up)."""
    await r.send("CC", {"containerTag": ctag, **({"containerData": {"group": group}} if group else {})})
    await r.cn(addNodes=[{"containerTag": ctag, "nodeTag": "echo", "pkg": "Test", "exe": "stringEcho.py"}],
               addInterfaces=echo_interfaces(ctag, r.robot))
    await r.send("CX", {"connect": [{"tagA": f"{ctag}/{t}", "tagB": f"{r.robot}/{t}"} for t in ("req", "resp")]})
    await r.wait_up("req", "resp", timeout=timeout)
    await echo_probe(r, timeout)


async def echo_probe(r: RawRobot, timeout: float = 60.0) -> None:
    """Return once an echo came back through robot ``r``'s echo container (``req``/``resp``),
    probing every 0.5 s; TimeoutError after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    for n in itertools.count(1):
        probe = f"{PROBE}{n}"       # numbered: an earlier probe's late echo is not taken for this one
        await r.send("DM", {"iTag": "req", "type": "std_msgs/String", "msgID": "", "msg": {"data": probe}})
        try:
            await r.expect("DM", timeout=0.5, pred=lambda d, p=probe: d["iTag"] == "resp" and d["msg"]["data"] == p)
            return
        except TimeoutError:
            if time.monotonic() > deadline:
                raise


def _not_a_probe(d: dict) -> bool:
    """An echo on ``resp`` that is not a warm-up probe's (:func:`echo_probe`). A probe sent while
    the direct route to the node was being set up may come back after a later one (a message on
    the new path can overtake one on the old: docs/INTERNALS.md, direct links), so one can arrive
    after the warm-up has returned."""
    return d["iTag"] == "resp" and not d["msg"]["data"].startswith(PROBE)


class Echoer:
    """Robot ``r`` sends numbered strings through its echo container, one at a time, until
    :meth:`stop`; every echo must come back, in order (else :attr:`failure`). :attr:`rtts`: s each."""

    def __init__(self, r: RawRobot, timeout: float = 20.0):
        self.r, self.timeout = r, timeout
        self.sent = 0
        self.rtts: list[float] = []
        self.failure: str | None = None
        self._stop = asyncio.Event()
        self._task: asyncio.Task | None = None

    def start(self) -> "Echoer":
        self._task = asyncio.ensure_future(self._run())
        return self

    async def _run(self) -> None:
        while not self._stop.is_set():
            self.sent += 1
            want = f"{self.r.robot}-{self.sent}"
            t = time.monotonic()
            await self.r.send("DM", {"iTag": "req", "type": "std_msgs/String", "msgID": "", "msg": {"data": want}})
            try:
                dm = await self.r.expect("DM", timeout=self.timeout, pred=_not_a_probe)
            except TimeoutError:
                self.failure = f"echo {want} did not come back within {self.timeout} s"
                return
            if dm["msg"]["data"] != want:
                self.failure = f"echo {want} came back as {dm['msg']['data']!r} (out of order)"
                return
            self.rtts.append(time.monotonic() - t)

    async def stop(self) -> None:
        """Stop after the echo in flight; raise AssertionError if one was lost or out of order."""
        self._stop.set()
        await self._task
        assert self.failure is None, self.failure
        assert self.rtts, "no echo came back"


def rss(pid: int) -> int:
    """Resident set size of process ``pid``, bytes."""
    return psutil.Process(pid).memory_info().rss


class PeakRss:
    """The highest RSS of process ``pid`` (bytes), sampled every ``period`` s between :meth:`start`
    and :meth:`stop` (which returns it)."""

    def __init__(self, pid: int, period: float = 0.05):
        self.proc, self.period, self.peak = psutil.Process(pid), period, 0
        self._task: asyncio.Task | None = None

    def start(self) -> "PeakRss":
        self.peak = self.proc.memory_info().rss
        self._task = asyncio.ensure_future(self._run())
        return self

    async def _run(self) -> None:
        while True:
            self.peak = max(self.peak, self.proc.memory_info().rss)
            await asyncio.sleep(self.period)      # a sampling period, not a synchronisation

    async def stop(self) -> int:
        self._task.cancel()
        await asyncio.gather(self._task, return_exceptions=True)
        self.peak = max(self.peak, self.proc.memory_info().rss)
        return self.peak


async def still_served(r: RawRobot, token: str = "alive") -> None:
    """Prove robot ``r``'s session is still served even when its bad-input ERs are rate-limited: a
    request (a CX between interfaces that cannot exist) is answered by an ER naming them."""
    await r.send("CX", {"connect": [{"tagA": f"{token}/a", "tagB": f"{token}/b"}]})
    await r.expect("ER", timeout=60, pred=lambda d: f"{token}/a" in d)
