"""Tone extraction: exact DFTs at known frequencies and a joint least-squares line fit.

The DFT at K arbitrary frequencies of an N-sample record is factorised: with ``k = a*M + b``,
``exp(-j*w*k) = exp(-j*w*a*M) * exp(-j*w*b)``, so the record reshaped to (A, M) times an
(M, 2K) real table is one BLAS product of N*2K multiply-adds plus tables of (A + M)*K
exponentials. This is what an FFT cannot do cheaply (frequencies off the bin grid) and what
``scipy`` does not offer for a handful of frequencies (``scipy.signal.czt`` costs a full FFT
of the record per call); hence written here.

All amplitudes are referred to the record's centre, ``t_c = (N-1)/(2*fs)``, which makes the
Gram matrix of cosines and sines block-diagonal and the phases insensitive to small
frequency errors.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import linalg
from scipy.special import diric


def _tables(n: int, freqs_hz: np.ndarray, fs_hz: float, m: int):
    a_count = -(-n // m)
    c = (n - 1) / 2.0
    r = freqs_hz / fs_hz  # cycles per sample, float64
    b = np.arange(m, dtype=np.float64) - c
    cyc_b = np.mod(np.outer(b, r), 1.0)  # (M, K)
    cyc_a = np.mod(np.outer(np.arange(a_count, dtype=np.float64), np.mod(r * m, 1.0)), 1.0)  # (A, K)
    return a_count, cyc_a, cyc_b


def exact_dft(x: np.ndarray, freqs_hz, fs_hz: float) -> np.ndarray:
    """``sum_k x[k] * exp(-j*2*pi*f*(k - (N-1)/2)/fs)`` for each f.

    Parameters
    ----------
    x : ndarray, shape (N,), float64 or complex128
    freqs_hz : array_like, shape (K,), Hz (any sign)
    fs_hz : float

    Returns
    -------
    ndarray, shape (K,), complex128 (not normalised)
    """
    freqs = np.atleast_1d(np.asarray(freqs_hz, dtype=np.float64))
    n = x.size
    m = int(2 ** max(6, round(math.log2(math.sqrt(n))) + 1))
    a_count, cyc_a, cyc_b = _tables(n, freqs, fs_hz, m)
    pad = a_count * m - n
    xr = np.pad(x, (0, pad)).reshape(a_count, m) if pad else x.reshape(a_count, m)
    eb = np.exp(-2j * np.pi * cyc_b)  # (M, K)
    if np.iscomplexobj(xr):
        y = xr @ eb
    else:
        tab = np.concatenate([eb.real, eb.imag], axis=1)  # (M, 2K) real
        yy = xr @ tab
        k = freqs.size
        y = yy[:, :k] + 1j * yy[:, k:]
    return np.sum(y * np.exp(-2j * np.pi * cyc_a), axis=0)


def _dirichlet(w: np.ndarray, n: int) -> np.ndarray:
    """``sum_{k'} exp(j*w*k')`` over the centred index (real), = N * diric(w, N)."""
    return n * diric(np.asarray(w, dtype=np.float64), n)


def fit_lines(x: np.ndarray, freqs_hz, fs_hz: float, dft: np.ndarray | None = None) -> np.ndarray:
    """Joint least-squares complex amplitudes of lines at known frequencies.

    Model (real x): ``x[k] = d + sum_l Re(c_l * exp(j*2*pi*f_l*(k - (N-1)/2)/fs))`` with a DC term
    ``d``; (complex x): ``x[k] = sum_l c_l * exp(...)`` with signed f_l. Leakage between the
    modelled lines is removed exactly; in white noise this is the maximum-likelihood estimate.

    Parameters
    ----------
    x : ndarray, shape (N,)
    freqs_hz : array_like, shape (K,), Hz (positive for real x)
    dft : ndarray, shape (K,), optional
        ``exact_dft(x, freqs_hz)`` if already computed.

    Returns
    -------
    ndarray, shape (K,), complex128, amplitude (V) and phase (rad) at the record's centre
    """
    f = np.atleast_1d(np.asarray(freqs_hz, dtype=np.float64))
    n = x.size
    w = 2 * np.pi * f / fs_hz
    if dft is None:
        dft = exact_dft(x, f, fs_hz)
    if np.iscomplexobj(x):
        g = _dirichlet(w[:, None] - w[None, :], n)
        return linalg.solve(g, dft, assume_a="sym")
    # cosine block with a DC column, sine block without
    wc = np.concatenate([[0.0], w])
    gc = 0.5 * (_dirichlet(wc[:, None] - wc[None, :], n) + _dirichlet(wc[:, None] + wc[None, :], n))
    gs = 0.5 * (_dirichlet(w[:, None] - w[None, :], n) - _dirichlet(w[:, None] + w[None, :], n))
    pc = np.concatenate([[float(np.sum(x))], dft.real])
    ps = -dft.imag
    alpha = linalg.solve(gc, pc, assume_a="sym")[1:]
    beta = linalg.solve(gs, ps, assume_a="sym")
    return alpha - 1j * beta


def fit_lines_segments(x: np.ndarray, starts: np.ndarray, length: int, freqs_hz, fs_hz: float) -> np.ndarray:
    """:func:`fit_lines` on many equal-length segments at once, each referred to its own centre.

    One (S, L) x (L, 2K) product gives every segment's DFTs (the phasor table is the same for
    all segments once each is referred to its centre); the Gram matrices are shared.

    Parameters
    ----------
    x : ndarray, shape (N,), float64 or complex128
    starts : ndarray of int, shape (S,), first sample of each segment
    length : int, samples per segment
    freqs_hz : array_like, shape (K,)

    Returns
    -------
    ndarray, shape (S, K), complex128
    """
    f = np.atleast_1d(np.asarray(freqs_hz, dtype=np.float64))
    starts = np.asarray(starts, dtype=np.int64)
    idx = starts[:, None] + np.arange(length)[None, :]
    seg = x[idx]  # (S, L)
    c = (length - 1) / 2.0
    cyc = np.mod(np.outer(np.arange(length, dtype=np.float64) - c, f / fs_hz), 1.0)
    eb = np.exp(-2j * np.pi * cyc)  # (L, K)
    w = 2 * np.pi * f / fs_hz
    if np.iscomplexobj(seg):
        dft = seg @ eb
        g = _dirichlet(w[:, None] - w[None, :], length)
        return linalg.solve(g, dft.T, assume_a="sym").T
    dft = seg @ eb.real + 1j * (seg @ eb.imag)
    wc = np.concatenate([[0.0], w])
    gc = 0.5 * (_dirichlet(wc[:, None] - wc[None, :], length) + _dirichlet(wc[:, None] + wc[None, :], length))
    gs = 0.5 * (_dirichlet(w[:, None] - w[None, :], length) - _dirichlet(w[:, None] + w[None, :], length))
    pc = np.concatenate([seg.sum(axis=1)[:, None], dft.real], axis=1)  # (S, K+1)
    alpha = linalg.solve(gc, pc.T, assume_a="sym").T[:, 1:]
    beta = linalg.solve(gs, (-dft.imag).T, assume_a="sym").T
    return alpha - 1j * beta
