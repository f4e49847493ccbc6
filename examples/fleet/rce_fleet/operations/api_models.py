"""The task API's request and response models (pydantic), and its OpenAPI 3.1 document built from them.

The models are the API's contract: :mod:`rce_fleet.operations.http_api` validates a ``POST /api/tasks``
body and a ``POST /api/login`` body with them, and :func:`openapi_document` publishes their JSON
Schemas (pydantic's, JSON Schema 2020-12, which OpenAPI 3.1 takes as it is) under
``components/schemas`` with the routes, the roles each needs and the security schemes
(``GET /api/openapi.json``). Field names are the fleet's (``fleet/TaskStatus``, ``fleet/TaskList``).
Every time says its clock: fleet time is the robots' clock, simulated seconds under ``rce-fleet serve`` and
``demo`` (``--speedup K``: K of them a wall second); a token's lifetime is wall time.
Sans-I/O: pydantic only.
"""
from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictFloat, StrictInt, StrictStr

from .tasks_api import ID_RE, MAX_ERRANDS

__all__ = ["ApiError", "FleetTask", "LoginAnswer", "LoginRequest", "RobotWork", "TaskList", "TaskRequest",
           "UserAdd", "UserChange", "UserChanged", "UserInfo", "UserList", "openapi_document"]

TaskState = Literal["queued", "assigned", "active", "done", "failed", "cancelled"]


class TaskRequest(BaseModel):
    """``POST /api/tasks``: a new task. A field not listed here is refused (a misspelt ``priority`` is
    not silently 0)."""
    model_config = ConfigDict(extra="forbid", title="TaskRequest")
    kind: ClassVar[str] = "task"
    hints: ClassVar[dict[str, str]] = {
        "errands": f"errands must be a list of 1 to {MAX_ERRANDS} cell numbers or place names",
        "id": "id: use 1-64 letters, digits or _ . : - (or none: the fleet names the task)",
        **dict.fromkeys(("priority", "earliest_start_s", "deadline_s"),
                        "priority, earliest_start_s and deadline_s must be numbers")}

    errands: list[StrictStr | StrictInt] = Field(
        max_length=MAX_ERRANDS, description=f"in order: cell numbers (42 or \"42\") or place names; 1 to {MAX_ERRANDS}")
    priority: StrictFloat = Field(0.0, description="higher first (one unit is worth about 100 cells of travel)")
    earliest_start_s: StrictFloat = Field(0.0, description="fleet s from now before which it does not start (the "
                                          "robots' clock: simulated s under rce-fleet serve, --speedup of them a "
                                          "wall second)")
    deadline_s: StrictFloat = Field(0.0, description="fleet s from now by which it must be done (0: none; the robots' "
                                    "clock: simulated s under rce-fleet serve, --speedup of them a wall second)")
    id: StrictStr = Field("", pattern=f"^({ID_RE.pattern[1:-1]})?$",
                          description="task id wanted (1-64 of A-Z a-z 0-9 _ . : -); empty: the fleet names it")


class FleetTask(BaseModel):
    """One task (``fleet/TaskStatus``). Times are fleet time, s: the robots' clock, simulated seconds under
    rce-fleet serve and demo (--speedup K: K of them a wall second); 0: not (yet) reached."""
    id: str
    errands: list[str] = Field(description="as given: place names, and cells as their numbers")
    cells: list[int] = Field(description="the errands' cells")
    priority: float
    state: TaskState
    robot: str = Field(description="its robot (empty: none)")
    next_errand: int = Field(description="index of the errand it waits for")
    reason: str = Field(description="why it failed or was cancelled")
    source: str = Field(description="who created it: http:USER (this API), cli:USER, operator:ROBOTID (the page), "
                                    "stream (a generated run)")
    cancelled_by: str = Field("", description="who cancelled it, in the same form as source (empty: not cancelled)")
    created: float = Field(description="fleet time it was created (simulated s)")
    earliest_start: float = Field(description="fleet time before which it does not start (simulated s; 0: none)")
    deadline: float = Field(description="fleet time by which it must be done (simulated s; 0: none)")
    assigned: float = Field(description="fleet time it was last given to a robot (simulated s; 0: not yet)")
    active: float = Field(description="fleet time its robot reached its first errand (simulated s; 0: not yet)")
    finished: float = Field(description="fleet time it was done, failed or cancelled (simulated s; 0: open)")
    reached: list[float] = Field(description="fleet time each errand was reached, in order (simulated s)")


