"""services/worker.py: one message in, one point out, whatever the message; the worker never dies of a frame."""

from __future__ import annotations

import os
import threading
import time

import msgspec
import numpy as np
import pytest
import zmq

from mtcw_core.simulate import simulate_frame
from services import sockets as S
from services.settings import WorkerSettings
from services.wire import FRAME_TOPIC, decode_points, encode_frame, encode_points, point_from_result
from services.worker import Worker

from .conftest import fast_mover_scene, make_scene


@pytest.fixture(scope="module")
def frame():
    return simulate_frame(make_scene(digitizer={"samples": 2**12}), seed=1).with_(source="bench", seq=7, t_ns=10**18)


@pytest.fixture
def worker(ctx):
    w = Worker(WorkerSettings(frames_endpoint="tcp://127.0.0.1:9", points_endpoint="tcp://127.0.0.1:9",
                              profile="fast"), ctx)
    yield w
    w.pull.close(linger=0)
    w.push.close(linger=0)


def _with_header(frame, **changes) -> list:
    """The frame's message with header keys replaced (a value of None deletes the key)."""
    topic, head, samples = encode_frame(frame)
    h = msgspec.msgpack.decode(head)
    for k, v in changes.items():
        if v is None:
            h.pop(k, None)
        else:
            h[k] = v
    return [topic, msgspec.msgpack.encode(h), bytes(samples)]


@pytest.mark.parametrize("changes, field", [
    ({"truth": [{}]}, "truth[0].range_m"),
    ({"truth": 5}, "truth"),
    ({"pulse": {"period_s": 1e-6, "duty": 0.5, "delay_s": "x"}}, "pulse.delay_s"),
    ({"tones_hz": ["a"]}, "tones_hz[0]"),
    ({"n": -1}, "n"),
    ({"fs_hz": float("nan")}, "fs_hz"),
])
def test_header_faults_that_once_killed_the_worker_become_rejected_points(worker, frame, changes, field):
    """A malformed ``truth`` or ``pulse.delay_s = "x"`` raised outside the wire contract and the
    worker exited (3.3 % of fuzzed frames); now each is a ``rejected`` point naming the field,
    with the frame's identity kept so the API counts it in order."""
    msg = worker.handle(_with_header(frame, **changes))
    assert msg.status == "rejected" and field in msg.reason and msg.reason.startswith("malformed_")
    assert (msg.source, msg.seq, msg.t_ns) == ("bench", 7, 10**18)


def test_garbage_without_identity_is_counted_not_ordered(worker):
    msg = worker.handle([FRAME_TOPIC, b"\xc1", b""])
    assert msg.status == "rejected" and msg.seq == -1 and msg.reason.startswith("malformed_bad_msgpack")


def test_a_chain_failure_is_a_rejected_point(worker, frame, monkeypatch):
    import services.worker as W

    def boom(*a, **k):
        raise RuntimeError("a bug")

    monkeypatch.setattr(W, "process_frame", boom)
    msg = worker.handle(encode_frame(frame))
    assert msg.status == "rejected" and msg.reason == "chain_error: RuntimeError: a bug" and msg.seq == 7


@pytest.mark.parametrize("fft", ["pocketfft", "pyfftw"])
def test_run_accounts_for_every_message_between_good_frames(ctx, frame, fft):
    """Good, malformed and good frames through a live worker: three points, in order, the worker alive;
    on either FFT backend (``MTCW_FFT_BACKEND``), scipy's default in force again once it stops."""
    from mtcw_core.dsp.spectrum import fft_backend

    if fft == "pyfftw":
        pytest.importorskip("pyfftw")
    push = S.open_socket(ctx, S.SocketSpec("t", zmq.PUSH, "tcp://127.0.0.1:0", True, 10, 0))
    pull = S.open_socket(ctx, S.SocketSpec("t", zmq.PULL, "tcp://127.0.0.1:0", True, 10, 0))
    w = Worker(WorkerSettings(frames_endpoint=S.bound_endpoint(push), points_endpoint=S.bound_endpoint(pull),
                              profile="fast", fft_backend=fft), ctx)
    stop = threading.Event()
    t = threading.Thread(target=w.run, args=(stop,))
    t.start()
    try:
        push.send_multipart(encode_frame(frame.with_(seq=0)))
        push.send_multipart(_with_header(frame.with_(seq=1), truth=[{}]))
        push.send_multipart(encode_frame(frame.with_(seq=2)))
        got = [decode_points(pull.recv_multipart()) if pull.poll(20_000) else None for _ in range(3)]
        assert [(p.seq, p.status) for p in got] == [(0, "ok"), (1, "rejected"), (2, "ok")]
        deadline = time.monotonic() + 5
        while w.sent < 3 and time.monotonic() < deadline:  # the count follows the send's return
            time.sleep(0.01)
        assert t.is_alive() and w.received == 3 and w.sent == 3
        assert np.isfinite(got[0].targets[0].range_m)
        assert fft_backend().startswith(fft if fft == "pyfftw" else "scipy default")
    finally:
        stop.set()
        t.join(10)
        push.close()
        pull.close()
    assert fft_backend() == "scipy default (pocketfft)"


