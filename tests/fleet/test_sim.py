"""rce_fleet.sim: walls from maps, differential drive, lidar, odometry,
localisation stand-in, local navigation (DWA) and obstacle detection."""
from __future__ import annotations

import math
import struct
import time
from pathlib import Path

import numpy as np
import pytest

from rce_fleet.maps.occupancy import OccupancyMap, load_map
from rce_fleet.sim.lidar import LidarParams, scan_to_points
from rce_fleet.sim.local_nav import LocalNavigator
from rce_fleet.sim.obstacles import ObstacleDetector
from rce_fleet.sim.walls import blocked_mask, merge_rectangles
from rce_fleet.sim.world import SimWorld
from rce_fleet.sim.walls import rasterise

ROOT = Path(__file__).resolve().parents[2]
MAPS = ROOT.parent / "shared" / "data" / "maps"

R = 0.105  # TurtleBot3 burger radius, m


def room(w_px: int = 120, h_px: int = 120, res: float = 0.05, wall: int = 3,
         origin=(0.0, 0.0, 0.0)) -> OccupancyMap:
    """A free room with `wall`-pixel walls; interior [wall*res, (w_px-wall)*res]."""
    occ = np.zeros((h_px, w_px), np.int8)
    occ[:wall, :] = 100
    occ[-wall:, :] = 100
    occ[:, :wall] = 100
    occ[:, -wall:] = 100
    return OccupancyMap(occ, res, origin)


def corridor(length_px: int = 200, width_px: int = 9, res: float = 0.05) -> tuple[OccupancyMap, float]:
    """A straight corridor along x, `width_px` pixels wide; returns (map, centre y)."""
    h = width_px + 20
    occ = np.full((h, length_px), 100, np.int8)
    occ[10:10 + width_px, 3:-3] = 0
    centre_y = (h - 10 - width_px / 2.0) * res
    return OccupancyMap(occ, res, (0.0, 0.0, 0.0)), centre_y


def drive(world: SimWorld, navs: dict[str, LocalNavigator], t_max: float,
          control_dt: float = 0.1, scan_every: int = 2, on_step=None) -> float:
    """Closed loop: navigators at 1/control_dt Hz, scans every `scan_every`
    control periods; returns the minimum robot pair distance seen."""
    md = math.inf
    k = 0
    while world.time < t_max - 1e-9:
        for rid, nav in navs.items():
            robot = world.robots[rid]
            pose = robot.localisation()[:3]
            scan = robot.scan() if k % scan_every == 0 else None
            robot.cmd_vel(*nav.update(pose, control_dt, scan))
        world.step(control_dt)
        k += 1
        md = min(md, world.min_pair_distance())
        if on_step is not None:
            on_step()
        if all(n.state == "reached" for n in navs.values()):
            break
    return md


# -- walls ------------------------------------------------------------------

def test_merge_rectangles_exactly_cover_random_masks():
    rng = np.random.default_rng(0)
    for _ in range(60):
        shape = (int(rng.integers(1, 40)), int(rng.integers(1, 40)))
        mask = rng.random(shape) < rng.random()
        rects = merge_rectangles(mask)
        cover = rasterise(rects, shape)
        assert np.array_equal(cover, mask.astype(np.int32))  # exact and disjoint


def test_merge_rectangles_few_for_walls_and_unknown():
    occ = np.zeros((200, 300), np.int8)
    occ[:40, :] = -1  # unknown band: treated as occupied
    occ[100:110, 20:280] = 100  # a thick wall
    occ[60:190, 150:153] = 100  # a crossing wall
    mask = blocked_mask(occ)
    rects = merge_rectangles(mask)
    assert np.array_equal(rasterise(rects, mask.shape), mask.astype(np.int32))
    assert len(rects) <= 6
    assert mask.sum() > 1000 * len(rects)


def test_world_walls_match_map_coordinates():
    # Origin off zero: pixel (row, col) covers x in [ox+col*res, ...], row 0 at the top.
    occ = np.zeros((40, 60), np.int8)
    occ[10:12, 30:40] = 100
    m = OccupancyMap(occ, 0.1, (-2.0, 1.0, 0.0))
    world = SimWorld(m, seed=0)
    assert len(world.wall_rects) == 1
    # The wall spans x in [1.0, 2.0], y in [1.0 + (40-12)*0.1, 1.0 + (40-10)*0.1] = [3.8, 4.0].
    assert not world.is_free(1.5, 3.9)
    assert world.is_free(1.5, 3.75)
    assert world.is_free(1.5, 4.05)
    assert world.is_free(0.95, 3.9)
    # Outside the image is closed by border walls.
    assert not world.is_free(-2.05, 2.0)
    assert world.bounds == pytest.approx((-2.0, 1.0, 4.0, 5.0))


