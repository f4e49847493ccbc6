"""The one schema of robot -> cloud requests (docs/design.md, section 3.3): CC, DC, CN (with each
component kind), CX and DM, as pydantic models.

Each rule is written once, as a field type with its own error text (:data:`Tag`,
:data:`Limit`, :data:`IType`, :data:`InterfaceRef`...), and shared: the robot
config (:mod:`rce.protocol.config`) builds its models on the component models here, under its short
keys (``cTag``, ``nTag``, ``eTag``, ``iTag``, ``iType``, ``iCls``; the field names) where the
wire uses the long ones (``containerTag``, ``nodeTag``...; the aliases).

:func:`validate` checks a complete message and returns its data as a model (:class:`CCData`,
:class:`DCData`, :class:`CNData`, :class:`CXData`, :class:`DataMessage`), which travels on past
validation: the robot session hands its shell the model, the shell sends the master its wire form,
and the master's request handlers read the attributes of the model it validates that into; an
interface type is an :class:`~rce.interfaces.kind.InterfaceType` parsed once. :func:`dm_data`
checks a DM the same way and returns its data as sent (DMs come at data rates). Both raise
:class:`ProtocolError` naming the type and the key path of the first
problem, e.g. ``CN.data.addNodes[0]: missing key 'pkg'``. Wire components take keys they do not
know (the RCE alpha client may send more); the CN and CX objects do not.
"""
from __future__ import annotations

from typing import Annotated, Any, Literal, TypeVar, Union

from pydantic import (BaseModel, ConfigDict, Field, PlainSerializer, PlainValidator, TypeAdapter, ValidationError,
                      model_validator)
from pydantic_core import PydanticCustomError

from rce.plumbing.errors import ProtocolError
from rce.interfaces.kind import InterfaceType
from rce.interfaces.lanes import Lane, parse_lane
from rce.protocol.frames import CC, CN, CX, DC, DM
from rce.plumbing.text import key_path, short_repr
from rce.protocol.limits import MAX_ER_TEXT, truncate

ROBOT_TO_CLOUD = (CC, DC, CN, CX, DM)


def split_interface_type(itype: str | InterfaceType) -> tuple[str, str]:
    """``"PublisherConverter"`` -> ``("Publisher", "Converter")``; legacy names are mapped: the
    (kind, side) of :meth:`InterfaceType.parse`, for callers that still take the pair.

    Raises :class:`ProtocolError` for an unknown interface type."""
    t = InterfaceType.parse(itype)
    return t.kind.value, t.side.value


# -- the rules, each with its error text ---------------------------------------------------------
def _refuse(text: str, value: Any) -> PydanticCustomError:
    return PydanticCustomError("rce", "{text}, got {value}", {"text": text, "value": short_repr(value)})


def _rule(check, text: str):
    """A field type accepting the values ``check`` passes, refusing others with ``text``."""
    def validate(value: Any) -> Any:
        if not check(value):
            raise _refuse(text, value)
        return value
    return PlainValidator(validate)


def _is_str(value: Any) -> bool:
    return isinstance(value, str)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _interface_type(value: Any) -> InterfaceType:
    if not isinstance(value, str):
        raise _refuse("must be a string", value)
    try:
        return InterfaceType.parse(value)
    except ProtocolError as e:
        raise PydanticCustomError("rce", "{text}", {"text": e.message}) from None


def _lane(value: Any) -> Lane:
    try:
        return parse_lane(value, "")
    except ProtocolError as e:
        raise PydanticCustomError("rce", "{text}", {"text": e.message}) from None


def _interface_ref(value: Any) -> str:
    if not isinstance(value, str) or not value:
        raise _refuse("must be a non-empty string", value)
    if value.count("/") != 1 or value.startswith("/") or value.endswith("/"):
        raise PydanticCustomError("rce", "{value} must be 'endpointTag/interfaceTag'", {"value": short_repr(value)})
    return value


