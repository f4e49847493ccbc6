"""bench/profile_threads.py: a py-spy raw profile (``--threads``) read into each thread's busy share
by module, drawn as a PNG; a line that is not py-spy's raw form is named."""
from __future__ import annotations

import json
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[2] / "bench"
sys.path.insert(0, str(BENCH))
from profile_threads import busy_shares, main  # noqa: E402

RAW = """thread (10): MainThread;<module> (run.py:3);plan (pibt.py:10);anneal (epibt.py:40) 50
thread (10): MainThread;<module> (run.py:3);plan (pibt.py:10);update (flow.py:9);_plan (flow.py:20) 30
thread (10): MainThread;<module> (run.py:3);step (simulator.py:5) 10
thread (11): guide-paths_0;worker (flow.py:30);_plan (flow.py:20) 40
thread (12): epibt-lns_0;anneal (epibt.py:40) 25
"""


def test_each_threads_busy_share_goes_to_the_deepest_listed_module():
    s = busy_shares(RAW, rate=10, seconds=10, modules=["epibt.py", "flow.py"])
    assert s == {"MainThread": {"epibt.py": 0.5, "flow.py": 0.3, "other": 0.1}, "guide-paths_0": {"flow.py": 0.4},
                 "epibt-lns_0": {"epibt.py": 0.25}}


def test_the_picture_and_json_are_written_and_a_bad_line_named(tmp_path, capsys):
    raw, png = tmp_path / "p.txt", tmp_path / "t.png"
    raw.write_text(RAW)
    args = [str(raw), "--rate", "10", "--seconds", "10", "--out", str(png), "--modules"]
    assert main([*args, "epibt.py", "flow.py"]) == 0
    assert json.loads(png.with_suffix(".json").read_text())["MainThread"]["other"] == 0.1
    assert png.stat().st_size > 5_000 and "MainThread: busy 90 %" in capsys.readouterr().out
    raw.write_text(RAW + "no count here\n")
    assert main([*args, "flow.py"]) == 2
    assert "line 6: not 'stack count'" in capsys.readouterr().err
