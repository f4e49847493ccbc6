"""End to end: the original engine's debug sample (configs/debug.config) on the real engine.

``rce-ros`` runs as a real process against the ``engine`` fixture's master; ``rce-topic`` and
``rce-service`` run as real processes on the robot's local bus it prints, and on the container's
bus through the master's admin API. Synchronisation is on printed lines and exit codes, each
with a timeout; never on sleeps."""
from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import sys
import tempfile
from pathlib import Path

import pytest

BIN = Path(sys.executable).parent
CONFIG = Path(__file__).resolve().parents[2] / "configs" / "debug.config"
PARAMS = "msg: |-\n  int:   99\n  str:   foo\n  float: 3.3\n  bool:  True\n"


class Proc:
    """A child process whose stdout/stderr lines are collected as they come."""

    def __init__(self, proc: asyncio.subprocess.Process, name: str):
        self.p, self.name = proc, name
        self.lines: dict[str, list[str]] = {"out": [], "err": []}
        self._new = asyncio.Event()
        self._readers = [asyncio.create_task(self._read(proc.stdout, "out")),
                         asyncio.create_task(self._read(proc.stderr, "err"))]

    @classmethod
    async def start(cls, *argv: str, env: dict | None = None) -> "Proc":
        p = await asyncio.create_subprocess_exec(*argv, stdout=asyncio.subprocess.PIPE,
                                                 stderr=asyncio.subprocess.PIPE, env=env)
        return cls(p, Path(argv[0]).name)

    async def _read(self, stream, key: str) -> None:
        while line := await stream.readline():
            self.lines[key].append(line.decode(errors="replace").rstrip("\n"))
            self._new.set()
        self._new.set()

    def text(self, key: str = "out") -> str:
        return "".join(line + "\n" for line in self.lines[key])

    def human_err(self) -> str:
        """stderr without the JSON log lines."""
        return "".join(line + "\n" for line in self.lines["err"] if not line.startswith("{"))

    def dump(self) -> str:
        return f"--- {self.name} stdout:\n{self.text()}--- {self.name} stderr:\n{self.human_err()}"

    async def wait_line(self, pattern: str, key: str = "out", timeout: float = 60.0) -> str:
        """The first line of ``key`` matching regex ``pattern``; fails on timeout or exit."""
        rx = re.compile(pattern)
        deadline = asyncio.get_running_loop().time() + timeout
        while True:
            for line in self.lines[key]:
                if rx.search(line):
                    return line
            if all(r.done() for r in self._readers):
                raise AssertionError(f"{self.name} exited ({self.p.returncode}) before printing "
                                     f"{pattern!r}\n{self.dump()}")
            left = deadline - asyncio.get_running_loop().time()
            if left <= 0:
                raise AssertionError(f"{self.name} did not print {pattern!r} within {timeout} s\n{self.dump()}")
            self._new.clear()
            try:
                await asyncio.wait_for(self._new.wait(), left)
            except asyncio.TimeoutError:
                pass

    async def wait(self, timeout: float = 60.0) -> int:
        try:
            rc = await asyncio.wait_for(self.p.wait(), timeout)
        except asyncio.TimeoutError:
            raise AssertionError(f"{self.name} did not exit within {timeout} s\n{self.dump()}") from None
        await asyncio.gather(*self._readers)
        return rc

    async def kill(self) -> None:
        if self.p.returncode is None:
            self.p.kill()
            await self.p.wait()


async def tool(*argv: str, env: dict, timeout: float = 60.0) -> tuple[int, str, str]:
    """Run rce-topic/rce-service to completion; returns (exit code, stdout, stderr)."""
    p = await Proc.start(str(BIN / argv[0]), *argv[1:], env=env)
    rc = await p.wait(timeout)
    return rc, p.text(), p.human_err()


@pytest.fixture
def engine(shared_engine):
    """The module's engine: its tests run one after the other with the same robot ID and container
    tag, the first one's robot and container gone (its ``rce-ros`` stopped, checked) before the next."""
    return shared_engine


@pytest.fixture
async def robot(engine):
    """``rce-ros configs/debug.config`` (URL rewritten to the engine's master), ready."""
    d = Path(tempfile.mkdtemp(prefix="rce-e2e-"))
    cfg = json.loads(CONFIG.read_text())
    cfg["url"] = engine.master_url
    (d / "debug.config").write_text(json.dumps(cfg))
    bus = str(d / "testRobot.sock")
    env = dict(os.environ, RCE_LOG_JSON="1")
    ros = await Proc.start(str(BIN / "rce-ros"), str(d / "debug.config"), "--bus", bus, "--timeout", "60", env=env)
    try:
        assert await ros.wait_line(r"^  export RCE_BUS=") == f"  export RCE_BUS={bus}"
        await ros.wait_line(r"^rce-ros: ready \(4 interface\(s\) up", timeout=90)
        tool_env = dict(os.environ, RCE_BUS=bus, RCE_ADMIN_TOKEN=engine.admin_token)
        yield ros, bus, tool_env
    finally:
        await ros.kill()
        for p in d.iterdir():
            p.unlink()
        d.rmdir()




