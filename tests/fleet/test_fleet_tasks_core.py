"""Sans-I/O logic of the operators' tasks: places, the battery model, the task book's
answers, and the global planner core dispatching tasks, charging and parking in a virtual
fleet (the planner core, one move_client core per robot, robots that jump to their waypoints)."""
from __future__ import annotations

import numpy as np
import pytest

from rce_fleet.operations.battery import Battery, BatteryParams
from rce_fleet.live.kinematic import KinematicFleet, run_stream
from rce_fleet.lifelong import TaskState
from rce_fleet.operations.places import Place, PlaceError, Places, generate_places
from rce_fleet.operations.tasks_api import TaskBook

from .test_nodes import VirtualFleet, lab  # noqa: F401  (lab: the fixture)

# the lab grid (8x8 cells of 1 m; ## = not free):
#  0  1  2  3  4  5  6  7
#  8  9 10 11 12 13 ## 15
# 16 17 18 19 20 21 22 23
# 24 25 26 27 28 ## 30 31
# 32 33 34 35 36 37 38 39
# 40 41 ## 43 44 ## 46 47
# 48 49 ## 51 52 ## 54 55
# 56 57 58 59 60 61 62 63


def lab_places(geo) -> Places:
    return Places([Place("pick1", "pickup", 16), Place("drop1", "dropoff", 23), Place("charger1", "charger", 0),
                   Place("charger2", "charger", 63), Place("park1", "parking", 56), Place("park2", "parking", 7)], geo)


class TaskFleet(VirtualFleet):
    """The virtual fleet with fleet time (pose stamps = the clock) and move_client progress
    routed to the planner, and robots that drain and charge batteries."""

    batteries: dict = {}
    chargers: set = set()

    @classmethod
    def make(cls, geo, starts: dict[str, int], charge: dict[str, float] | None = None, **kw) -> TaskFleet:
        """A fleet; ``charge`` robot -> starting level (0..1) gives those robots batteries of
        ``kw["battery"]`` (the others full)."""
        f = cls(geo, starts, **kw)
        if kw.get("battery") is not None:
            b = kw["battery"]
            f.batteries = {r: Battery(b, wh=(charge or {}).get(r, 1.0) * b.capacity_wh) for r in starts}
        f.chargers = set(kw["places"].cells("charger")) if kw.get("places") else set()
        return f

    def step(self) -> None:
        self.clock.t += 0.5
        for r in sorted(self.mc):
            g = self.goal_sent[r]
            moved = 0.0
            if g is not None:
                x0, y0, _ = self.pose[r]
                moved = abs(g[0] - x0) + abs(g[1] - y0)
                self.pose[r] = (g[0], g[1], 0.0)
                c = self.geo.cell_of(*g)
                if self.visited[r][-1] != c:
                    self.visited[r].append(c)
            if r in self.batteries:
                b = self.batteries[r]
                b.step(0.5, moved, self.geo.cell_of(*self.pose[r][:2]) in self.chargers)
                self.core.on_battery(r, b.fraction)
            self.route(self.mc[r].on_pose(*self.pose[r]))
            self.route(self.core.on_pose(r, *self.pose[r], stamp=self.clock.t))
            self.core.on_progress(r, self.mc[r].progress())
        self.route(self.core.tick())

    def run_until(self, pred, steps: int = 400) -> int:
        for k in range(steps):
            if pred():
                return k
            self.step()
        raise AssertionError(f"not within {steps} steps: {self.core.book.message(0, 0, [])['tasks']}")

    def add(self, *errands, **kw) -> dict:
        req = {"request": f"q{len(self.core.book.answers)}", "errands": [str(e) for e in errands], **kw}
        self.route(self.core.on_task(req))
        return self.core.book.answers[-1]

    def task(self, tid: str):
        return self.core.book.records[tid]


