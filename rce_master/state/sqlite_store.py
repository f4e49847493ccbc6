"""The master's state in one SQLite file (``rce-master --state PATH``): the embedded
:class:`~rce_master.state.store.Store` a master restarts from (docs/design.md, section 8.1).

- One table, ``records(key TEXT PRIMARY KEY, kind TEXT, record TEXT)``: ``key`` is the store key
  as a JSON array of strings, ``kind`` its first element, ``record`` the record's JSON text.
  ``PRAGMA user_version`` holds the layout version (:data:`LAYOUT`); a file of another layout is
  refused, never rewritten.
- Journal: WAL (https://sqlite.org/wal.html) with ``synchronous=NORMAL``. Every commit is in the
  WAL, in the operating system's hands, before :meth:`SqliteStore.commit` returns, so a master that
  dies (kill -9 included) loses nothing it committed. Only an OS crash or a power cut can lose
  the last commits (the file stays consistent, https://sqlite.org/pragma.html#pragma_synchronous):
  the containers, nodes and robots they recorded come back in the task sets' reports when they
  re-register (docs/INTERNALS.md, "Master state and restart"); a user added in that last moment
  must be added again. ``FULL`` would add an fsync to every commit, spent on the event
  loop's thread. Measured on the development VM (2 cores, virtio disk), a commit of two records:
  NORMAL median 40 us, p99 0.2 ms; FULL median 0.48 ms, p99 1 ms. A whole operation
  (``MasterState.add_container``) 85 us median with NORMAL against 28 us in memory.
- Checkpoints (copying the WAL back into the file, with an fsync) are the one slow step, up to
  ~100 ms on a busy disk: SQLite's automatic checkpoint, which would run inside a commit, is off,
  and a thread of the store's own (:class:`_Checkpointer`, its own connection) runs them at most
  every :data:`CHECKPOINT_INTERVAL` s after commits. Writers never wait for it (WAL).
- Each :meth:`SqliteStore.commit` is one transaction (``BEGIN IMMEDIATE`` ... ``COMMIT``).
- One master per file: an exclusive ``flock(2)`` on ``PATH.lock`` beside it, held while the store is
  open; a second opener is refused with a :class:`ConfigError` naming the file and the holder's pid.
"""
from __future__ import annotations

import fcntl
import json
import os
import sqlite3
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path

from rce.plumbing.errors import ConfigError, Unavailable
from rce_master.state.store import Change, Key, Store, encode

LAYOUT = 1                 # PRAGMA user_version of the layout this module writes
SYNCHRONOUS = "NORMAL"     # see the module docstring: nothing committed is lost when the master dies
BUSY_TIMEOUT_MS = 2000     # ms SQLite waits on a lock held by another connection (the checkpointer, a reader)
CHECKPOINT_INTERVAL = 1.0  # s, at most one checkpoint this often, off the event loop: bounds the WAL to ~1 s of commits


