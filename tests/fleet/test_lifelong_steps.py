"""bench/lifelong_steps.py: each finished task's steps against the least MAPF_T steps through its
errands, split into waits, turns and moves beyond; finishes from the events or the start-kit's log;
an output of another problem is refused, naming what differs."""
from __future__ import annotations

import json
import sys
from collections import deque
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"
sys.path.insert(0, str(BENCH))
from lifelong_steps import main, steps_of  # noqa: E402

from rce_fleet.lifelong.distances import heading_graph  # noqa: E402
from rce_fleet.lifelong.grid import LifelongGrid  # noqa: E402
from rce_fleet.lifelong.kernels import UNREACHABLE, bfs_fill  # noqa: E402
from rce_fleet.lifelong.lorr import load_problem  # noqa: E402

# 3 x 5, a pillar at (1, 1): row-major cells, 0 - 4 on the top row
MAP = "type octile\nheight 3\nwidth 5\nmap\n.....\n.@...\n.....\n"


def _problem(tmp_path: Path, tasks: list[list[int]], agents: list[int]) -> Path:
    (tmp_path / "m.map").write_text(MAP)
    (tmp_path / "a.agents").write_text(f"{len(agents)}\n" + "".join(f"{a}\n" for a in agents))
    (tmp_path / "t.tasks").write_text(f"{len(tasks)}\n" + "".join(",".join(map(str, t)) + "\n" for t in tasks))
    p = tmp_path / "p.json"
    p.write_text(json.dumps({"mapFile": "m.map", "agentFile": "a.agents", "taskFile": "t.tasks",
                             "teamSize": len(agents), "numTasksReveal": 1}))
    return p


def _brute(free: np.ndarray, goal: tuple[int, int], arrive: int) -> np.ndarray:
    """Least MAPF_T steps from every (row, col, heading) to goal facing ``arrive``, by BFS forwards
    from each state (the slow, obvious way)."""
    rows, cols = free.shape
    step = [(0, 1), (1, 0), (0, -1), (-1, 0)]
    out = np.full((rows, cols, 4), UNREACHABLE, dtype=np.int64)
    for r in range(rows):
        for c in range(cols):
            for h in range(4):
                if not free[r, c]:
                    continue
                seen = {(r, c, h): 0}
                q = deque([(r, c, h)])
                while q:
                    s = q.popleft()
                    if (s[0], s[1]) == goal and s[2] == arrive:
                        out[r, c, h] = seen[s]
                        break
                    dr, dc = step[s[2]]
                    nxt = [(s[0], s[1], (s[2] + 1) % 4), (s[0], s[1], (s[2] + 3) % 4)]
                    if 0 <= s[0] + dr < rows and 0 <= s[1] + dc < cols and free[s[0] + dr, s[1] + dc]:
                        nxt.append((s[0] + dr, s[1] + dc, s[2]))
                    for x in nxt:
                        if x not in seen:
                            seen[x] = seen[s] + 1
                            q.append(x)
    return out


@pytest.mark.parametrize("arrive", [0, 3])
def test_the_least_steps_count_turns_and_moves_as_the_rules_do(arrive):
    rng = np.random.default_rng(4)
    free = rng.random((6, 7)) > 0.25
    free[2, 3] = True
    g = LifelongGrid(free)
    row = np.empty(4 * g.n_cells, dtype=np.uint16)
    bfs_fill(heading_graph(g), (2 * 7 + 3) * 4 + arrive, row, np.empty(4 * g.n_cells, np.int32))
    want = _brute(free, (2, 3), arrive)
    assert (row.reshape(6, 7, 4)[free] == want[free]).all()
    assert row[(2 * 7 + 3) * 4 + 2] == {0: 2, 3: 1}[arrive]         # at the goal facing west, to face ``arrive``


def test_a_cycle_splits_into_the_least_steps_and_the_waits_turns_and_moves_beyond(tmp_path):
    # robot 0 at (0,0) facing east, task 0: errands (0,4) then (2,4). Least: 4 F, R, 2 F = 7 steps.
    # It takes F,W,F,F,F,R,C,R,F,F: one wait and two turns beyond (R,C), 10 steps.
    # Robot 1 at (2,0) facing east, task 1: errand (2,2) by F,F (the least, 2 steps), then waits.
    prob = _problem(tmp_path, [[4, 14], [12]], [0, 10])
    out = {"start": [[0, 0, "E"], [2, 0, "E"]],
           "actualPaths": ["F,W,F,F,F,R,C,R,F,F", "F,F,W,W,W,W,W,W,W,W"],
           "events": [[2, 1, 1, 1], [5, 0, 0, 1], [10, 0, 0, 2]]}
    r = steps_of(load_problem(prob), out)
    assert (r["tasks"], r["cycle"], r["least"], r["cells"]) == (2, 12, 9, 8)
    assert (r["waits"], r["turns_beyond"], r["moves_beyond"]) == (1, 2, 0)
    assert r["tail"] == 0 + 8 and r["robot_steps"] == 20
    assert r["cycle"] - r["least"] == r["waits"] + r["turns_beyond"] + r["moves_beyond"]