# -- places -------------------------------------------------------------------------------------------
def test_places_file_by_cell_and_metres_and_resolve(lab, tmp_path):  # noqa: F811
    x, y = lab.center(23)
    f = tmp_path / "places.yaml"
    f.write_text(f"places:\n  - {{name: pick1, kind: pickup, cell: 16}}\n"
                 f"  - {{name: drop1, kind: dropoff, x: {x + 0.2}, y: {y - 0.1}}}\n"
                 f"  - {{name: charger1, kind: charger, cell: 0}}\n")
    p = Places.load(f, lab)
    assert p.resolve("drop1") == 23 and p.resolve("pick1") == 16 and p.resolve("43") == 43 and p.resolve(5) == 5
    assert p.cells("charger") == [0]
    with pytest.raises(PlaceError, match=r"unknown place 'nowhere' \(places: charger1, drop1, pick1\)"):
        p.resolve("nowhere")
    with pytest.raises(PlaceError, match="outside the 8x8 grid"):
        p.resolve("64")
    with pytest.raises(PlaceError, match="not a free cell"):
        p.resolve("14")
    back = Places.load(p.dump(tmp_path / "again.yaml"), lab)
    assert back.to_param() == p.to_param() == Places.from_param(p.to_param(), lab).to_param()


@pytest.mark.parametrize("body, why", [
    ("  - {name: a, kind: shop, cell: 1}", "unknown kind 'shop'"),
    ("  - {name: a, kind: pickup, cell: 1}\n  - {name: a, kind: dropoff, cell: 2}", "declared twice"),
    ("  - {name: a, kind: pickup, cell: 1}\n  - {name: b, kind: dropoff, cell: 1}", "share cell 1"),
    ("  - {name: a, kind: pickup, cell: 14}", "cell 14 is not a free cell"),
    ("  - {name: a, kind: pickup}", "needs a cell or x and y"),
    ("  - {name: '7', kind: pickup, cell: 3}", "not a number"),
])
def test_bad_places_files_say_why(lab, tmp_path, body, why):  # noqa: F811
    f = tmp_path / "p.yaml"
    f.write_text("places:\n" + body + "\n")
    with pytest.raises(PlaceError, match=why):
        Places.load(f, lab)


def test_generated_places_are_free_distinct_and_complete(lab):  # noqa: F811
    p = generate_places(lab, robots=3)
    kinds = {k: p.cells(k) for k in ("pickup", "dropoff", "charger", "parking")}
    assert all(kinds.values()), kinds
    cells = [q.cell for q in p.by_name.values()]
    assert len(set(cells)) == len(cells) and all(lab.is_free(c) for c in cells)


# -- battery ------------------------------------------------------------------------------------------
def test_battery_drains_by_distance_and_time_and_charges_on_a_charger():
    b = Battery(BatteryParams(capacity_wh=10.0, drain_wh_per_m=0.1, idle_w=36.0, charge_w=360.0))
    b.step(10.0, 20.0, on_charger=False)            # 2 Wh driving + 0.1 Wh idle
    assert b.wh == pytest.approx(7.9) and not b.charging and b.charges == 0
    b.step(10.0, 0.0, on_charger=True)              # +1 Wh - 0.1 Wh
    assert b.wh == pytest.approx(8.8) and b.charging and b.charges == 1
    b.step(10.0, 0.0, on_charger=True)
    assert b.charges == 1 and b.wh == pytest.approx(9.7)
    m = b.message({"secs": 1, "nsecs": 0})
    assert m["percentage"] == pytest.approx(0.97) and m["power_supply_status"] == 1
    b.step(1000.0, 500.0, on_charger=False)
    assert b.wh == 0.0 and b.flat and b.min_wh == 0.0 and b.message({})["power_supply_status"] == 2
    with pytest.raises(ValueError, match="threshold"):
        BatteryParams(threshold=0.95)
    with pytest.raises(ValueError, match="initial_spread"):
        BatteryParams(initial=0.5, initial_spread=0.5)
    assert BatteryParams.from_param(BatteryParams(initial=0.6, initial_spread=0.45).to_param()).initial_spread == 0.45


