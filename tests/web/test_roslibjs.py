"""Unmodified roslibjs (npm ``roslib`` 1.4, ``build/roslib.min.js``) in Debian's
chromium (Playwright) against the rosbridge v2 endpoint of a real engine, on the Test package's
stringEcho in a container an RCE robot owns. The page connects with the full URL
``ws://127.0.0.1:PORT/?userID=..&robotID=..&password=..&container=..`` and does what a web app
does: a publish/subscribe echo (plain, and with ``png`` and ``cbor`` compression, each on its own
connection so the message can only have come through that form), a service call, parameters
(set, get, list), topic listing; then it provides a service the container calls."""
from __future__ import annotations

import asyncio
import hashlib
import threading
from pathlib import Path

import pytest

from wsclient import RawRobot

ROSLIB = Path(__file__).resolve().parent / "roslibjs" / "node_modules" / "roslib" / "build" / "roslib.min.js"
OWNER_WAIT = 60.0       # s for the owning robot to create the container and start the echo node
PAGE_WAIT = 60.0        # s for the page's whole first phase (connect, echo, calls, params)
STEP_WAIT = 15.0        # s for one step: the page's service to reach the graph, the container's call of it
RETRY_EVERY = 300       # ms between two publishes while the echo node's subscription is starting
CTAG = "rbJsC"


class ContainerOwner:
    """An RCE robot (raw protocol, own thread and event loop) that creates container ``ctag`` with
    the Test package's stringEcho.py and keeps it while the test runs (the container goes with it)."""

    def __init__(self, eng, robot: str, ctag: str):
        self.eng, self.robot, self.ctag = eng, robot, ctag
        self.ready = threading.Event()
        self.error: BaseException | None = None
        self._loop = asyncio.new_event_loop()
        self._leave: asyncio.Event | None = None
        self._thread = threading.Thread(target=self._loop.run_until_complete, args=(self._run(),),
                                        name=f"owner-{robot}", daemon=True)

    async def _run(self) -> None:
        self._leave = asyncio.Event()
        try:
            async with RawRobot(self.eng.master_url, self.robot) as r:
                await r.send("CC", {"containerTag": self.ctag})
                await r.expect("ST", pred=lambda d: d.get("topic") == "container" and d.get("cTag") == self.ctag
                               and d.get("status") == "running")
                await r.cn(addNodes=[{"containerTag": self.ctag, "nodeTag": "echo", "pkg": "Test",
                                      "exe": "stringEcho.py"}])
                self.ready.set()
                await self._leave.wait()
        except BaseException as e:          # shown by the test that waits on ready
            self.error = e
            self.ready.set()

    def __enter__(self) -> "ContainerOwner":
        self._thread.start()
        if not self.ready.wait(OWNER_WAIT):
            raise TimeoutError(f"container {self.ctag!r} not up within {OWNER_WAIT} s")
        if self.error is not None:
            raise self.error
        return self

    def __exit__(self, *exc) -> None:
        self._loop.call_soon_threadsafe(self._leave.set)
        self._thread.join(STEP_WAIT)


@pytest.fixture(scope="module")
def eng(shared_engine):
    return shared_engine


def _url(eng, robot: str) -> str:
    port = eng.robot_ready[0]["rosbridge_port"]
    pw = hashlib.sha256(b"testUser").hexdigest()
    return f"ws://127.0.0.1:{port}/?userID=testUser&robotID={robot}&password={pw}&container={CTAG}"


