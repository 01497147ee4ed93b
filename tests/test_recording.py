"""mtcw_core.recording: SigMF round trips, a total reader (every malformed metadata file refused
with a RecordingError naming the file and key; fuzzed), a writer that refuses malformed frames,
and a recording that survives its recorder being SIGKILLed."""

from __future__ import annotations

import copy
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given
from hypothesis import settings as hsettings
from hypothesis import strategies as st

from mtcw_core.frame import Frame, PulseInfo, TruthTarget
from mtcw_core.recording import U64_MAX, RecordingError, RecordingWriter, read_recording
from mtcw_core.scene import load_scene, scene_variant
from mtcw_core.simulate import Simulator
from services.wire import decode_frame, encode_frame

ROOT = Path(__file__).resolve().parents[1]
# a fixture shared by every example of a Hypothesis test is fine here: each example rewrites the
# files (the loaded profile, ci or long, still decides how many examples run)
FIXTURE_OK = hsettings(suppress_health_check=[*hsettings.default.suppress_health_check,
                                              HealthCheck.function_scoped_fixture])


def _frame(dtype="<i2", receiver="single", seq=0, n=16, **kw) -> Frame:
    channels = ("i", "q", "pulse_ref") if receiver == "iq" else ("pd", "pulse_ref")
    x = np.arange(len(channels) * n).reshape(len(channels), n) - 20
    base = dict(samples=x.astype(dtype), fs_hz=2e9, tones_hz=(1e8, 3e8), wavelength_m=1.064e-6, receiver=receiver,
                channels=channels, scale=0.5 if np.dtype(dtype).kind == "i" else 1.0, offset=0.0,
                tone_phases_rad=(0.5, -0.5), pulse=PulseInfo(1e-6, 0.25, 1e-8), seq=seq,
                t_ns=1_700_000_000_123_456_000 + seq * 1000, source="bench", truth=(TruthTarget(2.0, 0.5),))
    return Frame(**{**base, **kw})


def _write(prefix: Path, frames, **kw) -> Path:
    with RecordingWriter(prefix, **kw) as w:
        for fr in frames:
            w.write(fr)
    return prefix


def _same(a: Frame, b: Frame) -> None:
    """Equal samples (values and dtype) and fields; a recording does not keep ``run``."""
    np.testing.assert_array_equal(a.samples, b.samples)
    assert a.samples.dtype == b.samples.dtype.newbyteorder("=")
    assert a.with_(samples=None, run=None) == b.with_(samples=None, run=None)


# ---------------------------------------------------------------------------------------------
# round trips
@pytest.mark.parametrize("dtype", ["<f4", "<f8", "<i2", ">i2", "i1"])
@pytest.mark.parametrize("receiver", ["single", "iq"])
def test_sigmf_round_trip_through_the_mapping(tmp_path, dtype, receiver):
    frames = [_frame(dtype, receiver, seq=s) for s in range(3)]
    rec = read_recording(_write(tmp_path / "rec", frames))
    assert len(rec) == 3
    for fr, back in zip(frames, rec):
        _same(back, fr)


def test_sigmf_itself_reads_what_we_write(tmp_path):
    import sigmf

    frames = [_frame("<i2", "iq", seq=s) for s in range(2)]
    _write(tmp_path / "rec", frames)
    sf = sigmf.fromfile(str(tmp_path / "rec.sigmf-meta"), autoscale=False)  # checks core:sha512
    sf.validate()
    assert sf.get_global_field("core:num_channels") == 2 and len(sf.get_captures()) == 2
    x = sf.read_samples()  # (samples, SigMF channels), complex
    np.testing.assert_array_equal(x[:16, 0], frames[0].samples[0] + 1j * frames[0].samples[1])
    np.testing.assert_array_equal(x[16:, 1], frames[1].samples[2])


def test_a_recording_refuses_a_frame_unlike_the_first(tmp_path):
    with pytest.raises(RecordingError, match="pulse differs"):
        with RecordingWriter(tmp_path / "rec") as w:
            w.write(_frame())
            w.write(_frame(seq=1, pulse=None))
    rec = read_recording(tmp_path / "rec")  # closed by the with: the first frame is there
    assert len(rec) == 1 and rec.frame(0).pulse is not None


