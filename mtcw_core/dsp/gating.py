"""Quasi-CW coarse gating: find the echo pulse, a coarse round-trip delay, and where the echo is on.

The laser is gated with period ``P`` and duty ``D`` (on for ``W = D*P``); the echo is the same
gate delayed by the round trip ``tau``. The echo's presence is seen in the power of the beat
lines: per block of ``B`` samples, the power of the strongest non-DC spectral bins (the tone
beats, wherever Doppler put them) is the *envelope* ``e[b]``. The transmitted gate's centre
``c_tx`` comes from the reference channel (half-maximum crossings of its edges) or, without
one, from the known gate timing. ``tau`` is then

1. coarse: the lag maximising the cross-correlation of ``e`` with the periodic gate, block by
   block (an FFT correlation);
2. below a block: least squares of ``e[b] = A*G(b; c_tx + tau) + floor`` where ``G`` is the
   exact fraction of block ``b`` covered by the (periodic, rectangular) echo gate; its sigma
   follows from the residual and the slope of ``G`` at the edges;
3. fine: each gate edge fitted on the signed band signals (0 Hz and one band per tone), jointly
   over bands (:func:`refine_edges`); edges that agree are combined, disagreeing ones widen
   the sigma.

The delay is known modulo ``P`` (``c*P/2``: 30 km for the dissertation's 200 us).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import signal as sps
from scipy.optimize import minimize_scalar


@dataclass(frozen=True)
class GateEstimate:
    """Result of the coarse gating stage.

    Attributes
    ----------
    tau_s : float
        Round-trip delay of the echo gate relative to the transmitted gate (s), in ``[0, P)``.
    sigma_s : float
        Its standard deviation (s).
    windows : list of (int, int)
        Sample index ranges ``[a, b)`` in which the echo is fully on (margins removed).
    snr : float
        Echo envelope amplitude over its standard error (detection statistic).
    detected : bool
    width_s : float
        Gate width used (s).
    """

    tau_s: float
    sigma_s: float
    windows: list[tuple[int, int]]
    snr: float
    detected: bool
    width_s: float


def _crossings(r: np.ndarray, level: float, rising: bool) -> np.ndarray:
    """Fractional sample indices where ``r`` crosses ``level`` (linear interpolation)."""
    above = r >= level
    idx = np.flatnonzero(above[1:] & ~above[:-1]) if rising else np.flatnonzero(~above[1:] & above[:-1])
    y0, y1 = r[idx], r[idx + 1]
    return idx + (level - y0) / (y1 - y0)


def transmit_centre(ref: np.ndarray | None, fs_hz: float, period_s: float, duty: float,
                    delay_s: float) -> tuple[float, float]:
    """Centre of the transmitted gate modulo the period (s) and its half-maximum width (s).

    From the reference channel when given (``ref``: shape (N,), volts), else from the known gate
    timing (the gate is on for ``duty*period`` from ``delay_s``, symmetric ramps).
    """
    w_known = duty * period_s
    if ref is not None:
        r = np.asarray(ref, np.float64)
        lo, hi = np.percentile(r, 1), np.percentile(r, 99)
        if hi > lo:
            mid = 0.5 * (lo + hi)
            up = _crossings(r, mid, True) / fs_hz
            down = _crossings(r, mid, False) / fs_hz
            if up.size and down.size:
                # pair every rising edge with the next falling edge (the gate may wrap)
                widths, centres = [], []
                for u in up:
                    later = down[down > u]
                    d = later[0] if later.size else down[0] + period_s * math.ceil((u - down[0]) / period_s + 1e-12)
                    widths.append(d - u)
                    centres.append(0.5 * (u + d))
                w = float(np.median(widths))
                # circular mean of the centres modulo the period
                ang = 2 * np.pi * np.asarray(centres) / period_s
                c = float(np.angle(np.mean(np.exp(1j * ang)))) / (2 * np.pi) * period_s % period_s
                return c, w
            if up.size or down.size:  # one edge only: the known width fixes the centre
                edge = (up[0] + w_known / 2) if up.size else (down[0] - w_known / 2)
                return float(edge % period_s), w_known
    return (delay_s + w_known / 2) % period_s, w_known


def _coverage(starts_s: np.ndarray, block_s: float, t0_s: float, width_s: float, period_s: float) -> np.ndarray:
    """Fraction of each block ``[starts, starts + block)`` covered by the periodic gate on
    ``[t0 + m*P, t0 + m*P + width)``.

    Parameters
    ----------
    starts_s : ndarray, shape (M,), block start times (s)
    """
    # move each block's start into the period that begins at the gate's start
    u = np.mod(starts_s - t0_s, period_s)  # gate-relative start of the block, in [0, P)
    out = np.zeros(starts_s.size)
    # the block [u, u + block) may overlap the gate's copies at 0 and at P (block < P assumed)
    for shift in (0.0, period_s):
        lo = np.maximum(u, shift)
        hi = np.minimum(u + block_s, shift + width_s)
        out += np.clip(hi - lo, 0.0, None)
    return out / block_s


def envelope(x: np.ndarray, block: int, n_bins: int) -> np.ndarray:
    """Beat-line power per block: the ``n_bins`` strongest non-DC bins of the mean block spectrum.

    Parameters
    ----------
    x : ndarray, shape (N,), real or complex (V)
    block : int, samples per block
    n_bins : int, bins summed (about twice the number of tones plus one)

    Returns
    -------
    ndarray, shape (N // block,), V^2
    """
    nb = x.size // block
    xb = x[: nb * block].reshape(nb, block)
    if np.iscomplexobj(xb):
        p = np.abs(np.fft.fft(xb, axis=1)) ** 2
        p[:, 0] = 0
    else:
        p = np.abs(np.fft.rfft(xb, axis=1)) ** 2
        p[:, :2] = 0  # DC and its neighbour carry the sign-fluctuating carrier beat
    mean = p.mean(axis=0)
    k = np.argsort(mean)[-n_bins:]
    return p[:, k].sum(axis=1)


def band_signals(y: np.ndarray, fs_hz: float, tones_hz, half_band_hz: float) -> np.ndarray:
    """The complex baseband signal of each band (0 Hz, then each tone), shape (1 + T, M), V.

    A static target's band signal is ``g(t)*cos(psi(t))`` times a constant complex amplitude:
    signed, so that a fading ``cos(psi)`` passing through zero near an edge is still a smooth
    (linear) term, not the kink a magnitude would show.
    """
    m = y.size
    spec = np.fft.fft(y)
    f = np.fft.fftfreq(m, 1 / fs_hz)
    t = np.arange(m) / fs_hz
    centres = [0.0] + [float(c) for c in tones_hz]
    out = np.empty((len(centres), m), complex)
    for i, fc in enumerate(centres):
        # smooth (Hann-shaped) band so that the signal does not ring
        d = np.abs(np.abs(f) - fc) if fc > 0 else np.abs(f)
        w = np.where(d < half_band_hz, 0.5 * (1 + np.cos(np.pi * d / half_band_hz)), 0.0)
        if fc > 0:
            w = w * (f > 0)  # one side: the analytic band
        out[i] = np.fft.ifft(spec * w) * (np.exp(-2j * np.pi * fc * t) if fc > 0 else 1.0)
    return out


def _fit_edge_bands(z: np.ndarray, fs_hz: float, ramp_samples: float, rising: bool
                    ) -> tuple[float, float, float] | None:
    """A gate edge in the band signals ``z`` (shape (B, n)), jointly.

    Model per band: ``z_b[k] = H(k - t_e) * (a_b + c_b*(k - t_e)/n) + d_b`` with complex
    ``a_b, c_b, d_b`` and ``H`` a linear ramp of ``ramp_samples`` centred on the edge (the band
    filter's rise). Returns ``(t_e, sigma_t, contrast)`` in seconds from ``z[:, 0]`` (contrast:
    the step's amplitude over its standard error), or None.
    """
    nbands, n = z.shape
    k = np.arange(n, dtype=float)
    zt = z.T  # (n, B)

    def design(te: float) -> np.ndarray:
        h = np.clip((k - te) / ramp_samples + 0.5, 0, 1)
        if not rising:
            h = 1 - h
        return np.column_stack([h, h * (k - te) / n, np.ones(n)])

    def sse(te: float):
        a = design(te)
        coef, *_ = np.linalg.lstsq(a, zt, rcond=None)
        r = zt - a @ coef
        return float(np.sum(r.real**2 + r.imag**2)), coef, a

    grid = np.arange(ramp_samples, n - ramp_samples, max(ramp_samples / 4, 1.0))
    if grid.size < 3:
        return None
    vals = np.array([sse(t)[0] for t in grid])
    j = int(np.argmin(vals))
    step_g = grid[1] - grid[0]
    r = minimize_scalar(lambda t: sse(t)[0], bounds=(grid[j] - step_g, grid[j] + step_g), method="bounded",
                        options={"xatol": 1e-3})
    te = float(r.x)
    err, coef, a = sse(te)
    p = 3 * nbands
    # per real component; the band signals are smooth over ~ramp samples: count those, not samples
    s2 = err / max(2 * n * nbands - 2 * p, 1) * max(ramp_samples / 2, 1.0)
    hh = 0.25 * ramp_samples
    curv = (sse(te + hh)[0] - 2 * err + sse(te - hh)[0]) / hh**2
    if not (curv > 0 and s2 > 0):
        return None
    var_t = 2 * s2 / curv
    cov00 = s2 * float(np.linalg.pinv(a.T @ a)[0, 0])
    step2 = float(np.sum(np.abs(coef[0]) ** 2))
    contrast = math.sqrt(step2 / (2 * nbands * cov00)) if cov00 > 0 else math.inf
    return te / fs_hz, math.sqrt(var_t) / fs_hz, contrast


def _edge(x: np.ndarray, fs_hz: float, t_pred_s: float, half_window_s: float, off_level: float, tones,
          half_band: float, ramp: float, rising: bool, min_contrast: float) -> tuple[float, float, float] | None:
    """One edge: a wide window to find it, then a narrow one (+-3 filter rises) to place it.

    Fitted on the signed band signals (:func:`band_signals`), so that a fading ``cos(psi)`` is
    a slope, not a kink; the narrow pass keeps what fading remains from bending the step.
    Returns (time from the record's start (s), sigma (s), contrast) or None.
    """
    n = x.size
    hw = int(math.ceil(half_window_s * fs_hz))
    pad = int(2 * ramp)  # the band filters are circular (FFT): compute wider, keep the middle

    def bands(a: int, b: int) -> np.ndarray | None:
        if a - pad < 0 or b + pad > n:
            return None
        return band_signals(x[a - pad:b + pad] - off_level, fs_hz, tones, half_band)[:, pad:-pad]

    i0 = int(round(t_pred_s * fs_hz)) - hw
    z = bands(i0, i0 + 2 * hw)
    if z is None:
        return None
    fit = _fit_edge_bands(z, fs_hz, ramp, rising)
    if fit is None or fit[2] < min_contrast:
        return None
    t1 = i0 / fs_hz + fit[0]
    hw2 = int(3 * ramp)
    j0 = int(round(t1 * fs_hz)) - hw2
    z2 = bands(j0, j0 + 2 * hw2) if hw2 < hw else None
    if z2 is not None:
        fit2 = _fit_edge_bands(z2, fs_hz, ramp, rising)
        if fit2 is not None and fit2[2] >= min_contrast and abs(j0 / fs_hz + fit2[0] - t1) < ramp / fs_hz:
            return j0 / fs_hz + fit2[0], fit2[1], fit2[2]
    return t1, fit[1], fit[2]


def refine_edges(x: np.ndarray, fs_hz: float, t_start_s: float, width_s: float, period_s: float,
                 off_level: float, half_window_s: float, tones_hz, min_contrast: float = 5.0,
                 sure_contrast: float = 10.0) -> tuple[float, float] | None:
    """Echo gate centre (s, modulo the period) and its sigma from every edge inside the record.

    Each rising edge near ``t_start + m*P`` and falling edge near ``t_start + width + m*P`` is
    fitted on the band signals (:func:`band_signals`) of ``x - off_level``; a rising edge gives
    the centre as ``t + width/2``, a falling one as ``t - width/2``. Edges that agree are combined
    by inverse variance; when they disagree beyond their sigmas (an edge bent by fading), the one
    of highest contrast is kept and the sigma widened to cover the others. Edges of contrast
    between ``min_contrast`` and ``sure_contrast`` count only when two of them agree. None when
    no edge is usable.
    """
    n = x.size
    t = sorted(float(f) for f in tones_hz)
    half_band = 0.5 * min([b - a for a, b in zip(t, t[1:])] + [t[0]])
    ramp = max(fs_hz / half_band, 2.0)  # the band filter's rise, in samples
    centres, sig, contrast = [], [], []
    t_end = n / fs_hz
    m = math.floor(-t_start_s / period_s) - 1
    while t_start_s + m * period_s - width_s < t_end:
        for rising, t_pred in ((True, t_start_s + m * period_s), (False, t_start_s + width_s + m * period_s)):
            e = _edge(x, fs_hz, t_pred, half_window_s, off_level, t, half_band, ramp, rising, min_contrast)
            if e is None:
                continue
            # the step model is not the envelope's exact shape (the gate's own ramp, residual
            # fading): 0.15 of the band filter's rise is the floor of what one edge tells
            st = math.hypot(e[1], 0.15 * ramp / fs_hz)
            c = e[0] + width_s / 2 if rising else e[0] - width_s / 2
            centres.append(c % period_s)
            sig.append(st)
            contrast.append(e[2])
        m += 1
    if not centres:
        return None
    cen, sig = np.asarray(centres), np.asarray(sig)
    best = int(np.argmax(contrast))
    dev = (cen - cen[best] + period_s / 2) % period_s - period_s / 2
    agree = np.abs(dev) <= 3 * np.hypot(sig, sig[best])
    if contrast[best] < sure_contrast and np.count_nonzero(agree) < 2:
        return None  # weak edges that do not confirm each other
    w = 1 / sig[agree] ** 2
    c = float(cen[best] + np.sum(w * dev[agree]) / np.sum(w)) % period_s
    sigma = 1 / math.sqrt(float(np.sum(w)))
    if not agree.all():
        # an edge where the echo's cos(psi) fades through zero carries no timing and may be
        # fitted anywhere; which one did cannot be told (contrast, nearness to the block-level
        # estimate: both tried, both slipped more often): the spread is the sigma
        sigma = max(sigma, float(np.max(np.abs(dev[~agree]))) / 3)
    return c, sigma


def coarse_gate(x: np.ndarray, fs_hz: float, period_s: float, duty: float, delay_s: float,
                tones_hz, ref: np.ndarray | None = None, block: int = 256, margin_s: float = 10e-9,
                min_snr: float = 8.0) -> GateEstimate:
    """Find the echo gate in a pulsed record.

    Parameters
    ----------
    x : ndarray, shape (N,), detector signal (V), real or complex
    fs_hz, period_s, duty, delay_s : gate timing as known to the acquisition side
    tones_hz : sequence of float, the modulation tones (Hz)
    ref : ndarray, shape (N,), optional, the transmitted-gate reference channel (V)
    block : int, samples per envelope block (coarse stage)
    margin_s : float, extra time cut from each end of the echo-on windows (s)
    min_snr : float, detection threshold on the envelope amplitude over its standard error
    """
    n = x.size
    block = int(min(block, max(16, n // 64)))
    bs = block / fs_hz
    e = envelope(x - np.mean(x), block, 2 * len(tones_hz) + 1)
    nb = e.size
    c_tx, width = transmit_centre(ref, fs_hz, period_s, duty, delay_s)
    t_tx = c_tx - width / 2  # transmitted gate start (s), modulo P
    starts = np.arange(nb) * bs
    # 1. coarse: correlation over every lag in one period, block resolution
    nlag = max(int(math.ceil(period_s / bs)), 1)
    ext_starts = (np.arange(-nlag + 1, nb)) * bs
    g_ext = _coverage(ext_starts, bs, t_tx, width, period_s)
    corr = sps.correlate(e - e.mean(), g_ext - g_ext.mean(), mode="valid", method="fft")
    lags = (nlag - 1 - np.arange(corr.size)) * bs
    tau = float(-lags[int(np.argmax(corr))] % period_s)

    # 2. below one block: least squares of the envelope on the exact block coverage
    def fit(t: float):
        g = _coverage(starts, bs, t_tx + t, width, period_s)
        a = np.column_stack([g, np.ones(nb)])
        coef, *_ = np.linalg.lstsq(a, e, rcond=None)
        res = e - a @ coef
        return float(res @ res), coef, g

    r = minimize_scalar(lambda t: fit(t)[0], bounds=(tau - 1.5 * bs, tau + 1.5 * bs), method="bounded",
                        options={"xatol": 1e-4 * bs})
    tau = float(r.x) % period_s
    sse, (amp, _floor), g = fit(tau)
    s2 = sse / max(nb - 3, 1)
    a = np.column_stack([g, np.ones(nb)])
    cov = s2 * np.linalg.pinv(a.T @ a)
    snr = float(amp / math.sqrt(cov[0, 0])) if cov[0, 0] > 0 else math.inf
    h = 0.05 * bs
    dg = (_coverage(starts, bs, t_tx + tau + h, width, period_s)
          - _coverage(starts, bs, t_tx + tau - h, width, period_s)) / (2 * h)
    info = amp**2 * float(dg @ dg) / s2 if s2 > 0 else math.inf
    # a rectangle's coverage is not the envelope's exact shape (fading, the gate's ramps): a
    # quarter block is the floor of what the block fit can tell
    sigma = math.hypot(1 / math.sqrt(info) if info > 0 else math.inf, 0.25 * bs)
    detected = bool(amp > 0 and snr >= min_snr)
    if detected:
        # 3. the edges themselves, on the band envelope about the echo-off level
        gs = _coverage(np.arange(n // 16) * 16 / fs_hz, 16 / fs_hz, t_tx + tau, width, period_s)
        off = x[: gs.size * 16].reshape(gs.size, 16)[gs == 0]
        if off.size:
            fine = refine_edges(x, fs_hz, t_tx + tau, width, period_s, float(np.mean(off)),
                                half_window_s=max(6 * sigma, 2 * bs), tones_hz=tones_hz)
            if fine is not None and fine[1] < sigma:
                tau = float((fine[0] - c_tx) % period_s)
                sigma = fine[1]
    windows: list[tuple[int, int]] = []
    if detected:
        cut = margin_s + 3 * sigma
        on_start = t_tx + tau + cut
        on_len = width - 2 * cut
        t_end = n / fs_hz
        m = math.floor(-on_start / period_s)
        while on_len > 0 and on_start + m * period_s < t_end:
            a_i = int(math.ceil(max(on_start + m * period_s, 0.0) * fs_hz))
            b_i = int(math.floor(min(on_start + m * period_s + on_len, t_end) * fs_hz))
            if b_i - a_i >= 16:
                windows.append((a_i, b_i))
            m += 1
    return GateEstimate(tau, sigma, windows, snr, detected, width)
