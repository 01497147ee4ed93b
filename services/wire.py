"""Wire format version 1: ZeroMQ multipart messages with msgpack maps (docs/wire-format.md).

Frame message: ``[b"frame", header, samples]``; point message: ``[b"points", point]``;
end-of-run message: ``[b"end", end]`` (the acquisition node's last word on a run, passed on by a
worker to the API, so that frames lost at the tail of a run are counted too).

Each message has one schema, a :class:`msgspec.Struct` (:class:`FrameHeader`,
:class:`PointMessage`, :class:`EndMessage`), used by every service to build and to read it;
``msgspec.msgpack`` decodes straight into it and validates while decoding (types, finite
numbers, allowed values). The decoders are total: whatever bytes come in, the result is a typed
message or a :class:`WireError` whose ``reason`` is a short metric label and whose ``field``
names the offending field; no other exception escapes.

Samples travel as the raw little-endian buffer, channel-major, and are sent and received
without copying (``copy=False`` on both ends; the receiver wraps the ZeroMQ buffer with
``np.frombuffer``). A frame's fields are mapped to and from plain values by
:func:`mtcw_core.frame.frame_to_dict` / :func:`~mtcw_core.frame.frame_from_dict`, the same
mapping the SigMF recordings use.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Sequence
from typing import Annotated, Any, Literal, Optional, TypeVar

import msgspec
import numpy as np
from msgspec import Meta, Struct

from mtcw_core.results import FrameResult  # a leaf: the API never imports the chain
from mtcw_core.frame import SAMPLE_DTYPES, Frame, frame_from_dict, frame_to_dict

VERSION = 1
FRAME_TOPIC = b"frame"
POINTS_TOPIC = b"points"
END_TOPIC = b"end"

# ---------------------------------------------------------------------------------------------
# field types: what a number on the wire may be
_MAX = sys.float_info.max
#: a finite float (NaN and +-inf are refused; an integer is accepted as a float)
Finite = Annotated[float, Meta(ge=-_MAX, le=_MAX)]
#: a finite float > 0
Positive = Annotated[float, Meta(gt=0.0, le=_MAX)]
#: a finite float >= 0
NonNegative = Annotated[float, Meta(ge=0.0, le=_MAX)]
#: an integer >= 0 (msgpack uint)
UInt = Annotated[int, Meta(ge=0)]
Receiver = Literal["single", "balanced", "iq"]
Architecture = Literal["unmodulated_lo", "modulated_reference"]
Status = Literal["ok", "no_target", "rejected"]
Direction = Literal["receding", "approaching", "unknown", "static"]
SampleDtype = Literal["<f4", "<f8", "<i2", "<i1"]
assert set(SampleDtype.__args__) == set(SAMPLE_DTYPES)  # type: ignore[attr-defined]


# ---------------------------------------------------------------------------------------------
# schemas
class Pulse(Struct, kw_only=True, frozen=True):
    """Quasi-CW gate timing of a frame."""

    period_s: Positive
    duty: Annotated[float, Meta(gt=0.0, le=1.0)]
    delay_s: Finite = 0.0


class Truth(Struct, kw_only=True, frozen=True):
    """Simulator truth for one target, at the record's centre."""

    range_m: Finite
    velocity_mps: Finite


class FrameHeader(Struct, kw_only=True, frozen=True, omit_defaults=True):
    """The header (part 2) of a frame message; optional keys are absent when they have no value."""

    v: int
    source: str
    seq: UInt
    t_ns: UInt
    fs_hz: Positive
    n: Annotated[int, Meta(ge=1)]
    dtype: SampleDtype
    channels: Annotated[list[Annotated[str, Meta(min_length=1)]], Meta(min_length=1)]
    scale: Finite
    offset: Finite
    tones_hz: list[Positive]
    wavelength_m: Positive
    receiver: Receiver
    tone_phases_rad: Optional[list[Finite]] = None
    pulse: Optional[Pulse] = None
    architecture: Architecture = "unmodulated_lo"
    truth: Optional[list[Truth]] = None
    run: Optional[UInt] = None


class TargetMessage(Struct, kw_only=True, frozen=True):
    """One target of a point message; every key is always sent."""

    range_m: Finite
    range_sigma_m: NonNegative
    velocity_mps: Finite
    velocity_sigma_mps: NonNegative
    direction: Direction
    snr_db: Finite
    margin: Finite
    near_edge: bool = False
    cycle_ambiguous: bool = False
    blended: bool = False
    chi2_per_dof: NonNegative = 1.0
    residual_rms_rad: NonNegative = 0.0
    cycle_slip_prob: Annotated[float, Meta(ge=0, le=1)] = 0.0
    speed_min_mps: NonNegative = 0.0
    fit_r2: Optional[Finite] = None  # the AB-MTCW sine fit's R^2 (technique ab only)
    accumulated_frames: Annotated[int, Meta(ge=1, le=1024)] = 1  # frames the point rests on (--accumulate K)
    # --track K (mtcw_core.ranging.track): the point's track, the points its rate rests on, the rate (m/s)
    track_id: Optional[Annotated[int, Meta(ge=1)]] = None
    track_frames: Annotated[int, Meta(ge=0, le=1024)] = 0
    range_rate_mps: Optional[Finite] = None
    range_rate_sigma_mps: Optional[NonNegative] = None


