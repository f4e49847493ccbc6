"""The container's warm node launcher (rce_container/zygote.py): a Python node forked by the
zygote runs exactly as an exec'd one (environment, uid, capabilities, namespaces, cgroup, cwd,
argv, signals, descriptors), and the launcher still sees its exit code or signal, keeps its
output, respawns it, stops it, and reports a crash during import and the zygote's own death.

In-process: a real sandbox (namespaced, as root, and unconfined), the environment's zygote
template and the :class:`Launcher`, with no engine around them."""
from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import tempfile
import time
from pathlib import Path

import psutil
import pytest

from rce_container import sandbox as sandboxes
from rce_container.launcher import Launcher
from rce_container.zygote_client import ZygoteTemplate
from tests.container.harness import STEP, gone

NEEDS_ROOT = "the namespaced sandbox needs root; CI runs the test suite as root (run these tests as root)"

SCRIPTS = {
    "exiter.py": (
        "import sys\n"
        "print('argv=' + '|'.join(sys.argv[1:]), flush=True)\n"
        "print('bye', file=sys.stderr, flush=True)\n"
        "sys.exit(int(sys.argv[1]))\n"),
    "sleeper.py": "import time\nprint('up', flush=True)\ntime.sleep(600)\n",
    "broken.py": "import no_such_module_for_rce_tests\n",
    # What a node sees of itself, as one JSON line.
    "look.py": (
        "import json, os, signal, socket, sys\n"
        "KEYS = ('CapInh', 'CapPrm', 'CapEff', 'CapBnd', 'CapAmb', 'NoNewPrivs', 'Seccomp', 'Groups')\n"
        "with open('/proc/self/status') as f:\n"
        "    status = {k: v.strip() for k, _, v in (line.partition(':') for line in f) if k in KEYS}\n"
        "fds = {}\n"
        "for fd in os.listdir('/proc/self/fd'):\n"
        "    try:\n"
        "        fds[fd] = os.readlink(f'/proc/self/fd/{fd}')\n"
        "    except OSError:\n"
        "        pass\n"
        "with open('/proc/self/cmdline', 'rb') as f:\n"
        "    cmdline = [a.decode() for a in f.read().split(b'\\0')[:len(sys.argv) + 1]]\n"
        "with open('/proc/self/cgroup') as f:\n"
        "    cgroup = f.read()\n"
        "print(json.dumps({\n"
        "    'env': dict(os.environ), 'ids': [os.getresuid(), os.getresgid(), os.getgroups()], 'cwd': os.getcwd(),\n"
        "    'argv': sys.argv, 'name': __name__, 'path0': sys.path[0], 'status': status, 'cgroup': cgroup,\n"
        "    'ns': {n: os.readlink(f'/proc/self/ns/{n}') for n in ('pid', 'mnt', 'net', 'ipc', 'uts')},\n"
        "    'leader': [os.getsid(0) == os.getpid(), os.getpgid(0) == os.getpid()], 'cmdline': cmdline,\n"
        "    'signals': {s: str(signal.getsignal(getattr(signal, s))) for s in\n"
        "                ('SIGTERM', 'SIGINT', 'SIGPIPE', 'SIGCHLD', 'SIGHUP')},\n"
        "    'stdin': fds.get('0'), 'sockets': sorted(v for v in fds.values() if v.startswith('socket:')),\n"
        "    'umask': os.umask(0o22), 'hostname': socket.gethostname()}), flush=True)\n"),
}


class Box:
    """A set-up sandbox, the zygote template, and the statuses its launchers reported."""

    def __init__(self, sandbox: sandboxes.Sandbox, template: ZygoteTemplate):
        self.sandbox, self.template = sandbox, template
        self.statuses: list[tuple[str, str, dict]] = []
        self.launchers: list[Launcher] = []

    def launcher(self, zygote: bool = True) -> Launcher:
        lc = Launcher(self.sandbox, str(self.sandbox.bus_socket), "ztest",
                      lambda ntag, status, **f: self.statuses.append((ntag, status, f)), bus_token="t" * 64,
                      zygote=zygote, template=self.template)
        self.launchers.append(lc)
        return lc

    def of(self, ntag: str) -> list[tuple[str, dict]]:
        return [(s, f) for n, s, f in self.statuses if n == ntag]

    async def wait_status(self, ntag: str, status: str, count: int = 1) -> dict:
        """The ``count``-th ``status`` of ``ntag`` (polled until it comes)."""
        deadline = time.monotonic() + STEP
        while True:
            seen = [f for s, f in self.of(ntag) if s == status]
            if len(seen) >= count:
                return seen[count - 1]
            assert time.monotonic() < deadline, f"{ntag} never reported {status} #{count}: {self.of(ntag)}"
            await asyncio.sleep(0.01)


