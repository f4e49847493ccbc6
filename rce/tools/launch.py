"""The engine launcher: start the real engine (rce-master, rce-robot, rce-container) as
processes on loopback with ephemeral ports, for the fleet demo, tests and benchmarks. Readiness comes from each
process's ``--ready-file``, never from sleeping. Every process it starts gets SIGTERM when the launching
process ends, however it ends (:func:`rce.plumbing.process.popen_tied`), and stops its own children then.

::

    e = start_engine(workdir)            # master --dev (testUser/testUser), 1 robot task set, 1 container host
    e.master_url                          # http://127.0.0.1:PORT/
    e.kill_master(); e.restart_master()   # kill -9, then the same master again on its ports (and --state file)
    e.stop()

    e = start_engine(workdir, tls=True)   # https:// and wss:// with a throw-away CA: e.ca_file, e.master_url https://
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rce.transport import tls as _tls
from rce.transport.cluster_auth import KEY_ENV, ClusterKey
from rce.tools.admin_client import AdminClient
from rce.plumbing.process import create_private_file, popen_tied

__all__ = ["BIN", "Engine", "start_engine", "wait_file", "command"]

BIN = Path(sys.executable).parent
_MODULES = {"rce-master": "rce_master.cli", "rce-robot": "rce_robot.cli", "rce-container": "rce_container.cli"}


def command(name: str) -> list[str]:
    """argv prefix that runs console script ``name`` (rce-master, ...) of this installation:
    the script next to this interpreter, else on PATH, else ``python -m`` its module."""
    for cand in (BIN / name, shutil.which(name)):
        if cand and Path(cand).is_file():
            return [str(cand)]
    return [sys.executable, "-c", f"import sys, {_MODULES[name]} as m; sys.argv[0] = {name!r}; m.main()"]


def wait_file(path: Path, proc: subprocess.Popen, timeout: float = 30.0) -> dict:
    """Wait until ``path`` exists (JSON) or ``proc`` dies; returns the JSON."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists():
            try:
                return json.loads(path.read_text())
            except ValueError:      # being written
                pass
        if proc.poll() is not None:
            raise RuntimeError(f"{proc.args[0]} exited with {proc.returncode} before it was ready")
        time.sleep(0.02)
    raise TimeoutError(f"{proc.args[0]} not ready within {timeout} s")


@dataclass
class Engine:
    """A running engine: ``master_url`` (http://127.0.0.1:PORT/), ``admin_token``, process handles;
    ``masters``: the control addresses (``HOST:PORT``) task sets added from now on are given
    (default: the first master's; several masters: add theirs); ``ca_file``: with TLS, the CA that
    signed the engine's certificate (:func:`rce.transport.tls.make_dev_certificates`), else None;
    ``tls_args``: the ``--tls-cert``/``--tls-key`` arguments every robot task set is given."""
    workdir: Path
    env: dict
    procs: list[subprocess.Popen] = field(default_factory=list)
    master_url: str = ""
    control_port: int = 0
    admin_token: str = ""
    robot_ready: list[dict] = field(default_factory=list)
    logs: list[Path] = field(default_factory=list)
    masters: list[str] = field(default_factory=list)
    master: subprocess.Popen | None = None      # the running rce-master (None after kill_master)
    master_args: tuple = ()                     # its extra arguments, given again by restart_master
    restarts: int = 0
    ca_file: Path | None = None
    tls_args: tuple = ()
    cluster_key_file: Path | None = None        # the engine's cluster key (every process gets it: RCE_CLUSTER_KEY_FILE)
    _admin_ssl: Any = field(default=None, repr=False)   # admin()'s TLS context, made on first use

    @property
    def cluster_key(self) -> ClusterKey:
        """The engine's cluster key, for a test that opens internal links itself."""
        return ClusterKey.load(self.cluster_key_file)

    def _start_master(self, http_port: int, control_port: int, timeout: float = 30.0) -> dict:
        name = f"master{self.restarts}" if self.restarts else "master"
        ready = self.workdir / f"{name}.ready"
        self.master, info = self.spawn(name, [*command("rce-master"), "--dev", "--port", str(http_port),
                                              "--control-port", str(control_port), "--ready-file", str(ready),
                                              *self.master_args], ready, timeout)
        return info

    def kill_master(self) -> None:
        """kill -9 the master and reap it. It leaves ``procs``, so :meth:`alive` does not count it."""
        p, self.master = self.master, None
        if p is not None:
            p.send_signal(signal.SIGKILL)
            p.wait()
            self.procs.remove(p)

    def restart_master(self, timeout: float = 30.0) -> None:
        """Start the master again, with the same arguments (``--state`` file, ...) on the same ports;
        returns once it is ready (its ready file) within ``timeout`` s; raises TimeoutError, or
        RuntimeError when it exits first (e.g. its ports are taken)."""
        self.restarts += 1
        self._start_master(self.http_port, self.control_port, timeout)

    @property
    def http_port(self) -> int:
        """The master's HTTP (login, admin API) port."""
        return int(self.master_url.rsplit(":", 1)[1].strip("/"))

    def admin(self, path: str, body: dict | None = None, method: str | None = None):
        """Call the master's admin API (:class:`~rce.tools.admin_client.AdminClient`): GET ``path`` (or
        POST ``body``); returns the JSON answer. A refusal raises the :class:`~rce.plumbing.errors.RCEError`
        subclass for its HTTP status with the master's reason (:mod:`rce.tools.admin_client`)."""
        if self._admin_ssl is None:       # made once: loading the CAs costs ~30 ms a call, which tests feel
            self._admin_ssl = _tls.client_context(self.ca_file)
        client = AdminClient(self.master_url, self.admin_token, ssl_context=self._admin_ssl)
        return client.request(method or ("POST" if body is not None else "GET"), path, body)

    def spawn(self, name: str, argv: list[str], ready: Path | None = None,
              timeout: float = 30.0) -> tuple[subprocess.Popen, dict]:
        log = self.workdir / f"{name}.log"
        self.logs.append(log)
        if ready:       # a workdir used before holds the last run's file, with its dead ports
            ready.unlink(missing_ok=True)
        # tied to this process: a launcher killed with SIGKILL leaves no engine process running
        p = popen_tied(argv, stdout=open(log, "wb"), stderr=subprocess.STDOUT, env=self.env, start_new_session=True)
        self.procs.append(p)
        info = wait_file(ready, p, timeout) if ready else {}
        return p, info

    def add_robot_taskset(self, *extra: str) -> dict:
        n = len(self.robot_ready)
        ready = self.workdir / f"robot{n}.ready"
        _, info = self.spawn(f"robot{n}", [*command("rce-robot"), ",".join(self.masters),
                                           "--port", "0", "--data-port", "0", "--metrics-port", "0",
                                           "--rosbridge-port", "0", "--foxglove-port", "0", "--ready-file", str(ready),
                                           *self.tls_args,
                                           *extra], ready)
        self.robot_ready.append(info)
        return info

    def add_container_host(self, *extra: str) -> subprocess.Popen:
        n = sum(1 for p in self.procs
                if any("rce-container" in str(a) or "rce_container" in str(a) for a in p.args[:3]))
        ready = self.workdir / f"container{n}.ready"
        p, _ = self.spawn(f"container{n}", [*command("rce-container"), ",".join(self.masters),
                                            "--runtime-dir", str(self.workdir / f"rt{n}"),
                                            "--ready-file", str(ready), *extra], ready)
        return p

    def alive(self) -> list[str]:
        """Names of engine processes that have exited (empty when all run)."""
        return [str(p.args[0]) for p in self.procs if p.poll() is not None]

    def stop(self) -> None:
        for p in reversed(self.procs):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in reversed(self.procs):
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()

    def log_text(self) -> str:
        return "\n".join(f"== {p.name}\n{p.read_text(errors='replace')[-4000:]}" for p in self.logs if p.exists())


