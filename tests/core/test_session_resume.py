"""Session resume, sans I/O (rce/protocol/resume.py and both sessions; docs/INTERNALS.md "Session
resume"): what the shared vectors do not pin. The bounds of the kept buffer, tokens, the errors of
misuse, and a RobotSession and a ClientSession wired together over an in-memory link that drops
with frames in flight: every message arrives once and in order, both ways, calls survive."""
from __future__ import annotations

import asyncio
import json
import random

import pytest

from rce.plumbing.errors import ProtocolError
from rce.protocol.resume import TOKEN_BYTES, Incoming, Outgoing, ack_frame, new_token, read_ack, read_seq
from rce.protocol.events import Deliver, MessageReceived, ServiceCall, SessionStatus
from rce.protocol.session import ClientSession, ResumeOptions, RobotSession


def test_outgoing_bounds_messages_and_bytes_and_counts_what_it_forgets():
    out = Outgoing(max_messages=3, max_bytes=10)
    for _ in range(4):
        out.keep(out.number(), ["ab"])
    assert len(out) == 3 and out.forgotten == 1 and out.bytes == 6
    out.keep(out.number(), ["x" * 9])                     # over the bytes: the oldest go, the newest stays
    assert len(out) == 1 and out.forgotten == 4 and out.bytes == 9
    out.keep(out.number(), ["y" * 20])                    # one message larger than the bound is still kept
    assert len(out) == 1 and out.bytes == 20
    messages, lost = out.resend_after(2)
    assert messages == [["y" * 20]] and lost == 3          # 3, 4 and 5 were forgotten; the peer had 1 and 2


def test_outgoing_ack_and_resend_after():
    out = Outgoing()
    for i in range(5):
        out.keep(out.number(), [f"m{i + 1}"])
    out.ack(2)
    assert len(out) == 3 and out.acked == 2
    assert out.resend_after(1) == ([["m3"], ["m4"], ["m5"]], 0)      # an older ack than the last: nothing lost
    with pytest.raises(ProtocolError, match="seq 6 was never sent"):
        out.ack(6)
    out.clear()
    assert len(out) == 0 and out.bytes == 0


def test_incoming_duplicates_gaps_and_ack_schedule():
    inc = Incoming(ack_every=3, ack_delay=1.0)
    assert inc.take(1, 0.0) and not inc.take(1, 0.1) and inc.duplicates == 1
    assert inc.ack_due(0.5) is None and inc.ack_due(1.0) == 1 and inc.ack_due(5.0) is None
    assert inc.take(5, 2.0) and inc.gaps == 3 and inc.take(None, 2.0) and inc.last == 6
    assert inc.ack_due(2.0) is None
    assert inc.take(7, 2.0) and inc.ack_due(2.0) == 7       # three taken since the last AK


def test_frames_and_fields():
    assert json.loads(ack_frame(3)) == {"type": "AK", "data": {"seq": 3}}
    assert read_seq({"type": "DM"}) is None and read_seq({"seq": 4}) == 4
    for bad in (0, -1, "2", 1.5, True, None):
        with pytest.raises(ProtocolError, match="seq must be a positive integer"):
            read_seq({"seq": bad})
    assert read_ack({"seq": 0}) == 0
    for bad in ({"seq": -1}, {"seq": "1"}, {}, [], None, {"seq": False}):
        with pytest.raises(ProtocolError, match="AK.data.seq"):
            read_ack(bad)


def test_tokens_are_long_random_hex():
    tokens = {new_token() for _ in range(100)}
    assert len(tokens) == 100
    assert all(len(t) == 2 * TOKEN_BYTES and int(t, 16) >= 0 for t in tokens) and TOKEN_BYTES * 8 >= 128
    assert RobotSession("r1", resume=ResumeOptions()).token != RobotSession("r1", resume=ResumeOptions()).token
    assert RobotSession("r1").token is None


def test_misuse_is_refused():
    with pytest.raises(ProtocolError, match="did not opt in"):
        RobotSession("r1").detach()
    s = RobotSession("r1", resume=ResumeOptions())
    assert not s.can_resume(1) and s.can_resume(0) and not RobotSession("r1").can_resume(0)
    with pytest.raises(ProtocolError, match="ack 1 is not a message sent"):
        s.attach(1)
    c = ClientSession(resume=True)
    with pytest.raises(ProtocolError, match="not detached"):
        c.attach()
    assert c.resume_query() == {"session": "", "ack": "0"}