def test_real_map_turtlebot3_world_builds():
    from rce_fleet.maps.occupancy import load_map

    m = load_map(MAPS / "turtlebot3_world.yaml")
    world = SimWorld(m, seed=0)
    mask = blocked_mask(m.occupancy)
    assert np.array_equal(rasterise(world.wall_rects, mask.shape), mask.astype(np.int32))
    assert len(world.wall_rects) < mask.sum() / 100
    # The world is centred on the origin; the robot's spawn in the TurtleBot3
    # simulation (-2.0, -0.5) is free and the lidar sees the hexagon's pillars.
    assert world.is_free(-2.0, -0.5, R)
    robot = world.add_robot("r", -2.0, -0.5, 0.0)
    scan = robot.scan()
    assert np.isfinite(scan).sum() > 100


def test_real_map_warehouse_builds_fast():
    from rce_fleet.maps.occupancy import load_map

    m = load_map(MAPS / "warehouse.yaml")
    t0 = time.perf_counter()
    world = SimWorld(m, seed=0)
    build = time.perf_counter() - t0
    n_px = int(blocked_mask(m.occupancy).sum())
    print(f"\nwarehouse.yaml: {m.occupancy.shape[1]}x{m.occupancy.shape[0]} px, "
          f"{n_px} blocked px -> {len(world.wall_rects)} rectangles, world built in {build:.3f} s")
    assert len(world.wall_rects) < 5000
    assert build < 5.0  # generous for slow CI; typically ~0.06 s
    # Ten robots in free space scan at real-time rates.
    rng = np.random.default_rng(1)
    x0, y0, x1, y1 = world.bounds
    while len(world.robots) < 10:
        x, y = rng.uniform(x0, x1), rng.uniform(y0, y1)
        if m.occupancy[m.world_to_pixel(x, y)] == 0 and world.is_free(x, y, 0.3):
            world.add_robot(f"r{len(world.robots)}", x, y, rng.uniform(-math.pi, math.pi))
    t0 = time.perf_counter()
    for _ in range(5):
        for r in world.robots.values():
            r.scan()
    per_scan = (time.perf_counter() - t0) / 50
    for r in world.robots.values():
        r.cmd_vel(0.2, 0.3)
    t0 = time.perf_counter()
    n = world.step(2.0)
    steps_per_s = n / (time.perf_counter() - t0)
    print(f"scan: {per_scan * 1e3:.2f} ms/robot; physics with 10 robots: {steps_per_s:.0f} substeps/s")


# -- drive, lidar, odometry, localisation ------------------------------------

def test_robot_reaches_max_speed_and_accelerates_limited():
    world = SimWorld(room(), seed=0)
    robot = world.add_robot("r", 1.0, 3.0, 0.0)
    robot.cmd_vel(5.0, 0.0)  # clipped to 0.22 m/s
    world.step(0.04)
    assert 0.0 < robot.velocity()[0] < 0.22  # ramping at 2.5 m/s^2
    world.step(0.96)
    assert robot.velocity()[0] == pytest.approx(0.22, abs=1e-6)
    x1 = robot.pose()[0]
    world.step(2.0)
    assert (robot.pose()[0] - x1) / 2.0 == pytest.approx(0.22, abs=0.002)
    assert robot.pose()[1] == pytest.approx(3.0, abs=1e-6)


@pytest.mark.parametrize("yaw", [0.0, 0.4])
def test_wall_stops_robot(yaw):
    world = SimWorld(room(), seed=0)  # right wall's inner face at x = 5.85
    robot = world.add_robot("r", 4.5, 3.0, yaw)
    robot.cmd_vel(0.22, 0.0)
    max_x = 0.0
    for _ in range(200):  # 20 s: would be 4.4 m without the wall
        world.step(0.1)
        max_x = max(max_x, robot.pose()[0])
    assert max_x <= 5.85 - R + 0.003
    assert max_x > 5.85 - R - 0.01  # it did get there


def test_robot_cannot_turn_or_push_through_a_box():
    world = SimWorld(room(), seed=0)
    world.add_box("b", 3.0, 3.0, 0.3, 0.3)
    robot = world.add_robot("r", 2.0, 3.0, 0.0)
    robot.cmd_vel(0.22, 0.0)
    world.step(10.0)
    assert robot.pose()[0] <= 3.0 - 0.15 - R + 0.003
    assert world.remove_box("b") and not world.remove_box("b")
    world.step(3.0)
    assert robot.pose()[0] > 3.0


