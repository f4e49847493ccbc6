"""Dialling the cloud: the login at the master, the websocket handshake with a robot endpoint, and
the one mapping of a refused handshake to an error (401/403: :class:`~rce.plumbing.errors.AuthError`, any other
status: :class:`~rce.plumbing.errors.Unavailable`), for the first dial and for a move to another endpoint alike
(:mod:`rce_client.connection`, :mod:`rce_client.reconnect`).

Login is ``GET master_url?userID=U&version=V`` (JSON ``{"url": ws_url, "current"?}``), then a websocket
to ``ws_url?userID=U&robotID=R&password=P`` with ``P`` the hex SHA-256 of the password.
"""
from __future__ import annotations

import asyncio
import hashlib
import json
import os
import ssl
from typing import TYPE_CHECKING, Any
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

import aiohttp
from websockets.asyncio.client import ClientConnection, connect as ws_connect
from websockets.exceptions import InvalidHandshake, InvalidStatus, InvalidURI

from rce.transport import tls
from rce.transport.lane_socket import mptcp_connect
from rce.plumbing.errors import AuthError, Unavailable, http_reason
from rce.plumbing.log import get_logger
from rce_client.tunnel import Unreachable, url_addr

if TYPE_CHECKING:
    from rce_client.routes import Routes

log = get_logger("rce.client")

CLIENT_VERSION = "20130902"      # the RCE alpha client protocol version
CONNECT_TIMEOUT = 10.0           # s for each of the login and the websocket handshake
MAX_FRAME = 256 * 1024 * 1024    # bytes, largest websocket frame accepted


def hash_password(password: str) -> str:
    """The wire form of a password: hex SHA-256 of its UTF-8 bytes (64 chars)."""
    return hashlib.sha256(password.encode()).hexdigest()


def with_query(url: str, **params: str) -> str:
    """``url`` with ``params`` added to (or replacing those in) its query."""
    parts = urlsplit(url)
    query = dict(parse_qsl(parts.query))
    query.update(params)
    return urlunsplit((parts.scheme, parts.netloc, parts.path or "/", urlencode(query), parts.fragment))


def _socket_failure(error: BaseException) -> str:
    """The reason of a failed connection, without aiohttp's dump of its SSL context: the
    socket's error ("Connection refused", "Name or service not known"), else the error itself."""
    cause = getattr(error, "os_error", None) or error
    if isinstance(cause, ConnectionError) and cause.errno:
        return os.strerror(cause.errno)
    return getattr(cause, "strerror", None) or str(cause) or type(cause).__name__


async def login(master_url: str, user_id: str, version: str = CLIENT_VERSION,
                timeout: float = CONNECT_TIMEOUT, ssl_context: ssl.SSLContext | None = None,
                routes: Routes | None = None, robot_id: str | None = None) -> str:
    """Ask the master for this user's robot endpoint; returns its websocket URL.

    ``GET master_url?userID=U&version=V`` -> ``{"url": ws_url, "current"?: V'}`` (``current``
    only when this client is outdated: logged as a warning). An ``https://`` master is verified
    with ``ssl_context`` (default :func:`rce.transport.tls.client_context`: ``$RCE_CA_FILE``, else the
    system's CAs). Raises :class:`AuthError` (HTTP 401/403) or :class:`Unavailable` (any other
    HTTP error, an unreachable or untrusted master, a malformed answer) with the master's
    one-line reason. ``routes``: a follower's paths (direct, else a relay; :mod:`rce_client.routes`).
    ``robot_id``: the robot logging in (``&robotID=R``, which a 2013 master ignores), so that a master
    hands it the endpoint on its own computer where one runs (``rce-robot --zone robot:R``)."""
    url = with_query(master_url, userID=user_id, version=version, **({"robotID": robot_id} if robot_id else {}))
    try:
        if routes is not None:
            status, phrase, body = await routes.get(url, ssl_context, timeout)
        else:
            async with aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=timeout)) as http:
                async with http.get(url, ssl=ssl_context or tls.client_context()) as resp:
                    status, phrase, body = resp.status, resp.reason, await resp.read()
        if status in (401, 403):
            raise AuthError(f"login refused by {master_url}: {http_reason(body, phrase or 'unauthorized')}")
        if status >= 400:
            raise Unavailable(f"login at {master_url} failed (HTTP {status}): {http_reason(body, phrase or 'error')}")
    except (aiohttp.ClientError, asyncio.TimeoutError, OSError) as e:
        raise Unavailable(f"cannot reach the master at {master_url}: "
                          f"{tls.tls_failure(e, master_url) or _socket_failure(e)}") from None
    try:
        answer = json.loads(body)
        ws_url = answer["url"]
        if not isinstance(ws_url, str) or not ws_url:
            raise ValueError
    except (ValueError, KeyError, TypeError):
        raise Unavailable(f"login at {master_url}: answer has no websocket 'url': {body[:200]!r}") from None
    if answer.get("current"):
        log.warning("client protocol version is outdated", version=version, current=answer["current"])
    return ws_url