def test_a_resumed_session_reports_robot_messages_taken_and_buffer_losses():
    s = RobotSession("r1", resume=ResumeOptions(token="t" * 64, buffer=2))
    s.add_interface("req", "SubscriberConverter", "std_msgs/String")
    dm = {"iTag": "req", "type": "std_msgs/String", "msgID": "", "msg": {"data": "x"}}
    for seq in (1, 2, 3):
        s.receive_text(json.dumps({"type": "DM", "seq": seq, "data": dm}), 0)
    s.data_to_send()
    s.detach()
    for _ in range(5):                      # answers: every one is kept (and the bound forgets the oldest)
        s.send_dm("out", "std_msgs/String", "", {"data": "y"})
    s.attach(0)
    st = json.loads(s.data_to_send(1)[0])
    assert st["data"] == {"topic": "session", "status": "resumed", "session": "t" * 64, "grace": 30.0,
                          "ack": 3, "dropped": 3, "superseded": 0}
    assert [json.loads(f)["seq"] for f in s.data_to_send()] == [4, 5]
    assert s.stats()["resume_lost"] == 3 and s.stats()["resume_forgotten"] == 3


def test_a_link_down_longer_than_the_robots_buffer_loses_its_oldest_counted_on_both_sides():
    """No path for a while (a follower out of every relay's range): the robot's buffer keeps its newest
    3; the 2 it forgot are counted at the resume by the robot (``resume_lost``) and the cloud
    (``resume_gaps``, a Prometheus counter), and the rest arrive once, in order."""
    cloud = RobotSession("r1", resume=ResumeOptions(ack_every=1))
    cloud.add_interface("req", "SubscriberConverter", "std_msgs/String")
    robot = ClientSession(resume=True, resume_buffer=3)

    def move() -> None:
        for _ in range(4):
            for dst, frames in ((robot, cloud.data_to_send()), (cloud, robot.data_to_send())):
                for f in frames:
                    (dst.receive_text if isinstance(f, str) else dst.receive_binary)(f, 0.0)

    def dm(i: int) -> dict:
        return {"iTag": "req", "type": "std_msgs/String", "msgID": "", "msg": {"data": f"m{i}"}}
    move()
    assert robot.state == "live"
    robot.send("DM", dm(0))
    move()
    cloud.detach()
    assert robot.detach("code 1006")
    for i in range(1, 6):                   # 5 while no link is up; the robot keeps its newest 3
        robot.send("DM", dm(i))
    assert len(robot.outgoing) == 3 and robot.outgoing.forgotten >= 2
    q = robot.resume_query()
    robot.attach()
    cloud.attach(int(q["ack"]))
    move()
    got = [ev.data["msg"]["data"] for ev in cloud.events_received() if isinstance(ev, Deliver)]
    assert got == ["m0", "m3", "m4", "m5"]
    assert robot.resume_lost == 2 and cloud.stats()["resume_gaps"] == 2


# -- both sides over an in-memory link that drops with frames in flight --------------------------------
class Pair:
    """A cloud session (``RobotSession``, with an echo interface) and a robot session (``ClientSession``)
    joined by two in-memory directions; each frame is delivered or, when the link drops, lost."""

    def __init__(self, seed: int):
        self.rng = random.Random(seed)
        self.cloud = RobotSession("r1", resume=ResumeOptions(ack_every=4))
        self.cloud.add_interface("req", "SubscriberConverter", "std_msgs/String")
        self.cloud.add_interface("svc", "ServiceProviderConverter", "Test/StringEcho")
        self.cloud.add_interface("echo", "PublisherConverter", "std_msgs/String")     # control: all kept
        self.robot = ClientSession(resume=True, ack_every=4)
        self.got_by_cloud: list[str] = []
        self.got_by_robot: list[str] = []
        self.now = 0.0
        self.up = True

    def step(self) -> None:
        """Move every frame waiting on either side (some lost when the link drops meanwhile)."""
        self.now += 0.05
        self.cloud.tick(self.now)
        self.robot.tick(self.now)
        for _ in range(50):
            to_robot, to_cloud = self.cloud.data_to_send(), self.robot.data_to_send()
            if not (to_robot or to_cloud):
                break
            for side, f in [(self.cloud, f) for f in to_cloud] + [(self.robot, f) for f in to_robot]:
                if self.up and self.rng.random() < 0.005:      # the link drops: the frames in flight are lost
                    self.drop()
                if self.up:
                    (side.receive_text if isinstance(f, str) else side.receive_binary)(f, self.now)
            self.events()

    def events(self) -> None:
        for ev in self.cloud.events_received():
            match ev:
                case Deliver(data=data):
                    self.got_by_cloud.append(data["msg"]["data"])
                    self.cloud.send_dm("echo", "std_msgs/String", "", data["msg"], data=True)
                case ServiceCall(data=data):
                    self.cloud.answer_call(data, data["msg"])
        for ev in self.robot.events_received():
            if isinstance(ev, MessageReceived):
                self.got_by_robot.append(ev.msg["data"])

    def drop(self) -> None:
        """The link is lost: both sides detach; the next step resumes."""
        self.up = False
        self.cloud.detach()
        assert self.robot.detach("code 1006")
        self.events()

    def resume(self) -> None:
        q = self.robot.resume_query()
        assert q["session"] == self.cloud.token
        self.robot.attach()
        self.cloud.attach(int(q["ack"]))
        self.up = True


