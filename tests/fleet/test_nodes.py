"""Sans-I/O logic of the fleet's container nodes: the global planner core, the move_client
core, the cell tracker and the obstacle filter, wired together without sockets."""
from __future__ import annotations

from pathlib import Path

import pytest

from rce.messages import MessageRegistry
from rce.messages.forms import RCE_FORMS
from rce.node.package_path import load_package_types
from rce_fleet.maps.geometry import GridGeometry, quaternion_from_yaw, yaw_from_quaternion
from rce_fleet.maps.grid import make_grid
from rce_fleet.maps.lab_map import write_lab_map
from rce_fleet.maps.occupancy import load_map
from rce_fleet.nodes.global_planner_core import POSE_WAIT_S, GlobalPlannerCore
from rce_fleet.nodes.move_client_core import MoveClientCore, plan_id_of
from rce_fleet.planning import compress, compressed_index
from rce_fleet.nodes.tracking import CellTracker, ObstacleFilter

SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "maps"


@pytest.fixture(scope="module")
def lab(tmp_path_factory) -> GridGeometry:
    path = write_lab_map(tmp_path_factory.mktemp("lab"))
    return GridGeometry.from_cellgrid(make_grid(load_map(path)))


@pytest.fixture(scope="module")
def tb3() -> GridGeometry:
    return GridGeometry.from_cellgrid(make_grid(load_map(SHARED / "turtlebot3_world.yaml"), (8, 8)))


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


class VirtualFleet:
    """The planner core, one move_client core per robot, and robots that jump to the
    waypoint they were sent (one hop per round), with the messages routed by topic."""

    def __init__(self, geo: GridGeometry, starts: dict[str, int], **kw):
        self.geo = geo
        self.clock = Clock()
        self.core = GlobalPlannerCore(geo, list(starts), clock=self.clock, **kw)
        self.mc = {r: MoveClientCore(r, geo) for r in starts}
        self.pose = {r: (*geo.center(c), 0.0) for r, c in starts.items()}
        self.goal_sent: dict[str, tuple[float, float] | None] = {r: None for r in starts}
        self.log: list = []
        self.visited = {r: [c] for r, c in starts.items()}
        self.cancels = {r: 0 for r in starts}
        for r in starts:
            self.route(self.mc[r].on_pose(*self.pose[r]))
            self.route(self.core.on_pose(r, *self.pose[r]))

    def route(self, outs) -> None:
        for o in outs:
            self.log.append(o)
            robot, _, leaf = o.topic.strip("/").partition("/")
            if leaf == "goalNodesList":
                self.route(self.mc[robot].on_path(plan_id_of(o.msg["layout"]["dim"][0]["label"]), o.msg["data"]))
            elif leaf == "clearance":
                self.route(self.mc[robot].on_clearance(o.msg["plan"], o.msg["index"]))
            elif leaf == "cancelGoal":
                self.cancels[robot] += 1
                self.route(self.mc[robot].on_cancel(o.msg["data"]))
            elif leaf == "move_base_simple/goal":
                p = o.msg["pose"]["position"]
                self.goal_sent[robot] = (p["x"], p["y"])
            elif leaf == "move_base/cancel":
                self.goal_sent[robot] = None

    def step(self) -> None:
        """Every robot with a waypoint jumps to it; poses go to both cores."""
        self.clock.t += 0.5
        for r in sorted(self.mc):
            g = self.goal_sent[r]
            if g is not None:
                self.pose[r] = (g[0], g[1], 0.0)
                c = self.geo.cell_of(*g)
                if self.visited[r][-1] != c:
                    self.visited[r].append(c)
            self.route(self.mc[r].on_pose(*self.pose[r]))
            self.route(self.core.on_pose(r, *self.pose[r]))
        self.route(self.core.tick())

    def cells(self) -> dict[str, int]:
        return {r: self.geo.cell_of(*p[:2]) for r, p in self.pose.items()}


def test_compress_and_compressed_index():
    p = [5, 5, 6, 6, 6, 7, 8, 8]
    assert compress(p) == [5, 6, 7, 8]
    assert [compressed_index(p, k) for k in range(len(p))] == [0, 0, 1, 1, 1, 2, 3, 3]


