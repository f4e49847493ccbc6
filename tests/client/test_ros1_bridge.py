"""``rce-ros CONFIG --ros`` against a real ROS 1 graph.

A real ``rosmaster --core`` on loopback (an ephemeral port), the real engine (``engine``
fixture), ``rce-ros --ros`` as a real process, and Debian's ``rostopic`` and a plain rospy
program (run by the system's python3, with a genpy-generated ``Test/StringEcho``, as a robot's
catkin workspace would have it) as the robot's ROS 1 side. The container runs the Test package's
``stringEcho.py`` twice: in namespace ``/fwd`` (reached through forwarders) and ``/conv`` (through
converters). Synchronisation polls the master's ``getSystemState`` and waits for printed lines and
exits, each with a deadline; no sleeps.

The unit tests below need no master: the ROS 1 identities (type, MD5 sum) agree with rospy's own
classes, the raw classes carry bytes untouched, and the thread-to-loop handoff is bounded."""
from __future__ import annotations

import asyncio
import io
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import xmlrpc.client
from pathlib import Path

import pytest

from rce.plumbing.errors import ConfigError
from rce.messages import MessageRegistry, default_registry
from rce.node.package_path import load_package_types
from rce.messages.debian_ros1 import forget_ros1, import_rospy
from rce_client.ros1_bridge import Counts, Handoff
from rce.messages.ros1_types import (DEFINITION_SEPARATOR, message_identity, raw_message_class, raw_service_class,
                                   service_identity)

from .test_e2e_debug import BIN, Proc, tool

MASTER_START = 30.0          # s for rosmaster to answer
STEP = 60.0                  # s for one step of the end-to-end test (a loaded 2-core machine)
SYSTEM_PYTHON = "/usr/bin/python3"
ROBOT = "rosRobot"
CTAG = "cRos"

# The rospy program of the robot's ROS 1 side. It uses nothing of rce: Test/StringEcho is generated
# by genpy from its definition, and its MD5 is md5("string data" + "string data"), as catkin makes it.
ROS1_PROGRAM = r'''
import io, sys, hashlib
import rospy, genpy.dynamic
from std_msgs.msg import String

gen = {t: genpy.dynamic.generate_dynamic(t, "string data\n")[t]
       for t in ("Test/StringEchoRequest", "Test/StringEchoResponse")}
StringEcho = type("StringEcho", (), {"_type": "Test/StringEcho",
                                     "_md5sum": hashlib.md5(b"string datastring data").hexdigest(),
                                     "_request_class": gen["Test/StringEchoRequest"],
                                     "_response_class": gen["Test/StringEchoResponse"]})
rospy.init_node("robot_program", anonymous=True, disable_signals=True)

# a service on the robot that the cloud calls
rospy.Service("/robot_echo", StringEcho, lambda req: gen["Test/StringEchoResponse"](data=req.data + "!"))

# bad input: bytes with String's type and MD5 that do not deserialize (length 255, 2 bytes follow)
class Bad(rospy.AnyMsg):
    _type, _md5sum = String._type, String._md5sum
bad = Bad(); bad._buff = b"\xff\x00\x00\x00ab"
pub = rospy.Publisher("/conv_req", Bad, queue_size=10)
while pub.get_num_connections() == 0 and not rospy.is_shutdown():
    rospy.rostime.wallsleep(0.05)          # rospy's own idiom: wait for the bridge to connect
pub.publish(bad)
print("published bad", flush=True)

for name in sys.argv[1:]:
    rospy.wait_for_service(name, timeout=60)
    print(f"{name}: {rospy.ServiceProxy(name, StringEcho)(data='hello ' + name).data}", flush=True)
print("serving", flush=True)
sys.stdin.read()                           # until the test closes stdin
pub.unregister()
rospy.signal_shutdown("done")
'''


