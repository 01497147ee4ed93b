"""Fuzzing of every parser that takes outside bytes or values (issue 11): whatever comes in, the
parser returns its typed value or raises its own error naming the field; nothing else escapes.

- ``services.wire`` decoders (frame, header, points, end; ``topic``, ``rejection_point``): ZeroMQ
  parts in, a typed message or ``WireError`` (``reason``, ``field``) out;
- ``services.worker.Worker.handle`` on frames that do decode: the chain on hostile headers and
  samples gives a point that encodes (never a chain error), finite when ``ok``;
- ``services.api.PointReceiver.handle`` and ``PointStore``: any point or end message is stored or
  counted malformed; the books balance; served JSON is finite; the issue's failure 1 is refused;
- ``mtcw_core.scene`` (``scene_from_dict``, ``load_scene`` from TOML and JSON): ``SceneError``
  naming the field; NaN and inf refused;
- ``mtcw_core.calibration.Calibration.load``: ``CalibrationError`` naming the field;
- ``services.settings.load``, flags and ``MTCW_*`` environment variables: ``ValueError`` naming
  the field;
- ``mtcw_core.profiles.get_profile``: ``ValueError`` naming the override; NaN and inf refused;
- the HTTP API against its own OpenAPI schema (schemathesis): no 5xx, responses as documented.

Strategies: (a) random bytes and parts; (b) structure-aware: a valid message or document, built
with the module's own encoders, with one key at one path deleted, renamed or replaced by any
value (text, huge or negative integers, NaN/inf, lists, maps, bytes, nested); the error must
then name that path (or a documented cross-check field). The number of cases is the Hypothesis
profile's (``tests/conftest.py``: ``ci`` 300 per test, ``pytest --long`` 10^4). The SigMF
reader is fuzzed with the recording tests.
"""

from __future__ import annotations

import atexit
import copy
import json
import math
import os
import re
import shutil
import tempfile
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from unittest import mock

import msgpack
import msgspec
import numpy as np
import pytest
import schemathesis
from schemathesis.specs.openapi.checks import negative_data_rejection
from hypothesis import assume, event, example, given, note, strategies as st
from msgspec import to_builtins
from prometheus_client import generate_latest
from pydantic_settings import BaseSettings

from mtcw_core.calibration import Calibration, CalibrationError
from mtcw_core.chain import process_frame
from mtcw_core.frame import Frame, PulseInfo, TruthTarget
from mtcw_core.profiles import PROFILES, ChainSettings, get_profile
from mtcw_core.scene import Scene, SceneError, bundled_scenes, field_path, load_scene, scene_from_dict
from mtcw_core.simulate import Simulator, simulate_frame
from services.api import Metrics, PointReceiver, PointStore, create_app, served_json
from services.settings import AcquisitionSettings, ApiSettings, WorkerSettings, load
from services.wire import (END_TOPIC, FRAME_TOPIC, POINTS_TOPIC, VERSION, EndMessage, FrameHeader, PointMessage,
                           WireError, decode_end, decode_frame, decode_header, decode_points, encode_end,
                           encode_frame, encode_points, end_message, frame_header, point_from_result,
                           rejected_point, rejection_point, topic)
from services.worker import Worker

from .conftest import make_scene

Doc = Any  # a plain document: dicts, lists and scalars
PathT = tuple[Any, ...]  # keys and indexes from the root of a document to one value

_MAX = 1.7976931348623157e308
_REASONS = {"bad_parts", "bad_topic", "bad_msgpack", "bad_version", "missing_key", "bad_field", "bad_size"}
_NAMED = {"bad_version", "missing_key", "bad_field", "bad_size"}  # reasons that always name a field


# ---------------------------------------------------------------------------------------------
# documents, paths and mutations
def _paths(doc: Doc, prefix: PathT = ()) -> Iterator[PathT]:
    """Every path into ``doc`` (to a map value or a list item), parents first."""
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
    for k, v in items:
        yield prefix + (k,)
        yield from _paths(v, prefix + (k,))


def _mutate(doc: Doc, path: PathT, op: str, value: Any) -> Doc:
    """A deep copy of ``doc`` with the item at ``path`` deleted, replaced by ``value`` or (a map
    key) renamed to ``value``."""
    out = copy.deepcopy(doc)
    parent = out
    for k in path[:-1]:
        parent = parent[k]
    last = path[-1]
    if op == "delete":
        del parent[last]
    elif op == "replace":
        parent[last] = value
    else:  # rename a map key
        parent[value] = parent.pop(last)
    return out


def _get(doc: Doc, path: PathT) -> Any:
    for k in path:
        doc = doc[k]
    return doc


def _tokens(field: str) -> list[str]:
    """``targets[0].range_m`` / ``targets.0.range_m`` / ``stage_seconds[...]`` -> their parts
    (``["targets", "0", "range_m"]``, ``["stage_seconds", "..."]``)."""
    return [t.strip("[]") for t in re.findall(r"\[\.\.\.\]|[^.\[\]]+", field)]


def _path_tokens(path: PathT, free_maps: frozenset[str] = frozenset()) -> list[str]:
    """A path as field tokens; the keys of a free-form map (``stage_seconds``) read ``...``."""
    out: list[str] = []
    for k in path:
        out.append("..." if out and out[-1] in free_maps else str(k))
    return out


def _related(a: list[str], b: list[str]) -> bool:
    """One names a part of the other (``pulse`` and ``pulse.duty``)."""
    n = min(len(a), len(b))
    return n > 0 and a[:n] == b[:n]


def _all_finite(x: Any) -> bool:
    """Every float in a (nested) value is finite."""
    if isinstance(x, float):
        return math.isfinite(x)
    if isinstance(x, dict):
        return all(_all_finite(v) for v in x.values())
    if isinstance(x, (list, tuple)):
        return all(_all_finite(v) for v in x)
    return True


_FIELD_NAMES = sorted(set(FrameHeader.__struct_fields__) | set(PointMessage.__struct_fields__)
                      | set(EndMessage.__struct_fields__) | {"range_m", "velocity_mps", "period_s", "duty"})
_extreme_float = st.sampled_from([math.nan, math.inf, -math.inf, 0.0, -0.0, 5e-324, -5e-324, 1e-300, 1e300,
                                  _MAX, -_MAX, 1.0, -1.0, 0.5])
