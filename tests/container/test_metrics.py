"""The container task set's Prometheus export (rce_container/metrics.py), from a stats snapshot."""
from __future__ import annotations

from prometheus_client import generate_latest
from prometheus_client.parser import text_string_to_metric_families

from rce_container.metrics import snapshot_registry


def _sample(text: str, name: str, **labels) -> float:
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            if s.name == name and s.labels == labels:
                return s.value
    raise AssertionError(f"no sample {name}{labels} in:\n{text}")


def test_refusals_of_the_environment_are_exported_per_container():
    """What the environment turned away (bus connections, data frames, data links) shows
    in /metrics, not only in the admin API's stats."""
    stats = {"containers": [{"user": "alice", "ctag": "c1", "dropped": {"interfaces": 2, "bus": 0},
                             "environment": {"bus": {"refused": 3},
                                             "dataplane": {"refused": 5, "unauthenticated": 1}}}]}
    text = generate_latest(snapshot_registry(stats)).decode()
    assert _sample(text, "rce_container_refused_total", user="alice", ctag="c1", where="bus") == 3
    assert _sample(text, "rce_container_refused_total", user="alice", ctag="c1", where="dataplane") == 5
    assert _sample(text, "rce_container_refused_total", user="alice", ctag="c1", where="dataplane_link") == 1
    assert _sample(text, "rce_container_dropped_total", user="alice", ctag="c1", where="interfaces") == 2
