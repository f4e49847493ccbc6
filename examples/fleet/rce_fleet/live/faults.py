"""Faults injected into a running mission: ``rce-fleet demo --fault SPEC`` (repeatable), to show
that the fleet survives them (what survives what: docs/INTERNALS.md "Outliving the master" and
"Session resume").

SPEC, with T in sim s after the goals were sent (as ``--block``) and S in wall s (the outage is
real time, not simulated):

* ``master@T[+S]``: kill -9 rce-master, wait S s (default :data:`MASTER_DOWN_S`), start it again on
  the same ports and ``--state`` file (:meth:`rce.tools.launch.Engine.restart_master`). Served again:
  every task set has re-registered and login answers 200.
* ``link:ROBOT@T[+S]``: cut ROBOT's websocket for S s (default :data:`LINK_CUT_S`) at the loopback
  proxy the demo runs between that robot's bridge and rce-robot (:mod:`rce.transport.tcpproxy`, its login
  through :mod:`rce_fleet.live.linkproxy`).
  Served again: the robot's session is resumed (``ST session resumed``).

Each fault's record (the report's ``faults``), times in wall s unless named ``_sim_``:
``{fault, at_s, duration_s, injected, injected_sim_s, injected_wall_s (since the goals were sent),
served_again_after_s (from the restart's ready file, or the link's return, to served again),
recovered_after_s (from the fault to served again), fleet_state_max_gap_s (the longest pause of
/fleet/state at the fleet manager during the fault), recovered}``; a master fault adds
``restart_s`` (the restarted master's start to its ready file), a link fault ``dropped``
(messages to the robot its session lost, from the ST).
"""
from __future__ import annotations

import asyncio
import time
from typing import Callable

from rce.plumbing.errors import RCEError
from rce.tools.launch import Engine
from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks
from rce.transport.tcpproxy import TcpProxy
from rce_client.connection import Connection, login

from .linkproxy import LoginRelay
from .options import LINK_CUT_S, MASTER_DOWN_S, SPEC_HELP, Fault, parse_fault  # noqa: F401  (the --fault SPEC)

log = get_logger("fleet.faults")

RECOVERY_TIMEOUT_S = 60.0  # wall s after a fault ends for the fleet to be served again, else the run fails
POLL_S = 0.05              # wall s between checks that the restarted master serves (admin API, login)