def _config(master_url: str) -> dict:
    robot = [("fwdReq", "SubscriberForwarder", "std_msgs/String", "/fwd_req", "/fwd/stringEchoReq"),
             ("fwdResp", "PublisherForwarder", "std_msgs/String", "/fwd_resp", "/fwd/stringEchoResp"),
             ("convReq", "SubscriberConverter", "std_msgs/String", "/conv_req", "/conv/stringEchoReq"),
             ("convResp", "PublisherConverter", "std_msgs/String", "/conv_resp", "/conv/stringEchoResp"),
             ("echoSvc", "ServiceProviderConverter", "Test/StringEcho", "/echo_service", "/fwd/stringEchoService"),
             ("echoSvcRaw", "ServiceProviderForwarder", "Test/StringEcho", "/echo_service_raw",
              "/conv/stringEchoService"),
             ("robotSvc", "ServiceClientConverter", "Test/StringEcho", "/robot_echo", "/robot_echo"),
             # the bridge's own /fwd_resp messages must not come back to it (into the container's /tap)
             ("respTap", "SubscriberForwarder", "std_msgs/String", "/fwd_resp", "/tap")]
    container_side = {"Subscriber": "PublisherInterface", "Publisher": "SubscriberInterface",
                      "ServiceProvider": "ServiceClientInterface", "ServiceClient": "ServiceProviderInterface"}
    itfs, links = [], []
    for tag, kind, cls, addr, c_addr in robot:
        prefix = kind.removesuffix("Converter").removesuffix("Forwarder")
        itfs.append({"eTag": ROBOT, "iTag": tag, "iType": kind, "iCls": cls, "addr": addr})
        itfs.append({"eTag": CTAG, "iTag": tag, "iType": container_side[prefix], "iCls": cls, "addr": c_addr})
        links.append({"tagA": f"{CTAG}/{tag}", "tagB": f"{ROBOT}/{tag}"})
    return {"url": master_url, "userID": "testUser", "password": "testUser", "robotID": ROBOT,
            "containers": [{"cTag": CTAG}],
            "nodes": [{"cTag": CTAG, "nTag": f"echo_{ns}", "pkg": "Test", "exe": "stringEcho.py", "namespace": f"/{ns}"}
                      for ns in ("fwd", "conv")],
            "interfaces": itfs, "connections": links}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def _until(cond, what: str, timeout: float = STEP) -> None:
    """Poll ``cond()`` (blocking, run in a thread) until true; fail naming ``what`` after ``timeout`` s."""
    deadline = asyncio.get_running_loop().time() + timeout
    while not await asyncio.to_thread(cond):
        assert asyncio.get_running_loop().time() < deadline, f"{what}: not within {timeout} s"
        await asyncio.sleep(0.1)          # poll interval, not synchronisation


