"""Moving a running container to another host, make-before-break (docs/design.md, section 9.4).

1. **Make**: the container is created on the new host under a new ``cid`` (its old copy runs on),
   with its parameters, its container-side interfaces (the same iids) and its nodes; the move
   waits until its nodes are up: every topic a container-side ``PublisherInterface`` feeds has a
   node subscribed, every service a ``ServiceClientInterface`` calls is provided (at most
   :data:`READY_TIMEOUT` s). Meanwhile its interfaces learn their peers, so its results can go out
   (no input reaches it before the switch). Each step's requests go at once: a step costs one
   round trip to the new host, which may be a robot's computer across a slow link.
2. **Switch**, in one step per connection: the master's state names the new copy, and each peer
   end is told ``connect`` with the new data address, which replaces the old one
   (:meth:`rce.transport.interface.Interface.connect`): from that message on, the peer sends to the
   new copy only. Nothing is sent twice: each message goes to exactly one copy.
3. **Break**: the old copy finishes what was already on its way to it, behind a fence. Each peer
   told ``connect`` first sends a fence down each path it used to the old copy, after the last
   message it sent there (:meth:`rce.transport.dataplane.DataPlane.fence`), and says how many it
   sent. The old copy goes once it got every fence, its nodes handled every input that came
   before them, and each peer it sends to acknowledged the end of its stream (its last outputs
   arrived; ``drain`` op of :class:`rce_container.environment.Environment`); at most
   :data:`DRAIN_MAX` s, so that a dead or stalled peer cannot hang a move: past it the old copy
   goes anyway, and the fall-back is logged and counted (:attr:`Mover.fence_timeouts`). When its
   nodes hand their state over (:meth:`rce.node.Node.handoff`), the new copy was made holding its
   inputs; the old copy hands its state out after the same fence, the new copy takes it, then the
   inputs it held, in order (nothing handled twice, nothing skipped). A container made with
   ``ordered_moves`` is moved the same way without a state: its results keep one order per
   interface. Otherwise the new copy handles new inputs from the switch on, while the old one
   finishes its last ones.

A move that fails before the switch (the new host refuses, a node does not come up) destroys
what it made there and leaves the container running where it was (:class:`MoveFailed`).

**Spares.** The make is most of a move's cost across a slow link (a round trip per step, and the
nodes' start on a slow computer: about a second across 100 ms). A container that asks for one
(CC ``containerData`` ``spare: true``) is kept a made copy on the host it would move to next
(:meth:`Mover.make_spare`): created, with its parameters, interfaces and nodes up and wired, but
fed nothing, so it costs that host memory and no CPU. A move to that host takes it and only
switches and breaks; a move elsewhere destroys it. A spare is taken only if it is of the copy that
runs now and nothing it was made from changed since (parameters, interfaces, nodes, connections,
limits: :meth:`Mover.basis`); otherwise the move makes a fresh copy. One whose environment died
or whose host went is forgotten (:meth:`Mover.spare_lost`, :meth:`Mover.host_lost`). When the
container itself is lost with its host or environment, its failover takes its spare rather than
re-create it (:meth:`Mover.claim_spare`, :mod:`rce_master.failover`).
"""
from __future__ import annotations

import asyncio
import dataclasses
import json
import time
from dataclasses import dataclass

from rce.contract import environment as to_env
from rce.interfaces.naming import resolve
from rce.plumbing.errors import RCEError, RequestError, Timeout
from rce.plumbing.log import get_logger
from rce_master.control import Control
from rce_master.state.lifecycle import ContainerState
from rce_master.state.model import LIMIT_KEYS, ContainerRec, InterfaceRec
from rce_master.state.master_state import MasterState

__all__ = ["DRAIN_MAX", "READY_TIMEOUT", "Made", "MoveFailed", "MoveResult", "Mover"]

log = get_logger("rce.master.move")

READY_TIMEOUT = 20.0   # s the new copy's nodes have to come up
READY_POLL = 0.05      # s between looks at its bus
DRAIN_MAX = 10.0       # s the old copy may wait for its fences, its nodes and its peers' acknowledgements at most


class MoveFailed(RCEError):
    """A move that did not happen: the container runs where it was."""
    code = "request"


