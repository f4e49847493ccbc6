"""``rce-ros --record run.mcap``: every topic the robot's interfaces bridge, both ways, in an MCAP file (ROS 1
encoding, one channel per topic), read back with ``mcap``'s reader and ``mcap-ros1-support``'s decoder. The
original engine's debug sample on a real engine; the robot's local bus driven by ``rce-topic``."""
from __future__ import annotations

import json
import os
import signal

from .test_e2e_debug import BIN, CONFIG, Proc, tool


async def test_rce_ros_records_the_bridged_topics(engine, tmp_path):
    from mcap.reader import make_reader
    from mcap_ros1.decoder import DecoderFactory
    cfg = json.loads(CONFIG.read_text())
    cfg["url"] = engine.master_url
    (tmp_path / "debug.config").write_text(json.dumps(cfg))
    bus, mcap = str(tmp_path / "robot.sock"), tmp_path / "run.mcap"
    env = dict(os.environ, RCE_LOG_JSON="1")
    ros = await Proc.start(str(BIN / "rce-ros"), str(tmp_path / "debug.config"), "--bus", bus, "--timeout", "60",
                           "--record", str(mcap), env=env)
    try:
        await ros.wait_line(r"^rce-ros: ready \(4 interface\(s\) up", timeout=90)
        tool_env = dict(os.environ, RCE_BUS=bus)
        echo = await Proc.start(str(BIN / "rce-topic"), "echo", "/stringEchoResp", "-n", "2", env=tool_env)
        await echo.wait_line(r"^subscribed to /stringEchoResp", key="err")
        for word in ("hello", "world"):
            rc, _, err = await tool("rce-topic", "pub", "/stringEchoReq", f"{{data: {word}}}", "--once", env=tool_env)
            assert rc == 0, err
        assert await echo.wait(30) == 0
        ros.p.send_signal(signal.SIGINT)
        assert await ros.wait(30) == 0, ros.dump()
    finally:
        await ros.kill()
    assert "rce-ros: recorded 4 message(s) on 2 topic(s) to" in ros.text(), ros.dump()
    seen: dict[str, list[str]] = {}
    with open(mcap, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros1"
        summary = reader.get_summary()
        for _schema, channel, _message, msg in reader.iter_decoded_messages():
            assert channel.message_encoding == "ros1"
            assert summary.schemas[channel.schema_id].name == "std_msgs/String"
            seen.setdefault(channel.topic, []).append(msg.data)
    assert seen == {"/stringEchoReq": ["hello", "world"], "/stringEchoResp": ["hello", "world"]}
    assert len(summary.channels) == 2
