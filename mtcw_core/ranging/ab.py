"""AB-MTCW: amplitude-based multi-tone CW ranging (the dissertation's chapter 3), and its stage table.

Architecture ``modulated_reference``: the LO is the modulated beam itself, reflected by a
reference mirror at ``L_ref``; the echo comes back from the target at ``L``. With
``Dtau = tau_m - tau_ref`` the round-trip delay between the arms, a single photodiode sees at
each tone ``f_i`` (small signal, ``Theta`` the carrier phase difference ``2*pi*f0*Dtau`` mod
``2*pi``, averaged over the record, ``a_r``, ``a_m`` the two arms' field amplitudes)::

    c_i ~ m_i*g_i*exp(-j*2*pi*f_i*tau_ref) * (P + Q*exp(-j*2*pi*f_i*Dtau))
    P = a_r^2 + a_r*a_m*<cos Theta>,   Q = a_m^2 + a_r*a_m*<cos Theta>

(self-beats of each arm plus the two cross-beats; the dissertation's Eq. 3.7 is this with
``cos Theta = 1``). Normalised by a measurement of the reference arm alone
(``|m_i*g_i*a_r^2|^2``: the modulation depths and the detector's response per tone), the
tone powers follow a sinusoid across frequency::

    y_i = |c_i|^2 / |c_i,ref|^2 = alpha + beta*cos(2*pi*f_i*Dtau),   alpha = (P^2+Q^2)/a_r^4, beta = 2PQ/a_r^4

whose period ``1/Dtau`` is ``c/(2*DL)``. :func:`fit_sine` finds ``Dtau`` (``alpha``, ``beta``
linear, ``Dtau`` on a grid then refined), with the weighted-least-squares covariance as its
sigma and the dissertation's R^2 as its quality.

**The carrier phase.** ``P`` and ``Q`` depend on ``<cos Theta>``: for a static target, moving
the wavelength by ``lambda^2/(2*DL)`` (1.2 pm at 1 m and 1540 nm; 0.1 pm moves ``Theta`` by
0.53 rad) changes the tone levels, the pattern's depth ``beta`` and even its sign (``Q < 0``
when ``cos Theta < -a_m/a_r``); at ``cos Theta = -a_m/a_r`` the pattern vanishes. Handled, not
hidden: the fitted model leaves ``alpha`` and ``beta`` free (either sign), so the period, and
the range, do not depend on ``Theta``; the sigma follows the depth actually seen (a shallow
pattern is a wide sigma); a pattern whose depth is not ``MIN_DEPTH_Z`` sigmas from zero is
``no_target`` ("pattern faded") rather than a guess. For a moving target ``<cos Theta>``
averages towards 0 over the record and the pattern is the arms' self-beats alone
(``P = a_r^2, Q = a_m^2``): depth ``2*rho/(1+rho^2)`` with ``rho = a_m^2/a_r^2``, against
``2*sqrt(rho)/(1+rho)`` at ``cos Theta = 1`` -- the power balance between the arms matters much
more then (the dissertation's Fig. 11 and its remark that fast targets wash the pattern out).

**Unambiguous range.** ``cos(2*pi*f_i*Dtau)`` is periodic in ``Dtau`` with ``1/g`` (``g`` the
gcd of the tones) *and even*: ``Dtau`` and ``1/g - Dtau`` give the same powers. The powers
therefore fix ``DL`` within ``[0, c/(4*g)]`` (1.5 m for Fig. 10's 50 MHz gcd), half what the
dissertation's Eq. 3.10 states, and within ``[0, c/(8*g)]`` when every ``f_i/g`` is odd (the sign
flip of ``Dtau -> 1/(2g) - Dtau`` is absorbed by the free depth: 37.5 m for the bench's
79...2623 MHz, against the dissertation's 150 m); nor can they tell a target in front of the
reference mirror from one behind it (``|DL|``). The search covers ``[range_min_m,
range_max_m]`` within that interval; a runner-up peak of the fit close enough to the best that
noise swaps them with odds above ``cycle_slip_max`` (:func:`swap_odds`) is flagged
``cycle_ambiguous`` (the dissertation bounded its fit with the PToF range).

**Speed** from the baseband line of the carrier beat at ``|f_d|`` (the dissertation's PDV),
refined below a bin on the record's exact DFT, with the Cramér–Rao sigma of a sinusoid's
frequency in the local noise floor; a single photodiode gives no sign.

Range convention: ``range_m = c*|Dtau|/2 - c*tau0/2`` with ``tau0`` from the calibration (0
without): the path difference ``DL = L - L_ref`` itself, or ``L`` when the calibration was made
with the reference mirror's range (:func:`derive_reference`: ``tau0 = -2*L_ref/c``).
"""

from __future__ import annotations

import datetime as _dt
import math
from collections.abc import Iterable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.special import diric

from ..calibration import Calibration, CalibrationError
from ..dsp.doppler import intermod_frequencies
from ..dsp.spectrum import Spectrum, local_floor, power_spectrum, widths_at
from ..dsp.tones import exact_dft, fit_lines, lines_signal
from ..frame import Frame
from ..phase import C
from ..results import NoTarget, Rejected, TargetPoint
from .targets import shared_phase_error_hz

