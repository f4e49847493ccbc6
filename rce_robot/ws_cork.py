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

import asyncio
import fcntl
import struct
import termios
from collections.abc import Iterable
from typing import Any

from websockets.protocol import Side, State

RAW_MIN = 64 * 1024     # bytes: a binary frame this large is framed here, not copied into websockets' frame
_INT = struct.Struct("i")
_ZERO = bytes(_INT.size)


def corkable(ws: Any) -> bool:
    """Is ``ws`` a websockets asyncio connection whose protocol and transport this module drives?"""
    return hasattr(ws, "protocol") and hasattr(ws, "transport") and hasattr(ws, "paused")


def writable(ws: Any) -> bool:
    """Can :func:`write` take frames for ``ws`` now: open, and its transport not above its
    high-water mark?"""
    return corkable(ws) and not ws.paused and ws.protocol.state is State.OPEN


def backlog(ws: Any) -> int:
    """Frames ``ws`` has received that its reader has not taken yet (0 for anything that is not a
    websockets asyncio connection)."""
    frames = getattr(getattr(ws, "recv_messages", None), "frames", None)
    return len(frames) if frames is not None else 0


def unread(ws: Any) -> int:
    """Bytes of ``ws``'s that the kernel has received and nobody has read yet (``FIONREAD`` on its
    socket, tcp(7)): what waits behind the frames :func:`backlog` counts. 0 for anything that is
    not a websockets asyncio connection on a socket."""
    return fionread(ws.transport.get_extra_info("socket") if corkable(ws) else None)


def fionread(sock: Any) -> int:
    """Bytes the kernel has received on ``sock`` that nobody has read yet (``FIONREAD``, tcp(7)); 0 for
    None or a closed socket."""
    if sock is None:
        return 0
    try:
        return _INT.unpack(fcntl.ioctl(sock.fileno(), termios.FIONREAD, _ZERO))[0]
    except (OSError, ValueError):        # closed meanwhile
        return 0


def behind(ws: Any) -> int:
    """Frames (:func:`backlog`), else bytes (:func:`unread`), of ``ws``'s waiting to be taken: 0
    when the reader has taken everything the peer sent so far."""
    return backlog(ws) or unread(ws)


async def take_turn(ws: Any) -> None:
    """Let the loop's other work go first (other robots' frames, keepalives, the data plane)
    when ``ws`` has more received frames waiting (:func:`backlog`): one client's burst is then
    served frame by frame among the others, fair under load."""
    if backlog(ws):
        await asyncio.sleep(0)


def paused(ws: Any) -> bool:
    """Is the open connection ``ws`` waiting for its transport to drain (``await ws.drain()``)?"""
    return corkable(ws) and ws.paused and ws.protocol.state is State.OPEN


def write(ws: Any, frames: Iterable[str | bytes]) -> int:
    """Frame ``frames`` (str: a text frame, bytes: a binary frame) and write them to ``ws``'s
    transport in one ``writelines``; returns the bytes written. Call only while
    :func:`writable`; the transport buffers what the socket does not take at once. On a
    server's connection without extensions a binary frame of :data:`RAW_MIN` bytes or more gets
    its header here (:func:`binary_header`) and goes out uncopied."""
    proto = ws.protocol
    raw = proto.side is Side.SERVER and not proto.extensions     # unmasked, uncompressed: framing is a header
    out: list = []
    for f in frames:
        if isinstance(f, str):
            proto.send_text(f.encode())
        elif raw and len(f) >= RAW_MIN:
            out.extend(proto.data_to_send())
            out.append(binary_header(len(f)))
            out.append(f)                     # not copied into a frame buffer
        else:
            proto.send_binary(f)
    out.extend(proto.data_to_send())
    ws.transport.writelines(out)
    return sum(map(len, out))


def binary_header(nbytes: int) -> bytes:
    """The header of an unmasked, unfragmented binary frame of ``nbytes`` payload bytes."""
    return frame_header(0x82, nbytes)


def frame_header(first: int, nbytes: int) -> bytes:
    """The header of an unmasked frame whose first byte (FIN, opcode) is ``first`` and whose payload is
    ``nbytes`` bytes (RFC 6455 section 5.2: the 7-bit, 16-bit or 64-bit payload length)."""
    if nbytes < 126:
        return bytes((first, nbytes))
    if nbytes < 1 << 16:
        return bytes((first, 126)) + nbytes.to_bytes(2, "big")
    return bytes((first, 127)) + nbytes.to_bytes(8, "big")
