"""SigMF recordings of frames, with the ``mtcw`` extension namespace (version 1.0.0).

One capture segment per frame (``mtcw:seq``, ``core:datetime``, simulator truth as
``mtcw:truth``). Frames of a recording share fs, length, tones and channels. Metadata is
written and validated by the ``sigmf`` package; samples are read with ``numpy.memmap`` so a long
recording is never loaded whole.

Channel layout: SigMF interleaves channels sample by sample; a frame is channel-major. For an
IQ receiver the ``i``/``q`` channels travel as one complex SigMF channel (``cf32_le``,
``ci16_le``, ``ci8``); any further channel (``pulse_ref``) is a complex channel with zero
imaginary part.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .frame import Frame, frame_from_dict, frame_to_dict

EXTENSION = {"name": "mtcw", "version": "1.0.0", "optional": False}

_REAL = {np.dtype("<f4"): "rf32_le", np.dtype("<f8"): "rf64_le", np.dtype("<i2"): "ri16_le", np.dtype("i1"): "ri8"}
_COMPLEX = {np.dtype("<f4"): "cf32_le", np.dtype("<f8"): "cf64_le", np.dtype("<i2"): "ci16_le", np.dtype("i1"): "ci8"}
_BY_NAME = {v: (k, False) for k, v in _REAL.items()} | {v: (k, True) for k, v in _COMPLEX.items()}
_BY_NAME["ri16_be"] = (np.dtype(">i2"), False)
_BY_NAME["ci16_be"] = (np.dtype(">i2"), True)

#: keys of :func:`~mtcw_core.frame.frame_to_dict` stored once per recording, as ``mtcw:<key>``
#: (``fs_hz`` as ``core:sample_rate``); ``n`` is ``mtcw:frame_samples``, ``dtype`` the
#: ``core:datatype``, ``scale``/``offset`` are stored for integer datatypes only; ``seq``,
#: ``t_ns`` (as ``core:datetime``) and ``truth`` go on each frame's capture segment; a frame's
#: ``run`` is not recorded (a replay is a new run of the publisher that replays it).
_GLOBAL_KEYS = ("fs_hz", "tones_hz", "tone_phases_rad", "wavelength_m", "receiver", "architecture", "channels",
                "pulse", "source")
REQUIRED_GLOBAL = ("core:datatype", "core:sample_rate", "mtcw:tones_hz", "mtcw:wavelength_m", "mtcw:frame_samples")


class RecordingError(ValueError):
    """A recording is malformed: the message names the file and the key or reason."""


def _prefix(path: str | os.PathLike) -> Path:
    p = Path(path)
    for suf in (".sigmf-meta", ".sigmf-data", ".sigmf"):
        if p.name.endswith(suf):
            return p.with_name(p.name[: -len(suf)])
    return p


def _iso(t_ns: int) -> str:
    t = _dt.datetime.fromtimestamp(t_ns // 1_000_000_000, tz=_dt.timezone.utc)
    return t.strftime("%Y-%m-%dT%H:%M:%S") + f".{(t_ns % 1_000_000_000) // 1000:06d}Z"


def _parse_iso(s: str) -> int:
    t = _dt.datetime.strptime(s.rstrip("Z"), "%Y-%m-%dT%H:%M:%S.%f").replace(tzinfo=_dt.timezone.utc)
    return int(t.timestamp()) * 1_000_000_000 + t.microsecond * 1000


def _interleave(frame: Frame) -> np.ndarray:
    """Channel-major frame samples -> SigMF sample-major layout (raw dtype, little endian)."""
    s = frame.samples
    if frame.receiver == "iq":
        rows = [s[0], s[1]]
        for extra in s[2:]:
            rows += [extra, np.zeros_like(extra)]
        return np.stack(rows, axis=1).reshape(-1)
    return np.ascontiguousarray(s.T).reshape(-1)


class RecordingWriter:
    """Append frames to a SigMF recording; ``close()`` writes the validated metadata.

    Use as a context manager. The first frame fixes fs, length, tones and channels; a later
    frame that differs raises :class:`RecordingError`.
    """

    def __init__(self, prefix: str | os.PathLike, description: str = "mtcw recording", overwrite: bool = True):
        self.prefix = _prefix(prefix)
        self.prefix.parent.mkdir(parents=True, exist_ok=True)
        self.data_path = self.prefix.with_name(self.prefix.name + ".sigmf-data")
        self.meta_path = self.prefix.with_name(self.prefix.name + ".sigmf-meta")
        if not overwrite and (self.data_path.exists() or self.meta_path.exists()):
            raise RecordingError(f"{self.prefix}: recording exists")
        self._fh = open(self.data_path, "wb")
        self._first: dict | None = None  # frame_to_dict of the first frame
        self._captures: list[dict] = []
        self._written = 0
        self.description = description

    def __enter__(self) -> "RecordingWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def write(self, frame: Frame) -> None:
        d = frame_to_dict(frame)
        if self._first is None:
            self._first = d
        else:
            for key in (*_GLOBAL_KEYS, "n", "dtype", "scale", "offset"):
                if d[key] != self._first[key]:
                    raise RecordingError(f"frame seq {frame.seq}: {key} differs from the recording's first frame "
                                         f"({d[key]!r}, was {self._first[key]!r})")
        cap = {"core:sample_start": self._written, "core:datetime": _iso(d["t_ns"]), "mtcw:seq": d["seq"]}
        if d["truth"] is not None:
            cap["mtcw:truth"] = d["truth"]
        self._captures.append(cap)
        buf = _interleave(frame)
        self._fh.write(buf.astype(buf.dtype.newbyteorder("<"), copy=False).tobytes())
        self._written += frame.n

    def close(self) -> None:
        if self._fh.closed:
            return
        self._fh.close()
        if self._first is None:
            self.data_path.unlink(missing_ok=True)
            raise RecordingError("no frames written")
        d = self._first
        from sigmf import SigMFFile  # the reference implementation writes and validates the metadata

        complex_ = d["receiver"] == "iq"
        dt = np.dtype(d["dtype"])
        datatype = (_COMPLEX if complex_ else _REAL)[dt]
        n_sigmf = (len(d["channels"]) + 1) // 2 if complex_ else len(d["channels"])
        glob = {
            "core:datatype": datatype,
            "core:sample_rate": d["fs_hz"],
            "core:num_channels": n_sigmf,
            "core:description": self.description,
            "core:recorder": "mtcw",
            "core:extensions": [EXTENSION],
            "mtcw:frame_samples": d["n"],
        }
        glob |= {f"mtcw:{k}": d[k] for k in _GLOBAL_KEYS if k != "fs_hz" and d[k] is not None}
        if dt.kind == "i":
            glob["mtcw:scale"] = d["scale"]
            glob["mtcw:offset"] = d["offset"]
        meta = SigMFFile(data_file=str(self.data_path), global_info=glob)
        for cap in self._captures:
            start = cap.pop("core:sample_start")
            meta.add_capture(start, metadata=cap)
        meta.tofile(str(self.meta_path), overwrite=True)


@dataclass
class Recording:
    """A SigMF recording opened for reading frame by frame.

    Parameters
    ----------
    path : str or Path
        Prefix, ``.sigmf-meta`` or ``.sigmf-data`` path.
    """

    meta_path: Path
    data_path: Path
    meta: dict

    @classmethod
    def open(cls, path: str | os.PathLike) -> "Recording":
        prefix = _prefix(path)
        meta_path = prefix.with_name(prefix.name + ".sigmf-meta")
        data_path = prefix.with_name(prefix.name + ".sigmf-data")
        if not meta_path.exists():
            raise RecordingError(f"{meta_path}: no such metadata file")
        if not data_path.exists():
            raise RecordingError(f"{data_path}: no such data file")
        try:
            meta = json.loads(meta_path.read_text())
        except json.JSONDecodeError as err:
            raise RecordingError(f"{meta_path}: not valid JSON ({err})") from None
        rec = cls(meta_path, data_path, meta)
        rec._check()
        return rec

    # metadata ------------------------------------------------------------------------
    @property
    def glob(self) -> dict:
        return self.meta.get("global", {})

    def _check(self) -> None:
        g = self.glob
        for key in REQUIRED_GLOBAL:
            if key not in g:
                raise RecordingError(f"{self.meta_path}: missing global key {key!r}")
        if g["core:datatype"] not in _BY_NAME:
            raise RecordingError(
                f"{self.meta_path}: core:datatype {g['core:datatype']!r} not supported "
                f"(one of {', '.join(sorted(_BY_NAME))})"
            )
        self.dtype, self.is_complex = _BY_NAME[g["core:datatype"]]
        self.channels = tuple(g.get("mtcw:channels", ["i", "q"] if self.is_complex else ["pd"]))
        self.receiver = g.get("mtcw:receiver", "iq" if self.is_complex else "single")
        if self.receiver == "iq" and not self.is_complex:
            raise RecordingError(f"{self.meta_path}: mtcw:receiver 'iq' needs a complex core:datatype")
        self.n_sigmf = int(g.get("core:num_channels", 1))
        want = (len(self.channels) + 1) // 2 if self.is_complex else len(self.channels)
        if want != self.n_sigmf:
            raise RecordingError(
                f"{self.meta_path}: core:num_channels={self.n_sigmf} does not match mtcw:channels {list(self.channels)}"
            )
        if self.dtype.kind == "i" and "mtcw:scale" not in g:
            raise RecordingError(f"{self.meta_path}: integer datatype needs 'mtcw:scale'")
        self.frame_samples = int(g["mtcw:frame_samples"])
        self.values_per_sample = self.n_sigmf * (2 if self.is_complex else 1)
        self.bytes_per_frame = self.frame_samples * self.values_per_sample * self.dtype.itemsize
        caps = self.meta.get("captures")
        if not caps:
            raise RecordingError(f"{self.meta_path}: no captures (one per frame expected)")
        size = self.data_path.stat().st_size
        need = len(caps) * self.bytes_per_frame
        if size < need:
            raise RecordingError(
                f"{self.data_path}: truncated: {size} bytes, metadata declares {len(caps)} frames of "
                f"{self.bytes_per_frame} bytes ({need} bytes)"
            )
        for i, c in enumerate(caps):
            if "core:sample_start" not in c:
                raise RecordingError(f"{self.meta_path}: captures.{i} missing 'core:sample_start'")

    def __len__(self) -> int:
        return len(self.meta["captures"])

    def frame(self, i: int) -> Frame:
        """Frame i of the recording (samples copied out of the memory map)."""
        g = self.glob
        cap = self.meta["captures"][i]
        start = int(cap["core:sample_start"])
        mm = np.memmap(self.data_path, dtype=self.dtype, mode="r",
                       offset=start * self.values_per_sample * self.dtype.itemsize,
                       shape=(self.frame_samples * self.values_per_sample,))
        block = np.asarray(mm).astype(self.dtype.newbyteorder("="), copy=True).reshape(self.frame_samples, -1)
        del mm
        if self.is_complex:
            rows = [block[:, 0], block[:, 1]] + [block[:, 2 + 2 * e] for e in range(len(self.channels) - 2)]
            samples = np.stack(rows)
        else:
            samples = np.ascontiguousarray(block.T)
        d = {k: g[f"mtcw:{k}"] for k in _GLOBAL_KEYS if f"mtcw:{k}" in g}
        dtm = cap.get("core:datetime")
        d |= {"fs_hz": g["core:sample_rate"], "receiver": self.receiver, "channels": self.channels,
              "scale": g.get("mtcw:scale", 1.0), "offset": g.get("mtcw:offset", 0.0),
              "seq": cap.get("mtcw:seq", i), "t_ns": _parse_iso(dtm) if dtm else 0,
              "source": g.get("mtcw:source", self.meta_path.name.removesuffix(".sigmf-meta")),
              "truth": cap.get("mtcw:truth")}
        return frame_from_dict(d, samples)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self.frame(i)


def read_recording(path: str | os.PathLike) -> Recording:
    """Open a SigMF recording; raises :class:`RecordingError` naming the problem."""
    return Recording.open(path)