#: A tag or name: a non-empty string.
Tag = Annotated[str, _rule(lambda v: _is_str(v) and v != "", "must be a non-empty string")]
#: A container tag, ``containerTag`` on the wire (``cTag`` in a robot config).
CTag = Annotated[Tag, Field(alias="containerTag")]
#: An optional string (a node's name or namespace, a group, an address).
Text = Annotated[str, _rule(_is_str, "must be a string")]
#: A resource amount: cpu in cores, memory in MiB, pids in tasks (limits); size (the original RCE's
#: container size class, in slots) and bandwidth (bytes/s) are recorded only.
Limit = Annotated[float, _rule(lambda v: _is_number(v) and v >= 0, "must be a number greater than or equal to 0")]
#: A node's arguments: one string, or a list of strings.
Args = Annotated[Union[str, list[str]], _rule(lambda v: _is_str(v) or (isinstance(v, list) and all(map(_is_str, v))),
                                               "must be a string or a list of strings")]
#: Restart a node that exits: true/false, or an object of restart settings.
Respawn = Annotated[Union[bool, dict], _rule(lambda v: isinstance(v, (bool, dict)), "must be a boolean or an object")]
#: A DM's msgID: a string or an integer.
MsgID = Annotated[Union[str, int], _rule(lambda v: _is_str(v) or (isinstance(v, int) and not isinstance(v, bool)),
                                          "must be a string or an integer")]
Features = Annotated[list[str], _rule(lambda v: isinstance(v, list) and all(map(_is_str, v)),
                                      "must be a list of strings")]
#: Where a container may run (:mod:`rce_master.placement.placer`): ``auto`` (the placer decides), ``cloud``,
#: ``edge`` or ``robot`` (the computer of the robot it serves).
PLACEMENTS = ("auto", "cloud", "edge", "robot")
Placement = Annotated[str, _rule(lambda v: v in PLACEMENTS, "must be one of 'auto', 'cloud', 'edge', 'robot'")]
#: A time in ms, greater than 0.
Millis = Annotated[float, _rule(lambda v: _is_number(v) and v > 0, "must be a number of ms greater than 0")]
#: A JSON boolean (not 0 or 1).
Flag = Annotated[bool, _rule(lambda v: isinstance(v, bool), "must be true or false")]
#: Interface tags of the robot a container serves.
Tags = Annotated[list[str], _rule(lambda v: isinstance(v, list) and all(_is_str(t) and t for t in v),
                                  "must be a list of non-empty strings")]
#: An interface type (prefix x suffix, docs/design.md, section 3.5; RCE alpha names accepted), parsed into its
#: :class:`~rce.interfaces.kind.InterfaceType` (a ``str``: its canonical name on the wire).
IType = Annotated[InterfaceType, PlainValidator(_interface_type), PlainSerializer(str)]
#: A lane (:mod:`rce.interfaces.lanes`): ``"control"``, ``"state"`` or ``"bulk"``.
LaneName = Annotated[Lane, PlainValidator(_lane), PlainSerializer(str)]
#: An interface named ``endpointTag/interfaceTag``.
InterfaceRef = Annotated[str, PlainValidator(_interface_ref)]


# -- components (field names: the config's short keys; aliases: the wire's keys) -----------------
class Component(BaseModel):
    """A wire object: keys by alias, unknown keys ignored, error paths by alias."""
    model_config = ConfigDict(extra="ignore", validate_by_alias=True, validate_by_name=False)

    def wire(self) -> dict:
        """This object as the wire has it: the long keys, only those that were given (a record of
        the master keeps a node's addNodes entry so)."""
        return self.model_dump(by_alias=True, exclude_unset=True)


class ContainerData(Component):
    """A container's placement and limits (CC ``containerData``): ``cpu`` cores, ``memory`` MiB and
    ``pids`` tasks are limits (absent or 0: none); ``size`` is the original RCE's container size
    class (its client always sends ``size: 1``) and ``bandwidth`` bytes/s: both recorded only.

    What it needs, for the placer (:mod:`rce_master.placement.placer`; every key optional, a container that
    gives none of them is placed as before, on the least loaded cloud or edge host):
    ``placement`` (``auto``, the default once any of these is given; ``cloud``, ``edge``,
    ``robot``), ``deadline_ms`` (the latency its results are due within, input to output),
    ``robot`` (the robotID it serves; needed for ``robot``) and ``consumes`` (the interface tags of
    that robot it reads, whose measured bytes a placement off the robot carries over the link).
    ``ordered_moves``: true makes a move's new copy hold its inputs until the old copy has handled
    its last ones and its peers have its last results, so that results keep one order per
    interface across the move (its gap is then the old copy's drain); false or absent: the new
    copy serves at once (``docs/placement.md``, Moves). ``spare``: true keeps a made copy of it, fed
    nothing, on the host the placer would move it to next, so that a move there only switches
    (``docs/placement.md``, Spares)."""
    group: Text | None = None
    groupIp: Text | None = None
    size: Limit | None = None
    cpu: Limit | None = None
    memory: Limit | None = None
    pids: Limit | None = None
    bandwidth: Limit | None = None
    specialFeatures: Features | None = None
    placement: Placement | None = None
    deadline_ms: Millis | None = None
    robot: Tag | None = None
    consumes: Tags | None = None
    ordered_moves: Flag | None = None
    spare: Flag | None = None

    @model_validator(mode="after")
    def _robot_named(self):
        if self.placement == "robot" and not self.robot:
            raise PydanticCustomError("rce", "placement 'robot' needs 'robot': the robotID whose computer runs it")
        return self


