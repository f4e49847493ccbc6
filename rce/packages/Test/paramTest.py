#!/usr/bin/env python3
"""Test/paramTest.py: serves ``parameterTest`` (Test/ParameterTest: empty request, response
``string msg``) with the container parameters ``int``, ``str``, ``float`` and ``bool`` in the
original engine's exact text::

    int:   99
    str:   foo
    float: 3.14
    bool:  True

Source: the original RCE's test package, ``test/Test/nodes/paramTest.py`` of the
``rapyuta-robotics/rce`` repository (commit b29a58c4d65c3c81fc458ba42d3f9c6997cd2196):
``'int:   {0}\\nstr:   {1}\\nfloat: {2}\\nbool:  {3}'.format(...)`` under Python 2.7, so a value
reads as Python 2's ``str()`` shows it (:func:`py2_str`). A parameter that is not set reads
``<not set>`` (the original's service failed instead)."""
import json
import math

import rce.node

NAMES = ("int", "str", "float", "bool")
TEMPLATE = "int:   {0}\nstr:   {1}\nfloat: {2}\nbool:  {3}"   # the original's, character for character
NOT_SET = "<not set>"


def py2_str(value) -> str:
    """``value`` as Python 2.7's ``'{0}'.format(value)`` writes it: floats with 12 significant
    digits (``repr`` of 2.7 ``float.__str__``, ``.0`` added to whole numbers), ``True``/``False``;
    lists and objects as JSON (the original's test never set one)."""
    if value is None:
        return NOT_SET
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, float):
        text = f"{value:.12g}"
        if math.isfinite(value) and not any(c in text for c in ".e"):
            text += ".0"
        return text
    if isinstance(value, (int, str)):
        return str(value)
    return json.dumps(value)


async def main(node: rce.node.Node) -> None:
    async def handle(_req):
        values = [py2_str(await node.get_param(name, None)) for name in NAMES]
        return {"msg": TEMPLATE.format(*values)}
    await node.service("parameterTest", "Test/ParameterTest", handle)
    await node.spin()


if __name__ == "__main__":
    rce.node.run(main, "paramTest")
