"""One request to the fleet's HTTP API from a command line (``rce-fleet task --api``, ``rce-fleet users``).

:func:`call` makes the request as a user: with a bearer token when given, else it logs in
(``POST /api/login``, a token of :data:`LOGIN_TTL_S`) and logs out after. A refusal raises
:class:`ApiRefused` with the status, the API's ``code`` and its reason; a server that cannot be reached (or
answers what is not HTTP) raises :class:`ApiUnreachable`. :func:`report` prints either on stderr, one line,
and gives the exit code: 1 refused, 3 unreachable (a 502, 503 or 504 too).
"""
from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from urllib.parse import quote

__all__ = ["EXIT_REFUSED", "EXIT_UNREACHABLE", "LOGIN_TTL_S", "ApiRefused", "ApiUnreachable", "Caller", "call",
           "part", "report"]

EXIT_REFUSED, EXIT_UNREACHABLE = 1, 3
LOGIN_TTL_S = 300.0       # s the token of a one-request login lives (it is revoked after the request anyway)
MAX_REASON = 512          # characters of a reason printed


class ApiRefused(Exception):
    """The API refused: HTTP ``status``, its ``code`` and ``reason`` (``what``: the step refused)."""

    def __init__(self, status: int, answer: object, what: str = "refused"):
        if isinstance(answer, dict):
            code, reason = str(answer.get("code") or f"HTTP {status}"), str(answer.get("error") or "")
        else:
            code, reason = f"HTTP {status}", str(answer or "").strip()
        self.status, self.code, self.what = status, code, what
        self.reason = (reason or "(no reason given)")[:MAX_REASON]
        super().__init__(f"{what} ({code}): {self.reason}")


class ApiUnreachable(Exception):
    """The API could not be reached at all; the message says why."""


@dataclass
class Caller:
    """Who calls, and where: ``api`` (the page's URL; its query is ignored), ``user`` and ``password`` (for a
    login) or ``token``, ``ca_file`` (an https:// API's CA, else ``$RCE_CA_FILE`` or the system's) and
    ``timeout`` (s, the whole exchange)."""
    api: str
    user: str
    password: str | None = None
    token: str | None = None
    ca_file: str | None = None
    timeout: float = 30.0

    @property
    def base(self) -> str:
        return self.api.split("?")[0].rstrip("/") + "/"


def part(text: str) -> str:
    """``text`` as one segment of a URL path (a ``/`` in a task id stays in it)."""
    return quote(text, safe="")


async def _answer(r) -> object:
    text = await r.text(errors="replace")
    try:
        return json.loads(text)
    except ValueError:
        return text


async def call(who: Caller, method: str, path: str, body: object = None) -> object:
    """``method path`` (relative to the API's base, its segments quoted with :func:`part`) with JSON ``body``;
    returns the JSON answer. Raises :class:`ApiRefused` (a status >= 400; a refused login too) or
    :class:`ApiUnreachable`."""
    import aiohttp
    from yarl import URL

    from rce.plumbing.errors import RCEError
    from rce.transport.tls import client_context
    base = who.base
    try:
        ssl = client_context(who.ca_file) if base.startswith("https:") else None
    except RCEError as e:
        raise ApiUnreachable(e.message) from None
    try:
        async with aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=who.timeout)) as http:
            token = who.token
            if not token:
                async with http.post(base + "api/login", ssl=ssl, json={"user": who.user, "password": who.password,
                                                                       "ttl_s": LOGIN_TTL_S}) as r:
                    answer = await _answer(r)
                    if r.status != 200 or not isinstance(answer, dict) or "token" not in answer:
                        raise ApiRefused(r.status, answer, f"cannot log in at {base} as {who.user!r}")
                    token = answer["token"]
            auth = {"Authorization": f"Bearer {token}"}
            try:
                async with http.request(method, URL(base + path, encoded=True), json=body, headers=auth,
                                        ssl=ssl) as r:
                    out = await _answer(r)
                    if r.status >= 400:
                        raise ApiRefused(r.status, out)
                    return out
            finally:
                if not who.token:
                    async with http.post(base + "api/logout", headers=auth, ssl=ssl):
                        pass
    except (aiohttp.ClientError, OSError, ValueError) as e:
        raise ApiUnreachable(f"cannot reach the fleet's API at {base}: {e or type(e).__name__}") from None


def report(prog: str, e: ApiRefused | ApiUnreachable) -> int:
    """Print ``e`` on stderr as ``prog: ...``; returns the exit code (module docstring)."""
    print(f"{prog}: {e}", file=sys.stderr)
    if isinstance(e, ApiUnreachable) or e.status in (502, 503, 504):
        return EXIT_UNREACHABLE
    return EXIT_REFUSED
