"""Judging results against truth: truth matching, error summaries, and the Cramér–Rao bounds.

Shared by ``mtcw process`` (recordings with simulator truth) and the benchmark (``mtcw_bench``).

Bounds on range and speed come from a scene's true line amplitudes and noise, independent of the chain's own SNR estimates: the line amplitudes come from a least-squares fit
of a *noiseless* frame of the scene at the known line frequencies, and the noise variance from
a frame with the echo removed (LO only: shot and thermal noise as the scene declares them). For
a single/balanced detector, line ``i`` of a family has phase ``phi_i - 4*pi*f_i*L/c + psi_F``
with one nuisance phase per family and variance ``2*s2/(N*A_i^2)``; the range bound is the
inverse Fisher information with the nuisance phases profiled out (:func:`fisher_sigma`). The
speed bound combines the frequency bounds of the Doppler-shifted lines.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .dsp.tones import fit_lines
from .frame import TruthTarget
from .ranging.triangulation import fisher_sigma
from .results import FrameResult, TargetPoint
from .scene import Scene, scene_variant
from .simulate import Simulator


@dataclass(frozen=True)
class Bound:
    """Cramér–Rao bounds of one scene (first target)."""

    range_sigma_m: float
    speed_sigma_mps: float | None
    line_snr_db: float  # median post-integration SNR of the used lines, N*A^2/(2*s2)
    noise_var_v2: float


def noise_variance(scene: Scene, seed: int = 0) -> float:
    """Per-sample noise variance (V^2) of the detector with the echo removed."""
    quiet = scene_variant(scene, targets=[{"loss_db": 400.0}] * len(scene.targets))
    fr = Simulator(quiet, seed).frame(0)
    x = fr.signal()
    x = x - np.mean(x)
    return float(np.mean(np.abs(x) ** 2)) / (2.0 if np.iscomplexobj(x) else 1.0)


def range_bound(scene: Scene, seed: int = 0) -> Bound | None:
    """Bounds for the scene's first target; None where not defined here (IQ, pulsed scenes)."""
    if scene.receiver.kind == "iq" or scene.pulsing is not None:
        return None
    s2 = noise_variance(scene, seed)
    clean = Simulator(scene_variant(scene, noise={"shot": False, "thermal": False, "rin_db_per_hz": None}),
                      seed).frame(0)
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


def match_truth(res: FrameResult, truth: TruthTarget) -> tuple[TargetPoint, float] | None:
    """The point that answers a simulator truth target, and its range error (m).

    The point nearest in speed (several targets are told apart by Doppler); the error is wrapped
    into +-half the unambiguous range for CW frames (a range is only known modulo it), plain for
    gated frames (the coarse range removed the ambiguity). None when the result has no point.
    """
    if not res.targets:
        return None
    p = min(res.targets, key=lambda q: abs(abs(q.velocity_mps) - abs(truth.velocity_mps)))
    e = p.range_m - truth.range_m
    if res.coarse_range_m is None and res.unambiguous_range_m:
        lu = res.unambiguous_range_m
        e = (e + lu / 2) % lu - lu / 2
    return p, e


@dataclass
class ErrorLog:
    """Errors of matched points against truth, accumulated over frames.

    ``outlier_m``: a range error larger than this (e.g. a quarter of the finest synthetic
    wavelength: a wrong cycle) is counted as an outlier and kept out of the statistics.
    """

    outlier_m: float = math.inf
    range_error_m: list[float] = field(default_factory=list)
    range_sigma_m: list[float] = field(default_factory=list)
    speed_error_mps: list[float] = field(default_factory=list)
    outliers: int = 0

    def add(self, res: FrameResult, truth: TruthTarget) -> None:
        """Match ``truth`` in ``res`` (ok results only) and record the errors."""
        m = match_truth(res, truth) if res.status == "ok" else None
        if m is None:
            return
        p, e = m
        if abs(e) > self.outlier_m:
            self.outliers += 1
            return
        self.range_error_m.append(e)
        self.range_sigma_m.append(p.range_sigma_m)
        self.speed_error_mps.append(abs(p.velocity_mps) - abs(truth.velocity_mps))

    def summary(self) -> dict:
        """Bias, sample standard deviation (ddof 1), median reported sigma, largest error, speed bias
        and spread; None where there are too few matched points."""
        e, v = np.asarray(self.range_error_m), np.asarray(self.speed_error_mps)
        return {
            "matched": int(e.size), "outliers": self.outliers,
            "range_bias_m": float(np.mean(e)) if e.size else None,
            "range_std_m": float(np.std(e, ddof=1)) if e.size > 1 else None,
            "median_reported_sigma_m": float(np.median(self.range_sigma_m)) if e.size else None,
            "max_abs_range_error_m": float(np.max(np.abs(e))) if e.size else None,
            "speed_bias_mps": float(np.mean(v)) if v.size else None,
            "speed_std_mps": float(np.std(v, ddof=1)) if v.size > 1 else None,
        }


__all__ = ["Bound", "range_bound", "noise_variance", "match_truth", "ErrorLog"]
