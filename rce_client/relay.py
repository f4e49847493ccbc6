"""A robot that relays for nearby robots out of coverage (docs/relays.md): an HTTP CONNECT server
(:mod:`rce_client.tunnel`, RFC 9110 section 9.3.6) that opens a tunnel from a follower only to the
cloud (the master and the robot endpoints it names at ``GET /endpoints``; anything else is refused
with 403) and then carries the follower's bytes both ways unread: the follower's login, TLS and
session are end to end, so a relay can drop the follower's traffic but not read or forge it.

- At most ``max_followers`` tunnels at once; past that a follower gets 503 with the reason, and
  tries its next relay.
- The relay's own traffic goes first on its link: relayed sockets carry DSCP CS1 ("lower effort",
  RFC 8622: Wi-Fi's background access category) and ``SO_PRIORITY`` :data:`TC_PRIO_BULK` (the lowest
  band of Linux's default qdisc), and relayed bytes are paced to ``rate`` bytes/s in all (a token
  bucket).
- Each direction's buffers are bounded (:data:`PIPE_CHUNK`; the streams' own limits); a hop whose
  peer vanished drops after :data:`~rce_client.tunnel.TCP_USER_TIMEOUT_MS` of unacked data, and
  then the tunnel closes on both sides (the follower resumes through another path).

::

    conn = await Connection.connect(master, "testUser", "testUser", "leader", allow_reconnect=True)
    relay = await RobotRelay.for_connection(conn, port=9100, max_followers=4)
    ...
    await relay.close()
"""
from __future__ import annotations

import asyncio
import json
import socket
import time
from dataclasses import dataclass, field

import aiohttp

from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks
from rce.transport import tls
from rce_client.tunnel import (MAX_HEAD, HeadError, answer, join_hostport, mark_relay_hop, parse_request,
                               tcp_connect, url_addr)

log = get_logger("rce.relay")

DEFAULT_MAX_FOLLOWERS = 4        # tunnels a relay carries at once
DEFAULT_RATE = 2 * 1024 * 1024   # bytes/s of relayed traffic in all (both directions), past which it is paced
PIPE_CHUNK = 64 * 1024           # bytes read from one side before they are written to the other
HEAD_TIMEOUT = 5.0               # s a follower has to send its CONNECT head
DIAL_TIMEOUT = 3.0               # s to reach the cloud's side of a tunnel
ENDPOINTS_EVERY = 2.0            # s at least between two asks for the cloud's robot endpoints
DSCP_CS1 = 0x20                  # the IP TOS byte of DSCP CS1 (RFC 8622 lower effort)
TC_PRIO_BULK = 2                 # SO_PRIORITY of bulk traffic: pfifo_fast's lowest band (linux/pkt_sched.h)


def mark_low_priority(sock: socket.socket) -> None:
    """Mark a relayed socket so that the relay's own traffic goes first: DSCP CS1 and ``SO_PRIORITY``
    :data:`TC_PRIO_BULK` (set after the TOS, which also sets the priority)."""
    if sock.family == socket.AF_INET6:
        sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_TCLASS, DSCP_CS1)
    else:
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_TOS, DSCP_CS1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_PRIORITY, TC_PRIO_BULK)


class RelayPacer:
    """Paces bytes to ``rate`` bytes/s with bursts up to ``burst`` bytes (``rate`` 0: no pacing)."""

    def __init__(self, rate: float, burst: float):
        self.rate, self.burst = rate, burst
        self.tokens, self.stamp = burst, time.monotonic()

    def delay(self, n: int, now: float) -> float:
        """Take ``n`` bytes at ``now``: the s to wait before sending them (0: at once)."""
        if not self.rate:
            return 0.0
        self.tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate) - n
        self.stamp = now
        return max(0.0, -self.tokens / self.rate)


