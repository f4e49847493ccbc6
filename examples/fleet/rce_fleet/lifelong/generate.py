"""League of Robot Runners 2024 problems generated on a map, as the league's Problem Generator
(MAPF-Competition/Benchmark-Archive, ``Problem Generator``) makes them: distinct random free starts
and tasks of 2 - 5 errands, each errand a random free cell, or a random endpoint on maps that mark
them (``E`` end points and ``S`` sortation points, as the warehouse maps do).

Only cells of the map's largest connected part are used, so every errand is reachable from every
start. :func:`write_problem` writes the problem JSON, ``.agents`` and ``.tasks`` files in the 2024
format (locations are ``row * cols + col``; the map file is named relative to the JSON, as the
start-kit reads it) for ``rce-fleet lifelong``, ``bench/lifelong.py`` and the start-kit alike.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..planning.movingai import converted_free, is_converted
from .grid import LifelongGrid
from .lorr import _read, load_lorr_map

__all__ = ["ENDPOINT_MARKS", "generate_problem", "write_problem"]

ENDPOINT_MARKS = b"ES"          # map characters of endpoints: errands go there when the map has them
TASKS = 100_000                 # task lines per file, as the league's (revealed cyclically)
ERRANDS = (2, 5)                # errands per task, inclusive


def _largest_part(grid: LifelongGrid) -> np.ndarray:
    """(cells,) bool: the free cells of the map's largest 4-connected part."""
    label = np.full(grid.n_cells, -1, dtype=np.int64)
    best, best_size = -1, 0
    for seed in grid.free_cells():
        if label[seed] >= 0:
            continue
        label[seed] = seed
        stack, size = [int(seed)], 0
        while stack:
            c = stack.pop()
            size += 1
            for d in range(4):
                n = int(grid.nbr[c, d])
                if n >= 0 and label[n] < 0:
                    label[n] = seed
                    stack.append(n)
        if size > best_size:
            best, best_size = int(seed), size
    return label == best


def _endpoints(map_path: Path, grid: LifelongGrid) -> np.ndarray:
    """(cells,) bool: cells marked ``E`` or ``S`` in the map file (all False when none are, and on
    a map of 0/1 values)."""
    lines = _read(map_path)
    if is_converted(lines):
        return np.zeros(grid.n_cells, dtype=bool)
    bare = [ln.strip() for ln in lines]
    body = lines[bare.index("map") + 1:] if "map" in bare else lines[1:]
    marks = np.zeros(grid.n_cells, dtype=bool)
    for r, ln in enumerate(body[:grid.rows]):
        row = np.frombuffer(ln[:grid.cols].encode("ascii"), dtype=np.uint8)
        marks[r * grid.cols:r * grid.cols + len(row)] = np.isin(row, np.frombuffer(ENDPOINT_MARKS, np.uint8))
    return marks


def generate_problem(map_path: str | Path, robots: int, seed: int, tasks: int = TASKS,
                     errands: tuple[int, int] = ERRANDS) -> tuple[np.ndarray, list[np.ndarray]]:
    """(starts (robots,) cells, tasks [(k,) cells with ``errands[0]`` <= k <= ``errands[1]``]) on the
    map at ``map_path``, from ``seed``. Consecutive errands of a task differ. Raises ValueError when
    the largest connected part has fewer free cells than ``robots`` (or fewer than two errand cells),
    :class:`~rce_fleet.lifelong.lorr.ProblemError` for an unreadable map."""
    map_path = Path(map_path)
    grid = load_lorr_map(map_path)
    part = _largest_part(grid)
    cells = np.flatnonzero(part)
    if len(cells) < robots:
        raise ValueError(f"{map_path.name}: {robots} robots do not fit on {len(cells)} connected free cells")
    marked = np.flatnonzero(part & _endpoints(map_path, grid))
    spots = marked if len(marked) >= 2 else cells
    if len(spots) < 2:
        raise ValueError(f"{map_path.name}: fewer than two cells for errands")
    rng = np.random.default_rng(seed)
    starts = rng.choice(cells, size=robots, replace=False)
    counts = rng.integers(errands[0], errands[1] + 1, size=tasks)
    flat = spots[rng.integers(0, len(spots), size=int(counts.sum()))]
    out, i = [], 0
    for k in counts.tolist():
        e = flat[i:i + k].copy()
        i += k
        for j in range(1, k):                  # a repeated errand is a free one: move it on
            while e[j] == e[j - 1]:
                e[j] = spots[rng.integers(0, len(spots))]
        out.append(e)
    return starts, out


def write_problem(map_path: str | Path, robots: int, seed: int, out_dir: str | Path,
                  tasks: int = TASKS, reveal: float = 1.5) -> Path:
    """Write a generated problem (:func:`generate_problem`) into ``out_dir`` as
    ``MAPSTEM_ROBOTS_sSEED.json`` with its ``agents/`` and ``tasks/`` files; returns the JSON's path.
    ``reveal``: ``numTasksReveal`` (open tasks per robot; the league's 1.5). A map of 0/1 values
    (:func:`~rce_fleet.planning.movingai.converted_free`), which the start-kit cannot read, is written
    beside them as ``maps/MAPSTEM.map`` in the octile form and the JSON names that copy."""
    src, out_dir = Path(map_path).resolve(), Path(out_dir)
    starts, task_list = generate_problem(src, robots, seed, tasks)
    name = f"{src.stem.replace('-', '_')}_{robots}_s{seed}"
    (out_dir / "agents").mkdir(parents=True, exist_ok=True)
    (out_dir / "tasks").mkdir(parents=True, exist_ok=True)
    (out_dir / "agents" / f"{name}.agents").write_text(
        "# version for LoRR 2024\n" + f"{robots}\n" + "".join(f"{c}\n" for c in starts.tolist()))
    (out_dir / "tasks" / f"{name}.tasks").write_text(
        "# version for LoRR 2024\n" + f"{len(task_list)}\n" + "".join(",".join(map(str, t.tolist())) + "\n"
                                                                      for t in task_list))
    map_file, lines = src, _read(src)
    if is_converted(lines):                    # 0/1 values: the start-kit reads '@' and 'T' as blocked
        map_file = (out_dir / "maps" / f"{src.stem}.map").resolve()
        map_file.parent.mkdir(parents=True, exist_ok=True)
        free = converted_free(src, lines)
        map_file.write_text(f"type octile\nheight {free.shape[0]}\nwidth {free.shape[1]}\nmap\n"
                            + "".join("".join(".@"[int(not v)] for v in row) + "\n" for row in free))
    spec = {"mapFile": os.path.relpath(map_file, out_dir.resolve()), "agentFile": f"agents/{name}.agents",
            "teamSize": robots, "taskFile": f"tasks/{name}.tasks", "numTasksReveal": reveal,
            "version": "2024 LoRR"}
    path = out_dir / f"{name}.json"
    path.write_text(json.dumps(spec, indent=4) + "\n")
    return path
