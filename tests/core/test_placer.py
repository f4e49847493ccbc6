"""The placer's model and its choices (rce_master.placement.placer), on the inputs of the placement script:
a node with a 100 ms deadline that reads a 10 Hz, 10 kB sensor stream from its robot and burns
20 core-ms per result, a cloud host with free cores and a robot whose computer has 0.3 of a core."""
from __future__ import annotations

import pytest

from rce.plumbing.errors import RequestError
from rce.protocol.zones import Zone, parse_zone
from rce_master.placement.placer import (MISS_RATE_OK, ContainerView, EnergyModel, HostView, LinkView, Placer, choose,
                                         options)

CLOUD = HostView(1, "dc1", Zone("cloud"), cpu=8, load=1)
ROBOT = HostView(2, "r1-computer", Zone("robot", "r1", "alice"), cpu=0.3)
OTHER = HostView(3, "r2-computer", Zone("robot", "r2", "bob"), cpu=4)
NODE = ContainerView("alice", "costmap", "r1", deadline_ms=100, work_ms=20, rate_hz=10, in_bytes=100_000,
                     out_bytes=2_000)
GOOD = {"cloud": LinkView(rtt_ms=5, rate=10e6)}
BAD = {"cloud": LinkView(rtt_ms=100, rate=125_000)}       # 1 Mbit/s, 50 ms each way


def by_zone(opts):
    return {o.zone: o for o in opts}


def test_the_model_on_a_good_and_a_bad_link():
    o = by_zone(options(NODE, [CLOUD, ROBOT, OTHER], GOOD))
    assert set(o) == {"cloud", "robot:r1"}, "another user's robot computer is never an option"
    assert o["cloud"].compute_ms == pytest.approx(20)
    assert o["cloud"].link_ms == pytest.approx(5 + 1e3 * 10_200 / 10e6)
    assert o["robot:r1"].compute_ms == pytest.approx(20 / 0.3)
    assert o["robot:r1"].link_ms == 0 and o["cloud"].meets and o["robot:r1"].meets
    assert o["robot:r1"].robot_w == pytest.approx(EnergyModel().cpu_w * 0.2)          # 0.2 cores busy
    assert o["cloud"].robot_w == pytest.approx(EnergyModel().radio_j_per_byte * 102_000)
    bad = by_zone(options(NODE, [CLOUD, ROBOT], BAD))
    assert not bad["cloud"].meets and bad["cloud"].latency_ms > 100


def test_a_link_that_cannot_carry_the_stream_misses_whatever_its_round_trip():
    thin = {"cloud": LinkView(rtt_ms=1, rate=50_000)}
    assert not by_zone(options(NODE, [CLOUD], thin))["cloud"].meets


def test_choices_most_margin_then_the_deadline_then_energy_on_a_low_battery():
    good = options(NODE, [CLOUD, ROBOT], GOOD)
    ch = choose(good, current_tid=ROBOT.tid, deadline_ms=100)
    assert ch.target.tid == CLOUD.tid and ch.move and "more margin" in ch.why
    ch = choose(options(NODE, [CLOUD, ROBOT], BAD), current_tid=CLOUD.tid, deadline_ms=100)
    assert ch.target.tid == ROBOT.tid and ch.move and "misses its deadline" in ch.why
    heavy_radio = ContainerView("alice", "c", "r1", 100, work_ms=2, rate_hz=10, in_bytes=2_000_000)
    fat = {"cloud": LinkView(5, 100e6)}
    ch = choose(options(heavy_radio, [CLOUD, ROBOT], fat), current_tid=CLOUD.tid, battery_low=True,
                deadline_ms=100)
    assert ch.target.tid == ROBOT.tid and ch.move and "battery low" in ch.why
    ch = choose(options(heavy_radio, [CLOUD, ROBOT], fat), current_tid=CLOUD.tid, battery_low=False,
                deadline_ms=100)
    assert not ch.move and "hysteresis" in ch.why, "2 ms more margin on the robot is within the hysteresis"


def test_no_host_meets_it_then_it_stays():
    slow = ContainerView("alice", "c", "r1", 10, work_ms=50, rate_hz=10)
    ch = choose(options(slow, [CLOUD, ROBOT], GOOD), current_tid=CLOUD.tid, deadline_ms=10)
    assert not ch.move and "no host meets" in ch.why