def test_nanoseconds_and_float_scale_survive(tmp_path):
    """Sub-microsecond trigger times are written with 9 digits; a float frame's scale/offset are kept."""
    fr = _frame("<f4", t_ns=1_700_000_000_123_456_789, scale=2.0, offset=-0.25)
    back = read_recording(_write(tmp_path / "rec", [fr])).frame(0)
    assert back.t_ns == fr.t_ns and (back.scale, back.offset) == (2.0, -0.25)
    np.testing.assert_array_equal(back.volts("pd"), fr.volts("pd"))


def test_frame_index(tmp_path):
    rec = read_recording(_write(tmp_path / "rec", [_frame(seq=s) for s in range(3)]))
    assert rec.frame(-1).seq == 2 and rec.frame(-3).seq == 0
    for bad in (3, -4):
        with pytest.raises(IndexError):
            rec.frame(bad)


_finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
_positive = st.floats(min_value=1e-30, max_value=1e300)


@st.composite
def _frames(draw) -> list[Frame]:
    """2 frames of random but valid fields, as the wire allows them."""
    dtype = draw(st.sampled_from(["<f4", "<f8", "<i2", ">i2", "i1"]))
    receiver = draw(st.sampled_from(["single", "balanced", "iq"]))
    extra = draw(st.lists(st.sampled_from(["pulse_ref", "ref", "x"]), max_size=3, unique=True))
    channels = (("i", "q") if receiver == "iq" else ("pd",)) + tuple(extra)
    n = draw(st.integers(1, 64))
    tones = draw(st.lists(_positive, max_size=5))
    fields = dict(
        fs_hz=draw(st.floats(min_value=1e-30, max_value=1e12)), tones_hz=tuple(tones), wavelength_m=draw(_positive), receiver=receiver,
        channels=channels, scale=draw(_finite), offset=draw(_finite),
        tone_phases_rad=draw(st.none() | st.lists(_finite, min_size=len(tones), max_size=len(tones)).map(tuple)),
        pulse=draw(st.none() | st.builds(PulseInfo, _positive, st.floats(min_value=1e-9, max_value=1.0), _finite)),
        architecture=draw(st.sampled_from(["unmodulated_lo", "modulated_reference"])),
        source=draw(st.text(max_size=12)), run=draw(st.none() | st.integers(0, U64_MAX)))
    info = np.iinfo(dtype) if np.dtype(dtype).kind == "i" else np.finfo(dtype)
    out = []
    for k in range(2):
        values = draw(st.lists(st.integers(-100, 100), min_size=len(channels) * n, max_size=len(channels) * n))
        x = np.clip(np.array(values, dtype=float) * (1.0 if np.dtype(dtype).kind == "i" else 0.37), info.min, info.max)
        truth = draw(st.none() | st.lists(st.builds(TruthTarget, _finite, _finite), max_size=3).map(tuple))
        out.append(Frame(samples=x.reshape(len(channels), n).astype(dtype), seq=draw(st.integers(0, U64_MAX)),
                         t_ns=draw(st.integers(0, U64_MAX)), truth=truth, **fields))
    return out


@FIXTURE_OK
@given(frames=_frames())
def test_round_trip_of_any_valid_frames(tmp_path, frames):
    rec = read_recording(_write(tmp_path / "rec", frames))
    assert len(rec) == len(frames)
    for fr, back in zip(frames, rec):
        _same(back, fr)


# ---------------------------------------------------------------------------------------------
# the reader: malformed metadata, one case per rule
@pytest.fixture(scope="module")
def base(tmp_path_factory) -> tuple[dict, bytes]:
    """A valid recording's metadata and data: int16, pd + pulse_ref, pulse, phases, truth; 3 frames."""
    prefix = _write(tmp_path_factory.mktemp("base") / "rec", [_frame(seq=s) for s in range(3)])
    return (json.loads(prefix.with_suffix(".sigmf-meta").read_text()),
            prefix.with_suffix(".sigmf-data").read_bytes())


def _g(key, value):
    def f(m):
        if value is _DROP:
            del m["global"][key]
        else:
            m["global"][key] = value
        return m
    return f


def _c(i, key, value):
    def f(m):
        if value is _DROP:
            del m["captures"][i][key]
        else:
            m["captures"][i][key] = value
        return m
    return f


def _top(key, value):
    def f(m):
        m[key] = value
        return m
    return f


_DROP = object()
NAN, INF = float("nan"), float("inf")

