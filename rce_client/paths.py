"""Where a robot's local bus socket lives (shared by ``rce-ros`` and the bus tools)."""
from __future__ import annotations

import os
from pathlib import Path


def bus_dir() -> Path:
    """``$XDG_RUNTIME_DIR/rce`` when set, else ``/tmp/rce-<uid>``."""
    base = os.environ.get("XDG_RUNTIME_DIR")
    return Path(base) / "rce" if base else Path(f"/tmp/rce-{os.getuid()}")


def default_bus_path(robot_id: str) -> str:
    """Default local bus socket of robot ``robot_id``: ``<bus_dir>/<robotID>.sock``."""
    return str(bus_dir() / f"{robot_id}.sock")


def running_buses() -> list[str]:
    """Socket files in :func:`bus_dir` (those of running ``rce-ros`` processes, or stale ones)."""
    d = bus_dir()
    try:
        return sorted(str(p) for p in d.glob("*.sock") if p.is_socket())
    except OSError:
        return []
