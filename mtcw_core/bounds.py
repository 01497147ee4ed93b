"""Cramér–Rao bounds on range and speed from a scene's true line amplitudes and noise.

Independent of the chain's own SNR estimates: the line amplitudes come from a least-squares fit
of a *noiseless* frame of the scene at the known line frequencies, and the noise variance from
a frame with the echo removed (LO only: shot and thermal noise as the scene declares them). For
a single/balanced detector, line ``i`` of a family has phase ``phi_i - 4*pi*f_i*L/c + psi_F``
with one nuisance phase per family and variance ``2*s2/(N*A_i^2)``; the range bound is the
inverse Fisher information with the nuisance phases profiled out (:func:`fisher_sigma`). The
speed bound combines the frequency bounds of the Doppler-shifted lines.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .dsp.tones import fit_lines
from .ranging.triangulation import C, fisher_sigma
from .scene import Scene
from .simulate import Simulator


@dataclass(frozen=True)
class Bound:
    """Cramér–Rao bounds of one scene (first target)."""

    range_sigma_m: float
    speed_sigma_mps: float | None
    line_snr_db: float  # median post-integration SNR of the used lines, N*A^2/(2*s2)
    noise_var_v2: float


def _with(scene: Scene, **parts) -> Scene:
    return scene.model_copy(update=parts)


def noise_variance(scene: Scene, seed: int = 0) -> float:
    """Per-sample noise variance (V^2) of the detector with the echo removed."""
    quiet = [t.model_copy(update={"loss_db": 400.0}) for t in scene.targets]
    fr = Simulator(_with(scene, targets=quiet), seed).frame(0)
    x = fr.signal()
    x = x - np.mean(x)
    return float(np.mean(np.abs(x) ** 2)) / (2.0 if np.iscomplexobj(x) else 1.0)


def range_bound(scene: Scene, seed: int = 0) -> Bound | None:
    """Bounds for the scene's first target; None where not defined here (IQ, pulsed scenes)."""
    if scene.receiver.kind == "iq" or scene.pulsing is not None:
        return None
    s2 = noise_variance(scene, seed)
    clean = Simulator(_with(scene, noise=scene.noise.model_copy(update={"shot": False, "thermal": False,
                                                                         "rin_db_per_hz": None})), seed).frame(0)
    x = clean.volts("pd")
    n, fs = x.size, clean.fs_hz
    t = np.asarray(clean.tones_hz, float)
    tgt = scene.targets[0]
    fd = abs(2 * tgt.velocity_mps / scene.laser.wavelength_m)
    if fd == 0:
        families = [t]
    else:
        families = [t + fd, np.abs(t - fd)]
    freqs = np.concatenate(families)
    amp = np.abs(fit_lines(x, freqs, fs))
    var = 2 * s2 / (n * np.maximum(amp, 1e-300) ** 2)
    per_family = np.split(var, len(families))
    sig_r = fisher_sigma([t] * len(families), per_family)
    sig_v = None
    if fd > 0:
        # frequency CRB of a real sinusoid: 3*s2*fs^2/(pi^2*A^2*N^3) = 1.5*var_phase*fs^2/(pi^2*N^2)
        inv = float(np.sum(1 / (1.5 * var * fs**2 / (math.pi**2 * n**2))))
        sig_v = (1 / math.sqrt(inv)) * scene.laser.wavelength_m / 2 if inv > 0 else math.inf
    return Bound(sig_r, sig_v, float(np.median(-10 * np.log10(var))), s2)


__all__ = ["Bound", "range_bound", "noise_variance", "C"]
