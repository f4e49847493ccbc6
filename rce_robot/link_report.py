"""Each robot's link as the master's placer sees it (:mod:`rce_master.placer`): the round trip and
delivery rate the kernel measured on the robot's websocket (``TCP_INFO``), told to the master as
``robot_link {user, robot, rtt_ms, rate}`` every :data:`EVERY` s when either moved by
:data:`CHANGE` or more since the last report, and at least every :data:`REFRESH` s."""
from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from rce.transport.lane_socket import link_info, socket_of

__all__ = ["BATTERY_STEP", "CHANGE", "EVERY", "REFRESH", "LinkReports"]

EVERY = 0.5       # s between looks at the robots' sockets
CHANGE = 0.2      # a report when the round trip or the rate moved by this share
REFRESH = 10.0    # s, a report at least this often per robot
BATTERY_STEP = 1.0   # percentage points a robot's charge moves before the master is told again


class LinkReports:
    """What to tell the master about robots' links; ``send(user, robot, rtt_ms, rate)`` tells it.
    ``sample(now, robots)`` with ``robots`` (user, robot, websocket) triples; returns how many
    reports went out."""

    def __init__(self, send: Callable[[str, str, float, float], Any]):
        self.send = send
        self.last: dict[tuple[str, str], tuple[float, float, float]] = {}    # -> (rtt_ms, rate, when)

    def sample(self, now: float, robots: Iterable[tuple[str, str, Any]]) -> int:
        sent, seen = 0, set()
        for user, robot, ws in robots:
            sock = socket_of(ws) if ws is not None else None
            info = link_info(sock) if sock is not None else None
            if info is None:
                continue
            key = (user, robot)
            seen.add(key)
            rtt_ms, rate = info[0] * 1e3, info[1]
            old = self.last.get(key)
            if old is None or now - old[2] >= REFRESH or _moved(old[0], rtt_ms) or _moved(old[1], rate):
                self.last[key] = (rtt_ms, rate, now)
                self.send(user, robot, rtt_ms, rate)
                sent += 1
        for key in [k for k in self.last if k not in seen]:
            del self.last[key]
        return sent


def _moved(old: float, new: float) -> bool:
    return abs(new - old) > CHANGE * max(abs(old), 1e-9)