# -- the task book ------------------------------------------------------------------------------------
def test_bad_requests_are_refused_with_a_reason_and_lose_nothing(lab):  # noqa: F811
    blocked = {27: "operator"}
    book = TaskBook(lab_places(lab), lambda c: f"is blocked (by {blocked[c]})" if c in blocked else None)
    ok = book.request_add({"request": "a", "errands": ["pick1", "drop1"], "priority": 2}, 10.0)
    assert ok["ok"] and ok["id"] == "T1"
    bad = [({"errands": []}, "bad_request", "at least one errand"),
           ({"errands": ["pick1", "nowhere"]}, "bad_request", "errand 2: unknown place 'nowhere'"),
           ({"errands": ["27"]}, "bad_request", "errand 1: cell 27 is blocked (by operator)"),
           ({"errands": ["14"]}, "bad_request", "not a free cell"),
           ({"errands": ["99"]}, "bad_request", "outside the 8x8 grid"),
           ({"errands": ["1"], "priority": "high"}, "bad_request", "priority 'high' is not a number"),
           ({"errands": ["1"], "deadline_s": 5, "earliest_start_s": 9}, "bad_request", "not after"),
           ({"errands": ["1"], "id": "T1"}, "conflict", "exists already"),
           ({"errands": ["1"], "id": "no spaces"}, "bad_request", "task id")]
    for req, code, text in bad:
        a = book.request_add({"request": "r", **req}, 11.0)
        assert not a["ok"] and a["code"] == code and text in a["error"], (req, a)
    assert [r.id for r in book.open_records()] == ["T1"]
    assert book.records["T1"].cells == (16, 23) and book.records["T1"].state is TaskState.QUEUED
    assert book.request_cancel({"request": "c1", "id": "T9"}, 12.0)["code"] == "not_found"
    assert book.request_cancel({"request": "c2", "id": "T1", "source": "cli"}, 12.0)["ok"]
    again = book.request_cancel({"request": "c3", "id": "T1"}, 13.0)
    assert again["code"] == "conflict" and "is cancelled" in again["error"]
    rec = book.records["T1"]
    assert rec.state is TaskState.CANCELLED and rec.reason == "cancelled by cli" and rec.finished == 12.0
    st = book.stats()
    assert st["cancelled"] == 1 and st["done"] == 0 and st["queued"] == 0
    msg = book.message(1, 13.0, [])
    assert [t["state"] for t in msg["tasks"]] == ["cancelled"] and msg["answers"][-1]["request"] == "c3"


# -- dispatching in the virtual fleet -----------------------------------------------------------------
def test_tasks_are_allocated_done_in_order_and_timed(lab):  # noqa: F811
    f = TaskFleet(lab, {"Robot1": 33, "Robot2": 47}, places=lab_places(lab))
    a1 = f.add("pick1", "drop1")
    a2 = f.add(47, 60, id="near2")
    assert a1["ok"] and a2["ok"]
    f.run_until(lambda: f.task("T1").state is TaskState.DONE and f.task("near2").state is TaskState.DONE)
    t1, t2 = f.task("T1"), f.task("near2")
    assert t1.robot == "Robot1" and t2.robot == "Robot2"       # each to the robot that finishes it first
    assert 0 < t1.assigned <= t1.active < t1.finished and t2.active <= t2.finished
    assert [h[1] for h in t1.history] == ["queued", "assigned", "active", "done"]
    # each errand's time is kept and sent: the first is when it opened, the last when it was done
    msg = t1.message()
    assert msg["reached"] == [t1.active, t1.finished] and msg["active"] <= msg["reached"][1]
    # Robot1 went through the pick-up before the drop-off
    v = f.visited["Robot1"]
    assert 16 in v and v.index(16) < v.index(23)
    st = f.core.book.stats()
    assert st["done"] == 2 and st["mean_s"] > 0 and st["p95_s"] >= st["mean_s"]
    robots = {r["robot"]: r for r in f.core.tasks_msg().msg["robots"]}
    assert robots["Robot1"]["tasks_done"] == 1 and 0 < robots["Robot1"]["busy_s"] <= robots["Robot1"]["since_s"]


