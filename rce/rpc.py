"""Control-plane peer: request/response and notifications over one framed link, both ways.

Wire (CONTROL frames): request ``{"id": n, "op": str, "args": {...}}``; reply
``{"re": n, "ok": true, "result": ...}`` or ``{"re": n, "ok": false, "error":
{"code", "message"}}``; notification ``{"op": str, "args": {...}}`` (no id).
DATA frames on the same link go to ``on_data``.

Each incoming request runs in its own task, so a slow handler never stalls the
link; handlers that need ordering serialise themselves (the master keeps one
queue per robot).
"""
from __future__ import annotations

import asyncio
import itertools
from typing import Any, Awaitable, Callable

from rce import framing
from rce.errors import ProtocolError, RCEError, Unavailable
from rce.log import get_logger

Handler = Callable[[dict], Awaitable[Any]]
log = get_logger("rce.rpc")


class RpcPeer:
    """One end of a control link.

    ``handlers`` maps op names to ``async def handler(args) -> result``; a handler raises
    :class:`RCEError` to refuse. ``on_data(frame)`` receives DATA frames; ``on_close(peer)``
    runs once when the link ends."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                 handlers: dict[str, Handler] | None = None, *, name: str = "peer",
                 on_data: Callable[[framing.DataFrame], Any] | None = None,
                 on_close: Callable[["RpcPeer"], Any] | None = None,
                 max_frame: int = framing.DEFAULT_MAX_FRAME):
        self.reader, self.writer = reader, writer
        self.handlers = dict(handlers or {})
        self.name = name
        self.on_data = on_data
        self.on_close = on_close
        self.max_frame = max_frame
        self.info: dict = {}          # free slot for whoever owns the peer (e.g. registration data)
        self._ids = itertools.count(1)
        self._pending: dict[int, asyncio.Future] = {}
        self._tasks: set[asyncio.Task] = set()
        self._reader_task: asyncio.Task | None = None
        self._keepalive_task: asyncio.Task | None = None
        self.last_rx = 0.0          # loop time of the last frame received
        self.closed = asyncio.Event()
        self.handlers.setdefault("ping", _pong)

    def start(self) -> "RpcPeer":
        """Start reading the link in the background; returns self."""
        self._reader_task = asyncio.create_task(self._read_loop(), name=f"rpc-{self.name}")
        return self

    def keepalive(self, interval: float = 1.0, timeout: float = 4.0) -> None:
        """Send a ``ping`` notification every ``interval`` s and close the link when nothing has
        arrived for ``timeout`` s (a peer that is gone without closing its socket, or a
        partitioned network, is detected within ``timeout``)."""
        async def run() -> None:
            loop = asyncio.get_running_loop()
            while not self.closed.is_set():
                await asyncio.sleep(interval)
                if loop.time() - self.last_rx > timeout:
                    log.warning("control link silent, closing", peer=self.name, silent_s=round(loop.time() - self.last_rx, 1))
                    await self.close()
                    return
                self.notify("ping")
        self._keepalive_task = asyncio.create_task(run())

    @property
    def peername(self) -> str:
        p = self.writer.get_extra_info("peername")
        return f"{p[0]}:{p[1]}" if isinstance(p, tuple) else str(p)

    async def call(self, op: str, timeout: float | None = 30.0, **args) -> Any:
        """Send request ``op`` and await its result. Raises the peer's :class:`RCEError`,
        or :class:`Unavailable` when the link closes or ``timeout`` (s) passes."""
        return await self.request(op, args, timeout)

    async def request(self, op: str, args: dict, timeout: float | None = 30.0) -> Any:
        """:meth:`call` with the op's arguments as a dict, for arguments that may include a key
        named ``timeout`` (``bus_call``, ``bus_sample``), which ``call(**args)`` cannot pass."""
        if self.closed.is_set():
            raise Unavailable(f"control link to {self.name} is closed")
        rid = next(self._ids)
        fut = asyncio.get_running_loop().create_future()
        self._pending[rid] = fut
        try:
            self.writer.write(framing.encode_control({"id": rid, "op": op, "args": args}))
            return await asyncio.wait_for(fut, timeout)
        except asyncio.TimeoutError:
            raise Unavailable(f"{self.name} did not answer {op!r} within {timeout} s") from None
        finally:
            self._pending.pop(rid, None)

    def notify(self, op: str, **args) -> None:
        """Send a notification (no reply). Silently ignored on a closed link."""
        if not self.closed.is_set():
            self.writer.write(framing.encode_control({"op": op, "args": args}))

    def send_raw(self, data: bytes) -> None:
        """Write pre-framed bytes (DATA frames) to the link."""
        if not self.closed.is_set():
            self.writer.write(data)

    async def close(self) -> None:
        """Close the link and wait for the reader to stop."""
        if self._keepalive_task and self._keepalive_task is not asyncio.current_task():
            self._keepalive_task.cancel()
        if self._reader_task and not self._reader_task.done():
            self._reader_task.cancel()
        try:
            self.writer.close()
        except Exception:
            pass
        if self._reader_task:
            try:
                await self._reader_task
            except (asyncio.CancelledError, Exception):
                pass
        self._finish()

    def _finish(self) -> None:
        if self.closed.is_set():
            return
        self.closed.set()
        for fut in self._pending.values():
            if not fut.done():
                fut.set_exception(Unavailable(f"control link to {self.name} closed"))
        if self.on_close:
            try:
                self.on_close(self)
            except Exception:
                log.exception("on_close handler failed", peer=self.name)

    async def _read_loop(self) -> None:
        loop = asyncio.get_running_loop()
        self.last_rx = loop.time()
        try:
            while True:
                frame = await framing.read_frame(self.reader, self.max_frame)
                self.last_rx = loop.time()
                if isinstance(frame, framing.DataFrame):
                    if self.on_data:
                        self.on_data(frame)
                    continue
                self._dispatch(frame)
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        except ProtocolError as e:
            log.warning("closing control link on bad frame", peer=self.name, reason=str(e))
        except asyncio.CancelledError:
            raise
        except Exception:
            log.exception("control link failed", peer=self.name)
        finally:
            try:
                self.writer.close()
            except Exception:
                pass
            self._finish()

    def _dispatch(self, msg: dict) -> None:
        if "re" in msg:
            fut = self._pending.get(msg["re"])
            if fut and not fut.done():
                if msg.get("ok"):
                    fut.set_result(msg.get("result"))
                else:
                    fut.set_exception(RCEError.from_dict(msg.get("error") or {}))
            return
        op = msg.get("op")
        handler = self.handlers.get(op)
        rid = msg.get("id")
        if handler is None:
            if rid is not None:
                self._reply(rid, False, error=ProtocolError(f"unknown control op {op!r}").to_dict())
            return
        t = asyncio.create_task(self._run(handler, msg.get("args") or {}, rid))
        self._tasks.add(t)
        t.add_done_callback(self._tasks.discard)

    async def _run(self, handler: Handler, args: dict, rid: int | None) -> None:
        try:
            result = await handler(args)
        except RCEError as e:
            if rid is not None:
                self._reply(rid, False, error=e.to_dict())
            return
        except Exception as e:
            log.exception("control handler failed", peer=self.name)
            if rid is not None:
                self._reply(rid, False, error=RCEError(f"internal error: {type(e).__name__}: {e}").to_dict())
            return
        if rid is not None:
            self._reply(rid, True, result=result)

    def _reply(self, rid: int, ok: bool, **kw) -> None:
        if not self.closed.is_set():
            self.writer.write(framing.encode_control({"re": rid, "ok": ok, **kw}))


async def _pong(args: dict) -> None:
    return None


async def connect(host: str, port: int, handlers: dict[str, Handler] | None = None, **kw) -> RpcPeer:
    """Open a TCP control link to ``host:port`` and start it."""
    reader, writer = await asyncio.open_connection(host, port, limit=2**20)
    _nodelay(writer)
    return RpcPeer(reader, writer, handlers, **kw).start()


async def connect_unix(path: str, handlers: dict[str, Handler] | None = None, **kw) -> RpcPeer:
    """Open a Unix-socket link (container bus) to ``path`` and start it."""
    reader, writer = await asyncio.open_unix_connection(path, limit=2**20)
    return RpcPeer(reader, writer, handlers, **kw).start()


def _nodelay(writer: asyncio.StreamWriter) -> None:
    import socket
    sock = writer.get_extra_info("socket")
    if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


nodelay = _nodelay
