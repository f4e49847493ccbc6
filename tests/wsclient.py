"""A raw RCE protocol client for tests: speaks the wire format directly (as the RCE alpha
client did), so tests check the protocol itself rather than our client library."""
from __future__ import annotations

import asyncio
import hashlib
import json
import urllib.request

from websockets.asyncio.client import connect


def login(master_url: str, user: str = "testUser", version: str = "20130902") -> dict:
    with urllib.request.urlopen(f"{master_url}?userID={user}&version={version}", timeout=10) as r:
        return json.loads(r.read())


class RawRobot:
    """``async with RawRobot(url, robot) as r``: send dicts/bytes, receive parsed messages."""

    def __init__(self, master_url: str, robot: str, user: str = "testUser", password: str = "testUser",
                 query: str = ""):
        """``query``: more of the websocket URL's query (``&maxLag=0``)."""
        self.master_url, self.robot, self.user, self.password, self.query = master_url, robot, user, password, query
        self.ws = None

    async def __aenter__(self) -> "RawRobot":
        url = login(self.master_url, self.user)["url"]
        pw = hashlib.sha256(self.password.encode()).hexdigest()
        self.ws = await connect(f"{url}?userID={self.user}&robotID={self.robot}&password={pw}{self.query}",
                                max_size=None, compression=None)
        return self

    async def __aexit__(self, *exc) -> None:
        await self.ws.close()

    async def send(self, type_: str, data) -> None:
        await self.ws.send(json.dumps({"type": type_, "data": data}))

    async def recv(self, timeout: float = 20.0):
        """Next frame: a dict for JSON text, bytes for binary; TimeoutError after ``timeout`` s.
        (``asyncio.timeout``, not ``wait_for``: Python 3.11's ``wait_for`` loses a cancellation that
        arrives as the frame does, and a reading loop cancelled that way would read on.)"""
        async with asyncio.timeout(timeout):
            m = await self.ws.recv()
        return json.loads(m) if isinstance(m, str) else m

    async def expect(self, type_: str, timeout: float = 20.0, pred=lambda d: True) -> dict:
        """Skip frames until a message of ``type_`` whose data satisfies ``pred``; returns its data."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            m = await self.recv(max(0.01, deadline - loop.time()))
            if isinstance(m, dict) and m.get("type") == type_ and pred(m["data"]):
                return m["data"]

    async def errors_within(self, timeout: float) -> list:
        """The next frame within ``timeout`` s, as a list of the ER it is (empty: none came, or another)."""
        try:
            m = await self.recv(timeout)
        except TimeoutError:
            return []
        return [m["data"]] if isinstance(m, dict) and m.get("type") == "ER" else []

    async def probe(self) -> None:
        """Prove the session still answers: a DM to a missing interface must come back as ER."""
        await self.send("DM", {"iTag": "noSuchProbe", "type": "std_msgs/String", "msgID": "", "msg": {"data": ""}})
        await self.expect("ER", pred=lambda d: "noSuchProbe" in d)

    async def cn(self, **data) -> None:
        await self.send("CN", data)

    async def iface(self, etag, itag, itype, cls, addr=None) -> None:
        d = {"endpointTag": etag, "interfaceTag": itag, "interfaceType": itype, "className": cls}
        if addr:
            d["addr"] = addr
        await self.cn(addInterfaces=[d])

    async def wait_up(self, *itags: str, timeout: float = 30.0) -> None:
        left = set(itags)
        while left:
            d = await self.expect("ST", timeout, lambda d: d.get("topic") == "iu" and d.get("status") is True)
            left.discard(d["iTag"])
