"""rce.protocol: the schema of robot -> cloud messages (shared with the robot config), interface type
names, frames and binary parts."""
from __future__ import annotations

import json
import math
import os

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from rce.plumbing.errors import MessageError, ProtocolError, RequestError
from rce.interfaces.kind import InterfaceType, Kind, Side
from rce.protocol.frames import DEFAULT_EXPIRY, ID_LEN, Assembler, encode, is_part_id, new_id
from rce.protocol.schema import split_interface_type, validate
from rce.protocol import schema
from rce.protocol.frames import _binary_refs, _resolve, parse_frame, parse_text

ID1, ID2, ID3 = "0" * 31 + "1", "a" * 31 + "2", "F" * 31 + "3"


def frame(ref: str, payload: bytes) -> bytes:
    return ref.encode() + payload


def raises(match_parts: list[str], fn, *args):
    """Call ``fn`` expecting a ProtocolError whose message contains every string of ``match_parts``."""
    with pytest.raises(ProtocolError) as ei:
        fn(*args)
    for part in match_parts:
        assert part in ei.value.message, (part, ei.value.message)
    assert ei.value.code == "protocol"
    return ei.value


# -- validate: the message envelope ------------------------------------------------------------
@pytest.mark.parametrize("msg, parts", [
    ([], ["message", "JSON object", "list"]),
    ("CC", ["message", "JSON object"]),
    ({}, ["message", "missing key 'type'"]),
    ({"type": "XX", "data": {}}, ["unknown type 'XX'"]),
    ({"type": "ST", "data": {}}, ["unknown type 'ST'"]),      # cloud -> robot only
    ({"type": "ER", "data": "x"}, ["unknown type 'ER'"]),
    ({"type": None, "data": {}}, ["unknown type None"]),
    ({"type": ["CC"], "data": {}}, ["unknown type ['CC']"]),   # unhashable type value
    ({"type": {"a": 1}, "data": {}}, ["unknown type"]),
    ({"type": "CC"}, ["CC", "missing key 'data'"]),
    ({"type": "DM", "data": []}, ["DM.data", "JSON object"]),
    ({"type": "CN", "data": "x"}, ["CN.data", "JSON object"]),
])
def test_validate_envelope_errors(msg, parts):
    raises(parts, validate, msg)


# -- CC / DC ------------------------------------------------------------------------------------
def test_validate_cc_minimal_and_full():
    t, cc = validate({"type": "CC", "data": {"containerTag": "c1"}})
    assert (t, cc.cTag, cc.wire()) == ("CC", "c1", {"containerTag": "c1"})
    full = {"containerTag": "c1", "containerData": {
        "group": "g", "groupIp": "10.0.0.1", "size": 2, "cpu": 0.5, "memory": 256, "bandwidth": 0,
        "specialFeatures": ["gpu"]}}
    t, data = validate({"type": "CC", "data": full})
    assert t == "CC" and data.containerData.cpu == 0.5 and data.wire() == full
    # containerData: null is the same as absent
    assert validate({"type": "CC", "data": {"containerTag": "c1", "containerData": None}})[0] == "CC"


@pytest.mark.parametrize("data, parts", [
    ({}, ["CC.data", "missing key 'containerTag'"]),
    ({"containerTag": ""}, ["CC.data.containerTag: ", "non-empty string", "got ''"]),
    ({"containerTag": 7}, ["CC.data.containerTag: ", "got 7"]),
    ({"containerTag": "c", "containerData": []}, ["CC.data.containerData", "JSON object"]),
    ({"containerTag": "c", "containerData": {"cpu": -1}},
     ["CC.data.containerData.cpu: ", "greater than or equal to 0", "-1"]),
    ({"containerTag": "c", "containerData": {"memory": "1G"}}, ["CC.data.containerData.memory", "'1G'"]),
    ({"containerTag": "c", "containerData": {"size": True}}, ["CC.data.containerData.size", "True"]),
    ({"containerTag": "c", "containerData": {"bandwidth": [1]}}, ["CC.data.containerData.bandwidth"]),
    ({"containerTag": "c", "containerData": {"group": 3}},
     ["CC.data.containerData.group: ", "must be a string", "got 3"]),
    ({"containerTag": "c", "containerData": {"groupIp": []}}, ["CC.data.containerData.groupIp: ", "must be a string"]),
    ({"containerTag": "c", "containerData": {"specialFeatures": "gpu"}},
     ["CC.data.containerData.specialFeatures: ", "list of strings"]),
])
def test_validate_cc_errors(data, parts):
    raises(parts, validate, {"type": "CC", "data": data})


def test_validate_dc():
    assert validate({"type": "DC", "data": {"containerTag": "c1"}}) == ("DC", schema.DCData(containerTag="c1"))
    raises(["DC.data", "missing key 'containerTag'"], validate, {"type": "DC", "data": {}})
    raises(["DC.data.containerTag: ", "got None"], validate, {"type": "DC", "data": {"containerTag": None}})


# -- CN -----------------------------------------------------------------------------------------
GOOD_CN = {
    "addNodes": [{"containerTag": "c", "nodeTag": "n", "pkg": "Test", "exe": "stringEcho.py"},
                 {"containerTag": "c", "nodeTag": "n2", "pkg": "Test", "exe": "e", "args": ["-v"],
                  "name": "echo", "namespace": "/ns", "respawn": True},
                 {"containerTag": "c", "nodeTag": "n3", "pkg": "Test", "exe": "e", "args": "a b",
                  "respawn": {"max": 3}}],
    "removeNodes": [{"containerTag": "c", "nodeTag": "n"}],
    "setParam": [{"containerTag": "c", "name": "p", "value": None},
                 {"containerTag": "c", "name": "q", "value": {"a": [1, 2]}}],
    "deleteParam": [{"containerTag": "c", "name": "p"}],
    "addInterfaces": [{"endpointTag": "c", "interfaceTag": "i", "interfaceType": "PublisherInterface",
                       "className": "std_msgs/String", "addr": "/chatter"},
                      {"endpointTag": "r", "interfaceTag": "s", "interfaceType": "ServiceConverter",
                       "className": "Test/StringEcho"}],
    "removeInterfaces": [{"endpointTag": "c", "interfaceTag": "i"}],
    "resizeContainer": [{"containerTag": "c", "cpu": 2, "memory": 512}],
}


