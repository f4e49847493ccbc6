#!/usr/bin/env python3
"""Test/paramTest.py: serves ``parameterTest`` (Test/ParameterTest: empty request, response
``string msg``) listing the container parameters ``int``, ``str``, ``float`` and ``bool``,
one per line as ``int:   99``, as the original engine's test package did."""
import json

import rce.node

NAMES = ("int", "str", "float", "bool")


async def main(node: rce.node.Node) -> None:
    async def handle(_req):
        lines = []
        for name in NAMES:
            value = await node.get_param(name, None)
            shown = "<not set>" if value is None else (value if isinstance(value, str) else json.dumps(value))
            lines.append(f"{name}:   {shown}")
        return {"msg": "\n".join(lines)}
    await node.service("parameterTest", "Test/ParameterTest", handle)
    await node.spin()


if __name__ == "__main__":
    rce.node.run(main, "paramTest")
