"""ROS 2 actions over rosbridge v2: the action ops of rosbridge_suite's ROS 2 server (``ROSBRIDGE_PROTOCOL.md``
3.2.10 - 3.2.15; ``capabilities/send_action_goal.py``, ``advertise_action.py``, ``action_feedback.py``,
``action_result.py``), on the container's graph.

An action ``NAME`` of type ``pkg/action/T`` is five parts on the graph (:mod:`rce.interfaces.actions`: the
services ``NAME/_action/send_goal``, ``get_result``, ``cancel_goal`` and the topics ``feedback``, ``status``);
the session reaches each through a bridge of its own (:class:`~rce_robot.rosbridge.session.Bridge`), as it
reaches any topic or service, and plays the action client or server of ROS 2's action design
(https://design.ros2.org/articles/actions.html) on them:

- the client's **action client**: ``send_action_goal {id, action, action_type, args, feedback}`` sends the goal
  (a fresh goal UUID) to ``send_goal``; a refused goal, or a call that fails, answers ``action_result`` with
  ``result: false`` and the reason as ``values`` (status 0, unknown), as rosbridge does; an accepted one waits
  for ``get_result`` and answers ``action_result {id, action, values: the result, status, result: true}``;
  with ``feedback: true`` each of the goal's feedback messages goes as ``action_feedback {id, action, values}``
  (topic data: the newest kept when the client lags). ``cancel_action_goal {id, action}`` calls ``cancel_goal``
  for that goal once the server has answered its ``send_goal`` (a refusal gets a ``status`` warning); its
  ``action_result`` follows as the server ends it.
- the client's **action server**: ``advertise_action {action, type}`` serves the action on the graph: each goal a
  node sends is accepted and sent to the client as ``send_action_goal {id: "action_goal:NAME:N", action,
  action_type, args, feedback: true}``; a cancel request is sent as ``cancel_action_goal {id, action}`` (the
  goal counts as canceling); the client's ``action_feedback {id, action, values}`` is published on ``feedback``
  and its ``action_result {id, action, values, status, result}`` answers the goal's ``get_result`` calls
  (``result: false``: aborted). ``status`` carries the goals' states (GoalStatusArray) at each change.
  ``unadvertise_action {action}`` takes the five parts down.

Bounds: :data:`MAX_GOALS` goals in flight per session each way (more: refused, the client told), the
:data:`FINISHED_KEPT` last finished goals of a served action answer late ``get_result`` calls.
"""
from __future__ import annotations

import asyncio
import base64
import itertools
import os
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

from rce.interfaces.actions import PARTS, check_action_class, part_addr
from rce.interfaces.lanes import Lane
from rce.plumbing.errors import ProtocolError, RCEError, RequestError
from rce.plumbing.log import get_logger
from rce_robot.rosbridge.fragments import fragment_size_of

log = get_logger("rce.rosbridge")

# action_msgs/msg/GoalStatus
UNKNOWN, ACCEPTED, EXECUTING, CANCELING, SUCCEEDED, CANCELED, ABORTED = range(7)
TERMINAL = (SUCCEEDED, CANCELED, ABORTED)
# action_msgs/srv/CancelGoal return codes
ERROR_NONE, ERROR_REJECTED, ERROR_UNKNOWN_GOAL_ID = 0, 1, 2
MAX_GOALS = 256          # goals in flight per session, as client and as server each
FINISHED_KEPT = 64       # finished goals of a served action kept for late get_result calls
UUID_BYTES = 16          # unique_identifier_msgs/UUID
CLIENT_ROLES = {"send_goal": "c", "get_result": "c", "cancel_goal": "c", "feedback": "s"}   # status: not needed
PART = {p.name: p for p in PARTS}
SERVER_ROLES = {"send_goal": "v", "get_result": "v", "cancel_goal": "v", "feedback": "p", "status": "p"}


def goal_uuid(goal_id: Any) -> bytes:
    """The 16 bytes of a ``unique_identifier_msgs/UUID`` in JSON (``{"uuid": BASE64 | [ints]}``). Raises
    :class:`ProtocolError` for another shape."""
    raw = goal_id.get("uuid") if isinstance(goal_id, dict) else None
    try:
        out = base64.b64decode(raw, validate=True) if isinstance(raw, str) else bytes(raw)
    except (ValueError, TypeError):
        out = b""
    if len(out) != UUID_BYTES:
        raise ProtocolError(f"a goal_id must be {{uuid: {UUID_BYTES} bytes}}, got {goal_id!r:.80}")
    return out


def uuid_json(uuid: bytes) -> dict:
    """``unique_identifier_msgs/UUID`` ``uuid`` as JSON."""
    return {"uuid": list(uuid)}