@pytest.mark.parametrize("key", list(GOOD_CN))
def test_validate_cn_each_key_alone(key):
    t, data = validate({"type": "CN", "data": {key: GOOD_CN[key]}})
    assert t == "CN" and len(getattr(data, key)) == len(GOOD_CN[key])
    assert validate({"type": "CN", "data": data.wire()}) == (t, data)        # its wire form says the same


def test_validate_cn_all_keys_and_empty():
    assert validate({"type": "CN", "data": GOOD_CN})[0] == "CN"
    assert validate({"type": "CN", "data": {}}) == ("CN", schema.CNData())
    assert validate({"type": "CN", "data": {"addNodes": []}})[0] == "CN"


@pytest.mark.parametrize("data, parts", [
    ({"addNode": []}, ["CN.data", "unknown key 'addNode'"]),
    ({"addNodes": {"containerTag": "c"}}, ["CN.data.addNodes: must be a list", "dict"]),
    ({"setParam": None}, ["CN.data.setParam: must be a list"]),
    ({"addNodes": ["x"]}, ["CN.data.addNodes[0]", "JSON object"]),
    ({"addNodes": [GOOD_CN["addNodes"][0], {"containerTag": "c", "nodeTag": "n", "pkg": "p"}]},
     ["CN.data.addNodes[1]", "missing key 'exe'"]),
    ({"addNodes": [{"containerTag": "c", "nodeTag": "", "pkg": "p", "exe": "e"}]},
     ["CN.data.addNodes[0].nodeTag: ", "non-empty"]),
    ({"addNodes": [{"containerTag": "c", "nodeTag": "n", "pkg": "p", "exe": "e", "args": 5}]},
     ["CN.data.addNodes[0].args: ", "a string or a list of strings"]),
    ({"addNodes": [{"containerTag": "c", "nodeTag": "n", "pkg": "p", "exe": "e", "namespace": 1}]},
     ["CN.data.addNodes[0].namespace: ", "must be a string"]),
    ({"addNodes": [{"containerTag": "c", "nodeTag": "n", "pkg": "p", "exe": "e", "name": ["a"]}]},
     ["CN.data.addNodes[0].name: ", "got ['a']"]),
    ({"addNodes": [{"containerTag": "c", "nodeTag": "n", "pkg": "p", "exe": "e", "respawn": "yes"}]},
     ["CN.data.addNodes[0].respawn: ", "a boolean or an object"]),
    ({"removeNodes": [{"containerTag": "c"}]}, ["CN.data.removeNodes[0]", "missing key 'nodeTag'"]),
    ({"removeNodes": [{"nodeTag": "n"}]}, ["CN.data.removeNodes[0]", "missing key 'containerTag'"]),
    ({"setParam": [{"containerTag": "c", "name": "p"}]}, ["CN.data.setParam[0]", "missing key 'value'"]),
    ({"setParam": [{"containerTag": "c", "value": 1}]}, ["CN.data.setParam[0]", "missing key 'name'"]),
    ({"deleteParam": [{"containerTag": "c", "name": 3}]}, ["CN.data.deleteParam[0].name: ", "got 3"]),
    ({"addInterfaces": [{"endpointTag": "c", "interfaceTag": "i", "interfaceType": "PublisherInterface"}]},
     ["CN.data.addInterfaces[0]", "missing key 'className'"]),
    ({"addInterfaces": [{"endpointTag": "c", "interfaceTag": "i", "interfaceType": "Publisher",
                         "className": "std_msgs/String"}]},
     ["CN.data.addInterfaces[0].interfaceType", "unknown interface type 'Publisher'"]),
    ({"addInterfaces": [{"endpointTag": "c", "interfaceTag": "i", "interfaceType": "PublisherInterface",
                         "className": "std_msgs/String", "addr": 5}]},
     ["CN.data.addInterfaces[0].addr: ", "got 5"]),
    ({"removeInterfaces": [{"endpointTag": "c"}]}, ["CN.data.removeInterfaces[0]", "missing key 'interfaceTag'"]),
    ({"resizeContainer": [{"cpu": 1}]}, ["CN.data.resizeContainer[0]", "missing key 'containerTag'"]),
    ({"resizeContainer": [{"containerTag": "c", "memory": -5}]}, ["CN.data.resizeContainer[0].memory"]),
])
def test_validate_cn_errors(data, parts):
    raises(parts, validate, {"type": "CN", "data": data})


# -- CX -----------------------------------------------------------------------------------------
def test_validate_cx_good():
    data = {"connect": [{"tagA": "c/i", "tagB": "r/j"}], "disconnect": [{"tagA": "c/i", "tagB": "c2/k"}]}
    assert validate({"type": "CX", "data": data})[1].wire() == data
    assert validate({"type": "CX", "data": {}}) == ("CX", schema.CXData())


@pytest.mark.parametrize("tag", ["ci", "/c/i", "c/i/", "c/i/j", "/", "c//i", ""])
@pytest.mark.parametrize("key", ["connect", "disconnect"])
def test_validate_cx_tag_format(key, tag):
    data = {key: [{"tagA": "c/ok", "tagB": "r/ok"}, {"tagA": "c/ok", "tagB": tag}]}
    raises([f"CX.data.{key}[1]", "tagB"], validate, {"type": "CX", "data": data})


