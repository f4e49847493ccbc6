"""The one client of the master's admin API (routes: :mod:`rce_master.admin`), for rce-console,
rce-topic/rce-service ``--container``, the engine launcher (:mod:`rce.launch`) and the benchmarks.

JSON in and out, ``Authorization: Bearer TOKEN``. Blocking (:meth:`AdminClient.request`, for
command lines and test or bench harnesses) or asyncio (:meth:`AdminClient.arequest`, for rce-topic,
whose Ctrl-C must not wait for a blocked thread); both share everything but the transport.

::

    client = AdminClient.from_options("http://127.0.0.1:9000/")   # token: RCE_ADMIN_TOKEN or the token file
    client.request("GET", "/api/robots")                           # -> list of dicts

A refusal raises the :class:`RCEError` subclass for its HTTP status with the master's one-line
reason, as ``"GET /api/robots: HTTP 401: <reason>"`` (``.status`` holds the code): 401/403
:class:`AuthError`, 404 :class:`NotFound`, 504 :class:`Timeout`, other 5xx and an unreachable
master :class:`Unavailable`, other 4xx :class:`RequestError`.
"""
from __future__ import annotations

import json
import os
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import aiohttp

from rce.errors import AuthError, NotFound, RCEError, RequestError, Timeout, Unavailable

TIMEOUT = 30.0        # s, an admin API request, on top of the op's own timeout (a bus call's, a sample's)
TOKEN_ENV = "RCE_ADMIN_TOKEN"
MAX_REASON = 300      # chars of an error body kept as the reason


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


def refusal(method: str, path: str, status: int, body: bytes | str) -> RCEError:
    """The error for HTTP ``status`` with ``body`` (the master's reason) answering ``method path``."""
    text = body.decode(errors="replace") if isinstance(body, (bytes, bytearray)) else str(body)
    reason = next((ln.strip() for ln in text.splitlines() if ln.strip()), f"HTTP {status}")[:MAX_REASON]
    cls = (AuthError if status in (401, 403) else NotFound if status == 404 else Timeout if status == 504
           else Unavailable if status >= 500 else RequestError)
    err = cls(f"{method} {path}: HTTP {status}: {reason}")
    err.status = status
    return err


class AdminClient:
    """The admin API of the master at ``base`` (``http://HOST:9000/``) with ``token``.

    ``timeout`` (s) bounds each request, plus the ``op_timeout`` a request passes for an op that
    waits on its own (a service call, a sample)."""

    def __init__(self, base: str, token: str, timeout: float = TIMEOUT):
        self.base = base if base.endswith("/") else base + "/"
        self.token = token
        self.timeout = timeout
        self._session: aiohttp.ClientSession | None = None

    @classmethod
    def from_options(cls, base: str, token: str | None = None, token_path: Path | None = None) -> "AdminClient":
        """A client with the token :func:`find_token` finds. Raises :class:`AuthError` when there is none."""
        return cls(base, find_token(token, token_path))

    def _url(self, path: str) -> str:
        return self.base + path.lstrip("/")

    def _headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}", "Content-Type": "application/json"}

    def _failed(self, e: BaseException, what: str, timeout: float) -> RCEError:
        if isinstance(e, TimeoutError) or isinstance(getattr(e, "reason", None), TimeoutError):
            return Timeout(f"the master at {self.base} did not answer {what} within {timeout:g} s")
        why = getattr(e, "reason", None) or e or type(e).__name__
        return Unavailable(f"cannot reach the master at {self.base}: {why}")

    def request(self, method: str, path: str, body: Any = None, op_timeout: float = 0.0) -> Any:
        """``method path`` with JSON ``body`` (None: no body), blocking; the JSON answer.
        Raises as the module says."""
        data = json.dumps(body).encode() if body is not None else None
        req = urllib.request.Request(self._url(path), data=data, method=method, headers=self._headers())
        timeout = self.timeout + op_timeout
        try:
            with urllib.request.urlopen(req, timeout=timeout) as r:
                return json.loads(r.read() or b"null")
        except urllib.error.HTTPError as e:
            raise refusal(method, path, e.code, e.read()) from None
        except (urllib.error.URLError, OSError) as e:
            raise self._failed(e, f"{method} {path}", timeout) from None

    async def arequest(self, method: str, path: str, body: Any = None, op_timeout: float = 0.0) -> Any:
        """:meth:`request` for asyncio (one HTTP session, kept until :meth:`aclose`)."""
        if self._session is None:
            self._session = aiohttp.ClientSession(headers=self._headers())
        timeout = self.timeout + op_timeout
        try:
            async with self._session.request(method, self._url(path), json=body,
                                             timeout=aiohttp.ClientTimeout(total=timeout)) as r:
                status, data = r.status, await r.read()
        except (aiohttp.ClientError, OSError) as e:           # OSError: TimeoutError too
            raise self._failed(e, f"{method} {path}", timeout) from None
        if status >= 400:
            raise refusal(method, path, status, data)
        return json.loads(data or b"null")

    async def aclose(self) -> None:
        """Close the session :meth:`arequest` opened."""
        if self._session is not None:
            await self._session.close()
            self._session = None
