#!/usr/bin/env python3
"""Test/stringEcho.py: echoes std_msgs/String from ``stringEchoReq`` to ``stringEchoResp``
and serves ``stringEchoService`` (Test/StringEcho: string in, same string out), as the
original RoboEarth Cloud Engine's test package did."""
import rce.node


async def main(node: rce.node.Node) -> None:
    pub = await node.publisher("stringEchoResp", "std_msgs/String", queue_size=100)
    await node.subscriber("stringEchoReq", "std_msgs/String", pub.publish_nowait, queue_size=100)
    await node.service("stringEchoService", "Test/StringEcho", lambda req: {"data": req.data})
    await node.spin()


if __name__ == "__main__":
    rce.node.run(main, "stringEcho")
