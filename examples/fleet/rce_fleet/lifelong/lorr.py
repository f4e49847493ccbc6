"""League of Robot Runners 2024 problem files (MAPF-Competition/Start-Kit v2.1.2,
``Input_Output_Format.md``): the problem JSON, the map (MovingAI octile, Sturtevant 2012, or a
first line ``rows,cols``; as the start-kit's ``Grid::load_from_path`` reads it, ``@`` and ``T``
are obstacles and every other character is free: ``.``, ``E`` end points, ``S`` sortation points,
``W`` home locations), the agents file and the tasks file.

Problem JSON keys: ``mapFile``, ``agentFile``, ``taskFile`` (paths relative to the JSON),
``teamSize``, ``numTasksReveal``; optional ``version``. Agents file: comment lines start with
``#``, then the number of agents, then one start location a line. Tasks file: comments, the
number of tasks, then one task a line as comma-separated locations (its errands in order).
Locations are ``row * width + column``.

Every error is a :class:`ProblemError` naming the file and, where there is one, the line.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from ..planning.movingai import MapFileError, converted_free, is_converted, octile_header
from .grid import LifelongGrid

__all__ = ["LorrProblem", "ProblemError", "load_lorr_map", "load_problem"]


class ProblemError(ValueError):
    """A missing or malformed problem file: ``path`` and ``line`` (1-based, or None) say where."""

    def __init__(self, path: str | Path, message: str, line: int | None = None):
        self.path, self.line = str(path), line
        where = f"{path}:{line}" if line is not None else f"{path}"
        super().__init__(f"{where}: {message}")


@dataclass
class LorrProblem:
    """One LoRR problem: the grid, the agents' start cells and the task file's errands.

    starts: (teamSize,) int64 cells. tasks: list of tuples of cells (one tuple per line of the
    task file, errands in order). ``reveal`` is ``int(numTasksReveal * teamSize)``, the number
    of open tasks the simulator keeps revealed. ``warnings``: what the loader found that does
    not stop a run (a task no robot can finish), one line each, naming the file and line.
    """

    path: Path
    grid: LifelongGrid
    starts: np.ndarray
    tasks: list[tuple[int, ...]]
    team_size: int
    num_tasks_reveal: float
    version: str = "2024 LoRR"
    warnings: list[str] = field(default_factory=list)

    @property
    def reveal(self) -> int:
        """How many tasks are open at any time: ``int(numTasksReveal * teamSize)``."""
        return int(self.num_tasks_reveal * self.team_size)


def _read(path: Path) -> list[str]:
    """The lines of a UTF-8 file, without the byte-order mark Windows editors write."""
    try:
        return path.read_text(encoding="utf-8-sig").split("\n")
    except FileNotFoundError:
        raise ProblemError(path, "no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ProblemError(path, f"cannot read: {exc}") from None


#: The most open tasks per robot a problem may ask for (``numTasksReveal``; LoRR's use 1 - 1.5):
#: every open task is a Python object the scheduler weighs each step, so 10^9 would hang the run.
MAX_TASKS_REVEAL = 1000

OBSTACLES = b"@T"      # every other map character is free (the start-kit's Grid::load_from_path)


def load_lorr_map(path: str | Path) -> LifelongGrid:
    """A :class:`LifelongGrid` from a LoRR map: a MovingAI ``type octile`` header (``height``,
    ``width``, then ``map``) or a first line ``rows,cols``, then one line per row; ``@`` and
    ``T`` are blocked, every other character free (:data:`OBSTACLES`). A MovingAI map in the
    converted form of ``../shared/data/SOURCES.md`` (rows, columns, then 0/1 values, 1 blocked:
    :func:`~rce_fleet.planning.movingai.converted_free`) is read too. Raises ProblemError naming
    the file and line."""
    path = Path(path)
    lines = _read(path)
    try:
        if is_converted(lines):
            free = converted_free(path, lines)
            return LifelongGrid(free)
        if lines and "," in lines[0] and not lines[0].lstrip().startswith("type"):
            try:
                rows, cols = (int(x) for x in lines[0].split(",")[:2])
            except ValueError:
                raise ProblemError(path, f"expected 'rows,cols', got {lines[0]!r}", 1) from None
            i = 0                                   # the rows follow the first line
            if rows < 1 or cols < 1:
                raise ProblemError(path, f"the map must have at least one row and column, got {rows} x {cols}", 1)
            if len(lines) - 1 < rows:               # before allocating rows x cols
                raise ProblemError(path, f"the header says {rows} rows but {len(lines) - 1} follow", len(lines))
        else:
            rows, cols, i = octile_header(path, lines)
    except ProblemError:
        raise
    except MapFileError as exc:
        raise ProblemError(exc.path, exc.reason, exc.line) from None
    except ValueError as exc:                       # LifelongGrid's: no free cell
        raise ProblemError(path, str(exc)) from None
    body = lines[i + 1: i + 1 + rows]
    free = np.zeros((rows, cols), dtype=bool)
    blocked = np.frombuffer(OBSTACLES, dtype=np.uint8)
    for r in range(rows):
        ln = body[r].rstrip("\r")
        if len(ln) < cols:
            raise ProblemError(path, f"map row {r} has {len(ln)} cells, expected {cols}", i + 2 + r)
        try:
            row = np.frombuffer(ln[:cols].encode("ascii"), dtype=np.uint8)
        except UnicodeEncodeError:
            raise ProblemError(path, f"map row {r} has a character that is not ASCII", i + 2 + r) from None
        free[r] = ~np.isin(row, blocked)
    try:
        return LifelongGrid(free)
    except ValueError as exc:
        raise ProblemError(path, str(exc)) from None


def _numbered(path: Path) -> list[tuple[int, str]]:
    """(1-based line number, text) of the non-empty, non-comment lines."""
    return [(k + 1, ln.strip()) for k, ln in enumerate(_read(path)) if ln.strip() and not ln.lstrip().startswith("#")]


def _single(path: Path, line: int, text: str) -> str:
    """The one value of a count line or an agents line. The start-kit reads the first
    comma-separated field, so a trailing comma is accepted; a second value is refused (a
    ``row,col`` pair would otherwise be read silently as a location)."""
    fields = [f.strip() for f in text.split(",")]
    while len(fields) > 1 and not fields[-1]:
        fields.pop()
    if len(fields) != 1:
        raise ProblemError(path, f"expected one value, got {text!r}", line)
    return fields[0]


def _cell(path: Path, line: int, text: str, grid: LifelongGrid) -> int:
    try:
        cell = int(text)
    except ValueError:
        raise ProblemError(path, f"expected a location (integer), got {text!r}", line) from None
    if not grid.is_free(cell):
        r, c = divmod(cell, grid.cols) if cell >= 0 else (-1, -1)
        raise ProblemError(path, f"location {cell} (row {r}, col {c}) is not a free cell of the map", line)
    return cell


def _count(path: Path, lines: list[tuple[int, str]]) -> int:
    if not lines:
        raise ProblemError(path, "empty file: expected the count on the first line")
    ln, text = lines[0]
    try:
        n = int(_single(path, ln, text))
    except ValueError:
        raise ProblemError(path, f"expected the count, got {text!r}", ln) from None
    if n < 0 or len(lines) - 1 < n:
        raise ProblemError(path, f"count {n} but {len(lines) - 1} entries follow", ln)
    return n


def _key_line(text: str, key: str) -> int | None:
    """The 1-based line of the problem JSON where ``key`` is written (None if not found)."""
    return next((k + 1 for k, ln in enumerate(text.split("\n")) if f'"{key}"' in ln), None)


def _number(path: Path, text: str, spec: dict, key: str, integer: bool) -> float:
    """``spec[key]`` as a finite JSON number (an integral one if ``integer``), else ProblemError."""
    v = spec[key]
    ok = not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)
    if not ok or (integer and v != int(v)):
        kind = "an integer" if integer else "a number"
        raise ProblemError(path, f"{key} must be {kind}, got {v!r}", _key_line(text, key))
    return v


def _file(path: Path, text: str, spec: dict, key: str) -> Path:
    """The file ``spec[key]`` names, relative to the problem JSON's directory."""
    v = spec[key]
    if not isinstance(v, str) or not v.strip():
        raise ProblemError(path, f"{key} must be a file name, got {v!r}", _key_line(text, key))
    return path.parent / v


