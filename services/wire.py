"""Wire format version 1: ZeroMQ multipart messages with msgpack headers (docs/wire-format.md).

Frame message: ``[b"frame", header, samples]``; point message: ``[b"points", result]``;
end-of-run message: ``[b"end", header]`` (the acquisition node's last word on a run, passed on
by a worker to the API, so that frames lost at the tail of a run are counted too).
Samples travel as the raw little-endian buffer, channel-major, and are sent and received
without copying (``copy=False`` on both ends; the receiver wraps the ZeroMQ buffer with
``np.frombuffer``).
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import msgpack
import numpy as np

from mtcw_core.chain import FrameResult
from mtcw_core.frame import SAMPLE_DTYPES, Frame, PulseInfo, TruthTarget

VERSION = 1
FRAME_TOPIC = b"frame"
POINTS_TOPIC = b"points"
END_TOPIC = b"end"
_RECEIVERS = ("single", "balanced", "iq")
_FRAME_KEYS = ("v", "source", "seq", "t_ns", "fs_hz", "n", "dtype", "channels", "scale", "offset", "tones_hz",
               "wavelength_m", "receiver")
_POINT_KEYS = ("v", "source", "seq", "t_ns", "status", "profile", "targets")
#: fields of each target in a point message (the spec's list, plus the quality fields)
TARGET_KEYS = ("range_m", "range_sigma_m", "velocity_mps", "velocity_sigma_mps", "direction", "snr_db", "margin",
               "near_edge", "cycle_ambiguous", "blended", "chi2_per_dof", "residual_rms_rad")


class WireError(ValueError):
    """A message that is not valid wire format v1; ``reason`` is a short metric label."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