class HandshakeRefused(Exception):
    """A websocket handshake refused with an HTTP status (and the endpoint's reason)."""

    def __init__(self, status: int, reason: str):
        super().__init__(f"HTTP {status}: {reason}")
        self.status, self.reason = status, reason


async def open_robot_link(ws_url: str, user_id: str, password: str, robot_id: str, *, timeout: float,
                          ssl_context: ssl.SSLContext | None, resume: bool = False,
                          max_lag: float | None = None, routes: Routes | None = None,
                          mptcp: bool = False) -> ClientConnection:
    """Open robot ``robot_id``'s websocket at robot endpoint ``ws_url`` as ``user_id`` (``password`` in
    clear, hashed here), within ``timeout`` s; ``resume``: ask for session resume; ``max_lag``: the
    ``maxLag`` asked for (None: the endpoint's default); ``routes``: a follower's paths; ``mptcp``: as
    :func:`dial`. Newer clients ask
    for HTTP refusals (``refusal=http``). Raises :class:`AuthError` (the handshake refused with 401/403, with the
    endpoint's reason), :class:`Unreachable` (nothing listens) or :class:`Unavailable` (another
    refusal, or the endpoint could not be reached)."""
    query = {"userID": user_id, "robotID": robot_id, "password": hash_password(password), "refusal": "http",
             **({"resume": "1"} if resume else {}), **({"maxLag": f"{max_lag:g}"} if max_lag is not None else {})}
    try:
        return await dial(with_query(ws_url, **query), timeout, ssl_context, routes, mptcp)
    except HandshakeRefused as e:
        if e.status in (401, 403):
            raise AuthError(f"robot endpoint {ws_url} refused {user_id}/{robot_id}: {e.reason}") from None
        raise Unavailable(f"robot endpoint {ws_url} refused the connection (HTTP {e.status}): {e.reason}") from None
    except Unavailable as e:
        raise type(e)(f"cannot connect to the robot endpoint {ws_url}: {e.message}") from None


async def dial(url: str, timeout: float, ssl_context: ssl.SSLContext | None = None,
               routes: Routes | None = None, mptcp: bool = False) -> ClientConnection:
    """Open a websocket to ``url`` within ``timeout`` s (``wss://``: verified with ``ssl_context``; ``routes``:
    a follower's paths, direct else through a relay, :mod:`rce_client.routes`; ``mptcp``: without ``routes``,
    over Multipath TCP where the kernel offers it, :func:`rce.transport.lane_socket.mptcp_connect`). Raises
    :class:`HandshakeRefused` (the endpoint answered the handshake with an HTTP error) or :class:`Unavailable`
    (unreachable, an untrusted certificate, or the handshake failed)."""
    path = None
    try:
        if routes is not None:
            path = await routes.socket_to(url_addr(url))
            if path.relay:
                url = with_query(url, relay=path.relay)
                if not url.startswith("wss:"):
                    log.warning("the session goes through a relay unencrypted: with ws:// the relay can read it "
                                "(use wss://, docs/relays.md)", relay=path.relay)
        if path is not None:
            sock = path.sock
        elif mptcp:
            async with asyncio.timeout(timeout):
                sock = await mptcp_connect(url)
        else:
            sock = None
        ws = await ws_connect(url, open_timeout=timeout, max_size=MAX_FRAME, proxy=None, compression=None,
                              user_agent_header="rce-client", ssl=tls.for_url(url, ssl_context),
                              **({"sock": sock} if sock is not None else {}))
        if path is not None:
            routes.opened(ws, path)
        return ws
    except InvalidStatus as e:
        status = e.response.status_code
        reason = http_reason(e.response.body or b"", e.response.reason_phrase or str(status))
        raise HandshakeRefused(status, reason) from None
    except (ConnectionRefusedError, ConnectionResetError) as e:
        raise Unreachable(str(e) or type(e).__name__) from None
    except (InvalidHandshake, InvalidURI, OSError, TimeoutError) as e:
        raise Unavailable(tls.tls_failure(e, url.split("?", 1)[0]) or str(e) or type(e).__name__) from None


async def close_quietly(ws: ClientConnection) -> None:
    """Close ``ws``; a broken socket's error is not raised."""
    try:
        await ws.close()
    except Exception:   # closing a broken socket never raises out of close()
        pass


def close_text(src: Any) -> str:
    """Human text for a websocket close (an exception or a connection)."""
    rcvd = getattr(src, "rcvd", None) or getattr(src, "close_rcvd", None)
    if rcvd is not None:
        return f"code {rcvd.code}" + (f": {rcvd.reason}" if rcvd.reason else "")
    return "connection lost"