@pytest.mark.parametrize("data, parts", [
    ({"connect": [{"tagB": "r/j"}]}, ["CX.data.connect[0]", "missing key 'tagA'"]),
    ({"connect": [{"tagA": 1, "tagB": "r/j"}]}, ["CX.data.connect[0].tagA: ", "got 1"]),
    ({"connect": ["c/i"]}, ["CX.data.connect[0]", "JSON object"]),
    ({"connect": {"tagA": "c/i"}}, ["CX.data.connect: must be a list"]),
    ({"link": []}, ["CX.data", "unknown key 'link'"]),
])
def test_validate_cx_errors(data, parts):
    raises(parts, validate, {"type": "CX", "data": data})


def test_validate_cx_error_names_the_tag_format():
    e = raises(["CX.data.connect[0].tagA"], validate,
               {"type": "CX", "data": {"connect": [{"tagA": "x", "tagB": "c/i"}]}})
    assert "'endpointTag/interfaceTag'" in e.message


# -- DM -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("data", [
    {"iTag": "i", "type": "std_msgs/String", "msg": {"data": "x"}},
    {"iTag": "i", "type": "std_msgs/String", "msg": {"data": "x"}, "msgID": "abc"},
    {"iTag": "i", "type": "std_msgs/String", "msg": {}, "msgID": 7},
    {"iTag": "i", "type": "std_msgs/String", "msg": b"\x00", "msgID": None},
    {"iTag": "i", "type": "std_msgs/String", "msg*": ID1},
])
def test_validate_dm_good(data):
    """A DM's data travels on as sent (dm_data); validate gives its model."""
    assert schema.dm_data({"type": "DM", "data": data}) == data
    t, dm = validate({"type": "DM", "data": data})
    assert (t, dm.iTag, dm.msgID) == ("DM", "i", data.get("msgID"))


@pytest.mark.parametrize("data, parts", [
    ({"type": "std_msgs/String", "msg": {}}, ["DM.data", "missing key 'iTag'"]),
    ({"iTag": "i", "msg": {}}, ["DM.data", "missing key 'type'"]),
    ({"iTag": "i", "type": ""}, ["DM.data.type: ", "non-empty"]),
    ({"iTag": "i", "type": "std_msgs/String"}, ["DM.data", "missing key 'msg'"]),
    ({"iTag": "i", "type": "std_msgs/String", "msg": {}, "msgID": [1]}, ["DM.data.msgID: ", "a string or an integer"]),
    ({"iTag": 3, "type": "std_msgs/String", "msg": {}}, ["DM.data.iTag: ", "got 3"]),
])
def test_validate_dm_errors(data, parts):
    raises(parts, validate, {"type": "DM", "data": data})
    raises(parts, schema.dm_data, {"type": "DM", "data": data})


_DM_VALUES = st.one_of(st.none(), st.booleans(), st.integers(), st.floats(allow_nan=False),
                       st.sampled_from(["", "i"]), st.lists(st.integers(), max_size=2),
                       st.dictionaries(st.sampled_from(["data"]), st.text(max_size=2)))
_DM_DATA = st.dictionaries(st.sampled_from(["iTag", "type", "msgID", "msg", "msg*", "other"]), _DM_VALUES)


@settings(max_examples=400, deadline=None)
@given(data=_DM_DATA, envelope=st.sampled_from(["DM", "CC", None]))
def test_dm_hand_check_agrees_with_the_model(data, envelope):
    """dm_data's hand check of a DM (schema._valid_dm) passes exactly what the pydantic model passes:
    the data as sent, or the model's error text."""
    msg = {"type": envelope, "data": data}
    try:
        schema._REQUEST.validate_python(msg)
    except ValidationError:
        assert not schema._valid_dm(msg)
        with pytest.raises(ProtocolError):
            schema.dm_data(msg)
        return
    if envelope == "DM":
        assert schema._valid_dm(msg) and schema.dm_data(msg) == data


_PLAIN = st.none() | st.booleans() | st.integers(-2**63, 2**64 - 1) | st.text(max_size=3)   # exact (jsontext)
_KEYS = st.text(alphabet="abc", max_size=2)       # no '*': a key of its own ending in '*' would name a part


@settings(max_examples=300, deadline=None)
@given(st.recursive(_PLAIN, lambda kids: st.lists(kids, max_size=3) | st.dictionaries(
    _KEYS, kids | st.binary(max_size=3) | st.lists(st.binary(max_size=2), min_size=1, max_size=2), max_size=3),
    max_leaves=8))
def test_encode_plain_and_binary_messages_alike(data):
    """encode's one-dumps path (no bytes anywhere) and its walk (some bytes) give the same message back
    through the assembler, parts numbered in the given order."""
    ids = [f"{i:032x}" for i in range(30)]
    text, frames = encode({"type": "DM", "data": data}, ids=ids)
    a = Assembler()
    out = a.feed_text(text, now=0) + [m for f in frames for m in a.feed_binary(f, now=0)]
    assert out == [{"type": "DM", "data": data}]
    assert [f[:ID_LEN].decode() for f in frames] == ids[:len(frames)]


# -- interface types ----------------------------------------------------------------------------
@pytest.mark.parametrize("prefix", ["ServiceClient", "ServiceProvider", "Publisher", "Subscriber"])
@pytest.mark.parametrize("suffix", ["Interface", "Converter", "Forwarder"])
def test_split_interface_type_all_kinds(prefix, suffix):
    assert split_interface_type(prefix + suffix) == (prefix, suffix)


