"""What the robot endpoint's and rosbridge's websocket handshakes share about the front door
(docs/SECURITY.md): the address a login comes from, the answers to a throttled login and to
one that cannot be checked while the master is away, and how a refused login reaches a client of
2013, which never surfaces an HTTP status."""
from __future__ import annotations

import math
from http import HTTPStatus

from rce.plumbing.errors import Throttled

MASTER_AWAY_RETRY_AFTER = 5   # s, Retry-After of the 503 a connecting robot gets while the master is away (as the
                              # master's own 503 while task sets are absent)


# the query keys of the 2013 client's websocket URL (RCE alpha, autobahn_rce 0.6): a handshake with
# only these is that client's, which shows an ER frame but never an HTTP status (its connect waits
# 20 s for a timeout). Any other key (resume, maxLag, refusal, ...) is a newer client's.
QUERY_2013 = frozenset({"userID", "robotID", "password"})
REFUSAL_KEY = "refusal"      # refusal=http: a client that reads HTTP statuses, whatever else it sends


def refuse_in_band(query: dict) -> bool:
    """A refused login of this handshake's client is answered in band: the upgrade is accepted,
    one ER frame names the failure, and the websocket closes (1008). True for a client of 2013
    (only :data:`QUERY_2013` keys), unless it asks ``refusal=http``; newer clients get HTTP statuses."""
    return set(query) <= QUERY_2013 and query.get(REFUSAL_KEY) != "http"


def peer_address(connection) -> str:
    """The IP address a websocket ``connection`` (websockets' ``ServerConnection``) comes from: what
    the master's login throttling counts by (:mod:`rce_master.auth.login_guard`)."""
    addr = connection.remote_address
    return str(addr[0]) if addr else ""


def throttled(connection, refusal: Throttled):
    """The handshake's answer to a login the master throttles: HTTP 429 (RFC 6585) with
    ``Retry-After`` (s) and the master's one-line reason."""
    resp = connection.respond(HTTPStatus.TOO_MANY_REQUESTS, refusal.message + "\n")
    resp.headers["Retry-After"] = str(math.ceil(refusal.retry_after))
    return resp


def master_away(connection, master):
    """While the master (``master``: the task set's :class:`~rce.transport.masterlink.MasterLink`) is away a
    login cannot be checked: HTTP 503 with ``Retry-After``; None while it is there."""
    if master is not None and master.available:
        return None
    resp = connection.respond(HTTPStatus.SERVICE_UNAVAILABLE, "the master is unavailable; try again later\n")
    resp.headers["Retry-After"] = str(MASTER_AWAY_RETRY_AFTER)
    return resp


MAX_RELAY_NAME = 64     # characters of a relay's name kept from a handshake's query


def relay_name(query: dict) -> str:
    """The relay a follower's link goes through (``relay=NAME`` in its login or resume query; "" for its
    own path, docs/relays.md): at most :data:`MAX_RELAY_NAME` printable characters, told to the master
    as the follower said it (it is what the follower saw, not a credential)."""
    return "".join(c for c in str(query.get("relay", "")) if c.isprintable())[:MAX_RELAY_NAME]
