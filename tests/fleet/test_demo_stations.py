"""The warehouse demo's work, sans-I/O: paired stations (workstations all over the map, each drop-off
3 steps from its pick-up, off the chargers' rows), the task stream's drop-off nearest each pick-up and the
backlog of tasks waiting at the start; the default stream stays the one the offline prediction replays."""
from __future__ import annotations

from collections import deque

from rce_fleet.live.task_stream import TaskStream
from rce_fleet.maps.geometry import GridGeometry
from rce_fleet.maps.grid import fleet_grid
from rce_fleet.maps.occupancy import load_map
from rce_fleet.operations.places import PAIR_STEPS, generate_places

from .test_nodes import SHARED


def _warehouse() -> GridGeometry:
    grid, _ = fleet_grid(load_map(SHARED / "warehouse.yaml"), None, None)
    return GridGeometry.from_cellgrid(grid)


def _steps(geo: GridGeometry, a: int, b: int) -> int:
    seen, todo = {a: 0}, deque([a])
    while todo:
        c = todo.popleft()
        for n in geo.neighbours(c):
            if geo.is_free(n) and n not in seen:
                seen[n] = seen[c] + 1
                todo.append(n)
    return seen[b]


def test_paired_stations_put_each_drop_off_beside_its_pick_up_all_over_the_map():
    geo = _warehouse()
    places = generate_places(geo, 12, paired=True)
    picks, drops = places.of_kind("pickup"), places.of_kind("dropoff")
    assert len(picks) == len(drops) == 6
    for p, d in zip(picks, drops, strict=True):
        assert 1 <= _steps(geo, p.cell, d.cell) <= PAIR_STEPS, (p, d)
    charger_rows = {geo.rc(c)[0] for c in places.cells("charger")}
    assert all(geo.rc(q.cell)[0] > max(charger_rows) + 1 for q in picks + drops)
    cols = [geo.rc(p.cell)[1] for p in picks]
    assert min(cols) < geo.cols / 3 and max(cols) > 2 * geo.cols / 3      # not in one third: all over
    stream = TaskStream(places, 6.0, 1, backlog=12, nearest_drop=True).times_and_errands(120)
    assert [t for t, _ in stream[:12]] == [0.0] * 12 and all(t > 0 for t, _ in stream[12:])
    pair = {p.name: d.name for p, d in zip(picks, drops, strict=True)}
    assert all(errands[1] == pair[errands[0]] for _, errands in stream), stream


def test_the_default_stream_is_unchanged():
    """The stream of split stations and random drop-offs, as bench/fleet_live.py replays it (the numbers of
    its docs were measured on it)."""
    geo = _warehouse()
    stream = TaskStream(generate_places(geo, 12), 6.0, 1).times_and_errands(60)
    assert [(round(t, 2), e) for t, e in stream[:3]] == [(1.44, ["pick1", "drop3"]), (2.7, ["pick4", "drop4"]),
                                                          (13.24, ["pick2", "drop1"])], stream[:3]
    assert len(stream) == 11
