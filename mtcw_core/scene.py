"""Validated scene models: what a simulated bench contains.

A scene declares only what it needs; the simulator computes only those terms. Scenes are
TOML (or JSON) files validated by pydantic; a wrong scene fails with a message naming the
field (``targets.0.loss_db: Input should be greater than or equal to 0``).

All quantities are SI: Hz, s, m, W, A, V, Ohm, K.
"""

from __future__ import annotations

import json
import math
import re
import tomllib
from importlib import resources
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from .phase import C


class SceneError(ValueError):
    """A scene file could not be read or failed validation; the message names the field."""


class _Model(BaseModel):
    # NaN and inf are never a valid physical quantity here (a NaN range would simulate nothing)
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Laser(_Model):
    wavelength_m: float = Field(1.064e-6, gt=0, description="vacuum wavelength")
    power_w: float = Field(0.05, gt=0, description="laser output power P0")
    linewidth_hz: float = Field(0.0, ge=0, description="Lorentzian FWHM; 0 = ideal laser")

    @property
    def coherence_length_m(self) -> float:
        return math.inf if self.linewidth_hz == 0 else C / (math.pi * self.linewidth_hz)


class Tone(_Model):
    frequency_hz: float = Field(gt=0)
    modulation_index: float = Field(0.07, gt=0, le=math.pi, description="m_i = pi*V_i/V_pi")
    phase_rad: float = 0.0


class Modulator(_Model):
    transfer: Literal["exact", "small_signal"] = "exact"
    tones: list[Tone] = Field(min_length=1)

    @model_validator(mode="after")
    def _distinct(self) -> "Modulator":
        f = [t.frequency_hz for t in self.tones]
        for i, x in enumerate(f):
            if x in f[:i]:
                raise ValueError(f"tones.{i}.frequency_hz: {x:g} Hz repeats tones.{f.index(x)}: "
                                 f"frequencies must be distinct")
        return self

    @property
    def tones_hz(self) -> list[float]:
        return [t.frequency_hz for t in self.tones]


class Architecture(_Model):
    kind: Literal["unmodulated_lo", "modulated_reference"] = "unmodulated_lo"
    reference_range_m: float = Field(0.065, ge=0, description="reference mirror (modulated_reference)")
    reference_loss_db: float = Field(20.0, ge=0)


class Target(_Model):
    range_m: float = Field(description="one-way range at t = 0 of the sequence")
    velocity_mps: float = Field(0.0, description="dL/dt, positive = receding")
    loss_db: float = Field(20.0, ge=0, description="round-trip power loss")


class Paths(_Model):
    tau0_s: float = Field(0.0, ge=0, description="internal round-trip delay removed by calibration")
    lo_path_difference_m: float = Field(
        0.0, description="optical path of the LO minus the echo's internal path (tau_lo = tau0 + d/c)"
    )

    @model_validator(mode="after")
    def _lo_after_emission(self) -> "Paths":
        """No light arrives before it left: the LO's delay ``tau0_s + d/c`` is at least 0."""
        tau_lo = self.tau0_s + self.lo_path_difference_m / C
        if tau_lo < 0:
            raise ValueError(f"lo_path_difference_m: the LO's delay tau0_s + d/c = {tau_lo:g} s is negative")
        return self


class Receiver(_Model):
    kind: Literal["single", "balanced", "iq"] = "single"
    responsivity_a_per_w: float = Field(0.9, gt=0)
    load_ohm: float = Field(50.0, gt=0)
    gain: float = Field(1.0, gt=0, description="voltage gain after the load")
    bandwidth_hz: float | None = Field(None, gt=0, description="front-end low-pass (2nd-order Butterworth)")
    dark_current_a: float = Field(0.0, ge=0)


class Noise(_Model):
    shot: bool = False
    thermal: bool = False
    temperature_k: float = Field(300.0, gt=0)
    noise_figure: float = Field(1.0, ge=1.0, description="linear F_n of the front end")
    rin_db_per_hz: float | None = Field(None, lt=0)
    trigger_jitter_s: float = Field(0.0, ge=0, description="rms, per frame")
    rf_phase_drift_rad: float = Field(0.0, ge=0, description="rms random-walk step per frame per tone")


class Amplifier(_Model):
    """Optical booster in front of the detector, after LO and echo are combined (the dissertation's
    Eq. 5.11 set-up): LO, echo and sunlight gain ``G``; ASE ``(G - 1)*n_sp*h*f0`` per polarisation
    over ``optical_bandwidth_hz`` is added (``mtcw_core.snr``)."""

    gain_db: float = Field(ge=0, le=60, description="optical power gain G (dB)")
    spontaneous_emission_factor: float = Field(1.0, ge=1.0, le=10.0, description="n_sp")
    optical_bandwidth_hz: float = Field(gt=0, le=1e14, description="ASE band reaching the detector (rectangular)")


