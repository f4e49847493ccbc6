"""Containers that contain: each probe of one user's node against another user's container or the
host, replayed against real container hosts and real nodes, and failing.

- Two namespaced container hosts on one machine (each playing a different user): B's node
  looks for A's runtime directory, bus socket and the master's token file, and tries to join
  A's bus, read A's private parameter, call A's service and inject a message A receives.
- A node is root with CAP_DAC_OVERRIDE: it reads token files, writes /etc/passwd and the
  engine's code.
- A node inherits the host's environment (``RCE_ADMIN_TOKEN``); ``$(env X)`` copies host
  variables into argv.

The attacker is a node program written for the test (``Attack/attack.py``), started in B's
container through the container host's ``add_node``; where a probe needs a process that can
see A's socket (as if the mount namespace had failed), the same program runs on the host
under B's node uid, or under A's own node uid without A's bus token.

Needs root (the namespaced sandbox), like tests/container/test_sandbox.py.
"""
from __future__ import annotations

import asyncio
import json
import os
import socket
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from rce.bus.core import Bus
from rce.bus.server import BusServer
from rce.plumbing.errors import AuthError, RequestError
from rce.transport.rpc import connect_unix
from rce_container import mounts
from rce_container.node_env import ENV_DIRECTIVE_ALLOWED, RUNTIME_ROOT, node_env
from tests.container.harness import STEP, ContainerProcess, FakeMaster, has_service, make_helper_package
from tests.container.test_sandbox import start_host, stop_host, wait_stdout

pytestmark = pytest.mark.timeout(90)

ADMIN_TOKEN = "admin-token-of-the-host-do-not-leak"
SECRET = "alice's private parameter"

# The attacker. ``look``: what a node sees and may do from inside its container (one JSON
# line). ``join SOCKET TOKEN``: join a bus as a node would, then read /secret, call
# /stringEchoService and publish on /stringEchoReq (one JSON line of what worked).
ATTACK = r'''
import asyncio, errno, json, os, socket, sys

def attempt(fn):
    try:
        r = fn()
        return "ok" if r is None else r
    except OSError as e:
        return errno.errorcode.get(e.errno, str(e))

def append(path):
    open(path, "a").close()

def create(path):
    with open(path, "w") as f:
        f.write("x")
    os.unlink(path)

def connect(path):
    s = socket.socket(socket.AF_UNIX)
    s.settimeout(2)
    try:
        s.connect(path)
    finally:
        s.close()

def status():
    keys = ("Uid", "Gid", "Groups", "CapInh", "CapPrm", "CapEff", "CapBnd", "CapAmb", "NoNewPrivs")
    out = {}
    for line in open("/proc/self/status"):
        k, _, v = line.partition(":")
        if k in keys:
            out[k] = v.split()
    return out

def look(victim_runtime, victim_socket, token_file, engine_file):
    home = os.environ["HOME"]
    return {
        "status": status(), "env": sorted(os.environ), "home": home,
        "victim_runtime": attempt(lambda: os.listdir(victim_runtime)),
        "victim_socket": attempt(lambda: connect(victim_socket)),
        "tmp": sorted(os.listdir("/tmp")),
        "root_home": attempt(lambda: sorted(os.listdir("/root"))),
        "read_token_file": attempt(lambda: open(token_file).read() and None),
        "write_token_file": attempt(lambda: append(token_file)),
        "write_passwd": attempt(lambda: append("/etc/passwd")),
        "write_engine": attempt(lambda: append(engine_file)),
        "write_home": attempt(lambda: create(os.path.join(home, "mine"))),
        "write_tmp": attempt(lambda: create("/tmp/mine")),
        "write_var_tmp": attempt(lambda: create("/var/tmp/mine")),
        "write_root_dir": attempt(lambda: create("/mine")),
        "own_bus": attempt(lambda: connect(os.environ["RCE_BUS"])),
    }

async def join(path, token):
    from rce.transport.rpc import connect_unix
    out = {}
    try:
        peer = await connect_unix(path, name="attacker")
    except OSError as e:
        return {"connect": errno.errorcode.get(e.errno, str(e))}
    out["connect"] = "ok"
    async def op(opname, **a):
        try:
            return {"ok": await peer.request(opname, a, 5)}
        except Exception as e:
            return {"error": type(e).__name__ + ": " + str(e)}
    out["before_hello"] = await op("get_param", name="/secret")
    out["hello"] = await op("hello", name="/attacker", pid=os.getpid(), token=None if token == "-" else token)
    out["get_param"] = await op("get_param", name="/secret")
    out["resolve"] = await op("resolve_service", service="/stringEchoService")
    out["advertise"] = await op("advertise", topic="/stringEchoReq", type="std_msgs/String")
    await peer.close()
    return out

if sys.argv[1] == "look":
    print(json.dumps(look(*sys.argv[2:])), flush=True)
else:
    print(json.dumps(asyncio.run(join(*sys.argv[2:]))), flush=True)
'''