@pytest.mark.parametrize("legacy, expected", [
    ("ServiceInterface", ("ServiceClient", "Interface")),
    ("ServiceConverter", ("ServiceClient", "Converter")),
    ("ServiceForwarder", ("ServiceClient", "Forwarder")),
])
def test_split_interface_type_legacy_names(legacy, expected):
    assert split_interface_type(legacy) == expected


@pytest.mark.parametrize("bad", ["", "Publisher", "Interface", "PublisherInterfaceX", "publisherInterface",
                                 "ServiceProvider", "Service", "ServicePublisher", "SubscriberConverterForwarder"])
def test_split_interface_type_unknown(bad):
    e = raises(["unknown interface type", repr(bad)], split_interface_type, bad)
    assert "Publisher" in e.message and "Converter" in e.message   # lists what is allowed


def test_interface_type_is_parsed_once_into_kind_and_side():
    assert len(InterfaceType) == len(Kind) * len(Side) == 12
    t = InterfaceType.parse("ServiceConverter")                          # an RCE alpha name
    assert t is InterfaceType.SERVICE_CLIENT_CONVERTER and (t.kind, t.side) == (Kind.SERVICE_CLIENT, Side.CONVERTER)
    assert t.robot_side and t.kind.service and not InterfaceType.parse("PublisherInterface").robot_side
    assert InterfaceType.parse(t) is t                                   # parsing a member is a no-op
    assert [(k.peer, k.peer.peer) for k in (Kind.PUBLISHER, Kind.SERVICE_CLIENT)] == [
        (Kind.SUBSCRIBER, Kind.PUBLISHER), (Kind.SERVICE_PROVIDER, Kind.SERVICE_CLIENT)]
    # a member is its canonical wire name: it goes back on the wire and into records as that string
    assert t == "ServiceClientConverter" and json.dumps({"t": t}) == '{"t": "ServiceClientConverter"}' \
        and f"{t}" == "ServiceClientConverter"
    with pytest.raises(RequestError, match="PublisherInterface is a container interface, not a robot-side one"):
        InterfaceType.parse("PublisherInterface", robot_side=True)
    with pytest.raises(RequestError, match="'SubscriberForwarder' is a robot-side interface type"):
        InterfaceType.parse("SubscriberForwarder", robot_side=False)
    for bad in (None, 3, ["PublisherInterface"], "publisherInterface"):
        raises(["unknown interface type", repr(bad)], InterfaceType.parse, bad)


def test_validate_returns_the_models():
    """validate() hands the request on as its model (what the robot session's shell and the master's
    handlers read), with the interface type parsed; its wire form has the wire's keys."""
    itf = {"endpointTag": "r", "interfaceTag": "i", "interfaceType": "ServiceConverter", "className": "a/B", "x": 1}
    node = {"containerTag": "c", "nodeTag": "n", "pkg": "Test", "exe": "e", "args": ["-v"]}
    msg = {"type": "CN", "data": {"addInterfaces": [itf], "addNodes": [node]}}
    t, cn = validate(msg)
    assert t == "CN" and isinstance(cn, schema.CNData) and cn.removeNodes == []
    assert (cn.addNodes[0].cTag, cn.addNodes[0].nTag, cn.addNodes[0].args) == ("c", "n", ["-v"])
    assert cn.addInterfaces[0].iType is InterfaceType.SERVICE_CLIENT_CONVERTER
    assert cn.addNodes[0].wire() == node                                  # the wire's keys, only those given
    assert cn.addInterfaces[0].wire() == {**{k: v for k, v in itf.items() if k != "x"},
                                          "interfaceType": "ServiceClientConverter"}
    assert validate({"type": "CC", "data": {"containerTag": "c1"}})[1].cTag == "c1"
    assert validate({"type": "DC", "data": {"containerTag": "c1"}})[1] == schema.DCData.model_validate(
        {"containerTag": "c1"})
    cx = validate({"type": "CX", "data": {"connect": [{"tagA": "c/i", "tagB": "r/i"}]}})[1]
    assert (cx.connect[0].tagA, cx.disconnect) == ("c/i", [])
    assert validate({"type": "DM", "data": {"iTag": "i", "type": "t", "msg": {}}})[1].iTag == "i"
    raises(["CN.data.addNodes[0]", "missing key 'pkg'"], validate,
           {"type": "CN", "data": {"addNodes": [{"containerTag": "c", "nodeTag": "n", "exe": "e"}]}})


def test_a_component_built_by_field_name_is_validated_as_on_the_wire():
    c = schema.component(schema.ContainerComponent, {"cTag": "c1", "cpu": 1.5, "containerTag": "other"}, "resize")
    assert (c.cTag, c.cpu, c.memory) == ("c1", 1.5, None)                  # a wire key is not a field name
    raises(["resize.cpu: must be a number greater than or equal to 0, got -1"], schema.component,
           schema.ContainerComponent, {"cTag": "c1", "cpu": -1}, "resize")
    raises(["resize: missing key 'cTag'"], schema.component, schema.ContainerComponent, {"cpu": 1}, "resize")


# -- Assembler ----------------------------------------------------------------------------------
def dm(**data) -> str:
    return json.dumps({"type": "DM", "data": {"iTag": "i", "type": "std_msgs/String", **data}})


_STAR_KEYS = st.sampled_from(["a", "b*", "msg", "iTag", "seq", "x\u00e9", "q\"*"])
_ODD = st.none() | st.integers(0, 9) | st.sampled_from(["v*", 'say "*"', "\\", "\u2603", ""]) | st.just([]) | \
    st.dictionaries(_STAR_KEYS, st.just([]) | st.integers(0, 3), max_size=2)


