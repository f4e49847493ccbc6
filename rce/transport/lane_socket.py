"""The socket side of lanes (docs/lanes.md): DSCP marks and TCP options per lane, and MPTCP sockets.

- :func:`mark`: a connection's lane in its socket. The session's own link, once a bulk link has joined
  it, is the control lane: DSCP EF (``IP_TOS`` 0xB8, RFC 3246; ``IPV6_TCLASS`` on IPv6), ``TCP_NODELAY``,
  and ``TCP_NOTSENT_LOWAT`` of :data:`CONTROL_NOTSENT_LOWAT` (the kernel keeps little unsent, so what is
  written next is not stuck behind a deep socket buffer; Linux tcp(7)). The bulk link is DSCP CS1
  (``IP_TOS`` 0x20, RFC 4594's low-priority data). A link alone (a client with one websocket) is left
  unmarked: it carries every lane.
- :func:`paced_fragments`: one websocket message's fragments of at most
  :data:`~rce.protocol.lanes.BULK_SIZE`, each let out when the :class:`~rce.protocol.pacer.Pacer` says.
- :func:`mptcp_socket`, :func:`mptcp_connect`: a TCP socket that is MPTCP (RFC 8684) where the kernel offers it
  (``IPPROTO_MPTCP``, ``net.mptcp.enabled``), plain TCP where it does not.
"""
from __future__ import annotations

import asyncio
import socket
import time
from collections.abc import AsyncIterator
from typing import Any
from urllib.parse import urlsplit

from rce.plumbing.log import get_logger
from rce.protocol.lanes import BULK_SIZE, Lane
from rce.protocol.pacer import Pacer, chunks

log = get_logger("rce.transport")

TOS = {Lane.CONTROL: 0xB8, Lane.STATE: 0xB8, Lane.BULK: 0x20}     # EF, EF (state rides with control), CS1
CONTROL_NOTSENT_LOWAT = 8 * 1024      # bytes unsent the kernel keeps on a control link before it says "writable"
IPPROTO_MPTCP = getattr(socket, "IPPROTO_MPTCP", 262)            # Linux's protocol number (Python >= 3.10 names it)


def mark(sock: socket.socket | None, lane: Lane) -> bool:
    """Set ``lane``'s DSCP mark and TCP options on ``sock`` (an IPv4 or IPv6 TCP socket; None or another
    family: nothing). Returns False (logged) when the kernel refused one of them; the link works unmarked."""
    if sock is None or sock.family not in (socket.AF_INET, socket.AF_INET6):
        return False
    try:
        if sock.family == socket.AF_INET6:
            sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_TCLASS, TOS[lane])
        else:
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_TOS, TOS[lane])
        if lane is not Lane.BULK:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.setsockopt(socket.IPPROTO_TCP, getattr(socket, "TCP_NOTSENT_LOWAT", 25), CONTROL_NOTSENT_LOWAT)
    except OSError as e:
        log.warning("could not mark a lane's socket", lane=lane.value, reason=str(e))
        return False
    return True


def socket_of(ws: Any) -> Any:
    """The socket under websocket connection ``ws`` (None when it has none, e.g. a test double)."""
    transport = getattr(ws, "transport", None)
    return transport.get_extra_info("socket") if transport is not None else None


def marks(sock: socket.socket) -> int:
    """The DSCP/ECN byte ``sock`` sends with (``IP_TOS``, or ``IPV6_TCLASS``)."""
    if sock.family == socket.AF_INET6:
        return sock.getsockopt(socket.IPPROTO_IPV6, socket.IPV6_TCLASS)
    return sock.getsockopt(socket.IPPROTO_IP, socket.IP_TOS)


async def paced_fragments(frame: str | bytes, pacer: Pacer | None) -> AsyncIterator[str | bytes]:
    """``frame`` (a websocket message's payload) in fragments of at most :data:`BULK_SIZE` (characters of a
    text frame), each yielded once ``pacer`` lets its bytes out (None: at once). For ``ws.send``, which
    sends them as one fragmented message (RFC 6455 section 5.4)."""
    if isinstance(frame, str):
        parts = (frame[i:i + BULK_SIZE] for i in range(0, max(len(frame), 1), BULK_SIZE))
    else:
        parts = (bytes(c) for c in chunks(frame))
    for part in parts:
        if pacer is not None:
            wait = pacer.delay(len(part), time.monotonic())
            if wait > 0:
                pacer.waited(wait)
                await asyncio.sleep(wait)       # the pacer's timer
            pacer.spend(len(part), time.monotonic())
        yield part


def mptcp_socket(family: int = socket.AF_INET) -> tuple[socket.socket, bool]:
    """A new stream socket of ``family``: MPTCP when the kernel offers it, else TCP. Returns it and
    whether it is MPTCP."""
    try:
        return socket.socket(family, socket.SOCK_STREAM, IPPROTO_MPTCP), True
    except OSError as e:           # no MPTCP in this kernel, or net.mptcp.enabled = 0
        log.info("MPTCP not offered by the kernel; using TCP", reason=str(e))
        return socket.socket(family, socket.SOCK_STREAM), False


async def mptcp_connect(url: str) -> socket.socket:
    """A stream socket connected to the host and port of ``url`` (``ws://``: 80, ``wss://``: 443 by default):
    MPTCP where the kernel offers it, else TCP (:func:`mptcp_socket`). Raises OSError as a connect does."""
    parts = urlsplit(url)
    port = parts.port or (443 if parts.scheme in ("wss", "https") else 80)
    loop = asyncio.get_running_loop()
    family, _, _, _, addr = (await loop.getaddrinfo(parts.hostname, port, type=socket.SOCK_STREAM))[0]
    sock, _ = mptcp_socket(family)
    sock.setblocking(False)
    try:
        await loop.sock_connect(sock, addr)
    except BaseException:
        sock.close()
        raise
    return sock


def is_mptcp(sock: socket.socket) -> bool:
    """Is ``sock`` an MPTCP socket?"""
    return sock.proto == IPPROTO_MPTCP
