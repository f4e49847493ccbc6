"""A client connection's bulk link (docs/lanes.md): a second websocket to the same robot endpoint that
joins the session with its token (``?userID=U&robotID=R&session=TOKEN&lane=bulk``) and carries the bulk
lane's topic data both ways, while the session's own link becomes the control lane.

- Marks: the bulk link DSCP CS1, the session's link DSCP EF with ``TCP_NODELAY`` and a small
  ``TCP_NOTSENT_LOWAT`` (:func:`rce.transport.lane_socket.mark`).
- Out: each bulk interface keeps its newest messages waiting (:class:`~rce.protocol.outbox.Outbox`, as
  a ROS publisher's queue: :data:`BULK_QUEUE` in all, none older than :data:`BULK_MAX_LAG` s while a newer
  one waits); a writer sends one whole message at a time, in frames of at most 16 KiB
  paced as ``rate`` says (:func:`~rce.interfaces.pacer.new_pacer`: bytes/s; ``"auto"`` or None: under the
  rate estimated for the uplink's path from the bulk socket, :class:`~rce.transport.lane_socket.PacedLink`;
  ``"off"``: not paced). Drops are counted.
- In: the cloud's bulk DMs go to the same handlers as those on the session's link.
- A bulk link that drops is dialled again with backoff while the session lives; meanwhile bulk data
  goes on the session's link, as without lanes. A cloud that refuses the join (an endpoint without
  lanes: 400) leaves the connection on one link, and so does a path through a relay (docs/relays.md)
  until the session is back on its direct path.
"""
from __future__ import annotations

import asyncio
import time
from typing import Any, Protocol

from websockets.exceptions import ConnectionClosed

from rce.plumbing.errors import Unavailable
from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks
from rce.protocol.frames import DM
from rce.interfaces.lanes import Lane
from rce.protocol.outbox import Outbox
from rce.interfaces.pacer import Pacing, new_pacer
from rce.interfaces.rate_estimator import Mode
from rce.protocol.session import ClientSession
from rce.transport import lane_socket
from rce.transport.lane_socket import PacedLink, fragments, socket_of
from rce.transport.masterlink import Backoff
from rce_client.dial import HandshakeRefused, dial, with_query

log = get_logger("rce.client")

BULK_QUEUE = 8             # bulk messages waiting for the bulk link; past it the busiest interface drops its oldest
BULK_MAX_LAG = 0.5         # s a bulk message may wait while a newer one of its interface waits behind it
REDIAL_WAIT, REDIAL_WAIT_MAX = 0.05, 1.0      # s between dials of a dropped bulk link, doubling up to the max
ESTIMATE_LOG_MOVE = 0.2    # an estimated uplink rate is logged when it moved by this share since the last line,
ESTIMATE_LOG_EVERY = 1.0   # or the pacer went to or from cruising under it; at most once in this many s


class LaneOwner(Protocol):
    """What the bulk lane uses of its :class:`rce_client.connection.Connection`."""

    session: ClientSession
    ws: Any
    ws_url: str
    user_id: str
    robot_id: str
    reconnect: Any
    ssl_context: Any
    mptcp: bool
    routes: Any               # rce_client.routes.Routes | None

    @property
    def closed(self) -> bool:
        """Has the connection ended?"""

    async def _session_changed(self) -> None:
        """Wait until the session's state changes."""

    def _dispatch(self) -> None:
        """Do what the session's events say."""

    async def send(self, type_: str, data: Any, newest_of: str | None = None) -> None:
        """Send one message on the session's link (``newest_of``: its interface, when a newer one supersedes it)."""


