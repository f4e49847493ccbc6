"""A node's result latency (rce.node.results), sans I/O: outputs tied to the input whose callback
publishes them, or to a stamped input by its stamp; a container's misses against its deadline."""
from __future__ import annotations

from types import SimpleNamespace

from rce.node.results import INPUT_ARRIVAL, MAX_SAMPLES, ResultClock, ResultStats, stamp_of


def stamped(sec: int, nanosec: int = 0):
    return SimpleNamespace(header=SimpleNamespace(stamp=SimpleNamespace(sec=sec, nanosec=nanosec)))


def test_an_output_published_in_its_inputs_callback_is_timed_from_the_input():
    clock = ResultClock()
    running = [10.0, True]
    token = INPUT_ARRIVAL.set(running)
    try:
        clock.published(SimpleNamespace(data="x"), 10.025)
        running[1] = False                     # the callback returned: a task it left behind is not its result
        clock.published(SimpleNamespace(data="y"), 11.0)
    finally:
        INPUT_ARRIVAL.reset(token)
    assert clock.take() == {"results": 1, "samples": [25.0], "overflow": 0}
    assert clock.take()["samples"] == [], "a take hands each sample once"


def test_a_stamped_output_outside_any_callback_is_timed_from_the_input_of_its_stamp():
    clock = ResultClock()
    clock.arrived(stamp_of(stamped(5, 100)), 1.0)
    clock.published(stamped(5, 100), 1.2)             # from a timer, with its source's stamp
    clock.published(stamped(6), 1.3)                  # a stamp no input had: not a result
    clock.published({"header": {"stamp": {"secs": 5, "nsecs": 100}}}, 1.5)      # JSON form
    out = clock.take()
    assert out["results"] == 2 and [round(s) for s in out["samples"]] == [200, 500]


def test_samples_are_bounded_and_the_rest_counted():
    clock = ResultClock()
    token = INPUT_ARRIVAL.set([0.0, True])
    try:
        for _ in range(MAX_SAMPLES + 7):
            clock.published(None, 0.001)
    finally:
        INPUT_ARRIVAL.reset(token)
    out = clock.take()
    assert len(out["samples"]) == MAX_SAMPLES and out["overflow"] == 7 and out["results"] == MAX_SAMPLES + 7


def test_a_containers_misses_against_its_deadline():
    stats = ResultStats(deadline_ms=100)
    stats.add({"samples": [20, 50, 150], "overflow": 0}, now=0.0)
    stats.add({"samples": [120], "overflow": 2}, now=5.0)
    stats.add("not a report", now=5.0)
    s = stats.stats(now=5.5)
    assert (s["results"], s["misses"], s["unseen"], s["max_ms"]) == (6, 2, 2, 150)
    assert s["recent_p90_ms"] == 120, "the recent window holds the last seconds only"
    assert s["recent_p50_ms"] == 120
    assert (s["late_results"], s["late_misses"]) == (4, 2), "the late share is over the last 10 s"
    assert ResultStats().stats(0.0)["p50_ms"] is None