class SqliteStore(Store):
    """The records in the SQLite file ``path`` (created with its directory, mode 0700, if absent).

    Raises :class:`ConfigError` when another process holds the file, or when it is not an rce
    state file of this layout. A failed commit raises :class:`Unavailable` naming the file and
    leaves the file as it was."""

    def __init__(self, path: str | os.PathLike, *, synchronous: str = SYNCHRONOUS):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        self.lock_path = self.path.with_name(self.path.name + ".lock")
        self._lock_fd: int | None = _lock(self.lock_path, self.path)
        try:
            self._db = sqlite3.connect(self.path, isolation_level=None)   # transactions are ours: BEGIN/COMMIT
            self._setup(synchronous)
            self._checkpointer = _Checkpointer(self.path)
        except sqlite3.Error as e:
            self.close()
            raise ConfigError(f"state file {self.path}: {e}") from None
        except BaseException:
            self.close()
            raise

    def _setup(self, synchronous: str) -> None:
        db = self._db
        db.execute(f"PRAGMA busy_timeout = {BUSY_TIMEOUT_MS}")
        mode = db.execute("PRAGMA journal_mode = WAL").fetchone()[0]
        if mode.lower() != "wal":
            raise ConfigError(f"state file {self.path}: SQLite refused WAL mode (journal mode {mode!r})")
        if synchronous.upper() not in ("NORMAL", "FULL", "EXTRA"):
            raise ConfigError(f"state file {self.path}: synchronous must be NORMAL, FULL or EXTRA, got {synchronous!r}")
        db.execute(f"PRAGMA synchronous = {synchronous.upper()}")
        db.execute("PRAGMA wal_autocheckpoint = 0")          # the checkpointer thread does them
        version = db.execute("PRAGMA user_version").fetchone()[0]
        if version == 0:
            db.execute("CREATE TABLE IF NOT EXISTS records "
                       "(key TEXT PRIMARY KEY, kind TEXT NOT NULL, record TEXT NOT NULL) WITHOUT ROWID")
            db.execute(f"PRAGMA user_version = {LAYOUT}")
        elif version != LAYOUT:
            raise ConfigError(f"state file {self.path} has layout {version}; this rce-master reads layout {LAYOUT}")

    def close(self) -> None:
        """Stop the checkpointer, close the file and release its lock (idempotent)."""
        checkpointer = getattr(self, "_checkpointer", None)
        if checkpointer is not None:
            checkpointer.stop()
            self._checkpointer = None
        db = getattr(self, "_db", None)
        if db is not None:
            db.close()
            self._db = None
        if self._lock_fd is not None:
            os.close(self._lock_fd)            # releases the flock
            self._lock_fd = None

    def get(self, key: Key) -> dict | None:
        row = self._db.execute("SELECT record FROM records WHERE key = ?", (_key_text(key),)).fetchone()
        return None if row is None else json.loads(row[0])

    def items(self, kind: str | None = None) -> Iterator[tuple[Key, dict]]:
        if kind is None:
            rows = self._db.execute("SELECT key, record FROM records").fetchall()
        else:
            rows = self._db.execute("SELECT key, record FROM records WHERE kind = ?", (kind,)).fetchall()
        for key, text in sorted((tuple(json.loads(k)), t) for k, t in rows):
            yield key, json.loads(text)

    def commit(self, changes: Iterable[Change]) -> None:
        staged = [(_key_text(k), k[0], None if r is None else encode(k, r)) for k, r in changes]
        if not staged:
            return
        db = self._db
        try:
            db.execute("BEGIN IMMEDIATE")
            try:
                for key, kind, text in staged:
                    if text is None:
                        db.execute("DELETE FROM records WHERE key = ?", (key,))
                    else:
                        db.execute("INSERT OR REPLACE INTO records (key, kind, record) VALUES (?, ?, ?)",
                                   (key, kind, text))
                db.execute("COMMIT")
            except BaseException:
                db.execute("ROLLBACK")
                raise
        except sqlite3.Error as e:
            raise Unavailable(f"state file {self.path}: the batch was not stored: {e}") from None
        self._checkpointer.poke()

    def __len__(self) -> int:
        return self._db.execute("SELECT count(*) FROM records").fetchone()[0]


class _Checkpointer:
    """A thread with its own connection to ``path`` that checkpoints the WAL (``PRAGMA
    wal_checkpoint(PASSIVE)``: it waits for no reader or writer) after :meth:`poke`, at most every
    ``interval`` s. A failed checkpoint is retried on the next poke: the WAL only grows meanwhile."""

    def __init__(self, path: Path, interval: float = CHECKPOINT_INTERVAL):
        self.path, self.interval = path, interval
        self.failures = 0                        # checkpoints that raised (counted, retried)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"checkpoint {path.name}", daemon=True)
        self._thread.start()

    def poke(self) -> None:
        """There are new commits in the WAL."""
        self._wake.set()

    def stop(self) -> None:
        """Checkpoint what is left and end the thread."""
        self._stop.set()
        self._wake.set()
        self._thread.join()

    def _run(self) -> None:
        db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        db.execute(f"PRAGMA busy_timeout = {BUSY_TIMEOUT_MS}")
        try:
            while True:
                self._wake.wait()
                self._wake.clear()
                try:
                    db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
                except sqlite3.Error:
                    self.failures += 1
                if self._stop.is_set():
                    return
                self._stop.wait(self.interval)              # coalesce: at most one per interval
        finally:
            db.close()


def _key_text(key: Key) -> str:
    return json.dumps([str(k) for k in key], separators=(",", ":"))


def _lock(lock_path: Path, path: Path) -> int:
    """Hold an exclusive flock on ``lock_path`` (writing our pid into it); returns its fd.
    Raises :class:`ConfigError` naming ``path`` and the holder's pid when another process has it."""
    fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
        os.close(fd)
        raise ConfigError(f"state file {path} is in use by another rce-master (pid {holder}, lock {lock_path}); "
                          "stop that master or give this one another --state") from None
    except BaseException:
        os.close(fd)
        raise
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd
