"""Optical building blocks: laser phase noise, Mach-Zehnder modulator, quasi-CW gate.

Every function works on fractional cycles (float64) so that phases stay exact for long
records at GHz tones; see :mod:`mtcw_core.phase`.
"""

from __future__ import annotations

import math
from functools import reduce

import numpy as np

from ..phase import C, _as_int, frac, tone_cycles


def wiener_phase(n: int, fs_hz: float, linewidth_hz: float, rng: np.random.Generator) -> np.ndarray:
    """Laser phase noise on the sample grid, a Wiener process.

    Increments over ``dt = 1/fs`` have variance ``2*pi*linewidth*dt`` (Lorentzian line of FWHM
    ``linewidth``).

    Returns
    -------
    ndarray, shape (n,), float64, rad
    """
    step = math.sqrt(2 * math.pi * linewidth_hz / fs_hz)
    return np.cumsum(rng.normal(0.0, step, n))


def delayed_phase(
    phase: np.ndarray, pad: int, n: int, delay_s: float, fs_hz: float, linewidth_hz: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Sample a Wiener phase at ``t - delay`` for t on the record grid.

    ``phase[pad + k]`` is the process at sample k of the record. A fractional delay is
    bridged with a Brownian bridge (linear interpolation plus the bridge's own variance
    ``a*(1-a)*2*pi*linewidth/fs``), which keeps the increment statistics exact.

    Returns
    -------
    ndarray, shape (n,), rad
    """
    d = delay_s * fs_hz
    i = math.floor(d)
    a = d - i  # t - delay lies between samples k-i-1 (weight a) and k-i (weight 1-a)
    lo = pad - i
    if lo - 1 < 0:
        raise ValueError("phase-noise padding shorter than the delay")
    p0 = phase[lo:lo + n]
    if a == 0.0:
        return p0
    p1 = phase[lo - 1:lo - 1 + n]
    var = a * (1 - a) * 2 * math.pi * linewidth_hz / fs_hz
    return (1 - a) * p0 + a * p1 + rng.normal(0.0, math.sqrt(var), n)


def common_period(freqs_hz: list[float], fs_hz: float) -> int | None:
    """Samples after which every tone returns to its phase (``fs / gcd(fs, f_i)``), or None."""
    ints = [_as_int(f) for f in [fs_hz, *freqs_hz]]
    if any(v is None for v in ints):
        return None
    g = reduce(math.gcd, ints)
    return ints[0] // g


def mzm_transmission(
    tones_hz: list[float], indices: list[float], offsets_cycles: list[float], fs_hz: float, n: int,
    transfer: str, chirp_hz: list[float] | None = None,
) -> np.ndarray:
    """Field transmission of a push-pull MZM biased at quadrature.

    ``T = cos(pi/4 - 0.5*sum_i m_i*cos(2*pi*cyc_i))`` (exact) or its small-signal form
    ``(1 + 0.5*sum_i m_i*cos(2*pi*cyc_i))/sqrt(2)``, where ``cyc_i = f_i*k/fs + offset_i``
    (+ ``chirp_i*k/fs`` for the modulation's own Doppler shift of a moving target).

    When the drive is periodic (integer tones and rate, no chirp) only one period is
    computed and tiled.

    Returns
    -------
    ndarray, shape (n,), float64
    """
    period = None if chirp_hz else common_period(tones_hz, fs_hz)
    m = n if period is None or period * 4 > n else period
    s = np.zeros(m)
    for i, (f, mi, off) in enumerate(zip(tones_hz, indices, offsets_cycles)):
        cyc = tone_cycles(f, fs_hz, m, off)
        if chirp_hz and chirp_hz[i]:
            cyc = cyc + np.arange(m) * (chirp_hz[i] / fs_hz)
        s += mi * np.cos(2 * np.pi * cyc)
    if transfer == "exact":
        t = np.cos(np.pi / 4 - 0.5 * s)
    else:
        t = (1.0 + 0.5 * s) * (1 / math.sqrt(2))
    if m == n:
        return t
    return np.resize(t, n)


def gate(n: int, fs_hz: float, period_s: float, duty: float, start_s: float, rise_time_s: float) -> np.ndarray:
    """Quasi-CW gate g(t) at unit peak, on for ``duty*period`` from ``start_s`` modulo ``period``.

    Edges are raised-cosine ramps of ``rise_time_s`` (10-90 % is about 0.6 of it).

    Returns
    -------
    ndarray, shape (n,), float64 in [0, 1]
    """
    # position within the period in seconds, from exact cycles of the gate frequency
    u = tone_cycles(1.0 / period_s, fs_hz, n, -start_s / period_s) * period_s
    on = duty * period_s
    if rise_time_s <= 0:
        return (u < on).astype(np.float64)
    r = rise_time_s
    up = np.clip(u / r, 0, 1)
    down = np.clip((on - u) / r, 0, 1)
    ramp = np.minimum(up, down) * (u < on)
    return np.sin(0.5 * np.pi * ramp) ** 2


def carrier_cycles(wavelength_m: float, tau0_s: float, range_m: float) -> float:
    """``f0*tau`` reduced modulo 1 for ``tau = tau0 + 2*L/c`` without losing precision."""
    return frac(frac(C / wavelength_m * tau0_s) + frac(2.0 * range_m / wavelength_m))


def broadband_field(n: int, fs_hz: float, psd_w_per_hz: float, bandwidth_hz: float,
                    rng: np.random.Generator) -> np.ndarray:
    """One polarisation of unpolarised broadband light (ASE, sunlight) as a complex envelope.

    Circular complex Gaussian, two-sided power spectral density ``psd_w_per_hz`` (W/Hz) flat
    over ``|f| < bandwidth_hz/2`` around the carrier. A band at least as wide as the sample rate
    is white on the sample grid (``E|n|^2 = S*fs``: the part of the band the record can hold;
    :func:`beyond_band` supplies what the rest adds at the detector); a narrower band is cut
    from white noise with a brick-wall mask in the frequency domain (``E|n|^2 = S*B``).

    Returns
    -------
    ndarray, shape (n,), complex128, sqrt(W)
    """
    sd = math.sqrt(psd_w_per_hz * fs_hz / 2)
    x = sd * (rng.standard_normal(n) + 1j * rng.standard_normal(n))
    if bandwidth_hz < fs_hz:
        f = np.fft.fftfreq(n, 1 / fs_hz)
        x = np.fft.ifft(np.fft.fft(x) * (np.abs(f) <= bandwidth_hz / 2))
    return x


def beyond_band(lights: list[tuple[float, float]], fs_hz: float) -> tuple[float, float]:
    """What broadband light wider than the sample rate adds to ``|field|^2`` beyond its sampled part.

    A field sampled at ``fs`` holds ``fs`` of a band ``B >= fs``; its intensity then has mean
    ``S*fs`` and a white beat spectrum ``S^2*fs`` (two-sided) per polarisation where the light
    really has ``S*B`` and ``S^2*(B - |f|) ~ S^2*B`` (``|f| <= fs/2 << B``; relative error
    ``fs/(2B)``). The missing beat of a band against itself and of two bands against each other
    (``2*S_a*S_b*min(B_a, B_b)``) is a sum of ~``B/fs`` independent products per sample, hence
    Gaussian. Both polarisations.

    Parameters
    ----------
    lights : list of (psd_w_per_hz, bandwidth_hz), per polarisation
    fs_hz : sample rate (Hz)

    Returns
    -------
    (mean_w, variance_w2) : the added mean intensity (W) and the per-sample variance (W^2)
    """
    mean, psd = 0.0, 0.0
    for a, (sa, ba) in enumerate(lights):
        mean += sa * max(ba - fs_hz, 0.0)
        psd += sa * sa * max(ba - fs_hz, 0.0)
        for sb, bb in lights[a + 1:]:
            psd += 2 * sa * sb * max(min(ba, bb) - fs_hz, 0.0)
    return 2 * mean, 2 * psd * fs_hz