#: name -> (change to a valid metadata dict, or the whole file as bytes; what the message must name)
MALFORMED = {
    "frame_samples_not_an_integer": (_g("mtcw:frame_samples", "abc"), "global.mtcw:frame_samples: "),
    "frame_samples_zero": (_g("mtcw:frame_samples", 0), "global.mtcw:frame_samples: "),
    "frame_samples_fractional": (_g("mtcw:frame_samples", 16.5), "global.mtcw:frame_samples: "),
    "frame_samples_missing": (_g("mtcw:frame_samples", _DROP), "global.mtcw:frame_samples: "),
    "sample_start_negative": (_c(0, "core:sample_start", -1), "captures.0.core:sample_start: "),
    "sample_start_not_an_integer": (_c(1, "core:sample_start", 16.0), "captures.1.core:sample_start: "),
    "sample_start_missing": (_c(1, "core:sample_start", _DROP), "captures.1.core:sample_start: "),
    "sample_start_beyond_the_data": (_c(2, "core:sample_start", 10**6), "captures.2.core:sample_start = 1000000"),
    "captures_overlap": (_c(1, "core:sample_start", 1), "captures.1.core:sample_start: 1 overlaps"),
    "unknown_mtcw_key_in_global": (_g("mtcw:tone_phase_rad", [0.0, 0.0]), "global.mtcw:tone_phase_rad: unknown"),
    "unknown_mtcw_key_in_capture": (_c(0, "mtcw:sequence", 1), "captures.0.mtcw:sequence: unknown"),
    "top_level_list": (lambda m: [m], "Input should be an object"),
    "global_not_a_map": (_top("global", [1, 2]), "global: Input should be an object"),
    "global_missing": (lambda m: {"captures": m["captures"]}, "global: Field required"),
    "captures_not_a_list": (_top("captures", {"0": {}}), "captures: Input should be a valid"),
    "captures_empty": (_top("captures", []), "captures: List should have at least 1 item"),
    "capture_not_a_map": (lambda m: {**m, "captures": [m["captures"][0], 5]}, "captures.1: Input should be an object"),
    "datetime_garbage": (_c(0, "core:datetime", "yesterday"), "captures.0.core:datetime: not a UTC time"),
    "datetime_february_30": (_c(0, "core:datetime", "2026-02-30T00:00:00Z"), "captures.0.core:datetime: "),
    "datetime_hour_24": (_c(0, "core:datetime", "2026-01-01T24:00:00.5Z"), "captures.0.core:datetime: "),
    "datetime_before_1970": (_c(0, "core:datetime", "1969-12-31T23:59:59.999Z"), "captures.0.core:datetime: "),
    "datetime_not_utc": (_c(0, "core:datetime", "2026-01-01T00:00:00+01:00"), "captures.0.core:datetime: "),
    "datetime_a_number": (_c(0, "core:datetime", 1.7e9), "captures.0.core:datetime: must be a string"),
    "seq_negative": (_c(0, "mtcw:seq", -1), "captures.0.mtcw:seq: "),
    "seq_a_string": (_c(0, "mtcw:seq", "3"), "captures.0.mtcw:seq: "),
    "seq_beyond_uint64": (_c(2, "mtcw:seq", 2**64), "captures.2.mtcw:seq: "),
    "seq_a_bool": (_c(0, "mtcw:seq", True), "captures.0.mtcw:seq: "),
    "truth_not_a_list": (_c(0, "mtcw:truth", {"range_m": 1.0, "velocity_mps": 0.0}), "captures.0.mtcw:truth: "),
    "truth_without_range": (_c(1, "mtcw:truth", [{"velocity_mps": 0.0}]), "captures.1.mtcw:truth.0.range_m: "),
    "truth_nan": (_c(0, "mtcw:truth", [{"range_m": 1.0, "velocity_mps": NAN}]),
                  "captures.0.mtcw:truth.0.velocity_mps: Input should be a finite number"),
    "truth_unknown_key": (_c(0, "mtcw:truth", [{"range_m": 1.0, "velocity_mps": 0.0, "loss_db": 3}]),
                          "captures.0.mtcw:truth.0.loss_db: "),
    "sample_rate_nan": (_g("core:sample_rate", NAN), "global.core:sample_rate: Input should be a finite number"),
    "sample_rate_infinite": (_g("core:sample_rate", INF), "global.core:sample_rate: "),
    "sample_rate_zero": (_g("core:sample_rate", 0), "global.core:sample_rate: Input should be greater than 0"),
    "sample_rate_negative": (_g("core:sample_rate", -5e9), "global.core:sample_rate: "),
    "sample_rate_a_string": (_g("core:sample_rate", "5e9"), "global.core:sample_rate: "),
    "tones_not_a_list": (_g("mtcw:tones_hz", 5e8), "global.mtcw:tones_hz: "),
    "tone_zero": (_g("mtcw:tones_hz", [0.0, 3e8]), "global.mtcw:tones_hz.0: "),
    "tone_phases_too_few": (_g("mtcw:tone_phases_rad", [0.0]), "global.mtcw:tone_phases_rad: 1 phases for 2 tones"),
    "wavelength_negative": (_g("mtcw:wavelength_m", -1e-6), "global.mtcw:wavelength_m: "),
    "wavelength_missing": (_g("mtcw:wavelength_m", _DROP), "global.mtcw:wavelength_m: Field required"),
    "receiver_unknown": (_g("mtcw:receiver", "quad"), "global.mtcw:receiver: "),
    "receiver_iq_with_a_real_datatype": (_g("mtcw:receiver", "iq"), "global.mtcw:receiver: receiver 'iq' needs"),
    "channels_empty": (_g("mtcw:channels", []), "global.mtcw:channels: "),
    "channels_not_a_list": (_g("mtcw:channels", "pd"), "global.mtcw:channels: "),
    "channels_repeated": (_g("mtcw:channels", ["pd", "pd"]), "global.mtcw:channels: channel names must be distinct"),
    "channels_without_pd": (_g("mtcw:channels", ["x", "pulse_ref"]), "global.mtcw:channels: receiver 'single'"),
    "channel_name_empty": (_g("mtcw:channels", ["pd", ""]), "global.mtcw:channels.1: "),
    "pulse_duty_above_one": (_g("mtcw:pulse", {"period_s": 1e-6, "duty": 1.5}), "global.mtcw:pulse.duty: "),
    "pulse_misspelt_key": (_g("mtcw:pulse", {"period_s": 1e-6, "duty": 0.2, "dealy_s": 0.0}),
                           "global.mtcw:pulse.dealy_s: "),
    "pulse_not_a_map": (_g("mtcw:pulse", 5), "global.mtcw:pulse: "),
    "scale_a_string": (_g("mtcw:scale", "0.5"), "global.mtcw:scale: "),
    "scale_missing_for_integer_codes": (_g("mtcw:scale", _DROP), "global.mtcw:scale: required"),
    "offset_nan": (_g("mtcw:offset", NAN), "global.mtcw:offset: "),
    "num_channels_a_string": (_g("core:num_channels", "2"), "global.core:num_channels: "),
    "num_channels_mismatch": (_g("core:num_channels", 3), "global.core:num_channels: 3, but"),
    "datatype_unsupported": (_g("core:datatype", "cu32_le"), "global.core:datatype: "),
    "datatype_missing": (_g("core:datatype", _DROP), "global.core:datatype: Field required"),
    "architecture_unknown": (_g("mtcw:architecture", "fmcw"), "global.mtcw:architecture: "),
    "source_not_a_string": (_g("mtcw:source", 5), "global.mtcw:source: "),
    "non_conforming_dataset": (_g("core:dataset", "scope.bin"), "global.core:dataset: non-conforming"),
    "trailing_bytes": (_g("core:trailing_bytes", 16), "global.core:trailing_bytes: "),
    "metadata_only": (_g("core:metadata_only", True), "global.core:metadata_only: "),
    "header_bytes": (_c(0, "core:header_bytes", 8), "captures.0.core:header_bytes: "),
    "not_utf8": (lambda m: b"\xff\xfe" + json.dumps(m).encode("utf-16-le"), "Invalid JSON"),
    "latin1_string": (lambda m: json.dumps(m).replace('"bench"', '"b\u00e9nch"').encode("latin-1"), "Invalid JSON"),
    "not_json": (lambda m: json.dumps(m).encode()[:-7], "Invalid JSON"),
    "empty_file": (lambda m: b"", "Invalid JSON"),
    "deep_nesting": (lambda m: b"[" * 100_000 + b"]" * 100_000, "Invalid JSON"),
}


