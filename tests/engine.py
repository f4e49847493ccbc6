"""Start the real engine (rce-master, rce-robot, rce-container) as processes on loopback
with ephemeral ports, for tests and benchmarks. Readiness comes from each process's
``--ready-file``, never from sleeping.

The implementation lives in :mod:`rce_fleet.launch` (the fleet demo starts the engine the
same way); this module keeps the tests' and benchmarks' imports working."""
from __future__ import annotations

from rce_fleet.launch import BIN, Engine, command, start_engine, wait_file  # noqa: F401

__all__ = ["BIN", "Engine", "start_engine", "wait_file", "command"]
