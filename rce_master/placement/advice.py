"""The placer at work in the master: its measured inputs, its advice and a user's pin.

Inputs, all measured (:mod:`rce_master.placement.placer` is the model):

- hosts: each container host's zone and cores (registered), and the cores its containers asked for;
- links: each robot's round trip and delivery rate, as its robot endpoint's kernel measures them on
  the robot's websocket (``robot_link``, :mod:`rce_robot.link_report`); a shared zone's option of a
  robot's container uses that robot's link;
- containers: every :data:`POLL` s the host's counters of each container that asked for a placement
  (CC ``containerData``): its CPU use, and over its interfaces the messages it sends (its results)
  and the bytes in and out; the work per result is CPU seconds over results;
- batteries: a robot's charge (per cent) reported to ``POST /api/robots/{user}/{robot}/battery``
  (e.g. by the fleet from ``sensor_msgs/BatteryState``); below ``battery_low`` per cent, saving the
  robot's energy wins.

A container that asks for a spare (``spare: true``) is kept one on the host the placer ranks next
after the one it runs on (:func:`rce_master.placement.placer.runner_up`;
:mod:`rce_master.placement.mover`, Spares): made
when it has none and what it is made from has not changed for :data:`SPARE_SETTLE_S` s, kept while
that host may run it (a spare does not follow every turn of the
ranking: its make costs the host), destroyed when the container is pinned, is removed or asks no
more; a lost container's spare becomes it (:mod:`rce_master.failover`).

Every change of the placer's word on a container is logged with its inputs (``placement``). The
admin API's ``GET /api/placement`` gives, per container, where it runs, where the placer would put
it and why; ``POST /api/placement/{user}/{ctag}`` ``{"pin": "cloud"|"edge"|"robot"|"auto"}`` pins it
(``auto`` unpins), and a new or re-created container is placed in its pinned zone.
"""
from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass, field

from rce.plumbing.errors import RCEError, RequestError
from rce.plumbing.log import get_logger
from rce.protocol.schema import PLACEMENTS
from rce_master.state.lifecycle import ContainerState
from rce_master.state.model import ContainerRec
from rce_master.placement.mover import Mover
from rce_master.placement.placer import Choice, ContainerView, HostView, LinkView, Placer, late_share, runner_up
from rce_master.state.master_state import NEED_KEYS, MasterState

__all__ = ["BATTERY_LOW", "POLL", "Placement"]

log = get_logger("rce.master.placement")

POLL = 0.5            # s between looks at the containers' counters
MOVES_KEPT = 100      # moves kept for GET /api/placement/moves
BATTERY_LOW = 20.0    # per cent
WARMUP = 3.0          # s a container's copy runs before its results count for the placer (its first results are
                      # slow: imports, first calls): its late share and its measured median
MARKS_KEPT_S = 120.0  # s of a copy's counters kept for its late share (placer.late_share)
SPARE_RETRY_S = 10.0  # s after a spare's make failed before another is made
SPARE_SETTLE_S = 2.0  # s what a container is made from must stay the same before a spare of it is made (a robot
                      # sets a container up in several requests: a spare made between them would be made again)


@dataclass
class _Use:
    """A container's counters at ``t`` (monotonic s), and the rates derived from the last two looks."""
    t: float
    cpu_s: float
    msgs_out: int
    bytes_in: int
    bytes_out: int
    work_ms: float = 0.0
    rate_hz: float = 0.0
    in_bytes: float = 0.0
    out_bytes: float = 0.0
    results: int = 0                 # results its nodes timed (rce.node.results), and how many were late
    misses: int = 0
    node_ms: float | None = None     # p50 of its nodes' latency over the last seconds, where it runs now
    miss_rate: float | None = None   # the share of its results that missed its deadline, as it persisted
    since: float = 0.0               # monotonic s of the first look at this copy
    cid: int | None = None           # the copy these counters are of (a move makes a new one)
    marks: list[tuple[float, int, int]] = field(default_factory=list)   # (t, results, misses) after its warm-up


