"""ROS 1 serialization compiled per message class: the fast path of :class:`rce.messages.MessageRegistry`.

rosbags (whose typestore holds rce's classes) generates a function per class too, but one that
looks its nested classes up and packs every field on its own; a frequent small message
(``geometry_msgs/PoseWithCovarianceStamped``: 7 nested objects, 47 numbers) then costs more in
those calls than in its bytes. :func:`compile_codec` generates, once per class, Python source in
which nested messages are inlined, every run of fixed-size fields (across nested messages: a
header's ``seq`` and stamp, a pose's 7 numbers) is one :class:`struct.Struct` call, a message is
built with positional arguments, and arrays of numbers are one ``numpy.frombuffer`` (reading) or
one ``tobytes``/``struct.pack`` (writing). Three functions per class:

- ``deserialize(data) -> message``: as rosbags' (the same classes; arrays of numbers are
  read-only ``numpy`` views of ``data``, strings decoded with ``surrogateescape``,
  :mod:`rce.messages.ros_strings`);
- ``serialize(message) -> bytes``: a typestore instance;
- ``serialize_json(obj, forms) -> bytes``: a JSON-form dict (:meth:`MessageRegistry.from_json`)
  straight to bytes, without building the instance, for the canonical forms only: every field
  present, no other key, numbers as ``int``/``float`` (``bool`` for ``bool``), strings ``str``,
  times ``{"secs", "nsecs"}``, arrays lists.

And per class and client's JSON forms (:attr:`rce.messages.forms.JsonForms.key`), a
:class:`JsonReader`: ``to_json(data) -> dict``, the JSON form of a payload read straight from its
bytes, without building the message (what a converter sends a robot): non-finite floats ``null``,
strings with U+FFFD for bytes that are not UTF-8 (:func:`rce.messages.ros_strings.to_text`), byte
arrays base64 or ``bytes``, times as ``{secs, nsecs}`` or ``{sec, nanosec}`` (the other time forms
and images as files are the general path's).

The format is ROS 1 serialization (wiki.ros.org/msg, "Serialization"; rosbags' ``serde/ros1.py``
is the reference the tests compare against byte for byte): little endian, fixed-size fields back
to back, a ``string`` and a variable-length array prefixed with a ``uint32`` count (bytes, items),
a fixed-length array without one.

Anything else is not this module's to decide: each function raises :class:`Fallback` (or
whatever ``struct``/``numpy`` raise) where its input is not one it handles exactly as rosbags and
the JSON codec do (a value of another type, a missing field, a ``null`` float, a base64 byte
array, an image, a payload that does not fit), and the caller then takes the general path, which
gives the same result or the error that names the field. A class the generator does not handle
(an empty message, a field named like a Python keyword, a recursive definition) gets no codec
(:func:`compile_codec` returns None).
"""
from __future__ import annotations

import base64
import keyword
import math
import struct
import sys
from typing import Any, Callable, NamedTuple

import numpy as np
from rosbags.typesys.base import Nodetype

from rce.messages.ros_strings import ERRORS

__all__ = ["Codec", "Fallback", "JsonReader", "compile_codec", "compile_json_reader"]

#: struct format character of each ROS 1 base type (as rosbags packs them: ``byte`` signed, ``char`` unsigned)
_FMT = {"bool": "?", "byte": "b", "char": "B", "int8": "b", "uint8": "B", "int16": "h", "uint16": "H",
        "int32": "i", "uint32": "I", "int64": "q", "uint64": "Q", "float32": "f", "float64": "d"}
#: numpy dtype of each base type in an array (rosbags' ``ndtype``)
_DTYPE = {t: np.dtype({"bool": "bool", "char": "uint8"}.get(t, t)) for t in _FMT}
#: item size -> the arrays rosbags writes as their memory (numbers in native order; a uint8 array for
#: a ``byte[]``, as the JSON codec makes it, as well as the int8 rosbags reads)
_RAW = {size: frozenset(np.dtype(f"{k}{size}") for k in "iuf" if k != "f" or size > 1) | (
    {np.dtype(bool)} if size == 1 else set()) for size in (1, 2, 4, 8)}