# The page's first phase: everything a roslibjs user does, as one promise; each step fails with its name.
PHASE_ONE = """async ([urls, retryMs, waitMs]) => {
  const limit = new Promise((_, fail) => setTimeout(() => fail(new Error('over ' + waitMs + ' ms')), waitMs));
  const connect = (url) => new Promise((ok, fail) => {
    const ros = new ROSLIB.Ros({url});
    ros.on('connection', () => ok(ros));
    ros.on('error', (e) => fail(new Error('connect ' + url.split('?')[0] + ': ' + e)));
  });
  const call = (ros, name, type, req) => new Promise((ok, fail) =>
    new ROSLIB.Service({ros, name, serviceType: type}).callService(new ROSLIB.ServiceRequest(req), ok,
                                                                   (e) => fail(new Error(name + ': ' + e))));
  const echo = (ros, compression) => new Promise((ok) => {
    const sub = new ROSLIB.Topic({ros, name: '/stringEchoResp', messageType: 'std_msgs/String', compression});
    const pub = new ROSLIB.Topic({ros, name: '/stringEchoReq', messageType: 'std_msgs/String'});
    const timer = setInterval(() => pub.publish(new ROSLIB.Message({data: 'hello ' + compression})), retryMs);
    sub.subscribe((m) => {
      if (m.data === 'hello ' + compression) { clearInterval(timer); sub.unsubscribe(); ok(m); }
    });
  });
  const waitService = async (ros, name) => {
    for (;;) {
      const names = await new Promise((ok, fail) => ros.getServices(ok, fail));
      if (names.includes(name)) return names;
      await new Promise((ok) => setTimeout(ok, retryMs));
    }
  };
  const run = async () => {
  const [ros, rosPng, rosCbor] = await Promise.all(urls.map(connect));
  window.rbRos = ros;
  await waitService(ros, '/stringEchoService');
  const out = {};
  out.service = await call(ros, '/stringEchoService', 'Test/StringEcho', {data: 'svc'});
  [out.echo, out.png, out.cbor] = await Promise.all([echo(ros, 'none'), echo(rosPng, 'png'), echo(rosCbor, 'cbor')]);
  const speed = new ROSLIB.Param({ros, name: '/rbJs/speed'});
  await new Promise((ok, fail) => speed.set({max: 2.5, modes: ['a', 'b']}, ok, fail));
  out.param = await new Promise((ok, fail) => speed.get(ok, fail));
  out.leaf = await new Promise((ok, fail) => new ROSLIB.Param({ros, name: '/rbJs/speed/max'}).get(ok, fail));
  out.missing = await new Promise((ok, fail) => new ROSLIB.Param({ros, name: '/rbJs/none'}).get(ok, fail));
  out.params = await new Promise((ok, fail) => ros.getParams(ok, fail));
  out.topics = await new Promise((ok, fail) => ros.getTopics(ok, fail));
  out.serviceType = await new Promise((ok, fail) => ros.getServiceType('/stringEchoService', ok, fail));
  rosPng.close(); rosCbor.close();
  return out;
  };
  return await Promise.race([run(), limit]);
}"""

# The page provides /rbJsSvc (Test/StringEcho, upper-cases); resolves once the container's graph has it.
PROVIDE = """async ([retryMs, waitMs]) => {
  const limit = new Promise((_, fail) => setTimeout(() => fail(new Error('over ' + waitMs + ' ms')), waitMs));
  const ros = window.rbRos;
  window.rbServed = [];
  new ROSLIB.Service({ros, name: '/rbJsSvc', serviceType: 'Test/StringEcho'}).advertise((req, resp) => {
    window.rbServed.push(req.data);
    resp.data = req.data.toUpperCase();
    return true;
  });
  const onGraph = async () => {
    for (;;) {
      const names = await new Promise((ok, fail) => ros.getServices(ok, fail));
      if (names.includes('/rbJsSvc')) return names;
      await new Promise((ok) => setTimeout(ok, retryMs));
    }
  };
  return await Promise.race([onGraph(), limit]);
}"""


def test_roslibjs_echo_service_params_topics(eng, page):
    assert ROSLIB.is_file(), f"{ROSLIB} is missing: `make setup` installs roslib with npm"
    with ContainerOwner(eng, "rbJsOwner", CTAG):
        page.set_content("<!doctype html><title>roslibjs</title>")
        page.add_script_tag(path=str(ROSLIB))
        urls = [_url(eng, robot) for robot in ("rbJs", "rbJsPng", "rbJsCbor")]
        out = page.evaluate(PHASE_ONE, [urls, RETRY_EVERY, PAGE_WAIT * 1000])
        page.evaluate(PROVIDE, [RETRY_EVERY, STEP_WAIT * 1000])
        answer = eng.admin(f"/api/containers/testUser/{CTAG}/call",
                           {"service": "/rbJsSvc", "request": {"data": "shout"}, "timeout": STEP_WAIT})
        served = page.evaluate("window.rbServed")
    assert out["service"] == {"data": "svc"}
    assert out["echo"] == {"data": "hello none"}
    assert out["png"] == {"data": "hello png"}           # decoded by roslibjs from the PNG (canvas)
    assert out["cbor"] == {"data": "hello cbor"}         # decoded by roslibjs from the binary CBOR frame
    assert out["param"] == {"max": 2.5, "modes": ["a", "b"]} and out["leaf"] == 2.5 and out["missing"] is None
    assert {"/rbJs/speed/max", "/rbJs/speed/modes"} <= set(out["params"])
    assert {"/stringEchoReq", "/stringEchoResp"} <= set(out["topics"]["topics"])
    assert out["serviceType"] == "Test/StringEcho"
    assert answer == {"data": "SHOUT"} and served == ["shout"]