@settings(max_examples=300, deadline=None)
@given(st.dictionaries(_STAR_KEYS, _ODD, max_size=3), st.dictionaries(_STAR_KEYS, _ODD, max_size=3),
       st.booleans(), st.booleans(), st.booleans())
def test_a_forwarders_dm_is_read_as_the_walk_reads_it(data, top, ascii_only, as_bytes, part_first):
    """A DM whose ``data.msg*`` names a part, among any other keys and values (keys ending in ``*``
    with empty lists, nested dicts, values ending in ``*``, escapes): the ids ``parse_frame`` finds and
    the message the assembler completes are those of the walk (``_binary_refs``, ``_resolve``)."""
    msg = {**top, "type": "DM", "data": {**data, "msg*": ID1}}
    text = json.dumps(msg, ensure_ascii=ascii_only)
    if as_bytes:
        text = text.encode()
    want_refs: list[str] = []
    try:
        _binary_refs(parse_text(text), want_refs)
    except ProtocolError as e:                      # a key ending in '*' whose value is no id: the same error
        with pytest.raises(ProtocolError) as got:
            Assembler().feed_text(text, now=0)
        assert got.value.message == e.message
        return
    assert parse_frame(text)[1] == want_refs
    a = Assembler()
    if part_first:
        out = a.feed_binary(frame(ID1, b"p"), now=0) + a.feed_text(text, now=0)
    else:
        out = a.feed_text(text, now=0) + a.feed_binary(frame(ID1, b"p"), now=0)
    assert out == ([_resolve(parse_text(text), {ID1: b"p"})] if want_refs == [ID1] else [])


def test_assembler_plain_message_passes_through():
    a = Assembler()
    out = a.feed_text(json.dumps({"type": "DC", "data": {"containerTag": "c"}}), now=0)
    assert out == [{"type": "DC", "data": {"containerTag": "c"}}]
    assert a.pending == 0


def test_assembler_accepts_bytes_text():
    assert Assembler().feed_text(b'{"type": "CC", "data": {}}', now=0) == [{"type": "CC", "data": {}}]


def test_assembler_binary_after_json():
    a = Assembler()
    assert a.feed_text(dm(**{"msg*": ID1}), now=0) == []
    assert a.pending == 1
    out = a.feed_binary(frame(ID1, b"\x01\x02payload"), now=1)
    assert out == [{"type": "DM", "data": {"iTag": "i", "type": "std_msgs/String", "msg": b"\x01\x02payload"}}]
    assert a.pending == 0


def test_assembler_binary_before_json():
    a = Assembler()
    assert a.feed_binary(frame(ID1, b"abc"), now=0) == []
    assert a.pending == 1
    out = a.feed_text(dm(**{"msg*": ID1}), now=0.5)
    assert out[0]["data"]["msg"] == b"abc" and "msg*" not in out[0]["data"]
    assert a.pending == 0


def test_assembler_empty_payload_part():
    a = Assembler()
    a.feed_text(dm(**{"msg*": ID1}), now=0)
    assert a.feed_binary(frame(ID1, b""), now=0)[0]["data"]["msg"] == b""


def test_assembler_several_parts_any_order():
    a = Assembler()
    assert a.feed_binary(frame(ID2, b"two"), now=0) == []
    assert a.feed_text(json.dumps({"type": "DM", "data": {"a*": ID1, "b*": ID2, "c*": ID3}}), now=0) == []
    assert a.feed_binary(frame(ID3, b"three"), now=0) == []
    out = a.feed_binary(frame(ID1, b"one"), now=0)
    assert out == [{"type": "DM", "data": {"a": b"one", "b": b"two", "c": b"three"}}]
    assert a.pending == 0


def test_assembler_list_of_ids_under_one_key_keeps_order():
    a = Assembler()
    a.feed_text(json.dumps({"type": "DM", "data": {"imgs*": [ID3, ID1, ID2]}}), now=0)
    a.feed_binary(frame(ID1, b"1"), now=0)
    assert a.feed_binary(frame(ID2, b"2"), now=0) == []
    out = a.feed_binary(frame(ID3, b"3"), now=0)
    assert out[0]["data"] == {"imgs": [b"3", b"1", b"2"]}


def test_assembler_nested_star_keys_in_objects_and_lists():
    a = Assembler()
    msg = {"type": "DM", "data": {"iTag": "i", "msg": {"header": {"x": 1}, "img": {"data*": ID1},
                                                       "list": [{"blob*": ID2}, {"plain": 3}]}}}
    a.feed_binary(frame(ID2, b"B"), now=0)
    assert a.feed_text(json.dumps(msg), now=0) == []
    out = a.feed_binary(frame(ID1, b"A"), now=0)
    assert out[0]["data"]["msg"] == {"header": {"x": 1}, "img": {"data": b"A"},
                                     "list": [{"blob": b"B"}, {"plain": 3}]}


def test_assembler_two_messages_complete_independently():
    a = Assembler()
    a.feed_text(dm(**{"msg*": ID1}, msgID=1), now=0)
    a.feed_text(dm(**{"msg*": ID2}, msgID=2), now=0)
    out = a.feed_binary(frame(ID2, b"second"), now=0)
    assert [m["data"]["msgID"] for m in out] == [2]
    out = a.feed_binary(frame(ID1, b"first"), now=0)
    assert [(m["data"]["msgID"], m["data"]["msg"]) for m in out] == [(1, b"first")]
    assert a.pending == 0


@pytest.mark.parametrize("ref", ["abc", "g" * 32, "0" * 33, 5, None, {"id": ID1}, [ID1, "short"]])
def test_assembler_bad_reference_in_json(ref):
    e = raises(["msg*", "32-hex-char id"], Assembler().feed_text, json.dumps({"type": "DM", "data": {"msg*": ref}}), 0)
    assert e is not None


