"""Where a container serves best: the placer's model and its decisions, sans I/O (docs/design.md, section 9.3).

For each container whose placement is ``auto`` the placer weighs every host that may run it
(:func:`options`): the cloud's and the edge's shared hosts, and the computer of the robot it
serves. All inputs are measured (the master feeds them in): each host's cores and load, the
robot's link (round trip, rate), the container's CPU use and the bytes per second it reads
from the robot, and the robot's battery.

**Latency of one result** on a host: the compute time (the container's measured work per result,
in core-ms, over the share of a core it gets there: ``min(1, free cores)``) plus, off the robot,
the link: one round trip and the result's input bytes at the link's rate. Its **margin** is the
deadline minus that latency; a host whose link cannot carry the input stream at all, or whose
margin is below 0, misses the deadline.

**Robot energy** (a stated model, :class:`EnergyModel`): on the robot, CPU joules (W per busy
core x the core-seconds the container burns per second); off the robot, radio joules per byte
for every byte it reads from the robot and sends back. This is the computation-offloading model
of mobile edge computing (e.g. Kumar and Lu, "Cloud computing for mobile users: can offloading
computation save energy?", IEEE Computer 43(4), 2010): offload when the compute saved costs more
than the bytes sent.

**Choice** (:func:`choose`): a host that meets the deadline beats one that does not. Among those,
the most margin wins; when the robot's battery is below its threshold, the least robot energy
wins. **Hysteresis**: the placer keeps the current host while it meets the deadline unless
another beats it by ``margin_gain`` of the deadline (or, on a low battery, by ``energy_gain`` of
the power), the better host must stay better for ``settle_s`` (``settle_miss_s`` when the current
host misses the deadline: every moment there costs results), and a container is never moved twice
within ``dwell_s``. Its own record weighs beside the model (:class:`Placer`): no move for margin or
energy to a host where its results were late, and a move without the margin's hysteresis from a
host where some of its results are late (within :data:`MISS_RATE_OK`) to a host that meets the
deadline by the model and where its results were never late. A user's pin overrides
everything.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

from rce.protocol.zones import Zone

__all__ = ["LATE_RECORD_S", "LATE_WINDOW_S", "MIN_RESULTS", "MISS_RATE_OK", "Choice", "ContainerView", "EnergyModel",
           "HostView", "LinkView", "Option", "Placer", "choose", "late_share", "options", "runner_up"]


@dataclass(frozen=True)
class EnergyModel:
    """The robot's energy: ``cpu_w`` W per busy core, ``radio_j_per_byte`` J per byte its radio
    sends or receives. Defaults are round numbers of the order of an embedded ARM core and an
    802.11 radio; set them for your robot (``rce-master --energy-cpu-w``, ``--energy-radio-nj``)."""
    cpu_w: float = 2.5
    radio_j_per_byte: float = 50e-9


@dataclass(frozen=True)
class HostView:
    """A container host as the placer sees it: ``cpu`` cores, ``load`` cores in use (measured, or
    requested where nothing is measured)."""
    tid: int
    name: str
    zone: Zone
    cpu: float
    load: float = 0.0


@dataclass(frozen=True)
class LinkView:
    """The robot's link to a shared zone: ``rtt_ms`` round trip, ``rate`` bytes/s."""
    rtt_ms: float
    rate: float


@dataclass(frozen=True)
class ContainerView:
    """A container as the placer sees it. ``deadline_ms``: due time of a result (None: no deadline,
    any host meets it); ``work_ms``: core-ms of CPU per result (measured); ``rate_hz``: results per
    second; ``in_bytes`` and ``out_bytes``: bytes per second it reads from and sends to its robot;
    ``cpu``: cores it asked for (its share is at most that, when given); ``node_ms``: its nodes'
    own latency from input to output where it runs now, measured (the median of the last seconds,
    :mod:`rce.node.results`; None: not measured), and ``miss_rate`` the share of its results there
    that missed the deadline, as it persisted (:func:`late_share`; None: no record yet)."""
    user: str
    ctag: str
    robot: str | None
    deadline_ms: float | None
    work_ms: float = 0.0
    rate_hz: float = 0.0
    in_bytes: float = 0.0
    out_bytes: float = 0.0
    cpu: float = 0.0
    node_ms: float | None = None
    miss_rate: float | None = None


