"""MovingAI grid benchmark files: maps and scenarios (Sturtevant 2012, "Benchmarks for
Grid-Based Pathfinding", IEEE TCIAIG; formats: movingai.com/benchmarks/formats.html).

Two forms of each are read: the original (``type octile`` maps, ``version 1`` scenarios)
and the converted text form of ``../shared/data/SOURCES.md`` (maps: rows, columns, then
0/1 values with 1 = blocked; scenarios: N, then ``sx sy gx gy`` per agent).

Terrain of the original form, as the format page gives it, for a robot on the ground:
``.`` and ``G`` (passable terrain) and ``S`` (swamp, passable from terrain) are free; ``@``
and ``O`` (out of bounds), ``T`` (trees) and ``W`` (water, not passable from terrain) are
not. Any other character is an error. Every error is a ValueError naming the file and line.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .graph import GridGraph

__all__ = ["FREE_TERRAIN", "BLOCKED_TERRAIN", "MapFileError", "converted_free", "is_converted", "load_movingai_map",
           "load_movingai_scen", "octile_header"]

FREE_TERRAIN = ".GS"
BLOCKED_TERRAIN = "@OTW"


class MapFileError(ValueError):
    """A malformed map or scenario file: ``path``, ``line`` (1-based, or None) and ``reason``;
    its text is ``path:line: reason``."""

    def __init__(self, path: str | Path, line: int | None, reason: str):
        self.path, self.line, self.reason = str(path), line, reason
        super().__init__(f"{path}:{line}: {reason}" if line is not None else f"{path}: {reason}")


_err = MapFileError


def _lines(path: Path, what: str) -> list[str]:
    """The lines of a UTF-8 file (CRLF or LF), without the byte-order mark Windows editors write."""
    try:
        return path.read_text(encoding="utf-8-sig").replace("\r\n", "\n").split("\n")
    except FileNotFoundError:
        raise _err(path, None, f"no such {what} file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise _err(path, None, f"cannot read the {what}: {exc}") from None


def _int(path: Path, line: int, text: str, what: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise _err(path, line, f"expected {what} (an integer), got {text!r}") from None


def octile_header(path: Path, lines: list[str]) -> tuple[int, int, int]:
    """(rows, columns, index of the ``map`` line) of an original-form map's ``lines``: header lines
    ``key value`` (``height`` and ``width`` among them, in any order) up to ``map``, and at least
    ``rows`` lines after it. Raises :class:`MapFileError` naming the file and line."""
    hdr: dict[str, tuple[int, str]] = {}
    i = 0
    while i < len(lines) and lines[i].strip() != "map":
        parts = lines[i].split()
        if len(parts) == 2:
            hdr[parts[0]] = (i + 1, parts[1])
        elif parts:
            raise _err(path, i + 1, f"expected 'key value' or 'map', got {lines[i]!r}")
        i += 1
    if i == len(lines):
        raise _err(path, None, "no 'map' line after the header")
    size = []
    for key in ("height", "width"):
        if key not in hdr:
            raise _err(path, i + 1, f"the header has no {key!r} line")
        size.append(_int(path, *hdr[key], key))
    rows, cols = size
    if rows < 1 or cols < 1:
        raise _err(path, hdr["height"][0], f"the map must have at least one row and column, got {rows} x {cols}")
    if len(lines) - i - 1 < rows:            # before allocating rows x cols
        raise _err(path, len(lines), f"the header says {rows} rows but {len(lines) - i - 1} follow")
    return rows, cols, i


def _octile(path: Path, lines: list[str]) -> np.ndarray:
    """The free cells of an original-form map (:func:`octile_header`, then the terrain)."""
    rows, cols, i = octile_header(path, lines)
    free = np.zeros((rows, cols), dtype=bool)
    for r, ln in enumerate(lines[i + 1:i + 1 + rows]):
        if len(ln) < cols:
            raise _err(path, i + 2 + r, f"map row {r} has {len(ln)} cells, expected {cols}")
        for c, ch in enumerate(ln[:cols]):
            if ch not in FREE_TERRAIN and ch not in BLOCKED_TERRAIN:
                raise _err(path, i + 2 + r, f"unknown terrain {ch!r} at column {c} (free: {FREE_TERRAIN}; "
                           f"blocked: {BLOCKED_TERRAIN})")
        free[r] = [ch in FREE_TERRAIN for ch in ln[:cols]]
    return free


def is_converted(lines: list[str]) -> bool:
    """Whether ``lines`` are a converted-form map: its first two lines one integer each."""
    return len(lines) >= 2 and lines[0].strip().isdigit() and lines[1].strip().isdigit()


def converted_free(path: Path, lines: list[str]) -> np.ndarray:
    """(rows, cols) bool, True where free, of a converted-form map's ``lines``: rows, columns, then
    0/1 values (1 = blocked). Raises :class:`MapFileError` naming the file and line."""
    if len(lines) < 2:
        raise _err(path, 1, "expected the number of rows and of columns on the first two lines")
    rows, cols = _int(path, 1, lines[0].strip(), "the number of rows"), _int(path, 2, lines[1].strip(), "the columns")
    if rows < 1 or cols < 1:
        raise _err(path, 1, f"the map must have at least one row and column, got {rows} x {cols}")
    body = lines[2:2 + rows]
    if len(body) < rows:
        raise _err(path, len(lines), f"the header says {rows} rows but {len(body)} follow")
    free = np.zeros((rows, cols), dtype=bool)
    for r, ln in enumerate(body):
        vals = ln.split()
        if len(vals) != cols or any(v not in ("0", "1") for v in vals):
            raise _err(path, 3 + r, f"map row {r}: expected {cols} values 0 (free) or 1 (blocked), got {ln[:60]!r}")
        free[r] = [v == "0" for v in vals]
    return free


def load_movingai_map(path: str | Path) -> GridGraph:
    """A 4-connected :class:`GridGraph` from a MovingAI map.

    Converted form: line 1 rows, line 2 columns, then ``rows`` lines of ``cols`` 0/1
    values (1 = blocked). Original form: ``type octile``, ``height``, ``width`` (in any
    order), ``map``, then the rows; terrain per :data:`FREE_TERRAIN` and
    :data:`BLOCKED_TERRAIN`. Raises ValueError naming the file and line: a missing file, a bad
    header, a short row, an unknown character, or no free cell (a :class:`MapFileError`).
    """
    path = Path(path)
    lines = _lines(path, "map")
    free = _octile(path, lines) if lines[0].strip().startswith("type") else converted_free(path, lines)
    if not free.any():
        raise _err(path, None, "the map has no free cell")
    return GridGraph(free)


def load_movingai_scen(path: str | Path, graph: GridGraph) -> list[tuple[int, int]]:
    """Read a MovingAI scenario: the original ``version 1`` form (one problem a line: bucket,
    map, map width, map height, start x, start y, goal x, goal y, optimal length; tabs, or
    spaces when the map's name has none) or the converted text form (line 1 = N, then
    ``sx sy gx gy``).

    x is the column, y the row. Returns (start_cell, goal_cell) per line, numbered on
    ``graph`` (``cell = y * cols + x``). Raises ValueError naming the file and line: a missing
    file, a short line, a map size that is not ``graph``'s, or a start or goal outside the
    map or on a blocked cell. Whether each goal can be reached from its start is left to the
    planner (:class:`FleetPlanner` reports it; the one-shot solvers refuse it, naming the agent).
    """
    path = Path(path)
    rows, cols = graph.rows, graph.cols
    numbered = [(k + 1, ln.strip()) for k, ln in enumerate(_lines(path, "scenario")) if ln.strip()]
    if not numbered:
        raise _err(path, None, "empty scenario")
    recs: list[tuple[int, list[str]]] = []
    if numbered[0][1].split()[0] == "version":
        for ln, text in numbered[1:]:
            f = text.split("\t") if "\t" in text else text.split()
            if len(f) < 8:
                raise _err(path, ln, f"expected 9 fields (bucket, map, width, height, start x, start y, goal x, "
                           f"goal y, optimal length), got {len(f)}")
            w, h = _int(path, ln, f[2].strip(), "the map width"), _int(path, ln, f[3].strip(), "the map height")
            if (w, h) != (cols, rows):
                raise _err(path, ln, f"this problem is for a {w} x {h} map ({f[1].strip()}), "
                           f"the map is {cols} x {rows}")
            recs.append((ln, [v.strip() for v in f[4:8]]))
    else:
        ln0, text = numbered[0]
        n = _int(path, ln0, text, "the number of agents")
        if n < 0 or len(numbered) - 1 < n:
            raise _err(path, ln0, f"{n} agents but {len(numbered) - 1} lines follow")
        for ln, text in numbered[1:1 + n]:
            f = text.split()
            if len(f) < 4:
                raise _err(path, ln, f"expected 'start_x start_y goal_x goal_y', got {text!r}")
            recs.append((ln, f[:4]))
    out = []
    for ln, f in recs:
        sx, sy, gx, gy = (_int(path, ln, v, "a coordinate") for v in f)
        for what, x, y in (("start", sx, sy), ("goal", gx, gy)):
            if not (0 <= x < cols and 0 <= y < rows):
                raise _err(path, ln, f"{what} (x {x}, y {y}) is outside the {cols} x {rows} map")
            if not graph.free[y, x]:
                raise _err(path, ln, f"{what} (x {x}, y {y}) is a blocked cell of the map")
        out.append((sy * cols + sx, gy * cols + gx))
    return out
