"""Environments fork from the container task set's template (rce_container.env_template), and
the task set does without it. Real processes on loopback: a master, a robot task set, a
container host; a robot's containers echo ``std_msgs/String`` through stringEcho.py.

- A container's environment is a child of the template, shows the command line of an exec'd
  environment, and serves its container.
- kill -9 of the template: the running container keeps echoing; the next container's
  environment is exec'd by the task set itself; the template is started again, and the
  container after that forks from the new one.
"""
from __future__ import annotations

import os
import signal
from contextlib import AsyncExitStack
from pathlib import Path

import psutil
import pytest

from rce.tools.launch import start_engine
from security.hostile import echo_probe, echo_ready
from wsclient import RawRobot

pytestmark = pytest.mark.asyncio


@pytest.fixture
def engine(tmp_path: Path):
    e = start_engine(tmp_path / "engine")
    yield e
    e.stop()


def environment_of(engine, ctag: str) -> psutil.Process:
    return psutil.Process(engine.admin(f"/api/containers/testUser/{ctag}/stats")["environment"]["pid"])


def is_template(p: psutil.Process) -> bool:
    return "rce_container.env_template" in p.cmdline()


async def test_an_environment_forks_from_the_template_and_does_without_it(engine):
    async with AsyncExitStack() as robots:
        async def echo_container(ctag: str) -> tuple[RawRobot, psutil.Process]:
            """A robot of its own with an echo container ``ctag``; the robot and the environment."""
            r = await robots.enter_async_context(RawRobot(engine.master_url, f"bot{ctag}"))
            await echo_ready(r, ctag)
            return r, environment_of(engine, ctag)

        ra, env_a = await echo_container("tplA")
        template = env_a.parent()
        assert is_template(template), template.cmdline()
        assert env_a.cmdline()[1:4] == ["-m", "rce_container.environment", "--control"], env_a.cmdline()
        host = template.parent()
        assert any("rce-container" in a for a in host.cmdline()), host.cmdline()

        os.kill(template.pid, signal.SIGKILL)
        psutil.wait_procs([template], timeout=10)
        await echo_probe(ra)                              # the running container is untouched

        # the spare forked before the kill still serves one container; then the task set execs
        # environments until the new template is ready, and forks again from it
        parents = []
        for ctag in ("tplB", "tplC", "tplD", "tplE"):
            _, env = await echo_container(ctag)
            parents.append(env.parent())
            if is_template(parents[-1]) and parents[-1].pid != template.pid:
                break
        assert any(p.pid == host.pid for p in parents), [p.cmdline() for p in parents]      # exec'd by the host
        assert is_template(parents[-1]) and parents[-1].pid != template.pid, [p.cmdline() for p in parents]
        assert parents[-1].parent().pid == host.pid
        await echo_probe(ra)