_FLOATS = {"float32", "float64"}
_BYTES = {"uint8", "char", "byte"}                    # arrays of these are bytes in JSON (base64 or a binary part)
#: a time's keys in each JSON form that is an object (rce.messages.forms); the others are the general path's
_TIME_FORM_KEYS = {"secs": ("secs", "nsecs"), "sec": ("sec", "nanosec")}
_TIME_TYPES = {"builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration"}
_TIME_KEYS = {"sec": "secs", "nanosec": "nsecs"}     # a time's fields -> their keys in rce's JSON form
_PLACEHOLDER = "structure_needs_at_least_one_member"  # rosbags' field of an empty message
_IMAGE = "sensor_msgs/msg/Image"                      # has forms of its own (a PNG part): the JSON path never


class Fallback(Exception):
    """The input is not one the compiled function handles; take the general path."""


class Codec(NamedTuple):
    """The compiled functions of one class (see the module docstring); ``serialize_json`` is None
    for a class whose JSON forms the fast path does not cover (it holds a ``sensor_msgs/Image`` or
    a ``byte``, whose JSON range is not the one rosbags packs). ``read``, ``write`` and
    ``write_json`` are what the first three call, and what a class that holds this one in an array
    calls per item: ``read(data, pos) -> (message, pos)``, ``write(message, parts) -> parts`` and
    ``write_json(obj, parts, forms) -> parts`` (``parts``: a list of ``bytes`` appended to)."""
    deserialize: Callable[[bytes | memoryview], Any]
    serialize: Callable[[Any], bytes]
    serialize_json: Callable[[dict, Any], bytes] | None
    read: Callable
    write: Callable
    write_json: Callable


class JsonReader(NamedTuple):
    """The compiled JSON reader of one class in one client's forms: ``to_json(data) -> dict`` is
    :meth:`MessageRegistry.bytes_to_json` of a payload that fits (else it raises, and the general path
    decides); ``read(data, pos) -> (dict, pos)`` is what a class that holds this one in an array calls."""
    to_json: Callable[[bytes | memoryview], dict]
    read: Callable


class _Unsupported(Exception):
    pass


def _finite(values: list) -> list:
    """A float array's JSON form: non-finite values ``null`` (as the general path writes them)."""
    if all(map(math.isfinite, values)):
        return values
    return [x if math.isfinite(x) else None for x in values]


def _complete(obj: dict, names: frozenset, defaults: dict) -> dict:
    """``obj`` with the fields of ``names`` it lacks taken from ``defaults``; :class:`Fallback` for a
    key that is not in ``names`` or a missing field without a default."""
    if not obj.keys() <= names:
        raise Fallback("a key that is no field")
    missing = names - obj.keys()
    if not missing <= defaults.keys():
        raise Fallback("a field left out that has no plain default")
    full = {k: [] if defaults[k] == () else defaults[k] for k in missing}
    full.update(obj)
    return full


def compile_codec(fielddefs: dict, classes: dict, typename: str, max_sequence: int,
                  cache: dict[str, Codec | None]) -> Codec | None:
    """The :class:`Codec` of store type ``typename`` (``fielddefs``/``classes``: the rosbags
    typestore's ``fielddefs`` and ``types``; ``max_sequence``: its ``max_sequence_length``, the
    largest item count a payload may hold), or None when the class is not one this module
    handles. ``cache`` (type -> codec) holds the codecs of the classes inside arrays, which are
    compiled on the way; the result is stored in it too."""
    if typename in cache:
        return cache[typename]
    if sys.byteorder != "little":
        cache[typename] = None
        return None
    try:
        codec = _Generator(fielddefs, classes, max_sequence, cache).codec(typename, set())
    except _Unsupported:
        codec = None
    cache[typename] = codec
    return codec


def compile_json_reader(fielddefs: dict, classes: dict, typename: str, key: tuple, max_sequence: int,
                        cache: dict[tuple, JsonReader | None]) -> JsonReader | None:
    """The :class:`JsonReader` of store type ``typename`` in the JSON forms ``key``
    (:attr:`rce.messages.forms.JsonForms.key`), or None when the class or the forms are not ones this
    module handles (a time as ISO 8601 or float seconds; an image as a PNG or JPEG file). Arguments
    as :func:`compile_codec`; ``cache`` holds readers by ``(type, key)``."""
    if (typename, key) in cache:
        return cache[(typename, key)]
    reader = None
    if sys.byteorder == "little":
        try:
            reader = _Generator(fielddefs, classes, max_sequence, cache, key).json_reader(typename, set())
        except _Unsupported:
            pass
    cache[(typename, key)] = reader
    return reader


