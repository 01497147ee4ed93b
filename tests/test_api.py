"""services.api in-process: the point store (injected clock), the receiver on a real socket bound
to port 0, and the HTTP endpoints through FastAPI's TestClient (no subprocess)."""

from __future__ import annotations

import time

import msgpack
import pytest
import zmq
from fastapi.testclient import TestClient
from msgspec import to_builtins

from mtcw_core.chain import FrameResult, TargetPoint
from services.api import Metrics, PointStore, create_app
from services.settings import ApiSettings
from services.wire import POINTS_TOPIC, encode_end, encode_points, end_message, point_from_result, rejected_point

T0_NS = 1_700_000_000_000_000_000


def _settings(**kw) -> ApiSettings:
    return ApiSettings(points_endpoint="tcp://127.0.0.1:0", reorder_timeout_s=1.0, **kw)


def _point(seq: int, source: str = "bench", run: int = 1, range_m: float = 1.5, t_ns: int | None = None):
    t = TargetPoint(range_m=range_m, range_sigma_m=1e-4, velocity_mps=0.0, velocity_sigma_mps=1e-3,
                    direction="static", snr_db=40.0, margin=0.5, tone_snr_db={"500000000": 40.0})
    res = FrameResult(status="ok", profile="fast", seq=seq, t_ns=T0_NS + seq if t_ns is None else t_ns,
                      source=source, targets=[t], unambiguous_range_m=3.0, stage_seconds={"extract": 0.002})
    return point_from_result(res, run=run, processing_s=0.003)


