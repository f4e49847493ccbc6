"""The one HTTP/1.1 answer the engine writes by hand: a status, a body and ``Connection: close``
(the relay's refusal of a CONNECT, :mod:`rce_client.tunnel`; the ``/metrics`` endpoint,
:mod:`rce.plumbing.metrics_http`). RFC 9112, section 4 (status line) and 6 (message body)."""
from __future__ import annotations

from http import HTTPStatus

__all__ = ["closing_answer"]


def closing_answer(status: int, body: bytes, content_type: str) -> bytes:
    """Status line, ``Content-Type``, ``Content-Length`` and ``Connection: close`` headers, then
    ``body``: the whole answer to a request on a connection that closes after it."""
    return (f"HTTP/1.1 {status} {HTTPStatus(status).phrase}\r\nContent-Type: {content_type}\r\n"
            f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n").encode() + body
