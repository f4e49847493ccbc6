"""rce_fleet.lifelong.flow: traffic-flow guide paths (contraflow avoided, flow kept consistent
as paths are planned again) and the path rows PIBT follows."""
from __future__ import annotations

import time

import numpy as np

from rce_fleet.lifelong import DistanceCache, LifelongGrid
from rce_fleet.lifelong.flow import TrafficFlow, warm_up
from rce_fleet.lifelong.kernels import UNREACHABLE

# two corridors between an open west and an open east column: row 1 and row 3
TWO_WAYS = [".......",
            ".......",
            ".@@@@@.",
            ".......",
            "......."]


def grid(rows: list[str]) -> LifelongGrid:
    return LifelongGrid(np.array([[ch == "." for ch in r] for r in rows]))


def cell(g: LifelongGrid, r: int, c: int) -> int:
    return r * g.cols + c


def flow_from_paths(g: LifelongGrid, paths) -> np.ndarray:
    out = np.zeros((g.n_cells, 4), dtype=np.int64)
    for p in paths:
        if p is None:
            continue
        for u, v in zip(p[:-1], p[1:], strict=True):
            out[u, list(g.nbr[u]).index(v)] += 1
    return out


def test_a_robot_goes_round_against_a_stream_and_with_one_it_joins():
    warm_up()
    g = grid(["...",
              ".@.",
              "..."])
    cache = DistanceCache(g, max_bytes=2 * g.n_cells * 9)
    tf = TrafficFlow(g, cache, 5, threads=1)          # in order: each path sees those before it
    west, east = cell(g, 0, 0), cell(g, 0, 2)
    # three robots stream east along the top row; one goes west against them, one east with them
    pos = np.array([west, west, west, east, west], dtype=np.int64)
    goals = np.array([east, east, east, west, east], dtype=np.int64)
    slot = cache.slots(goals)
    far = time.perf_counter() + 60
    rows = tf.update(pos, goals, slot, far)
    assert rows.tolist() == [0, 1, 2, 3, 4] and tf.guided.all()
    assert [tf.paths[a].tolist() for a in range(3)] == [[0, 1, 2]] * 3
    # 2 steps + contraflow 3 a move + vertex flow 1 a cell (10) against 6 round the bottom
    assert tf.paths[3].tolist() == [2, 5, 8, 7, 6, 3, 0]
    # with the stream only the vertex flow in the middle counts: 2 + 1 < 6
    assert tf.paths[4].tolist() == [0, 1, 2]
    assert (tf.flow == flow_from_paths(g, tf.paths)).all()


def test_path_rows_fall_along_the_path_and_rise_off_it():
    g = grid(TWO_WAYS)
    cache = DistanceCache(g, max_bytes=2 * g.n_cells * 4)
    tf = TrafficFlow(g, cache, 1)
    pos = np.array([cell(g, 1, 0)], dtype=np.int64)
    goals = np.array([cell(g, 1, 6)], dtype=np.int64)
    tf.update(pos, goals, cache.slots(goals), time.perf_counter() + 60)
    p, row = tf.paths[0], tf.table[0]
    assert [int(row[c]) for c in p] == list(range(len(p) - 1, -1, -1))
    off = cell(g, 0, 3)                               # beside the middle of the path
    assert row[off] == row[cell(g, 1, 3)] + 1
    blocked = cell(g, 2, 3)
    assert row[blocked] == UNREACHABLE
    tf.radius = 0
    tf.refine(pos, cache.slots(goals), time.perf_counter() + 60)
    assert row[off] == UNREACHABLE and [int(row[c]) for c in tf.paths[0]] == list(range(len(p) - 1, -1, -1))


def test_flow_stays_the_sum_of_the_paths_through_goal_changes_and_refinement():
    g = grid(TWO_WAYS)
    cache = DistanceCache(g, max_bytes=2 * g.n_cells * g.n_cells)
    rng = np.random.default_rng(3)
    free = g.free_cells()
    n = 12
    tf = TrafficFlow(g, cache, n)
    pos = rng.choice(free, n, replace=False).astype(np.int64)
    far = time.perf_counter() + 60
    for step in range(6):
        goals = np.where(rng.random(n) < 0.3, -1, rng.choice(free, n)).astype(np.int64)
        if step:
            goals[:4] = tf.goal[:4]                  # some keep theirs
        slot = np.array([cache.slot(int(x)) if x >= 0 else -1 for x in goals], dtype=np.int64)
        rows = tf.update(pos, goals, slot, far)
        assert ((rows >= 0) == (goals >= 0)).all()
        tf.refine(pos, slot, far, passes=2)
        assert (tf.flow == flow_from_paths(g, tf.paths)).all()
        assert all((p is None) == (gl < 0) for p, gl in zip(tf.paths, goals, strict=True))
        assert all(p[0] == s and p[-1] == gl for p, s, gl in zip(tf.paths, pos, goals, strict=True) if p is not None)
        pos = np.array([p[1] if p is not None and len(p) > 1 else c for p, c in zip(tf.paths, pos, strict=True)],
                       dtype=np.int64)


