"""rce_fleet.maps.grid: cutting maps into the planner's cell grid."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rce_fleet.maps.grid import make_grid
from rce_fleet.maps.lab_map import lab_map, write_lab_map
from rce_fleet.maps.occupancy import OccupancyMap, load_map

MAPS = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "maps"


def open_room(h_px=40, w_px=60, res=0.05, origin=(0.0, 0.0, 0.0)) -> OccupancyMap:
    return OccupancyMap(np.zeros((h_px, w_px), dtype=np.int8), res, origin)


def test_row_major_numbering_from_top_left():
    m = open_room()                       # 3 m wide, 2 m high
    g = make_grid(m, rows_cols=(2, 3))     # 1 m cells
    assert (g.rows, g.cols, g.cell_w_m, g.cell_h_m) == (2, 3, 1.0, 1.0)
    assert g.cell_of(0.5, 1.5) == 0       # top-left
    assert g.cell_of(2.5, 1.5) == 2       # top-right
    assert g.cell_of(0.5, 0.5) == 3       # bottom-left (row 1)
    assert g.cell_of(2.9, 0.1) == 5
    assert g.center(0) == (0.5, 1.5) and g.center(5) == (2.5, 0.5)
    assert g.rc(4) == (1, 1) and g.cell(1, 1) == 4
    assert g.cell_of(-0.1, 0.5) is None and g.cell_of(0.5, 2.01) is None
    with pytest.raises(IndexError):
        g.rc(6)


def test_center_cell_of_round_trip_with_offset_origin():
    g = make_grid(open_room(80, 120, origin=(-3.0, 7.0, 0.3)), cell_m=0.5)
    assert (g.rows, g.cols) == (8, 12)
    for cell in range(g.n_cells):
        assert g.cell_of(*g.center(cell)) == cell


def test_neighbours_are_4_connected_free_cells():
    g = make_grid(open_room(), rows_cols=(2, 3))
    assert g.free.all()
    assert sorted(g.neighbours(0)) == [1, 3]
    assert sorted(g.neighbours(4)) == [1, 3, 5]


def test_free_fraction_threshold_and_robot_fit():
    occ = np.zeros((40, 40), dtype=np.int8)      # 2 m x 2 m, 2x2 cells of 1 m
    occ[0:10, 0:20] = 100                        # cell 0: 50 % occupied
    occ[29:31, 29:31] = 100                      # cell 3: tiny post right at the centre
    g = make_grid(OccupancyMap(occ, 0.05), rows_cols=(2, 2))
    assert g.free_fraction[0, 0] == pytest.approx(0.5)
    assert g.free_fraction[1, 1] == pytest.approx(0.99)
    assert g.free.tolist() == [[False, True], [True, False]]   # 3: the robot does not fit at its centre
    g2 = make_grid(OccupancyMap(occ, 0.05), rows_cols=(2, 2), free_fraction=0.4, robot_radius=0.0, margin=0.0)
    assert g2.free[0, 0]


def test_wall_on_cell_border_cuts_the_connection():
    occ = np.zeros((40, 40), dtype=np.int8)
    occ[19:21, :] = 100                           # 0.1 m wall along the row border ...
    occ[19:21, 22:38] = 0                         # ... with a 0.8 m door in the right column
    g = make_grid(OccupancyMap(occ, 0.05), rows_cols=(2, 2))
    assert g.free.all()
    assert 2 not in g.neighbours(0)               # wall
    assert 3 in g.neighbours(1)                   # door
    assert g.connected(1, 3) and not g.connected(0, 2)


def test_unknown_handling_and_cell_too_small():
    occ = np.full((40, 40), -1, dtype=np.int8)
    occ[:, :20] = 0
    m = OccupancyMap(occ, 0.05)
    assert make_grid(m, rows_cols=(1, 2), crop=False).free.tolist() == [[True, False]]
    assert make_grid(m, rows_cols=(1, 2), crop=False, unknown_is_occupied=False).free.tolist() == [[True, True]]
    # crop=True cuts the known part only
    g = make_grid(m, rows_cols=(1, 2))
    assert g.cell_w_m == pytest.approx(0.5) and g.free.all()
    with pytest.raises(ValueError, match="footprint"):
        make_grid(m, rows_cols=(20, 20), crop=False)
    with pytest.raises(ValueError, match="not both"):
        make_grid(m, rows_cols=(2, 2), cell_m=1.0)


def test_cell_m_grid_partial_last_column_is_not_free():
    g = make_grid(open_room(40, 50), cell_m=1.0)   # 2.5 m wide -> 3 columns, last half outside
    assert (g.rows, g.cols) == (2, 3)
    assert g.free[:, :2].all() and not g.free[:, 2].any()


def test_lab_map_default_grid(tmp_path):
    m = load_map(write_lab_map(tmp_path))
    assert m.occupancy.shape == (160, 160) and m.resolution == 0.05
    assert np.array_equal(m.occupancy, lab_map().occupancy)
    g = make_grid(m)
    assert (g.rows, g.cols) == (8, 8) and g.cell_w_m == pytest.approx(1.0)
    occupied = {c for c in range(64) if not g.free.ravel()[c]}
    assert occupied == {14, 29, 42, 45, 50, 53}
    assert g.is_free(26)
    assert 18 not in g.neighbours(26) and 27 in g.neighbours(19)    # partition, door at column 3
    # every free cell is reachable from every other
    seen, todo = {0}, [0]
    while todo:
        for n in g.neighbours(todo.pop()):
            if n not in seen:
                seen.add(n)
                todo.append(n)
    assert seen == set(g.free_cells())


def test_turtlebot3_world_8x8():
    g = make_grid(load_map(MAPS / "turtlebot3_world.yaml"))
    assert (g.rows, g.cols) == (8, 8)
    assert g.cell_w_m == pytest.approx(113 * 0.05 / 8) and g.cell_h_m == pytest.approx(104 * 0.05 / 8)
    assert g.free_cells() == [3, 4, 10, 11, 12, 13, 14, 17, 19, 22, 25, 26, 27, 28, 29, 30, 33, 34, 35, 36,
                              37, 38, 41, 43, 46, 50, 51, 52, 53, 54, 59, 60]
    assert g.is_free(26) and sorted(g.neighbours(26)) == [25, 27]
    for cell in range(64):
        assert g.cell_of(*g.center(cell)) == cell
    # the arena's centre (world 0, 0 is inside it) falls in a middle cell
    assert g.cell_of(-0.5, 0.0) in (27, 35)


def test_warehouse_1m_cells():
    g = make_grid(load_map(MAPS / "warehouse.yaml"), cell_m=1.0)
    assert (g.rows, g.cols) == (51, 31)
    assert 1100 < g.free.sum() < 1300
    assert g.cell_of(*g.center(g.free_cells()[0])) == g.free_cells()[0]
    # one connected component holds nearly all free cells
    start = g.free_cells()[len(g.free_cells()) // 2]
    seen, todo = {start}, [start]
    while todo:
        for n in g.neighbours(todo.pop()):
            if n not in seen:
                seen.add(n)
                todo.append(n)
    assert len(seen) > 0.95 * g.free.sum()
