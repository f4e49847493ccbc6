"""A link with a delay line in its middle (NetLab.link(delay=True), rce.tools.delayline), in network
namespaces the test makes (root; deleted after, also on failure): a UDP echo in namespace R answered
across it takes twice the set delay more than without it, the delay changes while the link carries
traffic, a TCP stream of segmentation-offload frames crosses intact (checksums and offload state
cross with each frame), a bad request is refused by name, and nothing of the lab is left after."""
from __future__ import annotations

import hashlib
import os
import socket
import subprocess
import sys
import time

import pytest

from rce.tools.netlab import NetLab

WAIT = 30.0     # s any one step may take on a loaded machine

ECHO = r"""
import socket, sys
u = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); u.bind(("0.0.0.0", 0))
t = socket.socket(); t.bind(("0.0.0.0", 0)); t.listen(1)
print(u.getsockname()[1], t.getsockname()[1], flush=True)
import threading, hashlib
def tcp():
    c, _ = t.accept(); h = hashlib.sha256(); n = 0
    while (b := c.recv(1 << 20)):
        h.update(b); n += len(b)
    c.sendall(f"{n} {h.hexdigest()}".encode()); c.close()
threading.Thread(target=tcp, daemon=True).start()
while True:
    b, a = u.recvfrom(2048); u.sendto(b, a)
"""


def rtts_ms(addr: tuple[str, int], n: int = 10) -> list[float]:
    """``n`` UDP round trips to the echo at ``addr`` (ms), sorted."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as u:
        u.settimeout(WAIT)
        out = []
        for i in range(n):
            t0 = time.monotonic()
            u.sendto(i.to_bytes(4, "big") * 25, addr)
            while u.recv(2048) != i.to_bytes(4, "big") * 25:
                pass
            out.append((time.monotonic() - t0) * 1e3)
    return sorted(out)


def test_a_delay_line_adds_its_delay_each_way_and_carries_a_stream_intact():
    with NetLab("dln") as lab:
        lab.namespace("r")
        link = lab.link(None, "r", 1, delay=True)
        echo = subprocess.Popen(lab.wrap("r", [sys.executable, "-c", ECHO]), stdout=subprocess.PIPE, text=True)
        try:
            udp, tcp = (int(x) for x in echo.stdout.readline().split())
            base = rtts_ms((link.b_ip, udp))
            assert lab.set_delay(link, 40)["delay_ms"] == 40
            delayed = rtts_ms((link.b_ip, udp))
            assert delayed[0] >= 80.0, delayed                 # 40 ms each way, never less
            assert delayed[len(delayed) // 2] < 80.0 + base[len(base) // 2] + 40.0, (delayed, base)

            data = os.urandom(4 << 20)
            with socket.create_connection((link.b_ip, tcp), timeout=WAIT) as c:
                for k in range(0, len(data), 1 << 20):
                    c.sendall(data[k:k + (1 << 20)])
                    if k == 1 << 21:
                        lab.set_delay(link, 0)                 # mid-stream: frames held keep their order
                c.shutdown(socket.SHUT_WR)
                reply = c.recv(200).decode().split()
            assert reply == [str(len(data)), hashlib.sha256(data).hexdigest()]
            assert rtts_ms((link.b_ip, udp))[0] < 40.0

            stats = lab.delay_stats(link)
            assert stats["forwarded"] > 0 and stats["dropped"] == 0 and stats["held"] == 0, stats
            with pytest.raises(RuntimeError, match="must be >= 0"):
                lab.set_delay(link, -5)
            plain = lab.link(None, "r", 2)
            with pytest.raises(ValueError, match="no delay line"):
                lab.set_delay(plain, 5)
            line = lab._delay_lines[0]
        finally:
            echo.kill()
            echo.wait()
        mid = lab.full("dl1")
    assert line.poll() is not None                              # the delay line ended with the lab
    assert mid not in subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert not os.path.exists(link.control)
