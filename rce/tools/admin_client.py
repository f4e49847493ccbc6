"""The one client of the master's admin API (routes: :mod:`rce_master.http.admin`), for rce-console,
rce-topic/rce-service ``--container``, the engine launcher (:mod:`rce.tools.launch`) and the benchmarks.

JSON in and out, ``Authorization: Bearer TOKEN``. Blocking (:meth:`AdminClient.request`, for
command lines and test or bench harnesses) or asyncio (:meth:`AdminClient.arequest`, for rce-topic,
whose Ctrl-C must not wait for a blocked thread); both share everything but the transport.

::

    client = AdminClient.from_options("http://127.0.0.1:9000/")   # token: RCE_ADMIN_TOKEN or the token file
    client.request("GET", "/api/robots")                           # -> list of dicts

A refusal raises the :class:`RCEError` subclass for its HTTP status with the master's one-line
reason, as ``"GET /api/robots: HTTP 401: <reason>"`` (``.status`` holds the code): 401/403
:class:`AuthError`, 404 :class:`NotFound`, 429 :class:`Throttled` (its ``retry_after`` from the
``Retry-After`` header), 504 :class:`Timeout`, other 5xx and an unreachable master :class:`Unavailable`,
other 4xx :class:`RequestError`.

Several masters (``AdminClient("http://m1:9000/,http://m2:9000/", ...)`` or a list; docs/INTERNALS.md,
"Several masters"): a request goes to the master that answered last, and to the others in turn
while they cannot be reached (refused or reset: a master that does not answer in time raises
:class:`Timeout`, as it may have done what was asked). A standby refuses what needs the leader
with 503 and the leader's URL in the ``X-RCE-Leader`` header: the request goes there next.
"""
from __future__ import annotations

import json
import os
import ssl
import urllib.error
import urllib.request
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rce.transport import tls
from rce.plumbing.errors import (AuthError, NotFound, RCEError, RequestError, Throttled, Timeout, Unavailable,
                                 http_reason)

if TYPE_CHECKING:
    import aiohttp      # imported by the first arequest: a command line that calls request only never loads it

TIMEOUT = 30.0        # s, an admin API request, on top of the op's own timeout (a bus call's, a sample's)
TOKEN_ENV = "RCE_ADMIN_TOKEN"
MAX_REASON = 300      # chars of an error body kept as the reason
LEADER_HEADER = "X-RCE-Leader"   # a standby's refusal names the leader's URL in it (empty: none elected now)


