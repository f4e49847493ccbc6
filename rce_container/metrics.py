"""Prometheus metrics of a container task set (``rce-container --metrics-port``).

Built per scrape from the task set's ``stats`` (:meth:`ContainerHost.op_stats`): containers
are labelled ``user``, ``ctag``; nodes ``user``, ``ctag``, ``node`` (the nTag).

Metrics (labels in brackets):

- ``rce_container_host_containers`` / ``_environments`` / ``_spares``: what the task set runs
- ``rce_environment_rss_bytes`` [env]: resident memory of each environment process
- ``rce_container_cpu_percent`` [user, ctag]: CPU use of every process of the container
  (100 = one core)
- ``rce_container_rss_bytes``, ``rce_container_processes`` [user, ctag]: resident memory,
  process count
- ``rce_container_cpu_limit_cores``, ``rce_container_memory_limit_bytes``,
  ``rce_container_tasks_limit`` [user, ctag]: limits in force (absent = none)
- ``rce_container_oom_kills_total`` [user, ctag]: processes the kernel killed for memory
- ``rce_container_messages_{in,out}_total``, ``rce_container_bytes_{in,out}_total``
  [user, ctag]: traffic over the container's interfaces
- ``rce_container_dropped_total`` [user, ctag, where (interfaces, bus)]: messages dropped
- ``rce_container_refused_total`` [user, ctag, where]: what the container's environment (shared
  by its group) turned away: ``bus`` connections without the container's uid or bus token,
  ``dataplane`` frames from senders not connected to their interface, ``dataplane_link`` data
  links closed for a wrong credential (docs/SECURITY.md)
- ``rce_node_cpu_percent``, ``rce_node_rss_bytes``, ``rce_node_processes``,
  ``rce_node_running`` [user, ctag, node]: per node
- ``rce_node_messages_{in,out}_total``, ``rce_node_bytes_{in,out}_total``,
  ``rce_node_dropped_total``, ``rce_node_undecodable_total`` [user, ctag, node]: the node's bus
  traffic (in = published by it; undecodable: delivered, but it could not deserialize them)
- ``rce_node_restarts_total`` [user, ctag, node]: respawns
"""
from __future__ import annotations

from prometheus_client import CollectorRegistry
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

C_LABELS = ["user", "ctag"]
N_LABELS = ["user", "ctag", "node"]


class _Snapshot:
    """A collector over one ``stats`` snapshot."""

    def __init__(self, stats: dict):
        self.stats = stats

    def collect(self):
        s = self.stats
        g = GaugeMetricFamily
        yield g("rce_container_host_containers", "Containers on this host", value=len(s.get("containers", [])))
        yield g("rce_container_host_environments", "Environment processes", value=s.get("environments", 0))
        yield g("rce_container_host_spares", "Warm spare environments", value=s.get("spares", 0))
        env = g("rce_environment_rss_bytes", "Resident memory of an environment process", labels=["env"])
        for k, mib in (s.get("environment_rss_mib") or {}).items():
            env.add_metric([str(k)], mib * 2**20)
        yield env

        fam = _families()
        for c in s.get("containers", []):
            if "error" not in c:
                _add_container(fam, c)
        yield from fam.values()


