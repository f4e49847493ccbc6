"""MovingAI maps and scenarios the project has never seen (format: movingai.com/benchmarks/
formats.html), written here as others write them: every terrain symbol, CRLF, ``version 1.0``
with buckets and spaces, and scenarios that do not fit their map. Each loads as the format says
or is refused naming the file and line; ``bench/planner.py --map --scen`` plans one for real and
refuses an instance that is not one, naming the agent."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from rce_fleet.planning import load_movingai_map, load_movingai_scen

ROOT = Path(__file__).resolve().parents[2]

# a room map: four rooms with doors, and each terrain symbol (free: . G S; blocked: @ O T W)
ROOM = [
    "@@@@@@@@@@@@@",
    "@..G..@..S..@",
    "@.T...@...W.@",
    "@.....O.....@",
    "@@@.@@@@@.@@@",
    "@.....@.....@",
    "@..S.......@.",
    "@.....@..G..@",
    "@@@@@@@@@@@@@",
]


def write_map(path: Path, rows: list[str], nl: str = "\n") -> Path:
    path.write_bytes(nl.join(["type octile", f"height {len(rows)}", f"width {len(rows[0])}", "map", *rows,
                              ""]).encode())
    return path


def scen_line(bucket: int, sx: int, sy: int, gx: int, gy: int, sep: str = "\t") -> str:
    return sep.join(map(str, (bucket, "room.map", len(ROOM[0]), len(ROOM), sx, sy, gx, gy, 4.0)))


def test_every_terrain_symbol_is_read_as_the_format_says(tmp_path):
    g = load_movingai_map(write_map(tmp_path / "room.map", ROOM, nl="\r\n"))
    assert (g.rows, g.cols) == (9, 13)
    assert g.free[1, 3] and g.free[1, 9] and g.free[6, 3] and g.free[7, 9]         # G, S, S, G
    assert not g.free[2, 2] and not g.free[2, 10] and not g.free[3, 6]             # T, W, O
    assert g.free[6, 12]                                            # a pocket on the edge, walled off


@pytest.mark.parametrize("text, message", [
    ("type octile\nheight 2\nwidth 3\nmap\n.E.\n...\n", "m.map:5: unknown terrain 'E' at column 1"),
    ("type octile\nheight 3\nwidth 3\nmap\n...\n..\n...\n", "m.map:6: map row 1 has 2 cells, expected 3"),
    ("type octile\nheight 100000000\nwidth 100000000\nmap\n...\n", "m.map:6: the header says 100000000 rows but 2"),
    ("type octile\nwidth 3\nmap\n...\n", "m.map:3: the header has no 'height' line"),
    ("type octile\nheight 1\nwidth 3\nmap\n@T@\n", "m.map: the map has no free cell"),
    ("2\n3\n0 0 1\n0 2 0\n", "m.map:4: map row 1: expected 3 values 0 (free) or 1 (blocked)"),
])
def test_a_malformed_map_is_named_with_its_line(tmp_path, text, message):
    (tmp_path / "m.map").write_text(text)
    with pytest.raises(ValueError) as e:
        load_movingai_map(tmp_path / "m.map")
    assert str(e.value).startswith(f"{tmp_path}/{message}"), str(e.value)


def test_scenarios_with_version_lines_buckets_and_spaces_load(tmp_path):
    g = load_movingai_map(write_map(tmp_path / "room.map", ROOM))
    text = "\r\n".join(["version 1.0", scen_line(0, 1, 1, 3, 1), scen_line(0, 9, 1, 3, 6, " "),
                        scen_line(3, 12, 6, 1, 7), "", ""])
    (tmp_path / "room.scen").write_bytes(b"\xef\xbb\xbf" + text.encode())          # with a byte-order mark
    assert load_movingai_scen(tmp_path / "room.scen", g) == [(14, 16), (22, 81), (90, 92)]


@pytest.mark.parametrize("line, message", [
    (scen_line(0, 13, 1, 1, 1), "start (x 13, y 1) is outside the 13 x 9 map"),
    (scen_line(0, 1, 1, 1, -1), "goal (x 1, y -1) is outside the 13 x 9 map"),
    (scen_line(0, 2, 2, 1, 1), "start (x 2, y 2) is a blocked cell of the map"),
    ("0\troom.map\t26\t18\t1\t1\t3\t1\t2", "this problem is for a 26 x 18 map (room.map), the map is 13 x 9"),
    ("0\troom.map\t13\t9\t1", "expected 9 fields"),
])
def test_a_scenario_that_does_not_fit_its_map_is_named_with_its_line(tmp_path, line, message):
    g = load_movingai_map(write_map(tmp_path / "room.map", ROOM))
    (tmp_path / "s.scen").write_text(f"version 1\n{scen_line(0, 1, 1, 3, 1)}\n{line}\n")
    with pytest.raises(ValueError) as e:
        load_movingai_scen(tmp_path / "s.scen", g)
    assert str(e.value).startswith(f"{tmp_path}/s.scen:3: {message}"), str(e.value)


def _bench(tmp_path: Path, scen: list[str], *argv: str) -> subprocess.CompletedProcess:
    write_map(tmp_path / "room.map", ROOM)
    (tmp_path / "room.scen").write_text("\n".join(["version 1", *scen]) + "\n")
    return subprocess.run([sys.executable, str(ROOT / "bench" / "planner.py"), "--map", str(tmp_path / "room.map"),
                           "--scen", str(tmp_path / "room.scen"), "--repeat", "1", "--scen-seeds", "--live-sizes",
                           "--time-limit", "1", "--json", str(tmp_path / "p.json"), "--plot", str(tmp_path / "p.png"),
                           *argv], capture_output=True, text=True, timeout=300)


PAIRS = [(1, 1, 11, 7), (9, 1, 1, 5), (3, 6, 9, 2), (10, 6, 2, 1), (5, 7, 8, 5), (10, 3, 4, 3)]


def test_bench_planner_plans_an_unseen_instance(tmp_path):
    r = _bench(tmp_path, [scen_line(k // 3, *p) for k, p in enumerate(PAIRS)], "--agents", "3", "6",
               "--lacam-agents", "6")
    assert r.returncode == 0, r.stderr
    assert "FleetPlanner on MovingAI room (room.scen)" in r.stdout
    d = json.loads((tmp_path / "p.json").read_text())
    for row in d["mapf"] + d["lacam"]:
        assert row["conflicts"] == 0 and row["reached"] == row["agents"]
    assert [row["agents"] for row in d["mapf"]] == [3, 6] and d["lacam"][0]["scenario"] == "room"


@pytest.mark.parametrize("scen, argv, message", [
    ([scen_line(0, 1, 1, 3, 1), scen_line(0, 12, 6, 11, 7)], ["--agents", "2", "--lacam-agents"],
     "agent 1: the goal (x 11, y 7) cannot be reached from the start (x 12, y 6)"),
    ([scen_line(0, 1, 1, 3, 1), scen_line(0, 1, 1, 4, 1)], ["--agents", "2", "--lacam-agents"],
     "agents 0 and 1 share the start (x 1, y 1)"),
    ([scen_line(0, 1, 1, 3, 1)], ["--agents", "1", "--lacam-agents", "5"],
     "the scenario has 1 agents, --agents/--lacam-agents ask for 5"),
])
def test_bench_planner_refuses_an_instance_that_is_not_one(tmp_path, scen, argv, message):
    """The pocket at (12, 6) is walled off: a goal from there is out of reach."""
    r = _bench(tmp_path, scen, *argv)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip() == f"bench/planner.py: {message}"


def test_bench_planner_refuses_a_maze_too_long_for_the_one_shot_solvers(tmp_path):
    """A 1-cell corridor snaking over 401 x 400 cells (80,599 steps end to end): FleetPlanner
    could plan it, LaCAM's uint16 distance maps cannot hold it."""
    rows = ["." * 400 if r % 2 == 0 else ("@" * 399 + "." if r % 4 == 1 else "." + "@" * 399) for r in range(401)]
    write_map(tmp_path / "maze.map", rows)
    (tmp_path / "maze.scen").write_text("version 1\n0\tmaze.map\t400\t401\t0\t0\t0\t400\t80599\n")
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "planner.py"), "--map", str(tmp_path / "maze.map"),
                        "--scen", str(tmp_path / "maze.scen"), "--agents", "1", "--lacam-agents", "1",
                        "--scen-seeds", "--live-sizes", "--json", str(tmp_path / "p.json")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and r.stderr.strip() == ("bench/planner.py: a shortest path on this map is 80599 steps "
                                                      "long; the planner's distance tables hold at most 65534")