class SolarBackground(_Model):
    """Sunlight collected through an optical filter: ``P = SSI * A * dlambda`` over ``c*dlambda/lambda^2``,
    unpolarised, in the LO's spatial mode (the dissertation's assumption; ``docs/snr.md``)."""

    spectral_irradiance_w_per_m2_nm: float = Field(gt=0, le=10.0, description="SSI at the laser wavelength")
    aperture_area_m2: float = Field(gt=0, le=100.0, description="receiver aperture (or one mode's effective area)")
    filter_bandwidth_m: float = Field(gt=0, le=1e-6, description="full width of the optical filter (2e-9 for +-1 nm)")


class OpticalNoise(_Model):
    """Broadband light at the detector; both off by default (no draw, no change to any frame)."""

    amplifier: Amplifier | None = None
    solar: SolarBackground | None = None


class Digitizer(_Model):
    sample_rate_hz: float = Field(5e9, gt=0)
    samples: int = Field(2**16, ge=2**8, le=2**26)
    adc_bits: int | None = Field(None, ge=4, le=16, description="None = float32 volts")
    full_scale_v: float | None = Field(None, gt=0, description="+-full scale; None = 1.05*max|v|")

    @property
    def duration_s(self) -> float:
        return self.samples / self.sample_rate_hz


class Pulsing(_Model):
    period_s: float = Field(gt=0)
    duty: float = Field(gt=0, le=1)
    delay_s: float = 0.0
    rise_time_s: float = Field(0.0, ge=0)
    reference_channel: bool = True


# -- PToF mode (issue 14; the simulator's part is mtcw_core/simulate/pulses.py) -------------------
class PulsedTof(_Model):
    """Pulsed time-of-flight mode: the transmitter sends short pulses instead of the modulated CW beam.

    The dissertation's mode-locked laser of its Sec. 3.4 (``gaussian``: picosecond pulses at
    25 MHz, seen through the detector's response) and the 4 ns generator pulse of its Sec. 5.5
    (``rectangular`` with raised-cosine edges). Direct (intensity) detection: the echoes of the
    targets (and of the reference mirror, ``modulated_reference``) add as powers.
    """

    shape: Literal["gaussian", "rectangular"] = "gaussian"
    repetition_hz: float = Field(25e6, gt=0, description="pulse repetition rate")
    pulse_width_s: float = Field(1e-12, gt=0, description="gaussian: FWHM of the optical pulse; rectangular: "
                                                          "time on between half maxima")
    rise_time_s: float = Field(0.0, ge=0, description="rectangular: raised-cosine edges")
    average_power_w: float = Field(1e-3, gt=0, description="transmitted average power")
    delay_s: float = Field(0.0, ge=0, description="emission of the first pulse after the trigger")
    reference_channel: bool = Field(False, description="the transmitted pulse as channel pulse_ref")

    @model_validator(mode="after")
    def _fits(self) -> "PulsedTof":
        if self.pulse_width_s + self.rise_time_s >= 0.5 / self.repetition_hz:
            raise ValueError(f"pulse_width_s: {self.pulse_width_s:g} s (+ rise_time_s) must be below half the "
                             f"period of repetition_hz ({0.5 / self.repetition_hz:g} s)")
        return self


class Frames(_Model):
    count: int = Field(1, ge=1)
    rate_hz: float = Field(10.0, gt=0)
    start_time_ns: int = Field(1_767_225_600_000_000_000, ge=0, description="trigger time of frame 0")


class Scene(_Model):
    name: str = "scene"
    description: str = ""
    seed: int = Field(0, ge=0, description="of the simulator's random generator (numpy needs it >= 0)")
    laser: Laser = Laser()
    lo_fraction: float = Field(0.1, gt=0, lt=1, description="coupler fraction beta to the LO")
    modulator: Modulator
    architecture: Architecture = Architecture()
    targets: list[Target] = Field(min_length=1)
    paths: Paths = Paths()
    receiver: Receiver = Receiver()
    noise: Noise = Noise()
    optical_noise: OpticalNoise = OpticalNoise()
    digitizer: Digitizer = Digitizer()
    pulsing: Pulsing | None = None
    frames: Frames = Frames()
    ptof: PulsedTof | None = Field(None, description="pulsed time-of-flight mode (mtcw_core.simulate.pulses)")

    @model_validator(mode="after")
    def _check_band(self) -> "Scene":
        nyq = self.digitizer.sample_rate_hz / 2
        for i, t in enumerate(self.modulator.tones):
            if t.frequency_hz >= nyq:
                raise ValueError(
                    f"modulator.tones.{i}.frequency_hz: {t.frequency_hz:g} Hz is at or above "
                    f"Nyquist ({nyq:g} Hz, half digitizer.sample_rate_hz)"
                )
        return self

    @property
    def tones_hz(self) -> list[float]:
        return self.modulator.tones_hz


