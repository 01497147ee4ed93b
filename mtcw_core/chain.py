"""The PB-MTCW chain: stages, profiles and the runner that times them.

One frame in, one :class:`FrameResult` out; nothing escapes as an exception. Stages:
``validate`` -> ``spectrum`` -> ``doppler`` -> ``extract`` -> ``mix`` -> ``resolve``. Each is a
plain function of arrays and typed settings; the runner (:func:`process_frame`) times them.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace
from typing import TYPE_CHECKING, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import signal as sps
from scipy.optimize import minimize_scalar
from scipy.stats import chi2 as chi2_dist

from .dsp.gating import GateEstimate, coarse_gate
from .dsp.mixing import LineFamily, consistency, pair_observations
from .dsp.spectrum import DopplerEstimate, Spectrum, power_spectrum, search_doppler
from .dsp.tones import exact_dft, fit_lines, fit_lines_segments
from .frame import Frame
from .ranging.triangulation import C, fisher_sigma, resolve_ml, resolve_seed, unambiguous_range

if TYPE_CHECKING:
    from .calibration import Calibration


class Rejected(Exception):
    """A frame that cannot be processed; ``reason`` is a short machine-readable key."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason
        self.detail = detail


class ChainSettings(BaseModel):
    """Choices of every stage. A profile is a named ChainSettings."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    profile: str = "custom"
    # stage 1
    max_clip_fraction: float = Field(1e-3, ge=0, le=1)
    expected_tones_hz: tuple[float, ...] | None = None
    expected_samples: int | None = None
    # stage 2: quasi-CW coarse gating (pulsed frames only)
    gate: Literal["auto", "off"] = "auto"
    gate_k_sigma: float = Field(3.0, gt=0, description="the period is certain when k coarse sigmas stay within "
                                                       "half the unambiguous range")
    gate_segment_s: float = Field(100e-9, gt=0, description="segment length for IF mixing in the echo windows; "
                                                          "short enough for the laser to stay coherent")
    gate_min_snr: float = Field(8.0, gt=0)
    # stage 3: spectrum and Doppler
    doppler_fraction: float = Field(0.25, gt=0, le=1, description="part of the record used for the Doppler FFT")
    window_beta: float = Field(14.0, ge=0)
    spectrum_single: bool = Field(False, description="Doppler-search spectrum in single precision (~2x faster; "
                                                     "line phases are fitted in float64 regardless)")
    doppler_min_bins: int = Field(4, ge=1)
    doppler_threshold: float = Field(8.0, gt=0)
    fd_max_hz: float | None = Field(None, gt=0, description="default: half the smallest tone spacing")
    doppler_phase_lines: int | None = Field(None, ge=1, description="phase refinement: the strongest lines only")
    doppler_refine: Literal["parabolic", "phase", "exact"] = Field(
        "parabolic", description="below one Doppler-spectrum bin: parabola through the search scores, then "
                                 "(phase) the phase advance of the lines across record quarters, or (exact) "
                                 "maximising the exact line power")
    max_targets: int = Field(3, ge=1, le=8, description="Doppler lines (moving targets) looked for")
    self_beat_margin_db: float = Field(15.0, ge=0, description="a static candidate this far below the movers' "
                                                               "lines is taken for their self-beat")
    incoherent_residual_rad: float = Field(0.25, gt=0, description="a moving candidate whose line phases miss one "
                                                                   "range by this much (rms) at > 25 dB is noise")
    blended_chi2: float = Field(10.0, gt=1, description="chi2/dof of the line phases above which one point "
                                                        "cannot explain them: flagged blended")
    # stage 4: tone extraction
    extraction: Literal["ls", "filter"] = "ls"
    model_products: bool = False
    segments: int = Field(1, ge=1)
    min_line_snr_db: float = Field(10.0, description="post-integration SNR for a line to be used")
    # stage 6: cycle resolution
    method: Literal["ml", "seed"] = "ml"
    points_per_cycle: int = Field(16, ge=4)
    range_min_m: float = -0.05
    range_max_m: float | None = None
    # the seed's extraction path
    seed_points: int = Field(2**23, ge=2**10)
    seed_bandwidth_hz: float = Field(1e6, gt=0)


PROFILES: dict[str, ChainSettings] = {
    # Doppler from 1/8 of the record, plain LS at known lines, coarse ML grid.
    "fast": ChainSettings(profile="fast", doppler_fraction=1 / 8, points_per_cycle=8, spectrum_single=True,
                          doppler_refine="phase", doppler_phase_lines=3),
    # Doppler from the whole record, joint LS of all used lines, ML on a 16-point grid.
    "balanced": ChainSettings(profile="balanced", doppler_fraction=1.0, spectrum_single=True, doppler_refine="phase"),
    # Full-record spectrum, exact Doppler refinement, MZM products modelled in the LS fit.
    "accurate": ChainSettings(profile="accurate", doppler_fraction=1.0, doppler_refine="exact",
                              model_products=True, points_per_cycle=32),
    # The dissertation: resample to 2^23, 1 MHz 2nd-order Butterworth filtfilt per line,
    # correlation with zero-phase cosines, candidate-matrix triangulation.
    "seed": ChainSettings(profile="seed", doppler_fraction=1.0, extraction="filter", method="seed"),
}


def get_profile(name: str, **overrides) -> ChainSettings:
    if name not in PROFILES:
        raise ValueError(f"profile: unknown {name!r} (one of {', '.join(PROFILES)})")
    base = PROFILES[name]
    return base.model_copy(update=overrides) if overrides else base


@dataclass
class TargetPoint:
    range_m: float
    range_sigma_m: float
    velocity_mps: float
    velocity_sigma_mps: float
    direction: str  # receding | approaching | unknown | static
    snr_db: float
    margin: float
    residual_rms_rad: float = 0.0
    near_edge: bool = False
    cycle_ambiguous: bool = False  # the coarse range could not pick one cycle: range is one of several
    blended: bool = False  # the line phases are not those of one target (e.g. two static targets)
    doppler_hz: float = 0.0  # the target's Doppler line (signed for IQ; 0 for the static target)
    chi2_per_dof: float = 1.0  # line-phase consistency; the sigma is scaled by its root when significant
    tone_snr_db: dict[str, float] = field(default_factory=dict)
    seed_sigma_k_m: float | None = None


@dataclass
class FrameResult:
    status: str  # ok | no_target | rejected
    profile: str
    seq: int = 0
    t_ns: int = 0
    source: str = ""
    reason: str | None = None
    targets: list[TargetPoint] = field(default_factory=list)
    unambiguous_range_m: float | None = None
    coarse_range_m: float | None = None
    coarse_sigma_m: float | None = None
    doppler_hz: float | None = None
    calibrated: bool = False
    clip_fraction: float = 0.0
    stage_seconds: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)


# ---------------------------------------------------------------------------------------------
# stage 1
def _rail_fraction(r: np.ndarray, rail) -> float:
    """Fraction of samples in runs of >= 3 consecutive samples stuck at ``rail``.

    A signal (even a periodic or coarsely quantised one) touches its extremes in isolated
    samples at GHz tones; a clipped one dwells on the rail.
    """
    at = r == rail
    if np.count_nonzero(at) < 3:
        return 0.0
    run = at[:-2] & at[1:-1] & at[2:]
    stuck = np.zeros(r.size, bool)
    stuck[:-2] |= run
    stuck[1:-1] |= run
    stuck[2:] |= run
    return float(np.count_nonzero(stuck)) / r.size


def validate(frame: Frame, settings: ChainSettings, calibration: Calibration | None) -> tuple[np.ndarray, float]:
    """Codes -> volts, and the checks. Returns (signal, clip_fraction) or raises Rejected."""
    if not (frame.fs_hz > 0 and math.isfinite(frame.fs_hz)):
        raise Rejected("bad_fs", f"fs_hz={frame.fs_hz!r}")
    if frame.samples.ndim != 2 or frame.samples.shape[0] != len(frame.channels):
        raise Rejected("bad_shape", f"samples shape {frame.samples.shape} vs channels {list(frame.channels)}")
    if frame.n < 256:
        raise Rejected("too_short", f"{frame.n} samples (need >= 256)")
    if settings.expected_samples is not None and frame.n != settings.expected_samples:
        raise Rejected("length_mismatch", f"{frame.n} samples, expected {settings.expected_samples}")
    tones = frame.tones_hz
    if len(tones) < 2:
        raise Rejected("tone_plan", "at least two tones are needed for pair phases")
    if any(not (0 < f < frame.fs_hz / 2) for f in tones):
        raise Rejected("tone_plan", f"tones {list(tones)} must lie in (0, fs/2)")
    if settings.expected_tones_hz is not None and tuple(tones) != tuple(settings.expected_tones_hz):
        raise Rejected("tone_plan", f"frame tones {list(tones)} != configured {list(settings.expected_tones_hz)}")
    if calibration is not None and tuple(calibration.tones_hz) != tuple(tones):
        raise Rejected("calibration_mismatch", f"calibration tones {list(calibration.tones_hz)} != frame {list(tones)}")
    if frame.receiver == "iq" and not {"i", "q"} <= set(frame.channels):
        raise Rejected("bad_channels", "iq receiver needs channels 'i' and 'q'")
    if frame.receiver != "iq" and "pd" not in frame.channels:
        raise Rejected("bad_channels", "channel 'pd' missing")
    raw = [frame.samples[frame.channels.index(c)] for c in (("i", "q") if frame.receiver == "iq" else ("pd",))]
    for r in raw:
        if r.dtype.kind == "f" and not np.all(np.isfinite(r)):
            raise Rejected("non_finite", f"{int(np.sum(~np.isfinite(r)))} NaN/inf samples")
    clip = 0.0
    for r in raw:
        hi, lo = r.max(), r.min()
        if hi == lo:
            raise Rejected("flat", "all samples equal (no signal)")
        clip = max(clip, _rail_fraction(r, hi), _rail_fraction(r, lo))
    if clip > settings.max_clip_fraction:
        raise Rejected("clipped", f"{clip:.2%} of samples at the rails (max {settings.max_clip_fraction:.2%})")
    return frame.signal(), clip


# ---------------------------------------------------------------------------------------------
# stages 3-4
def _fd_max(tones: tuple[float, ...], settings: ChainSettings) -> float:
    if settings.fd_max_hz is not None:
        return settings.fd_max_hz
    t = sorted(tones)
    return 0.5 * min(b - a for a, b in zip(t, t[1:]))


def doppler_stage(x: np.ndarray, frame: Frame, spec: Spectrum, settings: ChainSettings,
                  gated: bool = False) -> list[DopplerEstimate]:
    """Doppler lines, strongest first (``[not detected]`` when there is none).

    ``gated``: a quasi-CW record (echo in windows, laser incoherent at km delays): the phase
    refinement, which follows the lines' phases across the record, falls back to the parabola.
    """
    ests = search_doppler(spec, list(frame.tones_hz), _fd_max(frame.tones_hz, settings),
                          settings.doppler_min_bins, settings.doppler_threshold, max_targets=settings.max_targets)
    if settings.doppler_refine == "parabolic" or not ests[0].detected or (gated and settings.doppler_refine == "phase"):
        return ests
    iq = np.iscomplexobj(x)
    if settings.doppler_refine == "phase":
        return [_refine_by_phase(x, frame, est, iq, [e.fd_hz for e in ests], spec, settings.doppler_phase_lines)
                for est in ests]
    out = []
    for est in ests:
        def neg_power(fd: float) -> float:
            fr = _line_freqs(frame.tones_hz, fd, iq)
            return -float(np.sum(np.abs(exact_dft(x, fr, frame.fs_hz)) ** 2))

        half = spec.df_hz
        r = minimize_scalar(neg_power, bounds=(est.fd_hz - half, est.fd_hz + half), method="bounded",
                            options={"xatol": 1e-4 * frame.fs_hz / frame.n})
        # the power maximum is biased by what the line model leaves out (a folded line's image,
        # neighbours' skirts): 0.01 record bin, as seen on the folding test
        out.append(DopplerEstimate(float(r.x), True, est.score, est.threshold, est.min_detectable_hz,
                                   0.01 * frame.fs_hz / x.size, est.wander_hz))
    return out


def _refine_by_phase(x: np.ndarray, frame: Frame, est: DopplerEstimate, iq: bool, others: list[float],
                     spec: Spectrum, max_lines: int | None = None, segments: int = 4) -> DopplerEstimate:
    """The Doppler line's frequency from the phase advance of its lines across ``segments`` parts.

    Each line of the target (baseband, U, L) is measured on every part (exact DFT, centred
    phase); its phase advances by ``2*pi*f_line*L/fs`` per part of ``L`` samples, so the excess
    advance gives its frequency error -- without ambiguity within +-``fs/(2L)`` (two record bins
    for quarters; a parabola through a coarse spectrum is well inside). ``f_line`` moves with
    ``+-f_d``; the lines' estimates are combined with amplitude weights. Lines within three part
    bins of another line (a static line, another target's) are left out: they would leak in.
    ``max_lines``: only the strongest lines in ``spec`` (each costs about an eighth of a pass).
    One pass over the record, for the ~0.1-bin error a parabola leaves (0.8 record bins when the
    spectrum came from 1/8 of the record).
    """
    fs = frame.fs_hz
    fd = est.fd_hz
    length = x.size // segments
    if length < 64:
        return est
    freqs, slope = _target_lines(frame.tones_hz, fd, iq)
    # every other line there may be: the static target's (and 0 Hz), the other targets'
    near = np.concatenate([_target_lines(frame.tones_hz, o, iq)[0] for o in [0.0, *others] if o != fd])
    sep = 3 * fs / length
    use = np.array([np.all(np.abs(near - f) > sep) and np.sum(np.abs(freqs - f) < sep) == 1 for f in freqs])
    if not use.any():
        return est
    freqs, slope = freqs[use], slope[use]
    if max_lines is not None and freqs.size > max_lines:
        top = np.argsort(spec.power[np.clip(spec.bin_of(freqs), 0, spec.power.size - 1)])[::-1][:max_lines]
        freqs, slope = freqs[top], slope[top]
    z = np.array([exact_dft(x[k * length:(k + 1) * length], freqs, fs) for k in range(segments)])  # (S, K)
    advance = np.mod(freqs * length / fs, 1.0)  # expected cycles per part (float64, reduced)
    prod = z[1:] * np.conj(z[:-1]) * np.exp(-2j * np.pi * advance)
    if not np.any(np.abs(prod) > 0):
        return est
    d_line = np.angle(prod.sum(axis=0)) / (2 * np.pi * length / fs)  # Hz, per line
    # white-noise error per line: phase variance s2*L/(2|Z|^2) per part; the estimate is about
    # (phi_last - phi_first)/(S - 1), so twice that over (S - 1)^2
    exclude = list(freqs) + list(near)
    s2 = np.array([spec.noise_variance(f, exclude) for f in freqs])
    amp2 = np.mean(np.abs(z) ** 2, axis=0)
    var_phi = s2 * length / (2 * np.maximum(amp2, 1e-300))
    var_line = 2 * var_phi / (segments - 1) ** 2 / (2 * np.pi * length / fs) ** 2
    # combined with power weights (the local floors that inverse-variance weights would trust are
    # rough next to the strongest lines), and that combination's white-noise error
    w = np.abs(prod).sum(axis=0)
    delta = float(np.sum(w * slope * d_line) / np.sum(w))
    stat = float(np.sqrt(np.sum(w**2 * var_line)) / np.sum(w))
    # the lines' scatter about their mean says what white noise does not (leakage, skirts)
    chi2 = float(np.sum((slope * d_line - delta) ** 2 / var_line))
    spread = stat * math.sqrt(max(chi2 / max(len(w) - 1, 1), 1.0))
    return replace(est, fd_hz=fd + delta, refine_error_hz=spread)


def _target_lines(tones, fd: float, iq: bool) -> tuple[np.ndarray, np.ndarray]:
    """Every line of a target at Doppler ``fd`` -- baseband, then U and L -- (Hz), and how each
    moves with ``fd`` (+-1: a real detector's L line ``|f_i - fd|`` moves down until it folds
    through 0 Hz; baseband ``|fd|`` moves down for a negative ``fd``)."""
    freqs, slope = [fd if iq else abs(fd)], [1.0 if (iq or fd >= 0) else -1.0]
    for name, f, conj in _doppler_families(tones, fd, iq):
        freqs.extend(f)
        slope.extend(np.where(conj, 1.0, -1.0) if (name == "L" and not iq) else np.ones(len(f)))
    return np.asarray(freqs, float), np.asarray(slope)


def _doppler_families(tones, fd: float, iq: bool) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """The U and L lines of a target at Doppler ``fd``: (name, frequencies, conjugate mask).

    IQ: ``fd +- f_i`` (signed; L is the mirror image, conjugated). Real detector: ``f_i + fd``
    and ``|f_i - fd|`` (conjugated where it folds through 0 Hz).
    """
    t = np.asarray(tones, float)
    if iq:
        return [("U", fd + t, np.zeros(t.size, bool)), ("L", fd - t, np.ones(t.size, bool))]
    lo = t - fd
    return [("U", t + fd, np.zeros(t.size, bool)), ("L", np.abs(lo), lo < 0)]


def _line_freqs(tones, fd: float, iq: bool) -> np.ndarray:
    return np.concatenate([f for _, f, _ in _doppler_families(tones, fd, iq)])


def _plan_lines(frame: Frame, fds: list[float], iq: bool, settings: ChainSettings, fit_samples: int | None = None):
    """Line families per target candidate, and every frequency to fit.

    Candidate 0 is static (Doppler 0: the S lines of a real detector, the +-f_i lines of an IQ
    one); candidate k >= 1 is the k-th Doppler line (U and L families). Lines that fall within
    2 record-bins of lines already planned (or of each other) cannot be separated: they are
    marked unusable and not fitted. ``fit_samples``: the length of the records the lines are
    fitted on (a segment's, when extraction is segmented), which sets the resolution.
    """
    t = np.asarray(frame.tones_hz, float)
    res = 2 * frame.fs_hz / (fit_samples or frame.n)
    none = np.zeros(t.size, bool)
    # (target, name, line freqs, conj mask, unusable mask)
    fams: list[tuple[int, str, np.ndarray, np.ndarray, np.ndarray]] = []
    if iq:  # a static target is the Doppler-0 case of the U/L layout
        fams += [(0, name, f, conj, none) for name, f, conj in _doppler_families(t, 0.0, True)]
    else:
        fams.append((0, "S", t.copy(), none, none))
    used = np.concatenate([f for _, _, f, _, _ in fams])
    extra: list[float] = []
    for k, fd in enumerate(fds, start=1):
        cand = [(k, name, f, conj) for name, f, conj in _doppler_families(t, fd, iq)]
        new = np.concatenate([f for _, _, f, _ in cand])
        # a line within 2 bins of another (e.g. f_i + f_d = f_j - f_d at half the tone spacing,
        # or another target's line) cannot be told apart: it is left out of this target
        clash = np.abs(new[:, None] - used[None, :]).min(axis=1) <= res
        d = np.where(np.eye(new.size, dtype=bool), np.inf, np.abs(new[:, None] - new[None, :]))
        clash |= d.min(axis=1) <= res
        for j, (kk, name, f, conj) in enumerate(cand):
            bad = clash[j * t.size:(j + 1) * t.size]
            fams.append((kk, name, f, conj, bad))
            used = np.concatenate([used, f[~bad]])
        extra.append(fd if iq else abs(fd))
    if iq:
        extra.append(0.0)  # the complex fit has no DC column: the LO's DC is a line at 0 Hz
    if settings.model_products and not iq:
        prods = [2 * a for a in t] + [a + b for i, a in enumerate(t) for b in t[i + 1:]] + \
                [abs(a - b) for i, a in enumerate(t) for b in t[i + 1:]]
        extra += [p for p in prods if p < frame.fs_hz / 2]
    # a product line too close to a used line cannot be told apart: keep the used ones
    keep = []
    for f in extra:
        if np.all(np.abs(used - f) > 1.5 * res) and all(abs(f - k) > 1.5 * res for k in keep) and (
                abs(f) > 1.5 * res or (iq and f == 0.0)):
            keep.append(f)
    return fams, np.concatenate([used, np.asarray(keep, float)])


def _segments(n: int, fs: float, settings: ChainSettings, windows: list[tuple[int, int]] | None,
              fds: list[float] = ()) -> tuple[np.ndarray, int]:
    """Segment starts and common length: the whole record in ``settings.segments`` parts, or
    each echo window cut into pieces of ``gate_segment_s`` -- longer when a Doppler line ``fds``
    (Hz) is found, so that a mover's lines ``f_i +- f_d`` lie 3 segment-bins from ``f_i`` and
    are told apart from a static target's (the IF products cancel the laser's phase noise
    whatever the length; a longer segment only spreads an incoherent line over more bins)."""
    if not windows:
        length = n // settings.segments
        return np.arange(settings.segments) * length, length
    span = sum(b - a for a, b in windows)
    longest = max(b - a for a, b in windows)
    want = max(64, round(settings.gate_segment_s * fs))
    moving = [abs(f) for f in fds if f != 0.0]
    if moving:
        want = max(want, int(math.ceil(3 * fs / min(moving))))
    length = int(min(want, longest, span))
    starts = [a + k * length for a, b in windows for k in range((b - a) // length)]
    if not starts:
        raise Rejected("gate", f"echo windows ({span} samples) shorter than one segment")
    return np.asarray(starts, dtype=np.int64), length


def extract_stage(x: np.ndarray, frame: Frame, dops: list[DopplerEstimate], spec: Spectrum,
                  settings: ChainSettings, windows: list[tuple[int, int]] | None = None) -> list[LineFamily]:
    """Complex amplitude of every used line, per segment, with its phase variance.

    ``windows`` (sample ranges where a quasi-CW echo is on) restricts extraction to them.
    """
    iq = np.iscomplexobj(x)
    n = x.size
    fs = frame.fs_hz
    segmented = settings.extraction != "filter" and (windows or settings.segments > 1)
    if segmented:
        starts, length = _segments(n, fs, settings, windows, [d.fd_hz for d in dops if d.detected])
    fams, all_f = _plan_lines(frame, [d.fd_hz for d in dops if d.detected], iq, settings,
                              length if segmented else None)
    uniq = np.unique(np.round(all_f, 6))
    if settings.extraction == "filter":
        if windows:
            raise Rejected("unsupported", "the seed's filter extraction has no quasi-CW gating")
        z_all, centre = _seed_extract(x, fs, uniq, settings)
        z_all, centres = z_all[None, :], np.array([centre])
    elif not windows and settings.segments == 1:
        z_all, centres = fit_lines(x, uniq, fs)[None, :], np.array([(n - 1) / (2 * fs)])
    else:
        z_all = fit_lines_segments(x, starts, length, uniq, fs)
        centres = (starts + (length - 1) / 2) / fs
        n = int(starts.size * length)  # samples the amplitudes rest on
    kappa = 0.5 if iq else 2.0
    out = []
    for target, name, freqs, conj, bad in fams:
        idx = np.clip(np.searchsorted(uniq, np.round(freqs, 6)), 0, uniq.size - 1)
        z = z_all[:, idx].copy()
        z[:, conj] = np.conj(z[:, conj])
        z[:, bad] = 0.0
        amp2 = np.mean(np.abs(z) ** 2, axis=0)
        s2 = np.array([spec.noise_variance(f, list(uniq)) for f in freqs])
        var = kappa * s2 / (n * np.maximum(amp2, 1e-300))
        var[bad] = np.inf
        out.append(LineFamily(name, np.asarray(frame.tones_hz, float), freqs, z, centres, var, target))
    return out


def _seed_extract(x: np.ndarray, fs: float, freqs: np.ndarray, settings: ChainSettings) -> tuple[np.ndarray, float]:
    """The dissertation's path: resample, 1 MHz band-pass filtfilt, correlate with cosines."""
    if np.iscomplexobj(x):
        raise Rejected("unsupported", "the seed profile handles single/balanced receivers only")
    npts = settings.seed_points
    y = sps.resample(x - x.mean(), npts)
    fs2 = fs * npts / x.size
    out = np.empty(freqs.size, complex)
    bw = settings.seed_bandwidth_hz
    for i, f in enumerate(freqs):
        lo, hi = max(f - bw / 2, 1.0), min(f + bw / 2, fs2 / 2 * 0.999)
        sos = sps.butter(2, [lo, hi], btype="bandpass", fs=fs2, output="sos")
        # forward-backward (zero-phase) filtering; sosfiltfilt's initial-state solve is singular
        # for a 1 MHz band at hundreds of GSa/s, so start both passes from rest instead
        yf = sps.sosfilt(sos, sps.sosfilt(sos, y)[::-1])[::-1]
        out[i] = exact_dft(yf, [f], fs2)[0] * 2 / npts
    # amplitudes refer to the centre of the resampled grid, (npts-1)/(2*fs2) after the start
    return out, (npts - 1) / (2 * fs2)


def gate_stage(x: np.ndarray, frame: Frame, settings: ChainSettings) -> GateEstimate | None:
    """Stage 2: coarse gating of a pulsed frame (None for CW frames or with gating off)."""
    if frame.pulse is None or settings.gate == "off":
        return None
    p = frame.pulse
    ref = frame.volts("pulse_ref") if "pulse_ref" in frame.channels else None
    return coarse_gate(x, frame.fs_hz, p.period_s, p.duty, p.delay_s, frame.tones_hz, ref,
                       min_snr=settings.gate_min_snr)


def measure_lines(x: np.ndarray, frame: Frame, settings: ChainSettings, lap=None,
                  windows: list[tuple[int, int]] | None = None) -> tuple[list[DopplerEstimate], list[LineFamily]]:
    """Stages 3-4: spectrum, Doppler search and line extraction of a validated signal.

    ``lap(stage_name)``, when given, is called after each stage (the runner's timer);
    ``windows`` restricts extraction to a quasi-CW echo.
    """
    tick = lap or (lambda _name: None)
    # a gated record's spectrum is the echo-on part alone: the gate's own harmonics around every
    # line (multiples of 1/period) would otherwise pass for Doppler pairs
    xs = x
    if windows:
        a, b = max(windows, key=lambda w: w[1] - w[0])
        xs = x[a:b]
    nspec = max(256, int(xs.size * settings.doppler_fraction))
    spec = power_spectrum(xs, frame.fs_hz, ("kaiser", settings.window_beta), nspec, settings.spectrum_single)
    tick("spectrum")
    dops = doppler_stage(x, frame, spec, settings, gated=bool(windows))
    tick("doppler")
    fams = extract_stage(x, frame, dops, spec, settings, windows)
    tick("extract")
    return dops, fams


# ---------------------------------------------------------------------------------------------
def _velocity(dop: DopplerEstimate, frame: Frame, families: list[LineFamily], iq: bool) -> tuple[float, float, str]:
    lam = frame.wavelength_m
    n, fs = frame.n, frame.fs_hz
    if not dop.detected:
        return 0.0, dop.min_detectable_hz * lam / 2, "static"
    inv_var = 0.0
    for fam in families:
        if fam.name == "S":
            continue
        # CRB of a sinusoid's frequency: var_f = 3*s2*fs^2/(pi^2*A^2*N^3) (real), 1.5 (complex)
        # expressed with the phase variance 2*s2/(N*A^2) (real) or s2/(2*N*A^2) (complex)
        c = 1.5 if not iq else 3.0
        var_f = c * fam.phase_var * fs**2 / (np.pi**2 * n**2)
        inv_var += float(np.sum(1 / var_f))
    sig_f = 1 / math.sqrt(inv_var) if inv_var > 0 else math.inf
    sig_f = max(math.hypot(sig_f, dop.refine_error_hz, dop.wander_hz), 1e-3 * fs / n)
    if iq:
        v = -dop.fd_hz * lam / 2
        return v, sig_f * lam / 2, "receding" if v > 0 else "approaching"
    return abs(dop.fd_hz) * lam / 2, sig_f * lam / 2, "unknown"


def match_truth(res: FrameResult, truth) -> tuple[TargetPoint, float] | None:
    """The point that answers a simulator truth target, and its range error (m).

    The point nearest in speed (several targets are told apart by Doppler); the error is wrapped
    into +-half the unambiguous range for CW frames (a range is only known modulo it), plain for
    gated frames (the coarse range removed the ambiguity).
    """
    if not res.targets:
        return None
    p = min(res.targets, key=lambda q: abs(abs(q.velocity_mps) - abs(truth.velocity_mps)))
    e = p.range_m - truth.range_m
    if res.coarse_range_m is None and res.unambiguous_range_m:
        lu = res.unambiguous_range_m
        e = (e + lu / 2) % lu - lu / 2
    return p, e


def _median_snr(p: TargetPoint) -> float:
    return float(np.median(list(p.tone_snr_db.values())))


def _solve_target(fams: list[LineFamily], dop: DopplerEstimate, frame: Frame, settings: ChainSettings,
                  phases: dict[float, float], tau0: float, interval: tuple[float, float] | None, iq: bool,
                  res: FrameResult) -> TargetPoint | None:
    """Stages 5-6 for one target candidate: IF mixing, cycle resolution, sigma, quality."""
    obs = pair_observations(fams, phases, settings.min_line_snr_db)
    if obs.df_hz.size == 0:
        return None
    l_unamb = unambiguous_range(obs.df_hz)
    res.unambiguous_range_m = l_unamb if res.unambiguous_range_m is None else max(res.unambiguous_range_m, l_unamb)
    lo = settings.range_min_m
    hi = settings.range_max_m if settings.range_max_m is not None else lo + l_unamb
    ambiguous = False
    if interval is not None:
        # the phases fix the range modulo l_unamb; the coarse range picks the period: search
        # the one centred on it, and say so when the coarse sigma leaves the period in doubt
        centre, half = 0.5 * (interval[0] + interval[1]), 0.5 * (interval[1] - interval[0])
        ambiguous = half >= 0.5 * l_unamb
        lo, hi = centre - 0.5 * l_unamb, centre + 0.5 * l_unamb
    if settings.method == "seed":
        sol = resolve_seed(obs, tau0, hi, lo)
    else:
        sol = resolve_ml(obs, tau0, (lo, hi), settings.points_per_cycle)
    ok = [f.snr_db >= settings.min_line_snr_db for f in fams]
    used = [(f, m) for f, m in zip(fams, ok) if np.sum(m) >= 2]
    sigma = fisher_sigma([f.tone_hz[m] for f, m in used], [f.phase_var[m] for f, m in used])
    # do the line phases agree with one range within their noise? (Birge ratio)
    chi2, dof = consistency(fams, phases, tau0 + 2 * sol.range_m / C, settings.min_line_snr_db)
    ratio = chi2 / dof if dof > 0 else 1.0
    if dof > 0 and chi2_dist.sf(chi2, dof) < 1e-3:
        sigma *= math.sqrt(ratio)
    v, vs, direction = _velocity(dop, frame, fams, iq)
    tone_snr: dict[str, float] = {}
    for f in fams:
        for tone, snr in zip(f.tone_hz, f.snr_db):
            key = f"{tone:.0f}"
            tone_snr[key] = max(tone_snr.get(key, -np.inf), float(snr))
    return TargetPoint(
        range_m=sol.range_m, range_sigma_m=sigma, velocity_mps=v, velocity_sigma_mps=vs, direction=direction,
        snr_db=max(float(np.max(f.snr_db)) for f in fams), margin=sol.margin,
        residual_rms_rad=sol.residual_rms_rad, near_edge=sol.near_edge, cycle_ambiguous=ambiguous,
        blended=bool(dof > 0 and ratio > settings.blended_chi2), chi2_per_dof=float(ratio), doppler_hz=dop.fd_hz,
        tone_snr_db=tone_snr, seed_sigma_k_m=sol.seed_sigma_k_m,
    )


def process_frame(frame: Frame, settings: ChainSettings | str = "balanced",
                  calibration: Calibration | None = None) -> FrameResult:
    """Run the chain on one frame. Never raises: a bad frame comes back ``rejected`` with a reason."""
    if isinstance(settings, str):
        settings = get_profile(settings)
    res = FrameResult(status="rejected", profile=settings.profile, seq=frame.seq, t_ns=frame.t_ns,
                      source=frame.source, calibrated=calibration is not None)
    st = res.stage_seconds
    t = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal t
        now = time.perf_counter()
        st[name] = now - t
        t = now

    try:
        x, res.clip_fraction = validate(frame, settings, calibration)
        lap("validate")
        iq = np.iscomplexobj(x)
        if calibration is not None:
            phases, tau0 = dict(zip(calibration.tones_hz, calibration.tone_phases_rad)), calibration.tau0_s
        else:
            tp = frame.tone_phases_rad or (0.0,) * len(frame.tones_hz)
            phases, tau0 = dict(zip(frame.tones_hz, tp)), 0.0
        gate = gate_stage(x, frame, settings)
        if gate is not None:
            lap("gate")
            res.coarse_range_m = C * (gate.tau_s - tau0) / 2
            res.coarse_sigma_m = C * gate.sigma_s / 2
            if not gate.detected:
                res.status, res.reason = "no_target", f"no echo pulse (gate snr {gate.snr:.1f} < {settings.gate_min_snr})"
                return res
        dops, fams = measure_lines(x, frame, settings, lap, gate.windows if gate is not None else None)
        res.doppler_hz = dops[0].fd_hz
        lap("mix")
        interval = None
        if gate is not None:
            half = settings.gate_k_sigma * res.coarse_sigma_m
            interval = (res.coarse_range_m - half, res.coarse_range_m + half)
        static_dop = DopplerEstimate(0.0, False, 0.0, dops[0].threshold, dops[0].min_detectable_hz)
        moving = [d for d in dops if d.detected]
        points: list[tuple[int, TargetPoint]] = []
        for k in range(len(moving) + 1):
            fam_k = [f for f in fams if f.target == k]
            if not fam_k:
                continue  # a Doppler line whose lines could not be separated from others
            p = _solve_target(fam_k, moving[k - 1] if k else static_dop, frame, settings, phases, tau0, interval,
                              iq, res)
            if p is not None:
                points.append((k, p))
        # a "moving target" whose line phases are random at high SNR is the wings of the static
        # lines (a laser incoherent at the echo's delay), not a target: when a static target
        # is there, drop it
        if any(k == 0 for k, _ in points):
            points = [(k, p) for k, p in points if k == 0 or not (
                p.residual_rms_rad > settings.incoherent_residual_rad and _median_snr(p) > 25.0)]
        # the static candidate of a frame with moving targets is often their own self-beat
        # (|E_echo|^2 has no Doppler): at a mover's range, or far weaker than the movers' LO
        # beats (a self-beat is sqrt(P_echo/P_lo) below them), it is not a second target
        # -- and a weak "mover" at the static target's range is that target's own phase-noise
        # sidebands (they carry its tone phases): of two candidates at one range, the stronger
        # is the target
        def same_range(a: TargetPoint, b: TargetPoint) -> bool:
            return abs(a.range_m - b.range_m) < max(5 * math.hypot(a.range_sigma_m, b.range_sigma_m), 1e-3)

        static = next((p for k, p in points if k == 0), None)
        movers = [p for k, p in points if k > 0]
        if static is not None and movers:
            loudest = max(_median_snr(m) for m in movers)
            twins = [m for m in movers if same_range(static, m)]
            if _median_snr(static) < loudest - settings.self_beat_margin_db or any(
                    _median_snr(m) >= _median_snr(static) for m in twins):
                points = [(k, p) for k, p in points if k > 0]
            else:
                points = [(k, p) for k, p in points if not any(p is m for m in twins)]
        lap("resolve")
        if not points:
            res.status, res.reason = "no_target", f"fewer than two lines above {settings.min_line_snr_db} dB"
            return res
        # strongest first, by the median SNR of the target's lines (one strong line -- a baseband
        # beat sitting on a family's slot -- does not make a target strong)
        res.targets = [p for _, p in sorted(points, key=lambda kp: -_median_snr(kp[1]))]
        res.doppler_hz = res.targets[0].doppler_hz
        res.status = "ok"
        lap("report")
    except Rejected as rej:
        res.status, res.reason = "rejected", str(rej)
    except Exception as err:  # the chain never lets an exception escape
        res.status, res.reason = "rejected", f"internal_error: {type(err).__name__}: {err}"
    return res


__all__ = ["ChainSettings", "PROFILES", "get_profile", "process_frame", "match_truth", "FrameResult", "TargetPoint",
           "Rejected", "validate", "gate_stage", "doppler_stage", "extract_stage", "measure_lines", "C"]
