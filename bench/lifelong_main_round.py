"""The League of Robot Runners 2024 main round in ``bench/lifelong.py --main-round``: its ten
instances at their full length, rce beside the 2024 winner's code and the default entry, one
result JSON per (instance, system) written as it finishes, so that a rerun resumes where a run
stopped, and the table of all of them in ``docs/results/lifelong.md`` between markers.

Instances: MAPF-Competition/Benchmark-Archive, ``2024 Competition/Main Round Evaluation
Instances/`` (``random.domain/RANDOM-01.json`` ..., and ``simulation_time.json``: instance name ->
steps), read from a checkout outside the repository. Best known: that archive's ``2024
Competition/README.md`` (commit 25ffd5b), copied into ``BEST_KNOWN``.
"""
from __future__ import annotations

import itertools
import json
import os
import re
import time
from collections.abc import Callable
from pathlib import Path

# (instance, domain folder) in the archive's order of the record's tables
MAIN_ROUND = (("RANDOM-01", "random.domain"), ("RANDOM-02", "random.domain"), ("RANDOM-03", "random.domain"),
              ("RANDOM-04", "random.domain"), ("RANDOM-05", "random.domain"), ("CITY-01", "city.domain"),
              ("CITY-02", "city.domain"), ("GAME", "game.domain"), ("SORTATION", "warehouse.domain"),
              ("WAREHOUSE", "warehouse.domain"))
# tasks finished by the best known solution, and its team (Benchmark-Archive, 2024 Competition/README.md)
BEST_KNOWN = {"RANDOM-01": (696, "RAPID"), "RANDOM-02": (1260, "Kitty_Knight"), "RANDOM-03": (2368, "No_Man's_Sky"),
              "RANDOM-04": (2585, "No_Man's_Sky"), "RANDOM-05": (3050, "No_Man's_Sky"),
              "CITY-01": (8445, "Kitty_Knight"), "CITY-02": (17010, "SYSU-LCIS"), "GAME": (23274, "No_Man's_Sky"),
              "SORTATION": (152714, "No_Man's_Sky"), "WAREHOUSE": (154834, "No_Man's_Sky")}
SYSTEMS = ("rce", "winner", "default")
MAIN_DIR = Path("2024 Competition") / "Main Round Evaluation Instances"
WINDOW = 500         # steps per window of the rate's steadiness (the worst window over the best)
BEGIN, END = "<!-- main-round table: begin (bench/lifelong.py --main-round) -->", "<!-- main-round table: end -->"


def instances(archive: Path, only: list[str] | None = None, missing_ok: bool = False) -> list[tuple[str, Path, int]]:
    """(name, problem JSON, official steps) of the main round's instances under ``archive`` (a
    Benchmark-Archive checkout, its ``2024 Competition`` folder or its main-round folder), in
    ``MAIN_ROUND``'s order, those named in ``only`` when given. Raises FileNotFoundError naming
    the missing file (with ``missing_ok``, an instance without its files is left out), ValueError for a
    name in ``only`` that is not an instance of the round."""
    base = next((d for d in (archive / MAIN_DIR, archive / MAIN_DIR.name, archive)
                 if (d / "simulation_time.json").is_file()), None)
    if base is None:
        raise FileNotFoundError(f"{archive}: no simulation_time.json of the 2024 main round here (a checkout of "
                                "github.com/MAPF-Competition/Benchmark-Archive, or its "
                                f"'{MAIN_DIR}' folder)")
    names = [n for n, _ in MAIN_ROUND]
    if bad := [n for n in only or () if n not in names]:
        raise ValueError(f"--only {' '.join(bad)}: not a 2024 main-round instance ({', '.join(names)})")
    steps = json.loads((base / "simulation_time.json").read_text())
    out = []
    for name, domain in MAIN_ROUND:
        if only and name not in only:
            continue
        path = base / domain / f"{name}.json"
        if missing_ok and (not path.is_file() or name not in steps):
            continue
        if not path.is_file():
            raise FileNotFoundError(f"{path}: missing (the archive's {domain}/{name}.json)")
        if name not in steps:
            raise FileNotFoundError(f"{base / 'simulation_time.json'}: no steps for {name}")
        out.append((name, path, int(steps[name])))
    return out