def _meta_bytes(m) -> bytes:
    return m if isinstance(m, bytes) else json.dumps(m).encode()  # NaN and inf as JSON's NaN/Infinity


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_metadata_is_refused_naming_the_key(tmp_path, base, case):
    meta, data = base
    change, named = MALFORMED[case]
    (tmp_path / "r.sigmf-meta").write_bytes(_meta_bytes(change(copy.deepcopy(meta))))
    (tmp_path / "r.sigmf-data").write_bytes(data)
    with pytest.raises(RecordingError) as err:
        read_recording(tmp_path / "r")
    msg = str(err.value)
    assert msg.startswith(str(tmp_path / "r.sigmf-")), msg  # names the file
    assert named in msg, msg


def test_the_cases_start_from_a_valid_recording(tmp_path, base):
    """Each case above fails because of its change alone: the unchanged files read."""
    meta, data = base
    (tmp_path / "r.sigmf-meta").write_bytes(_meta_bytes(meta))
    (tmp_path / "r.sigmf-data").write_bytes(data)
    assert len(list(read_recording(tmp_path / "r"))) == 3


def test_keys_of_other_namespaces_and_unused_core_keys_are_accepted(tmp_path, base):
    meta, data = base
    m = copy.deepcopy(meta)
    m["global"] |= {"acme:gain_db": 3, "core:geolocation": {"type": "Point", "coordinates": [6.9, 50.9]},
                    "core:trailing_bytes": 0, "core:metadata_only": False}
    m["captures"][0] |= {"acme:note": [1, 2], "core:frequency": 1e9, "core:header_bytes": 0}
    m["annotations"] = [{"core:sample_start": 0, "acme:x": "y"}]
    m["acme:top"] = {}
    (tmp_path / "r.sigmf-meta").write_text(json.dumps(m))
    (tmp_path / "r.sigmf-data").write_bytes(data)
    rec = read_recording(tmp_path / "r")
    assert [f.seq for f in rec] == [0, 1, 2]


