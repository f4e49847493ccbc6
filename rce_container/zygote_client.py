"""The host side of a container's warm node launcher (:mod:`rce_container.zygote`): starts the
zygote through the container's sandbox, asks it to fork Python nodes, and gives the launcher
each forked node as a :class:`ZygoteChild`, which looks like the
:class:`asyncio.subprocess.Process` of an exec'd node (``pid``, ``returncode``, ``wait()``,
``stdout``, ``stderr``) so the launcher watches, logs, measures, stops and respawns both the
same way.

Pids: a forked node announces itself (``spawned``) on the zygote's socket before it runs
anything, and the host's end has ``SO_PASSCRED`` on, so the kernel gives the sender's pid as
the host sees it (:manpage:`unix(7)`, ``SCM_CREDENTIALS``: pids are translated into the
receiver's PID namespace): the host pid that status reports, stats and signals use, known
even if the node has exited (and been reaped) by the time the message is read. A child leads
its own process group, so it is stopped as an exec'd node is: SIGTERM to the group, SIGKILL
after the grace period. If the zygote dies, its children are killed and reported as exited
with ``error`` saying so; nodes started later are exec'd.
"""
from __future__ import annotations

import asyncio
import collections
import contextlib
import json
import os
import signal
import socket
import struct
import sys
from pathlib import Path
from typing import Any

from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks
from rce_container.node_env import node_env
from rce_container.sandbox import Sandbox
from rce_container.zygote import CMDLINE_ROOM, MAX_MESSAGE, STARTUP_VARS

log = get_logger("rce.container.zygote")

READY_TIMEOUT = 20.0        # s for the zygote to import the node runtime (slow under load; nodes wait for it
                            # rather than each importing the same modules at the same time)
SPAWN_TIMEOUT = 5.0         # s for the zygote to answer a spawn request (a fork); then the node is exec'd
STREAM_LIMIT = 2**16        # bytes of one stdout/stderr line (as asyncio's subprocess pipes)
ZYGOTE_LOG_LINES = 50       # lines of the zygote's own stdout/stderr kept for diagnostics
TEMPLATE_EXIT_TIMEOUT = 2.0  # s for the template to exit once its socket is closed, before SIGKILL


#: Ancillary buffer for one ``SCM_CREDENTIALS`` message (``struct ucred``: pid, uid, gid).
CRED_SPACE = socket.CMSG_SPACE(struct.calcsize("3i"))


def zygote_socketpair() -> tuple[socket.socket, socket.socket]:
    """(our end, the zygote's end) of a new ``SOCK_SEQPACKET`` pair; ours has ``SO_PASSCRED``
    on, so every message read from it carries its sender's host pid."""
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    ours.setsockopt(socket.SOL_SOCKET, socket.SO_PASSCRED, 1)
    return ours, theirs


def sender_pid(ancillary: list[tuple[int, int, bytes]]) -> int | None:
    """The pid in a received ``SCM_CREDENTIALS`` message (as this process's PID namespace sees it)."""
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == socket.SCM_CREDENTIALS and len(data) >= struct.calcsize("3i"):
            return struct.unpack_from("3i", data)[0] or None
    return None


async def first_message(sock: socket.socket, timeout: float, with_pid: bool = False) -> dict:
    """A fork server's first message on ``sock`` (made non-blocking here): ``{"op": "ready"}``,
    ``{"op": "failed", "error": ...}``, or ``{"error": why}`` when none came within ``timeout`` s.
    ``with_pid`` (``sock`` has ``SO_PASSCRED`` on): the sender's pid is added as ``"pid"``."""
    sock.setblocking(False)
    loop = asyncio.get_running_loop()
    pid = None
    try:
        async with asyncio.timeout(timeout):
            if with_pid:
                data, anc = await _recv_with_credentials(sock)
                pid = sender_pid(anc)
            else:
                data = await loop.sock_recv(sock, MAX_MESSAGE)
            msg = json.loads(data or b"{}")
    except (TimeoutError, OSError, ValueError) as e:
        msg = {"error": str(e) or type(e).__name__}
    if not isinstance(msg, dict):
        return {"error": "not a JSON object"}
    if pid is not None:
        msg["pid"] = pid
    return msg


