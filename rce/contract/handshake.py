"""The cluster handshake every TCP control link opens with (:mod:`rce.transport.cluster_auth`): its four
messages, each ``{"auth": kind, ...}``, served by :data:`rce.transport.cluster_auth.HANDSHAKE`. The
values are checked by the handshake's steps, which name what is wrong (a nonce's length, the
version, the key id), so they are typed loosely here: a value of another type fails there."""
from __future__ import annotations

from typing import Any

from rce.contract.base import OpArgs


class HandshakeHello(OpArgs):
    """(initiator) Version ``v`` of the handshake for ``purpose``, its ``nonce`` (hex) and ``key_id``."""
    OP = "hello"
    v: Any = None
    purpose: Any = None
    nonce: Any = None
    key_id: Any = None


class HandshakeChallenge(OpArgs):
    """(responder) Its ``nonce``, its ``proof`` of the key over both nonces, and its ``key_id``."""
    OP = "challenge"
    nonce: Any = None
    proof: Any = None
    key_id: Any = None


class HandshakeResponse(OpArgs):
    """(initiator) Its ``proof`` of the key."""
    OP = "response"
    proof: Any = None


class HandshakeOk(OpArgs):
    """(responder) The initiator is admitted."""
    OP = "ok"
