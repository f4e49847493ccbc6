"""Control-plane peer: request/response and notifications over one framed link, both ways.

Wire (CONTROL frames): request ``{"id": n, "op": str, "args": {...}}``; reply
``{"re": n, "ok": true, "result": ...}`` or ``{"re": n, "ok": false, "error":
{"code", "message"}}``; notification ``{"op": str, "args": {...}}`` (no id).
DATA frames on the same link go to ``on_data``. A TCP control link opens with the cluster
handshake (:mod:`rce.transport.cluster_auth`: :func:`connect` here, :class:`~rce.transport.cluster_auth.Gate` at the
master) before the first of these frames.

A typed op (:mod:`rce.contract`) is sent as its model (:meth:`RpcPeer.ask`, :meth:`RpcPeer.tell`) and
parsed into it by the receiving :class:`~rce.transport.op_table.OpTable`: the wire is the same.

Each incoming request runs in its own task (:class:`rce.transport.link.Responder`), so a slow handler
never stalls the link; handlers that need ordering serialise themselves (the master keeps
one queue per robot). Control frames are never dropped: a peer that leaves more than the
link's hard bound unread is cut off (the link closes and every call on it fails).
"""
from __future__ import annotations

import asyncio
from typing import Any, Callable

from rce.contract.base import OpArgs
from rce.transport.op_table import Handler
from rce.transport import cluster_auth

from rce.transport import framing
from rce.plumbing.errors import ProtocolError, RCEError, Unavailable
from rce.transport.link import STREAM_LIMIT, FramedLink, LinkFull, Responder, nodelay
from rce.plumbing.log import get_logger
from rce.plumbing.pending import PendingCalls
from rce.plumbing.tasks import Tasks

log = get_logger("rce.rpc")

CALL_TIMEOUT = 30.0          # s a control request waits for its reply unless the caller says otherwise
KEEPALIVE_INTERVAL = 1.0     # s between the pings of :meth:`RpcPeer.keepalive`
KEEPALIVE_TIMEOUT = 4.0      # s of silence after which :meth:`RpcPeer.keepalive` closes the link as dead
CONTROL_MAX_BUFFER = 64 * 1024 * 1024   # bytes that may wait unread (control frames: twice that, then the link is cut)
MAX_REQUESTS = 4096          # incoming requests one link runs at once (one per robot in flight, and more)

__all__ = ["RpcPeer", "connect", "connect_unix", "nodelay"]