class ContainerComponent(ContainerData):
    """A container tag with its placement and limits, flat (CN ``resizeContainer``, config ``containers``)."""
    cTag: CTag


class NodeComponent(Component):
    """A node to launch in a container (CN ``addNodes``)."""
    cTag: CTag
    nTag: Tag = Field(alias="nodeTag")
    pkg: Tag
    exe: Tag
    args: Args = ""
    name: Text | None = None
    namespace: Text | None = None
    respawn: Respawn | None = None


class ParameterComponent(Component):
    """A container parameter and its JSON value (CN ``setParam``; ``value`` may be null, not absent)."""
    cTag: CTag
    name: Tag
    value: Any


class InterfaceComponent(Component):
    """An interface on an endpoint: a container tag, or the robot's own robotID (CN ``addInterfaces``)."""
    eTag: Tag = Field(alias="endpointTag")
    iTag: Tag = Field(alias="interfaceTag")
    iType: IType = Field(alias="interfaceType")
    iCls: Tag = Field(alias="className")
    addr: Text | None = None
    lane: LaneName | None = None      # absent: from the class (rce.interfaces.lanes.default_lane)


class ConnectionComponent(Component):
    """A connection between two interfaces (CX ``connect``/``disconnect``)."""
    tagA: InterfaceRef
    tagB: InterfaceRef


class NodeRef(Component):
    """CN ``removeNodes``."""
    cTag: CTag
    nTag: Tag = Field(alias="nodeTag")


class ParameterRef(Component):
    """CN ``deleteParam``."""
    cTag: CTag
    name: Tag


class InterfaceRefs(Component):
    """CN ``removeInterfaces``."""
    eTag: Tag = Field(alias="endpointTag")
    iTag: Tag = Field(alias="interfaceTag")


class _Closed(Component):
    """An object whose keys are all known: an unknown one is refused, naming the known ones."""

    @model_validator(mode="before")
    @classmethod
    def _known_keys(cls, data: Any) -> Any:
        if isinstance(data, dict):
            known = [f.alias or name for name, f in cls.model_fields.items()]
            unknown = [k for k in data if k not in known]
            if unknown:
                raise PydanticCustomError("rce", "unknown key {key} (expected {known})",
                                          {"key": short_repr(unknown[0]), "known": ", ".join(known)})
        return data


# -- requests ------------------------------------------------------------------------------------
class CCData(Component):
    """CC data: create container ``cTag``."""
    cTag: CTag
    containerData: ContainerData | None = None


class DCData(Component):
    """DC data: destroy container ``cTag``."""
    cTag: CTag


class CNData(_Closed):
    """CN data: any of its keys, each a list of components."""
    addNodes: list[NodeComponent] = []
    removeNodes: list[NodeRef] = []
    setParam: list[ParameterComponent] = []
    deleteParam: list[ParameterRef] = []
    addInterfaces: list[InterfaceComponent] = []
    removeInterfaces: list[InterfaceRefs] = []
    resizeContainer: list[ContainerComponent] = []


class CXData(_Closed):
    """CX data: connections to make and to remove."""
    connect: list[ConnectionComponent] = []
    disconnect: list[ConnectionComponent] = []


class DataMessage(Component):
    """DM data: ``msg`` (or its binary part ``msg*``) for interface ``iTag`` of class ``type``."""
    iTag: Tag
    type: Tag
    msgID: MsgID | None = None
    msg: Any = None

    @model_validator(mode="wrap")
    @classmethod
    def _has_msg(cls, data: Any, handler: Any) -> Any:
        out = handler(data)                  # the fields first: their errors come before this one
        if "msg" not in data and "msg*" not in data:
            raise PydanticCustomError("rce", "missing key 'msg'")
        return out


