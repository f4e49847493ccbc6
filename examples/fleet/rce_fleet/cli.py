"""``rce-fleet``: the fleet system's command line.

::

    rce-fleet demo [--duration S] [--task-rate R/min] [--robots N] [--map YAML] [--places YAML]
                   [--battery KEY=V,...] [--report JSON] [--plot PNG]   # the warehouse run by tasks
    rce-fleet demo --mission [--map YAML] [--robots N] [--grid RxC | --cell M] [--seed S] [--speedup K]
                   [--goal RobotN=CELL]... [--start RobotN=CELL]... [--block CELL@S]...
                   [--obstacle CELL@S]... [--fault master@T[+S] | link:RobotN@T[+S]]...
                   [--timeout S] [--plot PNG] [--report JSON] [--bag FILE.bag] [--record FILE.mcap]
                   [--foxglove-port P]
                   [--headless] [--web-port P] [--places YAML] [--battery KEY=V,...]
                   [--out-of-coverage RobotN,... [--radio-range M]]      # the seed paper's one mission
    rce-fleet serve [same options, no mission]      # until Ctrl-C
                   [--web-bind ADDR] [--tls-cert PEM --tls-key PEM] [--users FILE] [--metrics-public]
                   [--admin-password-file FILE]
                   [--token-ttl S]                  # the page and the task API: docs/task-api.md
    rce-fleet replay RUN.mcap [--speed K] [--loop] [--web-port P | --headless] [--foxglove-port P]
    rce-fleet task add ERRAND... [--priority P] [--start-in S] [--deadline-in S] [--id ID] [--master URL | --api URL]
                   # S: fleet time, the robots' clock: simulated s under serve (--speedup K: K a wall second)
    rce-fleet task list [--json] | task get ID | task cancel ID     # the operators' task API
    rce-fleet users [list] | users add NAME [--role R] | users role NAME --role R | users password NAME
                   | users remove NAME  --api URL                   # an admin's: the users of a running serve
    rce-fleet configs [--out DIR] [--robots N] [--url URL]   # write robot1.config ...
    rce-fleet grid [--map YAML] [--grid RxC | --cell M]     # print the grid's cell numbers
    rce-fleet lifelong PROBLEM.json --steps N [--plan-time-limit MS] [--output OUT.json] [--seed S]
                   [--scheduler batch|greedy] [--cache-mb MB] [--lanes N]   # a LoRR 2024 problem under its rules
                   [--keep-right N] [--max-active N] [--pursue N] [--admission on|off] [--replan on|off]
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

# the help of --admission, rce-fleet lifelong's and bench/lifelong.py's
ADMISSION_HELP = ("the bound on robots holding a task set at run time: it starts at 0.04 robots per free cell "
                  "(half the team on maps under 4,000 free cells), rises while robots flow and falls while they "
                  "pack in at narrow passages, on larger maps at once to 0.7 of where they jammed and never "
                  "past it again (default: on from 0.1 to 0.3 robots per free cell on maps under 4,000 free "
                  "cells that are not maps of one-cell aisles, else off; ignored under --max-active)")
# the help of --pursue, the same in both
PURSUE_HELP = ("every robot may hold a task, and each step only N, those with the fewest steps left to the end of "
               "theirs, pursue it; the others stand aside (0: off; default: 0.058 robots per free cell from 0.1 "
               "to 0.3 robots per free cell on maps of 4,000 free cells or more that are not maps of one-cell "
               "aisles, in place of --admission, else 0)")
# the help of --replan, the same in both
MAX_ACTIVE_HELP = ("robots holding a task at most (0: no bound, no cut; default: 0.43 of the free cells where EPIBT "
                   "answers, else 0.3, 0.2 on a map of one-cell aisles, from 0.3 robots per free cell; below that "
                   "on a map of aisles 0.7 of the robots holding a task when a jam is first seen)")
REPLAN_HELP = ("whole LaCAM plans to the current goals, executed under turns in the plan's order and planned "
               "again at every arrival, the step's planner answering where no plan is found in time (default: on "
               "on maps under 100 free cells of which at least half have two free neighbours or fewer "
               "(corridors and dead ends), if the map has a dead end or the team is under 0.3 robots per "
               "free cell; MAPF_T)")

__all__ = ["main", "build_parser"]

DEMO_TIMEOUT_S = 300.0   # wall s a demo mission may take by default (--timeout)
DEFAULT_SPEEDUP = 3.0
# ``rce-fleet demo`` (``make demo``): the warehouse run by tasks, about two minutes of wall time at
# speed-up 4: workstations all over the warehouse (each pick-up with its drop-off 3 steps away), a task
# waiting per robot at the start, and batteries starting between 30 and 90 % of 10 Wh, so that the
# robots that start low go to charge once they need it (below 20 %), within the run
DEMO_MAP = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "maps" / "warehouse.yaml"
DEMO_ROBOTS = 12
DEMO_DURATION_S = 420.0
DEMO_SPEEDUP = 4.0
DEMO_TASK_RATE = 6.0
DEMO_BATTERY = "capacity_wh=10,initial=0.9,initial_spread=0.6,charge_w=500"
DEMO_STATIONS = "paired"
DEMO_PLOT, DEMO_TASKS_PLOT = "fleet_paths.png", "fleet_tasks.png"   # a mission's paths; a run's tasks and activity
SERVE_TIMEOUT_S = 10 ** 9   # wall s ``serve`` runs by default: until Ctrl-C
EXIT_PIPE = 141            # 128 + SIGPIPE: stdout's reader stopped reading
LIFELONG_MAX_STEPS = 10 ** 7   # steps a lifelong run records (LoRR's runs: 500 - 5,000; 10^7 is 116 days at 1 s a step)


def _grid(text: str) -> tuple[int, int]:
    r, sep, c = text.lower().partition("x")
    try:
        if not sep:
            raise ValueError
        rows, cols = int(r), int(c)
        if rows < 1 or cols < 1:
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected ROWSxCOLS like 8x8, got {text!r}") from None
    return rows, cols


def _positive(text: str) -> float:
    try:
        v = float(text)
        if not v > 0:
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}") from None
    return v


def _seed(text: str) -> int:
    """A random seed: an integer >= 0 (numpy's generators take no negative seed)."""
    try:
        v = int(text)
        if v < 0:
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    return v


def _rate(text: str) -> float:
    """``6``, ``6/min`` -> 6.0 (tasks per simulated minute, > 0)."""
    return _positive(text[:-4] if text.endswith("/min") else text)


def _robots(text: str) -> list[str]:
    """``Robot2,Robot5`` -> ["Robot2", "Robot5"]."""
    out = [r.strip() for r in text.split(",") if r.strip()]
    if not out:
        raise argparse.ArgumentTypeError(f"expected RobotN[,RobotM...], got {text!r}")
    return out


def _map_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--map", metavar="YAML", help="ROS map_server map (default: the project's lab map, generated)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--grid", type=_grid, metavar="ROWSxCOLS",
                   help="grid size (default 8x8 as in the paper; on a map where that gives cells over 2 m, "
                   "square cells of 1.2 m)")
    g.add_argument("--cell", type=_positive, metavar="METERS", help="square cells of this side instead")


def _run_args(p: argparse.ArgumentParser, mission: bool) -> None:
    _map_args(p)
    p.add_argument("--robots", type=int, default=None, metavar="N",
                   help=f"number of simulated robots (default {DEMO_ROBOTS} for demo on the warehouse, else 3)")
    p.add_argument("--seed", type=int, default=1, help="random starts/goals and sensor noise (default 1)")
    p.add_argument("--speedup", type=_positive, default=DEFAULT_SPEEDUP, metavar="K",
                   help=f"simulated time runs K times faster than wall time (default {DEFAULT_SPEEDUP:g}; demo on the "
                   f"warehouse {DEMO_SPEEDUP:g}); the fleet's clock, and every time of its tasks, is simulated time")
    p.add_argument("--start", action="append", default=[], metavar="RobotN=CELL", help="start cell of a robot")
    p.add_argument("--headless", action="store_true", help="no operator web page")
    p.add_argument("--web-port", type=int, default=8000, metavar="PORT",
                   help="port of the operator's web page (default 8000; any free port when taken; 0 = ephemeral)")
    _web_args(p)
    p.add_argument("--timeout", type=_positive, default=DEMO_TIMEOUT_S if mission else SERVE_TIMEOUT_S, metavar="S",
                   help="give up after S wall seconds" + (" (default 300)" if mission else ""))
    p.add_argument("--no-lidar-blocking", action="store_true",
                   help="the planner ignores obstacles the robots' lidars report")
    p.add_argument("--workdir", metavar="DIR", help="keep engine logs, configs and the map here (default: a temp dir)")
    p.add_argument("--keep", action="store_true", help="keep the temp dir")
    p.add_argument("--plot", metavar="PNG", default=DEMO_PLOT if mission else None,
                   help="PNG of the map, grid, blocked cells and driven paths (a run by tasks: tasks done over "
                   "time and each robot's activity)" + (f" (default {DEMO_PLOT}; by tasks {DEMO_TASKS_PLOT})"
                                                         if mission else ""))
    p.add_argument("--report", metavar="JSON", help="write a JSON report of the run")
    p.add_argument("--bag", metavar="FILE.bag", help="record the fleet topics (poses, paths, cancelGoal, fleet state) "
                   "into a ROS 1 bag")
    p.add_argument("--record", metavar="FILE.mcap", help="record the fleet topics into an MCAP file (ROS 1 "
                   "encoding, one channel per topic; a FILE.bag: a ROS 1 bag); rce-fleet replay plays it back")
    p.add_argument("--foxglove-port", type=int, metavar="PORT", help="serve the live fleet to Foxglove/Lichtblick "
                   "over the Foxglove WebSocket protocol on PORT (0 = ephemeral; default: not served)")
    p.add_argument("--places", metavar="YAML", help="named places (pick-up, drop-off, charger, parking) of the "
                   "map's grid (default: generated for the map, written to places.yaml in the work dir)")
    p.add_argument("--battery", metavar="KEY=VALUE,...", help="simulated batteries: capacity_wh, drain_wh_per_m, "
                   "idle_w, charge_w, threshold, recharge, initial, initial_spread (an empty value: the defaults; "
                   f"a run by tasks has them; demo on the warehouse: {DEMO_BATTERY})")
    p.add_argument("--out-of-coverage", type=_robots, default=[], metavar="RobotN,...",
                   help="robots without coverage of their own: they reach the cloud only through relays on the "
                   "other robots within --radio-range (docs/relays.md)")
    p.add_argument("--edge-hosts", action="store_true",
                   help="give each robot a computer of its own (a container host in zone robot:RobotN) and each "
                   "move_client a container the placer places; a robot out of coverage keeps it on board "
                   "(docs/placement.md)")
    p.add_argument("--ros2", action="store_true",
                   help="ROS 2 robots: each on a ROS 2 graph of its own (a domain leased for the run), bridged to the "
                   "cloud by an rce-ros --ros2 process (docs/fleet.md)")
    p.add_argument("--radio-range", type=_positive, metavar="M",
                   help="metres between two robots that hear each other (default: 3/4 of the map's shorter side: "
                   "6 on the lab map, 22.6 on warehouse.yaml)")
    p.add_argument("--live", dest="live", action="store_true", default=None,
                   help="live table even without a terminal")
    p.add_argument("--no-live", dest="live", action="store_false",
                   help="plain progress lines instead of the live table")


def _web_args(p: argparse.ArgumentParser) -> None:
    """Where the operator's page and the task API listen and who may use them (docs/task-api.md)."""
    from rce.transport.tls import add_server_arguments
    p.add_argument("--web-bind", default="127.0.0.1", metavar="ADDR",
                   help="address of the page and the task API (default 127.0.0.1; 0.0.0.0: every interface; "
                   "give it TLS then)")
    add_server_arguments(p, "serve the page and the task API over HTTPS (HTTP Basic needs it)")
    p.add_argument("--users", metavar="FILE", help="a master's users file (rce-console user add NAME --role "
                   "ROLE --file FILE), read only: who may log in to the page, the task API and the Foxglove port")
    p.add_argument("--admin-password-file", metavar="FILE", help="the first line of FILE is the password of the "
                   "first admin, user admin (default on loopback without --users: a password made for the run, "
                   "written to admin-password in the work dir, 0600; beyond loopback this or an admin in --users "
                   "is needed)")
    p.add_argument("--metrics-public", action="store_true", help="/metrics without a credential (default: a viewer's)")
    p.add_argument("--token-ttl", type=_positive, default=None, metavar="S",
                   help="wall s a token from POST /api/login lives (default 28800: 8 h)")


def build_parser() -> argparse.ArgumentParser:
    """The ``rce-fleet`` argument parser (sub-commands demo, serve, configs, grid, lifelong)."""
    p = argparse.ArgumentParser(prog="rce-fleet", description="The warehouse fleet on rce: demo, serve, configs.")
    sub = p.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("demo", help="a warehouse run by tasks for a bounded time, with batteries and charging, "
                       "ending with its KPIs (--mission: the seed paper's one mission instead)")
    _run_args(d, True)
    d.add_argument("--mission", action="store_true",
                   help="the seed paper's setup: one mission (a goal per robot; 3 robots on the lab map by default), "
                   "exit 0 when every robot reached its goal")
    d.add_argument("--goal", action="append", default=[], metavar="RobotN=CELL",
                   help="goal cell of a robot (repeatable; the others get random free cells)")
    d.add_argument("--block", action="append", default=[], metavar="CELL@S",
                   help="block CELL S simulated seconds after the goals were sent (repeatable)")
    d.add_argument("--obstacle", action="append", default=[], metavar="CELL@S",
                   help="drop a box in CELL S simulated seconds after the goals were sent (the start of a run by "
                   "tasks), unannounced: the robots' lidars must find it")
    d.add_argument("--fault", action="append", default=[], metavar="SPEC",
                   help="inject a fault T sim seconds after the goals were sent (repeatable): master@T[+S] kills "
                   "rce-master (kill -9) and restarts it on its state file after S wall seconds (default 2); "
                   "link:RobotN@T[+S] cuts RobotN's websocket for S wall seconds (default 5)")
    d.add_argument("--lifelong", action="store_true",
                   help="a run by tasks (the default without --mission; kept for scripts)")
    d.add_argument("--duration", type=_positive, default=None, metavar="S",
                   help=f"simulated seconds of the run by tasks (default {DEMO_DURATION_S:g} on the warehouse)")
    d.add_argument("--task-rate", type=_rate, default=None, metavar="R/min",
                   help=f"tasks per simulated minute (default {DEMO_TASK_RATE:g} on the warehouse)")
    d.add_argument("--backlog", type=int, default=None, metavar="N",
                   help="tasks waiting when the run by tasks starts, before the stream's (default 0; one per "
                   "robot on the warehouse)")
    d.add_argument("--stations", choices=("split", "paired"), default=None,
                   help="generated stations (without --places): split, pick-ups in the map's left third and "
                   "drop-offs in its right third, each task's drop-off drawn at random; paired, workstations "
                   "all over the map, each drop-off 3 steps from a pick-up and each task's drop-off the one "
                   f"nearest its pick-up (default split; {DEMO_STATIONS} on the warehouse)")
    s = sub.add_parser("serve", help="the same system without a mission, until Ctrl-C")
    _run_args(s, False)
    rp = sub.add_parser("replay", help="play a recording of --record FILE.mcap back onto the operator page "
                        "(and Foxglove), until Ctrl-C")
    rp.add_argument("recording", metavar="RUN.mcap", help="the MCAP file rce-fleet demo/serve --record wrote")
    rp.add_argument("--speed", type=_positive, default=1.0, metavar="K", help="K times the recorded pace (default 1)")
    rp.add_argument("--loop", action="store_true", help="start again at the end of the file")
    rp.add_argument("--web-port", type=int, default=8000, metavar="PORT",
                    help="port of the operator's web page (default 8000; any free port when taken; 0 = ephemeral)")
    rp.add_argument("--headless", action="store_true", help="no operator web page")
    rp.add_argument("--foxglove-port", type=int, metavar="PORT", help="also serve the replay to Foxglove/Lichtblick "
                    "on PORT (0 = ephemeral)")
    c = sub.add_parser("configs", help="write the robots' configs (robot1.config ...)")
    c.add_argument("--out", default="configs", metavar="DIR", help="directory (default configs)")
    c.add_argument("--robots", type=int, default=10, metavar="N", help="how many (default 10)")
    c.add_argument("--url", default="http://127.0.0.1:9000/", help="master login URL written into them")
    from .operations.task_cli import add_task_parser
    from .operations.users_cli import add_users_parser
    add_task_parser(sub)
    add_users_parser(sub)
    g = sub.add_parser("grid", help="print the grid's cell numbers (## = not free)")
    _map_args(g)
    lf = sub.add_parser("lifelong", help="run a League of Robot Runners 2024 problem under its rules "
                        "(lifelong tasks, MAPF_T actions, a time limit per step) and write the start-kit's output JSON")
    lf.add_argument("problem", metavar="PROBLEM.json", help="the problem JSON (mapFile, agentFile, taskFile, ...)")
    lf.add_argument("--steps", type=int, required=True, metavar="N", help="time steps to simulate")
    lf.add_argument("--plan-time-limit", type=_positive, default=1000.0, metavar="MS",
                    help="scheduler + planner wall time per step; an overrun is an all-wait step (default 1000)")
    lf.add_argument("--output", metavar="OUT.json", help="write the start-kit's output JSON here (PlanViz reads it)")
    lf.add_argument("--seed", type=_seed, default=0, help="tie-breaks of the planner (default 0)")
    lf.add_argument("--scheduler", choices=("batch", "greedy"), default="batch",
                    help="task allocation: batch assignment on finish times (default; bids greedily when the "
                    "matrix is too big for a step) or an auction on finish time")
    lf.add_argument("--cache-mb", type=_positive, metavar="MB",
                    help="bound of the distance maps (default: a map per free cell, within a quarter of the "
                    "available memory, at least 1024)")
    lf.add_argument("--lanes", type=int, metavar="N", help="extra cost of a move against a one-way lane in "
                    "one-cell-wide corridors (0: no lanes; default 4, and 9 where EPIBT answers a "
                    "team over 1,000 on a map of aisles)")
    lf.add_argument("--keep-right", type=int, metavar="N", help="extra cost of a move against the keep-right "
                    "lane of a corridor 2 - 12 cells wide (0: none; default 4)")
    lf.add_argument("--max-active", type=int, metavar="N", help=MAX_ACTIVE_HELP)
    lf.add_argument("--pursue", type=int, metavar="N", help=PURSUE_HELP)
    lf.add_argument("--admission", choices=("on", "off"), help=ADMISSION_HELP)
    lf.add_argument("--replan", choices=("on", "off"), help=REPLAN_HELP)
    lf.add_argument("--crowd-w", type=float, metavar="W", help="steps the scheduler adds per robot crowding a "
                    "task's errands beyond its share (default 5 for 3,000 robots or more, else 0)")
    lf.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def _lifelong(args: argparse.Namespace) -> int:
    """``rce-fleet lifelong``: 0 ok, 2 a missing or malformed problem or an unwritable
    ``--output``, 1 invalid or late steps."""
    import contextlib
    import json

    from .lifelong import ProblemError, load_problem
    from .lifelong.admission import jam_note
    from .lifelong.pursuit import check_pursue
    from .lifelong.runner import rich_progress, run_lifelong
    if not 1 <= args.steps <= LIFELONG_MAX_STEPS:
        print(f"rce-fleet lifelong: --steps must be 1 - {LIFELONG_MAX_STEPS:,}, got {args.steps:,}", file=sys.stderr)
        return 2
    try:
        check_pursue(args.pursue, args.max_active, args.admission == "on")
    except ValueError as e:
        print(f"rce-fleet lifelong: {e}; got --pursue {args.pursue}", file=sys.stderr)
        return 2
    try:
        problem = load_problem(args.problem)
    except ProblemError as e:
        print(f"rce-fleet lifelong: {e}", file=sys.stderr)
        return 2
    for w in problem.warnings:
        print(f"rce-fleet lifelong: {w}", file=sys.stderr)
    try:  # opened before the run, so a path that cannot be written costs no run
        out = open(args.output, "w") if args.output else contextlib.nullcontext(None)
    except OSError as e:
        print(f"rce-fleet lifelong: --output {args.output}: cannot write: {e.strerror}", file=sys.stderr)
        return 2
    from .lifelong.distances import cache_bytes_for
    try:
        cache_bytes = int(args.cache_mb * 2 ** 20) if args.cache_mb else cache_bytes_for(problem.grid,
                                                                                        problem.team_size)
    except MemoryError as e:
        print(f"rce-fleet lifelong: {e}; set --cache-mb", file=sys.stderr)
        return 2
    rows = cache_bytes // (2 * problem.grid.n_cells)
    need = min(problem.team_size + 16, int(problem.grid.flat.sum()))
    if rows < need:
        print(f"rce-fleet lifelong: --cache-mb {args.cache_mb:g} holds {rows} distance maps; "
              f"{problem.team_size} robots need {need} ({need * 2 * problem.grid.n_cells / 2 ** 20:.0f} MB)",
              file=sys.stderr)
        return 2
    bar = contextlib.nullcontext(None) if args.no_progress else rich_progress(args.steps, problem.path.stem)
    with out as f:
        with bar as cb:
            res = run_lifelong(problem, args.steps, plan_time_limit_ms=args.plan_time_limit, seed=args.seed,
                               scheduler=args.scheduler, cache_bytes=cache_bytes,
                               lanes=args.lanes, crowd_w=args.crowd_w,
                               keep_right=args.keep_right, max_active=args.max_active, pursue=args.pursue,
                               admission=None if args.admission is None else args.admission == "on",
                               replan=None if args.replan is None else args.replan == "on", progress=cb)
        s = res.summary()
        print(f"{problem.path.name}: {s['tasks_finished']} tasks finished in {s['steps']} steps by "
              f"{problem.team_size} robots; planner ms p50 {s['plan_ms_p50']:.1f} p99 {s['plan_ms_p99']:.1f} max "
              f"{s['plan_ms_max']:.1f}; timeouts {s['timeouts']}, invalid steps {s['invalid_steps']}, "
              f"schedule errors {s['schedule_errors']}")
        if (note := jam_note(s)) is not None:
            print(f"rce-fleet lifelong: {note}", file=sys.stderr)
        if f is not None:
            json.dump(res.sim.output(problem.version), f)
            print(f"wrote {args.output}")
    return 1 if s["timeouts"] or s["invalid_steps"] else 0


def _print_grid(args: argparse.Namespace) -> int:
    """``rce-fleet grid``: the cell numbers of the grid demo and serve cut the map into; 0 ok,
    2 a map that cannot be read or a grid that does not fit it."""
    import tempfile

    from .maps.grid import fleet_grid
    from .maps.lab_map import write_lab_map
    from .maps.occupancy import MapError, load_map
    try:
        with tempfile.TemporaryDirectory() as d:
            m = load_map(args.map or write_lab_map(d))
    except (MapError, OSError) as e:
        print(f"rce-fleet grid: --map: {e}", file=sys.stderr)
        return 2
    try:
        g, note = fleet_grid(m, args.grid, args.cell)
    except ValueError as e:
        print(f"rce-fleet grid: --grid/--cell: {e}", file=sys.stderr)
        return 2
    if note:
        print(note)
    print(f"{g.rows}x{g.cols} cells of {g.cell_w_m:.3f} x {g.cell_h_m:.3f} m, {len(g.free_cells())} free")
    print(g.ascii())
    return 0


def main(argv: list[str] | None = None) -> None:
    """Run ``rce-fleet``; exits with the demo's code (0 ok, 1 failure or timeout, 2 bad
    flags, 3 an unreachable goal). A reader that stops reading its output (``rce-fleet task list | head -1``)
    ends it quietly, with :data:`EXIT_PIPE`, as a shell reports a program that SIGPIPE ended."""
    try:
        try:
            _main(argv)
        finally:
            sys.stdout.flush()
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())   # nothing more to flush at exit
        sys.exit(EXIT_PIPE)


