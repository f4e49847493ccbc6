"""A request body of the fleet's HTTP API: JSON under the engine's bounds, then the operation's model.

:func:`parse_body` (sans I/O) takes the raw bytes (the web server has already refused a body over its size limit with
413) and returns the JSON value, or raises :class:`BodyError` naming what was wrong and where, never echoing
the body. Refused, each with a 400 and no cost beyond a linear scan:

- a body that is not UTF-8 (RFC 8259 section 8.1), or is empty;
- nesting deeper than :data:`~rce.protocol.limits.MAX_JSON_DEPTH` (64) levels, found by
  :func:`~rce.protocol.limits.json_too_deep` before any parser recurses (Python's ``json`` raised
  RecursionError past about 1,000);
- a lone surrogate escape (``"\\ud800"``: no Unicode character, so no UTF-8 can carry it on; RFC 8259
  section 8.2 leaves it to the parser) and any other malformed JSON, by orjson (which refuses both);
- a number that does not fit a double (orjson reads an integer beyond 64 bits as a double; a 5,000-digit
  one is infinite). Python's ``json`` instead raised ValueError past 4,300 digits, which was not a
  JSONDecodeError.

:func:`read_model` reads an aiohttp request's body, parses it so, and validates it with the operation's
pydantic model (:mod:`rce_fleet.operations.api_models`): every refusal is an
:class:`~rce_fleet.operations.api_errors.ApiRefusal` 400 whose text names the field and why, from the
model's ``hints`` where it has one, and quotes no more than a short prefix of anything the client sent.
"""
from __future__ import annotations

import orjson
from aiohttp import web
from pydantic import BaseModel, ValidationError

from rce.protocol.limits import MAX_JSON_DEPTH, json_too_deep, short_repr, truncate

from .api_errors import ApiRefusal

__all__ = ["BodyError", "parse_body", "read_model"]

MAX_REASON = 160        # bytes of the parser's own reason kept (it names a position, never the input)
MAX_NAMED = 5           # unknown fields a refusal names at most


class BodyError(ValueError):
    """A body that is not JSON the API takes; the message says why and where."""


def parse_body(raw: bytes) -> object:
    """The JSON value of ``raw``; raises :class:`BodyError` (module docstring)."""
    if not raw.strip():
        raise BodyError("the body is empty: it must be a JSON object")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise BodyError(f"the body is not UTF-8 (byte {e.start} of {len(raw)})") from None
    if json_too_deep(text, MAX_JSON_DEPTH):
        raise BodyError(f"the body nests arrays and objects deeper than {MAX_JSON_DEPTH} levels")
    try:
        return orjson.loads(raw)
    except orjson.JSONDecodeError as e:
        raise BodyError(f"the body is not JSON the API takes: {truncate(str(e), MAX_REASON)}") from None


async def read_model(req: web.Request, model: type[BaseModel]) -> BaseModel:
    """``req``'s body as ``model``; raises :class:`~rce_fleet.operations.api_errors.ApiRefusal` 400 naming what
    was wrong (aiohttp has refused a body over its limit with 413 as it read it)."""
    try:
        body = parse_body(await req.read())
    except BodyError as e:
        raise ApiRefusal(400, "bad_request", str(e)) from None
    if not isinstance(body, dict):
        raise ApiRefusal(400, "bad_request", "the body must be a JSON object")
    try:
        return model.model_validate(body)
    except ValidationError as e:
        raise ApiRefusal(400, "bad_request", why(e, model)) from None


def why(e: ValidationError, model: type[BaseModel]) -> str:
    """One line on what ``e`` found wrong in a body for ``model``: the unknown fields (at most
    :data:`MAX_NAMED`, each cut short), else the first wrong field with the model's hint for it
    (``model.hints``, a dict field -> text) or pydantic's message (which quotes no input)."""
    errs = e.errors()
    if unknown := sorted(str(x["loc"][0]) for x in errs if x["type"] == "extra_forbidden"):
        more = f" and {len(unknown) - MAX_NAMED} more" if len(unknown) > MAX_NAMED else ""
        return (f"unknown field(s) {', '.join(map(short_repr, unknown[:MAX_NAMED]))}{more} "
                f"(a {getattr(model, 'kind', 'request')} has {', '.join(model.model_fields)})")
    field = str(errs[0]["loc"][0]) if errs[0]["loc"] else ""
    hint = getattr(model, "hints", {}).get(field)
    if hint:
        return hint
    return f"{field}: {errs[0]['msg'].lower()}" if field else errs[0]["msg"]
