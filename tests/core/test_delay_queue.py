"""The delay line's queue (rce.tools.delayline.DelayQueue), sans I/O: frames leave no earlier than
their delay, in the order they came, a shrinking delay never lets one overtake another, and a full
queue drops and counts."""
from __future__ import annotations

import pytest

from rce.tools.delayline import DelayQueue


def test_a_frame_leaves_once_its_delay_has_passed_and_not_before():
    q = DelayQueue(0.05)
    q.push(10.0, b"a")
    assert q.next_due() == pytest.approx(10.05)
    assert q.pop_due(10.049) == []
    assert q.pop_due(10.05) == [b"a"]
    assert q.next_due() is None and q.forwarded == 1


def test_frames_keep_their_order_when_the_delay_shrinks():
    q = DelayQueue(0.05)
    q.push(0.0, b"slow")
    q.delay_s = 0.0
    q.push(0.01, b"fast")                 # due at 0.01 by its own delay, but behind "slow"
    assert q.pop_due(0.02) == []
    assert q.pop_due(0.05) == [b"slow", b"fast"]


def test_a_full_queue_drops_and_counts():
    q = DelayQueue(1.0, limit=2)
    assert q.push(0.0, b"1") and q.push(0.0, b"2")
    assert not q.push(0.0, b"3")
    assert q.dropped == 1
    assert q.pop_due(1.0) == [b"1", b"2"]


def test_a_negative_delay_is_refused():
    with pytest.raises(ValueError, match="must be >= 0"):
        DelayQueue(-0.001)