def test_past_the_deadline_a_new_goal_follows_its_distance_map():
    g = grid(TWO_WAYS)
    cache = DistanceCache(g, max_bytes=2 * g.n_cells * 4)
    tf = TrafficFlow(g, cache, 1)
    pos = np.array([cell(g, 1, 0)], dtype=np.int64)
    goals = np.array([cell(g, 3, 6)], dtype=np.int64)
    slot = cache.slots(goals)
    tf.update(pos, goals, slot, time.perf_counter() - 1)
    assert not tf.guided[0] and tf.paths[0] is None and tf.stats["guide_copied"] == 1
    assert (tf.table[0] == cache.table[slot[0]]).all()
    assert tf.refine(pos, slot, time.perf_counter() + 60) == 1 and tf.guided[0]


def test_past_the_hard_deadline_a_new_goal_waits_for_the_next_step():
    g = grid(TWO_WAYS)
    cache = DistanceCache(g, max_bytes=2 * g.n_cells * 4)
    tf = TrafficFlow(g, cache, 2)
    pos = np.array([cell(g, 1, 0), cell(g, 3, 0)], dtype=np.int64)
    goals = np.array([cell(g, 3, 6), -1], dtype=np.int64)
    slot = cache.slots(goals[:1]).tolist() + [-1]
    slot = np.array(slot, dtype=np.int64)
    past = time.perf_counter() - 1
    assert tf.update(pos, goals, slot, past, hard=past).tolist() == [-1, -1]
    assert tf.stats["guide_deferred"] == 1 and tf.goal[0] == -1
    assert tf.update(pos, goals, slot, time.perf_counter() + 60).tolist() == [0, -1] and tf.guided[0]


def test_on_two_threads_the_flow_stays_the_sum_of_the_paths():
    """Paths planned on two threads at once, goals changing and every path refined twice a step
    (the same robot twice in the list): the flow is the sum of the paths after every step, each
    path goes from its robot to its goal, and a lone robot listed three times is planned once at a
    time."""
    rows = ["." * 30] * 30
    rows[10] = "." + "@" * 28 + "."
    rows[20] = "." + "@" * 28 + "."
    g = grid(rows)
    cache = DistanceCache(g, max_bytes=2 * g.n_cells * g.n_cells)
    rng = np.random.default_rng(5)
    free = g.free_cells()
    n = 300
    tf = TrafficFlow(g, cache, n, threads=2)
    assert tf.stats["guide_threads"] == 2
    pos = rng.choice(free, n, replace=False).astype(np.int64)
    far = time.perf_counter() + 60
    for _ in range(5):
        goals = np.where(rng.random(n) < 0.1, -1, rng.choice(free, n)).astype(np.int64)
        slot = cache.slots(goals[goals >= 0])
        full = np.full(n, -1, dtype=np.int64)
        full[goals >= 0] = slot
        rows_ = tf.update(pos, goals, full, far)
        assert ((rows_ >= 0) == (goals >= 0)).all()
        # each robot's first place in the list is planned; its second is skipped only if the other thread
        # still plans its first then
        assert int((goals >= 0).sum()) <= tf.refine(pos, full, far, passes=2) <= 2 * int((goals >= 0).sum())
        assert (tf.flow == flow_from_paths(g, tf.paths)).all()
        assert all(p[0] == s and p[-1] == gl for p, s, gl in zip(tf.paths, pos, goals, strict=True) if p is not None)
    one = TrafficFlow(g, cache, 1, threads=2)
    goals = np.array([free[-1]], dtype=np.int64)
    slot = cache.slots(goals)
    one.update(pos[:1], goals, slot, far)
    refined = one.refine(pos[:1], slot, far, passes=3)
    assert 1 <= refined <= 3 and (one.flow == flow_from_paths(g, one.paths)).all()
