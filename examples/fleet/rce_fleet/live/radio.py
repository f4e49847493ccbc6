"""The simulated robots' radios, for ``rce-fleet demo --out-of-coverage RobotA,RobotB``: robots out of
the access point's coverage reach the cloud only through a relay on another simulated robot
(:class:`rce_client.relay.RobotRelay`, docs/relays.md), and only while that robot is within radio
range of them in the simulation.

- **No coverage.** A robot out of coverage has no path of its own: its direct dial (the
  :class:`~rce_client.routes.Routes` ``direct_dial``) fails at once with ``ENETUNREACH``, as a socket
  does on a robot whose Wi-Fi is not associated (no route). Its rce-ros bridge still tries it every
  second while relayed, as a real follower does.
- **Radio links.** Per (follower, relay robot) a loopback TCP forwarder to the relay's port
  (:class:`rce.transport.tcpproxy.TcpProxy`): up while the two robots' true positions are at most
  ``range_m`` apart (checked every simulator tick); when they part, every connection through it is
  reset and new ones are refused until they are in range again, so a relay that drives away really
  goes. The follower's relays list is its links, in robot order.
- **What each follower went through** (:class:`FollowerLog`): the relay that carried its link and
  for how long, and every dark spell (from the link's loss to the session's resume), in wall s: the
  network's time, not the simulation's.

The default range (:func:`default_range`) is three quarters of the map's shorter side: 6 m on the
project's 8 m x 8 m lab, 22.6 m on the 30.2 m x 50.2 m warehouse (Zigbee's or Bluetooth's indoor reach
among steel racks is 10 - 30 m): a follower has a relay in range most of the time and loses one when
the fleet spreads. A follower out of every relay's range stops at its last waypoint (the cloud's next
one cannot reach it) until a relay comes into range again; its session waits for it as long as the
robot endpoint's resume grace (30 s by default).
"""
from __future__ import annotations

import errno
import math
import socket
import time
from dataclasses import dataclass, field
from typing import Awaitable, Callable

from rce.plumbing.log import get_logger
from rce.transport.tcpproxy import TcpProxy
from rce_client.routes import Routes

log = get_logger("fleet.radio")

Positions = Callable[[], dict[str, tuple[float, float]]]


def default_range(width_m: float, height_m: float) -> float:
    """The default radio range (m) on a map of ``width_m`` x ``height_m``: 3/4 of its shorter side."""
    return round(min(width_m, height_m) * 0.75, 1)


def no_coverage_dial(robot: str) -> Callable[[tuple[str, int], float], Awaitable[socket.socket]]:
    """The direct dial of ``robot``, out of the access point's coverage: raises ``OSError(ENETUNREACH)``."""
    async def dial(addr: tuple[str, int], timeout: float) -> socket.socket:
        raise OSError(errno.ENETUNREACH, f"{robot} is out of the access point's coverage (simulated)")
    return dial


@dataclass
class FollowerLog:
    """One follower's relays and dark spells (wall s; ``at_s``: mission s, simulated)."""
    robot: str
    routes: Routes
    mission_t: Callable[[], float]
    used_s: dict[str, float] = field(default_factory=dict)    # relay -> wall s its link went through it
    dark: list[dict] = field(default_factory=list)            # {at_s, dark_s, then_via, dropped}
    _via: str | None = None
    _since: float | None = None
    _dark_since: float | None = None
    _conn: object = None

    def attach(self, conn) -> None:
        """Follow ``conn`` (the follower's :class:`~rce_client.connection.Connection`, just connected)."""
        self._conn = conn
        self._via, self._since = self.routes.relay, time.monotonic()
        conn.on_disconnected(self._lost)
        conn.on_resumed(self._resumed)

    def _close_segment(self, now: float) -> None:
        if self._since is not None and self._via is not None:
            self.used_s[self._via] = self.used_s.get(self._via, 0.0) + now - self._since
        self._since = None

    def _lost(self, reason: str) -> None:
        now = time.monotonic()
        self._close_segment(now)
        self._dark_since = now

    def _resumed(self, st: dict) -> None:
        now = time.monotonic()
        self._via, self._since = self.routes.relay, now
        if self._dark_since is not None:
            self.dark.append({"at_s": round(self.mission_t(), 2), "dark_s": round(now - self._dark_since, 3),
                              "then_via": self._via, "dropped": st.get("dropped", 0)})
            self._dark_since = None

    @property
    def via(self) -> str:
        """``dark`` while no path is up, else the relay its link goes through."""
        return "dark" if self._dark_since is not None else str(self.routes.relay)

    def report(self) -> dict:
        """``{relays_used: {relay: s}, via_now, switches, dark: [...], dark_max_s, dark_total_s, dark_now_s,
        lost_to_cloud}`` (``lost_to_cloud``: messages the follower's resume buffer forgot before the cloud
        got them; the cloud's losses are each dark spell's ``dropped``)."""
        now = time.monotonic()
        used = dict(self.used_s)
        if self._since is not None and self._via is not None:
            used[self._via] = used.get(self._via, 0.0) + now - self._since
        spells = [d["dark_s"] for d in self.dark]
        return {"relays_used": {r: round(s, 2) for r, s in sorted(used.items())}, "via_now": self.routes.relay,
                "switches": self.routes.switches, "dark": self.dark,
                "dark_max_s": max(spells, default=0.0), "dark_total_s": round(sum(spells), 3),
                "dark_now_s": round(now - self._dark_since, 3) if self._dark_since is not None else 0.0,
                "lost_to_cloud": self._conn.session.resume_lost if self._conn is not None else 0}