_extreme_int = st.sampled_from([0, 1, -1, 2, 255, 256, 2**31, 2**32, 2**53 + 1, 2**63 - 1, 2**63, 2**64 - 1,
                                -2**63])
#: any msgpack-able scalar
_leaf = (st.none() | st.booleans() | st.integers(-2**63, 2**64 - 1) | _extreme_int | st.floats() | _extreme_float
         | st.text(max_size=12) | st.sampled_from(["", "nan", "1.5", "pd", "iq", "ok", "static", "<f4"])
         | st.binary(max_size=12)
         | st.builds(msgpack.ExtType, st.integers(0, 127), st.binary(max_size=8)))
#: any msgpack-able value: scalars, lists, maps (keys: field names, text, integers, bytes), nested
_value = st.recursive(
    _leaf,
    lambda kids: st.lists(kids, max_size=4)
    | st.dictionaries(st.sampled_from(_FIELD_NAMES) | st.text(max_size=6) | st.integers(-5, 5) | st.binary(max_size=4),
                      kids, max_size=4),
    max_leaves=10)
_key = st.sampled_from(_FIELD_NAMES) | st.text(max_size=8) | st.integers(-2**63, 2**64 - 1) | st.binary(max_size=6)
_op = st.sampled_from(["delete", "replace", "replace", "replace", "rename"])


def _draw_mutation(data: st.DataObject, doc: Doc, value: st.SearchStrategy = _value,
                   key: st.SearchStrategy = _key) -> tuple[Doc, PathT, str, Any]:
    """One mutation of ``doc`` at one path, drawn; returns (mutated doc, path, op, value)."""
    path = data.draw(st.sampled_from(list(_paths(doc))), label="path")
    op = data.draw(_op, label="op")
    parent = doc
    for k in path[:-1]:
        parent = parent[k]
    if op == "rename" and not isinstance(parent, dict):
        op = "replace"
    new = data.draw(key if op == "rename" else value, label="value") if op != "delete" else None
    if op == "rename" and new in parent:
        op = "delete"
    return _mutate(doc, path, op, new), path, op, new


# ---------------------------------------------------------------------------------------------
# valid wire messages, built with the module's own encoders
def _synthetic(receiver: str = "single", dtype: str = "<i2", **kw: Any) -> Frame:
    rng = np.random.default_rng(0)
    channels = ("i", "q", "pulse_ref") if receiver == "iq" else ("pd", "pulse_ref")
    x = np.clip(rng.normal(0, 100, (len(channels), 64)), -120, 120).astype(dtype)
    base = dict(samples=x, fs_hz=1e9, tones_hz=(1e8, 1.5e8), wavelength_m=1.55e-6, receiver=receiver,
                channels=channels, scale=0.01, offset=-0.5, seq=7, t_ns=123_456_789, source="scope-1", run=99,
                tone_phases_rad=(0.1, -0.2), pulse=PulseInfo(1e-6, 0.5, 2e-8), truth=(TruthTarget(1.5, -0.25),),
                architecture="modulated_reference")
    return Frame(**{**base, **kw})


_SIM = simulate_frame(make_scene(digitizer={"samples": 2**12, "adc_bits": 12}))  # 3 tones, int16 codes
_FRAMES = [_synthetic("single"), _synthetic("iq", "<f4"), _synthetic("balanced", "<i1"), _SIM]
_FRAME_DOCS = [(to_builtins(frame_header(f)), bytes(encode_frame(f)[2])) for f in _FRAMES]


def _result_point(run: int | None = 1) -> PointMessage:
    return point_from_result(process_frame(_SIM, "fast"), run=run, processing_s=0.002)


_POINT_DOCS = [to_builtins(_result_point()), to_builtins(rejected_point("s", 3, 5, "too_long: x", run=2)),
               to_builtins(rejection_point(WireError("bad_size", "x", "samples"), [FRAME_TOPIC, b"\x80", b""]))]
_END_DOCS = [to_builtins(end_message("bench", 42, frames=60, t_ns=123, dropped=7)),
             to_builtins(end_message("bench", None, frames=1, t_ns=1, dropped=0))]
assert _POINT_DOCS[0]["status"] == "ok" and _POINT_DOCS[0]["targets"]  # a target to mutate

_DECODERS = {"frame": (decode_frame, FRAME_TOPIC, 3), "points": (decode_points, POINTS_TOPIC, 2),
             "end": (decode_end, END_TOPIC, 2)}
#: fields a frame's cross-checks name whatever was changed: sizes, receiver/channels, phases/tones
_FRAME_CROSS = frozenset({"samples", "channels", "tone_phases_rad"})
_FREE_MAPS = frozenset({"stage_seconds", "tone_snr_db"})


def _check_wire_error(err: WireError, path: PathT | None = None, op: str = "", cross: frozenset = frozenset(),
                      new: Any = None) -> None:
    """The decoder's error: a known reason, a field when the reason has one, named in the message;
    after a one-path mutation, the field is that path (or a part of it, or the key it was renamed
    to) or a cross-check field."""
    assert err.reason in _REASONS, err.reason
    assert (err.field is not None) == (err.reason in _NAMED), (err.reason, err.field, str(err))
    assert str(err) and err.detail
    if err.field is not None:
        assert err.field and err.field in str(err)
    if path is None:
        return
    if err.field is None:  # only a map key at the top that is not text leaves nothing to name
        assert op == "rename" and len(path) == 1, (err.reason, str(err))
        return
    paths = [path] + ([path[:-1] + (new,)] if op == "rename" and isinstance(new, str) else [])
    assert err.field in cross or any(_related(_tokens(err.field), _path_tokens(p, _FREE_MAPS)) for p in paths), (
        f"mutating {path} ({op} {new!r}) gave an error naming {err.field!r}: {err}")


def _decode_total(kind: str, parts: Any) -> Any:
    """Decode with the kind's decoder: a typed message, or None after checking the WireError."""
    decode = _DECODERS[kind][0]
    try:
        out = decode(parts)
    except WireError as err:
        _check_wire_error(err)
        return None
    assert isinstance(out, Frame if kind == "frame" else PointMessage if kind == "points" else EndMessage)
    return out


