"""The held-out maps of ``bench/lifelong.py --heldout`` (bench/heldout_maps.py): the same files on
every run, one connected part each, of four families, made by code that imports nothing of the
planner's; and the problems ``--heldout`` runs on them and on the tuned set, each named into its set."""
from __future__ import annotations

import ast
import sys
from pathlib import Path

import numpy as np

from rce_fleet.lifelong.lorr import load_lorr_map, load_problem

ROOT = Path(__file__).resolve().parents[2]
BENCH = ROOT / "bench"
DATA = (ROOT / ".." / "shared" / "data" / "lorr").resolve()
sys.path.insert(0, str(BENCH))
from heldout_maps import HELDOUT, HELDOUT_LARGE, make_map, write_maps  # noqa: E402
from lifelong import (HELDOUT_DENSITIES, HELDOUT_LARGE_DENSITY, TUNED, heldout_problems,  # noqa: E402
                      heldout_summary, set_of)


def parts(free: np.ndarray) -> int:
    """4-connected parts of the free cells."""
    seen = np.zeros_like(free)
    n = 0
    for r0, c0 in zip(*np.nonzero(free), strict=True):
        if seen[r0, c0]:
            continue
        n += 1
        stack = [(r0, c0)]
        seen[r0, c0] = True
        while stack:
            r, c = stack.pop()
            for a, b in ((r + 1, c), (r - 1, c), (r, c + 1), (r, c - 1)):
                if 0 <= a < free.shape[0] and 0 <= b < free.shape[1] and free[a, b] and not seen[a, b]:
                    seen[a, b] = True
                    stack.append((a, b))
    return n


def test_the_held_out_maps_are_fixed_connected_and_of_four_families(tmp_path):
    first, again = write_maps(tmp_path / "a"), write_maps(tmp_path / "b")
    assert set(first) == set(HELDOUT) and {f for f, _, _ in HELDOUT.values()} == {"maze", "rooms", "shelves", "caves"}
    for name, (path, cells) in first.items():
        assert path.read_bytes() == again[name][0].read_bytes(), name        # the seed fixes the map
        grid = load_lorr_map(path)                                          # the start-kit's format, read back
        free = grid.flat.reshape(grid.rows, grid.cols)
        assert int(free.sum()) == cells > 1000 and parts(free) == 1, (name, cells)
        assert 0.3 < cells / free.size < 0.95, name
    maze = np.array(make_map("maze-49-49-w1"))
    degree = sum(np.roll(maze, k, axis=a) for k in (1, -1) for a in (0, 1)) * maze
    assert (degree[maze] <= 2).mean() > 0.8                # a maze: corridors, few junctions


def test_the_held_out_generator_shares_no_code_with_the_planner():
    tree = ast.parse((BENCH / "heldout_maps.py").read_text())
    imported = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    imported |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    assert imported <= {"__future__", "random", "collections", "pathlib", "sys"}, imported


def test_heldout_problems_cover_both_sets_at_each_density(tmp_path):
    todo = heldout_problems(tmp_path, DATA, seed=2, steps=7)
    assert len(todo) == (len(HELDOUT) + len(TUNED)) * len(HELDOUT_DENSITIES) and {s for _, s in todo} == {7}
    sets = [set_of(p.stem) for p, _ in todo]
    assert sets.count("tuned") == len(TUNED) * len(HELDOUT_DENSITIES)
    for path, _ in todo:
        p = load_problem(path)
        density = p.team_size / len(p.grid.free_cells())
        assert min(abs(density - d) for d in HELDOUT_DENSITIES) < 0.01, (path.name, density)
    rows = [{"problem": todo[0][0].stem, "vs_peer": 2.0}, {"problem": todo[1][0].stem, "vs_peer": 0.5},
            {"problem": todo[-1][0].stem}]
    s = heldout_summary(rows)
    assert s["held-out"] == {"problems": 2, "with_peer": 2, "geomean_vs_peer": 1.0, "least_vs_peer": 0.5}
    assert s["tuned"]["problems"] == 1 and s["tuned"]["geomean_vs_peer"] is None


def test_the_large_held_out_maps_hold_teams_over_1000_at_their_density(tmp_path):
    """The large set: fixed, one connected part each, of the small set's families; its problems are
    teams over 1,000 (where the planner's thresholds choose its method), each named held-out."""
    first, again = write_maps(tmp_path / "a", list(HELDOUT_LARGE)), write_maps(tmp_path / "b", list(HELDOUT_LARGE))
    assert {f for f, _, _ in HELDOUT_LARGE.values()} <= {f for f, _, _ in HELDOUT.values()}
    for name, (path, cells) in first.items():
        assert path.read_bytes() == again[name][0].read_bytes(), name
        grid = load_lorr_map(path)
        free = grid.flat.reshape(grid.rows, grid.cols)
        assert int(free.sum()) == cells and parts(free) == 1, (name, cells)
    todo = heldout_problems(tmp_path / "p", DATA, seed=2, steps=9, large=True)
    assert len(todo) == len(HELDOUT_LARGE) and {s for _, s in todo} == {9}
    for path, _ in todo:
        p = load_problem(path)
        assert p.team_size > 1000 and set_of(path.stem) == "held-out", path.name
        assert abs(p.team_size / len(p.grid.free_cells()) - HELDOUT_LARGE_DENSITY) < 0.001, path.name
