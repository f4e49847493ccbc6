"""A small asyncio client of etcd's v3 API through its JSON gateway, for the master's state on
etcd (:mod:`rce_master.state.etcd_store`) and the election of a leader (:mod:`rce_master.leadership.election`).

The gateway (etcd 3.4, Debian's ``etcd-server``) maps each gRPC call of ``etcdserverpb/rpc.proto``
to ``POST /v3/<service>/<call>`` with the request as JSON
(https://etcd.io/docs/v3.4/dev-guide/api_grpc_gateway/): keys and values are base64, 64-bit
integers are decimal strings, and fields at their default value (``false``, ``0``, the event type
``PUT``) are left out of answers. A streaming call (watch) answers newline-separated
``{"result": ...}`` objects.

Why not a library: ``etcd3`` is unmaintained and pins an old protobuf; the gRPC clients pull in
grpcio and generated code for the six calls used here (range, txn, lease grant, keepalive and
revoke, watch), each a plain JSON POST over aiohttp (already a dependency).

``etcd://HOST:PORT[,HOST:PORT...][/PREFIX/][?max-txn-ops=N]`` names the endpoints (plain HTTP),
the key prefix (default ``/rce/``) and the largest transaction the server takes (etcd's
``--max-txn-ops``, default 128): :func:`parse_url`. A request goes to the endpoint that answered
last, then to the others in turn; an endpoint that does not answer within ``timeout`` counts as
unreachable.
"""
from __future__ import annotations

import asyncio
import base64
import json
from collections.abc import AsyncIterator
from dataclasses import dataclass
from urllib.parse import parse_qs, urlsplit

import aiohttp

from rce.plumbing.errors import ConfigError, RCEError, Unavailable, http_reason

SCHEME = "etcd"
DEFAULT_PREFIX = "/rce/"
DEFAULT_MAX_TXN_OPS = 128           # etcd's default --max-txn-ops: operations in one transaction
MAX_REQUEST_BYTES = 1536 * 1024     # bytes, etcd's default --max-request-bytes (1.5 MiB): one request's size
REQUEST_TIMEOUT = 2.0               # s, one unary request (range, txn, lease): etcd answers in ms; an endpoint
#                                     that takes longer is treated as unreachable and the next one is tried
ETCD_REASON = 300                   # chars of an etcd error body kept in our error
MAX_WATCH_MESSAGE = 64 * 1024 * 1024   # bytes, one watch answer (a line of JSON): a longer one breaks the watch


class EtcdUnavailable(Unavailable):
    """No etcd endpoint answered (refused, reset, or silent for the request's timeout)."""


class EtcdRefused(RCEError):
    """etcd answered a request with an error (a transaction too large, a malformed request)."""

    code = "etcd"


class Compacted(RCEError):
    """A watch asked for revisions etcd has compacted away: read everything again."""

    code = "etcd_compacted"


@dataclass(frozen=True)
class StoreUrl:
    """A parsed ``--store etcd://...``: ``endpoints`` (``http://HOST:PORT``), key ``prefix`` (ends with
    ``/``), ``max_txn_ops`` (the server's ``--max-txn-ops``)."""
    endpoints: tuple[str, ...]
    prefix: str = DEFAULT_PREFIX
    max_txn_ops: int = DEFAULT_MAX_TXN_OPS


def parse_url(url: str) -> StoreUrl:
    """The endpoints, prefix and limits of ``etcd://HOST:PORT[,HOST:PORT...][/PREFIX/][?max-txn-ops=N]``.
    Raises :class:`ConfigError` naming what is wrong."""
    parts = urlsplit(url)
    if parts.scheme != SCHEME:
        raise ConfigError(f"--store {url!r}: expected etcd://HOST:PORT[,HOST:PORT...][/PREFIX/]")
    endpoints = []
    for hp in parts.netloc.split(","):
        host, _, port = hp.strip().rpartition(":")
        if not host or not port.isdigit():
            raise ConfigError(f"--store {url!r}: endpoint {hp!r} is not HOST:PORT")
        endpoints.append(f"http://{host}:{port}")
    prefix = parts.path if parts.path not in ("", "/") else DEFAULT_PREFIX
    if not prefix.endswith("/"):
        prefix += "/"
    query = parse_qs(parts.query)
    ops = query.pop("max-txn-ops", [str(DEFAULT_MAX_TXN_OPS)])[-1]
    if query:
        raise ConfigError(f"--store {url!r}: unknown option(s) {', '.join(sorted(query))} (known: max-txn-ops)")
    if not ops.isdigit() or int(ops) < 2:
        raise ConfigError(f"--store {url!r}: max-txn-ops must be an integer >= 2, got {ops!r}")
    return StoreUrl(tuple(endpoints), prefix, int(ops))


