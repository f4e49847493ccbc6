"""A task set's control link to its master, which outlives the master (docs/INTERNALS.md,
"Master state and restart": "Re-registering" and "The task set's side").

A :class:`MasterLink` dials one of a list of masters and registers. When the link drops (the
master died, restarted, or was replaced by a standby) the task set keeps running: the link
dials again with exponential backoff and jitter (:class:`Backoff`), with no limit on
attempts, and re-registers with the ``tid`` of its first registration and a report of what it
holds. Every link opens with the cluster handshake (:mod:`rce.transport.cluster_auth`): the master
proves it holds the cluster key before anything is said, and so does the task set. A master that
stands by refuses ``register`` naming the leader
(:class:`~rce.plumbing.errors.NotLeader`): the link goes there at once.

While the master is away:

- :meth:`MasterLink.call` waits for it, up to ``master_wait`` s, then raises
  :class:`~rce.plumbing.errors.Unavailable` ("the master is unavailable (waited 30 s)");
- :meth:`MasterLink.notify` with ``keep=True`` puts the notification in a bounded backlog
  (the oldest go first when it is full, counted in ``dropped``), sent in order right after
  the next registration; other notifications are dropped;
- ``available`` is False (the owner answers, e.g., 503).

The backoff follows "Exponential Backoff And Jitter" (AWS Architecture Blog, 2015) with the
knobs of client-go's ``wait.Backoff`` (initial duration, factor, jitter, cap); the link's
settings are keywords with defaults, as nats.py's ``connect`` has them.
"""
from __future__ import annotations

import asyncio
import random
from collections import deque
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

from rce.contract.base import OpArgs
from rce.transport import framing

from rce.transport import rpc
from rce.transport.cluster_auth import AuthFailed, ClusterKey, initiate
from rce.plumbing.errors import ConfigError, NotLeader, RCEError, RequestError, Unavailable
from rce.transport.lane_socket import mark
from rce.transport.link import STREAM_LIMIT, nodelay
from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks
from rce.interfaces.lanes import Lane

log = get_logger("rce.masterlink")
T = TypeVar("T")

MASTER_PORT = 8080        # the master's control port when an address gives none
BACKOFF_INITIAL = 0.05    # s, delay after the first failed round: a master restarting is back in well under 1 s
BACKOFF_FACTOR = 2.0      # each failed round doubles the delay ...
BACKOFF_CAP = 2.0         # s ... up to this: a master that is back is found within BACKOFF_CAP of its start
BACKOFF_JITTER = 0.5      # each delay is drawn from [(1 - JITTER) * d, d]: task sets that lost one master spread out
CONNECT_TIMEOUT = 5.0     # s one dial may take (a master host that is down may never answer the SYN)
REGISTER_TIMEOUT = 30.0   # s for the answer to register (the master reconciles the report and writes its store)
MASTER_SILENCE = 15.0     # s of master silence before the link counts as dead and is dialled again. Longer than
                          # the master's own 4 s verdict on task sets: a busy master is not a lost one
MASTER_WAIT = 30.0        # s a call waits for an absent master before it fails (the master's reconcile grace)
BACKLOG = 1024            # kept notifications waiting for the master to come back; more: the oldest are dropped

Address = tuple[str, int]
Streams = tuple[asyncio.StreamReader, asyncio.StreamWriter]


async def open_tcp(addr: Address) -> Streams:
    """Open a TCP stream to ``addr`` (Nagle off, marked DSCP EF: the control lane, ahead of the data
    that shares a robot's link with it, :mod:`rce.transport.lane_socket`), as every control link does."""
    reader, writer = await asyncio.open_connection(addr[0], addr[1], limit=STREAM_LIMIT)
    nodelay(writer)
    mark(writer.get_extra_info("socket"), Lane.CONTROL)
    return reader, writer


