"""Benchmark the lifelong fleet (rce_fleet.lifelong) under the League of Robot Runners 2024 rules,
against the league's default entry run in the same benchmark on the same problem, steps and time
limit (the start-kit v2.1.2's ``lifelong``, built from source: ``bench/startkit_peer.py``).

Problems: the shared ones in ``../shared/data/lorr/`` at their official number of steps (default),
problem JSONs of your own (``--problems``; at the steps of a ``simulation_time.json`` beside their
domain folder when there is one, as in the league's Benchmark-Archive), problems generated on any
map as the league's Problem Generator makes them (``--generate MAP --robots N,...``), or the
density sweep over every shared map (``--sweep``: random-32-32-20 at 100 - 800 robots, Paris and
brc202d at 1,000 / 3,000, sortation and warehouse at 2,000 / 5,000 / 10,000), or the 2024 main
round's ten instances at their full length (``--main-round``: ``bench/lifelong_main_round.py``),
beside the default entry and the 2024 winner's code (``--winner``, built from source outside the
repository: docs/lifelong.md), each (instance, system) result kept as it finishes so that a rerun
resumes, rce's outputs replayed under the rules, the table written into docs/results/lifelong.md.

Prints a table: tasks finished by rce and by the peer with the ratio, the published default entry's
and best known (``lorr/RESULTS.md``; scaled by steps on a cut, and marked), planner ms per step
(p50/p99/max), timeouts and invalid steps. Writes JSON and a PNG of tasks finished over time.

Usage::

    .venv/bin/python bench/lifelong.py [--quick] [--only NAME ...] [--steps N] [--problems JSON ...]
        [--generate MAP ... --robots N,... ] [--sweep] [--heldout] [--seed S] [--problem-dir DIR]
        [--main-round [--archive DIR] [--results DIR] [--doc MD]
         [--winner PATH [--winner-args ARGS] [--winner-cwd DIR]]]
        [--peer PATH [--peer-args ARGS] [--peer-cwd DIR] | --build-peer DIR]
        [--plan-time-limit MS] [--scheduler batch|greedy|both]
        [--cache-mb MB] [--lanes N] [--crowd-w W] [--max-active N] [--pursue N] [--window on|off] [--epibt on|off]
        [--keep-right N] [--admission on|off] [--replan on|off] [--race on|off] [--length-w W]
        [--yield-steps N] [--data ../shared/data]
        [--json PATH] [--plot PATH]
        [--outputs DIR]

``--quick`` runs a small cut (two problems, 100 steps) for the test suite; published
numbers are then scaled by steps and marked as such. Results go to ``bench/results/``
(lifelong.json, lifelong.png; lifelong_quick.* with --quick).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import sys
import time
from pathlib import Path

from common import git_head

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = (ROOT / ".." / "shared" / "data").resolve()
RESULTS = ROOT / "bench" / "results"
QUICK = {"random_32_32_20_100": 60, "paris_1_256_250": 30}
SWEEP = {"random.domain/maps/random-32-32-20.map": (100, 200, 400, 600, 800),
         "city.domain/maps/Paris_1_256.map": (1000, 3000),
         "game.domain/maps/brc202d.map": (1000, 3000),
         "warehouse.domain/maps/sortation_large.map": (2000, 5000, 10000),
         "warehouse.domain/maps/warehouse_large.map": (2000, 5000, 10000)}
GENERATED_STEPS = 1000          # steps of a generated problem when --steps is not given
HELDOUT_STEPS = 200             # steps of a --heldout problem when --steps is not given
HELDOUT_DENSITIES = (0.05, 0.2)   # robots per free cell of the --heldout problems
HELDOUT_LARGE_DENSITY = 0.1      # ... and of --heldout large's (teams of 1,941 - 2,781) ...
HELDOUT_LARGE_STEPS = 400        # ... at this many steps (the race's first answer comes after step 100)
# the tuned set beside the held-out one: maps the planner's constants were measured on
TUNED = ("random.domain/maps/random-32-32-20.map",)
PEERS = (ROOT / ".." / "peers").resolve()      # where the docs check out the peers' sources
# the 2024 winner's command (github.com/Straple/LORR24): EPIBT with operations of four actions and LNS,
# its guidance graph, the greedy scheduler
WINNER_ARGS = ("--pa", "pepibt(4)_lns", "--gg", "enable", "--sa", "greedy")
# ... and what its authors added for one instance: on the competition's GAME 4,000 of the 6,500 robots
# never take a task (``--disable_agents 4000``, their Solution/tester.cpp); with every robot on a task
# its code jams there from step ~700 (docs/results/lifelong.md)
WINNER_INSTANCE_ARGS = {"GAME": ("--disable_agents", "4000")}


def published(results_md: Path) -> dict[str, dict]:
    """Rows of RESULTS.md's table: name -> {robots, steps, best, best_team, default}."""
    out = {}
    row = re.compile(r"^\|\s*([\w.]+)/(\w+)\.json\s*\|\s*([\d,]+)\s*\|\s*([\d,]+)\s*\|\s*([\d,]+)\s*\(([^)]*)\)\s*\|"
                     r"\s*([\d,]+)\s*\|")
    for ln in results_md.read_text().splitlines():
        m = row.match(ln.strip())
        if m:
            num = [int(m.group(k).replace(",", "")) for k in (3, 4, 5, 7)]
            out[m.group(2)] = {"domain": m.group(1), "robots": num[0], "steps": num[1], "best": num[2],
                               "best_team": m.group(6), "default": num[3]}
    return out