def _bare_worker(profile: str = "fast", calibration: Calibration | None = None) -> Worker:
    """A :class:`Worker` without sockets: :meth:`Worker.handle` needs only its chain settings."""
    w = Worker.__new__(Worker)
    w.settings = WorkerSettings.model_construct(profile=profile, name="fuzz")
    w.chain = get_profile(profile)
    w.calibration = calibration
    return w


_WORKER = _bare_worker()
_CAL_WORKER = _bare_worker(calibration=Calibration(tones_hz=_SIM.tones_hz, tone_phases_rad=(0.1, 0.2, 0.3),
                                                   tau0_s=1e-9))
#: reasons no frame may produce: the chain or the point schema failed (a bug, not a bad frame)
_BUG_REASONS = ("chain_error", "internal_error", "bad_result")


def _check_worker_point(point: PointMessage) -> str:
    """A worker's answer to one message: a point that travels, finite when ok, a reason otherwise
    (never a chain error); returns ``status reason-key`` for the fuzz statistics."""
    assert isinstance(point, PointMessage)
    assert decode_points([bytes(p) for p in encode_points(point)]) == point
    if point.status == "ok":
        assert point.targets and point.reason is None
        assert _all_finite(to_builtins(point))
    else:
        assert point.reason and not point.targets
    assert not (point.reason or "").startswith(_BUG_REASONS), point.reason
    return f"worker: {point.status} {(point.reason or '').split(':', 1)[0].split(' (', 1)[0]}"


# ---------------------------------------------------------------------------------------------
# (a) wire: arbitrary bytes and parts
_part = (st.binary(max_size=64) | st.sampled_from([FRAME_TOPIC, POINTS_TOPIC, END_TOPIC, b"", b"\x80", b"\xc1"])
         | st.builds(bytearray, st.binary(max_size=16)) | st.builds(memoryview, st.binary(max_size=16)))
_odd_part = st.none() | st.integers() | st.text(max_size=8) | st.floats() | st.just(object())
_parts = (st.lists(_part, max_size=5)
          | st.lists(_part | _odd_part, max_size=4)
          | st.tuples(st.sampled_from([FRAME_TOPIC, POINTS_TOPIC, END_TOPIC]), st.binary(max_size=128),
                      st.binary(max_size=64)).map(list)
          | _odd_part | st.binary(max_size=16))


@given(kind=st.sampled_from(sorted(_DECODERS)), parts=_parts)
def test_wire_decoders_are_total_on_arbitrary_parts(kind: str, parts: Any) -> None:
    """Any parts: a typed message or a WireError with a known reason; ``topic`` and the worker's
    ``rejection_point`` never raise, and the rejection travels."""
    _decode_total(kind, parts)
    assert isinstance(topic(parts), bytes)
    if kind == "frame":  # the worker's answer: a rejection naming the reason (or a point)
        point = _WORKER.handle(parts)
        event(_check_worker_point(point))
        try:
            decode_frame(parts)
        except WireError as err:
            assert point.status == "rejected" and point.reason.startswith(f"malformed_{err.reason}")


@given(body=st.binary(max_size=256) | _value.map(lambda v: msgpack.packb(v, use_bin_type=True)))
def test_decode_header_is_total(body: bytes) -> None:
    try:
        h = decode_header(body)
    except WireError as err:
        _check_wire_error(err)
    else:
        assert isinstance(h, FrameHeader) and h.v == VERSION


@given(kind=st.sampled_from(sorted(_DECODERS)),
       m=st.dictionaries(st.sampled_from(_FIELD_NAMES) | st.text(max_size=6), _value, max_size=14),
       v=st.sampled_from([VERSION, VERSION, 2, 0, True, None, "1", 1.0]))
def test_wire_decoders_are_total_on_arbitrary_maps(kind: str, m: dict, v: Any) -> None:
    if v is not None:
        m["v"] = v
    decode, tp, n = _DECODERS[kind]
    _decode_total(kind, [tp, msgpack.packb(m, use_bin_type=True), *([b"\0" * 8] * (n - 2))])


# ---------------------------------------------------------------------------------------------
# (b) wire: valid messages with one key at one path changed
@given(data=st.data(), which=st.integers(0, len(_FRAME_DOCS) - 1))
def test_frame_decoder_names_the_changed_field(data: st.DataObject, which: int) -> None:
    doc, samples = _FRAME_DOCS[which]
    bad, path, op, value = _draw_mutation(data, doc)
    parts = [FRAME_TOPIC, msgpack.packb(bad, use_bin_type=True), samples]
    try:
        frame = decode_frame(parts)
    except WireError as err:
        _check_wire_error(err, path, op, _FRAME_CROSS, value)
        event(f"frame: {err.reason}")
        point = _WORKER.handle(parts)
        assert point.status == "rejected" and point.reason.startswith(f"malformed_{err.reason}")
        event(_check_worker_point(point))
        return
    event("frame: decoded")
    assert isinstance(frame, Frame) and frame.samples.shape == (len(frame.channels), frame.n)
    event(_check_worker_point(_WORKER.handle(parts)))


@given(data=st.data(), kind=st.sampled_from(["points", "end"]), which=st.integers(0, 2))
def test_point_and_end_decoders_name_the_changed_field(data: st.DataObject, kind: str, which: int) -> None:
    docs = _POINT_DOCS if kind == "points" else _END_DOCS
    doc = docs[which % len(docs)]
    bad, path, op, value = _draw_mutation(data, doc)
    decode, tp, _ = _DECODERS[kind]
    try:
        msg = decode([tp, msgpack.packb(bad, use_bin_type=True)])
    except WireError as err:
        _check_wire_error(err, path, op, new=value)
        event(f"{kind}: {err.reason}")
        return
    event(f"{kind}: decoded")
    assert _all_finite(to_builtins(msg))  # a decoded message never carries NaN or inf
    assert decode([bytes(p) for p in (encode_points(msg) if kind == "points" else encode_end(msg))]) == msg


