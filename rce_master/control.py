"""The master's side of the control plane (docs/INTERNALS.md, "Control ops"): its links to the
task sets, and the I/O that requests, the admin API and teardowns share (call a container's
host or an interface's endpoint, tell both ends of a connection, tell a robot, destroy a
container). It reads :class:`~rce_master.state.master_state.MasterState` and changes it only through its
operations.
"""
from __future__ import annotations

import asyncio
from collections.abc import Awaitable
from typing import Any, TypeVar

from rce.contract import environment as to_env
from rce.contract import host as to_host
from rce.contract import robot as to_robot
from rce.contract.base import OpArgs
from rce.transport.cluster_auth import ClusterKey
from rce.plumbing.errors import RCEError, Unavailable
from rce.plumbing.log import get_logger
from rce.transport.rpc import CALL_TIMEOUT, RpcPeer
from rce_master.state.model import LIMIT_KEYS, ContainerRec, InterfaceRec, NodeRec
from rce_master.state.reconcile import Reconciled
from rce_master.state.master_state import MasterState, Pairs, TaskSetAbsent

log = get_logger("rce.master")

CREATE_TIMEOUT = 60.0     # s, create_container: it returns once the environment is up (sandbox, bus, ready)
# s a call to an absent container host (the master restarted or a standby took over, and the host
# has not re-registered yet) waits for it before it is refused: hosts redial within rce.transport.masterlink's
# 2 s backoff cap, so a robot's request right after a takeover waits instead of failing
ABSENT_WAIT = 10.0
A = TypeVar("A", bound=OpArgs)
B = TypeVar("B", bound=OpArgs)


async def _ask(peer: RpcPeer, msg: OpArgs, timeout: float | None) -> Any:
    """Send typed op ``msg`` on ``peer`` and await its answer (as :meth:`RpcPeer.ask`; through
    ``request``, which a test's stand-in for a link also has)."""
    return await peer.request(msg.OP, msg.wire(), timeout)