def make_packages(root: Path) -> tuple[Path, Path]:
    """CTest (the container tests' helpers) and Attack; Attack holds ``token-file``: root's,
    mode 0600, like the master's admin token file (and visible to nodes: the package is)."""
    make_helper_package(root)
    pkg = root / "Attack"
    pkg.mkdir()
    (pkg / "attack.py").write_text(ATTACK)
    token_file = pkg / "token-file"
    token_file.write_text(ADMIN_TOKEN)
    token_file.chmod(0o600)
    return root, token_file


async def start_ns_host(tmp_path: Path, pkgs: Path, name: str) -> tuple[FakeMaster, ContainerProcess]:
    """A namespaced rce-container whose own environment holds an admin token."""
    work = tmp_path / name
    work.mkdir()
    master, cp = await start_host(work, "--sandbox", "namespaced", pkgs=pkgs, env={"RCE_ADMIN_TOKEN": ADMIN_TOKEN})
    assert master.registration["sandbox"] == "namespaced"
    return master, cp


async def run_as(uid: int, *argv: str, mount_ns_of: int | None = None) -> dict:
    """Run the attacker (from stdin: the test's directory is root's) as ``uid`` (no groups,
    no capabilities), on the host or in the mount namespace of process ``mount_ns_of``; its
    JSON line."""
    enter = ["nsenter", "-t", str(mount_ns_of), "-m", "--"] if mount_ns_of else []
    cmd = [*enter, "setpriv", f"--reuid={uid}", f"--regid={uid}", "--clear-groups", "--inh-caps=-all",
           "--bounding-set=-all", "--", sys.executable, "-", *argv]
    env = {"PATH": os.environ["PATH"], "PYTHONPATH": str(RUNTIME_ROOT),
           **{k: os.environ[k] for k in ("LD_LIBRARY_PATH", "_ROS_WHEELS_BOOTSTRAP_COMPLETE") if k in os.environ}}
    r = await asyncio.to_thread(subprocess.run, cmd, input=ATTACK, capture_output=True, text=True, timeout=STEP,
                                env=env, cwd="/")
    assert r.returncode == 0 and r.stdout, r.stderr
    return json.loads(r.stdout)


def container_args(cid: int, ctag: str, user: str) -> dict:
    return {"cid": cid, "user": user, "ctag": ctag, "group": None,
            "limits": {"cpu": None, "memory": None, "pids": None, "size": None, "bandwidth": None}}


