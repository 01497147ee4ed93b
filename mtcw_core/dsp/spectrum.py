"""Windowed power spectrum, local noise floor and the Doppler search."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.fft
from scipy.signal import get_window

LN2 = float(np.log(2.0))
EULER_GAMMA = float(np.euler_gamma)


@dataclass(frozen=True)
class Spectrum:
    """Windowed periodogram of (part of) a record.

    Attributes
    ----------
    power : ndarray, shape (B,)
        ``|X|^2`` of the windowed record (rfft for real, fftshifted fft for complex input), V^2.
    df_hz : float
        Bin spacing (Hz).
    f0_hz : float
        Frequency of bin 0 (0 for real, ``-fs/2`` for complex input).
    window_power : float
        ``sum(w^2)``; white noise of per-sample variance s2 has ``E[power] = s2*window_power``
        (``2*s2*...`` counted over both quadratures for complex noise of total variance s2).
    n : int
        Samples transformed.
    """

    power: np.ndarray
    df_hz: float
    f0_hz: float
    window_power: float
    n: int
    complex_input: bool

    def bin_of(self, f_hz: float | np.ndarray) -> np.ndarray:
        return np.rint((np.asarray(f_hz) - self.f0_hz) / self.df_hz).astype(np.int64)

    def noise_variance(self, f_hz: float, exclude_hz: list[float], half_width: int = 256, guard: int = 12) -> float:
        """Per-sample noise variance (V^2) equivalent to the local noise density around f.

        Median of the periodogram over ``+-half_width`` bins, excluding ``+-guard`` bins around
        every frequency in ``exclude_hz`` (the lines); the median of an exponential variable is
        ``ln 2`` times its mean.
        """
        b = int(self.bin_of(f_hz))
        lo, hi = max(b - half_width, 0), min(b + half_width + 1, self.power.size)
        idx = np.arange(lo, hi)
        mask = np.ones(idx.size, bool)
        ex = self.bin_of(np.asarray(exclude_hz, dtype=float)) if len(exclude_hz) else np.empty(0, np.int64)
        for e in ex[(ex > lo - guard) & (ex < hi + guard)]:
            mask &= np.abs(idx - e) > guard
        vals = self.power[idx[mask]] if mask.any() else self.power[idx]
        if vals.size == 0:
            return float("nan")
        return float(np.median(vals) / LN2 / self.window_power)


@lru_cache(maxsize=8)
def _window(window: tuple | str, m: int, dtype: str = "float64") -> np.ndarray:
    """The (symmetric) window, cached: a stream's frames share one length, and a Kaiser window
    of 1e6 points costs more than the FFT it weights."""
    w = get_window(window, m, fftbins=False).astype(dtype)
    w.setflags(write=False)
    return w


@lru_cache(maxsize=8)
def _window_power(window: tuple | str, m: int) -> float:
    return float(np.sum(_window(window, m) ** 2))


def power_spectrum(x: np.ndarray, fs_hz: float, window: tuple | str = ("kaiser", 14.0), n: int | None = None,
                   single: bool = False) -> Spectrum:
    """Periodogram of the first ``n`` samples (all by default), mean removed.

    Parameters
    ----------
    x : ndarray, shape (N,), float64 or complex128, V
    window : scipy.signal window spec; the default Kaiser(14) has side lobes near -100 dB so a
        strong static line does not masquerade as a Doppler line a few bins away.
    single : bool
        Transform in single precision (about twice as fast). Its rounding floor lies ~140 dB
        below the record's total power, far under any noise floor a digitizer gives; phases are
        never taken from this spectrum (the line fits are float64).
    """
    seg = x if n is None or n >= x.size else x[:n]
    m = seg.size
    win = window if isinstance(window, str) else tuple(window)
    if single:
        seg = seg.astype(np.complex64 if np.iscomplexobj(seg) else np.float32)
    w = _window(win, m, "float32" if single else "float64")
    y = (seg - seg.mean()) * w
    if np.iscomplexobj(y):
        X = scipy.fft.fftshift(scipy.fft.fft(y))
        f0 = -fs_hz / 2 if m % 2 == 0 else -fs_hz / 2 + fs_hz / (2 * m)
        p = (X.real**2 + X.imag**2)
        # complex noise: E|X|^2 = s2_total * sum(w^2); keep the per-quadrature convention
        return Spectrum(p, fs_hz / m, f0, _window_power(window if isinstance(window, str) else tuple(window), m),
                        m, True)
    X = scipy.fft.rfft(y)
    p = X.real**2 + X.imag**2
    # real noise of variance s2: E|X|^2 = s2 * sum(w^2)
    return Spectrum(p, fs_hz / m, 0.0, _window_power(window if isinstance(window, str) else tuple(window), m), m,
                    False)


@dataclass(frozen=True)
class DopplerEstimate:
    """Result of the Doppler search.

    ``fd_hz`` is signed for complex (IQ) input and >= 0 for real input; 0 when no Doppler line
    was detected (``detected`` False). ``score`` is the summed line-to-noise ratio at the peak.
    """

    fd_hz: float
    detected: bool
    score: float
    threshold: float
    min_detectable_hz: float
    #: systematic error of the sub-bin refinement (Hz): the log-parabola through a Kaiser(14)
    #: main lobe is biased by up to ~0.1 bin; an exact refinement sets it to 0
    refine_error_hz: float = 0.0
    #: the line's own wander (Hz): a laser incoherent at the echo's delay broadens the beat into
    #: a Lorentzian of FWHM ``G``, whose centre over ``T`` seconds wanders by ``sqrt(G/(2*pi*T))``
    #: (the phase random walk's end-to-end change over ``2*pi*T``); 0 for a coherent line
    wander_hz: float = 0.0


@lru_cache(maxsize=64)
def intermod_frequencies(tones_hz: tuple[float, ...], f_max_hz: float, order: int | None = None) -> np.ndarray:
    """|sum_i n_i*f_i| for integer n with sum|n_i| <= order (5 for up to 4 tones, else 4), below f_max.

    These static lines (MZM harmonics and intermodulation) sit at fixed frequencies; a Doppler
    candidate whose baseband line falls on one of them is a blind speed of the tone plan.
    """
    t = np.asarray(tones_hz, float)
    if order is None:
        order = 5 if t.size <= 4 else 4
    out = set()
    for n in itertools.product(range(-order, order + 1), repeat=t.size):
        if 0 < sum(map(abs, n)) <= order:
            f = abs(float(np.dot(n, t)))
            if 0 < f <= f_max_hz:
                out.add(f)
    return np.array(sorted(out))


def local_floor(power: np.ndarray, inner: int = 8, outer: int = 48, mirror_dc: bool = False) -> np.ndarray:
    """Mean noise power around every bin, from the bins ``inner..outer`` away on both sides.

    A geometric mean (mean of ``log power``) corrected by Euler's constant, the bias of the mean
    log of an exponential variable: robust to the odd line in the ring, and local enough to follow
    coloured floors such as the laser phase-noise pedestal around a strong line, which a Doppler
    candidate inside it must beat (a wide-block median sits below the pedestal and lets its
    slope pass for a line). The ring skips the candidate's own main lobe (Kaiser(14): +-4.6 bins).

    Parameters
    ----------
    power : ndarray, shape (B,), periodogram (V^2)

    Returns
    -------
    ndarray, shape (B,), the local mean noise power (V^2)
    """
    tiny = np.finfo(power.dtype).tiny if power.dtype.kind == "f" else 1e-300
    lp = np.log(np.maximum(power, tiny))
    nb = lp.size
    # a real signal's spectrum is even about 0 Hz and about fs/2: at both ends the ring continues
    # on the mirror side (one-sided, it would see only the falling side of a pedestal around
    # 0 Hz); an fftshifted complex spectrum is periodic: the ring wraps around +-fs/2
    lp = np.pad(lp, outer, mode="reflect" if mirror_dc else "wrap")
    c = np.concatenate([[0.0], np.cumsum(lp, dtype=np.float64)])

    def window_sum(a: int, b: int) -> np.ndarray:
        """sum(lp[k + a : k + b]) for every bin k: differences of shifted slices of the running sum."""
        return c[outer + b: outer + b + nb] - c[outer + a: outer + a + nb]

    total = window_sum(-outer, -inner + 1) + window_sum(inner, outer + 1)
    count = 2.0 * (outer - inner + 1)
    return np.exp(total / count + EULER_GAMMA)


def line_width_bins(spec: Spectrum, tones_hz, half_span: int = 64) -> float:
    """Median equivalent width (bins) of the lines near 0 Hz and near each tone.

    ``sum(P)/max(P)`` over the strongest line's contiguous bins within 20 dB of its peak (inside
    +-``half_span`` bins): 1-2.3 bins for a coherent line through the
    Kaiser(14) window, ten bins and more when the laser is incoherent at the echo's delay and
    every line is a Lorentzian with a ragged top (about ``pi/2`` times its FWHM in bins).
    """
    centres = [0.0] + [float(f) for f in tones_hz]
    if spec.complex_input:
        centres += [-float(f) for f in tones_hz]
    return widths_at(spec, centres, half_span)


def widths_at(spec: Spectrum, centres, half_span: int = 64) -> float:
    """Median equivalent width (bins) of the strongest line near each of ``centres`` (Hz)."""
    p = spec.power
    dc = int(spec.bin_of(0.0))
    widths = []
    for f in centres:
        k0 = int(spec.bin_of(f))
        lo, hi = max(k0 - half_span, 0), min(k0 + half_span + 1, p.size)
        seg = p[lo:hi].copy()
        if lo <= dc < hi:  # the mean-removal notch and the DC bins are not a line
            seg[max(dc - lo - 1, 0): dc - lo + 2] = 0.0
        if not seg.size or seg.max() <= 0:
            continue
        # the strongest line's own extent: contiguous bins within 20 dB of its peak (a second
        # line nearby, e.g. the other Doppler sideband, is not counted)
        k = int(np.argmax(seg))
        m = float(seg[k])
        above = seg >= 0.01 * m
        r = k + (int(np.argmin(above[k:])) if not above[k:].all() else seg.size - k)
        l_ = k - (int(np.argmin(above[: k + 1][::-1])) if not above[: k + 1].all() else k + 1) + 1
        widths.append(float(seg[l_:r].sum()) / m)
    return float(np.median(widths)) if widths else 1.0


def _near(x: np.ndarray, marks: np.ndarray, tol: float) -> np.ndarray:
    """``|x - nearest mark| < tol`` for every x, by sorted search (x: many bins, marks: a few hundred)."""
    m = np.sort(np.asarray(marks, float))
    if m.size == 0:
        return np.zeros(x.shape, bool)
    i = np.clip(np.searchsorted(m, x), 1, m.size - 1)
    d = np.minimum(np.abs(x - m[i - 1]), np.abs(x - m[i]))
    if m.size == 1:
        d = np.abs(x - m[0])
    return d < tol


def search_doppler(
    spec: Spectrum,
    tones_hz: list[float],
    fd_max_hz: float,
    min_bins: int = 4,
    threshold_factor: float = 8.0,
    use_baseband: bool = True,
    max_targets: int = 1,
) -> list[DopplerEstimate]:
    """Find the Doppler shift from the baseband line and the symmetric lines ``f_i +- f_d``.

    Every candidate shift ``b`` (in bins) is scored by the sum over lines of power over the local
    noise floor: baseband ``|f_d|``, ``f_i + f_d`` and ``|f_i - f_d|`` (folding through 0 Hz for a
    real detector). The peak is accepted when it is a local maximum above ``threshold_factor``
    times the score expected from noise alone; its position is refined below one bin by a
    parabola through the logarithm of the three scores around it (the Kaiser window's main lobe is
    close to Gaussian). Zero Doppler is a valid answer.

    Several targets: after the strongest line, further candidates (up to ``max_targets``) at
    least ``2*min_bins`` away from those found are accepted when they pass the same tests and,
    in addition, at least two of their sideband pairs stand above the threshold (a second
    target must be rangeable, not a stray line).

    Returns
    -------
    list of DopplerEstimate, strongest first; ``[not detected]`` when there is none
    """
    df = spec.df_hz
    nb = spec.power.size
    # a Doppler line must lie outside the skirt of the lines: with a laser incoherent at the
    # echo's delay every line is a Lorentzian whose wings carry random bumps that would pass for
    # Doppler pairs; a coherent line is ~2.3 bins wide here
    # (a coherent line: clear its main lobe; a Lorentzian: its wings' random bumps reach ~2.5
    # FWHM at -15 dB, so keep ~5 FWHM, 4 equivalent widths, away)
    w = line_width_bins(spec, tones_hz)
    min_bins = max(min_bins, int(math.ceil(w + 2 if w < 4 else 4 * w)))

    def wander(fd: float) -> float:
        """The Doppler line's own wander (Hz) from the width of its lines (baseband, f_i +- f_d).

        A Lorentzian's equivalent width is pi/2 FWHM on top of the window's ~2.3 bins; a
        coherent line measures 2.3-3 bins (scalloping), so only wider lines count.
        """
        t = np.asarray(tones_hz, float)
        centres = np.concatenate([[fd], fd + t, fd - t]) if spec.complex_input else np.abs(
            np.concatenate([[fd], t + fd, t - fd]))
        wd = widths_at(spec, [float(c) for c in centres], half_span=16)
        fwhm_hz = (wd - 2.3) * df * 2 / math.pi if wd > 3.2 else 0.0
        return math.sqrt(fwhm_hz * df / (2 * math.pi)) if fwhm_hz > 0 else 0.0  # over T ~ 1/df
    # two bins beyond the limit, so that a line exactly at it is still a local maximum
    bmax = int(min(np.floor(fd_max_hz / df) + 2, nb // 2 - 1))
    tones = np.asarray(tones_hz, dtype=float)
    if bmax <= min_bins + 1:
        return [DopplerEstimate(0.0, False, 0.0, 0.0, min_bins * df)]
    floor = local_floor(spec.power, mirror_dc=not spec.complex_input)

    def power(f_hz: np.ndarray) -> np.ndarray:
        idx = spec.bin_of(f_hz)
        ok = (idx >= 0) & (idx < nb)
        out = np.zeros(idx.size)
        out[ok] = spec.power[idx[ok]]
        return out

    def line(f_hz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Power at f, and power over the local floor (the search's hot path: one lookup each)."""
        p = power(f_hz)
        return p, p / floor[np.clip(spec.bin_of(f_hz), 0, nb - 1)]

    signs = (1, -1) if spec.complex_input else (1,)
    n_lines = 2 * tones.size + (1 if use_baseband else 0)
    results = {}
    fd_all = {}
    for s in signs:
        b = np.arange(0, bmax + 1)
        fd = s * b * df
        fd_all[s] = fd
        score = np.zeros(b.size)
        f_base = fd if spec.complex_input else np.abs(fd)
        base_p, base = line(f_base)
        if use_baseband:
            score += base
        strongest_pair = np.zeros(b.size)  # raw power of the strongest sideband pair
        n_pairs = np.zeros(b.size, int)  # sideband pairs above the threshold
        for f in tones:
            up_p, up = line(fd + f)
            # the lower line: signed for IQ, folded through 0 Hz for a real detector
            down_p, down = line(fd - f if spec.complex_input else np.abs(f - fd))
            # a Doppler pair is symmetric; a spur (IMD product) usually sits on one side only
            pair = np.minimum(up, down)
            score += 2 * pair
            n_pairs += pair > threshold_factor
            strongest_pair = np.maximum(strongest_pair, np.minimum(up_p, down_p))
        valid = np.ones(b.size, bool)
        valid[:min_bins] = False
        if use_baseband:
            # the LO x echo-carrier beat is the strongest line of a moving target: require it,
            # and ignore candidates sitting on a static intermodulation product
            valid &= (base > threshold_factor) & (base_p > strongest_pair)
            # one cached enumeration per tone plan and search range (min_bins varies per frame)
            spurs = intermod_frequencies(tuple(float(f) for f in tones), 2.0 * float(fd_max_hz))
            spurs = spurs[spurs <= (bmax + min_bins) * df]
            if spurs.size:
                # on a static intermodulation product, a candidate counts only when its line is
                # stronger than every static first-order line (a product never is; a moving
                # target's carrier beat is stronger than its own sidebands)
                near = _near(np.abs(fd), spurs, min_bins * df)
                static_max = float(np.max(power(tones)))
                valid &= ~near | (base_p > static_max)
        results[s] = (score, valid, n_pairs)
    threshold = threshold_factor * n_lines
    found: list[DopplerEstimate] = []
    ghost_base = np.concatenate([[0.0], tones, -tones, intermod_frequencies(tuple(float(f) for f in tones),
                                                                            float(np.max(tones)) + fd_max_hz)])
    ghost_base = np.concatenate([ghost_base, -ghost_base])
    taken: list[tuple[int, int]] = []  # (sign, bin)
    for _ in range(max_targets):
        best = None
        for s, (score, valid, n_pairs) in results.items():
            ok = valid.copy()
            for ts, tb in taken:
                if ts == s or not spec.complex_input:
                    ok[max(tb - 2 * min_bins, 0): tb + 2 * min_bins + 1] = False
            if found:
                ok &= n_pairs >= 2
                # not a ghost of a target already found: its lines and intermodulation products
                # (tones, IMD, 0 Hz) shifted by that target's Doppler
                # -- and the beat of two targets found (one acts as the other's LO: lines at
                # the difference and the sum of their Dopplers)
                base_f = np.abs(fd_all[s])
                shifts = [d.fd_hz for d in found]
                shifts += [a.fd_hz + sgn * b.fd_hz for i, a in enumerate(found) for b in found[i + 1:]
                           for sgn in (1, -1)]
                for sh in shifts:
                    ghosts = np.abs(np.concatenate([ghost_base + sh, ghost_base - sh]))
                    near = _near(base_f, ghosts, min_bins * df)
                    ok &= ~near
            if not ok.any():
                continue
            k = int(np.flatnonzero(ok)[np.argmax(score[ok])])
            if best is None or score[k] > best[0]:
                best = (float(score[k]), k, s)
        if best is None:
            break
        peak, k, s = best
        score = results[s][0]
        is_local = 0 < k < score.size - 1 and score[k] >= score[k - 1] and score[k] >= score[k + 1]
        if peak < threshold or not is_local:
            break
        y0, y1, y2 = np.log(np.maximum(score[k - 1 : k + 2], 1e-300))
        den = y0 - 2 * y1 + y2
        delta = 0.5 * (y0 - y2) / den if den < 0 else 0.0
        delta = float(np.clip(delta, -0.5, 0.5))
        fd = s * (k + delta) * df
        found.append(DopplerEstimate(fd, True, peak, threshold, min_bins * df, 0.1 * df, wander(fd)))
        taken.append((s, k))
    return found or [DopplerEstimate(0.0, False, 0.0, threshold, min_bins * df)]
