"""JSON text of the client protocols (RCE frames, rosbridge ops), read and written fast, sans I/O.

orjson does the work (RFC 8259; about 7x the stdlib's ``json`` reading a pose's numbers, 10x
writing them); what orjson refuses the stdlib does, so nothing a client could send before is
refused now and nothing the engine could write before fails:

- :func:`loads` takes the ``NaN``/``Infinity`` tokens Python's ``json`` writes, and a malformed
  text's error names its line and column (the stdlib's ``JSONDecodeError``). Integers are exact
  from -2**63 to 2**64 - 1 (every ROS integer type); orjson reads one past that as a float, which
  no ROS integer field takes (:mod:`rce.messages` takes a float for an integer only when it is
  integral and at most 2**53, where floats are exact).
- :func:`dumps` writes compact JSON (no spaces), non-ASCII text as UTF-8 rather than ``\\u``
  escapes; a string with a lone surrogate, an integer past 64 bits or a key that is not a string
  goes through the stdlib. Non-finite floats become ``null`` (converters write them so already, as
  rosbridge does).
"""
from __future__ import annotations

import json
from typing import Any

import orjson

# json.dumps(obj, separators=(",", ":")), without building an encoder per call (json.dumps does, given any option)
_compact_json = json.JSONEncoder(separators=(",", ":")).encode


def loads(text: str | bytes) -> Any:
    """The value of JSON ``text``. Raises ``ValueError`` (the stdlib's ``JSONDecodeError``, with line
    and column) and ``RecursionError`` as ``json.loads``."""
    try:
        return orjson.loads(text)
    except orjson.JSONDecodeError:
        return json.loads(text)


def dumps(obj: Any) -> str:
    """Compact JSON text of ``obj``. Raises ``TypeError`` for what neither encoder takes (``bytes``
    among them)."""
    try:
        return orjson.dumps(obj).decode()
    except TypeError:
        return _compact_json(obj)