#: the share of its results a container may miss where it runs, in each of two windows in a row
#: (:func:`late_share`), before that host counts as missing its deadline
MISS_RATE_OK = 0.05
LATE_WINDOW_S = 4.0    # s a window of a copy's results spans at least (:func:`late_share`)
MIN_RESULTS = 20       # results a window holds at least: fewer say nothing of a share of 5 %


def late_share(marks: list[tuple[float, int, int]], window_s: float = LATE_WINDOW_S,
               min_results: int = MIN_RESULTS) -> float | None:
    """The share of a copy's results that missed its deadline, as it persisted: the smaller of
    the shares of the last two windows in a row, each spanning at least ``window_s`` s and holding
    at least ``min_results`` results; None until there are two such windows (a young copy, or a
    quiet one, has no record yet). ``marks``: ``(t, results, misses)`` looks at the copy's
    cumulative counters (t in s, oldest first), from the end of its warm-up on, so that the slow
    first results of a fresh copy (imports, first calls: the move itself) never count. One bad
    window (a burst of late results) does not make a host miss its deadline; two do."""
    if not marks:
        return None
    t, r, m = marks[-1]
    shares = []
    for _ in range(2):
        start = next((x for x in reversed(marks) if t - x[0] >= window_s and r - x[1] >= min_results), None)
        if start is None:
            return None
        shares.append((m - start[2]) / (r - start[1]))
        t, r, m = start
    return min(shares)


@dataclass(frozen=True)
class Option:
    """One host for one container: ``latency_ms`` = ``compute_ms`` + ``link_ms``; ``margin_ms`` =
    deadline - latency (inf without a deadline); ``robot_w``: the robot's power spent (W);
    ``meets``: the deadline holds (and the link carries the stream)."""
    tid: int
    host: str
    zone: str
    compute_ms: float
    link_ms: float
    latency_ms: float
    margin_ms: float
    robot_w: float
    meets: bool


def options(c: ContainerView, hosts: list[HostView], links: dict[str, LinkView],
            energy: EnergyModel = EnergyModel(), current_tid: int | None = None) -> list[Option]:
    """Every host that may run ``c`` (its robot's own computer, and shared hosts of the zone kinds
    in ``links``: a shared zone without a measured link is left out when ``c`` serves a robot),
    with its latency, margin and robot power. ``links``: zone kind (``"cloud"``, ``"edge"``) ->
    :class:`LinkView`. On the host it runs on now (``current_tid``) what is measured counts: the
    compute time is the measured median ``node_ms`` where it is the larger (CPU throttling,
    queueing, a noisy neighbour show there first), and a host where more than :data:`MISS_RATE_OK`
    of its results were late in two windows in a row (``miss_rate``, :func:`late_share`) misses
    its deadline whatever the model says. The median is
    compared with the other hosts' model (a mean): both are a typical result, not its tail."""
    out = []
    for h in hosts:
        if not h.zone.serves(c.user, c.robot):
            continue
        share = max(0.0, h.cpu - h.load)
        if c.cpu:
            share = min(share, c.cpu)
        share = min(1.0, share)
        compute = c.work_ms / share if share > 0 else float("inf")
        if c.work_ms == 0:
            compute = 0.0
        if h.tid == current_tid and c.node_ms is not None:
            compute = max(compute, c.node_ms)
        if h.zone.kind == "robot":
            link_ms, meets_link = 0.0, True
            watts = energy.cpu_w * c.work_ms * c.rate_hz / 1e3
        else:
            link = links.get(h.zone.kind)
            if link is None:
                if c.robot is not None:
                    continue
                link = LinkView(0.0, float("inf"))
            per_result = (c.in_bytes + c.out_bytes) / c.rate_hz if c.rate_hz else 0.0
            link_ms = link.rtt_ms + 1e3 * per_result / link.rate if link.rate > 0 else float("inf")
            meets_link = c.in_bytes + c.out_bytes < link.rate
            watts = energy.radio_j_per_byte * (c.in_bytes + c.out_bytes)
        latency = compute + link_ms
        margin = (c.deadline_ms - latency) if c.deadline_ms is not None else float("inf")
        late = h.tid == current_tid and c.miss_rate is not None and c.miss_rate > MISS_RATE_OK
        out.append(Option(h.tid, h.name, str(h.zone), compute, link_ms, latency, margin, watts,
                          meets_link and margin >= 0 and not late))
    return out


