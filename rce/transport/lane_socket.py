"""The socket side of lanes (docs/lanes.md): DSCP marks and TCP options per lane, and MPTCP sockets.

- :func:`mark`: a connection's lane in its socket. The session's own link, once a bulk link has joined
  it, is the control lane: DSCP EF (``IP_TOS`` 0xB8, RFC 3246; ``IPV6_TCLASS`` on IPv6), ``TCP_NODELAY``,
  and ``TCP_NOTSENT_LOWAT`` of :data:`CONTROL_NOTSENT_LOWAT` (the kernel keeps little unsent, so what is
  written next is not stuck behind a deep socket buffer; Linux tcp(7)). The bulk link is DSCP CS1
  (``IP_TOS`` 0x20, RFC 4594's low-priority data). A link alone (a client with one websocket) is left
  unmarked: it carries every lane.
- :class:`PacedLink`: a bulk link's :class:`~rce.interfaces.pacer.Pacer` on its socket. It writes one
  websocket message's fragments of at most :data:`~rce.interfaces.lanes.BULK_SIZE`, each when the pacer says
  (:meth:`PacedLink.fragments`); it has the kernel pace the socket's packets to the pacer's rate
  (``SO_MAX_PACING_RATE``, Linux's TCP internal pacing), so a fragment reaches the bottleneck spread out,
  not as a burst; and when the rate is estimated it feeds the pacer the socket's ``TCP_INFO``
  (:func:`tcp_sample`).
- :func:`mptcp_socket`, :func:`mptcp_connect`: a TCP socket that is MPTCP (RFC 8684) where the kernel offers it
  (``IPPROTO_MPTCP``, ``net.mptcp.enabled``), plain TCP where it does not.
"""
from __future__ import annotations

import asyncio
import socket
import struct
import time
from collections.abc import AsyncIterator, Iterator
from typing import Any
from urllib.parse import urlsplit

from rce.plumbing.log import get_logger
from rce.interfaces.lanes import BULK_SIZE, Lane
from rce.interfaces.pacer import Pacer, chunks
from rce.interfaces.rate_estimator import PathSample

log = get_logger("rce.transport")

TOS = {Lane.CONTROL: 0xB8, Lane.STATE: 0xB8, Lane.BULK: 0x20}     # EF, EF (state rides with control), CS1
CONTROL_NOTSENT_LOWAT = 8 * 1024      # bytes unsent the kernel keeps on a control link before it says "writable"
IPPROTO_MPTCP = getattr(socket, "IPPROTO_MPTCP", 262)            # Linux's protocol number (Python >= 3.10 names it)
SO_MAX_PACING_RATE = getattr(socket, "SO_MAX_PACING_RATE", 47)   # Linux's option number
KERNEL_PACING_ROOM = 1.1       # the kernel paces a bulk socket this much above the pacer, so it smooths, never limits
SAMPLE_EVERY = 0.005           # s: TCP_INFO is read at most this often per bulk link
# struct tcp_info (linux/tcp.h): byte offsets of the fields read, and the length that holds them all
_TCPI_RTT, _TCPI_BYTES_ACKED, _TCPI_NOTSENT, _TCPI_MIN_RTT, _TCPI_LEN = 68, 120, 144, 148, 152
_TCPI_DELIVERY_RATE, _TCPI_RATE_LEN = 160, 168
_TCPI_RWND_LIMITED, _TCPI_RWND_LEN = 176, 184


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


def _tcp_info(sock: socket.socket) -> bytes | None:
    """``sock``'s Linux ``TCP_INFO``, or None where the kernel gives none (not Linux, a kernel before
    4.6, a closed socket) or has measured no round trip yet."""
    try:
        info = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 256)
    except (OSError, AttributeError):
        return None
    if len(info) < _TCPI_LEN or struct.unpack_from("I", info, _TCPI_MIN_RTT)[0] in (0, 0xFFFFFFFF):
        return None
    return info


def tcp_sample(sock: socket.socket, waited: float, now: float) -> PathSample | None:
    """``sock``'s Linux ``TCP_INFO`` at ``now`` (s, monotonic) as a :class:`PathSample` (``waited``: s the
    pacer held the sender back since the last one); None where the kernel gives none (:func:`_tcp_info`)."""
    info = _tcp_info(sock)
    if info is None:
        return None
    (rtt,) = struct.unpack_from("I", info, _TCPI_RTT)
    (acked,) = struct.unpack_from("Q", info, _TCPI_BYTES_ACKED)
    notsent, min_rtt = struct.unpack_from("II", info, _TCPI_NOTSENT)
    return PathSample(now, acked, rtt / 1e6, min_rtt / 1e6, notsent, waited)


