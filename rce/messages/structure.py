"""Does a ROS 1 serialized message fit its class? A length walk, without building the message.

A forwarder passes the robot's bytes through untouched (docs/design.md, section 4.2), as the original
RCE did: strings are not decoded (a ``std_msgs/String`` that is not UTF-8 passes), numbers are
not read. What is checked is the structure: every length prefix stays inside the payload and
the last field ends exactly at its end.

The format is the ROS 1 serialization (wiki.ros.org/msg, "Serialization"): little endian;
fixed-size fields back to back; a ``string`` and a variable-length array start with a uint32
count (bytes, items); a fixed-length array has none; ``time`` and ``duration`` are two 32-bit
integers. :func:`compile_walker` turns a class's field definitions (the rosbags typestore's
``fielddefs``) into a list of steps, runs of fixed-size fields merged into one skip.
"""
from __future__ import annotations

import struct
from typing import Callable

from rosbags.typesys.base import Nodetype

_U32 = struct.Struct("<I").unpack_from
_SIZES = {"bool": 1, "byte": 1, "char": 1, "int8": 1, "uint8": 1, "int16": 2, "uint16": 2, "int32": 4,
          "uint32": 4, "int64": 8, "uint64": 8, "float32": 4, "float64": 8}
_SKIP, _STR, _SEQ_FIXED, _SEQ, _ARR, _MSG = range(6)

#: walk(payload, position, end) -> the position after the message; raises :class:`Short`
Walker = Callable[[memoryview, int, int], int]
_PLACEHOLDER = "structure_needs_at_least_one_member"   # rosbags' field of an empty message: not serialized


def _fields(fielddefs: dict, typename: str) -> list[tuple[str, tuple]]:
    """The serialized fields of ``typename`` (an empty message has none)."""
    return [(n, t) for n, t in fielddefs[typename][1] if n != _PLACEHOLDER]


class Short(Exception):
    """The payload ends inside field ``path`` (or holds a count that cannot fit)."""

    def __init__(self, path: str, why: str):
        super().__init__(path, why)
        self.path, self.why = path, why

    def within(self, name: str) -> "Short":
        """The same shortfall, with the enclosing field's name in front of the path."""
        if not self.path:
            return Short(name, self.why)
        return Short(f"{name}{self.path}" if self.path.startswith("[") else f"{name}.{self.path}", self.why)


def fixed_size(fielddefs: dict, typename: str) -> int | None:
    """Bytes of every message of ``typename`` if that is fixed (no string, no variable array), else None."""
    total = 0
    for _, ftype in _fields(fielddefs, typename):
        n = _field_size(fielddefs, ftype)
        if n is None:
            return None
        total += n
    return total


def _field_size(fielddefs: dict, ftype: tuple) -> int | None:
    nt, arg = ftype
    if nt == Nodetype.BASE:
        return _SIZES.get(arg[0])            # None for string
    if nt == Nodetype.NAME:
        return fixed_size(fielddefs, arg)
    sub, count = arg
    if nt == Nodetype.SEQUENCE:
        return None
    n = _field_size(fielddefs, sub)
    return None if n is None else n * count


def _min_size(fielddefs: dict, ftype: tuple) -> int:
    """The fewest bytes a value of ``ftype`` takes (a count prefix: 4)."""
    nt, arg = ftype
    n = _field_size(fielddefs, ftype)
    if n is not None:
        return n
    if nt == Nodetype.BASE or nt == Nodetype.SEQUENCE:
        return 4
    if nt == Nodetype.NAME:
        return sum(_min_size(fielddefs, f) for _, f in _fields(fielddefs, arg))
    return _min_size(fielddefs, arg[0]) * arg[1]


def compile_walker(fielddefs: dict, typename: str, cache: dict[str, Walker]) -> Walker:
    """The walker of ``typename`` (walkers of nested classes are kept in ``cache``)."""
    if typename in cache:
        return cache[typename]
    steps: list[tuple[int, object, object]] = []
    for fname, ftype in _fields(fielddefs, typename):
        op, arg = _step(fielddefs, ftype, cache)
        if op == _SKIP and steps and steps[-1][0] == _SKIP:   # one skip for a run of fixed-size fields
            steps[-1] = (_SKIP, steps[-1][1] + arg, [*steps[-1][2], (fname, arg)])
        else:
            steps.append((op, arg, [(fname, arg)] if op == _SKIP else fname))
    walker = cache[typename] = _make(steps)
    return walker


def _step(fielddefs: dict, ftype: tuple, cache: dict) -> tuple[int, object]:
    n = _field_size(fielddefs, ftype)
    if n is not None:
        return _SKIP, n
    nt, arg = ftype
    if nt == Nodetype.BASE:
        return _STR, 1
    if nt == Nodetype.NAME:
        return _MSG, compile_walker(fielddefs, arg, cache)
    sub, count = arg
    item = _field_size(fielddefs, sub)
    if nt == Nodetype.SEQUENCE and item is not None:
        return _SEQ_FIXED, item
    sub_step = _step(fielddefs, sub, cache)
    item_walk = sub_step[1] if sub_step[0] == _MSG else _make([(sub_step[0], sub_step[1], "")])   # a string
    if nt == Nodetype.SEQUENCE:
        return _SEQ, (item_walk, _min_size(fielddefs, sub))
    return _ARR, (item_walk, count)


def _count(buf: memoryview, pos: int, end: int, name: str, item: int) -> int:
    """The uint32 count at ``pos``; raises :class:`Short` when it or its ``item``-byte items cannot fit."""
    if pos + 4 > end:
        raise Short(name, f"needs a 4-byte length at offset {pos}, {end - pos} byte(s) left")
    n = _U32(buf, pos)[0]
    if n * item > end - pos - 4:
        raise Short(name, f"counts {n} item(s) of {item}+ byte(s) at offset {pos}, {end - pos - 4} byte(s) left")
    return n


def _short_skip(fields: list[tuple[str, int]], pos: int, end: int) -> Short:
    """Which of a run of fixed-size ``fields`` starting at ``pos`` the payload ends in."""
    for name, size in fields:
        if pos + size > end:
            return Short(name, f"needs {size} byte(s) at offset {pos}, {end - pos} left")
        pos += size
    return Short(fields[-1][0], "runs past the end")


def _make(steps: list[tuple[int, object, object]]) -> Walker:
    def walk(buf: memoryview, pos: int, end: int) -> int:
        for op, arg, name in steps:
            if op == _SKIP:
                if pos + arg > end:
                    raise _short_skip(name, pos, end)
                pos += arg
            elif op == _STR or op == _SEQ_FIXED:
                pos += 4 + _count(buf, pos, end, name, arg) * arg
            elif op == _MSG:
                try:
                    pos = arg(buf, pos, end)
                except Short as e:
                    raise e.within(name) from None
            else:
                item_walk, n = arg
                if op == _SEQ:
                    count = _count(buf, pos, end, name, n)
                    pos += 4
                else:
                    count = n
                for i in range(count):
                    try:
                        pos = item_walk(buf, pos, end)
                    except Short as e:
                        raise e.within(f"{name}[{i}]") from None
        return pos
    return walk
