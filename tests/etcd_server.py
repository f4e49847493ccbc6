"""A real etcd for tests (Debian's ``etcd-server``, ``/usr/bin/etcd``): one member on loopback,
on ephemeral ports, in a directory of the test; ready once its ``/health`` answers and the member
answering is this one (its name, from ``/v3/cluster/member/list``).

The ports are found free, released, then bound by etcd, so another test's server may take one in
between (pytest-xdist runs several at once). Then etcd exits ("address already in use") while the
other server answers on the port: a start that checked only ``/health`` would hand the test the
other etcd, and :meth:`EtcdServer.pause` would stop a process that is not the one answering. So
the start checks whose member answers, and starts again on new ports when its etcd lost a port
(at most :data:`START_ATTEMPTS` times).

::

    with EtcdServer(tmp_path / "etcd") as etcd:
        etcd.url          # etcd://127.0.0.1:PORT (rce-master --store)
        etcd.endpoint     # http://127.0.0.1:PORT

A machine without etcd fails the test (never skips it) with the install hint.
"""
from __future__ import annotations

import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

READY_TIMEOUT = 30.0     # s for etcd to answer /health (it takes < 1 s; a busy CI machine may take longer)
HEALTH_TIMEOUT = 1.0     # s, one /health request
POLL_INTERVAL = 0.05     # s between /health polls
STOP_TIMEOUT = 10.0      # s etcd may take to exit on SIGTERM before it is killed
START_ATTEMPTS = 3       # starts on new ports after etcd lost one of its ports to another server
INSTALL_HINT = ("etcd is not installed: the tests of several masters run a real etcd. Install Debian's "
                "etcd-server (`apt-get install etcd-server`; `make setup` does it when run as root, "
                "through .ci/system-deps)")


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now (bound to port 0, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def etcd_binary() -> str:
    """The etcd executable; fails the test with :data:`INSTALL_HINT` when there is none."""
    exe = shutil.which("etcd") or ("/usr/bin/etcd" if Path("/usr/bin/etcd").is_file() else None)
    if exe is None:
        pytest.fail(INSTALL_HINT, pytrace=False)
    return exe


class EtcdServer:
    """One etcd member in ``workdir`` (its data and log), started by :meth:`start` (or ``with``)."""

    def __init__(self, workdir: Path):
        self.workdir = Path(workdir)
        self.proc: subprocess.Popen | None = None
        self.port = self.peer_port = 0
        self.name = f"rce-test-{os.getpid()}-{secrets.token_hex(4)}"    # its member's, told from any other's
        self._log_from = 0       # where this start's lines begin in etcd.log

    @property
    def endpoint(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def url(self) -> str:
        """``etcd://127.0.0.1:PORT``, for ``rce-master --store``."""
        return f"etcd://127.0.0.1:{self.port}"

    def start(self) -> "EtcdServer":
        """Start etcd and wait until it answers as itself (at most :data:`READY_TIMEOUT` s). Raises
        RuntimeError when etcd exits for another reason than a port taken, or lost a port
        :data:`START_ATTEMPTS` times; TimeoutError when it is not ready in time."""
        exe = etcd_binary()
        self.workdir.mkdir(parents=True, exist_ok=True)
        for attempt in range(START_ATTEMPTS):
            if attempt:
                shutil.rmtree(self.workdir / "data", ignore_errors=True)    # what the lost start began
            self.port, self.peer_port = free_port(), free_port()
            client, peer = f"http://127.0.0.1:{self.port}", f"http://127.0.0.1:{self.peer_port}"
            argv = [exe, "--name", self.name, "--data-dir", str(self.workdir / "data"),
                    "--listen-client-urls", client, "--advertise-client-urls", client,
                    "--listen-peer-urls", peer, "--initial-advertise-peer-urls", peer,
                    "--initial-cluster", f"{self.name}={peer}"]
            with open(self.workdir / "etcd.log", "ab") as log:
                self._log_from = log.tell()
                self.proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
            if self._wait_ready():
                return self
        raise RuntimeError(f"etcd lost one of its ports to another server {START_ATTEMPTS} times:\n{self.log()}")

    def _wait_ready(self) -> bool:
        """True once ``/health`` answers healthy and the member answering is this one; False when
        etcd exited because one of its ports was taken."""
        deadline = time.monotonic() + READY_TIMEOUT
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                if b"address already in use" in (self.workdir / "etcd.log").read_bytes()[self._log_from:]:
                    return False
                raise RuntimeError(f"etcd exited with {self.proc.returncode} before it was ready:\n{self.log()}")
            try:
                with urllib.request.urlopen(self.endpoint + "/health", timeout=HEALTH_TIMEOUT) as r:
                    healthy = json.loads(r.read()).get("health") == "true"
                if healthy and self.member_name() == self.name and self.proc.poll() is None:
                    return True
            except (urllib.error.URLError, OSError, ValueError, KeyError, TypeError):
                pass
            time.sleep(POLL_INTERVAL)
        raise TimeoutError(f"etcd did not answer {self.endpoint}/health within {READY_TIMEOUT} s:\n{self.log()}")

    def member_name(self) -> str | None:
        """The name of the member that answers on :attr:`endpoint` (``/v3/cluster/member/list``).
        Raises OSError, ValueError, KeyError or TypeError when it does not answer or answers
        something else."""
        request = urllib.request.Request(self.endpoint + "/v3/cluster/member/list", data=b"{}", method="POST")
        with urllib.request.urlopen(request, timeout=HEALTH_TIMEOUT) as r:
            answer = json.loads(r.read())
        me = answer["header"]["member_id"]
        return next((m.get("name") for m in answer.get("members", []) if m.get("ID") == me), None)

    def pause(self) -> None:
        """SIGSTOP: etcd stops answering (a partition, as its clients see it)."""
        self.proc.send_signal(signal.SIGSTOP)

    def resume(self) -> None:
        """SIGCONT after :meth:`pause`."""
        self.proc.send_signal(signal.SIGCONT)

    def stop(self) -> None:
        """Stop etcd (SIGTERM, then SIGKILL after :data:`STOP_TIMEOUT` s)."""
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.send_signal(signal.SIGCONT)
        self.proc.terminate()
        try:
            self.proc.wait(STOP_TIMEOUT)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()

    def log(self) -> str:
        """The last 3,000 characters of etcd's log (every start's, in order)."""
        path = self.workdir / "etcd.log"
        return path.read_text(errors="replace")[-3000:] if path.exists() else ""

    def __enter__(self) -> "EtcdServer":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
