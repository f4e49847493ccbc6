"""Batteries of the fleet's robots, sans-I/O.

- :class:`BatteryParams`: capacity (Wh), drain per metre driven (Wh/m) and per second
  (W, always, idle or not), charging power at a charger (W), the level below which a robot
  is sent to charge (default 20 %), the level it charges to (default 90 %) and the level a
  simulated battery starts at (default full; with ``initial_spread``, each simulated battery
  starts somewhere between ``initial - initial_spread`` and ``initial``, as a fleet's do). The fleet
  manager sets them as the ``/fleet/battery`` parameter; the global planner's dispatcher
  uses them to estimate what a task costs.
- :class:`Battery`: one simulated battery; :meth:`Battery.step` drains and charges it by
  the distance driven and the time passed, never below 0; :meth:`Battery.message` is its
  ``sensor_msgs/BatteryState`` (as a ROS driver publishes it: ``percentage`` 0..1,
  ``power_supply_status`` 1 charging / 2 discharging / 4 full, ``charge`` and ``capacity`` in
  Ah at the nominal ``voltage``).

The defaults are a small AMR's: 100 Wh, 0.03 Wh/m and 3 W, charged at 50 W.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

__all__ = ["BATTERY_PARAM", "BATTERY_TOPIC", "Battery", "BatteryParams", "battery_links"]

BATTERY_PARAM = "/fleet/battery"
BATTERY_TOPIC = "/battery"              # the robot's local topic (as a ROS driver names it)
T_BATTERY = "sensor_msgs/BatteryState"
STATUS_CHARGING, STATUS_DISCHARGING, STATUS_FULL = 1, 2, 4   # sensor_msgs/BatteryState POWER_SUPPLY_STATUS_*


@dataclass(frozen=True)
class BatteryParams:
    """See the module docstring. Raises ValueError for a capacity <= 0, a negative drain or
    power, or levels outside 0 < threshold < recharge <= 1."""

    capacity_wh: float = 100.0
    drain_wh_per_m: float = 0.03
    idle_w: float = 3.0
    charge_w: float = 50.0
    threshold: float = 0.20
    recharge: float = 0.90
    voltage: float = 24.0
    initial: float = 1.0
    initial_spread: float = 0.0

    def __post_init__(self):
        if not self.capacity_wh > 0:
            raise ValueError(f"battery capacity must be > 0 Wh, got {self.capacity_wh}")
        if min(self.drain_wh_per_m, self.idle_w, self.charge_w) < 0:
            raise ValueError("battery drain and charging power must be >= 0")
        if not 0 < self.threshold < self.recharge <= 1:
            raise ValueError(f"battery levels need 0 < threshold ({self.threshold}) < recharge ({self.recharge}) <= 1")
        if not 0 < self.initial <= 1:
            raise ValueError(f"a battery's initial level must be in (0, 1], got {self.initial}")
        if not 0 <= self.initial_spread < self.initial:
            raise ValueError(f"initial_spread must be >= 0 and below initial ({self.initial}), "
                             f"got {self.initial_spread}")

    def to_param(self) -> dict:
        """JSON form (the ``/fleet/battery`` parameter)."""
        return asdict(self)

    @classmethod
    def from_param(cls, p: dict | None) -> BatteryParams | None:
        """From :meth:`to_param`'s form (None: no batteries); unknown keys are ignored."""
        if not p:
            return None
        names = set(cls.__dataclass_fields__)
        return cls(**{k: float(v) for k, v in p.items() if k in names})

    def energy_wh(self, metres: float, seconds: float) -> float:
        """Wh to drive ``metres`` taking ``seconds``."""
        return metres * self.drain_wh_per_m + seconds * self.idle_w / 3600.0


@dataclass
class Battery:
    """One robot's battery: ``params``, ``wh`` stored (starts full unless given); ``min_wh``
    the lowest it has been; ``charges`` charging sessions begun; ``flat`` whether it ever hit 0."""

    params: BatteryParams
    wh: float = -1.0                 # -1: the params' initial level
    min_wh: float = field(default=-1.0)
    charges: int = 0
    charging: bool = False
    flat: bool = False

    def __post_init__(self):
        if self.wh < 0:
            self.wh = self.params.initial * self.params.capacity_wh
        self.wh = min(self.wh, self.params.capacity_wh)
        self.min_wh = self.wh

    @property
    def fraction(self) -> float:
        """Charge, 0..1."""
        return self.wh / self.params.capacity_wh

    def step(self, dt: float, metres: float, on_charger: bool) -> None:
        """Advance ``dt`` s in which the robot drove ``metres``; it charges when ``on_charger``
        and not moving (a new session counts in ``charges``)."""
        p = self.params
        self.wh -= p.energy_wh(metres, dt)
        charging = on_charger and metres < 1e-3
        if charging:
            if not self.charging:
                self.charges += 1
            self.wh += p.charge_w * dt / 3600.0
        self.charging = charging
        if self.wh <= 0:
            self.wh, self.flat = 0.0, True
        self.wh = min(self.wh, p.capacity_wh)
        self.min_wh = min(self.min_wh, self.wh)

    def message(self, stamp: dict) -> dict:
        """The ``sensor_msgs/BatteryState`` message (JSON form) with header ``stamp``."""
        p = self.params
        full = self.wh >= p.capacity_wh - 1e-9
        status = STATUS_FULL if full and self.charging else STATUS_CHARGING if self.charging else STATUS_DISCHARGING
        return {"header": {"stamp": stamp, "frame_id": "base_link"}, "voltage": p.voltage,
                "current": (p.charge_w if self.charging else -p.idle_w) / p.voltage,
                "charge": self.wh / p.voltage, "capacity": p.capacity_wh / p.voltage,
                "design_capacity": p.capacity_wh / p.voltage, "percentage": self.fraction,
                "power_supply_status": status, "power_supply_health": 1, "power_supply_technology": 3,
                "present": True}


def battery_links(n: int, ctag: str) -> tuple[list[dict], list[dict]]:
    """The interfaces and connection that carry robot ``Robot<n>``'s ``/battery`` to
    ``/Robot<n>/battery`` in the fleet container (robot config form: eTag, iTag, ...)."""
    rid = f"Robot{n}"
    c_tag, r_tag = f"batteryReceiver_{n}", f"batterySender_{n}"
    ifaces = [{"eTag": ctag, "iTag": c_tag, "iType": "PublisherInterface", "iCls": T_BATTERY,
               "addr": f"/{rid}/battery"},
              {"eTag": rid, "iTag": r_tag, "iType": "SubscriberForwarder", "iCls": T_BATTERY, "addr": BATTERY_TOPIC}]
    return ifaces, [{"tagA": f"{ctag}/{c_tag}", "tagB": f"{rid}/{r_tag}"}]