def test_quaternion_roundtrip():
    for yaw in (-3.0, -1.0, 0.0, 0.5, 3.0):
        assert yaw_from_quaternion(quaternion_from_yaw(yaw)) == pytest.approx(yaw)


def test_plan_id_label():
    assert plan_id_of("plan 12") == 12 and plan_id_of("") == 0 and plan_id_of("cells") == 0


def test_cell_tracker_hysteresis(lab):
    t = CellTracker(lab, margin=0.1)
    x0, y0 = lab.center(9)
    x1, _ = lab.center(10)
    border = (x0 + x1) / 2
    assert t.update(x0, y0) == 9
    assert t.update(border + 0.05, y0) == 9        # just across the border: not yet
    assert t.update(border - 0.02, y0) == 9
    assert t.update(border + 0.12, y0) == 10       # well inside: switch
    assert t.update(border - 0.05, y0) == 10       # jitter back: stays
    assert t.update(float("nan"), y0) == 10


def test_obstacle_filter_needs_confirmation_and_skips_robots_and_walls(lab):
    f = ObstacleFilter(lab, min_points=3, confirm=2, window_s=5.0)
    cx, cy = lab.center(27)
    pts = [(cx + dx, cy) for dx in (-0.1, 0.0, 0.1)]
    obs = (cx - 1.0, cy)                           # observer one cell west
    assert f.update(obs, pts, 0.0, {"R1": obs}, [26], []) == []
    assert f.update(obs, pts, 1.0, {"R1": obs}, [26], []) == [27]
    # too few points, or a robot on them, or too far from the observer, or a robot in the cell
    assert f.update(obs, pts[:2], 2.0, {}, [], []) == []
    for t in (3.0, 4.0):
        assert f.update(obs, pts, t, {"R1": obs, "R2": (cx, cy)}, [], []) == []
        assert f.update((cx - 3.0, cy), pts, t, {}, [], []) == []
        assert f.update(obs, pts, t, {}, [27], []) == []
    # a point near an already blocked cell is that cell's box edge
    bx, by = lab.center(28)
    edge = [(bx - lab.cell_w_m / 2 - 0.05, by)] * 3
    for t in (5.0, 6.0):
        assert f.update(obs, edge, t, {}, [], [28]) == []
    # sightings older than the window do not count
    for t in (10.0, 20.0):
        assert f.update(obs, pts, t, {}, [], []) == []


def test_obstacle_filter_widens_a_robots_clearance_by_the_age_of_its_pose(lab):
    """A robot whose pose arrived late has moved on: the scan shows it up to its top speed times
    the lag away from that pose, and it must not block the cell it is driving through."""
    cx, cy = lab.center(27)
    obs = (cx - 1.0, cy)
    moved = [(cx + dx, cy) for dx in (-0.1, 0.0, 0.1)]        # where R2 is at the scan
    last = (cx - 0.6, cy)                                      # R2's last pose, 0.6 m behind
    for ages, want in (({"R2": 0.0}, [27]), ({"R2": 2.5}, []), ({"R2": -2.5}, [])):
        f = ObstacleFilter(lab, min_points=3, confirm=2, window_s=5.0, robot_speed=0.22)
        got = [f.update(obs, moved, t, {"R1": obs, "R2": last}, [], [], ages) for t in (0.0, 1.0)]
        assert got == [[], want], ages


