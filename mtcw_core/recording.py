"""SigMF recordings of frames, with the ``mtcw`` extension namespace (version 1.0.0).

One capture segment per frame (``mtcw:seq``, ``core:datetime``, simulator truth as
``mtcw:truth``). Frames of a recording share fs, length, tones and channels. A frame's samples
are read on their own (``numpy.fromfile`` at the frame's offset), so a long recording is never
loaded whole.

Channel layout: SigMF interleaves channels sample by sample; a frame is channel-major. For an
IQ receiver the first two channels (``i``, ``q``) travel as one complex SigMF channel
(``cf32_le``, ``ci16_le``, ``ci8``); every further channel (``pulse_ref``) is a complex channel
of its own with zero imaginary part.

**Reading is total.** :meth:`Recording.open` validates the whole metadata file against one typed
schema (:class:`SigMFMeta`: :class:`GlobalInfo` and one :class:`Capture` per frame; pydantic,
strict JSON types, finite numbers) and checks every capture against the data file's size, so a
malformed recording is refused when it is opened, never at frame 500. Every problem is a
:class:`RecordingError` whose message names the file and the key as a path
(``x.sigmf-meta: global.mtcw:frame_samples: Input should be a valid integer, got 'abc'``).
A frame's fields follow the wire's rules (``docs/wire-format.md``: finite numbers, positive
rates, tones and wavelength, ``seq`` and the capture's time uint64, the receiver's channels
present), so a frame read from a recording can always be sent.

Keys: ``core`` keys this module does not use are ignored, as are keys of any other namespace
(SigMF allows them) and top-level keys other than ``global`` and ``captures`` (``annotations``
is not read). An **unknown ``mtcw:`` key is refused**: the namespace is ours, and a misspelt key
(``mtcw:tone_phase_rad``) would otherwise silently change the ranges. Non-conforming datasets
(``core:dataset``, ``core:trailing_bytes``, ``core:header_bytes``, ``core:metadata_only``) are
refused. The reader does not run ``sigmf``'s own validator (it checks the keys it uses); the
writer does.

**Writing survives a kill.** :class:`RecordingWriter` keeps the ``.sigmf-meta`` current while it
writes: after the first frame and then at most every ``checkpoint_s`` it flushes and fsyncs the
data file, then replaces the metadata atomically (temporary file, fsync, ``os.replace``), so the
metadata on disk only ever claims frames already in the data file. A recorder killed mid-run
(SIGKILL, power cut) leaves a recording that opens and yields every frame its metadata claims;
frames written after the last checkpoint are in the data file but not claimed. A frame is
checked before any of it is written: its fields against the reader's schema, and the global
section (at the first frame) by ``sigmf``'s validator. ``close()`` writes the final metadata with
the data file's ``core:sha512``, validated by ``sigmf``.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import re
import stat
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError, model_validator
from pydantic_core import PydanticCustomError

from .frame import Frame, Receiver, frame_from_dict, frame_to_dict

EXTENSION = {"name": "mtcw", "version": "1.0.0", "optional": False}

_REAL = {np.dtype("<f4"): "rf32_le", np.dtype("<f8"): "rf64_le", np.dtype("<i2"): "ri16_le", np.dtype("i1"): "ri8"}
_COMPLEX = {np.dtype("<f4"): "cf32_le", np.dtype("<f8"): "cf64_le", np.dtype("<i2"): "ci16_le", np.dtype("i1"): "ci8"}
_BY_NAME = {v: (k, False) for k, v in _REAL.items()} | {v: (k, True) for k, v in _COMPLEX.items()}
_BY_NAME["ri16_be"] = (np.dtype(">i2"), False)
_BY_NAME["ci16_be"] = (np.dtype(">i2"), True)

#: keys of :func:`~mtcw_core.frame.frame_to_dict` stored once per recording, as ``mtcw:<key>``
#: (``fs_hz`` as ``core:sample_rate``); ``n`` is ``mtcw:frame_samples``, ``dtype`` the
#: ``core:datatype``, ``scale``/``offset`` are stored for integer datatypes (and for float ones
#: when they are not 1, 0); ``seq``, ``t_ns`` (as ``core:datetime``) and ``truth`` go on each
#: frame's capture segment; a frame's ``run`` is not recorded (a replay is a new run of the
#: publisher that replays it).
_GLOBAL_KEYS = ("fs_hz", "tones_hz", "tone_phases_rad", "wavelength_m", "receiver", "architecture", "channels",
                "pulse", "source")
#: the largest unsigned integer on the wire (msgpack uint64): bound of ``mtcw:seq`` and of a
#: capture's time in ns since 1970 (2554-07-21)
U64_MAX = 2**64 - 1
_EPOCH_ORDINAL = _dt.date(1970, 1, 1).toordinal()
_DATETIME = re.compile(r"([0-9]{4})-([0-9]{2})-([0-9]{2})T([0-9]{2}):([0-9]{2}):([0-9]{2})(?:\.([0-9]+))?Z")


class RecordingError(ValueError):
    """A recording is malformed: the message names the file and the key or reason."""


# ---------------------------------------------------------------------------------------------
# the metadata schema
def _short(x: Any, n: int = 60) -> str:
    """``repr(x)``, cut to ``n`` characters."""
    r = repr(x)
    return r if len(r) <= n else r[: n - 3] + "..."


def _key_error(key: str, detail: str) -> PydanticCustomError:
    """An error about ``key`` of the section being validated (its path is completed with the key)."""
    return PydanticCustomError("mtcw_key", "{key}: {detail}", {"key": key, "detail": detail})


def _describe(err: ValidationError, root: tuple = ()) -> str:
    """The first error of ``err`` as ``path.to.key: what is wrong, got <value>`` (+ how many more)."""
    errors = err.errors(include_url=False)
    e = errors[0]
    loc = [*root, *e["loc"]]
    if e["type"] == "mtcw_key":
        loc.append(e["ctx"]["key"])
        msg = e["ctx"]["detail"]
    elif e["type"] == "value_error":
        msg = str(e["ctx"]["error"])
    elif e["type"] in ("missing", "json_invalid"):
        msg = e["msg"]
    else:
        msg = f"{e['msg']}, got {_short(e['input'])}"
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    path = ".".join(str(p) for p in loc)
    return f"{path}: {msg}{more}" if path else msg + more


def _t_ns(value: Any) -> int:
    """``core:datetime`` (RFC 3339 in UTC, ``YYYY-MM-DDTHH:MM:SS[.fraction]Z``, any number of
    fractional digits, cut to ns) -> ns since 1970-01-01 (a uint64)."""
    if not isinstance(value, str):
        raise ValueError(f"must be a string YYYY-MM-DDTHH:MM:SS[.fraction]Z, got {_short(value)}")
    m = _DATETIME.fullmatch(value)
    if m is None:
        raise ValueError(f"not a UTC time YYYY-MM-DDTHH:MM:SS[.fraction]Z: {_short(value)}")
    year, month, day, hour, minute, second = (int(g) for g in m.groups()[:6])
    try:
        date = _dt.date(year, month, day)
    except ValueError as err:
        raise ValueError(f"{_short(value)}: {err}") from None
    if hour > 23 or minute > 59 or second > 60:  # 60: a leap second
        raise ValueError(f"{_short(value)}: time of day out of range")
    seconds = (date.toordinal() - _EPOCH_ORDINAL) * 86400 + hour * 3600 + minute * 60 + second
    t = seconds * 1_000_000_000 + int((m.group(7) or "")[:9].ljust(9, "0"))
    if not 0 <= t <= U64_MAX:
        raise ValueError(f"{_short(value)}: outside 1970-01-01 .. 2554-07-21 (ns since 1970 as a uint64)")
    return t


def _iso(t_ns: int) -> str:
    """ns since 1970 -> ``core:datetime`` (microseconds, or nanoseconds when they are not 0)."""
    s, ns = divmod(t_ns, 1_000_000_000)
    t = _dt.datetime(1970, 1, 1) + _dt.timedelta(seconds=s)
    frac = f"{ns // 1000:06d}" if ns % 1000 == 0 else f"{ns:09d}"
    return t.strftime("%Y-%m-%dT%H:%M:%S") + f".{frac}Z"


def _sigmf_channels(n_channels: int, is_complex: bool) -> int:
    """SigMF channels holding ``n_channels`` frame channels (see the channel layout above)."""
    return max(n_channels - 1, 1) if is_complex else n_channels


Positive = Annotated[float, Field(gt=0)]
UInt64 = Annotated[int, Field(ge=0, le=U64_MAX)]
Datatype = Literal["rf32_le", "rf64_le", "ri16_le", "ri16_be", "ri8", "cf32_le", "cf64_le", "ci16_le", "ci16_be",
                   "ci8"]
assert set(Datatype.__args__) == set(_BY_NAME)  # type: ignore[attr-defined]
_ABSENT = object()


class _Model(BaseModel):
    # JSON types as written (no "3" for 3, no 3.0 for an integer), NaN and inf refused
    model_config = ConfigDict(strict=True, frozen=True, allow_inf_nan=False, extra="forbid")


class _Section(_Model):
    """A SigMF section (global, a capture): keys of other namespaces are allowed and ignored; an
    unknown ``mtcw:`` key or a key of a non-conforming dataset is refused."""

    model_config = ConfigDict(extra="allow")
    #: keys of non-conforming datasets: key -> the one value accepted (``_ABSENT``: none)
    _unsupported: ClassVar[dict[str, Any]] = {}

    @model_validator(mode="before")
    @classmethod
    def _known_keys(cls, data: Any) -> Any:
        if isinstance(data, dict):
            known = {f.alias for f in cls.model_fields.values()}
            for key, value in data.items():
                if key.startswith("mtcw:") and key not in known:
                    mine = ", ".join(sorted(k for k in known if k and k.startswith("mtcw:")))
                    raise _key_error(key, f"unknown key of the mtcw namespace here (known: {mine})")
                if key in cls._unsupported:
                    ok = cls._unsupported[key]
                    if ok is _ABSENT or type(value) is not type(ok) or value != ok:
                        raise _key_error(key, f"non-conforming datasets are not supported, got {_short(value)}")
        return data


class Pulse(_Model):
    """``mtcw:pulse``: the quasi-CW gate timing (s), as the wire's ``pulse``."""

    period_s: Positive
    duty: float = Field(gt=0, le=1)
    delay_s: float = 0.0


