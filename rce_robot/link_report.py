"""Each robot's link as the master's placer sees it (:mod:`rce_master.placer`): the round trip and
delivery rate the kernel measures (``TCP_INFO``), told to the master as ``robot_link {user, robot,
rtt_ms, rate}`` every :data:`EVERY` s when either moved by :data:`CHANGE` or more since the last
report, and at least every :data:`REFRESH` s.

Where the link is measured depends on where the robot endpoint stands:

- a shared endpoint (cloud, edge): on the robot's own websocket, which crosses the robot's link;
- an endpoint on the robot's own computer (``rce-robot --zone robot:ID``): the robot's websocket is
  local, and the robot's link is the endpoint's uplink (:class:`Uplink`): the round trip of its
  control link to the master, and the delivery rate of its data links to the other hosts whenever
  they carried more than they were app-limited by (the last such rate is kept while they are idle:
  a link that carries nothing says nothing of its rate)."""
from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from rce.transport.lane_socket import link_info, link_sample, socket_of

__all__ = ["BATTERY_STEP", "CHANGE", "EVERY", "RATE_HOLD", "REFRESH", "LinkReports", "Uplink", "websocket_link"]

EVERY = 0.25      # s between looks at the robots' sockets
CHANGE = 0.2      # a report when the round trip or the rate moved by this share
REFRESH = 10.0    # s, a report at least this often per robot
BATTERY_STEP = 1.0   # percentage points a robot's charge moves before the master is told again
RATE_HOLD = 20.0     # s an uplink's rate is kept after it was last measured (Uplink)


class LinkReports:
    """What to tell the master about robots' links; ``send(user, robot, rtt_ms, rate)`` tells it."""

    def __init__(self, send: Callable[[str, str, float, float], Any]):
        self.send = send
        self.last: dict[tuple[str, str], tuple[float, float, float]] = {}    # -> (rtt_ms, rate, when)

    def sample(self, now: float, robots: Iterable[tuple[str, str, tuple[float, float] | None]]) -> int:
        """``robots``: ``(user, robot, (rtt_s, rate) | None)`` (None: not measured); returns how
        many reports went out."""
        sent, seen = 0, set()
        for user, robot, info in robots:
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


def websocket_link(ws: Any) -> tuple[float, float] | None:
    """``(rtt_s, rate)`` of a robot's websocket (None: no socket, or no ``TCP_INFO``)."""
    sock = socket_of(ws) if ws is not None else None
    return link_info(sock) if sock is not None else None


class Uplink:
    """The uplink of an endpoint on a robot's computer (module doc): ``control()`` gives the socket
    of its link to the master, ``data()`` the sockets of its data links to other hosts. A rate is
    kept :data:`RATE_HOLD` s after the last time it was measured (a link that stops carrying the
    stream, its container moved to the robot, says nothing of its rate: once the hold ends the rate
    is unknown again, and the cloud is weighed by its round trip alone, a probe every hold at most)."""

    def __init__(self, control: Callable[[], Any], data: Callable[[], Iterable[Any]]):
        self.control, self.data = control, data
        self.rate = 0.0              # bytes/s: the last rate measured while not app-limited (0: unknown)
        self.rate_at = float("-inf")

    def measure(self, now: float) -> tuple[float, float] | None:
        """``(rtt_s, rate)`` at monotonic ``now`` s (None while there is no link to the master)."""
        sock = self.control()
        info = link_sample(sock) if sock is not None else None
        if info is None:
            return None
        rates = [s[1] for s in (link_sample(d) for d in self.data() if d is not None)
                 if s is not None and not s[2] and s[1] > 0]
        if rates:
            self.rate, self.rate_at = max(rates), now
        elif now - self.rate_at > RATE_HOLD:
            self.rate = 0.0
        return info[0], self.rate


def _moved(old: float, new: float) -> bool:
    return abs(new - old) > CHANGE * max(abs(old), 1e-9)
