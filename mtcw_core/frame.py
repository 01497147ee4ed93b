"""The frame: one digitizer record with the metadata needed to process it.

This is the in-memory form shared by the simulator, SigMF recordings and the wire format.
Samples are kept as the digitizer sent them (float volts or integer ADC codes with
``volts = code*scale + offset``), channel-major.

:func:`frame_to_dict` and :func:`frame_from_dict` are the one mapping between a frame and
plain values (everything but the samples, under the wire format's key names); the wire codec
(``services/wire.py``) and the SigMF writer and reader (:mod:`mtcw_core.recording`) both go
through it, so that a frame's fields are spelled out here only.

Identity (``source``, ``seq``, ``t_ns``, ``run``) has one rule: **whoever emits a stream stamps
it.** On the wire that is the acquisition node's publisher, which stamps every frame it sends
(its source name, its own ``seq`` counter, the trigger time as its wall clock when it takes the
frame, its run id), replacing whatever the frame source put there. Offline, the simulator's
frames carry a default identity (``seq`` = frame index, ``t_ns`` = the scene's start time plus
the frame's simulated time, ``source`` = the scene's name, no run) so that ``mtcw simulate``
recordings are deterministic; a replayed recording's identity is replaced by the publisher's.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np

Receiver = Literal["single", "balanced", "iq"]
#: sample dtypes a frame may hold, by their wire names (little endian; int8 has no byte order)
SAMPLE_DTYPES = ("<f4", "<f8", "<i2", "<i1")
_DTYPES = {name: np.dtype(name) for name in SAMPLE_DTYPES}


@dataclass(frozen=True)
class PulseInfo:
    """Quasi-CW gate timing as known to the acquisition side."""

    period_s: float
    duty: float
    delay_s: float = 0.0

    def to_dict(self) -> dict:
        return {"period_s": self.period_s, "duty": self.duty, "delay_s": self.delay_s}


@dataclass(frozen=True)
class TruthTarget:
    """Simulator truth for one target, referred to the record's centre."""

    range_m: float
    velocity_mps: float

    def to_dict(self) -> dict:
        return {"range_m": self.range_m, "velocity_mps": self.velocity_mps}


@dataclass(frozen=True)
class Frame:
    """One record.

    Attributes
    ----------
    samples : ndarray, shape (n_channels, n)
        Raw samples, dtype one of float32, float64, int16, int8.
    fs_hz : float
        Sample rate (Hz).
    tones_hz : tuple of float
        Modulation tone frequencies (Hz).
    channels : tuple of str
        Channel names: ``("pd",)``, ``("i", "q")``, optionally followed by ``"pulse_ref"``.
    scale, offset : float
        ``volts = code*scale + offset`` (1, 0 for float samples).
    seq, t_ns, source, run : int, int, str, int or None
        Identity: +1 per frame, trigger time (Unix ns), name of the source, the publisher's
        random run id (see the module docstring for who stamps them).
    """

    samples: np.ndarray
    fs_hz: float
    tones_hz: tuple[float, ...]
    wavelength_m: float
    receiver: Receiver = "single"
    channels: tuple[str, ...] = ("pd",)
    scale: float = 1.0
    offset: float = 0.0
    tone_phases_rad: tuple[float, ...] | None = None
    pulse: PulseInfo | None = None
    architecture: str = "unmodulated_lo"
    seq: int = 0
    t_ns: int = 0
    source: str = "sim"
    truth: tuple[TruthTarget, ...] | None = None
    run: int | None = None

    @property
    def n(self) -> int:
        return int(self.samples.shape[-1])

    @property
    def duration_s(self) -> float:
        return self.n / self.fs_hz

    def volts(self, name: str) -> np.ndarray:
        """One channel in volts, float64, shape (n,)."""
        idx = self.channels.index(name)
        x = self.samples[idx]
        if self.scale == 1.0 and self.offset == 0.0:
            return x.astype(np.float64, copy=x.dtype.kind != "f")
        # one buffer: the codes are cast inside the multiply's loop (exactly: every int16 and
        # float32 is a float64), then the offset added in place -- two passes, not three
        v = np.multiply(x, np.float64(self.scale), dtype=np.float64)
        if self.offset != 0.0:
            v += self.offset
        return v

    def signal(self) -> np.ndarray:
        """The detector signal in volts: real float64 (single/balanced) or complex128 (iq), shape (n,)."""
        if self.receiver == "iq":
            # i + 1j*q, written into one complex buffer (the same numbers: 1j*q has real part 0)
            z = np.empty(self.n, dtype=np.complex128)
            plain = self.scale == 1.0 and self.offset == 0.0
            z.real = self.samples[self.channels.index("i")] if plain else self.volts("i")
            z.imag = self.samples[self.channels.index("q")] if plain else self.volts("q")
            return z
        return self.volts("pd")

    def with_(self, **kw) -> "Frame":
        return replace(self, **kw)


