"""What a fleet run shows and writes: the live table and progress line, the ``--report`` JSON and
the ``--plot`` PNG of the driven paths. Each function takes the run, a :class:`rce_fleet.live.demo.Run`
(not imported here: the run imports this module)."""
from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

from .task_stream import goal_motion_delays, robot_section, tasks_section

EXIT_OK, EXIT_FAIL, EXIT_USAGE, EXIT_UNREACHABLE = 0, 1, 2, 3   # the run's exit codes


def blocked_by(state: dict) -> dict[int, str]:
    """A fleet state's blocked cells: cell -> who blocked it."""
    return dict(zip(state.get("blocked", []), state.get("blocked_by", []), strict=False))


def fmt_state(state: str) -> str:
    """A robot state in the live table's colours (rich markup)."""
    colours = {"arrived": "green", "moving": "cyan", "waiting": "yellow", "unreachable": "red", "unknown": "dim"}
    c = colours.get(state)
    return f"[{c}]{state}[/{c}]" if c else state


def progress_line(run) -> str:
    """One plain progress line: sim time, goals reached, each robot's cell -> goal and state (a run by
    tasks: tasks done and each robot's activity)."""
    if run.o.lifelong:
        acts = activities(run)
        return (f"t={run.mission_t():6.1f}s  tasks done {(run.task_list or {}).get('done', 0)}  "
                + "  ".join(f"{r}:{acts[r]}{via(run, r)}" for r in run.robots))
    st = run.robot_states()
    parts = [f"{r}:{st.get(r, {}).get('cell', '?')}->{run.goals.get(r, '-')} {st.get(r, {}).get('state', '?')}"
             f"{via(run, r)}" for r in run.robots]
    head = f"reached {len(run.reached)}/{len(run.robots)}  " if run.o.mission else ""
    return f"t={run.mission_t():6.1f}s  {head}" + "  ".join(parts)


def via(run, robot: str) -> str:
    """`` via RELAY`` (or `` dark``) for a robot out of coverage, else ""."""
    lg = run.radio.logs.get(robot) if run.radio is not None else None
    return "" if lg is None else (" dark" if lg.via == "dark" else f" via {lg.via}")


ACTIVITIES = ("driving", "at errand", "to charger", "charging", "parking", "idle")   # as the table and PNG name them
_ACTIVITY_COLOURS = {"driving": "cyan", "at errand": "green", "to charger": "yellow", "charging": "magenta",
                     "parking": "blue", "idle": "dim"}


def activities(run) -> dict[str, str]:
    """Each robot's activity in a run by tasks (:data:`ACTIVITIES`), from the dispatcher's (task,
    to_charger, charging, parking, idle) and, on a task, whether the robot is moving."""
    st = run.robot_states()
    work = {r["robot"]: r for r in (run.task_list or {}).get("robots", [])}
    out = {}
    for r in run.robots:
        a = work.get(r, {}).get("activity", "idle")
        if a in ("task", "operator"):
            out[r] = "driving" if st.get(r, {}).get("state") == "moving" else "at errand"
        else:
            out[r] = {"to_charger": "to charger"}.get(a, a if a in ACTIVITIES else "idle")
    return out


def _robot_table(title: str, columns: tuple[tuple[str, str], ...]):
    """An empty rich table titled ``rce fleet: TITLE`` with ``columns`` (name, justify)."""
    from rich.table import Table
    t = Table(title=f"rce fleet: {title}", expand=False)
    for col, j in columns:
        t.add_column(col, justify=j)
    return t