def test_lidar_matches_room_geometry():
    sigma = 0.01
    world = SimWorld(room(), seed=5, lidar_params=LidarParams(noise_std=sigma))
    px, py, yaw = 3.0, 1.2, 0.3
    robot = world.add_robot("r", px, py, yaw)
    scan = robot.scan()
    assert scan.shape == (360,) and scan.dtype == np.float32
    lo, hi = 0.15, 5.85  # interior of the room
    a = yaw + np.arange(360) * 2 * math.pi / 360
    c, s = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0, (hi - px) / c, np.where(c < 0, (lo - px) / c, np.inf))
        ty = np.where(s > 0, (hi - py) / s, np.where(s < 0, (lo - py) / s, np.inf))
    expected = np.minimum(tx, ty)
    in_range = expected < 3.5 - 5 * sigma
    out = expected > 3.5 + 5 * sigma
    assert in_range.sum() > 100 and out.sum() > 50
    err = scan[in_range] - expected[in_range]
    assert np.abs(err).max() < 5 * sigma
    assert abs(err.mean()) < 0.003
    assert 0.5 * sigma < err.std() < 1.5 * sigma
    assert np.all(np.isposinf(scan[out]))
    # Beam 0 looks straight ahead; the beams turn counter-clockwise.
    assert scan[0] == pytest.approx(expected[0], abs=5 * sigma)


def test_lidar_sees_boxes_and_robots_not_itself():
    world = SimWorld(room(), seed=1, lidar_params=LidarParams(noise_std=0.0))
    robot = world.add_robot("a", 2.0, 3.0, 0.0)
    assert np.nanmin(np.abs(robot.scan())) > 1.0  # own body is invisible
    world.add_box("b", 3.0, 3.0, 0.2, 0.2)  # face at x = 2.9
    world.add_robot("other", 2.0, 4.0, 0.0)  # 1 m to the left
    scan = robot.scan()
    assert scan[0] == pytest.approx(0.9, abs=1e-6)
    assert scan[90] == pytest.approx(1.0 - R, abs=1e-6)
    world.add_box("close", 2.135, 3.0, 0.05, 1.0)  # face 0.11 m ahead: < range_min
    assert np.isneginf(robot.scan()[0])


def test_odometry_drifts_little_and_is_seeded():
    def run(seed):
        world = SimWorld(room(), seed=seed)
        robot = world.add_robot("r", 1.0, 1.0, 0.0)
        robot.cmd_vel(0.22, 0.0)
        world.step(8.0)  # ~1.75 m
        robot.cmd_vel(0.1, 1.0)
        world.step(2.0)
        robot.cmd_vel(0.22, 0.0)
        world.step(5.0)
        return robot.pose(), robot.odom()

    (tx, ty, tyaw), (ox, oy, oyaw, v, w) = run(3)
    assert math.hypot(ox - tx, oy - ty) < 0.06
    assert abs(math.remainder(oyaw - tyaw, 2 * math.pi)) < 0.05
    assert (ox, oy) != (tx, ty)  # there is some noise
    assert v == pytest.approx(0.22, abs=1e-6) and w == pytest.approx(0.0, abs=1e-9)
    assert run(3)[1] == (ox, oy, oyaw, v, w)  # reproducible
    assert run(4)[1] != (ox, oy, oyaw, v, w)


def test_localisation_bounded_with_covariance():
    world = SimWorld(room(), seed=2)
    robot = world.add_robot("r", 3.0, 3.0, 0.0)
    robot.cmd_vel(0.0, 0.5)
    errors = []
    for _ in range(300):
        world.step(0.2)
        x, y, yaw, cov = robot.localisation()
        tx, ty, tyaw = robot.pose()
        errors.append((x - tx, y - ty, math.remainder(yaw - tyaw, 2 * math.pi)))
    e = np.abs(np.array(errors))
    assert e[:, :2].max() <= 0.06 + 1e-9 and e[:, 2].max() <= 0.06 + 1e-9  # 3 sigma bound
    assert e[:, :2].max() > 0.005  # but not zero
    assert len(cov) == 36 and all(isinstance(c, float) for c in cov)
    c = np.array(cov).reshape(6, 6)
    assert np.allclose(c, c.T) and c[0, 0] > 0 and c[1, 1] > 0 and c[5, 5] > 0