def simulation_time(problem: Path) -> int | None:
    """The official steps of ``problem`` from the league's ``simulation_time.json`` (name -> steps)
    beside its domain folder, as the Benchmark-Archive's evaluation instances have it; None
    without one."""
    for d in (problem.parent, problem.parent.parent):
        f = d / "simulation_time.json"
        if f.is_file():
            steps = json.loads(f.read_text()).get(problem.stem)
            return int(steps) if steps else None
    return None


def run_one(path: Path, steps: int, limit_ms: float, scheduler: str, seed: int, pub: dict | None,
            outputs: Path | None, cache_mb: float | None = None, lanes: int | None = None,
            crowd_w: float | None = None, peer: Path | None = None, max_active: int | None = None,
            window: bool | None = None, epibt: bool | None = None, keep_right: int | None = None,
            admission: bool | None = None, peer_args: tuple[str, ...] = (), peer_cwd: Path | None = None,
            replan: bool | None = None, validate: bool = False, race: bool | None = None,
            length_w: float | None = None, yield_steps: int | None = None, pursue: int | None = None) -> dict:
    """Run one problem (and the start-kit binary ``peer`` on it, when given); returns its row (with
    the finished-over-time curve). With ``validate``, rce's output is replayed under the rules
    (``rce_fleet.lifelong.replay``): ``replayed_tasks`` and ``replay_invalid_steps`` in the row,
    and ``replay_error`` when the replay does not give the run's count."""
    from rce_fleet.lifelong import load_problem, replay
    from rce_fleet.lifelong.admission import jam_note
    from rce_fleet.lifelong.runner import rich_progress, run_lifelong

    prob = load_problem(path)
    with rich_progress(steps, f"{path.stem} ({scheduler})") as cb:
        res = run_lifelong(prob, steps, plan_time_limit_ms=limit_ms, seed=seed, scheduler=scheduler, progress=cb,
                           record=outputs is not None or validate,
                           cache_bytes=None if cache_mb is None else int(cache_mb * 2 ** 20),
                           lanes=lanes, crowd_w=crowd_w, max_active=max_active, pursue=pursue,
                           keep_right=keep_right, admission=admission, replan=replan, race=race, length_w=length_w,
                           planner_kw={k: v for k, v in (("ops", window), ("epibt", epibt),
                                                         ("yield_steps", yield_steps)) if v is not None} or None)
    s = res.summary()
    if (note := jam_note(s)) is not None:
        print(f"{path.stem}: {note}", file=sys.stderr)
    row = {"problem": path.stem, "robots": prob.team_size, "steps": steps, "scheduler": scheduler, **s,
           "tasks_per_step": s["tasks_finished"] / steps, "curve": res.finished.tolist()}
    if validate:
        again = replay(prob.grid, prob.tasks, prob.reveal, res.sim.output(prob.version))
        row.update(replayed_tasks=again.finished, replay_invalid_steps=again.invalid_steps)
        if again.finished != s["tasks_finished"] or again.invalid_steps != s["invalid_steps"]:
            row["replay_error"] = (f"replayed under the rules to {again.finished} tasks and {again.invalid_steps} "
                                   f"invalid steps, against the run's {s['tasks_finished']} and {s['invalid_steps']}")
            print(f"{path.stem}: {row['replay_error']}", file=sys.stderr)
    if pub:
        scale = steps / pub["steps"]
        row.update(official_steps=pub["steps"], scaled=scale != 1.0, default=pub["default"] * scale,
                   best=pub["best"] * scale, best_team=pub["best_team"])
        row["vs_default"] = s["tasks_finished"] / row["default"]
        row["vs_best"] = s["tasks_finished"] / row["best"]
    if peer is not None:
        from startkit_peer import run_peer
        try:
            label = " ".join((peer.name, *peer_args))
            if peer_args:                  # an entry other than the default one: named by its source tree
                row["peer_label"] = f"peer {peer.resolve().parent.parent.name}"
            with rich_progress(steps, f"{path.stem} (peer: {label})") as pcb:
                got = run_peer(peer, path, steps, limit_ms, progress=lambda k: pcb(k, 0, 0.0),
                               extra=peer_args, cwd=peer_cwd)
        except RuntimeError as e:          # the peer died (e.g. out of memory): the row says so, the run goes on
            row["peer_error"] = str(e).splitlines()[0]
            print(f"peer {peer.name} failed on {path.name}: {row['peer_error']}", file=sys.stderr)
        else:
            row.update({f"peer_{k}": v for k, v in got.items()})
            if got["tasks_finished"]:
                row["vs_peer"] = s["tasks_finished"] / got["tasks_finished"]
    if outputs is not None:
        outputs.mkdir(parents=True, exist_ok=True)
        out = outputs / f"{path.stem}.{scheduler}.json"
        out.write_text(json.dumps(res.sim.output(prob.version)))
        row["output"] = str(out)
    return row