@dataclass(frozen=True)
class Choice:
    """The placer's word on one container: ``target`` (None: no host can run it), ``current``
    (where it runs, None if nowhere the placer knows), ``move``: the placer wants it moved now,
    ``why``: the reason in words, ``options``: every host it weighed; ``wait_s``: s until it moves if
    the better host holds (0: no move pending, or it moves now)."""
    target: Option | None
    current: Option | None
    move: bool
    why: str
    options: list[Option] = field(default_factory=list)
    wait_s: float = 0.0

    def to_json(self) -> dict:
        return {"target": asdict(self.target) if self.target else None,
                "current": asdict(self.current) if self.current else None, "move": self.move, "why": self.why,
                "options": [asdict(o) for o in self.options]}


def _rank(o: Option, battery_low: bool) -> tuple:
    return (not o.meets, o.robot_w, -o.margin_ms) if battery_low else (not o.meets, -o.margin_ms, o.robot_w)


def choose(opts: list[Option], current_tid: int | None, battery_low: bool = False,
           margin_gain: float = 0.2, energy_gain: float = 0.2, deadline_ms: float | None = None) -> Choice:
    """The best of ``opts`` (module docstring), and whether it beats the current host
    ``current_tid`` by enough to move (hysteresis by gain only; time is :class:`Placer`'s)."""
    if not opts:
        return Choice(None, None, False, "no host may run it", [])
    best = min(opts, key=lambda o: _rank(o, battery_low))
    cur = next((o for o in opts if o.tid == current_tid), None)
    goal = "least robot energy (battery low)" if battery_low else "most margin"
    if cur is None:
        return Choice(best, None, False, f"{best.zone}: {_words(best)}; {goal}", opts)
    if best.tid == cur.tid:
        if not cur.meets:
            return Choice(best, cur, False, f"no host meets its deadline; stays on {cur.zone} ({_words(cur)})", opts)
        return Choice(best, cur, False, f"stays on {cur.zone}: {_words(cur)}; {goal}", opts)
    if not cur.meets:
        if best.meets:
            return Choice(best, cur, True, f"{cur.zone} misses its deadline ({_words(cur)}); {best.zone} "
                                           f"meets it ({_words(best)})", opts)
        return Choice(best, cur, False, f"no host meets its deadline; stays on {cur.zone} ({_words(cur)})", opts)
    if battery_low:
        gain = (cur.robot_w - best.robot_w) / cur.robot_w if cur.robot_w > 0 else 0.0
        if gain >= energy_gain:
            return Choice(best, cur, True, f"battery low: {best.zone} spends {best.robot_w:.2f} W of the robot's, "
                                           f"{cur.zone} {cur.robot_w:.2f} W; both meet the deadline", opts)
    else:
        span = deadline_ms if deadline_ms else max(cur.latency_ms, 1.0)
        if best.margin_ms - cur.margin_ms >= margin_gain * span:
            return Choice(best, cur, True, f"more margin on {best.zone}: {best.margin_ms:.0f} ms against "
                                           f"{cur.margin_ms:.0f} ms on {cur.zone}", opts)
    return Choice(best, cur, False, f"stays on {cur.zone} ({_words(cur)}): {best.zone} is not better by "
                                    f"the hysteresis", opts)


def runner_up(ch: Choice, battery_low: bool = False) -> Option | None:
    """The host ``ch`` ranks best after the one the container runs on (where a spare of it serves:
    the host it would move to next), whether or not it meets the deadline now; None if there is no
    other."""
    others = [o for o in ch.options if ch.current is None or o.tid != ch.current.tid]
    return min(others, key=lambda o: _rank(o, battery_low)) if others else None


def _words(o: Option) -> str:
    margin = "no deadline" if o.margin_ms == float("inf") else f"margin {o.margin_ms:.0f} ms"
    return (f"{o.latency_ms:.0f} ms ({o.compute_ms:.0f} compute + {o.link_ms:.0f} link), {margin}, "
            f"robot {o.robot_w:.2f} W")


#: s a host where a container's own results were late (its late share, :func:`late_share`) stays known
#: for it: the model's mean hides a heavy tail (one scan in ten that takes 4x the work), the record does not
LATE_RECORD_S = 120.0


