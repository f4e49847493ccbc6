"""The lacam3 peer of ``bench/planner.py``: the instance it hands lacam3 is the one rce plans
(read back by rce's own MovingAI loader, cell for cell), and a missing binary is refused
before any planning."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rce_fleet.planning import load_movingai_map, load_movingai_scen

BENCH = Path(__file__).resolve().parents[2] / "bench"
sys.path.insert(0, str(BENCH))
from lacam3_peer import _write_instance, run_lacam3  # noqa: E402


def test_the_written_map_and_scenario_are_the_instance(tmp_path):
    rng = np.random.default_rng(3)
    free = rng.random((7, 11)) > 0.25
    cells = np.flatnonzero(free.ravel())
    agents = list(zip(rng.choice(cells, 5, replace=False).tolist(), rng.choice(cells, 5, replace=False).tolist(),
                      strict=True))
    m, s = _write_instance(tmp_path, free, agents, [1, 2, 3, 4, 5])
    graph = load_movingai_map(m)
    assert graph.free.shape == (7, 11) and (graph.free == free).all()
    assert load_movingai_scen(s, graph) == agents
    assert [int(ln.split("\t")[8]) for ln in s.read_text().splitlines()[1:]] == [1, 2, 3, 4, 5]


def test_a_missing_binary_is_refused(tmp_path):
    with pytest.raises(FileNotFoundError, match="lacam3 binary not found"):
        run_lacam3(tmp_path / "main", np.ones((2, 2), bool), [(0, 3)], [2], 1.0)
    r = subprocess.run([sys.executable, str(BENCH / "planner.py"), "--lacam3", str(tmp_path / "main"),
                        "--json", str(tmp_path / "p.json"), "--plot", str(tmp_path / "p.png")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.strip() == f"bench/planner.py: lacam3 binary not found: {tmp_path / 'main'}"