class _Generator:
    """Writes the source of one class's three functions (nested messages inlined)."""

    def __init__(self, fielddefs: dict, classes: dict, max_sequence: int, cache: dict, key: tuple | None = None):
        """``key``: None to write a class's :class:`Codec`; a :attr:`JsonForms.key` to write its
        JSON reader in those forms (``cache`` then holds readers by ``(type, key)``)."""
        self.fielddefs, self.classes, self.max_sequence, self.cache = fielddefs, classes, max_sequence, cache
        self.key = key
        self.ns: dict[str, Any] = {"Fallback": Fallback, "frombuffer": np.frombuffer, "ndarray": np.ndarray,
                                   "U32": struct.Struct("<I").unpack_from, "P32": struct.Struct("<I").pack,
                                   "pack": struct.pack, "MAXSEQ": max_sequence, "ERR": ERRORS,
                                   "complete": _complete, "finite": _finite, "b64": base64.b64encode}
        self.names: dict[Any, str] = {}
        self.n = 0

    def var(self, prefix: str = "v") -> str:
        self.n += 1
        return f"{prefix}{self.n}"

    def const(self, value: Any, prefix: str, key: Any = None) -> str:
        """A name in the generated module's namespace bound to ``value`` (one per ``key``, default
        the value's identity)."""
        key = (prefix, id(value) if key is None else key)
        if key not in self.names:
            name = self.names[key] = f"{prefix}{len(self.names)}"
            self.ns[name] = value
        return self.names[key]

    def struct(self, fmt: str) -> str:
        return self.const(struct.Struct("<" + fmt), "S", fmt)

    def fields(self, typename: str) -> list[tuple[str, tuple]]:
        if typename not in self.fielddefs:
            raise _Unsupported(typename)
        fields = self.fielddefs[typename][1]
        for fname, _ in fields:
            if fname == _PLACEHOLDER or not fname.isidentifier() or keyword.iskeyword(fname):
                raise _Unsupported(fname)
        return fields

    def sub(self, typename: str, stack: set) -> Codec | JsonReader:
        """The codec (JSON reader, with :attr:`key`) of a class inside an array (a function of its own)."""
        if typename in stack:
            raise _Unsupported(typename)
        ck = typename if self.key is None else (typename, self.key)
        if ck not in self.cache:
            gen = _Generator(self.fielddefs, self.classes, self.max_sequence, self.cache, self.key)
            try:
                self.cache[ck] = gen.codec(typename, stack) if self.key is None else gen.json_reader(typename, stack)
            except _Unsupported:
                self.cache[ck] = None
        codec = self.cache[ck]
        if codec is None:
            raise _Unsupported(typename)
        return codec

    def json_reader(self, typename: str, stack: set) -> JsonReader:
        ns = self.exec(self.reader(typename, stack, "to_json"), f"{typename} to JSON {'/'.join(self.key)}")
        return JsonReader(ns["to_json"], ns["des"])

    def reader(self, typename: str, stack: set, name: str) -> list[str]:
        """The source of ``des(buf, pos) -> (value, pos)`` and of ``name(data) -> value``, which takes
        exactly the whole payload."""
        stack = stack | {typename}
        lines: list[str] = []
        run: list[tuple[str, str]] = []
        expr = self.des(typename, lines, run, stack)
        self.flush_des(lines, run)
        return ["def des(buf, pos):", *lines, f"    return {expr}, pos",
                f"def {name}(data):",
                "    value, pos = des(data, 0)",
                "    if pos != len(data):",
                "        raise Fallback('bytes left after the last field')",
                "    return value"]

    def exec(self, src: list[str], what: str) -> dict:
        """Compile and run ``src``; its namespace."""
        code = compile("\n".join(src), f"<rce.messages.compiled {what}>", "exec")
        ns = dict(self.ns)
        exec(code, ns)      # noqa: S102 - source generated from the typestore's field definitions
        return ns

    def codec(self, typename: str, stack: set) -> Codec:
        read = self.reader(typename, stack, "deserialize")
        stack = stack | {typename}
        json_ok = [True]
        run: list[tuple[str, str]] = []
        s_lines: list[str] = []
        self.ser(typename, "m", s_lines, run, stack)
        self.flush_ser(s_lines, run)
        j_lines: list[str] = []
        self.ser_json(typename, "d", j_lines, run, stack, json_ok)
        self.flush_ser(j_lines, run)
        src = [*read,
               "def ser(m, out):", *s_lines, "    return out",
               "def serialize(m):",
               "    return b''.join(ser(m, []))",
               "def ser_json(d, out, forms):",
               "    if type(d) is not dict:",
               "        raise Fallback('not an object')",
               *self.complete(typename, "d"),
               *j_lines, "    return out",
               "def serialize_json(d, forms):",
               "    return b''.join(ser_json(d, [], forms))"]
        ns = self.exec(src, typename)
        return Codec(ns["deserialize"], ns["serialize"], ns["serialize_json"] if json_ok[0] else None,
                     ns["des"], ns["ser"], ns["ser_json"])

    # -- reading -------------------------------------------------------------------------------------
    def flush_des(self, lines: list[str], run: list[tuple[str, str]]) -> None:
        if not run:
            return
        fmt = "".join(f for _, f in run)
        s = self.struct(fmt)
        lines.append(f"    {', '.join(v for v, _ in run)}, = {s}.unpack_from(buf, pos)")
        lines.append(f"    pos += {struct.calcsize('<' + fmt)}")
        run.clear()

    def des(self, typename: str, lines: list[str], run: list, stack: set) -> str:
        """Append the reading of ``typename``'s fields; the expression that builds the message (the
        JSON form's dict, with :attr:`key`)."""
        if self.key is not None and typename == _IMAGE and self.key[2] != "json":
            raise _Unsupported(typename)            # a PNG or JPEG file: the general path encodes it
        args = []
        for _, (nt, arg) in self.fields(typename):
            if nt == Nodetype.BASE and arg[0] in _FMT:
                v = self.var()
                run.append((v, _FMT[arg[0]]))
                # JSON has no NaN or infinity: null, as rosbridge sends them (x - x is 0 for finite x only)
                args.append(f"({v} if {v} - {v} == 0.0 else None)" if self.key is not None and arg[0] in _FLOATS
                            else v)
            elif nt == Nodetype.BASE and arg[0] == "string":
                self.flush_des(lines, run)
                v = self.var()
                # a message keeps bytes that are not UTF-8 (surrogate escapes); JSON gets U+FFFD for them
                # (what ros_strings.to_text makes of the escapes)
                errors = "ERR" if self.key is None else "'replace'"
                lines += ["    n, = U32(buf, pos)", "    pos += 4", "    e = pos + n",
                          "    if e > len(buf):", "        raise Fallback('a string passes the end')",
                          f"    {v} = str(buf[pos:e], 'utf-8', {errors})", "    pos = e"]
                args.append(v)
            elif nt == Nodetype.BASE:
                raise _Unsupported(arg[0])
            elif nt == Nodetype.NAME:
                if arg in stack:
                    raise _Unsupported(arg)
                args.append(self.des(arg, lines, run, stack | {arg}))
            else:
                self.flush_des(lines, run)
                args.append(self.des_array(nt, arg, lines, stack))
        if self.key is None:
            return f"{self.const(self.classes[typename], 'C')}({', '.join(args)})"
        names = [f for f, _ in self.fields(typename)]
        if typename in _TIME_TYPES:
            form = self.key[0] if typename.endswith("/Time") else self.key[1]
            if form not in _TIME_FORM_KEYS:
                raise _Unsupported(form)            # an ISO 8601 string or float seconds: the general path
            names = list(_TIME_FORM_KEYS[form])
        return "{" + ", ".join(f"{k!r}: {a}" for k, a in zip(names, args, strict=True)) + "}"

    def des_array(self, nt: int, arg: tuple, lines: list[str], stack: set) -> str:
        (sub_nt, sub_arg), length = arg
        v = self.var()
        if nt == Nodetype.SEQUENCE:
            lines += ["    n, = U32(buf, pos)", "    pos += 4", "    if n > MAXSEQ:",
                      "        raise Fallback('too many items')"]
        else:
            lines.append(f"    n = {length}")
        if sub_nt == Nodetype.BASE and sub_arg[0] in _FMT and self.key is not None and sub_arg[0] in _BYTES:
            form = "b64({0}).decode()" if self.key[3] == "base64" else "{0}"    # base64 text or a binary part
            lines += ["    if pos + n > len(buf):", "        raise Fallback('an array passes the end')",
                      f"    {v} = {form.format('bytes(buf[pos:pos + n])')}", "    pos += n"]
        elif sub_nt == Nodetype.BASE and sub_arg[0] in _FMT:
            size = struct.calcsize(_FMT[sub_arg[0]])
            dt = self.const(_DTYPE[sub_arg[0]], "DT")
            lines += [f"    {v} = frombuffer(buf, dtype={dt}, count=n, offset=pos)", f"    pos += n * {size}"]
            if self.key is not None:
                lines.append(f"    {v} = {'finite(' if sub_arg[0] in _FLOATS else '('}{v}.tolist())")
        elif sub_nt == Nodetype.BASE and sub_arg[0] == "string":
            errors = "ERR" if self.key is None else "'replace'"
            lines += [f"    {v} = []", "    for _ in range(n):", "        k, = U32(buf, pos)",
                      "        e = pos + 4 + k", "        if e > len(buf):",
                      "            raise Fallback('a string passes the end')",
                      f"        {v}.append(str(buf[pos + 4:e], 'utf-8', {errors}))", "        pos = e"]
        elif sub_nt == Nodetype.NAME:
            f = self.const(self.sub(sub_arg, stack).read, "D")
            lines += [f"    {v} = []", "    for _ in range(n):", f"        o, pos = {f}(buf, pos)",
                      f"        {v}.append(o)"]
        else:
            raise _Unsupported(sub_nt)
        return v

    # -- writing a typestore instance -------------------------------------------------------------
    def flush_ser(self, lines: list[str], run: list[tuple[str, str]]) -> None:
        if not run:
            return
        fmt = "".join(f for _, f in run)
        lines.append(f"    out.append({self.struct(fmt)}.pack({', '.join(e for e, _ in run)}))")
        run.clear()

    def ser(self, typename: str, obj: str, lines: list[str], run: list, stack: set) -> None:
        """Append the writing of instance ``obj`` (a local) of ``typename``."""
        for fname, (nt, arg) in self.fields(typename):
            val = f"{obj}.{fname}"
            if nt == Nodetype.BASE and arg[0] in _FMT:
                run.append((val, _FMT[arg[0]]))
            elif nt == Nodetype.BASE and arg[0] == "string":
                s = self.var("s")
                lines.append(f"    {s} = {val}.encode('utf-8', ERR)")
                run.append((f"len({s})", "I"))
                self.flush_ser(lines, run)
                lines.append(f"    out.append({s})")
            elif nt == Nodetype.NAME:
                o = self.var("o")
                lines.append(f"    {o} = {val}")
                self.ser(arg, o, lines, run, stack | {arg})
            else:
                self.ser_array(nt, arg, val, lines, run, stack)

    def array_head(self, nt: int, length: int, a: str, lines: list[str], run: list) -> None:
        """Append the check of a fixed-length array's length, or a sequence's count to the run; then
        write the run (the items follow)."""
        if nt == Nodetype.ARRAY:
            lines += [f"    if len({a}) != {length}:", "        raise Fallback('not the array length')"]
        else:
            run.append((f"len({a})", "I"))
        self.flush_ser(lines, run)

    def ser_array(self, nt: int, arg: tuple, val: str, lines: list[str], run: list, stack: set) -> None:
        (sub_nt, sub_arg), length = arg
        a = self.var("a")
        lines.append(f"    {a} = {val}")
        self.array_head(nt, length, a, lines, run)
        if sub_nt == Nodetype.BASE and sub_arg[0] in _FMT:
            size = _DTYPE[sub_arg[0]].itemsize
            ok = self.const(_RAW[size], "OK", ("OK", size))
            lines += [f"    if type({a}) is not ndarray or {a}.dtype not in {ok} or {a}.ndim != 1:",
                      "        raise Fallback('not an array of the field type')", f"    out.append({a}.tobytes())"]
        elif sub_nt == Nodetype.BASE and sub_arg[0] == "string":
            lines += [f"    for x in {a}:", "        x = x.encode('utf-8', ERR)", "        out.append(P32(len(x)))",
                      "        out.append(x)"]
        elif sub_nt == Nodetype.NAME:
            f = self.const(self.sub(sub_arg, stack).write, "W")
            lines += [f"    for x in {a}:", f"        {f}(x, out)"]
        else:
            raise _Unsupported(sub_nt)

    # -- writing a JSON-form dict -------------------------------------------------------------------
    def ser_json(self, typename: str, obj: str, lines: list[str], run: list, stack: set, ok: list) -> None:
        """Append the writing of dict ``obj`` (a local, already checked to be a dict with as many
        keys as ``typename`` has fields) of ``typename``."""
        if typename == _IMAGE:
            ok[0] = False
        time = typename in _TIME_TYPES
        for fname, (nt, arg) in self.fields(typename):
            key = _TIME_KEYS[fname] if time else fname
            v = self.var()
            lines.append(f"    {v} = {obj}[{key!r}]")
            if nt == Nodetype.BASE and arg[0] in _FMT:
                if arg[0] == "byte":        # JSON takes 0..255, rosbags packs -128..127: the general path decides
                    ok[0] = False
                if arg[0] in _FLOATS:
                    cond = f"type({v}) is not float and type({v}) is not int"
                else:
                    cond = f"type({v}) is not {'bool' if arg[0] == 'bool' else 'int'}"
                lines += [f"    if {cond}:", "        raise Fallback('not the canonical form')"]
                run.append((v, _FMT[arg[0]]))
            elif nt == Nodetype.BASE and arg[0] == "string":
                lines += [f"    if type({v}) is not str:", "        raise Fallback('not the canonical form')",
                          f"    {v} = {v}.encode('utf-8', ERR)"]
                run.append((f"len({v})", "I"))
                self.flush_ser(lines, run)
                lines.append(f"    out.append({v})")
            elif nt == Nodetype.NAME:
                lines += [f"    if type({v}) is not dict:", "        raise Fallback('not an object')",
                          *self.complete(arg, v)]
                self.ser_json(arg, v, lines, run, stack | {arg}, ok)
            else:
                self.ser_json_array(nt, arg, v, lines, run, stack, ok)
        if time:            # both fields were there and integers: the client's time form is {secs, nsecs}
            lines.append("    forms.saw('time', 'secs')")

    def complete(self, typename: str, obj: str) -> list[str]:
        """The lines that give dict ``obj`` the fields it leaves out, when each of them has a default
        that needs no form (a number, a ``bool``, a string, a variable-length array), and raise
        :class:`Fallback` for any other key missing or a key that is no field."""
        fields = self.fields(typename)
        defaults = {}
        for fname, (nt, arg) in fields:
            if nt == Nodetype.BASE:
                defaults[fname] = "" if arg[0] == "string" else False if arg[0] == "bool" else \
                    0.0 if arg[0] in _FLOATS else 0
            elif nt == Nodetype.SEQUENCE:
                defaults[fname] = ()        # copied to a list where it is used
        if typename in _TIME_TYPES:
            defaults = {}       # an absent time is (0, 0) but decides no form: the general path
        names = self.const(frozenset(_TIME_KEYS[f] if typename in _TIME_TYPES else f for f, _ in fields), "K",
                           ("K", typename))
        dflt = self.const(defaults, "F", ("F", typename))
        return [f"    if len({obj}) != {len(fields)}:", f"        {obj} = complete({obj}, {names}, {dflt})"]

    def ser_json_array(self, nt: int, arg: tuple, a: str, lines: list[str], run: list, stack: set,
                       ok: list) -> None:
        (sub_nt, sub_arg), length = arg
        lines += [f"    if type({a}) is not list:", "        raise Fallback('not the canonical form')"]
        self.array_head(nt, length, a, lines, run)
        if sub_nt == Nodetype.BASE and sub_arg[0] in _FMT:
            t = sub_arg[0]
            kinds = "{float, int}" if t in _FLOATS else "{bool}" if t == "bool" else "{int}"
            fmt = "B" if t == "byte" else _FMT[t]     # a byte[] in JSON is 0..255, as uint8[] (base64 or a list)
            lines += [f"    if {a} and not set(map(type, {a})) <= {kinds}:",
                      "        raise Fallback('not the canonical form')",
                      f"    out.append(pack('<%d{fmt}' % len({a}), *{a}))"]
        elif sub_nt == Nodetype.BASE and sub_arg[0] == "string":
            lines += [f"    for x in {a}:", "        if type(x) is not str:",
                      "            raise Fallback('not the canonical form')", "        x = x.encode('utf-8', ERR)",
                      "        out.append(P32(len(x)))", "        out.append(x)"]
        elif sub_nt == Nodetype.NAME:
            codec = self.sub(sub_arg, stack)
            if codec.serialize_json is None:
                ok[0] = False
                return
            f = self.const(codec.write_json, "J")
            lines += [f"    for x in {a}:", f"        {f}(x, out, forms)"]
        else:
            raise _Unsupported(sub_nt)