def test_finishes_come_from_the_log_and_bad_input_is_named(tmp_path, capsys):
    prob = _problem(tmp_path, [[2], [12], [4]], [0, 10])
    # robot 0 goes along the top row, F,F to (0,2), then F,F to (0,4) (the least, 2 steps each); robot 1
    # takes a detour up and back: C,F,R,R,F,C,F,F (8 steps, least 2): 2 moves and 4 turns beyond
    out = tmp_path / "o.json"
    out.write_text(json.dumps({"start": [[0, 0, "E"], [2, 0, "E"]],
                               "actualPaths": ["F,F,F,F,W,W,W,W", "C,F,R,R,F,C,F,F"], "events": []}))
    log = tmp_path / "o.log"
    log.write_text("[t]: *info* [timestep=2] Agent 0 finishes task 0\n"
                   "[t]: *info* [timestep=4] Agent 0 finishes task 2\n"
                   "[t]: *info* [timestep=8] Agent 1 finishes task 1\n")
    js = tmp_path / "r.json"
    assert main([str(prob), str(out), "--log", f"{out}={log}", "--json", str(js)]) == 0
    r = json.loads(js.read_text())["runs"][str(out)]
    assert (r["tasks"], r["cycle"], r["least"]) == (3, 12, 6)
    assert (r["waits"], r["turns_beyond"], r["moves_beyond"]) == (0, 4, 2)
    assert "3 tasks; per task 4.0 steps against the least 2.0" in capsys.readouterr().out
    # from step 1: only robot 0's second cycle (begun at step 2) counts
    assert main([str(prob), str(out), "--log", f"{out}={log}", "--from", "1", "--json", str(js)]) == 0
    r = json.loads(js.read_text())["runs"][str(out)]
    assert (r["tasks"], r["cycle"], r["least"], r["turns_beyond"]) == (1, 2, 2, 0)
    assert "1 tasks begun from step 1; per task 2.0 steps" in capsys.readouterr().out
    assert main([str(prob), str(out)]) == 2
    assert "no finished task in the output's events (give the start-kit's --log)" in capsys.readouterr().err
    out.write_text(json.dumps({"start": [[0, 1, "S"], [2, 0, "E"]], "actualPaths": ["F,F", "W,W"],
                               "events": [[1, 1, 1, 1]]}))                          # (0,1) south: the pillar
    assert main([str(prob), str(out)]) == 2
    assert "step 0: a robot moved off the map's free cells" in capsys.readouterr().err
    out.write_text(json.dumps({"start": [[0, 0, "E"]], "actualPaths": ["F"], "events": [[1, 0, 0, 1]]}))
    assert main([str(prob), str(out)]) == 2
    assert "the output has 1 robots, the problem 2" in capsys.readouterr().err


def test_an_output_without_paths_is_read_from_the_finishes(tmp_path, capsys):
    # robot 1 finishes task 1 at (2,2) facing east (F,F), then task 2 at (2,0): with its paths the least
    # is 2 turns and 2 moves; without them the heading at a finish is not known, so the least faces west
    prob = _problem(tmp_path, [[4, 14], [12], [10]], [0, 10])
    out = {"start": [[0, 0, "E"], [2, 0, "E"]], "makespan": 10,
           "actualPaths": ["F,W,F,F,F,R,C,R,F,F", "F,F,R,R,F,F,W,W,W,W"],
           "events": [[2, 1, 1, 1], [5, 0, 0, 1], [6, 1, 2, 1], [10, 0, 0, 2]]}
    problem = load_problem(prob)
    with_paths = steps_of(problem, out)
    assert (with_paths["tasks"], with_paths["cycle"], with_paths["least"], with_paths["cells"]) == (3, 16, 13, 10)
    no_paths = steps_of(problem, {k: v for k, v in out.items() if k != "actualPaths"})
    assert no_paths == steps_of(problem, out, paths=False)
    assert (no_paths["tasks"], no_paths["cycle"], no_paths["least"], no_paths["cells"]) == (3, 16, 11, 10)
    assert no_paths["waits"] is None and no_paths["turns_beyond"] is None and no_paths["robot_steps"] == 20
    assert not no_paths["paths"] and with_paths["paths"]
    # only the cycles that end by step 5: robot 1's first
    assert (steps_of(problem, out, paths=False, end=5)["tasks"], steps_of(problem, out, end=5)["cycle"]) == (1, 2)
    path = tmp_path / "o.json"
    path.write_text(json.dumps(out))
    assert main([str(prob), str(path), "--no-paths", "--from", "1", "--to", "6"]) == 0
    assert ("1 tasks begun from step 1 and finished by step 6; per task 4.0 steps against the least 2.0 "
            "(stretch 2.000), 2.0 cells; read without paths") in capsys.readouterr().out
    out["start"][0] = [1, 1, "E"]                                                       # the pillar
    path.write_text(json.dumps({k: v for k, v in out.items() if k != "actualPaths"}))
    assert main([str(prob), str(path)]) == 2
    assert "robot 0 starts off the map's free cells, at (1, 1)" in capsys.readouterr().err