def _task_table(run):
    """The live table of a run by tasks: a row per robot (activity, task, battery, tasks done, cell) and
    the run's counts."""
    from rich.console import Group
    from rich.text import Text
    t = _robot_table(f"{len(run.robots)} robots by tasks on {Path(str(run.map_path)).name}, speedup {run.o.speedup:g}",
                     (("robot", "left"), ("activity", "left"), ("task", "left"), ("battery %", "right"),
                      ("tasks done", "right"), ("charges", "right"), ("cell", "right")))
    st = run.robot_states()
    work = {r["robot"]: r for r in (run.task_list or {}).get("robots", [])}
    acts = activities(run)
    for r in run.robots:
        w = work.get(r, {})
        a = acts[r]
        c = _ACTIVITY_COLOURS.get(a, "dim")
        bat = w.get("battery_pct", -1.0)
        t.add_row(r, f"[{c}]{a}[/{c}]" + via(run, r), str(w.get("task", "") or "-"),
                  f"{bat:.0f}" if bat >= 0 else "-", str(w.get("tasks_done", 0)), str(w.get("charges", 0)),
                  str(st.get(r, {}).get("cell", "?")))
    tl = run.task_list or {}
    foot = Text(f"t={run.mission_t():.0f} of {run.o.duration:g} s sim   tasks done {tl.get('done', 0)}, "
                f"queued {tl.get('queued', 0)}, failed {tl.get('failed', 0)}   generated {run.generated}")
    return Group(t, foot, *(Text(e, style="dim") for e in run.events))


def table(run):
    """The live table (a rich renderable): a row per robot, the blocked cells, the closest pair, the events;
    a run by tasks: :func:`_task_table`."""
    from rich.console import Group
    from rich.text import Text
    if run.o.lifelong:
        return _task_table(run)
    t = _robot_table(f"{len(run.robots)} robots, grid {run.geo.rows}x{run.geo.cols}, speedup {run.o.speedup:g}",
                     (("robot", "left"), ("cell", "right"), ("goal", "right"), ("left m", "right"),
                      ("replans", "right"), ("cancels", "right"), ("state", "left")))
    st = run.robot_states()
    for r in run.robots:
        s = st.get(r, {})
        state = "reached" if r in run.reached else s.get("state", "?")
        t.add_row(r, str(s.get("cell", "?")), str(run.goals.get(r, "-")),
                  f"{s.get('distance_left', 0.0):.1f}", str(s.get("replans", 0)), str(s.get("cancels", 0)),
                  fmt_state(state) + via(run, r))
    blocked = (run.state or {}).get("blocked", [])
    mp = run.sim.min_pair if run.sim else math.inf
    foot = Text(f"t={run.mission_t():.1f} s sim   blocked: {blocked or '-'}   "
                f"closest robots: {mp:.2f} m   re-plans: {(run.state or {}).get('replans', 0)}")
    return Group(t, foot, *(Text(e, style="dim") for e in run.events))


def write_outputs(run, code: int, reason: str) -> None:
    """Write ``--plot`` and ``--report`` and print the verdict; a failed plot is reported, never raised."""
    o = run.o
    rep = report(run, code, reason)
    if o.plot and run.sim is not None and o.lifelong:
        from .plot import plot_tasks
        try:
            title = f"{Path(str(run.map_path)).name}: {len(run.robots)} robots by tasks"
            rep["plot"] = str(plot_tasks(o.plot, list(run.timeline), ACTIVITIES, title).resolve())
        except Exception as e:  # a plot never hides the result
            rep["plot_error"] = repr(e)
    elif o.plot and run.sim is not None:
        from .plot import plot_run
        blocked = blocked_by(run.state or {})
        traces = {r: [(x, y) for _, x, y in b.trace] for r, b in run.sim.bots.items()}
        t = rep.get("mission_time_s") or rep.get("sim_time_s") or 0.0
        title = (f"{Path(run.map_path).name}: {len(run.robots)} robots, grid {run.geo.rows}x{run.geo.cols}, "
                 f"t={t:.1f} s sim\n" + ("all goals reached" if code == EXIT_OK else "FAILED: " + reason[:90]))
        try:
            p = plot_run(o.plot, run.occ, run.geo, traces, run.starts, run.goals if o.mission else {},
                         blocked, title, {r: r in run.reached for r in run.robots})
            rep["plot"] = str(p.resolve())
        except Exception as e:  # a plot never hides the result
            rep["plot_error"] = repr(e)
    if o.report:
        Path(o.report).parent.mkdir(parents=True, exist_ok=True)
        Path(o.report).write_text(json.dumps(rep, indent=2))
    verdict = "OK" if code == EXIT_OK else "FAILED"
    print(f"rce-fleet: {verdict}: {reason}", file=sys.stdout if code == EXIT_OK else sys.stderr, flush=True)
    if rep.get("mission_time_s") is not None:
        mp = rep["min_pair_distance_m"]
        print(f"rce-fleet: mission time {rep['mission_time_s']:.1f} s sim, "
              f"{rep['mission_wall_s']:.1f} s wall; closest robots "
              f"{'-' if mp is None else format(mp, '.3f')} m; "
              f"re-plans {rep['planner']['replans']} (max {rep['planner']['max_plan_ms']:.1f} ms)",
              flush=True)
    if rep.get("tasks"):
        print(kpi_lines(rep), flush=True)
    if rep.get("placement"):
        pl = rep["placement"]
        where = ", ".join(f"{c['ctag'][3:]} {c['runs'].split(' ')[0]}" for c in pl["containers"])
        print(f"rce-fleet: move_clients ran on: {where}; {len(pl['moves'])} moves", flush=True)
    if rep.get("plot"):
        what = "tasks done and activity" if o.lifelong else "paths"
        print(f"rce-fleet: {what} plotted to {rep['plot']}", flush=True)


