"""Container failover (docs/INTERNALS.md, "Container failover"): a container whose host or
environment is lost is re-created with everything the master's state holds for it: on another
host when its host went away, on its own host when only its environment died.

The master sees a container lost in three ways:

- its host's control link closes (kill -9 of rce-container: at once), or falls silent (SIGSTOP,
  a partition: the keepalive closes it after ``rce.transport.rpc.KEEPALIVE_TIMEOUT``, 4 s);
- its environment dies: the host reports ``container_lost {cid, reason}``;
- its host re-registers without it (after the master restarted).

Then :meth:`Failover.lost` tells the far end of each of its connections ``disconnect`` (a
robot-side end says ``iu false``) and its owner ``ST {topic: container, cTag, status: lost}``
and an ER naming why, and a task re-creates it (:meth:`Failover._recover`):

1. place it (:meth:`MasterState.pick_container_host` without the hosts that already failed it;
   its own host first when only its environment died) and give it a new ``cid``
   (:meth:`MasterState.container_recovering`, state ``recovering``);
2. re-issue ``create_container``, ``set_param`` for each parameter, ``add_interface`` for each
   container-side interface and ``add_node`` for each node;
3. mark it ``running``; ``connect`` both ends of each of its connections whose other end is up
   (the robot-side end gets the new data address and says ``iu true``); ST ``running``.

A container with a spare (:mod:`rce_master.placement.mover`, Spares) that still holds is not re-created: its
spare, made and wired beforehand on another host that is up, becomes it (steps 1 and 2 skipped; its
nodes start fresh, with no state handed over), then step 3.

When no host can take it, it waits (``lost``) and is tried again each time a container host
registers, for up to ``wait`` s. A re-creation that fails is undone on its host, and that host
is not tried again for this loss. After ``attempts`` re-creations (an environment that dies at
once would loop forever) or ``wait`` s without a host, the master gives up: the container
stays lost and its owner gets an ER. A DC forgets a lost container at any time; a re-creation
that finds its container destroyed (or replaced) meanwhile undoes what it made and stops.
"""
from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from rce.contract import environment as to_env
from rce.plumbing.errors import RCEError, Unavailable
from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks
from rce_master.control import Control
from rce_master.state.lifecycle import ContainerState
from rce_master.state.model import ContainerRec, InterfaceRec, Robot
from rce_master.placement.mover import Made
from rce_master.state.master_state import MasterState

log = get_logger("rce.master")

RECOVERY_ATTEMPTS = 3     # re-creations of one lost container before the master gives up on it (a host that
                          # fails one is left out of the next; an environment that dies at once must not loop)
RECOVERY_WAIT = 300.0     # s a lost container waits for a container host that can take it; then it stays lost
RECOVERY_STABLE = 30.0    # s a re-created container must run before its next loss counts attempts afresh


class _Superseded(Exception):
    """The container being re-created was destroyed, replaced or lost again meanwhile."""


@dataclass(eq=False)
class Recovery:
    """The failover of one container: its attempts, the hosts that failed it (tids), the host it
    prefers (its own, when only its environment died), when it last came back (monotonic s)."""
    c: ContainerRec
    prefer: int | None = None
    attempts: int = 0
    failed: set[int] = field(default_factory=set)
    recovered_at: float | None = None
    task: asyncio.Task | None = None


