"""Tools around a running engine: the admin API client (:mod:`.admin_client`) and the engine
launcher for demos, tests and benchmarks (:mod:`.launch`)."""
from rce.tools.admin_client import AdminClient
from rce.tools.launch import Engine, start_engine

__all__ = ["AdminClient", "Engine", "start_engine"]