class _Message(BaseModel):
    model_config = ConfigDict(extra="ignore")


class CCMessage(_Message):
    type: Literal["CC"]
    data: CCData


class DCMessage(_Message):
    type: Literal["DC"]
    data: DCData


class CNMessage(_Message):
    type: Literal["CN"]
    data: CNData


class CXMessage(_Message):
    type: Literal["CX"]
    data: CXData


class DMMessage(_Message):
    type: Literal["DM"]
    data: DataMessage


Request = Annotated[Union[CCMessage, DCMessage, CNMessage, CXMessage, DMMessage], Field(discriminator="type")]
#: The data of a robot -> cloud message, as its model.
RequestData = Union[CCData, DCData, CNData, CXData, DataMessage]
_REQUEST = TypeAdapter(Request)


# -- errors --------------------------------------------------------------------------------------
def _describe(err: dict, msg: Any) -> str:
    """One line for the first error of a request: the key path, then what is wrong."""
    kind, loc, value = err["type"], tuple(err["loc"]), err.get("input")
    if kind == "union_tag_not_found":
        return "message: missing key 'type'"
    if kind == "union_tag_invalid":
        return f"message: unknown type {short_repr(msg.get('type'))} (expected one of {', '.join(ROBOT_TO_CLOUD)})"
    where = key_path(loc) or "message"
    if kind == "missing" and loc and isinstance(loc[-1], str):
        return f"{key_path(loc[:-1])}: missing key '{loc[-1]}'"
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        return f"{where}: must be a JSON object, got {type(value).__name__}"
    if kind == "list_type":
        return f"{where}: must be a list, got {type(value).__name__}"
    return f"{where}: {truncate(err['msg'], MAX_ER_TEXT // 2)}"


def _valid_dm(msg: Any) -> bool:
    """Does ``msg`` pass :class:`DMMessage` as it stands? The same rules as the model (iTag and
    type non-empty strings, msgID absent, null, a string or an integer, ``msg`` or ``msg*``
    present, other keys ignored), checked by hand: a DM is the one request that comes at data
    rates, and the model costs ~10x this. False sends it to the model, which names the problem."""
    if type(msg) is not dict or msg.get("type") != DM:
        return False
    data = msg.get("data")
    if type(data) is not dict:
        return False
    itag, cls, msg_id = data.get("iTag"), data.get("type"), data.get("msgID")
    return (type(itag) is str and itag != "" and type(cls) is str and cls != ""
            and (msg_id is None or type(msg_id) in (str, int))
            and ("msg" in data or "msg*" in data))


def validate(msg: Any) -> tuple[str, RequestData]:
    """Check a complete robot -> cloud message; return ``(type, data)`` with ``data`` its model
    (:data:`RequestData`), which travels on past validation: the robot session hands a request to its
    shell as it (:class:`~rce.protocol.events.RequestReady`), and the master's request handlers read
    its attributes (:func:`rce_master.requests.handle` validates the data it receives with this
    function too: one parse per process).

    Raises :class:`ProtocolError` naming the type and key path of the first problem."""
    try:
        m = _REQUEST.validate_python(msg)
    except ValidationError as e:
        raise ProtocolError(_describe(e.errors(include_url=False)[0], msg)) from None
    return m.type, m.data


def dm_data(msg: Any) -> dict:
    """The data of DM ``msg`` as sent, checked as :func:`validate` checks it: a well-formed DM takes
    the hand check :func:`_valid_dm` and travels on as its dict (a DM comes at data rates, and its
    model would cost ~10x the check); anything else the model, which names the problem.

    Raises :class:`ProtocolError` naming the type and key path of the first problem."""
    if not _valid_dm(msg):
        validate(msg)
    return msg["data"]


C = TypeVar("C", bound=Component)


def component(model: type[C], fields: dict, where: str) -> C:
    """Component ``model`` from ``fields`` keyed by field name (the short keys: ``cTag``,
    ``cpu``...), validated as on the wire: the admin API builds its requests so.

    Raises :class:`ProtocolError` naming ``where`` and the key path of the first problem."""
    try:
        return model.model_validate(fields, by_alias=False, by_name=True)
    except ValidationError as e:
        err = e.errors(include_url=False)[0]
        raise ProtocolError(_describe({**err, "loc": (where, *err["loc"])}, fields)) from None
