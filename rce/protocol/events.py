"""What a session tells its shell: one small frozen class per event, and the unions of them
(the ``websockets`` library's model: ``Event = Request | Response | Frame``). A shell drains
:meth:`~rce.protocol.session.RobotSession.events_received` and dispatches with ``match`` (or
``isinstance``), ending in :func:`unhandled` for a type it does not know, so a misspelt event
cannot exist.

- :data:`RobotEvent`: what :class:`~rce.protocol.robot_session.RobotSession` (the cloud side) asks of the
  robot endpoint (:mod:`rce_robot.namespace`).
- :data:`ClientEvent`: what :class:`~rce.protocol.client_session.ClientSession` (the robot side) tells the
  client library (:mod:`rce_client.connection`).

The session test vectors (``tests/vectors/README.md``) and the browser's ``rce.js`` write events as
``{"event": name, ...fields under their wire keys}``; :func:`as_record` gives that form.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, NoReturn, get_args

from rce.protocol.schema import Component, RequestData


# -- the cloud side (RobotSession) -------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class RequestReady:
    """A robot's request (``type``: CC, DC, CN or CX; ``data``: its model, :func:`rce.protocol.schema.validate`)
    is next for the master: send it (``data.wire()``), then :meth:`~rce.protocol.session.RobotSession.request_done`."""
    type: str
    data: RequestData


@dataclass(frozen=True, slots=True)
class Deliver:
    """A DM from the robot (``data``: ``{iTag, type, msgID, msg}``) for topic interface ``itag``."""
    itag: str
    data: dict


@dataclass(frozen=True, slots=True)
class ServiceCall:
    """A service call from the robot (``data``: its DM) through ServiceProvider interface ``itag``:
    answer with :meth:`~rce.protocol.session.RobotSession.answer_call` or
    :meth:`~rce.protocol.session.RobotSession.fail_call`."""
    itag: str
    data: dict


@dataclass(frozen=True, slots=True)
class CloseLink:
    """The robot does not read (``reason`` says how much waits for it): close its link."""
    reason: str


@dataclass(frozen=True, slots=True)
class Lagging:
    """The endpoint has been behind the robot's frames for ``behind_s`` s and sheds its topic
    messages from now on."""
    behind_s: float


@dataclass(frozen=True, slots=True)
class CaughtUp:
    """The endpoint is no longer behind the robot; ``shed``: topic messages dropped meanwhile."""
    shed: int


RobotEvent = RequestReady | Deliver | ServiceCall | CloseLink | Lagging | CaughtUp


# -- the robot side (ClientSession) ----------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class StatusReceived:
    """An ST from the cloud (``data``: ``{"topic": "iu", ...}``, ``{"topic": "node", ...}``, ...)."""
    data: dict


@dataclass(frozen=True, slots=True)
class InterfaceChanged:
    """An ST ``iu``: interface ``itag`` is now ``up`` (connected) or not."""
    itag: str
    up: bool


@dataclass(frozen=True, slots=True)
class ErrorReceived:
    """An ER from the cloud that answers no call or barrier: ``reason``, its text."""
    reason: str


@dataclass(frozen=True, slots=True)
class MessageReceived:
    """A DM from the cloud that answers no call: for interface ``itag``, of class ``type``."""
    itag: Any
    type: Any
    msg_id: Any
    msg: Any


@dataclass(frozen=True, slots=True)
class ResponseReceived:
    """The response ``msg`` of the call ``msg_id`` (its waiter has it)."""
    msg_id: str
    msg: Any


@dataclass(frozen=True, slots=True)
class CallFailed:
    """The call ``msg_id`` failed: an ER naming it, or the link closed (``reason``)."""
    msg_id: str
    reason: str


@dataclass(frozen=True, slots=True)
class BarrierPassed:
    """The barrier ``token`` passed: every request sent before it was handled."""
    token: str


@dataclass(frozen=True, slots=True)
class BarrierFailed:
    """The barrier ``token`` failed: the link closed (``reason``)."""
    token: str
    reason: str


@dataclass(frozen=True, slots=True)
class Dropped:
    """Input from the cloud was dropped: a malformed frame, expired parts, an unexpected message."""
    reason: str


@dataclass(frozen=True, slots=True)
class SessionStatus:
    """(resume) An ``ST session`` from the cloud (``data``: started or resumed, with its fields)."""
    data: dict


@dataclass(frozen=True, slots=True)
class Detached:
    """(resume) The link is lost and the session kept: resume with ``session`` and ``ack``."""
    session: str | None
    ack: int


ClientEvent = (StatusReceived | InterfaceChanged | ErrorReceived | MessageReceived | ResponseReceived | CallFailed
               | BarrierPassed | BarrierFailed | Dropped | SessionStatus | Detached)

Event = RobotEvent | ClientEvent

#: each event's name in the session vectors and rce.js
NAMES: dict[type, str] = {
    RequestReady: "request", Deliver: "deliver", ServiceCall: "call", CloseLink: "close", Lagging: "lagging",
    CaughtUp: "caught_up", StatusReceived: "status", InterfaceChanged: "interface", ErrorReceived: "error",
    MessageReceived: "message", ResponseReceived: "response", CallFailed: "call_failed", BarrierPassed: "barrier",
    BarrierFailed: "barrier_failed", Dropped: "dropped", SessionStatus: "session", Detached: "detached"}
_WIRE_KEYS = {"itag": "iTag", "msg_id": "msgID"}        # field -> its key in the vectors; others keep their name


def members(union: Any) -> tuple[type, ...]:
    """The event classes of a union (:data:`RobotEvent`, :data:`ClientEvent`, :data:`Event`)."""
    return get_args(union)


def as_record(event: Event) -> dict[str, Any]:
    """``event`` as the session vectors write it: ``{"event": name, field: value, ...}`` with the wire's
    key names (``iTag``, ``msgID``)."""
    return {"event": NAMES[type(event)],
            **{_WIRE_KEYS.get(f.name, f.name): _wire(getattr(event, f.name)) for f in fields(event)}}


def _wire(value: Any) -> Any:
    """A field's value as the wire has it (a request's model: its wire form)."""
    return value.wire() if isinstance(value, Component) else value


def unhandled(event: object) -> NoReturn:
    """The end of a shell's dispatch: ``event`` is of a type it does not handle. Raises :class:`TypeError`."""
    raise TypeError(f"no handler for session event {event!r} (a {type(event).__name__})")
