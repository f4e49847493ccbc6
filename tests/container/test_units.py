"""Sans-I/O pieces of the container task set: argument building, respawn specs, interface
types and classes, sandbox selection, socket paths."""
from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from rce.plumbing.errors import ConfigError, MessageError, NotFound, ProtocolError, RequestError
from rce.node.package_path import BUILTIN_DIR
from rce_container import cgroups, sandbox
from rce_container.host import MAX_SOCKET_PATH, socket_dir_for
from rce_container.interfaces import check_class, interface_kind
from rce_container.launcher import build_args, expand_directives, parse_respawn
from rce_container.usage import CpuRate


def test_build_args_splits_like_a_shell_and_expands_directives():
    env = {"HOME_DIR": "/home/with space", "N": "3"}
    assert build_args("a 'b c' $(env N)", env) == ["a", "b c", "3"]
    # an expanded value with spaces stays one word
    assert build_args("--home=$(env HOME_DIR) x", env) == ["--home=/home/with space", "x"]
    assert build_args("$(find Test)/srv", env) == [f"{BUILTIN_DIR / 'Test'}/srv"]
    assert build_args("$(optenv MISSING) $(optenv MISSING fallback value)", env) == ["fallback value"]
    assert build_args(["$(env N)", "raw 'quotes'"], env) == ["3", "raw 'quotes'"]
    assert build_args("", env) == [] and build_args(None, env) == []
    with pytest.raises(RequestError, match="NOT_SET"):
        build_args("$(env NOT_SET)", env)
    with pytest.raises(NotFound, match="NoPkg"):
        expand_directives("$(find NoPkg)", env)
    with pytest.raises(RequestError, match="arg"):
        build_args("$(arg x)", env)
    with pytest.raises(RequestError, match="quotation"):
        build_args("'unbalanced", env)
    with pytest.raises(RequestError):
        build_args({"not": "args"}, env)


def test_parse_respawn():
    assert parse_respawn(None) == (False, 0.0, None)
    assert parse_respawn(False) == (False, 0.0, None)
    assert parse_respawn(True)[0] is True and parse_respawn(True)[2] is None
    assert parse_respawn({"delay": 0.5, "limit": 3}) == (True, 0.5, 3)
    for bad in ({"delay": -1}, {"limit": -2}, {"limit": 1.5}, {"delay": "1"}, {"retries": 3}, "yes", 3):
        with pytest.raises(RequestError, match="respawn"):
            parse_respawn(bad)


def test_interface_types_and_classes():
    assert interface_kind("PublisherInterface") == "Publisher"
    assert interface_kind("ServiceInterface") == "ServiceClient"     # RCE alpha name
    assert interface_kind("ServiceProviderInterface") == "ServiceProvider"
    with pytest.raises(RequestError, match="robot-side"):
        interface_kind("SubscriberForwarder")
    with pytest.raises(ProtocolError, match="Bogus"):
        interface_kind("BogusInterface")
    assert check_class("Publisher", "std_msgs/String") == "std_msgs/String"
    assert check_class("Subscriber", "std_msgs/msg/String") == "std_msgs/msg/String"     # a ROS 2 class stays one
    assert check_class("ServiceClient", "std_srvs/srv/Trigger") == "std_srvs/srv/Trigger"
    assert check_class("ServiceClient", "Test/StringEcho") == "Test/StringEcho"
    with pytest.raises(MessageError, match="Test/StringEcho"):
        check_class("Publisher", "Test/StringEcho")          # a service is not a message class
    with pytest.raises(MessageError, match="geometry_msgs/Nope"):
        check_class("Subscriber", "geometry_msgs/Nope")