def test_step_uses_fixed_substeps():
    world = SimWorld(room(), seed=0, substep=0.02)
    assert world.step(0.01) == 0 and world.time == 0.0
    assert world.step(0.01) == 1
    assert world.step(1.0) == 50
    assert world.time == pytest.approx(1.02)


# -- local navigation --------------------------------------------------------

def test_navigator_reaches_goal_in_free_space():
    world = SimWorld(room(), seed=0)
    robot = world.add_robot("r", 1.0, 1.0, math.pi)  # facing away from the goal
    nav = LocalNavigator()
    assert nav.state == "idle" and nav.update(robot.pose(), 0.1) == (0.0, 0.0)
    nav.set_goal(4.5, 4.0)
    assert nav.state == "driving"
    drive(world, {"r": nav}, 60.0)
    assert nav.state == "reached"
    x, y, _ = robot.pose()
    assert math.hypot(x - 4.5, y - 4.0) < 0.08 + 0.06  # tolerance + localisation error
    assert world.time < 30.0  # ~4.6 m at 0.22 m/s plus turning and slowing down
    assert nav.update(robot.localisation()[:3], 0.1) == (0.0, 0.0)
    # Then a goal with a yaw.
    nav.set_goal(1.0, 4.5, math.pi / 2)
    drive(world, {"r": nav}, world.time + 60.0)
    assert nav.state == "reached"
    assert abs(math.remainder(robot.pose()[2] - math.pi / 2, 2 * math.pi)) < 0.1 + 0.06


def test_navigator_cancel_stops():
    world = SimWorld(room(), seed=0)
    robot = world.add_robot("r", 1.0, 3.0, 0.0)
    nav = LocalNavigator()
    nav.set_goal(5.0, 3.0)
    drive(world, {"r": nav}, 3.0)
    assert robot.velocity()[0] > 0.2
    nav.cancel()
    assert nav.state == "idle"
    drive(world, {"r": nav}, 4.0)
    assert robot.velocity()[0] == pytest.approx(0.0, abs=1e-9)


def box_gap(robot, bx, by, half) -> float:
    x, y, _ = robot.pose()
    return math.hypot(max(abs(x - bx) - half, 0.0), max(abs(y - by) - half, 0.0)) - R


def test_navigator_steers_around_box_without_contact():
    world = SimWorld(room(), seed=0)
    robot = world.add_robot("r", 1.0, 3.0, 0.0)
    world.add_box("b", 3.0, 3.0, 0.4, 0.4)
    nav = LocalNavigator()
    nav.set_goal(5.0, 3.0)
    gaps = []
    drive(world, {"r": nav}, 60.0, on_step=lambda: gaps.append(box_gap(robot, 3.0, 3.0, 0.2)))
    assert min(gaps) > 0.02  # never touched the box
    assert nav.state == "reached"


def test_navigator_stops_and_reports_blocked_in_front_of_box():
    m, cy = corridor(width_px=12)  # 0.6 m wide: no way around a box across it
    world = SimWorld(m, seed=0)
    robot = world.add_robot("r", 1.0, cy, 0.0)
    nav = LocalNavigator()
    nav.set_goal(8.0, cy)
    drive(world, {"r": nav}, 8.0)  # up to full speed first
    assert nav.state == "driving" and robot.velocity()[0] > 0.2
    world.add_box("b", 4.0, cy, 0.3, 0.6)  # drops ~2 m ahead
    gaps = []
    drive(world, {"r": nav}, 40.0, on_step=lambda: gaps.append(box_gap(robot, 4.0, cy, 0.15)))
    assert min(gaps) > 0.02
    assert nav.state == "blocked"
    assert abs(robot.velocity()[0]) < 0.01
    # The box goes away: the robot carries on.
    world.remove_box("b")
    drive(world, {"r": nav}, 90.0)
    assert nav.state == "reached"


def test_two_robots_head_on_pass_without_overlap():
    world = SimWorld(room(), seed=0)
    world.add_robot("a", 1.0, 3.0, 0.0)
    world.add_robot("b", 5.0, 3.0, math.pi)
    na, nb = LocalNavigator(), LocalNavigator()
    na.set_goal(5.0, 3.0)
    nb.set_goal(1.0, 3.0)
    md = drive(world, {"a": na, "b": nb}, 80.0)
    assert md >= 2 * R - 0.005
    assert na.state == nb.state == "reached"


