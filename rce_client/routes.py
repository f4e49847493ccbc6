"""A follower's ways to the cloud (docs/relays.md): its own direct path first, else the first relay
that answers (:mod:`rce_client.tunnel`), for the login and for every dial of the robot endpoint.

While the session runs through a relay:
- the link is pinged every :data:`RELAY_PING_INTERVAL` s and dropped when a pong is
  :data:`RELAY_PING_TIMEOUT` s late, so a relay that vanishes (it drove out of range, lost its uplink
  or stopped) is noticed within about 1 s and the session resumes through another path, long before
  the resume grace runs out; the relay hop's socket also has ``TCP_USER_TIMEOUT``;
- the direct path is tried every :data:`PROBE_EVERY` s (a TCP connect to the endpoint); once it
  answers, the relayed link is dropped and the session resumes on the direct path.

The session itself (login, TLS, resume token, acks and replay) is the follower's, end to end; the
dial names the relay it went through in the query (``relay=NAME``), so that the master knows the
topology.
"""
from __future__ import annotations

import asyncio
import socket
import ssl
from dataclasses import dataclass
from typing import Awaitable, Callable
from urllib.parse import urlsplit

from websockets.asyncio.client import ClientConnection

from rce.plumbing.errors import Unavailable
from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks
from rce.transport import tls
from rce_client.tunnel import Unreachable, join_hostport, open_tunnel, split_hostport, tcp_connect, url_addr

log = get_logger("rce.client")

DIRECT_TIMEOUT = 0.5             # s a follower waits for its direct path's TCP connect before it tries a relay
RELAY_TIMEOUT = 1.0              # s for a relay's TCP connect and CONNECT answer
PROBE_EVERY = 1.0                # s between tries of the direct path while relayed
RELAY_PING_INTERVAL = 0.25       # s between pings on a relayed link ...
RELAY_PING_TIMEOUT = 0.75        # s ... and how late a pong may be before the link counts as lost
MAX_LOGIN_ANSWER = 1024 * 1024   # bytes of a login answer read through a tunnel


def parse_relays(text: str) -> list[tuple[str, int]]:
    """``HOST:PORT[,HOST:PORT...]`` -> [(host, port)]. Raises :class:`ValueError` naming the bad entry."""
    out = [split_hostport(t.strip(), "--relays") for t in text.split(",") if t.strip()]
    if not out:
        raise ValueError("--relays: expected HOST:PORT[,HOST:PORT...], got nothing")
    return out


@dataclass(frozen=True)
class Path:
    """How a socket reached its target: ``relay`` is the relay's name (its robot ID), None for direct."""
    sock: socket.socket
    target: tuple[str, int]
    relay: str | None
    relay_addr: tuple[str, int] | None = None