class RobotWork(BaseModel):
    """One robot's work (``fleet/RobotTask``)."""
    robot: str
    task: str = Field(description="its task's id (empty: none)")
    activity: Literal["unknown", "idle", "parking", "task", "to_charger", "charging"]
    battery_pct: float = Field(description="battery level, % (-1: not reported)")
    busy_s: float = Field(description="fleet s spent on tasks so far (simulated s)")
    since_s: float = Field(description="fleet s since it was first seen (simulated s)")
    charges: int
    tasks_done: int
    stalled_s: float = Field(0.0, description="fleet s it has held work at one cell without progress, once it "
                             "stalled (60 simulated s; 0: it makes progress, or has nothing to do)")
    stalls: int = Field(0, description="stalls so far: each an alert and a recovery step")
    alert: str = Field("", description="its current stall: where, on what, what the fleet did (empty: none)")


class TaskList(BaseModel):
    """``GET /api/tasks``: the open tasks, then the most recently closed ones, each robot's work and the
    counts and times of closed tasks (``fleet/TaskList``)."""
    seq: int
    tasks: list[FleetTask]
    robots: list[RobotWork]
    queued: int
    done: int
    failed: int
    cancelled: int
    deadline_missed: int = Field(description="tasks done after their deadline or failed for it")
    mean_s: float = Field(description="mean simulated s from creation to done, over done tasks")
    p95_s: float = Field(description="95th percentile of the simulated s from creation to done")


class ApiError(BaseModel):
    """Every refusal: a one-line reason and a code."""
    error: str
    code: Literal["bad_request", "unauthorized", "forbidden", "not_found", "method_not_allowed", "conflict",
                  "too_large", "throttled", "internal", "bad_gateway", "unavailable", "timeout"]


class LoginRequest(BaseModel):
    """``POST /api/login``: a user of the master and the password; ``ttl_s`` asks for a token that expires
    sooner than the server's default."""
    model_config = ConfigDict(extra="forbid")
    kind: ClassVar[str] = "login"

    user: StrictStr = Field(min_length=1)
    password: StrictStr = Field(min_length=1)
    ttl_s: StrictFloat | None = Field(None, gt=0, description="wall s the token lives (at most the server's "
                                      "--token-ttl)")


class LoginAnswer(BaseModel):
    """A bearer token for ``Authorization: Bearer TOKEN`` until ``expires_in`` s from now (or logout, or a
    restart of the server: tokens live in its memory alone)."""
    token: str
    token_type: Literal["Bearer"] = "Bearer"
    expires_in: float = Field(description="wall s from now")
    user: str
    role: Literal["viewer", "operator", "admin"]
    survives_restart: Literal[False] = Field(False, description="false: a restart of rce-fleet serve ends every "
                                             "token (they live in its memory); log in again then")


Role = Literal["viewer", "operator", "admin"]
MIN_PASSWORD = 8            # characters of a password an admin sets, at least (as the first admin's)
MAX_PASSWORD = 1024         # ... at most
MAX_NAME = 64               # characters of a new user's name at most


class UserAdd(BaseModel):
    """``POST /api/users``: a new user of the master, with its role (default operator, as ``rce-console user
    add``'s)."""
    model_config = ConfigDict(extra="forbid")
    kind: ClassVar[str] = "user"
    hints: ClassVar[dict[str, str]] = {
        "name": f"name: 1-{MAX_NAME} letters, digits, '_', '-' or '.'",
        "password": f"password: {MIN_PASSWORD}-{MAX_PASSWORD} characters",
        "role": "role: viewer, operator or admin"}

    name: StrictStr = Field(min_length=1, max_length=MAX_NAME, pattern=r"^[A-Za-z0-9_.-]+$")
    password: StrictStr = Field(min_length=MIN_PASSWORD, max_length=MAX_PASSWORD)
    role: Role = "operator"


