"""rce_master.state.sqlite_store: the master's state in one SQLite file. Records and batches behave
as in the memory store; a batch is one transaction (all or nothing, also when SQLite fails half
way); the file reopens with the same records, also after its writer was killed with SIGKILL; one
master per file (the lock refuses a second opener and is released when the holder dies)."""
from __future__ import annotations

import fcntl
import math
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest

from rce.plumbing.errors import ConfigError, RequestError, Unavailable
from rce_master.state.sqlite_store import LAYOUT, SqliteStore
from rce_master.state.store import MemoryStore

U = "alice"


@pytest.fixture
def path(tmp_path: Path) -> Path:
    return tmp_path / "state" / "master.sqlite3"


@pytest.fixture
def store(path: Path):
    with SqliteStore(path) as s:
        yield s


def test_put_get_delete_and_key_order(store):
    store.commit([(("container", U, "c2"), {"cid": 2}), (("container", U, "c1"), {"cid": 1}),
                  (("user", U), {"name": U}), (("container", U, "c1x"), {"cid": 3})])
    assert store.get(("container", U, "c1")) == {"cid": 1} and store.get(("container", U, "nope")) is None
    # key order is tuple order, as in the memory store (not the order of the keys' JSON text)
    assert [k for k, _ in store.items()] == [("container", U, "c1"), ("container", U, "c1x"),
                                            ("container", U, "c2"), ("user", U)]
    assert [k for k, _ in store.items("user")] == [("user", U)]
    store.commit([(("container", U, "c1"), None), (("container", U, "c2"), {"cid": 22}),
                  (("container", U, "nope"), None)])                       # delete, replace, delete nothing
    assert dict(store.items("container")) == {("container", U, "c1x"): {"cid": 3}, ("container", U, "c2"): {"cid": 22}}
    assert len(store) == 3


def test_records_are_copies(store):
    rec = {"data": {"cpu": 1}}
    store.commit([(("container", U, "c"), rec)])
    rec["data"]["cpu"] = 99
    store.get(("container", U, "c"))["data"]["cpu"] = 7
    assert store.get(("container", U, "c")) == {"data": {"cpu": 1}}


@pytest.mark.parametrize("bad", [{"v": object()}, {"v": math.nan}, {"v": {1, 2}}])
def test_a_record_that_is_not_json_stores_nothing_of_its_batch(store, bad):
    store.commit([(("user", U), {"name": U})])
    with pytest.raises(RequestError, match="record param/alice/c/p is not JSON"):
        store.commit([(("user", U), None), (("param", U, "c", "p"), bad)])
    assert dict(store.items()) == {("user", U): {"name": U}}


def test_a_batch_sqlite_refuses_half_way_stores_nothing(store, path):
    store.commit([(("user", U), {"name": U})])
    # a trigger makes SQLite fail on the batch's third change, after two have been written
    with sqlite3.connect(path) as db:
        db.execute("""CREATE TRIGGER refuse BEFORE INSERT ON records WHEN NEW.kind = 'boom'
                      BEGIN SELECT RAISE(ABORT, 'disk says no'); END""")
    with pytest.raises(Unavailable, match=r"master\.sqlite3: the batch was not stored: disk says no"):
        store.commit([(("user", U), None), (("user", "bob"), {"name": "bob"}), (("boom",), {})])
    assert dict(store.items()) == {("user", U): {"name": U}}
    store.commit([(("user", "bob"), {"name": "bob"})])                  # the store works on
    assert len(store) == 2


def test_reopen_gives_the_same_records(path):
    records = [(("user", U), {"name": U, "salt": "00", "scrypt": "11"}), (("counter", "cid"), {"next": 7}),
               (("param", U, "c", "/a b"), {"value": {"x": [1, None, "é"]}}), (("connection", U, "1", "2"), {})]
    with SqliteStore(path) as s:
        s.commit(records)
        s.commit([(("counter", "cid"), {"next": 8})])
    with SqliteStore(path) as s:
        assert dict(s.items()) == {**dict(records), ("counter", "cid"): {"next": 8}}
        assert dict(s.items()) == dict(MemoryStore(s.items()).items())


def test_a_killed_writer_loses_nothing_it_committed_and_releases_the_lock(path):
    code = ("import os, sys; from rce_master.state.sqlite_store import SqliteStore\n"
            "s = SqliteStore(sys.argv[1])\n"
            "for i in range(50): s.commit([(('node', 'u', 'c', str(i)), {'i': i}), (('counter', 'n'), {'next': i})])\n"
            "os.kill(os.getpid(), 9)\n")
    p = subprocess.run([sys.executable, "-c", code, str(path)], timeout=60)
    assert p.returncode == -9
    with SqliteStore(path) as s:
        assert len(list(s.items("node"))) == 50 and s.get(("counter", "n")) == {"next": 49}


def test_a_second_opener_is_refused_until_the_first_closes(store, path):
    with pytest.raises(ConfigError) as ei:
        SqliteStore(path)
    msg = str(ei.value)
    assert str(path) in msg and f"pid {os.getpid()}" in msg and "another rce-master" in msg
    # another process is refused too
    code = "import sys; from rce_master.state.sqlite_store import SqliteStore; SqliteStore(sys.argv[1])"
    p = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=60)
    assert p.returncode != 0 and "is in use by another rce-master" in p.stderr
    store.close()
    store.close()                                          # idempotent
    with SqliteStore(path) as again:
        assert len(again) == 0


def test_a_file_of_another_layout_or_not_a_database_is_refused(tmp_path):
    other = tmp_path / "other.sqlite3"
    with sqlite3.connect(other) as db:
        db.execute(f"PRAGMA user_version = {LAYOUT + 1}")
    with pytest.raises(ConfigError, match=f"has layout {LAYOUT + 1}; this rce-master reads layout {LAYOUT}"):
        SqliteStore(other)
    junk = tmp_path / "junk.sqlite3"
    junk.write_bytes(b"not a database at all" * 100)
    with pytest.raises(ConfigError, match="junk.sqlite3"):
        SqliteStore(junk)
    for f in (other, junk):                                 # the refusals released their locks
        with open(f.with_name(f.name + ".lock"), "rb") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)


def test_wal_and_synchronous_settings(path):
    with SqliteStore(path) as s:
        assert s._db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert s._db.execute("PRAGMA synchronous").fetchone()[0] == 1           # NORMAL
    with SqliteStore(path, synchronous="full") as s:
        assert s._db.execute("PRAGMA synchronous").fetchone()[0] == 2
    with pytest.raises(ConfigError, match="synchronous must be"):
        SqliteStore(path, synchronous="OFF")
    with SqliteStore(path):                                 # and the refusal released the lock
        pass


def test_checkpoints_run_off_the_committing_thread_and_close_merges_the_wal(path):
    with SqliteStore(path) as s:
        assert s._db.execute("PRAGMA wal_autocheckpoint").fetchone()[0] == 0     # never inside a commit
        for i in range(300):
            s.commit([(("node", U, "c", str(i)), {"spec": "x" * 2000})])
        assert s._checkpointer.failures == 0
    assert not path.with_name(path.name + "-wal").exists() or path.with_name(path.name + "-wal").stat().st_size == 0
    with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
        assert db.execute("SELECT count(*) FROM records").fetchone()[0] == 300