def _main(argv: list[str] | None) -> None:
    args = build_parser().parse_args(argv)
    if args.cmd == "lifelong":
        sys.exit(_lifelong(args))
    if args.cmd == "task":
        from .operations.task_cli import run_task
        sys.exit(run_task(args))
    if args.cmd == "users":
        from .operations.users_cli import run_users
        sys.exit(run_users(args))
    if args.cmd == "configs":
        from .configs import write_configs
        for path in write_configs(args.out, args.robots, args.url):
            print(path)
        return
    if args.cmd == "grid":
        sys.exit(_print_grid(args))
    if args.cmd == "replay":
        from .live.replay import run as replay
        sys.exit(replay(args.recording, speed=args.speed, loop=args.loop,
                        web_port=None if args.headless else args.web_port, foxglove_port=args.foxglove_port))
    from .live.demo_output import EXIT_USAGE
    from .live.options import (Options, UsageError, check_robots, parse_battery, parse_cell_at, parse_faults,
                               parse_robot_cell, web_access)
    mission = args.cmd == "demo" and args.mission
    lifelong = args.cmd == "demo" and not mission
    if lifelong and args.map is None and args.robots is None:       # the warehouse of ``make demo``
        if DEMO_MAP.is_file():
            args.map = str(DEMO_MAP.resolve())
            args.robots = DEMO_ROBOTS
            args.battery = DEMO_BATTERY if args.battery is None else args.battery
            args.speedup = DEMO_SPEEDUP if args.speedup == DEFAULT_SPEEDUP else args.speedup
            args.stations = DEMO_STATIONS if args.stations is None else args.stations
            args.backlog = DEMO_ROBOTS if args.backlog is None else args.backlog
        else:
            print(f"rce-fleet: the warehouse map {DEMO_MAP} is not here; running on the lab map", file=sys.stderr)
    if args.robots is None:
        args.robots = 3
    duration = getattr(args, "duration", None) or DEMO_DURATION_S
    task_rate = getattr(args, "task_rate", None) or DEMO_TASK_RATE
    if lifelong:
        if args.timeout == DEMO_TIMEOUT_S:     # room for a machine slower than the asked speed-up
            args.timeout = max(DEMO_TIMEOUT_S, 3 * duration / args.speedup + 120)
        if args.plot == DEMO_PLOT:
            args.plot = DEMO_TASKS_PLOT
    try:
        opts = Options(map=args.map, robots=args.robots, grid=args.grid, cell=args.cell, seed=args.seed,
                       speedup=args.speedup, headless=args.headless, timeout=args.timeout,
                       web=web_access(args),
                       goals=parse_robot_cell(getattr(args, "goal", []), "goal"),
                       starts=parse_robot_cell(args.start, "start"),
                       blocks=parse_cell_at(getattr(args, "block", []), "block"),
                       obstacles=parse_cell_at(getattr(args, "obstacle", []), "obstacle"),
                       faults=parse_faults(getattr(args, "fault", [])),
                       plot=args.plot, report=args.report, bag=args.bag, record=args.record,
                       foxglove_port=args.foxglove_port, workdir=args.workdir, keep=args.keep,
                       lidar_blocking=not args.no_lidar_blocking, mission=mission, live=args.live,
                       web_port=args.web_port, places=args.places, lifelong=lifelong,
                       duration=duration, task_rate=task_rate, stations=getattr(args, "stations", None) or "split",
                       backlog=getattr(args, "backlog", None) or 0,
                       battery=parse_battery(args.battery, lifelong), out_of_coverage=args.out_of_coverage,
                       edge_hosts=args.edge_hosts,
                       radio_range=args.radio_range, ros2=args.ros2)
        check_robots(opts)              # before the run's imports: a bad flag is refused at once
    except UsageError as e:
        print(f"rce-fleet: {e}", file=sys.stderr)
        sys.exit(EXIT_USAGE)
    from rce.plumbing.process import exit_command

    from .live.demo import run
    exit_command(run(opts), argv)      # as the command, without the teardown of numba, scipy and matplotlib


if __name__ == "__main__":
    main()
