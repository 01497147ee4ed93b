"""The calibration file: tone phase offsets and the internal delay tau0 (a leaf: no chain import).

Derived by :func:`mtcw_core.calibrate.derive_calibration`; applied by the chain to every frame.

A measurement of a reflector at a known range ``L_cal`` gives, per tone, the effective phase
``phi_i_eff = phi_i - 2*pi*f_i*tau0`` (only phase *differences* are observable). It is
stored split into a linear part (``tau0``, the delay that best explains the offsets as a pure
delay, searched over ``[0, tau0_max]``) and per-tone residual phases; applying
``(phi_i, tau0)`` reproduces ``phi_i_eff`` exactly, so the split costs no accuracy.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path


FORMAT_VERSION = 1


class CalibrationError(ValueError):
    pass


@dataclass(frozen=True)
class Calibration:
    tones_hz: tuple[float, ...]
    tone_phases_rad: tuple[float, ...]
    tau0_s: float
    known_range_m: float = 0.0
    frames_used: int = 0
    phase_std_rad: tuple[float, ...] = ()
    source: str = ""
    created: str = ""
    version: int = FORMAT_VERSION

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(asdict(self), indent=2) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> "Calibration":
        try:
            d = json.loads(Path(path).read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise CalibrationError(f"cannot read calibration {path}: {err}") from None
        for key in ("tones_hz", "tone_phases_rad", "tau0_s"):
            if key not in d:
                raise CalibrationError(f"calibration {path}: missing key {key!r}")
        if d.get("version", 1) != FORMAT_VERSION:
            raise CalibrationError(f"calibration {path}: version {d.get('version')} unsupported")
        if len(d["tones_hz"]) != len(d["tone_phases_rad"]):
            raise CalibrationError(f"calibration {path}: tones_hz and tone_phases_rad differ in length")
        d["tones_hz"] = tuple(d["tones_hz"])
        d["tone_phases_rad"] = tuple(d["tone_phases_rad"])
        d["phase_std_rad"] = tuple(d.get("phase_std_rad", ()))
        return cls(**d)
