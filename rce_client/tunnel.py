"""The relay hop's wire: an HTTP CONNECT tunnel (RFC 9110 section 9.3.6) from a follower robot to a
relay robot, which then carries the follower's own bytes (its TLS, its websocket, its login) unread
(docs/relays.md).

The follower sends ``CONNECT HOST:PORT HTTP/1.1`` naming a robot endpoint or the master; the relay
answers ``HTTP/1.1 200 Connection established`` with ``RCE-Relay: NAME`` (its robot ID), after which
both directions are the follower's raw bytes, or refuses with a status and a one-line reason:
400 (not a CONNECT head), 403 (a target that is not the cloud's), 503 (the relay is full). The head
parsing and forming here is sans I/O; :func:`open_tunnel` and :func:`tcp_connect` are the
follower's two ways to a socket.
"""
from __future__ import annotations

import asyncio
import socket
from urllib.parse import urlsplit

from rce.plumbing.errors import Unavailable
from rce.plumbing.http1 import closing_answer

MAX_HEAD = 8192                 # bytes of a CONNECT request or answer head, CRLFCRLF included
RELAY_HEADER = "RCE-Relay"      # the answer's header naming the relay (its robot ID)
TCP_USER_TIMEOUT_MS = 1000      # ms data may stay unacked on the relay hop before the kernel drops the socket


class Unreachable(Unavailable):
    """Nothing listens at the robot endpoint's address (connection refused or reset)."""


class HeadError(ValueError):
    """A CONNECT head that is malformed or too long."""


class TunnelRefused(Unavailable):
    """The relay answered the CONNECT with an error status (``status``) and a reason."""

    def __init__(self, relay: str, status: int, reason: str):
        super().__init__(f"relay {relay} refused the tunnel (HTTP {status}): {reason}")
        self.status, self.reason = status, reason


def split_hostport(text: str, where: str) -> tuple[str, int]:
    """``HOST:PORT`` or ``[V6]:PORT`` -> (host, port). Raises :class:`ValueError` naming ``where``."""
    host, sep, port = text.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"{where}: expected HOST:PORT, got {text!r}")
    return host, int(port)


def url_addr(url: str) -> tuple[str, int]:
    """(host, port) a ``http(s)://`` or ``ws(s)://`` URL names (its scheme's default port if none)."""
    parts = urlsplit(url)
    port = parts.port or (443 if parts.scheme in ("https", "wss") else 80)
    return parts.hostname or "", port


def join_hostport(host: str, port: int) -> str:
    """(host, port) -> ``HOST:PORT`` (``[V6]:PORT`` for an IPv6 literal)."""
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def connect_request(target: tuple[str, int]) -> bytes:
    """The follower's CONNECT head for ``target`` (host, port)."""
    hp = join_hostport(*target)
    return f"CONNECT {hp} HTTP/1.1\r\nHost: {hp}\r\n\r\n".encode("ascii")


def parse_request(head: bytes) -> tuple[str, int]:
    """The target (host, port) of a CONNECT head (request line and headers, up to CRLFCRLF). Raises
    :class:`HeadError` naming what is wrong (another method, a target that is not HOST:PORT)."""
    line = head.split(b"\r\n", 1)[0].decode("latin-1")
    parts = line.split(" ")
    if len(parts) != 3 or not parts[2].startswith("HTTP/1."):
        raise HeadError(f"not an HTTP/1.x request line: {line[:80]!r}")
    if parts[0] != "CONNECT":
        raise HeadError(f"only CONNECT is relayed, got {parts[0][:20]!r}")
    try:
        return split_hostport(parts[1], "CONNECT target")
    except ValueError as e:
        raise HeadError(str(e)) from None


def answer(status: int, reason: str = "", name: str = "") -> bytes:
    """The relay's answer head: 200 names the relay (``RCE-Relay: name``); an error carries ``reason``
    as a one-line text body and closes."""
    if status == 200:
        return f"HTTP/1.1 200 Connection established\r\n{RELAY_HEADER}: {name}\r\n\r\n".encode()
    return closing_answer(status, (reason.replace("\n", " ") + "\n").encode(), "text/plain; charset=utf-8")