def print_table(rows: list[dict]) -> None:
    """The rows as a rich table."""
    from rich.console import Console
    from rich.table import Table

    t = Table(title="Lifelong fleet under the LoRR 2024 rules (MAPF_T), beside the start-kit's default entry")
    for col in ("problem", "robots", "steps", "sched", "tasks", "peer", "x peer", "default", "x default",
                "best known", "x best", "tasks/step", "ms p50", "ms p99", "ms max", "cores", "timeouts", "invalid"):
        t.add_column(col, justify="right", no_wrap=col == "problem")
    for r in rows:
        mark = "*" if r.get("scaled") else ""
        peer = (f"{r['peer_tasks_finished']}" + (f" ({r['peer_timeouts']} t/o)" if r["peer_timeouts"] else "")
                if "peer_tasks_finished" in r else "failed" if "peer_error" in r else "-")
        t.add_row(r["problem"], str(r["robots"]), str(r["steps"]), r["scheduler"], str(r["tasks_finished"]),
                  peer, f"{r['vs_peer']:.2f}" if "vs_peer" in r else "-",
                  f"{r['default']:.0f}{mark}" if "default" in r else "-",
                  f"{r['vs_default']:.2f}" if "vs_default" in r else "-",
                  f"{r['best']:.0f}{mark}" if "best" in r else "-",
                  f"{r['vs_best']:.2f}" if "vs_best" in r else "-",
                  f"{r['tasks_per_step']:.2f}", f"{r['plan_ms_p50']:.1f}", f"{r['plan_ms_p99']:.1f}",
                  f"{r['plan_ms_max']:.1f}", f"{r['cores']:.2f}" if "cores" in r else "-", str(r["timeouts"]),
                  str(r["invalid_steps"]))
    con = Console(width=max(Console().width, 210))
    con.print(t)
    if any(r.get("scaled") for r in rows):
        con.print("* published number scaled by steps / official steps (a shorter run than the official one)")