def token_file() -> Path:
    """``$XDG_CONFIG_HOME/rce/admin-token`` (default ``~/.config/rce/admin-token``): where the master
    writes its token when ``--admin-token-file`` is not given."""
    return Path(os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config") / "rce" / "admin-token"


def find_token(token: str | None = None, path: Path | None = None) -> str:
    """The admin token: ``token`` (``--admin-token``), else ``$RCE_ADMIN_TOKEN``, else the file
    ``path`` (``--admin-token-file``) or :func:`token_file`. Raises :class:`AuthError` when none is set."""
    if token:
        return token
    if os.environ.get(TOKEN_ENV):
        return os.environ[TOKEN_ENV]
    p = Path(path) if path else token_file()
    try:
        found = p.read_text().strip()
    except OSError:
        found = ""
    if not found:
        raise AuthError(f"no admin token: pass --admin-token, set {TOKEN_ENV} or write it to {p}")
    return found


def refusal(method: str, path: str, status: int, body: bytes | str, retry_after: str | None = None) -> RCEError:
    """The error for HTTP ``status`` with ``body`` (the master's reason) answering ``method path``;
    ``retry_after``: the answer's ``Retry-After`` (s), for a 429."""
    reason = http_reason(body, f"HTTP {status}", MAX_REASON)
    if status == 429:
        err = Throttled(f"{method} {path}: HTTP {status}: {reason}",
                        retry_after=float(retry_after) if (retry_after or "").isdigit() else 1.0)
        err.status = status
        return err
    cls = (AuthError if status in (401, 403) else NotFound if status == 404 else Timeout if status == 504
           else Unavailable if status >= 500 else RequestError)
    err = cls(f"{method} {path}: HTTP {status}: {reason}")
    err.status = status
    return err


def master_urls(masters: str | Sequence[str]) -> list[str]:
    """The master URLs in ``masters`` (one URL, several separated by commas, or a list of such),
    each ending with ``/``. Raises :class:`RequestError` when there is none."""
    items = [masters] if isinstance(masters, str) else list(masters)
    urls = [u.strip() for item in items for u in item.split(",") if u.strip()]
    if not urls:
        raise RequestError("no master URL given")
    return [u if u.endswith("/") else u + "/" for u in urls]


class _Tries:
    """One request's walk over the masters (the module says the order); collects why each failed."""

    def __init__(self, client: "AdminClient", method: str, path: str, timeout: float):
        self.client, self.method, self.path, self.timeout = client, method, path, timeout
        self.queue = [client.base] + [b for b in client.bases if b != client.base]
        self.failures: list[RCEError] = []

    def __iter__(self) -> Iterator[str]:
        tried = set()
        while self.queue:
            base = self.queue.pop(0)
            if base not in tried:
                tried.add(base)
                yield base

    def answered(self, base: str) -> None:
        self.client.base = base

    def unreachable(self, base: str, error: BaseException) -> None:
        """``base`` could not be reached; raises :class:`Timeout` when it did not answer in time."""
        if isinstance(error, TimeoutError) or isinstance(getattr(error, "reason", None), TimeoutError):
            raise Timeout(f"the master at {base} did not answer {self.method} {self.path} within "
                          f"{self.timeout:g} s") from None
        why = getattr(error, "reason", None) or error or type(error).__name__
        self.failures.append(Unavailable(f"cannot reach the master at {base}: {why}"))

    def refused(self, status: int, headers: Any, body: bytes) -> None:
        """``base`` refused: a standby's refusal sends the request to the leader it names, any
        other refusal is raised."""
        err = refusal(self.method, self.path, status, body, headers.get("Retry-After"))
        leader = headers.get(LEADER_HEADER) if status == 503 else None
        if leader is None:
            raise err
        self.failures.append(err)
        if leader:
            self.queue.insert(0, master_urls(leader)[0])

    def error(self) -> RCEError:
        """What to raise when no master answered."""
        refusals = [e for e in self.failures if getattr(e, "status", None)]     # standbys' (HTTP 503)
        if refusals or len(self.failures) == 1:
            return (refusals or self.failures)[-1]
        return Unavailable("cannot reach any master: " + "; ".join(e.message for e in self.failures))


class AdminClient:
    """The admin API of the master(s) at ``base`` (``http://HOST:9000/``; several: a list, or
    URLs separated by commas) with ``token``.

    ``timeout`` (s) bounds each request, plus the ``op_timeout`` a request passes for an op that
    waits on its own (a service call, a sample). :attr:`base` is the master that answered last."""

    def __init__(self, base: str | Sequence[str], token: str, timeout: float = TIMEOUT,
                 ssl_context: ssl.SSLContext | None = None):
        self.bases = master_urls(base)
        if ssl_context is None and any(b.lower().startswith("https:") for b in self.bases):
            ssl_context = tls.client_context()      # https:// masters: $RCE_CA_FILE, else the system's CAs
        self.ssl_context = ssl_context
        self.base = self.bases[0]
        self.token = token
        self.timeout = timeout
        self._session: aiohttp.ClientSession | None = None

    @classmethod
    def from_options(cls, base: str | Sequence[str], token: str | None = None,
                     token_path: Path | None = None, ca_file: Path | None = None) -> "AdminClient":
        """A client with the token :func:`find_token` finds, trusting ``ca_file`` for an https://
        master (:func:`rce.transport.tls.client_context`). Raises :class:`AuthError` when there is no token,
        :class:`ConfigError` when the CA file cannot be read."""
        return cls(base, find_token(token, token_path), ssl_context=tls.client_context(ca_file) if ca_file else None)

    def _headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}", "Content-Type": "application/json"}

    def request(self, method: str, path: str, body: Any = None, op_timeout: float = 0.0) -> Any:
        """``method path`` with JSON ``body`` (None: no body), blocking; the JSON answer.
        Raises as the module says."""
        data = json.dumps(body).encode() if body is not None else None
        tries = _Tries(self, method, path, self.timeout + op_timeout)
        for base in tries:
            req = urllib.request.Request(base + path.lstrip("/"), data=data, method=method, headers=self._headers())
            try:
                with urllib.request.urlopen(req, timeout=tries.timeout, context=self.ssl_context) as r:
                    answer = r.read()
            except urllib.error.HTTPError as e:
                tries.refused(e.code, e.headers, e.read())
                continue
            except (urllib.error.URLError, OSError) as e:
                tries.unreachable(base, e)
                continue
            tries.answered(base)
            return json.loads(answer or b"null")
        raise tries.error()

    async def arequest(self, method: str, path: str, body: Any = None, op_timeout: float = 0.0) -> Any:
        """:meth:`request` for asyncio (one HTTP session, kept until :meth:`aclose`)."""
        import aiohttp
        if self._session is None:
            self._session = aiohttp.ClientSession(headers=self._headers())
        tries = _Tries(self, method, path, self.timeout + op_timeout)
        for base in tries:
            try:
                async with self._session.request(method, base + path.lstrip("/"), json=body,
                                                 timeout=aiohttp.ClientTimeout(total=tries.timeout),
                                                 ssl=self.ssl_context or True) as r:
                    status, headers, data = r.status, r.headers, await r.read()
            except (aiohttp.ClientError, OSError) as e:           # OSError: TimeoutError too
                tries.unreachable(base, e)
                continue
            if status >= 400:
                tries.refused(status, headers, data)
                continue
            tries.answered(base)
            return json.loads(data or b"null")
        raise tries.error()

    async def aclose(self) -> None:
        """Close the session :meth:`arequest` opened."""
        if self._session is not None:
            await self._session.close()
            self._session = None
