"""Wire format v1 round trips and rejections; reordering and gap counting (no sockets)."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from mtcw_core.chain import process_frame
from mtcw_core.simulate import simulate_frame
from services.ordering import GapCounter, Reorderer
from services.wire import (VERSION, WireError, decode_end, decode_frame, decode_points, encode_end, encode_frame,
                           encode_points, frame_header, result_message)
from services.worker import rejection_message

from .conftest import make_scene


@pytest.fixture(scope="module")
def frame():
    return simulate_frame(make_scene(digitizer={"samples": 2**12, "adc_bits": 12}))


def _parts(frame):
    return [bytes(p) for p in encode_frame(frame)]


def test_frame_round_trip_keeps_codes_and_metadata(frame):
    assert frame.samples.dtype == np.int16  # ADC codes travel as codes, with scale/offset
    back = decode_frame(_parts(frame))
    np.testing.assert_array_equal(back.samples, frame.samples)
    for key in ("fs_hz", "tones_hz", "wavelength_m", "receiver", "channels", "scale", "offset", "seq", "t_ns",
                "source", "truth"):
        assert getattr(back, key) == getattr(frame, key), key
    assert process_frame(back).targets[0].range_m == pytest.approx(process_frame(frame).targets[0].range_m)


def test_samples_part_is_zero_copy(frame):
    parts = encode_frame(frame)
    assert isinstance(parts[2], memoryview)
    assert np.shares_memory(np.frombuffer(parts[2], dtype=frame.samples.dtype), frame.samples)
    # and decoding wraps the received buffer instead of copying it
    buf = bytearray(bytes(parts[2]))
    back = decode_frame([parts[0], parts[1], buf])
    assert np.shares_memory(back.samples, np.frombuffer(buf, dtype=frame.samples.dtype))


def _with_header(frame, **change):
    h = frame_header(frame)
    for k, v in change.items():
        if v is KeyError:
            h.pop(k)
        else:
            h[k] = v
    p = _parts(frame)
    return [p[0], msgpack.packb(h), p[2]]


@pytest.mark.parametrize("mutate,reason", [
    (lambda f: [b"frame", b"\xc1\xff garbage", _parts(f)[2]], "bad_msgpack"),
    (lambda f: [b"frame", msgpack.packb([1, 2]), _parts(f)[2]], "bad_msgpack"),
    (lambda f: _with_header(f, v=2), "bad_version"),
    (lambda f: _with_header(f, fs_hz=KeyError), "missing_key"),
    (lambda f: _with_header(f, n=f.n + 1), "bad_size"),
    (lambda f: _with_header(f, dtype="<u4"), "bad_field"),
    (lambda f: _with_header(f, receiver="quantum"), "bad_field"),
    (lambda f: _with_header(f, fs_hz=float("nan")), "bad_field"),
    (lambda f: _parts(f)[:2], "bad_parts"),
    (lambda f: [b"frmae"] + _parts(f)[1:], "bad_topic"),
])
def test_malformed_frames_are_rejected_with_a_reason(frame, mutate, reason):
    with pytest.raises(WireError) as err:
        decode_frame(mutate(frame))
    assert err.value.reason == reason
    # the worker turns it into a rejected point the consumer can count
    msg = rejection_message(err.value, mutate(frame))
    assert msg["status"] == "rejected" and msg["reason"].startswith(f"malformed_{reason}")
    decode_points(encode_points(msg))


def test_points_round_trip(frame):
    msg = result_message(process_frame(frame), latency_s=0.01)
    back = decode_points([bytes(p) for p in encode_points(msg)])
    assert back["v"] == VERSION and back["status"] == "ok"
    t = back["targets"][0]
    assert set(t) >= {"range_m", "range_sigma_m", "velocity_mps", "velocity_sigma_mps", "direction", "snr_db",
                      "margin"}
    assert t["range_m"] == pytest.approx(1.234, abs=5e-4)  # 12-bit codes, 4096 samples
    with pytest.raises(WireError, match="status"):
        decode_points([b"points", msgpack.packb({**msg, "status": "fine"})])


# ---------------------------------------------------------------------------------------------
def _msg(seq, t_ns=None, source="s", run=None):
    m = {"source": source, "seq": seq, "t_ns": 1000 + seq if t_ns is None else t_ns}
    if run is not None:
        m["run"] = run
    return m


def test_reorderer_releases_in_order_exactly_once():
    out = []
    r = Reorderer(lambda m: out.append(m["seq"]), timeout_s=1.0)
    for s in [0, 2, 1, 4, 3, 5]:
        r.add(_msg(s), now=0.0)
    assert out == [0, 1, 2, 3, 4, 5] and r.dropped == 0 and r.held() == 0


def test_reorderer_counts_a_gap_after_the_timeout_and_ignores_the_late_point():
    out = []
    r = Reorderer(lambda m: out.append(m["seq"]), timeout_s=1.0)
    for s in [0, 1, 3, 4]:
        r.add(_msg(s), now=0.0)
    assert out == [0, 1]
    r.poll(now=0.5)
    assert out == [0, 1]
    r.poll(now=1.5)
    assert out == [0, 1, 3, 4] and r.dropped == 1
    assert r.add(_msg(2), now=2.0) == "stale"  # arrived after its slot was given up: not released
    assert r.add(_msg(4), now=2.0) == "stale"  # a repeat
    assert out == [0, 1, 3, 4] and r.stale == 2


def test_reorderer_gives_up_when_too_many_are_held():
    out = []
    r = Reorderer(lambda m: out.append(m["seq"]), timeout_s=100.0, max_held=3)
    for s in [0, 2, 3, 4, 5]:
        r.add(_msg(s), now=0.0)
    assert out == [0, 2, 3, 4, 5] and r.dropped == 1


def test_reorderer_follows_a_publisher_restart_and_refuses_old_frames():
    out = []
    r = Reorderer(lambda m: out.append((m["seq"], m["t_ns"])), timeout_s=1.0)
    for s in [0, 1, 2, 4]:
        r.add(_msg(s, t_ns=100 + s, run=7), now=0.0)
    # a new run (new id, later trigger); its seq 1 overtakes its seq 0 (two workers)
    assert r.add(_msg(1, t_ns=501, run=8), now=0.1) == "restart"
    r.add(_msg(0, t_ns=500, run=8), now=0.1)
    assert r.add(_msg(3, t_ns=103, run=7), now=0.1) == "stale"  # the previous run's frame, late: not new
    assert r.add(_msg(2, t_ns=502, run=8), now=0.1) == "released"
    assert out == [(0, 100), (1, 101), (2, 102), (4, 104), (0, 500), (1, 501), (2, 502)]
    assert r.restarts == 1 and r.dropped == 1  # seq 3 of the old run never made it in time


def test_reorderer_without_run_ids_detects_restart_from_time():
    out = []
    r = Reorderer(lambda m: out.append(m["seq"]), timeout_s=1.0)
    for s in range(5):
        r.add(_msg(s, t_ns=100 + s), now=0.0)
    assert r.add(_msg(0, t_ns=500), now=0.1) == "restart"
    assert r.add(_msg(1, t_ns=102), now=0.1) == "stale"
    assert out == [0, 1, 2, 3, 4, 0]


def test_reorderer_counts_the_lost_tail_of_a_run_after_its_end_notice():
    out = []
    r = Reorderer(lambda m: out.append(m["seq"]), timeout_s=1.0)
    for s in [0, 1, 2, 4]:  # 3 is late, 5..9 never come
        r.add(_msg(s, run=7), now=0.0)
    assert r.end("s", 7, frames=10, t_ns=2000, now=0.2) == "ended"
    assert r.awaited() == 6 and r.dropped == 0  # 3 and 5..9
    r.add(_msg(3, run=7), now=0.5)
    r.poll(now=1.0)
    assert r.dropped == 0  # the timeout counts from the notice
    r.poll(now=1.3)
    assert out == [0, 1, 2, 3, 4] and r.dropped == 5 and r.awaited() == 0
    assert r.add(_msg(7, run=7), now=1.4) == "stale"  # a tail frame after its slot was given up
    assert r.end("s", 3, frames=4, t_ns=50, now=1.5) == "stale"  # an older run's notice changes nothing
    assert r.dropped == 5


def test_reorderer_end_notice_of_a_run_it_never_saw_counts_every_frame():
    r = Reorderer(lambda m: None, timeout_s=1.0)
    r.add(_msg(0, t_ns=100, run=1), now=0.0)
    assert r.end("s", 2, frames=3, t_ns=900, now=0.1) == "ended"  # new run: none of its frames came
    r.poll(now=1.2)
    assert r.dropped == 3 and r.restarts == 1


def test_end_message_round_trip_and_bad_fields():
    h = decode_end(encode_end("bench", 42, frames=60, t_ns=123, dropped=7))
    assert (h["source"], h["run"], h["frames"], h["t_ns"], h["dropped"]) == ("bench", 42, 60, 123, 7)
    assert "run" not in decode_end(encode_end("bench", None, 1, 1, 0))
    bad = [b"end", msgpack.packb({"v": VERSION, "source": "bench", "frames": -1, "t_ns": 0, "dropped": 0})]
    with pytest.raises(WireError, match="frames"):
        decode_end(bad)
    with pytest.raises(WireError) as err:
        decode_end([b"end"])
    assert err.value.reason == "bad_parts"


def test_gap_counter():
    g = GapCounter()
    gaps = [g.see("a", s) for s in [5, 6, 9, 10, 0, 1]]  # 0 after 10: restart, re-sync
    assert gaps == [0, 0, 2, 0, 0, 0] and g.dropped == 2 and g.received == 6