@dataclass
class RelayStats:
    """What a relay did: ``followers`` carried now; ``tunnels`` opened in all; ``refused_full``
    (503), ``refused_target`` (403), ``refused_bad`` (400), ``failed`` (the cloud's side could not be
    reached: 502 when nothing listens there, 504 when the uplink does not reach it); ``bytes_up`` (to
    the cloud) and ``bytes_down`` (to followers) relayed;
    ``paced_s``: s relayed bytes waited for the pacer."""
    followers: int = 0
    tunnels: int = 0
    refused_full: int = 0
    refused_target: int = 0
    refused_bad: int = 0
    failed: int = 0
    bytes_up: int = 0
    bytes_down: int = 0
    paced_s: float = 0.0
    by_follower: dict[str, int] = field(default_factory=dict)   # peer address -> tunnels opened

    def summary(self) -> str:
        """One line: what the relay carried and refused."""
        return (f"{self.tunnels} tunnel(s) for {len(self.by_follower)} follower address(es), "
                f"{self.bytes_up} bytes to the cloud, {self.bytes_down} bytes to followers, "
                f"paced {self.paced_s:.1f} s; "
                f"refused {self.refused_full} (full), {self.refused_target} (outside the cloud), "
                f"{self.refused_bad} (not CONNECT), {self.failed} (cloud unreachable)")