class PointMessage(Struct, kw_only=True, frozen=True, omit_defaults=True):
    """The body (part 2) of a point message: a worker's result for one frame.

    ``seq = -1`` for a message that was not a decodable frame. ``processing_s`` is the worker's
    own time for the frame (decode, chain, encode). There is no latency on the wire: the API
    measures trigger-to-point latency when a point reaches it (:class:`ServedPoint`).
    """

    v: int
    source: str
    seq: Annotated[int, Meta(ge=-1)]
    t_ns: UInt
    status: Status
    profile: str
    targets: list[TargetMessage]
    unambiguous_range_m: Optional[Finite]
    coarse_range_m: Optional[Finite]
    stage_seconds: dict[str, NonNegative]
    reason: Optional[str] = None
    run: Optional[UInt] = None
    tone_snr_db: dict[str, Finite] = {}
    processing_s: Optional[NonNegative] = None
    technique: Annotated[str, Meta(max_length=16)] = "pb"


class ServedPoint(PointMessage, kw_only=True, frozen=True, omit_defaults=True):
    """A point as the API serves it: the point message plus ``latency_s``, the time from the
    frame's trigger (``t_ns``, stamped by the acquisition node) to the point's arrival at the API,
    by the API's clock. Not a wire message."""

    latency_s: Optional[float] = None


class EndMessage(Struct, kw_only=True, frozen=True, omit_defaults=True):
    """The end-of-run notice: run ``run`` of ``source`` published ``seq`` 0 .. ``frames - 1``; the
    node itself dropped ``dropped`` of them (no worker free)."""

    v: int
    source: str
    frames: UInt
    t_ns: UInt
    dropped: UInt
    run: Optional[UInt] = None


class _Versioned(Struct):
    v: Any = None


# ---------------------------------------------------------------------------------------------
class WireError(ValueError):
    """A message that is not valid wire format v1.

    Attributes
    ----------
    reason : str
        Short metric label: ``bad_parts``, ``bad_topic``, ``bad_msgpack``, ``bad_version``,
        ``missing_key``, ``bad_field``, ``bad_size`` (or ``dtype`` on encoding).
    field : str or None
        The offending field as a path into the message (``targets[0].range_m``), when there is one.
    detail : str
        What is wrong, in words.
    """

    def __init__(self, reason: str, detail: str, field: str | None = None) -> None:
        super().__init__(f"{reason}: {field}: {detail}" if field else f"{reason}: {detail}")
        self.reason = reason
        self.field = field
        self.detail = detail


_AT = re.compile(r" - at `(?:key` in `)?\$(.*)`$")
_MISSING = re.compile(r"^Object missing required field `([^`]*)`")
_BOUND = re.compile(r"^Expected `float` ([<>]=?) (\S+)$")


def _validation_error(err: Exception, what: str) -> WireError:
    """A msgspec ValidationError -> :class:`WireError` naming the field (``targets[0].range_m``)."""
    msg = str(err)
    at = _AT.search(msg)
    path = at.group(1).lstrip(".") if at else ""
    detail = _AT.sub("", msg)
    if "`key` in" in msg:
        detail += " (a map key)"
    missing = _MISSING.match(msg)
    if missing:
        field = f"{path}.{missing.group(1)}" if path else missing.group(1)
        return WireError("missing_key", f"required in a {what} message", field)
    if not path:  # the message itself is not a map
        return WireError("bad_msgpack", f"{what}: {detail}")
    bound = _BOUND.match(detail)
    if bound:  # a float out of its range; NaN is out of every range
        within = "" if abs(float(bound.group(2))) >= _MAX else f" {bound.group(1)} {bound.group(2)}"
        detail = f"must be a finite number{within}"
    return WireError("bad_field", detail, path)


S = TypeVar("S", bound=Struct)
_DECODERS: dict[type, msgspec.msgpack.Decoder] = {}
_ENCODER = msgspec.msgpack.Encoder()


def _decode(buf: Any, schema: type[S], what: str) -> S:
    """msgpack bytes -> ``schema``, version checked; any failure -> :class:`WireError`."""
    dec = _DECODERS.get(schema)
    if dec is None:
        dec = _DECODERS[schema] = msgspec.msgpack.Decoder(schema)
    try:
        msg = dec.decode(buf)
    except msgspec.ValidationError as err:
        _check_version(_loose_version(buf), what)  # a v2 message fails v1's schema: say so first
        raise _validation_error(err, what) from None
    except Exception as err:  # DecodeError on garbage, RecursionError on deep nesting, ...
        raise WireError("bad_msgpack", f"{what}: {type(err).__name__}: {err}") from None
    _check_version(msg.v, what)
    return msg