async def run_pair(seed: int) -> int:
    """300 messages each way and 6 calls over a link that drops (seeded); asserts exactly once, in order,
    with nothing lost; returns the resends and duplicates seen."""
    p = Pair(seed)
    p.step()
    assert p.robot.state == "live"
    calls = []
    for i in range(300):
        p.robot.send("DM", {"iTag": "req", "type": "std_msgs/String", "msgID": "", "msg": {"data": f"m{i}"}})
        if i % 50 == 0:
            calls.append(asyncio.ensure_future(p.robot.pending.wait(
                p.robot.call("svc", "Test/StringEcho", {"data": f"call{i}"}), 5)))
        if not p.up and p.rng.random() < 0.3:
            p.resume()
        p.step()
    while not p.up or p.robot.outbox or p.cloud.outbox:
        if not p.up:
            p.resume()
        p.step()
    sent = [f"m{i}" for i in range(300)]
    assert p.got_by_cloud == sent
    assert p.got_by_robot == sent
    assert [c["data"] for c in await asyncio.gather(*calls)] == [f"call{i}" for i in range(0, 300, 50)]
    stats = p.cloud.stats()
    assert stats["resumes"] >= 2 and stats["resume_lost"] == 0 and p.robot.outgoing.forgotten == 0
    return stats["resent"] + p.robot.incoming.duplicates + p.cloud.incoming.duplicates


@pytest.mark.asyncio
async def test_both_ways_exactly_once_in_order_across_drops():
    resends_and_duplicates = [await run_pair(seed) for seed in range(8)]
    assert sum(resends_and_duplicates) > 0, "drops in flight were resent and their duplicates dropped"


# -- while no path exists: state keeps its newest, control keeps everything ---------------------------
class Partition:
    """A cloud and a robot session with a 10 Hz state stream and a 1 Hz control stream each way:
    robot -> cloud ``pose`` (geometry_msgs: state) and ``cmd`` (std_msgs: control); cloud -> robot
    ``odom`` (nav_msgs/Odometry: state) and ``goal`` (std_msgs: control). Time moves in 0.1 s steps."""

    def __init__(self):
        self.cloud = RobotSession("r1", resume=ResumeOptions())
        for itag, itype, cls in (("pose", "SubscriberConverter", "geometry_msgs/PoseStamped"),
                                 ("cmd", "SubscriberConverter", "std_msgs/String"),
                                 ("odom", "PublisherConverter", "nav_msgs/Odometry"),
                                 ("goal", "PublisherConverter", "std_msgs/String")):
            self.cloud.add_interface(itag, itype, cls)
        self.robot = ClientSession(resume=True)
        self.step_n = 0
        self.got_by_cloud: dict[str, list[int]] = {"pose": [], "cmd": []}
        self.got_by_robot: dict[str, list[int]] = {"odom": [], "goal": []}
        self.resumed: dict = {}                     # the cloud's last ST session resumed
        self.move(True)

    @property
    def now(self) -> float:
        return self.step_n * 0.1

    def tick(self, link: bool) -> None:
        """One period: each side sends a state, and every 10th period a command; then the frames move
        (``link``) or are lost on the way (the link is down, noticed or not)."""
        n = self.step_n
        self.robot.send("DM", {"iTag": "pose", "type": "geometry_msgs/PoseStamped", "msg": {"header": {"seq": n}}},
                        newest_of="pose")
        self.cloud.send_dm("odom", "nav_msgs/Odometry", "", {"header": {"seq": n}}, data=True)
        if n % 10 == 0:
            self.robot.send("DM", {"iTag": "cmd", "type": "std_msgs/String", "msg": {"data": str(n)}})
            self.cloud.send_dm("goal", "std_msgs/String", "", {"data": str(n)}, data=True)
        self.step_n += 1
        self.move(link)

    def move(self, link: bool) -> None:
        for _ in range(10):
            self.cloud.tick(self.now)
            self.robot.tick(self.now)
            to_robot, to_cloud = self.cloud.data_to_send(), self.robot.data_to_send()
            if not (to_robot or to_cloud):
                return
            if not link:
                continue
            for f in to_cloud:
                (self.cloud.receive_text if isinstance(f, str) else self.cloud.receive_binary)(f, self.now)
            for f in to_robot:
                (self.robot.receive_text if isinstance(f, str) else self.robot.receive_binary)(f, self.now)
            for ev in self.cloud.events_received():
                if isinstance(ev, Deliver):
                    m = ev.data["msg"]
                    self.got_by_cloud[ev.itag].append(m["header"]["seq"] if ev.itag == "pose" else int(m["data"]))
            for ev in self.robot.events_received():
                if isinstance(ev, SessionStatus) and ev.data.get("status") == "resumed":
                    self.resumed = ev.data
                if isinstance(ev, MessageReceived):
                    self.got_by_robot[ev.itag].append(ev.msg["header"]["seq"] if ev.itag == "odom"
                                                      else int(ev.msg["data"]))


