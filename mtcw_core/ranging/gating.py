"""Stage ``gate``: quasi-CW coarse gating: find the echo pulse, a coarse round-trip delay, and where the echo is on.

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
3. fine: a likelihood over each gate edge's time from the band signals (0 Hz and one band per
   tone), with the echo's wandering amplitude (a single detector sees ``cos(psi(t))``, which
   fades through zero with the laser's phase noise) integrated out by a Kalman filter; the
   edges' likelihoods combine, the gate width integrated out (:func:`refine_edges`). A faded
   edge is a wide likelihood, not a confident wrong time.

The delay is known modulo ``P`` (``c*P/2``: 30 km for the dissertation's 200 us).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import fft as sfft
from scipy import signal as sps
from scipy.optimize import minimize_scalar

from ..frame import Frame
from ..profiles import ChainSettings


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


def ref_levels(ref: np.ndarray) -> tuple[float, float]:
    """Low and high levels of the reference gate waveform: its 1st and 99th percentiles (V)."""
    lo, hi = np.percentile(np.asarray(ref, np.float64), [1, 99])
    return float(lo), float(hi)


def ramp_duration(ref: np.ndarray | None, fs_hz: float, levels: tuple[float, float] | None = None) -> float:
    """Length (s) of the transmitted gate's rising ramp from the reference channel, 0 without one.

    The 10-90 % time of the rising edges (median), as a raised-cosine ramp ``sin^2(pi*t/(2r))``
    (whose 10-90 % time is 0.590 ``r``).
    """
    if ref is None:
        return 0.0
    r = np.asarray(ref, np.float64)
    lo, hi = levels or ref_levels(r)
    if not hi > lo:
        return 0.0
    mid = _crossings(r, lo + 0.5 * (hi - lo), True)
    c10 = _crossings(r, lo + 0.1 * (hi - lo), True)
    c90 = _crossings(r, lo + 0.9 * (hi - lo), True)
    rise = []
    for u in mid:
        i, j = np.searchsorted(c10, u) - 1, np.searchsorted(c90, u)
        if i >= 0 and j < c90.size and u - c10[i] < 0.25 * r.size and c90[j] - u < 0.25 * r.size:
            rise.append(c90[j] - c10[i])
    return float(np.median(rise)) / fs_hz / 0.590 if rise else 0.0


def transmit_centre(ref: np.ndarray | None, fs_hz: float, period_s: float, duty: float,
                    delay_s: float, levels: tuple[float, float] | None = None) -> tuple[float, float]:
    """Centre of the transmitted gate modulo the period (s) and its half-maximum width (s).

    From the reference channel when given (``ref``: shape (N,), volts), else from the known gate
    timing (the gate is on for ``duty*period`` from ``delay_s``, symmetric ramps).
    """
    w_known = duty * period_s
    if ref is not None:
        r = np.asarray(ref, np.float64)
        lo, hi = levels or ref_levels(r)
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
        p = np.abs(sfft.fft(xb, axis=1)) ** 2
        p[:, 0] = 0
    else:
        p = np.abs(sfft.rfft(xb, axis=1)) ** 2
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
    spec = sfft.fft(y)
    f = sfft.fftfreq(m, 1 / fs_hz)
    t = np.arange(m) / fs_hz
    centres = [0.0] + [float(c) for c in tones_hz]
    out = np.empty((len(centres), m), complex)
    for i, fc in enumerate(centres):
        # smooth (Hann-shaped) band so that the signal does not ring
        d = np.abs(np.abs(f) - fc) if fc > 0 else np.abs(f)
        w = np.where(d < half_band_hz, 0.5 * (1 + np.cos(np.pi * d / half_band_hz)), 0.0)
        if fc > 0:
            w = w * (f > 0)  # one side: the analytic band
        out[i] = sfft.ifft(spec * w) * (np.exp(-2j * np.pi * fc * t) if fc > 0 else 1.0)
    return out


def _step_response(half_band_hz: float, fs_hz: float, ramp_s: float = 0.0):
    """The band signals' response to a gate edge, as a function of time from its half maximum
    (samples).

    The edge is a raised-cosine ramp of ``ramp_s`` (0: a step); the band weight is Hann-shaped,
    ``W(f) = (1 + cos(pi*f/B))/2`` for ``|f| < B``, with impulse response
    ``w(t) = B*sinc(2Bt)/(1 - (2Bt)^2)``. Their convolution is tabulated.
    """
    span = 12.0 / half_band_hz + ramp_s
    t = np.linspace(-span, span, 8193)
    dt = t[1] - t[0]
    x = 2 * half_band_hz * t
    den = 1 - x**2
    safe = np.where(np.abs(den) < 1e-9, 1.0, den)
    w = np.where(np.abs(den) < 1e-9, 0.5 * half_band_hz, half_band_hz * np.sinc(x) / safe)
    edge = (np.sin(0.5 * np.pi * np.clip(t / ramp_s + 0.5, 0, 1)) ** 2 if ramp_s > 0 else (t >= 0).astype(float))
    h = np.convolve(edge - 0.5, w * dt, mode="same") + 0.5 * np.sum(w * dt)
    h /= np.sum(w * dt)
    ts = t * fs_hz
    return lambda k: np.interp(k, ts, h, left=0.0, right=1.0)


@dataclass(frozen=True)
class _EchoStats:
    """What the edge likelihood needs to know of the echo, per frame.

    ``basis`` (2*bands, r): the real directions the echo takes in the stacked band signals
    ``[Re z; Im z]`` (r = 1 for a real detector, whose echo is ``a*cos(psi(t))``; 2 for an IQ
    receiver); per component ``r``: ``noise`` variance (echo off), ``drift`` variance growth per
    sample of the echo's slowly wandering amplitude (laser phase noise, Doppler; its value where
    the echo fades), ``power``.
    """

    basis: np.ndarray
    noise: np.ndarray
    drift: np.ndarray
    power: np.ndarray


def _echo_stats(on: list[tuple[int, int]], off: list[tuple[int, int]], bands, ramp: float, rank: int
                ) -> _EchoStats | None:
    """Estimate :class:`_EchoStats` from the band signals (``bands(a, b)``: shape (B, b - a)) of a
    few stretches ``(a, b)`` where the echo is on / off."""
    def stacked(spans):
        parts = [bands(a, b) for a, b in spans]
        return [np.concatenate([p.real, p.imag]) for p in parts if p is not None]

    on_parts, off_parts = stacked(on), stacked(off)
    if not on_parts or not off_parts:
        return None
    z_on = np.concatenate(on_parts, axis=1)
    _, evecs = np.linalg.eigh(z_on @ z_on.T)
    basis = evecs[:, ::-1][:, :rank]
    noise = np.mean(np.concatenate([basis.T @ p for p in off_parts], axis=1) ** 2, axis=1)
    lag = int(math.ceil(3 * ramp))  # noise decorrelated at this lag
    dif = [basis.T @ p for p in on_parts if p.shape[1] > 2 * lag]
    if not dif:
        return None
    var_lag = np.mean(np.concatenate([d[:, lag:] - d[:, :-lag] for d in dif], axis=1) ** 2, axis=1)
    power = np.mean((basis.T @ z_on) ** 2, axis=1)
    # the wander of cos(psi) is sin(psi)^2 * D per unit time: twice its average where the echo
    # fades through zero, which is where an edge can be mistaken
    drift = 2 * np.maximum(var_lag - 2 * noise, 1e-4 * power) / lag
    return _EchoStats(basis, noise, drift, power)


def _edge_loglik(y: np.ndarray, te: np.ndarray, step, stats: _EchoStats, dec: int, info_spacing: float,
                 rising: bool) -> np.ndarray:
    """Log-likelihood of each candidate edge time ``te`` (samples) given the projected band signals.

    ``y`` (r, n): the band signals in the echo's directions. Model per component:
    ``y[k] = h(k - te) * u[k] + noise`` where ``h`` is the filtered gate edge and ``u`` the echo's
    amplitude, a random walk (a single detector sees ``cos(psi(t))``: it fades through zero with
    the laser's phase noise, and where it does near an edge, the edge is simply not seen there,
    which a step-with-a-slope fit mistakes for an edge elsewhere). ``u`` is integrated out by a
    Kalman filter, one per candidate (vectorised). Samples are taken every ``dec``; each counts
    for ``dec / info_spacing`` of an independent one (the band-limited noise is correlated).
    """
    r, n = y.shape
    ks = np.arange(0, n, dec)
    obs = y[:, ks]
    hs = step(ks[:, None] - te[None, :])  # (samples, candidates): the gate seen through the bands
    if not rising:
        hs = 1.0 - hs
    inflate = max(info_spacing / dec, 1.0)
    ll = np.zeros(te.size)
    for c in range(r):
        m = np.zeros(te.size)
        pvar = np.full(te.size, stats.power[c])
        rv = stats.noise[c] * inflate
        q = stats.drift[c] * dec
        for j, h in enumerate(hs):
            pvar = pvar + q
            sv = h * h * pvar + rv
            v = obs[c, j] - h * m
            ll -= 0.5 * (np.log(sv) + v * v / sv)
            gain = pvar * h / sv
            m = m + gain * v
            pvar = pvar * (1 - gain * h)
    return ll


def _gate_starts(t_start_s: float, width_s: float, period_s: float, t_end_s: float):
    """Start (s) of every echo gate, ``t_start + m*P``, that may touch a record ending at ``t_end_s``."""
    m = math.floor(-t_start_s / period_s) - 1
    while t_start_s + m * period_s - width_s < t_end_s:
        yield t_start_s + m * period_s
        m += 1


class _Bands:
    """Band signals of ``x - off_level`` over sample ranges, computed with a margin (the band
    filters are circular FFT filters: compute wider, keep the middle)."""

    def __init__(self, x: np.ndarray, off_level: float | complex, fs_hz: float, tones_hz: list[float],
                 half_band_hz: float, pad: int) -> None:
        self.x, self.off, self.fs, self.tones, self.half, self.pad = x, off_level, fs_hz, tones_hz, half_band_hz, pad

    def __call__(self, a: int, b: int) -> np.ndarray | None:
        p = self.pad
        if a - p < 0 or b + p > self.x.size or b <= a:
            return None
        return band_signals(self.x[a - p:b + p] - self.off, self.fs, self.tones, self.half)[:, p:-p]


def _stretches(starts, width_s: float, period_s: float, fs_hz: float, hw: int, pad: int, n: int,
               seg: int) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """A few sample ranges where the echo is surely on (up to 12) and surely off (up to 4).

    Spread over the echo: its wander (cos(psi) over microseconds) is averaged over many states
    of psi, not taken from the few it had in one place.
    """
    on: list[tuple[int, int]] = []
    off: list[tuple[int, int]] = []
    for t0 in starts:
        a_on = int(t0 * fs_hz) + hw + pad
        b_on = int((t0 + width_s) * fs_hz) - hw - pad
        a_off = int((t0 + width_s) * fs_hz) + hw + pad
        b_off = int((t0 + period_s) * fs_hz) - hw - pad
        for lo, hi, dst, count, size in ((a_on, b_on, on, 6, 8192), (a_off, b_off, off, 2, 4096)):
            lo, hi = max(lo, pad), min(hi, n - pad)
            size = min(size, hi - lo)
            if size >= seg:
                k = min(count, (hi - lo) // size)
                dst.extend((int(c), int(c) + size) for c in np.linspace(lo, hi - size, k))
    return on[:12], off[:4]


def _centre_posterior(rising: np.ndarray, falling: np.ndarray, grid: np.ndarray, gstep: float,
                      width_sigma: float) -> np.ndarray | None:
    """Log-posterior of the gate centre's offset on ``grid`` (samples), the width integrated out.

    Rising edges sit at ``dc - dW/2``, falling ones at ``dc + dW/2``, with ``dW = 2*j*gstep``
    Gaussian of sigma ``width_sigma`` (samples). None when no offset is possible.
    """
    sw = max(width_sigma, gstep)
    jmax = min(int(math.ceil(4 * sw / (2 * gstep))), grid.size // 4)
    js = np.arange(-jmax, jmax + 1)
    joint = np.full((js.size, grid.size), -np.inf)
    for row, j in enumerate(js):
        i = np.arange(abs(j), grid.size - abs(j))  # both shifted offsets inside the grid
        joint[row, i] = rising[i - j] + falling[i + j] - 0.5 * (2 * j * gstep / sw) ** 2
    post = np.logaddexp.reduce(joint, axis=0)
    return post if np.isfinite(post).any() else None


def refine_edges(x: np.ndarray, fs_hz: float, t_start_s: float, width_s: float, period_s: float,
                 off_level: float | complex, half_window_s: float, tones_hz, width_sigma_s: float,
                 ramp_s: float = 0.0, min_gain: float = 12.5) -> tuple[float, float] | None:
    """Echo gate centre (s, modulo the period) and its sigma from every gate edge in the record.

    Each rising edge near ``t_start + m*P`` and falling edge near ``t_start + width + m*P`` gives
    a log-likelihood over its time (:func:`_edge_loglik`, on the band signals of
    ``x - off_level``). Rising edges sit at ``centre - W/2``, falling ones at ``centre + W/2``;
    the gate width ``W`` is known to ``width_sigma_s`` (measured on the reference channel, or
    only nominal without one: the gate's ramps are not known) and is integrated out, so that a
    centre resting on one kind of edge alone carries the width's doubt. The centre and its sigma
    are the mean and standard deviation of the result. An edge counts only if its best
    candidate beats "no edge in this window" by ``min_gain`` in log-likelihood. A faded edge
    has a flat, wide likelihood, so it neither pulls the centre nor makes the sigma small; edges
    that disagree give a wide or two-humped result, so a large sigma. None when no edge counts.

    Parameters
    ----------
    x : ndarray, shape (N,), detector signal (V), real or complex
    t_start_s, width_s, period_s : the predicted echo gate (s)
    off_level : the signal's mean where the echo is off (V)
    half_window_s : how far (s) around each predicted edge to look
    """
    n = x.size
    t = sorted(float(f) for f in tones_hz)
    half_band = 0.5 * min([b - a for a, b in zip(t, t[1:])] + [t[0]])
    ramp = max(fs_hz / half_band, 2.0)  # the band filter's rise, in samples
    pad = int(2 * ramp)
    bands = _Bands(x, off_level, fs_hz, t, half_band, pad)
    hw = int(math.ceil(half_window_s * fs_hz))
    on, off = _stretches(_gate_starts(t_start_s, width_s, period_s, n / fs_hz), width_s, period_s, fs_hz, hw,
                         pad, n, int(24 * ramp))
    stats = _echo_stats(on, off, bands, ramp, 2 if np.iscomplexobj(x) else 1)
    if stats is None:
        return None
    step = _step_response(half_band, fs_hz, ramp_s)
    dec = max(int(round(ramp / 4)), 1)
    info_spacing = ramp / 0.75  # noise-equivalent spacing of independent samples of a Hann band
    gstep = max(ramp / 16, 0.5)
    grid = np.arange(-hw + ramp, hw - ramp, gstep)  # offsets from the prediction, samples
    if grid.size < 3:
        return None  # a window shorter than the band filters' rise holds no edge to fit
    total = {True: np.zeros(grid.size), False: np.zeros(grid.size)}  # rising, falling
    used = 0
    for t0 in _gate_starts(t_start_s, width_s, period_s, n / fs_hz):
        for rising, t_pred in ((True, t0), (False, t0 + width_s)):
            i0 = int(round(t_pred * fs_hz)) - hw
            z = bands(i0, i0 + 2 * hw)
            if z is None:
                continue
            y = stats.basis.T @ np.concatenate([z.real, z.imag])
            off_pred = t_pred * fs_hz - i0  # the prediction's index in the window
            ll = _edge_loglik(y, off_pred + grid, step, stats, dec, info_spacing, rising)
            # no edge in the window at all: the step far outside it, on either side
            none = _edge_loglik(y, np.array([-10.0 * ramp, 2 * hw + 10.0 * ramp]), step, stats, dec, info_spacing,
                                rising)
            if ll.max() - none.max() >= min_gain:
                total[rising] += ll
                used += 1
    post = _centre_posterior(total[True], total[False], grid, gstep, width_sigma_s * fs_hz) if used else None
    if post is None:
        return None
    w = np.exp(post - post.max())
    w /= w.sum()
    mu = float(w @ grid)
    sd = math.sqrt(float(w @ (grid - mu) ** 2) + (ramp / 16) ** 2 / 12)
    if min(mu - grid[0], grid[-1] - mu) < 3 * sd:
        return None  # the centre is not inside the searched window
    centre = (t_start_s + width_s / 2 + mu / fs_hz) % period_s
    return centre, sd / fs_hz


def _correlation_time(res: np.ndarray) -> float:
    """Integrated autocorrelation time of a residual series (in samples, >= 1): ``1 + 2*sum rho_k``
    over the lags before the autocorrelation first drops below 0.05."""
    r = res - res.mean()
    n = r.size
    if n < 8:
        return 1.0
    f = sfft.rfft(r, 2 * n)
    acf = sfft.irfft(np.abs(f) ** 2)[: n // 4]
    if acf[0] <= 0:
        return 1.0
    rho = acf[1:] / acf[0]
    stop = int(np.argmax(rho < 0.05)) if np.any(rho < 0.05) else rho.size
    return float(max(1.0, 1.0 + 2.0 * np.sum(rho[:stop])))


def _block_fit(e: np.ndarray, bs: float, t_tx: float, width: float, period_s: float) -> tuple[float, float, float, float]:
    """Steps 1-2: the echo gate's delay from the block envelope ``e`` (blocks of ``bs`` s).

    Returns
    -------
    (tau_s, sigma_s, snr, amplitude): the delay modulo the period, its sigma, the envelope
    amplitude over its standard error, and that amplitude
    """
    nb = e.size
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
    sse, (amp, floor), g = fit(tau)
    s2 = sse / max(nb - 3, 1)
    a = np.column_stack([g, np.ones(nb)])
    cov = s2 * np.linalg.pinv(a.T @ a)
    snr = float(amp / math.sqrt(cov[0, 0])) if cov[0, 0] > 0 else math.inf
    h = 0.05 * bs
    dg = (_coverage(starts, bs, t_tx + tau + h, width, period_s)
          - _coverage(starts, bs, t_tx + tau - h, width, period_s)) / (2 * h)
    # the residuals are not independent from block to block: the echo fades with cos(psi(t)) over
    # microseconds, many blocks; the timing information counts independent stretches only
    info = amp**2 * float(dg @ dg) / (s2 * _correlation_time(e - a @ np.array([amp, floor]))) if s2 > 0 else math.inf
    # a rectangle's coverage is not the envelope's exact shape (fading, the gate's ramps): a
    # quarter block is the floor of what the block fit can tell
    sigma = math.hypot(1 / math.sqrt(info) if info > 0 else math.inf, 0.25 * bs)
    return tau, sigma, snr, float(amp)


def _echo_windows(on_start: float, on_len: float, period_s: float, fs_hz: float, n: int) -> list[tuple[int, int]]:
    """Sample ranges ``[a, b)`` (at least 16 samples) of every echo-on stretch in the record."""
    windows: list[tuple[int, int]] = []
    t_end = n / fs_hz
    m = math.floor(-on_start / period_s)
    while on_len > 0 and on_start + m * period_s < t_end:
        a_i = int(math.ceil(max(on_start + m * period_s, 0.0) * fs_hz))
        b_i = int(math.floor(min(on_start + m * period_s + on_len, t_end) * fs_hz))
        if b_i - a_i >= 16:
            windows.append((a_i, b_i))
        m += 1
    return windows


def coarse_gate(x: np.ndarray, fs_hz: float, period_s: float, duty: float, delay_s: float,
                tones_hz, ref: np.ndarray | None = None, block: int = 256, margin_s: float = 10e-9,
                min_snr: float = 8.0, nominal_width_sigma_s: float = 10e-9) -> GateEstimate:
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
    nominal_width_sigma_s : float, doubt on the echo gate's width when there is no reference
        channel and it is taken from ``duty * period`` (s)
    """
    n = x.size
    block = int(min(block, max(16, n // 64)))
    bs = block / fs_hz
    e = envelope(x - np.mean(x), block, 2 * len(tones_hz) + 1)
    levels = ref_levels(ref) if ref is not None else None
    c_tx, width = transmit_centre(ref, fs_hz, period_s, duty, delay_s, levels)
    # the echo gate's width between half maxima: measured on the reference (to about a tenth of
    # a sample), or nominal (the gate's ramps, unknown here, shorten it by their length)
    width_sigma_s = 0.1 / fs_hz if ref is not None else nominal_width_sigma_s
    ramp_s = ramp_duration(ref, fs_hz, levels)
    t_tx = c_tx - width / 2  # transmitted gate start (s), modulo P
    tau, sigma, snr, amp = _block_fit(e, bs, t_tx, width, period_s)
    # a fit whose delay or spread is not finite (a record that is all rail-to-rail toggling, say)
    # places no window: no echo, not an exception
    detected = bool(amp > 0 and snr >= min_snr and math.isfinite(tau) and math.isfinite(sigma))
    if not detected:
        return GateEstimate(tau, sigma, [], snr, detected, width)
    # 3. the edges themselves, on the band envelope about the echo-off level
    gs = _coverage(np.arange(n // 16) * 16 / fs_hz, 16 / fs_hz, t_tx + tau, width, period_s)
    off = x[: gs.size * 16].reshape(gs.size, 16)[gs == 0]
    if off.size:
        off_level = np.mean(off)  # complex for an IQ receiver
        fine = refine_edges(x, fs_hz, t_tx + tau, width, period_s, off_level.item(),
                            half_window_s=max(6 * sigma, 2 * bs), tones_hz=tones_hz,
                            width_sigma_s=width_sigma_s, ramp_s=ramp_s)
        if fine is not None and fine[1] < sigma:
            tau = float((fine[0] - c_tx) % period_s)
            sigma = fine[1]
    cut = margin_s + 3 * sigma
    windows = _echo_windows(t_tx + tau + cut, width - 2 * cut, period_s, fs_hz, n)
    return GateEstimate(tau, sigma, windows, snr, detected, width)


def is_gated(frame: Frame, settings: ChainSettings) -> bool:
    """Whether the ``gate`` stage applies: a pulsed (quasi-CW) frame, with gating not turned off."""
    return frame.pulse is not None and settings.gate != "off"


def gate_frame(x: np.ndarray, frame: Frame, settings: ChainSettings) -> GateEstimate | None:
    """The stage: coarse gating of a pulsed frame (None for CW frames or with gating off).

    Parameters
    ----------
    x : ndarray, shape (N,), the validated detector signal (V)
    frame : its frame, for the gate timing (``frame.pulse``) and the ``pulse_ref`` channel
    """
    if not is_gated(frame, settings):
        return None
    p = frame.pulse
    ref = frame.volts("pulse_ref") if "pulse_ref" in frame.channels else None
    return coarse_gate(x, frame.fs_hz, p.period_s, p.duty, p.delay_s, frame.tones_hz, ref,
                       min_snr=settings.gate_min_snr)