def result_path(results: Path, name: str, system: str, steps: int) -> Path:
    """Where the result of ``system`` on instance ``name`` over ``steps`` steps is kept."""
    return results / f"{name}.{system}.{steps}.json"


def load_result(path: Path, limit_ms: float) -> dict | None:
    """The finished result at ``path``, or None when there is none, it is not JSON, or it was run
    at another time limit (then it is run again)."""
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) and d.get("plan_time_limit_ms") == limit_ms else None


def save_result(path: Path, row: dict) -> None:
    """Write ``row`` to ``path`` whole or not at all (a temporary file renamed over it), so that a
    run killed while writing leaves no half result for a rerun to skip."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(row, indent=1))
    os.replace(tmp, path)


def run_round(todo: list[tuple[str, Path, int]], runners: dict[str, Callable[[Path, int], dict]], results: Path,
              limit_ms: float, stamp: dict, say: Callable[[str], None]) -> dict[tuple[str, str], dict]:
    """Run every (instance, system) of ``todo`` x ``runners`` (system -> ``run(problem, steps)``
    returning its row) that has no result in ``results`` yet; each result is saved as it
    finishes, with ``stamp`` (date, commit) and the time limit. ``say`` gets one line per run
    done or skipped. Returns (name, system) -> result for all of them."""
    got: dict[tuple[str, str], dict] = {}
    total, k = len(todo) * len(runners), 0
    for name, path, steps in todo:
        for system, run in runners.items():
            k += 1
            where = result_path(results, name, system, steps)
            if (old := load_result(where, limit_ms)) is not None:
                got[name, system] = old
                say(f"[{k}/{total}] {name} {system}: done before ({_brief(old)}), {where}")
                continue
            t0 = time.perf_counter()
            row = {**run(path, steps), "instance": name, "system": system, "steps": steps,
                   "plan_time_limit_ms": limit_ms, **stamp, "wall_s": time.perf_counter() - t0}
            save_result(where, row)
            got[name, system] = row
            say(f"[{k}/{total}] {name} {system}: {_brief(row)} in {row['wall_s'] / 60:.1f} min, {where}")
    return got


def with_recorded(archive: Path, todo: list[tuple[str, Path, int]], got: dict[tuple[str, str], dict],
                  results: Path, limit_ms: float, steps: int | None = None) -> list[tuple[str, Path, int]]:
    """Every instance of the round in ``archive``, in its order: those of ``todo`` at their steps, the
    others at ``steps`` (default: their official steps), whose results on record in ``results`` (of
    every system of ``SYSTEMS``, at ``limit_ms``) are added to ``got``; so a run of one instance keeps
    the others' rows in the table, and a run of rce alone keeps the peers' results on record."""
    mine = {name: (path, steps) for name, path, steps in todo}
    shown = []
    for name, path, n in instances(archive, missing_ok=True):
        path, n = mine.get(name, (path, steps or n))
        shown.append((name, path, n))
        for system in SYSTEMS:
            if (name, system) not in got and (old := load_result(result_path(results, name, system, n),
                                                                   limit_ms)) is not None:
                got[name, system] = old
    return shown


def window_rates(curve: list[int], window: int = WINDOW) -> list[int]:
    """Tasks finished in each whole ``window``-step window (steps 1 .. window, ...) of ``curve``
    (tasks finished by the end of each step, cumulative, as a run's ``curve``); a last part window
    is left out."""
    return [b - a for a, b in itertools.pairwise([0, *curve[window - 1::window]])]


def steadiness(r: dict, window: int = WINDOW) -> str:
    """The worst ``window``-step window's tasks over the best's in result ``r``, and which steps it
    was ("0.93 (worst: steps 500-1,000)"), or "-" with fewer than two whole windows."""
    rates = window_rates(r.get("curve") or [], window)
    if len(rates) < 2 or max(rates) <= 0:
        return "-"
    k = rates.index(min(rates))
    return f"{min(rates) / max(rates):.2f} (worst: steps {k * window:,}-{(k + 1) * window:,})"


def plot_round(todo: list[tuple[str, Path, int]], got: dict[tuple[str, str], dict], path: Path,
               every: int = 100) -> list[str]:
    """PNG at ``path``: for each instance of ``todo`` with an rce result in ``got``, the tasks
    finished in each ``every``-step window by every system whose result has a ``curve`` (rce, and
    the peers run with ``-c 1``: :func:`startkit_peer.finished_curve`), and the best known's mean
    rate over the official steps as a dotted line. Returns the instances drawn
    (none: no file is written)."""
    names = [(n, s) for n, _, s in todo if (n, "rce") in got]
    if not names:
        return []
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = min(len(names), 5)
    rows = -(-len(names) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.0 * rows), squeeze=False)
    cells = list(axes.flat)
    for ax, (name, steps) in zip(cells, names, strict=False):
        for k, system in enumerate(SYSTEMS):
            if (r := got.get((name, system))) is not None and (rates := window_rates(r.get("curve") or [], every)):
                ax.step([every * i for i in range(len(rates) + 1)], [*rates, rates[-1]], where="post", color=f"C{k}",
                        label=f"{system} ({r['tasks_finished']:,})")
        official = got[name, "rce"].get("official_steps", steps)
        best = BEST_KNOWN[name][0]
        ax.axhline(best * every / official, ls=":", color="black", label=f"best known's mean ({best:,})")
        ax.set_title(f"{name}, {steps:,} steps", fontsize=9)
        ax.set_xlabel("step")
        ax.set_ylabel(f"tasks per {every} steps")
        ax.set_ylim(bottom=0)
        ax.legend(fontsize=6)
    for ax in cells[len(names):]:
        ax.set_visible(False)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [n for n, _ in names]


def _brief(r: dict) -> str:
    if "error" in r:
        return f"failed: {r['error']}"
    peak = f", peak memory {r['peak_rss_mib'] / 1024:.1f} GiB" if "peak_rss_mib" in r else ""
    return f"{r['tasks_finished']} tasks, {r['timeouts']} timeouts, {r['invalid_steps']} invalid steps{peak}"


def table(todo: list[tuple[str, Path, int]], got: dict[tuple[str, str], dict],
          kept: dict[str, str] | None = None) -> str:
    """The markdown table of the results in ``got`` for the instances of ``todo``: rce's tasks and
    its ratio to the best known (pro rata on a cut, marked), to the winner's code and to the
    default entry measured here (their timeouts in brackets), rce's planner ms, timeouts, the
    steadiness of its rate (:func:`steadiness`), date and commit. An instance with no rce result
    in ``got`` keeps its row of ``kept`` (instance -> row, as :func:`recorded_rows` reads them) as
    it is, or has none; a peer with no result in ``got`` keeps its count from that row, at the same
    steps (a run of rce alone into a fresh ``--results``), and a kept row takes the peers' new
    counts at its steps (a run of the peers alone: :func:`_with_peers`); rows go in ``MAIN_ROUND``'s
    order."""
    head = ("| instance | robots | steps | rce | best known | rce / best | winner | rce / winner | default | "
            "rce / default | rce planner ms p50 / p99 / max | rce timeouts | rce 500-step windows, worst / best | "
            "date | commit |")
    rows = dict(kept or {})
    for name, path, steps in todo:
        r = got.get((name, "rce"))
        if r is None:
            if name in rows:
                rows[name] = _with_peers(rows[name], name, steps, got)
            continue
        best, team = BEST_KNOWN[name]
        official = r.get("official_steps", steps)
        scale = steps / official
        mine = r.get("tasks_finished")
        cells = [name, f"{r.get('robots', _team(path)):,}",
                 f"{steps:,}" if scale == 1 else f"{steps:,} of {official:,}",
                 _count(r), f"{best:,} ({team})", _ratio(mine, best * scale) + ("" if scale == 1 else " pro rata")]
        kept_cells = _at_steps(rows.get(name), steps)
        for system, col in (("winner", 6), ("default", 8)):
            p = got.get((name, system))
            if p is None and kept_cells and (theirs := _number(kept_cells[col])) is not None:
                cells += [kept_cells[col], _ratio(mine, theirs)]
            else:
                cells += [_count(p), _ratio(mine, p.get("tasks_finished") if p else None)]
        ms = (f"{r['plan_ms_p50']:.0f} / {r['plan_ms_p99']:.0f} / {r['plan_ms_max']:.0f}"
              if "plan_ms_p50" in r else "-")
        cells += [ms, str(r.get("timeouts", "-")), steadiness(r), r.get("date", "-"),
                  r.get("commit", "-").split(" ")[0]]
        rows[name] = "| " + " | ".join(cells) + " |"
    return "\n".join([head, "|" + "---|" * head.count(" | ") + "---|",
                      *(rows[name] for name, _ in MAIN_ROUND if name in rows)])


def _with_peers(row: str, name: str, steps: int, got: dict[tuple[str, str], dict]) -> str:
    """The recorded ``row`` of ``name`` with the counts of the peers in ``got`` in their cells, and
    their ratios to rce's count on record, when the row is at ``steps``; else ``row`` as it is."""
    cells = _at_steps(row, steps)
    mine = _number(cells[3]) if cells else None
    if mine is None:
        return row
    for system, col in (("winner", 6), ("default", 8)):
        if (p := got.get((name, system))) is not None:
            cells[col:col + 2] = [_count(p), _ratio(mine, p.get("tasks_finished"))]
    return "| " + " | ".join(cells) + " |"


def _at_steps(row: str | None, steps: int) -> list[str] | None:
    """The cells of a recorded table ``row`` when it is a full row at ``steps`` (its steps cell
    ``N`` or ``N of M``), else None."""
    cells = [c.strip() for c in row.split("|")[1:-1]] if row else []
    return cells if len(cells) >= 10 and cells[2].split(" of ")[0] == f"{steps:,}" else None


def _number(cell: str) -> int | None:
    """The count a table cell starts with (``"1,234 (5)"`` -> 1234), or None (``not run``, ``-``)."""
    head = cell.split(" ")[0].replace(",", "")
    return int(head) if head.isdigit() else None


def _team(path: Path) -> int:
    return int(json.loads(path.read_text())["teamSize"])


def _count(r: dict | None) -> str:
    if r is None:
        return "not run"
    if "error" in r:
        return "failed"
    t = r.get("timeouts", 0)
    return f"{r['tasks_finished']:,}" + (f" ({t})" if t and r.get("system") != "rce" else "")


def _ratio(a: float | None, b: float | None) -> str:
    return f"{a / b:.2f}" if a is not None and b else "-"


def recorded_rows(doc: Path) -> dict[str, str]:
    """The rows of the table between the main-round markers of ``doc``, by instance (its first
    cell); none when the file or its markers are missing. They keep a row whose results are not in
    this run's ``--results`` (measured on another machine, or before) when the table is written."""
    try:
        m = _table_block(doc.read_text())
    except OSError:
        return {}
    rows = {}
    for line in (m.group(1).splitlines() if m else ()):
        name = line.split("|")[1].strip() if line.startswith("| ") else ""
        if name in BEST_KNOWN:
            rows[name] = line
    return rows


def write_table(doc: Path, text: str) -> None:
    """Replace what is between the main-round markers of ``doc`` with ``text``. Raises ValueError
    naming the file when the markers are not there (once each, in order)."""
    old = doc.read_text()
    m = _table_block(old)
    if m is None or old.count(BEGIN) != 1 or old.count(END) != 1:
        raise ValueError(f"{doc}: no main-round table markers ({BEGIN} ... {END}) to write between")
    doc.write_text(old[:m.start()] + f"{BEGIN}\n{text}\n{END}" + old[m.end():])


def _table_block(text: str) -> re.Match | None:
    """The main-round markers in ``text`` and what is between them (group 1), or None."""
    return re.search(re.escape(BEGIN) + r"\n(.*?)" + re.escape(END), text, flags=re.S)
