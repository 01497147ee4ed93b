"""services.sockets: every role's options come from the settings and are the ones in force (read
back), port 0 binding with the bound endpoint exposed, the send policies, MAXMSGSIZE, and the
endpoint report a parent reads."""

from __future__ import annotations

import json
import logging
import threading
import time

import pytest
import zmq

from services import sockets as S
from services.settings import TransportSettings

ANY = "tcp://127.0.0.1:0"


def _settings(**kw) -> TransportSettings:
    return TransportSettings(**{"frames_endpoint": ANY, "monitor_endpoint": ANY, "points_endpoint": ANY, **kw})


def test_defaults_are_named_in_the_settings():
    st = TransportSettings()
    assert (st.hwm, st.linger_ms, st.points_hwm, st.points_linger_ms) == (
        S.DEFAULT_FRAME_HWM, S.DEFAULT_FRAME_LINGER_MS, S.DEFAULT_POINT_HWM, S.DEFAULT_POINT_LINGER_MS)
    assert (st.max_frame_bytes, st.max_point_bytes) == (S.DEFAULT_MAX_FRAME_BYTES, S.DEFAULT_MAX_POINT_BYTES)


def test_every_role_has_the_options_its_settings_give_and_logs_them_as_read_back(ctx, caplog):
    st = _settings(hwm=7, linger_ms=30, points_hwm=77, points_linger_ms=300, points_send_timeout_ms=250,
                   max_frame_bytes=10_000, max_point_bytes=1_000, drop_policy="block")
    push = S.open_socket(ctx, S.frames_push(st))
    pull_st = _settings(hwm=7, max_frame_bytes=10_000)
    pull_st.frames_endpoint = S.bound_endpoint(push)
    api = S.open_socket(ctx, S.points_pull(st))
    wst = _settings(points_hwm=77, points_linger_ms=300, points_send_timeout_ms=250)
    wst.points_endpoint = S.bound_endpoint(api)
    with caplog.at_level(logging.INFO, logger="mtcw.sockets"):
        socks = {
            "push": push, "pub": S.open_socket(ctx, S.monitor_pub(st)),
            "pull": S.open_socket(ctx, S.frames_pull(pull_st)),
            "sub": S.open_socket(ctx, S.monitor_sub(pull_st, hwm=3)),
            "points_push": S.open_socket(ctx, S.points_push(wst)), "api": api,
        }
    opts = {k: S.socket_options(s) for k, s in socks.items()}
    assert opts["push"] | {"endpoint": None} == {"type": "PUSH", "endpoint": None, "hwm": 7, "linger_ms": 30,
                                                 "policy": "block", "curve": "off"}
    assert (opts["pub"]["hwm"], opts["pub"]["linger_ms"], opts["pub"]["policy"]) == (7, 30, "drop")
    assert (opts["pull"]["hwm"], opts["pull"]["linger_ms"], opts["pull"]["max_msg_bytes"]) == (7, 0, 10_000)
    assert (opts["sub"]["hwm"], opts["sub"]["max_msg_bytes"]) == (3, 10_000)
    assert (opts["points_push"]["hwm"], opts["points_push"]["linger_ms"], opts["points_push"]["policy"]) == (
        77, 300, "wait 250 ms, then drop")
    assert (opts["api"]["hwm"], opts["api"]["max_msg_bytes"]) == (77, 1_000)
    logged = [json.loads(r.getMessage().split(": ", 1)[1]) for r in caplog.records]
    assert {json.dumps(o, sort_keys=True) for o in logged} >= {json.dumps(opts[k], sort_keys=True)
                                                               for k in ("pub", "pull", "sub", "points_push")}
    for s in socks.values():
        s.close()


def test_port_zero_binds_a_free_port_and_exposes_it(ctx):
    a = S.open_socket(ctx, S.frames_push(_settings()))
    b = S.open_socket(ctx, S.frames_push(_settings()))
    ea, eb = S.bound_endpoint(a), S.bound_endpoint(b)
    assert ea.startswith("tcp://127.0.0.1:") and not ea.endswith(":0") and ea != eb
    with pytest.raises(S.SocketError, match="^frames_endpoint: frames .*cannot bind"):
        S.open_socket(ctx, S.frames_push(_settings(frames_endpoint=ea)))  # taken: the error names field and role
    a.close()
    b.close()


def test_drop_policy_drops_at_once_and_block_waits(ctx):
    drop = S.open_socket(ctx, S.frames_push(_settings(drop_policy="drop")))
    t0 = time.monotonic()
    with pytest.raises(zmq.Again):
        drop.send_multipart([b"frame", b"x"])  # no worker: dropped, not queued
    assert time.monotonic() - t0 < 0.5
    block = S.open_socket(ctx, S.frames_push(_settings(drop_policy="block")))
    got = []
    puller = ctx.socket(zmq.PULL)

    def late_worker():
        time.sleep(0.3)
        puller.connect(S.bound_endpoint(block))
        got.append(puller.recv_multipart())

    t = threading.Thread(target=late_worker)
    t.start()
    block.send_multipart([b"frame", b"y"])  # waits for the worker
    t.join(5)
    assert got == [[b"frame", b"y"]]
    for s in (drop, block, puller):
        s.close(linger=0)


def test_maxmsgsize_refuses_an_oversized_message(ctx):
    st = _settings(max_point_bytes=1_000)
    api = S.open_socket(ctx, S.points_pull(st))
    st.points_endpoint = S.bound_endpoint(api)
    worker = S.open_socket(ctx, S.points_push(st))
    worker.send_multipart([b"points", b"x" * 5_000])  # the receiver drops the connection instead
    worker.send_multipart([b"points", b"small"])  # may follow on the sender's reconnection, or be lost
    worker2 = S.open_socket(ctx, S.points_push(st))
    worker2.send_multipart([b"points", b"ok"])
    got = []
    while api.poll(1000):
        got.append(api.recv_multipart())
    assert [b"points", b"ok"] in got  # the receiver goes on
    assert all(len(p) <= 1_000 for m in got for p in m), "an oversized message reached the application"
    assert set(map(tuple, got)) <= {(b"points", b"ok"), (b"points", b"small")}
    for s in (api, worker, worker2):
        s.close(linger=0)


def test_endpoint_report_round_trip_and_timeouts(tmp_path):
    path = tmp_path / "ep.json"
    S.report_endpoints(None, {"x": "y"})  # no file asked for: nothing written
    S.report_endpoints(path, {"frames_endpoint": "tcp://127.0.0.1:40000"})
    assert S.wait_for_endpoints(path, 1) == {"frames_endpoint": "tcp://127.0.0.1:40000"}
    assert [p.name for p in tmp_path.iterdir()] == ["ep.json"]  # written aside, then renamed
    with pytest.raises(TimeoutError, match="exited"):
        S.wait_for_endpoints(tmp_path / "none.json", 10, alive=lambda: False)
    with pytest.raises(TimeoutError, match="no endpoints"):
        S.wait_for_endpoints(tmp_path / "none.json", 0.1)
