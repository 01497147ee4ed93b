"""The frame: one digitizer record with the metadata needed to process it.

This is the in-memory form shared by the simulator, SigMF recordings and the wire format.
Samples are kept as the digitizer sent them (float volts or integer ADC codes with
``volts = code*scale + offset``), channel-major.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

Receiver = Literal["single", "balanced", "iq"]
SAMPLE_DTYPES = ("<f4", "<f8", "<i2", "<i1")


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
    extra: dict = field(default_factory=dict)

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
        if x.dtype.kind == "f" and self.scale == 1.0 and self.offset == 0.0:
            return x.astype(np.float64, copy=False)
        return x.astype(np.float64) * self.scale + self.offset

    def signal(self) -> np.ndarray:
        """The detector signal in volts: real float64 (single/balanced) or complex128 (iq), shape (n,)."""
        if self.receiver == "iq":
            return self.volts("i") + 1j * self.volts("q")
        return self.volts("pd")

    def with_(self, **kw) -> "Frame":
        return replace(self, **kw)
