"""The engine launcher (:mod:`rce.tools.launch`) that the fleet demo, the benches and the tests
start engines with: a workdir used before starts a working engine again."""
from __future__ import annotations

from pathlib import Path

from rce.tools.launch import start_engine


def test_an_engine_starts_again_in_the_workdir_of_a_stopped_one(tmp_path):
    """The ready files of the last run (with its dead ports) are not taken for the new run's."""
    first = start_engine(tmp_path, container_hosts=0)
    first.stop()
    second = start_engine(tmp_path, container_hosts=0)
    try:
        assert second.master.poll() is None
        assert second.admin("/api/robots") is not None       # answers on the port it reported
        assert second.robot_ready[0]["pid"] == second.procs[1].pid     # the new robot task set's file
    finally:
        second.stop()


def test_a_relative_workdir_is_given_to_the_processes_as_an_absolute_path(tmp_path, monkeypatch):
    """The container host's runtime dir and the state file are found whatever the processes' cwd."""
    monkeypatch.chdir(tmp_path)
    eng = start_engine("engine", robot_tasksets=0, container_hosts=1)
    try:
        assert eng.workdir == tmp_path / "engine"
        host = [p for p in eng.procs if "--runtime-dir" in p.args][0]
        assert Path(host.args[host.args.index("--runtime-dir") + 1]).is_absolute()
        assert eng.alive() == []
    finally:
        eng.stop()