def test_move_client_sends_next_waypoint_only_when_cleared(lab):
    mc = MoveClientCore("Robot1", lab)
    path = [8, 9, 10, 18]
    x, y = lab.center(8)
    assert mc.on_pose(x, y, 0.0) == []
    assert mc.progress()["state"] == "idle"
    assert mc.on_path(1, path) == []                       # nothing cleared yet
    assert mc.on_clearance(1, 0) == []                     # may stay where it is
    out = mc.on_clearance(1, 1)
    assert [o.topic for o in out] == ["/Robot1/move_base_simple/goal"]
    p = out[0].msg["pose"]["position"]
    assert (p["x"], p["y"]) == pytest.approx(lab.center(9))
    assert mc.progress()["state"] == "driving"
    # in cell 9 near its centre: 10 is not cleared -> no new goal
    x9, y9 = lab.center(9)
    assert mc.on_pose(x9 - 0.05, y9, 0.0) == []
    assert mc.progress()["state"] == "waiting" or mc.progress()["state"] == "driving"
    out = mc.on_clearance(1, 3)
    assert len(out) == 1 and out[0].msg["pose"]["position"]["x"] == pytest.approx(lab.center(10)[0])
    # straight on through 10 (9 -> 10 -> 18 turns at 10: must come near 10's centre first)
    x10, y10 = lab.center(10)
    assert mc.on_pose(x10 - 0.4, y10, 0.0) == []
    out = mc.on_pose(x10 - 0.1, y10, 0.0)
    assert len(out) == 1 and out[0].msg["pose"]["position"]["y"] == pytest.approx(lab.center(18)[1])
    x18, y18 = lab.center(18)
    mc.on_pose(x18, y18, 0.0)
    assert mc.progress()["state"] == "arrived" and mc.progress()["distance_left"] < 0.01
    assert mc.waypoints == 3


def test_move_client_straight_run_switches_on_entering_the_cell(lab):
    mc = MoveClientCore("Robot1", lab)
    mc.on_pose(*lab.center(8), 0.0)
    mc.on_path(1, [8, 9, 10, 11])
    mc.on_clearance(1, 3)
    x9, y9 = lab.center(9)
    out = mc.on_pose(x9 - 0.35, y9, 0.0)       # inside 9 (by 0.15 m), far from its centre
    assert len(out) == 1 and out[0].msg["pose"]["position"]["x"] == pytest.approx(lab.center(10)[0])


def test_move_client_cancel_stops_and_waits_for_a_new_plan(lab):
    mc = MoveClientCore("Robot1", lab)
    mc.on_pose(*lab.center(8), 0.0)
    mc.on_path(1, [8, 9, 10])
    mc.on_clearance(1, 2)
    out = mc.on_cancel(True)
    assert [o.topic for o in out] == ["/Robot1/move_base/cancel"] and out[0].msg == {"id": ""}
    assert mc.progress()["state"] == "cancelled" and mc.cancels == 1
    assert mc.on_clearance(1, 2) == []                    # the old plan's clearance is ignored
    assert mc.on_path(1, [8, 9, 10]) == []                # so is its path
    mc.on_path(2, [8, 16, 17])
    out = mc.on_clearance(2, 1)
    assert len(out) == 1 and out[0].msg["pose"]["position"]["y"] == pytest.approx(lab.center(16)[1])


def test_move_client_new_plan_keeps_a_committed_move_or_stops(lab):
    mc = MoveClientCore("Robot1", lab)
    mc.on_pose(*lab.center(8), 0.0)
    mc.on_path(1, [8, 9, 10])
    mc.on_clearance(1, 1)                       # driving to 9
    assert mc.target == 1
    assert mc.on_path(2, [8, 9, 17, 18]) == []   # 9 is still next: keep driving
    assert mc.target == 1
    out = mc.on_path(3, [8, 16, 24])             # 9 is not on it: stop first
    assert [o.topic for o in out] == ["/Robot1/move_base/cancel"] and mc.target == -1


def _run(fleet: VirtualFleet, goals: dict[str, int], rounds: int = 80, on_round=None) -> None:
    fleet.route(fleet.core.on_goals(goals))
    for i in range(rounds):
        if on_round:
            on_round(i)
        fleet.step()
        # no two robots ever in one cell (the planner's clearances keep them apart)
        cells = list(fleet.cells().values())
        assert len(cells) == len(set(cells)), (i, fleet.cells())
        if all(fleet.mc[r].progress()["state"] == "arrived" for r in goals):
            return
    raise AssertionError(f"not all arrived: {fleet.cells()} goals {goals}")


def test_virtual_fleet_reaches_goals_without_sharing_cells(tb3):
    starts = {"Robot1": 30, "Robot2": 14, "Robot3": 41}
    fleet = VirtualFleet(tb3, starts, lidar_blocking=False)
    _run(fleet, {"Robot1": 17, "Robot2": 25, "Robot3": 22})
    st = fleet.core.state()
    assert {r["robot"]: r["state"] for r in st["robots"]} == {"Robot1": "arrived", "Robot2": "arrived",
                                                              "Robot3": "arrived"}
    assert st["rows"] == 8 and len(st["free"]) == 64