class Backoff:
    """Delays between rounds of attempts: ``initial * factor**n`` s, at most ``cap`` s, each
    shortened by a random fraction of up to ``jitter`` (so a delay lies in ``[(1 - jitter) * d,
    d]``, and never exceeds ``cap``). ``rng()`` returns a float in [0, 1). Raises
    :class:`ConfigError` for settings that make no sense."""

    def __init__(self, initial: float = BACKOFF_INITIAL, factor: float = BACKOFF_FACTOR, cap: float = BACKOFF_CAP,
                 jitter: float = BACKOFF_JITTER, rng: Callable[[], float] = random.random):
        if not (0 < initial <= cap and factor >= 1 and 0 <= jitter < 1):
            raise ConfigError(f"backoff: need 0 < initial <= cap, factor >= 1, 0 <= jitter < 1; got initial "
                              f"{initial:g} s, cap {cap:g} s, factor {factor:g}, jitter {jitter:g}")
        self.initial, self.factor, self.cap, self.jitter, self.rng = initial, factor, cap, jitter, rng
        self.failures = 0

    def ceiling(self) -> float:
        """The next delay before jitter, s."""
        d = self.initial
        for _ in range(self.failures):
            d *= self.factor
            if d >= self.cap:
                return self.cap
        return min(d, self.cap)

    def next(self) -> float:
        """The delay after one more failed round, s."""
        d = self.ceiling()
        self.failures += 1
        return d * (1 - self.jitter * self.rng())

    def reset(self) -> None:
        """A round succeeded: the next failure starts from ``initial`` again."""
        self.failures = 0


def parse_masters(text: str | list[str], default_port: int = MASTER_PORT) -> list[Address]:
    """Master control addresses from ``"HOST[:PORT][,HOST[:PORT]...]"`` (or a list of such
    entries); an IPv6 address with a port is bracketed (``[::1]:8080``), and an entry without
    a port gets ``default_port``. Raises :class:`ConfigError` naming the bad entry."""
    entries = text.split(",") if isinstance(text, str) else list(text)
    out = []
    for raw in entries:
        e = raw.strip()
        host, port = e, default_port
        if e.startswith("["):
            host, sep, rest = e[1:].partition("]")
            if not sep or (rest and not rest.startswith(":")):
                raise ConfigError(f"master address {raw!r}: expected [IPV6] or [IPV6]:PORT")
            port = rest[1:] if rest else default_port
        elif e.count(":") == 1:
            host, port = e.split(":")
        try:
            port = int(port)
        except ValueError:
            raise ConfigError(f"master address {raw!r}: port {port!r} is not a number") from None
        if not host or not 0 < port < 65536:
            raise ConfigError(f"master address {raw!r}: expected HOST or HOST:PORT with a port in 1..65535")
        out.append((host, port))
    if not out:
        raise ConfigError("no master address given")
    return out


def show(addr: Address) -> str:
    """``host:port`` (``[v6]:port``)."""
    return f"[{addr[0]}]:{addr[1]}" if ":" in addr[0] else f"{addr[0]}:{addr[1]}"


