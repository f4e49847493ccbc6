"""What the operator page may send through the fleet's server into the fleet container, sans I/O.

The page's live view is an RCE session (``rce.js``) that the fleet's web server carries to the robot
endpoint as the fleet's internal user (:mod:`rce_fleet.live.page_door`), so the person behind the page
never holds the internal user's password. :class:`PageRules` reads each frame the page sends and lets
through only what the page itself does (``live/web/fleet.js``), for the person's role:

- ``CN`` with ``addInterfaces``/``removeInterfaces`` only: robot-side converters on the page's own
  robotID, and container-side interfaces whose tag starts with ``ROBOTID_`` on the fleet's topics
  (:data:`READS` for anyone; :data:`WRITES` for an operator or above), each with its topic's class;
- ``CX`` between the page's own interfaces, or the probe ``rce.js`` sends after a request (two tags
  ``rcesyncID/a``, ``rcesyncID/b`` that exist nowhere, which the cloud refuses with an ER);
- ``DM`` on the page's own robot-side ``SubscriberConverter`` (an operator's); a task, a cancel or a
  block gets ``source`` ``page:USER``, whatever the page wrote (who did what is the server's to say);
- ``AK`` (acknowledgements of a resumed session).

Anything else (``CC``, ``DC``, another endpoint's interfaces, another topic, binary frames) raises
:class:`PageRefused` naming it; the shell then closes the page's link (1008). A frame is never changed but
for the ``source`` it stamps (its ``seq`` is kept, so a resumed session's numbering holds).
"""
from __future__ import annotations

import re
from typing import Any

import orjson

from rce.protocol.limits import short_repr

from .api_auth import allows

__all__ = ["READS", "WRITES", "ROBOT_ID", "PageRules", "PageRefused"]

READS = {"/fleet/state": "fleet/FleetState", "/fleet/tasks": "fleet/TaskList"}
WRITES = {"/fleet/goal": "fleet/RobotGoal", "/fleet/block": "fleet/CellBlock", "/fleet/task": "fleet/Task",
          "/fleet/task_cancel": "fleet/TaskCancel", "/fleet/mission": "std_msgs/String"}
STAMPED = {"fleet/Task", "fleet/TaskCancel", "fleet/CellBlock"}     # classes whose ``source`` the server sets
ROBOT_ID = re.compile(r"^operator-[A-Za-z0-9]{1,32}$")             # the page's robotIDs (fleet.js)
TAG = re.compile(r"^[A-Za-z0-9_-]{1,96}$")
PROBE = re.compile(r"^(rcesync[A-Za-z0-9]{1,32})/([ab])$")
TYPES = {"CN", "CX", "DM", "AK"}


class PageRefused(ValueError):
    """A frame the page may not send; the message says what and why."""


