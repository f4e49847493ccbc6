#!/usr/bin/env python3
"""benchecho/echo.py: the server node of bench/paper_experiments.py.

    echo.py --type sensor_msgs/LaserScan [--back] [--suffix _echo] [--report 0.2] TOPIC...

Subscribes to every TOPIC (messages are deserialized, as a subscriber always does). With
``--back`` it publishes each message again on ``TOPIC + suffix`` (echo back to the sender);
without, it only counts, like ``rostopic echo`` with its printing left out. Every ``--report``
seconds it prints one JSON line ``{"counts": {topic: n}, "dropped": {topic: n}}`` (cumulative)."""
import argparse
import asyncio
import json
import time

import rce.node


async def main(node: rce.node.Node) -> None:
    p = argparse.ArgumentParser(prog="echo.py")
    p.add_argument("--type", required=True)
    p.add_argument("--back", action="store_true")
    p.add_argument("--suffix", default="_echo")
    p.add_argument("--report", type=float, default=0.2)
    p.add_argument("--queue", type=int, default=100)
    p.add_argument("topics", nargs="+")
    a = p.parse_args(rce.node.node_argv())
    subs = {}
    for t in a.topics:
        pub = await node.publisher(t + a.suffix, a.type, queue_size=a.queue) if a.back else None
        subs[t] = await node.subscriber(t, a.type, pub.publish_nowait if pub else (lambda m: None), queue_size=a.queue)
    while not node.is_shutdown:
        print(json.dumps({"t": time.time(), "counts": {t: s.received for t, s in subs.items()},
                          "dropped": {t: s.dropped for t, s in subs.items()}}), flush=True)
        await asyncio.sleep(a.report)


if __name__ == "__main__":
    rce.node.run(main, "benchecho")
