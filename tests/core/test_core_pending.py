"""rce.plumbing.pending.PendingCalls and rce.plumbing.tasks.Tasks, sans I/O: the one pending-call table and the
kept tasks every part of the engine uses."""
from __future__ import annotations

import asyncio
import logging

import pytest

from rce.plumbing.errors import RCEError, Timeout, Unavailable
from rce.plumbing.pending import PendingCalls
from rce.plumbing.tasks import Tasks


async def test_settle_wakes_the_waiter_and_forgets_the_call():
    calls = PendingCalls("peer")
    sent = []
    waiter = asyncio.ensure_future(calls.call(sent.append, timeout=5))
    await asyncio.sleep(0)                   # let the call open and send
    assert sent == [1] and 1 in calls
    assert calls.settle(1, "result")
    assert await waiter == "result"
    assert len(calls) == 0 and not calls.settle(1, "late")   # a late answer is refused, not an error


async def test_timeout_is_a_timeout_error_not_unavailable():
    calls = PendingCalls("master")
    cid = calls.open()
    with pytest.raises(Timeout) as e:
        await calls.wait(cid, 0.01, "'register'")
    assert isinstance(e.value, TimeoutError) and isinstance(e.value, RCEError)
    assert not isinstance(e.value, Unavailable)
    assert "master did not answer 'register' within 0.01 s" in str(e.value)
    assert cid not in calls


async def test_a_timeout_from_further_away_is_passed_on_unchanged():
    calls = PendingCalls("bus")
    cid = calls.open()
    calls.fail(cid, Timeout("the node did not answer within 1 s"))
    with pytest.raises(Timeout, match="the node did not answer"):
        await calls.wait(cid, 5)


async def test_fail_all_fails_waiters_and_later_opens():
    calls = PendingCalls("robot endpoint")
    waiters = [asyncio.ensure_future(calls.wait(calls.open(), None)) for _ in range(3)]
    assert calls.fail_all() == 3
    for w in waiters:
        with pytest.raises(Unavailable, match="the link to robot endpoint closed"):
            await w
    with pytest.raises(Unavailable):
        calls.open()


async def test_caller_keys_info_and_duplicates():
    calls = PendingCalls("robot")
    key = "a" * 32
    assert calls.open(key, info="itag") == key
    assert calls.info(key) == "itag" and list(calls.items()) == [(key, "itag")]
    with pytest.raises(RCEError, match="already in flight"):
        calls.open(key)
    calls.forget(key)
    assert key not in calls and calls.info(key) is None


async def test_a_send_that_fails_forgets_the_call():
    calls = PendingCalls("link")

    def full(cid):
        raise Unavailable("link full")
    with pytest.raises(Unavailable, match="link full"):
        await calls.call(full, timeout=1)
    assert len(calls) == 0


async def test_cancelling_the_waiter_cancels_the_wait_and_forgets():
    calls = PendingCalls("peer")
    cid = calls.open()
    waiter = asyncio.ensure_future(calls.wait(cid, 10))
    await asyncio.sleep(0)
    waiter.cancel()
    with pytest.raises(asyncio.CancelledError):
        await waiter
    assert cid not in calls


async def test_tasks_are_kept_and_failures_logged(caplog):
    tasks = Tasks("unit")

    async def boom():
        raise ValueError("bad")

    async def refuse():
        raise Unavailable("no host")

    async def forever():
        await asyncio.Event().wait()
    with caplog.at_level(logging.WARNING, logger="rce.plumbing.tasks"):
        t1, t2, t3 = tasks.spawn(boom(), "boom"), tasks.spawn(refuse(), "refuse"), tasks.spawn(forever(), "wait")
        assert len(tasks) == 3
        await asyncio.gather(t1, t2, return_exceptions=True)
        await asyncio.sleep(0)               # done callbacks run
        assert tasks.failed == 2 and len(tasks) == 1
        await tasks.cancel_all()
    assert t3.cancelled() and len(tasks) == 0
    messages = [r.getMessage() for r in caplog.records]
    assert messages.count("task failed") == 2
    assert any(r.levelno == logging.ERROR and r.exc_info for r in caplog.records)   # a bug: traceback kept