class Failover:
    """Re-creates lost containers (see the module doc) on ``state`` through ``control``; its tasks
    are kept in ``tasks``. ``attempts``, ``wait`` (s) and ``stable`` (s): as the defaults
    :data:`RECOVERY_ATTEMPTS`, :data:`RECOVERY_WAIT`, :data:`RECOVERY_STABLE`; ``spares(c)``: a lost
    container's spare that still holds, taken (:meth:`rce_master.placement.mover.Mover.claim_spare`)."""

    def __init__(self, state: MasterState, control: Control, tasks: Tasks, *, attempts: int = RECOVERY_ATTEMPTS,
                 wait: float = RECOVERY_WAIT, stable: float = RECOVERY_STABLE,
                 spares: Callable[[ContainerRec], Made | None] | None = None):
        self.state, self.control, self.tasks, self.spares = state, control, tasks, spares
        self.attempts, self.wait, self.stable = attempts, wait, stable
        self.recoveries: dict[tuple[str, str], Recovery] = {}     # (user, ctag) -> its failover, while it matters
        self.recovered = self.gave_up = 0                         # counters (metrics)
        self._hosts = asyncio.Event()                             # set (and replaced) when a container host registers

    # -- what the master sees ---------------------------------------------------------------------------
    async def lost(self, containers: list[ContainerRec], why: str, prefer: int | None = None) -> None:
        """Containers just marked lost (``why`` says how): cut their connections, tell their
        owners, re-create them (preferring host ``prefer``). One that never ran (its CC was under
        way) is not re-created: its CC fails and undoes it."""
        for c in containers:
            if not self._current(c):
                continue
            if self._orphan(c):
                await self._forget(c, why)
                continue
            await self.control.cut(c)
            again = bool(c.data_addr)
            self.control.tell_lost(c, why + ("; it is being re-created" if again else ""))
            if again:
                self._start(c, prefer)

    async def taskset_lost(self, lost: list[ContainerRec], robots: list[Robot],
                           why: str = "its host went away") -> None:
        """After :meth:`MasterState.drop_taskset`: its robots are gone (with the containers they
        own), then its containers still here are lost."""
        for r in robots:
            await self.control.robot_gone(r.user, r.robot)
        await self.lost(lost, why)

    async def environment_lost(self, tid: int, cid: int, reason: str) -> None:
        """Host ``tid`` says the environment of container ``cid`` died (``reason``): what is left
        of it there is destroyed, and, when it is a container the master runs there, it is lost
        and re-created on that host first. Otherwise (a report that waited while the master was
        away, after which the container was found lost and moved) only the remains go. One being
        created there (a CC, a re-creation) is left to that, which fails and undoes itself."""
        c = self.state.container_by_cid(cid)
        if c is not None and c.tid == tid and c.state in (ContainerState.STARTING, ContainerState.RECOVERING):
            return
        running = c is not None and c.tid == tid and c.state == ContainerState.RUNNING
        if running:
            self.state.container_lost(c)
        await self.control.destroy_on(tid, cid)
        if running:
            await self.lost([c], reason, prefer=tid)

    def host_registered(self) -> None:
        """A container host registered: the containers waiting for one are tried again."""
        self._hosts.set()
        self._hosts = asyncio.Event()

    def resume(self) -> None:
        """On taking office: re-create the lost containers the store holds (their hosts register
        later), those whose robot is still stored (a robot of an absent endpoint may come back)."""
        for c in self.state.interrupted_recoveries():
            if not self._orphan(c):
                self._start(c, None)

    def _orphan(self, container: ContainerRec) -> bool:
        """``container``'s robot is gone: a container belongs to its robot's session, so it is not re-created."""
        return (container.user, container.owner) not in self.state.robots

    async def _forget(self, container: ContainerRec, why: str) -> None:
        """Forget the lost ``container`` of a robot that is gone, with its interfaces' connections."""
        log.info("lost container forgotten", user=container.user, ctag=container.ctag,
                 reason=why + "; its robot is gone")
        await self.control.destroy(*self.state.remove_container(container.user, container.ctag))

    # -- re-creation ---------------------------------------------------------------------------------------
    def _start(self, container: ContainerRec, prefer: int | None) -> None:
        for key, rec in list(self.recoveries.items()):       # bound: drop what no longer matters
            done = rec.task is None or rec.task.done()
            if done and (not self._current(rec.c) or rec.recovered_at is None
                         or time.monotonic() - rec.recovered_at >= self.stable):
                del self.recoveries[key]
        rec = self.recoveries.get((container.user, container.ctag))
        if rec is None or rec.c is not container:
            rec = self.recoveries[(container.user, container.ctag)] = Recovery(container)
        elif rec.task is not None and not rec.task.done():
            return                                            # its task sees the loss and tries again
        rec.prefer = prefer
        rec.task = self.tasks.spawn(self._recover(rec), name=f"recover {container.user}/{container.ctag}")

    async def _recover(self, rec: Recovery) -> None:
        """Re-create ``rec.c`` until it runs, is destroyed, or the bounds say stop."""
        c = rec.c
        deadline = time.monotonic() + self.wait
        while self._current(c) and c.state == ContainerState.LOST:
            if self._orphan(c):                               # its robot left while it waited for a host
                await self._forget(c, "not re-created")
                return
            if rec.attempts >= self.attempts:
                self._give_up(c, f"{rec.attempts} re-creations failed")
                return
            made = self.spares(c) if self.spares is not None else None
            if made is not None:
                rec.attempts += 1
                if await self._attempt(c, made.rec.tid, made):
                    rec.recovered_at = time.monotonic()
                    return
                rec.failed.add(made.rec.tid)
                continue
            try:
                host = self.state.pick_container_host(c.data, c.user, exclude=rec.failed, prefer=rec.prefer)
            except Unavailable as e:
                if not await self._host_registers(deadline):
                    self._give_up(c, f"no container host could take it within {self.wait:g} s ({e.message})")
                    return
                continue
            rec.attempts += 1
            if await self._attempt(c, host.tid):
                rec.recovered_at = time.monotonic()
                return
            rec.failed.add(host.tid)

    async def _attempt(self, container: ContainerRec, tid: int, spare: Made | None = None) -> bool:
        """One re-creation of ``container`` on host ``tid`` (or the take-over of its ``spare`` there);
        True when it runs there. Undone when it fails."""
        t0 = time.monotonic()
        self.state.container_recovering(container, tid, spare.rec.cid if spare is not None else None)
        cid = container.cid
        try:
            if spare is None:
                await self._rebuild(container, cid)
            else:
                await self._adopt(container, cid, spare)
        except (RCEError, _Superseded) as e:
            await self.control.destroy_on(tid, cid)
            if self._current(container) and container.cid == cid and container.state == ContainerState.RECOVERING:
                self.state.container_lost(container)
            if isinstance(e, RCEError):
                log.warning("container re-creation failed", user=container.user, ctag=container.ctag, cid=cid, tid=tid,
                            reason=e.message)
            return False
        self.recovered += 1
        log.info("container re-created" if spare is None else "container taken over by its spare", user=container.user,
                 ctag=container.ctag, cid=cid, tid=tid, ms=round((time.monotonic() - t0) * 1000, 1))
        return True

    async def _rebuild(self, container: ContainerRec, cid: int) -> None:
        """Create ``container`` (now ``cid``) on its new host with its parameters, container-side
        interfaces and nodes; then it runs, its connections are made again, its owner is told."""
        answer = await self.control.create_container(container)
        for name, value in self.state.params_of(container):
            self._check(container, cid)
            await self.control.host_ask(container, to_env.EnvSetParam(cid=container.cid, name=name, value=value))
        for rec in self.state.interfaces_of(container.user, container.ctag, robot_side=False):
            self._check(container, cid)
            await self.control.install_interface(rec)
        for n in self.state.nodes_of(container):
            self._check(container, cid)
            await self.control.start_node(container, n.ntag, n.spec)
            self.state.node_running(n)
        await self._running(container, cid, answer)

    async def _adopt(self, container: ContainerRec, cid: int, spare: Made) -> None:
        """Lost ``container`` runs as its ``spare`` (now ``cid``), made and wired beforehand: its nodes
        are up (a spare made holding its inputs for a state takes none: they start fresh), then as
        :meth:`_rebuild` ends."""
        if spare.handoff:
            await self.control.host_ask(container, to_env.EnvStateIn(cid=container.cid, states={}))
        for n in self.state.nodes_of(container):
            self.state.node_running(n)
        await self._running(container, cid, spare.answer)

    async def _running(self, container: ContainerRec, cid: int, answer: dict) -> None:
        """``container`` (``cid``), made on its host (``answer``: its ``data_addr`` and ``sandbox``),
        runs: its connections are made again, its owner is told."""
        self._check(container, cid)
        self.state.container_ready(container, answer["data_addr"], answer.get("sandbox", ""))
        for a, b in self._live_connections(container):          # read right after it runs: see _live_connections
            await self.control.quiet(self.control.tell_connect(a, b))
        if self._current(container) and container.cid == cid and container.state == ContainerState.RUNNING:
            self.control.notify_robot(container.user, container.owner, "ST",
                                      {"topic": "container", "cTag": container.ctag, "status": "running",
                                       "sandbox": container.sandbox})

    def _live_connections(self, container: ContainerRec) -> list[tuple[InterfaceRec, InterfaceRec]]:
        """The connections of ``container``'s interfaces whose other end is up: a robot-side end whose
        endpoint is registered, or a container-side end whose container runs. Two containers
        re-created together: whichever runs second connects them (this is read with no await
        between marking ``container`` running and reading the other's state)."""
        out, seen = [], set()
        for rec in self.state.interfaces_of(container.user, container.ctag, robot_side=False):
            for me, peer in self.state.connections_of(rec.iid):
                pair = (min(me.iid, peer.iid), max(me.iid, peer.iid))
                if pair in seen:
                    continue
                seen.add(pair)
                if peer.robot_side:
                    up = peer.location in self.control.peers
                else:
                    other = self.state.container_by_cid(peer.location)
                    up = other is not None and other.state == ContainerState.RUNNING
                if up:
                    out.append((me, peer))
        return out

    async def _host_registers(self, deadline: float) -> bool:
        """Wait until a container host registers (True) or ``deadline`` (monotonic s) passes (False)."""
        left = deadline - time.monotonic()
        if left <= 0:
            return False
        try:
            async with asyncio.timeout(left):
                await self._hosts.wait()
        except TimeoutError:
            return False
        return True

    def _give_up(self, container: ContainerRec, why: str) -> None:
        self.gave_up += 1
        log.warning("container stays lost", user=container.user, ctag=container.ctag, reason=why)
        self.control.notify_robot(container.user, container.owner, "ER",
                                  f"container {container.ctag!r} could not be re-created: {why}; "
                                  "it stays lost (DC it to give it up)")

    def _current(self, container: ContainerRec) -> bool:
        return self.state.containers.get((container.user, container.ctag)) is container

    def _check(self, container: ContainerRec, cid: int) -> None:
        if not self._current(container) or container.cid != cid or container.state != ContainerState.RECOVERING:
            raise _Superseded(container.ctag)