def test_sandbox_selection():
    if os.geteuid() == 0:       # CI runs as root: the namespaced sandbox must work there, not be skipped
        assert sandbox.NamespaceSandbox.available(), "running as root, but unshare/nsenter/setsid/setpriv fail"
        strongest = sandbox.NamespaceSandbox
    else:
        assert not sandbox.NamespaceSandbox.available()
        with pytest.raises(ConfigError, match="needs root"):
            sandbox.select("namespaced")
        strongest = sandbox.ProcessGroupSandbox
    assert sandbox.select("auto") is strongest
    assert sandbox.select("unconfined") is sandbox.ProcessGroupSandbox
    with pytest.raises(ConfigError, match="jail"):
        sandbox.select("jail")

    class Unavailable(sandbox.Sandbox):         # a stronger sandbox this host cannot run
        kind, priority = "test-unavailable", 100

        @classmethod
        def available(cls) -> bool:
            return False
    try:
        assert sandbox.select("auto") is strongest
        with pytest.raises(ConfigError, match="not available"):
            sandbox.select("test-unavailable")
    finally:
        del sandbox.REGISTRY["test-unavailable"]


def test_socket_dir_falls_back_to_a_short_path():
    short = Path("/tmp/rt")
    assert socket_dir_for(short) == short
    deep = Path("/tmp/" + "d" * 120)
    alt = socket_dir_for(deep)
    assert alt != deep and alt == socket_dir_for(deep)                # deterministic
    assert len(str(alt / "c0000000000" / "bus.sock")) <= MAX_SOCKET_PATH


MOUNTINFO_V1 = """\
23 1 0:21 / /sys rw,nosuid,nodev,noexec,relatime shared:7 - sysfs sysfs rw
31 23 0:28 / /sys/fs/cgroup rw,relatime - tmpfs tmpfs rw,mode=755
32 31 0:29 / /sys/fs/cgroup/cpu rw,relatime - cgroup cgroup rw,cpu
33 31 0:30 / /sys/fs/cgroup/cpuacct rw,relatime - cgroup cgroup rw,cpuacct
35 31 0:32 / /sys/fs/cgroup/memory rw,relatime - cgroup cgroup rw,memory
39 31 0:36 / /sys/fs/cgroup/pids rw,relatime - cgroup cgroup rw,pids
40 31 0:37 / /sys/fs/cgroup/systemd rw,relatime - cgroup cgroup rw,name=systemd
41 31 0:38 / /sys/fs/cgroup/unified rw,relatime - cgroup2 cgroup2 rw
"""
PROC_CGROUP_V1 = "9:name=systemd:/\n8:pids:/\n4:memory:/outer/job7\n2:cpuacct:/\n1:cpu:/\n0::/\n"
MOUNTINFO_V2 = "30 23 0:26 / /sys/fs/cgroup rw,nosuid,nodev,noexec,relatime - cgroup2 cgroup2 rw,nsdelegate\n"


def test_cgroup_layout_detection():
    v1 = cgroups.detect("rce/h-1", MOUNTINFO_V1, PROC_CGROUP_V1, "")
    assert v1.version == 1
    # nested under the task set's own cgroup in each hierarchy
    assert v1.bases == {"cpu": "/sys/fs/cgroup/cpu/rce/h-1", "cpuacct": "/sys/fs/cgroup/cpuacct/rce/h-1",
                        "memory": "/sys/fs/cgroup/memory/outer/job7/rce/h-1", "pids": "/sys/fs/cgroup/pids/rce/h-1"}
    co = cgroups.detect("s", "32 31 0:29 / /c rw - cgroup cgroup rw,cpu,cpuacct\n"
                             "35 31 0:32 / /m rw - cgroup cgroup rw,memory\n",
                        "3:cpu,cpuacct:/\n2:memory:/\n", None)
    assert co.bases == {"cpu": "/c/s", "cpuacct": "/c/s", "memory": "/m/s"}          # co-mounted cpu,cpuacct
    v2 = cgroups.detect("rce/h-1", MOUNTINFO_V2, "0::/user.slice/x.scope\n", "cpuset cpu io memory pids")
    assert v2.version == 2 and v2.bases == {"": "/sys/fs/cgroup/rce/h-1"} and v2.v2_root == "/sys/fs/cgroup"
    # a v2 hierarchy without the controllers (like this machine's /sys/fs/cgroup/unified) is unusable
    assert cgroups.detect("s", MOUNTINFO_V2, "0::/\n", "") is None
    assert cgroups.detect("s", "", "", None) is None