class RosMaster:
    """A real ``rosmaster --core`` on 127.0.0.1 and the environment to reach it."""

    def __init__(self, home: Path):
        port = _free_port()
        self.uri = f"http://127.0.0.1:{port}/"
        home.mkdir(parents=True, exist_ok=True)
        self.env = dict(os.environ, ROS_MASTER_URI=self.uri, ROS_IP="127.0.0.1", ROS_HOME=str(home),
                        ROS_LOG_DIR=str(home / "log"))
        self.proc = subprocess.Popen(["rosmaster", "--core", "-p", str(port)], env=self.env,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def state(self) -> tuple[dict, dict, dict]:
        """(publishers, subscribers, services): name -> list of node names (the master's getSystemState)."""
        code, msg, (pubs, subs, srvs) = xmlrpc.client.ServerProxy(self.uri).getSystemState("/test")
        assert code == 1, msg
        return dict(pubs), dict(subs), dict(srvs)

    def answers(self) -> bool:
        """True once this rosmaster answers on its port (its getPid is this process's: a port found
        free may be taken by another test's server before rosmaster binds it, and then rosmaster
        exits while the other answers)."""
        if self.proc.poll() is not None:
            raise AssertionError(f"rosmaster exited with {self.proc.returncode}")
        try:
            code, _, pid = xmlrpc.client.ServerProxy(self.uri).getPid("/test")
            return code == 1 and pid == self.proc.pid
        except OSError:
            return False

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


@pytest.fixture
async def ros_master(tmp_path):
    m = RosMaster(tmp_path / "ros_home")
    try:
        await _until(m.answers, "rosmaster answers", MASTER_START)
        yield m
    finally:
        m.stop()


async def _echo_through(master: RosMaster, req: str, resp: str, text: str) -> None:
    """``rostopic pub -r`` on ``req`` comes back through the cloud's echo node to ``rostopic echo -n 1 resp``."""
    echo = await Proc.start("rostopic", "echo", "-n", "1", resp, env=master.env)
    pub = None
    try:
        await _until(lambda: any(n.startswith("/rostopic") for n in master.state()[1].get(resp, [])),
                     f"rostopic echo subscribed to {resp}")
        pub = await Proc.start("rostopic", "pub", "-r", "10", req, "std_msgs/String", f"data: '{text}'",
                               env=master.env)
        assert await echo.wait(STEP) == 0, echo.dump()
        assert echo.text() == f'data: "{text}"\n---\n', echo.dump()
    finally:
        await echo.kill()
        if pub is not None:
            await pub.kill()


async def test_ros1_graph_through_the_cloud(engine, ros_master, tmp_path):
    cfg = tmp_path / "ros.config"
    cfg.write_text(json.dumps(_config(engine.master_url)))
    env = dict(ros_master.env, RCE_LOG_JSON="1")
    ros = await Proc.start(str(BIN / "rce-ros"), str(cfg), "--ros", "--timeout", "90", env=env)
    prog = None
    try:
        await ros.wait_line(r"^rce-ros: ROS 1 node /rce_ros_\S+ on the master at " + ros_master.uri)
        await ros.wait_line(r"^rce-ros: ready \(8 interface\(s\) up", timeout=120)
        assert "export RCE_BUS" not in ros.text()

        # topics: a forwarder pair and a converter pair, each through a stringEcho.py in the container
        await _echo_through(ros_master, "/fwd_req", "/fwd_resp", "via forwarder")
        await _echo_through(ros_master, "/conv_req", "/conv_resp", "via converter")

        # a plain rospy program: bad bytes on /conv_req, then calls through the cloud's stringEchoService
        # (converter and forwarder), and a service the cloud calls (ServiceClientConverter)
        prog = Proc(await asyncio.create_subprocess_exec(
            SYSTEM_PYTHON, "-c", ROS1_PROGRAM, "/echo_service", "/echo_service_raw", env=ros_master.env,
            stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE),
            "robot_program")
        await prog.wait_line(r"^serving$", timeout=STEP)
        assert prog.lines["out"] == ["published bad", "/echo_service: hello /echo_service",
                                     "/echo_service_raw: hello /echo_service_raw", "serving"], prog.dump()
        rc, out, err = await tool("rce-service", "call", "robot_echo", "{data: from the cloud}", "--container", CTAG,
                                  "--master", engine.master_url, "--user", "testUser",
                                  env=dict(os.environ, RCE_ADMIN_TOKEN=engine.admin_token), timeout=STEP)
        assert (rc, out) == (0, "data: from the cloud!\n"), err

        # the bad message was counted, and the converter kept working after it
        await _echo_through(ros_master, "/conv_req", "/conv_resp", "still converting")

        ros.p.send_signal(signal.SIGINT)
        assert await ros.wait(STEP) == 0, ros.dump()
        text = ros.text()
        assert "rce-ros: convReq: 1 message(s) not sent to the cloud (1 refused)" in text, ros.dump()
        bad = [json.loads(line) for line in ros.lines["err"] if "message not sent to the cloud" in line]
        assert [(b["itag"], b["reason"]) for b in bad] == [
            ("convReq", "6 bytes do not deserialize as std_msgs/String: Invalid string length 255 at offset 0.")]
        assert "rce-ros: ROS 1 echoSvc: 1 from ROS 1, 0 to ROS 1, 0 dropped, 0 failed" in text, ros.dump()
        assert "rce-ros: ROS 1 robotSvc: 1 from ROS 1, 1 to ROS 1, 0 dropped, 0 failed" in text, ros.dump()
        assert "rce-ros: ROS 1 respTap: 0 from ROS 1, 0 to ROS 1, 0 dropped, 0 failed" in text, ros.dump()
        assert "rce-ros: removed 8 interface(s), destroyed 1 container(s)" in text, ros.dump()
        # rce-ros unregistered its topics and services from the ROS 1 master
        pubs, subs, srvs = await asyncio.to_thread(ros_master.state)
        assert not [n for names in (*pubs.values(), *subs.values(), *srvs.values()) for n in names
                    if n.startswith("/rce_ros")], (pubs, subs, srvs)
    finally:
        await ros.kill()
        if prog is not None:
            prog.p.stdin.close()
            await prog.kill()


@pytest.mark.parametrize("master, code, error", [
    (None, 2, "rce-ros: --ros: ROS_MASTER_URI is not set"),
    ("closed", 1, "rce-ros: --ros: the ROS 1 master at http://127.0.0.1:{port}/ does not answer: "),
])
async def test_ros_master_missing_is_refused_before_login(tmp_path, master, code, error):
    """No master named, or none answering: refused before anything is sent to the cloud (whose
    URL here is a closed port too: a login attempt would say so instead)."""
    port = _free_port()                  # closed: nothing listens there
    cfg = tmp_path / "ros.config"
    cfg.write_text(json.dumps(_config(f"http://127.0.0.1:{port}/")))
    env = {k: v for k, v in os.environ.items() if k != "ROS_MASTER_URI"}
    if master:
        env.update(ROS_MASTER_URI=f"http://127.0.0.1:{port}/", ROS_HOME=str(tmp_path))
    p = await Proc.start(str(BIN / "rce-ros"), str(cfg), "--ros", env=env)
    assert await p.wait(STEP) == code, p.dump()
    assert error.format(port=port) in p.human_err() and "logging in" not in p.text(), p.dump()


# -- without a master -----------------------------------------------------------------------------
@pytest.fixture(autouse=True)
def ros1_modules_go_after():
    """A test that imports rospy in this process leaves the message packages' names to ROS 2 again
    (the worker goes on with other tests; rce.messages.debian_ros1)."""
    yield
    forget_ros1()


@pytest.fixture(scope="module")
def registry() -> MessageRegistry:
    reg = default_registry()
    load_package_types(reg)
    return reg


def test_identities_agree_with_rospy_classes(registry):
    import_rospy()
    import roscpp.msg
    import roscpp.srv
    from sensor_msgs.msg import Image
    from std_msgs.msg import String
    for cls, ros in (("std_msgs/String", String), ("/sensor_msgs/msg/Image", Image)):
        ident = message_identity(cls, registry)
        assert (ident.type, ident.md5sum, ident.full_text) == (ros._type, ros._md5sum, ros._full_text)
    # a service rce only knows from its definition (as a node package would bring it) has catkin's MD5
    reg = MessageRegistry()
    reg.register_msg("roscpp/Logger", roscpp.msg.Logger._full_text)
    resp = roscpp.srv.GetLoggersResponse._full_text.split(DEFINITION_SEPARATOR)[0]
    reg.register_srv("roscpp/GetLoggers", roscpp.srv.GetLoggersRequest._full_text + "---\n" + resp)
    ident = service_identity("roscpp/GetLoggers", reg)
    assert (ident.type, ident.md5sum) == ("roscpp/GetLoggers", roscpp.srv.GetLoggers._md5sum)
    # and one no rospy class exists for: the Test package's, md5 of both parts' MD5 texts
    ident = service_identity("Test/StringEcho", registry)
    assert ident.md5sum == "a9e4701c829f791367680c5f8ed06ff4" and ident.request.type == "Test/StringEchoRequest"


def test_disagreeing_or_unknown_classes_are_refused(monkeypatch):
    import_rospy()
    import roslib.message
    from std_msgs.msg import Int32
    reg = MessageRegistry()
    reg.register_msg("rce_bridge_unit/Thing", "string data\n")
    # the robot's workspace has another rce_bridge_unit/Thing (an int32 where rce has a string)
    monkeypatch.setattr(roslib.message, "get_message_class",
                        lambda name: Int32 if name == "rce_bridge_unit/Thing" else None)
    with pytest.raises(ConfigError, match=f"rce_bridge_unit/Thing: the ROS 1 class has MD5 {Int32._md5sum} but"):
        message_identity("rce_bridge_unit/Thing", reg)
    with pytest.raises(ConfigError, match="message class nopkg/Nothing: no rospy class and"):
        message_identity("nopkg/Nothing", reg)
    with pytest.raises(ConfigError, match="service class nopkg/NoSrv: no rospy class and"):
        service_identity("nopkg/NoSrv", reg)


def test_raw_classes_carry_bytes_untouched(registry):
    import_rospy()
    from std_msgs.msg import String
    raw = raw_message_class(message_identity("std_msgs/String", registry))
    payload = b"\x03\x00\x00\x00\xff\xfe\x00"                  # not UTF-8: passed, not decoded
    out = io.BytesIO()
    raw.wrap(payload).serialize(out)
    assert out.getvalue() == payload and raw().deserialize(payload)._buff == payload
    assert (raw._type, raw._md5sum) == (String._type, String._md5sum)
    srv = raw_service_class(service_identity("Test/StringEcho", registry))
    assert srv._request_class._type == "Test/StringEchoRequest" and srv._md5sum == "a9e4701c829f791367680c5f8ed06ff4"


async def test_handoff_is_bounded_and_counts_drops():
    got: list[bytes] = []
    counts = Counts()
    handoff = Handoff(asyncio.get_running_loop(), got.append, counts, limit=3)
    offered = []
    t = threading.Thread(target=lambda: offered.extend(handoff.offer(bytes([i])) for i in range(5)))
    t.start()
    t.join()                                   # blocks the loop: it runs nothing meanwhile, 3 in flight, 2 dropped
    assert offered == [True, True, True, False, False]
    await asyncio.sleep(0)                     # one loop turn runs the scheduled handoffs
    assert got == [b"\x00", b"\x01", b"\x02"] and (counts.from_ros, counts.dropped) == (5, 2)
    assert handoff.offer(b"\x05") and handoff.in_flight == 1



def test_a_ros1_process_takes_ros1_message_packages_before_ros2s():
    """ROS 2's wheels put std_msgs and rosgraph_msgs in the venv: rospy (which needs ROS 1's) still works,
    and the process can go back to ROS 2's."""
    from std_msgs.msg import String as Ros2String
    assert hasattr(Ros2String, "get_fields_and_field_types")            # ROS 2's, from the venv
    import_rospy()
    from rosgraph_msgs.msg import Log              # what rospy imports; ROS 2's rosgraph_msgs has no Log
    from std_msgs.msg import String
    assert String._md5sum == "992ce8a1687cec8c8bd883ec73ca41d1" and Log._type == "rosgraph_msgs/Log"
    forget_ros1()
    from std_msgs.msg import String as Again
    assert hasattr(Again, "get_fields_and_field_types") and not hasattr(Again, "_md5sum")


async def test_a_rosmaster_whose_port_another_holds_is_not_taken_for_it(ros_master, tmp_path, monkeypatch):
    # the fixture's port handed out again as "free", as a test's server in another worker may take it first:
    # the second rosmaster cannot bind it, and the one answering there is the fixture's, never taken for it
    monkeypatch.setattr(sys.modules[__name__], "_free_port",
                        lambda: int(ros_master.uri.rsplit(":", 1)[1].rstrip("/")))
    other = RosMaster(tmp_path / "other")
    try:
        assert other.uri == ros_master.uri and ros_master.answers()
        assert xmlrpc.client.ServerProxy(other.uri).getPid("/test")[2] == ros_master.proc.pid
        assert not other.answers()
    finally:
        other.stop()
