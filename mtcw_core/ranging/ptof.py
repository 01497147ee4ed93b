"""PToF: pulsed time-of-flight ranging by pulse cross-correlation (the dissertation's Secs. 3.4 and 5.5), and its stage table.

The dissertation checks AB-MTCW against a mode-locked laser (25 MHz, sampled every 50 ps): the
time between the reference mirror's pulse and the target's gives ``DL = c*Dt/2`` (its Fig. 14);
and it measures the quasi-CW bench's path with a 4 ns pulse, cross-correlating the detected
pulse with the pulse generator's own output (its Sec. 5.5: 1862.3 m of total path +- 48 cm).
Both are here, with one estimator:

- **Template.** The reference pulse: the ``pulse_ref`` channel when the frame has one (the
  transmitted pulse; ranges then count from the calibrated zero, ``c*(tau - tau0)/2``), else,
  for a ``modulated_reference`` frame, the first pulse after the emission time (``pulse.delay_s``),
  which is the reference mirror's (ranges are then the path difference ``DL`` to the mirror, less
  ``c*tau0/2`` of a calibration). A frame with neither is rejected.
- **Folding.** The record is averaged over its whole periods (``period*fs`` must be a whole
  number of samples; a record shorter than a period is one span): the noise variance drops by
  the number of periods.
- **Delay.** Circular cross-correlation with the template (FFT) for the integer lag, then the
  fractional lag maximising the correlation of the band-limited (Fourier-shifted) template, the
  least-squares estimate for a known shape in white noise; with ``quantize`` the integer lag
  alone (the dissertation's estimator: resolution one sample, ``c/(2*fs)``, 0.75 cm at 20 GS/s).
- **Sigma.** ``var(d) = sigma_n^2*(1 + k*A^2)/(A^2*sum(t'^2))`` (samples^2): the echo's noise and,
  when the template is itself a noisy echo (``k = 1``), the template's, ``A`` the echo over the
  template, ``t'`` the template's derivative; ``sigma_n`` the robust (MAD) spread of the folded
  signal (at least the ADC step over ``sqrt(12)``); plus the fractional shift's error on an
  aliased template (:func:`aliasing_sigma`). Quantised: ``sqrt(var + 1/12)``.
- **Detection.** A pulse counts when its correlation amplitude is ``MIN_PULSE_SNR`` standard
  errors above zero; none: ``no_target``.

The two pulses' shapes must agree (the same detector sees both): a template from a channel that
does not pass the detector (the generator's output) against a band-limited echo biases the delay
by the detector's group delay, which a calibration's ``tau0`` removes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import fft as sfft
from scipy.optimize import minimize_scalar

from ..dsp.validate import rail_fraction
from ..frame import Frame
from ..phase import C
from ..results import NoTarget, Rejected, TargetPoint
from .gating import ref_levels

#: the chain's FrameState and Stage (not imported: the chain imports this module, and core has no
#: import cycles); the stages read and write the state's attributes, the table reuses pb's row type
FrameState = Any
Stage = Any

#: a pulse counts when its fitted amplitude is this many standard errors above 0
MIN_PULSE_SNR = 8.0
#: at most this many echo pulses are reported per frame (strongest first)
MAX_PULSES = 8


@dataclass(frozen=True)
class PulseEcho:
    """One echo pulse against the template.

    Attributes
    ----------
    delay_s, sigma_s : float, delay after the template's pulse (s, in ``[0, period)``) and its sigma (s)
    amplitude : float, echo over template
    snr : float, amplitude over its standard error
    """

    delay_s: float
    sigma_s: float
    amplitude: float
    snr: float


def fold(x: np.ndarray, period_samples: int) -> tuple[np.ndarray, int]:
    """The mean of the record's whole periods, shape (P,), and their number (the record itself, 1, when shorter)."""
    if period_samples >= x.size:
        return x.astype(np.float64, copy=True), 1
    m = x.size // period_samples
    return x[: m * period_samples].reshape(m, period_samples).mean(axis=0), m