def test_block_cancels_exactly_the_robots_whose_paths_crossed_it(tb3):
    starts = {"Robot1": 30, "Robot2": 46, "Robot3": 3}
    fleet = VirtualFleet(tb3, starts, lidar_blocking=False)
    crossed = {}

    def block(i):
        if i == 1:
            for r, path in fleet.core.fp.paths.items():
                crossed[r] = 26 in compress(path)[1:]
            fleet.route(fleet.core.on_block(26, True, "operator"))
    _run(fleet, {"Robot1": 17, "Robot2": 54, "Robot3": 4}, on_round=block)
    assert crossed["Robot1"] and not crossed["Robot2"]
    assert {r for r, hit in crossed.items() if hit} == {r for r, n in fleet.cancels.items() if n}
    for r, cells in fleet.visited.items():
        assert 26 not in cells[2:], (r, cells)
    st = fleet.core.state()
    assert st["blocked"] == [26] and st["blocked_by"] == ["operator"]
    assert {r["robot"]: r["cancels"] for r in st["robots"]}["Robot1"] == 1


def test_planner_messages_are_written_as_from_json_and_rosbags_write_them(tb3):
    """What the planner publishes (its fleet state with blocked cells, errors, a robot without a
    pose; its paths, clearances, cancels) takes the compiled JSON path (rce.messages.compiled) and
    gives the very bytes of the general path: from_json, then rosbags' serializer."""
    reg = MessageRegistry()
    load_package_types(reg)
    fleet = VirtualFleet(tb3, {"Robot1": 30, "Robot2": 46, "Robot3": 3}, lidar_blocking=False)
    fleet.core.add_robot("Robot4")                               # no pose yet: NaN x, y, yaw
    fleet.route(fleet.core.on_goals({"Robot9": 3, "Robot3": 0}))  # errors; Robot3 unreachable
    fleet.route(fleet.core.on_block(26, True, "operator"))
    _run(fleet, {"Robot1": 17, "Robot2": 54})
    outs = [(o.type, o.msg) for o in fleet.log] + [("fleet/FleetState", fleet.core.state())]
    state = outs[-1][1]
    assert state["blocked_by"] == ["operator"] and state["errors"] and len(state["robots"]) == 4
    for wire, msg in outs:
        t = reg.msg_type(wire)
        ref = bytes(reg.store.serialize_ros1(reg.from_json(t, msg), t))
        assert reg.json_to_bytes(t, msg) == ref, wire
    t = reg.msg_type("fleet/FleetState")
    assert reg.codec(t).serialize_json(state, RCE_FORMS) == bytes(reg.store.serialize_ros1(reg.from_json(t, state), t))


def test_unreachable_goal_is_reported_with_a_reason(tb3):
    fleet = VirtualFleet(tb3, {"Robot1": 30}, lidar_blocking=False)
    fleet.route(fleet.core.on_goals({"Robot1": 0}))             # a wall cell
    st = fleet.core.state()["robots"][0]
    assert st["state"] == "unreachable" and "not a free cell" in st["error"] and st["error_permanent"]
    assert any("Robot1" in e for e in fleet.core.state()["errors"])
    fleet.route(fleet.core.on_goals({"Robot9": 3, "Robot1": 999}))
    errs = fleet.core.state()["errors"]
    assert any("unknown robot 'Robot9'" in e for e in errs) and any("outside the 8x8 grid" in e for e in errs)


def test_lidar_points_block_a_cell_and_reroute(tb3):
    fleet = VirtualFleet(tb3, {"Robot1": 30}, lidar_blocking=True)
    fleet.route(fleet.core.on_goals({"Robot1": 17}))
    assert 28 in compress(fleet.core.fp.paths["Robot1"])
    cx, cy = tb3.center(28)
    pts = [(cx + d, cy) for d in (-0.05, 0.0, 0.05)]
    fleet.clock.t = 1.0
    fleet.route(fleet.core.on_obstacles("Robot1", pts))
    fleet.clock.t = 1.5
    fleet.route(fleet.core.on_obstacles("Robot1", pts))
    assert fleet.core.fp.blocked == {28: "lidar:Robot1"}
    assert 28 not in compress(fleet.core.fp.paths["Robot1"])
    assert fleet.cancels["Robot1"] == 1