# ---------------------------------------------------------------------------------------------
# (c) frames that decode, through the worker's handling (fast profile, n <= 2^12)
_pos = st.floats(min_value=5e-324, max_value=_MAX) | st.sampled_from([5e-324, 1e-300, 1.0, 1e9, 5e9, 1e300, _MAX])
_fin = st.floats(allow_nan=False, allow_infinity=False) | _extreme_float.filter(math.isfinite)
_tone = st.sampled_from([500e6, 700e6, 950e6, 600e6, 1.2e9, 1e8, 950e6 + 1.0]) | _pos
_CHANNELS = {"single": [["pd"], ["pd", "pulse_ref"], ["pulse_ref", "pd"], ["pd", "x"]],
             "balanced": [["pd"], ["pd", "pulse_ref"]],
             "iq": [["i", "q"], ["q", "i", "pulse_ref"], ["i", "q", "pd"]]}


_SIM_IQ = simulate_frame(make_scene(receiver={"kind": "iq"}, digitizer={"samples": 2**12, "adc_bits": 12},
                                    targets=[{"range_m": 1.234, "velocity_mps": 40.0, "loss_db": 20.0}]))


@st.composite
def _decodable_frames(draw: st.DrawFn) -> list:
    """A frame message whose header passes the schema: one the chain ranges (the simulated
    single-PD or IQ frame: 3 tones, 4096 samples) with up to three fields changed to extreme but
    typed values; samples of the right size (the simulated codes, random bytes -- NaN and inf in
    float dtypes --, a constant, or the dtype's extremes)."""
    receiver = draw(st.sampled_from(sorted(_CHANNELS)))
    sim = _SIM_IQ if receiver == "iq" else _SIM
    odd = draw(st.sets(st.sampled_from(["channels", "n", "dtype", "fs", "tones", "scale", "offset", "wavelength",
                                        "period", "duty", "delay", "samples"]), max_size=3), label="changed")

    def _mostly(name: str, nominal: Any, other: st.SearchStrategy) -> st.SearchStrategy:
        return other if name in odd else st.just(nominal)

    channels = draw(_mostly("channels", list(sim.channels), st.sampled_from(_CHANNELS[receiver])))
    n = draw(_mostly("n", sim.n, st.sampled_from([1, 2, 3, 255, 256, 1024]) | st.integers(1, 4096)))
    dtype = draw(_mostly("dtype", "<i2", st.sampled_from(["<f4", "<f8", "<i1"])))
    fs = draw(_mostly("fs", sim.fs_hz, _pos))
    tones = draw(_mostly("tones", list(sim.tones_hz), st.lists(_tone, max_size=6)))
    h: dict[str, Any] = {
        "v": VERSION, "source": draw(st.text(max_size=8)),
        "seq": draw(st.integers(0, 2**64 - 1) | _extreme_int.filter(lambda x: x >= 0)),
        "t_ns": draw(st.integers(0, 2**64 - 1)), "fs_hz": fs, "n": n, "dtype": dtype, "channels": channels,
        "scale": draw(_mostly("scale", sim.scale, _fin)), "offset": draw(_mostly("offset", 0.0, _fin)),
        "tones_hz": tones,
        "wavelength_m": draw(_mostly("wavelength", sim.wavelength_m, _pos)), "receiver": receiver,
        "architecture": draw(st.sampled_from(["unmodulated_lo", "modulated_reference"])),
    }
    if draw(st.booleans()):
        h["tone_phases_rad"] = draw(st.lists(_fin, min_size=len(tones), max_size=len(tones)))
    if draw(st.integers(0, 3)) == 0:  # quasi-CW: a period of a record or so, or anything
        per = min(max(n / fs * draw(st.sampled_from([0.25, 0.5, 1.0, 2.0])), 5e-324), _MAX)  # a valid float
        h["pulse"] = {"period_s": draw(_mostly("period", per, _pos)),
                      "duty": draw(_mostly("duty", 0.3, st.floats(min_value=5e-324, max_value=1.0))),
                      "delay_s": draw(_mostly("delay", 0.0, _fin))}
    if draw(st.booleans()):
        h["truth"] = [{"range_m": draw(_fin), "velocity_mps": draw(_fin)}]
    if draw(st.booleans()):
        h["run"] = draw(st.integers(0, 2**64 - 1))
    size = len(channels) * n * np.dtype(dtype).itemsize
    how = draw(_mostly("samples", "simulated", st.sampled_from(["random", "constant", "extremes"])))
    if how == "simulated":  # the simulated codes, channel by channel (repeated to fill)
        x = np.resize(sim.samples.astype(np.float64), (len(channels), n))
        x = x * sim.scale if dtype.startswith("<f") else np.clip(x, np.iinfo(dtype).min, np.iinfo(dtype).max)
        samples = x.astype(dtype).tobytes()
    elif how == "random":
        samples = draw(st.binary(min_size=size, max_size=size)) if size <= 4096 else \
            np.random.default_rng(draw(st.integers(0, 2**32 - 1))).bytes(size)
    elif how == "constant":
        samples = np.full((len(channels), n), draw(st.integers(-100, 100)), dtype).tobytes()
    else:
        info = np.finfo(dtype) if dtype.startswith("<f") else np.iinfo(dtype)
        samples = np.resize(np.array([info.max, info.min], dtype), (len(channels), n)).tobytes()
    assert len(samples) == size
    return [FRAME_TOPIC, msgpack.packb(h, use_bin_type=True), samples]


@given(parts=_decodable_frames(), calibrated=st.booleans())
def test_decodable_frames_give_a_point_that_travels(parts: list, calibrated: bool) -> None:
    """A frame the decoder accepts, however extreme, gives a point (never an exception, never a
    chain error); an ``ok`` point is finite."""
    note(f"header: {msgpack.unpackb(parts[1])}")
    frame = decode_frame(parts)  # the strategy draws headers the schema accepts
    point = (_CAL_WORKER if calibrated else _WORKER).handle(parts)
    event(_check_worker_point(point))
    assert (point.source, point.seq, point.t_ns, point.run) == (frame.source, frame.seq, frame.t_ns, frame.run)


