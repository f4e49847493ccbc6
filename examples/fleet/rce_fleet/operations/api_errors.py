"""Every error of the fleet's web server in the API's one form: ``{"error", "code"}`` (JSON), with its status.

:func:`json_errors` is an aiohttp middleware. The API's own refusals are that form already
(:class:`ApiRefusal`, raised by handlers; :func:`error_response`, returned); what aiohttp answers itself
is turned into it:

======  =======================  ==================================================================
status  code                     when
======  =======================  ==================================================================
404     ``not_found``            no route and no file of the page (the text echoes nothing of the path)
405     ``method_not_allowed``   the path is a route, not for this method (``GET /api/login``); ``Allow``
                                 lists its methods
413     ``too_large``            a body over :data:`MAX_BODY`
500     ``internal``             anything unexpected: the traceback goes to the server's log, never to the
                                 client
======  =======================  ==================================================================

The other statuses keep their text, in the same form (``code`` from :data:`CODES`). Websocket handshakes
refused before the upgrade are answered so too; a failure after the upgrade is the websocket's (its close
code). Errors that aiohttp answers before a request exists (a malformed request line or header, a URL or
header over 8 KiB) are aiohttp's own plain text: no handler runs for them.
"""
from __future__ import annotations

import asyncio
import json
import traceback

from aiohttp import web

from rce.plumbing.log import get_logger
from rce.protocol.limits import truncate

__all__ = ["CODES", "MAX_BODY", "ApiRefusal", "error_response", "json_errors"]

log = get_logger("fleet.api")

MAX_BODY = 1 << 20          # bytes of a request body at most (aiohttp's default, said here): 413 above
CODES = {400: "bad_request", 401: "unauthorized", 403: "forbidden", 404: "not_found", 405: "method_not_allowed",
         409: "conflict", 413: "too_large", 429: "throttled", 500: "internal", 502: "bad_gateway",
         503: "unavailable", 504: "timeout"}
MAX_TEXT = 512              # bytes of an error's text (UTF-8) at most
KEPT_HEADERS = ("WWW-Authenticate", "Retry-After", "Allow")


class ApiRefusal(web.HTTPException):
    """A refusal raised from a handler: ``{"error", "code"}`` with ``status`` (and ``headers``)."""

    def __init__(self, status: int, code: str, text: str, headers: dict | None = None):
        self.status_code = status
        super().__init__(text=json.dumps({"error": truncate(text, MAX_TEXT), "code": code}),
                         content_type="application/json", headers=headers)


def error_response(status: int, text: str, headers: dict | None = None) -> web.Response:
    """The API's error answer: ``{"error": text, "code"}`` with ``status`` (the code from :data:`CODES`, else
    ``error``) and ``headers``."""
    return web.json_response({"error": truncate(text, MAX_TEXT), "code": CODES.get(status, "error")},
                             status=status, headers=headers)


def _contract(request: web.Request, e: web.HTTPException) -> web.Response:
    headers = {k: e.headers[k] for k in KEPT_HEADERS if k in e.headers}
    status, text = e.status, e.text or e.reason
    if status == 405:
        text = f"{request.method} is not a method of this route: it takes {headers.get('Allow', '')}"
    elif status == 404:
        text = ("no such route of the API (GET /api/openapi.json lists them)" if request.path.startswith("/api/")
                else "no such page or file")
    elif status == 413:
        text = f"the body is over {MAX_BODY} bytes, the most this server takes"
    return error_response(status, text, headers)


@web.middleware
async def json_errors(request: web.Request, handler) -> web.StreamResponse:
    """The middleware (module docstring)."""
    try:
        return await handler(request)
    except web.HTTPException as e:
        if e.status < 400 or e.content_type == "application/json":
            raise
        return _contract(request, e)
    except (asyncio.CancelledError, ConnectionError):
        raise
    except Exception as e:
        if request.headers.get("Upgrade", "").lower() == "websocket":
            raise                          # past the handshake the answer is the websocket's close
        log.error("internal error", method=request.method, path=truncate(request.path, 200),
                  error=truncate(f"{type(e).__name__}: {e}", MAX_TEXT), traceback=traceback.format_exc(limit=20))
        return error_response(500, "internal error (the server's log says more)")
