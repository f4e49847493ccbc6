"""Who may call the fleet's task API, sans-I/O: roles, bearer tokens and the ``Authorization`` header.

Credentials are the rce master's users (the master checks the password, through the same login guard
as the robots' front door: :mod:`rce_master.auth.login_guard`); each user has a role, kept in the master's
user record:

=========  ===================================================================================================
viewer     reads the tasks (``GET /api/tasks``), ``/metrics`` and the operator page
operator   also adds and cancels tasks (``POST /api/tasks``, ``DELETE /api/tasks/ID``)
admin      also manages the users (``/api/users``) and revokes any user's tokens (``DELETE /api/tokens/USER``)
=========  ===================================================================================================

:class:`TokenBook` keeps the bearer tokens ``POST /api/login`` issues: random (256 bits), kept only as
their SHA-256, each bound to a user and role, valid ``ttl_s`` seconds (the server's ``--token-ttl``,
or less when the login asks), and revocable (``POST /api/logout``, or an admin's revocation of a
user's tokens). One user holds at most ``max_per_user`` live tokens: a further login ends that user's
oldest (counted in ``evicted_user``), so no user's logins can push out another's. At most ``max_tokens``
live at once in all: past it the oldest is forgotten (counted in ``evicted``). The book lives in the
serving process's memory: a restart of ``rce-fleet serve`` ends every token (the login's answer says so,
``survives_restart``). Times are given by the caller (monotonic s).
"""
from __future__ import annotations

import base64
import binascii
import hashlib
import secrets
from collections import OrderedDict
from dataclasses import dataclass

from rce.protocol.limits import short_repr

__all__ = ["DEFAULT_TTL_S", "ROLES", "Identity", "TokenBook", "allows", "parse_authorization"]

ROLES = ("viewer", "operator", "admin")     # in order: each may do what the ones before it may
DEFAULT_TTL_S = 8 * 3600.0                  # s a token lives by default: a work shift (rce-fleet serve --token-ttl)
MAX_TOKENS = 10_000                         # live tokens at most (~1 MB); past it the oldest is forgotten
MAX_PER_USER = 32                           # live tokens of one user at most; past it that user's oldest ends


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

    def __init__(self, ttl_s: float = DEFAULT_TTL_S, max_tokens: int = MAX_TOKENS, max_per_user: int = MAX_PER_USER):
        if not ttl_s > 0:
            raise ValueError(f"the token lifetime must be > 0 s, got {ttl_s!r}")
        if max_per_user < 1 or max_tokens < 1:
            raise ValueError(f"the token bounds must be >= 1, got {max_tokens!r} and {max_per_user!r} per user")
        self.ttl_s, self.max_tokens, self.max_per_user = float(ttl_s), int(max_tokens), int(max_per_user)
        self.tokens: OrderedDict[str, _Token] = OrderedDict()       # sha256 hex -> token, oldest first
        self.by_user: dict[str, OrderedDict[str, None]] = {}        # user -> its keys, oldest first
        self.evicted = 0          # tokens forgotten for the bound of all (max_tokens)
        self.evicted_user = 0     # tokens ended for their user's bound (max_per_user)

    @staticmethod
    def _key(token: str) -> str:
        return hashlib.sha256(token.encode()).hexdigest()

    def issue(self, user: str, role: str, now: float, ttl_s: float | None = None) -> tuple[str, float]:
        """A new token for ``user`` with ``role``; returns (token, s it lives: ``ttl_s`` capped at the
        book's, the book's when None)."""
        self.expire(now)
        life = self.ttl_s if ttl_s is None else min(float(ttl_s), self.ttl_s)
        token = secrets.token_urlsafe(32)
        key = self._key(token)
        mine = self.by_user.setdefault(user, OrderedDict())
        while len(mine) >= self.max_per_user:
            self._drop(next(iter(mine)))
            self.evicted_user += 1
        self.tokens[key] = _Token(user, role, now + life)
        mine[key] = None
        while len(self.tokens) > self.max_tokens:
            self._drop(next(iter(self.tokens)))
            self.evicted += 1
        return token, life

    def check(self, token: str, now: float) -> Identity | None:
        """The identity ``token`` stands for; None when it is unknown, expired or revoked."""
        return self.check_digest(self._key(token), now)

    def check_digest(self, digest_hex: str, now: float) -> Identity | None:
        """As :meth:`check`, given the token's SHA-256 (hex) rather than the token: what an RCE client
        sends for its password (the page's session through the fleet's server, :mod:`rce_fleet.live.page_door`)."""
        t = self.tokens.get(digest_hex.lower())
        if t is None or t.expires <= now:
            return None
        return Identity(t.user, t.role, "bearer")

    def revoke(self, token: str) -> bool:
        """End ``token``; False when it was not live."""
        return self._drop(self._key(token))

    def revoke_user(self, user: str) -> int:
        """End every token of ``user``; returns how many."""
        keys = list(self.by_user.get(user, ()))
        for k in keys:
            self._drop(k)
        return len(keys)

    def expire(self, now: float) -> None:
        """Forget the expired tokens (O(n) over the live ones, at each issue)."""
        for k in [k for k, t in self.tokens.items() if t.expires <= now]:
            self._drop(k)

    def _drop(self, key: str) -> bool:
        t = self.tokens.pop(key, None)
        if t is None:
            return False
        mine = self.by_user.get(t.user)
        if mine is not None:
            mine.pop(key, None)
            if not mine:
                del self.by_user[t.user]
        return True


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
    raise ValueError(f"Authorization: use 'Bearer TOKEN' (POST /api/login) or 'Basic' over TLS, not "
                     f"{short_repr(scheme)}")