def test_hysteresis_in_time_settle_then_dwell():
    p = Placer(settle_s=1.0, dwell_s=10.0, settle_miss_s=1.0)
    ch = p.decide(0.0, NODE, [CLOUD, ROBOT], BAD, CLOUD.tid)
    assert ch.target.tid == ROBOT.tid and not ch.move and "moves in 1.0 s" in ch.why
    assert not p.decide(0.5, NODE, [CLOUD, ROBOT], BAD, CLOUD.tid).move
    assert p.decide(1.0, NODE, [CLOUD, ROBOT], BAD, CLOUD.tid).move
    p.moved(1.0, "alice", "costmap")
    # the link comes back at once: better in the cloud again, but not twice within the dwell
    for t in (1.5, 5.0, 10.9):
        ch = p.decide(t, NODE, [CLOUD, ROBOT], GOOD, ROBOT.tid)
        assert ch.target.tid == CLOUD.tid and not ch.move
    assert p.decide(11.0, NODE, [CLOUD, ROBOT], GOOD, ROBOT.tid).move
    # a better host that does not hold for the settle time never moves it
    q = Placer(settle_s=1.0, settle_miss_s=1.0)
    assert not q.decide(0.0, NODE, [CLOUD, ROBOT], BAD, CLOUD.tid).move
    assert not q.decide(0.6, NODE, [CLOUD, ROBOT], GOOD, CLOUD.tid).move
    assert not q.decide(1.2, NODE, [CLOUD, ROBOT], BAD, CLOUD.tid).move, "settling starts again"
    # where it runs misses its deadline: the better host need hold only settle_miss_s
    m = Placer(settle_s=1.0, settle_miss_s=0.2)
    assert not m.decide(0.0, NODE, [CLOUD, ROBOT], BAD, CLOUD.tid).move
    assert m.decide(0.2, NODE, [CLOUD, ROBOT], BAD, CLOUD.tid).move


@pytest.mark.parametrize("text,user,err", [
    ("moon", None, "must be 'cloud', 'edge' or 'robot:ROBOT_ID'"),
    ("robot:", "alice", "give the robot's ID"),
    ("robot:r1", None, "serves one user"),
    ("cloud", "alice", "shared by every user"),
    ("edge:x", None, "only a robot zone"),
])
def test_bad_zones_are_named(text, user, err):
    with pytest.raises(RequestError, match=err):
        parse_zone(text, user)


def test_zones_serve():
    z = parse_zone("robot:r1", "alice")
    assert str(z) == "robot:r1" and z.serves("alice", "r1")
    assert not z.serves("bob", "r1") and not z.serves("alice", "r2") and not z.serves("alice", None)
    assert parse_zone("edge").serves("bob", None)


def test_a_robot_config_states_what_its_container_needs():
    from rce.plumbing.errors import ConfigError
    from rce.protocol.config import parse_config
    base = {"url": "http://m:9000/", "userID": "alice", "password": "p", "robotID": "r1"}
    cfg = parse_config({**base, "containers": [{"cTag": "costmap", "placement": "auto", "deadline_ms": 100,
                                                "robot": "r1", "consumes": ["scan"], "cpu": 0.5,
                                                "ordered_moves": True}]})
    assert cfg.containers[0].container_data() == {"placement": "auto", "deadline_ms": 100, "robot": "r1",
                                                  "consumes": ["scan"], "cpu": 0.5, "ordered_moves": True}
    assert parse_config({**base, "containers": [{"cTag": "old"}]}).containers[0].container_data() == {}
    with pytest.raises(ConfigError, match=r"containers\[0\]\.deadline_ms: must be a number of ms greater than 0"):
        parse_config({**base, "containers": [{"cTag": "c", "deadline_ms": -1}]})
    with pytest.raises(ConfigError, match=r"containers\[0\]\.ordered_moves: must be true or false"):
        parse_config({**base, "containers": [{"cTag": "c", "ordered_moves": "yes"}]})


def test_the_measured_latency_where_it_runs_overrides_a_hopeful_model():
    slow = ContainerView(**{**NODE.__dict__, "node_ms": 140.0})     # throttled there: measured 140 ms
    o = by_zone(options(slow, [CLOUD, ROBOT], GOOD, current_tid=ROBOT.tid))
    assert o["robot:r1"].compute_ms == pytest.approx(140) and not o["robot:r1"].meets
    assert o["cloud"].compute_ms == pytest.approx(20), "other hosts keep the model"
    ch = choose(options(slow, [CLOUD, ROBOT], GOOD, current_tid=ROBOT.tid), ROBOT.tid)
    assert ch.move and ch.target.zone == "cloud"


