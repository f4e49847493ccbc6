"""Per-container node uids: every namespaced container's nodes run as a uid of their own.

A uid comes from the range ``[NODE_UID_BASE, NODE_UID_BASE + NODE_UID_COUNT)``, which no
login account uses. It is held, machine-wide, by an exclusive ``flock(2)`` on the file
``UID_LOCK_DIR/<uid>`` for as long as the container lives (the lock goes with the holding
process, so a crashed environment frees its uids). Two container task sets on one machine,
even of two different masters, therefore never give the same uid to two containers, and a
node of one container cannot signal, trace or read the files of another's (DAC, and
``SO_PEERCRED`` on the bus sockets: :class:`rce.bus.server.BusServer`).
"""
from __future__ import annotations

import fcntl
import os
from pathlib import Path

from rce.plumbing.errors import RCEError

NODE_UID_BASE = 1_500_000_000   # first node uid (and gid): far above any account (Debian: < 60000)
NODE_UID_COUNT = 1 << 20        # uids in the range: containers that can live at once on one machine
UID_LOCK_DIR = Path("/run/rce/node-uids")   # root-only directory of the per-uid lock files


class NodeUid:
    """One leased uid: ``uid`` (also the gid) until :meth:`release`."""

    def __init__(self, uid: int, fd: int):
        self.uid, self._fd = uid, fd

    def release(self) -> None:
        """Give the uid back (idempotent)."""
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


def lease(cid: int, lock_dir: Path = UID_LOCK_DIR) -> NodeUid:
    """A free node uid for container ``cid``: ``NODE_UID_BASE + cid`` when free (so it is
    usually predictable), else the next free one. Needs root. Raises :class:`RCEError` when
    the lock directory cannot be made or every uid of the range is held."""
    try:
        lock_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
        os.chmod(lock_dir, 0o700)
    except OSError as e:
        raise RCEError(f"cannot make the node uid lock directory {lock_dir}: {e.strerror or e}") from None
    start = cid % NODE_UID_COUNT
    for i in range(NODE_UID_COUNT):
        uid = NODE_UID_BASE + (start + i) % NODE_UID_COUNT
        fd = os.open(lock_dir / str(uid), os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            continue
        return NodeUid(uid, fd)
    raise RCEError(f"every node uid from {NODE_UID_BASE} to {NODE_UID_BASE + NODE_UID_COUNT - 1} is in use")