class UserChange(BaseModel):
    """``PATCH /api/users/NAME``: a new role, a new password, or both. Either ends the user's tokens and page
    sessions: the user logs in again (and gets the new role)."""
    model_config = ConfigDict(extra="forbid")
    kind: ClassVar[str] = "user change"
    hints: ClassVar[dict[str, str]] = {"password": UserAdd.hints["password"], "role": UserAdd.hints["role"]}

    role: Role | None = None
    password: StrictStr | None = Field(None, min_length=MIN_PASSWORD, max_length=MAX_PASSWORD)


class UserInfo(BaseModel):
    """A user of the master and its role."""
    name: str
    role: Role


class UserList(BaseModel):
    """``GET /api/users``: the master's users (people's; the fleet's internal user is none of them)."""
    users: list[UserInfo]


class UserChanged(BaseModel):
    """A user added, changed or removed (``role`` empty), and how many of its tokens ended."""
    name: str
    role: Role | Literal[""]
    revoked: int = Field(description="tokens of the user that ended (its page sessions with them)")


def _ref(name: str) -> dict:
    return {"$ref": f"#/components/schemas/{name}"}


def _json(schema: dict, description: str) -> dict:
    return {"description": description, "content": {"application/json": {"schema": schema}}}


def _op(summary: str, role: str | None, answers: dict[str, dict], body: str | None = None,
        path: str | None = None) -> dict:
    """One operation with every status it can give: ``answers``, and 500 for any; with a ``body``, 400 (a
    malformed one) and 413 (over 1 MiB); ``role`` None is open to anyone, else 401 without a credential, 403
    below ``role``, and for HTTP Basic (checked at the master) 429 and 503. ``path``: its path parameter."""
    err = _ref("ApiError")
    op: dict = {"summary": summary + (f" (role {role} or above)" if role else ""), "responses": dict(answers)}
    if body:
        op["requestBody"] = {"required": True, "content": {"application/json": {"schema": _ref(body)}}}
        op["responses"].setdefault("400", _json(err, "a malformed body: not JSON (a lone surrogate, a number "
                                                     "beyond a double), nested deeper than 64 levels, a field "
                                                     "unknown or of the wrong type"))
        op["responses"]["413"] = _json(err, "a body over 1 MiB")
    if path:
        op["parameters"] = [{"name": path, "in": "path", "required": True, "schema": {"type": "string"}}]
    if role is None:
        op["security"] = []
    else:
        op["responses"]["401"] = _json(err, "no credential, or a wrong, expired or revoked one")
        op["responses"]["403"] = _json(err, f"the user's role is below {role}")
        op["responses"].setdefault("429", _json(err, "HTTP Basic: too many failed logins; wait Retry-After s"))
        op["responses"].setdefault("503", _json(err, "HTTP Basic: the master cannot check the password now"))
    op["responses"]["500"] = _json(err, "an internal error (the server's log says more)")
    return op