def asks_placement(data: dict) -> bool:
    """Whether a container's containerData asks the placer anything (a placement key or a pin)."""
    return any(k in data for k in ("placement", "pinned", *NEED_KEYS))


def pinned_to(data: dict) -> str | None:
    """The zone kind a container's containerData pins it to (a user's pin, or a placement other than
    ``auto``), None when the placer places it."""
    return data.get("pinned") or (data.get("placement") if data.get("placement") not in (None, "auto") else None)


class Placement:
    """The placer's inputs and advice for the master's ``state``; ``host_stats(container)`` awaits a
    container's counters from its host (the ``stats`` op)."""

    def __init__(self, state: MasterState, host_stats, placer: Placer | None = None,
                 battery_low: float = BATTERY_LOW, mover: Mover | None = None):
        self.state, self.host_stats, self.mover = state, host_stats, mover
        self.moves: list[dict] = []               # the last MOVES_KEPT moves: {t, user, ctag, from, to, gap_s, why}
        self._moving: dict[tuple[str, str], asyncio.Task] = {}
        self.placer = placer or Placer()
        self.battery_low = battery_low
        self.links: dict[tuple[str, str], LinkView] = {}
        self.batteries: dict[tuple[str, str], float] = {}
        self.use: dict[tuple[str, str], _Use] = {}
        self.last_word: dict[tuple[str, str], tuple] = {}
        self.decisions = 0
        self._changed = asyncio.Event()           # a robot's link or battery changed: decide again now
        self._spare_failed: dict[tuple[str, str], float] = {}   # when a container's spare was first seen failed
        self._basis: dict[tuple[str, str], tuple[str, float]] = {}   # what it is made from, and since when

    # -- inputs ------------------------------------------------------------------------------------
    def robot_link(self, user: str, robot: str, rtt_ms: float, rate: float) -> None:
        """A robot's measured link: round trip ``rtt_ms``, delivery rate ``rate`` bytes/s (0: not
        measured now). A rate once measured is kept while the reports say 0 (a link that carries
        nothing is as thin as it was last measured, until a fresh measure says otherwise); a link
        never measured counts by its round trip alone."""
        old = self.links.get((user, robot))
        if rate and rate > 0:
            r = float(rate)
        else:
            r = old.rate if old is not None else float("inf")
        self.links[(user, robot)] = LinkView(float(rtt_ms), r)
        self._changed.set()

    def robot_battery(self, user: str, robot: str, percent: float) -> None:
        """A robot's charge, per cent (0-100). Raises :class:`RequestError` for another value."""
        if not isinstance(percent, (int, float)) or isinstance(percent, bool) or not 0 <= percent <= 100:
            raise RequestError(f"battery of robot {robot!r}: 'percent' must be a number from 0 to 100, got {percent!r}")
        self.batteries[(user, robot)] = float(percent)
        self._changed.set()

    def pin(self, user: str, ctag: str, zone: str) -> ContainerRec:
        """Pin container ``user/ctag`` to zone kind ``zone`` (``auto``: unpin). Raises
        :class:`RequestError` for an unknown zone, :class:`~rce.plumbing.errors.NotFound` for an
        unknown container."""
        if zone not in PLACEMENTS:
            raise RequestError(f"pin: zone must be one of {', '.join(PLACEMENTS)}, got {zone!r}")
        c = self.state.container(user, ctag)
        if zone == "robot" and not c.data.get("robot"):
            raise RequestError(f"pin: container {ctag!r} names no robot it serves (containerData 'robot')")
        data = {k: v for k, v in c.data.items() if k != "pinned"}
        if zone != "auto":
            data["pinned"] = zone
        self.state.set_container_data(c, data)
        log.info("placement pinned", user=user, ctag=ctag, zone=zone)
        return self.state.container(user, ctag)

    async def poll(self) -> None:
        """Read the counters of every running container that asks for a placement, once."""
        for c in list(self.state.containers.values()):
            if c.state != ContainerState.RUNNING or not asks_placement(c.data):
                continue
            try:
                s = await self.host_stats(c)
            except RCEError:
                continue
            self._count(c, s, time.monotonic())

    def _count(self, c: ContainerRec, s: dict, now: float) -> None:
        cpu_s = float(s.get("cpu_seconds") or 0.0)
        res = s.get("results") or {}
        new = _Use(now, cpu_s, int(s.get("msgs_out") or 0), int(s.get("bytes_in") or 0), int(s.get("bytes_out") or 0),
                   results=int(res.get("results") or 0), misses=int(res.get("misses") or 0),
                   node_ms=res.get("recent_p50_ms"), cid=c.cid)
        old = self.use.get((c.user, c.ctag))
        if old is not None and old.cid != c.cid:
            old = None                    # a new copy (a move's switch): its record starts afresh
        new.since = old.since if old is not None else now
        if now - new.since < WARMUP:
            new.node_ms = None            # its first results are slow: they say nothing of the host
        else:
            new.marks = [m for m in (old.marks if old is not None else []) if now - m[0] <= MARKS_KEPT_S]
            new.marks.append((now, new.results, new.misses))
        new.miss_rate = late_share(new.marks)
        if old is not None and now > old.t:
            dt = now - old.t
            outputs = new.results - old.results if new.results > old.results else new.msgs_out - old.msgs_out
            new.rate_hz = max(0, outputs) / dt
            new.in_bytes = max(0, new.bytes_in - old.bytes_in) / dt
            new.out_bytes = max(0, new.bytes_out - old.bytes_out) / dt
            busy = max(0.0, cpu_s - old.cpu_s) / dt                 # cores
            new.work_ms = 1e3 * busy / new.rate_hz if new.rate_hz > 0 else old.work_ms
        self.use[(c.user, c.ctag)] = new

    # -- the placer's word --------------------------------------------------------------------------
    def hosts(self) -> list[HostView]:
        return [HostView(t.tid, t.name, t.zone, float((t.info.get("capacity") or {}).get("cpu") or 0), t.cpu_load)
                for t in self.state.tasksets.values() if t.kind == "container" and not t.lost]

    def word(self, c: ContainerRec, now: float | None = None) -> Choice | None:
        """The placer's choice for ``c`` (None: it asked for no placement); logs a change."""
        if not asks_placement(c.data):
            return None
        now = time.monotonic() if now is None else now
        d = c.data
        robot = d.get("robot")
        u = self.use.get((c.user, c.ctag))
        here = u is not None and u.cid == c.cid     # its record is of the copy that runs now (not one just moved)
        view = ContainerView(c.user, c.ctag, robot, d.get("deadline_ms"), u.work_ms if u else 0.0,
                             u.rate_hz if u else 0.0, u.in_bytes if u else 0.0, u.out_bytes if u else 0.0,
                             float(d.get("cpu") or 0), u.node_ms if here else None, u.miss_rate if here else None)
        link = self.links.get((c.user, robot)) if robot else None
        unmeasured = robot is not None and link is None     # its robot's link is not measured yet
        links = {"cloud": link, "edge": link} if link is not None else {"cloud": LinkView(0, float("inf")),
                                                                        "edge": LinkView(0, float("inf"))}
        low = self._low(c)
        ch = self.placer.decide(now, view, self.hosts(), links, c.tid, low)
        if unmeasured and ch.move:
            ch = Choice(ch.target, ch.current, False, f"robot {robot}'s link is not measured yet; {ch.why}",
                        ch.options)
        pinned = pinned_to(d)
        if pinned:
            how = "user pin" if d.get("pinned") else "its placement"
            ch = Choice(ch.target, ch.current, False, f"pinned to {pinned} ({how}); the placer would say: {ch.why}",
                        ch.options)
        key = (c.user, c.ctag)
        mark = (ch.target.tid if ch.target else None, ch.move, bool(pinned))
        if self.last_word.get(key) != mark:
            self.last_word[key] = mark
            self.decisions += 1
            log.info("placement", user=c.user, ctag=c.ctag, runs=ch.current.zone if ch.current else None,
                     best=ch.target.zone if ch.target else None, move=ch.move, why=ch.why,
                     link_rtt_ms=link.rtt_ms if link else None, link_rate=link.rate if link else None,
                     work_ms=round(view.work_ms, 2), rate_hz=round(view.rate_hz, 2), in_bytes=round(view.in_bytes),
                     node_ms=view.node_ms, miss_rate=view.miss_rate, misses=u.misses if u else 0,
                     battery=self.batteries.get((c.user, robot)) if robot else None)
        return ch

    def _low(self, c: ContainerRec) -> bool:
        """Whether the robot ``c`` serves is below the battery threshold."""
        robot = c.data.get("robot")
        return robot is not None and self.batteries.get((c.user, robot), 100.0) < self.battery_low

    def advice(self) -> list[dict]:
        """Per container: where it runs, where the placer would put it and why (``GET /api/placement``)."""
        ts = self.state.tasksets
        rows = []
        for c in sorted(self.state.containers.values(), key=lambda c: (c.user, c.ctag)):
            here = ts.get(c.tid)
            runs = f"{str(here.zone)} ({here.name})" if here is not None else "(lost)"
            ch = self.word(c)
            if ch is None:
                rows.append({"user": c.user, "ctag": c.ctag, "runs": runs, "best": "-", "move": False,
                             "pinned": None, "why": "asks no placement: on the least loaded shared host"})
                continue
            best = f"{ch.target.zone} ({ch.target.host})" if ch.target else "-"
            u = self.use.get((c.user, c.ctag))
            sp = self.mover.spare_of(c.user, c.ctag) if self.mover is not None else None
            spare = None
            if sp is not None and sp[0] in ts:
                spare = f"{str(ts[sp[0]].zone)} ({ts[sp[0]].name})" + ("" if sp[1] else ", being made")
            rows.append({"user": c.user, "ctag": c.ctag, "runs": runs, "best": best, "move": ch.move,
                         "pinned": c.data.get("pinned"), "spare": spare, "why": ch.why, **ch.to_json(),
                         "results": u.results if u else 0, "misses": u.misses if u else 0,
                         "node_ms": u.node_ms if u else None,
                         "battery": self.batteries.get((c.user, c.data["robot"])) if c.data.get("robot") else None,
                         "battery_low": self._low(c)})
        return rows

    async def move(self, c: ContainerRec, tid: int, why: str, drain_max: float | None = None) -> dict:
        """Move ``c`` to host ``tid`` now (:class:`~rce_master.placement.mover.Mover`; ``drain_max``: s its old
        copy may wait for its fences at most, default the mover's); the move's record.
        Raises :class:`~rce_master.placement.mover.MoveFailed` (it runs where it was) or :class:`RequestError`."""
        if self.mover is None:
            raise RequestError("this master moves no containers")
        names = {t.tid: f"{t.zone} ({t.name})" for t in self.state.tasksets.values()}
        r = await self.mover.move(c.user, c.ctag, tid, why, drain_max)
        self.placer.moved(time.monotonic(), c.user, c.ctag)
        self.use.pop((c.user, c.ctag), None)         # the new copy's counters start from 0
        rec = {"t": time.time(), "user": c.user, "ctag": c.ctag, "from": names.get(r.from_tid, str(r.from_tid)),
               "to": names.get(r.to_tid, str(r.to_tid)), "make_s": round(r.make_s, 3),
               "switch_s": round(r.switch_s, 4), "drain_s": round(r.drain_s, 3), "make_steps": r.make_steps,
               "spare": r.spare, "states": r.states,
               "fenced": r.fenced, "unfenced": r.unfenced, "why": why}
        self.moves = [*self.moves[-(MOVES_KEPT - 1):], rec]
        return rec

    def _carry_out(self, c: ContainerRec, ch: Choice) -> None:
        """Start the move the placer asked for, unless one of ``c`` runs."""
        key = (c.user, c.ctag)
        task = self._moving.get(key)
        if self.mover is None or (task is not None and not task.done()):
            return

        async def run() -> None:
            try:
                await self.move(c, ch.target.tid, ch.why)
            except RCEError as e:
                log.warning("placer's move not made", user=c.user, ctag=c.ctag, reason=str(e))
                self.placer.moved(time.monotonic(), c.user, c.ctag)      # no retry within the dwell
        self._moving[key] = asyncio.get_running_loop().create_task(run(), name=f"move {c.user}/{c.ctag}")

    def _decide(self) -> float:
        """Decide on every container, start the moves the placer asks for and keep the spares
        asked for; returns s until a pending move's hysteresis ends (inf: none pending)."""
        due = float("inf")
        for c in list(self.state.containers.values()):
            ch = self.word(c)
            if ch is not None and ch.move and c.state == ContainerState.RUNNING:
                self._carry_out(c, ch)
            elif ch is not None and ch.wait_s > 0:
                due = min(due, ch.wait_s)
            if ch is not None:
                self._keep_spare(c, ch)
        if self.mover is not None:
            for user, ctag in list(self.mover.spares):
                if (user, ctag) not in self.state.containers:
                    self.mover.drop_spare(user, ctag)
            for kept in (self._spare_failed, self._basis):
                for key in [k for k in kept if k not in self.state.containers]:
                    del kept[key]
        return due

    def _keep_spare(self, c: ContainerRec, ch: Choice) -> None:
        """Make ``c`` a spare on the host ranked next (:func:`runner_up`) when it runs, asks for one and
        has none; drop the one it has when it asks no more, is pinned, or the spare no longer holds.
        A lost container's spare is left to its failover (:meth:`rce_master.placement.mover.Mover.claim_spare`)."""
        if self.mover is None or c.state != ContainerState.RUNNING:
            return
        key = (c.user, c.ctag)
        wants = bool(c.data.get("spare")) and not pinned_to(c.data)
        if not wants or self.mover.spare_stale(c):
            if key in self.mover.spares:
                self.mover.drop_spare(c.user, c.ctag)
            return
        task = self._moving.get(key)
        if task is not None and not task.done():
            return
        if self.mover.spare_failed(c.user, c.ctag):
            if time.monotonic() - self._spare_failed.setdefault(key, time.monotonic()) < SPARE_RETRY_S:
                return
            self._spare_failed.pop(key, None)
        elif key in self.mover.spares:
            return
        basis, now = self.mover.basis(c), time.monotonic()
        if self._basis.get(key, ("", 0.0))[0] != basis:
            self._basis[key] = (basis, now)
        if now - self._basis[key][1] < SPARE_SETTLE_S:
            return
        nxt = runner_up(ch, self._low(c))
        if nxt is None:
            return
        try:
            self.mover.make_spare(c.user, c.ctag, nxt.tid)
        except RCEError as e:
            log.warning("spare not made", user=c.user, ctag=c.ctag, tid=nxt.tid, reason=str(e))

    async def run(self, stop: asyncio.Event) -> None:
        """Poll the counters every :data:`POLL` s, and re-decide and carry out the placer's moves
        after each poll, as soon as a robot's link or battery changes, and when a pending move's
        hysteresis ends (it moves then, not at the next poll), until ``stop`` is set."""
        loop = asyncio.get_running_loop()
        while not stop.is_set():
            await self.poll()
            self._changed.clear()
            due = loop.time() + self._decide()
            end = loop.time() + POLL
            while not stop.is_set() and (now := loop.time()) < end:
                if (left := min(end, due) - now) > 0:
                    waits = [asyncio.ensure_future(stop.wait()), asyncio.ensure_future(self._changed.wait())]
                    try:
                        await asyncio.wait(waits, timeout=left, return_when=asyncio.FIRST_COMPLETED)
                    finally:
                        for w in waits:
                            w.cancel()
                if not stop.is_set() and (self._changed.is_set() or loop.time() >= due):
                    self._changed.clear()
                    due = loop.time() + self._decide()

    def forget(self, user: str, ctag: str) -> None:
        """Drop what is kept of a container that is gone."""
        self.use.pop((user, ctag), None)
        self.last_word.pop((user, ctag), None)
        self.placer.forget(user, ctag)
