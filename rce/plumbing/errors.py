"""One error type per layer, each with a stable ``code`` and a human message.

Every refusal the engine makes (an ER frame to a robot, an HTTP error, a
control-plane error reply) carries one of these, so a client can tell *what*
was wrong (``code``) and read *where* (``message``).
"""
from __future__ import annotations

import json


class RCEError(Exception):
    """Base error: ``code`` is a short machine-readable token, ``message`` a one-line reason."""

    code = "error"

    def __init__(self, message: str, *, code: str | None = None):
        super().__init__(message)
        self.message = message
        if code is not None:
            self.code = code

    def to_dict(self) -> dict:
        """The wire form used on the control plane: ``{"code": ..., "message": ...}``."""
        return {"code": self.code, "message": self.message}

    @classmethod
    def from_dict(cls, record: dict) -> "RCEError":
        """Rebuild an error received over the control plane (inverse of :meth:`to_dict`)."""
        err = _BY_CODE.get(record.get("code", ""), RCEError)(str(record.get("message", "")), code=record.get("code"))
        if isinstance(err, NotLeader) and isinstance(record.get("leader"), dict):
            err.leader = record["leader"]
        if isinstance(err, Throttled) and isinstance(record.get("retry_after"), (int, float)):
            err.retry_after = record["retry_after"]
        return err

    def __str__(self) -> str:
        return self.message


class ProtocolError(RCEError):
    """A client or internal frame that does not follow the protocol (docs/design.md, section 3)."""

    code = "protocol"


class MessageError(RCEError):
    """An unknown message class, or a message that does not fit its class (docs/design.md, section 4.1)."""

    code = "message"


class ConfigError(RCEError):
    """A robot config or command-line configuration that cannot be used."""

    code = "config"


class RequestError(RCEError):
    """A well-formed request the master refuses (unknown tag, duplicate, unpairable interfaces...)."""

    code = "request"


class AuthError(RCEError):
    """Bad credentials (login or websocket handshake)."""

    code = "auth"


class NotFound(RequestError):
    """A tag, name or resource that does not exist."""

    code = "not_found"


class Unavailable(RCEError):
    """A resource that exists but cannot serve now (no container host, host lost, timeout)."""

    code = "unavailable"


class NotLeader(Unavailable):
    """Asked of a master that stands by (several masters on etcd, docs/INTERNALS.md "Several
    masters"): only the leader takes task sets and changes the state. ``leader`` is the leader's
    ``{"control": "HOST:PORT", "http": "http://HOST:PORT/"}``, or None while none is known; the
    control plane carries it as the error's ``"leader"`` field."""

    code = "not_leader"

    def __init__(self, message: str, *, code: str | None = None, leader: dict | None = None):
        super().__init__(message, code=code)
        self.leader = leader

    def to_dict(self) -> dict:
        return {**super().to_dict(), "leader": self.leader}


class Throttled(Unavailable):
    """Refused for now, to be tried again after ``retry_after`` s: too many failed logins for a user
    or from an address, or too many logins waiting for a password check (docs/SECURITY.md, "Login").
    HTTP 429 with ``Retry-After``; the control plane carries ``retry_after`` as a field."""

    code = "throttled"

    def __init__(self, message: str, *, code: str | None = None, retry_after: float = 1.0):
        super().__init__(message, code=code)
        self.retry_after = retry_after

    def to_dict(self) -> dict:
        return {**super().to_dict(), "retry_after": self.retry_after}


class Timeout(RCEError, TimeoutError):
    """A call that got no answer in time (a control request, a service call, a robot's reply).

    A :class:`TimeoutError` too, so ``except TimeoutError`` catches it; not an
    :class:`Unavailable`: the peer may be alive and merely slow."""

    code = "timeout"


_BY_CODE = {c.code: c for c in (RCEError, ProtocolError, MessageError, ConfigError, RequestError,
                                AuthError, NotFound, Unavailable, NotLeader, Throttled, Timeout)}


def http_reason(body: bytes | str, fallback: str = "", limit: int | None = None) -> str:
    """The one-line reason in an HTTP error body (the master's, a robot endpoint's, etcd's): plain
    text (its first non-empty line), or a JSON object's ``reason``/``message``/``error`` (a string,
    or an object with a ``message``/``reason``). ``fallback`` when there is none; at most ``limit``
    characters when given."""
    text = body.decode(errors="replace") if isinstance(body, (bytes, bytearray)) else str(body)
    text = text.strip()
    try:
        obj = json.loads(text)
    except ValueError:
        obj = None
    reason = ""
    if isinstance(obj, dict):
        for k in ("reason", "message", "error"):
            v = obj.get(k)
            if isinstance(v, dict):
                v = v.get("message") or v.get("reason")
            if isinstance(v, str) and v:
                reason = v
                break
    if not reason:
        reason = text.splitlines()[0].strip() if text else ""
    reason = reason or fallback
    return reason[:limit] if limit is not None else reason
