"""Who may call the fleet's task API, sans-I/O: roles, bearer tokens and the ``Authorization`` header.

Credentials are the rce master's users (the master checks the password, through the same login guard
as the robots' front door: :mod:`rce_master.auth.login_guard`); each user has a role, kept in the master's
user record:

=========  =============================================================================
viewer     reads the tasks (``GET /api/tasks``), ``/metrics`` and the operator page
operator   also adds and cancels tasks (``POST /api/tasks``, ``DELETE /api/tasks/ID``)
admin      also revokes any user's tokens (``DELETE /api/tokens/USER``)
=========  =============================================================================

:class:`TokenBook` keeps the bearer tokens ``POST /api/login`` issues: random (256 bits), kept only as
their SHA-256, each bound to a user and role, valid ``ttl_s`` seconds (the server's ``--token-ttl``,
or less when the login asks), and revocable (``POST /api/logout``, or an admin's revocation of a
user's tokens). At most ``max_tokens`` live at once: past it the oldest is forgotten (counted). Times
are given by the caller (monotonic s).
"""
from __future__ import annotations

import base64
import binascii
import hashlib
import secrets
from collections import OrderedDict
from dataclasses import dataclass

__all__ = ["DEFAULT_TTL_S", "ROLES", "Identity", "TokenBook", "allows", "parse_authorization"]

ROLES = ("viewer", "operator", "admin")     # in order: each may do what the ones before it may
DEFAULT_TTL_S = 8 * 3600.0                  # s a token lives by default: a work shift (rce-fleet serve --token-ttl)
MAX_TOKENS = 10_000                         # live tokens at most (~1 MB); past it the oldest is forgotten


def allows(role: str, needed: str) -> bool:
    """Whether ``role`` may do what ``needed`` may (an unknown role may do nothing)."""
    return role in ROLES and ROLES.index(role) >= ROLES.index(needed)


@dataclass(frozen=True)
class Identity:
    """Who a request comes from: the master's ``user``, its ``role``, and how it proved it
    (``bearer``: a token of the book; ``basic``: a password)."""
    user: str
    role: str
    via: str


@dataclass
class _Token:
    user: str
    role: str
    expires: float          # monotonic s


class TokenBook:
    """Bearer tokens (the module docstring). ``ttl_s``: the longest a token lives (s, > 0)."""

    def __init__(self, ttl_s: float = DEFAULT_TTL_S, max_tokens: int = MAX_TOKENS):
        if not ttl_s > 0:
            raise ValueError(f"the token lifetime must be > 0 s, got {ttl_s!r}")
        self.ttl_s, self.max_tokens = float(ttl_s), int(max_tokens)
        self.tokens: OrderedDict[str, _Token] = OrderedDict()       # sha256 hex -> token, oldest first
        self.evicted = 0

    @staticmethod
    def _key(token: str) -> str:
        return hashlib.sha256(token.encode()).hexdigest()

    def issue(self, user: str, role: str, now: float, ttl_s: float | None = None) -> tuple[str, float]:
        """A new token for ``user`` with ``role``; returns (token, s it lives: ``ttl_s`` capped at the
        book's, the book's when None)."""
        self.expire(now)
        life = self.ttl_s if ttl_s is None else min(float(ttl_s), self.ttl_s)
        token = secrets.token_urlsafe(32)
        self.tokens[self._key(token)] = _Token(user, role, now + life)
        while len(self.tokens) > self.max_tokens:
            self.tokens.popitem(last=False)
            self.evicted += 1
        return token, life

    def check(self, token: str, now: float) -> Identity | None:
        """The identity ``token`` stands for; None when it is unknown, expired or revoked."""
        t = self.tokens.get(self._key(token))
        if t is None or t.expires <= now:
            return None
        return Identity(t.user, t.role, "bearer")

    def revoke(self, token: str) -> bool:
        """End ``token``; False when it was not live."""
        return self.tokens.pop(self._key(token), None) is not None

    def revoke_user(self, user: str) -> int:
        """End every token of ``user``; returns how many."""
        keys = [k for k, t in self.tokens.items() if t.user == user]
        for k in keys:
            del self.tokens[k]
        return len(keys)

    def expire(self, now: float) -> None:
        """Forget the expired tokens (O(n) over the live ones, at each issue)."""
        for k in [k for k, t in self.tokens.items() if t.expires <= now]:
            del self.tokens[k]


def parse_authorization(header: str) -> tuple[str, str, str] | None:
    """An ``Authorization`` header -> ``("bearer", token, "")`` or ``("basic", user, password)``
    (RFC 6750, RFC 7617); None when it is empty. Raises ValueError naming what is wrong (another
    scheme, a Basic value that is not base64 of ``user:password``)."""
    scheme, _, value = header.strip().partition(" ")
    value = value.strip()
    if not scheme:
        return None
    if scheme.lower() == "bearer" and value:
        return "bearer", value, ""
    if scheme.lower() == "basic" and value:
        try:
            user, sep, password = base64.b64decode(value, validate=True).decode().partition(":")
        except (binascii.Error, UnicodeDecodeError):
            raise ValueError("Authorization: Basic needs base64 of user:password") from None
        if not sep or not user:
            raise ValueError("Authorization: Basic needs base64 of user:password")
        return "basic", user, password
    raise ValueError(f"Authorization: use 'Bearer TOKEN' (POST /api/login) or 'Basic' over TLS, not {scheme!r}")
