"""Every kind of bad input gets an ER (or HTTP error) naming what was wrong,
and that session and every other session keep working. Real processes, real websockets."""
from __future__ import annotations

import asyncio
import hashlib
import json
import urllib.error
import urllib.request

import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from rce.plumbing.errors import RequestError
from wsclient import RawRobot, login

pytestmark = pytest.mark.asyncio


@pytest.fixture(scope="module")
def eng(shared_engine):
    return shared_engine


async def _with_bystander(eng, robot: str, body):
    """Run ``body(r)`` on robot ``robot`` while another robot is connected; afterwards both answer."""
    async with RawRobot(eng.master_url, robot + "_bystander") as other, RawRobot(eng.master_url, robot) as r:
        await body(r)
        await r.probe()
        await other.probe()


async def test_malformed_json(eng):
    async def body(r):
        await r.ws.send('{"type": "CC", "data": ')
        er = await r.expect("ER")
        assert "malformed JSON" in er
    await _with_bystander(eng, "bad_json", body)


async def test_unknown_message_type(eng):
    async def body(r):
        await r.send("XX", {})
        assert "unknown type 'XX'" in await r.expect("ER")
    await _with_bystander(eng, "bad_type", body)


async def test_missing_keys(eng):
    async def body(r):
        await r.ws.send(json.dumps({"type": "CC"}))
        assert "CC: missing key 'data'" in await r.expect("ER")
        await r.cn(addNodes=[{"containerTag": "c", "nodeTag": "n", "pkg": "Test"}])
        assert "addNodes[0]: missing key 'exe'" in await r.expect("ER")
        await r.send("CX", {"connect": [{"tagA": "a/b"}]})
        assert "connect[0]: missing key 'tagB'" in await r.expect("ER")
    await _with_bystander(eng, "missing_keys", body)


async def test_unknown_tags(eng):
    async def body(r):
        await r.cn(addNodes=[{"containerTag": "nope", "nodeTag": "n", "pkg": "Test", "exe": "stringEcho.py"}])
        assert "container 'nope' does not exist" in await r.expect("ER")
        await r.send("DC", {"containerTag": "nope"})
        assert "container 'nope' does not exist" in await r.expect("ER")
        await r.send("CX", {"connect": [{"tagA": "nope/a", "tagB": "unknown_tags/b"}]})
        assert "interface 'nope/a' does not exist" in await r.expect("ER")
        # several items refused for one reason: the ER gives the reason once
        await r.cn(addInterfaces=[{"endpointTag": "nope", "interfaceTag": t, "interfaceType": "PublisherInterface",
                                   "className": "std_msgs/String", "addr": "/" + t} for t in ("a", "b", "c")])
        assert await r.expect("ER") == "CN: container 'nope' does not exist"
    await _with_bystander(eng, "unknown_tags", body)


async def test_unknown_package_names_pkg_and_exe(eng):
    async def body(r):
        await r.send("CC", {"containerTag": "pkgc"})
        await r.cn(addNodes=[{"containerTag": "pkgc", "nodeTag": "n", "pkg": "NoSuchPkg", "exe": "x.py"}])
        assert "NoSuchPkg" in await r.expect("ER")
        await r.cn(addNodes=[{"containerTag": "pkgc", "nodeTag": "n", "pkg": "Test", "exe": "nope.py"}])
        assert "nope.py" in await r.expect("ER")
    await _with_bystander(eng, "unknown_pkg", body)


async def test_a_bad_admin_op_is_refused_by_the_master_naming_the_key(eng):
    """The admin API's container ops are parsed into their ops' models at the master: a bad body is a 400
    naming the op and the key, and the container, its host and the robot's session go on."""
    async def body(r):
        await r.send("CC", {"containerTag": "adminc"})
        await r.probe()                                  # the CC is done before the probe's ER comes
        url = "/api/containers/testUser/adminc"
        with pytest.raises(RequestError, match="admin API: op 'bus_call': service: Field required"):
            await asyncio.to_thread(eng.admin, f"{url}/call", {"request": {}})
        with pytest.raises(RequestError, match=r"admin API: op 'bus_sample': count: Input should be a valid integer"):
            await asyncio.to_thread(eng.admin, f"{url}/sample", {"topic": "/t", "count": "many"})
        assert (await asyncio.to_thread(eng.admin, f"{url}/bus"))["launched"] == []
    await _with_bystander(eng, "bad_admin", body)


async def test_unpairable_interfaces(eng):
    async def body(r):
        await r.send("CC", {"containerTag": "pairc"})
        await r.iface("pairc", "pub", "PublisherInterface", "std_msgs/String", "/p")
        await r.iface("unpairable", "pub2", "PublisherConverter", "std_msgs/String")
        await r.iface("unpairable", "sub3", "SubscriberConverter", "std_msgs/Int32")
        await r.send("CX", {"connect": [{"tagA": "pairc/pub", "tagB": "unpairable/pub2"}]})
        er = await r.expect("ER")
        assert "a Publisher pairs only with a Subscriber" in er
        await r.send("CX", {"connect": [{"tagA": "pairc/pub", "tagB": "unpairable/sub3"}]})
        assert "classes differ" in await r.expect("ER")
        await r.iface("unpairable", "x", "Publisher", "std_msgs/String")
        assert "unknown interface type 'Publisher'" in await r.expect("ER")
    await _with_bystander(eng, "unpairable", body)