class RobotRelay:
    """An HTTP CONNECT relay named ``name`` (this robot's ID, told to followers) into the cloud of
    ``master_url``: tunnels only to the master and the robot endpoints the master names;
    ``max_followers`` tunnels at once; ``rate``: bytes/s of relayed traffic in all (0: no pacing);
    ``ssl_context`` verifies an ``https://`` master."""

    def __init__(self, name: str, master_url: str, *, max_followers: int = DEFAULT_MAX_FOLLOWERS,
                 rate: float = DEFAULT_RATE, ssl_context=None):
        if max_followers < 1:
            raise ValueError(f"relay max_followers must be at least 1, got {max_followers}")
        self.name, self.master_url, self.max_followers = name, master_url, max_followers
        self.ssl_context = ssl_context
        self.bucket = RelayPacer(rate, max(PIPE_CHUNK, rate / 10))
        self.stats = RelayStats()
        self.targets: set[tuple[str, int]] = {url_addr(master_url)}
        self.port: int | None = None
        self._asked = -ENDPOINTS_EVERY
        self._server: asyncio.Server | None = None
        self.tasks = Tasks(f"relay {name}")

    @classmethod
    async def for_connection(cls, conn, port: int, bind: str = "0.0.0.0", **kw) -> "RobotRelay":
        """Relay for nearby robots into the cloud ``conn`` (a :class:`~rce_client.connection.Connection`
        made by a login) is in, on ``bind:port`` (0: any free port, see :attr:`port`); the keywords are
        the constructor's. Raises :class:`ValueError` for a connection not made by a login, :class:`OSError`
        when the port cannot be bound."""
        if conn.relogin is None:
            raise ValueError("a relay needs a connection made by a login (it relays to that master's cloud)")
        relay = cls(conn.robot_id, conn.relogin[0], ssl_context=conn.ssl_context, **kw)
        relay.targets.add(url_addr(conn.ws_url))
        await relay.start(bind, port)
        return relay

    async def start(self, bind: str, port: int) -> None:
        """Listen on ``bind:port`` and ask the master for its robot endpoints. Raises :class:`OSError`."""
        self._server = await asyncio.start_server(
            lambda r, w: self.tasks.spawn(self._serve(r, w), name="tunnel"), bind, port, limit=MAX_HEAD)
        self.port = self._server.sockets[0].getsockname()[1]
        await self._refresh_targets()
        log.info("relaying for nearby robots", relay=self.name, port=self.port, max=self.max_followers,
                 targets=sorted(join_hostport(*t) for t in self.targets))

    async def close(self) -> None:
        """Stop listening and close every tunnel."""
        if self._server is not None:
            self._server.close()
        await self.tasks.cancel_all()
        if self._server is not None:
            await self._server.wait_closed()

    async def _refresh_targets(self) -> None:
        """Ask the master for its robot endpoints (``GET /endpoints``), at most every :data:`ENDPOINTS_EVERY` s."""
        now = time.monotonic()
        if now - self._asked < ENDPOINTS_EVERY:
            return
        self._asked = now
        url = self.master_url.rstrip("/") + "/endpoints"
        try:
            async with aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=DIAL_TIMEOUT)) as http:
                async with http.get(url, ssl=self.ssl_context or tls.client_context()) as resp:
                    body = json.loads(await resp.read()) if resp.status == 200 else {}
            self.targets |= {url_addr(u) for u in body.get("endpoints", []) if isinstance(u, str)}
        except (aiohttp.ClientError, asyncio.TimeoutError, OSError, ValueError, AttributeError) as e:
            log.warning("could not ask the master for its robot endpoints", url=url, reason=str(e) or type(e).__name__)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        who = join_hostport(*peer[:2]) if peer else "?"
        carried = False
        try:
            try:
                async with asyncio.timeout(HEAD_TIMEOUT):
                    head = await reader.readuntil(b"\r\n\r\n")
                target = parse_request(head)
            except (HeadError, asyncio.LimitOverrunError, asyncio.IncompleteReadError, TimeoutError) as e:
                self.stats.refused_bad += 1
                await _refuse(writer, 400, f"relay {self.name}: {e if isinstance(e, HeadError) else 'no CONNECT head'}")
                return
            if target not in self.targets:
                await self._refresh_targets()
            if target not in self.targets:
                self.stats.refused_target += 1
                log.warning("relay refused a target outside the cloud", follower=who, target=join_hostport(*target))
                await _refuse(writer, 403, f"relay {self.name} only relays to the cloud's master and robot "
                                           f"endpoints, not {join_hostport(*target)}")
                return
            if self.stats.followers >= self.max_followers:
                self.stats.refused_full += 1
                await _refuse(writer, 503, f"relay {self.name} is full: it carries {self.max_followers} "
                                           f"follower(s) already")
                return
            self.stats.followers += 1
            carried = True
            await self._carry(reader, writer, target, who)
        except (ConnectionError, OSError):
            pass
        finally:
            if carried:
                self.stats.followers -= 1
            writer.close()

    async def _carry(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, target: tuple[str, int],
                     who: str) -> None:
        """Open the cloud's side of a tunnel, answer 200 and pipe bytes both ways until either side ends."""
        try:
            sock = await tcp_connect(target, DIAL_TIMEOUT)
        except (OSError, TimeoutError) as e:
            self.stats.failed += 1
            # 502: the cloud's host answered and nothing listens there; 504: the relay's uplink does not
            # reach it now (no route, timed out): a follower waits for the uplink instead of moving
            status = 502 if isinstance(e, (ConnectionRefusedError, ConnectionResetError)) else 504
            await _refuse(writer, status, f"relay {self.name} cannot reach {join_hostport(*target)}: "
                                          f"{e or type(e).__name__}")
            return
        for s in (sock, writer.get_extra_info("socket")):
            raw = s if isinstance(s, socket.socket) else socket.socket(fileno=s.fileno())
            try:
                mark_relay_hop(raw)
                mark_low_priority(raw)
            finally:
                if raw is not s:
                    raw.detach()
        up_r, up_w = await asyncio.open_connection(sock=sock, limit=PIPE_CHUNK)
        self.stats.tunnels += 1
        self.stats.by_follower[who] = self.stats.by_follower.get(who, 0) + 1
        log.info("relaying", follower=who, target=join_hostport(*target), followers=self.stats.followers)
        writer.write(answer(200, name=self.name))
        try:
            pipes = [asyncio.ensure_future(self._pipe(reader, up_w, "bytes_up")),
                     asyncio.ensure_future(self._pipe(up_r, writer, "bytes_down"))]
            try:
                await asyncio.wait(pipes, return_when=asyncio.FIRST_COMPLETED)
            finally:
                for p in pipes:
                    p.cancel()
                await asyncio.gather(*pipes, return_exceptions=True)
        finally:
            up_w.close()
            log.info("relay tunnel closed", follower=who, target=join_hostport(*target))

    async def _pipe(self, src: asyncio.StreamReader, dst: asyncio.StreamWriter, counter: str) -> None:
        """Copy ``src`` to ``dst`` in chunks of at most :data:`PIPE_CHUNK` bytes, paced, waiting for
        ``dst`` to drain (so at most a chunk and the streams' own buffers are held)."""
        while data := await src.read(PIPE_CHUNK):
            if (wait := self.bucket.delay(len(data), time.monotonic())) > 0:
                self.stats.paced_s += wait
                await asyncio.sleep(wait)       # the pacer, a timer
            dst.write(data)
            setattr(self.stats, counter, getattr(self.stats, counter) + len(data))
            await dst.drain()


async def _refuse(writer: asyncio.StreamWriter, status: int, reason: str) -> None:
    """Answer a CONNECT with ``status`` and ``reason`` (and close, by the caller)."""
    try:
        writer.write(answer(status, reason))
        async with asyncio.timeout(HEAD_TIMEOUT):
            await writer.drain()
    except (ConnectionError, OSError, TimeoutError):
        pass
