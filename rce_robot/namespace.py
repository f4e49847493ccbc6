"""A robot namespace: the websocket shell of one connected robot's session.

The rules live in :class:`rce.protocol.session.RobotSession` (frames, binary parts,
validation, ordering, the bounded outbox, error accounting); this shell moves frames between
the websocket and the session and does what the session's events ask: a request goes to
the master (one at a time), a DM to its interface, a service call runs in a task. Every
task is kept (:class:`rce.tasks.Tasks`).
"""
from __future__ import annotations

import asyncio
import time
from typing import Any

from websockets.exceptions import ConnectionClosed

from rce.errors import RCEError
from rce.log import get_logger
from rce.protocol.session import Event, RobotSession
from rce.rpc import RpcPeer
from rce.tasks import Tasks
from rce_robot.interfaces import RobotInterface

log = get_logger("rce.robot")

# s a robot's request (CC, DC, CN, CX) waits for the master: creating a container (an environment
# process, its sandbox, its nodes) can take tens of seconds on a loaded host
REQUEST_TIMEOUT = 120.0
# s between two expiry checks at most (half the expiry when that is shorter)
EXPIRY_CHECK = 5.0
CLOSE_POLICY = 1008       # websocket close code when the cloud ends a session (policy violation)
CLOSE_REASON_MAX = 120    # chars of a close reason (a close frame holds 123 bytes)


class RobotNamespace:
    """Session of robot ``robot`` of user ``user`` on websocket ``ws``; ``master``: the control
    link its requests go through. Implements :class:`rce_robot.interfaces.RobotLink`."""

    def __init__(self, ws: Any, user: str, robot: str, master: RpcPeer, session: RobotSession):
        self.ws, self.user, self.robot, self.master, self.session = ws, user, robot, master, session
        self.interfaces: dict[str, RobotInterface] = {}
        self.tasks = Tasks(f"robot {user}/{robot}")
        self._wake = asyncio.Event()

    # -- the interface table -------------------------------------------------------------------------
    def add_interface(self, iface: RobotInterface) -> None:
        """Robot-side interface ``iface`` now exists (the master's ``add_interface``)."""
        self.session.add_interface(iface.itag, iface.itype, iface.cls)
        self.interfaces[iface.itag] = iface

    def remove_interface(self, iface: RobotInterface) -> None:
        if self.interfaces.get(iface.itag) is iface:
            del self.interfaces[iface.itag]
            self.session.remove_interface(iface.itag)

    # -- to the robot (RobotLink) ----------------------------------------------------------------------
    def send_dm(self, itag: str, cls: str, msg_id: Any, msg: Any, data: bool = False) -> bool:
        """Queue a DM to the robot; ``data=True`` marks droppable topic data (False: dropped)."""
        ok = self.session.send_dm(itag, cls, msg_id, msg, data)
        self._pump()
        return ok

    def send_status(self, data: dict) -> None:
        self.session.send_status(data)
        self._pump()

    def send_error(self, reason: str) -> None:
        log.info("ER to robot", user=self.user, robot=self.robot, reason=reason)
        self.session.send_error(reason)
        self._pump()

    async def _writer(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            while frames := self.session.data_to_send(1):     # one message at a time: the outbox stays the bound
                for f in frames:
                    await self.ws.send(f)

    # -- from the robot --------------------------------------------------------------------------------
    async def run(self) -> None:
        """Serve the session until the websocket closes."""
        self.tasks.spawn(self._writer(), name="writer")
        self.tasks.spawn(self._expire(), name="expire")
        try:
            async for frame in self.ws:
                if isinstance(frame, str):
                    self.session.receive_text(frame, time.monotonic())
                else:
                    self.session.receive_binary(frame, time.monotonic())
                self._pump()
        except ConnectionClosed:
            pass
        finally:
            await self.tasks.cancel_all()
            for iface in list(self.interfaces.values()):
                await iface.stop()
            self.interfaces.clear()

    def _pump(self) -> None:
        """Do what the session's events ask; wake the writer when frames wait."""
        while events := self.session.events_received():
            for ev in events:
                self._on_event(ev)
        if self.session.outbox:
            self._wake.set()

    def _on_event(self, ev: Event) -> None:
        f = ev.fields
        if ev.name == "request":
            self.tasks.spawn(self._request(f["type"], f["data"]), name="request")
        elif ev.name == "deliver":
            iface = self.interfaces.get(f["iTag"])
            try:
                if iface is None:
                    raise RCEError(f"DM: no interface {f['iTag']!r} on robot {self.robot!r}")
                iface.from_robot(f["data"])
            except RCEError as e:
                self.send_error(e.message)
        elif ev.name == "call":
            self.tasks.spawn(self._call(f["iTag"], f["data"]), name="call")
        elif ev.name == "close":
            log.warning("closing a robot that does not read", user=self.user, robot=self.robot, reason=f["reason"])
            self.tasks.spawn(self.close(f["reason"]), name="close")

    async def _request(self, type_: str, data: dict) -> None:
        try:
            await self.master.call("robot_request", timeout=REQUEST_TIMEOUT, user=self.user, robot=self.robot,
                                   type=type_, data=data)
        except RCEError as e:
            self.session.request_done(e.message)
        else:
            self.session.request_done()
        self._pump()

    async def _call(self, itag: str, data: dict) -> None:
        iface = self.interfaces.get(itag)
        try:
            if iface is None:
                raise RCEError(f"interface {itag!r} was removed")
            resp = await iface.call_from_robot(data)
        except RCEError as e:
            self.session.fail_call(data, e.message)
        else:
            self.session.answer_call(data, resp)
        self._pump()

    async def _expire(self) -> None:
        while True:
            await asyncio.sleep(min(EXPIRY_CHECK, self.session.assembler.expiry / 2))   # a timer
            self.session.tick(time.monotonic())
            self._pump()

    async def close(self, reason: str) -> None:
        """End the session: the robot sees a close with ``reason``."""
        await self.ws.close(CLOSE_POLICY, reason[:CLOSE_REASON_MAX])

    def stats(self) -> dict:
        """This robot's counters (:meth:`RobotSession.stats`) with its user and robot ID."""
        return {"user": self.user, "robot": self.robot, **self.session.stats()}