def robust_sigma(x: np.ndarray) -> float:
    """1.4826 times the median absolute deviation: the noise spread of a record whose pulses are rare."""
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def _shifted_correlation(yf: np.ndarray, tf: np.ndarray, n: int):
    """``c(d) = sum_k y[k]*t[k - d]`` for real ``d`` (samples), circular, the template band-limited.

    ``yf``, ``tf``: full FFTs of length n.
    """
    f = sfft.fftfreq(n)
    if n % 2 == 0:  # the Nyquist bin of a real signal cannot be shifted by a fraction: leave it out
        f = f.copy()
        keep = np.ones(n)
        keep[n // 2] = 0.0
    else:
        keep = np.ones(n)
    cross = yf * np.conj(tf) * keep

    def corr(d: float) -> float:
        return float(np.real(np.sum(cross * np.exp(2j * np.pi * f * d)))) / n

    return corr


def aliasing_ratio(template: np.ndarray) -> float:
    """``r``: the template's spectrum at Nyquist over its value at 0, the median over the top 5 % of
    the band (noise there makes it conservative); 0 for a template without power at 0."""
    spec = np.abs(sfft.rfft(template))
    return float(np.median(spec[-max(3, spec.size // 20):]) / spec[0]) if spec[0] > 0 else 0.0


def aliasing_sigma(template: np.ndarray) -> float:
    """Sigma (samples) of the fractional-delay error of a template that is not band-limited.

    The Fourier shift is exact for a pulse without content at Nyquist; a pulse sampled too
    coarsely (a 5 GHz detector's ~60 ps pulse every 50 ps) is aliased, and the shifted template
    misses the echo's shape by an error that swings with the echo's sub-sample position, about
    ``r/pi`` samples at most (:func:`aliasing_ratio`; measured: 0.09 sample at ``r = 0.25``); its
    rms, ``r/(pi*sqrt(2))``, is the sigma added.
    """
    return _ratio_sigma(aliasing_ratio(template))


def _ratio_sigma(r: float) -> float:
    """:func:`aliasing_sigma` of a template whose :func:`aliasing_ratio` is ``r``."""
    return r / (math.pi * math.sqrt(2.0))


def _mismatch_reach(auto: np.ndarray) -> int:
    """How far (samples) an echo's shape may leave a copy beside it in the correlation, where it is
    not the template's. An aliased pulse (:func:`aliasing_ratio` ``r``) sampled at another
    sub-sample phase than the template differs from the shifted template by up to ~``r`` of it,
    within the template's autocorrelation's support (lags where it is above 1e-4 of its peak, and a
    sample more; copies were seen out to 4.4 samples). Seen on the techniques probe's PToF benches
    (``r`` ~0.5, a 5 GHz detector at 20 GS/s): copies 0.6-12 % of the echo 1.6-3 samples away,
    1.2-2.3 cm, taken for second echoes (43 confident-false frames of 600). A template on a
    baseline (a pulse_ref channel's gate) has an autocorrelation with a floor: a quarter period
    then, but its ``r`` is that of a pulse tens of samples long, ~1 %."""
    n = auto.size
    lags = np.abs(auto[: n // 2]) > 1e-4 * auto[0]
    return (int(np.flatnonzero(~lags)[0]) if not lags.all() else n // 4) + 1


def find_echoes(signal: np.ndarray, template: np.ndarray, noise_sigma: float, template_noisy: bool,
                exclude: tuple[int, int] | None = None, quantize: bool = False,
                max_pulses: int = MAX_PULSES) -> list[PulseEcho]:
    """Delays (samples, as seconds with ``fs = 1``) of the copies of ``template`` in ``signal``.

    Parameters
    ----------
    signal, template : ndarray, shape (P,), baseline removed, circular (one folded period)
    noise_sigma : float, per-sample noise of ``signal`` (and of ``template`` when ``template_noisy``)
    exclude : (start, stop) or None, lags (samples, circular) not searched: the template's own pulse
    quantize : bool, integer lags only (the dissertation's estimator)

    Returns
    -------
    list of PulseEcho, strongest first, delays and sigmas in samples
    """
    n = signal.size
    yf, tf = sfft.fft(signal), sfft.fft(template)
    full = np.real(sfft.ifft(yf * np.conj(tf)))  # integer-lag correlation, circular
    e_t = float(template @ template)
    d_t = np.real(sfft.ifft(2j * np.pi * sfft.fftfreq(n) * tf))  # the template's derivative (per sample)
    e_dt = float(d_t @ d_t)
    if template_noisy:
        # the template's own noise inflates its derivative's energy: white noise of variance s^2 on
        # W samples adds s^2*W*pi^2/3 (the mean of (2*pi*f)^2 over the band); take it out
        e_dt -= noise_sigma**2 * np.count_nonzero(template) * math.pi**2 / 3
    if e_t <= 0 or e_dt <= 0 or noise_sigma <= 0:
        return []
    amp_se = noise_sigma / math.sqrt(e_t)  # standard error of an amplitude fit (template noise aside)
    mismatch = aliasing_ratio(template)
    alias_var = _ratio_sigma(mismatch) ** 2
    corr = _shifted_correlation(yf, tf, n)
    # the template's autocorrelation width: neighbouring lags within it belong to the same pulse
    auto = np.real(sfft.ifft(np.abs(tf) ** 2))
    half = int(np.argmax(auto[: n // 2] < 0.5 * auto[0])) if np.any(auto[: n // 2] < 0.5 * auto[0]) else n // 4
    guard = max(2 * half, 2)
    score = full / e_t / amp_se
    mask = np.ones(n, bool)
    if exclude is not None:
        a, b = exclude
        mask[np.arange(a, b) % n] = False
    reach = _mismatch_reach(auto)
    out: list[PulseEcho] = []
    clean = signal.astype(np.float64, copy=True)
    big = np.flatnonzero(np.abs(template) > 1e-3 * np.max(np.abs(template)))
    support = np.unique(np.concatenate([big - 1, big, big + 1]))  # an echo's samples, relative to its lag
    while len(out) < max_pulses:
        cand = np.where(mask, score, -np.inf)
        k = int(np.argmax(cand))
        if not cand[k] >= MIN_PULSE_SNR:
            break
        mask[np.arange(k - guard, k + guard + 1) % n] = False
        if quantize:
            d = float(k)
        else:
            r = minimize_scalar(lambda s: -corr(s), bounds=(k - 1.0, k + 1.0), method="bounded",
                                options={"xatol": 1e-5})
            d = float(r.x)
        amp = corr(d) / e_t
        if not amp / amp_se >= MIN_PULSE_SNR:
            continue  # nothing left once the stronger echoes are out: one of their copies (scene 1265)
        if any(abs((d - e.delay_s + n / 2) % n - n / 2) <= reach and abs(amp) < mismatch * abs(e.amplitude)
               for e in out):
            continue  # what a stronger echo's shape, not the template's, leaves beside it
        var = noise_sigma**2 * (1.0 + (amp**2 if template_noisy else 0.0)) / (amp**2 * e_dt) + alias_var
        if quantize:
            var += 1.0 / 12.0
        out.append(PulseEcho(d % n, math.sqrt(var), amp, amp / amp_se))
        # the weaker echoes are refined on the record without this one: the shifted template's tails
        # reach across the period, and through them a stronger echo pulled a weaker one 5-9 of its
        # sigmas (as the reference pulse had, :func:`_correlate`)
        clean[(int(round(d)) + support) % n] = 0.0
        corr = _shifted_correlation(sfft.fft(clean), tf, n)
    return out


# ---------------------------------------------------------------------------------------------
# the stages
@dataclass
class PToFState:
    """What the PToF stages hand each other (``FrameState.technique_state``)."""

    signal: np.ndarray | None = None  # folded pd, baseline removed, shape (P,)
    template: np.ndarray | None = None  # folded reference pulse, baseline removed, shape (P,)
    template_noisy: bool = False
    ref_index: float = 0.0  # where the template's pulse is (samples into the fold); 0 with a ref channel
    exclude: tuple[int, int] | None = None
    echoes: list[PulseEcho] | None = None
    periods: int = 1
    noise_sigma: float = 0.0


def _period_samples(frame: Frame) -> int:
    if frame.pulse is None:
        raise Rejected("bad_pulse", "ptof needs the pulse timing (pulse.period_s)")
    per = frame.pulse.period_s * frame.fs_hz
    if per >= frame.n:
        return frame.n
    if abs(per - round(per)) > 1e-6 * per or round(per) < 16:
        raise Rejected("bad_pulse", f"ptof folds whole periods: period_s*fs_hz = {per:.6g} samples must be a whole "
                                    f"number, at least 16")
    return int(round(per))


def _validate(s: FrameState) -> None:
    """Checks of a PToF frame (no tones): sample rate, shape, length, channels, finite samples, clipping."""
    f, st = s.frame, s.settings
    if not (f.fs_hz > 0 and math.isfinite(f.fs_hz)):
        raise Rejected("bad_fs", f"fs_hz={f.fs_hz!r}")
    if f.samples.ndim != 2 or f.samples.shape[0] != len(f.channels):
        raise Rejected("bad_shape", f"samples shape {f.samples.shape} vs channels {list(f.channels)}")
    if f.n > st.max_samples:
        raise Rejected("too_long", f"{f.n} samples per channel (limit {st.max_samples})")
    if f.n < 256:
        raise Rejected("too_short", f"{f.n} samples (need >= 256)")
    if f.receiver != "single" or "pd" not in f.channels:
        raise Rejected("bad_channels", "ptof needs a single photodiode channel 'pd'")
    has_ref = "pulse_ref" in f.channels
    if not has_ref and f.architecture != "modulated_reference":
        raise Rejected("bad_channels", "ptof needs a reference pulse: a 'pulse_ref' channel or the reference mirror "
                                       "of a modulated_reference bench")
    p = _period_samples(f)
    clip = 0.0
    for name in ("pd", "pulse_ref") if has_ref else ("pd",):
        raw = f.samples[f.channels.index(name)]
        if raw.dtype.kind == "f" and not np.all(np.isfinite(raw)):
            raise Rejected("non_finite", f"{int(np.sum(~np.isfinite(raw)))} NaN/inf samples in {name}")
        if raw.max() == raw.min():
            raise Rejected("flat", f"all samples of {name} equal (no signal)")
        if name == "pd":
            # a pulse record rests on its baseline: only the ADC's extreme codes are rails (for
            # float samples the top, where a clipped pulse would sit)
            if raw.dtype.kind == "i":
                info = np.iinfo(raw.dtype)
                clip = max(rail_fraction(raw, info.max), rail_fraction(raw, info.min))
            else:
                clip = rail_fraction(raw, raw.max())
    s.result.clip_fraction = clip
    if clip > st.max_clip_fraction:
        raise Rejected("clipped", f"{clip:.2%} of samples at the rails (max {st.max_clip_fraction:.2%})")
    t = _st(s)
    y, t.periods = fold(f.volts("pd"), p)
    # an ADC whose step exceeds the noise reads a flat baseline: its quantisation noise is the floor
    lsb = abs(f.scale) if f.samples.dtype.kind == "i" else 0.0
    t.noise_sigma = max(robust_sigma(y), lsb / math.sqrt(12 * t.periods))
    t.signal = y - np.median(y)
    if has_ref:
        r, _ = fold(f.volts("pulse_ref"), p)
        lo, _hi = ref_levels(r)  # the gate stage's levels of a reference pulse: its off level is the 1st percentile
        t.template = r - lo
        t.template_noisy = False
    s.x = t.signal


def _st(s: FrameState) -> PToFState:
    if not isinstance(s.technique_state, PToFState):
        s.technique_state = PToFState()
    return s.technique_state


def _reference(s: FrameState) -> None:
    """The template: the pulse_ref channel, or the reference mirror's pulse (the first after the emission)."""
    t, f = _st(s), s.frame
    assert t.signal is not None
    if t.template is not None:
        return
    y, n = t.signal, t.signal.size
    sig = t.noise_sigma
    above = y > MIN_PULSE_SNR * sig
    if not above.any():
        raise NoTarget(f"no pulse above {MIN_PULSE_SNR} sigma of the noise")
    emit = (f.pulse.delay_s * f.fs_hz) % n if f.pulse is not None else 0.0
    # the first run of samples above the threshold after the emission time (circularly)
    idx = np.flatnonzero(above)
    first = int(idx[np.argmin((idx - emit) % n)])
    k = first
    while y[(k + 1) % n] >= y[k % n]:
        k += 1
    peak = k % n
    # half width: out to where the pulse falls below 1 % of its peak (and at least 4 samples)
    lvl = 0.01 * y[peak]
    w = 1
    while w < n // 4 and (y[(peak + w) % n] > lvl or y[(peak - w) % n] > lvl):
        w += 1
    w = max(2 * w, 4)
    win = np.zeros(n)
    ii = np.arange(peak - w, peak + w + 1) % n
    win[ii] = y[ii]
    t.template = win
    t.template_noisy = True
    t.ref_index = 0.0
    # lags whose echo would overlap the template's window (taken out of the searched signal): the
    # window's +-w and the pulse's own half of it
    t.exclude = (-(w + w // 2), w + w // 2 + 1)


def _correlate(s: FrameState) -> None:
    t = _st(s)
    assert t.signal is not None and t.template is not None
    signal = t.signal
    if t.exclude is not None:
        # the template cut from the signal: its pulse taken out of what is searched. A fractional
        # shift of an aliased template (a 5 GHz detector's pulse every 50 ps) rings across the whole
        # period, and through those tails the reference mirror's pulse, hundreds of times an echo
        # 30 dB weaker, pulled that echo to the nearest sample: up to 0.94 sample (7 mm) at a stated
        # 0.11 (the techniques probe's PToF benches: 16-18 confident-wrong frames of 600)
        signal = np.where(t.template != 0, 0.0, signal)
    t.echoes = find_echoes(signal, t.template, t.noise_sigma, t.template_noisy, t.exclude)
    if not t.echoes:
        raise NoTarget(f"no echo pulse {MIN_PULSE_SNR} standard errors above the noise")


def _select(s: FrameState) -> None:
    t, f = _st(s), s.frame
    assert t.echoes is not None and t.signal is not None
    fs = f.fs_hz
    n = t.signal.size
    tau0 = s.calibration.tau0_s if s.calibration is not None else 0.0
    span_s = f.duration_s
    s.result.unambiguous_range_m = C * (n / fs) / 2
    pts = []
    for e in t.echoes:
        tau = e.delay_s / fs
        sigma_m = C * (e.sigma_s / fs) / 2
        pts.append(TargetPoint(
            range_m=C * (tau - tau0) / 2, range_sigma_m=sigma_m, velocity_mps=0.0,
            # one record cannot see a pulse move: 0, with the speed that would move it by its
            # own sigma (times sqrt(12), a straight-line fit's) within the record as the sigma
            velocity_sigma_mps=2 * math.sqrt(3.0) * sigma_m / span_s, direction="unknown",
            snr_db=20 * math.log10(max(e.snr, 1e-30)), margin=1.0, chi2_per_dof=1.0))
    s.result.targets = pts
    s.result.status = "ok"


def stages(pb: tuple[Stage, ...]) -> tuple[Stage, ...]:
    """The PToF stage table: ``ptof_validate`` (checks, folding), ``ptof_reference`` (the template),
    ``ptof_correlate`` (echo delays), ``ptof_select`` (the points)."""
    row = type(pb[0])  # the chain's Stage

    del pb  # no PB stage applies to a record without tones
    return (row("ptof_validate", _validate), row("ptof_reference", _reference),
            row("ptof_correlate", _correlate), row("ptof_select", _select))


__all__ = ["fold", "robust_sigma", "find_echoes", "PulseEcho", "PToFState", "stages", "MIN_PULSE_SNR"]