def _fake_v1(root: Path) -> cgroups.Layout:
    bases = {c: str(root / c / "rce" / "h") for c in ("cpu", "cpuacct", "memory", "pids")}
    return cgroups.Layout(1, bases)


def test_cgroup_limits_v1_and_v2_files(tmp_path):
    cg = cgroups.CgroupSet(_fake_v1(tmp_path), "c5")
    cg.create()
    for f in ("memory.limit_in_bytes", "memory.memsw.limit_in_bytes"):     # as the kernel says "unlimited"
        (cg.dirs["memory"] / f).write_text("9223372036854771712")
    assert cg.apply({"cpu": 0.5, "memory": 64, "pids": 32, "size": 1, "bandwidth": 10}) == \
        {"cpu": 0.5, "memory": 64.0, "pids": 32}
    assert cg.files() == {"cpu.cfs_quota_us": "50000", "cpu.cfs_period_us": "100000", "cpu.shares": "1024",
                          "memory.limit_in_bytes": str(64 << 20), "memory.memsw.limit_in_bytes": str(64 << 20),
                          "pids.max": "32"}      # half a core weighs what one process does: no less
    assert cg.procs_files[2] == str(tmp_path / "memory/rce/h/c5/cgroup.procs")
    cg.apply({"cpu": 1.5})                      # only what is given changes
    assert cg.files()["cpu.cfs_quota_us"] == "150000" and cg.files()["pids.max"] == "32"
    assert cg.files()["cpu.shares"] == "1536"   # 1.5 cores weigh 1.5 processes
    cg.apply({"size": 4})                       # the original RCE's size class: no limit, nothing written
    assert cg.files()["pids.max"] == "32"
    cg.apply({"cpu": 0, "memory": 0, "pids": 0})  # 0 = no limit
    assert cg.files()["cpu.cfs_quota_us"] == "-1" and cg.files()["memory.limit_in_bytes"] == "-1"
    assert cg.files()["cpu.shares"] == "1024"
    assert cg.files()["pids.max"] == "max"
    with pytest.raises(RequestError, match="memory"):
        cg.apply({"memory": -1})
    with pytest.raises(RequestError, match="limit 'pids' must be at least 1 task"):
        cg.apply({"pids": 0.5})
    # CPU weights above the containers: each container weighs one process or its cores, the parents their sum
    cgroups.CgroupSet(_fake_v1(tmp_path), "c6").create()
    assert (tmp_path / "cpu/rce/h/cpu.shares").read_text() == "2048"
    assert (tmp_path / "cpu/rce/cpu.shares").read_text() == "2048"
    cg.apply({"cpu": 3})
    assert cg.files()["cpu.shares"] == "3072"
    assert (tmp_path / "cpu/rce/h/cpu.shares").read_text() == "4096"      # 3 cores + one process
    assert (tmp_path / "cpu/rce/cpu.shares").read_text() == "4096"

    root = tmp_path / "v2"
    root.mkdir()
    (root / "cgroup.controllers").write_text("cpu memory pids\n")
    (root / "cgroup.subtree_control").write_text("")
    v2 = cgroups.CgroupSet(cgroups.Layout(2, {"": str(root / "rce" / "h")}, v2_root=str(root)), "c1")
    v2.create()
    assert (root / "cgroup.subtree_control").read_text() == "+cpu +memory +pids"
    (v2.dirs[""] / "memory.swap.max").write_text("max")
    v2.apply({"cpu": 2, "memory": 128, "pids": 10, "size": 1})
    assert v2.files() == {"cpu.max": "200000 100000", "cpu.weight": "200", "memory.max": str(128 << 20),
                          "memory.swap.max": "0", "pids.max": "10"}
    assert (root / "rce/h/cpu.weight").read_text() == "200"
    assert v2.procs_files == [str(root / "rce/h/c1/cgroup.procs")]


def test_cpu_rate():
    r = CpuRate()
    first = r.percent("k", 1.0, time.monotonic() - 2.0)
    assert 45 < first < 55                       # first reading: 1 s of CPU over 2 s since the start
    assert r.percent("k", 5.0) == first          # within MIN_INTERVAL: the same value again, not noise
    assert r.percent("other", 3.0) == 0.0        # no start known: nothing to say yet