def b64(data: bytes | str) -> str:
    """Base64 of ``data`` (str: its UTF-8), as the gateway wants keys and values."""
    return base64.b64encode(data.encode() if isinstance(data, str) else data).decode()


def unb64(text: str | None) -> bytes:
    """The bytes of a base64 field of an answer (absent: empty)."""
    return base64.b64decode(text or "")


def range_end(prefix: bytes) -> bytes:
    """The ``range_end`` that makes a range or watch cover every key starting with ``prefix``
    (the prefix with its last byte incremented, as etcd's clientv3.GetPrefixRangeEnd)."""
    end = bytearray(prefix)
    while end:
        if end[-1] < 0xFF:
            end[-1] += 1
            return bytes(end)
        end.pop()
    return b"\0"                    # every key


class EtcdClient:
    """The gateway of the etcd cluster at ``endpoints`` (``http://HOST:PORT``).

    Every call raises :class:`EtcdUnavailable` when no endpoint answered and :class:`EtcdRefused`
    when etcd refused the request. Close with :meth:`close`."""

    def __init__(self, endpoints: tuple[str, ...] | list[str], *, timeout: float = REQUEST_TIMEOUT):
        if not endpoints:
            raise ConfigError("etcd: no endpoint given")
        self.endpoints = list(endpoints)
        self.timeout = timeout
        self._current = 0
        self._session: aiohttp.ClientSession | None = None

    def _http(self) -> aiohttp.ClientSession:
        if self._session is None:
            self._session = aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=None))
        return self._session

    async def close(self) -> None:
        """Close the HTTP connections."""
        if self._session is not None:
            await self._session.close()
            self._session = None

    def _order(self) -> list[str]:
        n = len(self.endpoints)
        return [self.endpoints[(self._current + i) % n] for i in range(n)]

    async def call(self, path: str, body: dict, *, timeout: float | None = None) -> dict:
        """POST ``body`` to ``path`` (``/v3/kv/range``, ...) on the first endpoint that answers; its JSON."""
        timeout = self.timeout if timeout is None else timeout
        why = []
        for endpoint in self._order():
            try:
                async with self._http().post(endpoint + path, json=body,
                                             timeout=aiohttp.ClientTimeout(total=timeout)) as r:
                    status, data = r.status, await r.read()
            except (aiohttp.ClientError, OSError) as e:        # OSError: TimeoutError too
                why.append(f"{endpoint}: {type(e).__name__} {e}".strip())
                continue
            if status >= 500:
                why.append(f"{endpoint}: HTTP {status} {http_reason(data, limit=ETCD_REASON)}")
                continue
            self._current = self.endpoints.index(endpoint)
            if status >= 400:
                reason = http_reason(data, limit=ETCD_REASON)
                raise EtcdRefused(f"etcd {endpoint} refused {path}: HTTP {status}: {reason}")
            return json.loads(data or b"{}")
        raise EtcdUnavailable(f"etcd {path}: no endpoint answered ({'; '.join(why)})")

    # -- kv ------------------------------------------------------------------------------------------
    async def range(self, key: bytes, end: bytes | None = None, *, limit: int = 0,
                    at: int = 0) -> tuple[int, list[dict], bool]:
        """The keys in ``[key, end)`` (only ``key`` when ``end`` is None), at most ``limit`` of them
        (0: all), at revision ``at`` (0: the latest): ``(revision, kvs, more)``. Each kv has ``key``
        and ``value`` as bytes and ``create_revision``, ``mod_revision`` and ``lease`` as ints."""
        body: dict = {"key": b64(key)}
        if end is not None:
            body["range_end"] = b64(end)
        if limit:
            body["limit"] = str(limit)
        if at:
            body["revision"] = str(at)
        r = await self.call("/v3/kv/range", body)
        return revision(r), [kv(x) for x in r.get("kvs", [])], bool(r.get("more"))

    async def txn(self, compare: list[dict], success: list[dict], failure: list[dict] = ()) -> dict:
        """One transaction (gateway JSON of its parts); the answer (``succeeded`` is False when absent)."""
        r = await self.call("/v3/kv/txn", {"compare": compare, "success": success, "failure": list(failure)})
        r["succeeded"] = bool(r.get("succeeded"))
        return r

    # -- leases --------------------------------------------------------------------------------------
    async def lease_grant(self, ttl: int) -> int:
        """A new lease of ``ttl`` s (etcd may raise it to its minimum); its id."""
        r = await self.call("/v3/lease/grant", {"TTL": str(ttl)})
        if r.get("error"):
            raise EtcdRefused(f"etcd refused a lease: {r['error']}")
        return int(r["ID"])

    async def lease_keepalive(self, lease: int, *, timeout: float | None = None) -> int:
        """Renew ``lease``; its TTL (s) from now, 0 when it has expired or was revoked."""
        r = await self.call("/v3/lease/keepalive", {"ID": str(lease)}, timeout=timeout)
        return int((r.get("result") or {}).get("TTL", 0))

    async def lease_revoke(self, lease: int) -> None:
        """End ``lease`` now: its keys are deleted."""
        await self.call("/v3/lease/revoke", {"ID": str(lease)})

    # -- watch ---------------------------------------------------------------------------------------
    async def watch(self, key: bytes, end: bytes | None, start_revision: int, *,
                    idle: float) -> AsyncIterator[dict]:
        """Yield each watch answer for ``[key, end)`` from ``start_revision`` on (``{"header",
        "events": [...]}``, events as :func:`event`). Ends after ``idle`` s without an answer (a
        silent network looks like a quiet cluster: the caller looks again). Raises
        :class:`EtcdUnavailable` when the stream cannot open or breaks, :class:`Compacted` when
        ``start_revision`` is gone."""
        create = {"key": b64(key), "start_revision": str(start_revision), "prev_kv": False}
        if end is not None:
            create["range_end"] = b64(end)
        endpoint = self._order()[0]
        try:
            async with self._http().post(endpoint + "/v3/watch", json={"create_request": create},
                                         timeout=aiohttp.ClientTimeout(total=None, connect=self.timeout)) as r:
                if r.status != 200:
                    reason = http_reason(await r.read(), limit=ETCD_REASON)
                    raise EtcdUnavailable(f"etcd {endpoint} watch: HTTP {r.status} {reason}")
                async for message in _lines(r.content, idle):
                    result = message.get("result")
                    if result is None:
                        reason = http_reason(json.dumps(message), limit=ETCD_REASON)
                        raise EtcdUnavailable(f"etcd {endpoint} watch: {reason}")
                    if result.get("compact_revision") and result["compact_revision"] != "0":
                        raise Compacted(f"etcd {endpoint}: revision {start_revision} is compacted "
                                        f"(oldest kept {result['compact_revision']})")
                    if result.get("canceled"):
                        raise EtcdUnavailable(f"etcd {endpoint} canceled the watch: {result.get('cancel_reason', '')}")
                    result["events"] = [event(e) for e in result.get("events", [])]
                    yield result
        except (aiohttp.ClientError, OSError) as e:
            self._current = (self.endpoints.index(endpoint) + 1) % len(self.endpoints)
            raise EtcdUnavailable(f"etcd {endpoint} watch broke: {type(e).__name__} {e}".strip()) from None


