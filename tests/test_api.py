"""services.api in-process: the point store (injected clock), the receiver on a real socket bound
to port 0, and the HTTP endpoints through FastAPI's TestClient (no subprocess). The store's own
tests, and restarts of a real ``mtcw api`` process, are in ``tests/test_history.py``."""

from __future__ import annotations

import json
import re
import sqlite3
import subprocess
import threading
import time
from pathlib import Path

import msgpack
import pytest
import zmq
from fastapi.testclient import TestClient
from msgspec import to_builtins
from prometheus_client import generate_latest

from mtcw_core.chain import FrameResult, TargetPoint
from services.api import Metrics, PointStore, create_app
from services.settings import ApiSettings
from services.wire import POINTS_TOPIC, encode_end, encode_points, end_message, point_from_result, rejected_point

T0_NS = 1_700_000_000_000_000_000


def _settings(**kw) -> ApiSettings:
    """API settings on a free port; the store is the test's own, in memory (``MTCW_STORE_PATH`` from conftest)."""
    return ApiSettings(**{"points_endpoint": "tcp://127.0.0.1:0", "reorder_timeout_s": 1.0, **kw})


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
def _history(store: PointStore, **kw) -> list[dict]:
    docs, _, _ = store.db.points(kw.get("since_seq", -1), kw.get("limit", 10_000), kw.get("source"))
    return [json.loads(d) for d in docs]


@pytest.fixture
def store():
    stores = []

    def make(**kw) -> PointStore:
        clock = kw.pop("clock_ns", lambda: T0_NS)
        stores.append(PointStore(_settings(**kw), Metrics(), clock_ns=clock))
        return stores[-1]

    yield make
    for s in stores:
        s.close()


class TestPointStore:
    def test_latency_is_trigger_to_arrival_by_the_store_clock(self, store):
        st = store(clock_ns=lambda: T0_NS + 25_000_000)
        st.add(_point(0, t_ns=T0_NS), now_mono=0.0)
        assert "bench" not in st.latest  # shown once committed, not before
        st.flush()
        p = st.latest["bench"]
        assert p.latency_s == pytest.approx(0.025) and p.processing_s == 0.003

    def test_counts_add_up_in_order_with_drops_rejections_and_end(self, store):
        st = store()
        for s in (0, 2, 1, 4):
            st.add(_point(s), now_mono=0.0)
        st.add(rejected_point("", -1, 0, "malformed_bad_size: samples"), now_mono=0.0)
        st.end(end_message("bench", 1, frames=6, t_ns=T0_NS + 10, dropped=0), now_mono=0.0)
        st.poll(now_mono=2.0)
        st.flush()
        snap = st.snapshot()
        assert [p["seq"] for p in _history(st)] == [0, 1, 2, 4]
        assert (snap["received"], snap["processed"], snap["rejected"], snap["dropped"]) == (5, 4, 1, 2)
        assert snap["received"] == snap["processed"] + snap["rejected"]

    def test_what_is_shown_is_what_is_committed(self, store):
        """A commit that fails shows nothing new (no point a restart would take back), keeps the
        batch, says why in /readyz's store check, and the next commit writes it all."""
        st = store()
        st.add(_point(0), now_mono=0.0)
        st.flush()
        real_write = st.db.write

        def full_disk(*a, **kw):
            raise sqlite3.OperationalError("database or disk is full")

        st.db.write = full_disk
        for s in (1, 2):
            st.add(_point(s), now_mono=0.1)
        assert st.commit(now_mono=time.monotonic()) is False
        assert st.latest["bench"].seq == 0 and st.snapshot()["processed"] == 1
        ok, why = st.store_status(receiver_running=True)
        assert not ok and "disk is full" in why
        st.db.write = real_write
        assert st.commit(now_mono=time.monotonic()) is True
        assert st.latest["bench"].seq == 2 and [p["seq"] for p in _history(st)] == [0, 1, 2]
        assert st.store_status(receiver_running=True)[0]
        assert 'mtcw_store_errors_total{kind="commit"} 1.0' in generate_latest(st.m.registry).decode()

    def test_points_triggered_in_the_future_or_beyond_int64_are_refused(self, store):
        st = store(max_future_s=60.0)
        st.add(_point(0), now_mono=0.0)
        assert st.add(_point(1, t_ns=T0_NS + 61 * 10**9), now_mono=0.0) == "refused"
        assert st.add(_point(2**63), now_mono=0.0) == "refused"
        assert st.add(_point(1, t_ns=T0_NS + 59 * 10**9), now_mono=0.0) == "released"
        st.flush()
        assert st.snapshot()["received"] == 2
        text = generate_latest(st.m.registry).decode()
        assert 'mtcw_messages_malformed_total{reason="future_t_ns"} 1.0' in text
        assert 'mtcw_messages_malformed_total{reason="out_of_range"} 1.0' in text


