"""Login hardening (docs/SECURITY.md "Login"): the rules of
:mod:`rce_master.auth.login_guard` without sockets, then against a real engine: user names cannot be
enumerated (login and handshake answer the same), failures back off per user (from one address)
and per address with 429 + Retry-After while the real user from another address still logs in,
and a real login succeeds during a password attack that gets 429s (the latencies are in
``bench/login_attack.py``)."""
from __future__ import annotations

import asyncio
import hashlib
import json
import threading
import urllib.request

import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from rce.plumbing.errors import AuthError, Throttled
from rce.tools.launch import start_engine
from rce_master.auth import users as users_mod
from rce_master.auth.login_guard import FailureTable, LoginGuard, PasswordCheck
from rce_master.state.model import User, password_digest
from rce_master.auth.scrypt_pool import NORMAL, URGENT, PriorityPool

PER_USER, PER_ADDRESS = 3, 6          # the engine's --login-failures-per-user/-address: small, for a quick test
HANDSHAKE_TIMEOUT = 20.0              # s a websocket handshake may take on a busy machine (scrypt queued)
ATTACK = 120                          # wrong logins in the attack, ...
ATTACK_CONCURRENCY = 24               # ... this many at a time, from ...
ATTACK_ADDRESSES = [f"127.0.1.{i}" for i in range(1, 7)]   # ... these addresses


# -- the rules, sans I/O -----------------------------------------------------------------------
def test_failures_back_off_per_user_at_an_address_then_per_address():
    g = LoginGuard(per_user=3, per_address=5)
    for _ in range(3):
        g.admit("u", "a", 0.0)
        g.done("u", "a", False)
    with pytest.raises(Throttled) as ei:
        g.admit("u", "a", 0.5)
    assert ei.value.retry_after == 1
    g.admit("u", "b", 0.5)                  # the same user from another address
    g.done("u", "b", True)
    g.admit("v", "a", 0.5)                  # another user from the address: 4 of its 5 free failures
    g.done("v", "a", False)
    g.admit("u", "a", 1.0)                  # the back-off is over: one more try, then 2 s
    g.done("u", "a", False)
    with pytest.raises(Throttled) as ei:
        g.admit("w", "a", 1.5)              # the address has used its free failures: 1 s from its 5th
    assert ei.value.retry_after == 1
    with pytest.raises(Throttled) as ei:
        g.admit("u", "a", 2.5)
    assert ei.value.retry_after == 1        # 2 s from t=1.0 (rounded up)


def test_a_success_forgets_the_failures_and_is_not_counted():
    g = LoginGuard(per_user=3, per_address=5)
    for _ in range(2):
        g.admit("u", "a", 0.0)
        g.done("u", "a", False)
    g.admit("u", "a", 0.0)
    g.done("u", "a", True)
    assert ("u", "a") not in g.users.entries and g.addresses.entries["a"].failures == 2
    g.admit("u", "a", 0.0)
    g.done("u", "a", None)                  # not checked (the pool was busy): taken back
    assert ("u", "a") not in g.users.entries and g.addresses.entries["a"].failures == 2


def test_concurrent_attempts_count_as_they_start_and_in_flight_is_capped():
    g = LoginGuard(per_user=3, per_address=100, in_flight_per_address=2)
    g.admit("u", "a", 0.0)
    g.admit("u", "a", 0.0)
    with pytest.raises(Throttled, match="in progress"):
        g.admit("u", "a", 0.0)              # a third at once from one address
    g.done("u", "a", False)
    g.admit("u", "a", 0.0)                  # the third failure, counted as it starts, ...
    with pytest.raises(Throttled, match="failed logins"):
        g.admit("u", "a", 0.0)              # ... starts the back-off before any answer


def test_tables_are_bounded_and_expire_in_order():
    t = FailureTable(2, memory=10.0, max_entries=3)
    for i, k in enumerate("abcd"):
        t.fail(k, float(i))
    assert list(t.entries) == ["b", "c", "d"] and t.evicted == 1
    t.expire(12.5)                          # b (t=1) and c (t=2) are older than 10 s
    assert list(t.entries) == ["d"]
    t.fail("d", 3.0)
    assert t.retry_after("d", 3.0) == 1.0   # the second failure: back-off 1 s
    t.fail("d", 4.0)
    assert t.retry_after("d", 4.0) == 2.0   # then it doubles


