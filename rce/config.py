"""The one robot-config loader (DESIGN section 3.6): the seed paper's ``robot1.config``
JSON, or YAML with the same keys.

The whole file is validated before anything is sent; a bad config raises
:class:`ConfigError` naming the file, the key path and the reason, e.g.
``configs/r1.config: interfaces[2].iType: unknown interface type 'Publisher'``.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Union

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from rce.errors import ConfigError, ProtocolError
from rce.protocol import split_interface_type

JSONValue = Union[bool, int, float, str, list, dict, None]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", populate_by_name=True)


class ContainerSpec(_Model):
    """A container to create: tag and optional placement and limits (cpu in cores, memory in MiB)."""
    cTag: str = Field(min_length=1)
    group: str | None = None
    groupIp: str | None = None
    size: float | None = Field(default=None, ge=0)
    cpu: float | None = Field(default=None, ge=0)
    memory: float | None = Field(default=None, ge=0)
    bandwidth: float | None = Field(default=None, ge=0)
    specialFeatures: list[str] = Field(default_factory=list)

    def container_data(self) -> dict:
        """The CC ``containerData`` object for this spec (only keys that are set)."""
        d = self.model_dump(exclude={"cTag"}, exclude_none=True)
        if not d.get("specialFeatures"):
            d.pop("specialFeatures", None)
        return d


class NodeSpec(_Model):
    """A node to launch in a container (RCE addNodes component)."""
    cTag: str = Field(min_length=1)
    nTag: str = Field(min_length=1)
    pkg: str = Field(min_length=1)
    exe: str = Field(min_length=1)
    args: str | list[str] = ""
    name: str | None = None
    namespace: str | None = None
    respawn: bool | dict | None = None

    def component(self) -> dict:
        """The CN addNodes component for this node."""
        d = {"containerTag": self.cTag, "nodeTag": self.nTag, "pkg": self.pkg, "exe": self.exe}
        for k in ("args", "name", "namespace", "respawn"):
            v = getattr(self, k)
            if v not in (None, ""):
                d[k] = v
        return d


class ParameterSpec(_Model):
    """A container parameter (any JSON value)."""
    cTag: str = Field(min_length=1)
    name: str = Field(min_length=1)
    value: JSONValue


class InterfaceSpec(_Model):
    """An interface on an endpoint (a container tag, or the robot's own robotID)."""
    eTag: str = Field(min_length=1)
    iTag: str = Field(min_length=1)
    iType: str
    iCls: str = Field(min_length=1)
    addr: str | None = None

    @field_validator("iType")
    @classmethod
    def _known_type(cls, v: str) -> str:
        try:
            split_interface_type(v)
        except ProtocolError as e:
            raise ValueError(e.message) from None
        return v

    def component(self) -> dict:
        """The CN addInterfaces component for this interface."""
        d = {"endpointTag": self.eTag, "interfaceTag": self.iTag, "interfaceType": self.iType,
             "className": self.iCls}
        if self.addr:
            d["addr"] = self.addr
        return d


class ConnectionSpec(_Model):
    """A connection between two interfaces, each ``endpointTag/interfaceTag``."""
    tagA: str
    tagB: str

    @field_validator("tagA", "tagB")
    @classmethod
    def _tag_form(cls, v: str) -> str:
        if v.count("/") != 1 or v.startswith("/") or v.endswith("/"):
            raise ValueError(f"{v!r} must be 'endpointTag/interfaceTag'")
        return v


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

    @model_validator(mode="after")
    def _cross_checks(self) -> "RobotConfig":
        seen = set()
        for i, itf in enumerate(self.interfaces):
            _, suffix = split_interface_type(itf.iType)
            robot_side = suffix in ("Converter", "Forwarder")
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


def _loc(loc: tuple) -> str:
    out = ""
    for p in loc:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "(top level)"


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
        raise ConfigError(f"{source}: {_loc(err['loc'])}: {msg}") from None


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
