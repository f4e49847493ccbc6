"""``bench/lifelong.py --main-round``: the 2024 main round's layout read, one result JSON per
(instance, system) written as it finishes, a rerun resuming from them, and the table written
between its markers.

The archive here is laid out as MAPF-Competition/Benchmark-Archive's main-round folder; its
RANDOM-01 is built from the shared LoRR files of random-32-32-20 with 100 robots (the main
round's map and team, the test round's agents and tasks), so the test needs no checkout."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from rce_fleet.lifelong import load_problem
from rce_fleet.lifelong.runner import run_lifelong

ROOT = Path(__file__).resolve().parents[2]
RANDOM = ROOT / ".." / "shared" / "data" / "lorr" / "random.domain"
BENCH = ROOT / "bench" / "lifelong.py"
sys.path.insert(0, str(BENCH.parent))
from lifelong_main_round import plot_round, steadiness, window_rates  # noqa: E402
from startkit_peer import PREPROCESS_MS, finished_curve, run_peer  # noqa: E402

BEGIN, END = "<!-- main-round table: begin (bench/lifelong.py --main-round) -->", "<!-- main-round table: end -->"


def _archive(tmp: Path) -> Path:
    base = tmp / "2024 Competition" / "Main Round Evaluation Instances"
    shutil.copytree(RANDOM, base / "random.domain", ignore=shutil.ignore_patterns("*.json"))
    problem = json.loads((RANDOM / "random_32_32_20_100.json").read_text())
    (base / "random.domain" / "RANDOM-01.json").write_text(json.dumps(problem))
    (base / "random.domain" / "RANDOM-02.json").write_text(json.dumps(problem))
    (base / "simulation_time.json").write_text(json.dumps({"RANDOM-01": 600, "RANDOM-02": 600}))
    return tmp


def _bench(*argv) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(BENCH), "--main-round", *map(str, argv)], capture_output=True,
                          text=True, timeout=120)


def test_main_round_keeps_each_result_resumes_and_writes_the_table(tmp_path):
    archive, res, doc = _archive(tmp_path / "archive"), tmp_path / "results", tmp_path / "record.md"
    doc.write_text(f"# record\n\n{BEGIN}\nold table\n{END}\n\nafter\n")
    args = ("--archive", archive, "--only", "RANDOM-01", "--steps", 3, "--results", res, "--plan-time-limit", 500,
            "--doc", doc)
    r = _bench(*args)
    assert r.returncode == 0, r.stderr[-2000:]
    kept = res / "RANDOM-01.rce.3.json"
    d = json.loads(kept.read_text())
    assert (d["instance"], d["system"], d["steps"], d["official_steps"]) == ("RANDOM-01", "rce", 3, 600)
    assert d["robots"] == 100
    assert d["plan_time_limit_ms"] == 500 and d["timeouts"] == 0 and d["invalid_steps"] == 0
    assert d["replayed_tasks"] == d["tasks_finished"] and d["replay_invalid_steps"] == 0 and "replay_error" not in d
    assert len(d["curve"]) == 3 and d["date"] and d["commit"]
    assert sorted(p.name for p in res.iterdir()) == [kept.name, "main_round.png"]   # no temporary left behind
    assert (res / "main_round.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = doc.read_text()
    assert "old table" not in text and text.endswith(f"{END}\n\nafter\n")
    row = next(ln for ln in text.splitlines() if ln.startswith("| RANDOM-01 |"))
    assert "| 3 of 600 |" in row and "696 (RAPID)" in row and "pro rata" in row and "| not run |" in row
    assert row.count("|") == text.splitlines()[text.splitlines().index(BEGIN) + 1].count("|")   # header's columns
    stamp, before = kept.stat().st_mtime_ns, kept.read_bytes()

    again = _bench(*args)                                          # resumes: nothing left to run
    assert again.returncode == 0, again.stderr[-2000:]
    assert "[1/1] RANDOM-01 rce: done before" in again.stderr and "(batch)" not in again.stderr
    assert kept.stat().st_mtime_ns == stamp and kept.read_bytes() == before
    assert row in doc.read_text()

    # a run of another instance keeps the first one's row (its result on record), and a run of rce
    # alone keeps the winner's result on record for its own instance
    winner = {"tasks_finished": 7, "timeouts": 0, "invalid_steps": 0, "instance": "RANDOM-02", "system": "winner",
              "steps": 3, "plan_time_limit_ms": 500}
    (res / "RANDOM-02.winner.3.json").write_text(json.dumps(winner))
    other = _bench(*[("RANDOM-02" if a == "RANDOM-01" else a) for a in args])
    assert other.returncode == 0, other.stderr[-2000:]
    rows = [ln for ln in doc.read_text().splitlines() if ln.startswith("| RANDOM-")]
    assert [ln.split(" | ")[0] for ln in rows] == ["| RANDOM-01", "| RANDOM-02"] and row in rows, doc.read_text()
    assert "| 7 | " in rows[1] and "| not run |" in rows[1], rows[1]      # the winner's on record, no default

    bare = tmp_path / "bare.md"
    bare.write_text("# no markers\n")
    r = _bench(*args[:-2], "--doc", bare)      # resumed, then refused
    assert r.returncode == 2 and f"{bare}: no main-round table markers" in r.stderr


def test_rows_measured_elsewhere_stay_in_the_table_when_one_instance_is_run(tmp_path):
    """A run into a fresh ``--results`` (another machine, the record's results not there) replaces
    the rows it measured and keeps every other row of the table as it was, in the round's order, and
    in the row it measured, the peers' counts on record."""
    archive, doc = _archive(tmp_path / "archive"), tmp_path / "record.md"
    city = "| CITY-01 | 1,500 | 3,000 | 8,382 | 8,445 (Kitty_Knight) | 0.99 | 8,000 | 1.05 | - | 2026-11-28 | c89b4c1 |"
    second = "| RANDOM-02 | 200 | 600 | 1,083 | 1,260 (Kitty_Knight) | 0.86 | 1,196 | 0.91 | - | 2026-11-28 | dac76bf |"
    stale = ("| RANDOM-01 | 100 | 3 of 600 | 1 | 696 (RAPID) | 0.00 pro rata | 5 | 0.20 | 1,000 (2) | 0.00 | - | 0 "
             "| - | 2026-01-01 | 0000000 |")
    doc.write_text(f"# record\n\n{BEGIN}\n| instance | ... |\n|---|\n{city}\n{stale}\n{second}\n{END}\n")
    r = _bench("--archive", archive, "--only", "RANDOM-01", "--steps", 3, "--results", tmp_path / "fresh",
               "--plan-time-limit", 500, "--doc", doc)
    assert r.returncode == 0, r.stderr[-2000:]
    rows = [ln for ln in doc.read_text().splitlines() if ln.startswith("| ") and not ln.startswith("| instance")]
    assert [ln.split(" | ")[0] for ln in rows] == ["| RANDOM-01", "| RANDOM-02", "| CITY-01"], rows
    assert stale not in rows and "| 3 of 600 |" in rows[0] and rows[1:] == [second, city]
    cells = [c.strip() for c in rows[0].split("|")[1:-1]]
    mine = int(cells[3].replace(",", ""))
    # the peers' counts on record stay beside rce's new count, their ratios to it recomputed
    assert cells[6:10] == ["5", f"{mine / 5:.2f}", "1,000 (2)", f"{mine / 1000:.2f}"], cells


def test_a_run_of_the_peers_alone_fills_their_cells_in_rces_row_on_record(tmp_path):
    """``--peers-only``: the winner's code runs (a stand-in binary here, which writes the start-kit's
    counts), rce does not; its row on record keeps rce's count and takes the winner's, with their
    ratio. The other rows are left as they were."""
    archive, doc = _archive(tmp_path / "archive"), tmp_path / "record.md"
    entry = tmp_path / "bin" / "lifelong"
    entry.parent.mkdir()
    entry.write_text(f"""#!{sys.executable}
import json, sys
argv = sys.argv[1:]
json.dump({{"numTaskFinished": 40, "numEntryTimeouts": 0, "numPlannerErrors": 0, "numScheduleErrors": 0}},
          open(argv[argv.index("-o") + 1], "w"))
""")
    entry.chmod(0o755)
    first = ("| RANDOM-01 | 100 | 3 of 600 | 30 | 696 (RAPID) | 8.62 pro rata | not run | - | not run | - | 1 / 1 / 1 "
             "| 0 | - | 2026-11-28 | c89b4c1 |")
    second = "| RANDOM-02 | 200 | 600 | 1,083 | 1,260 (Kitty_Knight) | 0.86 | not run | - | 2026-11-28 | dac76bf |"
    doc.write_text(f"# record\n\n{BEGIN}\n| instance | ... |\n|---|\n{first}\n{second}\n{END}\n")
    r = _bench("--archive", archive, "--only", "RANDOM-01", "--steps", 3, "--results", tmp_path / "res",
               "--peers-only", "--winner", entry, "--plan-time-limit", 500, "--doc", doc)
    assert r.returncode == 0, r.stderr[-2000:]
    assert [p.name for p in (tmp_path / "res").glob("*.json")] == ["RANDOM-01.winner.3.json"]
    rows = [ln for ln in doc.read_text().splitlines() if ln.startswith("| R")]
    assert rows == [first.replace("| not run | - | not run |", "| 40 | 0.75 | not run |"), second]
    r = _bench("--archive", archive, "--only", "RANDOM-01", "--steps", 3, "--peers-only", "--doc", doc)
    assert r.returncode == 2 and "--peers-only: give --winner or --peer" in r.stderr


def test_the_winners_code_runs_with_its_authors_line_for_each_instance(tmp_path):
    """On GAME the 2024 winner's authors ran their code with 4,000 robots left without a task; the
    harness gives it that line there and nothing more elsewhere, unless ``--winner-args`` sets one
    line for all; the arguments given are kept in the result. A stand-in binary records its argv."""
    archive = _archive(tmp_path / "archive")
    base = archive / "2024 Competition" / "Main Round Evaluation Instances"
    shutil.copytree(base / "random.domain", base / "game.domain")
    (base / "game.domain" / "GAME.json").write_text((base / "random.domain" / "RANDOM-01.json").read_text())
    (base / "simulation_time.json").write_text(json.dumps({"RANDOM-01": 600, "RANDOM-02": 600, "GAME": 5000}))
    entry = tmp_path / "bin" / "lifelong"
    entry.parent.mkdir()
    entry.write_text(f"""#!{sys.executable}
import json, pathlib, sys
argv = sys.argv[1:]
stem = pathlib.Path(argv[argv.index("-i") + 1]).stem
json.dump(argv, open(pathlib.Path({str(tmp_path)!r}) / f"argv-{{stem}}.json", "w"))
json.dump({{"numTaskFinished": 5, "numEntryTimeouts": 0, "numPlannerErrors": 0, "numScheduleErrors": 0}},
          open(argv[argv.index("-o") + 1], "w"))
""")
    entry.chmod(0o755)
    doc = tmp_path / "record.md"
    doc.write_text(f"# record\n\n{BEGIN}\n| instance | ... |\n|---|\n{END}\n")
    common = ("--archive", archive, "--only", "RANDOM-01", "GAME", "--steps", 3, "--peers-only", "--winner", entry,
              "--winner-cwd", tmp_path, "--plan-time-limit", 500, "--doc", doc)
    r = _bench(*common, "--results", tmp_path / "own")
    assert r.returncode == 0, r.stderr[-2000:]
    own = ["--pa", "pepibt(4)_lns", "--gg", "enable", "--sa", "greedy"]
    tail = {stem: json.loads((tmp_path / f"argv-{stem}.json").read_text())[-8:] for stem in ("RANDOM-01", "GAME")}
    assert tail["GAME"] == own + ["--disable_agents", "4000"]
    assert tail["RANDOM-01"][-6:] == own and "--disable_agents" not in tail["RANDOM-01"]
    kept = json.loads((tmp_path / "own" / "GAME.winner.3.json").read_text())
    assert kept["args"] == own + ["--disable_agents", "4000"] and kept["tasks_finished"] == 5

    r = _bench(*common, "--results", tmp_path / "set", "--winner-args", "--pa 'epibt(4)'")
    assert r.returncode == 0, r.stderr[-2000:]
    for stem in ("RANDOM-01", "GAME"):
        assert json.loads((tmp_path / f"argv-{stem}.json").read_text())[-2:] == ["--pa", "epibt(4)"]
    assert json.loads((tmp_path / "set" / "GAME.winner.3.json").read_text())["args"] == ["--pa", "epibt(4)"]


def test_the_rate_is_counted_in_whole_windows_and_the_worst_is_named():
    curve = [k // 2 for k in range(1, 1201)]           # a task every second step, then none from step 1,000
    curve[1000:] = [curve[999]] * 200
    assert window_rates(curve, 500) == [250, 250]        # the last part window (steps 1,000 - 1,200) left out
    slow = [min(k, 500) + max(0, k - 500) // 2 for k in range(1, 1501)]     # 1 a step, then 1 in 2
    assert window_rates(slow, 500) == [500, 250, 250]
    assert steadiness({"curve": slow}) == "0.50 (worst: steps 500-1,000)"
    assert steadiness({"curve": slow[:999]}) == "-" and steadiness({}) == "-"     # under two whole windows


def test_the_plot_draws_each_instance_with_an_rce_result(tmp_path):
    slow = [min(k, 500) + max(0, k - 500) // 2 for k in range(1, 1001)]
    got = {("RANDOM-04", "rce"): {"curve": slow, "tasks_finished": slow[-1]},
           ("RANDOM-04", "default"): {"curve": [k // 4 for k in range(1, 1001)], "tasks_finished": 250},
           ("RANDOM-04", "winner"): {"tasks_finished": 900},                   # no curve: not drawn, no error
           ("RANDOM-05", "default"): {"curve": slow, "tasks_finished": slow[-1]}}     # no rce result: left out
    todo = [("RANDOM-04", Path("RANDOM-04.json"), 1000), ("RANDOM-05", Path("RANDOM-05.json"), 2000)]
    png = tmp_path / "img" / "round.png"
    assert plot_round(todo, got, png) == ["RANDOM-04"]
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert plot_round(todo[1:], got, tmp_path / "none.png") == [] and not (tmp_path / "none.png").exists()


def test_a_start_kit_outputs_events_give_the_tasks_finished_by_each_step():
    problem = load_problem(RANDOM / "random_32_32_20_100.json")
    res = run_lifelong(problem, 40, plan_time_limit_ms=300, record=True)
    out = res.sim.output()           # the start-kit's format, events and tasks included
    assert res.finished[-1] > 0
    assert finished_curve(out, 40) == res.finished.tolist()
    assert finished_curve({**out, "events": []}, 40) is None                         # written with -c 3
    assert finished_curve({**out, "numTaskFinished": out["numTaskFinished"] + 1}, 40) is None     # not adding up
    # an output without its tasks (the 2024 winner's code): each task's errands from the problem's task file
    bare = {k: v for k, v in out.items() if k != "tasks"}
    assert finished_curve(bare, 40) is None
    assert finished_curve(bare, 40, [len(t) for t in problem.tasks]) == res.finished.tolist()
    assert finished_curve(bare, 40, [len(t) + 1 for t in problem.tasks]) is None           # errands that do not match


def test_a_peer_gets_the_rules_preprocessing_time(tmp_path):
    """The start-kit's own default gives an entry 30 s to preprocess; the rules give 30 minutes per
    map, and the harness asks for them. A stand-in for the entry's binary writes what it was given
    and the smallest output the start-kit writes."""
    entry = tmp_path / "lifelong"
    entry.write_text(f"""#!{sys.executable}
import json, sys
argv = sys.argv[1:]
json.dump(argv, open({str(tmp_path / "argv.json")!r}, "w"))
json.dump({{"numTaskFinished": 4, "numEntryTimeouts": 0, "numPlannerErrors": 0, "numScheduleErrors": 0}},
          open(argv[argv.index("-o") + 1], "w"))
""")
    entry.chmod(0o755)
    got = run_peer(entry, RANDOM / "random_32_32_20_100.json", 7, 1000, extra=("--pa", "x"))
    assert (got["tasks_finished"], got["timeouts"]) == (4, 0)
    argv = json.loads((tmp_path / "argv.json").read_text())
    assert argv[argv.index("-p") + 1] == str(PREPROCESS_MS) == "1800000"
    assert (argv[argv.index("-s") + 1], argv[argv.index("-t") + 1], argv[-2:]) == ("7", "1000", ["--pa", "x"])


def test_a_peer_whose_output_leaves_its_events_out_gets_its_curve_from_its_log(tmp_path):
    """The 2024 winner's code writes no events; the start-kit's log names each finish with its step.
    The curve is read from there, and left out when the log's finishes do not add up to the count."""
    entry = tmp_path / "lifelong"

    def stand_in(finished: int) -> None:
        entry.write_text(f"""#!{sys.executable}
import json, sys
argv = sys.argv[1:]
with open(argv[argv.index("-l") + 1], "w") as log:
    log.write("[2026-11-30 05:00:00.1]: *info* [timestep=0] Preprocessing success\\n")
    for step, agent, task in ((2, 5, 11), (2, 6, 12), (4, 5, 13), (9, 1, 14)):
        log.write(f"[2026-11-30 05:00:01.2]: *info* [timestep={{step}}] Agent {{agent}} finishes task {{task}}\\n")
json.dump({{"numTaskFinished": {finished}, "numEntryTimeouts": 0, "numPlannerErrors": 0, "numScheduleErrors": 0,
           "events": []}}, open(argv[argv.index("-o") + 1], "w"))
""")
        entry.chmod(0o755)

    stand_in(3)           # the finish at step 9 is past the 5 steps run; the other three add up
    got = run_peer(entry, RANDOM / "random_32_32_20_100.json", 5, 1000, curve=True)
    assert got["tasks_finished"] == 3 and got["curve"] == [0, 2, 2, 3, 3]
    stand_in(4)           # the count says 4, the log's steps hold 3: no curve rather than a wrong one
    got = run_peer(entry, RANDOM / "random_32_32_20_100.json", 5, 1000, curve=True)
    assert got["tasks_finished"] == 4 and "curve" not in got


def test_main_round_names_what_is_missing(tmp_path):
    r = _bench("--archive", tmp_path, "--steps", 3)
    assert r.returncode == 2 and f"{tmp_path}: no simulation_time.json of the 2024 main round" in r.stderr
    r = _bench("--archive", _archive(tmp_path), "--only", "RANDOM-06", "--steps", 3)
    assert r.returncode == 2 and "--only RANDOM-06: not a 2024 main-round instance" in r.stderr
    r = _bench("--archive", tmp_path, "--only", "RANDOM-03", "--steps", 3)
    assert r.returncode == 2 and "random.domain/RANDOM-03.json: missing" in r.stderr


def test_a_peers_peak_memory_is_measured_and_named_when_it_is_killed(tmp_path):
    """The peers that do not fit this machine are killed out of memory: the harness reads each run's
    peak resident memory (its own address space's high-water mark) and gives it with the counts, or
    in the error of a run killed with SIGKILL. A stand-in entry writes to 256 MiB, logs its first
    step, and holds the memory until the harness has looked at it again after reporting that step."""
    entry, go = tmp_path / "lifelong", tmp_path / "go"

    def stand_in(then: str) -> None:
        go.unlink(missing_ok=True)
        entry.write_text(f"""#!{sys.executable}
import json, os, sys, time
argv = sys.argv[1:]
held = b"x" * (256 << 20)
with open(argv[argv.index("-l") + 1], "w") as log:
    log.write("[2026-11-30 05:00:00.1]: *info* [timestep=0] planner returns\\n")
while not os.path.exists({str(go)!r}):
    time.sleep(0.01)
json.dump({{"numTaskFinished": 2, "numEntryTimeouts": 0, "numPlannerErrors": 0, "numScheduleErrors": 0}},
          open(argv[argv.index("-o") + 1], "w"))
{then}
""")
        entry.chmod(0o755)

    reports: list[int] = []

    def progress(step: int) -> None:    # the second report of step 0 done: the memory was read between the two
        reports.append(step)
        if reports.count(1) >= 2:
            go.touch()

    stand_in("")
    got = run_peer(entry, RANDOM / "random_32_32_20_100.json", 5, 1000, progress=progress)
    assert got["tasks_finished"] == 2 and 256 <= got["peak_rss_mib"] < 256 + 64, got
    reports.clear()
    stand_in("os.kill(os.getpid(), 9)")
    with pytest.raises(RuntimeError, match=r"killed \(out of memory\?\) .* peak resident memory 0\.[23] GiB"):
        run_peer(entry, RANDOM / "random_32_32_20_100.json", 5, 1000, progress=progress)
