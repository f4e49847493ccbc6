"""``rce-fleet lifelong`` and ``bench/lifelong.py --quick``: a short run end to end, its
output replayed under the rules, and a malformed problem named with file and line."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from rce_fleet.cli import main
from rce_fleet.lifelong import load_problem, replay

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / ".." / "shared" / "data"
RANDOM = DATA / "lorr" / "random.domain" / "random_32_32_20_100.json"


def test_lifelong_cli_writes_an_output_that_replays_with_its_task_count(tmp_path, capsys):
    out = tmp_path / "out.json"
    with pytest.raises(SystemExit) as e:
        main(["lifelong", str(RANDOM), "--steps", "40", "--output", str(out), "--seed", "3", "--no-progress",
              "--plan-time-limit", "500"])      # the planner spends about half its limit: half the CPU
    assert e.value.code == 0
    text = capsys.readouterr().out
    assert "tasks finished in 40 steps by 100 robots" in text and "timeouts 0" in text
    d = json.loads(out.read_text())
    assert d["actionModel"] == "MAPF_T" and d["teamSize"] == 100 and d["makespan"] == 40
    assert d["numTaskFinished"] > 0 and len(d["plannerTimes"]) == 40
    p = load_problem(RANDOM)
    again = replay(p.grid, p.tasks, p.reveal, d)
    assert again.finished == d["numTaskFinished"] and again.invalid_steps == 0


def test_lifelong_cli_takes_lanes_crowd_and_cache_bounds_and_refuses_a_cache_too_small(tmp_path, capsys):
    out = tmp_path / "out.json"
    with pytest.raises(SystemExit) as e:
        main(["lifelong", str(RANDOM), "--steps", "20", "--output", str(out), "--lanes", "0", "--crowd-w", "5",
              "--cache-mb", "1", "--no-progress", "--plan-time-limit", "250"])   # 1 MiB: 512 of its 819 maps
    assert e.value.code in (0, 1)
    d = json.loads(out.read_text())
    p = load_problem(RANDOM)
    assert replay(p.grid, p.tasks, p.reveal, d).finished == d["numTaskFinished"]
    with pytest.raises(SystemExit) as e:
        main(["lifelong", str(RANDOM), "--steps", "5", "--cache-mb", "0.01", "--no-progress"])
    assert e.value.code == 2
    assert "--cache-mb 0.01 holds 5 distance maps; 100 robots need 116" in capsys.readouterr().err


def test_lifelong_cli_names_a_malformed_problem_file_and_line(tmp_path, capsys):
    bad = tmp_path / "p.json"
    bad.write_text('{\n  "mapFile": "x.map",\n  "teamSize": 2,,\n}')
    with pytest.raises(SystemExit) as e:
        main(["lifelong", str(bad), "--steps", "5"])
    assert e.value.code == 2
    assert f"{bad}:3: not JSON" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["lifelong", str(tmp_path / "none.json"), "--steps", "5"])
    assert e.value.code == 2 and "none.json: no such file" in capsys.readouterr().err


def test_bench_lifelong_quick(tmp_path):
    js, png = tmp_path / "l.json", tmp_path / "l.png"
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "lifelong.py"), "--quick", "--json", str(js),
                        "--plot", str(png), "--plan-time-limit", "500"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    runs = json.loads(js.read_text())["runs"]
    assert {x["problem"] for x in runs} == {"random_32_32_20_100", "paris_1_256_250"}
    for x in runs:
        assert x["invalid_steps"] == 0 and x["timeouts"] == 0 and x["tasks_finished"] > 0
        assert len(x["curve"]) == x["steps"] and x["default"] > 0 and x["best"] > 0
    assert png.stat().st_size > 10_000
    assert "x default" in r.stdout


def test_bench_lifelong_generates_problems_on_a_map_and_runs_them(tmp_path):
    js, png = tmp_path / "g.json", tmp_path / "g.png"
    small = ROOT / "tests" / "vectors" / "lorr_startkit" / "small-16-16.map"
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "lifelong.py"), "--generate", str(small),
                        "--robots", "10,30", "--seed", "4", "--steps", "15", "--problem-dir", str(tmp_path / "p"),
                        "--length-w", "0.5", "--yield-steps", "7", "--json", str(js), "--plot", str(png)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    runs = json.loads(js.read_text())["runs"]
    assert [(x["problem"], x["robots"], x["steps"]) for x in runs] == [("small_16_16_10_s4", 10, 15),
                                                                        ("small_16_16_30_s4", 30, 15)]
    assert all(x["invalid_steps"] == 0 and x["timeouts"] == 0 and x["length_w"] == 0.5 and x["yield_steps"] == 7
               for x in runs)
    written = sorted(f.name for f in (tmp_path / "p").glob("*.json"))
    assert written == ["small_16_16_10_s4.json", "small_16_16_30_s4.json"]
    bad = subprocess.run([sys.executable, str(ROOT / "bench" / "lifelong.py"), "--generate", str(small)],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--generate needs --robots" in bad.stderr
    peer = subprocess.run([sys.executable, str(ROOT / "bench" / "lifelong.py"), "--quick", "--peer", str(small)],
                          capture_output=True, text=True, timeout=60)
    assert peer.returncode == 2 and "not an executable" in peer.stderr
    weight = subprocess.run([sys.executable, str(ROOT / "bench" / "lifelong.py"), "--quick", "--length-w", "-1"],
                            capture_output=True, text=True, timeout=60)
    assert weight.returncode == 2 and "--length-w -1.0: a task's length weighs a finite share >= 0" in weight.stderr
    stuck = subprocess.run([sys.executable, str(ROOT / "bench" / "lifelong.py"), "--quick", "--yield-steps", "-2"],
                           capture_output=True, text=True, timeout=60)
    assert stuck.returncode == 2 and "--yield-steps -2: steps without progress, >= 0" in stuck.stderr
    both = subprocess.run([sys.executable, str(ROOT / "bench" / "lifelong.py"), "--quick", "--pursue", "5",
                           "--max-active", "9"], capture_output=True, text=True, timeout=60)
    assert both.returncode == 2 and "--pursue 5: robots pursuing their task, >= 0" in both.stderr


def test_lifelong_cli_refuses_a_pursuit_bound_below_zero_or_beside_another_bound(capsys):
    for bad in (["--pursue", "-1"], ["--pursue", "3", "--admission", "on"]):
        with pytest.raises(SystemExit) as e:
            main(["lifelong", str(RANDOM), "--steps", "5", "--no-progress", *bad])
        assert e.value.code == 2
        assert f"got --pursue {bad[1]}" in capsys.readouterr().err


def test_lifelong_cli_refuses_an_unwritable_output_before_it_runs(tmp_path, capsys):
    out = tmp_path / "no-such-dir" / "run.json"
    with pytest.raises(SystemExit) as e:
        main(["lifelong", str(RANDOM), "--steps", "5", "--output", str(out), "--no-progress"])
    assert e.value.code == 2
    cap = capsys.readouterr()
    assert f"--output {out}: cannot write: No such file or directory" in cap.err
    assert "tasks finished" not in cap.out


def test_lifelong_cli_says_when_the_team_jams_and_what_to_turn_on(tmp_path, capsys):
    """Two open rooms joined by one door, random tasks over both: the team packs the door."""
    from rce_fleet.lifelong.generate import write_problem
    rows = ["".join("@" if c == 40 and r != 10 else "." for c in range(81)) for r in range(20)]
    door = tmp_path / "door.map"
    door.write_text("type octile\nheight 20\nwidth 81\nmap\n" + "\n".join(rows) + "\n")
    problem = write_problem(door, 190, 1, tmp_path)
    with pytest.raises(SystemExit) as e:
        main(["lifelong", str(problem), "--steps", "150", "--plan-time-limit", "250", "--no-progress",
              "--admission", "off"])        # a jam is seen in its second 25-step window over the mark
    assert e.value.code == 0
    err = capsys.readouterr().err
    assert "the team jammed from step" in err and "--admission on" in err
    with pytest.raises(SystemExit) as e:        # by default the bound is on at 0.12 robots per free cell
        main(["lifelong", str(problem), "--steps", "100", "--plan-time-limit", "250", "--no-progress"])
    assert e.value.code == 0 and "jammed" not in capsys.readouterr().err


@pytest.mark.parametrize("replan", ["on", "off"])
def test_lifelong_cli_runs_whole_plans_or_the_step_planner_on_a_map_of_a_few_cells(tmp_path, capsys, replan):
    from rce_fleet.lifelong.generate import write_problem
    from rce_fleet.lifelong.lorr import load_problem
    from rce_fleet.lifelong.simulator import replay
    tunnel = tmp_path / "tunnel.map"
    tunnel.write_text("type octile\nheight 6\nwidth 4\nmap\n.@@@\n....\n.@@@\n.@@@\n.@@@\n.@@@\n")
    problem = write_problem(tunnel, 3, 1, tmp_path)
    out = tmp_path / "run.json"
    with pytest.raises(SystemExit) as e:
        main(["lifelong", str(problem), "--steps", "60", "--plan-time-limit", "300", "--no-progress",
              "--replan", replan, "--output", str(out)])
    assert e.value.code == 0
    assert "tasks finished in 60 steps by 3 robots" in capsys.readouterr().out
    p = load_problem(problem)
    doc = json.loads(out.read_text())
    assert replay(p.grid, p.tasks, p.reveal, doc).finished == doc["numTaskFinished"]