#: the chain's FrameState and Stage (not imported: the chain imports this module, and core has no
#: import cycles); the stages read and write the state's attributes, the table reuses pb's row type
FrameState = Any
Stage = Any

#: the pattern's depth |beta| must be this many of its sigmas from 0, else the frame is
#: ``no_target`` (pattern faded: the carrier phase at the null, an echo too weak against the
#: reference, or a path difference below the shortest one the tones resolve)
MIN_DEPTH_Z = 5.0
#: the lowest minima of the sine fit's grid profile that are refined before ranking them
REFINED_MINIMA = 8
#: relative floor of a normalised tone power's sigma: the small-signal model's own accuracy (the
#: MZM's second-order products and Bessel terms are not in it; an exact MZM at m = 0.2 moves a
#: noiseless bench's powers by ~1e-4 of themselves), so that a nearly noiseless tone does not
#: take all the weight of the fit
MODEL_REL_SIGMA = 1e-3
#: false-alarm probability of the baseband Doppler search over all its bins
DOPPLER_FALSE_ALARM = 1e-6
#: bins next to 0 Hz never searched for the Doppler line: the main lobe of the mean-removal
#: residue through the Kaiser(14) window is +-4.6 bins wide
DC_GUARD_BINS = 6
#: the baseband candidate is a line where its equivalent width (:func:`~mtcw_core.dsp.spectrum.widths_at`
#: over +-:data:`LINE_WIDTH_SPAN_BINS`) is at most this many bins: a coherent line through the Kaiser(14)
#: window is 2.3-3; a bump of a product's phase-noise pedestal is wider (a 500 kHz laser, a target at
#: 6.9 m moving 0.28 MHz: a bump 0.8 MHz beside the 32 MHz product stood 19x over the floor, and
#: the still-looking target read 25 m/s, 2400 sigmas off)
MAX_LINE_WIDTH_BINS = 3.2
LINE_WIDTH_SPAN_BINS = 8
#: the baseband search's second, near floor: the bins this far from the candidate (its Kaiser(14)
#: main lobe, +-4.6 bins, left out), beside the chain's ring of 8-48
NEAR_FLOOR_BINS = (5, 12)


# ---------------------------------------------------------------------------------------------
# the closed form (what the simulator must reproduce; used by tests and the benchmark)
def pattern(f_hz, dtau_s: float, a_ref: float, a_meas: float, cos_theta: float) -> np.ndarray:
    """Normalised tone powers ``y_i`` of the module's model (small signal, single photodiode).

    Parameters
    ----------
    f_hz : array_like, shape (K,), tone frequencies (Hz)
    dtau_s : float, round-trip delay of the measurement arm minus the reference arm's (s)
    a_ref, a_meas : float, field amplitudes of the arms (``10**(-loss_db/20)``)
    cos_theta : float, the carrier phase factor ``<cos Theta>`` (1 for the dissertation's
        Eq. 3.7, 0 for a target moving over many Doppler periods in the record)

    Returns
    -------
    ndarray, shape (K,), ``|P + Q*exp(-j*2*pi*f*dtau)|^2 / a_ref^4``
    """
    f = np.asarray(f_hz, dtype=np.float64)
    p = a_ref**2 + a_ref * a_meas * cos_theta
    q = a_meas**2 + a_ref * a_meas * cos_theta
    return np.abs(p + q * np.exp(-2j * np.pi * f * dtau_s)) ** 2 / a_ref**4


def pattern_depth(a_ref: float, a_meas: float, cos_theta: float) -> float:
    """``beta/alpha = 2PQ/(P^2 + Q^2)`` of :func:`pattern`: the sine's relative depth (the dissertation's m')."""
    p = a_ref**2 + a_ref * a_meas * cos_theta
    q = a_meas**2 + a_ref * a_meas * cos_theta
    return 2 * p * q / (p * p + q * q)


