"""rce.transport.cluster_auth: the cluster key file, the control-link handshake (sans I/O, then on
in-memory streams) and the data-plane credentials. No sockets."""
from __future__ import annotations

import asyncio
import stat

import pytest
from memlink import pipe

from rce.transport import cluster_auth

from rce.transport import framing
from rce.transport.cluster_auth import AuthFailed, ClusterKey, Gate, Handshake
from rce.plumbing.errors import ConfigError, ProtocolError, RequestError

STEP = 5.0          # s, the longest any single wait may take
KEY, OTHER = ClusterKey.generate(), ClusterKey.generate()


def run(initiator: Handshake, responder: Handshake) -> list[dict]:
    """Play a whole handshake; the messages, in order."""
    said = [initiator.hello()]
    side = [responder, initiator]
    while True:
        out = side[(len(said) - 1) % 2].receive(said[-1])
        if out is None:
            return said
        said.append(out)


# -- the handshake, sans I/O ------------------------------------------------------------------------
def test_both_ends_with_the_key_prove_it_to_each_other():
    i, r = Handshake(KEY, "initiator"), Handshake(KEY, "responder")
    said = run(i, r)
    assert [m["auth"] for m in said] == ["hello", "challenge", "response", "ok"]
    assert i.done and r.done
    assert said[0]["key_id"] == said[1]["key_id"] == KEY.key_id and len(KEY.key_id) == 8
    assert KEY.secret.hex() not in str(said)


def test_a_peer_without_the_key_is_refused_and_says_why():
    with pytest.raises(AuthFailed, match="cluster keys differ.*--cluster-key-file"):
        run(Handshake(OTHER, "initiator"), Handshake(KEY, "responder"))
    r = Handshake(KEY, "responder")                  # a rogue that copies the public key id still has no proof
    r.receive({**Handshake(OTHER, "initiator").hello(), "key_id": KEY.key_id})
    with pytest.raises(AuthFailed, match="wrong proof"):
        r.receive({"auth": "response", "proof": "00" * 32})
    assert not r.done


def test_a_task_set_knows_it_reached_the_real_master():
    i = Handshake(KEY, "initiator")
    hello = i.hello()
    fake = Handshake(OTHER, "responder")
    challenge = fake.receive({**hello, "key_id": OTHER.key_id})     # a fake that skips the key id check
    with pytest.raises(AuthFailed, match="wrong proof"):
        i.receive({**challenge, "key_id": KEY.key_id})
    with pytest.raises(AuthFailed, match="refused us: wrong key"):
        Handshake(KEY, "initiator").receive({"auth": "refused", "reason": "wrong key"})


def test_proofs_cannot_be_replayed_or_reflected():
    i1, r1 = Handshake(KEY, "initiator"), Handshake(KEY, "responder")
    said = run(i1, r1)
    r2 = Handshake(KEY, "responder")                 # the same hello again: a fresh responder nonce
    r2.receive(said[0])
    with pytest.raises(AuthFailed):
        r2.receive(said[2])                          # the recorded response
    r3 = Handshake(KEY, "responder")
    challenge = r3.receive(Handshake(KEY, "initiator", nonce=bytes(16)).hello())
    with pytest.raises(AuthFailed):                   # the responder's own proof sent back as a response
        r3.receive({"auth": "response", "proof": challenge["proof"]})


@pytest.mark.parametrize("hello, why", [
    ({"auth": "hello", "v": 2}, "version 1"),
    ({"auth": "hello", "v": 1, "purpose": "data"}, "version 1 for 'control'"),
    ({"auth": "hello", "v": 1, "purpose": "control", "nonce": "abc"}, "32 hex digits"),
    ({"auth": "hello", "v": 1, "purpose": "control", "nonce": "zz" * 16}, "32 hex digits"),
    ({"auth": "response", "proof": "00"}, "expected 'hello'"),
    ({"op": "register", "id": 1, "args": {}}, "expected 'hello'"),
])
def test_what_is_not_the_handshake_is_refused_by_name(hello, why):
    with pytest.raises(ProtocolError, match=why):
        Handshake(KEY, "responder").receive(hello)


def test_nothing_after_the_handshake_is_taken_as_part_of_it():
    i, r = Handshake(KEY, "initiator"), Handshake(KEY, "responder")
    run(i, r)
    with pytest.raises(ProtocolError, match="expected"):
        r.receive({"auth": "response", "proof": "00"})


