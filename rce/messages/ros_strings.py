"""ROS 1 strings are bytes: the serializer must carry any bytes a ROS string holds.

ROS 1 does not say that a ``string`` field holds UTF-8; rospy nodes pass whatever bytes they are
given (genpy decodes with its own ``rosmsg`` error handler instead of failing). rosbags, whose
ROS 1 serializer rce uses, decodes and encodes strings as strict UTF-8, so a message holding
``b'\\xff'`` would not deserialize in a node at all. :func:`install` makes every ROS 1
(de)serializer rosbags generates from then on use ``surrogateescape`` (PEP 383): bytes that are
not UTF-8 become lone surrogates in the Python string and are encoded back to the very same
bytes, so a node that echoes a string echoes its bytes unchanged. JSON cannot carry such bytes:
a converter gives the robot the string with U+FFFD in their place (:func:`to_text`), as genpy's
``rosmsg`` handler does for rospy.

It works on the code rosbags generates (``rosbags.serde.ros1``: ``.decode()``/``.encode()`` of
string fields, compiled by ``compile_lines``); tests/core/test_core_node_bus.py checks it, so a
rosbags release that generates other code fails there, not silently in a node.
"""
from __future__ import annotations

import threading

import rosbags.serde.ros1 as _ros1

__all__ = ["ERRORS", "install", "to_text"]

ERRORS = "surrogateescape"
_DECODE, _ENCODE = ".decode()", ".encode()"
_lock = threading.Lock()


def _rewrite(lines: list[str]) -> list[str]:
    return [line.replace(_DECODE, f".decode('utf-8', '{ERRORS}')").replace(_ENCODE, f".encode('utf-8', '{ERRORS}')")
            for line in lines]


def install() -> None:
    """Make rosbags' ROS 1 (de)serializers carry any bytes in strings (idempotent; call it before
    the first message of a typestore is (de)serialized: rosbags caches what it generated)."""
    with _lock:
        compile_lines = _ros1.compile_lines
        if getattr(compile_lines, "rce_bytes_in_strings", False):
            return

        def compile_bytes_in_strings(lines: list[str]):
            return compile_lines(_rewrite(lines))

        compile_bytes_in_strings.rce_bytes_in_strings = True
        _ros1.compile_lines = compile_bytes_in_strings


def to_text(value: str) -> str:
    """``value`` as text JSON can carry: the bytes that were not UTF-8 (surrogate escapes) become
    U+FFFD REPLACEMENT CHARACTER. ASCII and valid text are returned as they are."""
    if value.isascii():
        return value
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:
        return value.encode("utf-8", ERRORS).decode("utf-8", "replace")
    return value
