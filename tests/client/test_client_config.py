"""Robot configs: the shipped samples load, bad ones are refused naming file, key path and
reason, and rce-ros refuses them (exit code 2) before it contacts anything."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from rce.protocol.config import load_config
from rce.plumbing.errors import ConfigError
from rce_client import rce_ros

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def base() -> dict:
    return json.loads((CONFIGS / "debug.config").read_text())


def write(tmp_path: Path, cfg, name: str = "robot.config") -> Path:
    p = tmp_path / name
    p.write_text(cfg if isinstance(cfg, str) else (yaml.safe_dump(cfg) if name.endswith(".yaml")
                                                   else json.dumps(cfg)))
    return p


def test_debug_samples_load_and_agree():
    a, b = load_config(CONFIGS / "debug.config"), load_config(CONFIGS / "debug.yaml")
    assert a == b
    assert (a.url, a.userID, a.password, a.robotID) == ("http://127.0.0.1:9000/", "testUser", "testUser", "testRobot")
    assert [c.cTag for c in a.containers] == ["cTag_01"]
    assert [(n.nTag, n.pkg, n.exe) for n in a.nodes] == [("strEcho", "Test", "stringEcho.py"),
                                                         ("paramTest", "Test", "paramTest.py")]
    assert {p.name: p.value for p in a.parameters} == {"int": 99, "str": "foo", "float": 3.3, "bool": True}
    robot = {i.iTag: i.iType for i in a.interfaces if i.eTag == "testRobot"}
    cont = {i.iTag: i.iType for i in a.interfaces if i.eTag == "cTag_01"}
    assert robot == {"stringEchoReq": "SubscriberConverter", "stringEchoResp": "PublisherConverter",
                     "stringEchoService": "ServiceProviderConverter", "parameterTest": "ServiceProviderConverter"}
    assert cont == {"stringEchoReq": "PublisherInterface", "stringEchoResp": "SubscriberInterface",
                    "stringEchoService": "ServiceClientInterface", "parameterTest": "ServiceClientInterface"}
    # every robot-side interface is connected to its container twin
    pairs = {frozenset((c.tagA, c.tagB)) for c in a.connections}
    assert pairs == {frozenset((f"cTag_01/{t}", f"testRobot/{t}")) for t in robot}


def _mutate(path: str, value):
    """A copy of debug.config with the value at dotted ``path`` replaced (``_del`` deletes it)."""
    cfg = base()
    *parents, last = path.split(".")
    node = cfg
    for p in parents:
        node = node[int(p)] if p.isdigit() else node[p]
    key = int(last) if last.isdigit() else last
    if value == "_del":
        del node[key]
    else:
        node[key] = value
    return cfg


@pytest.mark.parametrize("path, value, where, reason", [
    ("robotID", "_del", "robotID", "Field required"),
    ("userID", "", "userID", "at least 1 character"),
    ("interfaces.2.iType", "Publisher", "interfaces[2].iType", "unknown interface type 'Publisher'"),
    ("url", 5, "url", "valid string"),
    ("interfaces.0.eTag", "testRobot", "interfaces[0].eTag", "lives in a container"),
    ("interfaces.5.eTag", "cTag_01", "interfaces[5].eTag", "lives on the robot"),
    ("connections.1.tagB", "testRobot", "connections[1].tagB", "must be 'endpointTag/interfaceTag'"),
    ("nodes.0.exe", "_del", "nodes[0].exe", "Field required"),
    ("nodes.1.bogus", 1, "nodes[1].bogus", "unknown key"),
    ("containers.0.cpu", -1, "containers[0].cpu", "greater than or equal to 0"),
    ("parameters", {"int": 1}, "parameters", "valid list"),
    ("interfaces.4.lane", "fast", "interfaces[4].lane", "unknown lane 'fast': expected one of 'control', 'state', "
                                                         "'bulk'"),
    ("interfaces.4.lane", 1, "interfaces[4].lane", "unknown lane 1"),
])
def test_bad_configs_name_file_key_path_and_reason(tmp_path, path, value, where, reason):
    p = write(tmp_path, _mutate(path, value))
    with pytest.raises(ConfigError) as ei:
        load_config(p)
    msg = ei.value.message
    assert msg.startswith(f"{p}: {where}: "), msg
    assert reason in msg, msg


def test_a_lane_per_interface_goes_on_the_wire_and_configs_without_it_keep_working(tmp_path):
    assert all(i.lane is None and "lane" not in i.component() for i in load_config(CONFIGS / "debug.config").interfaces)
    cfg = _mutate("interfaces.4.lane", "Control")
    itf = load_config(write(tmp_path, cfg)).interfaces[4]
    assert itf.lane == "control" and itf.component()["lane"] == "control"


def test_duplicates(tmp_path):
    cfg = base()
    cfg["containers"].append({"cTag": "cTag_01"})
    with pytest.raises(ConfigError, match=r"containers\[1\]\.cTag: duplicate container tag 'cTag_01'"):
        load_config(write(tmp_path, cfg))
    cfg = base()
    cfg["interfaces"].append(dict(cfg["interfaces"][0]))
    with pytest.raises(ConfigError, match=r"interfaces\[8\]\.iTag: duplicate interface cTag_01/stringEchoReq"):
        load_config(write(tmp_path, cfg))


def test_unparsable_files(tmp_path):
    with pytest.raises(ConfigError, match=r"robot.config: not valid JSON \(line 1"):
        load_config(write(tmp_path, '{"url": "x", '))
    with pytest.raises(ConfigError, match=r"robot.yaml: not valid YAML"):
        load_config(write(tmp_path, "url: [unclosed", "robot.yaml"))
    with pytest.raises(ConfigError, match=r"nope.config: cannot read"):
        load_config(tmp_path / "nope.config")
    with pytest.raises(ConfigError, match=r"list.config: the config must be an object"):
        load_config(write(tmp_path, "[1, 2]", "list.config"))


def test_yaml_errors_name_the_key_path_too(tmp_path):
    cfg = _mutate("interfaces.3.iCls", "")
    p = write(tmp_path, cfg, "robot.yaml")
    with pytest.raises(ConfigError, match=rf"^{p}: interfaces\[3\]\.iCls: "):
        load_config(p)


def _run_rce_ros(argv, capsys) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as ei:
        rce_ros.main(argv)
    out, err = capsys.readouterr()
    return ei.value.code, out, err


def test_rce_ros_refuses_a_bad_config_before_sending_anything(tmp_path, capsys):
    # the url points nowhere reachable: exit 2 proves nothing was attempted (that would be exit 1)
    cfg = _mutate("interfaces.6.iType", "ServiceThing")
    cfg["url"] = "http://127.0.0.1:9/"
    p = write(tmp_path, cfg)
    code, out, err = _run_rce_ros([str(p), "--bus", str(tmp_path / "b.sock")], capsys)
    assert code == 2
    assert f"rce-ros: {p}: interfaces[6].iType: unknown interface type 'ServiceThing'" in err
    assert out == "" and not (tmp_path / "b.sock").exists()


def test_rce_ros_refuses_a_converter_class_unknown_locally(tmp_path, capsys):
    cfg = _mutate("interfaces.5.iCls", "nope_msgs/Nothing")
    cfg["interfaces"][1]["iCls"] = "nope_msgs/Nothing"
    cfg["url"] = "http://127.0.0.1:9/"
    p = write(tmp_path, cfg)
    code, out, err = _run_rce_ros([str(p), "--bus", str(tmp_path / "b.sock")], capsys)
    assert code == 2
    assert f"{p}: interfaces[5].iCls: unknown message class 'nope_msgs/Nothing'" in err
    assert "RCE_PACKAGE_PATH" in err and out == ""


def test_rce_ros_refuses_conflicting_local_addresses(tmp_path, capsys):
    cfg = base()
    cfg["interfaces"][7]["addr"] = "/stringEchoService"      # two bridged services on one local name
    cfg["url"] = "http://127.0.0.1:9/"
    p = write(tmp_path, cfg)
    code, _, err = _run_rce_ros([str(p), "--bus", str(tmp_path / "b.sock")], capsys)
    assert code == 2
    assert f"{p}: interfaces[7].addr: local service /stringEchoService is already bridged by stringEchoService" in err


def test_rce_ros_unreachable_master_exits_1(tmp_path, capsys):
    cfg = base()
    cfg["url"] = "http://127.0.0.1:9/"
    p = write(tmp_path, cfg)
    code, out, err = _run_rce_ros([str(p), "--bus", str(tmp_path / "b.sock")], capsys)
    assert code == 1
    assert "cannot reach the master at http://127.0.0.1:9/" in err
    assert f"export RCE_BUS={tmp_path / 'b.sock'}" in out
    assert not (tmp_path / "b.sock").exists()           # the local bus went away with it


@pytest.mark.parametrize("bad", ["-1", "nan", "inf"])
def test_rce_ros_refuses_a_max_lag_that_is_not_0_or_more_seconds(tmp_path, capsys, bad):
    cfg = _mutate("interfaces.0.iCls", "std_msgs/String")
    cfg["url"] = "http://127.0.0.1:9/"
    code, out, err = _run_rce_ros([str(write(tmp_path, cfg)), "--bus", str(tmp_path / "b.sock"), f"--max-lag={bad}"],
                                  capsys)
    assert code == 2 and "--max-lag must be 0 or more seconds" in err and out == ""