@pytest.mark.parametrize("text", ["{not json", "", "\xff", b"\xff\xfe", "[1, 2]", '"DM"', "null"])
def test_assembler_malformed_json(text):
    a = Assembler()
    with pytest.raises(ProtocolError):
        a.feed_text(text, now=0)
    assert a.pending == 0


@pytest.mark.parametrize("data", [b"", b"0" * (ID_LEN - 1), ("z" * ID_LEN).encode() + b"x",
                                  b"\xff" * ID_LEN + b"x", ("0" * 31 + "-").encode()])
def test_assembler_bad_binary_frames(data):
    a = Assembler()
    with pytest.raises(ProtocolError) as ei:
        a.feed_binary(data, now=0)
    assert "id" in ei.value.message
    assert a.pending == 0


def test_assembler_exact_id_length_frame_is_an_empty_part():
    a = Assembler()
    assert a.feed_binary(ID1.encode(), now=0) == []
    assert a.pending == 1


def test_assembler_accepts_memoryview_and_bytearray():
    a = Assembler()
    a.feed_text(dm(**{"msg*": ID1}), now=0)
    out = a.feed_binary(memoryview(bytearray(frame(ID1, b"mv"))), now=0)
    assert out[0]["data"]["msg"] == b"mv" and isinstance(out[0]["data"]["msg"], bytes)


def test_assembler_default_expiry_is_60s():
    assert DEFAULT_EXPIRY == 60.0 and Assembler().expiry == 60.0


def test_assembler_expires_incomplete_message():
    a = Assembler(expiry=10)
    a.feed_text(dm(**{"msg*": ID1}), now=100)
    assert a.expire(now=110) == []          # exactly at the limit: still waiting
    assert a.pending == 1
    reasons = a.expire(now=110.5)
    assert len(reasons) == 1 and "DM" in reasons[0] and "'i'" in reasons[0] and "expired" in reasons[0]
    assert "1 binary part" in reasons[0]
    assert a.pending == 0 and a.dropped == 1
    # the late part is now an orphan, not a completion
    assert a.feed_binary(frame(ID1, b"late"), now=111) == []
    assert a.pending == 1


def test_assembler_expires_orphan_parts():
    a = Assembler(expiry=5)
    a.feed_binary(frame(ID1, b"x" * 10), now=0)
    a.feed_binary(frame(ID2, b"y"), now=4)
    reasons = a.expire(now=6)
    assert len(reasons) == 1 and ID1 in reasons[0] and "no message" in reasons[0]
    assert a.pending == 1 and a.dropped == 1
    # the expired part no longer completes a message; the fresh one still does
    assert a.feed_text(dm(**{"msg*": ID1}), now=6) == []
    a2 = a.feed_text(dm(**{"msg*": ID2}), now=6)
    assert a2[0]["data"]["msg"] == b"y"


def test_assembler_parts_of_a_waiting_message_are_kept_until_the_message_expires():
    a = Assembler(expiry=5)
    a.feed_text(json.dumps({"type": "DM", "data": {"a*": ID1, "b*": ID2}}), now=3)
    a.feed_binary(frame(ID1, b"a"), now=0.5)   # arrived "early" (clock passed explicitly)
    assert a.expire(now=7) == []               # the part is old, but its message still waits
    assert a.pending == 2
    out = a.feed_binary(frame(ID2, b"b"), now=7.5)
    assert out[0]["data"] == {"a": b"a", "b": b"b"}


def test_assembler_expired_message_releases_its_parts():
    a = Assembler(expiry=5)
    a.feed_text(json.dumps({"type": "DM", "data": {"a*": ID1, "b*": ID2}}), now=0)
    a.feed_binary(frame(ID1, b"a"), now=0)
    reasons = a.expire(now=10)
    assert len(reasons) == 2 and a.pending == 0 and a.dropped == 2


def test_assembler_max_pending_bytes():
    a = Assembler(max_pending_bytes=10)
    a.feed_binary(frame(ID1, b"x" * 6), now=0)
    with pytest.raises(ProtocolError) as ei:
        a.feed_binary(frame(ID2, b"y" * 5), now=0)
    assert "10 bytes" in ei.value.message
    assert a.pending == 1                       # the refused part is not kept
    a.feed_binary(frame(ID2, b"y" * 4), now=0)  # exactly at the limit is fine
    # completing the message frees the bytes again
    a.feed_text(json.dumps({"type": "DM", "data": {"a*": ID1, "b*": ID2}}), now=0)
    assert a.pending == 0
    a.feed_binary(frame(ID3, b"z" * 10), now=0)


def test_assembler_max_pending_bytes_freed_by_expiry():
    a = Assembler(max_pending_bytes=8, expiry=1)
    a.feed_binary(frame(ID1, b"x" * 8), now=0)
    with pytest.raises(ProtocolError):
        a.feed_binary(frame(ID2, b"y"), now=0)
    a.expire(now=2)
    a.feed_binary(frame(ID2, b"y" * 8), now=2)
    assert a.pending == 1


def test_assembler_resent_part_is_counted_once():
    a = Assembler(max_pending_bytes=10)
    a.feed_binary(frame(ID1, b"x" * 4), now=0)
    a.feed_binary(frame(ID1, b"x" * 4), now=0)     # the client sent the same part twice
    assert a.pending == 1
    out = a.feed_text(dm(**{"msg*": ID1}), now=0)
    assert out[0]["data"]["msg"] == b"xxxx"
    # nothing is held any more, so the full budget is available
    a.feed_binary(frame(ID2, b"y" * 10), now=0)
    assert a.pending == 1