class FaultInjector:
    """Injects one run's faults and records them (see the module docstring). ``engine``: the
    running engine; ``tasks``: where the injections run; ``user``: whose login checks that the
    master serves again; ``mission_t()``: sim s since the goals were sent."""

    def __init__(self, faults: list[Fault], engine: Engine, tasks: Tasks, user: str,
                 mission_t: Callable[[], float]):
        self.faults, self.engine, self.tasks, self.user = faults, engine, tasks, user
        self.mission_t = mission_t
        self.proxies: dict[str, TcpProxy] = {}
        self.relays: dict[str, LoginRelay] = {}
        self.error: str | None = None            # why a fault was not recovered from: the run fails
        self._resumed: dict[str, asyncio.Event] = {}
        self._resume_st: dict[str, tuple[float, dict]] = {}   # robot -> (when, ST session resumed)
        self._open: list[dict] = []               # records of the faults in progress
        self._last_state: float | None = None
        self._wall_mission = 0.0

    @property
    def busy(self) -> bool:
        """Is a fault in progress (the mission does not end before it is recovered from)?"""
        return bool(self._open)

    async def start_links(self) -> dict[str, str]:
        """A proxy and a login relay per robot a fault cuts; returns robot -> its login URL."""
        ws_port = self.engine.robot_ready[0]["ws_port"]
        for f in self.faults:
            if f.kind == "link" and f.robot not in self.proxies:
                self.proxies[f.robot] = proxy = await TcpProxy(ws_port).start()
                self.relays[f.robot] = await LoginRelay(self.engine.master_url, proxy.url).start()
                self._resumed[f.robot] = asyncio.Event()
        return {r: relay.url for r, relay in self.relays.items()}

    def watch(self, robot: str, conn: Connection) -> None:
        """Hear when ``robot``'s session (``conn``, its bridge's connection) is resumed."""
        def resumed(st: dict) -> None:
            self._resume_st[robot] = (time.monotonic(), st)
            self._resumed[robot].set()
        conn.on_resumed(resumed)

    def schedule(self, at: Callable[[float, Callable[[], None]], None], t_mission: float) -> None:
        """Schedule every fault with ``at(sim_time, callback)`` (:meth:`rce_fleet.live.simhost.SimHost.at`);
        ``t_mission``: the sim time the goals were sent."""
        self._wall_mission = time.monotonic()
        for f in self.faults:
            f.record = {"fault": f.name, "at_s": f.at, "duration_s": f.duration, "injected": False}
            at(t_mission + f.at, lambda fault=f: self.tasks.spawn(self._inject(fault), name=f"fault-{fault.name}"))

    def on_state(self) -> None:
        """A ``/fleet/state`` arrived at the fleet manager (the gaps of the faults in progress)."""
        now = time.monotonic()
        if self._last_state is not None:
            for rec in self._open:
                rec["fleet_state_max_gap_s"] = round(max(rec.get("fleet_state_max_gap_s", 0.0),
                                                         now - self._last_state), 3)
        self._last_state = now

    async def _inject(self, fault: Fault) -> None:
        rec = fault.record
        t0 = time.monotonic()
        rec.update(injected=True, injected_sim_s=round(self.mission_t(), 2),
                   injected_wall_s=round(t0 - self._wall_mission, 2), recovered=False)
        self._open.append(rec)
        log.warning("fault injected", fault=fault.name, duration_s=fault.duration, t=rec["injected_sim_s"])
        try:
            async with asyncio.timeout(fault.duration + RECOVERY_TIMEOUT_S):
                t_back, t_served = await (self._master(fault) if fault.kind == "master" else self._link(fault))
            rec.update(recovered=True, served_again_after_s=round(t_served - t_back, 3),
                       recovered_after_s=round(t_served - t0, 3))
            log.info("fault recovered", **rec)
        except TimeoutError:
            self.error = f"fault {fault.name}: the fleet was not served again within {RECOVERY_TIMEOUT_S:g} s"
        except (RuntimeError, OSError) as e:
            self.error = f"fault {fault.name}: {e}"
        finally:
            self._open.remove(rec)

    async def _master(self, fault: Fault) -> tuple[float, float]:
        """kill -9, wait, restart; returns (restarted master ready, served again), monotonic s."""
        await asyncio.to_thread(self.engine.kill_master)
        await asyncio.sleep(fault.duration)         # the outage itself (its length), not a synchronisation
        t_start = time.monotonic()
        await asyncio.to_thread(self.engine.restart_master)
        t_ready = time.monotonic()
        fault.record["restart_s"] = round(t_ready - t_start, 3)
        while not await self._master_serves():
            await asyncio.sleep(POLL_S)        # polling another process's state
        return t_ready, time.monotonic()

    async def _master_serves(self) -> bool:
        """Has every task set re-registered, and does login answer 200?"""
        try:
            tasksets = (await asyncio.to_thread(self.engine.admin, "/api/state"))["tasksets"]
            await login(self.engine.master_url, self.user)
        except (RCEError, OSError):
            return False
        return bool(tasksets) and not any(t.get("absent") for t in tasksets)

    async def _link(self, fault: Fault) -> tuple[float, float]:
        """Cut, wait, restore; returns (link back, session resumed), monotonic s."""
        resumed = self._resumed[fault.robot]
        resumed.clear()
        self.proxies[fault.robot].cut()
        await asyncio.sleep(fault.duration)         # the cut itself (its length), not a synchronisation
        self.proxies[fault.robot].restore()
        t_back = time.monotonic()
        await resumed.wait()
        t_served, st = self._resume_st[fault.robot]
        fault.record["dropped"] = st.get("dropped", 0)
        return t_back, t_served

    def report(self) -> list[dict]:
        """Every fault's record (a fault the mission ended before: ``injected`` False)."""
        return [f.record or {"fault": f.name, "at_s": f.at, "duration_s": f.duration, "injected": False}
                for f in self.faults]

    async def close(self) -> None:
        """Stop the login relays and the proxies."""
        for relay in self.relays.values():
            await relay.stop()
        for proxy in self.proxies.values():
            await proxy.close()
