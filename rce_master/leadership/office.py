"""Whether this master leads (docs/INTERNALS.md, "Several masters"). A master alone (its state in
memory or a SQLite file) always leads; masters on etcd elect one (:class:`rce_master.leadership.elected.ElectedOffice`),
and the others stand by: they serve login and admin reads and refuse the rest with
:class:`~rce.plumbing.errors.NotLeader`, which names the leader (over HTTP: 503 with the leader's URL in
the header :data:`rce.tools.admin_client.LEADER_HEADER`).
"""
from __future__ import annotations

from typing import Protocol

from rce.plumbing.errors import NotLeader

RETRY_AFTER_NO_LEADER = 2      # s, Retry-After of a standby's refusal while no leader is elected (about a lease TTL)


class Office(Protocol):
    """``leading``: this master leads; ``leader``: the leader's ``{"control": "HOST:PORT", "http":
    "http://HOST:PORT/", ...}`` (None: none known); ``me``: this master's, when it runs on etcd."""
    leading: bool
    leader: dict | None
    me: dict


class Alone:
    """The office of a master with no other: it always leads."""
    leading = True
    leader: dict | None = None
    me: dict = {}


def require_leader(office: Office, what: str) -> None:
    """Raise :class:`NotLeader` naming ``what`` was asked and where the leader is, unless this master leads."""
    if office.leading:
        return
    leader = office.leader
    if leader and leader.get("control"):
        raise NotLeader(f"{what}: this master stands by; the leader is at control {leader['control']}, "
                        f"http {leader.get('http', '?')}",
                        leader={"control": leader["control"], "http": leader.get("http")})
    raise NotLeader(f"{what}: this master stands by and no leader is elected now; try again in "
                    f"{RETRY_AFTER_NO_LEADER} s")
