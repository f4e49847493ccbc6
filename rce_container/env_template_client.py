"""The task set's side of the warm environment launcher (:mod:`rce_container.env_template`):
starts the template once, asks it to fork each environment, and gives the task set each one as
a :class:`~rce_container.zygote_client.ForkedChild`, which looks like the
:class:`asyncio.subprocess.Process` of an exec'd environment (``pid``, ``returncode``,
``wait()``), so the task set watches, stops and measures both the same way.

If the template cannot start, or dies, :meth:`EnvTemplate.spawn` returns None and the task set
execs the environment; a dead template is started again in the background for the next one.
Environments it forked outlive it (they are no longer its children): each is then watched
through a pidfd (:manpage:`pidfd_open(2)`), and its exit status, which only its reaper can
know, is reported as :data:`UNKNOWN_EXIT`.
"""
from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import socket
import sys
from typing import Any

from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks
from rce_container.zygote import CMDLINE_ROOM, MAX_MESSAGE
from rce_container.zygote_client import ForkedChild, first_message

log = get_logger("rce.container")

READY_TIMEOUT = 20.0         # s for the template to import the environment (slow under load)
SPAWN_TIMEOUT = 5.0          # s for the template to answer a spawn request (a fork); then the environment is exec'd
EXIT_TIMEOUT = 2.0           # s for the template to exit once its socket is closed, before SIGKILL
UNKNOWN_EXIT = 255           # the exit code reported for an environment whose template died before it


class EnvTemplate:
    """The template process of one container task set (``python -m rce_container.env_template``)."""

    def __init__(self):
        self.proc: asyncio.subprocess.Process | None = None
        self.sock: socket.socket | None = None
        self.forks = 0                               # environments forked (for stats and tests)
        self._ready: asyncio.Future | None = None    # -> True once it said ready, False if it failed
        self._waiting: dict[int, asyncio.Future] = {}
        self._children: dict[int, ForkedChild] = {}
        self._next_id = 0
        self._tasks = Tasks("environment template")

    @property
    def alive(self) -> bool:
        return self.sock is not None and self._ready is not None and self._ready.done() and self._ready.result()

    def start_soon(self) -> None:
        """Start it in the background (a failure is logged; environments are then exec'd)."""
        self._ready = asyncio.get_running_loop().create_future()
        self._tasks.spawn(self._start(), name="environment template")

    async def _start(self) -> None:
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            self.proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "rce_container.env_template", str(theirs.fileno()), " " * CMDLINE_ROOM,
                stdin=asyncio.subprocess.DEVNULL, start_new_session=True, pass_fds=(theirs.fileno(),))
        except OSError as e:
            ours.close()
            log.warning("no environment template, environments are exec'd", reason=str(e))
            self._ready.set_result(False)
            return
        finally:
            theirs.close()
        msg = await first_message(ours, READY_TIMEOUT)
        if msg.get("op") != "ready":
            ours.close()
            log.warning("no environment template, environments are exec'd", reason=msg.get("error", "it exited"))
            await self._reap()
            self._ready.set_result(False)
            return
        self.sock = ours
        asyncio.get_running_loop().add_reader(ours.fileno(), self._readable)
        self._ready.set_result(True)
        log.debug("environment template ready", pid=self.proc.pid)

    async def spawn(self, args: list[str], zygote_template: socket.socket | None = None) -> ForkedChild | None:
        """Fork an environment with ``args`` (those of ``python -m rce_container.environment``)
        and, if given, the socket of its ``zygote_template`` (it gets ``--zygote-template-fd``);
        None when the template cannot (failed, dead, no answer within :data:`SPAWN_TIMEOUT`): the
        caller then execs it. A template that is still starting is waited for (at most
        :data:`READY_TIMEOUT`); a dead one is started again for the next environment."""
        if self._ready is None:
            return None
        if not self._ready.done():
            try:
                async with asyncio.timeout(READY_TIMEOUT):
                    await asyncio.shield(self._ready)
            except TimeoutError:
                return None
        if not self.alive:
            if self._ready.result():            # it ran and died: start another for the next one
                self.start_soon()
            return None
        self._next_id += 1
        rid = self._next_id
        fut = self._waiting[rid] = asyncio.get_running_loop().create_future()
        try:
            socket.send_fds(self.sock, [json.dumps({"op": "spawn", "id": rid, "args": args}).encode()],
                            [zygote_template.fileno()] if zygote_template is not None else [])
            async with asyncio.timeout(SPAWN_TIMEOUT):
                msg = await fut
        except (OSError, TimeoutError) as e:
            log.warning("the environment template did not fork, exec'ing", reason=str(e) or type(e).__name__)
            return None
        finally:
            self._waiting.pop(rid, None)
        if msg.get("op") != "spawned":
            log.warning("the environment template refused, exec'ing", reason=msg.get("error"))
            return None
        self.forks += 1
        return self._children[rid]

    def _readable(self) -> None:
        while self.sock is not None:
            try:
                data = self.sock.recv(MAX_MESSAGE)
            except BlockingIOError:
                return
            except OSError:
                data = b""
            if not data:
                self._gone()
                return
            self._dispatch(json.loads(data))

    def _dispatch(self, msg: dict[str, Any]) -> None:
        op, rid = msg.get("op"), msg.get("id")
        if op == "spawned":
            child = self._children[rid] = ForkedChild(msg["pid"])
            fut = self._waiting.get(rid)
            if fut is None or fut.done():       # its caller gave up waiting: nobody would watch it
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(child.pid, signal.SIGKILL)
            else:
                fut.set_result(msg)
        elif op == "refused":
            fut = self._waiting.get(rid)
            if fut is not None and not fut.done():
                fut.set_result(msg)
        elif op == "exit":
            child = self._children.pop(rid, None)
            if child is not None:
                child.exited(-msg["signal"] if "signal" in msg else msg["code"])

    def _gone(self) -> None:
        """The template's end closed: what waits is refused, its environments are watched by pidfd."""
        asyncio.get_running_loop().remove_reader(self.sock.fileno())
        self.sock.close()
        self.sock = None
        log.warning("the environment template exited; environments are exec'd until it is back")
        for fut in self._waiting.values():
            if not fut.done():
                fut.set_result({"op": "refused", "error": "the environment template exited"})
        for child in self._children.values():
            self._watch_orphan(child)
        self._children.clear()
        self._tasks.spawn(self._reap(), name="environment template reaper")

    @staticmethod
    def _watch_orphan(child: ForkedChild) -> None:
        try:
            fd = os.pidfd_open(child.pid)
        except OSError:                          # gone already
            child.exited(UNKNOWN_EXIT)
            return
        loop = asyncio.get_running_loop()

        def exited() -> None:
            loop.remove_reader(fd)
            os.close(fd)
            child.exited(UNKNOWN_EXIT)
        loop.add_reader(fd, exited)

    async def _reap(self) -> None:
        if self.proc is not None and self.proc.returncode is None:
            try:
                async with asyncio.timeout(EXIT_TIMEOUT):
                    await self.proc.wait()
            except TimeoutError:
                self.proc.kill()
                await self.proc.wait()

    async def close(self) -> None:
        """Stop the template (its socket closes; SIGKILL after :data:`EXIT_TIMEOUT`). The
        environments it forked are the task set's to stop."""
        if self.sock is not None:
            asyncio.get_running_loop().remove_reader(self.sock.fileno())
            self.sock.close()
            self.sock = None
        for child in self._children.values():     # none normally: the task set has stopped them
            self._watch_orphan(child)
        self._children.clear()
        await self._reap()
        await self._tasks.cancel_all()
