"""bench/lifelong_waits.py: a run's waits per cell and window, replayed from its output JSON under
the 2024 rules' actions, and the map picture; an output of another map is refused."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parents[2] / "bench"
sys.path.insert(0, str(BENCH))
from lifelong_waits import main, read_map, wait_maps  # noqa: E402

MAP = "type octile\nheight 3\nwidth 4\nmap\n....\n.@..\n....\n"


def test_waits_are_counted_where_each_robot_stands_in_each_window(tmp_path):
    (tmp_path / "m.map").write_text(MAP)
    free = read_map(tmp_path / "m.map")
    # robot 0 at (0,0) facing east: F to (0,1), W, W, R (faces south), F to (1,1)? blocked: it waits instead
    # robot 1 at (2,3) facing east: W, C (north), F to (1,3), F to (0,3), W
    out = {"start": [[0, 0, "E"], [2, 3, "E"]], "actualPaths": ["F,W,W,R,W", "W,C,F,F,W"]}
    maps = wait_maps(free, out, [(0, 2), (2, 5)])
    first, second = np.zeros((3, 4), int), np.zeros((3, 4), int)
    first[0, 1] = 1          # robot 0's W at step 1, at (0,1)
    first[2, 3] = 1          # robot 1's W at step 0, at (2,3)
    second[0, 1] = 2         # robot 0's W at steps 2 and 4
    second[0, 3] = 1         # robot 1's W at step 4, at (0,3)
    assert (maps[0] == first).all() and (maps[1] == second).all()


def test_the_picture_and_json_are_written_and_bad_input_named(tmp_path, capsys):
    (tmp_path / "m.map").write_text(MAP)
    out = tmp_path / "o.json"
    out.write_text(json.dumps({"start": [[0, 0, "S"]], "actualPaths": ["F,F,W,W"]}))
    png = tmp_path / "w.png"
    assert main([str(tmp_path / "m.map"), str(out), "--windows", "0:2", "2:4", "--out", str(png)]) == 0
    d = json.loads(png.with_suffix(".json").read_text())
    assert [w["waits"] for w in d["windows"]] == [0, 2] and d["windows"][1]["top_cells"][0] == [2, 0, 2]
    assert png.stat().st_size > 5_000
    assert main([str(tmp_path / "m.map"), str(out), "--windows", "0:9", "--out", str(png)]) == 2
    assert "window 0:9 outside the run's 4 steps" in capsys.readouterr().err
    out.write_text(json.dumps({"start": [[0, 0, "E"]], "actualPaths": ["F,R,F,W"]}))      # (0,1) south: the pillar
    assert main([str(tmp_path / "m.map"), str(out), "--windows", "0:4", "--out", str(png)]) == 2
    assert "step 2: a robot moved off the map's free cells" in capsys.readouterr().err