def test_scans_from_before_an_unblock_do_not_block_the_cell_again(tb3):
    """The operator unblocks a cell whose box the robots' lidars still see: scans taken before
    the box went (in flight, or from a world that has not yet heard) arrive after the unblock.
    They do not block the cell again; an obstacle still there after ``clear_hold_s`` does."""
    fleet = VirtualFleet(tb3, {"Robot1": 30}, lidar_blocking=True)
    hold = fleet.core.obstacles.clear_hold_s
    fleet.route(fleet.core.on_goals({"Robot1": 17}))
    cx, cy = tb3.center(28)
    box = [(cx + d, cy + e) for d in (-0.05, 0.0, 0.05) for e in (-0.05, 0.05)]
    fleet.clock.t = 1.0
    fleet.route(fleet.core.on_block(28, True, "operator"))
    fleet.route(fleet.core.on_obstacles("Robot1", box))       # the box, inside a blocked cell: not sighted
    fleet.clock.t = 2.0
    fleet.route(fleet.core.on_block(28, False, "operator"))
    assert fleet.core.fp.blocked == {}
    for t in (2.05, 2.1, 2.2, 2.0 + 0.9 * hold):               # scans that still show the box
        fleet.clock.t = t
        fleet.route(fleet.core.on_obstacles("Robot1", box))
    assert fleet.core.fp.blocked == {} and 28 not in fleet.core.state()["blocked"]
    for t in (2.0 + 1.1 * hold, 2.0 + 1.2 * hold):             # it is still there: sighted as usual
        fleet.clock.t = t
        fleet.route(fleet.core.on_obstacles("Robot1", box))
    assert fleet.core.fp.blocked == {28: "lidar:Robot1"}


def test_lidar_reports_wait_until_every_robot_has_a_pose(tb3):
    """A robot the planner serves but that has no pose yet stands somewhere unknown: the points
    the others' lidars see there are not used (counted), until it reports its pose."""
    clock = Clock()
    core = GlobalPlannerCore(tb3, ["Robot1", "Robot2"], clock=clock, lidar_blocking=True)
    core.on_pose("Robot1", *tb3.center(30), 0.0)
    cx, cy = tb3.center(28)                  # Robot2, not yet localised, stands in cell 28
    pts = [(cx + d, cy) for d in (-0.05, 0.0, 0.05)]
    for t in (1.0, 1.5):
        clock.t = t
        assert core.on_obstacles("Robot1", pts) == []
    assert core.fp.blocked == {} and core.obstacle_reports_held == 2
    core.on_pose("Robot2", *tb3.center(20), 0.0)     # it was elsewhere; the points are an obstacle
    for t in (2.0, 2.5):
        clock.t = t
        core.on_obstacles("Robot1", pts)
    assert core.fp.blocked == {28: "lidar:Robot1"} and core.obstacle_reports_held == 2


def test_a_robot_that_never_reports_a_pose_holds_lidar_reports_only_so_long(tb3):
    """POSE_WAIT_S without a first pose from anyone, a robot still without one is taken to be away:
    one robot that never comes up does not turn the fleet's lidar blocking off for good."""
    clock = Clock()
    core = GlobalPlannerCore(tb3, ["Robot1", "Robot2", "Robot3"], clock=clock, lidar_blocking=True)
    cx, cy = tb3.center(28)
    pts = [(cx + d, cy) for d in (-0.05, 0.0, 0.05)]
    clock.t = 0.6 * POSE_WAIT_S
    core.on_pose("Robot1", *tb3.center(30), 0.0)          # the fleet still comes up: the wait starts again
    clock.t = 1.5 * POSE_WAIT_S
    assert core.on_obstacles("Robot1", pts) == [] and core.obstacle_reports_held == 1
    core.on_pose("Robot2", *tb3.center(20), 0.0)
    for dt in (0.0, 0.5):                                   # Robot3 never came up: its wait is over
        clock.t = 1.5 * POSE_WAIT_S + POSE_WAIT_S + 1.0 + dt
        core.on_obstacles("Robot1", pts)
    assert core.fp.blocked == {28: "lidar:Robot1"} and core.obstacle_reports_held == 1