class Control:
    """The registered task sets' links (``peers``: tid -> :class:`RpcPeer`) and what is said on them.

    A call raises the far end's :class:`RCEError`, :class:`Unavailable` when the link is gone, or
    :class:`rce.plumbing.errors.Timeout` when the far end did not answer in time (it may still do what
    was asked: the request handlers undo that too, see :mod:`rce_master.requests`), and
    :class:`TaskSetAbsent` when that task set has not re-registered since the master restarted.

    ``cluster_key``: what the credential handed with each ``connect`` derives from
    (:meth:`ClusterKey.connection_token`; default: a fresh key, for tests without task sets)."""

    def __init__(self, state: MasterState, cluster_key: ClusterKey | None = None):
        self.state = state
        self.key = cluster_key or ClusterKey.generate()
        self.peers: dict[int, RpcPeer] = {}
        self._back: dict[int, asyncio.Event] = {}      # tid -> set when that absent task set is back

    # -- calls ----------------------------------------------------------------------------------------
    async def host_ask(self, container: ContainerRec, msg: OpArgs, timeout: float = CALL_TIMEOUT,
                       wait: bool = True) -> Any:
        """Send op ``msg`` (a host's, :mod:`rce.contract.host`, or an environment's it relays,
        :mod:`rce.contract.environment`, naming its ``cid``) to the host of ``container``; its answer.
        An absent host is waited for (``wait``, robot requests: up to :data:`ABSENT_WAIT`), or refused
        at once (the admin API: its HTTP 503 says when to ask again)."""
        return await _ask(await self._host_peer(container, wait), msg, timeout)

    async def _host_peer(self, container: ContainerRec, wait: bool) -> RpcPeer:
        peer = self.peers.get(container.tid)
        if peer is None:
            what = f"the host of container {container.ctag!r}"
            if not wait:
                self._check_absent(container.tid, what)
                raise Unavailable(f"{what} is gone")
            peer = await self._host_back(container.tid, what)
        return peer

    def attach(self, tid: int, peer: RpcPeer) -> None:
        """Task set ``tid`` (re-)registered on link ``peer``: calls waiting for it go on."""
        self.peers[tid] = peer
        back = self._back.pop(tid, None)
        if back is not None:
            back.set()

    async def _host_back(self, tid: int, what: str) -> RpcPeer:
        """The link of container host ``tid`` once it is back, waiting up to :data:`ABSENT_WAIT`
        when it is absent. Raises :class:`TaskSetAbsent` (still absent) or :class:`Unavailable` (gone)."""
        self._check_absent(tid, what, wait=False)
        back = self._back.setdefault(tid, asyncio.Event())
        try:
            async with asyncio.timeout(ABSENT_WAIT):
                await back.wait()
        except TimeoutError:
            self._check_absent(tid, f"{what} (waited {ABSENT_WAIT:g} s)")
        peer = self.peers.get(tid)
        if peer is None:
            raise Unavailable(f"{what} is gone")
        return peer

    def _check_absent(self, tid: int, what: str, wait: bool = True) -> None:
        """Raise :class:`TaskSetAbsent` when task set ``tid`` is absent (``wait``: refuse it;
        else: let the caller wait for it), :class:`Unavailable` when it is gone altogether."""
        ts = self.state.tasksets.get(tid)
        if ts is None or not (ts.lost or wait):
            raise Unavailable(f"{what} is gone")
        if ts.lost and wait:
            raise TaskSetAbsent(f"{what} has not re-registered since the master restarted; try again later")

    async def endpoint_ask(self, rec: InterfaceRec, msg: OpArgs) -> Any:
        """Send op ``msg`` to the endpoint holding interface ``rec``: its robot task set (robot side,
        an op of :mod:`rce.contract.robot`) or its container's host (container side, an op of
        :mod:`rce.contract.environment`, :meth:`to_end` builds either)."""
        if not rec.robot_side:
            c = self.state.container_by_cid(rec.location)
            if c is None:
                raise Unavailable(f"container {rec.etag!r} is gone")
            return await self.host_ask(c, msg)
        peer = self.peers.get(rec.location)
        if peer is None:
            self._check_absent(rec.location, f"the robot endpoint of {rec.tag}")
            raise Unavailable(f"the robot endpoint of {rec.tag} is gone")
        return await _ask(peer, msg, CALL_TIMEOUT)

    @staticmethod
    def to_end(rec: InterfaceRec, robot_op: type[A], env_op: type[B], cid: int | None = None, **fields: Any) -> A | B:
        """The op for the endpoint holding ``rec``: ``robot_op`` of ``fields`` on a robot's side,
        else ``env_op`` on container ``cid`` (default: the one the state has ``rec`` in)."""
        if rec.robot_side:
            return robot_op(**fields)
        return env_op(cid=rec.location if cid is None else cid, **fields)

    # -- what a container is made of (a CC and CN, and its re-creation after a loss) --------------------
    async def create_container(self, container: ContainerRec, handoff: bool = False) -> dict:
        """``create_container`` on ``container``'s host with its group, limits (``container.data``, as last
        resized) and deadline; the host's ``{data_addr, sandbox, startup_ms}``. ``handoff``: it is a
        move's new copy, whose nodes wait for their state (:mod:`rce_master.placement.mover`)."""
        return await self.host_ask(container, to_host.CreateContainer(
            cid=container.cid, user=container.user, ctag=container.ctag, group=container.group,
            limits={k: container.data.get(k) for k in LIMIT_KEYS}, deadline_ms=container.data.get("deadline_ms"),
            handoff=handoff), CREATE_TIMEOUT)

    async def start_node(self, container: ContainerRec, ntag: str, spec: dict) -> Any:
        """``add_node`` on ``container``'s host: node ``ntag`` of addNodes entry ``spec``."""
        return await self.host_ask(container, to_env.EnvAddNode(
            cid=container.cid, ntag=ntag, pkg=spec["pkg"], exe=spec["exe"], args=spec.get("args", ""),
            name=spec.get("name"), namespace=spec.get("namespace"), respawn=spec.get("respawn")))

    async def install_interface(self, rec: InterfaceRec, into: ContainerRec | None = None) -> Any:
        """``add_interface`` on the endpoint of ``rec``: its robot task set (robot side) or its
        container's host (container side; ``into``: the copy of its container to install it in, a
        move's new one; default: the one the state has it in)."""
        if rec.robot_side:
            return await self.endpoint_ask(rec, to_robot.EndpointAddInterface(
                user=rec.user, robot=rec.etag, iid=rec.iid, itag=rec.itag, itype=rec.itype, cls=rec.cls, lane=rec.lane))
        msg = to_env.EnvAddInterface(cid=rec.location if into is None else into.cid, iid=rec.iid, tag=rec.tag,
                                  itype=rec.itype, cls=rec.cls, addr=rec.addr)
        return await (self.endpoint_ask(rec, msg) if into is None else self.host_ask(into, msg))

    async def remove_interface(self, rec: InterfaceRec) -> Any:
        """``remove_interface`` on the endpoint of ``rec``."""
        msg = self.to_end(rec, to_robot.EndpointRemoveInterface, to_env.EnvRemoveInterface, iid=rec.iid)
        return await self.endpoint_ask(rec, msg)

    async def destroy_on(self, tid: int, cid: int) -> None:
        """Destroy container ``cid`` on host ``tid`` whatever the state says (undoing a re-creation
        the state no longer wants), quietly."""
        peer = self.peers.get(tid)
        if peer is not None:
            await self.quiet(_ask(peer, to_host.DestroyContainer(cid=cid), CALL_TIMEOUT))

    @staticmethod
    async def quiet(call: Awaitable[Any]) -> None:
        """Await ``call``, logging a refusal instead of raising it (teardown and undo)."""
        try:
            await call
        except RCEError as e:
            log.debug("ignored on teardown", reason=str(e))

    # -- what both ends and the robot are told --------------------------------------------------------
    def connect_op(self, me: InterfaceRec, peer: InterfaceRec, peer_addr: str, *, fence: int | None = None,
                   cid: int | None = None) -> to_robot.EndpointConnect | to_env.EnvConnect:
        """The ``connect`` telling ``me`` its peer ``peer`` at ``peer_addr``, with the credential
        that lets it send there (:mod:`rce.transport.cluster_auth`, "Data-plane credentials") and the
        peer's class (``peer_cls``: where one end is ROS 1 and the other ROS 2, the sender converts,
        :mod:`rce.messages.convert`); ``fence``: a move's (:mod:`rce_master.placement.mover`); ``cid``:
        the copy of ``me``'s container it goes to (as for :meth:`to_end`)."""
        fields: dict[str, Any] = {"iid": me.iid, "peer_iid": peer.iid, "peer_addr": peer_addr, "peer_cls": peer.cls,
                                  "token": self.key.connection_token(me.iid, peer.iid, peer_addr)}
        if fence is not None:
            fields["fence"] = fence
        return self.to_end(me, to_robot.EndpointConnect, to_env.EnvConnect, cid, **fields)

    async def tell_connect(self, end_a: InterfaceRec, end_b: InterfaceRec) -> None:
        """Tell both ends of a new connection the other's iid, data address and credential; the
        end that receives first (a Publisher*, a ServiceClient*) is told first, so that it knows its
        peer (and takes its frames) before the other end sends."""
        if end_b.kind in ("Publisher", "ServiceClient"):
            end_a, end_b = end_b, end_a
        addr_a, addr_b = self.state.data_addr(end_a), self.state.data_addr(end_b)
        await self.endpoint_ask(end_a, self.connect_op(end_a, end_b, addr_b))
        await self.endpoint_ask(end_b, self.connect_op(end_b, end_a, addr_a))

    async def disconnect_end(self, me: InterfaceRec, peer_iid: int) -> Any:
        """``disconnect`` the connection of ``me`` to interface ``peer_iid``, on ``me``'s endpoint."""
        msg = self.to_end(me, to_robot.EndpointDisconnect, to_env.EnvDisconnect, iid=me.iid, peer_iid=peer_iid)
        return await self.endpoint_ask(me, msg)

    async def tell_disconnect(self, end_a: InterfaceRec, end_b: InterfaceRec) -> None:
        """Tell both ends a connection is gone (quietly: either may be gone too). An end whose task
        set is absent is not waited for: when it re-registers, the master's records (which no
        longer have the connection) are what it reconciles with."""
        for me, peer in ((end_a, end_b), (end_b, end_a)):
            if self._attached(me):
                await self.quiet(self.disconnect_end(me, peer.iid))

    def _attached(self, rec: InterfaceRec) -> bool:
        """The task set holding interface ``rec`` has a link to this master now."""
        if rec.robot_side:
            return rec.location in self.peers
        c = self.state.container_by_cid(rec.location)
        return c is not None and c.tid in self.peers

    async def tell_disconnects(self, pairs: Pairs) -> None:
        for a, b in pairs:
            await self.tell_disconnect(a, b)

    async def readdress(self, container: ContainerRec) -> None:
        """``container`` has a new data address: tell the peers of its interfaces' connections
        (a ``connect`` for a connection that exists replaces the peer's address)."""
        for rec in self.state.interfaces_of(container.user, container.ctag):
            for me, peer in self.state.connections_of(rec.iid):
                await self.quiet(self.endpoint_ask(peer, self.connect_op(peer, me, container.data_addr)))

    def notify_robot(self, user: str, robot: str, type_: str, data: Any) -> None:
        """Send the robot an ST or ER (``notify``) through its endpoint, if it is connected."""
        r = self.state.robot(user, robot)
        peer = self.peers.get(r.tid) if r else None
        if peer:
            msg = to_robot.EndpointNotify(user=user, robot=robot, type=type_, data=data)
            peer.notify(msg.OP, **msg.wire())

    def tell_node_status(self, container: ContainerRec, node: NodeRec, status: str, detail: dict) -> None:
        """ST ``node`` to the container's owner; an ER too when the node exited with an error."""
        self.notify_robot(container.user, container.owner, "ST",
                          {"topic": "node", "cTag": container.ctag, "nTag": node.ntag, "status": status, **detail})
        if status in ("exited", "failed") and (detail.get("code") or detail.get("signal")):
            how = f"code {detail['code']}" if detail.get("code") is not None else f"signal {detail.get('signal')}"
            self.notify_robot(container.user, container.owner, "ER",
                              f"node {node.ntag!r} in container {container.ctag!r} exited with {how}"
                              + (f": {detail['reason']}" if detail.get("reason") else ""))

    # -- teardowns --------------------------------------------------------------------------------------
    async def destroy(self, container: ContainerRec, pairs: Pairs) -> None:
        """After :meth:`MasterState.remove_container`: disconnect its interfaces' peers and
        destroy it on its host (unless lost or being re-created: :mod:`rce_master.failover` undoes that)."""
        await self.tell_disconnects(pairs)
        if not container.down and container.tid in self.peers:      # a recovering one is undone by its re-creation
            try:
                await self.host_ask(container, to_host.DestroyContainer(cid=container.cid))
            except RCEError as e:
                log.warning("destroy failed", ctag=container.ctag, reason=str(e))
        log.info("container destroyed", user=container.user, ctag=container.ctag, cid=container.cid)

    async def robot_gone(self, user: str, robot: str) -> None:
        """A robot left: forget it with its interfaces and destroy the containers it owns."""
        pairs, owned = self.state.robot_disconnect(user, robot)
        await self.tell_disconnects(pairs)
        for c in owned:
            if self.state.containers.get((c.user, c.ctag)) is c:
                await self.destroy(*self.state.remove_container(c.user, c.ctag))

    async def robot_moved(self, recs: list[InterfaceRec]) -> None:
        """After :meth:`MasterState.robot_moved`: install the robot's interfaces ``recs`` on its new
        endpoint (``add_interface``, same iids), then ``connect`` both ends of each of their
        connections with the new data address (the robot then sees ``iu true``). One that fails is
        logged, and its peers told ``disconnect``; the others go on."""
        for rec in recs:
            try:
                await self.install_interface(rec)
            except RCEError as e:
                log.warning("could not move an interface", tag=rec.tag, reason=str(e))
                await self.tell_disconnects(self.state.connections_of(rec.iid))
                continue
            for me, peer in self.state.connections_of(rec.iid):
                await self.quiet(self.tell_connect(me, peer))

    async def cut(self, container: ContainerRec) -> None:
        """``container`` was just lost: the far end of each of its interfaces' connections gets
        ``disconnect`` (a robot-side end then says ``iu false``), quietly. The records stay: its
        re-creation connects them again."""
        for rec in self.state.interfaces_of(container.user, container.ctag, robot_side=False):
            for me, peer in self.state.connections_of(rec.iid):
                if peer.robot_side or peer.location != container.cid:
                    await self.quiet(self.disconnect_end(peer, me.iid))

    def tell_lost(self, container: ContainerRec, why: str) -> None:
        """Tell ``container``'s owner ``ST {topic: container, cTag, status: lost}`` and an ER saying ``why``."""
        self.notify_robot(container.user, container.owner, "ST",
                          {"topic": "container", "cTag": container.ctag, "status": "lost"})
        self.notify_robot(container.user, container.owner, "ER", f"container {container.ctag!r} was lost: {why}")

    async def reconciled(self, out: Reconciled) -> None:
        """After :func:`rce_master.state.reconcile.register`: tell the peers of forgotten interfaces and
        of moved containers, the robots of lost containers and nodes (again, for lost containers
        of the robots it kept: their endpoint was absent when they were lost), and forget the
        robots it did not report. Its lost containers are the failover's (:mod:`rce_master.failover`)."""
        await self.tell_disconnects(out.pairs)
        for c in out.readdressed:
            await self.readdress(c)
        for c, ntag in out.nodes_lost:
            self.notify_robot(c.user, c.owner, "ST", {"topic": "node", "cTag": c.ctag, "nTag": ntag, "status": "lost"})
        kept = {(r.user, r.robot) for r in out.kept}
        for c in self.state.containers.values():
            if c.down and (c.user, c.owner) in kept:
                self.tell_lost(c, "its host went away")
        for r in out.gone:
            await self.robot_gone(r.user, r.robot)
