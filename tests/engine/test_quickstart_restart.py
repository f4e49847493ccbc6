"""The README's quickstart, run for real and started again: ``rce-master --dev``, ``rce-robot``,
``rce-container`` and ``rce-ros configs/debug.config`` as a user runs them (fixed ports, the
dev master's own state file in the user's ``$XDG_STATE_HOME``), then ``rce-service call
stringEchoService``. Everything is stopped (SIGINT, as Ctrl-C in each terminal, the master
first; or kill -9 of every process; or kill -9 of the master alone) and started again: the echo
answers at once, and a 2013 client's ``createContainer`` of the config's container tag works on
the second run."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
from pathlib import Path

import pytest

from rce.tools.launch import command, wait_file
from wsclient import RawRobot

ROOT = Path(__file__).resolve().parents[2]
CALL_TIMEOUT = 60.0      # s an rce-service call may take (generous on a loaded 2-core machine; it answers in ms)
FIRST_START_ATTEMPTS = 3  # first starts, each on ports found free again, when another test took one meanwhile


def free_ports(n: int) -> list[int]:
    """``n`` distinct free TCP ports on loopback (bound together, then released)."""
    socks = [socket.socket() for _ in range(n)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


class PortTaken(RuntimeError):
    """A process of the quickstart exited before it was ready: another process held its port."""


class Quickstart:
    """The quickstart's four processes in a user's home ``home`` (XDG dirs under it)."""

    def __init__(self, home: Path):
        self.home = home
        self.http, self.control, self.ws, self.data = free_ports(4)
        self.env = dict(os.environ, HOME=str(home), XDG_CONFIG_HOME=str(home / "config"),
                        XDG_STATE_HOME=str(home / "state"), XDG_RUNTIME_DIR=str(home / "run"), RCE_LOG_JSON="1")
        for k in ("RCE_CLUSTER_KEY_FILE", "RCE_ADMIN_TOKEN"):
            self.env.pop(k, None)
        (home / "run").mkdir(parents=True, exist_ok=True)
        self.procs: dict[str, subprocess.Popen] = {}
        self.runs = 0
        self.bus = ""

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.http}/"

    def _spawn(self, name: str, argv: list[str], ready: bool = True) -> dict:
        log = open(self.home / f"{name}.{self.runs}.log", "wb")
        ready_file = self.home / f"{name}.{self.runs}.ready"
        p = subprocess.Popen(argv + (["--ready-file", str(ready_file)] if ready else []), env=self.env,
                             stdout=subprocess.PIPE if not ready else log, stderr=log, start_new_session=True)
        self.procs[name] = p
        try:
            return wait_file(ready_file, p, 60.0) if ready else {}
        except RuntimeError as e:
            if b"address already in use" in (self.home / f"{name}.{self.runs}.log").read_bytes():
                raise PortTaken(f"{name}: {e}") from None
            raise

    def start(self, ros: bool = True) -> None:
        """Terminals 1 to 4 (``ros``: with rce-ros); returns once rce-ros has printed its
        ``export RCE_BUS=...``. The ports were found free and released (:func:`free_ports`), so
        another test's server may bind one first: the first start then begins again on ports found
        free again (a process of ours that lost a port exits saying so). Later starts keep the ports,
        as a user's terminals do."""
        first = self.runs == 0
        for attempt in range(1, FIRST_START_ATTEMPTS + 1):
            try:
                return self._start(ros)
            except PortTaken:
                if not first or attempt == FIRST_START_ATTEMPTS:
                    raise
                self.kill_all()
                self.procs.clear()
                self.http, self.control, self.ws, self.data = free_ports(4)

    def _start(self, ros: bool) -> None:
        self.runs += 1
        self._spawn("master", [*command("rce-master"), "--dev", "--port", str(self.http),
                               "--control-port", str(self.control)])
        master = f"127.0.0.1:{self.control}"
        self._spawn("robot", [*command("rce-robot"), master, "--port", str(self.ws), "--data-port", str(self.data),
                              "--metrics-port", "0", "--rosbridge-port", "0"])
        self._spawn("container", [*command("rce-container"), master, "--runtime-dir", str(self.home / "rt")])
        if not ros:
            self.procs.pop("ros", None)
            return
        self._spawn("ros", [*command("rce-ros"), str(ROOT / "configs" / "debug.config"), "--url", self.url],
                    ready=False)
        out = self.procs["ros"].stdout
        for raw in out:                      # rce-ros prints the export line once its setup is done
            line = raw.decode(errors="replace").strip()
            if line.startswith("export RCE_BUS="):
                self.bus = line.split("=", 1)[1]
                return
        raise AssertionError(f"rce-ros exited ({self.procs['ros'].wait()}) before its setup was done:\n"
                             + self.logs())

    def call_echo(self, text: str) -> dict:
        """Terminal 5: ``rce-service call stringEchoService '{data: TEXT}'``; its answer."""
        r = subprocess.run([*command("rce-service"), "call", "stringEchoService", json.dumps({"data": text}),
                            "--bus", self.bus], env=self.env, capture_output=True, timeout=CALL_TIMEOUT)
        assert r.returncode == 0, f"rce-service failed: {r.stdout!r} {r.stderr!r}\n{self.logs()}"
        return _parse_answer(r.stdout.decode())

    def stop(self, sig: int, only: str | None = None) -> None:
        """Send ``sig`` to every process (the master first, as terminal 1 is the first one), or to
        ``only``; wait for each to exit."""
        names = [only] if only else ["master", "robot", "container", "ros"]
        for name in [n for n in names if n in self.procs]:
            p = self.procs[name]
            if p.poll() is None:
                p.send_signal(sig)
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
                raise AssertionError(f"{name} did not exit on signal {sig} within 30 s") from None
            if p.stdout:
                p.stdout.close()

    def restart_master(self) -> None:
        self._spawn("master", [*command("rce-master"), "--dev", "--port", str(self.http),
                               "--control-port", str(self.control)])

    def kill_all(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
            p.wait()
            if p.stdout:
                p.stdout.close()

    def logs(self) -> str:
        return "\n".join(f"== {p.name}\n{p.read_text(errors='replace')[-3000:]}"
                         for p in sorted(self.home.glob("*.log")))


def _parse_answer(text: str) -> dict:
    """rce-service prints the response as YAML-like ``key: value`` lines (or JSON)."""
    import yaml
    return yaml.safe_load(text)


@pytest.fixture
def quickstart(tmp_path):
    q = Quickstart(tmp_path / "home")
    yield q
    q.kill_all()


async def _create_container_2013(r: RawRobot) -> None:
    """The 2013 client's ``createContainer`` of the config's tag: it must succeed (no ER). Its DC of
    a missing tag is a marker: its ER comes after the CC's answer."""
    await r.send("CC", {"containerTag": "cTag_01"})
    await r.send("DC", {"containerTag": "noSuchMarker"})
    while True:
        m = await r.recv(30.0)
        if isinstance(m, dict) and m.get("type") == "ER":
            assert "noSuchMarker" in m["data"], f"createContainer failed: {m['data']}"
            return


@pytest.mark.parametrize("how", ["sigint", "kill-9"])
async def test_quickstart_stopped_and_started_again_echoes_at_once(quickstart, how):
    q = quickstart
    q.start()
    assert q.call_echo("hello") == {"data": "hello"}
    state = q.home / "state" / "rce"
    assert (state / f"dev-master-{q.http}.sqlite3").exists()
    assert not (state / "master.sqlite3").exists(), "rce-master --dev wrote the user's default state file"
    if how == "sigint":
        q.stop(signal.SIGINT)
    else:
        q.kill_all()
    q.start()
    assert q.call_echo("hello again") == {"data": "hello again"}


async def test_quickstart_master_killed_alone_and_restarted_echoes_at_once(quickstart):
    q = quickstart
    q.start()
    assert q.call_echo("before") == {"data": "before"}
    q.stop(signal.SIGKILL, only="master")
    q.restart_master()
    assert q.call_echo("after") == {"data": "after"}
    assert q.procs["ros"].poll() is None, "rce-ros gave up while the master was away"


async def test_2013_client_creates_its_container_again_after_a_full_stop(quickstart):
    """A 2013 client creates cTag_01 and is still connected when every process is stopped with
    SIGINT; on the second run its ``createContainer`` of the same tag works."""
    q = quickstart
    q.start(ros=False)
    async with RawRobot(q.url, "robot2013") as r:
        await _create_container_2013(r)
        q.stop(signal.SIGINT)
    q.start(ros=False)
    async with RawRobot(q.url, "robot2013") as r:
        await _create_container_2013(r)


def test_a_port_taken_before_the_first_start_starts_it_again_on_ports_found_free_again(quickstart):
    """Another process listens on the robot endpoint's port before the first start (as another test's
    server can, between finding the port free and our process binding it): rce-robot exits saying
    so, and the quickstart starts again on ports found free again; a later start would keep them."""
    q = quickstart
    first_ws = q.ws
    taken = socket.socket()
    taken.bind(("127.0.0.1", first_ws))
    taken.listen()
    try:
        q.start(ros=False)
    finally:
        taken.close()
    assert q.runs == 2 and q.ws != first_ws
    assert b"address already in use" in (q.home / "robot.1.log").read_bytes()
    assert all(p.poll() is None for p in q.procs.values()), q.logs()
