"""A robot in a network namespace for tests (docs/testing.md): ``rce-ros`` run in a namespace a
:class:`~rce.tools.netlab.NetLab` made, with the lines it prints; the test reaches the robot's local bus
through its Unix socket (shared across network namespaces)."""
from __future__ import annotations

import asyncio
import json
import sys
from pathlib import Path

from rce.tools.netlab import NetLab

WAIT = 60.0                  # s any one step may take on a loaded machine before the test fails


class RosRun:
    """An rce-ros process in a namespace, with the lines it printed."""

    def __init__(self, proc: asyncio.subprocess.Process, bus: Path):
        self.proc, self.bus = proc, bus
        self.lines: list[str] = []
        self._new = asyncio.Event()
        self._readers = [asyncio.ensure_future(self._read(s)) for s in (proc.stdout, proc.stderr)]

    @classmethod
    async def start(cls, lab: NetLab, ns: str, cfg: dict, tmp: Path, *args: str) -> "RosRun":
        """``rce-ros CONFIG --bus TMP/ROBOT.sock ARGS`` in namespace ``ns`` of ``lab`` (``cfg`` written to
        ``TMP/ROBOT.config``)."""
        path = tmp / f"{cfg['robotID']}.config"
        path.write_text(json.dumps(cfg))
        bus = tmp / f"{cfg['robotID']}.sock"
        argv = lab.wrap(ns, [sys.executable, "-m", "rce_client.rce_ros", str(path), "--bus", str(bus), *args])
        proc = await asyncio.create_subprocess_exec(*argv, stdout=asyncio.subprocess.PIPE,
                                                    stderr=asyncio.subprocess.PIPE)
        return cls(proc, bus)

    async def _read(self, stream: asyncio.StreamReader) -> None:
        while line := await stream.readline():
            self.lines.append(line.decode(errors="replace").rstrip())
            self._new.set()

    async def wait_line(self, text: str, after: int = 0) -> str:
        """The first line from index ``after`` on that contains ``text``."""
        async with asyncio.timeout(WAIT):
            while True:
                for line in self.lines[after:]:
                    if text in line:
                        return line
                assert self.proc.returncode is None, "\n".join(self.lines[-40:])
                self._new.clear()
                await self._new.wait()

    async def stop(self) -> None:
        if self.proc.returncode is None:
            self.proc.terminate()
            try:
                await asyncio.wait_for(self.proc.wait(), 15)
            except asyncio.TimeoutError:
                self.proc.kill()
                await self.proc.wait()
        await asyncio.gather(*self._readers, return_exceptions=True)


def echo_config(url: str, robot: str, camera: bool = False) -> dict:
    """An rce-ros config for ``robot`` (user testUser): container ``c<robot>`` runs the Test
    package's ``stringEcho.py``; the robot's ``/req`` goes to it and its answer comes back on
    ``/resp`` (converters), and with ``camera`` the robot's ``/camera`` (sensor_msgs/Image) is
    forwarded to the container's ``/camera``."""
    c = f"c{robot}"
    cloud = [("req", "PublisherInterface", "std_msgs/String", "/stringEchoReq"),
             ("resp", "SubscriberInterface", "std_msgs/String", "/stringEchoResp")]
    local = [("req", "SubscriberConverter", "std_msgs/String", "/req"),
             ("resp", "PublisherConverter", "std_msgs/String", "/resp")]
    if camera:
        cloud.append(("cam", "PublisherInterface", "sensor_msgs/Image", "/camera"))
        local.append(("cam", "SubscriberForwarder", "sensor_msgs/Image", "/camera"))
    return {"url": url, "userID": "testUser", "password": "testUser", "robotID": robot,
            "containers": [{"cTag": c}],
            "nodes": [{"cTag": c, "nTag": "echo", "pkg": "Test", "exe": "stringEcho.py"}],
            "interfaces": [{"eTag": e, "iTag": t, "iType": k, "iCls": cls, "addr": a}
                           for e, side in ((c, cloud), (robot, local)) for t, k, cls, a in side],
            "connections": [{"tagA": f"{c}/{t}", "tagB": f"{robot}/{t}"} for t, *_ in cloud]}
