"""Corked websocket writes: a message's frames (a DM's JSON text frame and its binary parts) go
to the socket in one ``transport.writelines`` (one ``writev`` on uvloop), written at once by the
caller instead of one awaited ``send`` (a lock, an async context manager and a ``write`` system
call) per frame.

It works on a :class:`websockets.asyncio.connection.Connection` through its sans-I/O protocol
(``protocol.send_text``/``send_binary``/``data_to_send``: RFC 6455 framing, masking on the
client side) and its transport. Flow control stays the connection's: :func:`writable` is false
while the transport's buffer is above its high-water mark (``paused``, set by the transport
during the write that crossed it) or the connection is not open; then the caller waits
(``await ws.drain()``) or falls back to ``await ws.send(frame)``, which raises
:class:`~websockets.exceptions.ConnectionClosed` on a closed link. Anything that is not such a
connection (a test double, another library) is never :func:`writable`: the caller sends.
"""
from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from websockets.protocol import State


def corkable(ws: Any) -> bool:
    """Is ``ws`` a websockets asyncio connection whose protocol and transport this module drives?"""
    return hasattr(ws, "protocol") and hasattr(ws, "transport") and hasattr(ws, "paused")


def writable(ws: Any) -> bool:
    """Can :func:`write` take frames for ``ws`` now: open, and its transport not above its
    high-water mark?"""
    return corkable(ws) and not ws.paused and ws.protocol.state is State.OPEN


def paused(ws: Any) -> bool:
    """Is the open connection ``ws`` waiting for its transport to drain (``await ws.drain()``)?"""
    return corkable(ws) and ws.paused and ws.protocol.state is State.OPEN


def write(ws: Any, frames: Iterable[str | bytes]) -> int:
    """Frame ``frames`` (str: a text frame, bytes: a binary frame) and write them to ``ws``'s
    transport in one ``writelines``; returns the bytes written. Call only while
    :func:`writable`; the transport buffers what the socket does not take at once."""
    proto = ws.protocol
    for f in frames:
        if isinstance(f, str):
            proto.send_text(f.encode())
        else:
            proto.send_binary(f)
    out = proto.data_to_send()
    ws.transport.writelines(out)
    return sum(map(len, out))