async def _recv_with_credentials(sock: socket.socket) -> tuple[bytes, list]:
    """One message on the non-blocking ``sock`` and its ancillary data (credentials)."""
    while True:
        try:
            data, anc, _, _ = sock.recvmsg(MAX_MESSAGE, CRED_SPACE)
            return data, anc
        except BlockingIOError:
            await _until_readable(sock.fileno())


async def _until_readable(fd: int) -> None:
    """Wait until ``fd`` is readable (a socket has data or EOF; a pidfd's process has exited)."""
    loop = asyncio.get_running_loop()
    readable = loop.create_future()
    loop.add_reader(fd, lambda: readable.done() or readable.set_result(None))
    try:
        await readable
    finally:
        loop.remove_reader(fd)


async def _keep(stream: asyncio.StreamReader, sink: collections.deque) -> None:
    """Lines of a zygote's own stdout/stderr into the bounded ``sink`` (diagnostics)."""
    while line := await stream.readline():
        sink.append(line.decode(errors="replace").rstrip("\n"))


def _signal_group(pgid: int | None, sig: int) -> None:
    if not pgid:
        return
    try:
        os.killpg(pgid, sig)
    except (ProcessLookupError, PermissionError):
        pass


class ForkedChild:
    """A process a fork server forked, as the caller sees it (the server reaps it and reports its
    exit): ``pid``; ``returncode``: None while it runs, then its exit code or ``-signal``;
    ``error``: what the server said of its end, if anything. Looks like an
    :class:`asyncio.subprocess.Process` to whoever watches it (``pid``, ``returncode``, ``wait()``)."""

    def __init__(self, pid: int | None):
        self.pid = pid
        self.returncode: int | None = None
        self.error: str | None = None
        self._done = asyncio.Event()

    def exited(self, code: int, error: str | None = None) -> None:
        if self.returncode is None:
            self.returncode, self.error = code, error
            self._done.set()

    async def wait(self) -> int:
        """Wait until it has been reaped; its return code."""
        await self._done.wait()
        return self.returncode


class ZygoteChild(ForkedChild):
    """A node forked by the zygote. ``pid``: host pid (None if it was gone before it could be
    found); ``error``: ``"uncaught TYPE: MESSAGE"`` when its script raised; ``stdout``,
    ``stderr``: its output."""

    def __init__(self, pid: int | None, stdout: asyncio.StreamReader, stderr: asyncio.StreamReader,
                 transports: list[asyncio.BaseTransport]):
        super().__init__(pid)
        self.stdout, self.stderr = stdout, stderr
        self._transports = transports

    def close_pipes(self) -> None:
        """Stop reading its stdout and stderr (when a process it left behind holds them open)."""
        for t in self._transports:
            t.close()


