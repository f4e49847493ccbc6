"""Values quoted in errors and logs, at a bounded cost: :func:`short_repr`; where a value was, as a key
path: :func:`key_path`.

Every layer names the bad value it refuses, and none echoes more than a short prefix of it (an
error message is not a copy of hostile input)."""
from __future__ import annotations

import reprlib

SHORT_REPR = 80                 # chars of a value an error message quotes (a tag, a type, a bad value)


def _short_repr() -> reprlib.Repr:
    r = reprlib.Repr()
    r.maxstring, r.maxother, r.maxlevel = SHORT_REPR, SHORT_REPR, 3
    r.maxlist = r.maxdict = r.maxtuple = r.maxset = 6
    return r


_REPR = _short_repr()


def short_repr(value: object) -> str:
    """``repr(value)`` cut short (strings and other values to about :data:`SHORT_REPR` chars, at most 6
    items of a container, 3 levels; at most twice :data:`SHORT_REPR` chars in all): what an error
    message quotes of a value, at a bounded cost."""
    r = _REPR.repr(value)
    return r if len(r) <= 2 * SHORT_REPR else r[:2 * SHORT_REPR] + "..."


def key_path(loc: tuple) -> str:
    """A pydantic error location as a key path: ``("CN", "data", "addNodes", 0)`` ->
    ``CN.data.addNodes[0]``."""
    out = ""
    for p in loc:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out
