#!/usr/bin/env python3
"""benchcostmap/costmap.py: the CPU-heavy node with a deadline of bench/placement.py.

    costmap.py [--scan /scan] [--out /costmap_done] [--cells 160] [--passes 6] [--samples 80] [--queue 4]

Subscribes to SCAN (``sensor_msgs/LaserScan``) and, for each scan, builds a local costmap as a
navigation stack's obstacle layer does, in numpy: every finite return is marked on a ``CELLS`` x
``CELLS`` grid (5 cm cells) and the space along its beam is cleared (each beam sampled at every of
``SAMPLES`` points, a block of beams at a time), then the obstacles are inflated by ``PASSES``
passes of a 3 x 3 max filter with a cost decay. The work grows with the number of finite returns (a
cluttered scene costs more than an empty one) and with ``PASSES``. Each result is published on OUT
as a ``geometry_msgs/PointStamped`` whose header is the scan's (its ``seq`` and ``stamp``, so the
sender matches results to scans and measures the latency end to end; its ``frame_id`` is
``copy=ID;dropped=N``: a random ID of this process, which tells the copies of a moved container
apart, and the scans its subscriber's queue of ``QUEUE`` dropped so far, oldest first); its
point holds the lethal cells (x), the inflated cells (y) and the CPU ms the scan took (z)."""
import argparse
import secrets
import time

import numpy as np

import rce.node


COPY = secrets.token_hex(4)    # this process: a move's old and new copies answer with different IDs
BLOCK = 1 << 16    # beam samples cleared at once: each temporary stays under ~1 MB and is reused by the
                   # allocator (every beam at once allocated ~100 MB of fresh pages a cluttered scan, whose
                   # page faults made its time on a capped robot computer swing 3x from one scan to the next)


def costmap(ranges: np.ndarray, angle_min: float, angle_inc: float, cells: int, passes: int,
            samples: int = 80) -> np.ndarray:
    """The inflated costmap (``cells`` x ``cells`` uint8, 254 lethal) of one scan's ``ranges`` (m),
    each beam cleared at ``samples`` points, :data:`BLOCK` beam samples at a time."""
    res = 0.05
    half = cells // 2
    grid = np.zeros((cells, cells), np.uint8)
    ok = np.isfinite(ranges)
    r = ranges[ok]
    a = angle_min + angle_inc * np.nonzero(ok)[0]
    dx = (r * np.cos(a) / res).astype(np.float32)                          # a beam's end, in cells
    dy = (r * np.sin(a) / res).astype(np.float32)
    t = np.linspace(0.0, 1.0, max(1, samples), endpoint=False, dtype=np.float32)[None, :]
    free = np.zeros((cells, cells), bool)
    block = max(1, BLOCK // max(1, samples))                                # beams at once
    for b in range(0, len(r), block):                                       # every beam, cleared
        xs = (half + dx[b:b + block, None] * t).astype(np.int32)
        ys = (half + dy[b:b + block, None] * t).astype(np.int32)
        inside = (xs >= 0) & (xs < cells) & (ys >= 0) & (ys < cells)
        free[ys[inside], xs[inside]] = True
    ex = (half + dx).astype(np.int32)                                       # its end, marked
    ey = (half + dy).astype(np.int32)
    hit = (ex >= 0) & (ex < cells) & (ey >= 0) & (ey < cells)
    grid[ey[hit], ex[hit]] = 254
    cost = grid.astype(np.int32)
    for _ in range(passes):                                                 # inflation, decaying
        p = np.pad(cost, 1)
        nb = np.maximum.reduce([p[i:i + cells, j:j + cells] for i in range(3) for j in range(3)])
        cost = np.maximum(cost, (nb * 0.8).astype(np.int32))
    cost[free & (grid == 0)] = np.minimum(cost[free & (grid == 0)], 0)
    return cost.astype(np.uint8)


async def main(node: rce.node.Node) -> None:
    p = argparse.ArgumentParser(prog="costmap.py")
    p.add_argument("--scan", default="/scan")
    p.add_argument("--out", default="/costmap_done")
    p.add_argument("--cells", type=int, default=160)
    p.add_argument("--passes", type=int, default=6)
    p.add_argument("--samples", type=int, default=80)
    p.add_argument("--queue", type=int, default=4)
    a = p.parse_args(rce.node.node_argv())
    pub = await node.publisher(a.out, "geometry_msgs/PointStamped", queue_size=100)

    sub = None

    def on_scan(m) -> None:
        t0 = time.process_time()
        ranges = np.asarray(m.ranges, dtype=np.float32)
        c = costmap(ranges, float(m.angle_min), float(m.angle_increment), a.cells, a.passes, a.samples)
        ms = (time.process_time() - t0) * 1e3
        pub.publish_nowait({"header": {"seq": m.header.seq, "stamp": {"sec": m.header.stamp.sec,
                                                                      "nanosec": m.header.stamp.nanosec},
                                       "frame_id": f"copy={COPY};dropped={sub.dropped if sub else 0}"},
                            "point": {"x": float((c == 254).sum()), "y": float((c > 0).sum()), "z": ms}})
    sub = await node.subscriber(a.scan, "sensor_msgs/LaserScan", on_scan, queue_size=a.queue)
    await node.spin()


if __name__ == "__main__":
    rce.node.run(main, "benchcostmap")
