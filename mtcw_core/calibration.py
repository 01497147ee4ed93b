"""Calibration from a known reflector: tone phase offsets and the internal delay tau0.

A measurement of a reflector at a known range ``L_cal`` gives, per tone, the effective phase
``phi_i_eff = phi_i - 2*pi*f_i*tau0`` (only phase *differences* are observable). It is
stored split into a linear part (``tau0``, the delay that best explains the offsets as a pure
delay, searched over ``[0, tau0_max]``) and per-tone residual phases; applying
``(phi_i, tau0)`` reproduces ``phi_i_eff`` exactly, so the split costs no accuracy.
"""

from __future__ import annotations

import datetime as _dt
import json
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .chain import ChainSettings, get_profile, measure_lines, validate
from .frame import Frame
from .ranging.triangulation import C

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


def derive_calibration(frames: Iterable[Frame], known_range_m: float, settings: ChainSettings | None = None,
                       tau0_max_s: float = 200e-9, source: str = "") -> Calibration:
    """Tone phase offsets and tau0 from frames of a reflector at ``known_range_m``.

    Per frame and line family, ``z_i*conj(z_0)`` referred to the record's start and to the
    known range gives ``phi_i_eff - phi_0_eff``; products are summed over frames and families.
    """
    settings = settings or get_profile("accurate")
    acc = None
    tones = None
    per_frame = []
    n_frames = 0
    for fr in frames:
        x, _ = validate(fr, settings, None)
        _, fams = measure_lines(x, fr, settings)
        t = np.asarray(fr.tones_hz, float)
        if tones is None:
            tones = t
            acc = np.zeros(t.size, complex)
        elif not np.array_equal(t, tones):
            raise CalibrationError(f"frame seq {fr.seq}: tone plan differs from the first frame")
        frame_sum = np.zeros(t.size, complex)
        for fam in (f for f in fams if f.target == 0):  # the static reflector's lines
            d = t - t[0]
            tau = 2 * known_range_m / C
            prod = fam.z * np.conj(fam.z[:, :1]) * np.exp(-2j * np.pi * np.outer(fam.seg_centre_s, d))
            # remove the known range: phi_i_eff - phi_0_eff = arg(prod) + 2*pi*d*tau
            frame_sum += np.sum(prod, axis=0) * np.exp(2j * np.pi * d * tau) / np.sqrt(fam.phase_var * fam.phase_var[0])
        acc += frame_sum
        per_frame.append(np.angle(frame_sum))
        n_frames += 1
    if n_frames == 0 or tones is None:
        raise CalibrationError("no frames to calibrate from")
    eff = np.angle(acc)
    spread = np.angle(np.exp(1j * (np.asarray(per_frame) - eff)))
    # split into a pure delay and residual per-tone phases
    grid = np.linspace(0, tau0_max_s, 20001)
    score = np.abs(np.exp(1j * (eff[None, :] + 2 * np.pi * np.outer(grid, tones))).sum(axis=1))
    tau0 = float(grid[int(np.argmax(score))])
    resid = np.angle(np.exp(1j * (eff + 2 * np.pi * tones * tau0)))
    return Calibration(
        tones_hz=tuple(float(f) for f in tones), tone_phases_rad=tuple(float(p) for p in resid), tau0_s=tau0,
        known_range_m=float(known_range_m), frames_used=n_frames,
        phase_std_rad=tuple(float(s) for s in np.std(spread, axis=0)), source=source,
        created=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    )
