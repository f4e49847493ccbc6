"""How ``make test`` spreads the suite over pytest-xdist workers (``--dist loadfile``).

A test file runs in one worker, so that module-scoped engines are started once. Two changes to
xdist's plain ``loadfile`` keep a 2-core machine busy to the end instead of waiting on one long
file started last:

- **Longest first.** The files and tests in :data:`LONG_FIRST` (about 15 s or more each, most of it
  waiting on simulated or real time) are handed out first, in that order; the rest keep their
  collection order. xdist's default reorder (files with the most tests first) would start them last.
- **Spread.** The files in :data:`SPREAD` have no module-scoped fixture (each test starts its own
  engine), so their tests are separate work units and may run on different workers.

Add a file to these lists when ``--durations`` shows it among the longest."""
from __future__ import annotations

from xdist.scheduler import LoadScopeScheduling

LONG_FIRST = (
    "tests/bench/test_faults_smoke.py",
    "tests/fleet/test_fleet_e2e.py::test_ten_robots",
    "tests/bench/test_bench_smoke.py::test_paper_experiments",
    "tests/bench/test_fleet_load_smoke.py",
    "tests/fleet/test_fleet_e2e.py",
    "tests/fleet/test_fleet_bag.py",
    "tests/engine/test_quickstart_restart.py",
    "tests/bench/test_bench_smoke.py",
    "tests/fleet/test_fleet_faults.py",
    "tests/fleet/test_fleet_coverage.py",
    "tests/web/test_web_fleet.py",
    "tests/web/test_web_relays.py",
    "tests/client/test_e2e_debug.py",
    "tests/security/test_fuzz.py",
    "tests/fleet/test_battery_charging.py",
    "tests/fleet/test_fleet_blocked_errand.py",
    "tests/engine/test_relay.py",
    "tests/engine/test_relay_single.py",
    "tests/fleet/test_demo_default.py",
    "tests/web/test_web_warehouse.py",
    "tests/bench/test_lanes_smoke.py",
    "tests/fleet/test_fleet_tasks_bench.py",
    "tests/engine/test_direct_links.py",
    "tests/engine/test_sandbox_engine.py",
    "tests/engine/test_endpoint_failover.py",
)
SPREAD = (
    "tests/bench/test_bench_smoke.py",
    "tests/fleet/test_fleet_e2e.py",
    "tests/engine/test_quickstart_restart.py",
    "tests/fleet/test_fleet_faults.py",
)


def rank(nodeid: str) -> int:
    """Position of ``nodeid`` in the hand-out order: the index of the first :data:`LONG_FIRST`
    prefix it starts with, else ``len(LONG_FIRST)`` (after all of them)."""
    return next((i for i, p in enumerate(LONG_FIRST) if nodeid.startswith(p)), len(LONG_FIRST))


class LongFirstFileScheduling(LoadScopeScheduling):
    """xdist's ``loadfile`` with the longest work units first and :data:`SPREAD` files split per test."""

    def __init__(self, config, log=None) -> None:
        super().__init__(config, log)
        config.option.loadscopereorder = False          # keep the order add_node_collection gives

    def add_node_collection(self, node, collection) -> None:
        super().add_node_collection(node, sorted(collection, key=rank))     # stable: ties keep collection order

    def _split_scope(self, nodeid: str) -> str:
        path = nodeid.split("::", 1)[0]
        return nodeid if path in SPREAD else path
