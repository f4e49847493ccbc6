"""An interface's ROS 2 quality of service (QoS), as a robot config gives it, sans rclpy.

ROS 2 matches a publisher with a subscription only where their QoS are compatible
(https://docs.ros.org/en/jazzy/Concepts/Intermediate/About-Quality-of-Service-Settings.html):
a ``best_effort`` publisher does not serve a ``reliable`` subscription, nor a ``volatile`` one a
``transient_local`` subscription. A config sets, per interface, the QoS its ROS 2 end uses:

- a profile by name: ``"default"`` (rmw_qos_profile_default: reliable, volatile, keep last 10),
  ``"sensor_data"`` (rmw_qos_profile_sensor_data: best effort, volatile, keep last 5),
  ``"services_default"`` (reliable, volatile, keep last 10), ``"map"`` (reliable, transient local,
  keep last 1: what map_server and Nav2 use for ``/map``);
- or an object, each key optional, over the default profile: ``reliability`` (``reliable`` |
  ``best_effort``), ``durability`` (``volatile`` | ``transient_local``), ``history`` (``keep_last`` |
  ``keep_all``), ``depth`` (messages, 1 - 10,000, with keep_last), or ``profile`` (one of the names
  above, the base of the other keys).

:func:`parse_qos` raises :class:`ValueError` naming the key and the values it takes.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

RELIABILITY = ("reliable", "best_effort")
DURABILITY = ("volatile", "transient_local")
HISTORY = ("keep_last", "keep_all")
MAX_DEPTH = 10_000      # messages a keep_last history holds at most (a bound on the bridge's memory)


@dataclass(frozen=True, slots=True)
class QoS:
    """One QoS profile: ``reliability``, ``durability``, ``history`` (strings of the tuples above)
    and ``depth`` (messages kept, with ``keep_last``)."""
    reliability: str = "reliable"
    durability: str = "volatile"
    history: str = "keep_last"
    depth: int = 10

    def as_dict(self) -> dict[str, Any]:
        """The profile as a config object (what :func:`parse_qos` reads back)."""
        return {"reliability": self.reliability, "durability": self.durability, "history": self.history,
                "depth": self.depth}


DEFAULT = QoS()
PROFILES = {
    "default": DEFAULT,
    "services_default": DEFAULT,
    "sensor_data": QoS(reliability="best_effort", depth=5),
    "map": QoS(durability="transient_local", depth=1),
}
#: The QoS rcl_action gives an action's status topic (rcl_action_qos_profile_status_default).
ACTION_STATUS = QoS(durability="transient_local", depth=1)


def _choice(key: str, value: Any, choices: tuple[str, ...]) -> str:
    if value not in choices:
        raise ValueError(f"qos.{key}: {value!r} is not one of {', '.join(choices)}")
    return value


def parse_qos(value: Any) -> QoS:
    """The :class:`QoS` of a config's ``qos`` value (None: the default profile). Raises
    :class:`ValueError` naming the key that is wrong."""
    if value is None:
        return DEFAULT
    if isinstance(value, QoS):
        return value
    if isinstance(value, str):
        return PROFILES[_choice("profile", value, tuple(PROFILES))]
    if not isinstance(value, dict):
        raise ValueError(f"qos: expected a profile name ({', '.join(PROFILES)}) or an object, got {value!r}")
    unknown = set(value) - {"profile", "reliability", "durability", "history", "depth"}
    if unknown:
        raise ValueError(f"qos: unknown key(s) {', '.join(sorted(unknown))}: expected profile, reliability, "
                         f"durability, history, depth")
    base = PROFILES[_choice("profile", value.get("profile", "default"), tuple(PROFILES))]
    depth = value.get("depth", base.depth)
    if isinstance(depth, bool) or not isinstance(depth, int) or not 1 <= depth <= MAX_DEPTH:
        raise ValueError(f"qos.depth: {depth!r} is not a whole number of messages in 1 - {MAX_DEPTH}")
    return replace(base, reliability=_choice("reliability", value.get("reliability", base.reliability), RELIABILITY),
                   durability=_choice("durability", value.get("durability", base.durability), DURABILITY),
                   history=_choice("history", value.get("history", base.history), HISTORY), depth=depth)
