"""ROS 2 message, service and action types, and their CDR serialization.

A class named in ROS 2's form, ``pkg/msg/Type``, ``pkg/srv/Type`` or ``pkg/action/Type``
(:func:`is_ros2_name`), is a ROS 2 type: its messages travel as CDR (OMG DDS-XTypes XCDR1, little
endian, behind the 4-byte encapsulation header: what rclpy's ``serialize_message`` writes and a
ROS 2 subscription's ``raw=True`` reads), never re-encoded on the engine's internal hops. A class
in ROS 1's form, ``pkg/Type``, stays a ROS 1 type (:mod:`rce.messages.registry`).

Definitions come from rosbags' Jazzy typestore (``Stores.ROS2_JAZZY``: the common interfaces),
then from the ``.msg``, ``.srv`` and ``.action`` files every ROS 2 package installs under
``share/<pkg>/{msg,srv,action}`` of an ament prefix (``AMENT_PREFIX_PATH``, and this Python's own
prefix, where the PyPI wheels of ROS 2 put them), loaded on first use with the types they use. A
service ``pkg/srv/T`` is the pair ``T_Request`` and ``T_Response``; an action ``pkg/action/T``
brings ``T_Goal``, ``T_Result``, ``T_Feedback`` and the types rosidl generates for its parts
(``T_SendGoal``, ``T_GetResult``, ``T_FeedbackMessage``, :mod:`rce.interfaces.actions`; the layouts
of rosidl's ``action/action.idl.em`` templates).
"""
from __future__ import annotations

import os
import re
import sys
from pathlib import Path
from typing import Any

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.base import Nodetype

from rce.interfaces.classes import is_ros2_name
from rce.messages.registry import MessageRegistry, set_ros2_factory
from rce.plumbing.errors import MessageError

_NAME = re.compile(r"([A-Za-z][A-Za-z0-9_]*)/(msg|srv|action)/([A-Za-z][A-Za-z0-9_]*)")
#: Suffixes of the types rosidl generates for an action's parts, with their layouts (.msg syntax).
_ACTION_PARTS = {
    "_SendGoal_Request": "unique_identifier_msgs/UUID goal_id\n{T}_Goal goal",
    "_SendGoal_Response": "bool accepted\nbuiltin_interfaces/Time stamp",
    "_GetResult_Request": "unique_identifier_msgs/UUID goal_id",
    "_GetResult_Response": "int8 status\n{T}_Result result",
    "_FeedbackMessage": "unique_identifier_msgs/UUID goal_id\n{T}_Feedback feedback",
}
_ACTION_SERVICES = ("_SendGoal", "_GetResult")
#: The one field rosidl gives an empty message (a struct needs a member; its CDR is one byte).
_EMPTY = [("structure_needs_at_least_one_member", (Nodetype.BASE, ("uint8", 0)))]


def split_name(cls: str) -> tuple[str, str, str]:
    """``pkg/msg/T`` -> ``(pkg, "msg", T)``; :class:`MessageError` for another form."""
    m = _NAME.fullmatch(cls.strip("/")) if isinstance(cls, str) else None
    if m is None:
        raise MessageError(f"malformed ROS 2 class {cls!r}: expected 'pkg/msg/Type', 'pkg/srv/Type' or "
                           f"'pkg/action/Type'")
    return m.group(1), m.group(2), m.group(3)


def ament_prefixes() -> list[Path]:
    """Where ROS 2 packages are installed: ``AMENT_PREFIX_PATH``'s entries, then this Python's prefix."""
    out = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    return out + [Path(sys.prefix)]


