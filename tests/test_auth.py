"""services/auth.py: CurveZMQ keys, the allow-list, refused strangers, squatters that get nothing."""

from __future__ import annotations

import stat
import time

import pytest
import zmq
import zmq.auth

from services import auth as A
from services import sockets as S
from services.settings import TransportSettings, WorkerSettings, load


@pytest.fixture
def keys(tmp_path):
    d = tmp_path / "keys"
    A.make_keys(d)
    return d


@pytest.fixture
def actx():
    """A context whose ZAP handler is stopped before it is destroyed."""
    c = zmq.Context()
    yield c
    A.stop_authenticator(c)
    c.destroy(linger=0)


def _st(keys, **kw) -> TransportSettings:
    base = dict(frames_endpoint="tcp://127.0.0.1:0", monitor_endpoint="tcp://127.0.0.1:0",
                points_endpoint="tcp://127.0.0.1:0", curve_dir=keys)
    return TransportSettings(**{**base, **kw})


def _recv(sock: zmq.Socket, timeout_ms: int) -> list | None:
    return sock.recv_multipart() if sock.poll(timeout_ms) else None


# ---------------------------------------------------------------------------------------------
def test_make_keys_lays_out_server_clients_and_allow_list_and_is_idempotent(tmp_path):
    d = tmp_path / "k"
    made = A.make_keys(d, ("worker", "recorder"))
    assert set(made) == {"server", "worker", "recorder"}
    assert {p.stem for p in (d / "authorized").glob("*.key")} == {"worker", "recorder"}
    for sec in d.rglob("*.key_secret"):
        assert stat.S_IMODE(sec.stat().st_mode) == 0o600, sec
    server_before = (d / "server.key_secret").read_bytes()
    assert A.make_keys(d, ("worker", "extra")) == {"extra": d / "clients" / "extra.key_secret"}
    assert (d / "server.key_secret").read_bytes() == server_before  # kept, not replaced
    srv = A.server_keys(d)
    cli = A.client_keys(d, "extra")
    assert cli.public in srv.allowed and cli.server_public == srv.public and len(srv.allowed) == 3
    with pytest.raises(ValueError, match="server"):
        A.make_keys(d, ("server",))
    with pytest.raises(A.CurveKeyError, match="nobody.key_secret"):
        A.client_keys(d, "nobody")


@pytest.mark.parametrize("ep, local", [
    ("tcp://127.0.0.1:5555", True), ("tcp://127.3.2.1:1", True), ("tcp://localhost:5", True),
    ("tcp://[::1]:5555", True), ("ipc:///tmp/x", True), ("inproc://x", True),
    ("tcp://*:5555", False), ("tcp://0.0.0.0:5555", False), ("tcp://192.168.1.4:5555", False),
    ("tcp://api:5557", False), ("tcp://[::]:5", False), ("tcp://127.0.0.1;10.0.0.2:5555", False),
    ("pgm://eth0;239.1.1.1:5555", False),
])
def test_which_endpoints_stay_on_this_machine(ep, local):
    assert A.is_local_endpoint(ep) is local


def test_settings_refuse_an_endpoint_off_this_machine_without_keys(keys):
    with pytest.raises(ValueError, match=r"^frames_endpoint: tcp://\*:5555 is reachable from other machines"):
        load(TransportSettings, frames_endpoint="tcp://*:5555")
    with pytest.raises(ValueError, match=r"points_endpoint: tcp://api:5557"):
        load(WorkerSettings, points_endpoint="tcp://api:5557")
    assert load(TransportSettings, frames_endpoint="tcp://*:5555", curve_dir=keys).curve_dir == keys
    with pytest.raises(ValueError, match=r"^curve_dir: .* holds no CurveZMQ keys"):
        load(TransportSettings, curve_dir=keys / "clients")
    with pytest.raises(ValueError, match="curve_client"):
        load(TransportSettings, curve_client="../server")


def test_unbindable_endpoint_is_an_error_naming_the_settings_field(ctx):
    a = S.open_socket(ctx, S.points_pull(TransportSettings(points_endpoint="tcp://127.0.0.1:0")))
    taken = S.bound_endpoint(a)
    with pytest.raises(S.SocketError, match=r"^points_endpoint: points \(API PULL\) cannot bind tcp://127.0.0.1:\d+"):
        S.open_socket(ctx, S.points_pull(TransportSettings(points_endpoint=taken)))
    a.close()


