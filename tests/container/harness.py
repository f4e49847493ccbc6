"""Test harness for the container task set: a tiny control server that plays the master,
the real ``rce-container`` process, and a robot-side data plane.

Readiness always comes from an event (the task set's ``register``, a ``node_status``, a
condition on ``describe``), never from sleeping.
"""
from __future__ import annotations

import asyncio
import json
import os
import signal
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import psutil

from rce.transport.cluster_auth import KEY_ENV, ClusterKey, respond
from rce.transport.dataplane import DataPlane
from rce.transport.interface import Interface
from rce.transport.rpc import RpcPeer

BIN = Path(sys.executable).parent
STEP = 15.0   # s, the longest any single wait may take

# A helper node package for the tests (found through RCE_PACKAGE_PATH).
HELPER_PKG = {
    "exiter.py": (
        "import sys\n"
        "print('argv=' + '|'.join(sys.argv[1:]), flush=True)\n"
        "print('bye', file=sys.stderr, flush=True)\n"
        "sys.exit(int(sys.argv[1]) if len(sys.argv) > 1 else 0)\n"),
    # Forks a grandchild and ignores SIGTERM: teardown must SIGKILL the whole process group.
    "stubborn.py": (
        "import signal, subprocess, sys, time\n"
        "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
        "child = subprocess.Popen(['sleep', '600'])\n"
        "print(f'child={child.pid}', flush=True)\n"
        "time.sleep(600)\n"),
    "run.sh": "#!/bin/sh\necho shell-node \"$@\" \"$RCE_CONTAINER\"\n",
    # Allocates (and touches) 4 MiB at a time until the kernel stops it.
    "hog.py": (
        "import time\n"
        "chunks = []\n"
        "while True:\n"
        "    chunks.append(b'x' * (4 << 20))\n"
        "    time.sleep(0.002)\n"),
    # Burns CPU.
    "spin.py": "while True:\n    pass\n",
    # Looks around from inside its container; prints one JSON line (see tests/container/test_sandbox.py).
    "probe.py": (
        "import errno, json, os, socket, sys\n"
        "import rce.node\n"
        "def attempt(fn):\n"
        "    try:\n"
        "        fn()\n"
        "        return 'ok'\n"
        "    except OSError as e:\n"
        "        return errno.errorcode.get(e.errno, str(e))\n"
        "def unix(path):\n"
        "    s = socket.socket(socket.AF_UNIX)\n"
        "    s.settimeout(2)\n"
        "    try:\n"
        "        s.connect(path)\n"
        "    finally:\n"
        "        s.close()\n"
        "def open_for_writing(path):\n"      # opening is enough to tell: nothing is written
        "    open(path, 'a').close()\n"
        "async def main(node):\n"
        "    port, others = int(sys.argv[1]), sys.argv[2:]\n"
        "    out = {'tcp': attempt(lambda: socket.create_connection(('127.0.0.1', port), timeout=2).close())}\n"
        "    out['unix'] = {p: attempt(lambda p=p: unix(p)) for p in others}\n"
        "    out['own_bus'] = attempt(lambda: unix(os.environ['RCE_BUS']))\n"
        "    procs = {}\n"
        "    for d in os.listdir('/proc'):\n"
        "        if d.isdigit():\n"
        "            try:\n"
        "                procs[d] = open(f'/proc/{d}/cmdline', 'rb').read().replace(b'\\0', b' ').decode().strip()\n"
        "            except OSError:\n"
        "                pass\n"
        "    out['procs'] = procs\n"
        "    out['hostname'] = socket.gethostname()\n"
        "    out['links'] = sorted(n for _, n in socket.if_nameindex())\n"
        "    cap = next(l for l in open('/proc/self/status') if l.startswith('CapBnd'))\n"
        "    out['cap_sys_admin'] = bool(int(cap.split()[1], 16) >> 21 & 1)\n"
        "    mounts = [l.split() for l in open('/proc/self/mountinfo')]\n"
        "    roots = [m[4] for m in mounts if m[m.index('-') + 1] in ('cgroup', 'cgroup2')]\n"
        "    out['cgroup_escape'] = {r: attempt(lambda r=r: open_for_writing(r + '/cgroup.procs')) for r in roots}\n"
        "    rt = os.path.dirname(os.path.dirname(os.environ['RCE_BUS']))\n"
        "    out['runtime_dir'] = sorted(os.listdir(rt))\n"
        "    out['topics'] = sorted(t['name'] for t in (await node.describe())['topics'])\n"
        "    print(json.dumps(out), flush=True)\n"
        "rce.node.run(main, 'probe')\n"),
}


def make_helper_package(root: Path) -> Path:
    pkg = root / "CTest"
    pkg.mkdir(parents=True)
    for name, text in HELPER_PKG.items():
        (pkg / name).write_text(text)
    (pkg / "run.sh").chmod(0o755)
    return root


