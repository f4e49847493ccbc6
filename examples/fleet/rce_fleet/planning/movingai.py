"""MovingAI grid benchmark files: maps and scenarios (Sturtevant 2012, "Benchmarks for
Grid-Based Pathfinding", IEEE TCIAIG; formats: movingai.com/benchmarks/formats.html).

Two forms of each are read: the original (``type octile`` maps, ``version 1`` scenarios)
and the converted text form of ``../shared/data/SOURCES.md`` (maps: rows, columns, then
0/1 values with 1 = blocked; scenarios: N, then ``sx sy gx gy`` per agent).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .graph import GridGraph

__all__ = ["load_movingai_map", "load_movingai_scen"]


def _free_cells(lines: list[str]) -> np.ndarray:
    """The (rows, cols) bool array of free cells of a map file's lines (either form)."""
    if lines[0].startswith("type"):
        hdr = dict(ln.split(None, 1) for ln in lines[1:3])
        rows, cols = int(hdr["height"]), int(hdr["width"])
        start = next(i for i, ln in enumerate(lines) if ln.strip() == "map") + 1
        body = [ln.rstrip("\r") for ln in lines[start:start + rows]]
        free = np.array([[ch in ".G" for ch in ln[:cols]] for ln in body], dtype=bool)
    else:
        rows, cols = int(lines[0]), int(lines[1])
        body = [ln.split() for ln in lines[2:2 + rows]]
        free = np.array([[v == "0" for v in ln] for ln in body], dtype=bool)
    if free.shape != (rows, cols):
        raise ValueError(f"expected {rows}x{cols} cells, got {free.shape}")
    return free


def load_movingai_map(path: str | Path) -> GridGraph:
    """A 4-connected :class:`GridGraph` from a MovingAI map.

    Converted form: line 1 rows, line 2 columns, then ``rows`` lines of ``cols`` 0/1
    values (1 = blocked). Original ``type octile`` form: ``.`` and ``G`` free, others
    blocked. Raises ValueError naming the file.
    """
    path = Path(path)
    try:
        free = _free_cells(path.read_text().split("\n"))
    except (ValueError, KeyError, IndexError, StopIteration) as exc:
        raise ValueError(f"{path}: not a MovingAI map: {exc}") from exc
    return GridGraph(free)


def load_movingai_scen(path: str | Path, graph: GridGraph) -> list[tuple[int, int]]:
    """Read a MovingAI scenario in the converted text form: line 1 = N, then ``sx sy gx gy``.

    Also accepts the original ``version 1`` .scen format. x is the column, y the
    row. Returns (start_cell, goal_cell) per agent, numbered on ``graph``
    (``cell = y * cols + x``). Raises ValueError naming the file.
    """
    path = Path(path)
    cols = graph.cols
    lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    try:
        if lines[0].startswith("version"):
            recs = [ln.split("\t") if "\t" in ln else ln.split() for ln in lines[1:]]   # tabs, or spaces
            xy = [(int(r[4]), int(r[5]), int(r[6]), int(r[7])) for r in recs]
        else:
            n = int(lines[0])
            xy = [tuple(int(v) for v in ln.split()[:4]) for ln in lines[1:1 + n]]
    except (ValueError, IndexError) as exc:
        raise ValueError(f"{path}: not a MovingAI scenario: {exc}") from exc
    return [(sy * cols + sx, gy * cols + gx) for sx, sy, gx, gy in xy]
