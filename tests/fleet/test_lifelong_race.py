"""rce_fleet.lifelong.race: the run chooses its step planner by racing EPIBT and PIBT on the robots'
progress; the race's turns, its early end, its margin and its repeats; a real run that races."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rce_fleet.lifelong.kernels import UNREACHABLE
from rce_fleet.lifelong.race import MethodRace, progress


def _run(race: MethodRace, scores: dict[str, float], steps: int, settle_score: dict[str, float] | None = None):
    """Feed ``race`` ``steps`` steps, each scored by the arm answering it; the arms in turn."""
    seen = []
    for _ in range(steps):
        a = race.arm()
        seen.append(a)
        racing, pos = race.racing, (race._k - race._start) % race.window
        in_settle = racing and pos < race.settle and settle_score is not None
        race.observe(settle_score[a] if in_settle else scores[a])
    return seen


def test_an_arm_far_ahead_wins_after_one_round_and_the_next_race_comes_after_the_hold():
    r = MethodRace(["epibt", "pibt"], first=0, window=10, settle=3, hold=50)
    seen = _run(r, {"epibt": 10.0, "pibt": 20.0}, 20)
    assert seen == ["epibt"] * 10 + ["pibt"] * 10          # the one answering first, then the other
    assert r.history == [{"step": 0, "scores": {"epibt": 10.0, "pibt": 20.0}, "chosen": "pibt"}]
    assert r.current == 1 and r.switches == 1 and not r.racing
    assert _run(r, {"epibt": 10.0, "pibt": 20.0}, 50) == ["pibt"] * 50
    assert r.racing and r.arm() == "pibt"                  # the next race, the answering arm first
    _run(r, {"epibt": 10.0, "pibt": 20.0}, 20)
    assert [h["chosen"] for h in r.history] == ["pibt", "pibt"] and r.hold == 100   # the same again: twice the hold


def test_close_arms_race_every_round_and_the_one_answering_keeps_it_within_the_margin():
    r = MethodRace(["epibt", "pibt"], window=10, settle=3, rounds=2, margin=0.03, hold=50)
    seen = _run(r, {"epibt": 100.0, "pibt": 102.0}, 20)
    assert not r.history                                   # 2 % apart: not decisive, a second round
    seen += _run(r, {"epibt": 100.0, "pibt": 102.0}, 20)
    assert seen == (["epibt"] * 10 + ["pibt"] * 10) * 2
    assert r.history[0]["chosen"] == "epibt" and r.switches == 0   # under the 3 % margin
    r2 = MethodRace(["epibt", "pibt"], window=10, settle=3, rounds=2, margin=0.03)
    _run(r2, {"epibt": 100.0, "pibt": 110.0}, 40)          # 10 % ahead: over the margin, under decisive
    assert r2.history[0]["chosen"] == "pibt" and r2.switches == 1


def test_the_settling_steps_of_a_window_are_not_scored():
    r = MethodRace(["epibt", "pibt"], window=10, settle=3, rounds=1)
    # the other method's plan still moves the robots in a window's first steps: scores there are ignored
    _run(r, {"epibt": 5.0, "pibt": 8.0}, 20, settle_score={"epibt": 1000.0, "pibt": -1000.0})
    assert r.history[0]["scores"] == {"epibt": 5.0, "pibt": 8.0} and r.history[0]["chosen"] == "pibt"


def test_a_race_needs_two_arms_and_a_scored_step_in_a_window():
    with pytest.raises(ValueError, match="two arms or more"):
        MethodRace(["epibt"])
    with pytest.raises(ValueError, match="settle"):
        MethodRace(["epibt", "pibt"], window=3, settle=3)


def test_progress_sums_the_fall_of_each_robots_distance_to_its_goal():
    table = np.array([[0, 1, 2, 3], [3, 2, 1, UNREACHABLE]], dtype=np.uint16)
    slot = np.array([0, 0, 1, -1, 1])
    before = np.array([3, 1, 0, 2, 2])
    after = np.array([2, 0, 1, 3, 3])
    # 3->2: 1; 1->0 (arrives): 1; 3->2: 1; no goal: nothing; into a cell the goal cannot be reached from: nothing
    assert progress(table, slot, before, after) == 3.0
    assert progress(table, np.full(5, -1), before, after) == 0.0
    assert progress(table, slot, after, before) == -3.0


def test_a_run_races_epibt_and_pibt_and_keeps_the_rules(tmp_path):
    """A real run with the race on: both methods answer steps and are scored in every race (the stats
    list the races), and the run keeps its rules."""
    from rce_fleet.lifelong.generate import write_problem
    from rce_fleet.lifelong.lorr import load_problem
    from rce_fleet.lifelong.runner import run_lifelong
    small = Path(__file__).resolve().parents[1] / "vectors" / "lorr_startkit" / "small-16-16.map"
    p = load_problem(write_problem(small, 12, 1, tmp_path))
    kw = {"plan_time_limit_ms": 300.0, "record": False, "planner_kw": {"samples": 4}}
    race_kw = {"start": 0, "window": 10, "settle": 2, "hold": 30, "decisive": 10.0}
    s = run_lifelong(p, 120, race_kw=race_kw, **kw).summary()             # on by default
    # no timeouts asserted: a 300 ms limit on a machine the suite loads is a clock, not a check
    assert s["invalid_steps"] == 0 and s["tasks_finished"] > 0, s
    assert s["epibt"] is True                               # what answers a team of 12 before the first race
    hist = s["race"]["history"]
    assert len(hist) >= 2 and {h["chosen"] for h in hist} <= {"epibt", "pibt"}, hist
    assert all(set(h["scores"]) == {"epibt", "pibt"} for h in hist), hist
    assert all(v > 0 for h in hist for v in h["scores"].values()), hist     # robots moved to their goals
    # EPIBT planned the steps of its turns, and not the others: PIBT answered 2 x 10 steps of each race
    assert 10 <= s.get("epibt_steps", 0) <= 120 - 20 * len(hist), s
    late = run_lifelong(p, 5, **kw).summary()                   # the default race begins at step 100
    assert late["race"] == {"history": [], "switches": 0, "last": "epibt"} and "epibt_steps" in late, late
    assert run_lifelong(p, 5, race=False, **kw).summary()["race"] is None


def test_an_arm_far_behind_is_dropped_after_its_early_steps_not_its_window():
    """With ``early``, the arm answering keeps its place as soon as the other has that many scored
    steps and trails it by ``decisive``: a method far behind costs settle + early steps of a race."""
    r = MethodRace(["epibt", "pibt"], window=25, settle=5, early=5, hold=400, start=100)
    seen = _run(r, {"epibt": 100.0, "pibt": 50.0}, 100 + 25 + 10)
    assert seen == ["epibt"] * 125 + ["pibt"] * 10             # PIBT's turn ends after 5 + 5 steps
    assert r.history == [{"step": 100, "scores": {"epibt": 100.0, "pibt": 50.0}, "chosen": "epibt"}]
    assert not r.racing and r.switches == 0 and r._start == 135 + 400
    close = MethodRace(["epibt", "pibt"], window=25, settle=5, early=5, start=0)
    assert _run(close, {"epibt": 100.0, "pibt": 90.0}, 50) == ["epibt"] * 25 + ["pibt"] * 25   # 10 % behind: a turn
    lead = MethodRace(["epibt", "pibt"], window=25, settle=5, early=5, start=0)
    assert _run(lead, {"epibt": 50.0, "pibt": 100.0}, 50)[25:] == ["pibt"] * 25     # the other leading: no early stop
    assert lead.history[0]["chosen"] == "pibt"


def test_a_turn_keeps_the_bound_of_the_method_chosen_before_the_race(tmp_path):
    """In a dense team each method has its own bound on the robots holding a task; a turn of the
    other method in a race does not take tasks back to its bound (they would be given again when
    the turn ends): the run ends inside PIBT's turn with EPIBT's bound."""
    from rce_fleet.lifelong import runner
    from rce_fleet.lifelong.generate import write_problem
    from rce_fleet.lifelong.lorr import load_lorr_map, load_problem
    small = Path(__file__).resolve().parents[1] / "vectors" / "lorr_startkit" / "small-16-16.map"
    n_free = len(load_lorr_map(small).free_cells())
    p = load_problem(write_problem(small, int(0.4 * n_free), 1, tmp_path))
    race_kw = {"start": 0, "window": 10, "settle": 2, "decisive": 10.0, "early": 0}
    assert runner.run_lifelong(p, 1, plan_time_limit_ms=300.0, record=False).summary()["race"] is None  # off so dense
    s = runner.run_lifelong(p, 15, plan_time_limit_ms=300.0, record=False, race=True, race_kw=race_kw).summary()
    assert s["epibt"] is True and s["race"]["last"] == "pibt" and not s["race"]["history"], s["race"]
    assert s["max_active"] == int(runner.EPIBT_ACTIVE_FRAC * n_free) != int(runner.ACTIVE_FRAC * n_free)
    assert s["invalid_steps"] == 0