@pytest.mark.parametrize("change, reason", [
    # each was an internal_error (an exception inside the chain, caught by process_frame)
    ({"scale": _MAX, "samples": (_SIM.samples * _SIM.scale).astype("<f4")}, "bad_scale"),  # ValueError: NaN to int
    ({"scale": 7795598619762060.0}, "bad_scale"),  # OverflowError: inf to int (float32 spectrum)
    ({"scale": 0.0}, "flat"),  # LinAlgError: singular matrix
    ({"scale": 1e-300}, "bad_scale"),  # LinAlgError: singular matrix
    ({"fs_hz": 4.406151356884573e16, "samples": _SIM.samples[:, :256]}, "tone_plan"),  # LinAlgError: lines
    # 0.003 bins apart
    ({"tones_hz": (1.0, 0.5), "tone_phases_rad": None, "samples": _SIM.samples[:, :1]}, "tone_plan"),  # ZeroDivision
    # a gate period far from the record: the gate stage's work grows with it (0.5 s: no_target
    # after 14 s for a 4096-sample frame; 4e6 s: a MemoryError for 9 PiB), or a fraction of a sample
    ({"pulse": PulseInfo(0.5, 0.3, 0.0)}, "bad_pulse"),
    ({"pulse": PulseInfo(4194303.0, 1.0, 0.0)}, "bad_pulse"),
    ({"pulse": PulseInfo(1e-12, 0.3, 0.0)}, "bad_pulse"),
    # a gate that never switches off (duty 1): no edge to time, an OverflowError in the edge fit
    ({"pulse": PulseInfo(2.048e-07, 1.0, 0.0)}, "bad_pulse"),
])
def test_frames_that_broke_the_chain_are_refused_with_a_reason(change: dict, reason: str) -> None:
    """Frames that broke the chain (found by the fuzzing above, with neighbours found by hand),
    each now refused by ``validate`` before any work."""
    frame = _SIM.with_(**change)
    t0 = time.perf_counter()
    point = _WORKER.handle([bytes(p) for p in encode_frame(frame)])
    assert point.status == "rejected" and point.reason.split(":", 1)[0] == reason, point.reason
    assert set(point.stage_seconds) == {"validate"} and time.perf_counter() - t0 < 1.0
    _check_worker_point(point)


# ---------------------------------------------------------------------------------------------
# the API's receiver and store: any message; the failure 1 stays refused
def _api_settings(**kw: Any) -> ApiSettings:
    # the store in memory, always: the schemathesis app is made at import, before conftest's fixtures
    return ApiSettings(**{"points_endpoint": "tcp://127.0.0.1:0", "reorder_timeout_s": 1.0, "reorder_max": 8,
                          "store_path": ":memory:", **kw})


@pytest.fixture(scope="module")
def receiver() -> Iterator[PointReceiver]:
    """One points receiver (its socket bound to port 0, never started): :meth:`handle` is fed directly."""
    settings = _api_settings()
    recv = PointReceiver(PointStore(settings, Metrics()), settings)
    yield recv
    recv.sock.close()


def test_failure_1_points_that_killed_the_receiver_are_refused_naming_the_field(receiver: PointReceiver) -> None:
    """Issue 11, failure 1: a point without ``range_m``, a string for a number, a list for
    ``source`` or text for ``t_ns`` killed the API's receiver. The decoder refuses each, naming the
    field, and the receiver counts it and goes on."""
    good = to_builtins(_result_point())
    t0 = good["targets"][0]
    cases = [({**good, "targets": [{k: v for k, v in t0.items() if k != "range_m"}]}, "missing_key",
              "targets[0].range_m"),
             ({**good, "targets": [{**t0, "range_m": "1.5 m"}]}, "bad_field", "targets[0].range_m"),
             ({**good, "source": ["bench"]}, "bad_field", "source"),
             ({**good, "t_ns": "now"}, "bad_field", "t_ns")]
    receiver.store = PointStore(receiver.settings, Metrics())
    for doc, reason, field in cases:
        parts = [POINTS_TOPIC, msgpack.packb(doc)]
        with pytest.raises(WireError) as err:
            decode_points(parts)
        assert (err.value.reason, err.value.field) == (reason, field)
        assert receiver.handle(parts, 0.0) == "malformed"
    assert receiver.handle(encode_points(_result_point()), 0.0) == "point"
    assert receiver.store.counts["received"] == 1 and receiver.malformed >= 4


@st.composite
def _api_messages(draw: st.DrawFn) -> list[Any]:
    """1-6 messages: valid point/end messages with identity drawn (sources, seqs, runs), mutated
    ones, and arbitrary parts."""
    out: list[Any] = []
    for _ in range(draw(st.integers(1, 6))):
        kind = draw(st.sampled_from(["points", "points", "end", "raw"]))
        if kind == "raw":
            out.append(draw(_parts))
            continue
        docs = _POINT_DOCS if kind == "points" else _END_DOCS
        doc = copy.deepcopy(draw(st.sampled_from(docs)))
        doc.update(source=draw(st.sampled_from(["a", "b", ""])), t_ns=draw(st.integers(0, 10) | st.just(2**64 - 1)))
        if kind == "points":
            doc["seq"] = draw(st.integers(-1, 12) | st.just(2**63))
        else:
            doc["frames"] = draw(st.integers(0, 12) | st.just(2**64 - 1))
        doc["run"] = draw(st.none() | st.integers(0, 2))
        if draw(st.booleans()):
            path = draw(st.sampled_from(list(_paths(doc))))
            doc = _mutate(doc, path, "replace", draw(_value))
        out.append([POINTS_TOPIC if kind == "points" else END_TOPIC, msgpack.packb(doc, use_bin_type=True)])
    return out


@given(messages=_api_messages())
def test_api_receiver_stores_or_counts_any_message(receiver: PointReceiver, messages: list[Any]) -> None:
    """Whatever arrives, the receiver's ``handle`` stores it or counts it malformed (never
    ``error``: the store must take every decoded point); the books balance once the reorder
    timeout has passed; every served point is finite JSON; the metrics render."""
    store = receiver.store = PointStore(receiver.settings, Metrics(), clock_ns=lambda: 10**18)
    for i, parts in enumerate(messages):
        kind = receiver.handle(parts, float(i))
        assert kind in ("point", "end", "malformed", "refused"), (kind, receiver.last_error)
        event(f"api: {kind}")
    store.poll(1e6)
    store.flush()
    snap = store.snapshot()
    assert snap["held_for_reordering"] == 0
    assert snap["received"] == snap["processed"] + snap["rejected"], snap
    for p in store.latest.values():
        json.dumps(served_json(p), allow_nan=False, ensure_ascii=False).encode()
    docs, _, _ = store.db.points(-1, 10_000)
    for doc in docs:  # what /v1/points serves: JSON with finite numbers only
        assert "NaN" not in doc.decode() and "Infinity" not in doc.decode()
        json.loads(doc)
    assert generate_latest(store.m.registry)
    assert store.m.registry.get_sample_value("mtcw_receiver_errors_total") == 0


