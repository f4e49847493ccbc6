"""Join a container's sandbox from a running process, in-process: what ``sh`` (the cgroup),
``nsenter``, ``setsid`` and ``setpriv`` do for an exec'd node (:class:`rce_container.sandbox.
NamespaceSandbox`), for the container's zygote forked from the environment's warm template
(:mod:`rce_container.zygote`). Stdlib only.

``spec`` (:meth:`rce_container.sandbox.Sandbox.enter_spec`): ``{"cwd": workdir, "init_pid":
host pid of the container's init or absent, "uid": node uid or absent, "procs_files": [the
container's ``cgroup.procs`` files]}``. Without ``init_pid`` (the unconfined sandbox) only
``setsid`` and ``chdir`` apply.

:func:`join` (before a fork: the PID namespace applies to children) writes the caller into the
cgroup and ``setns(2)`` s into the init's IPC, UTS, network, PID and mount namespaces (mount
last: it resets root and cwd). :func:`drop` (in the forked child) makes it a session leader
in the workdir and drops to the node uid exactly as ``setpriv --reuid=U --regid=U
--clear-groups --inh-caps=-all --ambient-caps=-all --bounding-set=-all --no-new-privs`` does,
then checks the result in ``/proc/self/status`` and raises if any capability, group or uid is
left (fail closed).
"""
from __future__ import annotations

import ctypes
import os

NAMESPACES = ("ipc", "uts", "net", "pid", "mnt")    # nsenter's order: mnt last (it changes root and cwd)
PR_CAPBSET_DROP, PR_SET_NO_NEW_PRIVS, PR_CAP_AMBIENT, PR_CAP_AMBIENT_CLEAR_ALL = 24, 38, 47, 4
LINUX_CAPABILITY_VERSION_3 = 0x20080522             # capget(2)/capset(2): two 32-bit words per set

_libc = ctypes.CDLL(None, use_errno=True)


class _CapHeader(ctypes.Structure):
    _fields_ = [("version", ctypes.c_uint32), ("pid", ctypes.c_int)]


class _CapData(ctypes.Structure):
    _fields_ = [("effective", ctypes.c_uint32), ("permitted", ctypes.c_uint32), ("inheritable", ctypes.c_uint32)]


def _check(rc: int, what: str) -> None:
    if rc != 0:
        e = ctypes.get_errno()
        raise OSError(e, f"{what}: {os.strerror(e)}")


def join(spec: dict) -> None:
    """Enter the container's cgroup and namespaces (this process; its children are in the PID
    namespace). Raises :class:`OSError` naming the step that failed."""
    for path in spec.get("procs_files", ()):
        with open(path, "w") as f:
            f.write(str(os.getpid()))
    init = spec.get("init_pid")
    if init is None:
        return
    fds = [os.open(f"/proc/{init}/ns/{n}", os.O_RDONLY | os.O_CLOEXEC) for n in NAMESPACES]
    try:
        for n, fd in zip(NAMESPACES, fds, strict=True):
            _check(_libc.setns(fd, 0), f"setns {n} of pid {init}")
    finally:
        for fd in fds:
            os.close(fd)


def _clear_inheritable() -> None:
    head, data = _CapHeader(LINUX_CAPABILITY_VERSION_3, 0), (_CapData * 2)()
    _check(_libc.capget(ctypes.byref(head), data), "capget")
    for d in data:
        d.inheritable = 0
    _check(_libc.capset(ctypes.byref(head), data), "capset")


def drop(spec: dict) -> None:
    """Session leader in ``cwd``; with ``uid``: that uid and gid, no groups, no capability in
    any set, ``no_new_privs``. Raises :class:`OSError` if a step fails or anything is left."""
    os.setsid()
    os.chdir(spec["cwd"])
    uid = spec.get("uid")
    if uid is None:
        return
    os.setgroups([])
    _clear_inheritable()
    _check(_libc.prctl(PR_CAP_AMBIENT, PR_CAP_AMBIENT_CLEAR_ALL, 0, 0, 0), "clear the ambient capabilities")
    with open("/proc/sys/kernel/cap_last_cap") as f:
        last = int(f.read())
    for cap in range(last + 1):
        _check(_libc.prctl(PR_CAPBSET_DROP, cap, 0, 0, 0), f"drop capability {cap} from the bounding set")
    os.setresgid(uid, uid, uid)
    os.setresuid(uid, uid, uid)          # from root to another uid: the permitted and effective sets go
    _check(_libc.prctl(PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0), "set no_new_privs")
    verify(uid)


def verify(uid: int) -> None:
    """Raise :class:`OSError` unless this process runs as ``uid`` (real, effective, saved, fs;
    gid too), with no supplementary group, every capability set empty and ``no_new_privs``."""
    with open("/proc/self/status") as f:
        status = dict(line.rstrip("\n").split(":\t", 1) for line in f if ":\t" in line)
    want = {**{k: "0000000000000000" for k in ("CapInh", "CapPrm", "CapEff", "CapBnd", "CapAmb")},
            "NoNewPrivs": "1", "Groups": "", "Uid": "\t".join([str(uid)] * 4), "Gid": "\t".join([str(uid)] * 4)}
    wrong = {k: status.get(k, "").strip() for k, v in want.items() if status.get(k, "").strip() != v}
    if wrong:
        raise OSError(f"privileges not dropped: {wrong}")