def parse_answer(head: bytes, body: bytes = b"") -> tuple[int, str]:
    """(status, relay name for a 200 or the reason of a refusal) from a relay's answer head (and the
    bytes after it). Raises :class:`HeadError` for one that is not an HTTP/1.x status line."""
    lines = head.decode("latin-1").split("\r\n")
    parts = lines[0].split(" ", 2)
    if len(parts) < 2 or not parts[0].startswith("HTTP/1.") or not parts[1].isdigit():
        raise HeadError(f"not an HTTP/1.x answer: {lines[0][:80]!r}")
    status = int(parts[1])
    if status == 200:
        name = next((v.strip() for k, _, v in (h.partition(":") for h in lines[1:])
                     if k.strip().lower() == RELAY_HEADER.lower()), "")
        return status, name
    return status, body.decode("utf-8", "replace").strip() or (parts[2] if len(parts) > 2 else "")


def mark_relay_hop(sock: socket.socket) -> None:
    """Make a relay hop's socket notice a vanished peer: data unacked for :data:`TCP_USER_TIMEOUT_MS`
    drops it (``TCP_USER_TIMEOUT``, RFC 5482), and no Nagle delay."""
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT, TCP_USER_TIMEOUT_MS)


async def tcp_connect(addr: tuple[str, int], timeout: float) -> socket.socket:
    """A connected non-blocking TCP socket to ``addr`` within ``timeout`` s. Raises :class:`OSError`
    (refused, unreachable) or :class:`TimeoutError`."""
    loop = asyncio.get_running_loop()
    async with asyncio.timeout(timeout):
        infos = await loop.getaddrinfo(addr[0], addr[1], type=socket.SOCK_STREAM)
        family, type_, proto, _, sockaddr = infos[0]
        sock = socket.socket(family, type_, proto)
        sock.setblocking(False)
        try:
            await loop.sock_connect(sock, sockaddr)
        except BaseException:
            sock.close()
            raise
    return sock


async def _read_head(sock: socket.socket) -> tuple[bytes, bytes]:
    """Read up to CRLFCRLF (at most :data:`MAX_HEAD` bytes): (head, what came after it)."""
    loop = asyncio.get_running_loop()
    buf = b""
    while b"\r\n\r\n" not in buf:
        if len(buf) > MAX_HEAD:
            raise HeadError(f"answer head longer than {MAX_HEAD} bytes")
        chunk = await loop.sock_recv(sock, MAX_HEAD)
        if not chunk:
            raise ConnectionResetError("the relay closed the connection before answering")
        buf += chunk
    head, _, rest = buf.partition(b"\r\n\r\n")
    return head, rest


async def open_tunnel(relay: tuple[str, int], target: tuple[str, int], timeout: float) -> tuple[socket.socket, str]:
    """Open a CONNECT tunnel through ``relay`` to ``target`` within ``timeout`` s: (the socket, now
    carrying the follower's bytes to ``target``; the relay's name). Raises :class:`TunnelRefused`
    (the relay refused: full, a target not the cloud's) or :class:`Unavailable` (the relay cannot be
    reached or does not speak CONNECT)."""
    where = join_hostport(*relay)
    loop = asyncio.get_running_loop()
    try:
        sock = await tcp_connect(relay, timeout)
    except (OSError, TimeoutError) as e:
        raise Unavailable(f"cannot reach relay {where}: {e or type(e).__name__}") from None
    try:
        async with asyncio.timeout(timeout):
            await loop.sock_sendall(sock, connect_request(target))
            head, rest = await _read_head(sock)
        status, text = parse_answer(head, rest)
    except (OSError, TimeoutError, HeadError) as e:
        sock.close()
        raise Unavailable(f"relay {where} did not open a tunnel: {e or type(e).__name__}") from None
    if status != 200:
        sock.close()
        raise TunnelRefused(where, status, text)
    mark_relay_hop(sock)
    return sock, text or where