# ---------------------------------------------------------------------------------------------
# scenes: mappings, TOML and JSON files
_SCENE_TEXTS = {name: p.read_text() for name, p in sorted(bundled_scenes().items())}
_SCENE_DOCS = [load_scene(name).model_dump() for name in _SCENE_TEXTS] + [
    make_scene(receiver={"kind": "iq", "bandwidth_hz": 2e9}, noise={"rin_db_per_hz": -150.0},
               digitizer={"adc_bits": 12, "full_scale_v": 1.0},
               pulsing={"period_s": 2e-6, "duty": 0.2}).model_dump()]
_json_leaf = (st.none() | st.booleans() | st.integers() | _extreme_int | st.floats() | _extreme_float
              | st.text(max_size=12) | st.sampled_from(["", "nan", "inf", "1.5", "single", "iq", "exact"]))
_toml_leaf = _json_leaf | st.datetimes() | st.dates() | st.times()
_json_value = st.recursive(_json_leaf, lambda kids: st.lists(kids, max_size=4) | st.dictionaries(
    st.text(max_size=6), kids, max_size=4), max_leaves=10)
_toml_value = st.recursive(_toml_leaf, lambda kids: st.lists(kids, max_size=4) | st.dictionaries(
    st.text(max_size=6), kids, max_size=4), max_leaves=10)
def _names(line: str, path: PathT, op: str = "", new: Any = None) -> bool:
    """``line`` (``<field>: <message>``) names ``path``, a part of it, a field inside it, or (a
    renamed key) the new key."""
    paths = [path] + ([path[:-1] + (new,)] if op == "rename" else [])
    return any(line.startswith(field_path(p[:k]) + ":") for p in paths for k in range(1, len(p) + 1)) or any(
        line.startswith(field_path(p) + ".") for p in paths)


def _check_scene_error(err: SceneError, path: PathT | None, op: str = "", new: Any = None) -> None:
    """``invalid scene <origin>:`` then one line per error, ``  <field>: <message>``; after a
    one-path change, one of them names that path (or a part of it), or is the Nyquist check
    naming the tone and the sample rate."""
    text = str(err)
    assert text.startswith(("invalid scene ", "cannot read scene ")), text
    if not text.startswith("invalid scene"):
        return
    lines = [ln[2:] for ln in text.splitlines()[1:]]
    assert lines and all(": " in ln for ln in lines), text
    if path is None:
        return
    assert any(_names(ln, path, op, new) or (ln.startswith("(root): ") and "Nyquist" in ln
                                             and "digitizer.sample_rate_hz" in ln) for ln in lines), (
        f"changing {path} ({op} {new!r}) gave: {text}")


def _check_scene(sc: Scene) -> None:
    """A scene that loads holds no NaN or inf and starts a simulator."""
    assert isinstance(sc, Scene)
    assert _all_finite(sc.model_dump()), "a scene holds a NaN or inf"
    Simulator(sc)


@given(data=st.data(), which=st.integers(0, len(_SCENE_DOCS) - 1))
def test_scene_from_dict_names_the_changed_field(data: st.DataObject, which: int) -> None:
    bad, path, op, value = _draw_mutation(data, _SCENE_DOCS[which], _toml_value, st.text(max_size=8))
    try:
        sc = scene_from_dict(bad)
    except SceneError as err:
        _check_scene_error(err, path, op, value)
        event("scene: refused")
        return
    event("scene: valid")
    _check_scene(sc)


_NUMBER_PATHS = [(i, path) for i, doc in enumerate(_SCENE_DOCS) for path in _paths(doc)
                 if isinstance(_get(doc, path), (int, float)) and not isinstance(_get(doc, path), bool)]


@given(where=st.sampled_from(_NUMBER_PATHS),
       value=_extreme_float | _extreme_int | st.floats() | st.integers() | st.integers(-3, 3))
@example(where=(0, ("seed",)), value=-1)  # was accepted, then numpy's generator refused it
def test_scene_numbers_at_their_extremes(where: tuple[int, PathT], value: float | int) -> None:
    """Every number of a scene set to an extreme (negative, zero, huge, NaN, inf): refused naming
    that field, or a scene that holds no NaN and starts a simulator (a negative ``seed`` was
    accepted and then failed in numpy's generator)."""
    which, path = where
    try:
        sc = scene_from_dict(_mutate(_SCENE_DOCS[which], path, "replace", value))
    except SceneError as err:
        _check_scene_error(err, path)
        event(f"scene: refused {path[-1]}")
        return
    _check_scene(sc)
    assert isinstance(value, int) or math.isfinite(value)


_TOML_TOKENS = ["nan", "inf", "-inf", "+inf", "-nan", "1e999", "-1", "0", "1e-400", '"x"', "''", "[]", "[1, 2]",
                "{}", "{ a = 1 }", "true", "1979-05-27T07:32:00Z", "07:32:00", "9223372036854775807",
                "9223372036854775808", "0x7fffffffffffffff", "-0.0", "1_000", '"""', "[[]]"]
_ASSIGN = re.compile(r"^(\s*)([A-Za-z_][\w-]*)(\s*=\s*)(.*)$")
_tmp = Path(tempfile.mkdtemp(prefix="mtcw-fuzz-"))  # the files the loaders read (rewritten per case)
atexit.register(shutil.rmtree, _tmp, True)


@given(name=st.sampled_from(sorted(_SCENE_TEXTS)), data=st.data())
def test_load_scene_toml_with_one_value_changed(name: str, data: st.DataObject) -> None:
    """A bundled scene's TOML with one ``key = value`` line's value replaced: a scene or a
    SceneError; a NaN or inf anywhere is refused naming its key."""
    lines = _SCENE_TEXTS[name].splitlines()
    at = data.draw(st.sampled_from([i for i, ln in enumerate(lines) if _ASSIGN.match(ln)]), label="line")
    token = data.draw(st.sampled_from(_TOML_TOKENS) | st.text(max_size=12), label="value")
    indent, key, eq, _ = _ASSIGN.match(lines[at]).groups()
    lines[at] = f"{indent}{key}{eq}{token}"
    path = _tmp / f"{name}.toml"
    path.write_text("\n".join(lines) + "\n")
    try:
        sc = load_scene(path)
    except SceneError as err:
        _check_scene_error(err, None)
        try:
            tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError:
            assert str(err).startswith("cannot read scene"), str(err)
        else:  # valid TOML, refused by the schema: the key is named
            assert key in str(err), (key, str(err))
        return
    _check_scene(sc)
    assert token.lstrip("+-") not in ("nan", "inf"), f"{key} = {token} was accepted"