def openapi_document(server_url: str = "/", metrics_public: bool = False) -> dict:
    """The OpenAPI 3.1 document of the task API (``GET /api/openapi.json``): the routes, the models'
    JSON Schemas and the security schemes (a bearer token from ``POST /api/login``, or HTTP Basic over
    TLS). ``server_url``: the API's base URL; ``metrics_public``: ``/metrics`` needs no credential."""
    from pydantic.json_schema import models_json_schema
    requests = (TaskRequest, LoginRequest, UserAdd, UserChange)
    models = [(m, "validation" if m in requests else "serialization")
              for m in (*requests, FleetTask, RobotWork, TaskList, ApiError, LoginAnswer, UserInfo, UserList,
                        UserChanged)]
    _, defs = models_json_schema(models, ref_template="#/components/schemas/{model}")
    err = _ref("ApiError")
    task = _json(_ref("FleetTask"), "the task")
    paths = {
        "/api/login": {"post": _op("Log in with a user of the master: a bearer token", None, {
            "200": _json(_ref("LoginAnswer"), "the token"),
            "401": _json(err, "a wrong user or password"),
            "429": _json(err, "too many failed logins: wait Retry-After s"),
            "503": _json(err, "the master cannot check the password now")}, body="LoginRequest")},
        "/api/logout": {"post": _op("Revoke the token the request carries", "viewer", {
            "200": {"description": "revoked"}})},
        "/api/tokens/{user}": {"delete": _op("Revoke every token of a user (and end its page sessions)", "admin", {
            "200": {"description": "how many were revoked"}}, path="user")},
        "/api/tasks": {
            "get": _op("The task list", "viewer", {"200": _json(_ref("TaskList"), "the tasks")}),
            "post": _op("Queue a task", "operator", {
                "201": {**task, "headers": {"Location": {"schema": {"type": "string"},
                                                         "description": "/api/tasks/ID"}}},
                "400": _json(err, "a bad request (unknown field, place, cell, ...)"),
                "409": _json(err, "the id exists"),
                "504": _json(err, "the fleet did not answer within 10 s")}, body="TaskRequest")},
        "/api/tasks/{id}": {
            "get": _op("One task", "viewer", {"200": task, "404": _json(err, "not among the open and recent tasks")},
                       path="id"),
            "delete": _op("Cancel a task", "operator", {"200": task, "400": _json(err, "refused by the fleet"),
                                                        "404": _json(err, "no such task"),
                                                        "409": _json(err, "already closed"),
                                                        "504": _json(err, "the fleet did not answer within 10 s")},
                          path="id")},
        "/api/users": {
            "get": _op("The master's users and their roles", "admin", {"200": _json(_ref("UserList"), "the users")}),
            "post": _op("Add a user of the master", "admin", {
                "201": _json(_ref("UserChanged"), "added"),
                "409": _json(err, "the user exists")}, body="UserAdd")},
        "/api/users/{name}": {
            "patch": _op("Give a user a role or a password; its tokens and page sessions end", "admin", {
                "200": _json(_ref("UserChanged"), "changed"), "404": _json(err, "no such user"),
                "409": _json(err, "the last admin would be none, or the user has robots connected")},
                body="UserChange", path="name"),
            "delete": _op("Remove a user; its tokens and page sessions end", "admin", {
                "200": _json(_ref("UserChanged"), "removed (role empty)"), "404": _json(err, "no such user"),
                "409": _json(err, "the last admin, or a user with robots connected")}, path="name")},
        "/api/openapi.json": {"get": _op("This document", None, {"200": {"description": "OpenAPI 3.1"}})},
        "/metrics": {"get": _op("Prometheus text: tasks by state, queue, task times, per-robot utilisation, "
                                "battery", None if metrics_public else "viewer",
                                {"200": {"description": "text/plain; version=0.0.4",
                                         "content": {"text/plain": {"schema": {"type": "string"}}}}})},
    }
    return {
        "openapi": "3.1.0",
        "info": {"title": "rce fleet task API", "version": "1",
                 "description": "Tasks for the warehouse fleet of rce-fleet serve. Credentials are the rce "
                                "master's users; roles: viewer (read), operator (add, cancel), admin (also "
                                "manage the users and revoke their tokens)."},
        "servers": [{"url": server_url}],
        "security": [{"bearer": []}, {"basic": []}],
        "paths": paths,
        "components": {"schemas": defs["$defs"],
                       "securitySchemes": {"bearer": {"type": "http", "scheme": "bearer",
                                                      "description": "a token from POST /api/login"},
                                           "basic": {"type": "http", "scheme": "basic",
                                                     "description": "a user and password of the master; over "
                                                                    "TLS only"}}},
    }