def _families() -> dict:
    """One empty metric family per key (the module doc lists them)."""
    g = GaugeMetricFamily
    return {
        "cpu": g("rce_container_cpu_percent", "CPU use of the container's processes, percent of one core",
                 labels=C_LABELS),
        "rss": g("rce_container_rss_bytes", "Resident memory of the container's processes", labels=C_LABELS),
        "procs": g("rce_container_processes", "Processes in the container", labels=C_LABELS),
        "lcpu": g("rce_container_cpu_limit_cores", "CPU limit in force, cores", labels=C_LABELS),
        "lmem": g("rce_container_memory_limit_bytes", "Memory limit in force", labels=C_LABELS),
        "ltasks": g("rce_container_tasks_limit", "Task (pids) limit in force", labels=C_LABELS),
        "oom": CounterMetricFamily("rce_container_oom_kills", "Processes killed for exceeding the memory limit",
                                   labels=C_LABELS),
        "min": CounterMetricFamily("rce_container_messages_in", "Messages into the container's interfaces",
                                   labels=C_LABELS),
        "mout": CounterMetricFamily("rce_container_messages_out", "Messages out of the container's interfaces",
                                    labels=C_LABELS),
        "bin": CounterMetricFamily("rce_container_bytes_in", "Bytes into the container's interfaces",
                                   labels=C_LABELS),
        "bout": CounterMetricFamily("rce_container_bytes_out", "Bytes out of the container's interfaces",
                                    labels=C_LABELS),
        "drop": CounterMetricFamily("rce_container_dropped", "Messages dropped", labels=[*C_LABELS, "where"]),
        "refused": CounterMetricFamily("rce_container_refused", "Bus connections, data frames and data links "
                                       "the container's environment turned away", labels=[*C_LABELS, "where"]),
        "ncpu": g("rce_node_cpu_percent", "CPU use of the node's processes, percent of one core", labels=N_LABELS),
        "nrss": g("rce_node_rss_bytes", "Resident memory of the node's processes", labels=N_LABELS),
        "nprocs": g("rce_node_processes", "Processes of the node", labels=N_LABELS),
        "nrun": g("rce_node_running", "1 while the node runs", labels=N_LABELS),
        "nrest": CounterMetricFamily("rce_node_restarts", "Respawns of the node", labels=N_LABELS),
        "nmin": CounterMetricFamily("rce_node_messages_in", "Messages the node published", labels=N_LABELS),
        "nmout": CounterMetricFamily("rce_node_messages_out", "Messages delivered to the node", labels=N_LABELS),
        "nbin": CounterMetricFamily("rce_node_bytes_in", "Bytes the node published", labels=N_LABELS),
        "nbout": CounterMetricFamily("rce_node_bytes_out", "Bytes delivered to the node", labels=N_LABELS),
        "ndrop": CounterMetricFamily("rce_node_dropped", "Messages the node's subscriptions dropped",
                                     labels=N_LABELS),
        "nundec": CounterMetricFamily("rce_node_undecodable", "Messages delivered to the node that it could not "
                                      "deserialize", labels=N_LABELS),
    }


def _add_container(fam: dict, container: dict) -> None:
    """Add one container's stats (and its nodes') to the families of :func:`_families`."""
    lab = [container.get("user", ""), container.get("ctag", "")]
    fam["cpu"].add_metric(lab, container.get("cpu_percent", 0.0))
    fam["rss"].add_metric(lab, container.get("rss_mib", 0.0) * 2**20)
    fam["procs"].add_metric(lab, container.get("processes", 0))
    limits = container.get("limits") or {}
    if limits.get("cpu"):
        fam["lcpu"].add_metric(lab, limits["cpu"])
    if limits.get("memory"):
        fam["lmem"].add_metric(lab, limits["memory"] * 2**20)
    if limits.get("pids"):
        fam["ltasks"].add_metric(lab, limits["pids"])
    fam["oom"].add_metric(lab, (container.get("memory") or {}).get("oom_kills", 0))
    for key, stat in (("min", "msgs_in"), ("mout", "msgs_out"), ("bin", "bytes_in"), ("bout", "bytes_out")):
        fam[key].add_metric(lab, container.get(stat, 0))
    for where, n in (container.get("dropped") or {}).items():
        fam["drop"].add_metric([*lab, where], n)
    env = container.get("environment") or {}
    plane = env.get("dataplane") or {}
    for where, n in (("bus", (env.get("bus") or {}).get("refused")), ("dataplane", plane.get("refused")),
                     ("dataplane_link", plane.get("unauthenticated"))):
        if n is not None:
            fam["refused"].add_metric([*lab, where], n)
    for ntag, n in (container.get("per_node") or {}).items():
        nl = [*lab, ntag]
        fam["ncpu"].add_metric(nl, n.get("cpu_percent", 0.0))
        fam["nrss"].add_metric(nl, n.get("rss_mib", 0.0) * 2**20)
        fam["nprocs"].add_metric(nl, n.get("processes", 0))
        fam["nrun"].add_metric(nl, 1 if n.get("running") else 0)
        for key, stat in (("nrest", "restarts"), ("nmin", "msgs_in"), ("nmout", "msgs_out"), ("nbin", "bytes_in"),
                          ("nbout", "bytes_out"), ("ndrop", "dropped"), ("nundec", "undecodable")):
            fam[key].add_metric(nl, n.get(stat, 0))


def snapshot_registry(stats: dict) -> CollectorRegistry:
    """A registry exposing one ``stats`` snapshot (see the module doc)."""
    reg = CollectorRegistry(auto_describe=False)
    reg.register(_Snapshot(stats))
    return reg