class Truth(_Model):
    """One target of ``mtcw:truth`` (simulator truth at the record's centre): m, m/s."""

    range_m: float
    velocity_mps: float


class GlobalInfo(_Section):
    """The ``global`` section: what every frame of the recording shares.

    Attributes are named after the keys without their namespace (``sample_rate`` is
    ``core:sample_rate`` in Hz, ``frame_samples`` is ``mtcw:frame_samples``); the ``frame_*``
    properties apply the defaults for absent keys.
    """

    _unsupported: ClassVar[dict[str, Any]] = {"core:dataset": _ABSENT, "core:trailing_bytes": 0,
                                              "core:metadata_only": False}

    datatype: Datatype = Field(alias="core:datatype")
    sample_rate: Positive = Field(alias="core:sample_rate")
    num_channels: int = Field(1, alias="core:num_channels", ge=1)
    frame_samples: int = Field(alias="mtcw:frame_samples", ge=1)
    tones_hz: list[Positive] = Field(alias="mtcw:tones_hz")
    tone_phases_rad: list[float] | None = Field(None, alias="mtcw:tone_phases_rad")
    wavelength_m: Positive = Field(alias="mtcw:wavelength_m")
    receiver: Receiver | None = Field(None, alias="mtcw:receiver")
    architecture: Literal["unmodulated_lo", "modulated_reference"] | None = Field(None, alias="mtcw:architecture")
    channels: Annotated[list[Annotated[str, Field(min_length=1)]], Field(min_length=1)] | None = Field(
        None, alias="mtcw:channels")
    pulse: Pulse | None = Field(None, alias="mtcw:pulse")
    scale: float | None = Field(None, alias="mtcw:scale")
    offset: float | None = Field(None, alias="mtcw:offset")
    source: str | None = Field(None, alias="mtcw:source")

    @property
    def dtype(self) -> np.dtype:
        """numpy dtype of one real value in the data file (byte order as stored)."""
        return _BY_NAME[self.datatype][0]

    @property
    def is_complex(self) -> bool:
        return _BY_NAME[self.datatype][1]

    @property
    def frame_receiver(self) -> str:
        return self.receiver or ("iq" if self.is_complex else "single")

    @property
    def frame_channels(self) -> tuple[str, ...]:
        if self.channels is not None:
            return tuple(self.channels)
        return ("i", "q") if self.is_complex else ("pd",)

    @model_validator(mode="after")
    def _consistent(self) -> "GlobalInfo":
        rx, ch = self.frame_receiver, self.frame_channels
        if self.is_complex != (rx == "iq"):
            raise _key_error("mtcw:receiver", f"receiver {rx!r} needs a {'complex' if rx == 'iq' else 'real'} "
                                              f"core:datatype, not {self.datatype!r}")
        need = ("i", "q") if rx == "iq" else ("pd",)
        if not set(need) <= set(ch):
            raise _key_error("mtcw:channels", f"receiver {rx!r} needs channels {list(need)}, got {list(ch)}")
        if len(set(ch)) != len(ch):
            raise _key_error("mtcw:channels", f"channel names must be distinct, got {list(ch)}")
        n_sigmf = _sigmf_channels(len(ch), self.is_complex)
        if self.num_channels != n_sigmf:
            raise _key_error("core:num_channels", f"{self.num_channels}, but mtcw:channels {list(ch)} in "
                                                  f"{self.datatype} make {n_sigmf} SigMF channels")
        if self.dtype.kind == "i" and self.scale is None:
            raise _key_error("mtcw:scale", f"required with the integer core:datatype {self.datatype!r} "
                                           f"(volts = code*scale + offset)")
        if self.tone_phases_rad is not None and len(self.tone_phases_rad) != len(self.tones_hz):
            raise _key_error("mtcw:tone_phases_rad", f"{len(self.tone_phases_rad)} phases for "
                                                     f"{len(self.tones_hz)} tones")
        return self


