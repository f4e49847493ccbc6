"""rce-topic record: ROS 1 bags from a real local bus (the Test package's nodes as processes) and
through the admin API path; read back with the rosbags reader and Debian's ``rosbag info``."""
from __future__ import annotations

import asyncio
import os
import shutil
import signal
import subprocess

import pytest
import yaml
from rosbags.rosbag1 import Reader

from rce.plumbing.errors import MessageError, RequestError
from rce.messages import default_registry
from rce_client.bag import BagRecorder

from .test_client_tools import BIN, admin, bus, run, until  # noqa: F401  (fixtures)

ROSBAG_HINT = "Debian's rosbag is missing: apt-get install -y python3-rosbag (.ci/system-deps installs it as root)"
SIGNAL_WAIT = 10.0      # s for ``rce-topic record`` to start recording, and to exit after SIGTERM
LATER_WAIT = 30.0       # s for a publisher started later (a new interpreter) to be found and recorded: a hang's
                        # limit (a machine 7x oversubscribed took more than 10 s)


def read_bag(path) -> tuple[dict[str, str], list[tuple[str, int, str]]]:
    """(topic -> ROS 1 type, [(topic, stamp ns, data)]) of a bag of std_msgs/String topics, as rosbags reads it."""
    reg = default_registry()
    with Reader(path) as r:
        types = {c.topic: c.msgtype for c in r.connections}
        msgs = [(c.topic, t, reg.deserialize(c.msgtype, raw).data) for c, t, raw in r.messages()]
    return types, msgs