async def test_one_users_node_cannot_see_or_join_another_users_container(tmp_path):
    assert os.geteuid() == 0, "the namespaced sandbox needs root; run the security tests as root"
    pkgs, token_file = make_packages(tmp_path / "pkgs")
    (ma, a), (mb, b) = await asyncio.gather(start_ns_host(tmp_path, pkgs, "alice"),
                                            start_ns_host(tmp_path, pkgs, "bob"))
    try:
        # Alice's robot container: an echo node (service + topic) and a private parameter
        await ma.call("create_container", **container_args(1, "alice-robot", "alice"))
        await ma.call("set_param", cid=1, name="/secret", value=SECRET)
        await ma.call("add_node", cid=1, ntag="echo", pkg="Test", exe="stringEcho.py", name="echo")
        await ma.wait_bus(1, lambda d: has_service(d, "/stringEchoService"))
        victim_sock = str(a.runtime_dir / "c1" / "bus.sock")
        alice = (await ma.call("stats", cid=1))["sandbox_info"]["uid"]
        # the bus socket is not world-writable: its node uid's only
        st = os.stat(victim_sock)
        assert stat.S_IMODE(st.st_mode) == 0o660 and st.st_uid == st.st_gid == alice != 0

        # Bob's container on the same machine (same cid on another task set); his node attacks
        await mb.call("create_container", **container_args(1, "bob-robot", "bob"))
        await mb.call("add_node", cid=1, ntag="look", pkg="Attack", exe="attack.py",
                      args=["look", str(a.runtime_dir), victim_sock, str(token_file),
                            str(RUNTIME_ROOT / "rce" / "__init__.py")])
        seen = json.loads((await wait_stdout(mb, 1, "look"))[0])
        bob = (await mb.call("stats", cid=1))["sandbox_info"]["uid"]
        assert bob != alice and bob != 0

        # an unprivileged uid of its own, with no capability at all and no way back to root
        s = seen["status"]
        assert s["Uid"] == [str(bob)] * 4 and s["Gid"] == [str(bob)] * 4 and s["Groups"] == []
        assert {k: s[k] for k in ("CapInh", "CapPrm", "CapEff", "CapBnd", "CapAmb")} == \
            dict.fromkeys(("CapInh", "CapPrm", "CapEff", "CapBnd", "CapAmb"), ["0000000000000000"])
        assert s["NoNewPrivs"] == ["1"]
        # nothing of Alice's host is visible: its runtime dir, bus socket; nor root's home
        assert seen["victim_runtime"] == "ENOENT" and seen["victim_socket"] == "ENOENT"
        assert a.runtime_dir.name not in seen["tmp"] and "mine" not in seen["tmp"]
        assert seen["root_home"] in ("EACCES", [".pyenv"], []), seen["root_home"]
        # a file of root's it can see, the passwd file and the engine's code: neither read nor written
        assert seen["read_token_file"] == "EACCES" and seen["write_token_file"] in ("EACCES", "EROFS")
        assert seen["write_passwd"] in ("EACCES", "EROFS") and seen["write_engine"] in ("EACCES", "EROFS")
        # only its own directory (and a private /tmp) is writable
        assert seen["write_home"] == "ok" and seen["write_tmp"] == "ok"
        assert seen["write_var_tmp"] in ("EROFS", "EACCES", "ENOENT") and seen["write_root_dir"] in ("EROFS", "EACCES")
        assert seen["home"] == str(b.runtime_dir / "c1") and seen["own_bus"] == "ok"
        # a minimal, explicit environment: no host variable, no admin token (PWD: nsenter --wd sets it)
        assert set(seen["env"]) <= {"PATH", "HOME", "LANG", "PYTHONUNBUFFERED", "PYTHONPATH", "RCE_BUS",
                                    "RCE_BUS_TOKEN", "RCE_CONTAINER", "RCE_NODE_NAME", "RCE_NAMESPACE",
                                    "RCE_PACKAGE_PATH", "RCE_LOG_JSON", "RCE_LOG_LEVEL", "PWD",
                                    "LD_LIBRARY_PATH", "_ROS_WHEELS_BOOTSTRAP_COMPLETE"}, seen["env"]
        # $(env X) cannot copy a host variable into argv
        with pytest.raises(RequestError, match="RCE_ADMIN_TOKEN"):
            await mb.call("add_node", cid=1, ntag="leak", pkg="Attack", exe="attack.py",
                          args="look $(env RCE_ADMIN_TOKEN)")

        # Had Bob's node found Alice's socket anyway: the socket refuses its uid ...
        assert (await run_as(bob, "join", victim_sock, "-")) == {"connect": "EACCES"}
        # ... and a process of Alice's node uid that the launcher did not start (run in her
        # container's view: on the host her runtime directory is root's) has no bus token
        init = (await ma.call("stats", cid=1))["sandbox_info"]["init_pid"]
        got = await run_as(alice, "join", victim_sock, "-", mount_ns_of=init)
        assert got["connect"] == "ok", got
        for step in ("before_hello", "hello", "get_param", "resolve", "advertise"):
            assert "ok" not in got.get(step, {}), (step, got)
        assert "AuthError" in got["hello"]["error"] and "bus token" in got["hello"]["error"]
        wrong = await run_as(alice, "join", victim_sock, "0" * 64, mount_ns_of=init)
        assert "AuthError" in wrong["hello"]["error"] and "ok" not in wrong["get_param"]
        # root (another uid than the container's) is cut off at connect by SO_PEERCRED
        with socket.socket(socket.AF_UNIX) as sk:
            sk.connect(victim_sock)
            sk.settimeout(STEP)
            assert sk.recv(1) == b""
        env_bus = (await ma.call("stats", cid=1))["environment"]["bus"]
        assert env_bus["refused"] == 3, env_bus
        # Alice's container is untouched: her param, her service, no stranger on her bus
        d = await ma.call("describe", cid=1)
        assert [n for n in d["nodes"] if "attacker" in str(n)] == []
        assert await ma.call("bus_call", cid=1, service="/stringEchoService", request={"data": "still mine"},
                             timeout=5) == {"data": "still mine"}
        for host in (a, b):                                    # and both hosts shut down cleanly
            assert await host.terminate() == 0, host.log_text()
    except BaseException:
        print(a.log_text()[-5000:], b.log_text()[-5000:])
        raise
    finally:
        await asyncio.gather(stop_host(ma, a), stop_host(mb, b))


