"""``rce-fleet grid``: the cell numbers of the very grid ``rce-fleet demo`` and ``serve`` drive on
(so a ``--goal RobotN=CELL`` read off it means the same cell), and a map or grid it cannot use
named on stderr with exit 2."""
from __future__ import annotations

from pathlib import Path

import pytest

from rce_fleet.cli import main
from rce_fleet.maps.grid import fleet_grid
from rce_fleet.maps.occupancy import load_map

ROOT = Path(__file__).resolve().parents[2]
WAREHOUSE = ROOT / ".." / "shared" / "data" / "maps" / "warehouse.yaml"


def _grid(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(["grid", *argv])
    cap = capsys.readouterr()
    return e.value.code, cap.out, cap.err


def test_grid_prints_the_grid_the_demo_drives_on(capsys):
    code, out, _ = _grid(["--map", str(WAREHOUSE)], capsys)
    assert code == 0
    grid, note = fleet_grid(load_map(WAREHOUSE))      # what the demo's Fleet cuts the map into
    assert (grid.rows, grid.cols) == (42, 26) and note.startswith("grid: 42x26 cells of 1.2 m")
    assert note in out and "42x26 cells of 1.200 x 1.200 m, 801 free" in out
    assert grid.ascii() in out
    code, out, _ = _grid(["--map", str(WAREHOUSE), "--grid", "8x8"], capsys)
    assert code == 0 and out.startswith("8x8 cells of ")        # asked for: no note


def test_grid_names_a_missing_map_and_a_grid_that_does_not_fit(tmp_path, capsys):
    missing = tmp_path / "none.yaml"
    code, out, err = _grid(["--map", str(missing)], capsys)
    assert code == 2 and out == ""
    assert err.startswith(f"rce-fleet grid: --map: {missing}: cannot read map YAML")
    code, out, err = _grid(["--grid", "500x500"], capsys)
    assert code == 2 and out == ""
    assert err.startswith("rce-fleet grid: --grid/--cell: cells of ") and "smaller than the robot footprint" in err
