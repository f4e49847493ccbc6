"""Environments fork from the container task set's template (rce_container.env_template), and
the task set does without it. Real processes on loopback: a master, a robot task set, a
container host; a robot's containers echo ``std_msgs/String`` through stringEcho.py.

- A container's environment is a child of the template, shows the command line of an exec'd
  environment, and serves its container.
- kill -9 of the template: the running container keeps echoing; the next container's
  environment is exec'd by the task set itself; the template is started again, and the
  container after that forks from the new one.
- An environment's zygote template is forked from the task set's zygote template, with a
  node's environment only; kill -9 of it: the environment's next container still starts and
  echoes (its zygote spawned in the sandbox); kill -9 of the task set's: the next environment
  execs its own, the task set's is started again, and later environments' fork from the new one.
"""
from __future__ import annotations

import os
import signal
from contextlib import AsyncExitStack
from pathlib import Path

import psutil
import pytest

from rce.tools.launch import start_engine
from rce_container.node_env import PASSED_THROUGH
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


def zygote_template_of(engine, ctag: str) -> dict:
    return engine.admin(f"/api/containers/testUser/{ctag}/stats")["environment"]["zygote_template"]


def is_zygote_template(p: psutil.Process) -> bool:
    return p.cmdline()[1:3] == ["-m", "rce_container.zygote"] and "--template" in p.cmdline()


#: Every variable a template may have: a node's environment (rce_container.node_env), nothing of the host's.
NODE_ENV_KEYS = {"PATH", "HOME", "LANG", "PYTHONUNBUFFERED", "PYTHONPATH", "RCE_BUS", "RCE_BUS_TOKEN", "RCE_CONTAINER",
                 "RCE_NODE_NAME", "RCE_NAMESPACE", *PASSED_THROUGH}


async def test_an_environments_zygote_template_forks_from_the_task_sets_and_does_without_it(engine):
    async with AsyncExitStack() as robots:
        async def echo_container(ctag: str, group: str | None = None) -> RawRobot:
            r = await robots.enter_async_context(RawRobot(engine.master_url, f"bot{ctag}"))
            await echo_ready(r, ctag, group=group)
            return r

        ra = await echo_container("zyA", group="g")
        tpl = zygote_template_of(engine, "zyA")
        assert tpl["forked"] and tpl["running"], tpl
        env_tpl = psutil.Process(tpl["pid"])
        root = env_tpl.parent()
        assert is_zygote_template(env_tpl) and is_zygote_template(root), (env_tpl.cmdline(), root.cmdline())
        host = root.parent()
        assert any("rce-container" in a for a in host.cmdline()), host.cmdline()
        for p in (env_tpl, root):                  # /proc/PID/environ: the memory every fork copies
            assert set(p.environ()) <= NODE_ENV_KEYS, set(p.environ()) - NODE_ENV_KEYS
        assert set(host.environ()) - NODE_ENV_KEYS     # the host has more, which no template shows

        # the environment's template dies: its running node is untouched, its next container's
        # zygote is spawned in the sandbox
        os.kill(env_tpl.pid, signal.SIGKILL)
        psutil.wait_procs([env_tpl], timeout=10)
        await echo_probe(ra)
        await echo_container("zyB", group="g")
        assert zygote_template_of(engine, "zyB") == {**tpl, "running": False}
        await echo_probe(ra)

        # the task set's template dies: the spare environment forked before keeps its template,
        # the next environment execs its own, and later ones fork from the task set's new one
        os.kill(root.pid, signal.SIGKILL)
        psutil.wait_procs([root], timeout=10)
        await echo_probe(ra)
        seen = []
        for ctag in ("zyC", "zyD", "zyE", "zyF", "zyG"):
            await echo_container(ctag)
            t = zygote_template_of(engine, ctag)
            parent = psutil.Process(t["pid"]).parent()
            seen.append((t, parent.pid, parent.cmdline()))
            assert t["running"], seen
            if t["forked"] and is_zygote_template(parent) and parent.pid != root.pid:
                break
        env_of = {ctag: environment_of(engine, ctag).pid for ctag in ("zyC", "zyD", "zyE", "zyF", "zyG")[:len(seen)]}
        assert any(not t["forked"] and ppid in env_of.values() for t, ppid, _ in seen), seen   # exec'd by its env
        t, ppid, _ = seen[-1]
        assert t["forked"] and ppid != root.pid and psutil.Process(ppid).parent().pid == host.pid, seen
        await echo_probe(ra)