def test_two_robots_head_on_in_corridor_stop_without_overlap():
    m, cy = corridor(width_px=9)  # 0.45 m: too narrow to pass
    world = SimWorld(m, seed=0)
    world.add_robot("a", 1.0, cy, 0.0)
    world.add_robot("b", 8.0, cy, math.pi)
    na, nb = LocalNavigator(), LocalNavigator()
    na.set_goal(8.0, cy)
    nb.set_goal(1.0, cy)
    md = drive(world, {"a": na, "b": nb}, 50.0)
    assert md >= 2 * R - 0.005
    assert na.state == nb.state == "blocked"


def test_ten_robots_swap_places_without_overlap():
    world = SimWorld(room(), seed=0)
    rng = np.random.default_rng(0)
    pts: list[np.ndarray] = []
    while len(pts) < 10:
        p = rng.uniform(0.5, 5.5, 2)
        if all(np.hypot(*(p - q)) > 0.5 for q in pts):
            pts.append(p)
    navs = {}
    for i, p in enumerate(pts):
        world.add_robot(f"r{i}", p[0], p[1], rng.uniform(-math.pi, math.pi))
        navs[f"r{i}"] = LocalNavigator()
        navs[f"r{i}"].set_goal(*pts[(i + 3) % 10])
    md = drive(world, navs, 90.0)
    assert md >= 2 * R - 0.005
    assert sum(n.state == "reached" for n in navs.values()) >= 8


# -- obstacle detection --------------------------------------------------------

def test_detected_obstacles_drop_static_walls_and_known_robots():
    m = room()
    world = SimWorld(m, seed=0)
    robot = world.add_robot("r", 2.0, 3.0, 0.0)
    world.add_robot("other", 2.0, 4.0, 0.0)
    nav = LocalNavigator(obstacle_detector=ObstacleDetector(m))
    pose = robot.localisation()[:3]
    scan = robot.scan()
    # Without a box: walls are filtered, the other robot is excluded by disc.
    assert nav.detected_obstacles(scan, pose, exclude=[(2.0, 4.0, R + 0.1)]) == []
    assert len(nav.detected_obstacles(scan, pose)) > 5  # the other robot is seen
    world.add_box("b", 3.5, 3.0, 0.4, 0.4)
    pts = np.array(nav.detected_obstacles(robot.scan(), pose, exclude=[(2.0, 4.0, R + 0.1)]))
    assert len(pts) > 5
    assert np.all(np.abs(pts[:, 0] - 3.3) < 0.08)  # the box's near face
    assert np.all(np.abs(pts[:, 1] - 3.0) < 0.25)
    # Without a detector every hit comes back, in world coordinates.
    all_hits = LocalNavigator().detected_obstacles(robot.scan(), pose)
    assert len(all_hits) == len(scan_to_points(robot.scan(), pose, include_too_close=False))


def _public_ranges(robot) -> np.ndarray:
    lidar = robot.lidar
    lidar.fast = False
    try:
        return lidar.true_ranges(*robot.pose(), robot.shape.filter)
    finally:
        lidar.fast = True


def _same_ranges(fast: np.ndarray, slow: np.ndarray) -> bool:
    return np.array_equal(np.isinf(fast), np.isinf(slow)) and np.allclose(fast, slow, rtol=0, atol=1e-9)


def test_lidar_fast_path_matches_public_pymunk_api():
    world = SimWorld(room(), seed=0)
    world.add_box("b", 3.0, 3.5, 0.3, 0.6)
    robot = world.add_robot("a", 2.0, 3.0, 0.2)
    world.add_robot("other", 2.5, 2.2, 0.0)
    fast = robot.lidar.true_ranges(*robot.pose(), robot.shape.filter)
    assert _same_ranges(fast, _public_ranges(robot))
    assert np.isfinite(fast).sum() > 180


