"""``rce-fleet lifelong`` on League of Robot Runners problems the project has never seen, written
here the way other people write them (start-kit ``Input_Output_Format.md``): other map sizes and
symbols, CRLF, the 2023 form, a ``rows,cols`` header, files reached from another directory, a map
in separate parts. Each either runs under the rules or is refused with the file and line."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rce_fleet.cli import main
from rce_fleet.lifelong import MAPF, MAPF_T, ProblemError, load_problem, replay
from rce_fleet.lifelong.grid import MAX_STEPS
from rce_fleet.lifelong.kernels import UNREACHABLE
from rce_fleet.lifelong.runner import run_lifelong

# 9 x 23, not square: every symbol the start-kit's maps use (@ and T block; . E S W are free)
MAP = [
    ".......................",
    ".@@T.E.S.W.@@@.T..E..S.",
    ".@..........W.....@....",
    ".T..@@@..TT....@@@.....",
    "..E..S...W...E.....S...",
    ".@@@...T.....@@@..T....",
    "......W.....E......W...",
    ".T..@@.....S.....@@..T.",
    ".......................",
]
COLS = len(MAP[0])


def cell(r: int, c: int) -> int:
    assert MAP[r][c] not in "@T"
    return r * COLS + c


def write_problem(d: Path, rows: list[str] = MAP, agents: list = (), tasks: list = (), nl: str = "\n",
                  header: str = "octile", **spec) -> Path:
    """A problem in ``d``: maps/, agents/ and tasks/ beside the JSON, as the start-kit ships them."""
    for sub in ("maps", "agents", "tasks"):
        (d / sub).mkdir(parents=True, exist_ok=True)
    head = ([f"{len(rows)},{len(rows[0])}"] if header == "rows,cols"
            else ["type octile", f"height {len(rows)}", f"width {len(rows[0])}", "map"])
    (d / "maps" / "m.map").write_bytes(nl.join(head + list(rows)).encode() + (nl * 3).encode())
    (d / "agents" / "a.agents").write_bytes(nl.join(["# agents", str(len(agents)), *map(str, agents)]).encode()
                                            + (nl * 2).encode())
    (d / "tasks" / "t.tasks").write_bytes(nl.join(["# tasks", str(len(tasks)),
                                                   *(",".join(map(str, t)) for t in tasks)]).encode() + nl.encode())
    body = {"mapFile": "maps/m.map", "agentFile": "agents/a.agents", "taskFile": "tasks/t.tasks",
            "teamSize": len(agents), "numTasksReveal": 1.5, "version": "2024 LoRR", **spec}
    p = d / "problem.json"
    p.write_text(json.dumps(body, indent=4))
    return p


AGENTS = [cell(0, 0), cell(8, 22), cell(4, 5), cell(6, 6), cell(2, 12), cell(0, 10)]
TASKS = [(cell(0, 22), cell(8, 0)), (cell(4, 2), cell(6, 12), cell(1, 5)), (cell(7, 11),), (cell(2, 2), cell(8, 10))]


def test_an_unseen_problem_runs_from_another_directory_and_replays(tmp_path):
    """CRLF lines, blank lines at the ends, teamSize 4 of 6 agents, 4 tasks for int(1.5 x 4) = 6
    open ones (revealed cyclically), multi-errand tasks, paths relative to the JSON, the CLI
    started in another directory with a relative problem path."""
    prob = write_problem(tmp_path / "lorr" / "mine.domain", agents=AGENTS, tasks=TASKS, nl="\r\n", teamSize=4)
    out = tmp_path / "run.json"
    r = subprocess.run([sys.executable, "-m", "rce_fleet.cli", "lifelong", "mine.domain/problem.json", "--steps", "60",
                        "--output", str(out), "--no-progress"], cwd=tmp_path / "lorr", capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr and "warning" not in r.stderr
    d = json.loads(out.read_text())
    assert d["teamSize"] == 4 and d["makespan"] == 60 and d["numTaskFinished"] > 0
    assert d["numPlannerErrors"] == 0 and d["numEntryTimeouts"] == 0
    assert [s[:2] for s in d["start"]] == [list(divmod(c, COLS)) for c in AGENTS[:4]]
    p = load_problem(prob)
    assert p.reveal == 6 and len(p.tasks) == 4
    again = replay(p.grid, p.tasks, p.reveal, d)
    assert again.finished == d["numTaskFinished"] and again.invalid_steps == 0


def test_both_action_models_run_an_unseen_map_with_one_robot_and_with_several(tmp_path):
    many = load_problem(write_problem(tmp_path / "many", agents=AGENTS, tasks=TASKS))
    one = load_problem(write_problem(tmp_path / "one", agents=[cell(4, 11)], tasks=TASKS))
    for p in (many, one):
        for model in (MAPF, MAPF_T):
            res = run_lifelong(p, 80, model=model, record=False)
            s = res.summary()
            assert s["tasks_finished"] > 0 and s["invalid_steps"] == 0 and s["timeouts"] == 0, (p.team_size, model)


def test_the_2023_form_and_a_rows_cols_header_run(tmp_path):
    """2023: single-errand task lines, an integer numTasksReveal, taskAssignmentStrategy, no
    version; the map's first line ``rows,cols``; a count line with the start-kit's trailing comma;
    a JSON that starts with a UTF-8 byte-order mark (the start-kit's JSON parser skips it too)."""
    prob = write_problem(tmp_path, agents=AGENTS[:3], tasks=[(c,) for c in AGENTS[3:]] + [(cell(4, 20),)],
                         header="rows,cols", numTasksReveal=1, taskAssignmentStrategy="roundrobin")
    spec = json.loads(prob.read_text())
    del spec["version"]
    prob.write_bytes(b"\xef\xbb\xbf" + json.dumps(spec).encode())      # a byte-order mark, as Notepad writes
    agents = tmp_path / "agents" / "a.agents"
    agents.write_text(agents.read_text().replace("\n3\n", "\n3,\n"))
    out = tmp_path / "run.json"
    with pytest.raises(SystemExit) as e:
        main(["lifelong", str(prob), "--steps", "40", "--output", str(out), "--no-progress"])
    assert e.value.code == 0
    d = json.loads(out.read_text())
    assert d["teamSize"] == 3 and d["numTaskFinished"] > 0 and d["numPlannerErrors"] == 0


def test_a_movingai_map_of_0_1_values_is_read_and_generated_on_for_the_start_kit_too(tmp_path):
    """The converted MovingAI form of the shared data (rows, columns, then 0/1 values, 1 blocked):
    read as the one-shot planner reads it, a problem generated on it names an octile copy the
    start-kit can read (same cells), and it runs under the rules; a bad row is named with its line."""
    from rce_fleet.lifelong import load_lorr_map
    from rce_fleet.lifelong.generate import write_problem as generate
    from rce_fleet.planning import load_movingai_map
    src = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "mapf" / "warehouse-10-20-10-2-1.map"
    grid = load_lorr_map(src)
    assert grid.free.shape == (63, 161) and (grid.free == load_movingai_map(src).free).all()
    prob = generate(src, 40, 3, tmp_path / "gen", tasks=500)
    spec = json.loads(prob.read_text())
    copy = (prob.parent / spec["mapFile"]).resolve()
    assert copy.parent == (tmp_path / "gen" / "maps").resolve()
    text = copy.read_text().split("\n")
    assert text[:4] == ["type octile", "height 63", "width 161", "map"] and set("".join(text[4:])) == {".", "@"}
    problem = load_problem(prob)
    assert (problem.grid.free == grid.free).all()
    res = run_lifelong(problem, 20)
    assert res.sim.t == 20 and res.sim.invalid_steps == 0
    bad = tmp_path / "bad.map"
    bad.write_text("2\n3\n0 1 0\n0 2 0\n")
    with pytest.raises(ProblemError, match=r"bad\.map:4: map row 1: expected 3 values 0 \(free\) or 1 \(blocked\)"):
        load_lorr_map(bad)


def test_a_map_in_separate_parts_runs_to_the_end_and_names_the_task_no_robot_can_finish(tmp_path, capsys):
    """As in the start-kit, a task no robot can reach stays open (it does not hang or stop the
    run); the CLI says which, with the task file's line."""
    rows = ["....@....", "....@....", "....@....", "....@...."]
    prob = write_problem(tmp_path, rows, agents=[0, 9], tasks=[(2,), (8,), (3, 35), (20,)], numTasksReveal=1.0)
    with pytest.raises(SystemExit) as e:
        main(["lifelong", str(prob), "--steps", "30", "--no-progress"])
    cap = capsys.readouterr()
    assert e.value.code == 0 and "tasks finished in 30 steps by 2 robots" in cap.out
    tasks = tmp_path / "tasks" / "t.tasks"
    assert f"{tasks}:4: warning: no robot can finish task [8]: the map has 2 separate parts" in cap.err
    assert "(2 of 4 tasks like it)" in cap.err


def _bad(tmp_path: Path, change) -> Path:
    """A good problem with one thing changed by ``change(problem_dir)``."""
    prob = write_problem(tmp_path, agents=AGENTS, tasks=TASKS)
    change(tmp_path)
    return prob


def _json(**kw):
    def change(d: Path) -> None:
        p = d / "problem.json"
        p.write_text(json.dumps({**json.loads(p.read_text()), **kw}, indent=4))
    return change


def _agents(second: str):
    """The agents file with the second agent's line (line 4) replaced by ``second``."""
    lines = ["# agents", str(len(AGENTS)), str(AGENTS[0]), second, *map(str, AGENTS[2:])]
    return lambda d: (d / "agents" / "a.agents").write_text("\n".join(lines) + "\n")


BAD = {
    "robot on an obstacle": (_agents(str(1 * COLS + 1)),
                             "agents/a.agents:4: location 24 (row 1, col 1) is not a free cell of the map"),
    "two robots on one start": (_agents(str(AGENTS[0])),
                                "agents/a.agents:4: location 0 is also the start of the agent of line 3"),
    "a row,col pair for an agent": (_agents("3,4"), "agents/a.agents:4: expected one value, got '3,4'"),
    "mapFile not a string": (_json(mapFile=5), "problem.json:2: mapFile must be a file name, got 5"),
    "teamSize not an integer": (_json(teamSize=1.5), "problem.json:5: teamSize must be an integer, got 1.5"),
    "no task revealed": (_json(numTasksReveal=0.1), "problem.json:6: numTasksReveal 0.1 x teamSize 6 reveals no task"),
    "10^308 tasks revealed": (_json(numTasksReveal=1e308), "problem.json:6: numTasksReveal must be at most 1000"),
    "a header with more rows than the file": (
        lambda d: (d / "maps" / "m.map").write_text("type octile\nheight 100000000\nwidth 100000000\nmap\n...\n"),
        "maps/m.map:6: the header says 100000000 rows but 2 follow"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_a_malformed_unseen_problem_is_named_with_file_and_line(tmp_path, capsys, case):
    change, message = BAD[case]
    prob = _bad(tmp_path, change)
    with pytest.raises(SystemExit) as e:
        main(["lifelong", str(prob), "--steps", "5", "--no-progress"])
    cap = capsys.readouterr()
    assert e.value.code == 2 and cap.out == ""
    assert cap.err.startswith("rce-fleet lifelong: ") and f"{tmp_path}/{message}" in cap.err, cap.err


def test_a_negative_seed_and_a_run_too_long_to_record_are_usage_errors(tmp_path, capsys):
    prob = write_problem(tmp_path, agents=AGENTS, tasks=TASKS)
    with pytest.raises(SystemExit) as e:
        main(["lifelong", str(prob), "--steps", "5", "--seed", "-5"])
    assert e.value.code == 2 and "--seed: expected an integer >= 0, got '-5'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:         # its per-step records would need 7 TiB
        main(["lifelong", str(prob), "--steps", str(10 ** 12), "--no-progress"])
    assert e.value.code == 2
    assert "rce-fleet lifelong: --steps must be 1 - 10,000,000, got 1,000,000,000,000" in capsys.readouterr().err


def test_a_maze_longer_than_the_distance_tables_is_refused(tmp_path, capsys):
    """A 1-cell corridor snaking over 401 x 400 cells: its end is 80,599 steps from its start,
    more than the planner's uint16 distance maps hold; refused, not planned with wrapped distances."""
    w = 400
    rows = ["." * w if r % 2 == 0 else ("@" * (w - 1) + "." if r % 4 == 1 else "." + "@" * (w - 1))
            for r in range(401)]
    prob = write_problem(tmp_path, rows, agents=[0], tasks=[(400 * w,)])
    with pytest.raises(SystemExit) as e:
        main(["lifelong", str(prob), "--steps", "5", "--no-progress"])
    assert e.value.code == 2
    assert (f"{tmp_path}/maps/m.map: a shortest path on this map is 80599 steps long; the planner's distance tables "
            "hold at most 65534") in capsys.readouterr().err
    assert MAX_STEPS == UNREACHABLE - 1 == 65534
    np.testing.assert_equal(load_problem(write_problem(tmp_path / "open", ["." * w] * 200, agents=[0],
                                                       tasks=[(5,)])).grid.longest_path_bound(), 598)