async def test_unknown_message_class(eng):
    async def body(r):
        await r.iface("unknown_cls", "s", "SubscriberConverter", "std_msgs/NoSuchThing")
        assert "unknown message class 'std_msgs/NoSuchThing'" in await r.expect("ER")
        await r.send("CC", {"containerTag": "clsc"})
        await r.iface("clsc", "p", "PublisherInterface", "nopkg/Nope", "/p")
        assert "nopkg/Nope" in await r.expect("ER")
    await _with_bystander(eng, "unknown_cls", body)


async def test_message_that_does_not_fit_its_class(eng):
    async def body(r):
        await r.iface("misfit", "pose", "SubscriberConverter", "geometry_msgs/PoseStamped")
        await r.send("DM", {"iTag": "pose", "type": "geometry_msgs/PoseStamped", "msgID": "",
                            "msg": {"pose": {"position": {"x": "far"}}}})
        er = await r.expect("ER")
        assert "geometry_msgs/PoseStamped" in er and "pose.position.x" in er
        await r.send("DM", {"iTag": "pose", "type": "geometry_msgs/PoseStamped", "msgID": "",
                            "msg": {"pose": {"orientation": {"w": 1}}, "bogus": 1}})
        assert "unknown field 'bogus'" in await r.expect("ER")
        await r.send("DM", {"iTag": "pose", "type": "std_msgs/String", "msgID": "", "msg": {"data": "x"}})
        assert "carries 'geometry_msgs/PoseStamped'" in await r.expect("ER")
    await _with_bystander(eng, "misfit", body)


async def test_frame_over_size_limit(engine_ws_impls):
    eng = engine_ws_impls
    async def body(r):
        big = "x" * (32 * 1024 * 1024 + 10)   # the robot task set's default --max-message is 32 MiB
        await r.send("DM", {"iTag": "s", "type": "std_msgs/String", "msgID": "", "msg": {"data": big}})
        er = await r.expect("ER", timeout=60)
        assert "exceeds the limit of 33554432 bytes" in er
    await _with_bystander(eng, "too_big", body)


async def test_binary_part_errors(eng):
    async def body(r):
        await r.ws.send(b"short")
        assert "shorter than its 32-char id" in await r.expect("ER")
        await r.send("DM", {"iTag": "s", "type": "std_msgs/String", "msgID": "", "msg*": "not-an-id"})
        assert "32-hex-char id" in await r.expect("ER")
    await _with_bystander(eng, "binary_err", body)


async def test_bad_credentials_at_login(eng):
    # an unknown user gets the answer a known one gets (no user enumeration, docs/SECURITY.md); the
    # password check at the robot endpoint then refuses both alike (tests/security/test_login.py)
    assert login(eng.master_url, user="nobody") == login(eng.master_url, user="testUser")
    with pytest.raises(urllib.error.HTTPError) as ei:
        urllib.request.urlopen(eng.master_url + "?version=20130902")
    assert ei.value.code == 400 and "userID" in ei.value.read().decode()


async def test_bad_credentials_at_websocket(engine_ws_impls):
    eng = engine_ws_impls
    url = login(eng.master_url)["url"]
    wrong = hashlib.sha256(b"wrong").hexdigest()
    with pytest.raises(InvalidStatus) as ei:          # a newer client: the HTTP status
        async with connect(f"{url}?userID=testUser&robotID=badpw&password={wrong}&refusal=http"):
            pass
    assert ei.value.response.status_code == 401
    assert b"invalid user ID or password" in ei.value.response.body


@pytest.mark.parametrize("user", ["testUser", "nobody"])
async def test_a_2013_client_that_only_reads_frames_learns_its_login_failed(engine_ws_impls, user):
    """The 2013 client (autobahn_rce 0.6) never surfaces an HTTP status: it is shown one ER naming
    the failure, the same for an unknown user and a wrong password, and the websocket closes (1008)."""
    eng = engine_ws_impls
    url = login(eng.master_url, user=user)["url"]
    wrong = hashlib.sha256(b"wrong").hexdigest()
    async with connect(f"{url}?userID={user}&robotID=badpw&password={wrong}") as ws:
        frame = json.loads(await asyncio.wait_for(ws.recv(), 10))
        with pytest.raises(ConnectionClosed):
            await asyncio.wait_for(ws.recv(), 10)
    assert frame == {"type": "ER", "data": f"login refused: invalid user ID or password for user {user!r}"}
    assert ws.close_code == 1008
    with pytest.raises(InvalidStatus) as ei:          # a request that is not a login at all: 400
        async with connect(f"{url}?userID=testUser&robotID=badpw"):
            pass
    assert ei.value.response.status_code == 400 and b"password" in ei.value.response.body
    # the RCE alpha client sent the raw SHA-256 digest, URL-encoded: accepted too
    from urllib.parse import quote
    raw = quote(hashlib.sha256(b"testUser").digest().decode("latin-1"), encoding="latin-1")
    async with connect(f"{url}?userID=testUser&robotID=alpha&password={raw}") as ws:
        await ws.send(json.dumps({"type": "XX", "data": {}}))
        assert json.loads(await asyncio.wait_for(ws.recv(), 10))["type"] == "ER"


async def test_duplicate_robot_id_refused(engine_ws_impls):
    eng = engine_ws_impls
    async with RawRobot(eng.master_url, "dup"):
        with pytest.raises(InvalidStatus) as ei:
            async with RawRobot(eng.master_url, "dup"):
                pass
        assert ei.value.response.status_code == 409
        assert b"already connected" in ei.value.response.body
