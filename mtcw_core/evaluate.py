"""Judging results against truth: truth matching, error summaries, and the Cramér–Rao bounds.

Shared by ``mtcw process`` (recordings with simulator truth) and the benchmarks (``mtcw_bench``).
:func:`judge_frame` pairs every point of a frame with the truth target it answers and says which
are confident and wrong (issue 12's honesty rule: ``ok``, no flag, ``|z| > 5``), which are ghosts
and which targets were missed.

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
from .results import FLAGS, FrameResult, TargetPoint
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


@dataclass(frozen=True)
class PhaseNoiseBound:
    """The range bound with the laser's phase-noise leakage counted as noise (:func:`phase_noise_bound`).

    ``range_sigma_m``: from the line phase variances ``white + leakage``; ``white_sigma_m``: the
    white-noise bound alone (:func:`range_bound`); ``leak_var_rad2``: each line's leakage phase
    variance (rad^2), shape (F*T,), families in :func:`range_bound`'s order (U then L for a mover).
    """

    range_sigma_m: float
    white_sigma_m: float
    leak_var_rad2: np.ndarray


def phase_noise_bound(scene: Scene, seed: int = 0, frames: int = 8) -> PhaseNoiseBound | None:
    """:func:`range_bound` with the laser's phase noise leaking between lines counted as noise.

    The carrier phase ``Phi(t)`` between echo and LO (the laser's phase over the echo's delay)
    multiplies every line of a family alike: that part cancels in the pair phases and costs no
    range information. But each line's phase noise also spreads a pedestal over the spectrum
    (two-sided PSD ``linewidth*(1 - cos(2*pi*f*tau))/(pi*f^2)`` at offset ``f``), which falls on the
    other lines: a strong line near a weak one -- the baseband Doppler line, 35 dB above the
    sidebands, 14-26 MHz from a 20 MHz tone's lines -- sets a phase-noise floor the white-noise
    bound does not see, and which more echo power does not lower.

    Measured, not modelled: ``frames`` noiseless frames of the scene (shot, thermal, RIN off) and
    their ideal-laser twins (the same seed: the same trajectory); per family the ratio of the
    lines fitted at their true frequencies, its common phase taken out (weighted by the line
    variances, iterated), leaves each line's leakage phase; its mean square over the frames is
    added to the white-noise phase variance ``2*s2/(N*A^2)`` and the range bound follows as in
    :func:`range_bound` (one nuisance phase per family). The leakage is treated as independent
    noise per line: the bound of estimators that take it for noise. One that tracks the carrier
    phase (from the strong baseband line) and takes the pedestals out could do better, so this is
    a reference for where the white-noise bound is out of reach, not a lower bound.

    Returns None where :func:`range_bound` is (IQ, pulsed scenes).
    """
    white = range_bound(scene, seed)
    if white is None:
        return None
    quiet = {"shot": False, "thermal": False, "rin_db_per_hz": None}
    t = np.asarray(scene.tones_hz, float)
    fd = abs(2 * scene.targets[0].velocity_mps / scene.laser.wavelength_m)
    families = [t] if fd == 0 else [t + fd, np.abs(t - fd)]
    freqs = np.concatenate(families)
    nf, nt = len(families), t.size
    ratios, amp2 = [], None
    twins = Simulator(scene_variant(scene, noise=quiet, laser={"linewidth_hz": 0.0}), seed).frames(frames)
    noisy = Simulator(scene_variant(scene, noise=quiet), seed).frames(frames)
    for ideal, fr in zip(twins, noisy):
        z0 = fit_lines(ideal.volts("pd"), freqs, ideal.fs_hz)
        ratios.append(fit_lines(fr.volts("pd"), freqs, fr.fs_hz) / np.where(z0 == 0, 1.0, z0))
        if amp2 is None:  # the first frame's amplitudes, as range_bound takes them
            amp2 = np.abs(z0) ** 2
    r = np.asarray(ratios)  # (frames, F*T)
    n = scene.digitizer.samples
    white_var = 2 * white.noise_var_v2 / (n * np.maximum(amp2, 1e-300))
    var = white_var
    leak = np.zeros_like(white_var)
    for _ in range(3):  # the common phase weighted by the variances found so far
        d = r.copy()
        for j in range(nf):
            sl = slice(j * nt, (j + 1) * nt)
            d[:, sl] *= np.exp(-1j * np.angle(np.sum(d[:, sl] / var[sl], axis=1)))[:, None]
        leak = np.mean(np.angle(d) ** 2, axis=0)
        leak[leak < 1e-24] = 0.0  # rounding: an ideal laser's lines equal their twins'
        var = white_var + leak
    sigma = fisher_sigma([t] * nf, np.split(var, nf))
    return PhaseNoiseBound(sigma, white.range_sigma_m, leak)


def range_error_m(point: TargetPoint, res: FrameResult, truth: TruthTarget) -> float:
    """``point``'s range error against ``truth`` (m), wrapped into +-half the unambiguous range for
    CW frames (a CW range is only known modulo it), plain for gated frames (the coarse range
    removed the ambiguity)."""
    e = point.range_m - truth.range_m
    if res.coarse_range_m is None and res.unambiguous_range_m:
        lu = res.unambiguous_range_m
        e = (e + lu / 2) % lu - lu / 2
    return e


def speed_error_mps(point: TargetPoint, truth: TruthTarget) -> float:
    """``point``'s speed error against ``truth`` (m/s): signed velocities when the point knows the
    direction (IQ: ``receding``/``approaching``), else speeds ``|v|`` (a real detector sees
    ``|f_d|``; a ``static`` point says 0)."""
    if point.direction in ("receding", "approaching"):
        return point.velocity_mps - truth.velocity_mps
    return abs(point.velocity_mps) - abs(truth.velocity_mps)


def range_rate_error_mps(point: TargetPoint, truth: TruthTarget) -> float | None:
    """``point``'s range rate over frames (:mod:`mtcw_core.ranging.track`) against ``truth``'s
    velocity (m/s, positive receding: the rate of its range); None where it carries none."""
    return None if point.range_rate_mps is None else point.range_rate_mps - truth.velocity_mps


def match_truth(res: FrameResult, truth: TruthTarget) -> tuple[TargetPoint, float] | None:
    """The point that answers a simulator truth target, and its range error (m).

    The point nearest in speed (several targets are told apart by Doppler); the error is
    :func:`range_error_m`. None when the result has no point.
    """
    if not res.targets:
        return None
    p = min(res.targets, key=lambda q: abs(abs(q.velocity_mps) - abs(truth.velocity_mps)))
    return p, range_error_m(p, res, truth)


@dataclass
class ErrorLog:
    """Errors of matched points against truth, accumulated over frames.

    ``outlier_m``: a range error larger than this (e.g. a quarter of the finest synthetic
    wavelength: a wrong cycle) is counted as an outlier and kept out of the statistics. A speed
    that could not be measured (the 0 of direction ``unknown`` with the search's largest speed as
    its sigma: a laser incoherent at the target) is no error and kept out of the speed's; a point's
    range rate over frames (:mod:`mtcw_core.ranging.track`) is compared with the truth's velocity.
    """

    outlier_m: float = math.inf
    range_error_m: list[float] = field(default_factory=list)
    range_sigma_m: list[float] = field(default_factory=list)
    speed_error_mps: list[float] = field(default_factory=list)
    rate_error_mps: list[float] = field(default_factory=list)
    rate_z: list[float] = field(default_factory=list)
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
        if p.speed_measured or p.direction == "static":  # a static claim's 0 is an answer
            self.speed_error_mps.append(abs(p.velocity_mps) - abs(truth.velocity_mps))
        ed = range_rate_error_mps(p, truth)
        if ed is not None:
            self.rate_error_mps.append(ed)
            self.rate_z.append(_z(ed, p.range_rate_sigma_mps))

    def summary(self) -> dict:
        """Bias, sample standard deviation (ddof 1), median reported sigma, largest error, speed bias
        and spread; None where there are too few matched points. With range rates (``--track``):
        their count, bias, spread and largest ``|z|``."""
        e, v, r = np.asarray(self.range_error_m), np.asarray(self.speed_error_mps), np.asarray(self.rate_error_mps)
        rates = {} if not r.size else {
            "range_rates": int(r.size), "range_rate_bias_mps": float(np.mean(r)),
            "range_rate_std_mps": float(np.std(r, ddof=1)) if r.size > 1 else None,
            "range_rate_max_abs_z": float(np.max(np.abs(self.rate_z)))}
        return {
            "matched": int(e.size), "outliers": self.outliers,
            "range_bias_m": float(np.mean(e)) if e.size else None,
            "range_std_m": float(np.std(e, ddof=1)) if e.size > 1 else None,
            "median_reported_sigma_m": float(np.median(self.range_sigma_m)) if e.size else None,
            "max_abs_range_error_m": float(np.max(np.abs(e))) if e.size else None,
            "speed_bias_mps": float(np.mean(v)) if v.size else None,
            "speed_std_mps": float(np.std(v, ddof=1)) if v.size > 1 else None,
            **rates,
        }


#: |z| above which an error is "wrong" (issue 12: a confident wrong answer is |z| > 5, unflagged).
Z_WRONG = 5.0


@dataclass(frozen=True)
class PointVerdict:
    """One reported point judged against the truth.

    ``truth_index`` is the truth target it answers (None: a false target). Errors are in m and
    m/s; z-scores are error over the point's own sigma. ``speed_measured`` is False for a point
    that reports ``static`` (speed 0 with the smallest detectable speed as its sigma) and for one
    whose speed could not be measured (``unknown``, 0 with the search's largest speed as its sigma:
    :attr:`~mtcw_core.results.TargetPoint.speed_measured`). ``rate_error_mps``/``rate_z``: the
    point's range rate over frames (:mod:`mtcw_core.ranging.track`) against the truth's velocity
    (positive receding), None where the point carries none.
    """

    truth_index: int | None
    range_error_m: float | None
    range_z: float | None
    speed_error_mps: float | None
    speed_z: float | None
    speed_measured: bool
    flags: tuple[str, ...]
    rate_error_mps: float | None = None
    rate_z: float | None = None

    @property
    def flagged(self) -> bool:
        return bool(self.flags)

    def wrong(self, z_wrong: float = Z_WRONG) -> bool:
        """A false target, or a range, speed or range rate off by more than ``z_wrong`` of its own sigma."""
        if self.truth_index is None:
            return True
        return abs(self.range_z) > z_wrong or abs(self.speed_z) > z_wrong or abs(self.rate_z or 0.0) > z_wrong


@dataclass(frozen=True)
class FrameVerdict:
    """One frame's result judged against every truth target (:func:`judge_frame`).

    ``missed``: truth indices no point answers. ``confident_wrong``: the issue's definition -- a
    point answering a truth, status ``ok``, no flag, ``|z| > z_wrong`` on range or speed.
    ``confident_false``: an unflagged point that answers no truth (a ghost). ``flagged_wrong``:
    points that are wrong but carry a flag (a flag beside a wrong number).
    """

    status: str
    points: tuple[PointVerdict, ...]
    missed: tuple[int, ...]
    z_wrong: float = Z_WRONG

    @property
    def false_targets(self) -> int:
        return sum(p.truth_index is None for p in self.points)

    @property
    def flagged_points(self) -> int:
        return sum(p.flagged for p in self.points)

    @property
    def confident_wrong(self) -> bool:
        return any(p.truth_index is not None and not p.flagged and p.wrong(self.z_wrong) for p in self.points)

    @property
    def confident_false(self) -> bool:
        return any(p.truth_index is None and not p.flagged for p in self.points)

    @property
    def flagged_wrong(self) -> int:
        return sum(p.flagged and p.wrong(self.z_wrong) for p in self.points)


def flags_of(point: TargetPoint) -> tuple[str, ...]:
    """The names in :data:`FLAGS` that ``point`` raises."""
    return tuple(f for f in FLAGS if getattr(point, f))


def judge_frame(res: FrameResult, truths: tuple[TruthTarget, ...] | list[TruthTarget],
                z_wrong: float = Z_WRONG) -> FrameVerdict:
    """Judge every point of ``res`` against every truth target, one point per truth.

    A point *answers* a truth when it agrees with it on speed or on range (:func:`_answers`): a
    point with the right speed and a wrong cycle, or the right range and a speed reported 0 for a
    mover, answers it (and is wrong); a point wrong on both is a ghost. Points and truths that
    answer each other are paired greedily: first those that agree on both range and speed (a
    mover reported ``static`` within its speed floor answers the mover at its range, not a static
    target 7 m away), then by speed difference (targets are told apart by their Doppler), ties by
    range error; a point left over is a false target, a truth left over is missed. Only ``ok``
    results have points; any other status misses every truth.

    Parameters
    ----------
    res : the chain's result for the frame
    truths : the simulator's truth targets (range at the record's centre, m; velocity, m/s)
    z_wrong : |z| above which a matched point is wrong
    """
    points = list(res.targets) if res.status == "ok" else []
    pairs = sorted((-agree, abs(dv), abs(dr), i, j) for i, p in enumerate(points) for j, t in enumerate(truths)
                   for dv, dr in [(speed_error_mps(p, t), range_error_m(p, res, t))]
                   for agree in [_answers(p, t, dv, dr)] if agree)
    owner: dict[int, int] = {}
    taken: set[int] = set()
    for _, _, _, i, j in pairs:
        if i not in owner and j not in taken:
            owner[i] = j
            taken.add(j)
    verdicts = []
    for i, p in enumerate(points):
        j = owner.get(i)
        measured = p.speed_measured
        if j is None:
            verdicts.append(PointVerdict(None, None, None, None, None, measured, flags_of(p)))
            continue
        er, ev = range_error_m(p, res, truths[j]), speed_error_mps(p, truths[j])
        ed = range_rate_error_mps(p, truths[j])
        verdicts.append(PointVerdict(j, er, _z(er, p.range_sigma_m), ev, _z(ev, p.velocity_sigma_mps), measured,
                                     flags_of(p), ed, None if ed is None else _z(ed, p.range_rate_sigma_mps)))
    return FrameVerdict(res.status, tuple(verdicts), tuple(j for j in range(len(truths)) if j not in taken), z_wrong)


#: a point agrees with a truth on speed within the larger of 5 of its sigmas, a quarter of the
#: speed and this (m/s); on range within the larger of 5 of its sigmas and this (m)
SPEED_AGREE_MPS, RANGE_AGREE_M = 0.01, 0.01


def _answers(p: TargetPoint, t: TruthTarget, dv: float, dr: float) -> int:
    """On how many of speed and range point ``p`` agrees with truth ``t`` (speed error ``dv``, m/s;
    range error ``dr``, m): 0 (it cannot be the chain's answer for ``t``), 1 or 2."""
    close_v = abs(dv) <= max(Z_WRONG * p.velocity_sigma_mps, 0.25 * abs(t.velocity_mps), SPEED_AGREE_MPS)
    close_r = abs(dr) <= max(Z_WRONG * p.range_sigma_m, RANGE_AGREE_M)
    return int(close_v) + int(close_r)


def _z(error: float, sigma: float) -> float:
    """error/sigma; an exact answer with a zero sigma is 0, a wrong one inf."""
    if sigma > 0:
        return error / sigma
    return 0.0 if error == 0 else math.copysign(math.inf, error)


__all__ = ["Bound", "range_bound", "PhaseNoiseBound", "phase_noise_bound", "noise_variance", "match_truth", "range_error_m", "speed_error_mps",
           "range_rate_error_mps",
           "ErrorLog", "FLAGS", "Z_WRONG", "PointVerdict", "FrameVerdict", "flags_of", "judge_frame"]