def test_an_unknown_user_costs_one_scrypt_as_a_wrong_password(monkeypatch):
    calls = []
    real = User.check
    monkeypatch.setattr(User, "check", lambda self, d: calls.append(self.name) or real(self, d))
    known = {"alice": User.create("alice", "s3cret")}
    assert users_mod.verify(known, "alice", password_digest("s3cret"))
    assert not users_mod.verify(known, "alice", password_digest("wrong"))
    assert not users_mod.verify(known, "mallory", password_digest("s3cret"))
    assert not users_mod.verify(known, "mallory", None)
    assert calls == ["alice", "alice", "", ""]        # "": the dummy user, whose scrypt an unknown name costs


def test_clean_logins_go_ahead_of_the_others_in_the_pool():
    pool = PriorityPool(1, "test-scrypt")
    started, release, order = threading.Event(), threading.Event(), []
    try:
        blocker = pool.submit(NORMAL, lambda: (started.set(), release.wait(10)))
        assert started.wait(10)
        futs = [pool.submit(p, order.append, name) for p, name in ((NORMAL, "a"), (NORMAL, "b"), (URGENT, "c"))]
        release.set()
        for f in (blocker, *futs):
            f.result(10)
        assert order == ["c", "a", "b"]
    finally:
        pool.close()


async def test_password_check_answers_the_same_and_refuses_when_busy():
    known = {"alice": User.create("alice", "s3cret")}
    check = PasswordCheck(LoginGuard(per_user=100, per_address=100, in_flight_per_address=100), workers=1, queue=1,
                          reserved=0)
    try:
        answers = []
        for user in ("alice", "mallory"):
            with pytest.raises(AuthError) as ei:
                await check.authenticate(known, user, password_digest("wrong"), "a")
            answers.append(ei.value.message.replace(repr(user), "U"))
        assert answers[0] == answers[1]
        results = await asyncio.gather(*(check.authenticate(known, "alice", password_digest("wrong"), "a")
                                         for _ in range(4)), return_exceptions=True)
        assert sum(isinstance(r, Throttled) for r in results) == 2          # 1 running + 1 waiting, 2 refused
        await check.authenticate(known, "alice", password_digest("s3cret"), "a")
        assert check.busy == 0 and check.results["ok"] == 1 and check.results["busy"] == 2
    finally:
        check.close()


# -- against the engine ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def eng(tmp_path_factory):
    e = start_engine(tmp_path_factory.mktemp("engine"), container_hosts=0,
                     master_args=("--login-failures-per-user", str(PER_USER),
                                  "--login-failures-per-address", str(PER_ADDRESS)))
    yield e
    e.stop()


def _http_login(eng, user: str) -> tuple[int, bytes]:
    with urllib.request.urlopen(f"{eng.master_url}?userID={user}&version=20130902", timeout=10) as r:
        return r.status, r.read()


async def _ws_login(eng, user: str, password: str, robot: str, addr: str) -> tuple[int, str, dict]:
    """A newer client's websocket login (``refusal=http``: refusals as HTTP statuses) from source
    address ``addr``: (status, body, headers); 101 when it opened (then closed again)."""
    url = json.loads(_http_login(eng, user)[1])["url"]
    digest = hashlib.sha256(password.encode()).hexdigest()
    try:
        ws = await connect(f"{url}?userID={user}&robotID={robot}&password={digest}&refusal=http", local_addr=(addr, 0),
                           open_timeout=HANDSHAKE_TIMEOUT)
    except InvalidStatus as e:
        r = e.response
        return r.status_code, r.body.decode(), dict(r.headers)
    await ws.close()
    return 101, "", {}