class PageRules:
    """The rules of one page session (module docstring): ``user`` and ``role`` (the person's, from the
    page's token), ``robot_id`` (the page's, :data:`ROBOT_ID`), ``ctag`` (the fleet container)."""

    def __init__(self, user: str, role: str, robot_id: str, ctag: str):
        if not ROBOT_ID.match(robot_id):
            raise PageRefused(f"robotID {short_repr(robot_id)}: the page's are operator-ID (letters and digits)")
        self.user, self.role, self.robot_id, self.ctag = user, role, robot_id, ctag
        self.operator = allows(role, "operator")
        self.writers: dict[str, str] = {}       # the page's SubscriberConverter tags -> class

    def text(self, frame: str) -> str:
        """The frame to forward (``frame`` itself, or with a stamped ``source``); raises :class:`PageRefused`."""
        try:
            m = orjson.loads(frame)
        except orjson.JSONDecodeError as e:
            raise PageRefused(f"not JSON: {e}") from None
        if not isinstance(m, dict) or m.get("type") not in TYPES or not isinstance(m.get("data"), dict):
            kind = m.get("type") if isinstance(m, dict) else type(m).__name__
            raise PageRefused(f"a {short_repr(kind)} message: the page may send {', '.join(sorted(TYPES))} only")
        data = m["data"]
        match m["type"]:
            case "CN":
                self._configure(data)
            case "CX":
                self._connect(data)
            case "DM":
                if self._message(data):
                    return orjson.dumps(m).decode()
        return frame

    def binary(self) -> None:
        """A binary frame: the page sends none (its interfaces are converters); raises :class:`PageRefused`."""
        raise PageRefused("binary frames: the page's interfaces are converters (JSON)")

    # -- the rules ----------------------------------------------------------------------------------
    def _configure(self, data: dict) -> None:
        if set(data) - {"addInterfaces", "removeInterfaces"}:
            raise PageRefused(f"CN {', '.join(sorted(set(data) - {'addInterfaces', 'removeInterfaces'}))}: the page "
                          "may add and remove interfaces only")
        for i in _items(data.get("addInterfaces", []), "CN addInterfaces"):
            self._add(i)
        for i in _items(data.get("removeInterfaces", []), "CN removeInterfaces"):
            if not self._own(str(i.get("endpointTag")), str(i.get("interfaceTag"))):
                raise PageRefused(f"CN removeInterfaces {i.get('endpointTag')}/{i.get('interfaceTag')}: "
                                  f"not this page's")

    def _add(self, i: dict) -> None:
        etag, itag, kind, cls = (str(i.get(k, "")) for k in ("endpointTag", "interfaceTag", "interfaceType",
                                                            "className"))
        where = f"CN addInterfaces {etag}/{itag}"
        if not self._own(etag, itag):
            raise PageRefused(f"{where}: not this page's (its robot {self.robot_id}, or "
                              f"{self.ctag}/{self.robot_id}_...)")
        if etag == self.robot_id:
            if kind == "SubscriberConverter" and self.operator:
                self.writers[itag] = cls
            elif kind != "PublisherConverter":
                raise PageRefused(f"{where}: a {kind} {self._needs(kind == 'SubscriberConverter')}")
            return
        topic = str(i.get("addr", ""))
        table = READS if kind == "SubscriberInterface" else WRITES if kind == "PublisherInterface" else None
        if table is None or table.get(topic) != cls:
            raise PageRefused(f"{where}: a {kind} of {cls} on {topic!r} is not one of the page's")
        if table is WRITES and not self.operator:
            raise PageRefused(f"{where}: {self._needs(True)}")

    def _connect(self, data: dict) -> None:
        if set(data) - {"connect", "disconnect"}:
            raise PageRefused("CX: connect and disconnect only")
        for pair in _items(data.get("connect", []), "CX connect") + _items(data.get("disconnect", []), "CX disconnect"):
            a, b = str(pair.get("tagA", "")), str(pair.get("tagB", ""))
            pa, pb = PROBE.match(a), PROBE.match(b)
            if pa and pb and pa.group(1) == pb.group(1):
                continue
            if not (self._own_tag(a) and self._own_tag(b)):
                raise PageRefused(f"CX {a} - {b}: not between this page's interfaces")

    def _message(self, data: dict) -> bool:
        itag = str(data.get("iTag", ""))
        cls = self.writers.get(itag)
        if cls is None:
            raise PageRefused(f"DM on {itag!r}: not one of this page's publishing interfaces")
        msg = data.get("msg")
        if cls in STAMPED and isinstance(msg, dict):
            msg["source"] = f"page:{self.user}"
            return True
        return False

    # -- whose is a tag ---------------------------------------------------------------------------
    def _own(self, etag: str, itag: str) -> bool:
        if not TAG.match(itag):
            return False
        return etag == self.robot_id or (etag == self.ctag and itag.startswith(f"{self.robot_id}_"))

    def _own_tag(self, tag: str) -> bool:
        etag, sep, itag = tag.partition("/")
        return bool(sep) and self._own(etag, itag)

    def _needs(self, writes: bool) -> str:
        return (f"publishes into the fleet: user {self.user!r} is {self.role}, this needs operator or above"
                if writes else "is not an interface the page uses")


def _items(value: Any, where: str) -> list[dict]:
    if not isinstance(value, list) or not all(isinstance(x, dict) for x in value):
        raise PageRefused(f"{where}: expected a list of objects")
    return value
