"""The init (PID 1) of a namespaced container; stdlib only, run as
``unshare --pid --fork --mount --ipc --uts --net --mount-proc --kill-child python -I -S nsinit.py SPEC``.

``SPEC`` is JSON: ``{"hostname": str, "masks": [[dir, [keep, ...], tmpfs_opts], ...],
"writable": [path, ...]}`` (:func:`rce_container.mounts.plan`). In its new mount namespace
(private propagation, /proc already remounted by unshare) it

1. hides each mask ``dir`` (that exists) under an empty tmpfs mounted with ``tmpfs_opts``,
   except the ``keep`` directories below it, which are bind-mounted back (the container's own
   workdir and bus socket directory stay reachable, and what nodes need to start; other
   containers' sockets, the host's control socket, its /tmp and /root do not);
2. remounts every mount read-only except the ``writable`` ones (the container's own
   directory and its private scratch tmpfs); ``/proc/sys`` is bound onto itself first, so
   it is read-only too: a node cannot leave its cgroup, raise its limits, change kernel
   settings, or write the host's files;
3. brings ``lo`` up in the new (otherwise empty) network namespace and sets the hostname;

then prints ``ready`` on stdout and reaps orphans until stdin closes (its environment went
away) or SIGTERM. When it exits the kernel kills every process left in the PID namespace.
On a setup error it prints ``error: REASON`` and exits 1.
"""
import ctypes
import fcntl
import json
import os
import select
import signal
import socket
import struct
import sys

MS_RDONLY, MS_NOSUID, MS_NODEV, MS_NOEXEC = 1, 2, 4, 8
MS_REMOUNT, MS_NOATIME, MS_NODIRATIME, MS_BIND = 32, 1024, 2048, 4096
MS_RELATIME, MS_STRICTATIME = 1 << 21, 1 << 24
FLAG_OPTS = {"nosuid": MS_NOSUID, "nodev": MS_NODEV, "noexec": MS_NOEXEC, "noatime": MS_NOATIME,
             "nodiratime": MS_NODIRATIME, "relatime": MS_RELATIME, "strictatime": MS_STRICTATIME}
SIOCGIFFLAGS, SIOCSIFFLAGS, IFF_UP = 0x8913, 0x8914, 0x1

_libc = ctypes.CDLL(None, use_errno=True)
_libc.mount.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_char_p, ctypes.c_ulong, ctypes.c_char_p]


def _enc(text):
    return text.encode() if text is not None else None


def mount(src, target, fstype, flags, data=None):
    if _libc.mount(_enc(src), _enc(target), _enc(fstype), flags, _enc(data)) != 0:
        e = ctypes.get_errno()
        raise OSError(e, f"mount {target}: {os.strerror(e)}")


def mask(directory, keep, opts="mode=0755,size=64k"):
    """Empty tmpfs (``opts``) over ``directory``, if it exists; each ``keep`` (below it)
    bind-mounted back."""
    if not os.path.isdir(directory):
        return
    fds = {k: os.open(k, os.O_PATH | os.O_DIRECTORY) for k in keep}
    mount("tmpfs", directory, "tmpfs", MS_NOSUID | MS_NODEV, opts)
    for k, fd in fds.items():
        target = os.path.join(directory, os.path.relpath(k, directory))
        os.makedirs(target, exist_ok=True)
        mount(f"/proc/self/fd/{fd}", target, None, MS_BIND)
        os.close(fd)


def readonly(keep_writable):
    """Remount every mount read-only (this namespace only) except those at ``keep_writable``.
    A mount hidden under a mask (its path now names something else, or nothing) may fail:
    it cannot be reached anyway."""
    with open("/proc/self/mountinfo") as f:
        lines = f.read().splitlines()
    for line in lines:
        fields = line.split()
        point = fields[4].replace("\\040", " ")
        if point in keep_writable:
            continue
        flags = MS_REMOUNT | MS_BIND | MS_RDONLY
        for opt in fields[5].split(","):
            flags |= FLAG_OPTS.get(opt, 0)
        try:
            mount(None, point, None, flags)
        except OSError:
            pass


def check_readonly(paths):
    """Raise OSError if one of ``paths`` is still writable (the read-only view failed)."""
    for p in paths:
        if os.statvfs(p).f_flag & os.ST_RDONLY == 0:
            raise OSError(f"{p} is still writable after remounting it read-only")


def lo_up():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        req = struct.pack("16sH22x", b"lo", 0)
        flags = struct.unpack("16sH22x", fcntl.ioctl(s, SIOCGIFFLAGS, req))[1]
        fcntl.ioctl(s, SIOCSIFFLAGS, struct.pack("16sH22x", b"lo", flags | IFF_UP))
    finally:
        s.close()


def setup(spec):
    for directory, keep, *opts in spec.get("masks", []):
        mask(directory, keep, *opts)
    mount("/proc/sys", "/proc/sys", None, MS_BIND)
    readonly(set(spec.get("writable", [])))
    check_readonly(["/", "/sys", "/proc/sys"])
    lo_up()
    if spec.get("hostname"):
        socket.sethostname(spec["hostname"])


def reap_forever():
    r, w = os.pipe()
    os.set_blocking(w, False)
    signal.set_wakeup_fd(w)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    signal.signal(signal.SIGTERM, lambda *_: os._exit(0))
    while True:
        try:
            ready = select.select([0, r], [], [])[0]
        except InterruptedError:
            ready = []
        if 0 in ready and not os.read(0, 4096):
            os._exit(0)                          # the environment is gone
        if r in ready:
            os.read(r, 4096)
        try:
            while os.waitpid(-1, os.WNOHANG)[0] > 0:
                pass
        except ChildProcessError:
            pass


def main():
    try:
        setup(json.loads(sys.argv[1]))
    except (OSError, ValueError, IndexError) as e:
        print(f"error: {e}", flush=True)
        sys.exit(1)
    print("ready", flush=True)
    os.dup2(os.open(os.devnull, os.O_WRONLY), 1)
    reap_forever()


if __name__ == "__main__":
    main()