class RpcPeer:
    """One end of a control link (also the node <-> bus link).

    ``handlers`` maps op names to ``async def handler(args) -> result``; a handler raises
    :class:`RCEError` to refuse. ``on_data(frame)`` receives DATA frames; ``on_close(peer)``
    runs once when the link ends; ``max_frame``, ``max_buffer``: bytes, as for the
    :class:`~rce.transport.link.FramedLink` (``link``); ``info`` is a free slot for whoever owns the
    peer (e.g. registration data)."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                 handlers: dict[str, Handler] | None = None, *, name: str = "peer",
                 on_data: Callable[[framing.DataFrame], Any] | None = None,
                 on_close: Callable[["RpcPeer"], Any] | None = None,
                 max_frame: int = framing.DEFAULT_MAX_FRAME, max_buffer: int = CONTROL_MAX_BUFFER):
        self.link = FramedLink(reader, writer, name=name, on_frame=self._on_frame, on_close=self._link_closed,
                               max_frame=max_frame, max_buffer=max_buffer)
        self.handlers = dict(handlers or {})
        self.handlers.setdefault("ping", _pong)
        self.on_data = on_data
        self.on_close = on_close
        self.info: dict = {}
        self.calls = PendingCalls(name)
        self.tasks = Tasks(f"rpc {name}")
        self.responder = Responder(f"control link {name}", self.tasks, MAX_REQUESTS)
        self.closed = self.link.closed
        self._keepalive: asyncio.Task | None = None

    @property
    def name(self) -> str:
        """The peer's name in logs and errors (its owner may rename it, e.g. once registered)."""
        return self.link.name

    @name.setter
    def name(self, value: str) -> None:
        self.link.name = self.calls.name = value
        self.responder.owner = f"control link {value}"

    @property
    def peername(self) -> str:
        """The peer's address (``host:port``, or the Unix socket path)."""
        return self.link.peername

    @property
    def last_rx(self) -> float:
        """Loop time of the last bytes received."""
        return self.link.last_rx

    def start(self) -> "RpcPeer":
        """Start reading the link in the background; returns self."""
        self.link.start()
        return self

    def keepalive(self, interval: float = KEEPALIVE_INTERVAL, timeout: float = KEEPALIVE_TIMEOUT) -> None:
        """Send a ``ping`` notification every ``interval`` s and close the link when nothing has
        arrived for ``timeout`` s (a peer that is gone without closing its socket, or a
        partitioned network, is detected within ``timeout``)."""
        async def run() -> None:
            loop = asyncio.get_running_loop()
            while not self.closed.is_set():
                await asyncio.sleep(interval)
                silent = loop.time() - self.link.last_rx
                if silent > timeout:
                    log.warning("control link silent, closing", peer=self.name, silent_s=round(silent, 1))
                    self.link.close(f"silent for {silent:.1f} s")
                    return
                self.notify("ping")
        self._keepalive = self.tasks.spawn(run(), name="keepalive")

    async def call(self, op: str, timeout: float | None = CALL_TIMEOUT, **args) -> Any:
        """Send request ``op`` and await its result. Raises the peer's :class:`RCEError`,
        :class:`Unavailable` when the link is or becomes closed (or saturated), and
        :class:`~rce.plumbing.errors.Timeout` when ``timeout`` (s) passes."""
        return await self.request(op, args, timeout)

    async def request(self, op: str, args: dict, timeout: float | None = CALL_TIMEOUT) -> Any:
        """:meth:`call` with the op's arguments as a dict, for arguments that may include a key
        named ``timeout`` (``bus_call``, ``bus_sample``), which ``call(**args)`` cannot pass."""
        if self.closed.is_set():
            raise Unavailable(f"control link to {self.name} is closed")
        return await self.calls.call(lambda rid: self._send({"id": rid, "op": op, "args": args}), timeout,
                                     what=repr(op))

    async def ask(self, msg: OpArgs, timeout: float | None = CALL_TIMEOUT) -> Any:
        """Send op ``msg`` (its ``OP``, its :meth:`~rce.contract.base.OpArgs.wire` as the arguments) and
        await its result; raises as :meth:`call` does."""
        return await self.request(msg.OP, msg.wire(), timeout)

    def tell(self, msg: OpArgs) -> None:
        """Send op ``msg`` as a notification (no reply). Ignored on a closed link."""
        self._send_quietly({"op": msg.OP, "args": msg.wire()})

    def notify(self, op: str, **args) -> None:
        """Send a notification (no reply). Ignored on a closed link."""
        self._send_quietly({"op": op, "args": args})

    def send_raw(self, frame: bytes, payload: bytes | memoryview = b"") -> None:
        """Write pre-framed bytes (a DATA frame's header, then its payload: no copy) that must
        not be lost. Ignored on a closed link; a peer that leaves the link's hard bound unread
        is cut off (:meth:`_write`)."""
        try:
            self._write(frame, payload)
        except Unavailable:
            pass

    async def close(self) -> None:
        """Close the link and wait for the reader to stop."""
        self.link.close()
        await self.link.wait_closed()

    # -- internals -------------------------------------------------------------------------------
    def _write(self, frame: bytes, payload: bytes | memoryview = b"") -> None:
        """The policy for frames that must not be lost: rather than drop one, cut the link of
        a peer that no longer reads (its calls fail, its owner sees it closed)."""
        try:
            self.link.send(frame, payload)
        except LinkFull as e:
            log.warning("control link saturated, closing", peer=self.name, reason=e.message)
            self.link.close(e.message)
            raise

    def _send(self, obj: dict) -> None:
        self._write(framing.encode_control(obj))

    def _send_quietly(self, obj: dict) -> None:
        """Replies and notifications: nobody waits to hear that the link is gone."""
        try:
            self._send(obj)
        except Unavailable:
            pass

    def _link_closed(self, _link: FramedLink) -> None:
        if self._keepalive is not None and self._keepalive is not asyncio.current_task():
            self._keepalive.cancel()
        self.calls.fail_all(Unavailable(f"control link to {self.name} closed"))
        if self.on_close:
            try:
                self.on_close(self)
            except Exception as e:
                log.error("on_close handler failed", peer=self.name, exc_info=e)

    def _on_frame(self, msg: dict | framing.DataFrame) -> None:
        if isinstance(msg, framing.DataFrame):
            if self.on_data:
                self.on_data(msg)
            return
        if "re" in msg:
            self._settle(msg)
            return
        op, rid = msg.get("op"), msg.get("id")
        if rid is None and op == "ping":
            return                       # a keepalive: receiving it was the point
        handler = self.handlers.get(op)
        if handler is None:
            if rid is not None:
                self._reply(rid, False, error=ProtocolError(f"unknown control op {op!r}").to_dict())
            return
        args = msg.get("args") or {}
        if rid is None:
            self.responder.serve(lambda: handler(args), _ignore, self._notification_refused(op), f"notification {op}")
        else:
            self.responder.serve(lambda: handler(args), lambda result: self._reply(rid, True, result=result),
                                 lambda error: self._reply(rid, False, error=error.to_dict()), f"request {op}")

    def _settle(self, msg: dict) -> None:
        rid = msg["re"]
        if not isinstance(rid, int):
            raise ProtocolError(f"reply to {rid!r}: a request id is an integer")
        if msg.get("ok"):
            self.calls.settle(rid, msg.get("result"))
        else:
            self.calls.fail(rid, RCEError.from_dict(msg.get("error") or {}))

    def _notification_refused(self, op: str) -> Callable[[RCEError], None]:
        def refused(error: RCEError) -> None:
            log.warning("notification refused", peer=self.name, op=op, reason=error.message)
        return refused

    def _reply(self, rid: Any, ok: bool, **kw) -> None:
        self._send_quietly({"re": rid, "ok": ok, **kw})


def _ignore(_result: Any) -> None:
    pass


async def _pong(args: dict) -> None:
    return None


async def connect(host: str, port: int, handlers: dict[str, Handler] | None = None, *,
                  cluster_key: cluster_auth.ClusterKey, **kw) -> RpcPeer:
    """Open a TCP control link to ``host:port``, prove both ends hold ``cluster_key``
    (:func:`rce.transport.cluster_auth.initiate`: raises :class:`~rce.transport.cluster_auth.AuthFailed`,
    :class:`ProtocolError`, :class:`~rce.plumbing.errors.Timeout`, :class:`OSError`) and start it."""
    reader, writer = await asyncio.open_connection(host, port, limit=STREAM_LIMIT)
    nodelay(writer)
    try:
        await cluster_auth.initiate(reader, writer, cluster_key)
    except BaseException:
        writer.close()
        raise
    return RpcPeer(reader, writer, handlers, **kw).start()


async def connect_unix(path: str, handlers: dict[str, Handler] | None = None, **kw) -> RpcPeer:
    """Open a Unix-socket link (container bus) to ``path`` and start it."""
    reader, writer = await asyncio.open_unix_connection(path, limit=STREAM_LIMIT)
    return RpcPeer(reader, writer, handlers, **kw).start()