class BulkLane:
    """The bulk link of ``conn``; ``rate``: how its writer is paced (bytes/s, ``"auto"`` or None: the
    path's rate estimated, ``"off"``: not paced; :func:`~rce.interfaces.pacer.new_pacer`). Counters:
    :attr:`sent` (messages written whole), :attr:`bytes`, :attr:`dropped` (the newest-per-interface
    bound), :attr:`joins` (links joined), :attr:`received` (DMs taken on it); :meth:`pacing`."""

    def __init__(self, conn: LaneOwner, rate: Pacing | None = None):
        self.conn, self.rate = conn, rate
        self.pacer = new_pacer(rate)      # one for the lane: a link joined again starts from what it learnt
        self.queue: Outbox[tuple[str, str, Any]] = Outbox(BULK_QUEUE, BULK_MAX_LAG)     # (iTag, type, msg)
        self.ws: Any = None
        self.sent = self.bytes = self.joins = 0
        self.refused: str | None = None          # why the cloud refused the join (then the connection has one link)
        self._logged: tuple[float, float, bool] | None = None     # (when, estimate, cruising) last logged
        self._wake = asyncio.Event()
        self._joined = asyncio.Condition()       # notified when a bulk link joins
        self.tasks = Tasks(f"rce-client {conn.robot_id} bulk lane")
        self.tasks.spawn(self._run(), name="bulk-link")

    @property
    def up(self) -> bool:
        """Is a bulk link joined now?"""
        return self.ws is not None

    @property
    def dropped(self) -> int:
        return self.queue.dropped

    @property
    def received(self) -> int:
        return self.conn.session.bulk_in

    def pacing(self) -> dict | None:
        """The uplink's pacing (:meth:`~rce.interfaces.pacer.Pacer.stats`: ``rate_source``, ``rate`` bytes/s,
        and when estimated ``rate_estimate`` bytes/s, ``rate_mode``, ...); None: not paced."""
        return self.pacer.stats() if self.pacer is not None else None

    async def wait_up(self, timeout: float, joins: int = 1) -> None:
        """Wait until a bulk link is up and ``joins`` have been joined in all. Raises :class:`Unavailable`
        after ``timeout`` s (with the cloud's refusal, if it refused)."""
        try:
            async with self._joined, asyncio.timeout(timeout):
                await self._joined.wait_for(lambda: self.up and self.joins >= joins)
        except TimeoutError:
            raise Unavailable(f"no bulk link after {timeout:g} s" + (f": {self.refused}" if self.refused else "")) \
                from None

    def put(self, itag: str, type_: str, msg: Any) -> None:
        """Queue topic DM ``{iTag, type, msg}`` for the bulk link (each interface keeps its newest)."""
        self.queue.put_data(itag, (itag, type_, msg), time.monotonic())
        self._wake.set()

    async def close(self) -> None:
        await self.tasks.cancel_all()
        if self.ws is not None:
            await self.ws.close()

    # -- the link --------------------------------------------------------------------------------
    async def _run(self) -> None:
        """Join, serve until the link drops, dial again with backoff while the session lives."""
        backoff = Backoff(REDIAL_WAIT, cap=REDIAL_WAIT_MAX)
        conn = self.conn
        while not conn.closed:
            session = conn.session
            relayed = conn.routes is not None and conn.routes.relay is not None
            if session.state != "live" or not session.token or relayed:     # a relay carries one link only
                await conn._session_changed()
                continue
            url = with_query(conn.ws_url, userID=conn.user_id, robotID=conn.robot_id, session=session.token,
                             lane=Lane.BULK.value)
            try:
                ws = await dial(url, conn.reconnect.timeout if conn.reconnect else 10.0, conn.ssl_context,
                                mptcp=conn.mptcp)
            except HandshakeRefused as e:
                if e.status == 400:              # an endpoint without lanes: one link it is
                    self.refused = f"the robot endpoint refused a bulk link: {e.reason}"
                    log.info("bulk lane refused; one link", robot=conn.robot_id, reason=e.reason)
                    return
                await asyncio.sleep(backoff.next())     # 401: the session is being resumed or moved; a timer
                continue
            except Unavailable:
                await asyncio.sleep(backoff.next())     # a timer
                continue
            backoff.failures = 0
            await self._serve(ws)

    async def _serve(self, ws: Any) -> None:
        conn = self.conn
        lane_socket.mark(socket_of(ws), Lane.BULK)
        lane_socket.mark(socket_of(conn.ws), Lane.CONTROL)
        self.ws = ws
        self.joins += 1
        async with self._joined:
            self._joined.notify_all()
        log.info("bulk link joined", robot=conn.robot_id, url=conn.ws_url)
        writer = self.tasks.spawn(self._writer(ws), name="bulk-writer")
        try:
            async for frame in ws:
                conn.session.receive_bulk(frame, time.monotonic())
                conn._dispatch()
        except ConnectionClosed:
            pass
        finally:
            writer.cancel()
            self.ws = None
        log.info("bulk link closed; bulk data goes on the session's link until it is back", robot=conn.robot_id)
        for itag, type_, msg in self.queue.drain():      # what waited goes on the session's link
            try:
                await conn.send(DM, {"iTag": itag, "type": type_, "msg": msg}, newest_of=itag)
            except Unavailable:
                return

    async def _writer(self, ws: Any) -> None:
        paced = PacedLink(self.pacer, socket_of(ws)) if self.pacer is not None else None
        try:
            while True:
                await self._wake.wait()
                self._wake.clear()
                while (item := self.queue.take(time.monotonic())) is not None:
                    frames = self.conn.session.bulk_frames(*item)
                    for f in frames:
                        await ws.send(paced.fragments(f) if paced is not None else fragments(f))
                    self.sent += 1
                    self.bytes += sum(len(f) for f in frames)
                    self._log_estimate(time.monotonic())
        except (ConnectionClosed, OSError):      # the reader sees it too
            pass

    def _log_estimate(self, now: float) -> None:
        """Log the uplink's estimated rate when it moved by :data:`ESTIMATE_LOG_MOVE`, or the pacer went
        to or from cruising under it (at most every :data:`ESTIMATE_LOG_EVERY` s)."""
        est = self.pacer.estimator if self.pacer is not None else None
        if est is None or est.estimate is None:
            return
        cruising = est.mode in (Mode.CRUISE, Mode.PROBE)
        if self._logged is not None:
            when, logged, was_cruising = self._logged
            if now - when < ESTIMATE_LOG_EVERY or (
                    abs(est.estimate - logged) < ESTIMATE_LOG_MOVE * logged and cruising == was_cruising):
                return
        self._logged = (now, est.estimate, cruising)
        log.info("uplink rate estimated", robot=self.conn.robot_id, **self.pacer.stats())