def _stamp() -> dict:
    sec, ns = divmod(time.time_ns(), 1_000_000_000)
    return {"sec": sec, "nanosec": ns}


def _action_type(op: dict, key: str) -> str:
    try:
        return check_action_class(op.get(key))
    except ValueError as e:
        raise ProtocolError(f"{op.get('op')}: {key}: {e}") from None


def _name(op: dict) -> str:
    v = op.get("action")
    if not isinstance(v, str) or not v:
        raise ProtocolError(f"op {op.get('op')!r}: field 'action' must be a non-empty str, got {v!r}")
    return v


@dataclass
class ClientGoal:
    """A goal the client sent (``send_action_goal``): its op ``id``, ``action``, goal ``uuid``, what its
    answers go with, and ``sent``: set once the action server answered it (a cancel waits for that)."""
    op_id: Any
    action: str
    uuid: bytes
    feedback: bool
    fragment_size: int | None
    sent: asyncio.Event = field(default_factory=asyncio.Event)


@dataclass
class ServedGoal:
    """A goal a node sent to an action the client serves: the ``id`` the client knows it by, its ``uuid``,
    ``stamp`` (accepted), ``status``, ``result`` (once the client gave it) and the ``get_result`` calls waiting."""
    id: str
    uuid: bytes
    stamp: dict
    status: int = EXECUTING
    result: Any = None
    waiting: list = field(default_factory=list)


@dataclass
class ServedAction:
    """An action the client serves (``advertise_action``): its parts' bridges and goals (by UUID, in order)."""
    name: str
    type: str
    parts: dict[str, Any] = field(default_factory=dict)
    goals: OrderedDict[bytes, ServedGoal] = field(default_factory=OrderedDict)
    by_id: dict[str, ServedGoal] = field(default_factory=dict)
    ids: Any = field(default_factory=lambda: itertools.count(1))

    @property
    def running(self) -> int:
        return sum(g.status not in TERMINAL for g in self.goals.values())


