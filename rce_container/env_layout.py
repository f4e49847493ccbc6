"""What the container task set and its environments (:mod:`rce_container.environment`) agree on
without the task set importing the environment (and with it the bus and the message registry):
where a container's files and bus socket are, and a bus call's default timeout."""
from __future__ import annotations

from pathlib import Path

SOCKET_NAME = "bus.sock"
BUS_CALL_TIMEOUT = 10.0   # s a bus_call waits for the service when the request gives no timeout
MAX_SOCKET_PATH = 107     # bytes, sun_path minus the NUL


def container_paths(runtime_dir: Path, socket_dir: Path, cid: int) -> tuple[Path, Path]:
    """(private workdir, bus socket path) of container ``cid``: the one place the layout lives."""
    return Path(runtime_dir) / f"c{cid}", Path(socket_dir) / f"c{cid}" / SOCKET_NAME
