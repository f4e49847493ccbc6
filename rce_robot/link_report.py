"""Each robot's link as the master's placer sees it (:mod:`rce_master.placement.placer`): the round trip and
delivery rate the kernel measures (``TCP_INFO``), told to the master as ``robot_link {user, robot,
rtt_ms, rate}`` every :data:`EVERY` s when either moved by :data:`CHANGE` or more since the last
report, and at least every :data:`REFRESH` s.

Where the link is measured depends on where the robot endpoint stands:

- a shared endpoint (cloud, edge): on the robot's own websocket, which crosses the robot's link;
- an endpoint on the robot's own computer (``rce-robot --zone robot:ID``): the robot's websocket is
  local, and the robot's link is the endpoint's uplink (:class:`Uplink`): the round trip of its
  control link to the master (a ``ping`` request every look, the least of the last
  :data:`PING_KEEP_S` s: the kernel's smoothed round trip of a link that carries little takes
  seconds to follow a link that fell), and the delivery rate of its data links to the other hosts whenever
  they carried more than they were app-limited by. A data link that has held bytes it could not
  send at every look for :data:`BACKLOG_S` s is backed up: what the uplink carried meanwhile is its
  rate (a link that falls is seen within that time). An idle or app-limited link says nothing of its
  rate, so the endpoint also probes the link (:func:`probe_rate`): a request of :data:`PROBE_DRAIN_BYTES`
  to the master and one of :data:`PROBE_BYTES` right behind it; the time between their answers is
  what the link took to carry the second. A probe holds the control links' class up for as long as
  the link takes to carry it (0.38 s at 1 Mbit/s), so it goes only right after a ping (which sees a
  link that fell first), at most every :data:`PROBE_EVERY` s and :data:`PROBE_SHARE` of the link's
  time, never while a data link waits for the uplink, and not for :data:`PROBE_HOLD_S` s after the
  round trip grew (:meth:`Uplink.probe_due`): a switch to a container that moved because the link
  fell does not wait behind it. Once the round trip moved, the next probe goes as soon as it may.
  The last rate measured either way is kept (never forgotten for
  being old: a link that could not carry a stream stays that thin until a fresh measure says
  otherwise)."""
from __future__ import annotations

import ipaddress
from collections.abc import Callable, Iterable
from typing import Any

from rce.transport.lane_socket import link_backlog, link_info, link_sample, socket_of

__all__ = ["BACKLOG_S", "BATTERY_STEP", "CHANGE", "EVERY", "PING_KEEP_S", "PROBE_BYTES", "PROBE_DRAIN_BYTES",
           "PROBE_EVERY", "PROBE_HOLD_S", "PROBE_KEEP_S", "PROBE_SHARE", "REFRESH", "RWND_SHARE", "LinkReports",
           "Uplink", "crosses_uplink", "probe_rate", "websocket_link"]

EVERY = 0.25      # s between looks at the robots' sockets
CHANGE = 0.2      # a report when the round trip or the rate moved by this share
REFRESH = 10.0    # s, a report at least this often per robot
BATTERY_STEP = 1.0   # percentage points a robot's charge moves before the master is told again
PROBE_DRAIN_BYTES = 32_000   # bytes of a probe's first request: it drains a shaper's burst allowance (up to its size)
PROBE_BYTES = 16_000   # bytes of its second request, which the link's rate spaces from the first
PROBE_EVERY = 1.0      # s between probes (48 kB: ~380 kbit/s of the link's time)
PROBE_KEEP_S = 1.25    # s of measurements the rate is the fastest of (each errs only low)
BACKLOG_S = 0.5        # s a data link holds unsent bytes at every look before its throughput is the link's rate
RWND_SHARE = 0.1       # share of that time it may have waited for its reader's window (more: the reader's rate)
PING_KEEP_S = 0.6      # s of pings the round trip is the least of (two or three: one that waited is not the link)
PROBE_SHARE = 0.05     # share of the link's time its probes take at most (at its last measured rate)
PROBE_HOLD_S = 2.0     # s without a probe after a ping's round trip moved: the placer may move containers now
PING_MOVE_S = 0.005    # s a ping must differ by (beside CHANGE) for the round trip to have moved (jitter is not)


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


