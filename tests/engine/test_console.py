"""rce-console against a real master: tables, users (hashed, never in clear), logs."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from wsclient import RawRobot, login

BIN = Path(sys.executable).parent


@pytest.fixture
def engine(shared_engine):
    """The module's engine: its tests use distinct robots, containers and users."""
    return shared_engine


def console(eng, *args, stdin: str | None = None, check=True) -> subprocess.CompletedProcess:
    p = subprocess.run([str(BIN / "rce-console"), "--master", eng.master_url, *args], input=stdin,
                       capture_output=True, text=True, env=eng.env, timeout=60)
    if check:
        assert p.returncode == 0, p.stderr
    return p


@pytest.mark.asyncio
async def test_tables_show_what_runs(engine):
    async with RawRobot(engine.master_url, "consoleBot") as r:
        await r.send("CC", {"containerTag": "consoleC", "containerData": {"group": "g1"}})
        await r.cn(addNodes=[{"containerTag": "consoleC", "nodeTag": "echo", "pkg": "Test", "exe": "stringEcho.py"}],
                   addInterfaces=[{"endpointTag": "consoleC", "interfaceTag": "req",
                                   "interfaceType": "PublisherInterface", "className": "std_msgs/String",
                                   "addr": "/stringEchoReq"},
                                  {"endpointTag": "consoleBot", "interfaceTag": "req",
                                   "interfaceType": "SubscriberConverter", "className": "std_msgs/String"}])
        await r.send("CX", {"connect": [{"tagA": "consoleC/req", "tagB": "consoleBot/req"}]})
        await r.wait_up("req")
        robots = json.loads(console(engine, "--json", "robots").stdout)
        assert [x["robot"] for x in robots] == ["consoleBot"]
        containers = json.loads(console(engine, "--json", "containers").stdout)
        assert containers[0]["ctag"] == "consoleC" and containers[0]["group"] == "g1"
        assert containers[0]["state"] == "running"
        out = console(engine, "interfaces").stdout
        assert "consoleC/req" in out and "PublisherInterface" in out and "consoleBot/req" in out
        assert "consoleC/req" in console(engine, "connections").stdout
        assert "stringEcho.py" in console(engine, "nodes").stdout
        ts = json.loads(console(engine, "--json", "tasksets").stdout)
        assert sorted(t["kind"] for t in ts) == ["container", "robot"]
        # a node's output is kept and readable
        logs = console(engine, "--json", "logs", "testUser", "consoleC", "echo")
        assert logs.returncode == 0


def test_user_add_login_and_delete(engine, tmp_path):
    p = console(engine, "user", "add", "alice", "--password-stdin", stdin="s3cret\n")
    assert "added" in p.stdout
    assert login(engine.master_url, "alice")["url"].startswith("ws://")
    assert "alice" in console(engine, "users").stdout
    dup = console(engine, "user", "add", "alice", "--password-stdin", stdin="x\n", check=False)
    assert dup.returncode == 1 and "already exists" in dup.stderr
    console(engine, "user", "del", "alice")
    assert "alice" not in console(engine, "users").stdout
    bad = subprocess.run([str(BIN / "rce-console"), "--master", engine.master_url, "--admin-token", "wrong", "users"],
                         capture_output=True, text=True, timeout=30)
    assert bad.returncode == 1 and "HTTP 401" in bad.stderr


def test_roles_are_set_listed_and_told_by_the_password_check(engine):
    p = console(engine, "user", "add", "vera", "--role", "viewer", "--password-stdin", stdin="v3ra\n")
    assert "added, is viewer" in p.stdout
    users = {u["name"]: u["role"] for u in json.loads(console(engine, "--json", "users").stdout)}
    assert users["vera"] == "viewer" and users["testUser"] == "admin"          # --dev's user administers
    assert "is now operator" in console(engine, "user", "role", "vera", "--role", "operator").stdout
    from rce.plumbing.errors import AuthError, Throttled
    from rce_master.state.model import password_digest
    ok = engine.admin("/api/auth", {"user": "vera", "password": password_digest("v3ra"), "addr": "192.0.2.7"})
    assert ok == {"user": "vera", "role": "operator"}
    for _ in range(5):                      # the robots' login guard: five free failures per user and address
        with pytest.raises(AuthError):
            engine.admin("/api/auth", {"user": "vera", "password": password_digest("no"), "addr": "192.0.2.7"})
    with pytest.raises(Throttled) as e:     # then 429: even the right password waits
        engine.admin("/api/auth", {"user": "vera", "password": password_digest("v3ra"), "addr": "192.0.2.7"})
    assert e.value.status == 429 and e.value.retry_after >= 1 and "retry after" in str(e.value)
    assert engine.admin("/api/auth", {"user": "vera", "password": password_digest("v3ra"),
                                      "addr": "192.0.2.8"})["role"] == "operator"   # not from another address
    bad = console(engine, "user", "role", "vera", "--role", "boss", check=False)
    assert bad.returncode == 2 and "invalid choice: 'boss'" in bad.stderr
    console(engine, "user", "del", "vera")


def test_users_file_is_hashed_and_loaded(tmp_path):
    f = tmp_path / "users.json"
    p = subprocess.run([str(BIN / "rce-console"), "user", "add", "bob", "--file", str(f), "--password-stdin"],
                       input="hunter22\n", capture_output=True, text=True, timeout=30)
    assert p.returncode == 0, p.stderr
    text = f.read_text()
    assert "hunter22" not in text and "scrypt" in text and (f.stat().st_mode & 0o777) == 0o600
    from rce.tools.launch import start_engine
    e = start_engine(tmp_path / "eng", robot_tasksets=1, container_hosts=0, master_args=("--users", str(f)))
    try:
        assert login(e.master_url, "bob")["url"].startswith("ws://")
    finally:
        e.stop()
    offline = [str(BIN / "rce-console"), "user", "add", "bob", "--file", str(f), "--password-stdin"]
    dup = subprocess.run(offline, input="x\n", capture_output=True, text=True, timeout=30)
    assert dup.returncode == 1 and f"{f}: user 'bob' already exists" in dup.stderr
    offline[2] = "del"
    assert subprocess.run(offline, capture_output=True, text=True, timeout=30).returncode == 0
    assert json.loads(f.read_text()) == {"users": []}
    gone = subprocess.run(offline, capture_output=True, text=True, timeout=30)
    assert gone.returncode == 1 and "no user 'bob'" in gone.stderr