class Capture(_Section):
    """One capture segment, i.e. one frame: where it starts (in SigMF samples), its trigger time
    (``core:datetime``, held as ``t_ns``, ns since 1970), ``mtcw:seq`` and ``mtcw:truth``."""

    _unsupported: ClassVar[dict[str, Any]] = {"core:header_bytes": 0}

    sample_start: int = Field(alias="core:sample_start", ge=0)
    t_ns: Annotated[int, BeforeValidator(_t_ns)] | None = Field(None, alias="core:datetime")
    seq: UInt64 | None = Field(None, alias="mtcw:seq")
    truth: list[Truth] | None = Field(None, alias="mtcw:truth")


class SigMFMeta(_Model):
    """A ``.sigmf-meta`` file as this module reads it: ``global`` and at least one capture."""

    model_config = ConfigDict(extra="allow")

    global_info: GlobalInfo = Field(alias="global")
    captures: list[Capture] = Field(min_length=1)


# ---------------------------------------------------------------------------------------------
def _prefix(path: str | os.PathLike) -> Path:
    p = Path(path)
    for suf in (".sigmf-meta", ".sigmf-data", ".sigmf"):
        if p.name.endswith(suf):
            return p.with_name(p.name[: -len(suf)])
    return p


def _interleave(frame: Frame) -> np.ndarray:
    """Channel-major frame samples -> SigMF sample-major layout (raw dtype, byte order as given)."""
    s = frame.samples
    if frame.receiver == "iq":
        rows = [s[0], s[1]]
        for extra in s[2:]:
            rows += [extra, np.zeros_like(extra)]
        return np.stack(rows, axis=1).reshape(-1)
    return np.ascontiguousarray(s.T).reshape(-1)