def test_optional_keys_absent_take_their_defaults(tmp_path, base):
    meta, data = base
    m = copy.deepcopy(meta)
    for key in ("mtcw:receiver", "mtcw:architecture", "mtcw:pulse", "mtcw:tone_phases_rad", "mtcw:source",
                "mtcw:offset", "core:num_channels"):
        del m["global"][key]
    m["global"]["mtcw:channels"] = ["pd"]
    m["global"]["mtcw:frame_samples"] = 32  # the data file's 2-channel samples read as 1 channel
    m["captures"] = [{"core:sample_start": 0}, {"core:sample_start": 32, "mtcw:seq": 7}]
    (tmp_path / "r.sigmf-meta").write_text(json.dumps(m))
    (tmp_path / "r.sigmf-data").write_bytes(data)
    a, b = read_recording(tmp_path / "r")
    assert (a.receiver, a.channels, a.architecture, a.pulse, a.tone_phases_rad, a.offset) == (
        "single", ("pd",), "unmodulated_lo", None, None, 0.0)
    assert (a.seq, a.t_ns, a.source, a.truth, b.seq) == (0, 0, "r", None, 7)


def test_missing_unreadable_and_truncated_files(tmp_path, base):
    meta, data = base
    p = tmp_path / "r"
    with pytest.raises(RecordingError, match=r"r\.sigmf-meta: no such metadata file"):
        read_recording(p)
    (tmp_path / "r.sigmf-meta").write_text(json.dumps(meta))
    with pytest.raises(RecordingError, match=r"r\.sigmf-data: no such data file"):
        read_recording(p)
    (tmp_path / "r.sigmf-data").mkdir()
    with pytest.raises(RecordingError, match=r"r\.sigmf-data: not a regular file"):
        read_recording(p)
    (tmp_path / "r.sigmf-data").rmdir()
    (tmp_path / "r.sigmf-data").write_bytes(data[:-1])  # the last frame lacks a byte
    with pytest.raises(RecordingError, match=r"r\.sigmf-data: truncated: .*captures\.2\.core:sample_start"):
        read_recording(p)
    (tmp_path / "r.sigmf-data").write_bytes(data + b"\0" * 5)  # more data than claimed: a killed writer's tail
    rec = read_recording(p)
    (tmp_path / "r.sigmf-data").write_bytes(data[: len(data) // 2])  # cut after it was opened
    rec.frame(0)
    with pytest.raises(RecordingError, match="frame 2: only 0 of"):
        rec.frame(2)
    (tmp_path / "d.sigmf-meta").mkdir()
    with pytest.raises(RecordingError, match=r"d\.sigmf-meta: cannot read"):
        read_recording(tmp_path / "d")


# ---------------------------------------------------------------------------------------------
# the reader, fuzzed: any change to a valid metadata file gives a RecordingError or frames that read
_KEYS = ["global", "captures", "annotations", "core:datatype", "core:sample_rate", "core:num_channels",
         "core:sample_start", "core:datetime", "core:header_bytes", "core:trailing_bytes", "core:dataset",
         "mtcw:frame_samples", "mtcw:tones_hz", "mtcw:tone_phases_rad", "mtcw:wavelength_m", "mtcw:receiver",
         "mtcw:architecture", "mtcw:channels", "mtcw:pulse", "mtcw:scale", "mtcw:offset", "mtcw:source",
         "mtcw:seq", "mtcw:truth", "mtcw:bogus", "acme:key", "period_s", "duty", "delay_s", "range_m",
         "velocity_mps"]
_scalars = (st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats() | st.text(max_size=12)
            | st.sampled_from([0, 1, -1, 2, 3, 16, 32, 48, 2**63, 2**64, 0.5, 1e-300, 1e308, "pd", "i", "q", "iq",
                               "single", "pulse_ref", "ri16_le", "cf32_le", "ci8", "rf64_le",
                               "2026-01-01T00:00:00Z", "1970-01-01T00:00:00.000000001Z", "modulated_reference"]))
_values = st.recursive(_scalars, lambda inner: st.lists(inner, max_size=4)
                       | st.dictionaries(st.sampled_from(_KEYS) | st.text(max_size=8), inner, max_size=4),
                       max_leaves=12)


def _paths(node, at=()):
    yield at
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, (*at, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _paths(v, (*at, i))


def _get(node, path):
    for p in path:
        node = node[p]
    return node


def _mutate(draw, meta, values):
    """One random change at any key path: replace, delete or insert a value drawn from ``values``."""
    path = draw(st.sampled_from(list(_paths(meta))))
    op = draw(st.sampled_from(["replace", "delete", "insert"]))
    if not path:
        return draw(values) if op == "replace" else meta
    parent, last = _get(meta, path[:-1]), path[-1]
    target = _get(meta, path)
    if op == "replace":
        parent[last] = draw(values)
    elif op == "delete":
        del parent[last]
    elif isinstance(target, dict):
        target[draw(st.sampled_from(_KEYS) | st.text(max_size=8))] = draw(values)
    elif isinstance(target, list):
        target.insert(draw(st.integers(0, len(target))), draw(values))
    else:
        parent[last] = [target, draw(values)]
    return meta


@pytest.fixture(scope="module")
def fuzz_bases(tmp_path_factory) -> list[tuple[dict, bytes]]:
    """Valid recordings of each layout: int16 single with every optional key; int16 IQ with a pulse
    reference; float IQ with nothing optional; int8 single. 3 frames of 2^10 samples each."""
    root = tmp_path_factory.mktemp("fuzz-bases")
    n = 2**10
    recipes = [dict(dtype="<i2"), dict(dtype="<i2", receiver="iq"),
               dict(dtype="<f4", receiver="iq", channels=("i", "q"), pulse=None, truth=None, tone_phases_rad=None),
               dict(dtype="i1", channels=("pd",), pulse=None)]
    out = []
    for k, kw in enumerate(recipes):
        frames = []
        for s in range(3):
            fr = _frame(seq=s, n=n, **kw)
            frames.append(fr.with_(samples=fr.samples[: len(fr.channels)]))
        p = _write(root / f"b{k}", frames)
        out.append((json.loads(p.with_suffix(".sigmf-meta").read_text()), p.with_suffix(".sigmf-data").read_bytes()))
    return out


def _check_total(tmp_path, meta_bytes: bytes, data: bytes) -> None:
    """The property: a RecordingError naming a file, or a recording whose every frame reads and
    could be sent on the wire as it is."""
    (tmp_path / "f.sigmf-meta").write_bytes(meta_bytes)
    (tmp_path / "f.sigmf-data").write_bytes(data)
    try:
        rec = read_recording(tmp_path / "f")
    except RecordingError as err:
        assert str(err).startswith(str(tmp_path / "f.sigmf-")), err
        event("refused")  # --hypothesis-show-statistics shows how often each branch is taken
        return
    event("opened")
    frames = list(rec)
    assert len(frames) == len(rec) >= 1
    for fr in frames:
        assert fr.samples.shape == (len(rec.channels), rec.frame_samples)
        back = decode_frame(encode_frame(fr))  # the wire's schema accepts every frame a recording yields
        np.testing.assert_array_equal(back.samples, fr.samples)


@FIXTURE_OK
@given(data=st.data())
def test_fuzzed_metadata_gives_a_recording_error_or_frames_that_read(tmp_path, fuzz_bases, data):
    meta, samples = copy.deepcopy(data.draw(st.sampled_from(fuzz_bases)))
    # values of any JSON type, or (plausible near-misses) a value found anywhere in a valid recording
    found = [_get(m, p) for m, _ in fuzz_bases for p in _paths(m)]
    values = _values | st.sampled_from(found).map(copy.deepcopy)
    for _ in range(data.draw(st.integers(1, 3))):
        meta = _mutate(data.draw, meta, values)
    if data.draw(st.booleans()):
        samples = samples[: data.draw(st.integers(0, len(samples)))]
    _check_total(tmp_path, json.dumps(meta).encode(), samples)


@FIXTURE_OK
@given(data=st.data())
def test_fuzzed_metadata_bytes_give_a_recording_error_or_frames_that_read(tmp_path, fuzz_bases, data):
    meta, samples = data.draw(st.sampled_from(fuzz_bases))
    text = json.dumps(meta).encode()
    if data.draw(st.booleans()):  # any bytes at all
        blob = data.draw(st.binary(max_size=2000))
    else:  # a valid file with a slice replaced by random bytes
        i = data.draw(st.integers(0, len(text)))
        j = data.draw(st.integers(i, min(len(text), i + 40)))
        blob = text[:i] + data.draw(st.binary(max_size=40)) + text[j:]
    _check_total(tmp_path, blob, samples)


# ---------------------------------------------------------------------------------------------
# the writer refuses malformed frames, writing nothing
BAD_FRAMES = {
    "fs_nan": (dict(fs_hz=NAN), "global.core:sample_rate"),
    "fs_negative": (dict(fs_hz=-1.0), "global.core:sample_rate"),
    "fs_beyond_sigmf": (dict(fs_hz=2e12), "refused by sigmf: global.core:sample_rate"),
    "wavelength_zero": (dict(wavelength_m=0.0), "global.mtcw:wavelength_m"),
    "tone_inf": (dict(tones_hz=(1e8, INF)), "global.mtcw:tones_hz.1"),
    "phases_too_many": (dict(tone_phases_rad=(0.0, 0.0, 0.0)), "global.mtcw:tone_phases_rad"),
    "receiver_unknown": (dict(receiver="quad"), "receiver"),
    "channels_repeated": (dict(channels=("pd", "pd")), "global.mtcw:channels"),
    "channels_without_pd": (dict(channels=("x", "pulse_ref")), "global.mtcw:channels"),
    "rows_unlike_channels": (dict(channels=("pd",)), "samples: 2 rows for channels"),
    "samples_one_dimensional": (dict(samples=np.zeros(16, "<i2")), "samples: must be an array"),
    "dtype_unsigned": (dict(samples=np.zeros((2, 16), "<u2")), "dtype"),
    "pulse_duty_zero": (dict(pulse=PulseInfo(1e-6, 0.0)), "global.mtcw:pulse.duty"),
    "seq_negative": (dict(seq=-1), ".mtcw:seq: "),
    "t_ns_negative": (dict(t_ns=-5), "t_ns"),
    "truth_nan": (dict(truth=(TruthTarget(NAN, 0.0),)), ".mtcw:truth.0.range_m: "),
    "source_not_text": (dict(source=5), "global.mtcw:source"),
    "scale_nan": (dict(scale=NAN), "global.mtcw:scale"),
    "fs_not_a_number": (dict(fs_hz="fast"), "could not convert"),
}


@pytest.mark.parametrize("case", sorted(BAD_FRAMES))
@pytest.mark.parametrize("position", ["first", "later"])
def test_the_writer_refuses_a_malformed_frame_and_writes_nothing(tmp_path, case, position):
    change, named = BAD_FRAMES[case]
    with RecordingWriter(tmp_path / "r", checkpoint_s=0) as w:
        if position == "later":
            w.write(_frame(seq=0))
        with pytest.raises(RecordingError) as err:
            w.write(_frame(**{"seq": 1, **change}))
        assert str(err.value).startswith(str(tmp_path / "r.sigmf-meta")), err.value
        if position == "first" or case in ("seq_negative", "t_ns_negative", "truth_nan", "rows_unlike_channels",
                                           "samples_one_dimensional", "dtype_unsigned", "fs_not_a_number"):
            assert named in str(err.value), err.value
        else:  # a later frame's global fields are checked against the first frame's
            assert "differs from the recording's first frame" in str(err.value), err.value
        w.write(_frame(seq=2))  # the writer goes on
    rec = read_recording(tmp_path / "r")
    assert [f.seq for f in rec] == ([0, 2] if position == "later" else [2])
    assert (tmp_path / "r.sigmf-data").stat().st_size == len(rec) * rec.bytes_per_frame


def test_the_writer_refuses_nothing_at_all(tmp_path):
    with pytest.raises(RecordingError, match="no frames written"):
        RecordingWriter(tmp_path / "r").close()
    assert not (tmp_path / "r.sigmf-data").exists()
    _write(tmp_path / "r", [_frame()])
    with pytest.raises(RecordingError, match="recording exists"):
        RecordingWriter(tmp_path / "r", overwrite=False)
    with pytest.raises(ValueError, match="checkpoint_s"):
        RecordingWriter(tmp_path / "q", checkpoint_s=math.nan)


# ---------------------------------------------------------------------------------------------
# the metadata is kept current, and a killed recorder leaves a readable recording
def test_the_metadata_follows_the_frames(tmp_path):
    with RecordingWriter(tmp_path / "r", checkpoint_s=0) as w:
        for s in range(4):
            w.write(_frame(seq=s))
            assert len(read_recording(tmp_path / "r")) == s + 1
            assert "core:sha512" not in json.loads((tmp_path / "r.sigmf-meta").read_text())["global"]
    assert "core:sha512" in json.loads((tmp_path / "r.sigmf-meta").read_text())["global"]
    assert not (tmp_path / "r.sigmf-meta.tmp").exists()


def test_checkpoints_are_spaced_by_checkpoint_s(tmp_path):
    with RecordingWriter(tmp_path / "r", checkpoint_s=3600) as w:
        for s in range(5):
            w.write(_frame(seq=s))
        assert w.checkpoints == 1 and len(read_recording(tmp_path / "r")) == 1  # the first frame only
        w.checkpoint()
        assert len(read_recording(tmp_path / "r")) == 5
    assert len(read_recording(tmp_path / "r")) == 5


def test_overwriting_removes_the_old_metadata_first(tmp_path):
    _write(tmp_path / "r", [_frame(seq=s) for s in range(3)])
    w = RecordingWriter(tmp_path / "r")  # a kill now must not leave 3 old frames claimed over new data
    with pytest.raises(RecordingError, match="no such metadata file"):
        read_recording(tmp_path / "r")
    w.write(_frame(seq=9))
    w.close()
    assert [f.seq for f in read_recording(tmp_path / "r")] == [9]


_RECORDER = """
import sys
from mtcw_core.recording import RecordingWriter
from mtcw_core.scene import load_scene, scene_variant
from mtcw_core.simulate import Simulator

sc = scene_variant(load_scene("moving-target"), digitizer={"samples": 2**10, "adc_bits": 12})
with RecordingWriter(sys.argv[1], checkpoint_s=float(sys.argv[2])) as w:
    for i, fr in enumerate(Simulator(sc, 7).frames(10**9)):
        w.write(fr)
        if i == 2:
            print("ready", flush=True)
"""


@pytest.mark.parametrize("checkpoint_s", [0.0, 0.02])
def test_a_sigkilled_recorder_leaves_a_readable_recording(tmp_path, checkpoint_s):
    """A recorder writing simulator frames is SIGKILLed mid-run; meanwhile and afterwards the
    recording opens, and every frame its metadata claims is bit-exact."""
    prefix = tmp_path / "cap"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-c", _RECORDER, str(prefix), str(checkpoint_s)], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready", proc.stderr.read()
        opened, t0 = 0, time.monotonic()
        while True:  # a reader racing the writer always finds a whole recording
            rec = read_recording(prefix)
            rec.frame(-1)
            opened += 1
            if len(rec) >= 3 and time.monotonic() - t0 > 0.3:
                break
            assert time.monotonic() - t0 < 60, "the recorder claims fewer than 3 frames after 60 s"
        assert proc.poll() is None, proc.stderr.read()
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(10)
    assert proc.returncode == -signal.SIGKILL and opened > 0
    meta = json.loads((tmp_path / "cap.sigmf-meta").read_text())
    assert "core:sha512" not in meta["global"]  # really killed before close()
    rec = read_recording(prefix)
    assert len(rec) >= 3
    assert (tmp_path / "cap.sigmf-data").stat().st_size >= len(rec) * rec.bytes_per_frame
    sc = scene_variant(load_scene("moving-target"), digitizer={"samples": 2**10, "adc_bits": 12})
    for want, got in zip(Simulator(sc, 7).frames(len(rec)), rec):
        assert got.samples.dtype == np.int16
        _same(got, want)