@given(data=st.data(), which=st.integers(0, len(_SCENE_DOCS) - 1))
def test_load_scene_json_names_the_changed_field(data: st.DataObject, which: int) -> None:
    bad, path, op, value = _draw_mutation(data, json.loads(json.dumps(_SCENE_DOCS[which])), _json_value,
                                          st.text(max_size=8))
    f = _tmp / "scene.json"
    f.write_text(json.dumps(bad))
    try:
        sc = load_scene(f)
    except SceneError as err:
        _check_scene_error(err, path, op, value)
        return
    _check_scene(sc)


@given(raw=st.binary(max_size=200) | st.text(max_size=200).map(str.encode), suffix=st.sampled_from([".toml",
                                                                                                   ".json"]),
       head=st.sampled_from([b"", b"\xff\xfe", b"\xef\xbb\xbf", _SCENE_TEXTS["cw-bench"].encode()[:300]]))
@example(raw=b"\x80", suffix=".toml", head=b"")  # was a UnicodeDecodeError
def test_load_scene_is_total_on_arbitrary_bytes(raw: bytes, suffix: str, head: bytes) -> None:
    f = _tmp / f"raw{suffix}"
    f.write_bytes(head + raw)
    try:
        sc = load_scene(f)
    except SceneError as err:
        _check_scene_error(err, None)
        return
    _check_scene(sc)


# ---------------------------------------------------------------------------------------------
# calibration files
_CAL_DOCS = [Calibration(tones_hz=(5e8, 7e8, 9.5e8), tone_phases_rad=(0.1, -0.2, 0.3), tau0_s=3.3e-9,
                         known_range_m=0.065, frames_used=4, phase_std_rad=(1e-3, 1e-3, 2e-3), source="rec",
                         created="2026-01-01T00:00:00Z").model_dump(mode="json"),
             Calibration(tones_hz=(5e8, 7e8), tone_phases_rad=(0.0, 0.0), tau0_s=0.0).model_dump(mode="json")]
_CAL_MODEL_CHECKS = ("differ in length", "positive and distinct")


def _load_calibration(text: bytes, path: PathT | None = None, op: str = "", new: Any = None) -> Calibration | None:
    """Calibration.load of a file holding ``text``: a calibration, or a CalibrationError
    ``calibration <file>: <field>: <message>`` naming the changed ``path`` when there is one."""
    f = _tmp / "cal.json"
    f.write_bytes(text)
    try:
        cal = Calibration.load(f)
    except CalibrationError as err:
        head = f"calibration {f}: "
        assert str(err).startswith(head), str(err)
        rest = str(err)[len(head):]
        if path is not None:
            assert _names(rest, path, op, new) or (
                rest.startswith("(file): ") and any(c in rest for c in _CAL_MODEL_CHECKS)), f"changing {path}: {err}"
        event(f"calibration: {rest.split(':')[0].split('.')[0]}")
        return None
    assert isinstance(cal, Calibration) and len(cal.tones_hz) == len(cal.tone_phases_rad)
    assert _all_finite(cal.model_dump())
    return cal


@given(data=st.data(), which=st.integers(0, len(_CAL_DOCS) - 1))
def test_calibration_names_the_changed_field(data: st.DataObject, which: int) -> None:
    bad, path, op, value = _draw_mutation(data, _CAL_DOCS[which], _json_value, st.text(max_size=8))
    _load_calibration(json.dumps(bad).encode(), path, op, value)


@given(raw=st.binary(max_size=200) | _json_value.map(lambda v: json.dumps(v).encode())
       | st.sampled_from([b"", b"\xff", b"[" * 10_000, b"{" * 10_000, b'{"tones_hz": [1e400, 2]}', b"null"]))
def test_calibration_is_total_on_arbitrary_bytes(raw: bytes) -> None:
    _load_calibration(raw)


@pytest.mark.parametrize("where", ["no/such/dir/cal.json", "", ".", "a\0b"])
def test_calibration_load_refuses_unreadable_paths_with_its_error(where: str) -> None:
    with pytest.raises(CalibrationError, match="cannot read calibration"):
        Calibration.load(where)


# ---------------------------------------------------------------------------------------------
# service settings: flags and MTCW_* environment variables
_SETTINGS: list[type[BaseSettings]] = [ApiSettings, WorkerSettings, AcquisitionSettings]
_env_text = (st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\0"), max_size=16)
             | st.sampled_from(["", " ", "nan", "inf", "-inf", "-1", "0", "1e3", "1e999", "9" * 5000, "true",
                                "maybe", "[1]", "{}", '{"a": 1}', "null", "0x10", "1_000", "tcp://", "ipc://x",
                                "drop", "block", "fast", "sim", "replay", "/nonexistent", "65536"]))


def _check_settings(cls: type[BaseSettings], field: str, make: Any) -> None:
    """``make()`` is ``load(cls, ...)`` with one field given: settings, or a ValueError whose
    message starts with that field (names are matched without regard to case, as the settings
    read them)."""
    try:
        s = make()
    except ValueError as err:
        assert type(err) is ValueError  # load's own, not pydantic's
        assert str(err).lower().startswith((f"{field.lower()}:", f"{field.lower()}.")), (field, str(err))
        event(f"settings: refused {field}")
        return
    assert isinstance(s, cls)
    event("settings: valid")


_clean_env = {k: v for k, v in os.environ.items() if not k.startswith("MTCW_")}


@given(cls=st.sampled_from(_SETTINGS), data=st.data(), value=_env_text)
def test_settings_from_the_environment_are_total(cls: type[BaseSettings], data: st.DataObject, value: str) -> None:
    field = data.draw(st.sampled_from(sorted(cls.model_fields)), label="field")
    with mock.patch.dict(os.environ, {**_clean_env, f"MTCW_{field.upper()}": value}, clear=True):
        _check_settings(cls, field, lambda: load(cls))