def kpi_lines(rep: dict) -> str:
    """The KPIs of a run by tasks as console lines: tasks done and per hour, the sim time the first was
    done, task time mean and p95, utilisation, charges, stall alerts."""
    t, per = rep["tasks"], rep.get("per_robot", {})
    util = [w["utilisation"] for w in per.values() if "utilisation" in w]
    charges = sum(int(w.get("charges", 0)) for w in per.values())
    mean_util = 100.0 * sum(util) / len(util) if util else 0.0
    first = "-" if t.get("first_done_s") is None else f"{t['first_done_s']:.0f} s"
    return (f"rce-fleet: tasks done {t['done']} in {rep['lifelong']['duration_s']:.0f} s sim "
            f"({t['per_hour']:.0f} per hour), failed {t['failed']}, queued {t['queued']}; first done at {first} sim\n"
            f"rce-fleet: task time mean {t['mean_s']:.1f} s, p95 {t['p95_s']:.1f} s; "
            f"utilisation {mean_util:.0f} %; charges {charges}; stall alerts {len(rep.get('alerts', []))}")


def report(run, code: int, reason: str) -> dict:
    """The ``--report`` JSON (per robot, blocks, obstacles, planner, simulator ground truth)."""
    st = run.robot_states()
    sim = run.sim
    t0 = run.t_mission
    per = {}
    for r in run.robots:
        s = st.get(r, {})
        b = sim.bots.get(r) if sim else None
        cells = [(round(t - (t0 or 0.0), 2), c) for t, c in b.cells] if b else []
        per[r] = {"start": run.starts.get(r), "goal": run.goals.get(r), "reached": r in run.reached,
                  "reached_at_s": round(run.reached[r] - t0, 2) if r in run.reached and t0 is not None else None,
                  "state": s.get("state"), "error": s.get("error", ""),
                  "cancel_goal": s.get("cancels", 0), "replans": s.get("replans", 0),
                  "robot_cancels_received": b.cancels_received if b else 0,
                  "waypoints_received": b.goals_received if b else 0,
                  "distance_m": round(b.distance, 3) if b else 0.0,
                  "cells": cells}
    blocks = []
    for rec in run.block_log:
        entries = sim.entries_after(rec["cell"], rec["sent_t"]) if sim else []
        blocks.append({k: v for k, v in rec.items() if k != "sent_t"} |
                      {"entered_after": [{"robot": rr, "t_s": round(t - t0, 2)} for rr, t in entries]})
    all_reached = run.reached and len(run.reached) == len(run.robots)
    mission_t = (max(run.reached.values()) - t0) if all_reached else None
    fs = run.state or {}
    return {
        "ok": code == EXIT_OK, "exit_code": code, "reason": reason,
        "map": str(run.map_path), "robots": len(run.robots), "seed": run.o.seed, "speedup": run.o.speedup,
        "grid": {"rows": run.geo.rows, "cols": run.geo.cols, "cell_w_m": run.geo.cell_w_m,
                 "cell_h_m": run.geo.cell_h_m, "free_cells": len(run.geo.free_cells())},
        "mission_time_s": round(mission_t, 2) if mission_t is not None else None,
        "mission_wall_s": round(time.monotonic() - run.wall_mission, 2) if run.wall_mission else None,
        "run_wall_s": round(getattr(run, "wall_total", 0.0), 2),
        "sim_time_s": round(sim.time - (t0 or 0.0), 2) if sim else 0.0,
        "sim_lag_resets": sim.lag_resets if sim else 0,
        "sim_max_speedup": round(sim.effective_speedup(), 2) if sim else None,
        "robot_radius_m": sim.radius if sim else None,
        "min_pair_distance_m": round(sim.min_pair, 4) if sim and math.isfinite(sim.min_pair) else None,
        "min_pair_at": ({"t_s": round(sim.min_pair_at[0] - (t0 or 0.0), 2), "robots": list(sim.min_pair_at[1:])}
                        if sim and sim.min_pair_at else None),
        "blocks": blocks,
        "obstacles": [{k: v for k, v in o.items() if k != "sent_t"} for o in run.obstacle_log],
        "blocked": {str(c): src for c, src in blocked_by(fs).items()},
        "planner": {"replans": fs.get("replans", 0), "max_plan_ms": fs.get("max_plan_ms", 0.0),
                    "last_plan_ms": fs.get("last_plan_ms", 0.0), "replan_bound_ms": fs.get("replan_bound_ms", 0.0),
                    "replans_bounded": fs.get("replans_bounded", 0),
                    "replans_abandoned": fs.get("replans_abandoned", 0),
                    "robots_deferred_total": fs.get("robots_deferred_total", 0)},
        "errors": fs.get("errors", []),
        "alerts": [{"t_s": round(a["t"] - (t0 or 0.0), 2), "robot": a["robot"], "text": a["text"]}
                   for a in (run.manager.alerts if run.manager else [])],
        "alerts_dropped": run.manager.alerts_dropped if run.manager else 0,
        "bag": run.bag.report() if run.bag else None,
        "faults": run.faults.report() if run.faults else [],
        "per_robot": per,
        **lifelong_report(run, per),
        **({"coverage": run.radio.report() | {"master": run.master_relays}} if run.radio else {}),
        **({"placement": run.placement} if run.placement else {}),
        "workdir": str(run.workdir),
    }


