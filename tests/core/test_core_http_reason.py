"""rce.plumbing.errors.http_reason: the one reader of an HTTP error body's reason (client login, the
admin-API client, the etcd client)."""
from rce.plumbing.errors import http_reason


def test_plain_text_gives_its_first_non_empty_line():
    assert http_reason(b"\n  unknown user 'x'\nmore\n") == "unknown user 'x'"


def test_json_gives_reason_message_or_error():
    assert http_reason('{"reason": "r", "message": "m"}') == "r"
    assert http_reason(b'{"error": {"message": "etcdserver: key not found"}}') == "etcdserver: key not found"
    assert http_reason('{"code": 5, "message": "lease not found"}') == "lease not found"


def test_fallback_and_limit():
    assert http_reason(b"", "HTTP 503") == "HTTP 503"
    assert http_reason("x" * 500, limit=300) == "x" * 300
