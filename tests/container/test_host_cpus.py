"""A container host's capacity under a CPU quota (rce_container.cgroups.host_cpus): a process in a
cgroup this test makes (root), capped at 0.3 cores through whichever CPU controller this machine
mounts (v1 ``cpu.cfs_quota_us``, else v2 ``cpu.max``), registers 0.3 cores."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from rce_container.cgroups import cfs_quota_cores, cpu_max_cores

CAP = "rce-test-host-cpus"


def capped_dir() -> tuple[Path, str, str]:
    """(the cgroup to make, its quota file, the quota's text) on this machine's CPU controller."""
    v1 = Path("/sys/fs/cgroup/cpu")
    if (v1 / "cpu.cfs_quota_us").exists():
        return v1 / f"{CAP}-{os.getpid()}", "cpu.cfs_quota_us", "30000"
    return Path("/sys/fs/cgroup") / f"{CAP}-{os.getpid()}", "cpu.max", "30000 100000"


def test_a_host_in_a_capped_cgroup_registers_the_cap():
    d, quota_file, quota = capped_dir()
    d.mkdir()
    try:
        (d / quota_file).write_text(quota)
        code = "from rce_container.cgroups import host_cpus; print(host_cpus())"
        out = subprocess.run(["sh", "-c", f'echo $$ > {d}/cgroup.procs && exec "$0" -c "$1"', sys.executable, code],
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        assert float(out.stdout) == 0.3
    finally:
        d.rmdir()


def test_quota_texts():
    assert cfs_quota_cores("-1", "100000") is None and cfs_quota_cores("50000", "100000") == 0.5
    assert cfs_quota_cores("x", "100000") is None
    assert cpu_max_cores("max 100000") is None and cpu_max_cores("150000 100000") == 1.5