@dataclass
class MoveResult:
    """A move done: from host ``from_tid`` (cid ``old_cid``) to ``to_tid`` (``new_cid``); ``make_s``:
    s to build and wire the new copy (``spare``: it took a spare, and ``make_s`` is the s it waited
    for it; ``make_steps`` are then the spare's own), ``switch_s``: s to point every peer at it, ``drain_s``: s the
    old copy drained (and handed its state over); ``states``: nodes that took their old state;
    ``fenced``: the old copy went only after every fence, its nodes and its peers' acknowledgements
    (False: after :data:`DRAIN_MAX` s, or a peer could not be told; ``unfenced`` says what was missing);
    ``make_steps``: s each step of the make took (``create``, ``interfaces``, ``nodes``, then ``ready`` and
    ``wired``, which overlap: each counted from the end of ``nodes``)."""
    user: str
    ctag: str
    from_tid: int
    to_tid: int
    old_cid: int
    new_cid: int
    make_s: float
    switch_s: float
    drain_s: float
    states: int = 0
    fenced: bool = True
    unfenced: str = ""
    make_steps: dict = dataclasses.field(default_factory=dict)
    spare: bool = False


@dataclass
class Made:
    """A copy of a container made on a host, its nodes up and wired, fed nothing yet: ``rec`` (its
    ``cid`` and ``tid``), the host's ``answer`` to its creation (``data_addr``, ``sandbox``),
    ``handoff``: it holds its inputs for the old copy's state; ``of_cid``: the copy it was made
    from, ``basis``: what it was made from (:meth:`Mover.basis`); ``make_s``: s the make took,
    ``steps``: s each step took (:class:`MoveResult`)."""
    rec: ContainerRec
    answer: dict
    handoff: bool
    of_cid: int
    basis: str
    make_s: float
    steps: dict


@dataclass(eq=False)
class _Spare:
    tid: int
    task: asyncio.Task


def _made(sp: _Spare) -> Made | None:
    """The spare's copy, None while it is being made or when its make failed."""
    if not sp.task.done() or sp.task.cancelled() or sp.task.exception() is not None:
        return None
    return sp.task.result()


