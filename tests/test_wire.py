"""services.wire: every codec's round trip, the schemas' checks, and total decoders (no sockets)."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from msgspec import to_builtins

from mtcw_core.chain import FrameResult, TargetPoint, process_frame
from mtcw_core.frame import Frame, PulseInfo, TruthTarget
from mtcw_core.simulate import simulate_frame
from services.wire import (END_TOPIC, FRAME_TOPIC, POINTS_TOPIC, VERSION, EndMessage, PointMessage,
                           TargetMessage, WireError, decode_end, decode_frame, decode_points, encode_end,
                           encode_frame, encode_points, end_message, frame_header, point_from_result,
                           rejected_point, rejection_point)

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
    h = to_builtins(frame_header(frame))
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
    point = rejection_point(err.value, mutate(frame))
    msg = to_builtins(point)
    assert msg["status"] == "rejected" and msg["reason"].startswith(f"malformed_{reason}")
    decode_points(encode_points(point))


def test_points_round_trip(frame):
    point = point_from_result(process_frame(frame), processing_s=0.01)
    msg = to_builtins(point)
    back = to_builtins(decode_points([bytes(p) for p in encode_points(point)]))
    assert back["v"] == VERSION and back["status"] == "ok"
    t = back["targets"][0]
    assert set(t) >= {"range_m", "range_sigma_m", "velocity_mps", "velocity_sigma_mps", "direction", "snr_db",
                      "margin"}
    assert t["range_m"] == pytest.approx(1.234, abs=5e-4)  # 12-bit codes, 4096 samples
    with pytest.raises(WireError, match="status"):
        decode_points([b"points", msgpack.packb({**msg, "status": "fine"})])


def test_end_message_round_trip_and_bad_fields():
    h = to_builtins(decode_end(encode_end(end_message("bench", 42, frames=60, t_ns=123, dropped=7))))
    assert (h["source"], h["run"], h["frames"], h["t_ns"], h["dropped"]) == ("bench", 42, 60, 123, 7)
    assert "run" not in to_builtins(decode_end(encode_end(end_message("bench", None, 1, 1, 0))))
    bad = [b"end", msgpack.packb({"v": VERSION, "source": "bench", "frames": -1, "t_ns": 0, "dropped": 0})]
    with pytest.raises(WireError, match="frames"):
        decode_end(bad)
    with pytest.raises(WireError) as err:
        decode_end([b"end"])
    assert err.value.reason == "bad_parts"




# ---------------------------------------------------------------------------------------------
# round trips of every codec, on small synthetic frames
def _synthetic(dtype="<i2", receiver="single", **kw) -> Frame:
    rng = np.random.default_rng(0)
    channels = ("i", "q", "pulse_ref") if receiver == "iq" else ("pd", "pulse_ref")
    x = rng.normal(0, 100, (len(channels), 64))
    samples = x.astype(dtype) if np.dtype(dtype).kind == "f" else np.clip(x, -100, 100).astype(dtype)
    base = dict(samples=samples, fs_hz=1e9, tones_hz=(1e8, 1.5e8), wavelength_m=1.55e-6, receiver=receiver,
                channels=channels, scale=0.01, offset=-0.5, seq=7, t_ns=123_456_789, source="scope-1", run=99)
    return Frame(**{**base, **kw})


@pytest.mark.parametrize("dtype", ["<f4", "<f8", "<i2", "i1", ">i2"])
@pytest.mark.parametrize("receiver", ["single", "iq"])
def test_frame_round_trip_every_dtype_and_receiver(dtype, receiver):
    fr = _synthetic(dtype, receiver, tone_phases_rad=(0.1, -0.2), pulse=PulseInfo(1e-6, 0.5, 2e-8),
                    truth=(TruthTarget(1.5, -0.25),), architecture="modulated_reference")
    back = decode_frame([bytes(p) for p in encode_frame(fr)])
    np.testing.assert_array_equal(back.samples, fr.samples)
    assert back.with_(samples=None) == fr.with_(samples=None)  # every other field, by the one mapping


def test_frame_header_keys_are_those_of_v1():
    keys = set(msgpack.unpackb(encode_frame(_synthetic())[1]))
    assert keys == {"v", "source", "seq", "t_ns", "fs_hz", "n", "dtype", "channels", "scale", "offset", "tones_hz",
                    "wavelength_m", "receiver", "run"}  # optional keys absent when the frame has no value
    full = _synthetic(tone_phases_rad=(0.0, 0.0), pulse=PulseInfo(1e-6, 0.5), truth=(TruthTarget(1.0, 0.0),),
                      architecture="modulated_reference")
    h = msgpack.unpackb(encode_frame(full)[1])
    assert set(h) - keys == {"tone_phases_rad", "pulse", "truth", "architecture"}
    assert h["pulse"] == {"period_s": 1e-6, "duty": 0.5, "delay_s": 0.0} and h["dtype"] == "<i2"


def test_a_frame_that_cannot_be_sent_is_refused_naming_the_field():
    with pytest.raises(WireError) as err:
        encode_frame(_synthetic(fs_hz=float("inf")))
    assert err.value.field == "fs_hz"
    with pytest.raises(WireError) as err:
        encode_frame(_synthetic("<u2"))
    assert err.value.field == "dtype"


def test_frame_header_cross_checks():
    for change, field in [({"tone_phases_rad": [0.0]}, "tone_phases_rad"), ({"channels": ["i", "q"]}, "channels"),
                          ({"n": 0}, "n"), ({"pulse": {"period_s": 1e-6, "duty": 2.0}}, "pulse.duty"),
                          ({"tones_hz": [1e8, -1.0]}, "tones_hz[1]"), ({"run": -1}, "run")]:
        with pytest.raises(WireError) as err:
            decode_frame(_with_header(_synthetic(), **change))
        assert err.value.field == field, change


def _result(**target) -> FrameResult:
    t = TargetPoint(range_m=1.5, range_sigma_m=1e-4, velocity_mps=-0.5, velocity_sigma_mps=1e-3,
                    direction="approaching", snr_db=np.float64(40.0), margin=0.3, near_edge=np.bool_(True),
                    tone_snr_db={"100000000": 41.0})
    for k, v in target.items():
        setattr(t, k, v)
    return FrameResult(status="ok", profile="fast", seq=3, t_ns=1_000, source="s", targets=[t],
                       unambiguous_range_m=3.0, stage_seconds={"extract": 0.01})


def test_point_round_trip_is_typed_and_keeps_v1_keys():
    p = point_from_result(_result(), run=5, processing_s=0.02)
    back = decode_points(encode_points(p))
    assert back == p and isinstance(back.targets[0], TargetMessage)
    assert back.targets[0].near_edge is True and back.tone_snr_db == {"100000000": 41.0}
    raw = msgpack.unpackb(encode_points(p)[1])
    assert set(raw) == {"v", "source", "seq", "t_ns", "status", "profile", "targets", "unambiguous_range_m",
                        "coarse_range_m", "stage_seconds", "run", "tone_snr_db", "processing_s"}
    assert raw["coarse_range_m"] is None  # required keys travel as nil when unknown
    assert set(raw["targets"][0]) == set(TargetMessage.__struct_fields__)  # every target key, always


def test_a_result_the_schema_refuses_becomes_a_counted_rejection():
    p = point_from_result(_result(velocity_sigma_mps=math.inf), run=5)
    assert p.status == "rejected" and p.seq == 3 and p.run == 5 and not p.targets
    assert p.reason.startswith("bad_result: targets[0].velocity_sigma_mps: must be a finite number")
    assert decode_points(encode_points(p)) == p


def test_rejection_point_keeps_what_is_readable_of_the_identity():
    h = {"v": 1, "source": "a", "seq": 4, "t_ns": "later", "run": 2}
    p = rejection_point(WireError("bad_field", "x", "t_ns"), [b"frame", msgpack.packb(h), b""])
    assert (p.source, p.seq, p.t_ns, p.run) == ("a", 4, 0, 2)
    p = rejection_point(WireError("bad_parts", "x"), [b"frame"])
    assert (p.source, p.seq, p.reason) == ("", -1, "malformed_bad_parts: x")
    assert rejected_point("a", 1, 5, "chain_error: boom").status == "rejected"


def _point_map(**change) -> dict:
    m = to_builtins(point_from_result(_result(), run=1))
    for path, v in change.items():
        *head, last = path.split("__")
        d = m
        for k in head:
            d = d[int(k)] if isinstance(d, list) else d[k]
        if v is KeyError:
            d.pop(last)
        else:
            d[last] = v
    return m


@pytest.mark.parametrize("change,reason,field", [
    ({"targets__0__range_m": KeyError}, "missing_key", "targets[0].range_m"),
    ({"targets__0__range_m": "far"}, "bad_field", "targets[0].range_m"),
    ({"targets__0__range_m": float("nan")}, "bad_field", "targets[0].range_m"),
    ({"targets__0__range_sigma_m": float("inf")}, "bad_field", "targets[0].range_sigma_m"),
    ({"targets__0__direction": "sideways"}, "bad_field", "targets[0].direction"),
    ({"targets__0__near_edge": 1}, "bad_field", "targets[0].near_edge"),
    ({"targets": "none"}, "bad_field", "targets"),
    ({"source": ["a", "b"]}, "bad_field", "source"),
    ({"t_ns": "yesterday"}, "bad_field", "t_ns"),
    ({"seq": -2}, "bad_field", "seq"),
    ({"seq": True}, "bad_field", "seq"),
    ({"status": "fine"}, "bad_field", "status"),
    ({"stage_seconds__extract": -1.0}, "bad_field", "stage_seconds[...]"),  # msgspec: a value of the map
    ({"unambiguous_range_m": KeyError}, "missing_key", "unambiguous_range_m"),
    ({"v": 2}, "bad_version", "v"),
    ({"v": KeyError}, "bad_version", "v"),
])
def test_malformed_points_are_refused_naming_the_field(change, reason, field):
    with pytest.raises(WireError) as err:
        decode_points([POINTS_TOPIC, msgpack.packb(_point_map(**change))])
    assert (err.value.reason, err.value.field) == (reason, field)
    assert field in str(err.value)


def test_end_message_checks():
    assert decode_end([END_TOPIC, msgpack.packb({"v": 1, "source": "s", "frames": 2, "t_ns": 1, "dropped": 0,
                                                 "extra_key": [1]})]) == end_message("s", None, 2, 1, 0)
    for change, field in [({"dropped": "none"}, "dropped"), ({"run": 1.5}, "run"), ({"source": None}, "source")]:
        m = {**to_builtins(end_message("s", 1, 2, 3, 0)), **change}
        with pytest.raises(WireError) as err:
            decode_end([END_TOPIC, msgpack.packb(m)])
        assert err.value.field == field


# ---------------------------------------------------------------------------------------------
# total decoders: anything in, a typed message or a WireError out (fuzzed in tests/test_fuzz.py)
_DECODERS = [(decode_frame, FRAME_TOPIC, 3), (decode_points, POINTS_TOPIC, 2), (decode_end, END_TOPIC, 2)]


def _total(decode, parts):
    try:
        out = decode(parts)
    except WireError as err:
        assert err.reason and str(err)
        return None
    assert isinstance(out, (Frame, PointMessage, EndMessage))
    return out


@pytest.mark.parametrize("which", _DECODERS)
def test_decoders_are_total_on_deep_nesting_and_odd_parts(which):
    decode, topic, n = which
    deep = b"\x81\xa1v" + b"\x91" * 100_000 + b"\x00"  # {"v": [[[[...]]]]}
    assert _total(decode, [topic, deep, *([b""] * (n - 2))]) is None
    for parts in ([], None, 42, [topic, "text", b""][:n], [topic, object(), b""][:n], [b"", b"", b""][:n]):
        assert _total(decode, parts) is None
