"""How ``make test`` spreads the suite over pytest-xdist workers (``--dist loadfile``).

A test file runs in one worker, so that module-scoped engines are started once. Two changes to
xdist's plain ``loadfile`` keep a 2-core machine busy to the end instead of waiting on one long
file started last:

- **Longest first.** The files and tests in :data:`LONG_FIRST` (about 20 s or more each, most of it
  waiting on simulated or real time) are handed out first, in that order (longest first); the rest
  keep their collection order. xdist's default reorder (files with the most tests first) would start
  them last. The order is the workers' collection order (:func:`order_items`, called from
  ``pytest_collection_modifyitems``): xdist sends a worker the indexes of its tests in the collection
  the scheduler was given, and the worker runs those indexes of its own collection, so the two must be
  the same list (sorted on the scheduler's side alone, a worker ran other tests than the scheduler
  handed it, and a file's tests ran on several workers, each starting the file's shared engine).
- **Spread.** The files in :data:`SPREAD` have no module-scoped fixture (each test starts its own
  engine), so their tests are separate work units and may run on different workers.

Add a file to these lists when ``--durations`` shows it among the longest."""
from __future__ import annotations

from xdist.scheduler import LoadScopeScheduling

LONG_FIRST = (
    "tests/web/test_web_fleet.py",
    "tests/fleet/test_fleet_tasks_api.py",
    "tests/bench/test_faults_smoke.py",
    "tests/bench/test_placement_smoke.py",
    "tests/fleet/test_oneshot_pp.py::test_lacam_along_one_way_lanes",
    "tests/fleet/test_spacetime.py::test_the_lns_bench_on_the_clock_of_work",
    "tests/engine/test_resume.py",
    "tests/bench/test_fleet_load_smoke.py",
    "tests/web/test_web_tasks.py",
    "tests/web/test_web_stall.py",
    "tests/client/test_ros2_bridge.py",
    "tests/container/test_ros2_nodes.py",
    "tests/fleet/test_fleet_ros2.py",
    "tests/security/test_fleet_doors.py",
    "tests/engine/test_rosbridge_ros2.py",
    "tests/fleet/test_fleet_orphans.py",
    "tests/fleet/test_lifelong_cli.py::test_bench_lifelong_quick",
    "tests/fleet/test_fleet_e2e.py::test_ten_robots",
    "tests/fleet/test_lifelong_output.py",
    "tests/fleet/test_lifelong_planner.py",
    "tests/fleet/test_movingai_unseen.py",
    "tests/fleet/test_demo_default.py",
    "tests/engine/test_dataflow.py",
    "tests/web/test_foxglove.py",
    "tests/fleet/test_oneshot_pp.py::test_forked_processes_killed",
    "tests/fleet/test_lorr_unseen.py",
    "tests/fleet/test_fleet_edge.py",
    "tests/bench/test_bench_smoke.py::test_paper_experiments",
    "tests/fleet/test_lifelong_cli.py::test_bench_lifelong_generates",
    "tests/security/test_tls.py",
    "tests/fleet/test_fleet_coverage.py",
    "tests/engine/test_master_standby.py",
    "tests/engine/test_failover.py",
    "tests/fleet/test_fleet_tasks_bench.py",
    "tests/web/test_web_relays.py",
    "tests/web/test_web_roles.py",
    "tests/fleet/test_fleet_users_api.py",
    "tests/fleet/test_sim.py",
    "tests/fleet/test_fleet_bag.py",
    "tests/container/test_sandbox.py",
    "tests/engine/test_console.py",
    "tests/engine/test_relay_single.py",
    "tests/fleet/test_fleet_faults.py",
    "tests/fleet/test_fleet_e2e.py",
    "tests/engine/test_quickstart_restart.py",
    "tests/client/test_ros1_bridge.py",
    "tests/engine/test_direct_links.py",
    "tests/security/test_fuzz.py",
    "tests/client/test_e2e_debug.py",
    "tests/security/test_hostile_input.py",
    "tests/engine/test_lanes_netns.py",
    "tests/fleet/test_battery_charging.py",
    "tests/engine/test_placement.py",
    "tests/engine/test_master_restart.py",
    "tests/engine/test_move_netns.py",
    "tests/fleet/test_fleet_blocked_errand.py",
    "tests/web/test_web_warehouse.py",
    "tests/bench/test_bench_smoke.py",
    "tests/fleet/test_oneshot_pp.py",
    "tests/fleet/test_spacetime.py",
    "tests/fleet/test_lifelong_cli.py",
    "tests/engine/test_relay.py",
    "tests/container/test_container.py",
    "tests/bench/test_lanes_smoke.py",
    "tests/engine/test_sandbox_engine.py",
    "tests/engine/test_endpoint_failover.py",
)
SPREAD = (
    "tests/bench/test_bench_smoke.py",
    "tests/fleet/test_fleet_e2e.py",
    "tests/engine/test_quickstart_restart.py",
    "tests/fleet/test_fleet_faults.py",
    "tests/fleet/test_oneshot_pp.py",
    "tests/fleet/test_spacetime.py",
    "tests/fleet/test_lifelong_cli.py",
    "tests/fleet/test_lifelong_output.py",
    "tests/fleet/test_fleet_edge.py",
    "tests/engine/test_relay.py",
    "tests/container/test_container.py",
)


def rank(nodeid: str) -> int:
    """Position of ``nodeid`` in the hand-out order: the index of the first :data:`LONG_FIRST`
    prefix it starts with, else ``len(LONG_FIRST)`` (after all of them)."""
    return next((i for i, p in enumerate(LONG_FIRST) if nodeid.startswith(p)), len(LONG_FIRST))


def order_items(items: list) -> None:
    """Sort collected ``items`` (in place) into the hand-out order: by :func:`rank`, stable, so a
    file's tests stay together and in their order."""
    items.sort(key=lambda item: rank(item.nodeid))


class LongFirstFileScheduling(LoadScopeScheduling):
    """xdist's ``loadfile`` on the collection in :func:`order_items` order (kept, not reordered by
    size), with :data:`SPREAD` files split per test."""

    def __init__(self, config, log=None) -> None:
        super().__init__(config, log)
        config.option.loadscopereorder = False          # keep the collection's order (order_items)

    def _split_scope(self, nodeid: str) -> str:
        path = nodeid.split("::", 1)[0]
        return nodeid if path in SPREAD else path