# ---------------------------------------------------------------------------------------------
class TestHttp:
    @pytest.fixture
    def client(self):
        app = create_app(_settings(), start_receiver=False, clock_ns=lambda: T0_NS + 10**6)
        with TestClient(app) as c:
            c.app_state = app.state
            yield c

    def test_bad_http_parameters_get_4xx_with_a_message(self, client):
        for params in ({"limit": 0}, {"limit": "many"}, {"since_seq": -5}, {"limit": 10**9}, {"after": -1},
                       {"since_seq": 2**63}):
            r = client.get("/v1/points", params=params)
            assert r.status_code == 422 and r.json()["detail"], params
        r = client.get("/v1/points/latest", params={"source": "nope"})
        assert r.status_code == 404 and "no points" in r.json()["detail"]

    def test_points_are_served_as_json_with_latency(self, client):
        store = client.app_state.store
        for s in range(5):
            store.add(_point(s), now_mono=time.monotonic())
        store.add(_point(0, source="other", range_m=2.0), now_mono=time.monotonic())
        store.flush()
        latest = client.get("/v1/points/latest").json()["points"]
        assert latest["bench"]["seq"] == 4 and latest["other"]["targets"][0]["range_m"] == 2.0
        one = client.get("/v1/points/latest", params={"source": "bench"}).json()
        assert one["latency_s"] == pytest.approx(1e-3 - 4e-9) and one["processing_s"] == 0.003
        assert "reason" not in one and one["targets"][0]["direction"] == "static"
        r = client.get("/v1/points", params={"since_seq": 1, "limit": 2, "source": "bench"}).json()
        assert [p["seq"] for p in r["points"]] == [2, 3] and r["more"] is True
        r = client.get("/v1/points", params={"since_seq": 1, "limit": 2, "source": "bench", "after": r["next"]}).json()
        assert [p["seq"] for p in r["points"]] == [4] and r["more"] is False  # the next page, by the cursor
        pages, after = [], 0
        while True:  # every point, two at a time
            r = client.get("/v1/points", params={"limit": 2, "after": after}).json()
            pages += [(p["source"], p["seq"]) for p in r["points"]]
            if not r["more"]:
                break
            after = r["next"]
        assert pages == [("bench", s) for s in range(5)] + [("other", 0)]
        assert client.get("/readyz").status_code == 200
        h = client.get("/healthz").json()
        assert h["status"] == "alive" and h["receiver"] == {"state": "not_started"}

    def test_livez_always_and_readyz_lists_its_checks_when_verbose(self, client):
        assert client.get("/livez").status_code == 200 and client.get("/livez").json()["status"] == "alive"
        r = client.get("/readyz")
        assert r.status_code == 503 and r.json()["reason"] == "no frame yet" and "checks" not in r.json()
        for q in ("verbose", "verbose=1", "verbose=true", "verbose=YES"):
            checks = client.get(f"/readyz?{q}").json()["checks"]
            assert set(checks) == {"receiver", "store", "frames"}, q
            assert checks["store"]["ok"] and checks["receiver"]["ok"] and not checks["frames"]["ok"]
            assert checks["frames"]["why"] == "no frame yet"
        assert "checks" not in client.get("/readyz?verbose=0").json()
        assert client.get("/readyz?verbose=maybe").status_code == 422
        client.app_state.store.add(_point(0), now_mono=time.monotonic())
        client.app_state.store.flush()
        r = client.get("/readyz", params={"verbose": "1"})
        assert r.status_code == 200 and all(c["ok"] for c in r.json()["checks"].values())
        assert client.get("/livez").status_code == 200

    def test_readyz_fails_while_the_store_cannot_commit(self, client):
        store = client.app_state.store
        store.add(_point(0), now_mono=time.monotonic())
        store.flush()
        real_write = store.db.write
        store.db.write = lambda *a, **kw: (_ for _ in ()).throw(sqlite3.OperationalError("disk I/O error"))
        store.add(_point(1), now_mono=time.monotonic())
        store.flush()
        r = client.get("/readyz?verbose")
        assert r.status_code == 503 and "disk I/O error" in r.json()["reason"]
        assert not r.json()["checks"]["store"]["ok"] and r.json()["checks"]["frames"]["ok"]
        assert client.get("/livez").status_code == 200  # alive, not ready
        store.db.write = real_write
        store.flush()
        assert client.get("/readyz").status_code == 200

    def test_metrics_have_process_platform_gc_collectors_and_build_info(self, client):
        text = client.get("/metrics").text
        for name in ("process_cpu_seconds_total", "process_resident_memory_bytes", "python_info",
                     "python_gc_collections_total", "mtcw_store_points", "mtcw_store_commit_seconds_count"):
            assert name in text, name
        info = re.search(r'^mtcw_build_info\{commit="([^"]*)",python="([^"]*)",version="([^"]*)"\} 1.0$', text, re.M)
        assert info, text[-2000:]
        from importlib.metadata import version
        import platform

        assert info.group(3) == version("mtcw") and info.group(2) == platform.python_version()
        root = Path(__file__).resolve().parents[1]
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True)
        if head.returncode == 0:  # a checkout: the commit is read from .git (no git process)
            assert info.group(1) == head.stdout.strip()
        else:
            assert info.group(1) == "unknown"

    def test_a_stored_point_that_cannot_be_read_is_skipped_not_a_500(self, client):
        store = client.app_state.store
        for s in range(3):
            store.add(_point(s), now_mono=time.monotonic())
        store.flush()
        with sqlite3.connect(store.db.uri, uri=True) as db:  # damage the middle row behind the store's back
            db.execute("UPDATE points SET body = ? WHERE seq = 1", (b"\xa6source\xa4b\xffch",))
        r = client.get("/v1/points")
        assert r.status_code == 200 and [p["seq"] for p in r.json()["points"]] == [0, 2]
        assert 'mtcw_store_errors_total{kind="bad_row"} 1.0' in client.get("/metrics").text


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

    def test_invalid_utf8_is_refused_at_decode_and_never_stored(self, api):
        client, push = api
        good = msgpack.packb(to_builtins(_point(0)))
        for bad in (good.replace(b"bench", b"be\xffch"), good.replace(b"extract", b"extr\xed\xa0\x80t")):
            push.send_multipart([POINTS_TOPIC, bad])  # a bad source; a lone surrogate in a map key
        push.send_multipart(encode_points(_point(0)))
        _wait(lambda: client.get("/healthz").json()["processed"] == 1, "the good point")
        assert 'mtcw_messages_malformed_total{reason="bad_msgpack"} 2.0' in client.get("/metrics").text
        r = client.get("/v1/points")
        assert r.status_code == 200 and [p["source"] for p in r.json()["points"]] == ["bench"]

    def test_forged_seqs_and_end_notices_do_not_move_the_books(self, api):
        """One point with seq 2^62, an end notice with 10^15 frames and one of another run: each
        refused and counted; the real run goes on and its books are exact."""
        client, push = api
        for s in range(5):
            push.send_multipart(encode_points(_point(s)))
        _wait(lambda: client.get("/healthz").json()["processed"] == 5, "the first points")
        push.send_multipart(encode_points(_point(2**62, t_ns=T0_NS + 5)))
        push.send_multipart(encode_end(end_message("bench", 1, frames=10**15, t_ns=T0_NS + 10, dropped=0)))
        push.send_multipart(encode_end(end_message("bench", 77, frames=3, t_ns=T0_NS + 10**9, dropped=0)))
        for s in range(5, 10):
            push.send_multipart(encode_points(_point(s)))
        push.send_multipart(encode_end(end_message("bench", 1, frames=12, t_ns=T0_NS + 20, dropped=0)))
        h = _wait(lambda: (j := client.get("/healthz").json())["dropped"] == 2 and j, "the real tail counted", 10)
        assert (h["received"], h["processed"], h["rejected"], h["held_for_reordering"]) == (10, 10, 0, 0)
        assert [p["seq"] for p in client.get("/v1/points").json()["points"]] == list(range(10))
        text = client.get("/metrics").text
        for reason in ("seq_jump", "end_frames", "end_run"):
            assert f'mtcw_messages_malformed_total{{reason="{reason}"}} 1.0' in text, reason
        assert "mtcw_frames_dropped_total 2.0" in text  # 10 and 11, the real tail; nothing forged
        assert client.get("/readyz").status_code == 200

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