def test_track_gives_each_sources_points_a_range_rate(ctx):
    """``--track K``: a source's points join one track and carry its range rate from the third
    frame on (on the wire too); another source's frames start their own track; K < 3 names ``track``."""
    from mtcw_core.scene import load_scene, scene_variant
    from mtcw_core.simulate import Simulator

    sc = scene_variant(load_scene("moving-target"), digitizer={"samples": 2**14})
    w = Worker(WorkerSettings(frames_endpoint="tcp://127.0.0.1:9", points_endpoint="tcp://127.0.0.1:9",
                              profile="fast", track=3), ctx)
    try:
        got = []
        for i, fr in enumerate(Simulator(sc, 2).frames(5)):
            msg = w.handle(list(encode_frame(fr.with_(source="a" if i != 2 else "b", seq=i))))
            got.append((msg.source, msg.targets[0].track_frames, msg.targets[0].range_rate_mps is not None))
        assert got == [("a", 1, False), ("a", 2, False), ("b", 1, False), ("a", 3, True), ("a", 3, True)], got
        t = decode_points(encode_points(msg)).targets[0]
        assert t.track_id == 1 and abs(t.range_rate_mps - 0.10) < 5 * t.range_rate_sigma_mps
    finally:
        w.pull.close(linger=0)
        w.push.close(linger=0)
    with pytest.raises(ValueError, match="track"):
        WorkerSettings(frames_endpoint="tcp://127.0.0.1:9", points_endpoint="tcp://127.0.0.1:9", track=2)


def test_accumulate_averages_each_sources_frames_and_says_how_many(ctx):
    """``--accumulate K``: a point per frame, resting on that source's last K frames (at most);
    a source's frames do not mix with another's; the point message carries ``accumulated_frames``."""
    from mtcw_core.scene import load_scene, scene_variant
    from mtcw_core.simulate import Simulator

    sc = scene_variant(load_scene("low-coherence"), targets=[{"loss_db": 60.0}], digitizer={"samples": 2**14})
    w = Worker(WorkerSettings(frames_endpoint="tcp://127.0.0.1:9", points_endpoint="tcp://127.0.0.1:9",
                              accumulate=3), ctx)
    try:
        got = []
        for i, fr in enumerate(Simulator(sc, 2).frames(5)):
            msg = w.handle(list(encode_frame(fr.with_(source="a" if i != 2 else "b", seq=i, t_ns=10**18 + i))))
            got.append((msg.source, msg.status, msg.targets[0].accumulated_frames if msg.targets else None))
        assert got == [("a", "ok", 1), ("a", "ok", 2), ("b", "ok", 1), ("a", "ok", 3), ("a", "ok", 3)], got
        truth = fr.truth[0].range_m
        t = msg.targets[0]
        assert abs(t.range_m - truth) < 5 * t.range_sigma_m and t.direction == "unknown"
        assert decode_points(encode_points(msg)).targets[0].accumulated_frames == 3
    finally:
        w.pull.close(linger=0)
        w.push.close(linger=0)
    with pytest.raises(ValueError, match="accumulate"):
        Worker(WorkerSettings(frames_endpoint="tcp://127.0.0.1:9", points_endpoint="tcp://127.0.0.1:9",
                              accumulate=3, technique="ab"), ctx)


def _blas_threads() -> dict[str, int]:
    from threadpoolctl import threadpool_info

    return {i["filepath"]: i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}