def _wait(cond, what: str, timeout_s: float = 10.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        out = cond()
        if out:
            return out
        time.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")


# ---------------------------------------------------------------------------------------------
class TestPointStore:
    def test_latency_is_trigger_to_arrival_by_the_store_clock(self):
        store = PointStore(_settings(), Metrics(), clock_ns=lambda: T0_NS + 25_000_000)
        store.add(_point(0, t_ns=T0_NS), now_mono=0.0)
        p = store.latest["bench"]
        assert p.latency_s == pytest.approx(0.025) and p.processing_s == 0.003

    def test_counts_add_up_in_order_with_drops_rejections_and_end(self):
        store = PointStore(_settings(), Metrics(), clock_ns=lambda: T0_NS)
        for s in (0, 2, 1, 4):
            store.add(_point(s), now_mono=0.0)
        store.add(rejected_point("", -1, 0, "malformed_bad_size: samples"), now_mono=0.0)
        store.end(end_message("bench", 1, frames=6, t_ns=T0_NS + 10, dropped=0), now_mono=0.0)
        store.poll(now_mono=2.0)
        snap = store.snapshot()
        assert [p.seq for p in store.history] == [0, 1, 2, 4]
        assert (snap["received"], snap["processed"], snap["rejected"], snap["dropped"]) == (5, 4, 1, 2)
        assert snap["received"] == snap["processed"] + snap["rejected"]


# ---------------------------------------------------------------------------------------------
class TestHttp:
    @pytest.fixture
    def client(self):
        app = create_app(_settings(), start_receiver=False, clock_ns=lambda: T0_NS + 10**6)
        with TestClient(app) as c:
            c.app_state = app.state
            yield c

    def test_bad_http_parameters_get_4xx_with_a_message(self, client):
        for params in ({"limit": 0}, {"limit": "many"}, {"since_seq": -5}, {"limit": 10**9}):
            r = client.get("/v1/points", params=params)
            assert r.status_code == 422 and r.json()["detail"], params
        r = client.get("/v1/points/latest", params={"source": "nope"})
        assert r.status_code == 404 and "no points" in r.json()["detail"]

    def test_points_are_served_as_json_with_latency(self, client):
        store = client.app_state.store
        for s in range(5):
            store.add(_point(s), now_mono=time.monotonic())
        store.add(_point(0, source="other", range_m=2.0), now_mono=time.monotonic())
        latest = client.get("/v1/points/latest").json()["points"]
        assert latest["bench"]["seq"] == 4 and latest["other"]["targets"][0]["range_m"] == 2.0
        one = client.get("/v1/points/latest", params={"source": "bench"}).json()
        assert one["latency_s"] == pytest.approx(1e-3 - 4e-9) and one["processing_s"] == 0.003
        assert "reason" not in one and one["targets"][0]["direction"] == "static"
        r = client.get("/v1/points", params={"since_seq": 1, "limit": 2, "source": "bench"}).json()
        assert [p["seq"] for p in r["points"]] == [2, 3] and r["more"] is True
        assert client.get("/readyz").status_code == 200
        h = client.get("/healthz").json()
        assert h["status"] == "alive" and h["receiver"] == {"state": "not_started"}


# ---------------------------------------------------------------------------------------------
class TestReceiver:
    @pytest.fixture
    def api(self):
        ctx = zmq.Context()
        app = create_app(_settings())
        with TestClient(app) as client:
            push = ctx.socket(zmq.PUSH)
            push.setsockopt(zmq.LINGER, 0)
            push.connect(app.state.receiver.endpoint)  # the port the receiver bound (port 0)
            yield client, push
            push.close()
        ctx.term()

    def test_malformed_points_are_counted_and_the_next_good_one_is_served(self, api):
        client, push = api
        good = to_builtins(_point(0))
        no_range = {**good, "targets": [{k: v for k, v in good["targets"][0].items() if k != "range_m"}]}
        text_range = {**good, "targets": [{**good["targets"][0], "range_m": "1.5 m"}]}
        for bad in (no_range, text_range, {**good, "source": ["bench"]}, {**good, "t_ns": "now"}):
            push.send_multipart([POINTS_TOPIC, msgpack.packb(bad)])
        push.send_multipart([b"points", b"\xc1 not msgpack"])
        push.send_multipart([b"end", msgpack.packb({"v": 1, "source": "bench"})])
        push.send_multipart(encode_points(_point(0)))
        latest = _wait(lambda: (r := client.get("/v1/points/latest")).status_code == 200 and r.json(), "the good point")
        assert latest["points"]["bench"]["seq"] == 0
        metrics = client.get("/metrics").text
        assert 'mtcw_messages_malformed_total{reason="missing_key"} 2.0' in metrics  # no range_m; the end's frames
        assert 'mtcw_messages_malformed_total{reason="bad_field"} 3.0' in metrics
        assert 'mtcw_messages_malformed_total{reason="bad_msgpack"} 1.0' in metrics
        h = client.get("/healthz")
        assert h.status_code == 200 and h.json()["status"] == "alive"
        recv = h.json()["receiver"]
        assert recv["state"] == "alive" and recv["malformed"] == 6 and "frames" in recv["last_error"]
        assert h.json()["received"] == 1

    def test_end_notice_through_the_socket_counts_the_lost_tail(self, api):
        client, push = api
        push.send_multipart(encode_points(_point(0)))
        push.send_multipart(encode_end(end_message("bench", 1, frames=3, t_ns=T0_NS + 5, dropped=0)))
        h = _wait(lambda: (j := client.get("/healthz").json())["dropped"] == 2 and j, "the tail counted", 10)
        assert (h["processed"], h["dropped"], h["awaited_after_end"]) == (1, 2, 0)

    def test_healthz_says_when_the_receiver_thread_is_dead(self, api):
        client, _ = api
        recv = client.app.state.receiver

        def broken(now_mono: float) -> None:
            raise RuntimeError("store poll broke")

        recv.store.poll = broken  # a bug outside message handling kills the thread
        _wait(lambda: not recv.is_alive(), "the receiver to die")
        h = client.get("/healthz")
        assert h.status_code == 503 and h.json()["status"] == "receiver_dead"
        assert h.json()["receiver"]["state"] == "dead" and "store poll broke" in h.json()["receiver"]["last_error"]
        assert client.get("/readyz").status_code == 503


def test_receiver_handle_never_raises():
    app = create_app(_settings(), start_receiver=False)
    from services.api import PointReceiver

    recv = PointReceiver(app.state.store, app.state.settings)
    try:
        for parts in ([], [b""], [b"points"], [b"points", b"", b""], [b"end", b"\x80"], [b"points", b"\x91\x01"]):
            assert recv.handle(parts, 0.0) == "malformed", parts
        assert recv.handle(encode_points(_point(0)), 0.0) == "point"
    finally:
        recv.sock.close()