async def test_debug_config_end_to_end(engine, robot):
    ros, bus, env = robot

    # topics: the robot's /stringEchoReq -> container stringEcho.py -> the robot's /stringEchoResp
    rc, out, err = await tool("rce-topic", "list", "-v", env=env)
    assert rc == 0, err
    assert "/stringEchoReq [std_msgs/String] 0 publisher(s), 1 subscriber(s)" in out
    assert "/stringEchoResp [std_msgs/String] 1 publisher(s), 0 subscriber(s)" in out

    echo = await Proc.start(str(BIN / "rce-topic"), "echo", "/stringEchoResp", "-n", "2", env=env)
    await echo.wait_line(r"^subscribed to /stringEchoResp \[std_msgs/String\]", key="err")
    rc, _, err = await tool("rce-topic", "pub", "/stringEchoReq", "std_msgs/String", "{data: hello}", env=env)
    assert rc == 0 and "published 1 message on /stringEchoReq" in err, err
    rc, _, err = await tool("rce-topic", "pub", "/stringEchoReq", "{data: world}", "--once", env=env)
    assert rc == 0, err
    assert await echo.wait(30) == 0
    assert echo.text() == "data: hello\n---\ndata: world\n---\n"

    # services: the robot calls the container through ServiceProviderConverter <-> ServiceClientInterface
    rc, out, err = await tool("rce-service", "list", env=env)
    assert rc == 0 and out.split() == ["/parameterTest", "/stringEchoService"], (out, err)
    rc, out, err = await tool("rce-service", "call", "stringEchoService", "{data: hello}", env=env)
    assert (rc, out) == (0, "data: hello\n"), err
    rc, out, err = await tool("rce-service", "call", "parameterTest", "{}", env=env)
    assert (rc, out) == (0, PARAMS), err

    # a refusal is named
    rc, _, err = await tool("rce-topic", "pub", "/stringEchoReq", "{data: 5}", env=env)
    assert rc == 1 and "std_msgs/String: field 'data' must be a string, got int" in err

    # the container's own bus through the master's admin API: publish there, see it on the robot
    adm = ["--container", "cTag_01", "--master", engine.master_url, "--user", "testUser"]
    rc, out, err = await tool("rce-topic", "list", *adm, env=env)
    assert rc == 0 and {"/stringEchoReq", "/stringEchoResp"} <= set(out.split()), (out, err)
    echo = await Proc.start(str(BIN / "rce-topic"), "echo", "/stringEchoResp", "-n", "1", env=env)
    await echo.wait_line(r"^subscribed to", key="err")
    rc, _, err = await tool("rce-topic", "pub", "/stringEchoReq", "{data: from the cloud}", *adm, env=env)
    assert rc == 0, err
    assert await echo.wait(30) == 0 and echo.text() == "data: from the cloud\n---\n"

    # Ctrl-C: interfaces and the container go, the websocket closes, the socket is removed, exit 0
    ros.p.send_signal(signal.SIGINT)
    assert await ros.wait(30) == 0, ros.dump()
    assert "rce-ros: removed 4 interface(s), destroyed 1 container(s)" in ros.text()
    assert not os.path.exists(bus)
    assert not [c for c in engine.admin("/api/containers") if c.get("ctag") == "cTag_01"]
    assert not [r for r in engine.admin("/api/robots") if r.get("robot") == "testRobot"]
    assert "error from the cloud" not in ros.human_err(), ros.dump()


async def test_admin_api_call_and_sample(engine, robot):
    """``rce-service call`` and ``rce-topic echo`` on the container's bus (admin /call and /sample)."""
    ros, bus, env = robot
    adm = ["--container", "cTag_01", "--master", engine.master_url, "--user", "testUser"]
    rc, out, err = await tool("rce-service", "call", "parameterTest", "{}", *adm, env=env)
    assert (rc, out) == (0, PARAMS), err
    echo = await Proc.start(str(BIN / "rce-topic"), "echo", "/stringEchoReq", "-n", "1", *adm, env=env)
    await echo.wait_line(r"^sampling /stringEchoReq", key="err")
    # publish from the robot once the container's bus shows the sampling subscriber
    deadline = asyncio.get_running_loop().time() + 30
    while not any("admin:bus_sample" in t["subscribers"] for t in
                  (await asyncio.to_thread(engine.admin, "/api/containers/testUser/cTag_01/bus"))["topics"]
                  if t["name"] == "/stringEchoReq"):
        assert asyncio.get_running_loop().time() < deadline, "the sample never subscribed"
    # a sample is a window (ECHO_SAMPLE_TIMEOUT) and the next one follows it: publish until one is taken
    pub = await Proc.start(str(BIN / "rce-topic"), "pub", "/stringEchoReq", "{data: sampled}", "-r", "5", env=env)
    try:
        assert await echo.wait(30) == 0
    finally:
        await pub.kill()
    assert echo.text() == "data: sampled\n---\n"