# -- the key file ---------------------------------------------------------------------------------------
def test_the_master_creates_the_key_at_the_default_path_once(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    monkeypatch.delenv(cluster_auth.KEY_ENV, raising=False)
    k = ClusterKey.load_or_create()
    path = tmp_path / "state" / "rce" / "cluster-key"
    assert k.path == path and stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    assert len(bytes.fromhex(path.read_text())) == cluster_auth.KEY_BYTES
    assert ClusterKey.load_or_create().secret == ClusterKey.load().secret == k.secret     # a task set finds it
    assert list(path.parent.iterdir()) == [path]                                          # no temp file left


def test_a_named_key_file_must_exist_and_be_a_key(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    missing = tmp_path / "elsewhere" / "key"
    monkeypatch.setenv(cluster_auth.KEY_ENV, str(missing))
    for make in (ClusterKey.load, ClusterKey.load_or_create):
        with pytest.raises(ConfigError, match=f"no cluster key at {missing}: start rce-master"):
            make()
    assert not missing.exists() and not (tmp_path / "state").exists()
    bad = tmp_path / "bad"
    bad.write_text("not hex\n")
    with pytest.raises(ConfigError, match=f"cluster key {bad}: expected hex"):
        ClusterKey.load(bad)                                      # the flag wins over the environment
    bad.write_text("ab" * 8)
    with pytest.raises(ConfigError, match="has 8 bytes; at least 16"):
        ClusterKey.load(bad)
    good = tmp_path / "good"
    good.write_text(KEY.secret.hex())
    good.chmod(0o600)
    assert ClusterKey.load(good).key_id == KEY.key_id


# -- data-plane credentials ------------------------------------------------------------------------------
def test_a_grant_proves_one_direction_of_one_connection_to_one_endpoint_on_one_link():
    token = bytes.fromhex(KEY.connection_token(10, 20, "b:2"))
    nonce = bytes(16)
    grant = {"grant": [10, 20], "proof": cluster_auth.grant_proof(token, nonce, 10, 20).hex()}
    assert cluster_auth.check_grant(KEY.data_key("b:2"), nonce, grant) == (10, 20)
    for key, n, g in [(KEY.data_key("c:3"), nonce, grant),                     # another endpoint
                      (KEY.data_key("b:2"), b"\1" * 16, grant),                 # another link
                      (KEY.data_key("b:2"), nonce, {**grant, "grant": [20, 10]}),  # the other direction
                      (OTHER.data_key("b:2"), nonce, grant),                    # another cluster
                      (None, nonce, grant)]:                                    # no data key yet
        with pytest.raises(AuthFailed):
            cluster_auth.check_grant(key, n, g)
    for bad in ({"grant": [10], "proof": "00"}, {"grant": [10, -1], "proof": "00"}, {"grant": [1, True], "proof": "0"},
                {"grant": [1, 2]}, {"nonce": "00"}):
        with pytest.raises(ProtocolError, match="a grant is"):
            cluster_auth.check_grant(KEY.data_key("b:2"), nonce, bad)


def test_a_connect_without_a_credential_is_refused_by_name():
    assert cluster_auth.token_of("ab" * 32) == b"\xab" * 32
    for token in (None, "", "ab", 5, "xy" * 32):
        with pytest.raises(RequestError, match="connect: 'token' must be the master's credential"):
            cluster_auth.token_of(token)


# -- on streams ----------------------------------------------------------------------------------------------
async def test_the_handshake_on_a_stream_leaves_what_follows_unread():
    (ra, wa), (rb, wb) = pipe()
    gate = Gate(KEY, "test")
    admitted = asyncio.ensure_future(gate.admit(rb, wb))
    await cluster_auth.initiate(ra, wa, KEY)
    wa.transport.write(framing.encode_control({"op": "register", "id": 1}))
    assert await asyncio.wait_for(admitted, STEP)
    assert framing.FrameDecoder().feed(await rb.read(4096)) == [{"op": "register", "id": 1}]
    assert (gate.admitted, sum(gate.refused.values()), gate.pending) == (1, 0, 0)


async def test_the_gate_refuses_counts_and_closes():
    refusals = []
    gate = Gate(KEY, "test", timeout=0.2, on_refused=refusals.append)

    async def attempt(send: bytes) -> tuple[bool, bytes]:
        (ra, wa), (rb, wb) = pipe()
        if send:
            wa.transport.write(send)
        ok = await asyncio.wait_for(gate.admit(rb, wb), STEP)
        return ok, await asyncio.wait_for(ra.read(), STEP)
    (ra, wa), (rb, wb) = pipe()
    admitted = asyncio.ensure_future(gate.admit(rb, wb))
    with pytest.raises(AuthFailed, match="refused us: cluster keys differ"):
        await cluster_auth.initiate(ra, wa, OTHER)
    assert not await admitted
    ok, said = await attempt(framing.encode_control({"op": "register", "id": 1, "args": {"kind": "robot"}}))
    assert not ok and framing.FrameDecoder().feed(said)[0]["auth"] == "refused"
    assert not (await attempt(framing.encode_data(framing.MSG, 1, 2, 0, b"x")))[0]
    assert not (await attempt(b""))[0]                                 # says nothing: timed out
    assert refusals == ["wrong_key", "malformed", "malformed", "timeout"] and gate.admitted == 0
    gate.max_pending = gate.pending
    assert not (await attempt(b""))[0] and refusals[-1] == "busy"


async def test_a_flood_of_refusals_is_counted_but_logged_a_bounded_number_of_times(caplog, monkeypatch):
    monkeypatch.setattr(cluster_auth, "LOGGED_REFUSALS", 3)
    gate = Gate(KEY, "flooded")
    for _ in range(10):
        (_ra, wa), (rb, wb) = pipe()
        wa.transport.write(framing.encode_control({"op": "register"}))
        assert not await asyncio.wait_for(gate.admit(rb, wb), STEP)
    assert gate.refused["malformed"] == 10
    assert len([r for r in caplog.records if "unauthenticated link refused" in r.getMessage()]) == 3
    gate._window_start -= cluster_auth.LOG_WINDOW                 # the next window: logged again, with the count
    (_ra, wa), (rb, wb) = pipe()
    wa.transport.write(framing.encode_control({"op": "register"}))
    await gate.admit(rb, wb)
    assert gate._unlogged == 0 and gate.refused["malformed"] == 11
