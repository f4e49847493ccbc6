"""What a fleet run shows and writes before and without its engine: the live table, the progress
line and the report of a run that was prepared but never started (a failed start's report)."""
from __future__ import annotations

import json

from rich.console import Console

from rce_fleet.live.demo import Options, Run
from rce_fleet.live.demo_output import EXIT_FAIL, progress_line, report, table, write_outputs


def _prepared(tmp_path, **kw) -> Run:
    run = Run(Options(robots=3, workdir=str(tmp_path / "work"), plot=None, goals={"Robot2": 7}, **kw))
    run.prepare()
    return run


def test_table_and_progress_line_name_every_robot_and_goal(tmp_path):
    run = _prepared(tmp_path)
    console = Console(width=160, record=True)
    console.print(table(run))
    text = console.export_text()
    for r in run.robots:
        assert r in text
    assert "rce fleet: 3 robots, grid 8x8" in text
    line = progress_line(run)
    assert line.startswith("t=   0.0s  reached 0/3  ")
    assert "Robot2:?->7 ?" in line


def test_report_of_a_run_that_never_started(tmp_path):
    run = _prepared(tmp_path, report=str(tmp_path / "out" / "report.json"))
    write_outputs(run, EXIT_FAIL, "engine did not start")
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    assert rep == report(run, EXIT_FAIL, "engine did not start") | {"mission_wall_s": None}
    assert rep["ok"] is False and rep["exit_code"] == EXIT_FAIL and rep["reason"] == "engine did not start"
    assert rep["per_robot"]["Robot2"]["goal"] == 7 and rep["per_robot"]["Robot2"]["reached"] is False
    assert rep["grid"]["rows"] == 8 and rep["bag"] is None and "tasks" not in rep