async def wait_logs(lc: Launcher, ntag: str, stream: str = "stdout") -> list[str]:
    deadline = time.monotonic() + STEP
    while not (lines := lc.logs(ntag)[stream]):
        assert time.monotonic() < deadline, f"{ntag} printed nothing on {stream}"
        await asyncio.sleep(0.01)
    return lines


@pytest.fixture(params=["namespaced", "unconfined"])
async def box(request, tmp_path, monkeypatch):
    if request.param == "namespaced":
        assert os.geteuid() == 0, NEEDS_ROOT
    pkg = tmp_path / "pkgs" / "ZTest"
    pkg.mkdir(parents=True)
    for name, text in SCRIPTS.items():
        (pkg / name).write_text(text)
    monkeypatch.setenv("RCE_PACKAGE_PATH", str(pkg.parent))
    sandboxes._readable.cache_clear()          # the package directory is new: nodes must see it
    cls = sandboxes.select(request.param)
    scope = sandboxes.host_scope(f"zygote-test-{request.param}")
    cls.prepare_host(scope)
    run = Path(tempfile.mkdtemp(prefix="rcez-"))
    (run / "c").mkdir()
    (run / "s").mkdir()
    sb = cls(900_000 + os.getpid() % 100_000, "ztest", {}, run / "c", bus_socket=run / "s" / "bus.sock",
             scope=scope, grace=1)
    template = ZygoteTemplate.for_nodes(run)
    b = Box(sb, template)
    try:
        await sb.setup()
        template.start_soon()
        assert await template.wait_started(), f"the zygote template did not start: {list(template.output)}"
        yield b
    finally:
        for lc in b.launchers:
            await lc.close()
        await template.close()
        await sb.close()
        cls.cleanup_host(scope)
        sandboxes._readable.cache_clear()
        shutil.rmtree(run, ignore_errors=True)


@pytest.mark.parametrize("via", ["template", "forked template", "sandbox"])
async def test_a_forked_node_sees_what_an_execd_node_sees(box, via):
    if via == "sandbox":
        box.template = None                    # the zygote is spawned in the sandbox like a node
    elif via == "forked template":             # as an environment's: a fork of the task set's template
        box.template = ZygoteTemplate.for_nodes(box.template.env["HOME"], box.template.fork_template())
        box.template.start_soon()
        assert await box.template.wait_started() and box.template.forked
    forked, execd = box.launcher(), box.launcher(zygote=False)
    spec = {"ntag": "look", "pkg": "ZTest", "exe": "look.py", "args": "'a b' c $(env RCE_CONTAINER)",
            "name": "looker", "namespace": "ns"}
    try:
        await forked.add(spec)
        await execd.add(spec)
        seen_forked = json.loads((await wait_logs(forked, "look"))[0])
        seen_execd = json.loads((await wait_logs(execd, "look"))[0])
        assert forked.forks == 1 and execd.forks == 0 and execd.starts == 1
        seen_execd["env"].pop("PWD", None)      # set by the exec chain's sh (to "/", wrong anyway); not a node variable
        assert seen_forked == seen_execd
        assert seen_forked["argv"][1:] == ["a b", "c", "ztest"] and seen_forked["name"] == "__main__"
        assert seen_forked["env"]["RCE_NODE_NAME"] == "looker" and seen_forked["sockets"] == []
        assert seen_forked["leader"] == [True, True] and seen_forked["stdin"] == "/dev/null"
        if box.sandbox.node_uid is not None:   # namespaced: the container's uid, nothing left of root
            uid = box.sandbox.node_uid
            assert seen_forked["ids"] == [[uid] * 3, [uid] * 3, []]
            assert seen_forked["status"]["CapBnd"] == "0000000000000000" and seen_forked["status"]["NoNewPrivs"] == "1"
            assert seen_forked["ns"]["net"] != os.readlink("/proc/self/ns/net")
    finally:
        await forked.close()
        await execd.close()
        if via == "forked template":
            await box.template.close()


