"""How a client connection outlives a lost link (docs/INTERNALS.md "Session resume", "Moving to
another endpoint"), as nats.py reconnects: with ``allow_reconnect`` the connection asks for session
resume, dials the same robot endpoint again with backoff and resumes the session with its token;
messages sent meanwhile are kept and sent after the resume, calls and barriers in flight stay pending.
A connection made by a login whose robot endpoint died (its dials refused ``gone_after`` times in a
row) logs in again and moves to the endpoint the master names, in a fresh session.
"""
from __future__ import annotations

import asyncio
import re
import ssl
import time
from dataclasses import dataclass
from typing import Any, Callable

from websockets.asyncio.client import ClientConnection

from rce.plumbing.errors import AuthError, Unavailable
from rce.plumbing.log import get_logger
from rce.transport.masterlink import Backoff
from rce.protocol.resume import DEFAULT_GRACE, DEFAULT_RESUME_BUFFER
from rce.protocol.session import ClientSession
from rce.plumbing.tasks import Tasks
from rce_client.routes import Routes
from rce_client.dial import CONNECT_TIMEOUT, HandshakeRefused, Unreachable, dial, login, open_robot_link, with_query

log = get_logger("rce.client")

RECONNECT_WAIT = 0.05            # s before the second attempt to reconnect; it doubles after each failure ...
RECONNECT_WAIT_MAX = 1.0         # s ... up to this: a robot endpoint that is reachable again is found within 1 s
ENDPOINT_GONE_AFTER = 5         # dials refused in a row (connection refused or reset: nothing listens) after which
                                # the robot endpoint counts as dead and the robot logs in again to move to another
                                # one: about 0.75 s of backoff (0.05 + 0.1 + 0.2 + 0.4 s), jitter aside
FINAL_CLOSE = (1000, 1008)       # close codes by which the cloud ends a session: nothing to resume
LINK_EVENTS = ("disconnected", "reconnected", "resumed", "moved")    # what on_* callbacks are told of


@dataclass(frozen=True)
class Reconnect:
    """How a connection with ``allow_reconnect`` reconnects and resumes (the knobs of nats.py's
    ``connect``): ``max_attempts`` dials per gap (None: until the session's grace, which the cloud
    gives, has passed since the drop); ``time_wait``: s before the second dial, doubling after each
    failure up to ``max_wait`` s (with jitter, :class:`rce.transport.masterlink.Backoff`); ``resume_buffer``:
    messages kept until the cloud acks them (past it the oldest are lost and counted);
    ``timeout``: s for each dial's handshake; ``gone_after``: dials refused in a row after which the
    endpoint counts as dead, and a connection made by a login moves to the endpoint the master names."""

    max_attempts: int | None = None
    time_wait: float = RECONNECT_WAIT
    max_wait: float = RECONNECT_WAIT_MAX
    resume_buffer: int = DEFAULT_RESUME_BUFFER
    timeout: float = CONNECT_TIMEOUT
    gone_after: int = ENDPOINT_GONE_AFTER


