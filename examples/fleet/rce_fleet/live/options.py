"""What ``rce-fleet demo`` and ``rce-fleet serve`` run: their flags as :class:`Options`, parsed and
checked here, before the run's machinery is imported (the engine's launcher, the simulator,
numba, scipy, matplotlib: about 1.5 s of CPU), so that a bad flag is refused at once. The checks
that need the map and its grid (cells, places) are :meth:`rce_fleet.live.demo.Run.prepare`'s.

Stdlib and :mod:`rce_fleet.operations.battery` only."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..operations.battery import BatteryParams

MASTER_DOWN_S = 2.0        # wall s the master stays dead (--fault master@T without +S)
LINK_CUT_S = 5.0           # wall s a robot's link stays cut (--fault link:ROBOT@T without +S)
SPEC_HELP = "master@T[+S] or link:ROBOT@T[+S] (T: sim s after the goals; S: wall s), e.g. master@5 or link:Robot1@5+5"


@dataclass
class Fault:
    """One ``--fault``: ``kind`` master or link, at ``at`` sim s after the goals, for ``duration`` wall s."""
    kind: str
    at: float
    duration: float
    robot: str = ""
    record: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return "master" if self.kind == "master" else f"link:{self.robot}"


def parse_fault(text: str) -> Fault:
    """``"master@5"`` / ``"link:Robot1@5+5"`` -> :class:`Fault`; raises ValueError naming the flag."""
    head, sep, when = text.partition("@")
    t, plus, dur = when.partition("+")
    try:
        if not sep:
            raise ValueError
        at, duration = float(t), (float(dur) if plus else None)
    except ValueError:
        raise ValueError(f"--fault {text!r}: expected {SPEC_HELP}") from None
    if at < 0 or (duration is not None and not duration > 0):
        raise ValueError(f"--fault {text!r}: T must be >= 0 and S > 0")
    if head == "master":
        return Fault("master", at, MASTER_DOWN_S if duration is None else duration)
    kind, colon, robot = head.partition(":")
    if kind == "link" and colon and robot:
        return Fault("link", at, LINK_CUT_S if duration is None else duration, robot)
    raise ValueError(f"--fault {text!r}: unknown fault {head!r}; expected {SPEC_HELP}")


class UsageError(ValueError):
    """A bad flag value; the message says which and why."""


@dataclass
class WebAccess:
    """Where the page and the task API listen and who may use them: ``bind`` (address), ``tls_cert`` and
    ``tls_key`` (PEM files: HTTPS), ``users`` (the master's ``--users`` file), ``metrics_public``
    (``/metrics`` without a credential), ``token_ttl`` (s a login's token lives; None: the default),
    ``admin_password_file`` (the first admin's password, :mod:`rce_fleet.live.access`)."""

    bind: str = "127.0.0.1"
    tls_cert: str | None = None
    tls_key: str | None = None
    users: str | None = None
    metrics_public: bool = False
    token_ttl: float | None = None
    admin_password_file: str | None = None


def web_access(args) -> WebAccess:
    """The :class:`WebAccess` of ``rce-fleet demo``/``serve``'s flags. Raises UsageError for one of
    ``--tls-cert``/``--tls-key`` without the other, or a ``--users`` file that is not there."""
    if (args.tls_cert is None) != (args.tls_key is None):
        raise UsageError("give both --tls-cert and --tls-key, or neither")
    for flag, path in (("--tls-cert", args.tls_cert), ("--tls-key", args.tls_key), ("--users", args.users),
                       ("--admin-password-file", args.admin_password_file)):
        if path is not None and not Path(path).is_file():
            raise UsageError(f"{flag} {path}: no such file")
    if args.foxglove_port is not None and args.headless:
        raise UsageError("--foxglove-port logs clients in with the page's tokens (POST /api/login): drop --headless")
    return WebAccess(args.web_bind, str(args.tls_cert) if args.tls_cert else None,
                     str(args.tls_key) if args.tls_key else None, str(Path(args.users).resolve()) if args.users
                     else None, args.metrics_public, args.token_ttl,
                     str(Path(args.admin_password_file).resolve()) if args.admin_password_file else None)


@dataclass
class Options:
    """What to run: the ``rce-fleet demo``/``serve`` flags (see :mod:`rce_fleet.cli`)."""

    map: str | None = None
    robots: int = 3
    grid: tuple[int, int] | None = None
    cell: float | None = None
    seed: int = 1
    speedup: float = 3.0
    headless: bool = False
    timeout: float = 300.0          # wall s the run may take (``--timeout``; ``serve``: until Ctrl-C)
    goals: dict[str, int] = field(default_factory=dict)
    starts: dict[str, int] = field(default_factory=dict)
    blocks: list[tuple[int, float]] = field(default_factory=list)
    obstacles: list[tuple[int, float]] = field(default_factory=list)
    plot: str | None = "fleet_paths.png"
    report: str | None = None
    bag: str | None = None          # ROS 1 bag of the fleet topics (``--bag``)
    record: str | None = None       # MCAP (``.mcap``) or ROS 1 bag of the fleet topics (``--record``)
    foxglove_port: int | None = None   # the Foxglove WebSocket server (rce_fleet.live.foxglove); None: none
    workdir: str | None = None
    keep: bool = False
    lidar_blocking: bool = True
    mission: bool = True
    live: bool | None = None        # None: when stdout is a terminal
    web_port: int = 8000            # the operator's web page (rce_fleet.live.webui); taken if free, else any
    web: WebAccess = field(default_factory=WebAccess)   # where the page and the task API listen, who may use them
    faults: list[Fault] = field(default_factory=list)   # ``--fault`` (injected by rce_fleet.live.faults)
    places: str | None = None       # ``--places`` YAML (None: generated for the map)
    lifelong: bool = False          # ``demo --lifelong``: a generated task stream for ``duration`` sim s
    duration: float = 600.0         # sim s of a lifelong run
    task_rate: float = 6.0          # tasks per sim minute of a lifelong run
    stations: str = "split"         # generated stations: split (left / right thirds) or paired (workstations)
    backlog: int = 0                # tasks waiting when a lifelong run starts
    battery: BatteryParams | None = None   # simulated batteries (``--battery``; a lifelong run has them)
    out_of_coverage: list[str] = field(default_factory=list)   # robots reaching the cloud only through relays
    edge_hosts: bool = False        # each robot's own computer (zone robot:RobotN) and a placed move_client container
    radio_range: float | None = None       # m between robots that hear each other (None: rce_fleet.live.radio default)
    ros2: bool = False              # ROS 2 robots, each with an rce-ros --ros2 process (rce_fleet.live.ros2_robots)


def parse_battery(spec: str | None, lifelong: bool) -> BatteryParams | None:
    """``--battery KEY=VALUE,...`` (keys of :class:`rce_fleet.operations.battery.BatteryParams`; empty:
    the defaults) -> params; None without the flag unless ``lifelong``. Raises UsageError."""
    if spec is None:
        return BatteryParams() if lifelong else None
    kw = {}
    for item in filter(None, (x.strip() for x in spec.split(","))):
        k, sep, v = item.partition("=")
        if not sep or k not in BatteryParams.__dataclass_fields__:
            raise UsageError(f"--battery {item!r}: expected KEY=VALUE with KEY one of "
                             f"{', '.join(BatteryParams.__dataclass_fields__)}")
        try:
            kw[k] = float(v)
        except ValueError:
            raise UsageError(f"--battery {item!r}: {v!r} is not a number") from None
    try:
        return BatteryParams(**kw)
    except ValueError as e:
        raise UsageError(f"--battery: {e}") from None


def parse_robot_cell(items: list[str], what: str) -> dict[str, int]:
    """``["Robot1=12", ...]`` -> ``{"Robot1": 12}``; raises UsageError."""
    out = {}
    for it in items or []:
        rid, sep, cell = it.partition("=")
        try:
            if not sep or not rid:
                raise ValueError
            out[rid] = int(cell)
        except ValueError:
            raise UsageError(f"--{what} {it!r}: expected ROBOT=CELL, e.g. Robot1=42") from None
    return out


def parse_cell_at(items: list[str], what: str) -> list[tuple[int, float]]:
    """``["26@5", ...]`` -> ``[(26, 5.0)]``; raises UsageError."""
    out = []
    for it in items or []:
        cell, sep, t = it.partition("@")
        try:
            if not sep:
                raise ValueError
            out.append((int(cell), float(t)))
        except ValueError:
            raise UsageError(f"--{what} {it!r}: expected CELL@SECONDS, e.g. 26@5") from None
        if out[-1][1] < 0:
            raise UsageError(f"--{what} {it!r}: seconds must be >= 0")
    return out


def parse_faults(items: list[str]) -> list[Fault]:
    """``["master@5", "link:Robot1@5+5"]`` -> faults (:func:`parse_fault`); raises UsageError."""
    try:
        return [parse_fault(it) for it in items or []]
    except ValueError as e:
        raise UsageError(str(e)) from None


def check_robots(o: Options) -> None:
    """The checks of ``o`` that need no map: the number of robots, the speed-up, and the robots that
    ``--goal``, ``--start``, ``--fault``, ``--out-of-coverage`` name. Raises UsageError naming the flag."""
    if o.robots < 1:
        raise UsageError("--robots must be >= 1")
    if o.backlog < 0:
        raise UsageError("--backlog must be >= 0 tasks")
    if o.speedup <= 0:
        raise UsageError("--speedup must be > 0")
    robots = {f"Robot{i}" for i in range(1, o.robots + 1)}
    for r in list(o.goals) + list(o.starts) + [f.robot for f in o.faults if f.robot]:
        if r not in robots:
            raise UsageError(f"unknown robot {r!r}: the robots are Robot1..Robot{o.robots}")
    for r in o.out_of_coverage:
        if r not in robots:
            raise UsageError(f"--out-of-coverage: unknown robot {r!r}: the robots are Robot1..Robot{o.robots}")
    if o.ros2 and (o.out_of_coverage or any(f.kind == "link" for f in o.faults)):
        raise UsageError(f"--ros2 with {'--out-of-coverage' if o.out_of_coverage else '--fault link:'}: a ROS 2 "
                         f"robot's bridge is an rce-ros process of its own, whose link the demo does not route "
                         f"(drop --ros2 for relays and link faults)")
    if not o.out_of_coverage:
        return
    if len(set(o.out_of_coverage)) == len(robots):
        raise UsageError("--out-of-coverage: at least one robot must have coverage, to relay for the others")
    for f in o.faults:
        if f.robot in o.out_of_coverage:
            raise UsageError(f"--fault {f.name}: {f.robot} is out of coverage (its links are radio links "
                             f"to relays, which drop as the robots move)")
    if o.radio_range is not None and not o.radio_range > 0:
        raise UsageError("--radio-range must be > 0 m")