# -- encode -------------------------------------------------------------------------------------
def test_new_id_is_32_hex_and_fresh():
    ids = {new_id() for _ in range(50)}
    assert len(ids) == 50 and all(is_part_id(i) for i in ids)


def test_a_forked_child_makes_other_ids_than_its_parent():
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:                       # the child: its next ids, then out
        os.write(w, " ".join(new_id() for _ in range(3)).encode())
        os._exit(0)
    os.close(w)
    child = os.read(r, 4096).decode().split()
    os.close(r)
    os.waitpid(pid, 0)
    parent = [new_id() for _ in range(3)]
    assert len(child) == 3 and all(is_part_id(i) for i in child)
    assert child[0][:16] != parent[0][:16] and not set(child) & set(parent)


def test_encode_without_bytes_is_plain_json():
    text, frames = encode({"type": "ER", "data": "reason"})
    assert json.loads(text) == {"type": "ER", "data": "reason"} and frames == []


@pytest.mark.parametrize("text, value", [
    ('{"type":"DM","data":{"msg":{"x":NaN,"y":-Infinity}}}', [math.nan, -math.inf]),   # Python's json writes these
    ('{"type":"DM","data":{"msg":{"x":18446744073709551615,"y":-9223372036854775808}}}', [2**64 - 1, -2**63]),
])
def test_parse_takes_what_pythons_json_writes(text, value):
    """The fast parser refuses NaN tokens (the stdlib's takes them); uint64 and int64 stay exact."""
    msg = parse_text(text)["data"]["msg"]
    got = [msg["x"], msg["y"]]
    assert [str(v) for v in got] == [str(v) for v in value]


def test_an_integer_past_64_bits_reads_as_a_float_which_no_integer_field_takes():
    from rce.messages import default_registry
    reg = default_registry()
    msg = parse_text('{"type":"DM","data":{"msg":{"data":-9223372036854775809}}}')["data"]["msg"]
    assert isinstance(msg["data"], float)
    with pytest.raises(MessageError, match="field 'data'.*integer"):
        reg.json_to_bytes(reg.msg_type("std_msgs/Int64"), msg)


def test_parse_error_names_line_and_column():
    with pytest.raises(ProtocolError) as e:
        parse_text('{"type": "DM",\n "data": }')
    assert "malformed JSON" in e.value.message and "line 2 column" in e.value.message


@pytest.mark.parametrize("data", ["caf\u00e9 \u6e2f", "lone \ud800 surrogate", 2**70, {"nested": [1.5, None, True]}])
def test_encode_what_json_reads_back(data):
    """Non-ASCII text, a lone surrogate (which only the stdlib encodes), a big integer: all come out
    as JSON that reads back to the same value."""
    text, frames = encode({"type": "DM", "data": {"iTag": "t", "msg": {"data": data}}})
    assert frames == [] and json.loads(text)["data"]["msg"]["data"] == data


def test_encode_round_trip_through_assembler():
    msg = {"type": "DM", "data": {"iTag": "i", "type": "std_msgs/String", "msgID": "m1",
                                  "msg": b"\x00\x01\xff", "nested": {"img": bytearray(b"IMG"), "n": 1},
                                  "list": [{"p": memoryview(b"P")}, 2]}}
    text, frames = encode(msg)
    wire = json.loads(text)
    assert set(wire["data"]) == {"iTag", "type", "msgID", "msg*", "nested", "list"}
    assert set(wire["data"]["nested"]) == {"img*", "n"} and "p*" in wire["data"]["list"][0]
    assert len(frames) == 3 and all(len(f) >= ID_LEN for f in frames)
    assert frames[0][:ID_LEN].decode() == wire["data"]["msg*"] and frames[0][ID_LEN:] == b"\x00\x01\xff"
    expected = {"type": "DM", "data": {"iTag": "i", "type": "std_msgs/String", "msgID": "m1",
                                       "msg": b"\x00\x01\xff", "nested": {"img": b"IMG", "n": 1},
                                       "list": [{"p": b"P"}, 2]}}
    # JSON first, then the parts
    a = Assembler()
    assert a.feed_text(text, now=0) == []
    outs = [m for f in frames for m in a.feed_binary(f, now=0)]
    assert outs == [expected]
    # parts first (reversed), then the JSON
    a = Assembler()
    for f in reversed(frames):
        assert a.feed_binary(f, now=0) == []
    assert a.feed_text(text, now=0) == [expected]
    assert schema.dm_data(expected) == expected["data"]


def test_encode_list_of_bytes_round_trips_as_list_of_ids():
    msg = {"type": "DM", "data": {"iTag": "i", "type": "t", "msg": {}, "imgs": [b"a", b"bb", b""]}}
    text, frames = encode(msg)
    wire = json.loads(text)
    assert isinstance(wire["data"]["imgs*"], list) and len(wire["data"]["imgs*"]) == 3 and len(frames) == 3
    a = Assembler()
    a.feed_text(text, now=0)
    outs = [m for f in frames for m in a.feed_binary(f, now=0)]
    assert outs == [msg]


def test_assembler_id_reused_by_two_messages_is_consumed_once_each():
    a = Assembler()
    a.feed_text(dm(**{"msg*": ID1}, msgID=1), now=0)
    a.feed_text(json.dumps({"type": "DM", "data": {"a*": ID1, "b*": ID2, "msgID": 2}}), now=0)
    out = a.feed_binary(frame(ID1, b"one"), now=0)
    assert [m["data"]["msgID"] for m in out] == [1]
    assert a.feed_binary(frame(ID2, b"two"), now=0) == []     # the second still needs its own ID1
    out = a.feed_binary(frame(ID1, b"uno"), now=0)
    assert out == [{"type": "DM", "data": {"a": b"uno", "b": b"two", "msgID": 2}}]
    assert a.pending == 0