def dtype_name(dtype: np.dtype) -> str:
    """The wire name (one of :data:`SAMPLE_DTYPES`) of a sample dtype of either byte order.

    Raises
    ------
    ValueError
        When the dtype is not float32, float64, int16 or int8 (the message names ``dtype``).
    """
    dt = np.dtype(dtype)
    for name, d in _DTYPES.items():
        if dt == d or dt == d.newbyteorder(">"):
            return name
    raise ValueError(f"dtype: samples dtype {dt} is not one of {', '.join(SAMPLE_DTYPES)}")


def frame_to_dict(frame: Frame) -> dict[str, Any]:
    """Every field of ``frame`` but the samples, as plain Python values.

    Keys are those of the wire format's frame header (``docs/wire-format.md``) without ``v``;
    optional fields are present with ``None`` when the frame has no value for them.

    Parameters
    ----------
    frame : Frame

    Returns
    -------
    dict
        ``source``, ``seq``, ``t_ns``, ``run``, ``fs_hz``, ``n``, ``dtype`` (wire name, see
        :func:`dtype_name`), ``channels``, ``scale``, ``offset``, ``tones_hz``,
        ``tone_phases_rad``, ``wavelength_m``, ``receiver``, ``pulse`` (map or None),
        ``architecture``, ``truth`` (list of maps or None).
    """
    return {
        "source": frame.source, "seq": int(frame.seq), "t_ns": int(frame.t_ns),
        "run": None if frame.run is None else int(frame.run),
        "fs_hz": float(frame.fs_hz), "n": frame.n, "dtype": dtype_name(frame.samples.dtype),
        "channels": list(frame.channels), "scale": float(frame.scale), "offset": float(frame.offset),
        "tones_hz": [float(f) for f in frame.tones_hz],
        "tone_phases_rad": None if frame.tone_phases_rad is None else [float(p) for p in frame.tone_phases_rad],
        "wavelength_m": float(frame.wavelength_m), "receiver": frame.receiver,
        "pulse": None if frame.pulse is None else frame.pulse.to_dict(),
        "architecture": frame.architecture,
        "truth": None if frame.truth is None else [t.to_dict() for t in frame.truth],
    }


def frame_from_dict(d: Mapping[str, Any], samples: np.ndarray) -> Frame:
    """The frame described by ``d`` (keys of :func:`frame_to_dict`) with ``samples``.

    Optional keys may be absent or ``None``. Values are not validated here: the wire decoder
    validates them against its schema first, a SigMF reader checks its own keys.

    Parameters
    ----------
    d : mapping
        As returned by :func:`frame_to_dict`; ``fs_hz``, ``tones_hz`` and ``wavelength_m`` are
        required.
    samples : ndarray, shape (n_channels, n)
        Kept as given (not copied).
    """
    phases, pulse, truth = d.get("tone_phases_rad"), d.get("pulse"), d.get("truth")
    run = d.get("run")
    return Frame(
        samples=samples, fs_hz=float(d["fs_hz"]), tones_hz=tuple(float(f) for f in d["tones_hz"]),
        wavelength_m=float(d["wavelength_m"]), receiver=d.get("receiver") or "single",
        channels=tuple(d.get("channels") or ("pd",)),
        scale=float(d.get("scale", 1.0)), offset=float(d.get("offset", 0.0)),
        tone_phases_rad=None if phases is None else tuple(float(p) for p in phases),
        pulse=None if pulse is None else PulseInfo(float(pulse["period_s"]), float(pulse["duty"]),
                                                   float(pulse.get("delay_s", 0.0))),
        architecture=d.get("architecture") or "unmodulated_lo",
        seq=int(d.get("seq", 0)), t_ns=int(d.get("t_ns", 0)), source=d.get("source", "sim"),
        truth=None if truth is None else tuple(TruthTarget(float(t["range_m"]), float(t["velocity_mps"]))
                                               for t in truth),
        run=None if run is None else int(run),
    )