@pytest.mark.parametrize("seed", [0, 1])
def test_lidar_caster_matches_pymunk_on_the_warehouse(seed):
    """The compiled ray caster finds what pymunk's segment query finds, beam for beam: the
    warehouse's 2,084 wall rectangles, boxes and 60 robots, robots standing anywhere (also inside
    a box, or overlapping another robot: hit at 0 there, as chipmunk), after moves and box changes."""
    world = SimWorld(load_map(MAPS / "warehouse.yaml"), seed=seed)
    rng = np.random.default_rng(seed)
    x0, y0, x1, y1 = world.bounds
    robots = []
    while len(robots) < 60:
        x, y = rng.uniform(x0 + 0.2, x1 - 0.2), rng.uniform(y0 + 0.2, y1 - 0.2)
        if world.is_free(x, y, R):
            robots.append(world.add_robot(f"r{len(robots)}", x, y, rng.uniform(-math.pi, math.pi)))
    # a robot inside a box, and a box over two robots' centres
    bx, by = robots[0].pose()[:2]
    world.add_box("on-r0", bx, by, 0.5, 0.5)
    world.add_box("between", *np.mean([robots[1].pose()[:2], robots[2].pose()[:2]], axis=0), 0.3, 0.3)
    for r in robots[3:]:
        r.cmd_vel(0.22, rng.uniform(-1, 1))
    seen = 0
    for _ in range(2):
        for r in robots:
            fast = r.lidar.true_ranges(*r.pose(), r.shape.filter)
            assert _same_ranges(fast, _public_ranges(r)), r.robot_id
            seen += int(np.isfinite(fast).sum())
        world.step(1.0)
        world.remove_box("between")
    assert (robots[0].lidar.true_ranges(*robots[0].pose(), robots[0].shape.filter) == 0).all()
    assert seen > 60 * 360 // 2


def test_arc_clearance_matches_a_kd_tree():
    """The local planner's compiled clearance gives the distances scipy's k-d tree gives, inf
    from the bound on, for the navigator's own arcs and hits around the robot."""
    from scipy.spatial import cKDTree

    from rce_fleet.sim.clearance import arc_clearance
    nav = LocalNavigator()
    rng = np.random.default_rng(0)
    for v_cap in (0.22, 0.05):
        _, _, _, ax, ay = nav._arcs(v_cap)
        for n_pts in (1, 40, 300):
            pts = rng.uniform(-1.1, 1.1, (n_pts, 2))
            bound = 0.505
            want, _ = cKDTree(pts).query(np.column_stack((ax.ravel(), ay.ravel())), distance_upper_bound=bound)
            want = want.reshape(ax.shape).min(axis=1)
            got = arc_clearance(ax, ay, pts, bound)
            assert np.array_equal(np.isinf(got), np.isinf(want))
            assert np.allclose(got, want, rtol=0, atol=1e-12)
            assert np.isfinite(got).any()


def test_normal_block_hands_out_the_generators_own_sequence():
    from rce_fleet.sim.noise import NormalBlock
    one = np.random.default_rng(7)
    block = NormalBlock(np.random.default_rng(7), 3, rows=5)
    assert [block.next() for _ in range(12)] == [one.normal(0.0, 1.0, 3).tolist() for _ in range(12)]


def test_points_wire_packs_what_the_registry_serialises():
    """The simulator's obstacles bytes are the message registry's for the same message."""
    from rce.messages import default_registry
    from rce_fleet.live.points_wire import PointsWire
    reg = default_registry()
    t = reg.msg_type("geometry_msgs/PoseArray")
    rng = np.random.default_rng(0)
    wire = PointsWire("map")
    for secs, nsecs in ((0, 0), (12, 500_000_000), (2 ** 31 - 1, 999_999_999)):
        for n in (0, 1, 120):
            pts = rng.uniform(-20, 20, (n, 2))
            msg = {"header": {"stamp": {"secs": secs, "nsecs": nsecs}, "frame_id": "map"},
                   "poses": [{"position": {"x": x, "y": y}, "orientation": {"w": 1.0}} for x, y in pts.tolist()]}
            assert wire.pack(secs, nsecs, pts) == reg.json_to_bytes(t, msg)
    with pytest.raises(struct.error):
        wire.pack(2 ** 31, 0, np.zeros((1, 2)))


def test_simulated_batteries_start_spread_below_the_initial_level():
    from rce.messages import default_registry
    from rce_fleet.live.simhost import SimHost
    from rce_fleet.maps.geometry import GridGeometry
    from rce_fleet.maps.grid import fleet_grid
    from rce_fleet.maps.lab_map import lab_map
    from rce_fleet.operations.battery import BatteryParams
    occ = lab_map()
    geo = GridGeometry.from_cellgrid(fleet_grid(occ)[0])
    host = SimHost(occ, geo, default_registry(), seed=3,
                   battery=BatteryParams(capacity_wh=10.0, initial=0.6, initial_spread=0.4))
    cells = geo.free_cells()[:6]
    levels = [host.spawn(f"Robot{i}", int(c)).battery.fraction for i, c in enumerate(cells, 1)]
    assert all(0.2 - 1e-9 <= x <= 0.6 + 1e-9 for x in levels) and max(levels) - min(levels) > 0.05