def test_limit_threads_sets_and_restores_the_blas_pools(monkeypatch):
    """``threads = 1`` puts every BLAS pool of the process at one thread; 0 leaves them alone; the
    limit is undone on restore (the worker's run ends)."""
    from services.worker import limit_threads

    before = _blas_threads()
    assert before, "numpy without a BLAS that threadpoolctl sees: nothing to limit"
    assert limit_threads(0) is None and _blas_threads() == before
    from services.worker import THREAD_VARS

    for var in THREAD_VARS:
        monkeypatch.delenv(var, raising=False)
    lim = limit_threads(1)
    try:
        assert set(_blas_threads().values()) == {1}
        assert all(os.environ[v] == "1" for v in THREAD_VARS)  # for a library that loads later
    finally:
        lim.restore_original_limits()
    assert _blas_threads() == before


def test_one_blas_thread_changes_no_result():
    """The chain's results with the BLAS pools at one thread are those with the libraries' default,
    to the last bit (issue 16: the worker's threads are a speed setting, not a numerical one);
    checked on a 2^16-sample frame with a moving target, `balanced`, where the products and
    solves of every stage run."""
    from threadpoolctl import threadpool_limits

    from mtcw_core.chain import get_profile, process_frame

    fr = simulate_frame(make_scene(digitizer={"samples": 2**16}, targets=[{"range_m": 1.7, "velocity_mps": 1.0, "loss_db": 20.0}]),
                        seed=3)
    chain = get_profile("balanced")
    default = process_frame(fr, chain, None)
    with threadpool_limits(limits=1):
        one = process_frame(fr, chain, None)
    assert default.status == "ok" and default.targets
    strip = lambda r: msgspec.to_builtins(  # noqa: E731 - everything but the stage times
        {k: v for k, v in msgspec.structs.asdict(point_from_result(r)).items() if k not in ("stage_seconds",)})
    assert strip(one) == strip(default)


def test_threads_setting_is_validated_naming_the_field(monkeypatch):
    monkeypatch.setenv("MTCW_THREADS", "-1")
    with pytest.raises(ValueError, match="threads"):
        WorkerSettings()
    monkeypatch.setenv("MTCW_THREADS", "2")
    assert WorkerSettings().threads == 2
    monkeypatch.delenv("MTCW_THREADS")
    assert WorkerSettings().threads == 1


def test_fft_backend_setting_is_validated_naming_the_field(monkeypatch):
    monkeypatch.setenv("MTCW_FFT_BACKEND", "mkl")
    with pytest.raises(ValueError, match="fft_backend"):
        WorkerSettings()
    monkeypatch.delenv("MTCW_FFT_BACKEND")
    assert WorkerSettings().fft_backend == "pocketfft"
    pytest.importorskip("pyfftw")
    monkeypatch.setenv("MTCW_FFT_BACKEND", "pyfftw")
    assert WorkerSettings().fft_backend == "pyfftw"


def test_a_worker_with_sideband_direction_says_which_way_one_photodiode_moves(ctx):
    """``sideband_direction`` reaches the worker's chain: a 47.9 m/s receding target on one
    photodiode (2^18 samples, 40 dB) is served ``receding``; by default ``unknown``."""
    from mtcw_core.simulate import Simulator

    sc = fast_mover_scene()
    fr = next(Simulator(sc, 4).frames(1)).with_(source="bench", seq=1, t_ns=10**18)
    for on, want in ((False, "unknown"), (True, "receding")):
        w = Worker(WorkerSettings(frames_endpoint="tcp://127.0.0.1:9", points_endpoint="tcp://127.0.0.1:9",
                                  sideband_direction=on), ctx)
        try:
            msg = w.handle(list(encode_frame(fr)))
            assert msg.status == "ok" and msg.targets[0].direction == want, msg
        finally:
            w.pull.close(linger=0)
            w.push.close(linger=0)


def test_the_workers_declared_tone_drift_reaches_the_chain(ctx, monkeypatch):
    """``MTCW_TONE_PHASE_SIGMA_RAD`` (or ``--tone-phase-sigma-rad``) is the chain's setting."""
    monkeypatch.setenv("MTCW_TONE_PHASE_SIGMA_RAD", "0.02")
    w = Worker(WorkerSettings(frames_endpoint="tcp://127.0.0.1:9", points_endpoint="tcp://127.0.0.1:9"), ctx)
    try:
        assert w.chain.tone_phase_sigma_rad == 0.02
    finally:
        w.pull.close(linger=0)
        w.push.close(linger=0)
