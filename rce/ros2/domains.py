"""ROS 2 domain ids this machine leases to graphs that must stay apart: a container's graph in a
sandbox without a network namespace of its own, a test's, a simulated robot's. A lease is an
exclusive ``flock(2)`` on ``<dir>/<id>`` (no daemon; a crashed holder frees its id)."""
from __future__ import annotations

import fcntl
import os
from pathlib import Path

from rce.plumbing.errors import RCEError

#: The ids leased (0 is every ROS 2 install's default; ids above 101 collide with ephemeral ports on Linux,
#: https://docs.ros.org/en/jazzy/Concepts/Intermediate/About-Domain-ID.html).
DOMAIN_IDS = range(1, 102)
#: Where the lock files are: the first of these that can be made.
DOMAIN_LOCK_DIRS = (Path("/run/rce/ros2-domains"), Path(f"/tmp/rce-ros2-domains-{os.getuid()}"))


class DomainLease:
    """One leased ROS 2 domain id (``domain``) until :meth:`release`."""

    def __init__(self, domain: int, fd: int = -1):
        self.domain, self._fd = domain, fd

    def release(self) -> None:
        """Give the domain id back (idempotent)."""
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1


def lease_domain(lock_dir: Path | None = None) -> DomainLease:
    """A ROS 2 domain id of :data:`DOMAIN_IDS` no other graph on this machine holds (a container's in an
    unconfined sandbox, a test's, a simulated robot's), and not
    the host's own ``ROS_DOMAIN_ID``: held by an exclusive ``flock(2)`` on ``lock_dir/<id>``
    (default: the first of :data:`DOMAIN_LOCK_DIRS` that can be made) while the lease lives (a
    crashed environment frees it). Raises :class:`RCEError` when every id is held."""
    dirs = [lock_dir] if lock_dir else list(DOMAIN_LOCK_DIRS)
    for d in dirs:
        try:
            d.mkdir(parents=True, exist_ok=True, mode=0o700)
            break
        except OSError:
            continue
    else:
        raise RCEError(f"cannot make a ROS 2 domain lock directory ({', '.join(map(str, dirs))})")
    host = os.environ.get("ROS_DOMAIN_ID", "0")
    for domain in DOMAIN_IDS:
        if str(domain) == host:
            continue
        fd = os.open(d / str(domain), os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            continue
        return DomainLease(domain, fd)
    raise RCEError(f"every ROS 2 domain id of {DOMAIN_IDS.start} - {DOMAIN_IDS.stop - 1} is held by a graph "
                   f"of this machine")