def test_goal_before_first_pose_waits_for_it(tb3):
    core = GlobalPlannerCore(tb3, ["Robot1"], lidar_blocking=False)
    assert core.on_goals({"Robot1": 17}) == []
    assert core.state()["robots"][0]["goal"] == 17
    out = core.on_pose("Robot1", *tb3.center(30), 0.0)
    paths = [o for o in out if o.topic == "/Robot1/goalNodesList"]
    assert paths and paths[-1].msg["data"][0] == 30 and paths[-1].msg["data"][-1] == 17


def test_repeats_and_plan_ids(tb3):
    clock = Clock()
    core = GlobalPlannerCore(tb3, ["Robot1"], clock=clock, lidar_blocking=False)
    core.on_pose("Robot1", *tb3.center(30), 0.0)
    core.on_goals({"Robot1": 17})
    out = core.tick()
    assert {o.topic for o in out} == {"/Robot1/goalNodesList", "/Robot1/clearance"}
    clock.t += 0.1
    assert core.tick() == []
    clock.t += 0.5
    assert {o.topic for o in core.tick()} == {"/Robot1/clearance"}
    # moving along the path keeps the plan id; the clearance index grows in the same list
    plan = core.robots["Robot1"].plan
    cells = core.robots["Robot1"].cells
    out = core.on_pose("Robot1", *tb3.center(cells[1]), 0.0)
    assert core.robots["Robot1"].plan == plan
    assert all(o.topic != "/Robot1/goalNodesList" for o in out)


def test_no_obstacles_reported_at_the_map_border():
    """The simulator closes the map's border with walls; the robots' obstacle detector must
    count them as static even where the image's edge pixels are free (warehouse.yaml's bottom
    edge), or cells along the border get blocked by phantom lidar obstacles."""
    from rce_fleet.sim.obstacles import ObstacleDetector
    from rce_fleet.sim.world import SimWorld
    m = load_map(SHARED / "warehouse.yaml")
    geo = GridGeometry.from_cellgrid(make_grid(m, cell_m=1.2))
    world = SimWorld(m, seed=3)
    det = ObstacleDetector(m)
    bottom = [c for c in geo.free_cells() if geo.rc(c)[0] == geo.rows - 1]
    assert bottom
    for c in bottom[::3]:
        x, y = geo.center(c)
        r = world.add_robot(f"r{c}", x, y - 0.2, -1.57)
        assert det.detect(r.scan(), r.pose()) == [], c
        world.remove_robot(f"r{c}")


def test_planar_pose_reads_what_the_full_message_holds_and_refuses_what_it_refuses():
    """The nodes' pose reader (no message built) against the registry's full deserialization: the
    same x, y, yaw and stamp, any bytes in frame_id, and the same bytes refused."""
    from rce.messages import default_registry
    from rce.plumbing.errors import MessageError
    from rce_fleet.nodes.common import planar_pose

    reg = default_registry()
    t = reg.msg_type("geometry_msgs/PoseWithCovarianceStamped")
    for frame_id, yaw, sec in (("map", 0.7, 1_700_000_000), ("", -3.0, 0), ("x\udcff\udcfe", 2.5, -5)):
        q = quaternion_from_yaw(yaw)
        data = reg.serialize(t, reg.from_json(t, {
            "header": {"seq": 9, "stamp": {"secs": sec, "nsecs": 123_456_789}, "frame_id": frame_id},
            "pose": {"pose": {"position": {"x": 1.25, "y": -7.5, "z": 0.5}, "orientation": q},
                     "covariance": [float(i) for i in range(36)]}}))
        msg = reg.deserialize(t, data)
        p, st = msg.pose.pose, msg.header.stamp
        assert tuple(planar_pose(data)) == (p.position.x, p.position.y, yaw_from_quaternion(p.orientation),
                                            st.sec + st.nanosec * 1e-9)
        for bad in (data[:-1], data + b"\0", data[:10], b""):
            with pytest.raises(MessageError):
                reg.deserialize(t, bad)
            with pytest.raises(MessageError, match="geometry_msgs/PoseWithCovarianceStamped"):
                planar_pose(bad)
