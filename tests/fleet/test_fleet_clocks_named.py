"""Every time the fleet's task API, its command line and its page give says which clock it counts: fleet
time is the robots' clock, simulated seconds under ``rce-fleet serve``/``demo`` (``--speedup K``: K of them
a wall second), and a token's lifetime is wall time."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from rce_fleet.operations.api_models import openapi_document
from rce_fleet.operations.places import Place, Places
from rce_fleet.operations.tasks_api import TaskBook

from .test_nodes import lab  # noqa: F401  (the fixture)

BIN = Path(sys.executable).parent
SIMULATED = {"TaskRequest": ("earliest_start_s", "deadline_s"),
             "FleetTask": ("created", "earliest_start", "deadline", "assigned", "active", "finished", "reached"),
             "RobotWork": ("busy_s", "since_s", "stalled_s"), "TaskList": ("mean_s", "p95_s")}
WALL = {"LoginRequest": ("ttl_s",), "LoginAnswer": ("expires_in",)}
PAGE = Path(__file__).resolve().parents[2] / "examples" / "fleet" / "rce_fleet" / "live" / "web"


def test_the_api_schema_names_the_clock_of_every_time():
    schemas = openapi_document()["components"]["schemas"]
    for clock, fields in (("simulated", SIMULATED), ("wall", WALL)):
        for model, names in fields.items():
            for name in names:
                said = schemas[model]["properties"][name].get("description", "")
                assert clock in said, (model, name, said)
    assert "simulated" in schemas["FleetTask"]["description"] and "--speedup" in schemas["FleetTask"]["description"]


def test_a_refused_time_window_names_its_clock(lab):  # noqa: F811
    book = TaskBook(Places([Place("pick1", "pickup", 16)], lab))
    a = book.request_add({"errands": ["pick1"], "deadline_s": -5}, 0.0)
    assert not a["ok"] and "simulated s from now" in a["error"], a


def test_the_command_line_and_the_page_name_their_clocks():
    demo = subprocess.run([str(BIN / "rce-fleet"), "demo", "--help"], capture_output=True, text=True, timeout=60).stdout
    flat = " ".join(demo.split())
    for said in ("simulated seconds of the run by tasks", "give up after S wall seconds", "S simulated seconds after",
                 "--token-ttl S wall s a token"):
        assert said in flat, said
    page = (PAGE / "index.html").read_text()
    assert "age, sim s" in page
    assert "s sim`" in (PAGE / "tasks.js").read_text()


def test_the_task_command_names_the_clock_of_its_times():
    said = " ".join(subprocess.run([str(BIN / "rce-fleet"), "task", "add", "--help"], capture_output=True, text=True,
                                   timeout=60).stdout.split())
    assert "earliest start, fleet time: simulated s from now" in said and "deadline, fleet time: simulated s" in said


def test_metrics_carry_a_stalled_robot():
    """A robot that holds work and does not move shows on /metrics (its fleet/RobotTask's stall fields)."""
    from rce_fleet.operations.http_api import prometheus_text
    text = prometheus_text({"robots": [{"robot": "Robot1", "busy_s": 10.0, "since_s": 100.0, "stalled_s": 75.0,
                                        "stalls": 2}, {"robot": "Robot2", "busy_s": 0.0, "since_s": 100.0}]})
    assert 'rce_fleet_robot_stalled_seconds{robot="Robot1"} 75' in text
    assert 'rce_fleet_robot_stalls_total{robot="Robot1"} 2' in text
    assert 'rce_fleet_robot_stalled_seconds{robot="Robot2"} 0' in text