async def test_signals_the_host_was_started_with_ignored_stay_ignored_in_a_forked_node(box):
    """Under ``nohup`` or as a shell's background job a host starts with SIGINT / SIGHUP ignored:
    an exec'd node inherits them ignored, and so does a forked one."""
    old = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGHUP)}
    for sig in old:
        signal.signal(sig, signal.SIG_IGN)
    template = ZygoteTemplate.for_nodes(box.template.env["HOME"])
    forked = execd = None
    try:
        template.start_soon()
        assert await template.wait_started()
        box.template = template
        forked, execd = box.launcher(), box.launcher(zygote=False)
        spec = {"ntag": "look", "pkg": "ZTest", "exe": "look.py", "args": "x", "name": "looker"}
        await forked.add(spec)
        await execd.add(spec)
        seen_forked = json.loads((await wait_logs(forked, "look"))[0])["signals"]
        seen_execd = json.loads((await wait_logs(execd, "look"))[0])["signals"]
        assert forked.forks == 1 and execd.forks == 0
        assert seen_execd["SIGINT"] == seen_execd["SIGHUP"] == str(signal.SIG_IGN)
        assert seen_forked == seen_execd
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
        for lc in (forked, execd):
            if lc is not None:
                await lc.close()
        await template.close()


async def test_exit_signal_logs_respawn_crash_and_removal(box):
    lc = box.launcher()
    try:
        await lc.add({"ntag": "exiter", "pkg": "ZTest", "exe": "exiter.py", "args": "3"})
        st = await box.wait_status("exiter", "exited")
        assert st == {"code": 3} and lc.logs("exiter") == {"stdout": ["argv=3"], "stderr": ["bye"]}

        first = (await lc.add({"ntag": "sleeper", "pkg": "ZTest", "exe": "sleeper.py",
                               "respawn": {"delay": 0, "limit": 1}}))["pid"]
        await wait_logs(lc, "sleeper")
        assert psutil.Process(first).cmdline()[1].endswith("sleeper.py")     # a host pid, its own command line
        os.kill(first, signal.SIGKILL)
        assert (await box.wait_status("sleeper", "respawning"))["signal"] == signal.SIGKILL
        second = (await box.wait_status("sleeper", "started", 2))["pid"]
        assert second != first and lc.nodes["sleeper"].restarts == 1 and lc.forks == 3
        assert len(lc.logs("sleeper")["stdout"]) in (1, 2)                      # kept across the restart
        await lc.remove("sleeper")
        assert gone(second)
        assert (await box.wait_status("sleeper", "exited")) == {"reason": "removed", "signal": signal.SIGTERM}

        await lc.add({"ntag": "broken", "pkg": "ZTest", "exe": "broken.py"})
        st = await box.wait_status("broken", "exited")
        assert st["code"] == 1
        assert st["reason"] == "uncaught ModuleNotFoundError: No module named 'no_such_module_for_rce_tests'"
        assert lc.logs("broken")["stderr"][0].startswith("Traceback")
    finally:
        await lc.close()


async def test_the_zygote_dying_kills_its_nodes_and_later_nodes_are_execd(box):
    lc = box.launcher()
    try:
        pid = (await lc.add({"ntag": "sleeper", "pkg": "ZTest", "exe": "sleeper.py"}))["pid"]
        await wait_logs(lc, "sleeper")
        assert lc.forks == 1
        os.kill(lc.zygote.pid, signal.SIGKILL)
        st = await box.wait_status("sleeper", "exited")
        assert st["signal"] == signal.SIGKILL and "zygote exited" in st["reason"]
        assert not await _alive_after(pid), "a node of the dead zygote kept running"
        await lc.add({"ntag": "after", "pkg": "ZTest", "exe": "exiter.py", "args": "0"})
        assert (await box.wait_status("after", "exited")) == {"code": 0}
        assert lc.forks == 1 and lc.starts == 2 and lc.logs("after")["stdout"] == ["argv=0"]
    finally:
        await lc.close()


async def _alive_after(pid: int) -> bool:
    deadline = time.monotonic() + STEP
    while not gone(pid):
        if time.monotonic() > deadline:
            return True
        await asyncio.sleep(0.01)
    return False