def test_cancel_an_active_task_and_a_blocked_errand_fails_it_with_the_reason(lab):  # noqa: F811
    f = TaskFleet(lab, {"Robot1": 33}, places=lab_places(lab))
    f.add("pick1", "drop1", id="a")
    f.run_until(lambda: f.task("a").state is TaskState.ACTIVE)
    f.route(f.core.on_task_cancel({"request": "x", "id": "a", "source": "operator"}))
    assert f.task("a").state is TaskState.CANCELLED
    f.step()
    # it dropped the task's goal and, having worked, parks off the stations
    assert f.core.fp.goals.get("Robot1") in (56, 7) and f.core.dispatcher.robots["Robot1"].activity == "parking"
    f.add("pick1", "drop1", id="b")
    f.run_until(lambda: f.task("b").state is TaskState.ACTIVE)
    f.route(f.core.on_block(23, True, "operator"))
    b = f.task("b")
    assert b.state is TaskState.FAILED and b.reason == "errand cell 23 was blocked (operator)"
    refused = f.add("pick1", "drop1")
    assert not refused["ok"] and "cell 23 is blocked (by operator)" in refused["error"]


def test_deadline_passed_fails_the_task(lab):  # noqa: F811
    f = TaskFleet(lab, {"Robot1": 56}, places=lab_places(lab))
    f.add(7, id="far", deadline_s=2.0)
    f.run_until(lambda: not f.task("far").open, steps=40)
    assert f.task("far").state is TaskState.FAILED and "deadline" in f.task("far").reason
    assert f.core.book.stats()["deadline_missed"] == 1


def test_low_battery_charges_to_the_recharge_level_and_never_runs_flat(lab):  # noqa: F811
    params = BatteryParams(capacity_wh=1.0, drain_wh_per_m=0.01, idle_w=1.0, charge_w=60.0,
                           threshold=0.3, recharge=0.8)
    f = TaskFleet.make(lab, {"Robot1": 33, "Robot2": 39}, {"Robot1": 0.25}, places=lab_places(lab), battery=params)
    f.step()
    w = f.core.dispatcher.robots["Robot1"]
    assert w.activity == "to_charger" and w.target == 0             # the nearest free charger
    f.run_until(lambda: f.core.dispatcher.robots["Robot1"].activity == "charging")
    f.run_until(lambda: f.core.dispatcher.robots["Robot1"].activity not in ("charging", "to_charger"), steps=600)
    assert f.batteries["Robot1"].fraction >= 0.8 and w.charges == 1
    # tasks keep coming: nobody runs flat, every task is done
    for k in range(6):
        f.add("pick1", "drop1", id=f"t{k}")
    f.run_until(lambda: f.core.book.stats()["done"] == 6, steps=3000)
    assert not any(b.flat for b in f.batteries.values())
    assert min(b.min_wh for b in f.batteries.values()) > 0


def test_a_robot_never_takes_a_task_it_cannot_finish_and_idle_robots_park(lab):  # noqa: F811
    params = BatteryParams(capacity_wh=1.0, drain_wh_per_m=0.02, idle_w=0.0, charge_w=60.0,
                           threshold=0.2, recharge=0.9)
    # 40 % is above the threshold, but pick1 -> drop1 -> a charger is ~ 20 cells: 0.4 Wh + 5 % reserve
    f = TaskFleet.make(lab, {"Robot1": 36}, {"Robot1": 0.4}, places=lab_places(lab), battery=params, park_idle=True)
    f.add("pick1", "drop1", id="long")
    f.step()
    w = f.core.dispatcher.robots["Robot1"]
    assert w.activity == "to_charger" and f.task("long").state is TaskState.QUEUED
    f.run_until(lambda: f.task("long").state is TaskState.DONE, steps=2000)
    assert f.batteries["Robot1"].min_wh > 0
    f.run_until(lambda: f.core.fp.positions["Robot1"] in (56, 7) and w.activity == "parking", steps=200)