def test_a_dead_receiver_calls_on_death():
    died = []
    app = create_app(_settings(), on_receiver_death=died.append)
    with TestClient(app):
        recv = app.state.receiver

        def broken(now_mono: float) -> None:
            raise RuntimeError("store poll broke")

        recv.store.poll = broken
        _wait(lambda: died, "on_death")
    assert died == ["RuntimeError: store poll broke"]


def test_serve_ends_with_status_3_when_the_receiver_dies(monkeypatch):
    """Under serve (``mtcw api``) a dead receiver stops the server: the supervisor restarts it."""
    import services.api as api

    def broken(self, now_mono: float) -> None:
        raise RuntimeError("store poll broke")

    monkeypatch.setattr(api.PointStore, "poll", broken)
    out = []

    def run() -> None:
        try:
            api.serve(_settings(port=0))
            out.append(None)
        except SystemExit as e:
            out.append(e.code)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(30)
    assert out == [api.EXIT_RECEIVER_DEAD]


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
        app.state.store.close()


def test_an_unbindable_points_endpoint_is_a_settings_error_naming_the_field(ctx):
    from services.api import serve

    squatter = ctx.socket(zmq.PULL)
    port = squatter.bind_to_random_port("tcp://127.0.0.1")
    try:
        with pytest.raises(SystemExit, match=rf"^error: settings: points_endpoint: .*cannot bind tcp://127.0.0.1:{port}"):
            serve(_settings(points_endpoint=f"tcp://127.0.0.1:{port}", port=0))
    finally:
        squatter.close(linger=0)


