"""The calibration file: tone phase offsets and the internal delay tau0 (a leaf: no chain import).

Derived by :func:`mtcw_core.calibrate.derive_calibration`; applied by the chain to every frame.

A measurement of a reflector at a known range ``L_cal`` gives, per tone, the effective phase
``phi_i_eff = phi_i - 2*pi*f_i*tau0`` (their differences; on a real receiver with an unmodulated
LO their own values modulo pi too, ``phases_absolute``). It is
stored split into a linear part (``tau0``, the delay that best explains the offsets as a pure
delay, searched over ``[0, tau0_max]``) and per-tone residual phases; applying
``(phi_i, tau0)`` reproduces ``phi_i_eff`` exactly, so the split costs no accuracy.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator, model_validator

from .scene import field_path  # the one rendering of an error's field path


FORMAT_VERSION = 1


class CalibrationError(ValueError):
    """A calibration file that cannot be used; the message names the file and the field."""


class Calibration(BaseModel):
    """Tone phase offsets and the internal delay, as measured on a reflector at a known range.

    Attributes
    ----------
    tones_hz : tuple of float, the tone plan it was measured with (Hz); frames with another plan
        are rejected (``calibration_mismatch``)
    tone_phases_rad : tuple of float, each tone's residual RF phase (rad), same length
    tau0_s : float, the internal round-trip delay (s)
    known_range_m, frames_used, phase_std_rad, source, created : provenance
    reference_powers_v2, reference_power_sigma_v2 : tuple of float, AB-MTCW only: the reference
        arm's tone line powers (V^2, per tone) from frames without the measurement arm, and
        their standard errors; empty otherwise
    tone_amplitudes, tone_amplitude_std : tuple of float, the reflector's line amplitude at each
        tone relative to their mean, averaged over the frames, and that mean's standard error; the
        chain checks the static point's lines against them (``ChainSettings.tone_amplitudes``);
        empty in files written before they were measured
    version : the file format's version
    phases_absolute : bool, ``tone_phases_rad`` are the tones' own phases modulo pi, not only their
        differences: a reflector on one photodiode or a balanced pair with an unmodulated LO shows
        them (its lines are real), and the chain then checks a still point's lines for the
        complex sum of two echoes (:func:`~mtcw_core.ranging.mixing.realness_chi2`); False in
        files written before, or from an IQ receiver
    """

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)

    tones_hz: tuple[float, ...] = Field(min_length=2)
    tone_phases_rad: tuple[float, ...]
    tau0_s: float
    known_range_m: float = 0.0
    frames_used: int = Field(0, ge=0)
    phase_std_rad: tuple[float, ...] = ()
    source: str = ""
    created: str = ""
    version: Literal[1] = FORMAT_VERSION
    tone_amplitudes: tuple[float, ...] = ()
    tone_amplitude_std: tuple[float, ...] = ()
    # AB-MTCW (mtcw_core.ranging.ab.derive_reference): a reference-only measurement's tone powers
    reference_powers_v2: tuple[float, ...] = ()
    reference_power_sigma_v2: tuple[float, ...] = ()
    phases_absolute: bool = False

    @field_validator("reference_powers_v2", "reference_power_sigma_v2")
    @classmethod
    def _per_tone(cls, v: tuple[float, ...], info: ValidationInfo) -> tuple[float, ...]:
        n = len(info.data.get("tones_hz", ()))
        if v and (len(v) != n or any(x < 0 for x in v)):
            raise ValueError(f"one non-negative value per tone ({n})")
        return v

    @field_validator("tone_amplitudes", "tone_amplitude_std")
    @classmethod
    def _amplitudes(cls, v: tuple[float, ...], info: ValidationInfo) -> tuple[float, ...]:
        n = len(info.data.get("tones_hz", ()))
        positive = info.field_name == "tone_amplitudes"
        if v and (len(v) != n or any(not (x > 0 if positive else x >= 0) for x in v)):
            raise ValueError(f"one {'positive' if positive else 'non-negative'} value per tone ({n})")
        if v and not positive and not info.data.get("tone_amplitudes"):  # declared before it: validated first
            raise ValueError("given without (valid) tone_amplitudes")
        return v

    @model_validator(mode="after")
    def _same_length(self) -> "Calibration":
        if len(self.tones_hz) != len(self.tone_phases_rad):
            raise ValueError("tones_hz and tone_phases_rad differ in length")
        if any(f <= 0 for f in self.tones_hz) or len(set(self.tones_hz)) != len(self.tones_hz):
            raise ValueError("tones_hz must be positive and distinct")
        return self

    def save(self, path: str | Path) -> None:
        Path(path).write_text(self.model_dump_json(indent=2) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> "Calibration":
        """Read and validate a calibration file (JSON).

        Raises
        ------
        CalibrationError
            Unreadable file, not JSON, not an object, unknown or missing keys, wrong types,
            non-finite numbers, mismatched lengths; the message names the field.
        """
        try:
            text = Path(path).read_bytes()
        except (OSError, ValueError) as err:  # ValueError: a NUL in the path
            raise CalibrationError(f"cannot read calibration {path}: {err}") from None
        try:
            return cls.model_validate_json(text)
        except ValidationError as err:
            e = err.errors()[0]
            loc = field_path(e["loc"]) or "(file)"
            raise CalibrationError(f"calibration {path}: {loc}: {e['msg']}") from None
