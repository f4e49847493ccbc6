"""The start-kit's output JSON, schedule included: an official output (the League of Robot Runners
start-kit v2.1.2's default entry on a problem of ours, ``tests/vectors/lorr_startkit/``) is read and
replayed under rce's rules, and rce's own output on the same problem passes the same schedule rules,
checked here independently of rce's simulator:

- an entry ``T:task`` takes effect at timestep T >= 1 (after the move of step T - 1), for a task
  revealed before T (``TaskManager::update_tasks`` assigns before it reveals);
- every change of a robot's task since its last entry is recorded, ``-1`` included, so no task is
  ever held by two robots;
- a task once opened (its first errand reached, an ``events`` entry) stays with its robot.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from rce_fleet.lifelong import load_problem, replay
from rce_fleet.lifelong.generate import generate_problem, write_problem
from rce_fleet.lifelong.runner import run_lifelong
from rce_fleet.lifelong.simulator import schedule_entries

VECTORS = Path(__file__).resolve().parents[1] / "vectors" / "lorr_startkit"
PROBLEM = VECTORS / "small_16_16_24_s7.json"
OFFICIAL = VECTORS / "startkit_output.json"


def schedule_faults(out: dict) -> list[str]:
    """What in ``out``'s ``actualSchedule`` breaks the start-kit's schedule rules (empty: none)."""
    revealed = {tid: t for tid, t, _ in out["tasks"]}
    finished: dict[int, int] = {}           # task -> timestep its last errand was reached
    opened: dict[int, tuple[int, int]] = {}  # task -> (timestep, robot) of its first errand
    last_errand = {tid: len(locs) // 2 for tid, _, locs in out["tasks"]}
    for t, robot, tid, seq in out["events"]:
        if seq == 1:
            opened.setdefault(tid, (t, robot))
        if seq == last_errand[tid]:
            finished[tid] = t
    faults = []
    holder: dict[int, int] = {}              # task -> robot holding it now
    task_of = [-1] * out["teamSize"]
    for t in sorted(sched := schedule_entries(out["actualSchedule"])):
        for tid in [k for k, at in finished.items() if at < t and k in holder]:
            task_of[holder.pop(tid)] = -1    # finished before T: its robot holds nothing
        for robot, tid in sched[t]:
            if t < 1:
                faults.append(f"robot {robot}: entry at timestep {t} (the first is 1)")
            old = task_of[robot]
            if old >= 0 and holder.get(old) == robot:
                del holder[old]
                if old in opened and opened[old][0] < t and finished.get(old, 10 ** 9) >= t:
                    faults.append(f"robot {robot} dropped task {old} opened at {opened[old][0]} (at {t})")
            task_of[robot] = tid
            if tid < 0:
                continue
            if revealed.get(tid, 10 ** 9) >= t:
                faults.append(f"robot {robot} assigned task {tid} at {t}, not revealed before")
            holder[tid] = robot
        held = [tid for tid in task_of if tid >= 0]
        if len(held) != len(set(held)):
            dup = sorted({tid for tid in held if held.count(tid) > 1})
            faults.append(f"at {t}: task(s) {dup[:3]} held by two robots")
    return faults


def test_official_output_replays_under_rces_rules_with_its_count():
    out = json.loads(OFFICIAL.read_text())
    p = load_problem(PROBLEM)
    assert out["actualSchedule"][0].startswith("1:")          # official outputs begin at timestep 1
    again = replay(p.grid, p.tasks, p.reveal, out)
    assert again.finished == out["numTaskFinished"] > 0
    assert again.invalid_steps == 0 and again.schedule_errors == []
    assert schedule_faults(out) == []


def test_rces_output_keeps_the_start_kits_schedule_rules():
    p = load_problem(PROBLEM)
    res = run_lifelong(p, 60, plan_time_limit_ms=1000.0, seed=1, record=True)
    out = res.sim.output()
    assert out["numTaskFinished"] > 0 and out["numEntryTimeouts"] == 0 and out["numScheduleErrors"] == 0
    assert all(s.split(",")[0].split(":")[0] != "0" for s in out["actualSchedule"] if s)
    assert schedule_faults(out) == []
    again = replay(p.grid, p.tasks, p.reveal, out)
    assert again.finished == out["numTaskFinished"] and again.invalid_steps == 0 and again.schedule_errors == []
    # the checker fails an output written one step early
    early = dict(out, actualSchedule=[",".join(f"{int(e.split(':')[0]) - 1}:{e.split(':')[1]}" for e in s.split(","))
                                      if s else s for s in out["actualSchedule"]])
    assert any("not revealed before" in f or "timestep 0" in f for f in schedule_faults(early))


def test_generated_problem_has_free_distinct_starts_and_two_to_five_errands(tmp_path):
    path = write_problem(VECTORS / "small-16-16.map", 30, 5, tmp_path, tasks=500)
    p = load_problem(path)
    assert len(set(p.starts.tolist())) == 30 == p.team_size and len(p.tasks) == 500
    assert {len(t) for t in p.tasks} == {2, 3, 4, 5}
    assert all(a != b for t in p.tasks for a, b in zip(t, t[1:], strict=False))
    assert p.warnings == []                 # every errand reachable from every start
    starts, tasks = generate_problem(VECTORS / "small-16-16.map", 30, 5, tasks=500)
    assert np.array_equal(starts, p.starts)  # the seed makes the problem


def test_the_run_picks_guidance_and_turn_commitment_by_density(tmp_path):
    free = len(load_problem(PROBLEM).grid.free_cells())
    sparse = load_problem(write_problem(VECTORS / "small-16-16.map", int(0.05 * free), 1, tmp_path, tasks=200))
    dense = load_problem(write_problem(VECTORS / "small-16-16.map", int(0.5 * free), 1, tmp_path, tasks=200))
    packed = load_problem(write_problem(VECTORS / "small-16-16.map", int(0.9 * free), 1, tmp_path, tasks=200))
    got = [(r.stats["guide"], r.stats["claim_steps"], r.sim.invalid_steps)
           for r in (run_lifelong(p, 8, record=False) for p in (sparse, dense, packed))]
    assert got == [(False, 1, 0), (True, 1, 0), (True, 0, 0)]


def test_tasks_taken_back_by_the_run_time_bound_keep_the_schedule_rules():
    """A bound set at run time (admission) takes unopened tasks back: each robot that loses one
    gets its -1 entry, no task is held twice, and the output replays to its count."""
    p = load_problem(PROBLEM)
    res = run_lifelong(p, 60, plan_time_limit_ms=250.0, seed=1, record=True, admission=True,
                       admission_kw={"window": 5, "target": 0.99, "decrease": 0.7, "start": None, "jam_factor": None})
    out = res.sim.output()
    bounds = [d[2] for d in res.stats["admission"]]
    assert res.stats["shed"] > 0 and bounds[0] is not None and bounds[-1] < bounds[0]
    assert out["numTaskFinished"] > 0 and out["numScheduleErrors"] == 0
    assert schedule_faults(out) == []
    assert any(e.endswith(":-1") for s in out["actualSchedule"] for e in s.split(",") if e)
    again = replay(p.grid, p.tasks, p.reveal, out)
    assert again.finished == out["numTaskFinished"] and again.invalid_steps == 0 and again.schedule_errors == []
