"""What the robot endpoint's and rosbridge's websocket handshakes share about the front door
(docs/SECURITY.md): the address a login comes from, and the answers to a throttled login and to
one that cannot be checked while the master is away."""
from __future__ import annotations

import math
from http import HTTPStatus

from rce.errors import Throttled

MASTER_AWAY_RETRY_AFTER = 5   # s, Retry-After of the 503 a connecting robot gets while the master is away (as the
                              # master's own 503 while task sets are absent)


def peer_address(connection) -> str:
    """The IP address a websocket ``connection`` (websockets' ``ServerConnection``) comes from: what
    the master's login throttling counts by (:mod:`rce_master.login_guard`)."""
    addr = connection.remote_address
    return str(addr[0]) if addr else ""


def throttled(connection, e: Throttled):
    """The handshake's answer to a login the master throttles: HTTP 429 (RFC 6585) with
    ``Retry-After`` (s) and the master's one-line reason."""
    resp = connection.respond(HTTPStatus.TOO_MANY_REQUESTS, e.message + "\n")
    resp.headers["Retry-After"] = str(math.ceil(e.retry_after))
    return resp


def master_away(connection, master):
    """While the master (``master``: the task set's :class:`~rce.masterlink.MasterLink`) is away a
    login cannot be checked: HTTP 503 with ``Retry-After``; None while it is there."""
    if master is not None and master.available:
        return None
    resp = connection.respond(HTTPStatus.SERVICE_UNAVAILABLE, "the master is unavailable; try again later\n")
    resp.headers["Retry-After"] = str(MASTER_AWAY_RETRY_AFTER)
    return resp