def test_encode_with_given_ids_numbers_parts_depth_first():
    text, frames = encode({"type": "DM", "data": {"a": b"A", "b": {"c": [b"C1", b"C2"]}}}, ids=[ID1, ID2, ID3])
    assert json.loads(text)["data"] == {"a*": ID1, "b": {"c*": [ID2, ID3]}}
    assert frames == [frame(ID1, b"A"), frame(ID2, b"C1"), frame(ID3, b"C2")]
    with pytest.raises(ProtocolError, match="binary part 1: needs a 32-hex-char id"):
        encode({"type": "DM", "data": {"a": b"A", "b": b"B"}}, ids=[ID1])
    with pytest.raises(ProtocolError, match="binary part 0"):
        encode({"type": "DM", "data": {"a": b"A"}}, ids=["0" * 32 + "\n"])


def test_assembler_bounds_the_messages_waiting_for_parts():
    a = Assembler(max_pending_messages=2)
    a.feed_text(dm(**{"msg*": ID1}), now=0)
    a.feed_text(dm(**{"msg*": ID2}), now=0)
    with pytest.raises(ProtocolError, match="2 messages already wait for their binary parts"):
        a.feed_text(dm(**{"msg*": ID3}), now=0)
    assert a.pending == 2
    assert a.feed_text(dm(msg={}), now=0) != []        # a message without parts never waits


# -- one schema for the wire and the robot config -----------------------------------------------
def test_wire_components_take_keys_they_do_not_know():
    """The RCE alpha client may send more than docs/design.md, section 3.3, names: components and DM data
    take unknown keys; only the CN and CX objects (whose keys say what to do) refuse them."""
    node = {"containerTag": "c", "nodeTag": "n", "pkg": "Test", "exe": "e", "launcher": "x"}
    cn = validate({"type": "CN", "data": {"addNodes": [node]}})[1]
    assert cn.addNodes[0].wire() == {k: v for k, v in node.items() if k != "launcher"}      # taken, not passed on
    assert validate({"type": "CC", "data": {"containerTag": "c", "extra": 1}})[0] == "CC"
    dm = {"iTag": "i", "type": "t", "msg": {}, "seq": 3}
    assert validate({"type": "DM", "data": dm})[0] == "DM" and schema.dm_data({"type": "DM", "data": dm}) == dm
    assert validate({"type": "CC", "data": {"containerTag": "c"}, "id": 7})[0] == "CC"


def test_wire_uses_the_long_keys_only():
    raises(["CC.data", "missing key 'containerTag'"], validate, {"type": "CC", "data": {"cTag": "c"}})
    raises(["CN.data.addInterfaces[0]", "missing key 'endpointTag'"], validate,
           {"type": "CN", "data": {"addInterfaces": [{"eTag": "c", "iTag": "i", "iType": "PublisherInterface",
                                                      "iCls": "std_msgs/String"}]}})


def test_the_config_builds_on_the_schema_components():
    from rce.protocol.config import ConnectionSpec, ContainerSpec, InterfaceSpec, NodeSpec, ParameterSpec, parse_config
    from rce.protocol import schema
    for spec, wire in ((ContainerSpec, schema.ContainerComponent), (NodeSpec, schema.NodeComponent),
                       (ParameterSpec, schema.ParameterComponent), (InterfaceSpec, schema.InterfaceComponent),
                       (ConnectionSpec, schema.ConnectionComponent)):
        assert issubclass(spec, wire)
    cfg = parse_config({"url": "http://m/", "userID": "u", "password": "p", "robotID": "r",
                        "containers": [{"cTag": "c", "cpu": 1, "group": "g"}],
                        "nodes": [{"cTag": "c", "nTag": "n", "pkg": "Test", "exe": "e", "args": ["-v"]}],
                        "interfaces": [{"eTag": "c", "iTag": "i", "iType": "PublisherInterface",
                                        "iCls": "std_msgs/String", "addr": "/p"}],
                        "connections": [{"tagA": "c/i", "tagB": "r/i"}]})
    # what the config sends passes the wire schema unchanged
    cc = {"containerTag": "c", "containerData": cfg.containers[0].container_data()}
    assert validate({"type": "CC", "data": cc})[1].wire() == {"containerTag": "c",
                                                              "containerData": {"group": "g", "cpu": 1}}
    cn = {"addNodes": [n.component() for n in cfg.nodes], "addInterfaces": [i.component() for i in cfg.interfaces]}
    assert validate({"type": "CN", "data": cn})[1].wire()["addNodes"] == [
        {"containerTag": "c", "nodeTag": "n", "pkg": "Test", "exe": "e", "args": ["-v"]}]
    assert cn["addInterfaces"] == [{"endpointTag": "c", "interfaceTag": "i", "interfaceType": "PublisherInterface",
                                    "className": "std_msgs/String", "addr": "/p"}]


def test_the_same_rule_words_its_error_the_same_on_the_wire_and_in_a_config():
    from rce.protocol.config import parse_config
    from rce.plumbing.errors import ConfigError
    base = {"url": "http://m/", "userID": "u", "password": "p", "robotID": "r"}
    with pytest.raises(ConfigError) as ei:
        parse_config({**base, "nodes": [{"cTag": "c", "nTag": "n", "pkg": "Test", "exe": "e", "respawn": "yes"}]}, "f")
    assert ei.value.message == "f: nodes[0].respawn: must be a boolean or an object, got 'yes'"
    wire = raises([], validate, {"type": "CN", "data": {"addNodes": [
        {"containerTag": "c", "nodeTag": "n", "pkg": "Test", "exe": "e", "respawn": "yes"}]}})
    assert wire.message == "CN.data.addNodes[0].respawn: must be a boolean or an object, got 'yes'"