async def _lines(content: aiohttp.StreamReader, idle: float) -> AsyncIterator[dict]:
    """The JSON objects of a newline-separated stream, until it ends or is silent ``idle`` s."""
    buf = b""
    while True:
        try:
            async with asyncio.timeout(idle):
                chunk = await content.readany()
        except TimeoutError:
            return
        if not chunk:
            return
        buf += chunk
        if len(buf) > MAX_WATCH_MESSAGE:
            raise EtcdUnavailable(f"etcd watch: an answer is over {MAX_WATCH_MESSAGE} bytes")
        *lines, buf = buf.split(b"\n")
        for line in lines:
            if line.strip():
                yield json.loads(line)


def revision(answer: dict) -> int:
    """The store revision in an answer's header."""
    return int((answer.get("header") or {}).get("revision", 0))


def kv(kv: dict) -> dict:
    """A gateway KeyValue with its key and value decoded and its numbers as ints."""
    return {"key": unb64(kv.get("key")), "value": unb64(kv.get("value")),
            "create_revision": int(kv.get("create_revision", 0)), "mod_revision": int(kv.get("mod_revision", 0)),
            "lease": int(kv.get("lease", 0))}


def event(event: dict) -> dict:
    """A watch event: ``{"type": "PUT"|"DELETE", "kv": kv}``."""
    return {"type": event.get("type", "PUT"), "kv": kv(event.get("kv") or {})}