def _finite(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


# ---------------------------------------------------------------------------------------------
def frame_header(frame: Frame) -> dict:
    """The msgpack-able header of a frame (everything but the samples)."""
    h: dict[str, Any] = {
        "v": VERSION, "source": frame.source, "seq": int(frame.seq), "t_ns": int(frame.t_ns),
        "fs_hz": float(frame.fs_hz), "n": frame.n, "dtype": frame.samples.dtype.newbyteorder("<").str,
        "channels": list(frame.channels), "scale": float(frame.scale), "offset": float(frame.offset),
        "tones_hz": [float(f) for f in frame.tones_hz], "wavelength_m": float(frame.wavelength_m),
        "receiver": frame.receiver,
    }
    if frame.tone_phases_rad is not None:
        h["tone_phases_rad"] = [float(p) for p in frame.tone_phases_rad]
    if frame.pulse is not None:
        h["pulse"] = frame.pulse.to_dict()
    if frame.architecture != "unmodulated_lo":
        h["architecture"] = frame.architecture
    if frame.truth is not None:
        h["truth"] = [t.to_dict() for t in frame.truth]
    if frame.extra.get("run") is not None:
        h["run"] = int(frame.extra["run"])
    return h


def encode_frame(frame: Frame) -> list:
    """``[b"frame", header, samples]``; the samples part is a zero-copy view of the frame's array."""
    s = frame.samples
    if s.dtype.str not in SAMPLE_DTYPES:
        s = s.astype(s.dtype.newbyteorder("<"))
    if s.dtype.str not in SAMPLE_DTYPES:
        raise WireError("dtype", f"samples dtype {frame.samples.dtype} is not one of {SAMPLE_DTYPES}")
    s = np.ascontiguousarray(s)
    return [FRAME_TOPIC, msgpack.packb(frame_header(frame), use_bin_type=True), memoryview(s).cast("B")]


def _unpack(buf, what: str) -> dict:
    try:
        obj = msgpack.unpackb(bytes(buf), raw=False, strict_map_key=True)
    except Exception as err:  # msgpack raises several unrelated types on garbage
        raise WireError("bad_msgpack", f"{what}: {type(err).__name__}: {err}") from None
    if not isinstance(obj, dict):
        raise WireError("bad_msgpack", f"{what} is a {type(obj).__name__}, not a map")
    return obj


def _check_version(h: dict) -> None:
    if h.get("v") != VERSION:
        raise WireError("bad_version", f"v={h.get('v')!r}, this decoder speaks v{VERSION}")


def decode_header(part) -> dict:
    """Parse and check a frame header; raises :class:`WireError` naming the field."""
    h = _unpack(part, "frame header")
    _check_version(h)
    missing = [k for k in _FRAME_KEYS if k not in h]
    if missing:
        raise WireError("missing_key", f"frame header lacks {', '.join(missing)}")
    if not isinstance(h["source"], str):
        raise WireError("bad_field", "source must be a string")
    for k in ("seq", "t_ns", "n"):
        if not isinstance(h[k], int) or isinstance(h[k], bool) or h[k] < 0:
            raise WireError("bad_field", f"{k} must be a non-negative integer, got {h[k]!r}")
    for k in ("fs_hz", "scale", "offset", "wavelength_m"):
        if not _finite(h[k]):
            raise WireError("bad_field", f"{k} must be a finite number, got {h[k]!r}")
    if h["dtype"] not in SAMPLE_DTYPES:
        raise WireError("bad_field", f"dtype {h['dtype']!r} not one of {SAMPLE_DTYPES}")
    if not (isinstance(h["channels"], list) and h["channels"] and all(isinstance(c, str) for c in h["channels"])):
        raise WireError("bad_field", "channels must be a non-empty list of names")
    if not (isinstance(h["tones_hz"], list) and all(_finite(f) for f in h["tones_hz"])):
        raise WireError("bad_field", "tones_hz must be a list of numbers")
    if h["receiver"] not in _RECEIVERS:
        raise WireError("bad_field", f"receiver {h['receiver']!r} not one of {_RECEIVERS}")
    tp = h.get("tone_phases_rad")
    if tp is not None and not (isinstance(tp, list) and len(tp) == len(h["tones_hz"]) and all(_finite(p) for p in tp)):
        raise WireError("bad_field", "tone_phases_rad must list one number per tone")
    if "run" in h and not (isinstance(h["run"], int) and not isinstance(h["run"], bool)):
        raise WireError("bad_field", "run must be an integer")
    p = h.get("pulse")
    if p is not None and not (isinstance(p, dict) and all(_finite(p.get(k)) for k in ("period_s", "duty"))):
        raise WireError("bad_field", "pulse must be a map with period_s and duty")
    return h


def decode_frame(parts: Sequence) -> Frame:
    """``[b"frame", header, samples]`` -> :class:`Frame` (samples wrap the received buffer, read-only).

    Raises :class:`WireError` with a reason: ``bad_parts``, ``bad_topic``, ``bad_msgpack``,
    ``bad_version``, ``missing_key``, ``bad_field`` or ``bad_size``.
    """
    if len(parts) != 3:
        raise WireError("bad_parts", f"frame message has {len(parts)} parts, expected 3")
    topic = bytes(parts[0])
    if topic != FRAME_TOPIC:
        raise WireError("bad_topic", f"topic {topic[:16]!r}, expected {FRAME_TOPIC!r}")
    h = decode_header(parts[1])
    buf = parts[2].buffer if hasattr(parts[2], "buffer") else parts[2]
    dt = np.dtype(h["dtype"])
    expect = len(h["channels"]) * h["n"] * dt.itemsize
    nbytes = memoryview(buf).nbytes
    if nbytes != expect:
        raise WireError("bad_size", f"samples are {nbytes} bytes; {len(h['channels'])} channels x {h['n']} x "
                                    f"{dt.itemsize} B = {expect} expected")
    samples = np.frombuffer(buf, dtype=dt).reshape(len(h["channels"]), h["n"])
    p = h.get("pulse")
    truth = h.get("truth")
    return Frame(
        samples=samples, fs_hz=float(h["fs_hz"]), tones_hz=tuple(float(f) for f in h["tones_hz"]),
        wavelength_m=float(h["wavelength_m"]), receiver=h["receiver"], channels=tuple(h["channels"]),
        scale=float(h["scale"]), offset=float(h["offset"]),
        tone_phases_rad=tuple(h["tone_phases_rad"]) if h.get("tone_phases_rad") is not None else None,
        pulse=PulseInfo(float(p["period_s"]), float(p["duty"]), float(p.get("delay_s", 0.0))) if p else None,
        architecture=h.get("architecture", "unmodulated_lo"), seq=h["seq"], t_ns=h["t_ns"], source=h["source"],
        truth=tuple(TruthTarget(float(t["range_m"]), float(t["velocity_mps"])) for t in truth) if truth else None,
        extra={"run": h["run"]} if "run" in h else {},
    )


# ---------------------------------------------------------------------------------------------
def result_message(res: FrameResult, latency_s: float | None = None, run: int | None = None) -> dict:
    """The point message body for a chain result (``run``: the frame's run id, passed through)."""
    out: dict[str, Any] = {
        "v": VERSION, "source": res.source, "seq": int(res.seq), "t_ns": int(res.t_ns), "status": res.status,
        "profile": res.profile,
        "targets": [{k: (bool(v) if isinstance(v, (bool, np.bool_)) else v) for k, v in
                     ((k, getattr(t, k)) for k in TARGET_KEYS)} for t in res.targets],
        "unambiguous_range_m": res.unambiguous_range_m, "coarse_range_m": res.coarse_range_m,
        "stage_seconds": dict(res.stage_seconds),
    }
    if res.status != "ok":
        out["reason"] = res.reason
    if res.targets:
        out["tone_snr_db"] = dict(res.targets[0].tone_snr_db)
    if latency_s is not None:
        out["latency_s"] = float(latency_s)
    if run is not None:
        out["run"] = int(run)
    return out


def encode_points(msg: dict) -> list[bytes]:
    return [POINTS_TOPIC, msgpack.packb(msg, use_bin_type=True)]


def _two_part(parts: Sequence, topic: bytes, what: str) -> dict:
    """``[topic, msgpack map]`` -> the map, its parts, topic and version checked."""
    if len(parts) != 2:
        raise WireError("bad_parts", f"{what} message has {len(parts)} parts, expected 2")
    if bytes(parts[0]) != topic:
        raise WireError("bad_topic", f"topic {bytes(parts[0])[:16]!r}, expected {topic!r}")
    m = _unpack(parts[1], what)
    _check_version(m)
    return m


def decode_points(parts: Sequence) -> dict:
    """``[b"points", result]`` -> dict; raises :class:`WireError`."""
    m = _two_part(parts, POINTS_TOPIC, "points")
    missing = [k for k in _POINT_KEYS if k not in m]
    if missing:
        raise WireError("missing_key", f"points message lacks {', '.join(missing)}")
    if m["status"] not in ("ok", "no_target", "rejected"):
        raise WireError("bad_field", f"status {m['status']!r}")
    if not isinstance(m["seq"], int) or isinstance(m["seq"], bool):
        raise WireError("bad_field", "seq must be an integer")
    if not isinstance(m["targets"], list):
        raise WireError("bad_field", "targets must be a list")
    return m


# ---------------------------------------------------------------------------------------------
def encode_end(source: str, run: int | None, frames: int, t_ns: int, dropped: int) -> list[bytes]:
    """``[b"end", header]``: the run ``run`` of ``source`` published seq ``0 .. frames - 1``.

    ``dropped`` is how many of them the acquisition node itself could not hand to a worker.
    """
    h: dict[str, Any] = {"v": VERSION, "source": source, "frames": int(frames), "t_ns": int(t_ns),
                         "dropped": int(dropped)}
    if run is not None:
        h["run"] = int(run)
    return [END_TOPIC, msgpack.packb(h, use_bin_type=True)]


def decode_end(parts: Sequence) -> dict:
    """``[b"end", header]`` -> dict with ``source``, ``frames``, ``t_ns``, ``dropped`` (and ``run``)."""
    h = _two_part(parts, END_TOPIC, "end")
    if not isinstance(h.get("source"), str):
        raise WireError("bad_field", "end: source must be a string")
    for k in ("frames", "t_ns", "dropped"):
        if not isinstance(h.get(k), int) or isinstance(h.get(k), bool) or h[k] < 0:
            raise WireError("bad_field", f"end: {k} must be a non-negative integer, got {h.get(k)!r}")
    if "run" in h and not (isinstance(h["run"], int) and not isinstance(h["run"], bool)):
        raise WireError("bad_field", "end: run must be an integer")
    return h