def probe_rate(first_done_s: float, second_done_s: float, nbytes: int = PROBE_BYTES) -> float:
    """The link's rate (bytes/s) from a probe: a message of :data:`PROBE_DRAIN_BYTES` and one of
    ``nbytes`` sent right behind it, answered at monotonic ``first_done_s`` and ``second_done_s`` s.
    The second waited behind the first at the link's bottleneck, so the time between the answers is
    what the link took to carry ``nbytes`` (packet-pair dispersion: the round trip cancels). The
    first drains a shaper's burst allowance: a burst of up to :data:`PROBE_DRAIN_BYTES` cannot pass
    the second at line rate (a larger one, up to both, makes the rate look too fast by at most
    ``nbytes / (drain + nbytes - burst)``). A spacing under 0.1 ms counts as 0.1 ms (the clock's and
    the loop's grain)."""
    return nbytes / max(second_done_s - first_done_s, 1e-4)


class Uplink:
    """The uplink of an endpoint on a robot's computer (module doc): ``control()`` gives the socket
    of its link to the master, ``data()`` the sockets of its data links that cross the uplink
    (:func:`crosses_uplink`: not those to a peer on the same computer).

    **Backed up**: when a data link has held bytes it could not send yet (``tcpi_notsent_bytes``) at
    every look of the last :data:`BACKLOG_S` s, not held back by its reader (the peer's receive
    window), the link carried all it could the whole time: what the uplink's links got acknowledged
    over that time (``tcpi_bytes_acked``, the link to the master's and the data links') is its rate,
    a measurement that errs neither low nor high. It stands alone: what was measured before is
    forgotten (a link that falls is seen within :data:`BACKLOG_S` s and a look).

    **Round trip**: the least of the pings of the last :data:`PING_KEEP_S` s (:meth:`pinged`: a
    request to the master and its answer, every look while no probe is on the link), else the
    kernel's smoothed round trip of the link to the master (``tcpi_rtt``). A ping measures the round
    trip a container's messages would see now; the kernel's estimate moves an eighth of the way to
    each new sample, and a control link that carries a keepalive a second takes seconds to show a
    link whose delay grew tenfold. The least of two or three pings is not fooled by one that waited
    behind a burst, and a link that fell is seen within :data:`PING_KEEP_S` s.

    Otherwise the rate is the fastest of what was measured in the last :data:`PROBE_KEEP_S` s: the
    delivery rates of busy data links and the endpoint's probes (:meth:`probed`, every
    :data:`PROBE_EVERY` s). Each of them errs only low (a data link's sample taken right after it
    idled is about the stream's own rate; a probe's answers can be read late), so the fastest is
    the nearest to the link's rate. A rate is never forgotten for being old: with nothing measured
    in the window, the link is as thin (or as fast) as it was last measured, until a measurement
    says otherwise."""

    def __init__(self, control: Callable[[], Any], data: Callable[[], Iterable[Any]]):
        self.control, self.data = control, data
        self.rate = 0.0              # bytes/s: the last rate measured (0: never measured)
        self.samples: list[tuple[float, float]] = []    # (monotonic s, bytes/s) of the last PROBE_KEEP_S s
        self.backed_up = 0           # looks whose rate was a backed-up link's (counter)
        self.pings: list[tuple[float, float]] = []      # (monotonic s, round trip s) of the last PING_KEEP_S s
        self.waiting = False         # a data link held bytes it could not send yet at the last look
        self.rtt_moved_at = float("-inf")   # monotonic s of the last ping whose round trip moved (pinged)
        self.rtt_rose = False               # ... and whether it grew
        # per socket (its id): looks (monotonic s, bytes acked, bytes not sent, us held by the reader's window)
        self._looks: dict[int, list[tuple[float, int, int, int]]] = {}

    def measure(self, now: float) -> tuple[float, float] | None:
        """``(rtt_s, rate)`` at monotonic ``now`` s (None while there is no link to the master)."""
        sock = self.control()
        info = link_sample(sock) if sock is not None else None
        if info is None:
            return None
        data = [d for d in self.data() if d is not None]
        rates = [s[1] for s in (link_sample(d) for d in data) if s is not None and not s[2] and s[1] > 0]
        full = self._backlog(now, sock, data)
        if full is not None:
            self.backed_up += 1
            self.samples, self.rate = [(now, full)], full
        else:
            self._take(now, rates)
        self.pings = [x for x in self.pings if now - x[0] <= PING_KEEP_S]
        return (min(r for _, r in self.pings) if self.pings else info[0]), self.rate

    def pinged(self, now: float, rtt_s: float) -> None:
        """A ping's round trip ``rtt_s`` (s), answered at monotonic ``now`` s (class doc). One that
        differs from the least of the pings kept by :data:`CHANGE` of it and :data:`PING_MOVE_S` marks
        the round trip as moved (:meth:`probe_due`)."""
        if rtt_s < 0:
            return
        kept = [r for t, r in self.pings if now - t <= PING_KEEP_S]
        if kept and abs(rtt_s - min(kept)) >= max(PING_MOVE_S, CHANGE * min(kept)):
            self.rtt_moved_at, self.rtt_rose = now, rtt_s > min(kept)
        self.pings.append((now, rtt_s))

    def probe_due(self, now: float, probed_at: float) -> bool:
        """Whether a probe may go at monotonic ``now`` s, the last having gone at ``probed_at``: never
        while a data link waits for the uplink, nor for :data:`PROBE_HOLD_S` s after the round trip
        grew (the link fell: the probe would take it longest, when containers may move across it);
        at once once the round trip moved since the last probe (its rate moved too, likely); else
        every :data:`PROBE_EVERY` s, and no oftener than keeps probes to :data:`PROBE_SHARE` of the
        link's time at its last measured rate."""
        if self.waiting or (self.rtt_rose and now - self.rtt_moved_at < PROBE_HOLD_S):
            return False
        if self.rtt_moved_at > probed_at:
            return True
        spacing = PROBE_EVERY
        if self.rate > 0:
            spacing = max(spacing, (PROBE_DRAIN_BYTES + PROBE_BYTES) / self.rate / PROBE_SHARE)
        return now - probed_at >= spacing

    def _backlog(self, now: float, control: Any, data: list[Any]) -> float | None:
        """The uplink's rate (bytes/s) if a data link was backed up over the last :data:`BACKLOG_S` s
        (class doc), else None; records this look."""
        looks: dict[int, list[tuple[float, int, int, int]]] = {}
        for sock in (control, *data):
            got = link_backlog(sock)
            if got is not None:
                kept = [x for x in self._looks.get(id(sock), ()) if now - x[0] <= BACKLOG_S + 2 * EVERY
                        and x[1] <= got[0]]           # (a socket gone, and its id taken by a new one: not its looks)
                looks[id(sock)] = [*kept, (now, *got)]
        self._looks = looks
        self.waiting = any(looks[id(d)][-1][2] > 0 for d in data if id(d) in looks)
        spans = [_span(looks.get(id(d), ()), now) for d in data]
        backed = [sp for sp in spans if sp and all(x[2] > 0 for x in sp)
                  and (sp[-1][3] - sp[0][3]) / 1e6 < RWND_SHARE * (sp[-1][0] - sp[0][0])]
        if not backed:
            return None
        t0 = min(sp[0][0] for sp in backed)
        acked = 0
        for xs in looks.values():
            first = next((x for x in reversed(xs) if x[0] <= t0), xs[0])
            acked += xs[-1][1] - first[1]
        return acked / (now - t0)

    def probed(self, now: float, rate: float) -> None:
        """A probe's rate (bytes/s, :func:`probe_rate`) at monotonic ``now`` s."""
        if rate > 0:
            self._take(now, [rate])

    def _take(self, now: float, rates: list[float]) -> None:
        self.samples = [x for x in self.samples if now - x[0] <= PROBE_KEEP_S] + [(now, r) for r in rates]
        if self.samples:
            self.rate = max(r for _, r in self.samples)


def _span(looks, now: float) -> list | None:
    """The looks of one socket from the newest at least :data:`BACKLOG_S` s old to ``now`` (None:
    it has none that old)."""
    start = next((i for i in range(len(looks) - 1, -1, -1) if now - looks[i][0] >= BACKLOG_S), None)
    return None if start is None else list(looks[start:])


def crosses_uplink(sock: Any) -> bool:
    """Whether a connected socket may cross the computer's uplink: its peer is not this computer
    (its own address, or loopback). A link to a container host on the same computer says nothing
    of the uplink (its delivery rate is the memory's, its backlog its reader's)."""
    try:
        peer, me = sock.getpeername()[0], sock.getsockname()[0]
    except (OSError, AttributeError, IndexError, TypeError):
        return False
    return peer != me and not ipaddress.ip_address(peer.split("%")[0]).is_loopback


def _moved(old: float, new: float) -> bool:
    return abs(new - old) > CHANGE * max(abs(old), 1e-9)