def link_info(sock: socket.socket) -> tuple[float, float] | None:
    """``sock``'s smoothed round trip (s) and last delivery rate (bytes/s, 0 if the kernel measured
    none yet) from Linux ``TCP_INFO`` (``tcpi_rtt``, ``tcpi_delivery_rate``, Linux >= 4.9); None where
    the kernel gives none (:func:`_tcp_info`)."""
    info = _tcp_info(sock)
    if info is None:
        return None
    (rtt,) = struct.unpack_from("I", info, _TCPI_RTT)
    rate = struct.unpack_from("Q", info, _TCPI_DELIVERY_RATE)[0] if len(info) >= _TCPI_RATE_LEN else 0
    return rtt / 1e6, float(rate)


def link_sample(sock: socket.socket) -> tuple[float, float, bool] | None:
    """:func:`link_info` and whether the delivery rate was app-limited (the sender had nothing
    more to send, so the rate says nothing of the path: ``tcpi_delivery_rate_app_limited``, bit 0
    of byte 7 of ``struct tcp_info``); None where the kernel gives none."""
    info = _tcp_info(sock)
    if info is None:
        return None
    (rtt,) = struct.unpack_from("I", info, _TCPI_RTT)
    rate = struct.unpack_from("Q", info, _TCPI_DELIVERY_RATE)[0] if len(info) >= _TCPI_RATE_LEN else 0
    return rtt / 1e6, float(rate), bool(info[7] & 1)


def link_backlog(sock: socket.socket) -> tuple[int, int, int] | None:
    """``sock``'s bytes acknowledged by its peer so far, bytes written and not yet sent (waiting for
    the congestion window), and us it was held back by the peer's receive window so far (a reader
    that does not keep up, not the path), from Linux ``TCP_INFO`` (``tcpi_bytes_acked``,
    ``tcpi_notsent_bytes``, ``tcpi_rwnd_limited``: Linux >= 4.10); None where the kernel gives none
    (:func:`_tcp_info`) or not all of them."""
    info = _tcp_info(sock)
    if info is None or len(info) < _TCPI_RWND_LEN:
        return None
    (acked,) = struct.unpack_from("Q", info, _TCPI_BYTES_ACKED)
    (notsent,) = struct.unpack_from("I", info, _TCPI_NOTSENT)
    (rwnd_us,) = struct.unpack_from("Q", info, _TCPI_RWND_LIMITED)
    return acked, notsent, rwnd_us


class PacedLink:
    """A bulk link's ``pacer`` on its ``sock`` (None: a socket not known, e.g. a test double; then only
    the pacer). Counters: :attr:`samples` taken; :attr:`kernel_pacing`: the kernel took
    ``SO_MAX_PACING_RATE``."""

    def __init__(self, pacer: Pacer, sock: socket.socket | None):
        self.pacer, self.sock = pacer, sock
        self.samples = 0
        self._sampled = float("-inf")        # when TCP_INFO was last read
        self._kernel_rate = 0                # the rate the kernel was last told (bytes/s)
        self.kernel_pacing = sock is not None
        self._pace_kernel()

    def _pace_kernel(self) -> None:
        """Have the kernel pace the socket's packets a little above the pacer's rate (once the rate moved)."""
        rate = int(self.pacer.rate * KERNEL_PACING_ROOM)
        if not self.kernel_pacing or abs(rate - self._kernel_rate) < 0.02 * rate:
            return
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, SO_MAX_PACING_RATE, min(rate, 0xFFFFFFFF))
            self._kernel_rate = rate
        except OSError as e:                 # e.g. an MPTCP socket: the pacer alone paces, per fragment
            self.kernel_pacing = False
            log.info("the kernel does not pace this bulk link's socket; the pacer alone does", reason=str(e))

    def _observe(self, now: float) -> None:
        """Feed the estimator the socket's state (at most every :data:`SAMPLE_EVERY` s)."""
        if self.pacer.estimator is None or self.sock is None or now - self._sampled < SAMPLE_EVERY:
            return
        self._sampled = now
        sample = tcp_sample(self.sock, self.pacer.held(), now)
        if sample is not None:
            self.samples += 1
            self.pacer.observe(sample, now)
            self._pace_kernel()

    async def fragments(self, frame: str | bytes) -> AsyncIterator[str | bytes]:
        """``frame`` (a websocket message's payload) in fragments of at most :data:`BULK_SIZE` (characters
        of a text frame), each yielded once the pacer lets its bytes out. For ``ws.send``, which sends them
        as one fragmented message (RFC 6455 section 5.4)."""
        for part in fragments(frame):
            self._observe(time.monotonic())
            wait = self.pacer.delay(len(part), time.monotonic())
            if wait > 0:
                self.pacer.waited(wait)
                await asyncio.sleep(wait)       # the pacer's timer
            self.pacer.spend(len(part), time.monotonic())
            yield part


def fragments(frame: str | bytes) -> Iterator[str | bytes]:
    """``frame`` in fragments of at most :data:`BULK_SIZE` (characters of a text frame, bytes of a binary one)."""
    if isinstance(frame, str):
        return (frame[i:i + BULK_SIZE] for i in range(0, max(len(frame), 1), BULK_SIZE))
    return (bytes(c) for c in chunks(frame))


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