class RosbridgeActions:
    """The action ops of one :class:`~rce_robot.rosbridge.session.RosbridgeSession` (:attr:`ops`, op -> handler),
    as the module docstring says. Counters: :attr:`goals_sent` (client goals sent), :attr:`goals_served`."""

    def __init__(self, session: Any):
        self.session = session
        self.goals: dict[Any, ClientGoal] = {}                        # op id -> a goal the client sent
        self.by_uuid: dict[bytes, ClientGoal] = {}
        self.served: dict[str, ServedAction] = {}                     # action name -> what the client serves
        self.goals_sent = self.goals_served = 0
        self._ids = itertools.count(1)
        self.ops = {"send_action_goal": self._send_goal, "cancel_action_goal": self._cancel_goal,
                    "advertise_action": self._advertise, "unadvertise_action": self._unadvertise,
                    "action_feedback": self._client_feedback, "action_result": self._client_result}

    # -- the client's action client -------------------------------------------------------------------------
    async def _client_parts(self, action: str, atype: str) -> dict[str, Any]:
        parts = {}
        for part in PARTS:
            role = CLIENT_ROLES.get(part.name)
            if role is not None:
                hook = {"on_message": self._feedback_of(action)} if part.name == "feedback" else {}
                parts[part.name] = await self.session._bridge(role, part_addr(action, part), part.class_for(atype),
                                                              Lane.CONTROL if role == "c" else None, **hook)
        return parts

    async def _send_goal(self, op: dict) -> None:
        action, atype = _name(op), _action_type(op, "action_type")
        args = op.get("args") or {}
        if not isinstance(args, dict):
            raise ProtocolError(f"send_action_goal {action!r}: args must be an object (the goal), got {args!r:.80}")
        if len(self.goals) >= MAX_GOALS:
            raise ProtocolError(f"send_action_goal {action!r}: {MAX_GOALS} goals are in flight; wait for a result")
        op_id = op.get("id") if op.get("id") is not None else f"send_action_goal:{action}:{next(self._ids)}"
        if op_id in self.goals:
            raise ProtocolError(f"send_action_goal {action!r}: goal id {op_id!r} is in flight already")
        size = fragment_size_of(op)
        parts = await self._client_parts(action, atype)
        goal = ClientGoal(op_id, action, os.urandom(UUID_BYTES), bool(op.get("feedback")), size)
        self.goals[op_id] = self.by_uuid[goal.uuid] = goal
        self.goals_sent += 1
        self.session.tasks.spawn(self._run(goal, parts, args), name=f"goal {action}")

    async def _run(self, goal: ClientGoal, parts: dict[str, Any], args: dict) -> None:
        """Send ``goal``, wait for its result and answer the client's ``send_action_goal`` with it."""
        s = self.session
        try:
            sent = await s._call(parts["send_goal"], {"goal_id": uuid_json(goal.uuid), "goal": args})
            goal.sent.set()
            if not (isinstance(sent, dict) and sent.get("accepted")):
                raise RequestError(f"the action server of {goal.action!r} rejected the goal")
            got = await s._call(parts["get_result"], {"goal_id": uuid_json(goal.uuid)})
            self._answer(goal, got.get("result"), int(got.get("status", UNKNOWN)), True)
        except RCEError as e:
            self._answer(goal, e.message, UNKNOWN, False)
        finally:
            goal.sent.set()
            self.goals.pop(goal.op_id, None)
            self.by_uuid.pop(goal.uuid, None)

    def _answer(self, goal: ClientGoal, values: Any, status: int, ok: bool) -> None:
        self.session.send({"op": "action_result", "id": goal.op_id, "action": goal.action, "values": values,
                           "status": status, "result": ok}, goal.fragment_size)

    def _feedback_of(self, action: str):
        def feedback(msg: Any) -> None:
            try:
                goal = self.by_uuid.get(goal_uuid(msg.get("goal_id") if isinstance(msg, dict) else None))
            except ProtocolError:
                return
            if goal is not None and goal.feedback:
                self.session.send({"op": "action_feedback", "id": goal.op_id, "action": action,
                                   "values": msg.get("feedback")}, goal.fragment_size,
                                  key=("action_feedback", goal.op_id), lane=Lane.STATE)
        return feedback

    async def _cancel_goal(self, op: dict) -> None:
        action = _name(op)
        goal = self.goals.get(op.get("id"))
        if goal is None or goal.action != action:
            raise ProtocolError(f"cancel_action_goal {action!r}: no goal {op.get('id')!r} of it is in flight")
        cancel = self.session.bridges.get(("c", part_addr(action, PART["cancel_goal"])))
        if cancel is None:
            raise ProtocolError(f"cancel_action_goal {action!r}: the action's cancel_goal service is not bridged")
        self.session.tasks.spawn(self._cancel(goal, cancel, op.get("id")), name=f"cancel {action}")

    async def _cancel(self, goal: ClientGoal, cancel: Any, op_id: Any) -> None:
        await goal.sent.wait()                 # a goal the server has not seen yet cannot be canceled there
        if self.goals.get(goal.op_id) is not goal:
            return                             # it ended meanwhile (refused, or its result came)
        try:
            got = await self.session._call(cancel, {"goal_info": {"goal_id": uuid_json(goal.uuid),
                                                                   "stamp": {"sec": 0, "nanosec": 0}}})
            code = got.get("return_code", ERROR_NONE) if isinstance(got, dict) else ERROR_NONE
            if code != ERROR_NONE:
                self.session.status("warning", f"cancel_action_goal {goal.action!r}: the action server refused "
                                               f"(return_code {code})", op_id)
        except RCEError as e:
            self.session.status("warning", f"cancel_action_goal {goal.action!r}: {e.message}", op_id)

    # -- the client's action server -------------------------------------------------------------------------
    async def _advertise(self, op: dict) -> None:
        action, atype = _name(op), _action_type(op, "type")
        served = self.served.get(action)
        if served is not None:
            if served.type != atype:
                raise ProtocolError(f"advertise_action {action!r}: already served with type {served.type!r}")
            return
        served = ServedAction(action, atype)
        hooks = {"send_goal": self._on_send_goal, "get_result": self._on_get_result,
                 "cancel_goal": self._on_cancel}
        for part in PARTS:
            role = SERVER_ROLES[part.name]
            hook = {"on_call": (lambda mid, req, f=hooks[part.name]: f(served, mid, req))} if role == "v" else {}
            served.parts[part.name] = await self.session._bridge(
                role, part_addr(action, part), part.class_for(atype), Lane.CONTROL if role == "v" else None, **hook)
        self.served[action] = served

    async def _unadvertise(self, op: dict) -> None:
        action = _name(op)
        served = self.served.pop(action, None)
        if served is None:
            raise ProtocolError(f"unadvertise_action: action {action!r} is not advertised (advertise_action first)")
        for bridge in served.parts.values():
            await self.session._drop(bridge)

    def _reply(self, served: ServedAction, part: str, msg_id: Any, msg: dict) -> None:
        """Answer the container's call ``msg_id`` to ``part`` of ``served`` with ``msg``."""
        iface = self.session.interfaces.get(served.parts[part].itag)
        if iface is None:
            return
        try:
            iface.from_robot({"msgID": msg_id, "msg": msg})
        except RCEError as e:       # the call timed out meanwhile, or the answer does not fit
            log.info("an action's answer was not taken", action=served.name, part=part, reason=e.message)

    def _on_send_goal(self, served: ServedAction, msg_id: Any, request: Any) -> None:
        try:
            uuid = goal_uuid(request.get("goal_id") if isinstance(request, dict) else None)
        except ProtocolError:
            self._reply(served, "send_goal", msg_id, {"accepted": False, "stamp": _stamp()})
            return
        if uuid in served.goals or sum(a.running for a in self.served.values()) >= MAX_GOALS:
            self._reply(served, "send_goal", msg_id, {"accepted": False, "stamp": _stamp()})
            return
        goal = ServedGoal(f"action_goal:{served.name}:{next(served.ids)}", uuid, _stamp())
        served.goals[uuid] = goal
        served.by_id[goal.id] = goal
        self.goals_served += 1
        self._reply(served, "send_goal", msg_id, {"accepted": True, "stamp": goal.stamp})
        self.session.send({"op": "send_action_goal", "id": goal.id, "action": served.name, "action_type": served.type,
                           "args": request.get("goal") or {}, "feedback": True})
        self._publish_status(served)

    def _on_get_result(self, served: ServedAction, msg_id: Any, request: Any) -> None:
        try:
            goal = served.goals.get(goal_uuid(request.get("goal_id") if isinstance(request, dict) else None))
        except ProtocolError:
            goal = None
        if goal is None:
            self._reply(served, "get_result", msg_id, {"status": UNKNOWN})
        elif goal.status in TERMINAL:
            self._reply(served, "get_result", msg_id, {"status": goal.status, "result": goal.result or {}})
        else:
            goal.waiting.append(msg_id)

    def _on_cancel(self, served: ServedAction, msg_id: Any, request: Any) -> None:
        info = request.get("goal_info") if isinstance(request, dict) else None
        try:
            uuid = goal_uuid(info.get("goal_id") if isinstance(info, dict) else None)
        except ProtocolError:
            uuid = b""
        every = uuid == bytes(UUID_BYTES)          # a zero goal id: cancel every goal (CancelGoal.srv)
        goals = [g for g in served.goals.values() if (every or g.uuid == uuid) and g.status not in TERMINAL]
        for g in goals:
            g.status = CANCELING
            self.session.send({"op": "cancel_action_goal", "id": g.id, "action": served.name})
        self._reply(served, "cancel_goal", msg_id, {
            "return_code": ERROR_NONE if goals else ERROR_UNKNOWN_GOAL_ID,
            "goals_canceling": [{"goal_id": uuid_json(g.uuid), "stamp": g.stamp} for g in goals]})
        if goals:
            self._publish_status(served)

    def _served_goal(self, op: dict) -> tuple[ServedAction, ServedGoal]:
        action = _name(op)
        served = self.served.get(action)
        if served is None:
            raise ProtocolError(f"{op['op']}: action {action!r} is not advertised by this client")
        goal = served.by_id.get(op.get("id"))
        if goal is None or goal.status in TERMINAL:
            raise ProtocolError(f"{op['op']} {action!r}: no goal {op.get('id')!r} of it is running")
        return served, goal

    async def _client_feedback(self, op: dict) -> None:
        served, goal = self._served_goal(op)
        values = op.get("values") or {}
        iface = self.session._iface(served.parts["feedback"])
        iface.from_robot({"msg": {"goal_id": uuid_json(goal.uuid), "feedback": values}})

    async def _client_result(self, op: dict) -> None:
        served, goal = self._served_goal(op)
        status = op.get("status")
        values = op.get("values")
        # result false, or a status that does not end a goal: aborted (as rosbridge's server ends it)
        goal.status = status if op.get("result") is not False and status in TERMINAL else ABORTED
        goal.result = values if isinstance(values, dict) else {}
        for msg_id in goal.waiting:
            self._reply(served, "get_result", msg_id, {"status": goal.status, "result": goal.result})
        goal.waiting.clear()
        served.by_id.pop(goal.id, None)
        self._publish_status(served)
        finished = [u for u, g in served.goals.items() if g.status in TERMINAL]
        for u in finished[:max(0, len(finished) - FINISHED_KEPT)]:
            del served.goals[u]

    def _publish_status(self, served: ServedAction) -> None:
        iface = self.session.interfaces.get(served.parts["status"].itag)
        if iface is None:
            return
        iface.from_robot({"msg": {"status_list": [
            {"goal_info": {"goal_id": uuid_json(g.uuid), "stamp": g.stamp}, "status": g.status}
            for g in served.goals.values()]}})

    def close(self) -> None:
        """The session ends: its goals are forgotten (their calls end with the interfaces)."""
        self.goals.clear()
        self.by_uuid.clear()
        self.served.clear()