class ZygoteClient:
    """The zygote of one container. ``sandbox``: where it runs (as a node does); ``env``: its
    environment (a node's, :func:`rce_container.node_env.node_env`); ``ctag``: for logs."""

    def __init__(self, sandbox: Sandbox, env: dict[str, str], ctag: str):
        self.sandbox, self.env, self.ctag = sandbox, env, ctag
        self.proc: asyncio.subprocess.Process | None = None
        self.pid: int | None = None                  # the zygote's host pid
        self.sock: socket.socket | None = None
        self.ready: asyncio.Future = asyncio.get_running_loop().create_future()      # -> its host pid
        self.output: collections.deque = collections.deque(maxlen=ZYGOTE_LOG_LINES)
        self._waiting: dict[int, asyncio.Future] = {}
        self._children: dict[int, ZygoteChild] = {}
        self._starting: dict[int, dict | None] = {}   # spawned, not yet taken by the caller: id -> exit or None
        self._next_id = 0
        self._tasks = Tasks(f"zygote of {ctag}")

    @property
    def alive(self) -> bool:
        return self.sock is not None and self.ready.done() and not self.ready.cancelled() \
            and self.ready.exception() is None

    def fits(self, env: dict[str, str]) -> bool:
        """Can a node with environment ``env`` be forked (the variables an interpreter reads
        when it starts are the zygote's)?"""
        return all(env.get(k) == self.env.get(k) for k in STARTUP_VARS)

    async def start(self, template: "ZygoteTemplate | None" = None) -> None:
        """Start the zygote: forked from ``template`` when it runs (it has imported the node
        runtime already), else spawned in the sandbox; returns once it is ready. Raises
        :class:`OSError` if it cannot be started, :class:`RuntimeError` if it fails."""
        ours = None
        if template is not None and await template.wait_started():
            try:
                ours = template.fork_zygote(self.sandbox.enter_spec())
            except OSError as e:
                log.warning("the zygote template did not take a container", container=self.ctag, reason=str(e))
        ours = ours or await self._spawn()
        ours.setblocking(False)
        self.sock = ours
        asyncio.get_running_loop().add_reader(ours.fileno(), self._readable)
        try:
            async with asyncio.timeout(READY_TIMEOUT):
                self.pid = await asyncio.shield(self.ready)
        except TimeoutError:
            raise RuntimeError(f"the zygote did not start within {READY_TIMEOUT:g} s") from None
        log.debug("zygote ready", container=self.ctag, pid=self.pid, forked=self.proc is None)

    async def _spawn(self) -> socket.socket:
        """A new zygote spawned through the sandbox, as a node is; our end of its socket."""
        ours, theirs = zygote_socketpair()
        try:
            argv = [sys.executable, "-m", "rce_container.zygote", str(theirs.fileno()), " " * CMDLINE_ROOM]
            self.proc = await self.sandbox.spawn(argv, self.env, pass_fds=(theirs.fileno(),))
        except BaseException:
            ours.close()
            raise
        finally:
            theirs.close()
        for stream in (self.proc.stdout, self.proc.stderr):
            self._tasks.spawn(_keep(stream, self.output), name=f"zygote output of {self.ctag}")
        return ours

    def _readable(self) -> None:
        while self.sock is not None:
            try:
                data, anc, _, _ = self.sock.recvmsg(MAX_MESSAGE, CRED_SPACE)
            except BlockingIOError:
                return
            except OSError:
                data, anc = b"", []
            if not data:
                self._gone("the container's zygote exited" + (f": {self.output[-1]}" if self.output else ""))
                return
            self._dispatch(json.loads(data), sender_pid(anc))

    def _dispatch(self, msg: dict[str, Any], sender: int | None) -> None:
        op = msg.get("op")
        if op == "ready" and not self.ready.done():
            self.ready.set_result(sender)
        elif op == "failed" and not self.ready.done():
            self.ready.set_exception(RuntimeError(f"the zygote failed: {msg['error']}"))
        elif op in ("spawned", "refused"):
            msg["host_pid"] = sender             # a spawned message comes from the forked node itself
            fut = self._waiting.pop(msg["id"], None)
            if fut is not None and not fut.done():
                fut.set_result(msg)
                if op == "spawned":
                    self._starting[msg["id"]] = None
            elif op == "spawned":     # its caller gave up waiting: nobody would watch it
                _signal_group(msg["host_pid"], signal.SIGKILL)
        elif op == "exit":
            child = self._children.pop(msg["id"], None)
            if child is not None:
                child.exited(-msg["signal"] if "signal" in msg else msg["code"], msg.get("error"))
            elif msg["id"] in self._starting:          # exited before its caller took it
                self._starting[msg["id"]] = msg

    def _gone(self, why: str) -> None:
        """The zygote's end closed: fail what waits, kill and report its children."""
        if self.sock is not None:
            asyncio.get_running_loop().remove_reader(self.sock.fileno())
            self.sock.close()
            self.sock = None
        if not self.ready.done():
            self.ready.set_exception(RuntimeError(why))
            self.ready.exception()           # retrieved: nobody may be waiting for it
        for fut in self._waiting.values():
            if not fut.done():
                fut.set_result({"op": "refused", "error": why})
        for child in self._children.values():
            _signal_group(child.pid, signal.SIGKILL)
            child.exited(-signal.SIGKILL, why)
        self._waiting.clear()
        self._children.clear()
        self._starting.clear()

    async def spawn(self, argv: list[str], env: dict[str, str], cwd: str) -> ZygoteChild | None:
        """Fork a node running ``argv`` = ``[python, script, arg...]`` with ``env`` in ``cwd``;
        None when the zygote cannot (not running, refused, request too large, no answer within
        :data:`SPAWN_TIMEOUT`): the caller then execs the node."""
        if not self.alive:
            return None
        self._next_id += 1
        rid = self._next_id
        out_r, out_w = os.pipe()
        err_r, err_w = os.pipe()
        fut = self._waiting[rid] = asyncio.get_running_loop().create_future()
        try:
            socket.send_fds(self.sock, [json.dumps({"op": "spawn", "id": rid, "argv": argv, "env": env,
                                                    "cwd": str(cwd)}).encode()], [out_w, err_w])
        except OSError as e:                          # EMSGSIZE (too large), EAGAIN (not reading), EPIPE
            log.warning("zygote cannot take a node, exec'ing it", container=self.ctag, reason=str(e))
            self._waiting.pop(rid, None)
            for fd in (out_r, out_w, err_r, err_w):
                os.close(fd)
            return None
        finally:
            if rid in self._waiting:
                os.close(out_w)
                os.close(err_w)
        return await self._answered(rid, fut, out_r, err_r)

    async def _answered(self, rid: int, fut: asyncio.Future, out_r: int, err_r: int) -> ZygoteChild | None:
        try:
            async with asyncio.timeout(SPAWN_TIMEOUT):
                msg = await fut
        except TimeoutError:
            msg = {"op": "refused", "error": f"no answer within {SPAWN_TIMEOUT:g} s"}
        finally:
            self._waiting.pop(rid, None)
        if msg["op"] != "spawned":
            log.warning("zygote refused a node, exec'ing it", container=self.ctag, reason=msg.get("error"))
            os.close(out_r)
            os.close(err_r)
            return None
        streams, transports = [], []
        loop = asyncio.get_running_loop()
        for fd in (out_r, err_r):
            reader = asyncio.StreamReader(limit=STREAM_LIMIT)
            transport, _ = await loop.connect_read_pipe(
                lambda pipe_reader=reader: asyncio.StreamReaderProtocol(pipe_reader), os.fdopen(fd, "rb", 0))
            streams.append(reader)
            transports.append(transport)
        child = ZygoteChild(msg["host_pid"], *streams, transports)
        early = self._starting.pop(rid, None)
        if early is not None:
            child.exited(-early["signal"] if "signal" in early else early["code"], early.get("error"))
        elif self.sock is None:
            _signal_group(child.pid, signal.SIGKILL)
            child.exited(-signal.SIGKILL, "the container's zygote exited")
        else:
            self._children[rid] = child
        return child

    async def kill(self, child: ZygoteChild, grace: float) -> None:
        """Stop ``child`` and its process group: SIGTERM, SIGKILL after ``grace`` s; returns
        once the zygote has reaped it."""
        if child.returncode is None:
            _signal_group(child.pid, signal.SIGTERM)
            try:
                async with asyncio.timeout(grace):
                    await child.wait()
            except TimeoutError:
                log.warning("node ignored SIGTERM, killing", container=self.ctag, pid=child.pid)
        _signal_group(child.pid, signal.SIGKILL)     # even when it is gone: its children may still be there
        await child.wait()

    async def close(self) -> None:
        """Stop the zygote: its socket closes, so it kills any child left and exits; a spawned
        one is reaped here, a forked one by the container's init (or, unconfined, by init)."""
        if self.sock is not None:
            self._gone("the container is closing")
        if self.proc is not None:
            await self.sandbox.kill(self.proc)
        await self._tasks.cancel_all()