def lifelong_report(run, per: dict) -> dict:
    """The ``tasks`` section and the task stream's numbers of a lifelong run; adds each robot's
    work (utilisation, distance_m, battery_min_pct, charges, and ``charge_trips``: [sim s, battery %]
    as each trip to a charger began) to ``per``."""
    if not run.o.lifelong or run.t_mission is None:
        return {}
    for r, work in robot_section(run.task_list, run.sim).items():
        per.setdefault(r, {}).update(work, charge_trips=[list(x) for x in run.charge_trips.get(r, ())])
    t = run.mission_t()
    delays = goal_motion_delays(run.task_list, run.sim)
    ds = sorted(delays)
    tasks = tasks_section(run.task_list, t, run.generated)
    tasks["first_done_s"] = round(run.first_done, 2) if run.first_done is not None else None
    return {"tasks": tasks,
            "lifelong": {"duration_s": round(t, 2), "task_rate_per_min": run.o.task_rate,
                         "generated": run.generated, "refused": run.refused[:20],
                         "real_time_factor": round(t / max(time.monotonic() - run.wall_mission, 1e-9), 3),
                         "host_cpu_per_sim_s": round((time.process_time() - run.cpu_mission) / max(t, 1e-9), 3),
                         "goal_to_motion_s": {"n": len(ds), "p50": ds[len(ds) // 2] if ds else None,
                                              "p99": ds[min(len(ds) - 1, int(0.99 * len(ds)))] if ds else None},
                         "battery": run.o.battery.to_param() if run.o.battery else None,
                         "timeline_samples": len(run.timeline), "timeline_dropped": run.timeline_dropped,
                         "places": str(run.o.places or run.workdir / "places.yaml")}}