def _unreachable_warning(grid: LifelongGrid, starts: np.ndarray, tpath: Path,
                         tasks: list[tuple[int, ...]], lines: list[int]) -> str | None:
    """A warning naming the first task that no robot can finish (an errand in a part of the
    map without robots, or errands in two parts) and how many there are; None if none."""
    labels, parts = ndimage.label(grid.free)        # 4-connected parts of the free cells
    if parts == 1:
        return None
    flat = labels.ravel()
    manned = set(flat[starts].tolist())
    bad = [k for k, t in enumerate(tasks) if len({int(flat[e]) for e in t}) > 1 or int(flat[t[0]]) not in manned]
    if not bad:
        return None
    k = bad[0]
    return (f"{tpath}:{lines[k]}: warning: no robot can finish task {list(tasks[k])}: the map has {parts} separate "
            f"parts and this task's errands are not all in one part with a robot ({len(bad)} of {len(tasks)} tasks "
            "like it); such a task stays open and holds one of the revealed tasks for good")


def load_problem(path: str | Path) -> LorrProblem:
    """Read a LoRR 2024 problem JSON and the map, agents and tasks files it names.

    The 2023 form is read too: single-errand task lines, an integer ``numTasksReveal`` and
    ``taskAssignmentStrategy`` (ignored: the scheduler assigns, as in 2024). Raises
    ProblemError (a ValueError) naming the file and line of the first problem: a missing
    file, bad JSON, a missing key or one of the wrong type, a location that is not a free
    cell, two agents on one start, fewer agents than ``teamSize``, no task,
    ``numTasksReveal * teamSize`` < 1 or ``numTasksReveal`` > :data:`MAX_TASKS_REVEAL`. A task
    that no robot can reach is not an error (the start-kit runs it too); it is named in
    ``warnings``.
    """
    path = Path(path)
    text = "\n".join(_read(path))
    try:
        spec = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ProblemError(path, f"not JSON: {exc.msg}", exc.lineno) from None
    if not isinstance(spec, dict):
        raise ProblemError(path, "expected a JSON object", 1)
    for key in ("mapFile", "agentFile", "taskFile", "teamSize"):
        if key not in spec:
            raise ProblemError(path, f"missing key {key!r}")
    team = int(_number(path, text, spec, "teamSize", integer=True))
    if team < 1:
        raise ProblemError(path, f"teamSize must be >= 1, got {team}", _key_line(text, "teamSize"))
    reveal = float(_number(path, text, spec, "numTasksReveal", integer=False)) if "numTasksReveal" in spec else 1.0
    if reveal > MAX_TASKS_REVEAL:
        raise ProblemError(path, f"numTasksReveal must be at most {MAX_TASKS_REVEAL} (open tasks per robot), "
                           f"got {reveal}", _key_line(text, "numTasksReveal"))
    if int(reveal * team) < 1:
        raise ProblemError(path, f"numTasksReveal {reveal} x teamSize {team} reveals no task (it must be >= 1)",
                           _key_line(text, "numTasksReveal"))
    mpath, apath, tpath = (_file(path, text, spec, k) for k in ("mapFile", "agentFile", "taskFile"))
    grid = load_lorr_map(mpath)
    alines = _numbered(apath)
    n = _count(apath, alines)
    if n < team:
        raise ProblemError(apath, f"{n} agents but teamSize is {team}", alines[0][0])
    first: dict[int, int] = {}
    for ln, t in alines[1:1 + team]:
        cell = _cell(apath, ln, _single(apath, ln, t), grid)
        if cell in first:
            raise ProblemError(apath, f"location {cell} is also the start of the agent of line {first[cell]}: "
                               "two robots cannot start on one cell", ln)
        first[cell] = ln
    starts = np.array(list(first), dtype=np.int64)
    tlines = _numbered(tpath)
    m = _count(tpath, tlines)
    if m < 1:
        raise ProblemError(tpath, "no task", tlines[0][0])
    tasks = []
    for ln, t in tlines[1:1 + m]:
        errands = tuple(_cell(tpath, ln, x.strip(), grid) for x in t.split(",") if x.strip())
        if not errands:
            raise ProblemError(tpath, "a task needs at least one errand", ln)
        tasks.append(errands)
    warning = _unreachable_warning(grid, starts, tpath, tasks, [ln for ln, _ in tlines[1:1 + m]])
    return LorrProblem(path=path, grid=grid, starts=starts, tasks=tasks, team_size=team,
                       num_tasks_reveal=reveal, version=str(spec.get("version", "2024 LoRR")),
                       warnings=[warning] if warning else [])