def test_a_robot_whose_next_station_is_taken_waits_beside_it_not_on_the_one_it_served(lab):  # noqa: F811
    f = TaskFleet(lab, {"Robot1": 56, "Robot2": 17}, places=lab_places(lab))
    f.route(f.core.on_goal("Robot1", 23))      # an operator sends Robot1 to the drop-off station
    f.add("pick1", "drop1", id="a")
    f.run_until(lambda: f.task("a").state is TaskState.ACTIVE)
    assert f.task("a").robot == "Robot2"
    f.step()
    f.step()
    # drop1 (23) is Robot1's goal: Robot2 leaves pick1 (16) for a free cell near 23
    spot = f.core.fp.goals["Robot2"]
    dist = f.core.dispatcher.cache.table[f.core.dispatcher.cache.slot(23)]
    assert spot not in (16, 23) and spot not in f.core.places.by_cell and 0 < dist[spot] <= 3, spot
    f.run_until(lambda: f.cells()["Robot2"] == spot and f.cells()["Robot1"] == 23)
    assert f.task("a").state is TaskState.ACTIVE
    f.route(f.core.on_goal("Robot1", 0))       # the station frees: Robot2 drops off
    f.run_until(lambda: f.task("a").state is TaskState.DONE)
    assert f.task("a").robot == "Robot2" and 23 in f.visited["Robot2"]


def test_kinematic_fleet_runs_a_task_stream_through_the_planner_and_move_clients(lab):  # noqa: F811
    stream = [(1.0, ["pick1", "drop1"]), (2.0, ["drop1", "pick1"]), (3.0, [str(47), "pick1"])]
    r = run_stream(lab, lab_places(lab), {"Robot1": 33, "Robot2": 38}, stream, 240.0)
    assert r["tasks_done"] == 3 and r["failed"] == 0 and r["refused"] == 0, r
    # the robots drove at most at their speed for the whole run
    assert 0 < r["distance_m"] <= 2 * 0.22 * 240.0
    # the robots' time split by what they did: every step counted once
    assert abs(sum(r["time_split"].values()) - 1.0) < 1e-3 and r["time_split"]["driving"] > 0, r["time_split"]



def test_robots_cross_a_standing_robot_that_yields_without_sharing_a_cell(lab):  # noqa: F811
    # row 2 of the lab as a corridor (rows 1 and 3 blocked) with a pocket at 27 below 19:
    # Robot1 stands on its goal 19; Robot2 shuttles 16 <-> 23 through it, and Robot1 is
    # re-planned while it yields (its plan passes 19 twice; the move_client must follow only
    # the planner's current plan)
    f = KinematicFleet(lab, {"Robot1": 19, "Robot2": 16})
    for c in (8, 9, 10, 11, 12, 13, 15, 24, 25, 26, 28, 30, 31):
        f.route(f.core.on_block(c))
    f.route(f.core.on_goal("Robot1", 19))
    f.route(f.core.on_goal("Robot2", 23))
    assert 27 in f.core.fp.paths["Robot1"] and not f.core.fp.unreachable
    crossings = 0
    for k in range(3000):
        f.step()
        if f.core.fp.positions["Robot2"] == f.core.fp.goals["Robot2"]:
            crossings += 1
            f.route(f.core.on_goal("Robot2", 16 if f.core.fp.goals["Robot2"] == 23 else 23))
        if k % 7 == 0:
            f.route(f.core.on_goal("Robot1", 19))
    assert crossings >= 4 and f.visited["Robot1"].count(27) >= 4
    assert f.shared_cells == 0


def test_control_loop_stays_collision_free_while_re_plans_pass_their_bound(lab):  # noqa: F811
    # the planner core's re-plans pass a bound no re-plan can meet while robots drive tasks:
    # robots not reached keep their plans or hold, nobody shares a cell, the counts show it,
    # and once the bound is back the deferred robots are served and the tasks get done
    from dataclasses import replace
    f = KinematicFleet(lab, {"Robot1": 33, "Robot2": 38, "Robot3": 0, "Robot4": 7}, places=lab_places(lab),
                       park_idle=True)
    for i, errands in enumerate([["pick1", "drop1"], ["drop1", "pick1"], ["pick1", "drop1"], ["drop1", "pick1"]]):
        f.route(f.core.on_task({"request": f"t{i}", "errands": errands, "source": "test"}))
    normal = f.core.fp.limits
    for k in range(1500):
        if k == 60:
            f.core.fp.limits = replace(normal, bound_s=1e-9)
        if k == 400:
            f.core.fp.limits = normal
        f.step()
        assert f.shared_cells == 0, f"two robots in one cell at step {k}"
    st = f.core.state()
    assert st["replans_bounded"] > 0 and st["robots_deferred_total"] > 0, st
    assert f.core.book.stats()["done"] >= 2 and not f.core.fp.deferred