class Ros2Registry(MessageRegistry):
    """The ROS 2 half of the message registry: the same JSON codec as ROS 1's
    (:class:`~rce.messages.registry.MessageRegistry`, over the Jazzy typestore) with CDR as the
    serialization. Type names here are the typestore's (``std_msgs/msg/String``,
    ``std_srvs/srv/Trigger_Request``, ``test_msgs/action/Fibonacci_SendGoal_Request``).

    ``prefixes``: ament prefixes to look for definitions in (default :func:`ament_prefixes`)."""

    def __init__(self, prefixes: list[Path] | None = None) -> None:
        super().__init__()
        self.store = get_typestore(Stores.ROS2_JAZZY)
        self.prefixes = list(prefixes) if prefixes is not None else ament_prefixes()
        self._missing: set[str] = set()       # definitions looked for and not found (looked for once)

    # -- definitions --------------------------------------------------------------------------
    def _find(self, pkg: str, sub: str, name: str) -> Path | None:
        for prefix in self.prefixes:
            f = prefix / "share" / pkg / sub / f"{name}.{sub}"
            if f.is_file():
                return f
        return None

    @staticmethod
    def _parse(f: Path, pkg: str, sub: str, base: str) -> dict:
        """The types of definition file ``f`` (``.msg``; ``.srv``: request ``---`` response; ``.action``:
        goal ``---`` result ``---`` feedback, with the types of its parts)."""
        halves = {"msg": ("",), "srv": ("_Request", "_Response"), "action": ("_Goal", "_Result", "_Feedback")}[sub]
        texts = re.split(r"^---[ \t]*$", f.read_text(), flags=re.M)
        if len(texts) != len(halves):
            raise MessageError(f"{f}: expected {len(halves)} part(s) separated by '---', found {len(texts)}")
        name = f"{pkg}/{sub}/{base}"
        types: dict = {}
        parts = list(zip(halves, texts, strict=True))
        if sub == "action":
            parts += [(suffix, text.replace("{T}", name)) for suffix, text in _ACTION_PARTS.items()]
        for half, text in parts:
            # parsed as the package's message (its plain type names are the package's messages, as
            # rosidl reads them), then named as what it is
            definition, = get_types_from_msg(text, f"{pkg}/msg/{base}{half}").values()
            types[name + half] = definition
        return types

    def _ensure(self, typename: str) -> bool:
        """Load ``typename`` (a typestore name) and what it uses, if a definition is installed.
        Returns whether it is known now."""
        if typename in self.store.fielddefs:
            return True
        if typename in self._missing:
            return False
        pkg, sub, name = split_name(typename)
        base = name.removesuffix("_Request").removesuffix("_Response") if sub == "srv" else name
        if sub == "action":
            base = next((name[:-len(s)] for s in (*_ACTION_PARTS, "_Goal", "_Result", "_Feedback")
                         if name.endswith(s)), name)
        f = self._find(pkg, sub, base)
        if f is None:
            self._missing.add(typename)
            return False
        try:
            types = self._parse(f, pkg, sub, base)
        except MessageError:
            raise
        except Exception as e:   # rosbags raises several parser error types
            raise MessageError(f"{f}: cannot read the ROS 2 definition: {e}") from e
        for _, (_, fields) in types.items():       # first what they use
            for _, (nt, arg) in fields:
                sub_t = arg[0] if nt in (Nodetype.ARRAY, Nodetype.SEQUENCE) else (nt, arg)
                if sub_t[0] == Nodetype.NAME and sub_t[1] not in types and not self._ensure(sub_t[1]):
                    raise MessageError(f"{f}: uses {sub_t[1]!r}, which has no ROS 2 definition installed")
        self._register(typename, types)
        return typename in self.store.fielddefs

    # -- lookup -------------------------------------------------------------------------------
    def msg_type(self, wire: str) -> str:
        """Typestore name of ROS 2 message class ``wire`` (``pkg/msg/T``, or an action's
        ``pkg/action/T_FeedbackMessage``, ``_Goal``, ``_Result``, ``_Feedback``); :class:`MessageError`
        if it is not a message class or no definition is installed."""
        pkg, sub, name = split_name(wire)
        typename = f"{pkg}/{sub}/{name}"
        if sub == "srv" or (sub == "action" and not any(name.endswith(s) for s in
                                                         ("_FeedbackMessage", "_Goal", "_Result", "_Feedback"))):
            raise MessageError(f"{wire!r} is a ROS 2 {'service' if sub == 'srv' else 'action'}, not a message class")
        if not self._ensure(typename):
            raise MessageError(f"unknown ROS 2 message class {wire!r}: no definition in rosbags' Jazzy types nor "
                               f"under share/{pkg}/{sub}/ of {os.pathsep.join(map(str, self.prefixes))}")
        return typename

    def srv_types(self, wire: str) -> tuple[str, str]:
        """(request, response) typestore names of ROS 2 service class ``wire`` (``pkg/srv/T``, or an
        action's ``pkg/action/T_SendGoal`` / ``T_GetResult``); :class:`MessageError` if unknown."""
        pkg, sub, name = split_name(wire)
        if sub == "msg" or (sub == "action" and not name.endswith(_ACTION_SERVICES)):
            raise MessageError(f"{wire!r} is not a ROS 2 service class")
        req, resp = f"{pkg}/{sub}/{name}_Request", f"{pkg}/{sub}/{name}_Response"
        if not (self._ensure(req) and self._ensure(resp)):
            raise MessageError(f"unknown ROS 2 service class {wire!r}: no definition in rosbags' Jazzy types nor "
                               f"under share/{pkg}/{sub}/ of {os.pathsep.join(map(str, self.prefixes))}")
        return req, resp

    # -- CDR ----------------------------------------------------------------------------------
    def codec(self, typename: str) -> None:
        """No compiled codec: CDR goes through rosbags' (de)serializers."""
        return None

    def serialize(self, typename: str, msg: Any) -> bytes:
        """CDR (little endian, with its encapsulation header) of typestore instance ``msg``.
        Raises :class:`MessageError`."""
        try:
            return bytes(self.store.serialize_cdr(msg, typename))
        except Exception as e:
            raise MessageError(f"cannot serialize {typename}: {e}") from e

    def deserialize(self, typename: str, data: bytes | memoryview) -> Any:
        """The typestore instance of CDR ``data``; :class:`MessageError` if it does not fit ``typename``."""
        buf = bytes(data)
        if len(buf) < 4 or buf[0] != 0 or buf[1] not in (0, 1):
            raise MessageError(f"{len(buf)} bytes are not CDR of {typename}: no CDR encapsulation header "
                               f"(got {buf[:4].hex() or 'nothing'})")
        try:
            return self.store.deserialize_cdr(buf, typename)
        except Exception as e:
            raise MessageError(f"{len(buf)} bytes do not deserialize as {typename}: {e or type(e).__name__}") from e

    def check_structure(self, typename: str, payload: bytes | memoryview) -> None:
        """Check that CDR ``payload`` fits ``typename`` (it is decoded: CDR's alignment leaves no
        cheaper walk). Raises :class:`MessageError` naming the class."""
        self.deserialize(typename, payload)

    def to_json(self, typename: str, msg: Any, forms=None) -> Any:
        """As :meth:`MessageRegistry.to_json`; an empty message (``std_srvs/srv/Trigger``'s request) is
        ``{}``, without the placeholder rosidl gives it in CDR (``structure_needs_at_least_one_member``)."""
        if self.store.fielddefs[typename][1] == _EMPTY:
            return {}
        return super().to_json(typename, msg, forms)

    def json_to_bytes(self, typename: str, obj: Any, forms=None) -> bytes:
        return self.serialize(typename, self.from_json(typename, obj, forms))

    def bytes_to_json(self, typename: str, data: bytes, forms=None) -> Any:
        return self.to_json(typename, self.deserialize(typename, data), forms)


set_ros2_factory(Ros2Registry)
__all__ = ["Ros2Registry", "ament_prefixes", "is_ros2_name", "split_name"]
