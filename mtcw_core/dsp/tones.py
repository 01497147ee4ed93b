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
from functools import lru_cache

import numpy as np
from scipy import linalg


def _block(n: int) -> int:
    """Block length M of the factorisation: about sqrt(2n), a power of two (the (A, M) x (M, 2K)
    product is then close to square, which BLAS does best)."""
    return int(2 ** max(6, round(math.log2(math.sqrt(n))) + 1))


def phasors(offset: float, count: int, step: np.ndarray) -> np.ndarray:
    """``exp(-2j*pi*((offset + i)*step mod 1))`` for ``i < count``, shape (count, K).

    Built as the outer product of two tables of about ``sqrt(count)`` rows each (``i = i1*L + i2``),
    so it costs ``2*sqrt(count)*K`` exponentials and ``count*K`` complex products instead of
    ``count*K`` exponentials; every factor's cycles are reduced modulo 1 in float64 first.

    Parameters
    ----------
    offset : float, the first index (may be a half-integer: the record's centre)
    step : ndarray, shape (K,), cycles per index
    """
    step = np.asarray(step, dtype=np.float64)
    if count <= 64:
        return np.exp(-2j * np.pi * np.mod(np.outer(offset + np.arange(count, dtype=np.float64), step), 1.0))
    width = int(math.ceil(math.sqrt(count)))
    rows = -(-count // width)
    coarse = np.exp(-2j * np.pi * np.mod(np.outer(offset + width * np.arange(rows, dtype=np.float64), step), 1.0))
    fine = np.exp(-2j * np.pi * np.mod(np.outer(np.arange(width, dtype=np.float64), step), 1.0))
    return (coarse[:, None, :] * fine[None, :, :]).reshape(rows * width, step.size)[:count]


def exact_dft_parts(parts: np.ndarray, freqs_hz, fs_hz: float) -> np.ndarray:
    """:func:`exact_dft` of every row of ``parts``, each referred to its own centre.

    One batched product: the phasor tables depend on the frequencies and the row length only,
    so they are built once for all rows. The last ``L mod M`` samples of each row (those that do
    not fill a block) are summed against their own small table; nothing is copied or padded.

    Parameters
    ----------
    parts : ndarray, shape (S, L), float64 or complex128
    freqs_hz : array_like, shape (K,), Hz (any sign)
    fs_hz : float

    Returns
    -------
    ndarray, shape (S, K), complex128: ``sum_k parts[s, k] * exp(-j*2*pi*f*(k - (L-1)/2)/fs)``
    """
    freqs = np.atleast_1d(np.asarray(freqs_hz, dtype=np.float64))
    parts = np.atleast_2d(parts)
    s_count, n = parts.shape
    m = min(_block(n), n)
    a_count = n // m
    c = (n - 1) / 2.0
    r = freqs / fs_hz  # cycles per sample, float64
    eb, ea, et = _tables(n, r.tobytes())
    body = parts[:, :a_count * m].reshape(s_count, a_count, m)  # a view: rows keep their stride
    if np.iscomplexobj(parts):
        y = body @ eb  # (S, A, K)
    else:
        # the complex table's own memory read as real (M, 2K), cosine and sine columns interleaved:
        # the product's rows are then the complex sums themselves (no table copy, no recombining)
        y = (body @ eb.view(np.float64)).view(np.complex128)  # (S, A, K)
    out = np.einsum("sak,ak->sk", y, ea)
    if et is not None:
        out += parts[:, a_count * m:] @ et
    return out


@lru_cache(maxsize=4)
def _tables(n: int, r_bytes: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The phasor tables of :func:`exact_dft_parts` for rows of ``n`` samples at the frequencies
    ``r`` (cycles per sample, float64, as bytes): (M, K), (A, K) and the tail's (n mod M, K) or
    None. Cached (read-only): a stream's static lines, and the Doppler refinement's two
    transforms of one line set, ask for the same tables frame after frame.

    Sample ``a*M + b`` is ``exp(-j*w*a*M) * exp(-j*w*(b - c))``, each factor's cycles reduced
    modulo 1 in float64 (``c = (n - 1)/2``, the centre).
    """
    r = np.frombuffer(r_bytes, dtype=np.float64)
    m = min(_block(n), n)
    a_count = n // m
    c = (n - 1) / 2.0
    eb = phasors(-c, m, r)  # (M, K)
    ea = phasors(0.0, a_count, np.mod(r * m, 1.0))  # (A, K)
    tail = n - a_count * m
    et = phasors(a_count * m - c, tail, r) if tail else None
    for t in (eb, ea, et):
        if t is not None:
            t.setflags(write=False)
    return eb, ea, et


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
    return exact_dft_parts(np.asarray(x)[None, :], freqs_hz, fs_hz)[0]


def _dirichlet(w: np.ndarray, n: int) -> np.ndarray:
    """``sum_{k'} exp(j*w*k')`` over the centred index (real), = N * diric(w, N).

    ``scipy.special.diric``'s formula and its float64 threshold (``sin(w/2)`` below 1e-7 takes
    the limit ``(-1)^(round(w/2pi)*(N-1))``), without its masking machinery, which costs ~0.15 ms
    per call on the few-by-few Gram matrices here -- more than the matrices' solve.
    """
    half = np.asarray(w, dtype=np.float64) / 2
    denom = np.sin(half)
    small = np.abs(denom) < 1e-7
    out = np.sin(n * half) / np.where(small, 1.0, denom)  # no division by ~0 (no errstate: it costs more)
    return np.where(small, n * (-1.0) ** (np.round(half / np.pi) * (n - 1)), out)


def _gram_real(w: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The cosine block with a DC column (shape (K+1, K+1)) and the sine block (K, K) of the real
    line fit: ``(D(a - b) +- D(a + b))/2`` over the centred index, the sine block's kernels being
    the cosine block's without the DC row and column (two kernel evaluations, not four)."""
    wc = np.concatenate([[0.0], w])
    dm = _dirichlet(wc[:, None] - wc[None, :], n)
    dp = _dirichlet(wc[:, None] + wc[None, :], n)
    return 0.5 * (dm + dp), 0.5 * (dm[1:, 1:] - dp[1:, 1:])


def fit_lines(x: np.ndarray, freqs_hz, fs_hz: float, dft: np.ndarray | None = None,
              total: float | None = None) -> np.ndarray:
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
    total : float, optional
        ``np.sum(x)`` (V) if already computed (real x: the DC column's projection).

    Returns
    -------
    ndarray, shape (K,), complex128, amplitude (V) and phase (rad) at the record's centre
    """
    f = np.atleast_1d(np.asarray(freqs_hz, dtype=np.float64))
    if dft is None:
        dft = exact_dft(x, f, fs_hz)
    iq = np.iscomplexobj(x)
    total = 0.0 if iq else float(np.sum(x) if total is None else total)
    return solve_lines(dft, f, fs_hz, x.size, total, iq)[1]


def solve_lines(dft: np.ndarray, freqs_hz: np.ndarray, fs_hz: float, n: int, total: float, iq: bool
                ) -> tuple[float, np.ndarray]:
    """The least-squares lines of :func:`fit_lines` from the record's exact DFT at their frequencies:
    the energy (V^2) they explain and their complex amplitudes (V, phase at the record's centre).

    Parameters
    ----------
    dft : ndarray, shape (K,), complex: :func:`exact_dft` of the record at ``freqs_hz``
    freqs_hz : ndarray, shape (K,), Hz
    n : the record's length
    total : the record's sum (V; the DC column of a real record's fit, unused for IQ)
    iq : a complex record (no DC column, signed frequencies)
    """
    w = 2 * np.pi * np.asarray(freqs_hz, dtype=np.float64) / fs_hz
    if iq:
        c = linalg.solve(_dirichlet(w[:, None] - w[None, :], n), dft, assume_a="sym")
        return float(np.real(np.vdot(dft, c))), c
    # cosine block with a DC column, sine block without
    gc, gs = _gram_real(w, n)
    pc = np.concatenate([[total], dft.real])
    ps = -dft.imag
    alpha = linalg.solve(gc, pc, assume_a="sym")
    beta = linalg.solve(gs, ps, assume_a="sym")
    return float(pc @ alpha + ps @ beta), alpha[1:] - 1j * beta


def centre_turn(parts: int, length: int, n: int, freqs_hz, fs_hz: float) -> np.ndarray:
    """``exp(-2j*pi*f*(s*L + (L-1)/2 - (N-1)/2)/fs)``: what turns a phase about part ``s``'s centre
    (``parts`` consecutive parts of ``length`` samples) into one about the record's, cycles from
    the integer sample offsets reduced modulo 1 in float64; shape (parts, K)."""
    r = np.atleast_1d(np.asarray(freqs_hz, dtype=np.float64)) / fs_hz
    offs = np.arange(parts, dtype=np.float64) * length + (length - 1) / 2.0 - (n - 1) / 2.0
    return np.exp(-2j * np.pi * np.mod(np.outer(offs, r), 1.0))


def exact_dft_tiled(x: np.ndarray, parts: int, freqs_hz, fs_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`exact_dft` of the whole record and of its ``parts`` consecutive parts of
    ``L = N // parts`` samples (each about its own centre), in one pass.

    The whole record's sum is its parts' sums turned by their centres' phases,
    ``X(f) = sum_s X_s(f) exp(-j*2*pi*f*(s*L + (L-1)/2 - (N-1)/2)/fs)`` (cycles reduced modulo 1
    in float64), with the ``N mod parts`` samples left over added the same way: a caller that
    needs both (the whole-record fit and the segments' fits of one set of lines) reads the
    record once.

    Parameters
    ----------
    x : ndarray, shape (N,), float64 or complex128
    parts : int, 1 <= parts <= N
    freqs_hz : array_like, shape (K,), Hz (any sign)

    Returns
    -------
    whole : ndarray, shape (K,), complex128, as :func:`exact_dft` (within rounding)
    each : ndarray, shape (parts, K), complex128, as :func:`exact_dft_parts` of the parts
    """
    f = np.atleast_1d(np.asarray(freqs_hz, dtype=np.float64))
    n = x.size
    length = n // parts
    r = f / fs_hz
    c = (n - 1) / 2.0
    each = exact_dft_parts(x[:parts * length].reshape(parts, length), f, fs_hz)
    whole = np.sum(each * centre_turn(parts, length, n, f, fs_hz), axis=0)
    rest = n - parts * length
    if rest:
        off = parts * length + (rest - 1) / 2.0 - c
        whole = whole + exact_dft(x[parts * length:], f, fs_hz) * np.exp(-2j * np.pi * np.mod(r * off, 1.0))
    return whole, each


def fit_lines_segments(x: np.ndarray, starts: np.ndarray, length: int, freqs_hz, fs_hz: float,
                       dft: np.ndarray | None = None) -> np.ndarray:
    """:func:`fit_lines` on many equal-length segments at once, each referred to its own centre.

    :func:`exact_dft_parts` gives every segment's DFTs (the phasor tables are the same for all
    segments once each is referred to its centre); the Gram matrices are shared.

    Parameters
    ----------
    x : ndarray, shape (N,), float64 or complex128
    starts : ndarray of int, shape (S,), first sample of each segment
    length : int, samples per segment
    freqs_hz : array_like, shape (K,)
    dft : ndarray, shape (S, K), optional: the segments' DFTs if already computed
        (:func:`exact_dft_tiled`)

    Returns
    -------
    ndarray, shape (S, K), complex128
    """
    f = np.atleast_1d(np.asarray(freqs_hz, dtype=np.float64))
    starts = np.asarray(starts, dtype=np.int64)
    if starts.size and np.all(starts == np.arange(starts.size) * length) and starts.size * length <= x.size:
        seg = x[:starts.size * length].reshape(starts.size, length)  # consecutive segments: a view
    else:
        seg = x[starts[:, None] + np.arange(length)[None, :]]  # (S, L)
    if dft is None:
        dft = exact_dft_parts(seg, f, fs_hz)  # (S, K), each segment about its own centre
    w = 2 * np.pi * f / fs_hz
    if np.iscomplexobj(seg):
        g = _dirichlet(w[:, None] - w[None, :], length)
        return linalg.solve(g, dft.T, assume_a="sym").T
    gc, gs = _gram_real(w, length)
    pc = np.concatenate([seg.sum(axis=1)[:, None], dft.real], axis=1)  # (S, K+1)
    alpha = linalg.solve(gc, pc.T, assume_a="sym").T[:, 1:]
    beta = linalg.solve(gs, (-dft.imag).T, assume_a="sym").T
    return alpha - 1j * beta