async def test_user_names_cannot_be_enumerated(eng):
    known, unknown = _http_login(eng, "testUser"), _http_login(eng, "nobodyAtAll")
    assert known == unknown and known[0] == 200                      # login: the same answer
    a = await _ws_login(eng, "testUser", "wrong", "enumBot", "127.0.0.5")
    b = await _ws_login(eng, "nobodyAtAll", "wrong", "enumBot", "127.0.0.5")
    assert a[0] == b[0] == 401
    assert a[1].replace("'testUser'", "U") == b[1].replace("'nobodyAtAll'", "U")
    assert "invalid user ID or password" in a[1]


async def test_failures_back_off_per_user_and_the_user_logs_in_elsewhere(eng):
    for _ in range(PER_USER):
        assert (await _ws_login(eng, "testUser", "guess", "victimBot", "127.0.0.2"))[0] == 401
    status, body, headers = await _ws_login(eng, "testUser", "guess", "victimBot", "127.0.0.2")
    assert status == 429 and int(headers["retry-after"]) >= 1 and "too many failed logins" in body
    status, _, _ = await _ws_login(eng, "testUser", "testUser", "victimBot", "127.0.0.2")
    assert status == 429                                             # even the right password, from there
    assert (await _ws_login(eng, "testUser", "testUser", "victimBot", "127.0.0.1"))[0] == 101


async def test_failures_back_off_per_address(eng):
    for i in range(PER_ADDRESS):
        assert (await _ws_login(eng, f"someone{i}", "guess", "scanBot", "127.0.0.3"))[0] == 401
    status, _, headers = await _ws_login(eng, "someoneNew", "guess", "scanBot", "127.0.0.3")
    assert status == 429 and "retry-after" in headers
    assert (await _ws_login(eng, "testUser", "testUser", "scanVictim", "127.0.0.1"))[0] == 101
    metrics = urllib.request.urlopen(eng.master_url + "metrics", timeout=10).read().decode()
    assert 'rce_master_auth_total{result="throttled"}' in metrics


async def test_a_real_login_succeeds_during_a_password_attack(eng):
    sem = asyncio.Semaphore(ATTACK_CONCURRENCY)

    async def guess(i: int) -> int:
        async with sem:
            return (await _ws_login(eng, "testUser", f"guess{i}", "attackBot", ATTACK_ADDRESSES[i % 6]))[0]

    attack = asyncio.gather(*(guess(i) for i in range(ATTACK)))
    real = await _ws_login(eng, "testUser", "testUser", "realBot", "127.0.0.1")
    statuses = await attack
    assert real[0] == 101, real
    assert statuses.count(429) > ATTACK // 2 and set(statuses) <= {401, 429}
    assert eng.alive() == []


async def test_a_fleet_behind_one_address_logs_in_together_a_few_at_a_time():
    """Robots of one user behind one NAT log in at once: past the per-address checks in flight they wait
    for a turn instead of a 429 (the fleet demo's and fleet_load's robots all come from 127.0.0.1)."""
    known = {"alice": User.create("alice", "s3cret")}
    check = PasswordCheck(LoginGuard(in_flight_per_address=2), workers=2)
    try:
        await asyncio.gather(*(check.authenticate(known, "alice", password_digest("s3cret"), "nat")
                               for _ in range(12)))
        assert check.results == {"ok": 12, "failed": 0, "throttled": 0, "busy": 0}
        assert check.waiting == 0 and check.guard.in_flight == {}
    finally:
        check.close()


async def test_waiting_attempts_from_one_address_still_meet_the_back_off():
    """Wrong guesses that waited for their turn are refused once the failures before them start the
    back-off: waiting is no way around it."""
    known = {"alice": User.create("alice", "s3cret")}
    check = PasswordCheck(LoginGuard(per_user=3, in_flight_per_address=1), workers=1)
    try:
        results = await asyncio.gather(*(check.authenticate(known, "alice", password_digest("wrong"), "x")
                                         for _ in range(8)), return_exceptions=True)
        assert sum(isinstance(r, AuthError) and not isinstance(r, Throttled) for r in results) == 3
        assert sum(isinstance(r, Throttled) for r in results) == 5
    finally:
        check.close()