def test_a_host_where_recent_results_were_late_misses_whatever_the_model():
    late = ContainerView(**{**NODE.__dict__, "node_ms": 20.0, "miss_rate": 0.3})    # the typical result is fine
    o = by_zone(options(late, [CLOUD, ROBOT], GOOD, current_tid=CLOUD.tid))
    assert not o["cloud"].meets and o["robot:r1"].meets
    ok = ContainerView(**{**NODE.__dict__, "node_ms": 20.0, "miss_rate": 0.02})
    assert by_zone(options(ok, [CLOUD, ROBOT], GOOD, current_tid=CLOUD.tid))["cloud"].meets


# -- a copy's record, the link's bound (rce_master.placement.placer.late_share, rce_master.placement.advice) ---
def marks_at(share: float, seconds: float, start: float = 0.0, hz: float = 10.0, every: float = 0.5,
             base: tuple[int, int] = (0, 0)) -> list[tuple[float, int, int]]:
    """Looks every ``every`` s at a copy that yields ``hz`` results a second, ``share`` of them late."""
    out, r, m = [], float(base[0]), float(base[1])
    t = start
    while t <= start + seconds + 1e-9:
        out.append((t, int(r), int(m)))
        r += hz * every
        m += hz * every * share
        t += every
    return out


def test_a_late_share_counts_only_once_two_windows_of_enough_results_hold_it():
    from rce_master.placement.placer import LATE_WINDOW_S, MIN_RESULTS, late_share
    assert late_share([]) is None
    assert late_share(marks_at(0.5, LATE_WINDOW_S * 1.5)) is None, "one window: a young copy has no record yet"
    assert late_share(marks_at(0.2, 2 * LATE_WINDOW_S)) == pytest.approx(0.2)
    slow = marks_at(0.5, 2 * LATE_WINDOW_S, hz=MIN_RESULTS / LATE_WINDOW_S / 2)       # 10 results a window
    assert late_share(slow) is None, "windows of fewer than MIN_RESULTS results say nothing"
    assert late_share(marks_at(0.5, 4 * LATE_WINDOW_S, hz=MIN_RESULTS / LATE_WINDOW_S / 2)) == pytest.approx(0.5)
    # one bad window after good ones (a burst) is not a host that misses; two in a row are
    good = marks_at(0.0, 2 * LATE_WINDOW_S)
    t, r, m = good[-1]
    burst = good + marks_at(0.3, LATE_WINDOW_S, start=t + 0.5, base=(r + 5, m))[1:]
    assert late_share(burst) == pytest.approx(0.0)
    t, r, m = burst[-1]
    both = burst + marks_at(0.3, LATE_WINDOW_S, start=t + 0.5, base=(r + 5, m + 1.5))[1:]
    assert late_share(both) > MISS_RATE_OK


class _Rec:
    def __init__(self, cid: int):
        self.user, self.ctag, self.cid = "alice", "costmap", cid


def stats(results: int, misses: int, p50: float = 6.0) -> dict:
    return {"cpu_seconds": results * 0.006, "msgs_out": results, "bytes_in": results * 40_000, "bytes_out": 0,
            "results": {"results": results, "misses": misses, "recent_p50_ms": p50}}