def target_delay_problem(scene: Scene, index: int, frame: int) -> str | None:
    """Why target ``index`` cannot be simulated up to the end of frame ``frame`` (its echo delay
    ``tau0_s + 2*R(t)/c`` below 0: no light arrives before it left -- an approaching target has
    reached the sensor, or a range lies behind the calibration's zero by more than ``tau0_s``), or
    None. Checked per frame by the simulator (a stream goes on beyond the scene's frames)."""
    t = scene.targets[index]
    t_end = frame / scene.frames.rate_hz + scene.digitizer.samples / scene.digitizer.sample_rate_hz
    r_min = min(t.range_m, t.range_m + t.velocity_mps * t_end)
    if scene.paths.tau0_s + 2 * r_min / C >= 0:
        return None
    return (f"targets.{index}.range_m: at {t.velocity_mps:g} m/s from {t.range_m:g} m the echo delay "
            f"tau0_s + 2*R/c falls below 0 by frame {frame} (t = {t_end:g} s, R = {r_min:g} m): the target "
            f"has reached the sensor")


_PLAIN_KEY = re.compile(r"[A-Za-z0-9_-]+")


def field_path(loc: tuple) -> str:
    """A pydantic error location as a dotted field path (``targets.0.loss_db``); a key that is not a
    plain word (an unknown key such as ``""`` or ``"a b"``) is quoted, so that it is still visible."""
    return ".".join(str(x) if isinstance(x, int) or _PLAIN_KEY.fullmatch(str(x)) else repr(x) for x in loc)


def _format_validation(err: ValidationError, origin: str) -> str:
    lines = [f"invalid scene {origin}:"]
    for e in err.errors():
        loc = field_path(e["loc"]) or "(root)"
        lines.append(f"  {loc}: {e['msg']}")
    return "\n".join(lines)


def scene_from_dict(data: dict, origin: str = "<dict>") -> Scene:
    """Validate a mapping as a :class:`Scene`; raise :class:`SceneError` naming the field."""
    try:
        return Scene.model_validate(data)
    except ValidationError as err:
        raise SceneError(_format_validation(err, origin)) from None


def _merge(base, change):
    """``change`` laid over ``base``: mappings merge key by key, a non-empty list of mappings
    merges item by item (extra items appended, the base's remaining items kept), anything else
    -- an empty list too -- replaces."""
    if isinstance(base, dict) and isinstance(change, dict):
        return {**base, **{k: _merge(base.get(k), v) for k, v in change.items()}}
    if isinstance(base, list) and isinstance(change, list) and change and all(isinstance(c, dict) for c in change):
        merged = [_merge(b, c) for b, c in zip(base, change)]
        return merged + list(change[len(base):]) + list(base[len(change):])
    return change


def scene_variant(scene: Scene, **changes) -> Scene:
    """A validated copy of ``scene`` with ``changes`` laid over it (nested mappings merge).

    ``scene_variant(sc, digitizer={"samples": 2**16}, targets=[{"loss_db": 60.0}])`` changes the
    record length and the first target's loss and keeps everything else. Raises
    :class:`SceneError` naming the field when the result is not a valid scene.
    """
    return scene_from_dict(_merge(scene.model_dump(), changes), origin=f"variant of {scene.name}")


def bundled_scenes() -> dict[str, Path]:
    """Example scenes shipped with the package, by name (file stem)."""
    root = resources.files("mtcw_core") / "scenes"
    return {Path(p.name).stem: Path(str(p)) for p in root.iterdir() if p.name.endswith(".toml")}


def resolve_scene_path(name_or_path: str | Path) -> Path:
    """A scene file path, or the name of a bundled scene (``cw-bench``)."""
    p = Path(name_or_path)
    if p.exists():
        return p
    scenes = bundled_scenes()
    stem = p.stem if p.suffix == ".toml" else p.name
    if stem in scenes:
        return scenes[stem]
    raise SceneError(f"scene {str(name_or_path)!r} not found (bundled: {', '.join(sorted(scenes))})")


def load_scene(name_or_path: str | Path) -> Scene:
    """Load and validate a scene from TOML/JSON or a bundled scene name."""
    path = resolve_scene_path(name_or_path)
    try:
        text = path.read_bytes().decode("utf-8")
        data = json.loads(text) if path.suffix == ".json" else tomllib.loads(text)
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError, json.JSONDecodeError, RecursionError) as err:
        raise SceneError(f"cannot read scene {path}: {type(err).__name__}: {err}") from None
    return scene_from_dict(data, origin=str(path))