def rosbag_info(path) -> dict:
    """``rosbag info --yaml PATH``, parsed; fails with the install hint when rosbag is missing."""
    exe = shutil.which("rosbag")
    if exe is None:
        pytest.fail(ROSBAG_HINT)
    p = subprocess.run([exe, "info", "--yaml", str(path)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    return yaml.safe_load(p.stdout)


def tool_subscribed(b, topic: str) -> bool:
    t = b.topics.get(topic)
    return t is not None and any(s.owner.startswith("/rce_tool") for s in t.subscriptions)


async def test_record_a_real_bus_until_count(bus, capsys, tmp_path):   # noqa: F811
    b, path = bus
    out = tmp_path / "echo.bag"
    rec = asyncio.create_task(run("topic", ["--bus", path, "record", "-o", str(out), "/stringEchoReq",
                                            "stringEchoResp", "--count", "6"], capsys))
    await until(lambda: tool_subscribed(b, "/stringEchoReq") and tool_subscribed(b, "/stringEchoResp"),
                what="record subscribed")
    sent = ["one", "zwei ü", "three"]
    errs = []           # one capture for all: the recorder's last line may land in a pub's share
    for text in sent:
        _, e = await run("topic", ["--bus", path, "pub", "/stringEchoReq", "std_msgs/String", f"{{data: '{text}'}}"],
                         capsys)
        errs.append(e)
    _, err = await asyncio.wait_for(rec, 10)
    assert f"recorded 6 message(s) on 2 topic(s) to {out}" in "".join(errs) + err
    assert out.exists() and not out.with_name("echo.bag.active").exists()

    types, msgs = read_bag(out)
    assert types == {"/stringEchoReq": "std_msgs/msg/String", "/stringEchoResp": "std_msgs/msg/String"}
    assert [d for t, _, d in msgs if t == "/stringEchoReq"] == sent
    assert [d for t, _, d in msgs if t == "/stringEchoResp"] == sent          # the echo node's replies
    stamps = [s for _, s, _ in msgs]
    assert stamps == sorted(stamps) and stamps[-1] - stamps[0] < 30 * 10**9

    info = rosbag_info(out)
    assert info["messages"] == 6 and info["version"] == 2.0
    assert {t["topic"]: (t["type"], t["messages"]) for t in info["topics"]} == {
        "/stringEchoReq": ("std_msgs/String", 3), "/stringEchoResp": ("std_msgs/String", 3)}
    assert info["types"] == [{"type": "std_msgs/String", "md5": "992ce8a1687cec8c8bd883ec73ca41d1"}]


async def test_record_for_a_duration(bus, capsys, tmp_path):  # noqa: F811
    _, path = bus
    out = tmp_path / "quiet.bag"
    t0 = asyncio.get_running_loop().time()
    _, err = await run("topic", ["--bus", path, "record", "-o", str(out), "/stringEchoResp", "--duration", "0.5"],
                       capsys)
    assert asyncio.get_running_loop().time() - t0 >= 0.5
    assert f"recorded 0 message(s) on 0 topic(s) to {out}" in err
    assert read_bag(out) == ({}, [])
    info = rosbag_info(out)     # an empty bag: rosbag shows no message count at all
    assert info["version"] == 2.0 and info.get("messages", 0) == 0 and "topics" not in info


async def start_record(path: str, out, *topics: str, until_line: bytes, extra: tuple = ()):
    """``rce-topic record`` as a process; returns it once its stderr printed ``until_line``."""
    proc = await asyncio.create_subprocess_exec(str(BIN / "rce-topic"), "--bus", path, "record", "-o", str(out),
                                                *topics, *extra, stderr=asyncio.subprocess.PIPE)
    line = b""
    while until_line not in line:
        line = await asyncio.wait_for(proc.stderr.readline(), SIGNAL_WAIT)
        assert line, "rce-topic record exited early"
    return proc


async def test_a_topic_that_appears_later_is_recorded_from_then_on(bus, tmp_path):  # noqa: F811
    _, path = bus
    out = tmp_path / "later.bag"
    rec = await start_record(path, out, "/later", until_line=b"[/later] does not appear to be published yet",
                             extra=("--count", "2"))
    env = dict(os.environ, RCE_BUS=path)
    pub = await asyncio.create_subprocess_exec(str(BIN / "rce-topic"), "pub", "/later", "std_msgs/String",
                                               "{data: late}", "-r", "20", env=env)
    try:
        _, err = await asyncio.wait_for(rec.communicate(), LATER_WAIT)
    finally:
        pub.terminate()
        await pub.wait()
    assert rec.returncode == 0 and b"recording /later [std_msgs/String]" in err
    types, msgs = read_bag(out)
    assert types == {"/later": "std_msgs/msg/String"} and [d for _, _, d in msgs] == ["late", "late"]
    assert rosbag_info(out)["messages"] == 2


async def test_record_stops_on_sigterm_and_keeps_the_bag(bus, tmp_path):  # noqa: F811
    b, path = bus
    out = tmp_path / "term.bag"
    proc = await start_record(path, out, "/stringEchoResp", until_line=b"recording /stringEchoResp")
    await until(lambda: tool_subscribed(b, "/stringEchoResp"), what="record subscribed")
    env = dict(os.environ, RCE_BUS=path)
    p = await asyncio.create_subprocess_exec(str(BIN / "rce-topic"), "pub", "/stringEchoReq", "{data: x}",
                                             "-r", "50", "-n", "5", env=env)
    assert await p.wait() == 0
    await until(lambda: b.topics["/stringEchoResp"].messages >= 5, what="5 echoes")
    proc.send_signal(signal.SIGTERM)
    _, err = await asyncio.wait_for(proc.communicate(), SIGNAL_WAIT)
    assert proc.returncode == 0, err
    assert f"recorded 5 message(s) on 1 topic(s) to {out}".encode() in err
    assert [d for _, _, d in read_bag(out)[1]] == ["x"] * 5


async def test_record_through_the_admin_api(admin, capsys, tmp_path):  # noqa: F811
    url, seen, _ = admin
    out = tmp_path / "admin.bag"
    await run("topic", ["--container", "cTag_01", "--master", url, "--user", "testUser", "--admin-token", "s3cret",
                        "record", "-o", str(out), "/stringEchoResp", "--count", "3"], capsys)
    assert seen[-1] == ("sample", {"topic": "/stringEchoResp", "count": 1, "timeout": 1.0, "type": "std_msgs/String"})
    types, msgs = read_bag(out)
    assert types == {"/stringEchoResp": "std_msgs/msg/String"} and [d for _, _, d in msgs] == ["m0"] * 3
    assert rosbag_info(out)["messages"] == 3


def test_bag_recorder_refuses_what_it_cannot_write(tmp_path):
    with pytest.raises(RequestError, match="cannot write the bag"):
        BagRecorder(tmp_path / "no" / "such" / "dir.bag").open()
    bag = BagRecorder(tmp_path / "two.bag")
    bag.open()
    bag.write("/t", "std_msgs/String", b"\x01\x00\x00\x00a")
    with pytest.raises(MessageError, match="topic /t is recorded as std_msgs/msg/String"):
        bag.write("/t", "std_msgs/Bool", b"\x01")
    with pytest.raises(MessageError, match="unknown message class"):
        bag.write("/u", "nope/Nothing", b"")
    assert bag.close() == tmp_path / "two.bag" and bag.close() == tmp_path / "two.bag"
    bag.write("/t", "std_msgs/String", b"\x01\x00\x00\x00b")        # after close: counted, not written
    assert bag.late == 1 and bag.counts == {"/t": 1}
    assert read_bag(tmp_path / "two.bag")[1][0][2] == "a"