def start_engine(workdir: Path | None = None, *, robot_tasksets: int = 1, container_hosts: int = 1,
                 master_args: tuple = (), robot_args: tuple = (), container_args: tuple = (),
                 admin_token: str = "test-admin-token", env: dict | None = None, tls: bool = False,
                 tls_hosts: tuple[str, ...] = ("127.0.0.1", "localhost")) -> Engine:
    """Start master (``--dev``), robot task set(s) and container host(s); returns the :class:`Engine`.

    ``env`` is added to the processes' environment (``os.environ`` plus the admin token,
    JSON logs, the engine's cluster key (``workdir/cluster-key``, in ``RCE_CLUSTER_KEY_FILE``), and a
    private ``XDG_CONFIG_HOME`` and ``XDG_STATE_HOME``); the master's state file is the engine's own,
    ``workdir/master.sqlite3``, unless ``master_args`` name a ``--state`` or ``--store``. ``tls``: the
    master serves https:// and the robot task sets wss://, with a certificate for 127.0.0.1 made for
    this engine (in ``workdir/tls``; its CA in ``ca_file``), or for ``tls_hosts``."""
    workdir = Path(workdir or tempfile.mkdtemp(prefix="rce-engine-")).resolve()   # processes get absolute paths
    workdir.mkdir(parents=True, exist_ok=True)
    key_file = workdir / "cluster-key"
    create_private_file(key_file, ClusterKey.generate().secret.hex() + "\n")
    penv = dict(os.environ, RCE_ADMIN_TOKEN=admin_token, RCE_LOG_JSON="1", **{KEY_ENV: str(key_file)},
                XDG_CONFIG_HOME=str(workdir / "config"), XDG_STATE_HOME=str(workdir / "state"), **(env or {}))
    if "--state" not in master_args and "--store" not in master_args:    # restart_master comes back to it
        master_args = ("--state", str(workdir / "master.sqlite3"), *master_args)
    e = Engine(workdir, penv, admin_token=admin_token, master_args=tuple(master_args), cluster_key_file=key_file)
    if tls:
        certs = _tls.make_dev_certificates(workdir / "tls", tls_hosts)
        e.ca_file, e.tls_args = certs.ca, ("--tls-cert", str(certs.cert), "--tls-key", str(certs.key))
        e.master_args += e.tls_args
    info = e._start_master(0, 0)
    e.master_url = f"{'https' if tls else 'http'}://127.0.0.1:{info['http_port']}/"
    e.control_port = info["control_port"]
    e.masters = [f"127.0.0.1:{e.control_port}"]
    try:
        for _ in range(robot_tasksets):
            e.add_robot_taskset(*robot_args)
        for _ in range(container_hosts):
            e.add_container_host(*container_args)
    except Exception:
        e.stop()
        raise
    return e