class Radio:
    """The radio links from ``followers`` to the relays ``relay_ports`` (robot -> its relay's port on
    127.0.0.1), up while within ``range_m`` of each other by ``positions()`` (robot -> (x, y), m)."""

    def __init__(self, range_m: float, followers: list[str], relay_ports: dict[str, int], positions: Positions):
        if not range_m > 0:
            raise ValueError(f"radio range must be > 0 m, got {range_m}")
        self.range_m, self.followers, self.relay_ports = range_m, list(followers), dict(relay_ports)
        self.positions = positions
        self.links: dict[tuple[str, str], TcpProxy] = {}
        self.up: dict[tuple[str, str], bool] = {}
        self.went_out: dict[tuple[str, str], int] = {}    # times the pair drove out of range
        self.logs: dict[str, FollowerLog] = {}

    async def start(self) -> None:
        """Open every link (down) and bring up those in range now. Raises OSError."""
        for f in self.followers:
            for r, port in self.relay_ports.items():
                proxy = await TcpProxy(port).start()
                proxy.cut()
                self.links[(f, r)], self.up[(f, r)], self.went_out[(f, r)] = proxy, False, 0
        self.update()

    def routes(self, follower: str) -> Routes:
        """The paths of ``follower``: no coverage of its own; its radio links to the relays, in robot order."""
        relays = [("127.0.0.1", self.links[(follower, r)].port) for r in self.relay_ports]
        return Routes(relays, direct_dial=no_coverage_dial(follower))

    def follow(self, follower: str, conn, mission_t: Callable[[], float]) -> None:
        """Log ``follower``'s relays and dark spells from its connection ``conn``."""
        self.logs[follower] = log_ = FollowerLog(follower, conn.routes, mission_t)
        log_.attach(conn)

    def update(self) -> None:
        """Bring each link up or down by the robots' distance now (a simulator tick calls it)."""
        pos = self.positions()
        for (f, r), proxy in self.links.items():
            (fx, fy), (rx, ry) = pos[f], pos[r]
            near = math.hypot(fx - rx, fy - ry) <= self.range_m
            if near == self.up[(f, r)]:
                continue
            self.up[(f, r)] = near
            if near:
                proxy.restore()
            else:
                proxy.cut()
                self.went_out[(f, r)] += 1
            log.info("radio link " + ("up" if near else "down (out of range)"), follower=f, relay=r)

    def report(self) -> dict:
        """The report's ``coverage`` section: range, followers' logs, links (``went_out``: drives out of range)."""
        return {"radio_range_m": self.range_m, "out_of_coverage": self.followers, "relays": list(self.relay_ports),
                "followers": {f: lg.report() for f, lg in self.logs.items()},
                "links": {f"{f}-{r}": {"up": self.up[(f, r)], "went_out": self.went_out[(f, r)],
                                       **self.links[(f, r)].stats()} for f, r in self.links}}

    async def close(self) -> None:
        """Close every link."""
        for proxy in self.links.values():
            await proxy.close()
