"""The fleet's JSON HTTP API and Prometheus metrics, on ``rce-fleet serve``'s web server.

Routes (the fleet manager's :class:`~rce_fleet.operations.tasks_client.TaskChannel` does the work):

==========================  =========================================================================
``POST /api/tasks``         body ``{"errands": ["pick1", "42"], "priority": 0, "earliest_start_s": 0,
                            "deadline_s": 0, "id": ""}`` -> 201 and the task; 400 (bad request), 409
                            (the id exists) with ``{"error", "code"}``;
                            a field not listed here is a 400
``GET /api/tasks``          the task list: ``tasks`` (open, then recently closed), ``robots`` (each
                            robot's task, activity, battery), counts and times
``GET /api/tasks/ID``       one task, 404 when the fleet does not know it
``DELETE /api/tasks/ID``    cancel it -> 200 and the task; 404 unknown, 409 already closed
``GET /metrics``            Prometheus text: tasks by state, queue length, task times, per-robot
                            utilisation, battery and tasks done
==========================  =========================================================================

A task is ``{"id", "errands", "cells", "priority", "state", "robot", "next_errand", "reason",
"source", "created", "earliest_start", "deadline", "assigned", "active", "finished", "reached"}``
(times in fleet seconds, 0: not reached; ``reached``: the time each errand was reached, in order).
A request the fleet does not answer within 10 s is a 504.
"""
from __future__ import annotations

import json

from aiohttp import web

from .tasks_client import TaskChannel, TaskRefused

__all__ = ["add_routes", "prometheus_text"]

STATUS = {"bad_request": 400, "not_found": 404, "conflict": 409, "timeout": 504}
FIELDS = ("errands", "priority", "earliest_start_s", "deadline_s", "id")   # of a POST's body


def _error(status: int, code: str, text: str) -> web.Response:
    return web.json_response({"error": text, "code": code}, status=status)


def add_routes(app: web.Application, channel: TaskChannel) -> None:
    """Add the task API and ``/metrics`` (module docstring) to ``app``."""

    async def post(req: web.Request) -> web.Response:
        try:
            body = await req.json()
        except (json.JSONDecodeError, UnicodeDecodeError):
            return _error(400, "bad_request", "the body must be a JSON object")
        if not isinstance(body, dict):
            return _error(400, "bad_request", "the body must be a JSON object")
        if unknown := sorted(set(body) - set(FIELDS)):     # a misspelt "priority" is not silently 0
            return _error(400, "bad_request", f"unknown field(s) {', '.join(map(repr, unknown))} "
                                              f"(a task has {', '.join(FIELDS)})")
        errands = body.get("errands")
        if not isinstance(errands, list) or not all(isinstance(e, (str, int)) and not isinstance(e, bool)
                                                    for e in errands):
            return _error(400, "bad_request", "errands must be a list of cell numbers or place names")
        try:
            prio, es, dl = (float(body.get(k, 0.0) or 0.0) for k in ("priority", "earliest_start_s", "deadline_s"))
        except (TypeError, ValueError):
            return _error(400, "bad_request", "priority, earliest_start_s and deadline_s must be numbers")
        try:
            task = await channel.add(errands, priority=prio, earliest_start_s=es, deadline_s=dl,
                                     task_id=str(body.get("id") or ""))
        except TaskRefused as e:
            return _error(STATUS.get(e.code, 400), e.code, e.reason)
        return web.json_response(task, status=201, headers={"Location": f"/api/tasks/{task['id']}"})

    async def listing(_req: web.Request) -> web.Response:
        return web.json_response(_public(channel.latest))

    async def one(req: web.Request) -> web.Response:
        t = channel.get(req.match_info["id"])
        if t is None:
            return _error(404, "not_found", f"no task {req.match_info['id']!r} among the open and recent tasks")
        return web.json_response(t)

    async def delete(req: web.Request) -> web.Response:
        try:
            return web.json_response(await channel.cancel(req.match_info["id"]))
        except TaskRefused as e:
            return _error(STATUS.get(e.code, 400), e.code, e.reason)

    async def metrics(_req: web.Request) -> web.Response:
        return web.Response(text=prometheus_text(channel.latest), content_type="text/plain", charset="utf-8",
                            headers={"Cache-Control": "no-store"})

    app.router.add_post("/api/tasks", post)
    app.router.add_get("/api/tasks", listing)
    app.router.add_get("/api/tasks/{id}", one)
    app.router.add_delete("/api/tasks/{id}", delete)
    app.router.add_get("/metrics", metrics)


def _public(task_list: dict | None) -> dict:
    tl = dict(task_list or {})
    tl.pop("answers", None)
    tl.pop("header", None)
    return tl


def prometheus_text(task_list: dict | None) -> str:
    """The Prometheus exposition text of a ``fleet/TaskList`` (JSON form); empty metrics
    before the first one."""
    tl = task_list or {}
    lines = []

    def metric(name: str, kind: str, help_: str, samples: list[tuple[str, float]]) -> None:
        lines.append(f"# HELP {name} {help_}")
        lines.append(f"# TYPE {name} {kind}")
        lines.extend(f"{name}{labels} {value:g}" for labels, value in samples)

    metric("rce_fleet_tasks_total", "counter", "Tasks closed, by final state.",
           [(f'{{state="{s}"}}', float(tl.get(s, 0))) for s in ("done", "failed", "cancelled")])
    states = {}
    for t in tl.get("tasks", []):
        if t["state"] in ("queued", "assigned", "active"):
            states[t["state"]] = states.get(t["state"], 0) + 1
    metric("rce_fleet_tasks_open", "gauge", "Open tasks, by state.",
           [(f'{{state="{s}"}}', float(states.get(s, 0))) for s in ("queued", "assigned", "active")])
    metric("rce_fleet_tasks_deadline_missed_total", "counter", "Tasks that missed their deadline.",
           [("", float(tl.get("deadline_missed", 0)))])
    metric("rce_fleet_task_seconds", "gauge", "Seconds from creation to done over done tasks (mean, p95).",
           [('{stat="mean"}', float(tl.get("mean_s", 0.0))), ('{stat="p95"}', float(tl.get("p95_s", 0.0)))])
    robots = tl.get("robots", [])
    metric("rce_fleet_robot_utilisation", "gauge", "Share of a robot's time on a task.",
           [(f'{{robot="{r["robot"]}"}}', r["busy_s"] / r["since_s"] if r.get("since_s") else 0.0) for r in robots])
    metric("rce_fleet_robot_battery_percent", "gauge", "A robot's battery level (-1: not reported).",
           [(f'{{robot="{r["robot"]}"}}', float(r.get("battery_pct", -1.0))) for r in robots])
    metric("rce_fleet_robot_tasks_done_total", "counter", "Tasks a robot finished.",
           [(f'{{robot="{r["robot"]}"}}', float(r.get("tasks_done", 0))) for r in robots])
    metric("rce_fleet_robot_charges_total", "counter", "Charging sessions a robot began.",
           [(f'{{robot="{r["robot"]}"}}', float(r.get("charges", 0))) for r in robots])
    return "\n".join(lines) + "\n"
