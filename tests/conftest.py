"""Shared fixtures: the real engine as processes on loopback."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from rce.tools.launch import Engine, start_engine  # noqa: E402

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture
def engine(tmp_path: Path):
    """A fresh engine per test: master (--dev: testUser/testUser), one robot task set, one container host."""
    e = start_engine(tmp_path / "engine")
    yield e
    e.stop()


@pytest.fixture(scope="module")
def shared_engine(tmp_path_factory):
    """One engine for a whole test module (tests must use distinct robot IDs and container tags)."""
    e = start_engine(tmp_path_factory.mktemp("engine"))
    yield e
    e.stop()


from rce_robot.ws_link import DEFAULT_IMPL, IMPLS as WS_IMPLS  # noqa: E402  rce-robot --ws-impl: both stay tested


@pytest.fixture(scope="module", params=WS_IMPLS)
def engine_ws_impls(request, shared_engine, tmp_path_factory):
    """The module's engine (rce-robot on its default websocket library), then one whose rce-robot runs
    the other (``--ws-impl``): a test that takes this runs on both."""
    if request.param == DEFAULT_IMPL:
        yield shared_engine
        return
    e = start_engine(tmp_path_factory.mktemp(f"engine-{request.param}"), robot_args=("--ws-impl", request.param))
    yield e
    e.stop()


@pytest.fixture(params=WS_IMPLS)
def engine_each_ws_impl(request, tmp_path: Path):
    """A fresh engine per test (as :func:`engine`) whose rce-robot runs each websocket library in turn."""
    e = start_engine(tmp_path / "engine", robot_args=("--ws-impl", request.param))
    yield e
    e.stop()


def pytest_runtest_makereport(item, call):
    """Attach the engine's process logs to a failing test's report."""
    if call.when == "call" and call.excinfo is not None:
        for name in ("engine", "shared_engine", "engine_ws_impls", "engine_each_ws_impl", "eng"):
            e = item.funcargs.get(name) if hasattr(item, "funcargs") else None
            if isinstance(e, Engine):
                item.add_report_section("call", "engine logs", e.log_text())


def pytest_sessionstart(session):
    """The real maps and benchmark data live in ../shared/data (never copied into the repository).
    Tests that use them must not silently skip: say clearly what is missing instead."""
    if not SHARED_DATA.is_dir():
        raise pytest.UsageError(f"{SHARED_DATA} is missing: the tests read the real maps and MAPF data from "
                                "../shared/data beside the project (see the project's shared folder)")


def pytest_collection_modifyitems(config, items):
    """Under ``--dist loadfile``, the workers collect the tests in the order the scheduler hands them
    out (tests/xdist_order.py): the scheduler names a test by its index in that collection."""
    if config.getvalue("dist") == "loadfile":
        from xdist_order import order_items
        order_items(items)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile`` hands out the longest files first and splits some per test (tests/xdist_order.py)."""
    if config.getvalue("dist") == "loadfile":
        from xdist_order import LongFirstFileScheduling
        return LongFirstFileScheduling(config, log)
    return None