def unambiguous_path(tones_hz) -> float:
    """The largest ``|DL|`` (m) the normalised powers fix, ``g`` the gcd of the tones on a 1 Hz grid.

    ``c/(4*g)``: ``Dtau`` and ``1/g - Dtau`` give the same cosines. And ``c/(8*g)`` when every
    ``f_i/g`` is odd: ``Dtau -> 1/(2g) - Dtau`` then flips the sign of every cosine, which a free
    depth ``beta`` (its sign set by the carrier phase) absorbs -- the case of the bench's tones,
    all odd multiples of 1 MHz (37.5 m, not the 150 m of the dissertation's Eq. 3.10).
    """
    ints = [int(round(f)) for f in tones_hz]
    g = math.gcd(*ints)
    return C / (8 * g) if all((f // g) % 2 == 1 for f in ints) else C / (4 * g)


# ---------------------------------------------------------------------------------------------
# the stages' maths
@dataclass(frozen=True)
class BasebandLine:
    """The carrier beat near 0 Hz: the target's ``|f_d|``.

    Attributes
    ----------
    fd_hz : float, the line's frequency (Hz, >= 0; 0 when not detected)
    sigma_hz : float, its Cramér–Rao sigma (Hz); the smallest searched frequency when not detected
    detected : bool
    snr_db : float, line power over the local floor (dB)
    min_detectable_hz : float, the lowest frequency searched (Hz)
    max_searched_hz : float, the highest frequency searched (Hz)
    doubt : str, why the strongest candidate, above the threshold, was not taken for the target's
        line, and its speed is unknown up to ``max_searched_hz`` (not 0): ``"broad"`` (no coherent
        line, wider than :data:`MAX_LINE_WIDTH_BINS`: a bump of a pedestal, or a carrier beat the
        laser is incoherent over), ``"product"`` (within the lowest searched frequency of one of the
        tones' static products: the product moved by a Doppler below the band); ``""`` otherwise
    """

    fd_hz: float
    sigma_hz: float
    detected: bool
    snr_db: float
    min_detectable_hz: float
    max_searched_hz: float = math.inf
    doubt: str = ""


def baseband_doppler(x: np.ndarray, fs_hz: float, spec: Spectrum, tones_hz, min_bins: int,
                     fd_max_hz: float | None) -> BasebandLine:
    """Find and refine the baseband Doppler line.

    The strongest bin of ``spec`` from ``max(min_bins, DC_GUARD_BINS)`` bins up to ``fd_max_hz``
    (default: half the lowest tone and half the smallest tone spacing) counts when it exceeds
    its local floor (:func:`~mtcw_core.dsp.spectrum.local_floor`) by ``ln(bins/DOPPLER_FALSE_ALARM)``
    (an exponential noise bin passes with probability ``DOPPLER_FALSE_ALARM`` over the search).
    Its frequency is then the maximum of the energy a real sinusoid and a constant explain
    (least squares; a plain periodogram, or the fitted line's power, is biased by the line's
    image at ``-f`` and the constant when the record holds few cycles) over the whole record
    within +-1 spectrum bin (the maximum-likelihood estimate of one sinusoid's frequency in white
    noise),
    its sigma the Cramér–Rao bound ``fs*sqrt(6)*sigma_n/(pi*A*N^1.5)`` with the line's amplitude
    ``A`` (joint fit with the tones) and the per-sample noise ``sigma_n`` of the local floor.

    Parameters
    ----------
    x : ndarray, shape (N,), float64, V
    spec : the ``spectrum`` stage's periodogram of (part of) ``x``
    """
    t = sorted(float(f) for f in tones_hz)
    top = min([0.5 * t[0]] + [0.5 * (b - a) for a, b in zip(t, t[1:])])
    if fd_max_hz is not None:
        top = min(top, fd_max_hz)
    k_lo = max(min_bins, DC_GUARD_BINS)
    k_hi = min(int(top / spec.df_hz), spec.power.size - 1)
    f_lo = k_lo * spec.df_hz
    if k_hi <= k_lo + 2:
        return BasebandLine(0.0, f_lo, False, -math.inf, f_lo, top)
    spec, prods = _without_products(x, fs_hz, t, spec, top)
    # the floor near the candidate too: the carrier beat's phase-noise pedestal falls steeply
    # beside a line under the band, where the wide ring reads it low (a bump 3x its pedestal stood
    # 19.5x over the wide ring: a target moving 0.72 MHz under a 500 kHz laser read 2.8 MHz)
    wide = local_floor(spec.power, mirror_dc=True)[k_lo:k_hi + 1]
    near = local_floor(spec.power, NEAR_FLOOR_BINS[0], NEAR_FLOOR_BINS[1], mirror_dc=True)[k_lo:k_hi + 1]
    band = spec.power[k_lo:k_hi + 1]
    ratio = band / np.maximum(wide, near)
    k = int(np.argmax(ratio))
    threshold = math.log((k_hi - k_lo + 1) / DOPPLER_FALSE_ALARM)
    snr_db = 10 * math.log10(max(float(ratio[k]), 1e-30))
    if ratio[k] < threshold:
        # a line over the wide floor but not over the near one: inside a pedestal, its own (a mover
        # under a laser incoherent over its delay) or another line's: a speed, unknown
        doubt = "broad" if float(np.max(band / wide)) >= threshold else ""
        return BasebandLine(0.0, f_lo, False, snr_db, f_lo, top, doubt)
    if k == 0:  # the band's first bin the highest: the skirt of a line below the band (a Doppler under f_lo)
        return BasebandLine(0.0, f_lo, False, snr_db, f_lo, top)
    f0 = (k_lo + k) * spec.df_hz
    doubt = _doubt(spec, f0, prods, f_lo)
    if doubt:
        return BasebandLine(0.0, f_lo, False, snr_db, f_lo, top, doubt)
    n = x.size
    # the tone lines (and the Doppler sidebands beside them) removed first: their leakage
    # through the record's rectangular window would pull a line of a few cycles
    lines = np.array([*t, *(np.array(t) + f0), *(np.array(t) - f0)])
    amps = fit_lines(x, lines, fs_hz)
    kc = np.arange(n, dtype=np.float64) - (n - 1) / 2
    y = x - x.mean()
    for f_l, c_l in zip(lines, amps):
        y = y - np.real(c_l * np.exp(2j * np.pi * np.mod(kc * (f_l / fs_hz), 1.0)))
    res = minimize_scalar(lambda f: -_explained(y, f, fs_hz),
                          bounds=(max(f0 - spec.df_hz, 0.5 * f_lo), f0 + spec.df_hz), method="bounded",
                          options={"xatol": 1e-4 * fs_hz / n})
    fd = float(res.x)
    amp = abs(fit_lines(x, [fd, *t], fs_hz)[0])
    noise = spec.noise_variance(fd, [0.0, fd])
    sigma = fs_hz * math.sqrt(6.0 * noise) / (math.pi * amp * n**1.5) if amp > 0 else math.inf
    return BasebandLine(fd, sigma, True, snr_db, f_lo, top)


def _without_products(x: np.ndarray, fs_hz: float, tones_hz: list[float], spec: Spectrum, f_max_hz: float
                      ) -> tuple[Spectrum, np.ndarray]:
    """``spec`` of ``x`` with the tones' static products below ``f_max_hz`` (plus the window's
    reach) fitted and taken out: the baseband search's spectrum, and those products (Hz).

    The arms' self-beats carry the tones' intermodulation products (the MZM's and the square law's,
    :func:`~mtcw_core.dsp.doppler.intermod_frequencies`, folded at the sample rate): on the AB bench's
    tones 971 + 1657 - 2623 = 5 MHz, 32 and 38 MHz lie in the band searched. They are static
    lines, but one line alone is all this search asks of a Doppler, and before they were taken
    out a still target read 3.85 m/s (5 MHz at 1540 nm) in 47 of 452 frames of a random probe
    (``python -m mtcw_bench.techniques_probe --technique ab``). Fitted jointly with the tones
    (:func:`~mtcw_core.dsp.tones.fit_lines`), they leave a mover within a record bin or so of one
    unseen: reported ``static`` -- a blind speed of the tone plan (the bench's tones: 3.85, 4.6,
    24.6 and 29.3 m/s), as the PB chain's spur test has its own; ``spec`` unchanged where none lies
    in the band."""
    reach = 8 * spec.df_hz  # a Kaiser(14) line's skirt
    prods = intermod_frequencies(tuple(tones_hz), f_max_hz + reach, fs_hz=fs_hz)
    prods = prods[prods > fs_hz / x.size]
    if prods.size > 1:  # two products within half a record bin are one line to the fit
        prods = prods[np.concatenate([[True], np.diff(prods) > 0.5 * fs_hz / x.size])]
    if not prods.size:
        return spec, prods
    lines = np.concatenate([prods, tones_hz])
    amps = fit_lines(x, lines, fs_hz)
    y = x - lines_signal(amps[:prods.size], prods, fs_hz, x.size, False)
    single = np.dtype(spec.power.dtype) == np.float32
    out = power_spectrum(y, fs_hz, spec.window or ("kaiser", 14.0), spec.n if spec.n < x.size else None, single)
    return replace(out, record_n=spec.record_n), prods  # the same samples, the same floor rings


def _doubt(spec: Spectrum, f0_hz: float, prods_hz: np.ndarray, f_lo_hz: float) -> str:
    """Why the baseband candidate at ``f0_hz`` is not the target's line (:attr:`BasebandLine.doubt`),
    or ``""``. A product moved by a Doppler ``f_d`` under the band (``|p +- f_d|``, the target's
    cross-beat with the reference's products) stands where the baseband line at ``f_d`` is not
    searched: a still-looking target at 6.4 m moving 66 kHz read 3.85 m/s beside the 5 MHz
    product; a carrier beat whose laser is incoherent over the delay, or a pedestal's bump, is no
    line (:data:`MAX_LINE_WIDTH_BINS`)."""
    if prods_hz.size and float(np.min(np.abs(prods_hz - f0_hz))) < f_lo_hz:
        return "product"
    if widths_at(spec, [f0_hz], LINE_WIDTH_SPAN_BINS) > MAX_LINE_WIDTH_BINS:
        return "broad"
    return ""


def _explained(x: np.ndarray, f_hz: float, fs_hz: float) -> float:
    """Energy (V^2) of the least-squares fit of ``d + a*cos(w*k') + b*sin(w*k')`` to ``x`` (``k'`` the centred index).

    ``p^T G^-1 p`` with the correlations ``p`` (one exact DFT) and the Gram matrix ``G`` in
    closed form (Dirichlet kernels): O(N) per frequency, no basis arrays.
    """
    n = x.size
    w = 2 * np.pi * f_hz / fs_hz
    z = exact_dft(x, [f_hz], fs_hz)[0]

    def dk(v: float) -> float:
        return n * float(diric(v, n))

    gc = 0.5 * np.array([[2 * n, dk(w) + dk(-w)], [dk(-w) + dk(w), n + dk(2 * w)]])
    gs = 0.5 * (n - dk(2 * w))
    pc = np.array([float(np.sum(x)), z.real])
    return float(pc @ np.linalg.solve(gc, pc) + (z.imag**2 / gs if gs > 0 else 0.0))


@dataclass(frozen=True)
class TonePowers:
    """Power of every tone line and its variance.

    Attributes
    ----------
    tones_hz : ndarray, shape (K,), Hz
    power_v2 : ndarray, shape (K,), ``|c_i|^2`` less its noise bias (V^2; ``c_i`` the line's amplitude)
    var_v4 : ndarray, shape (K,), its variance ``2|c|^2 s^2 + s^4`` with ``s^2 = 4*sigma_n^2/N`` (V^4)
    snr_db : ndarray, shape (K,), ``|c|^2/s^2`` (dB)
    """

    tones_hz: np.ndarray
    power_v2: np.ndarray
    var_v4: np.ndarray
    snr_db: np.ndarray


def tone_powers(x: np.ndarray, fs_hz: float, tones_hz, spec: Spectrum, fd_hz: float = 0.0) -> TonePowers:
    """The tones' line powers from a joint least-squares fit at known frequencies.

    With a Doppler line ``fd_hz > 0`` the fit also holds ``fd`` and every ``f_i +- fd`` (the
    cross-beats a moving target puts beside each tone), so that they do not leak into ``f_i``.
    The noise per line is the local floor of ``spec`` (per-sample variance ``sigma_n^2``): a real
    line's LS amplitude then has complex variance ``s^2 = 4*sigma_n^2/N``.

    Parameters
    ----------
    x : ndarray, shape (N,), float64, V
    """
    f = np.asarray(sorted(float(v) for v in tones_hz))
    freqs = list(f)
    if fd_hz > 0:
        freqs += [fd_hz, *(f + fd_hz), *(f - fd_hz)]
    c = fit_lines(x, freqs, fs_hz)[: f.size]
    marks = [0.0, *freqs]
    s2 = np.array([4 * spec.noise_variance(fi, marks) / x.size for fi in f])
    p = np.abs(c) ** 2
    return TonePowers(f, p - s2, 2 * p * s2 + s2 * s2, 10 * np.log10(np.maximum(p, 1e-300) / s2))


@dataclass(frozen=True)
class SineFit:
    """The sine fit of normalised tone powers across frequency.

    Attributes
    ----------
    dtau_s, sigma_s : float, ``|Dtau|`` (s) and its sigma (s)
    alpha, beta, beta_sigma : float, offset, depth (signed) and the depth's sigma
    r2 : float, the dissertation's R^2 = 1 - SS_res/SS_tot (unweighted)
    chi2, dof : float, int, weighted residual sum and ``K - 3``
    runner_up_s, delta_chi2 : float, the second-best peak's ``Dtau`` and its chi2 excess over
        the best (Birge-scaled); ``inf`` when there is none
    lo_s, hi_s : float, the searched interval of ``Dtau`` (s)
    """

    dtau_s: float
    sigma_s: float
    alpha: float
    beta: float
    beta_sigma: float
    r2: float
    chi2: float
    dof: int
    runner_up_s: float
    delta_chi2: float
    lo_s: float
    hi_s: float


def _linear(f: np.ndarray, y: np.ndarray, w: np.ndarray, tau: np.ndarray):
    """Weighted LS of ``y = alpha + beta*cos(2*pi*f*tau)`` for every ``tau`` (shape (G,)): alpha, beta, chi2."""
    c = np.cos(2 * np.pi * np.outer(tau, f))  # (G, K)
    s0 = w.sum()
    s1 = c @ w
    s2 = (c * c) @ w
    b0 = float(w @ y)
    b1 = c @ (w * y)
    det = s0 * s2 - s1 * s1
    ok = det > 1e-12 * s0 * np.maximum(s2, 1e-300)
    safe = np.where(ok, det, 1.0)
    alpha = np.where(ok, (s2 * b0 - s1 * b1) / safe, b0 / s0)
    beta = np.where(ok, (s0 * b1 - s1 * b0) / safe, 0.0)
    chi2 = float(w @ (y * y)) - (alpha * b0 + beta * b1)
    return alpha, beta, np.maximum(chi2, 0.0)


def fit_sine(f_hz, y, var, lo_s: float, hi_s: float, points_per_cycle: int = 16,
             max_points: int = 2**22) -> SineFit:
    """Fit ``y = alpha + beta*cos(2*pi*f*Dtau)`` with ``Dtau`` in ``[lo_s, hi_s]``.

    A grid of ``points_per_cycle`` points per period of the highest tone's cosine, the weighted
    linear solution at each, the best point refined (bounded scalar search between its
    neighbours); the runner-up is the best other local minimum of the chi2 profile, refined
    the same way. The covariance is the inverse Fisher matrix of ``(alpha, beta, Dtau)``, scaled
    by ``chi2/dof`` when that exceeds 1 (Birge).

    Parameters
    ----------
    f_hz, y, var : array_like, shape (K,), K >= 3: tone frequencies (Hz), normalised powers, their variances

    Raises
    ------
    ValueError
        Fewer than 3 tones, a non-positive variance, or an empty interval.
    """
    f = np.asarray(f_hz, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    v = np.asarray(var, dtype=np.float64)
    if f.size < 3:
        raise ValueError("tones: a sine fit of 3 parameters needs at least 3 tones")
    if not np.all(v > 0) or not np.all(np.isfinite(v)):
        raise ValueError("var: variances must be positive and finite")
    if not hi_s > lo_s:
        raise ValueError(f"interval: [{lo_s:g}, {hi_s:g}] s is empty")
    w = 1.0 / v
    step = 1.0 / (f.max() * points_per_cycle)
    count = min(int(math.ceil((hi_s - lo_s) / step)) + 1, max_points)
    grid = np.linspace(lo_s, hi_s, max(count, 3))
    chi2 = np.concatenate([_linear(f, y, w, grid[i:i + 8192])[2] for i in range(0, grid.size, 8192)])

    def prof(t: float) -> float:
        return float(_linear(f, y, w, np.array([t]))[2][0])

    def refine(i: int) -> tuple[float, float]:
        a, b = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
        r = minimize_scalar(prof, bounds=(a, b), method="bounded", options={"xatol": 1e-6 * step})
        return (float(r.x), float(r.fun)) if r.fun <= chi2[i] else (float(grid[i]), float(chi2[i]))

    # local minima of the profile (the interval's ends count when lower than their neighbour)
    inner = (chi2[1:-1] <= chi2[:-2]) & (chi2[1:-1] <= chi2[2:])
    minima = np.flatnonzero(np.concatenate([[chi2[0] <= chi2[1]], inner, [chi2[-1] <= chi2[-2]]]))
    order = minima[np.argsort(chi2[minima])]
    # the few lowest grid minima refined, then ranked (a grid point may sit off its peak)
    cands = sorted((refine(int(i)) + (int(i),) for i in order[:REFINED_MINIMA]), key=lambda c: c[1])
    t_best, c_best, best_i = cands[0]
    others = [c for c in cands[1:] if abs(c[2] - best_i) > 1]
    dof = f.size - 3
    birge = max(1.0, c_best / dof) if dof > 0 else 1.0
    if others:
        t_ru, c_ru, _ = others[0]
        dchi2 = (c_ru - c_best) / birge
    else:
        t_ru, dchi2 = math.nan, math.inf
    alpha, beta, _ = (float(a[0]) for a in _linear(f, y, w, np.array([t_best])))
    th = 2 * np.pi * f * t_best
    jac = np.column_stack([np.ones_like(f), np.cos(th), -2 * np.pi * f * beta * np.sin(th)])
    fisher = jac.T @ (w[:, None] * jac)
    try:
        cov = np.linalg.inv(fisher) * birge
        sig_t, sig_b = math.sqrt(max(cov[2, 2], 0.0)), math.sqrt(max(cov[1, 1], 0.0))
    except np.linalg.LinAlgError:
        sig_t = sig_b = math.inf
    model = alpha + beta * np.cos(th)
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 - float(np.sum((y - model) ** 2)) / ss_tot if ss_tot > 0 else 0.0
    return SineFit(abs(t_best), sig_t, alpha, beta, sig_b, r2, c_best, dof, t_ru, dchi2, lo_s, hi_s)


# ---------------------------------------------------------------------------------------------
# the reference-only measurement
def reference_powers(cal: Calibration | None, tones_hz) -> tuple[np.ndarray, np.ndarray]:
    """The reference arm's tone powers (V^2) and their sigmas from the calibration, in the order of sorted ``tones_hz``.

    Raises
    ------
    Rejected
        ``calibration``: none, or one without reference powers (``mtcw calibrate --technique ab``).
    """
    if cal is None or not cal.reference_powers_v2:
        raise Rejected("calibration", "ab needs the reference arm's tone powers: a calibration from a reference-only "
                                      "recording (mtcw calibrate RECORDING --technique ab --known-range L_REF)")
    order = np.argsort(np.asarray(cal.tones_hz))
    p = np.asarray(cal.reference_powers_v2, dtype=np.float64)[order]
    s = (np.asarray(cal.reference_power_sigma_v2, dtype=np.float64)[order] if cal.reference_power_sigma_v2
         else np.zeros_like(p))
    return p, s


def derive_reference(frames: Iterable[Frame], reference_range_m: float = 0.0, source: str = "") -> Calibration:
    """An AB calibration from frames of the reference arm alone (the measurement arm blocked).

    Per tone: the mean line power over the frames and its standard error from the line noise (the normalisation of
    every later frame), the line phase (kept as ``tone_phases_rad`` for the record, unused by
    AB), and ``tau0_s = -2*reference_range_m/c`` so that ranges come out from the calibrated zero
    (``L``) rather than as the path difference to the mirror.

    Raises
    ------
    CalibrationError
        No frames, frames with different tone plans, or a frame that is not a single-photodiode record.
    """
    from ..profiles import get_profile
    from ..dsp.spectrum import search_spectrum
    from ..dsp.validate import validate

    settings = get_profile("balanced", technique="ab")
    powers, variances, phases, tones = [], [], [], None
    for fr in frames:
        if fr.receiver != "single":
            raise CalibrationError(f"frame seq {fr.seq}: ab needs a single photodiode (receiver {fr.receiver!r})")
        x, _ = validate(fr, settings, None)
        t = tuple(fr.tones_hz)  # the frame's order: the chain checks calibration tones against it
        if tones is None:
            tones = t
        elif t != tones:
            raise CalibrationError(f"frame seq {fr.seq}: tone plan differs from the first frame")
        spec = search_spectrum(x, fr.fs_hz, settings.window_beta, 1.0, False)
        tp = tone_powers(x, fr.fs_hz, t, spec)  # sorted by frequency: back to the frame's order
        p_frame, v_frame = np.empty(len(t)), np.empty(len(t))
        p_frame[np.argsort(t)], v_frame[np.argsort(t)] = tp.power_v2, tp.var_v4
        powers.append(p_frame)
        variances.append(v_frame)
        phases.append(np.angle(fit_lines(x, t, fr.fs_hz)))
    if tones is None:
        raise CalibrationError("no frames to calibrate from")
    pw = np.asarray(powers)
    # the mean's standard error from the lines' noise (a spread over a few frames would be a
    # noisy estimate of it, and none from one frame)
    se = np.sqrt(np.mean(variances, axis=0) / len(pw))
    ph = np.angle(np.mean(np.exp(1j * np.asarray(phases)), axis=0))
    return Calibration(tones_hz=tuple(float(f) for f in tones), tone_phases_rad=tuple(float(p) for p in ph),
                       tau0_s=-2.0 * reference_range_m / C, known_range_m=float(reference_range_m),
                       frames_used=len(pw), source=source,
                       created=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                       reference_powers_v2=tuple(float(p) for p in pw.mean(axis=0)),
                       reference_power_sigma_v2=tuple(float(s) for s in se))


# ---------------------------------------------------------------------------------------------
# the stages
@dataclass
class ABState:
    """What the AB stages hand each other (``FrameState.technique_state``)."""

    line: BasebandLine | None = None
    powers: TonePowers | None = None
    fit: SineFit | None = None
    offset_m: float = 0.0  # c*tau0/2 of the calibration: range = c*Dtau/2 - offset


def swap_odds(delta_chi2: float) -> float:
    """The odds that noise put the sine fit's best peak ahead of the right one ``delta_chi2`` (after
    the Birge scaling) behind it: for Gaussian errors the log-likelihood ratio of two hypotheses
    ``D`` apart has mean ``D`` and variance ``4D``, so they swap with probability
    ``Phi(-sqrt(D)/2)``. Read against ``ChainSettings.cycle_slip_max`` (1e-3: ``D`` ~38), as the PB
    chain reads its own cycle odds; the fixed ``D`` of 25 this replaced (0.6 %) let a still echo at
    31.7 m under a 500 kHz laser (``D`` = 26.2) through on the wrong period (the techniques probe's
    scene 1060)."""
    if not math.isfinite(delta_chi2):
        return 0.0
    return float(0.5 * math.erfc(math.sqrt(max(delta_chi2, 0.0)) / 2 / math.sqrt(2.0)))


def _st(s: FrameState) -> ABState:
    if not isinstance(s.technique_state, ABState):
        s.technique_state = ABState()
    return s.technique_state


def _doppler(s: FrameState) -> None:
    if s.frame.receiver != "single":
        raise Rejected("receiver", f"ab needs a single photodiode (the arms' self-beats); got {s.frame.receiver!r}")
    st = s.settings
    ab = _st(s)
    ab.line = baseband_doppler(s.x, s.frame.fs_hz, s.spectrum, s.frame.tones_hz, st.doppler_min_bins, st.fd_max_hz)
    s.result.doppler_hz = ab.line.fd_hz


def _powers(s: FrameState) -> None:
    ab = _st(s)
    if len(s.frame.tones_hz) < 3:
        raise Rejected("tone_plan", "ab fits 3 parameters: at least 3 tones are needed")
    ref, _ = reference_powers(s.calibration, s.frame.tones_hz)  # rejects before the work
    assert ab.line is not None
    ab.powers = tone_powers(s.x, s.frame.fs_hz, s.frame.tones_hz, s.spectrum, ab.line.fd_hz)
    if not np.all(ref > 0):
        raise Rejected("calibration", "reference_powers_v2: every reference tone power must be positive")


def _fit(s: FrameState) -> None:
    ab = _st(s)
    pw = ab.powers
    assert pw is not None
    ref, ref_sigma = reference_powers(s.calibration, s.frame.tones_hz)
    y = pw.power_v2 / ref
    s2 = (np.sqrt(pw.var_v4 + pw.power_v2**2) - pw.power_v2)  # the line's noise s^2 back from var = 2*p*s^2 + s^4
    ab.offset_m = C * s.calibration.tau0_s / 2 if s.calibration is not None else 0.0
    st = s.settings
    top = unambiguous_path(pw.tones_hz)
    s.result.unambiguous_range_m = top
    lo = max(0.0, st.range_min_m + ab.offset_m)
    hi = top if st.range_max_m is None else min(top, st.range_max_m + ab.offset_m)
    if not hi > lo:
        raise Rejected("range", f"the searched interval [{lo:g}, {hi:g}] m of |DL| is empty (range_min_m, "
                                f"range_max_m against the calibration's reference range and c/(4*gcd) = {top:g} m)")
    # weights from the fitted powers, not the measured ones (a tone measured low by chance would
    # weigh more and pull the fit): a first fit with the measured, then one with the model's
    var = pw.var_v4 / ref**2 + (y * ref_sigma / ref) ** 2 + (MODEL_REL_SIGMA * y) ** 2
    for _ in range(2):
        ab.fit = fit_sine(pw.tones_hz, y, var, 2 * lo / C, 2 * hi / C, st.points_per_cycle, st.max_grid_points)
        model = np.maximum(ab.fit.alpha + ab.fit.beta * np.cos(2 * np.pi * pw.tones_hz * ab.fit.dtau_s), 0.0)
        var = (2 * model * ref * s2 + s2 * s2) / ref**2 + (model * ref_sigma / ref) ** 2 + (MODEL_REL_SIGMA * model) ** 2


def _select(s: FrameState) -> None:
    ab = _st(s)
    fit, pw, line = ab.fit, ab.powers, ab.line
    assert fit is not None and pw is not None and line is not None
    depth_z = abs(fit.beta) / fit.beta_sigma if fit.beta_sigma > 0 else math.inf
    if not depth_z >= MIN_DEPTH_Z:
        raise NoTarget(f"tone-power pattern faded: depth {fit.beta:.3g} is {depth_z:.1f} sigma (< {MIN_DEPTH_Z}); "
                       f"the carrier phase at the pattern's null, an echo too weak against the reference, or a path "
                       f"difference too short for the tones")
    sigma_m = C * fit.sigma_s / 2
    if not math.isfinite(sigma_m):
        raise NoTarget("sine fit: its covariance is singular")
    lam = s.frame.wavelength_m
    if line.detected:
        # the laser's phase over the path difference the fit found moves the line's frequency
        # (:func:`~mtcw_core.ranging.targets.shared_phase_error_hz`: a 500 kHz laser, 8.5 m, 2^16
        # samples at 20 GS/s: 9 kHz, against a white-noise bound of 1 kHz; seen 7.8 kHz off)
        wander = shared_phase_error_hz(s.settings.laser_linewidth_hz, fit.dtau_s, s.frame.n / s.frame.fs_hz)
        v, v_sig, direction = line.fd_hz * lam / 2, math.hypot(line.sigma_hz, wander) * lam / 2, "unknown"
    elif line.doubt:  # something stood there, not the target's line: any speed the search covers
        v, v_sig, direction = 0.0, line.max_searched_hz * lam / 2, "unknown"
    else:
        v, v_sig, direction = 0.0, line.min_detectable_hz * lam / 2, "static"
    dl = C * fit.dtau_s / 2
    edge_lo, edge_hi = C * fit.lo_s / 2, C * fit.hi_s / 2
    near = (dl - edge_lo < 3 * sigma_m and edge_lo > 0) or edge_hi - dl < 3 * sigma_m
    chi2_dof = fit.chi2 / fit.dof if fit.dof > 0 else 1.0
    margin = 1.0 - 1.0 / (1.0 + fit.delta_chi2 / max(fit.chi2, 1.0)) if math.isfinite(fit.delta_chi2) else 1.0
    s.result.targets = [TargetPoint(
        range_m=dl - ab.offset_m, range_sigma_m=sigma_m, velocity_mps=v, velocity_sigma_mps=v_sig,
        direction=direction, snr_db=float(np.max(pw.snr_db)), margin=float(min(max(margin, 0.0), 1.0)),
        near_edge=bool(near), cycle_ambiguous=bool(swap_odds(fit.delta_chi2) > s.settings.cycle_slip_max),
        cycle_slip_prob=swap_odds(fit.delta_chi2),
        blended=bool(chi2_dof > s.settings.blended_chi2), doppler_hz=line.fd_hz, chi2_per_dof=float(chi2_dof),
        tone_snr_db={f"{f:.0f}": float(d) for f, d in zip(pw.tones_hz, pw.snr_db)}, fit_r2=float(fit.r2))]
    s.result.status = "ok"


def stages(pb: tuple[Stage, ...]) -> tuple[Stage, ...]:
    """The AB stage table: pb's ``validate`` and ``spectrum``, then ``ab_doppler`` (baseband line),
    ``ab_powers`` (tone powers), ``ab_fit`` (normalised sine fit), ``ab_select`` (the point)."""
    row = type(pb[0])  # the chain's Stage

    by = {st.name: st for st in pb}
    return (by["validate"], by["spectrum"], row("ab_doppler", _doppler), row("ab_powers", _powers),
            row("ab_fit", _fit), row("ab_select", _select))


__all__ = ["pattern", "pattern_depth", "unambiguous_path", "baseband_doppler", "BasebandLine", "tone_powers",
           "TonePowers", "fit_sine", "SineFit", "reference_powers", "derive_reference", "stages", "ABState",
           "swap_odds", "MIN_DEPTH_Z"]

