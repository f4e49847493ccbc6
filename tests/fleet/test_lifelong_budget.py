"""rce_fleet.lifelong.budget: the step's marks move up after quiet windows, never past the least
margin, and fall back to the start on a late step."""
from __future__ import annotations

from pathlib import Path

import pytest

from rce_fleet.lifelong.budget import StepBudget


def test_quiet_windows_move_the_marks_up_to_the_top_and_a_late_step_puts_them_back():
    b = StepBudget(1.0, window=10)
    assert (b.deadline, b.hard) == (0.5, 0.7)
    for _ in range(9):
        b.observe(0.69)
    assert b.hard == 0.7                              # not a whole window yet
    b.observe(0.69)
    assert b.hard == pytest.approx(0.75) and b.deadline == pytest.approx(0.55)
    for _ in range(100):
        b.observe(b.hard - 0.01)
    assert b.hard == pytest.approx(0.9)               # the top, and no further
    b.observe(0.9 + 0.034)                            # a third of the 0.1 left: back to the start
    assert (b.hard, b.falls) == (0.7, 1) and [h for _, h in b.history][-1] == 0.7


def test_a_window_with_lateness_moves_up_only_while_the_margin_stays_factor_times_it():
    b = StepBudget(1.0, window=10, factor=3.0)
    for _ in range(10):
        b.observe(0.75)                               # 0.05 late each: 0.15 <= 0.25 left at 0.75
    assert b.hard == pytest.approx(0.75)
    for _ in range(10):
        b.observe(0.8)                                # 0.05 late: 0.15 <= 0.2 left at 0.8
    assert b.hard == pytest.approx(0.8)
    for _ in range(10):
        b.observe(0.85)                               # 0.05 late: 0.15 > 0.15? equal: moves to 0.85
    assert b.hard == pytest.approx(0.85)
    for _ in range(10):
        b.observe(0.89)                               # 0.04 late: 0.12 > 0.1 left at 0.9: stays
    assert b.hard == pytest.approx(0.85) and b.falls == 0


def test_a_short_limit_keeps_the_margin_of_the_start():
    b = StepBudget(0.3, window=5)                     # 100 ms of 300 is more than the 0.3 margin allows
    for _ in range(50):
        b.observe(0.5)
    assert b.hard == 0.7 and b.history == [(0, 0.7)]
    with pytest.raises(ValueError, match="0 < deadline <= hard <= top < 1"):
        StepBudget(1.0, deadline=0.8, hard=0.7)
    with pytest.raises(ValueError, match="window >= 1"):
        StepBudget(1.0, window=0)


def test_a_run_with_the_measured_budget_moves_its_marks_up_on_steps_that_return_early(tmp_path):
    """By default the marks are measured: a small problem's steps return in milliseconds of their second,
    so after 100 of them the marks move up one notch; the run reports its marks, keeps its rules and times
    nothing out. A fixed ``budget_frac`` keeps them."""
    from rce_fleet.lifelong.generate import write_problem
    from rce_fleet.lifelong.lorr import load_problem
    from rce_fleet.lifelong.runner import run_lifelong
    small = Path(__file__).resolve().parents[1] / "vectors" / "lorr_startkit" / "small-16-16.map"
    p = load_problem(write_problem(small, 4, 1, tmp_path))
    s = run_lifelong(p, 120, plan_time_limit_ms=1000.0, record=False,
                     planner_kw={"samples": 1, "epibt": False}).summary()   # the plain PIBT step, milliseconds
    assert s["timeouts"] == 0 and s["invalid_steps"] == 0 and s["tasks_finished"] > 0
    assert s["budget"]["history"] == [(0, 0.7), (100, pytest.approx(0.75))] and s["budget"]["falls"] == 0, s["budget"]
    fixed = run_lifelong(p, 3, plan_time_limit_ms=1000.0, budget_frac=0.5, record=False).summary()
    assert fixed["budget"] == {"deadline": 0.5, "hard": 0.7}