class Reconnecting:
    """Reconnect, resume and move for a :class:`~rce_client.connection.Connection` (mixed into it)."""

    reconnect: Reconnect | None
    relogin: tuple[str, str, str] | None
    session: ClientSession
    ws: ClientConnection
    ws_url: str
    user_id: str
    robot_id: str
    ssl_context: ssl.SSLContext | None
    routes: Routes | None
    max_lag: float | None
    mptcp: bool
    close_reason: str | None
    moves: int
    moved_lost: int
    tasks: Tasks
    _link_cbs: dict[str, list[Callable[[Any], Any]]]
    _reader: asyncio.Task

    def on_disconnected(self, cb: Callable[[str], Any]) -> None:
        """(``allow_reconnect``) Call ``cb(reason)`` when the link is lost and the session kept: the
        connection reconnects and resumes; sends and calls wait meanwhile."""
        self._link_cbs["disconnected"].append(cb)

    def on_reconnected(self, cb: Callable[[str], Any]) -> None:
        """(``allow_reconnect``) Call ``cb(ws_url)`` when a new link is open (the resume follows)."""
        self._link_cbs["reconnected"].append(cb)

    def on_resumed(self, cb: Callable[[dict], Any]) -> None:
        """(``allow_reconnect``) Call ``cb(data)`` when the session is resumed: ``data`` is the cloud's
        ``ST {"topic": "session", "status": "resumed", "ack", "dropped", ...}`` (``dropped``: messages to
        the robot the cloud's buffer lost)."""
        self._link_cbs["resumed"].append(cb)

    def on_moved(self, cb: Callable[[dict], Any]) -> None:
        """(``allow_reconnect``, made by a login) Call ``cb({"ws_url", "lost"})`` when the robot endpoint
        died and a fresh session is open on the one the master named (``ws_url``): the cloud re-creates the
        robot's interfaces and connections there (``iu true``); ``lost``: messages to the cloud that
        were in flight or sent during the gap, lost with the dead endpoint. Calls in flight failed."""
        self._link_cbs["moved"].append(cb)

    def _resuming(self, ws: ClientConnection, reason: str) -> bool:
        """The link is lost: keep the session and start reconnecting, when it can be resumed."""
        rcvd = ws.protocol.close_rcvd
        if self.reconnect is None or self.close_reason is not None or (rcvd is not None and rcvd.code in FINAL_CLOSE):
            return False
        if not self.session.detach(reason):
            return False
        self._dispatch()
        log.info("link to the cloud lost; resuming", robot=self.robot_id, reason=reason)
        for cb in self._link_cbs["disconnected"]:
            self._run_cb(cb, reason)
        self.tasks.spawn(self._reconnect(), name="reconnect")
        return True

    async def _reconnect(self) -> None:
        """Dial the robot endpoint with the resume query until it takes it (then the new link's reader
        waits for the cloud's ST resumed), the grace has passed, or it refuses: then the connection closes.
        A connection made by a login whose endpoint refused ``gone_after`` dials in a row moves
        (:meth:`_move`) to the endpoint the master names."""
        r = self.reconnect
        backoff = Backoff(r.time_wait, cap=max(r.time_wait, r.max_wait))
        deadline = time.monotonic() + (self.session.grace or DEFAULT_GRACE)
        attempts = refused = 0
        said: set[str] = set()
        while True:
            attempts += 1
            url = with_query(self.ws_url, userID=self.user_id, robotID=self.robot_id, **self.session.resume_query())
            try:
                if self.relogin is not None and refused >= r.gone_after:
                    if await self._move():
                        return
                    refused = 0                 # the endpoint lives (or the master has not seen it die yet)
                    if "same endpoint" not in said:
                        said.add("same endpoint")
                        log.info("the master still names this robot endpoint: resuming there",
                                 robot=self.robot_id, url=self.ws_url)
                    continue
                ws = await dial(url, r.timeout, self.ssl_context, self.routes, self.mptcp)
                break
            except (HandshakeRefused, AuthError) as e:  # 401: the session expired (or the token is wrong); 400: bad ack
                self.close_reason = f"the cloud refused to resume the session ({e})"
            except Unavailable as e:
                # once the endpoint counts as dead, a failed move (the master is away, or has not seen it die yet)
                # is tried again after the backoff
                refused = refused + 1 if isinstance(e, Unreachable) or refused >= r.gone_after else 0
                if (why := _reason(e.message)) not in said:
                    said.add(why)
                    log.info("reconnect attempt failed; retrying", robot=self.robot_id, attempt=attempts,
                             reason=e.message)
                delay = backoff.next()
                if (r.max_attempts is None or attempts < r.max_attempts) and time.monotonic() + delay < deadline:
                    await asyncio.sleep(delay)      # the backoff, a timer
                    continue
                self.close_reason = f"could not resume the session ({attempts} attempt(s)): {e.message}"
            log.info("connection closed", robot=self.robot_id, reason=self.close_reason)
            await self._finish()
            return
        self.ws = ws
        self.session.attach()
        self._reader = self.tasks.spawn(self._read_loop(ws), name="reader")
        log.info("reconnected; resuming", robot=self.robot_id, url=self.ws_url, attempts=attempts)
        for cb in self._link_cbs["reconnected"]:
            self._run_cb(cb, self.ws_url)

    async def _move(self) -> bool:
        """The robot endpoint looks dead: log in at the master again and, when it names another endpoint,
        open a fresh session (``resume=1``) there, where the cloud re-creates the robot's interfaces and
        connections (docs/INTERNALS.md "Session resume", "Moving to another endpoint"). What the old
        session kept is lost (counted in :attr:`moved_lost`), its calls and barriers fail. False (nothing
        done) when the master names the same endpoint: it lives, and the session is resumed there.
        Raises :class:`Unavailable` (the master is unreachable; try again) or :class:`AuthError`."""
        master_url, password, version = self.relogin
        timeout = self.reconnect.timeout
        ws_url = await login(master_url, self.user_id, version, timeout, self.ssl_context, self.routes,
                             self.robot_id)
        if ws_url == self.ws_url:
            return False
        ws = await open_robot_link(ws_url, self.user_id, password, self.robot_id, timeout=timeout,
                                   ssl_context=self.ssl_context, resume=True, max_lag=self.max_lag,
                                   routes=self.routes, mptcp=self.mptcp)
        old = self.session
        lost = len(old.outgoing) if old.outgoing is not None else 0
        old.close(f"the robot endpoint {self.ws_url} died; the session moved to {ws_url}")
        self._dispatch()                             # calls and barriers in flight fail
        self.session = ClientSession(expiry=old.assembler.expiry, resume=True,
                                     resume_buffer=self.reconnect.resume_buffer)
        self.ws, self.ws_url = ws, ws_url
        self.moves += 1
        self.moved_lost += lost
        self._reader = self.tasks.spawn(self._read_loop(ws), name="reader")
        log.warning("robot endpoint died; moved to another", robot=self.robot_id, url=ws_url, lost=lost)
        for cb in self._link_cbs["moved"]:
            self._run_cb(cb, {"ws_url": ws_url, "lost": lost})
        return True


def _reason(message: str) -> str:
    """A failure's kind, for saying each once: its text without numbers (ports, counts, times)."""
    return re.sub(r"[0-9.:]+", "#", message)