@given(cls=st.sampled_from(_SETTINGS), data=st.data(),
       value=_json_value | st.binary(max_size=8) | st.builds(Path, st.text(max_size=8)))
def test_settings_from_flags_are_total(cls: type[BaseSettings], data: st.DataObject, value: Any) -> None:
    field = data.draw(st.sampled_from(sorted(cls.model_fields)) | st.from_regex(
        r"[A-Za-z][A-Za-z0-9_]{0,7}", fullmatch=True), label="field")  # a field, or an unknown (or upper-case) one
    assume(value is not None)  # None means "flag not given"
    with mock.patch.dict(os.environ, _clean_env, clear=True):
        _check_settings(cls, field, lambda: load(cls, **{field: value}))


# Values the settings once accepted and a service then died of (found by the fuzzing above): now refused,
# naming the field (finite, bounded timeouts; an endpoints file with a name; a file name the system takes).
@pytest.mark.parametrize("cls, value, field", [
    (AcquisitionSettings, "inf", "wait_for_worker_s"),  # OverflowError: int(inf * 1000) in Publisher.wait_for_worker
    (AcquisitionSettings, "1e300", "wait_for_worker_s"),  # OverflowError: zmq poll timeout beyond a C long
    (AcquisitionSettings, "inf", "end_timeout_s"),  # OverflowError in Publisher.finish
    (ApiSettings, "", "endpoints_file"),  # Path("") is ".": report_endpoints raises ValueError (empty name)
    (AcquisitionSettings, "9" * 5000, "recording"),  # OSError (file name too long) escapes load itself
    (ApiSettings, "9" * 5000, "store_path"),  # OSError (file name too long) from is_dir, found by CI's fuzzing
    (AcquisitionSettings, "inf", "rate_hz"),
    (ApiSettings, "inf", "stale_after_s"),
    (ApiSettings, "nan", "reorder_timeout_s"),
])
def test_settings_a_service_cannot_use_are_refused(cls: type[BaseSettings], value: str, field: str) -> None:
    with mock.patch.dict(os.environ, {**_clean_env, f"MTCW_{field.upper()}": value}, clear=True):
        with pytest.raises(ValueError, match=f"^{field}:"):
            load(cls)


# ---------------------------------------------------------------------------------------------
# chain profiles and their overrides
@given(name=st.sampled_from(sorted(PROFILES)) | st.text(max_size=8) | st.none() | st.integers()
       | st.lists(st.text(max_size=2), max_size=2),
       overrides=st.dictionaries(st.sampled_from(sorted(ChainSettings.model_fields))
                                 | st.text(min_size=1, max_size=6).filter(lambda k: k != "name"),
                                 _extreme_float | _extreme_int | _json_value, max_size=2))
@example(name="balanced", overrides={"range_min_m": math.nan})  # was accepted: a NaN bound switches a check off
@example(name="fast", overrides={"min_line_snr_db": -math.inf})
@example(name=[], overrides={})  # was a TypeError
def test_get_profile_is_total_and_refuses_non_finite_overrides(name: Any, overrides: dict) -> None:
    """An unknown profile is named as such; a bad override is named (``profile fast: <key>: ...``);
    accepted settings hold no NaN or inf."""
    try:
        s = get_profile(name, **overrides)
    except ValueError as err:
        text = str(err)
        if text.startswith("profile: unknown"):
            assert not (isinstance(name, str) and name in PROFILES), text
            return
        assert text.startswith(f"profile {name}: "), text
        assert any(_names(text[len(f"profile {name}: "):], (k,)) for k in overrides), (overrides, text)
        return
    assert isinstance(s, ChainSettings) and name in PROFILES
    assert _all_finite(s.model_dump()), f"overrides {overrides} accepted a NaN or inf"


# ---------------------------------------------------------------------------------------------
# the HTTP API against its own OpenAPI schema (schemathesis, in process)
def _api_with_points() -> Any:
    """An app (no receiver thread) whose store holds points from two sources, one rejected point
    and one undecodable frame's rejection; ready for the whole run (``/readyz`` answers 503, a
    server error to schemathesis, once the last point is ``stale_after_s`` old)."""
    app = create_app(_api_settings(reorder_timeout_s=2.0, reorder_max=256, stale_after_s=86_400.0), start_receiver=False)
    store: PointStore = app.state.store
    now = time.monotonic()
    for seq in range(4):
        store.add(msgspec.structs.replace(_result_point(), seq=seq, source="bench"), now)
    store.add(rejected_point("other", 0, 5, "too_long: 1e9 samples", run=2), now)
    store.add(rejected_point("", -1, 0, "malformed_bad_size: samples"), now)
    return app


# Loaded when this module is imported (schemathesis' lazy loader, ``from_fixture``, does not run
# under pytest 9: it sets a private attribute of the test item).
_openapi = schemathesis.openapi.from_asgi("/openapi.json", _api_with_points())


@_openapi.parametrize()
def test_http_api_conforms_to_its_openapi_schema(case: Any) -> None:
    """Every operation, positive and negative cases: never a 5xx, status codes, content types and
    bodies as documented, invalid requests refused (schemathesis' default checks).

    One leniency is let through: a query parameter given several times (``?since_seq={}&since_seq=0``)
    is answered with the last value, as FastAPI reads repeated scalar parameters, where the schema
    (one integer) calls the request invalid (found by ``--long``; refusing it is the API's call).
    """
    repeated = any(isinstance(v, list) for v in (case.query or {}).values())
    case.call_and_validate(excluded_checks=[negative_data_rejection] if repeated else None)
    event(f"http: {case.method} {case.path}{' (repeated parameter)' if repeated else ''}")


def test_http_latest_without_points_is_a_documented_404() -> None:
    """``/v1/points/latest`` before any point: 404 with a ``detail``, as the schema documents it."""
    app = create_app(_api_settings(), start_receiver=False)
    case = schemathesis.openapi.from_asgi("/openapi.json", app)["/v1/points/latest"]["GET"].Case()
    r = case.call_and_validate()
    assert r.status_code == 404 and r.json() == {"detail": "no points received yet"}