class ZygoteTemplate:
    """A warm template (:class:`rce_container.zygote.Template`) with ``env`` (a node's minimal
    environment, no container's values): the container task set's, exec'd once, and one per
    environment process, before its containers, forked from the task set's (``sock``: the
    environment's end of its socket, :meth:`fork_template`) or, without one, exec'd by the
    environment. Each container's zygote is forked from its environment's template, so a
    container's first node does not wait for the node runtime's imports; and an environment's
    template is a fork, so it does not import them either."""

    def __init__(self, env: dict[str, str], sock: socket.socket | None = None):
        self.env = env
        self.proc: asyncio.subprocess.Process | None = None   # when exec'd
        self.pid: int | None = None
        self.sock: socket.socket | None = None
        self.forked = False                  # a fork of the task set's template (not exec'd)
        self.output: collections.deque = collections.deque(maxlen=ZYGOTE_LOG_LINES)
        self._given = sock
        self._pidfd: int | None = None       # of a forked template (not our child)
        self._ready = False
        self._started = asyncio.Event()      # set once it is ready or has failed
        self._launched = False
        self._tasks = Tasks("zygote template")

    @classmethod
    def for_nodes(cls, home: str | Path, sock: socket.socket | None = None) -> "ZygoteTemplate":
        """A template with a node's environment (:func:`rce_container.node_env.node_env`) and no
        container's values (no bus, no token); ``home``: a directory (HOME) of the environment's
        (or the task set's); ``sock``: see the class doc."""
        return cls(node_env(bus="", token="", ctag="", name="zygote", namespace="/", home=home), sock)

    @property
    def alive(self) -> bool:
        return self._ready and self.sock is not None and (self.proc is None or self.proc.returncode is None)

    @property
    def lost(self) -> bool:
        """It was ready once and is gone (it exited, was killed, or does not take requests)."""
        return self._ready and not self.alive

    def start_soon(self) -> None:
        """Start it in the background (a failure is logged; zygotes are then spawned per container)."""
        self._launched = True
        self._tasks.spawn(self._start(), name="zygote template")

    async def wait_started(self) -> bool:
        """Wait (at most :data:`READY_TIMEOUT`) until it is ready or has failed; whether it runs.
        A container created while the template still imports waits for it: it is further
        along than a zygote spawned now would be."""
        if not self._launched:
            return False
        try:
            async with asyncio.timeout(READY_TIMEOUT):
                await self._started.wait()
        except TimeoutError:
            return False
        return self.alive

    async def _start(self) -> None:
        try:
            if not await self._adopt():
                await self._spawn()
            if self._ready:
                asyncio.get_running_loop().add_reader(self.sock.fileno(), self._readable)
        finally:
            self._started.set()

    async def _adopt(self) -> bool:
        """Take the forked template on the given socket once it says ready (its pid: the
        message's credentials); False if there is none or it never became ready."""
        sock, self._given = self._given, None
        if sock is None:
            return False
        msg = await first_message(sock, READY_TIMEOUT, with_pid=True)
        if msg.get("op") == "ready" and msg.get("pid"):
            try:
                self._pidfd = os.pidfd_open(msg["pid"])
            except OSError:
                pass
            # the pidfd is its, not a later process's, if it was alive when the pidfd was opened:
            # only it holds the other end of the socket, which would read EOF once it is gone
            if self._pidfd is not None and not _at_eof(sock):
                self.sock, self.pid, self._ready, self.forked = sock, msg["pid"], True, True
                return True
        log.warning("the forked zygote template did not start, exec'ing one", reason=msg.get("error", "it exited"))
        sock.close()
        self._close_pidfd()
        return False

    async def _spawn(self) -> None:
        ours, theirs = zygote_socketpair()
        try:
            self.proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "rce_container.zygote", str(theirs.fileno()), "--template", " " * CMDLINE_ROOM,
                env=self.env, cwd="/", stdin=asyncio.subprocess.DEVNULL, stdout=asyncio.subprocess.PIPE,
                stderr=asyncio.subprocess.PIPE, start_new_session=True, pass_fds=(theirs.fileno(),))
        except OSError as e:
            ours.close()
            log.warning("no zygote template", reason=str(e))
            return
        finally:
            theirs.close()
        self.sock, self.pid = ours, self.proc.pid
        for stream in (self.proc.stdout, self.proc.stderr):
            self._tasks.spawn(_keep(stream, self.output), name="zygote template output")
        msg = await first_message(ours, READY_TIMEOUT)
        self._ready = msg.get("op") == "ready"
        if not self._ready:
            log.warning("no zygote template", reason=msg.get("error", "it exited"), output=list(self.output)[-5:])

    def _readable(self) -> None:
        """A template says nothing after ready: its socket is readable when it is gone."""
        try:
            if self.sock.recv(MAX_MESSAGE):
                return
        except BlockingIOError:
            return
        except OSError:
            pass
        self._gone()

    def _gone(self) -> None:
        log.warning("the zygote template exited", pid=self.pid)
        asyncio.get_running_loop().remove_reader(self.sock.fileno())
        self.sock.close()
        self.sock = None

    def _send(self, op: dict, fd: int) -> None:
        if self.sock is None:
            raise OSError("the zygote template is not running")
        try:
            socket.send_fds(self.sock, [json.dumps(op).encode()], [fd])
        except ConnectionError:          # it is gone (its end closed)
            self._gone()
            raise

    def fork_zygote(self, spec: dict) -> socket.socket:
        """Ask for a zygote in the sandbox ``spec`` (:meth:`rce_container.sandbox.Sandbox.enter_spec`);
        our end of its socket. Nothing of a container's but ``spec`` goes through the template
        (no bus token: every later zygote is a copy of the template's memory); the zygote keeps
        the template's environment, and each node gets its own with its spawn request. Raises
        :class:`OSError` if the template does not take the request."""
        return self._fork({"op": "container", "spec": spec})

    def fork_template(self) -> socket.socket:
        """Ask for a new template forked from this one (for an environment: ``ZygoteTemplate(env,
        sock)``); the other end of its socket, on which it says ready. Raises :class:`OSError` if
        this template does not take the request."""
        return self._fork({"op": "template"})

    def _fork(self, op: dict) -> socket.socket:
        """Send ``op`` with the far end of a new socket pair; our end. Raises as :meth:`_send`."""
        ours, theirs = zygote_socketpair()
        try:
            self._send(op, theirs.fileno())
        except OSError:
            ours.close()
            raise
        finally:
            theirs.close()
        return ours

    async def close(self) -> None:
        """Stop the template (its socket closes; SIGKILL after :data:`TEMPLATE_EXIT_TIMEOUT`)."""
        if self._given is not None:
            self._given.close()
            self._given = None
        if self.sock is not None:
            asyncio.get_running_loop().remove_reader(self.sock.fileno())
            self.sock.close()
            self.sock = None
        if self.proc is not None and self.proc.returncode is None:
            try:
                async with asyncio.timeout(TEMPLATE_EXIT_TIMEOUT):
                    await self.proc.wait()
            except TimeoutError:
                _signal_group(self.proc.pid, signal.SIGKILL)
                await self.proc.wait()
        if self._pidfd is not None:            # forked: its parent reaps it; wait until it has exited
            if not await _pidfd_exited(self._pidfd, TEMPLATE_EXIT_TIMEOUT):
                with contextlib.suppress(ProcessLookupError):
                    signal.pidfd_send_signal(self._pidfd, signal.SIGKILL)
            self._close_pidfd()
        await self._tasks.cancel_all()

    def _close_pidfd(self) -> None:
        if self._pidfd is not None:
            os.close(self._pidfd)
            self._pidfd = None


def _at_eof(sock: socket.socket) -> bool:
    """Whether ``sock`` (non-blocking) reads end of file now: its peer is gone."""
    try:
        return sock.recv(MAX_MESSAGE, socket.MSG_PEEK) == b""
    except BlockingIOError:
        return False
    except OSError:
        return True


async def _pidfd_exited(pidfd: int, timeout: float) -> bool:
    """Wait at most ``timeout`` s for the process of ``pidfd`` to exit; whether it did."""
    try:
        async with asyncio.timeout(timeout):
            await _until_readable(pidfd)
        return True
    except TimeoutError:
        return False
