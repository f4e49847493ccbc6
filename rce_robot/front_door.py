"""What the robot endpoint's and rosbridge's websocket handshakes share about the front door
(docs/SECURITY.md): the address a login comes from, and the answer to a throttled one."""
from __future__ import annotations

import math
from http import HTTPStatus

from rce.errors import Throttled


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
