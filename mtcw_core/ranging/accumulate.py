"""Reach beyond the laser's coherence: digital IF mixing of the whole band, and accumulation over frames.

Issue 12, case 9. With a laser incoherent at the LO delay (the dissertation's 5.3 GHz laser,
500x its coherence length) every LO x echo beat is spread over the laser's linewidth and only
the echo's self-beat ``|E_echo|^2`` keeps lines at the tones; those scale with the echo power
*squared* and are lost from ~40 dB of echo loss (``docs/reach.md`` has the numbers).

**Whole-band digital IF mixing** (:func:`square_lines`; the dissertation's section 5.2.4: the
RF "mixed, either electronically or in the digital domain"). Square the whole record after
removing its mean. The LO x echo beat ``b(t) = 2*R*Re(conj(E_lo)*E_echo)`` squared is
``2*R^2*|E_lo|^2*|E_echo|^2 + 2*R^2*Re((conj(E_lo)*E_echo)^2)``: the first term is the echo's
intensity ``|M(t - tau)|^2`` times the LO power, with lines at every tone ``f_i`` whose phase is
``phi_i - 2*pi*f_i*tau`` -- the laser's phase (LO and echo alike) and the carrier's Doppler have
cancelled, as in the self-beat, but the line is ``~sqrt(8)*I_LO/sigma`` stronger than the
self-beat in a noise of rms ``sigma``; the second term carries twice the laser phase difference
and is spread over twice the linewidth (noise). It is every pair product "band around ``f_i``
times the conjugate of the band around 0" at once: with the beat spread over GHz the bands
cannot be cut apart, and cutting them keeps only a part of the power (measured: ``docs/reach.md``).
The same holds for a balanced receiver (``b`` alone) and an IQ receiver (``|x|^2``).

**Accumulation over frames** (:class:`Accumulator`). The squared lines of a static target carry
no per-frame nuisance phase (no carrier, no laser phase), and the tone phases are referred to
the trigger, so successive frames' line phasors (referred to the record's first sample) have
the same expected value: their inverse-variance weighted mean has its noise variance divided
by the number of frames ``K``, and the range is solved from the mean by the chain's own IF
mixing, cycle resolution, Fisher sigma and consistency checks
(:func:`mtcw_core.ranging.mixing.pair_observations`, :func:`mtcw_core.ranging.targets.solve_target`).

Honesty rules of the accumulator:

- a change of source, run, tone plan, tone phases, sample rate, record length or receiver
  starts a new window (``reset_reason`` says why);
- a *phase drift test* on every new frame: the newest frame's phasors against the mean of the
  others, and the newer half of the window against the older half (both a chi-square of the
  complex differences over their noise, exact at any SNR for a static target); either beyond
  ``drift_p`` starts a new window from the newest frame (a mover, a changed target);
- the point rests on the frames it averages (``TargetPoint.accumulated_frames``) and refers to
  their mean (for a target moving slower than the drift test sees, the range at the window's
  centre);
- speed: the squared lines carry no Doppler (it cancels with the laser phase), so the point says
  0 with the largest searched speed as its sigma, direction ``unknown``: never a claimed ``static``.

Settings live in :class:`AccumulateSettings` (not in :class:`~mtcw_core.profiles.ChainSettings`):
the chain's settings (threshold ``min_line_snr_db``, cycle resolution, declared timing jitter)
are used as they are.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
import scipy.fft as sfft
from scipy.stats import chi2 as chi2_dist

from ..calibration import Calibration
from ..dsp.doppler import MIN_CARRIER_COHERENCE, DopplerEstimate, fd_max
from ..dsp.extract import LineFamily
from ..dsp.spectrum import cached_window, window_power
from ..dsp.tones import fit_lines
from ..dsp.validate import validate
from ..frame import Frame, TruthTarget
from ..phase import unambiguous_range
from ..profiles import ChainSettings
from ..results import FrameResult, NoTarget, Rejected, TargetPoint
from .gating import is_gated
from .mixing import pair_observations
from .targets import Reference, _search_interval, carrier_coherence, solve_target

#: the largest number of frames a point may rest on (issue 12's target: <= 32)
MAX_FRAMES = 32
LN2 = math.log(2.0)


class AccumulateSettings(BaseModel):
    """How the accumulator extracts and averages (kept apart from the chain's settings).

    ``frames``: the window, K <= 32 frames (1: whole-band IF mixing of one frame, no averaging).
    ``extraction``: ``square`` (whole-band digital IF mixing, :func:`square_lines`).
    ``drift_p``: false-alarm probability of each phase drift test per frame.
    ``edge_samples``: samples left out at each end of a record before squaring (a front end's
    filter settling at the record's start puts a broadband transient there; 0 for none).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    frames: int = Field(1, ge=1, le=MAX_FRAMES, description="frames a point may rest on (K)")
    extraction: Literal["square"] = Field("square", description="square: whole-band digital IF mixing")
    drift_p: float = Field(1e-4, gt=0, lt=0.5, description="false-alarm probability of each drift test")
    edge_samples: int = Field(0, ge=0, le=2**20, description="samples dropped at each record end")
    noise_half_width: int = Field(512, ge=16, le=2**16, description="bins each side of a line for its noise floor")


# -------------------------------------------------------------------------------------------
# whole-band digital IF mixing
def _fold(f: np.ndarray, fs: float) -> np.ndarray:
    """Frequencies (Hz) folded into [0, fs/2] as a real sampled signal sees them."""
    return np.abs((np.asarray(f, float) + fs / 2) % fs - fs / 2)


def product_lines(tones_hz: np.ndarray, fs_hz: float) -> np.ndarray:
    """The other lines of a squared record: ``|f_i - f_j|``, ``f_i + f_j``, ``2*f_i`` (folded, Hz).

    The echo's intensity ``|M|^2`` holds the MZM's products, and squaring the self-beat and the
    tones adds them again; they are fitted jointly with the tones so that none leaks into a tone.
    """
    t = np.asarray(tones_hz, float)
    i, j = np.triu_indices(t.size, 1)
    return _fold(np.concatenate([np.abs(t[i] - t[j]), t[i] + t[j], 2 * t]), fs_hz)


@dataclass(frozen=True)
class SquaredLines:
    """One frame's tone lines in the squared record.

    Attributes
    ----------
    tone_hz : ndarray, shape (T,), Hz
    z_start : ndarray, shape (T,), complex
        Cosine amplitude of each line (V^2), referred to the record's first sample (model
        ``Re(z*exp(j*2*pi*f*t))``); phase ``phi_i - 2*pi*f_i*tau`` for one static target.
    var_z : ndarray, shape (T,)
        ``E|dz|^2`` of each amplitude's noise (V^4), from the local noise floor; inf where the
        line cannot be told from a product line.
    n : int
        Samples the amplitudes rest on.
    """

    tone_hz: np.ndarray
    z_start: np.ndarray
    var_z: np.ndarray
    n: int

    @property
    def snr_db(self) -> np.ndarray:
        """Post-integration line SNR ``|z|^2/E|dz|^2`` (dB), shape (T,)."""
        with np.errstate(divide="ignore"):
            return 10 * np.log10(np.abs(self.z_start) ** 2 / self.var_z)


def square_lines(x: np.ndarray, fs_hz: float, tones_hz, edge_samples: int = 0,
                 noise_half_width: int = 512) -> SquaredLines:
    """Whole-band digital IF mixing: the tone lines of the squared record (see the module docstring).

    Parameters
    ----------
    x : ndarray, shape (N,), float64 (single/balanced photodiode) or complex128 (IQ), V
    fs_hz : float, sample rate (Hz)
    tones_hz : array_like, shape (T,), the modulation tones (Hz)
    edge_samples : samples dropped at each end before squaring
    noise_half_width : bins each side of a line over which its noise floor is taken

    Returns
    -------
    SquaredLines

    Notes
    -----
    Amplitudes: a joint least-squares fit (:func:`mtcw_core.dsp.tones.fit_lines`) of the tones and
    every product line at their exact frequencies. Noise: the median of a Kaiser-windowed
    (beta 14) periodogram of the squared record over ``+-noise_half_width`` bins around each
    tone, lines excluded (median = ln 2 x mean of an exponential variable), as a per-sample
    white-noise variance ``s2``; ``E|dz|^2 = 4*s2/N`` for the fitted cosine amplitude. A tone
    within 2 bins of a product line cannot be told from it: its variance is inf.
    """
    x = np.asarray(x)
    if edge_samples:
        x = x[edge_samples:x.size - edge_samples]
    n = x.size
    if n < 256:
        raise Rejected("too_short", f"{n} samples left to square (edge_samples {edge_samples})")
    t = np.asarray(tones_hz, float)
    y = x - x.mean()
    p = (y.real**2 + y.imag**2) if np.iscomplexobj(y) else y * y
    p = p - p.mean()
    res = fs_hz / n
    prods = product_lines(t, fs_hz)
    clash = np.abs(t[:, None] - prods[None, :]).min(axis=1) <= 2 * res
    keep = [f for f in np.unique(np.round(prods, 6))
            if np.all(np.abs(t - f) > 2 * res) and 2 * res < f < fs_hz / 2 - 2 * res]
    freqs = np.concatenate([t, np.asarray(keep, float)])
    z = fit_lines(p, freqs, fs_hz)[: t.size]
    t_c = (n - 1) / (2 * fs_hz)
    z_start = z * np.exp(-2j * np.pi * np.mod(t * t_c, 1.0))
    # the local noise floor of the squared record
    spec = np.abs(sfft.rfft(p * cached_window(("kaiser", 14.0), n))) ** 2  # the chain's cached window
    wpow = window_power(("kaiser", 14.0), n)
    lines = np.concatenate([t, prods, [0.0]])
    bins = np.arange(spec.size)
    s2 = np.empty(t.size)
    for k, f in enumerate(t):
        b = int(round(f / res))
        lo, hi = max(b - noise_half_width, 0), min(b + noise_half_width + 1, spec.size)
        idx = bins[lo:hi]
        mask = np.ones(idx.size, bool)
        for g in lines:
            mask &= np.abs(idx - g / res) > 16
        vals = spec[idx[mask]] if mask.sum() >= 16 else spec[idx]
        s2[k] = float(np.median(vals)) / LN2 / wpow
    var = 4 * s2 / n
    var[clash] = np.inf
    return SquaredLines(t, z_start, var, n)


# -------------------------------------------------------------------------------------------
# ranging from (averaged) lines
def family_of(lines: SquaredLines) -> LineFamily:
    """The lines as a :class:`~mtcw_core.dsp.extract.LineFamily` for the chain's IF mixing and
    cycle resolution (one segment centred on the record's first sample; ``phase_var`` from the
    amplitude's noise with ``|z|^2`` debiased by it, so that a line near the noise is not
    credited with the noise's own power)."""
    amp2 = np.maximum(np.abs(lines.z_start) ** 2 - lines.var_z, 1e-3 * np.where(
        np.isfinite(lines.var_z), lines.var_z, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        pv = np.where(np.isfinite(lines.var_z) & (amp2 > 0), lines.var_z / (2 * amp2), np.inf)
    return LineFamily("Q", lines.tone_hz, lines.tone_hz.copy(), lines.z_start[None, :].copy(), np.zeros(1), pv, 0)


def range_from_lines(lines: SquaredLines, frame: Frame, settings: ChainSettings, ref: Reference
                     ) -> tuple[TargetPoint, float]:
    """One point from (possibly averaged) squared lines: the chain's IF mixing, ``ml``/``seed``
    cycle resolution, Fisher sigma, line-phase consistency, cycle-slip odds and declared timing
    jitter (:func:`~mtcw_core.ranging.targets.solve_target`). The speed is unknown (0 with the
    largest searched speed as its sigma). Raises :class:`~mtcw_core.results.NoTarget` when fewer
    than two lines clear ``settings.min_line_snr_db``.

    Returns the point and the unambiguous range (m) of the pairs it rests on (a tone left out
    widens it: ``c/(2*gcd)`` of the differences used, not of the plan)."""
    fam = family_of(lines)
    obs = pair_observations([fam], ref.tone_phases_rad, settings.min_line_snr_db)
    if obs.df_hz.size == 0:
        best = float(np.max(fam.snr_db)) if np.isfinite(fam.snr_db).any() else -np.inf
        raise NoTarget(f"fewer than two squared lines above {settings.min_line_snr_db} dB (best {best:.1f} dB)")
    v_max = fd_max(frame.tones_hz, settings) * frame.wavelength_m / 2
    static = DopplerEstimate(0.0, False, 0.0, 0.0, 0.0)
    l_unamb = float(unambiguous_range(obs.df_hz))
    # the tone amplitudes are the LO-beat lines': the squared record's lines are the echo's
    # intensity, ``a_0*a_i`` plus the tones' products that fall on ``f_i`` (none checked against them)
    p = solve_target([fam], obs, static, frame, settings, replace(ref, tone_amplitudes=None), None, l_unamb)
    # the squared lines carry no Doppler: any speed up to the search's limit fits them
    return replace(p, velocity_mps=0.0, velocity_sigma_mps=v_max, direction="unknown", speed_min_mps=v_max), l_unamb


def square_can_range(settings: ChainSettings, tones_hz) -> bool:
    """Whether the declared laser is incoherent (carrier coherence below ``MIN_CARRIER_COHERENCE``)
    anywhere in the searched range interval: where it is not, :func:`square_point` refuses every
    range, so the chain need not square the record. ``|2L - d_LO|`` is convex in ``L``, so the
    coherence is lowest at an end of the interval (no quasi-CW gate here: the plan's unambiguous
    range, the longest any subset of its pairs can give). False for a laser declared coherent."""
    lo, hi, _ = _search_interval(settings, float(unambiguous_range(np.diff(np.sort(np.asarray(tones_hz, float))))),
                                 None)
    return min(carrier_coherence(settings, lo), carrier_coherence(settings, hi)) < MIN_CARRIER_COHERENCE


def square_point(x: np.ndarray, frame: Frame, settings: ChainSettings, ref: Reference,
                 why: str | None = None) -> tuple[list[TargetPoint], float, str]:
    """The chain's ``square`` stage: one frame's point from its squared record, when the chain's
    own lines gave none (``why``).

    The squared lines carry neither the laser's phase nor the carrier's Doppler: they range a
    target far beyond the laser's coherence (issue 12 case 9, ``docs/reach.md``), with its speed
    unknown. They hold the *sum* of every target's intensity, so several targets blend into one
    plausible wrong range (3 tones leave one degree of freedom to see it). Where the declared
    laser is coherent at the range they give (carrier coherence >= ``MIN_CARRIER_COHERENCE``), a
    single target there would have shown in the chain's own lines, far stronger: the squared
    lines are then taken for a blend (or an undeclared laser) and give no point.

    Parameters
    ----------
    x : ndarray, shape (N,), float64 or complex128, V: the validated record
    frame : Frame
    settings : ChainSettings (``laser_linewidth_hz``, ``lo_path_difference_m``: the declared laser)
    ref : Reference, the tone phases and ``tau0`` in force
    why : why the chain's own lines gave no target (for the reasons below)

    Returns
    -------
    ([TargetPoint], unambiguous range (m), reason): the point, the period its range is given in
    (the pairs it rests on), and the result's reason saying where it came from

    Raises
    ------
    NoTarget
        Fewer than two squared lines above ``settings.min_line_snr_db``, or a range where the
        declared laser is coherent: ``why`` and that.
    """
    why = why or "no target"
    try:
        point, l_unamb = range_from_lines(square_lines(x, frame.fs_hz, frame.tones_hz), frame, settings, ref)
    except NoTarget as sq:
        raise NoTarget(f"{why}; {sq}") from None
    coherence = carrier_coherence(settings, point.range_m)
    if coherence >= MIN_CARRIER_COHERENCE:
        raise NoTarget(f"{why}; the squared record's lines give {point.range_m:.3f} m, where the declared laser is "
                       f"coherent (carrier coherence {coherence:.2f}): one target there would show in the chain's "
                       "own lines, so they blend several")
    return [point], l_unamb, f"squared record (whole-band IF mixing): {why} in the chain's own; speed unknown"


def square_rival(x: np.ndarray, frame: Frame, settings: ChainSettings, ref: Reference, own: TargetPoint
                 ) -> tuple[list[TargetPoint], float, str] | None:
    """The ``square`` stage beside the chain's own point ``own`` (:func:`square_rivals`): the
    squared record's point, its unambiguous range (m) and the result's reason where it is the
    better one (:func:`better_point`); None to keep ``own`` (also when the squared lines give none)."""
    try:
        points, l_unamb, _ = square_point(x, frame, settings, ref, "no target")
    except NoTarget:
        return None
    if not better_point(own, points[0]):
        return None
    return points, l_unamb, (f"squared record (whole-band IF mixing): the chain's own lines (the echo's self-beat) "
                             f"gave {own.range_m:.4f} +- {own.range_sigma_m:.4f} m{' (flagged)' if own.flagged else ''};"
                             " speed unknown")


def square_rivals(targets: list[TargetPoint], settings: ChainSettings) -> bool:
    """Whether the chain's own answer is one point at a range where the declared laser is
    incoherent (its lines are then the echo's self-beat, ``|E_echo|^2``, which scales with the
    echo power squared): the squared record's lines, ``~sqrt(8)*I_LO/sigma`` stronger than the
    self-beat, may range it better (:func:`better_point`). Several points are left alone (the
    squared lines hold the sum of every target's intensity)."""
    return len(targets) == 1 and carrier_coherence(settings, targets[0].range_m) < MIN_CARRIER_COHERENCE


def better_point(own: TargetPoint, squared: TargetPoint) -> bool:
    """Whether the squared record's point should replace the chain's own (:func:`square_rivals`).

    Both rest on the echo's intensity, Doppler-free, and state sigmas that cover their errors; an
    unflagged point is preferred to a flagged one (``cycle_ambiguous``, ``near_edge``, ``blended``),
    then the smaller range sigma. Near the self-beat's threshold the chain's own lines pick wrong
    cycles (flagged, cm sigmas: the honesty map's 5.3 GHz rows at 12-20 dB) where the squared
    lines give mm -- the smaller sigma is the one the lines' SNR supports, not a lucky draw of it."""
    return (squared.flagged, squared.range_sigma_m) < (own.flagged, own.range_sigma_m)


# -------------------------------------------------------------------------------------------
# accumulation over frames
def _key(frame: Frame, ref: Reference) -> tuple:
    """What must stay the same for frames to be averaged: source, run, tone plan and phases,
    sample rate, length, receiver, architecture."""
    return (frame.source, frame.run, tuple(frame.tones_hz), tuple(round(ref.tone_phases_rad[f], 12)
                                                                  for f in frame.tones_hz),
            round(ref.tau0_s, 18), frame.fs_hz, frame.n, frame.receiver, frame.architecture)


def weighted_mean(items: list[SquaredLines]) -> SquaredLines:
    """Inverse-variance weighted mean of the lines of several frames, per tone; its ``var_z``
    is ``1/sum(1/var_z)`` (the noise of independent frames)."""
    z = np.stack([s.z_start for s in items])
    v = np.stack([s.var_z for s in items])
    w = np.where(np.isfinite(v), 1 / v, 0.0)
    ws = w.sum(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        zm = np.where(ws > 0, (w * z).sum(axis=0) / ws, 0.0)
        vm = np.where(ws > 0, 1 / ws, np.inf)
    return SquaredLines(items[0].tone_hz, zm, vm, sum(s.n for s in items))


def same_phasors_p(a: SquaredLines, b: SquaredLines) -> float:
    """P-value of "``a`` and ``b`` are the same lines" (same static target, same amplitude).

    ``sum_i 2*|a_i - b_i|^2/(var_a_i + var_b_i)`` is chi-square with 2 degrees of freedom per
    line (complex Gaussian noise), at any SNR; lines with an infinite variance are left out.
    """
    v = a.var_z + b.var_z
    ok = np.isfinite(v) & (v > 0)
    if not ok.any():
        return 1.0
    stat = float(np.sum(2 * np.abs(a.z_start[ok] - b.z_start[ok]) ** 2 / v[ok]))
    return float(chi2_dist.sf(stat, 2 * int(ok.sum())))


@dataclass
class _Entry:
    lines: SquaredLines
    seq: int
    t_ns: int


class Accumulator:
    """Averages the squared lines of successive frames of one static target and ranges from them.

    Feed frames in order with :meth:`add`; each call returns the point of the window ending at
    that frame (a :class:`~mtcw_core.results.FrameResult` like the chain's, its target's
    ``accumulated_frames`` saying how many frames it rests on) and never raises.

    Parameters
    ----------
    settings : AccumulateSettings
    chain : ChainSettings
        The chain's settings in force (line threshold, cycle resolution, declared timing
        jitter); ``chain.technique`` must be ``pb``.
    calibration : Calibration, optional
        Tone phases and ``tau0`` (else the frames' tone phases and 0).

    Attributes
    ----------
    reset_reason : str or None
        Why the last :meth:`add` started a new window (None: it extended the window).
    resets : dict
        Count of new windows by reason.
    """

    def __init__(self, settings: AccumulateSettings | None = None, chain: ChainSettings | None = None,
                 calibration: Calibration | None = None) -> None:
        self.settings = settings or AccumulateSettings()
        self.chain = chain or ChainSettings(profile="balanced")
        if self.chain.technique != "pb":
            raise ValueError(f"accumulate: technique {self.chain.technique!r} not supported (pb only)")
        self.calibration = calibration
        self._window: deque[_Entry] = deque(maxlen=self.settings.frames)
        self._key: tuple | None = None
        self.reset_reason: str | None = None
        self.resets: dict[str, int] = {}

    def __len__(self) -> int:
        return len(self._window)

    def reset(self, reason: str = "reset") -> None:
        """Forget every frame (the next one starts a window)."""
        self._window.clear()
        self._key = None
        self._note(reason)

    def _note(self, reason: str) -> None:
        self.reset_reason = reason
        self.resets[reason.split(":")[0]] = self.resets.get(reason.split(":")[0], 0) + 1

    def _reference(self, frame: Frame) -> Reference:
        return Reference.of(frame, self.chain, self.calibration)

    def _admit(self, key: tuple, entry: _Entry) -> None:
        """Start a new window or extend this one, after the change and drift tests."""
        self.reset_reason = None
        if self._key is not None and key != self._key:
            self._window.clear()
            self._note("changed: source, run, tone plan, tone phases or record differ")
        elif self._window and entry.seq <= self._window[-1].seq:
            self._window.clear()
            self._note("changed: seq went back")
        self._key = key
        if self._window:
            p = self.settings.drift_p
            if same_phasors_p(entry.lines, weighted_mean([e.lines for e in self._window])) < p:
                self._window.clear()
                self._note("moved: newest frame differs from the window")
            elif len(self._window) >= 3:
                # the newer half (with the newest frame) against the older half: a slow drift
                # (the frames the window will hold: the oldest leaves a full window)
                items = [e.lines for e in self._window][-(self.settings.frames - 1):] + [entry.lines]
                h = len(items) // 2
                if same_phasors_p(weighted_mean(items[:h]), weighted_mean(items[h:])) < p:
                    self._window.clear()
                    self._note("moved: the window's halves differ")
        self._window.append(entry)

    def add(self, frame: Frame) -> FrameResult:
        """One frame in; the point of the window ending at it (never raises)."""
        st = self.chain
        res = FrameResult(status="rejected", profile=st.profile, technique="pb", seq=frame.seq, t_ns=frame.t_ns,
                          source=frame.source, calibrated=self.calibration is not None)
        t0 = time.perf_counter()
        try:
            if is_gated(frame, st):
                raise Rejected("unsupported", "accumulation of quasi-CW (gated) frames")
            x, res.clip_fraction = validate(frame, st, self.calibration)
            res.stage_seconds["validate"] = time.perf_counter() - t0
            t1 = time.perf_counter()
            ref = self._reference(frame)
            s = self.settings
            lines = square_lines(x, frame.fs_hz, frame.tones_hz, s.edge_samples, s.noise_half_width)
            self._admit(_key(frame, ref), _Entry(lines, int(frame.seq), int(frame.t_ns)))
            mean = weighted_mean([e.lines for e in self._window])
            point, l_unamb = range_from_lines(mean, frame, st, ref)
            res.stage_seconds["accumulate"] = time.perf_counter() - t1
            k = len(self._window)
            res.targets = [replace(point, accumulated_frames=k)]
            res.unambiguous_range_m = l_unamb
            res.doppler_hz = 0.0
            res.status = "ok"
        except NoTarget as why:
            res.status, res.reason = "no_target", f"{why} ({len(self._window)} frames)"
        except Rejected as rej:
            res.status, res.reason = "rejected", str(rej)
        except Exception as err:  # like the chain: nothing escapes
            res.status, res.reason = "rejected", f"internal_error: {type(err).__name__}: {err}"
        res.stage_seconds.setdefault("accumulate", time.perf_counter() - t0 - res.stage_seconds.get("validate", 0.0))
        return res

    def window_seqs(self) -> list[int]:
        """The seqs of the frames the next point's window holds (oldest first)."""
        return [e.seq for e in self._window]


def mean_truth(truths: list[tuple[TruthTarget, ...]]) -> tuple[TruthTarget, ...]:
    """The truth an accumulated point answers: each target's range and speed averaged over the
    frames it rests on (for a target moving linearly, its position at the window's centre).

    Parameters
    ----------
    truths : one tuple of TruthTarget per frame (oldest first); frames with a different number of
        targets than the newest are left out

    Returns
    -------
    tuple of TruthTarget (empty when ``truths`` is)
    """
    if not truths:
        return ()
    same = [t for t in truths if len(t) == len(truths[-1])]
    return tuple(TruthTarget(float(np.mean([t[i].range_m for t in same])),
                             float(np.mean([t[i].velocity_mps for t in same]))) for i in range(len(truths[-1])))


__all__ = ["AccumulateSettings", "mean_truth", "Accumulator", "MAX_FRAMES", "SquaredLines", "square_lines", "product_lines",
           "family_of", "range_from_lines", "weighted_mean", "same_phasors_p"]