class MasterLink:
    """The control link of a task set (rce-robot, rce-container) to its master.

    ``masters``: control addresses (:func:`parse_masters`), tried in turn from the last one that
    worked; ``handlers``: the master's ops this task set serves (installed on every new link);
    ``info``: the ``register`` fields (``kind``, ``name``, ``host``, ...); ``report()``: the
    report fields sent with the ``tid`` when re-registering (``robots``/``interfaces`` or
    ``containers``); ``on_registered(answer)``: obeys a register answer (``drop_containers``,
    ``drop_nodes``, ``drop_interfaces``, ``close_robots``), before calls may go out again.

    Settings (s): ``master_wait`` a call waits for an absent master; ``silence`` of the master
    before the link is dialled again; ``connect_timeout`` of one dial; ``register_timeout``
    for the answer to ``register``; ``backoff`` between rounds of dials (:class:`Backoff`);
    ``backlog``: bound of the kept notifications; ``max_frame``: bytes, as for :class:`RpcPeer`.
    ``dial(addr)`` opens the streams of one attempt and ``sleep(s)`` waits out a backoff delay
    (defaults: TCP and :func:`asyncio.sleep`; tests replace them).

    ``cluster_key``: the :class:`~rce.transport.cluster_auth.ClusterKey` both ends prove they hold on every
    new link, before ``register``; a master that refuses it at the first registration is a
    mistake (:class:`~rce.transport.cluster_auth.AuthFailed` from :meth:`start`), later it is logged and
    dialled again.

    ``tid``, ``address`` (where it registered last), ``attempts`` (dials), ``registrations``,
    ``dropped`` (kept notifications dropped), ``lost_at`` (loop time the master went away; None
    while it is here)."""

    def __init__(self, masters: list[Address], handlers: dict[str, rpc.Handler], info: dict, *,
                 cluster_key: ClusterKey, report: Callable[[], dict] = dict,
                 on_registered: Callable[[dict], Awaitable[None]] | None = None,
                 name: str = "master", master_wait: float = MASTER_WAIT, silence: float = MASTER_SILENCE,
                 connect_timeout: float = CONNECT_TIMEOUT, register_timeout: float = REGISTER_TIMEOUT,
                 backoff: Backoff | None = None, backlog: int = BACKLOG,
                 max_frame: int = framing.DEFAULT_MAX_FRAME,
                 dial: Callable[[Address], Awaitable[Streams]] = open_tcp,
                 sleep: Callable[[float], Awaitable[Any]] = asyncio.sleep):
        if not masters:
            raise ConfigError("no master address given")
        self.masters = list(masters)
        self.handlers, self.info, self.report, self.on_registered = handlers, info, report, on_registered
        self.cluster_key = cluster_key
        self.name, self.master_wait, self.silence = name, master_wait, silence
        self.connect_timeout, self.register_timeout = connect_timeout, register_timeout
        self.backoff = backoff or Backoff()
        self.max_frame, self.dial, self.sleep = max_frame, dial, sleep
        self.tid: Any = None
        self.peer: rpc.RpcPeer | None = None          # the registered link; None while the master is away
        self.address: Address | None = None
        self.attempts = self.registrations = self.dropped = 0
        self.lost_at: float | None = None
        self._backlog: deque[tuple[str, dict]] = deque(maxlen=backlog)
        self._available = asyncio.Event()              # registered and the answer obeyed (also set by close)
        self._closed = False
        self._first: asyncio.Future | None = None
        self._tasks = Tasks(f"link to {name}")

    @property
    def available(self) -> bool:
        """The master is here: registered, and its answer obeyed."""
        return self._available.is_set() and not self._closed

    # -- lifecycle -----------------------------------------------------------------------------
    async def start(self) -> dict:
        """Dial and register (retrying with backoff for as long as it takes), then keep the link
        up in the background; returns the first register answer. Raises the master's
        :class:`RequestError` when it refuses this task set outright, :class:`AuthFailed` when
        the cluster keys differ, and :class:`Unavailable`
        when :meth:`close` is called first."""
        self._first = asyncio.get_running_loop().create_future()
        self._tasks.spawn(self._run(), name="dial")
        return await self._first

    async def close(self) -> None:
        """Stop dialling and close the link; calls waiting for the master fail at once."""
        self._closed = True
        self._available.set()             # wake the waiters: they see the link closed
        if self._first is not None and not self._first.done():
            self._first.set_exception(Unavailable(f"the link to the {self.name} was closed before it registered"))
        await self._tasks.cancel_all()
        if self.peer is not None:
            await self.peer.close()

    # -- calls ------------------------------------------------------------------------------------
    async def call(self, op: str, timeout: float | None = rpc.CALL_TIMEOUT, **args: Any) -> Any:
        """Send request ``op`` once the master is here (waiting up to ``master_wait`` s) and await
        its result. Raises :class:`Unavailable` when the master stays away or goes away before it
        answers, the master's :class:`RCEError`, or :class:`~rce.plumbing.errors.Timeout` after ``timeout`` s."""
        return await self.request(op, args, timeout)

    async def request(self, op: str, args: dict, timeout: float | None = rpc.CALL_TIMEOUT) -> Any:
        """:meth:`call` with the op's arguments as a dict."""
        peer = await self._here()
        try:
            return await peer.request(op, args, timeout)
        except Unavailable:
            if peer.closed.is_set():
                raise Unavailable(f"the {self.name} went away before it answered (it may have done it)") from None
            raise

    async def ask(self, msg: OpArgs, timeout: float | None = rpc.CALL_TIMEOUT) -> Any:
        """:meth:`call` with typed op ``msg`` (:mod:`rce.contract`)."""
        return await self.request(msg.OP, msg.wire(), timeout)

    def tell(self, msg: OpArgs, *, keep: bool = False) -> bool:
        """:meth:`notify` with typed op ``msg`` (:mod:`rce.contract`)."""
        return self._notify(msg.OP, msg.wire(), keep)

    def notify(self, op: str, *, keep: bool = False, **args: Any) -> bool:
        """Send notification ``op`` if the master is here. Otherwise, with ``keep``, it waits in
        the backlog for the next registration (the oldest is dropped when it is full, counted in
        ``dropped``); without, it is dropped. True when it went out now."""
        return self._notify(op, args, keep)

    def _notify(self, op: str, args: dict, keep: bool) -> bool:
        if self.peer is not None and not self.peer.closed.is_set() and not self._backlog:
            self.peer.notify(op, **args)
            return True
        if keep:
            if len(self._backlog) == self._backlog.maxlen:
                self.dropped += 1
            self._backlog.append((op, args))
        return False

    async def _here(self) -> rpc.RpcPeer:
        if self._closed:
            raise Unavailable(f"the link to the {self.name} is closed")
        if not self._available.is_set():
            try:
                async with asyncio.timeout(self.master_wait):
                    await self._available.wait()
            except TimeoutError:
                raise Unavailable(f"the {self.name} is unavailable (waited {self.master_wait:g} s)") from None
        if self._closed or self.peer is None:
            raise Unavailable(f"the link to the {self.name} is closed")
        return self.peer

    # -- dialling -----------------------------------------------------------------------------------
    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        while not self._closed:
            try:
                peer, answer = await self._register_somewhere()
            except (RequestError, AuthFailed) as e:   # refused at the first registration: a mistake, not an outage
                if not self._first.done():
                    self._first.set_exception(e)
                return
            if self._closed:      # closed while the answer was on its way: close() did not stop this registration
                await peer.close()
                return
            self.peer, self.tid = peer, answer.get("tid", self.tid)
            self.registrations += 1
            away = None if self.lost_at is None else round(loop.time() - self.lost_at, 3)
            log.info("registered with the master", master=show(self.address), tid=self.tid,
                     resumed=answer.get("resumed"), away_s=away, kept=len(self._backlog),
                     drop_containers=answer.get("drop_containers"), drop_nodes=answer.get("drop_nodes"),
                     drop_interfaces=answer.get("drop_interfaces"), close_robots=answer.get("close_robots"))
            self._flush()
            await self._obey(answer)
            self.lost_at = None
            self._available.set()
            if not self._first.done():
                self._first.set_result(answer)
            await peer.closed.wait()
            self._available.clear()
            self.peer, self.lost_at = None, loop.time()
            if not self._closed:
                log.warning("control link to the master lost; dialling again", master=show(self.address),
                            reason=peer.link.close_reason)

    def _closed_link(self, peer: rpc.RpcPeer) -> None:
        """A link closed: when it is the registered one, the master is away from now on (calls wait)."""
        if peer is self.peer and not self._closed:
            self._available.clear()

    async def _obey(self, answer: dict) -> None:
        if self.on_registered is None:
            return
        try:
            await self.on_registered(answer)
        except Exception as e:        # the link stays: what could not be done is logged
            log.error("could not do what the master's register answer asked", exc_info=e)

    def _flush(self) -> None:
        while self._backlog and self.peer is not None:
            op, args = self._backlog.popleft()
            self.peer.notify(op, **args)

    def _order(self) -> list[Address]:
        """The addresses of one round: where it registered last first (a leader it was sent to
        need not be in the list), then the list."""
        first = [self.address] if self.address is not None else []
        return first + [a for a in self.masters if a != self.address]

    async def _register_somewhere(self) -> tuple[rpc.RpcPeer, dict]:
        """Rounds of attempts over the masters, with a backoff delay after each failed round."""
        self.backoff.reset()
        rounds = 0
        while True:
            for addr in self._order():
                got = await self._try(addr)
                if got is not None:
                    return got
            rounds += 1
            delay = self.backoff.next()
            (log.warning if rounds == 1 else log.debug)("no master reachable; trying again", rounds=rounds,
                                                        delay_s=round(delay, 3))
            await self.sleep(delay)      # the backoff timer

    async def _try(self, addr: Address) -> tuple[rpc.RpcPeer, dict] | None:
        """Register at ``addr``, or at the leader a standby there names; None when that fails.
        Raises :class:`RequestError` for a refusal of the first registration."""
        for hop in range(2):
            try:
                peer, answer = await self._attempt(addr)
                self.address = addr
                return peer, answer
            except NotLeader as e:
                leader = (e.leader or {}).get("control")
                log.debug("the master stands by", master=show(addr), leader=leader)
                if hop or not leader:
                    return None
                try:
                    addr = parse_masters(leader)[0]
                except ConfigError as bad:
                    log.warning("a standby named a leader that is no address", leader=leader, reason=bad.message)
                    return None
            except (RequestError, AuthFailed) as e:     # refused (or the cluster keys differ): a mistake at first
                if self.tid is None:
                    raise
                log.error("the master refused to take this task set back; trying again", master=show(addr),
                          reason=e.message)
                return None
            except (OSError, TimeoutError, RCEError) as e:
                log.debug("master not reachable", master=show(addr), reason=str(e))
                return None
            except Exception as e:        # a bug: logged, and the link keeps trying
                log.error("registering with the master failed", master=show(addr), exc_info=e)
                return None
        return None

    async def _attempt(self, addr: Address) -> tuple[rpc.RpcPeer, dict]:
        self.attempts += 1
        async with asyncio.timeout(self.connect_timeout):    # not wait_for: it may swallow a cancel (3.11)
            reader, writer = await self.dial(addr)
        try:
            await initiate(reader, writer, self.cluster_key)
        except BaseException:
            writer.close()
            raise
        peer = rpc.RpcPeer(reader, writer, self.handlers, name=self.name, max_frame=self.max_frame,
                           on_close=self._closed_link).start()
        args = dict(self.info)
        if self.tid is not None:
            args.update(self.report(), tid=self.tid)
        try:
            answer = await peer.request("register", args, self.register_timeout)
        except BaseException:
            await peer.close()
            raise
        peer.keepalive(timeout=self.silence)
        return peer, answer if isinstance(answer, dict) else {}


async def unless_stopped(aw: Awaitable[T], stopped: asyncio.Event) -> T | None:
    """Await ``aw`` unless ``stopped`` is set first (then ``aw`` is cancelled and None returned):
    a task set stopped while it waits for its first registration."""
    work, stop = asyncio.ensure_future(aw), asyncio.ensure_future(stopped.wait())
    try:
        await asyncio.wait([work, stop], return_when=asyncio.FIRST_COMPLETED)
    finally:
        stop.cancel()
        if not work.done():
            work.cancel()
            await asyncio.wait([work])
    return work.result() if not work.cancelled() else None
