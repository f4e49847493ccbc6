"""What a person at a terminal sees when the cloud refuses: ``rce-fleet task`` and ``rce-ros`` run on a
pseudo-terminal against a real engine print human lines (no JSON log records) and each error from
the cloud exactly once (the client logs an error at WARNING only when no caller reports it)."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from ptyrun import run_on_a_terminal
from rce.tools.launch import start_engine

BIN = Path(sys.executable).parent
RUN_TIMEOUT_S = 60


@pytest.fixture(scope="module")
def engine(tmp_path_factory):
    e = start_engine(tmp_path_factory.mktemp("engine"))
    yield e
    e.stop()


def human(out: str) -> list[str]:
    lines = [ln.strip() for ln in out.splitlines() if ln.strip()]
    assert not [ln for ln in lines if ln.startswith("{")], "no JSON log records on a terminal:\n" + out
    return lines


def test_task_cli_says_a_cloud_error_once(engine, tmp_path):
    code, out = run_on_a_terminal([str(BIN / "rce-fleet"), "task", "list", "--master", engine.master_url,
                                   "--timeout", "10"], tmp_path, RUN_TIMEOUT_S)
    assert code != 0
    lines = human(out)
    said = [ln for ln in lines if "container 'cTag_01' does not exist" in ln]
    assert len(said) == 1 and said[0].startswith("rce-fleet task: cannot attach"), out


def test_rce_ros_says_a_cloud_error_once(engine, tmp_path):
    cfg = tmp_path / "robot.config"
    cfg.write_text(json.dumps({"url": engine.master_url, "userID": "testUser", "password": "testUser",
                               "robotID": "R1", "containers": [{"cTag": "c1"}],
                               "nodes": [{"cTag": "c1", "nTag": "n", "pkg": "Nope", "exe": "nope.py"}]}))
    code, out = run_on_a_terminal([str(BIN / "rce-ros"), str(cfg), "--bus", str(tmp_path / "R1.sock")], tmp_path,
                                  RUN_TIMEOUT_S, interrupt_after="package 'Nope' not found")
    lines = human(out)
    said = [ln for ln in lines if "package 'Nope' not found" in ln]
    assert len(said) == 1 and said[0].startswith("rce-ros: error from the cloud"), out
    assert any(ln.startswith("rce-ros: ready") for ln in lines) and "rce-ros: stopping" in out