def test_a_taken_station_goes_to_the_robot_nearest_to_it(lab):  # noqa: F811
    # two robots hold tasks at pick1 (16); the one sent there first is on its way from afar
    # when the other reaches the station's side: the nearer one goes in, the other waits beside
    # it; a robot only a step or two nearer does not take it (no goals bouncing between robots)
    from rce_fleet.operations.dispatcher import Dispatcher, RobotView
    from rce_fleet.lifelong import LifelongGrid
    places = lab_places(lab)
    book = TaskBook(places)
    d = Dispatcher(book, LifelongGrid(np.array(lab.free, dtype=bool).reshape(lab.rows, lab.cols)),
                   parking=places.cells("parking"), places=places.by_cell)
    d.add_robot("Robot1")
    d.add_robot("Robot2")

    def view(c1: int, c2: int) -> dict[str, RobotView]:
        goals = {n: d.robots[n].sent for n in ("Robot1", "Robot2")}
        return {"Robot1": RobotView(c1, goals["Robot1"]), "Robot2": RobotView(c2, goals["Robot2"])}

    book.request_add({"request": "a", "id": "a", "errands": ["pick1", "drop1"]}, 0.0)
    assert d.update(0.0, view(17, 63)) == {"Robot1": 16}
    book.request_add({"request": "b", "id": "b", "errands": ["pick1", "drop1"]}, 1.0)
    goals = d.update(1.0, view(17, 63))
    assert book.records["b"].robot == "Robot2" and goals["Robot2"] not in (16, *places.by_cell)
    # Robot2 came 1 step nearer than Robot1: nothing changes
    assert d.update(2.0, view(18, 17)) == {}
    # Robot2 is 4 steps nearer: it goes in, Robot1 waits beside the station
    goals = d.update(3.0, view(36, 24))
    assert goals["Robot2"] == 16 and goals["Robot1"] not in (16, *places.by_cell), goals
    assert d.robots["Robot1"].spot == goals["Robot1"] and d.robots["Robot2"].spot is None


def test_a_robot_waiting_for_one_planned_before_it_that_stalls_is_re_planned_to_go_first(lab):  # noqa: F811
    # a crossing (row 2 and column 3 of the lab, every other cell blocked): whichever robot the
    # plan sends through the centre (19) first stalls two cells short of it; the other, waiting
    # in front of the centre, is re-planned to go first instead of waiting for it for ever
    plus = {c for c in range(16, 24)} | {3, 11, 19, 27, 35, 43, 51, 59}
    f = KinematicFleet(lab, {"Robot1": 17, "Robot2": 3})
    for c in range(lab.n_cells):
        if lab.free[c] and c not in plus:
            f.route(f.core.on_block(c))
    f.route(f.core.on_goals({"Robot1": 21, "Robot2": 35}))
    adg = f.core.fp._adg
    first = next(r for r in ("Robot1", "Robot2")
                 if any(adg.pred[o][k] == (r, j) for o in ("Robot1", "Robot2") if o != r
                        for k, (c, _, _) in enumerate(adg.visits[o]) if c == 19
                        for j, (c2, _, _) in enumerate(adg.visits[r]) if c2 == 19))
    other = "Robot2" if first == "Robot1" else "Robot1"
    drive = f._drive
    f._drive = lambda r: None if r == first else drive(r)       # the first robot stalls where it stands
    for _ in range(400):
        f.step()
        if f.core.fp.positions[other] == f.core.fp.goals[other]:
            break
    assert f.core.fp.positions[other] == f.core.fp.goals[other] and 19 in f.visited[other]
    assert f.core.stale_replans >= 1 and f.visited[first] == [17 if first == "Robot1" else 3]
    f._drive = drive
    for _ in range(400):
        f.step()
        if f.core.fp.positions[first] == f.core.fp.goals[first]:
            break
    assert f.core.fp.positions[first] == f.core.fp.goals[first] and f.shared_cells == 0
