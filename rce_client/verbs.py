"""Sending on a client connection: one writer at a time, and the requests (docs/design.md, section 3.3): CC,
DC, CN and CX, fire-and-forget as in the RCE alpha (the cloud answers a refused request with an ER
and reports interface and node states with ST), and the barrier that waits until the cloud has
handled everything sent before it.
"""
from __future__ import annotations

import asyncio
from typing import Any

from websockets.asyncio.client import ClientConnection
from websockets.exceptions import ConnectionClosed

from rce.protocol import frames
from rce.plumbing.errors import Timeout, Unavailable
from rce.plumbing.log import get_logger
from rce.protocol.session import ClientSession
from rce.plumbing.tasks import Tasks
from rce_client.dial import close_text

log = get_logger("rce.client")

WAIT_TIMEOUT = 30.0              # s a barrier or wait_interfaces_up waits for the cloud by default


class Verbs:
    """Sending and the requests of a :class:`~rce_client.connection.Connection` (mixed into it)."""

    session: ClientSession
    ws: ClientConnection
    reconnect: Any
    tasks: Tasks
    _barrier_ok: bool
    _send_lock: asyncio.Lock
    _kicked: bool

    # -- sending -----------------------------------------------------------------------------
    async def send(self, type_: str, data: Any, newest_of: str | None = None) -> None:
        """Send one message ``{"type": type_, "data": data}``; ``bytes`` values anywhere in
        ``data`` go as binary parts (JSON frame first, then one binary frame per part). ``newest_of``:
        the interface of a state or bulk topic message, whose newer message supersedes it while no link
        is up (:meth:`ClientSession.send`). Raises :class:`Unavailable` when the connection is closed."""
        self.session.send(type_, data, newest_of=newest_of)
        await self._write()

    async def _write(self) -> None:
        """Write what the session has to send, in order, on the current link (one writer at a time:
        frames leave in the order the session made them). Raises :class:`Unavailable` when the link
        closed, unless the session is kept for a resume (it then sends what the cloud did not get)."""
        async with self._send_lock:
            while frames := self.session.data_to_send():
                ws = self.ws
                try:
                    for f in frames:
                        await ws.send(f)
                except ConnectionClosed as e:
                    if self.reconnect is not None and self.session.state != "off":
                        return
                    raise Unavailable(f"connection to the cloud closed: {close_text(e)}") from None

    def _kick(self) -> None:
        """Frames the reader or a timer made (AKs, a resume's resend) go out, from a task."""
        if self.session.outbox and not self._kicked:
            self._kicked = True
            self.tasks.spawn(self._kicked_write(), name="write")

    async def _kicked_write(self) -> None:
        self._kicked = False
        try:
            await self._write()
        except Unavailable:      # the reader sees the closed link too
            pass

    async def create_container(self, tag: str, group: str | None = None, **container_data: Any) -> None:
        """CC: create container ``tag``. ``container_data`` keys: ``groupIp``, ``size``, ``cpu``
        (cores), ``memory`` (MiB), ``bandwidth``, ``specialFeatures``, and where it runs:
        ``placement`` (``auto``, ``cloud``, ``edge``, ``robot``), ``deadline_ms``, ``robot``,
        ``consumes``, ``ordered_moves``, ``spare`` (docs/placement.md); None values are left out."""
        cd = {k: v for k, v in {"group": group, **container_data}.items() if v is not None}
        data: dict = {"containerTag": tag}
        if cd:
            data["containerData"] = cd
        await self.send(frames.CC, data)

    async def destroy_container(self, tag: str) -> None:
        """DC: destroy container ``tag`` (with its nodes, interfaces and connections)."""
        await self.send(frames.DC, {"containerTag": tag})

    async def configure(self, cn_data: dict) -> None:
        """CN with raw data: any of ``addNodes``, ``removeNodes``, ``setParam``, ``deleteParam``,
        ``addInterfaces``, ``removeInterfaces``, each a list of components."""
        await self.send(frames.CN, cn_data)

    async def add_node(self, ctag: str, ntag: str, pkg: str, exe: str, args: str | list[str] = "",
                       name: str | None = None, namespace: str | None = None,
                       respawn: bool | dict | None = None) -> None:
        """CN addNodes: launch ``pkg``/``exe`` with ``args`` in container ``ctag`` as node ``ntag``."""
        node = {"containerTag": ctag, "nodeTag": ntag, "pkg": pkg, "exe": exe}
        for k, v in (("args", args), ("name", name), ("namespace", namespace), ("respawn", respawn)):
            if v not in (None, ""):
                node[k] = v
        await self.configure({"addNodes": [node]})

    async def remove_node(self, ctag: str, ntag: str) -> None:
        """CN removeNodes: stop node ``ntag`` of container ``ctag``."""
        await self.configure({"removeNodes": [{"containerTag": ctag, "nodeTag": ntag}]})

    async def set_param(self, ctag: str, name: str, value: Any) -> None:
        """CN setParam: set parameter ``name`` of container ``ctag`` to a JSON value."""
        await self.configure({"setParam": [{"containerTag": ctag, "name": name, "value": value}]})

    async def delete_param(self, ctag: str, name: str) -> None:
        """CN deleteParam: delete parameter ``name`` of container ``ctag``."""
        await self.configure({"deleteParam": [{"containerTag": ctag, "name": name}]})

    async def add_interface(self, etag: str, itag: str, itype: str, cls: str, addr: str | None = None,
                            lane: str | None = None) -> None:
        """CN addInterfaces: interface ``itag`` of type ``itype`` (e.g. ``PublisherInterface``,
        ``SubscriberConverter``) and message/service class ``cls`` on endpoint ``etag`` (a
        container tag, or this robot's ID for robot-side interfaces); ``addr`` is the topic or
        service name on that endpoint's bus; ``lane``: ``control``, ``state`` or ``bulk``
        (:mod:`rce.interfaces.lanes`; None: from ``cls``)."""
        itf = {"endpointTag": etag, "interfaceTag": itag, "interfaceType": itype, "className": cls}
        if addr:
            itf["addr"] = addr
        if lane is not None:
            itf["lane"] = lane
        await self.configure({"addInterfaces": [itf]})

    async def remove_interface(self, etag: str, itag: str) -> None:
        """CN removeInterfaces: remove interface ``etag/itag``."""
        await self.configure({"removeInterfaces": [{"endpointTag": etag, "interfaceTag": itag}]})

    async def connect_interfaces(self, tag_a: str, tag_b: str) -> None:
        """CX connect: wire interfaces ``tag_a`` and ``tag_b`` (each ``endpointTag/interfaceTag``)."""
        await self.send(frames.CX, {"connect": [{"tagA": tag_a, "tagB": tag_b}]})

    async def disconnect(self, tag_a: str, tag_b: str) -> None:
        """CX disconnect: remove the connection between ``tag_a`` and ``tag_b``."""
        await self.send(frames.CX, {"disconnect": [{"tagA": tag_a, "tagB": tag_b}]})

    async def barrier(self, timeout: float = WAIT_TIMEOUT) -> bool:
        """Wait until the cloud has processed every request sent before this call.

        The protocol has no acks, but the master handles a robot's requests one at a time,
        in order, and answers each refusal with an ER: this sends a CX between two interfaces
        that cannot exist and waits for the ER naming them (which is not passed to
        :meth:`on_error` callbacks). Returns True when passed; False when the cloud did not
        answer within ``timeout`` s, after which barriers are skipped (return False at once)
        for the rest of the connection. Raises :class:`Unavailable` when the connection closes."""
        if not self._barrier_ok:
            return False
        token = self.session.barrier()
        try:
            await self._write()
            await self.session.pending.wait(token, timeout)
            return True
        except Timeout:
            self._barrier_ok = False
            log.warning("the cloud did not answer a sync probe; barriers disabled", timeout=timeout)
            return False
        finally:
            self.session.pending.forget(token)