class FakeMaster:
    """Plays rce-master's control port: records ``register`` (answering ``answer``) and
    ``node_status`` and lets the test call ops on the registered task set. Like rce-master it
    holds a cluster key (``key``, in the file ``key_file`` once started) and serves only links
    that prove it."""

    def __init__(self) -> None:
        self.key = ClusterKey.generate()
        self.key_file: Path | None = None
        self.server: asyncio.AbstractServer | None = None
        self.port = 0
        self.peer: RpcPeer | None = None
        self.registration: dict = {}
        self.registered = asyncio.Event()
        self.answer: dict = {"tid": 7}
        self.statuses: list[dict] = []
        self._changed = asyncio.Condition()

    async def start(self) -> None:
        self.server = await asyncio.start_server(self._accept, "127.0.0.1", 0)
        self.port = self.server.sockets[0].getsockname()[1]
        fd, name = tempfile.mkstemp(prefix="rce-cluster-key-")     # mode 0600
        with os.fdopen(fd, "w") as f:
            f.write(self.key.secret.hex())
        self.key_file = Path(name)

    def token(self, iid: int, peer_iid: int, peer_addr: str) -> str:
        """The credential rce-master hands ``iid`` with ``connect`` (hex)."""
        return self.key.connection_token(iid, peer_iid, peer_addr)

    async def _accept(self, reader, writer) -> None:
        await respond(reader, writer, self.key)
        peer = RpcPeer(reader, writer, name="task set")

        async def register(a: dict) -> dict:
            self.peer, self.registration = peer, a
            self.registered.set()
            return self.answer

        async def node_status(a: dict) -> None:
            async with self._changed:
                self.statuses.append(a)
                self._changed.notify_all()
        peer.handlers.update(register=register, node_status=node_status)
        peer.start()
        peer.keepalive()        # as rce-master does: the task set sees pings, and must answer them

    async def call(self, op: str, **args) -> Any:
        return await self.peer.request(op, args, STEP + 10)

    async def wait_status(self, pred: Callable[[dict], bool], timeout: float = STEP) -> dict:
        """The first recorded node_status matching ``pred`` (waits for it)."""
        async def find() -> dict:
            async with self._changed:
                while True:
                    for s in self.statuses:
                        if pred(s):
                            return s
                    await self._changed.wait()
        return await asyncio.wait_for(find(), timeout)

    def statuses_of(self, cid: int, ntag: str) -> list[dict]:
        return [s for s in self.statuses if s["cid"] == cid and s["ntag"] == ntag]

    async def wait_bus(self, cid: int, pred: Callable[[dict], bool], timeout: float = STEP) -> dict:
        """Poll ``describe`` until ``pred(description)`` holds (a condition, not a delay)."""
        deadline = time.monotonic() + timeout
        while True:
            d = await self.call("describe", cid=cid)
            if pred(d):
                return d
            if time.monotonic() > deadline:
                raise AssertionError(f"bus of container {cid} never reached the condition: {d}")
            await asyncio.sleep(0.02)

    async def close(self) -> None:
        if self.peer:
            await self.peer.close()
        if self.server:
            self.server.close()
        if self.key_file:
            self.key_file.unlink(missing_ok=True)


def topic(d: dict, name: str) -> dict:
    return next((t for t in d["topics"] if t["name"] == name), {"publishers": [], "subscribers": []})


def has_service(d: dict, name: str) -> bool:
    return any(s["name"] == name for s in d["services"])


class ContainerProcess:
    """The real ``rce-container`` process, registered with a :class:`FakeMaster`."""

    def __init__(self, workdir: Path, master: FakeMaster, extra_env: dict | None = None, args: tuple = ()):
        self.workdir, self.master = workdir, master
        self.args = tuple(args)
        self.runtime_dir = Path(tempfile.mkdtemp(prefix="rcec-"))
        self.ready_file = workdir / "container.ready"
        self.log_path = workdir / "container.log"
        self.env = {**os.environ, "RCE_LOG_JSON": "0", KEY_ENV: str(master.key_file), **(extra_env or {})}
        self.proc: asyncio.subprocess.Process | None = None

    async def start(self) -> None:
        with open(self.log_path, "wb") as logf:
            self.proc = await asyncio.create_subprocess_exec(
                str(BIN / "rce-container"), "127.0.0.1", "--master-port", str(self.master.port),
                "--ready-file", str(self.ready_file), "--runtime-dir", str(self.runtime_dir), "--grace", "1",
                "--name", "test-host", *self.args, stdout=logf, stderr=logf, env=self.env)
        waiter = asyncio.create_task(self.proc.wait())
        reg = asyncio.create_task(self.master.registered.wait())
        done, _ = await asyncio.wait({waiter, reg}, timeout=STEP, return_when=asyncio.FIRST_COMPLETED)
        waiter.cancel()
        if reg not in done:
            reg.cancel()
            raise AssertionError(f"rce-container did not register:\n{self.log_text()}")

    def ready_info(self) -> dict:
        return json.loads(self.ready_file.read_text())

    async def terminate(self, sig: int = signal.SIGTERM) -> int:
        if self.proc.returncode is None:
            self.proc.send_signal(sig)
        return await asyncio.wait_for(self.proc.wait(), STEP)

    async def kill(self) -> None:
        if self.proc and self.proc.returncode is None:
            self.proc.kill()
            await self.proc.wait()

    def log_text(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-20000:]
        except FileNotFoundError:
            return ""


class RobotInterface(Interface):
    """A robot-side interface on the test's data plane: records what arrives."""

    def __init__(self, plane: DataPlane, iid: int, tag: str, kind: str, cls: str):
        super().__init__(plane, iid, tag, kind, cls)
        self.inbox: asyncio.Queue = asyncio.Queue()

    def on_message(self, payload) -> None:
        self.inbox.put_nowait(bytes(payload))


def gone(pid: int) -> bool:
    """True if ``pid`` no longer runs (absent, or a zombie nobody reaped yet)."""
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


async def wait_gone(pids: list[int], timeout: float = STEP) -> list[int]:
    """Wait (polling) until every pid in ``pids`` is gone; returns those still alive."""
    deadline = time.monotonic() + timeout
    while True:
        alive = [p for p in pids if not gone(p)]
        if not alive or time.monotonic() > deadline:
            return alive
        await asyncio.sleep(0.02)


def kill_leftovers(pids: list[int]) -> None:
    for p in pids:
        try:
            os.kill(p, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