def test_a_partition_resends_each_states_newest_once_and_every_command_once_in_order():
    p = Partition()
    for _ in range(20):                             # 2 s live
        p.tick(True)
    for _ in range(10):                             # the link dies; for 1 s neither side notices: lost in flight
        p.tick(False)
    p.cloud.detach()
    assert p.robot.detach("code 1006")
    for _ in range(90):                             # 9 s with no path: both keep sending
        p.tick(False)
    last = p.step_n - 1
    before = {k: len(v) for k, v in p.got_by_cloud.items()} | {k: len(v) for k, v in p.got_by_robot.items()}
    q = p.robot.resume_query()
    p.robot.attach()
    p.cloud.attach(int(q["ack"]))
    p.move(True)
    commands = list(range(0, last + 1, 10))
    # each way: every command once, in order; of the states only the newest, once
    assert p.got_by_cloud["cmd"] == commands and p.got_by_robot["goal"] == commands
    assert p.got_by_cloud["pose"][before["pose"]:] == [last] and p.got_by_robot["odom"][before["odom"]:] == [last]
    assert p.got_by_cloud["pose"][:before["pose"]] == list(range(20))
    # the states sent after the last taken (20 .. last - 1) are superseded, counted, and none is lost
    stats = p.cloud.stats()
    assert p.robot.superseded == last - 20 and stats["superseded"] == last - 20
    assert stats["resume_gaps"] == 0 and stats["resume_lost"] == 0 and stats["duplicates"] == 0
    assert p.robot.incoming.gaps == 0 and p.robot.resume_lost == 0 and p.robot.incoming.duplicates == 0
    assert p.resumed["superseded"] == last - 20 and p.resumed["dropped"] == 0       # the cloud's ST told the robot
    # the session goes on, numbered on from the resent messages
    p.tick(True)
    assert p.got_by_cloud["pose"][-1] == last + 1 and p.got_by_robot["odom"][-1] == last + 1
    assert p.cloud.incoming.gaps == 0 and p.robot.incoming.gaps == 0


def test_while_no_path_exists_the_kept_buffer_holds_each_states_newest_and_the_commands():
    p = Partition()
    p.tick(True)
    p.cloud.detach()
    assert p.robot.detach("code 1006")
    for _ in range(300):                            # 30 s dark: 300 states and 30 commands each way
        p.tick(False)
    # kept: the newest state and the 30 commands (the first state and command may be in flight too)
    assert len(p.robot.outgoing) <= 33 and len(p.cloud.outgoing) <= 33
    assert p.robot.superseded == p.cloud.stats()["superseded"] == 299


def test_outgoing_numbers_the_resent_messages_again_after_the_ack_and_the_lost():
    out = Outgoing(max_messages=4)
    seqs = lambda frames: [json.loads(f[0])["seq"] for f in frames]      # noqa: E731
    out.numbered({"type": "DM", "data": {"n": 1}}, newest_of="pose")    # 1: in flight when the link is lost
    out.numbered({"type": "DM", "data": {"n": 2}})                      # 2: a command, in flight
    out.cut()
    for n in range(3, 8):                                               # 3 .. 7: states, each superseding the last
        out.numbered({"type": "DM", "data": {"n": n}}, newest_of="pose")
    out.numbered({"type": "DM", "data": {"n": 8}})
    out.numbered({"type": "DM", "data": {"n": 9}})                      # the bound (4) forgets 1: lost
    assert out.superseded == 4 and out.forgotten == 1 and len(out) == 4
    frames, lost = out.resend_after(0)
    assert lost == 1 and out.superseded == 4
    assert [json.loads(f[0])["data"]["n"] for f in frames] == [2, 7, 8, 9]
    assert seqs(frames) == [2, 3, 4, 5] and out.last == 5              # 1 is the gap of the lost one
    assert json.loads(out.numbered({"type": "DM", "data": {}})[0])["seq"] == 6
    out.ack(6)
    assert len(out) == 0 and out.bytes == 0