class Routes:
    """A follower's paths to the cloud: direct first, then ``relays`` [(host, port)] in order (the relay
    whose link was just lost last, so that a relay that vanished costs no dial timeout).

    ``direct_dial(addr, timeout)`` opens the robot's own path: a connected non-blocking socket, or
    :class:`OSError`/:class:`TimeoutError` (default :func:`~rce_client.tunnel.tcp_connect`; a simulated
    robot's dial goes through its simulated access point, ``rce_fleet.live.radio``).

    :attr:`relay`: the name of the relay the current link goes through (None: direct); :attr:`switches`:
    links opened on another path than the one before."""

    def __init__(self, relays: list[tuple[str, int]], *, direct_timeout: float = DIRECT_TIMEOUT,
                 relay_timeout: float = RELAY_TIMEOUT, probe_every: float = PROBE_EVERY,
                 direct_dial: Callable[[tuple[str, int], float], Awaitable[socket.socket]] = tcp_connect):
        self.relays = list(relays)
        self.direct_dial = direct_dial
        self.direct_timeout, self.relay_timeout, self.probe_every = direct_timeout, relay_timeout, probe_every
        self.relay: str | None = None
        self.switches = 0
        self.tasks = Tasks("rce-client routes")
        self._opened = False
        self._suspect: tuple[str, int] | None = None     # the relay whose link was lost last: tried last

    async def socket_to(self, addr: tuple[str, int]) -> Path:
        """A socket to ``addr``: direct if it answers within :attr:`direct_timeout` s, else through the
        first relay that opens a tunnel. Raises :class:`Unreachable` when a path reached the place and nothing
        listened there (the direct dial refused, or a relay answered 502), else :class:`Unavailable`, naming
        why each path failed."""
        try:
            return Path(await self.direct_dial(addr, self.direct_timeout), addr, None)
        except (OSError, TimeoutError) as e:
            why = [f"direct: {e or type(e).__name__}"]
            refused = isinstance(e, (ConnectionRefusedError, ConnectionResetError))
        order = sorted(self.relays, key=lambda r: r == self._suspect)    # stable: the lost relay goes last
        for relay in order:
            try:
                sock, name = await open_tunnel(relay, addr, self.relay_timeout)
                return Path(sock, addr, name, relay)
            except Unavailable as e:
                why.append(e.message)
                refused = refused or getattr(e, "status", None) == 502
        error = Unreachable if refused else Unavailable
        raise error(f"no path to {join_hostport(*addr)}: " + "; ".join(why))

    def opened(self, ws: ClientConnection, path: Path) -> None:
        """A link opened on ``path``: while relayed, ping it and try the direct path; counts a switch."""
        if self._opened and path.relay != self.relay:
            self.switches += 1
        self._opened = True
        if path.relay != self.relay:
            log.info("link to the cloud", via=path.relay or "direct",
                     relay=join_hostport(*path.relay_addr) if path.relay_addr else None)
        self.relay, self._suspect = path.relay, None
        if path.relay is not None:
            self.tasks.spawn(self._watch(ws, path), name="relay-watch")

    async def _watch(self, ws: ClientConnection, path: Path) -> None:
        """While ``ws`` is relayed on ``path``: ping it (drop it when a pong is late) and probe the direct
        path (drop it when that answers: the dial that follows takes the direct path)."""
        probe_at = asyncio.get_running_loop().time() + self.probe_every
        while ws.transport is not None and not ws.transport.is_closing():
            try:
                pong = await ws.ping()
                async with asyncio.timeout(RELAY_PING_TIMEOUT):
                    await pong
            except TimeoutError:
                log.info("relay link lost (pong late)", via=path.relay, timeout=RELAY_PING_TIMEOUT)
                self._suspect = path.relay_addr
                ws.transport.abort()
                return
            except Exception:               # the link closed under the ping: its reader resumes
                self._suspect = path.relay_addr
                return
            if asyncio.get_running_loop().time() >= probe_at:
                probe_at = asyncio.get_running_loop().time() + self.probe_every
                try:
                    (await self.direct_dial(path.target, self.direct_timeout)).close()
                except (OSError, TimeoutError):
                    pass
                else:
                    log.info("direct path to the cloud is back; leaving the relay", via=path.relay)
                    ws.transport.abort()
                    return
            await asyncio.sleep(RELAY_PING_INTERVAL)      # the ping period, a timer

    async def get(self, url: str, ssl_context: ssl.SSLContext | None, timeout: float) -> tuple[int, str, bytes]:
        """``GET url`` (``http(s)://``) on a path of :meth:`socket_to`: (status, reason phrase, body).
        Raises :class:`Unavailable` (no path), :class:`OSError` or :class:`TimeoutError`."""
        parts = urlsplit(url)
        path = await self.socket_to(url_addr(url))
        if path.relay:
            log.info("logging in through a relay", via=path.relay)
        secure = parts.scheme == "https"
        async with asyncio.timeout(timeout):
            reader, writer = await asyncio.open_connection(
                sock=path.sock, ssl=(ssl_context or tls.client_context()) if secure else None,
                server_hostname=parts.hostname if secure else None)
            try:
                target = parts.path or "/"
                target += f"?{parts.query}" if parts.query else ""
                writer.write(f"GET {target} HTTP/1.1\r\nHost: {parts.netloc}\r\nUser-Agent: rce-client\r\n"
                             f"Connection: close\r\n\r\n".encode())
                data = await reader.read(MAX_LOGIN_ANSWER)
                while chunk := await reader.read(MAX_LOGIN_ANSWER):
                    data += chunk
                    if len(data) > MAX_LOGIN_ANSWER:
                        raise Unavailable(f"the answer to GET {url} is longer than {MAX_LOGIN_ANSWER} bytes")
            finally:
                writer.close()
        head, _, body = data.partition(b"\r\n\r\n")
        status_line = head.split(b"\r\n", 1)[0].decode("latin-1").split(" ", 2)
        if len(status_line) < 2 or not status_line[1].isdigit():
            raise Unavailable(f"GET {url}: not an HTTP answer: {head[:80]!r}")
        return int(status_line[1]), status_line[2] if len(status_line) > 2 else "", body

    async def close(self) -> None:
        """Stop watching the relayed link."""
        await self.tasks.cancel_all()
