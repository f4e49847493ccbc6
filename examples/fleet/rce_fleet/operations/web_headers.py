"""The headers every answer of the fleet's web server carries (the page, its files, the task API,
``/metrics``), set on aiohttp's ``on_response_prepare`` so that errors, static files and websocket
handshakes get them too.

=================================  =================================================================
``X-Frame-Options: DENY``          the page cannot be framed (clickjacking; RFC 7034), and for browsers
``Content-Security-Policy:          that read CSP Level 2 the same, with plugins and ``<base>`` off
frame-ancestors 'none'; ...``
``X-Content-Type-Options:          answers are taken as the type they say (no MIME sniffing)
nosniff``
``Referrer-Policy: no-referrer``   links from the page tell no other site where they came from
``Strict-Transport-Security``      over TLS only: browsers keep to https:// for a year (RFC 6797)
``Cache-Control: no-store``        on ``/api/...``, ``/metrics`` and the page's generated files: tasks,
                                   tokens and the configuration are never kept by a cache
``Server: rce-fleet``              no names or versions of the libraries behind it
=================================  =================================================================

Sans-I/O apart from aiohttp's types.
"""
from __future__ import annotations

from aiohttp import web

__all__ = ["HEADERS", "HSTS", "add_security_headers"]

HEADERS = {"X-Frame-Options": "DENY",
           "Content-Security-Policy": "frame-ancestors 'none'; object-src 'none'; base-uri 'self'",
           "X-Content-Type-Options": "nosniff",
           "Referrer-Policy": "no-referrer"}
HSTS = "max-age=31536000"            # s browsers keep to https:// (a year)
SERVER = "rce-fleet"
NO_STORE_PREFIXES = ("/api/", "/metrics", "/config.json", "/map.png", "/relays.json", "/placement.json")


def add_security_headers(app: web.Application, *, tls: bool) -> None:
    """Give every answer of ``app`` the headers of the module docstring (HSTS with ``tls``)."""

    async def prepare(req: web.Request, resp: web.StreamResponse) -> None:
        resp.headers.update(HEADERS)
        resp.headers["Server"] = SERVER
        if tls:
            resp.headers["Strict-Transport-Security"] = HSTS
        if req.path.startswith(NO_STORE_PREFIXES):
            resp.headers["Cache-Control"] = "no-store"

    app.on_response_prepare.append(prepare)