def _loose_version(buf: Any) -> Any:
    try:
        return msgspec.msgpack.decode(buf, type=_Versioned).v
    except Exception:
        return VERSION  # not even a map with a v: the schema's error says more


def _check_version(v: Any, what: str) -> None:
    if v != VERSION or isinstance(v, bool):
        raise WireError("bad_version", f"{what}: v={v!r}, this decoder speaks v{VERSION}", "v")


def _part(part: Any) -> memoryview:
    """A message part (bytes, zmq.Frame, buffer) as a memoryview of its bytes."""
    try:
        return memoryview(part.buffer if hasattr(part, "buffer") else part).cast("B")
    except (TypeError, ValueError) as err:
        raise WireError("bad_parts", f"a message part is not a byte buffer ({type(part).__name__}: {err})") from None


def _split(parts: Any, topic: bytes, n: int, what: str) -> list[memoryview]:
    """Check a multipart message's length and topic; returns its parts as memoryviews."""
    try:
        count = len(parts)
    except TypeError:
        raise WireError("bad_parts", f"{what} message is a {type(parts).__name__}, not a list of parts") from None
    if count != n:
        raise WireError("bad_parts", f"{what} message has {count} parts, expected {n}")
    views = [_part(p) for p in parts]
    if views[0] != topic:
        raise WireError("bad_topic", f"topic {bytes(views[0][:16])!r}, expected {topic!r}")
    return views


# ---------------------------------------------------------------------------------------------
# frame messages
def frame_header(frame: Frame) -> FrameHeader:
    """The header of ``frame``'s message (everything but the samples), validated.

    Raises
    ------
    WireError
        When the frame cannot be sent as it is (a non-finite number, an unknown dtype, ...).
    """
    try:
        d = frame_to_dict(frame)
    except ValueError as err:
        raise WireError("dtype", str(err), "dtype") from None
    try:
        return msgspec.convert({"v": VERSION, **d}, FrameHeader)
    except msgspec.ValidationError as err:
        raise _validation_error(err, "frame") from None


def encode_frame(frame: Frame) -> list:
    """``[b"frame", header, samples]``; the samples part is a zero-copy view of the frame's array
    (a copy only when they are not little-endian or not contiguous)."""
    h = frame_header(frame)
    s = frame.samples
    if s.dtype.byteorder == ">":
        s = s.astype(s.dtype.newbyteorder("<"))
    s = np.ascontiguousarray(s)
    return [FRAME_TOPIC, _ENCODER.encode(h), memoryview(s).cast("B")]


def decode_header(part: Any) -> FrameHeader:
    """A frame header, validated; raises :class:`WireError` naming the field."""
    h = _decode(_part(part), FrameHeader, "frame header")
    if h.tone_phases_rad is not None and len(h.tone_phases_rad) != len(h.tones_hz):
        raise WireError("bad_field", f"{len(h.tone_phases_rad)} phases for {len(h.tones_hz)} tones",
                        "tone_phases_rad")
    need = ("i", "q") if h.receiver == "iq" else ("pd",)
    if not set(need) <= set(h.channels):
        raise WireError("bad_field", f"receiver {h.receiver!r} needs channels {list(need)}, got {h.channels}",
                        "channels")
    return h


def decode_frame(parts: Sequence) -> Frame:
    """``[b"frame", header, samples]`` -> :class:`Frame` (samples wrap the received buffer, read-only).

    Raises
    ------
    WireError
        With a reason: ``bad_parts``, ``bad_topic``, ``bad_msgpack``, ``bad_version``,
        ``missing_key``, ``bad_field`` or ``bad_size``, and the field.
    """
    _, head, buf = _split(parts, FRAME_TOPIC, 3, "frame")
    h = decode_header(head)
    dt = np.dtype(h.dtype)
    expect = len(h.channels) * h.n * dt.itemsize
    if buf.nbytes != expect:
        raise WireError("bad_size", f"samples are {buf.nbytes} bytes; {len(h.channels)} channels x {h.n} x "
                                    f"{dt.itemsize} B = {expect} expected", "samples")
    samples = np.frombuffer(buf, dtype=dt).reshape(len(h.channels), h.n)
    return frame_from_dict(msgspec.to_builtins(h), samples)