class Mover:
    """Moves running containers between hosts (module docstring) for the master's ``state``."""

    def __init__(self, state: MasterState, control: Control):
        self.state, self.control = state, control
        self.moving: set[tuple[str, str]] = set()
        self.spares: dict[tuple[str, str], _Spare] = {}
        self._undo: set[asyncio.Task] = set()
        self.moves = self.failed = 0
        self.fence_timeouts = 0       # moves whose old copy went before everything was fenced (DRAIN_MAX, a peer gone)
        self.spares_taken = 0         # moves that took a spare (switch and break only)

    async def move(self, user: str, ctag: str, tid: int, why: str = "", drain_max: float | None = None) -> MoveResult:
        """Move container ``user/ctag`` to container host ``tid``; ``drain_max``: s its old copy may
        wait for its fences, inputs and outputs at most (default :data:`DRAIN_MAX`). A spare of it on
        ``tid`` that still holds is taken (one still being made there is waited for); one elsewhere
        is destroyed. Raises :class:`MoveFailed` (it runs where it was), :class:`RequestError` for a
        container that is not running, is already there or is being moved, or a host that is not up
        or does not serve it, :class:`~rce.plumbing.errors.NotFound` for none."""
        c = self._check(user, ctag, tid)
        key = (user, ctag)
        if key in self.moving:
            raise RequestError(f"container {ctag!r} is being moved already")
        self.moving.add(key)
        try:
            t0 = time.monotonic()
            made = await self._take_spare(c, tid)
            return await self._move(c, tid, why, DRAIN_MAX if drain_max is None else drain_max, made, t0)
        finally:
            self.moving.discard(key)

    def make_spare(self, user: str, ctag: str, tid: int) -> asyncio.Task:
        """Start making a spare of container ``user/ctag`` on host ``tid`` (module docstring), in
        place of any it had; the task making it (its result: the :class:`Made` copy; it raises
        :class:`MoveFailed` when the make fails, having undone it). Raises as :meth:`move` does."""
        c = self._check(user, ctag, tid)
        if (user, ctag) in self.moving:
            raise RequestError(f"container {ctag!r} is being moved: its spare waits for the move")
        self.drop_spare(user, ctag)
        task = asyncio.get_running_loop().create_task(self._make(c, tid), name=f"spare {user}/{ctag}")
        task.add_done_callback(lambda t: t.cancelled() or t.exception())     # its failure is logged by _make
        self.spares[(user, ctag)] = _Spare(tid, task)
        log.info("spare making", user=user, ctag=ctag, tid=tid)
        return task

    def spare_of(self, user: str, ctag: str) -> tuple[int, bool] | None:
        """Where container ``user/ctag`` has a spare: ``(tid, ready)`` (False: still being made), or
        None (none, or its make failed)."""
        sp = self.spares.get((user, ctag))
        if sp is None or self.spare_failed(user, ctag):
            return None
        return sp.tid, sp.task.done()

    def spare_failed(self, user: str, ctag: str) -> bool:
        """Whether container ``user/ctag``'s last spare failed to be made (it is not tried again at once)."""
        sp = self.spares.get((user, ctag))
        return sp is not None and sp.task.done() and _made(sp) is None

    def spare_stale(self, c: ContainerRec) -> bool:
        """Whether ``c``'s spare can no longer serve: it is on the host ``c`` runs on, of a copy that
        no longer runs (re-created by a failover meanwhile), or made before ``c`` changed (a node, an
        interface, a connection or a parameter since: :meth:`basis`)."""
        sp = self.spares.get((c.user, c.ctag))
        if sp is None:
            return False
        made = _made(sp)
        return sp.tid == c.tid or (made is not None and not self._holds(made, c))

    def drop_spare(self, user: str, ctag: str) -> None:
        """Destroy container ``user/ctag``'s spare, if it has one (in the background)."""
        sp = self.spares.pop((user, ctag), None)
        if sp is None:
            return
        log.info("spare dropped", user=user, ctag=ctag, tid=sp.tid)
        if not sp.task.done():
            sp.task.cancel()                  # _make undoes what it made
            return
        made = _made(sp)
        if made is None:
            return
        undo = asyncio.get_running_loop().create_task(self.control.destroy_on(made.rec.tid, made.rec.cid))
        self._undo.add(undo)
        undo.add_done_callback(self._undo.discard)

    def spare_lost(self, tid: int, cid: int) -> bool:
        """Host ``tid`` reports container ``cid``'s environment dead: whether it was a spare (then it
        is forgotten)."""
        for key, sp in list(self.spares.items()):
            made = _made(sp)
            if sp.tid == tid and made is not None and made.rec.cid == cid:
                del self.spares[key]
                log.warning("spare lost with its environment", user=key[0], ctag=key[1], tid=tid, cid=cid)
                return True
        return False

    def host_lost(self, tid: int) -> None:
        """Host ``tid`` is gone: its spares with it."""
        for key, sp in list(self.spares.items()):
            if sp.tid == tid:
                del self.spares[key]
                sp.task.cancel()

    def claim_spare(self, c: ContainerRec) -> Made | None:
        """For the failover of lost container ``c``: its spare, taken from the spares, when it is
        made, of the copy that was lost and of what ``c`` is now (:meth:`basis`), on a host that is
        up; None otherwise (a spare that does not hold is destroyed)."""
        sp = self.spares.get((c.user, c.ctag))
        made = _made(sp) if sp is not None else None
        if made is None:
            return None
        host = self.state.tasksets.get(sp.tid)
        if not self._holds(made, c) or host is None or host.lost:
            self.drop_spare(c.user, c.ctag)
            return None
        del self.spares[(c.user, c.ctag)]
        self.spares_taken += 1
        return made

    def _holds(self, made: Made, c: ContainerRec) -> bool:
        """Whether copy ``made`` can serve as ``c``: made of the copy ``c`` is now, from what ``c`` is now."""
        return made.of_cid == c.cid and made.basis == self.basis(c)

    def basis(self, c: ContainerRec) -> str:
        """What a copy of ``c`` is made from, as one string: its group, limits and deadline, its
        parameters, container-side interfaces, nodes and connections (with each peer's data address)."""
        ifaces = self.state.interfaces_of(c.user, c.ctag, robot_side=False)
        conns = [(me.iid, peer.iid, self.state.data_addr(peer)) for rec in ifaces
                 for me, peer in self.state.connections_of(rec.iid)]
        return json.dumps([c.group, [c.data.get(k) for k in (*LIMIT_KEYS, "deadline_ms", "ordered_moves")],
                           sorted(self.state.params_of(c)),
                           sorted((r.iid, r.tag, r.itype, r.cls, r.addr) for r in ifaces),
                           sorted((n.ntag, n.spec) for n in self.state.nodes_of(c)), sorted(conns)],
                          sort_keys=True, default=str)

    def _check(self, user: str, ctag: str, tid: int) -> ContainerRec:
        c = self.state.container(user, ctag)
        if c.state != ContainerState.RUNNING:
            raise RequestError(f"container {ctag!r} is {c.state}: only a running container moves")
        if c.tid == tid:
            raise RequestError(f"container {ctag!r} already runs on host {tid}")
        host = self.state.tasksets.get(tid)
        if host is None or host.kind != "container" or host.lost:
            raise RequestError(f"host {tid} is not a container host that is up")
        if not host.zone.serves(user, c.data.get("robot")):
            raise RequestError(f"host {host.name} ({host.zone}) does not serve container {ctag!r}")
        return c

    async def _take_spare(self, c: ContainerRec, tid: int) -> Made | None:
        """``c``'s spare on ``tid`` if it holds (waited for while it is being made); None, having
        destroyed a spare elsewhere or one that no longer holds."""
        sp = self.spares.get((c.user, c.ctag))
        if sp is None:
            return None
        if sp.tid != tid:
            self.drop_spare(c.user, c.ctag)
            return None
        try:
            made = await asyncio.shield(sp.task)
        except (RCEError, MoveFailed, asyncio.CancelledError):
            if not sp.task.done():
                raise                             # this move was cancelled; the spare goes on
            self.spares.pop((c.user, c.ctag), None)
            return None
        if not self._holds(made, c) or self.state.containers.get((c.user, c.ctag)) is not c:
            log.info("spare no longer holds; the move makes a fresh copy", user=c.user, ctag=c.ctag, tid=tid)
            self.drop_spare(c.user, c.ctag)
            return None
        del self.spares[(c.user, c.ctag)]
        self.spares_taken += 1
        return made

    async def _make(self, c: ContainerRec, tid: int) -> Made:
        """Make a copy of ``c`` on host ``tid`` (module docstring, step 1): created, with its parameters,
        interfaces and nodes, wired to its peers, its nodes up. Raises :class:`MoveFailed` having
        destroyed what it made (as it does when cancelled, then re-raising)."""
        t0 = time.monotonic()
        old_cid = c.cid
        basis = self.basis(c)
        new = dataclasses.replace(c, cid=self.state.reserve_cid(), tid=tid, state=ContainerState.STARTING)
        ifaces = self.state.interfaces_of(c.user, c.ctag, robot_side=False)
        conns = [(me, peer) for rec in ifaces for me, peer in self.state.connections_of(rec.iid)]
        steps: dict[str, float] = {}
        mark = [t0]

        def step(name: str) -> None:
            now = time.monotonic()
            steps[name], mark[0] = round(now - mark[0], 3), now
        try:
            hooks = (await self.control.host_ask(c, to_env.EnvDescribe(cid=c.cid))).get("handoff") or []
            handoff = bool(hooks) or bool(c.data.get("ordered_moves"))     # the new copy holds its inputs
            answer = await self.control.create_container(new, handoff=handoff)
            step("create")
            # each step's requests go at once (a round trip a step, not one a request: the new host may be
            # a robot's computer across a link of 100 ms), and a step begins once the last has its answers
            await asyncio.gather(
                *(self.control.host_ask(new, to_env.EnvSetParam(cid=new.cid, name=name, value=value))
                  for name, value in self.state.params_of(c)),
                *(self.control.install_interface(rec, into=new) for rec in ifaces))
            step("interfaces")
            await asyncio.gather(*(self.control.start_node(new, n.ntag, n.spec) for n in self.state.nodes_of(c)))
            step("nodes")
            self._still(c, old_cid)

            async def timed(name: str, work) -> None:
                await work
                steps[name] = round(time.monotonic() - mark[0], 3)
            # while its nodes come up, the new copy learns its peers, so that its results can go out
            await asyncio.gather(timed("ready", self._ready(new, ifaces)), timed("wired", asyncio.gather(*(
                self.control.host_ask(new, self.control.connect_op(me, peer, self.state.data_addr(peer), cid=new.cid))
                for me, peer in conns))))
            self._still(c, old_cid)
        except (RCEError, MoveFailed) as e:
            await self.control.destroy_on(tid, new.cid)
            log.warning("container copy not made; it runs where it was", user=c.user, ctag=c.ctag, to_tid=tid,
                        reason=str(e))
            raise MoveFailed(f"container {c.ctag!r} not moved to host {tid}, it runs where it was: {e}") from None
        except asyncio.CancelledError:
            await self.control.destroy_on(tid, new.cid)
            raise
        return Made(new, answer, handoff, old_cid, basis, time.monotonic() - t0, steps)

    async def _move(self, c: ContainerRec, tid: int, why: str, drain_max: float, made: Made | None,
                    t0: float) -> MoveResult:
        old_tid, old_cid = c.tid, c.cid
        log.info("container moving", user=c.user, ctag=c.ctag, from_tid=old_tid, to_tid=tid, why=why,
                 spare=made is not None)
        spare = made is not None
        if made is None:
            try:
                made = await self._make(c, tid)
            except MoveFailed:
                self.failed += 1
                raise
        new = made.rec
        ifaces = self.state.interfaces_of(c.user, c.ctag, robot_side=False)
        conns = [(me, peer) for rec in ifaces for me, peer in self.state.connections_of(rec.iid)]
        t1 = time.monotonic()
        addr = made.answer["data_addr"]
        self.state.container_moved(c, tid, new.cid, addr, made.answer.get("sandbox", ""))
        expect, unreached = await self._switch(c, new.cid, conns, addr)
        t2 = time.monotonic()
        old = dataclasses.replace(c, cid=old_cid, tid=old_tid)
        moved_states = 0
        done = await self._finish_old(old, new.cid, expect, drain_max)
        if unreached:
            done = dict(done, complete=False, unreached=unreached)
        if made.handoff:
            moved_states = await self._hand_over(old, new)
        await self.control.destroy_on(old_tid, old_cid)
        t3 = time.monotonic()
        self.moves += 1
        fenced = bool(done.get("complete"))
        if not fenced:
            self.fence_timeouts += 1
        unfenced = "" if fenced else ", ".join(f"{k}: {done[k]}" for k in ("missing", "unsettled", "unflushed",
                                                                         "unreached", "error") if done.get(k))
        result = MoveResult(c.user, c.ctag, old_tid, tid, old_cid, new.cid, t1 - t0, t2 - t1, t3 - t2, moved_states,
                            fenced, unfenced, made.steps, spare)
        log.info("container moved", **dataclasses.asdict(result), why=why)
        self.control.notify_robot(c.user, c.owner, "ST", {"topic": "container", "cTag": c.ctag, "status": "running",
                                                          "sandbox": c.sandbox, "moved": True})
        return result

    async def _switch(self, c: ContainerRec, cid: int, conns: list[tuple[InterfaceRec, InterfaceRec]],
                      addr: str) -> tuple[list[list[int]], list[str]]:
        """Tell every peer of ``c``'s interfaces (``conns``: ``(its interface, the peer's)``) to send to
        the new copy ``cid`` at data address ``addr`` from now on, all at once, each with a fence.
        Returns the fences the old copy is to get (``[src, dst, n]``) and the tags of the peers that
        could not be told (they may still send to the old copy: nothing fences that)."""
        t0 = time.monotonic()

        async def told(me: InterfaceRec, peer: InterfaceRec) -> dict:
            r = await self.control.endpoint_ask(peer, self.control.connect_op(peer, me, addr, fence=cid))
            log.info("peer switched", user=c.user, ctag=c.ctag, peer=peer.tag, s=round(time.monotonic() - t0, 3))
            return r
        answers = await asyncio.gather(*(told(me, peer) for me, peer in conns), return_exceptions=True)
        expect: list[list[int]] = []
        unreached: list[str] = []
        for (me, peer), r in zip(conns, answers, strict=True):
            if isinstance(r, RCEError):
                log.warning("a peer of a moved container was not switched", user=c.user, ctag=c.ctag,
                            peer=peer.tag, reason=str(r))
                unreached.append(peer.tag)
                continue
            if isinstance(r, BaseException):
                raise r
            n = int((r or {}).get("fenced") or 0) if isinstance(r, dict) else 0
            if n:
                expect.append([peer.iid, me.iid, n])
        return expect, unreached

    def _still(self, c: ContainerRec, cid: int) -> None:
        if self.state.containers.get((c.user, c.ctag)) is not c or c.cid != cid or c.state != ContainerState.RUNNING:
            raise MoveFailed(f"container {c.ctag!r} was removed, lost or replaced meanwhile")

    async def _ready(self, new: ContainerRec, ifaces: list[InterfaceRec]) -> None:
        """Wait until the new copy's nodes took up what its interfaces feed and call."""
        topics = {resolve(r.addr, "/") for r in ifaces if r.kind == "Publisher"}
        services = {resolve(r.addr, "/") for r in ifaces if r.kind == "ServiceClient"}
        deadline = time.monotonic() + READY_TIMEOUT
        while True:
            bus = await self.control.host_ask(new, to_env.EnvDescribe(cid=new.cid))
            subscribed = {t["name"] for t in bus["topics"]
                          if any(not s.startswith("interface:") for s in t["subscribers"])}
            provided = {s["name"] for s in bus["services"] if not str(s["provider"]).startswith("interface:")}
            exited = [n["ntag"] for n in bus.get("launched", []) if not n.get("running") and not n.get("restarts")]
            if exited:
                raise MoveFailed(f"node {exited[0]!r} exited on the new host before it came up")
            if topics <= subscribed and services <= provided:
                return
            if time.monotonic() > deadline:
                missing = sorted((topics - subscribed) | (services - provided))
                raise Timeout(f"its nodes did not take up {', '.join(missing)} within {READY_TIMEOUT:g} s")
            await asyncio.sleep(READY_POLL)

    async def _hand_over(self, old: ContainerRec, new: ContainerRec) -> int:
        """The state of the old copy's nodes into the new copy's, which then take their held inputs
        (:meth:`rce.node.Node.handoff`); how many nodes took a state. Called once the old copy has
        handled its last inputs (:meth:`_finish_old`). A state that cannot be had leaves the new
        nodes to start fresh."""
        try:
            states = (await self.control.host_ask(old, to_env.EnvStateOut(cid=old.cid))).get("states") or {}
        except RCEError as e:
            log.warning("old copy's state not had; the new copy starts fresh", user=old.user, ctag=old.ctag,
                        reason=str(e))
            states = {}
        took = (await self.control.host_ask(new, to_env.EnvStateIn(cid=new.cid, states=states))).get("nodes") or []
        return len(took)

    async def _finish_old(self, old: ContainerRec, fence: int, expect: list[list[int]], drain_max: float) -> dict:
        """Wait until the old copy got the fences ``expect`` (``[src, dst, n]``: ``n`` fences ``fence``
        of connection ``src -> dst``), handled what came before them and its peers took its last
        outputs, at most ``drain_max`` s (module doc). Returns the ``drain`` op's answer
        (``complete`` False: it goes without them, logged)."""
        try:
            done = await self.control.host_ask(old, to_env.EnvDrain(cid=old.cid, fence=fence, expect=expect,
                                                                 timeout=drain_max), drain_max + 5.0)
        except RCEError as e:
            done = {"complete": False, "error": str(e)}
        if not done.get("complete"):
            log.warning("old copy of a moved container goes before it was fenced", user=old.user, ctag=old.ctag,
                        cid=old.cid, **{k: v for k, v in done.items() if k != "complete"})
        return done