def plot(rows: list[dict], path: Path) -> None:
    """PNG: tasks finished over time per problem, with the published numbers as lines."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = sorted({r["problem"] for r in rows}, key=lambda n: [r["robots"] for r in rows if r["problem"] == n][0])
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.8), squeeze=False)
    for ax, name in zip(axes[0], names, strict=True):
        mine = [r for r in rows if r["problem"] == name]
        for r in mine:
            ax.plot(range(1, len(r["curve"]) + 1), r["curve"], label=f"rce ({r['scheduler']})")
        r = mine[0]
        if "peer_tasks_finished" in r:
            ax.scatter([r["steps"]], [r["peer_tasks_finished"]], color="C3", marker="x", zorder=3,
                       label=f"{r.get('peer_label', 'default entry')}, same run")
        if "default" in r:
            steps = r["steps"]
            ax.plot([0, steps], [0, r["default"]], "--", color="grey", label="default entry (pro rata)")
            ax.plot([0, steps], [0, r["best"]], ":", color="black", label=f"best known ({r['best_team']})")
            ax.scatter([steps, steps], [r["default"], r["best"]], color=["grey", "black"], zorder=3, s=12)
        ax.set_title(f"{name} ({r['robots']} robots)", fontsize=9)
        ax.set_xlabel("step")
        ax.set_ylabel("tasks finished")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _robots(text: str) -> list[int]:
    try:
        out = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected N,N,... robots, got {text!r}") from None
    if not out or min(out) < 1:
        raise argparse.ArgumentTypeError(f"expected N,N,... robots (each >= 1), got {text!r}")
    return out


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data directory")
    ap.add_argument("--quick", action="store_true", help="a small cut for the test suite (2 problems, short runs)")
    ap.add_argument("--only", nargs="+", metavar="NAME", help="problems by name (e.g. random_32_32_20_100)")
    ap.add_argument("--problems", nargs="+", type=Path, metavar="JSON", help="problem JSONs of your own")
    ap.add_argument("--generate", nargs="+", type=Path, metavar="MAP",
                    help="generate problems on these maps (with --robots), as the league's Problem Generator does")
    ap.add_argument("--robots", type=_robots, metavar="N,...", help="team sizes of --generate")
    ap.add_argument("--sweep", action="store_true", help="generate and run the density sweep on every shared map")
    ap.add_argument("--heldout", nargs="?", const="small", choices=("small", "large"),
                    help="maps no constant was set on (bench/heldout_maps.py) at 0.05 and 0.2 robots per free "
                         f"cell, beside the tuned set's ({', '.join(Path(m).stem for m in TUNED)}), "
                         f"{HELDOUT_STEPS} steps; the summary compares the two sets; 'large': the same families "
                         f"at sizes for teams over 1,000, at {HELDOUT_LARGE_DENSITY} robots per free cell, "
                         f"{HELDOUT_LARGE_STEPS} steps")
    ap.add_argument("--problem-dir", type=Path, default=RESULTS / "problems", metavar="DIR",
                    help="where generated problems are written (default bench/results/problems)")
    ap.add_argument("--steps", type=int, help="steps for every problem (default: the official number; "
                    f"{GENERATED_STEPS} for generated ones)")
    ap.add_argument("--plan-time-limit", type=float, default=1000.0, metavar="MS")
    ap.add_argument("--scheduler", choices=("batch", "greedy", "both"), default="batch")
    ap.add_argument("--seed", type=int, default=0, help="seed of the generated problems and of the planner")
    ap.add_argument("--peer", type=Path, metavar="PATH", help="the start-kit's lifelong binary: run it beside rce")
    ap.add_argument("--peer-args", type=shlex.split, default=(), metavar="ARGS",
                    help="more arguments for a --peer that takes its own (an entry built on the start-kit), "
                         "one shell-quoted string")
    ap.add_argument("--peer-cwd", type=Path, metavar="DIR",
                    help="the directory the --peer runs in (default: a temporary one), for an entry that reads "
                         "its own data files from there")
    ap.add_argument("--build-peer", type=Path, metavar="DIR",
                    help="build the start-kit checked out at DIR (bench/startkit_peer.py) and use it as --peer")
    ap.add_argument("--cache-mb", type=float, help="bound of the distance maps (default: sized to the team and memory)")
    ap.add_argument("--lanes", type=int, help="extra cost of a move against a one-way lane (0: no lanes; default: the "
                    "runner's, 4, or 9 where EPIBT answers a team over 1,000 on a map of aisles)")
    ap.add_argument("--crowd-w", type=float, help="scheduler's steps per robot crowding a task's errands "
                    "(default: 5 for 3,000 robots or more, else 0)")
    from rce_fleet.cli import ADMISSION_HELP, MAX_ACTIVE_HELP, PURSUE_HELP, REPLAN_HELP
    ap.add_argument("--max-active", type=int, metavar="N", help=MAX_ACTIVE_HELP)
    ap.add_argument("--pursue", type=int, metavar="N", help=PURSUE_HELP)
    ap.add_argument("--keep-right", type=int, metavar="N",
                    help="extra cost of a move against the keep-right lane of a corridor 2 - 12 cells wide "
                         "(0: none; default 4)")
    ap.add_argument("--admission", choices=("on", "off"), help=ADMISSION_HELP)
    ap.add_argument("--replan", choices=("on", "off"), help=REPLAN_HELP)
    ap.add_argument("--window", choices=("on", "off"),
                    help="the windowed plan (operations + LNS) as a candidate of the lookahead where EPIBT is "
                         "off (default: on from 0.1 to 0.8 robots per free cell, up to 1,000 robots)")
    ap.add_argument("--epibt", choices=("on", "off"),
                    help="EPIBT with LNS as a candidate of the lookahead (default: on in teams up to 1,000 robots, "
                         "from 0.3 robots per free cell in any team, and in larger teams from 0.02 on maps that are "
                         "not maps of aisles and from 0.15 on maps of aisles; MAPF_T)")
    ap.add_argument("--race", choices=("on", "off"),
                    help="EPIBT and PIBT race in turns from step 100 and the one whose robots make the more "
                         "progress answers until the next race (rce_fleet.lifelong.race; default: on under 0.3 robots "
                         "per free cell, MAPF_T)")
    ap.add_argument("--length-w", type=float, metavar="W",
                    help="the share of a task's own length in its cost to a robot, beside the way to its first "
                         "errand (default: the scheduler's)")
    ap.add_argument("--yield-steps", type=int, metavar="N",
                    help="under EPIBT a robot without progress for more than N steps yields its priority (0: none; "
                         "default: 20, none from 0.3 robots per free cell, 0.15 on maps of aisles in teams over "
                         "1,000, and 5 on maps of fewer than 100 free cells)")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--plot", type=Path, help="the PNG of the runs (default bench/results/STEM.png; with "
                    "--main-round, each instance's tasks per 100 steps, default DIR/main_round.png of --results)")
    ap.add_argument("--outputs", type=Path, help="also write each run's start-kit output JSON into DIR")
    mr = ap.add_argument_group("the 2024 main round (--main-round)")
    mr.add_argument("--main-round", action="store_true",
                    help="run the 2024 main round's ten instances (--only: some of them) at their steps from "
                         "simulation_time.json, rce beside --peer and --winner; resumes from --results")
    mr.add_argument("--archive", type=Path, default=PEERS / "Benchmark-Archive", metavar="DIR",
                    help="a checkout of MAPF-Competition/Benchmark-Archive (or its 2024 main-round folder; "
                         "default ../peers/Benchmark-Archive)")
    mr.add_argument("--results", type=Path, default=RESULTS / "main_round", metavar="DIR",
                    help="one JSON per finished (instance, system); a rerun skips those there "
                         "(default bench/results/main_round)")
    mr.add_argument("--doc", type=Path, metavar="MD",
                    help="the markdown file whose main-round table is replaced (default docs/results/lifelong.md, "
                         "written only when every run is at its full length)")
    mr.add_argument("--peers-only", action="store_true",
                    help="run only --winner and --peer; rce's count is its row's in the --doc table")
    mr.add_argument("--winner", type=Path, metavar="PATH",
                    help="the 2024 winner's lifelong binary, built from its source (docs/lifelong.md)")
    mr.add_argument("--winner-args", type=shlex.split, metavar="ARGS",
                    help=f"its arguments on every instance, one shell-quoted string (default "
                         f"\"{shlex.join(WINNER_ARGS)}\", and on GAME its authors' "
                         "\"--disable_agents 4000\" after them)")
    mr.add_argument("--winner-cwd", type=Path, metavar="DIR",
                    help="the directory it runs in, where it reads its guidance maps (its source tree; default: "
                         "two levels above --winner)")
    return ap


def _rce_runner(args, peer: Path | None, validate: bool = False):
    """``run(problem, steps, scheduler, pub)`` -> rce's row on it, with the CLI's settings (and
    ``peer`` run beside it when given)."""
    def run(path: Path, steps: int, scheduler: str = "batch", pub: dict | None = None,
            with_peer: bool = True) -> dict:
        return run_one(path, steps, args.plan_time_limit, scheduler, args.seed, pub, args.outputs, args.cache_mb,
                       args.lanes, args.crowd_w, peer if with_peer else None, args.max_active,
                       None if args.window is None else args.window == "on",
                       None if args.epibt is None else args.epibt == "on", args.keep_right,
                       None if args.admission is None else args.admission == "on",
                       tuple(args.peer_args), args.peer_cwd,
                       None if args.replan is None else args.replan == "on", validate,
                       None if args.race is None else args.race == "on", args.length_w, args.yield_steps,
                       args.pursue)
    return run


def _peer_runner(binary: Path, extra: tuple[str, ...], cwd: Path | None, limit_ms: float, label: str,
                 per_instance: dict[str, tuple[str, ...]] | None = None):
    """``run(problem, steps)`` -> a start-kit-built entry's counts on it, with the arguments it was
    given (``args``: ``extra``, then ``per_instance``'s for the problem's name), or ``{"error": ...}``
    when it fails (e.g. killed out of memory), so that the round goes on."""
    def run(path: Path, steps: int) -> dict:
        from rce_fleet.lifelong.runner import rich_progress
        from startkit_peer import run_peer
        argv = (*extra, *(per_instance or {}).get(path.stem, ()))
        try:
            with rich_progress(steps, f"{path.stem} ({label})") as cb:
                return {**run_peer(binary, path, steps, limit_ms, progress=lambda k: cb(k, 0, 0.0), extra=argv,
                                   cwd=cwd, curve=True), "args": list(argv)}
        except RuntimeError as e:
            print(f"{label} failed on {path.name}: {e}", file=sys.stderr)
            return {"error": str(e).splitlines()[0], "args": list(argv)}
    return run


def _main_round(args, peer: Path | None) -> int:
    """``--main-round``: run what is not in ``--results`` yet, print and write the table (with the
    other instances' results on record there, at their official steps)."""
    import lifelong_main_round as mr
    from rich.console import Console

    con = Console(stderr=True)
    try:
        todo = mr.instances(args.archive, args.only)
    except (OSError, ValueError) as e:
        print(f"--main-round: {e}", file=sys.stderr)
        return 2
    official = {n: s for n, _, s in todo}
    if args.steps:
        todo = [(n, p, args.steps) for n, p, _ in todo]
    runners = {"rce": _rce_runner(args, None, validate=True)}
    if args.winner is not None:
        if not os.access(args.winner, os.X_OK):
            print(f"--winner {args.winner}: not an executable (docs/lifelong.md says how it is built)",
                  file=sys.stderr)
            return 2
        own = args.winner_args is None
        runners["winner"] = _peer_runner(args.winner, WINNER_ARGS if own else tuple(args.winner_args),
                                         args.winner_cwd or args.winner.resolve().parent.parent,
                                         args.plan_time_limit, "winner", WINNER_INSTANCE_ARGS if own else None)
    if peer is not None:
        runners["default"] = _peer_runner(peer, (), None, args.plan_time_limit, "default entry")
    rce_run = runners["rce"]
    runners["rce"] = lambda path, steps: {**rce_run(path, steps), "official_steps": official[path.stem]}
    if args.peers_only:
        if len(runners) == 1:
            print("--peers-only: give --winner or --peer", file=sys.stderr)
            return 2
        del runners["rce"]
    head = git_head()
    got = mr.run_round(todo, runners, args.results, args.plan_time_limit,
                       {"date": time.strftime("%Y-%m-%d"), "commit": head},
                       lambda line: con.print(line, soft_wrap=True, highlight=False))
    shown = mr.with_recorded(args.archive, todo, got, args.results, args.plan_time_limit, args.steps)
    cut = any(s != official[n] for n, _, s in todo)
    doc = args.doc or (None if cut else ROOT / "docs" / "results" / "lifelong.md")
    text = mr.table(shown, got, mr.recorded_rows(doc) if doc is not None else None)
    print(text)
    plot_path = args.plot or args.results / "main_round.png"
    if mr.plot_round(shown, got, plot_path):
        print(f"wrote {plot_path}")
    if doc is not None:
        try:
            mr.write_table(doc, text)
        except (OSError, ValueError) as e:
            print(f"--doc: {e}", file=sys.stderr)
            return 2
        print(f"wrote the table into {doc}")
    else:
        print("a cut (--steps): the record's table is left alone (--doc MD writes it)")
    rce = [r for (_, s), r in got.items() if s == "rce"]
    return 1 if any(r["timeouts"] or r["invalid_steps"] or "replay_error" in r for r in rce) else 0


def _problems(args, lorr: Path, pub: dict) -> list[tuple[Path, int]]:
    """(problem JSON, steps) to run, as the arguments say."""
    from rce_fleet.lifelong.generate import write_problem

    gen: list[tuple[Path, int]] = []
    if args.heldout:
        large = args.heldout == "large"
        return heldout_problems(args.problem_dir, lorr, args.seed,
                                args.steps or (HELDOUT_LARGE_STEPS if large else HELDOUT_STEPS), large=large)
    if args.sweep:
        gen += [(lorr / m, n) for m, teams in SWEEP.items() for n in teams]
    if args.generate:
        gen += [(m, n) for m in args.generate for n in args.robots]
    if gen:
        out = []
        for m, n in gen:
            path = write_problem(m, n, args.seed, args.problem_dir)
            print(f"generated {path}", flush=True)
            out.append((path, args.steps or GENERATED_STEPS))
        return out + [(p, args.steps or GENERATED_STEPS) for p in args.problems or ()]
    if args.problems:
        return [(p, args.steps or pub.get(p.stem, {}).get("steps") or simulation_time(p) or GENERATED_STEPS)
                for p in args.problems]
    problems = sorted(lorr.glob("*.domain/*.json"), key=lambda p: pub.get(p.stem, {}).get("robots", 0))
    if args.quick:
        problems = [p for p in problems if p.stem in QUICK]
    if args.only:
        problems = [p for p in problems if p.stem in args.only]
    return [(p, args.steps or (QUICK[p.stem] if args.quick else pub.get(p.stem, {}).get("steps", 1000)))
            for p in problems]


def heldout_problems(folder: Path, lorr: Path, seed: int, steps: int, large: bool = False) -> list[tuple[Path, int]]:
    """(problem JSON, steps) of ``--heldout``: the held-out maps (written to ``folder/heldout``) and
    the tuned set's, each at :data:`HELDOUT_DENSITIES`, as the league's Problem Generator makes
    problems (:mod:`rce_fleet.lifelong.generate`); ``large``: the large held-out maps alone
    (:data:`heldout_maps.HELDOUT_LARGE`), at :data:`HELDOUT_LARGE_DENSITY`."""
    from heldout_maps import HELDOUT_LARGE, write_maps
    from rce_fleet.lifelong.generate import write_problem
    from rce_fleet.lifelong.lorr import load_lorr_map

    if large:
        maps = list(write_maps(folder / "heldout", list(HELDOUT_LARGE)).values())
        return [(write_problem(path, round(HELDOUT_LARGE_DENSITY * cells), seed, folder), steps)
                for path, cells in maps]
    maps = list(write_maps(folder / "heldout").values())
    for m in TUNED:
        free = load_lorr_map(lorr / m).free_cells()
        maps.append((lorr / m, len(free)))
    out = []
    for path, cells in maps:
        for d in HELDOUT_DENSITIES:
            out.append((write_problem(path, max(1, round(d * cells)), seed, folder), steps))
    return out


def set_of(problem: str) -> str:
    """``"held-out"`` for a problem on a held-out map, ``"tuned"`` for the others."""
    from heldout_maps import EVERY
    return "held-out" if any(problem.startswith(n.replace("-", "_")) for n in EVERY) else "tuned"


def heldout_summary(rows: list[dict]) -> dict[str, dict]:
    """Per set (held-out, tuned): the problems, and the geometric mean and least of rce's tasks over
    the default entry's in the same run (rows with the peer's count)."""
    import math
    out = {}
    for name in ("held-out", "tuned"):
        ratios = [r["vs_peer"] for r in rows if "vs_peer" in r and set_of(r["problem"]) == name]
        out[name] = {"problems": sum(1 for r in rows if set_of(r["problem"]) == name), "with_peer": len(ratios),
                     "geomean_vs_peer": math.exp(sum(map(math.log, ratios)) / len(ratios)) if ratios else None,
                     "least_vs_peer": min(ratios) if ratios else None}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = _parser()
    args = ap.parse_args(argv)
    if args.generate and not args.robots:
        ap.error("--generate needs --robots N,...")
    if args.heldout and (args.quick or args.problems or args.generate or args.sweep or args.main_round):
        ap.error("--heldout runs its own problems: not with --quick, --problems, --generate, --sweep or --main-round")
    if args.main_round and (args.quick or args.problems or args.generate or args.sweep):
        ap.error("--main-round runs the main round's instances: not with --quick, --problems, --generate or --sweep")
    if args.main_round and args.scheduler == "both":
        ap.error("--main-round runs one scheduler")
    if args.length_w is not None and not 0 <= args.length_w < float("inf"):
        ap.error(f"--length-w {args.length_w}: a task's length weighs a finite share >= 0")
    if args.yield_steps is not None and args.yield_steps < 0:
        ap.error(f"--yield-steps {args.yield_steps}: steps without progress, >= 0 (0: none yields)")
    from rce_fleet.lifelong.pursuit import check_pursue
    try:
        check_pursue(args.pursue, args.max_active, args.admission == "on")
    except ValueError as e:
        ap.error(f"--pursue {args.pursue}: robots pursuing their task, >= 0, alone ({e})")
    lorr = args.data / "lorr"
    if not (lorr / "RESULTS.md").is_file():
        print(f"LoRR problems not found under {lorr}", file=sys.stderr)
        return 2
    pub = published(lorr / "RESULTS.md")
    peer = args.peer
    if args.build_peer:
        from startkit_peer import build_peer
        try:
            peer = build_peer(args.build_peer)
        except RuntimeError as e:
            print(f"--build-peer: {e}", file=sys.stderr)
            return 2
    if peer is not None and not os.access(peer, os.X_OK):
        print(f"--peer {peer}: not an executable (build it: bench/startkit_peer.py)", file=sys.stderr)
        return 2
    if args.main_round:
        return _main_round(args, peer)
    try:
        problems = _problems(args, lorr, pub)
    except (OSError, ValueError) as e:
        print(f"bench/lifelong.py: {e}", file=sys.stderr)
        return 2
    scheds = ("greedy", "batch") if args.scheduler == "both" else (args.scheduler,)
    stem = ("lifelong_quick" if args.quick else "lifelong_heldout_large" if args.heldout == "large"
            else "lifelong_heldout" if args.heldout else "lifelong_sweep" if args.sweep or args.generate
            else "lifelong")
    json_path = args.json or RESULTS / f"{stem}.json"
    plot_path = args.plot or RESULTS / f"{stem}.png"
    rows = []
    t0 = time.perf_counter()
    run = _rce_runner(args, peer)
    for p, steps in problems:
        for sch in scheds:
            rows.append(run(p, steps, sch, pub.get(p.stem), with_peer=sch == scheds[-1]))
            json_path.parent.mkdir(parents=True, exist_ok=True)
            json_path.write_text(json.dumps({"plan_time_limit_ms": args.plan_time_limit, "git": git_head(),
                                             "date": time.strftime("%Y-%m-%d"), "peer": str(peer) if peer else None,
                                             "peer_args": list(args.peer_args),
                                             "wall_s": time.perf_counter() - t0, "runs": rows}, indent=1))
    print_table(rows)
    if args.heldout:
        summary = heldout_summary(rows)
        for name, x in summary.items():
            if x["with_peer"]:
                print(f"{name}: {x['problems']} problems, rce / default entry: geometric mean "
                      f"{x['geomean_vs_peer']:.2f}, least {x['least_vs_peer']:.2f} ({x['with_peer']} beside it)")
            else:
                print(f"{name}: {x['problems']} problems (no --peer: no ratio)")
        data = json.loads(json_path.read_text())
        data["sets"] = summary
        json_path.write_text(json.dumps(data, indent=1))
    print(f"wrote {json_path}")
    plot_path.parent.mkdir(parents=True, exist_ok=True)
    plot(rows, plot_path)
    print(f"wrote {plot_path}")
    return 1 if any(r["timeouts"] or r["invalid_steps"] for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