def test_a_fresh_copys_slow_first_results_never_make_it_move():
    from rce_master.placement.advice import WARMUP, Placement
    p = Placement(None, None)
    # a fresh copy: its first two results are late (imports), then it meets its deadline
    p._count(_Rec(1), stats(0, 0, p50=None), 0.0)
    p._count(_Rec(1), stats(10, 2, p50=150.0), 1.0)
    u = p.use[("alice", "costmap")]
    assert u.node_ms is None and u.miss_rate is None, "its warm-up says nothing of the host"
    t, results = WARMUP, 30
    while t < WARMUP + 12:
        p._count(_Rec(1), stats(results, 2 + results // 100), t)      # 1 % late after the warm-up
        t, results = t + 0.5, results + 5
    u = p.use[("alice", "costmap")]
    assert u.miss_rate is not None and u.miss_rate < MISS_RATE_OK, u.miss_rate
    o = by_zone(options(ContainerView(**{**NODE.__dict__, "node_ms": u.node_ms, "miss_rate": u.miss_rate}),
                        [CLOUD, ROBOT], GOOD, current_tid=CLOUD.tid))
    assert o["cloud"].meets
    # a move's switch: the new copy (another cid) starts its record afresh, its own warm-up first
    p._count(_Rec(2), stats(3, 3, p50=180.0), t)
    u = p.use[("alice", "costmap")]
    assert u.cid == 2 and u.miss_rate is None and u.node_ms is None and u.marks == []


def test_a_link_rate_once_measured_is_kept_as_a_bound_while_reports_carry_none():
    from rce_master.placement.advice import Placement
    p = Placement(None, None)
    p.robot_link("alice", "r1", 5.0, 0.0)
    assert p.links[("alice", "r1")].rate == float("inf"), "never measured: the round trip alone"
    p.robot_link("alice", "r1", 60.0, 125_000.0)          # the link fell to 1 Mbit/s, measured while busy
    p.robot_link("alice", "r1", 5.0, 0.0)                 # the container left it: nothing measured, rtt low
    link = p.links[("alice", "r1")]
    assert link.rtt_ms == 5.0 and link.rate == 125_000.0
    stream = ContainerView(**{**NODE.__dict__, "in_bytes": 400_000, "miss_rate": 0.07})
    ch = Placer(settle_s=0.0, settle_miss_s=0.0).decide(100.0, stream, [CLOUD, ROBOT], {"cloud": link}, ROBOT.tid)
    assert not ch.move and not by_zone(ch.options)["cloud"].meets, \
        "a robot that misses 7 % does not go back onto a link last measured too thin for its stream"
    p.robot_link("alice", "r1", 5.0, 10e6)                # a probe: the link is back
    ch = Placer(settle_s=0.0, settle_miss_s=0.0).decide(101.0, stream, [CLOUD, ROBOT],
                                                        {"cloud": p.links[("alice", "r1")]}, ROBOT.tid)
    assert ch.move and ch.target.tid == CLOUD.tid


def test_no_move_for_margin_or_energy_to_a_host_where_its_own_results_were_late():
    from rce_master.placement.placer import LATE_RECORD_S
    p = Placer(settle_s=0.0, settle_miss_s=0.0, dwell_s=0.0)
    light = {**NODE.__dict__, "work_ms": 6.0}                              # 20 ms on the robot's 0.3 cores, by the mean
    on_robot = ContainerView(**{**light, "miss_rate": 0.17})               # but its heavy scans miss there
    ch = p.decide(10.0, on_robot, [CLOUD, ROBOT], GOOD, ROBOT.tid)
    assert ch.move and ch.target.tid == CLOUD.tid, "the robot misses by its record: to the cloud"
    p.moved(10.0, "alice", "costmap")
    slow_link = {"cloud": LinkView(rtt_ms=30, rate=1e6)}                     # the model's robot has more margin
    in_cloud = ContainerView(**{**light, "miss_rate": 0.0})
    assert choose(options(in_cloud, [CLOUD, ROBOT], slow_link, current_tid=CLOUD.tid), CLOUD.tid,
                  deadline_ms=100).move
    ch = p.decide(20.0, in_cloud, [CLOUD, ROBOT], slow_link, CLOUD.tid)
    assert not ch.move and "late on robot:r1" in ch.why
    assert not p.decide(21.0, in_cloud, [CLOUD, ROBOT], slow_link, CLOUD.tid, battery_low=True).move
    assert p.decide(10.0 + LATE_RECORD_S + 1, in_cloud, [CLOUD, ROBOT], slow_link, CLOUD.tid).move, \
        "the record is kept for LATE_RECORD_S"
    # where it runs misses its deadline, a host with a late record may still take it (it missed less)
    q = Placer(settle_s=0.0, settle_miss_s=0.0, dwell_s=0.0)
    q.decide(0.0, on_robot, [CLOUD, ROBOT], GOOD, ROBOT.tid)
    assert q.decide(1.0, NODE, [CLOUD, ROBOT], BAD, CLOUD.tid).move



async def test_a_pending_move_is_made_when_its_hysteresis_ends_not_at_the_next_poll(monkeypatch):
    import asyncio
    import types

    from rce_master.placement import advice as placement
    from rce_master.state.model import ContainerRec, TaskSet
    from rce_master.placement.mover import MoveFailed
    monkeypatch.setattr(placement, "POLL", 60.0)          # the next poll would come far too late
    hosts = {1: TaskSet(1, "container", "dc1", "h", {"capacity": {"cpu": 8}}),
             2: TaskSet(2, "container", "r1-computer", "h", {"capacity": {"cpu": 0.3}, "zone": "robot:r1",
                                                             "zone_user": "alice"})}
    c = ContainerRec(7, "alice", "costmap", "r1", 1, None, {"placement": "auto", "deadline_ms": 100, "robot": "r1",
                                                            "consumes": ["scan"]}, state="running")
    state = types.SimpleNamespace(containers={("alice", "costmap"): c}, tasksets=hosts)
    polled, moved = asyncio.Event(), asyncio.Event()
    asked = []

    async def host_stats(_c):
        polled.set()
        return stats(100, 0)

    class Mover:
        spares: dict = {}

        async def move(self, user, ctag, tid, why, drain_max):
            asked.append(tid)
            moved.set()
            raise MoveFailed("not moved: the test only asks when")
    p = placement.Placement(state, host_stats, Placer(settle_miss_s=0.05), mover=Mover())
    p.robot_link("alice", "r1", 5.0, 10e6)
    stop = asyncio.Event()
    task = asyncio.create_task(p.run(stop))
    try:
        await asyncio.wait_for(polled.wait(), 10)
        p.robot_link("alice", "r1", 300.0, 10e6)          # the link's round trip grows: the cloud misses
        ch = p.word(c)
        assert not ch.move and ch.target.tid == 2 and 0 < ch.wait_s < 0.05 + 1e-6, ch
        await asyncio.wait_for(moved.wait(), 10)          # at the end of its settle, with no poll meanwhile
        assert asked == [2]
    finally:
        stop.set()
        await task


def test_from_a_host_where_some_results_are_late_to_one_where_none_were():
    from rce_master.placement.placer import LATE_RECORD_S
    p = Placer(settle_s=0.0, settle_miss_s=0.0, dwell_s=0.0)
    light = {**NODE.__dict__, "work_ms": 6.0}
    in_cloud = ContainerView(**{**light, "miss_rate": 0.0})                 # never late in the cloud
    assert not p.decide(0.0, in_cloud, [CLOUD, ROBOT], GOOD, CLOUD.tid).move
    assert p.decide(1.0, in_cloud, [CLOUD, ROBOT], BAD, CLOUD.tid).move, "the link fell: to the robot"
    p.moved(1.0, "alice", "costmap")
    on_robot = ContainerView(**{**light, "node_ms": 20.0, "miss_rate": 0.04})  # a heavy scan in 25 late: it meets
    ch = p.decide(20.0, on_robot, [CLOUD, ROBOT], BAD, ROBOT.tid)
    assert not ch.move, "the cloud misses by the model: a clean record there does not count"
    near = {"cloud": LinkView(rtt_ms=20, rate=10e6)}                         # back, but not better by the hysteresis
    assert not choose(options(on_robot, [CLOUD, ROBOT], near, current_tid=ROBOT.tid), ROBOT.tid,
                      deadline_ms=100).move
    ch = p.decide(21.0, on_robot, [CLOUD, ROBOT], near, ROBOT.tid)
    assert ch.move and ch.target.tid == CLOUD.tid and "none on cloud" in ch.why, ch.why
    never_late = ContainerView(**{**light, "node_ms": 20.0, "miss_rate": 0.0})
    assert not p.decide(22.0, never_late, [CLOUD, ROBOT], near, ROBOT.tid).move, "no late result: the model decides"
    q = Placer(settle_s=0.0, settle_miss_s=0.0, dwell_s=0.0)
    q.decide(0.0, in_cloud, [CLOUD, ROBOT], GOOD, CLOUD.tid)
    assert not q.decide(LATE_RECORD_S + 1, on_robot, [CLOUD, ROBOT], near, ROBOT.tid).move, \
        "a clean record is kept for LATE_RECORD_S"


def test_a_spare_goes_where_the_placer_ranks_next():
    from rce_master.placement.placer import runner_up
    ch = Placer().decide(0.0, NODE, [CLOUD, ROBOT], GOOD, CLOUD.tid)
    assert ch.current.tid == CLOUD.tid and runner_up(ch).tid == ROBOT.tid
    ch = Placer().decide(0.0, NODE, [CLOUD, ROBOT], BAD, ROBOT.tid)
    assert runner_up(ch).tid == CLOUD.tid, "the cloud misses now, but it is where the container goes back to"
    ch = Placer().decide(0.0, NODE, [ROBOT], GOOD, ROBOT.tid)
    assert runner_up(ch) is None, "no other host: no spare"