class Placer:
    """The placer's memory across decisions: per container, when a better host was first seen and
    when it last moved, so that a move happens only once the better host has held for
    ``settle_s`` (``settle_miss_s`` when the host it runs on misses its deadline) and never twice
    within ``dwell_s``; and the hosts where its own results were late (more than
    :data:`MISS_RATE_OK` in two windows in a row) in the last ``late_record_s``: while the host it
    runs on meets its deadline, it is not moved to such a host for more margin or less energy
    (meeting the deadline comes first, and there it was measured not to).

    The other way round, the hosts where none of its results were late (a late share of 0 in two
    windows in a row) in the last ``late_record_s``: where it runs now some of its results are late,
    though not enough to count as missing (a heavy scan in twelve on a capped robot computer that
    meets the rest), and a clean one meets the deadline by the model, it moves to the best such host
    whatever the margins (the model's typical result hides the tail that the records show; the
    settle time and the dwell still hold). Times: the caller's clock, s."""

    def __init__(self, settle_s: float = 0.5, dwell_s: float = 10.0, margin_gain: float = 0.2,
                 energy_gain: float = 0.2, energy: EnergyModel = EnergyModel(), settle_miss_s: float = 0.2,
                 late_record_s: float = LATE_RECORD_S):
        self.settle_s, self.dwell_s, self.settle_miss_s = settle_s, dwell_s, settle_miss_s
        self.margin_gain, self.energy_gain, self.energy = margin_gain, energy_gain, energy
        self.late_record_s = late_record_s
        self._better_since: dict[tuple[str, str], tuple[int, float]] = {}
        self._moved_at: dict[tuple[str, str], float] = {}
        self._late_at: dict[tuple[str, str], dict[int, float]] = {}    # container -> host tid -> when it was late there
        self._clean_at: dict[tuple[str, str], dict[int, float]] = {}   # container -> host tid -> when never late there

    def decide(self, now: float, c: ContainerView, hosts: list[HostView], links: dict[str, LinkView],
               current_tid: int | None, battery_low: bool = False) -> Choice:
        """The choice for ``c`` at time ``now``; ``move`` is True only past the hysteresis in time."""
        key = (c.user, c.ctag)
        ch = choose(options(c, hosts, links, self.energy, current_tid), current_tid, battery_low, self.margin_gain,
                    self.energy_gain, c.deadline_ms)
        late = self._late_at.setdefault(key, {})
        clean = self._clean_at.setdefault(key, {})
        if current_tid is not None and c.miss_rate is not None and c.miss_rate > MISS_RATE_OK:
            late[current_tid] = now
        if current_tid is not None and c.miss_rate == 0:
            clean[current_tid] = now
        spotless = [o for o in ch.options if o.meets and o.tid != current_tid
                    and now - clean.get(o.tid, -float("inf")) <= self.late_record_s]
        if not ch.move and ch.current is not None and ch.current.meets and c.miss_rate and spotless:
            to = min(spotless, key=lambda o: _rank(o, battery_low))
            ch = Choice(to, ch.current, True, f"{c.miss_rate:.0%} of its results late on {ch.current.zone}, "
                                              f"none on {to.zone}, which meets the deadline ({_words(to)})",
                        ch.options)
        if ch.move and ch.current is not None and ch.current.meets and \
                now - late.get(ch.target.tid, -float("inf")) <= self.late_record_s:
            ago = now - late[ch.target.tid]
            ch = Choice(ch.target, ch.current, False, f"{ch.why}; but its results were late on {ch.target.zone} "
                                                      f"{ago:.0f} s ago: stays", ch.options)
        if not ch.move:
            self._better_since.pop(key, None)
            return ch
        tid, since = self._better_since.get(key, (None, now))
        if tid != ch.target.tid:
            since = now
        self._better_since[key] = (ch.target.tid, since)
        settle = self.settle_s if ch.current is None or ch.current.meets else self.settle_miss_s
        wait = max(since + settle, self._moved_at.get(key, -float("inf")) + self.dwell_s) - now
        if wait > 0:
            return Choice(ch.target, ch.current, False, f"{ch.why}; moves in {wait:.1f} s if it holds", ch.options,
                          wait)
        return ch

    def moved(self, now: float, user: str, ctag: str) -> None:
        """Record that container ``user/ctag`` moved at ``now`` (starts its dwell)."""
        self._moved_at[(user, ctag)] = now
        self._better_since.pop((user, ctag), None)

    def forget(self, user: str, ctag: str) -> None:
        """Drop what is kept of a container that is gone."""
        self._better_since.pop((user, ctag), None)
        self._moved_at.pop((user, ctag), None)
        self._late_at.pop((user, ctag), None)
        self._clean_at.pop((user, ctag), None)