def test_with_keys_a_stranger_pushing_points_is_refused_counted_and_never_served(tmp_path):
    from services.auth import CurveClient, apply_client, client_keys, make_keys, server_keys, stop_authenticator
    from services.sockets import open_socket, points_push

    keys = tmp_path / "k"
    make_keys(keys)
    st = _settings(curve_dir=keys)
    app = create_app(st)
    c = zmq.Context()
    try:
        with TestClient(app) as client:
            ep = app.state.receiver.endpoint
            stranger = c.socket(zmq.PUSH)
            pk, sk = zmq.curve_keypair()
            apply_client(stranger, CurveClient(pk, sk, server_keys(keys).public))
            stranger.connect(ep)
            stranger.send_multipart(encode_points(_point(0, range_m=9.99)))  # queued; the handshake fails
            worker = open_socket(c, points_push(_settings(curve_dir=keys, points_endpoint=ep)))
            worker.send_multipart(encode_points(_point(0, range_m=1.5)))
            _wait(lambda: client.get("/v1/points/latest").status_code == 200, "the allowed worker's point")
            _wait(lambda: 'mtcw_peers_refused_total{socket="points"}' in client.get("/metrics").text,
                  "the refusal counted")
            assert client.get("/v1/points/latest").json()["points"]["bench"]["targets"][0]["range_m"] == 1.5
            assert client.get("/healthz").json()["received"] == 1
            assert client_keys(keys, "worker").public in server_keys(keys).allowed
            for s in (stranger, worker):
                s.close(linger=0)
    finally:
        stop_authenticator(zmq.Context.instance())
        c.term()
