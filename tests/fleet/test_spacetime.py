"""rce_fleet.lifelong.spacetime: the reservation table's bit rows and parked goals, a group
re-planned and kept or rolled back in one compiled call, and the safe-interval search's state
table (the searches' arrivals against each other: test_lifelong_planner.py)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rce_fleet.lifelong import DistanceCache, LifelongGrid
from rce_fleet.lifelong.kernels import UNREACHABLE, heap_pop, heap_push
from rce_fleet.lifelong.refine import _arrivals, warm_up
from rce_fleet.lifelong.spacetime import SpaceTimeTable, _last_taken, _next_step, _sipp


def grid(rows: list[str]) -> LifelongGrid:
    return LifelongGrid(np.array([[ch == "." for ch in r] for r in rows]))


def assert_table(res: SpaceTimeTable, goals: np.ndarray, placed) -> None:
    """``occ`` holds exactly the placed agents' paths up to their arrivals, ``bits`` is
    ``occ >= 0`` bit by bit, ``park`` each placed agent's arrival on its goal (H elsewhere),
    and no two placed agents share a cell at a step or exchange cells."""
    occ = np.full_like(res.occ, -1)
    park = np.full_like(res.park, res.H)
    for a in placed:
        p, L = res.paths[a], res.lengths[a]
        assert (occ[p[:L], np.arange(L)] == -1).all(), "vertex"
        occ[p[:L], np.arange(L)] = a
        park[goals[a]] = L - 1
        assert p[L - 1] == goals[a]
    for a in placed:
        p, L = res.paths[a], res.lengths[a]
        for t in range(1, L):
            j = occ[p[t], t - 1]
            assert j < 0 or j == a or occ[p[t - 1], t] != j, "swap"
        later = occ[goals[a], L:]
        assert (later == -1).all(), "a goal passed over after its agent parked"
    assert (res.occ == occ).all() and (res.park == park).all()
    taken = np.zeros(res.bits.shape[1] * 64, dtype=bool)
    for c in range(res.occ.shape[0]):
        taken[:] = False
        taken[: res.H] = occ[c] >= 0
        words = np.packbits(taken.reshape(-1, 64)[:, ::-1], axis=1).view(">u8")[:, 0]
        assert (res.bits[c] == words).all(), f"bits of cell {c}"


def test_bit_rows_find_the_next_free_and_taken_step_as_a_scan_does():
    rng = np.random.default_rng(0)
    H = 200                                      # four words, the last one partly used
    for density in (0.05, 0.5, 0.95):
        taken = rng.random((3, H)) < density
        taken[2] = False                         # a row with nothing taken
        bits = np.zeros((3, 4), dtype=np.uint64)
        for c, t in zip(*np.nonzero(taken), strict=True):
            bits[c, t >> 6] |= np.uint64(1) << np.uint64(t & 63)
        for c in range(3):
            last = np.flatnonzero(taken[c])
            assert _last_taken(bits, c) == (last[-1] if len(last) else -1)
            for t in range(H + 1):
                for lim in (t, min(t + 1, H), min(t + 70, H), H):
                    for want in (True, False):
                        hit = np.flatnonzero(taken[c, t:lim] == want)
                        assert _next_step(bits, c, t, lim, want) == (t + hit[0] if len(hit) else lim)


def test_the_heap_pops_keys_in_order_with_their_values_through_pushes_and_pops_mixed():
    rng = np.random.default_rng(1)
    hk, hv = np.zeros(4096, np.int64), np.zeros(4096, np.int64)
    size, held, popped = 0, [], []
    for _ in range(6000):
        if size and rng.random() < 0.45:
            key, val, size = heap_pop(hk, hv, size)
            popped.append((key, val))
            assert key == min(k for k, _ in held)
            held.remove((key, val))
        else:
            key = int(rng.integers(0, 50))          # many equal keys
            size = heap_push(hk, hv, size, key, len(popped) * 10_000 + size)
            held.append((key, len(popped) * 10_000 + size - 1))
    while size:
        key, val, size = heap_pop(hk, hv, size)
        popped.append((key, val))
        held.remove((key, val))
    assert not held and len(popped) > 3000


def test_a_group_replan_in_one_call_is_kept_only_when_not_worse_and_rolls_back_exactly():
    warm_up()
    g = grid([".....", "@@.@@"])                 # a corridor with one bay below its middle
    cache = DistanceCache(g)
    starts, goals = np.array([0, 7]), np.array([4, 2])
    hrow = np.array([cache.slot(int(x)) for x in goals])
    for sipp in (False, True):
        res = SpaceTimeTable(2, g.n_cells, 12, 4)
        assert res.plan(g.nbr, cache.table, hrow, starts, goals, [0, 1], 10_000, sipp) == 2
        assert_table(res, goals, [0, 1])
        before = [a.copy() for a in (res.occ, res.bits, res.park, res.paths, res.lengths)]
        # agent 1 first: it parks on 2 at step 1 and agent 0 can no longer cross: rolled back
        assert not res.replan(g.nbr, cache.table, hrow, starts, goals, np.array([1, 0]), 10_000, sipp)
        for old, now in zip(before, (res.occ, res.bits, res.park, res.paths, res.lengths), strict=True):
            assert (old == now).all()
        # the same order again: the same sum, kept
        assert res.replan(g.nbr, cache.table, hrow, starts, goals, np.array([0, 1]), 10_000, sipp)
        assert res.lengths.sum() == before[4].sum()
        assert_table(res, goals, [0, 1])


def test_group_replans_on_a_crowded_solution_keep_it_conflict_free_and_never_worse():
    """Random groups of a crowded LaCAM solution re-planned by both searches, some with an
    expansion cap so small that searches fail: each call keeps a sum of costs not higher or
    restores the table exactly, and the table stays a valid solution throughout."""
    from rce_fleet.lifelong.lacam import solve_lacam
    warm_up()
    rng = np.random.default_rng(7)
    g = LifelongGrid(rng.random((12, 12)) > 0.2)
    cache = DistanceCache(g)
    cells = np.flatnonzero(g.flat)
    reach = cache.from_source(int(cells[0]))
    pick = rng.choice(cells[reach[cells] < UNREACHABLE], 60, replace=False)
    starts, goals = pick[:30].astype(np.int64), pick[30:].astype(np.int64)
    sol = solve_lacam(g, starts, goals, time_limit_s=30)
    assert sol["solved"]
    hrow = np.array([cache.slot(int(x)) for x in goals])
    res = SpaceTimeTable(30, g.n_cells, sol["paths"].shape[0] + 16, int(cache.table[hrow, starts].max()) + 1)
    res.paths[:, : sol["paths"].shape[0]] = sol["paths"].T
    res.lengths[:] = _arrivals(sol["paths"], goals) + 1
    res.place(goals, np.arange(30))
    assert_table(res, goals, range(30))
    kept = rolled = 0
    for i in range(120):
        group = rng.choice(30, size=int(rng.integers(1, 7)), replace=False).astype(np.int64)
        sipp, cap = bool(i % 2), (5, 10 ** 6)[i % 3 > 0]
        before = [a.copy() for a in (res.occ, res.bits, res.park, res.paths, res.lengths)]
        if res.replan(g.nbr, cache.table, hrow, starts, goals, group, cap, sipp):
            kept += 1
            assert res.lengths.sum() <= before[4].sum()
            assert (res.paths[group, 0] == starts[group]).all()
            assert_table(res, goals, range(30))
        else:
            rolled += 1
            for old, now in zip(before, (res.occ, res.bits, res.park, res.paths, res.lengths), strict=True):
                assert (old == now).all()
    assert kept and rolled
    assert res.lengths.sum() < (_arrivals(sol["paths"], goals) + 1).sum()


def test_the_safe_interval_search_gives_up_when_its_state_table_is_half_full():
    warm_up()
    g = grid(["........"] * 8)
    cache = DistanceCache(g)
    res = SpaceTimeTable(1, g.n_cells, 40, 14)
    h = cache.table[cache.slot(63)]
    stats = np.zeros(1, dtype=np.int64)
    hk, hv = np.zeros(4096, np.int64), np.zeros(4096, np.int64)
    out = np.zeros(40, dtype=np.int64)
    args = (g.nbr, h, 0, 63, res.occ, res.bits, res.park, 0, 39)
    assert _sipp(*args, np.zeros((8, 4), np.int32), 1, hk, hv, 10 ** 6, out, stats) == 0     # 4 states only
    assert _sipp(*args, np.zeros((256, 4), np.int32), 1, hk, hv, 10 ** 6, out, stats) == 15
    assert out[0] == 0 and out[14] == 63
    with pytest.raises(ValueError, match="2 \\*\\* 31"):
        SpaceTimeTable(1, 2 ** 20, 2 ** 11, 1)


def test_the_lns_bench_reports_the_replan_cost_and_the_parallel_efficiency(tmp_path):
    """``bench/lns_parallel.py`` end to end on a small instance: its numbers and plot."""
    bench = Path(__file__).resolve().parents[2] / "bench" / "lns_parallel.py"
    out, png = tmp_path / "lns.json", tmp_path / "lns.png"
    p = subprocess.run([sys.executable, str(bench), "--agents", "60", "--budget", "0.2", "--seeds", "0",
                        "--iterations", "40", "--json", str(out), "--plot", str(png)],
                       capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert p.returncode == 0, (p.stdout + p.stderr)[-3000:]
    res = json.loads(out.read_text())
    assert res["agents"] == 60 and res["first_ratio"] >= 1.0
    assert res["replan"]["iterations"] == 40 and res["replan"]["expanded"] > 0
    run = res["parallel"][0]
    for key in ("one", "two", "one_double"):
        assert 1.0 <= run[key]["ratio"] <= res["first_ratio"]
    assert run["two"]["worker_cpu_s"] > 0
    assert png.stat().st_size > 1000 and "efficiency" in p.stdout


def test_the_lns_bench_on_the_clock_of_work_gives_the_same_result_in_every_run(tmp_path):
    """``bench/lns.py --clock work``: the budget counts states expanded and iterations, not
    CPU, so two runs of one variant and seed end at the same sum of costs, conflict-free and
    never above the first solution."""
    bench = Path(__file__).resolve().parents[2] / "bench" / "lns.py"
    runs = []
    for k in range(2):
        out, png = tmp_path / f"lns{k}.json", tmp_path / f"lns{k}.png"
        p = subprocess.run([sys.executable, str(bench), "--agents", "200", "--scen-seeds", "--seeds", "0",
                            "--cpu", "0.3", "--checkpoints", "0.1", "0.3", "--clock", "work",
                            "--json", str(out), "--plot", str(png)],
                           capture_output=True, text=True, timeout=300, cwd=tmp_path)
        assert p.returncode == 0, (p.stdout + p.stderr)[-3000:]
        res = json.loads(out.read_text())
        assert res["clock"] == "work" and png.stat().st_size > 1000
        runs.append(res["rows"])
    assert [r["variant"] for r in runs[0]] == ["default", "capped"]
    for a, b in zip(*runs, strict=True):
        assert a["conflicts"] == 0 and a["at_goal"]
        assert 1.0 <= a["ratio"]["0.3"] <= a["ratio"]["0.1"] <= a["first_ratio"]
        assert a["ratio"] == b["ratio"] and a["iterations"] == b["iterations"]
