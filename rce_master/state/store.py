"""The store under the master's state (docs/design.md, section 8.1): every change to
:class:`~rce_master.state.master_state.MasterState` passes through it as records put and deleted by key.

- A **key** is a tuple of strings whose first element names the kind of record:
  ``("user", name)``, ``("taskset", tid)``, ``("robot", user, robot)``,
  ``("container", user, ctag)``, ``("node", user, ctag, ntag)``, ``("param", user, ctag, name)``,
  ``("interface", user, etag, itag)``, ``("connection", user, iid_a, iid_b)``, ``("counter", name)``
  (the master's id counters). Ids in keys are decimal strings.
- A **record** is a JSON object (dict); the shapes are those of ``to_record`` in
  :mod:`rce_master.state.model`. The records alone rebuild the whole state (:class:`MasterState`
  built on a store loads it).
- Changes arrive in **batches** (:meth:`Store.commit`): one state operation (a request's step,
  or its undo) is one batch, applied all or nothing. This module has the in-memory store; the
  file store is :class:`rce_master.state.sqlite_store.SqliteStore`, the replicated one
  :class:`rce_master.state.etcd_store.EtcdStore`.
- A commit may return before its batch is durable (etcd: written behind, in order):
  :meth:`Store.flush` waits until it is. The master awaits it before it answers a request.
"""
from __future__ import annotations

import json
from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator

from rce.plumbing.errors import RequestError

Key = tuple[str, ...]
Change = tuple[Key, "dict | None"]        # (key, record), or (key, None) to delete


class Store(ABC):
    """Records by key. Implementations keep records as JSON: what :meth:`get` returns is a copy."""

    @abstractmethod
    def get(self, key: Key) -> dict | None:
        """The record at ``key``, or None."""

    @abstractmethod
    def items(self, kind: str | None = None) -> Iterator[tuple[Key, dict]]:
        """Every ``(key, record)`` (of one ``kind`` when given), in key order."""

    @abstractmethod
    def commit(self, changes: Iterable[Change]) -> None:
        """Apply a batch of puts (record) and deletes (None) in order, all or nothing.
        Raises :class:`RequestError` for a record that is not JSON."""

    async def flush(self) -> None:  # noqa: B027 (a store whose commits are durable at once has nothing to wait for)
        """Return once every batch committed so far is durable. Raises :class:`~rce.plumbing.errors.Unavailable`
        when one never will be (the store failed). Nothing to wait for in memory or SQLite."""

    def close(self) -> None:  # noqa: B027 (a store that holds nothing needs no close)
        """Release what the store holds (a file, its lock); nothing for the memory store."""

    def __enter__(self) -> "Store":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def encode(key: Key, record: dict) -> str:
    """The JSON text of ``record``; raises :class:`RequestError` naming ``key`` when it is not JSON."""
    try:
        return json.dumps(record, allow_nan=False, separators=(",", ":"))
    except (TypeError, ValueError) as e:
        raise RequestError(f"record {'/'.join(key)} is not JSON: {e}") from None


def stage(changes: Iterable[Change]) -> list[tuple[Key, str | None]]:
    """A batch with keys as tuples and records as JSON text (None: delete): every record encodes,
    or :func:`encode` raises and nothing of the batch lands."""
    return [(tuple(k), None if r is None else encode(k, r)) for k, r in changes]


class MemoryStore(Store):
    """The store in memory (``rce-master`` without ``--state``): lost when the master exits.

    ``MemoryStore(other.items())`` copies another store's records."""

    def __init__(self, records: Iterable[tuple[Key, dict]] = ()):
        self._data: dict[Key, str] = {}
        self.commit(records)

    def __len__(self) -> int:
        return len(self._data)

    def get(self, key: Key) -> dict | None:
        text = self._data.get(tuple(key))
        return None if text is None else json.loads(text)

    def items(self, kind: str | None = None) -> Iterator[tuple[Key, dict]]:
        for key in sorted(self._data):
            if kind is None or key[0] == kind:
                yield key, json.loads(self._data[key])

    def commit(self, changes: Iterable[Change]) -> None:
        self._apply_texts(stage(changes))

    def _apply_texts(self, staged: list[tuple[Key, str | None]]) -> None:
        """Put (JSON text) and delete (None) records that :func:`stage` encoded."""
        for key, text in staged:
            if text is None:
                self._data.pop(key, None)
            else:
                self._data[key] = text
