"""The one robot-config loader (docs/design.md, section 3.6): the seed paper's ``robot1.config``
JSON, or YAML with the same keys.

The whole file is validated before anything is sent; a bad config raises
:class:`ConfigError` naming the file, the key path and the reason, e.g.
``configs/r1.config: interfaces[2].iType: unknown interface type 'Publisher'``.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from rce.interfaces import actions
from rce.interfaces.qos import QoS, parse_qos
from rce.plumbing.errors import ConfigError
from rce.protocol import schema
from rce.plumbing.text import key_path

# A config file uses the schema's field names (the short keys) and refuses keys it does not know.
_FILE = ConfigDict(extra="forbid", validate_by_name=True, validate_by_alias=False, loc_by_alias=False)


class _Model(BaseModel):
    model_config = _FILE


class ContainerSpec(schema.ContainerComponent):
    """A container to create: tag and optional placement and limits (cpu in cores, memory in MiB)."""
    model_config = _FILE

    def container_data(self) -> dict:
        """The CC ``containerData`` object for this spec (only keys that are set)."""
        d = self.model_dump(exclude={"cTag"}, exclude_none=True)
        if not d.get("specialFeatures"):
            d.pop("specialFeatures", None)
        return d


class NodeSpec(schema.NodeComponent):
    """A node to launch in a container (RCE addNodes component)."""
    model_config = _FILE

    def component(self) -> dict:
        """The CN addNodes component for this node."""
        return {k: v for k, v in self.model_dump(by_alias=True).items() if v not in (None, "")}


class ParameterSpec(schema.ParameterComponent):
    """A container parameter (any JSON value)."""
    model_config = _FILE


class InterfaceSpec(schema.InterfaceComponent):
    """An interface on an endpoint (a container tag, or the robot's own robotID). ``qos``: the QoS
    of its ROS 2 end (:mod:`rce.interfaces.qos`; a profile name or an object; absent: ROS 2's
    default). ``action``: set on the parts of an action entry (:mod:`rce.interfaces.actions`), the
    action's own iTag."""
    model_config = _FILE
    qos: QoS | None = None
    action: str | None = None

    @field_validator("qos", mode="before")
    @classmethod
    def _qos(cls, value: Any) -> QoS | None:
        return None if value is None else parse_qos(value)

    def component(self) -> dict:
        """The CN addInterfaces component for this interface."""
        return {k: v for k, v in self.model_dump(by_alias=True, exclude={"qos", "action"}).items()
                if v not in (None, "")}


class ConnectionSpec(schema.ConnectionComponent):
    """A connection between two interfaces, each ``endpointTag/interfaceTag``."""
    model_config = _FILE


class RobotConfig(_Model):
    """A robot config file (the seed paper's ``robot1.config``)."""
    url: str = Field(min_length=1)
    userID: str = Field(min_length=1)
    password: str
    robotID: str = Field(min_length=1)
    containers: list[ContainerSpec] = Field(default_factory=list)
    nodes: list[NodeSpec] = Field(default_factory=list)
    parameters: list[ParameterSpec] = Field(default_factory=list)
    interfaces: list[InterfaceSpec] = Field(default_factory=list)
    connections: list[ConnectionSpec] = Field(default_factory=list)

    @model_validator(mode="before")
    @classmethod
    def _expand_actions(cls, data: Any) -> Any:
        """Each action entry (``ActionProvider*``/``ActionClient*``) becomes its five parts, and each
        connection between two actions the five connections of their parts (:mod:`rce.interfaces.actions`)."""
        if not isinstance(data, dict) or not isinstance(data.get("interfaces"), list):
            return data
        out, names = [], set()
        for i, entry in enumerate(data["interfaces"]):
            if not (isinstance(entry, dict) and actions.is_action_type(entry.get("iType"))):
                out.append(entry)
                continue
            for key in ("eTag", "iTag", "iCls"):
                if not isinstance(entry.get(key), str) or not entry[key]:
                    raise _KeyError(f"interfaces[{i}].{key}", "must be a non-empty string")
            try:
                out += [{**part, "action": entry["iTag"]} for part in actions.expand_interface(entry)]
            except ValueError as e:
                raise _KeyError(f"interfaces[{i}].iCls", str(e)) from None
            names.add(f"{entry['eTag']}/{entry['iTag']}")
        conns = []
        for c in data.get("connections") or []:
            if isinstance(c, dict) and c.get("tagA") in names and c.get("tagB") in names:
                conns += [{**c, "tagA": a, "tagB": b} for a, b in actions.expand_connection(c["tagA"], c["tagB"])]
            else:
                conns.append(c)
        return {**data, "interfaces": out, "connections": conns if "connections" in data else []}

    @model_validator(mode="after")
    def _cross_checks(self) -> "RobotConfig":
        seen = set()
        for i, itf in enumerate(self.interfaces):
            robot_side = itf.iType.robot_side
            if robot_side and itf.eTag != self.robotID:
                raise _KeyError(f"interfaces[{i}].eTag",
                                f"a {itf.iType} lives on the robot, so eTag must be the robotID {self.robotID!r}, "
                                f"got {itf.eTag!r}")
            if not robot_side and itf.eTag == self.robotID:
                raise _KeyError(f"interfaces[{i}].eTag",
                                f"a {itf.iType} lives in a container, so eTag must be a container tag")
            key = (itf.eTag, itf.iTag)
            if key in seen:
                raise _KeyError(f"interfaces[{i}].iTag", f"duplicate interface {itf.eTag}/{itf.iTag}")
            seen.add(key)
        tags = [c.cTag for c in self.containers]
        for i, c in enumerate(tags):
            if tags.index(c) != i:
                raise _KeyError(f"containers[{i}].cTag", f"duplicate container tag {c!r}")
        return self


class _KeyError(ValueError):
    def __init__(self, path: str, reason: str):
        super().__init__(reason)
        self.path, self.reason = path, reason


def parse_config(data: Any, source: str = "<config>") -> RobotConfig:
    """Validate an already-parsed config object. Raises :class:`ConfigError`."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: the config must be an object with keys url, userID, password, robotID, ...")
    try:
        return RobotConfig.model_validate(data)
    except _KeyError as e:
        raise ConfigError(f"{source}: {e.path}: {e.reason}") from None
    except ValidationError as e:
        err = e.errors()[0]
        ctx_err = (err.get("ctx") or {}).get("error")
        if isinstance(ctx_err, _KeyError):
            raise ConfigError(f"{source}: {ctx_err.path}: {ctx_err.reason}") from None
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        raise ConfigError(f"{source}: {key_path(tuple(err['loc'])) or '(top level)'}: {msg}") from None


def load_config(path: str | Path) -> RobotConfig:
    """Load and validate a robot config file (JSON, or YAML by extension/content).

    Raises :class:`ConfigError` naming the file, the key path and the reason."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as e:
        raise ConfigError(f"{p}: cannot read: {e.strerror}") from None
    if p.suffix in (".yaml", ".yml"):
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise ConfigError(f"{p}: not valid YAML: {e}") from None
    else:
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            try:
                data = yaml.safe_load(text)
            except yaml.YAMLError:
                raise ConfigError(f"{p}: not valid JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None
    return parse_config(data, str(p))
