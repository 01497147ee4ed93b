"""Deriving a calibration from frames of a reflector at a known range (uses the chain's stages).

A measurement of a reflector at a known range ``L_cal`` gives, per tone, the effective phase
``phi_i_eff = phi_i - 2*pi*f_i*tau0`` (their differences; on a real receiver with an unmodulated
LO, whose still lines are real, their own values modulo pi too). It is
stored split into a linear part (``tau0``, the delay that best explains the offsets as a pure
delay, searched over ``[0, tau0_max]``) and per-tone residual phases; applying
``(phi_i, tau0)`` reproduces ``phi_i_eff`` exactly, so the split costs no accuracy.
"""

from __future__ import annotations

import datetime as _dt
import math
from collections.abc import Iterable

import numpy as np

from .calibration import Calibration, CalibrationError
from .chain import run_stages
from .dsp.extract import LineFamily
from .frame import Frame
from .phase import C, wrap_pi
from .profiles import ChainSettings, get_profile
from .ranging.targets import line_powers


def derive_calibration(frames: Iterable[Frame], known_range_m: float, settings: ChainSettings | None = None,
                       tau0_max_s: float = 200e-9, source: str = "") -> Calibration:
    """Tone phase offsets and tau0 from frames of a reflector at ``known_range_m``.

    Per frame and line family, ``z_i*conj(z_0)`` referred to the record's start and to the
    known range gives ``phi_i_eff - phi_0_eff``; products are summed over frames and families.
    The lines' sizes relative to their mean (:func:`relative_amplitudes`), averaged over the
    frames, are the tone amplitudes the chain checks a static point's lines against. On a real
    receiver with an unmodulated LO a still reflector's lines are real (``2*cos(psi)`` times the
    tone's phasor): the first tone's own phase is then known modulo pi (its segments' squares) and
    the phases are stored absolute (``Calibration.phases_absolute``).
    """
    settings = settings or get_profile("accurate")
    acc = None
    tones = None
    per_frame, amps = [], []
    n_frames = 0
    own = 0j  # the first tone's line, squared, at the known range: its phase is 2*phi_0_eff (mod 2*pi)
    absolute = True
    tau = 2 * known_range_m / C
    for fr in frames:
        fams = run_stages(fr, settings, None, until="extract").families  # raises Rejected
        t = np.asarray(fr.tones_hz, float)
        if tones is None:
            tones = t
            acc = np.zeros(t.size, complex)
        elif not np.array_equal(t, tones):
            raise CalibrationError(f"frame seq {fr.seq}: tone plan differs from the first frame")
        frame_sum = np.zeros(t.size, complex)
        amps.append(relative_amplitudes(fams))
        absolute = absolute and fr.receiver != "iq" and fr.architecture == "unmodulated_lo"
        for fam in (f for f in fams if f.target == 0):  # the static reflector's lines
            d = t - t[0]
            own += np.sum((fam.z[:, 0] * np.exp(-2j * np.pi * t[0] * (fam.seg_centre_s - tau))) ** 2) / fam.phase_var[0]
            prod = fam.z * np.conj(fam.z[:, :1]) * np.exp(-2j * np.pi * np.outer(fam.seg_centre_s, d))
            # remove the known range: phi_i_eff - phi_0_eff = arg(prod) + 2*pi*d*tau
            frame_sum += np.sum(prod, axis=0) * np.exp(2j * np.pi * d * tau) / np.sqrt(fam.phase_var * fam.phase_var[0])
        acc += frame_sum
        per_frame.append(np.angle(frame_sum))
        n_frames += 1
    if n_frames == 0 or tones is None:
        raise CalibrationError("no frames to calibrate from")
    eff = np.angle(acc)
    spread = wrap_pi(np.asarray(per_frame) - eff)
    if absolute:
        eff = eff + 0.5 * np.angle(own)
    # split into a pure delay and residual per-tone phases
    grid = np.linspace(0, tau0_max_s, 20001)
    score = np.abs(np.exp(1j * (eff[None, :] + 2 * np.pi * np.outer(grid, tones))).sum(axis=1))
    tau0 = float(grid[int(np.argmax(score))])
    resid = wrap_pi(eff + 2 * np.pi * tones * tau0)
    return Calibration(
        tones_hz=tuple(float(f) for f in tones), tone_phases_rad=tuple(float(p) for p in resid), tau0_s=tau0,
        known_range_m=float(known_range_m), frames_used=n_frames, phases_absolute=bool(absolute),
        phase_std_rad=tuple(float(s) for s in np.std(spread, axis=0)), source=source,
        tone_amplitudes=tuple(float(a) for a in np.mean(amps, axis=0)),
        tone_amplitude_std=tuple(float(a) for a in np.std(amps, axis=0, ddof=min(1, n_frames - 1))
                                 / math.sqrt(n_frames)),
        created=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    )


def relative_amplitudes(fams: list[LineFamily]) -> np.ndarray:
    """The static lines' sizes (:func:`~mtcw_core.ranging.targets.line_powers`, as the chain's check
    takes them: less the noise's share, an IQ record's two sidebands pooled) relative to their
    mean, shape (T,), in the frame's tone order: what a reflector's frame says of the tone
    amplitudes (the modulation depths and the front end's response at each tone;
    ``ChainSettings.tone_amplitudes``)."""
    static = [f for f in fams if f.target == 0]
    tones, power, _ = line_powers(static)
    a = np.sqrt(np.maximum(power, 0.0))[np.searchsorted(tones, static[0].tone_hz)]
    if not np.all(np.isfinite(a)) or np.min(a) <= 0:
        raise CalibrationError("a tone's line is missing from the reflector's frame: no tone amplitudes")
    return a / np.mean(a)


def tone_amplitudes(frames: Iterable[Frame], settings: ChainSettings | None = None) -> tuple[float, ...]:
    """One target's relative tone amplitudes (:func:`relative_amplitudes`) averaged over ``frames``
    of a reflector (any range, no other echo), for ``ChainSettings.tone_amplitudes``."""
    settings = settings or get_profile("accurate")
    amps = [relative_amplitudes(run_stages(fr, settings, None, until="extract").families) for fr in frames]
    if not amps:
        raise CalibrationError("no frames to measure tone amplitudes from")
    return tuple(float(a) for a in np.mean(amps, axis=0))