# ---------------------------------------------------------------------------------------------
# point messages
def point_from_result(res: FrameResult, run: int | None = None, processing_s: float | None = None) -> PointMessage:
    """The point message for a chain result (``run``: the frame's run id, passed through).

    A result that the schema refuses (a non-finite sigma, say) becomes a ``rejected`` point with
    reason ``bad_result: <field>: ...``, so that it is counted rather than lost at the API.
    """
    t0 = res.targets[0] if res.targets else None
    d = _plain({
        "v": VERSION, "source": res.source, "seq": int(res.seq), "t_ns": int(res.t_ns), "status": res.status,
        "profile": res.profile, "technique": res.technique,
        "targets": [{f: getattr(t, f) for f in TargetMessage.__struct_fields__} for t in res.targets],
        "unambiguous_range_m": res.unambiguous_range_m, "coarse_range_m": res.coarse_range_m,
        "stage_seconds": dict(res.stage_seconds), "reason": res.reason if res.status != "ok" else None,
        "run": run, "tone_snr_db": dict(t0.tone_snr_db) if t0 is not None else {}, "processing_s": processing_s,
    })
    try:
        return msgspec.convert(d, PointMessage)
    except msgspec.ValidationError as err:
        e = _validation_error(err, "result")
        return rejected_point(res.source, res.seq, res.t_ns, f"bad_result: {e.field}: {e.detail}", run=run,
                              profile=res.profile, processing_s=processing_s)


def _plain(x: Any) -> Any:
    """numpy scalars (``np.bool_``, ``np.float64``, ...) -> Python ones, recursively through dicts and lists."""
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    return x.item() if isinstance(x, np.generic) else x


def rejected_point(source: str, seq: int, t_ns: int, reason: str, run: int | None = None, profile: str = "",
                   processing_s: float | None = None) -> PointMessage:
    """A ``rejected`` point message (no targets) with ``reason`` (``key: detail``)."""
    return PointMessage(v=VERSION, source=source, seq=seq, t_ns=max(int(t_ns), 0), status="rejected",
                        profile=profile, targets=[], unambiguous_range_m=None, coarse_range_m=None,
                        stage_seconds={}, reason=reason, run=run, processing_s=processing_s)


class _Identity(Struct):
    """What a worker can still read of a frame header it refuses (each field independently)."""

    source: Any = ""
    seq: Any = -1
    t_ns: Any = 0
    run: Any = None


def rejection_point(err: WireError, parts: Any, processing_s: float | None = None) -> PointMessage:
    """The point message for a frame message the decoder refused, with reason
    ``malformed_<reason>: <detail>``; ``source``, ``seq``, ``t_ns`` and ``run`` are kept when
    readable, else ``""``, ``-1`` (not ordered, only counted), ``0`` and none."""
    ident = _Identity()
    try:
        ident = msgspec.msgpack.decode(_part(parts[1]), type=_Identity)
    except Exception:  # unreadable: the defaults say so
        pass

    def _uint(x: Any) -> int | None:
        return x if isinstance(x, int) and not isinstance(x, bool) and 0 <= x < 2**64 else None

    source = ident.source if isinstance(ident.source, str) else ""
    seq = _uint(ident.seq)
    detail = f"{err.field}: {err.detail}" if err.field else err.detail
    return rejected_point(source, -1 if seq is None else seq, _uint(ident.t_ns) or 0,
                          f"malformed_{err.reason}: {detail}", run=_uint(ident.run), processing_s=processing_s)


def encode_points(msg: PointMessage) -> list[bytes]:
    """``[b"points", point]``."""
    return [POINTS_TOPIC, _ENCODER.encode(msg)]


def decode_points(parts: Sequence) -> PointMessage:
    """``[b"points", point]`` -> :class:`PointMessage`, every target checked; raises :class:`WireError`."""
    _, body = _split(parts, POINTS_TOPIC, 2, "points")
    return _decode(body, PointMessage, "points")


# ---------------------------------------------------------------------------------------------
# end-of-run messages
def end_message(source: str, run: int | None, frames: int, t_ns: int, dropped: int) -> EndMessage:
    """The end-of-run notice of run ``run`` of ``source``: it published seq ``0 .. frames - 1``, of
    which the node itself could not hand ``dropped`` to a worker."""
    return EndMessage(v=VERSION, source=source, frames=int(frames), t_ns=int(t_ns), dropped=int(dropped),
                      run=None if run is None else int(run))


def encode_end(msg: EndMessage) -> list[bytes]:
    """``[b"end", end]``."""
    return [END_TOPIC, _ENCODER.encode(msg)]


def decode_end(parts: Sequence) -> EndMessage:
    """``[b"end", end]`` -> :class:`EndMessage`; raises :class:`WireError`."""
    _, body = _split(parts, END_TOPIC, 2, "end")
    return _decode(body, EndMessage, "end")


def topic(parts: Any) -> bytes:
    """The first part of a message (b"" when there is none), to choose a decoder; never raises."""
    try:
        return bytes(_part(parts[0])) if len(parts) else b""
    except Exception:
        return b""