def test_an_allowed_worker_gets_frames_and_strangers_get_none_and_are_counted(actx, keys, tmp_path):
    refused: list[str] = []
    push = S.open_socket(actx, S.frames_push(_st(keys, drop_policy="block")), on_refused=refused.append)
    assert S.socket_options(push)["curve"] == "server"
    ep = S.bound_endpoint(push)
    # a stranger with keys of its own, and one speaking plain ZeroMQ
    stranger_pub, stranger_sec = zmq.curve_keypair()
    stranger = actx.socket(zmq.PULL)
    A.apply_client(stranger, A.CurveClient(stranger_pub, stranger_sec, A.server_keys(keys).public))
    stranger.connect(ep)
    plain = actx.socket(zmq.PULL)
    plain.connect(ep)
    time.sleep(0.3)
    good = S.open_socket(actx, S.frames_pull(_st(keys, frames_endpoint=ep)))
    assert S.socket_options(good)["curve"] == "client"
    for i in range(6):
        push.send_multipart([b"frame", str(i).encode()])
    got = [_recv(good, 2000) for _ in range(6)]
    assert [g[1] for g in got if g] == [str(i).encode() for i in range(6)]  # every frame to the allowed worker
    assert _recv(stranger, 200) is None and _recv(plain, 200) is None
    assert refused and set(refused) == {"frames"}
    for s in (push, good, stranger, plain):
        s.close(linger=0)


def test_a_squatter_on_the_points_port_receives_nothing_from_a_worker(actx, keys):
    squatter = actx.socket(zmq.PULL)  # bound first, without the server's secret key
    port = squatter.bind_to_random_port("tcp://127.0.0.1")
    st = _st(keys, points_endpoint=f"tcp://127.0.0.1:{port}", points_send_timeout_ms=300)
    push = S.open_socket(actx, S.points_push(st))
    push.send_multipart([b"points", b"x"])  # queued for a connection whose handshake never completes
    assert _recv(squatter, 1000) is None
    # the real API (with the server key) on a port of its own gets it
    pull = S.open_socket(actx, S.points_pull(_st(keys)))
    push2 = S.open_socket(actx, S.points_push(_st(keys, points_endpoint=S.bound_endpoint(pull),
                                                  points_send_timeout_ms=2000)))
    push2.send_multipart([b"points", b"y"])
    assert _recv(pull, 2000) == [b"points", b"y"]
    for s in (squatter, push, pull, push2):
        s.close(linger=0)


def test_a_worker_without_its_key_file_is_a_settings_error(keys):
    st = _st(keys, curve_client="nobody")
    with pytest.raises(A.CurveKeyError, match=r"^curve_dir: cannot read .*nobody.key_secret"):
        S.frames_pull(st)


def test_a_malformed_allow_list_is_a_key_error_naming_curve_dir(keys):
    (keys / "authorized" / "broken.key").write_text("metadata\n")
    with pytest.raises(A.CurveKeyError, match=r"^curve_dir: .*authorized"):
        A.server_keys(keys)
    (keys / "authorized" / "broken.key").write_text('curve\n    public-key = "abc"\n')
    with pytest.raises(A.CurveKeyError, match="40-character"):
        A.server_keys(keys)


def test_without_its_zap_handler_a_curve_server_lets_nobody_in(actx, keys):
    """ZAP_ENFORCE_DOMAIN: a server socket whose handler was stopped refuses every peer (libzmq's
    default would let any CURVE client in, allow-list or not)."""
    pull = S.open_socket(actx, S.points_pull(_st(keys)))
    A.stop_authenticator(actx)
    pk, sk = zmq.curve_keypair()
    stranger = actx.socket(zmq.PUSH)
    A.apply_client(stranger, A.CurveClient(pk, sk, A.server_keys(keys).public))
    stranger.connect(S.bound_endpoint(pull))
    stranger.send_multipart([b"points", b"forged"])
    assert _recv(pull, 1000) is None
    for s in (pull, stranger):
        s.close(linger=0)