async def test_a_bus_admits_only_its_token_and_uid(tmp_path):
    """In-process: a bus with a token (and a uid) refuses, counts and cuts off anyone else;
    the rightful node joins and works."""
    path = str(tmp_path / "bus.sock")
    server = BusServer(Bus("t"), token="right", uids={os.geteuid()})
    await server.listen(path)
    try:
        assert stat.S_IMODE(os.stat(path).st_mode) == 0o660
        for token in (None, "wrong", 7):
            peer = await connect_unix(path, name="stranger")
            with pytest.raises(Exception, match="unknown control op"):
                await peer.call("describe")                   # nothing before hello
            with pytest.raises(AuthError, match="bus token"):
                await peer.call("hello", name="/x", token=token)
            await asyncio.wait_for(peer.link.closed.wait(), STEP)   # and the link is closed
        assert server.refused == 3 and not server.bus.nodes
        peer = await connect_unix(path, name="node")
        assert await peer.call("hello", name="/n", token="right") == {"bus": "t"}
        await peer.call("set_param", name="/p", value=1)
        assert await peer.call("get_param", name="/p") == 1
        await peer.close()
        server.uids = frozenset({os.geteuid() + 1})           # a process of another uid: cut at connect
        peer = await connect_unix(path, name="other uid")
        await asyncio.wait_for(peer.link.closed.wait(), STEP)
        assert server.refused == 4
    finally:
        await server.close()


def test_node_env_is_minimal_and_directives_read_only_the_allow_list():
    host = {"RCE_ADMIN_TOKEN": "x", "AWS_SECRET_ACCESS_KEY": "y", "RCE_PACKAGE_PATH": "/pkgs", "HOME": "/root",
            "PATH": "/host/bin"}
    env = node_env(bus="/b.sock", token="t", ctag="c", name="n", namespace="/", home="/w", host=host,
                   extra={"ROS_MASTER_URI": "http://localhost:11311"})
    assert "RCE_ADMIN_TOKEN" not in env and "AWS_SECRET_ACCESS_KEY" not in env
    assert env["HOME"] == "/w" and env["RCE_PACKAGE_PATH"] == "/pkgs" and env["RCE_BUS_TOKEN"] == "t"
    assert env["PATH"].endswith(":/usr/local/bin:/usr/bin:/bin") and "/host/bin" not in env["PATH"]
    assert env["ROS_MASTER_URI"] == "http://localhost:11311"
    assert "RCE_BUS_TOKEN" not in ENV_DIRECTIVE_ALLOWED and "RCE_ADMIN_TOKEN" not in ENV_DIRECTIVE_ALLOWED
    from rce_container.launcher import build_args
    assert build_args("$(env HOME)", env, ENV_DIRECTIVE_ALLOWED) == ["/w"]
    for name in ("RCE_BUS_TOKEN", "RCE_ADMIN_TOKEN"):
        with pytest.raises(RequestError, match=f"may not read '{name}'"):
            build_args(f"--x=$(env {name})", env, ENV_DIRECTIVE_ALLOWED)
        assert build_args(f"$(optenv {name} d)", env, ENV_DIRECTIVE_ALLOWED) == ["d"]   # as if not set


def test_mount_plan_hides_tmp_run_and_closed_homes_but_keeps_the_runtime():
    modes = {"/root": 0o40700}
    plan = mounts.plan("/tmp/rcec-1/c3", "/tmp/rcec-1/c3",
                       ["/root/.pyenv/versions/3.11", "/root/.pyenv/versions/3.11/lib", "/work/main",
                        "/tmp/p/pkgs"],
                       mode_of=lambda p: modes.get(p, 0o40755))
    masks = {d: (keep, opts) for d, keep, opts in plan["masks"]}
    assert masks["/tmp"] == (["/tmp/rcec-1/c3", "/tmp/p/pkgs"], mounts.SCRATCH_OPTS)
    assert masks["/root"] == (["/root/.pyenv/versions/3.11"], mounts.SKELETON_OPTS)
    assert masks["/run"] == ([], mounts.SKELETON_OPTS) and "/dev/shm" in masks
    assert "/tmp/rcec-1" not in masks and "/work" not in masks      # hidden by /tmp already; open to all
    assert plan["writable"] == ["/tmp/rcec-1/c3", "/tmp", "/dev/shm"]
    # a runtime dir outside the hidden ones: only the container's own directory is bound back
    plan = mounts.plan("/srv/rce/c1", "/srv/rce/c1", [], mode_of=lambda p: 0o40755)
    assert ["/srv/rce", ["/srv/rce/c1"], mounts.SKELETON_OPTS] in plan["masks"]