def _replace(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically and durably: a reader finds the old file or the new
    one, whole (temporary file beside it, fsync, ``os.replace``, fsync of the folder)."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    try:
        fd = os.open(path.parent, os.O_RDONLY)
    except OSError:  # a folder that cannot be opened (some platforms): the rename is done anyway
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class RecordingWriter:
    """Append frames to a SigMF recording, keeping its metadata current (see the module docstring).

    Use as a context manager. The first frame fixes the recording's shared fields (fs, length,
    tones, channels, dtype, ...). :meth:`write` refuses with :class:`RecordingError`, writing
    nothing, a frame that differs from the first or whose fields the reader would refuse (a
    NaN, a negative ``seq``, samples that do not match the channels, ...).

    Parameters
    ----------
    prefix : str or Path
        Writes ``PREFIX.sigmf-data`` and ``PREFIX.sigmf-meta``.
    description : str
        ``core:description``.
    overwrite : bool
        Replace an existing recording (its metadata is removed first, so that a kill before the
        first checkpoint cannot leave the old metadata describing the new data); if False, an
        existing recording is a :class:`RecordingError`.
    checkpoint_s : float
        How long (s) the metadata on disk may lag the frames written. The interval is stretched to
        20 times what the last checkpoint took (the metadata is rewritten whole, so this grows with
        the recording): keeping it current costs at most about 5 % of the writer's time. 0 rewrites
        it after every frame, however long that takes.
    """

    def __init__(self, prefix: str | os.PathLike, description: str = "mtcw recording", overwrite: bool = True,
                 checkpoint_s: float = 1.0) -> None:
        if not checkpoint_s >= 0:
            raise ValueError(f"checkpoint_s: must be >= 0 s, got {checkpoint_s!r}")
        self.prefix = _prefix(prefix)
        self.data_path = self.prefix.with_name(self.prefix.name + ".sigmf-data")
        self.meta_path = self.prefix.with_name(self.prefix.name + ".sigmf-meta")
        self.description = description
        self.checkpoint_s = float(checkpoint_s)
        #: metadata rewrites so far (checkpoints, not counting close)
        self.checkpoints = 0
        try:
            self.prefix.parent.mkdir(parents=True, exist_ok=True)
            if overwrite:
                self.meta_path.unlink(missing_ok=True)
            elif self.meta_path.exists():
                raise FileExistsError
            self._fh = open(self.data_path, "wb" if overwrite else "xb")
        except FileExistsError:
            raise RecordingError(f"{self.prefix}: recording exists") from None
        except OSError as err:
            raise RecordingError(f"{self.data_path}: cannot create ({err.strerror or err})") from None
        self._first: dict | None = None  # frame_to_dict of the first frame
        self._global: dict | None = None  # the global section, as sigmf normalises it
        self._captures: list[dict] = []
        self._written = 0  # SigMF samples in the data file
        self._due = 0.0  # time.monotonic() of the next checkpoint

    def __enter__(self) -> "RecordingWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def frames(self) -> int:
        """Frames written so far."""
        return len(self._captures)

    # ---------------------------------------------------------------------------------------
    def _fields(self, frame: Frame, where: str) -> dict[str, Any]:
        """``frame_to_dict(frame)``, or RecordingError when the frame cannot even be mapped."""
        s = getattr(frame, "samples", None)
        if not isinstance(s, np.ndarray) or s.ndim != 2:
            raise RecordingError(f"{where}: samples: must be an array of shape (channels, n), got "
                                 f"{type(s).__name__} of shape {getattr(s, 'shape', None)}")
        try:
            d = frame_to_dict(frame)
        except (TypeError, ValueError, AttributeError, OverflowError) as err:
            raise RecordingError(f"{where}: {err}") from None
        if s.shape[0] != len(d["channels"]):
            raise RecordingError(f"{where}: samples: {s.shape[0]} rows for channels {d['channels']}")
        return d

    def _check(self, model: type[BaseModel], section: dict, root: tuple, where: str) -> None:
        """Validate ``section`` as the reader will read it (its JSON text) against ``model``."""
        try:
            model.model_validate_json(json.dumps(section))
        except (TypeError, ValueError) as err:  # ValidationError is a ValueError
            detail = _describe(err, root) if isinstance(err, ValidationError) else f"not JSON ({err})"
            raise RecordingError(f"{where}: refused: {detail}") from None

    def _global_section(self, d: dict[str, Any], where: str) -> dict:
        complex_ = d["receiver"] == "iq"
        dt = np.dtype(d["dtype"])
        glob = {
            "core:datatype": (_COMPLEX if complex_ else _REAL)[dt],
            "core:sample_rate": d["fs_hz"],
            "core:num_channels": _sigmf_channels(len(d["channels"]), complex_),
            "core:description": self.description,
            "core:recorder": "mtcw",
            "core:extensions": [EXTENSION],
            "mtcw:frame_samples": d["n"],
        }
        glob |= {f"mtcw:{k}": d[k] for k in _GLOBAL_KEYS if k != "fs_hz" and d[k] is not None}
        if dt.kind == "i" or (d["scale"], d["offset"]) != (1.0, 0.0):
            glob["mtcw:scale"] = d["scale"]
            glob["mtcw:offset"] = d["offset"]
        self._check(GlobalInfo, glob, ("global",), where)
        from sigmf import SigMFFile  # the reference implementation: core keys and their limits

        meta = SigMFFile(global_info=glob)
        self._sigmf_validate(meta, where)
        return meta.get_global_info()

    def _sigmf_validate(self, meta: Any, where: str) -> None:
        from jsonschema.exceptions import ValidationError as SchemaError

        try:
            meta.validate()
        except SchemaError as err:
            path = ".".join(str(p) for p in err.absolute_path)
            raise RecordingError(f"{where}: refused by sigmf: {path}: {err.message}") from None

    def write(self, frame: Frame) -> None:
        """Append ``frame``; the metadata on disk claims it by the next checkpoint.

        Raises
        ------
        RecordingError
            The frame is refused (nothing written): the message names the field.
        OSError
            Writing the data failed (the partial frame is cut off again).
        """
        where = f"{self.meta_path}: frame seq {_short(getattr(frame, 'seq', None))}"
        if self._fh.closed:
            raise RecordingError(f"{where}: the recording is closed")
        d = self._fields(frame, where)
        glob = self._global_section(d, where) if self._first is None else self._global
        if self._first is not None:
            for key in (*_GLOBAL_KEYS, "n", "dtype", "scale", "offset"):
                if d[key] != self._first[key]:
                    raise RecordingError(f"{where}: {key} differs from the recording's first frame "
                                         f"({_short(d[key])}, was {_short(self._first[key])})")
        if not (isinstance(d["t_ns"], int) and 0 <= d["t_ns"] <= U64_MAX):
            raise RecordingError(f"{where}: refused: t_ns: must be 0 .. 2^64-1 ns since 1970, got {d['t_ns']!r}")
        cap = {"core:sample_start": self._written, "core:datetime": _iso(d["t_ns"]), "mtcw:seq": d["seq"]}
        if d["truth"] is not None:
            cap["mtcw:truth"] = d["truth"]
        self._check(Capture, cap, ("captures", len(self._captures)), where)
        buf = _interleave(frame)
        raw = buf.astype(buf.dtype.newbyteorder("<"), copy=False).tobytes()
        pos = self._fh.tell()
        try:
            self._fh.write(raw)
        except BaseException:
            try:  # leave no partial frame for the next one to be misplaced behind
                self._fh.seek(pos)
                self._fh.truncate()
            except OSError:
                pass
            raise
        if self._first is None:
            self._first, self._global = d, glob
        self._captures.append(cap)
        self._written += frame.n
        if time.monotonic() >= self._due:
            self.checkpoint()

    def checkpoint(self) -> None:
        """Make the metadata on disk claim every frame written so far.

        The data file is flushed and fsynced first, then the metadata (compact JSON, no
        ``core:sha512``) replaced atomically. ``sigmf``'s validator is not run here: it costs
        10-30 ms a call whatever the metadata (it re-checks its own schema each time), and the
        captures were built here and checked against the reader's schema by :meth:`write`.
        """
        if self._global is None or self._fh.closed:
            return
        t0 = time.monotonic()
        self._fh.flush()
        os.fsync(self._fh.fileno())
        meta = {"global": self._global, "captures": self._captures, "annotations": []}
        _replace(self.meta_path, json.dumps(meta).encode())
        self.checkpoints += 1
        now = time.monotonic()
        self._due = now + max(self.checkpoint_s, 20.0 * (now - t0)) if self.checkpoint_s > 0 else now

    def close(self) -> None:
        """Write the final metadata (with the data's ``core:sha512``, validated by ``sigmf``).

        Raises
        ------
        RecordingError
            No frame was written (the data file is removed).
        """
        if self._fh.closed:
            return
        try:
            self._fh.flush()
            os.fsync(self._fh.fileno())
        finally:
            self._fh.close()
        if self._global is None:
            self.data_path.unlink(missing_ok=True)
            raise RecordingError(f"{self.prefix}: no frames written")
        from sigmf import SigMFFile

        meta = SigMFFile(metadata={"global": self._global, "captures": self._captures, "annotations": []},
                         data_file=str(self.data_path))  # computes core:sha512
        self._sigmf_validate(meta, str(self.meta_path))
        _replace(self.meta_path, (meta.dumps(pretty=True) + "\n").encode())


class Recording:
    """A SigMF recording opened for reading frame by frame; validated whole by :meth:`open`.

    Attributes
    ----------
    meta_path, data_path : Path
    meta : SigMFMeta
        The validated metadata.
    dtype : numpy.dtype
        One real value in the data file, byte order as stored.
    is_complex : bool
        Complex SigMF datatype (an IQ receiver).
    receiver : str
        ``single``, ``balanced`` or ``iq``.
    channels : tuple of str
        The frames' channels.
    frame_samples : int
        Samples per channel per frame.
    n_sigmf : int
        SigMF channels (``core:num_channels``).
    values_per_sample : int
        Real values per SigMF sample (all channels, real and imaginary parts).
    bytes_per_frame : int
        Bytes of one frame in the data file.
    """

    def __init__(self, meta_path: Path, data_path: Path, meta: SigMFMeta, data_bytes: int) -> None:
        self.meta_path, self.data_path, self.meta = meta_path, data_path, meta
        g = meta.global_info
        self.dtype, self.is_complex = g.dtype, g.is_complex
        self.receiver, self.channels = g.frame_receiver, g.frame_channels
        self.frame_samples = g.frame_samples
        self.n_sigmf = g.num_channels
        self.values_per_sample = self.n_sigmf * (2 if self.is_complex else 1)
        self.bytes_per_frame = self.frame_samples * self.values_per_sample * self.dtype.itemsize
        self._check_layout(data_bytes)

    @classmethod
    def open(cls, path: str | os.PathLike) -> "Recording":
        """Open and validate a recording.

        Parameters
        ----------
        path : str or Path
            Prefix, ``.sigmf-meta`` or ``.sigmf-data`` path.

        Raises
        ------
        RecordingError
            Missing or unreadable files, metadata that is not the schema (:class:`SigMFMeta`),
            captures that overlap or that the data file does not hold; the message names the
            file and the key.
        """
        prefix = _prefix(path)
        meta_path = prefix.with_name(prefix.name + ".sigmf-meta")
        data_path = prefix.with_name(prefix.name + ".sigmf-data")
        try:
            text = meta_path.read_bytes()
        except FileNotFoundError:
            raise RecordingError(f"{meta_path}: no such metadata file") from None
        except OSError as err:
            raise RecordingError(f"{meta_path}: cannot read ({err.strerror or err})") from None
        try:
            meta = SigMFMeta.model_validate_json(text)
        except ValidationError as err:
            raise RecordingError(f"{meta_path}: {_describe(err)}") from None
        try:
            st = os.stat(data_path)
        except FileNotFoundError:
            raise RecordingError(f"{data_path}: no such data file") from None
        except OSError as err:
            raise RecordingError(f"{data_path}: cannot read ({err.strerror or err})") from None
        if not stat.S_ISREG(st.st_mode):
            raise RecordingError(f"{data_path}: not a regular file")
        return cls(meta_path, data_path, meta, st.st_size)

    def _check_layout(self, data_bytes: int) -> None:
        """Captures in order, one frame each without overlap, all within the data file."""
        n = self.frame_samples
        held = data_bytes // (self.values_per_sample * self.dtype.itemsize)  # whole SigMF samples
        end = 0
        for i, c in enumerate(self.meta.captures):
            if c.sample_start < end:
                raise RecordingError(
                    f"{self.meta_path}: captures.{i}.core:sample_start: {c.sample_start} overlaps the frame of "
                    f"captures.{i - 1} (samples {end - n} .. {end - 1}; mtcw:frame_samples = {n})")
            end = c.sample_start + n
            if end > held:
                raise RecordingError(
                    f"{self.data_path}: truncated: holds {held} samples ({data_bytes} bytes), but "
                    f"captures.{i}.core:sample_start = {c.sample_start} needs {end} (frame {i} of "
                    f"{len(self.meta.captures)} in {self.meta_path.name}, mtcw:frame_samples = {n})")

    def __len__(self) -> int:
        return len(self.meta.captures)

    def frame(self, i: int) -> Frame:
        """Frame ``i`` (negative counts from the end); its samples are read from the data file.

        Raises
        ------
        IndexError
            ``i`` is out of range (the caller's error, not the recording's).
        RecordingError
            The data file no longer holds the frame (changed since the recording was opened).
        """
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {i} of a recording of {len(self)} frames")
        i %= len(self)
        cap = self.meta.captures[i]
        g = self.meta.global_info
        count = self.frame_samples * self.values_per_sample
        try:
            raw = np.fromfile(self.data_path, dtype=self.dtype, count=count,
                              offset=cap.sample_start * self.values_per_sample * self.dtype.itemsize)
        except (OSError, ValueError) as err:
            raise RecordingError(f"{self.data_path}: frame {i}: cannot be read ({err})") from None
        if raw.size != count:
            raise RecordingError(f"{self.data_path}: frame {i}: only {raw.size} of {count} values left "
                                 f"(the file was cut after it was opened)")
        block = raw.astype(self.dtype.newbyteorder("="), copy=False).reshape(self.frame_samples, -1)
        if self.is_complex:
            rows = [block[:, 0], block[:, 1]] + [block[:, 2 + 2 * e] for e in range(len(self.channels) - 2)]
            samples = np.stack(rows)
        else:
            samples = np.ascontiguousarray(block.T)
        d = {"fs_hz": g.sample_rate, "tones_hz": g.tones_hz, "tone_phases_rad": g.tone_phases_rad,
             "wavelength_m": g.wavelength_m, "receiver": self.receiver, "architecture": g.architecture,
             "channels": self.channels, "pulse": None if g.pulse is None else g.pulse.model_dump(),
             "scale": 1.0 if g.scale is None else g.scale, "offset": 0.0 if g.offset is None else g.offset,
             "seq": i if cap.seq is None else cap.seq,
             "t_ns": cap.t_ns or 0,
             "source": self.meta_path.name.removesuffix(".sigmf-meta") if g.source is None else g.source,
             "truth": None if cap.truth is None else [t.model_dump() for t in cap.truth]}
        return frame_from_dict(d, samples)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self.frame(i)


def read_recording(path: str | os.PathLike) -> Recording:
    """Open a SigMF recording, validated whole; raises :class:`RecordingError` naming the file and key."""
    return Recording.open(path)
