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
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy import linalg

from .spectrum import cached_window


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


#: :func:`_times_table` multiplies a long record's rows by its table this many bytes of rows at a
#: time. OpenBLAS packs the whole left operand before a GEMM with few columns; on a record fresh
#: from memory that pass costs as much as the product. Rows that fit in L2 are packed from cache:
#: on a 1e6-sample record with 625-2048-sample rows and 2-22 columns the product took 0.4-1.2 ms
#: instead of 1.0-2.0 ms (2-core EPYC, 1 MiB L2 per core; 64-512 KiB all helped, 256 KiB the most).
ROW_CHUNK_BYTES = 256 << 10
#: ... at most this many multiply-adds per product (rows x row length x the table's real
#: columns), and at most :data:`PRODUCT_MAX_COLUMNS` real columns of the table at a time. Above
#: about 1e6 multiply-adds OpenBLAS (0.3.31, Haswell kernels on the 2-core EPYC) leaves the path it
#: takes for small products, and a product with 32-60 real columns ran 1.3-1.5x slower; wider
#: tables, whose rows' cap would leave a few rows per product, re-read the whole table for each.
#: Measured on a 1e6-sample record (``python`` timing of :func:`_times_table`, median of 9, old and
#: new alternated), 312- and 2048-sample rows: 44 columns 2.8 / 3.4 -> 2.0 / 2.1 ms (the phase
#: advance's moments in ``balanced``), 80 columns 4.4 / 5.5 -> 3.7 / 3.5 ms, 120 columns 6.2 / 7.7
#: -> 5.5 / 5.1 ms (44-47 GFLOPS, near the core's peak); 24 columns and fewer within 10 % as before
PRODUCT_MAX_MACS = 800_000
#: (see :data:`PRODUCT_MAX_MACS`)
PRODUCT_MAX_COLUMNS = 32


def _times_table(a: np.ndarray, table: np.ndarray) -> np.ndarray:
    """``a @ table`` for a complex ``table`` (M, K), ``a`` of shape (..., M), real or complex.

    A real ``a`` meets the table's own memory read as real (M, 2K), cosine and sine columns
    interleaved: the product's rows are then the complex sums themselves (no table copy, no
    complex copy of ``a``, no recombining). One line (K = 1) on a single matrix of rows (2-D
    ``a``, or 3-D with one batch) takes two matrix-vector products instead: the same sums (to
    rounding), at memory speed. A complex ``a`` is read as real too, (..., 2M), against the real
    form of the table (:func:`_real_pair`): OpenBLAS's complex GEMM with 3-12 columns ran at
    half the speed of this real one on a 1e6-sample IQ record (3 lines 2.0 -> 0.9 ms, 7 lines
    2.9 -> 1.8 ms, 12 lines 3.4 -> 2.4 ms, the table's build included); one line keeps the
    complex product (as fast). Long products run in pieces (:func:`_chunked`)."""
    if not np.iscomplexobj(a):
        real = table.view(np.float64)
        if real.shape[1] == 2 and (a.ndim == 2 or (a.ndim == 3 and a.shape[0] == 1)):
            # one line, one matrix of rows: a matrix-vector product per column (OpenBLAS's GEMV reads
            # a 1e6-sample record in ~0.3 ms; its GEMM with two columns took ~1 ms in the chain)
            rows = a if a.ndim == 2 else a[0]
            out = np.empty((rows.shape[0], 2))
            out[:, 0] = rows @ np.ascontiguousarray(real[:, 0])
            out[:, 1] = rows @ np.ascontiguousarray(real[:, 1])
            return out.view(np.complex128).reshape(a.shape[:-1] + (1,))
        return _chunked(a, real).view(np.complex128)
    if table.shape[1] > 1 and a.dtype == np.complex128 and a.strides[-1] == a.itemsize:
        return _chunked(a.view(np.float64), _real_pair(table)).view(np.complex128)
    return _chunked(a, table)


def _real_pair(table: np.ndarray) -> np.ndarray:
    """The real form (2M, 2K) of a complex table (M, K): a complex row read as real, ``(re_0, im_0,
    re_1, ...)``, times it gives the complex product read as real, ``(Re_0, Im_0, Re_1, ...)``
    (``Re = re*tr - im*ti``, ``Im = re*ti + im*tr``)."""
    m, k = table.shape
    out = np.empty((m, 2, k, 2))
    out[:, 0, :, 0] = out[:, 1, :, 1] = table.real
    out[:, 0, :, 1] = table.imag
    out[:, 1, :, 0] = -table.imag
    return out.reshape(2 * m, 2 * k)


def _chunked(a: np.ndarray, table: np.ndarray) -> np.ndarray:
    """``a @ table`` (``a`` (..., M), ``table`` (M, C)) in pieces: :data:`ROW_CHUNK_BYTES` of
    ``a``'s rows per product and, for a real table, at most :data:`PRODUCT_MAX_MACS` multiply-adds
    and :data:`PRODUCT_MAX_COLUMNS` columns (every row's sum is the same dot product, so the result
    is the product's, to rounding)."""
    real = not np.iscomplexobj(table)
    max_macs, group = (PRODUCT_MAX_MACS, PRODUCT_MAX_COLUMNS) if real else (math.inf, table.shape[1])
    if a.size * a.itemsize <= 2 * ROW_CHUNK_BYTES and a.size * table.shape[1] <= max_macs:
        return a @ table
    out = np.empty(a.shape[:-1] + (table.shape[1],), dtype=np.result_type(a, table))
    groups = [(c, table if table.shape[1] <= group else np.ascontiguousarray(table[:, c:c + group]))
              for c in range(0, table.shape[1], group)]
    width = groups[0][1].shape[1]
    step = int(max(1, min(ROW_CHUNK_BYTES // (a.shape[-1] * a.itemsize), max_macs // (a.shape[-1] * width))))
    for rows, dest in zip(a.reshape((-1,) + a.shape[-2:]), out.reshape((-1,) + out.shape[-2:])):
        for i in range(0, rows.shape[0], step):
            for c, cols in groups:  # every group on these rows while they are in cache
                if len(groups) == 1:
                    np.matmul(rows[i:i + step], cols, out=dest[i:i + step])
                else:
                    dest[i:i + step, c:c + cols.shape[1]] = rows[i:i + step] @ cols
    return out


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
    y = _times_table(body, eb)  # (S, A, K)
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


def mean_leak(x: np.ndarray, freqs_hz, fs_hz: float) -> np.ndarray:
    """The record mean's share of :func:`exact_dft` at each frequency: ``mean(x) * D_N(2*pi*f/fs)``
    (the exact DFT of a constant, ``D_N`` the centred Dirichlet kernel); subtracted, a line's
    amplitude is read as from the mean-free record. Near 0 Hz on one photodiode the LO's DC
    leaks through the rectangular window as much as a line's own size.

    Parameters
    ----------
    x : ndarray, shape (N,), float64 or complex128
    freqs_hz : array_like, shape (K,), Hz

    Returns
    -------
    ndarray, shape (K,), complex128 (real for a real record)
    """
    f = np.atleast_1d(np.asarray(freqs_hz, dtype=np.float64))
    return np.mean(x) * _dirichlet(2 * np.pi * f / fs_hz, x.size)


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


#: :class:`PartDFTs` cuts the record into blocks of this fraction of its shortest part: a Kaiser(8)
#: window and a line's small frequency offset are then, across a block, a polynomial of degree
#: :data:`PART_DEGREE` in the block's index to within ~1e-8 of the strongest line's DFT (measured
#: against the direct sums: ``test_tones``; on a moving-target frame every line within 4e-8 of its
#: own; degree 3 on blocks 2.5x longer is as close and ~10 % slower in the chain)
PART_BLOCK_FRACTION = 1 / 100
#: ... and at least this long: below it (records under ~4e5 samples at 16 parts) a part count's
#: fixed cost (~0.5 ms) exceeds what the shared pass saves, and the parts are read one by one, exactly
PART_MIN_BLOCK = 256
#: the degree of that polynomial
PART_DEGREE = 2
#: a line is read from block moments taken at a frequency at most this far off (radians of phase
#: across half a block; the Taylor term left out, ``theta^3/6``, is then below ~2e-8 of the line)
PART_OFFSET_RAD = 0.005


@dataclass(frozen=True)
class _PartGeometry:
    """Where the blocks of :class:`PartDFTs` fall in ``parts`` consecutive parts of ``length``
    samples (blocks of ``m`` from the record's start; cached per record shape, read-only).

    Part ``s`` starts at ``s*length``; its first whole block is ``first[s]``, ``head[s]`` samples
    into it; ``count`` whole blocks follow (the same number in every part); the ``head[s]`` samples
    before and the ``length - head[s] - count*m`` after them are read exactly."""

    first: np.ndarray  # (S,) int, the first whole block of each part
    head: np.ndarray  # (S,) int, samples before it
    count: int  # whole blocks per part
    poly: np.ndarray  # (S, count, deg+1): the window across each block, increasing powers of t
    head_w: np.ndarray  # (S, m): the window on each part's first m samples where they are its head, else 0
    tail_w: np.ndarray  # (S, 2m): the window on each part's last 2m samples where they are its tail, else 0
    head_in: np.ndarray  # (S, m): 1 on the head samples, 0 beyond
    tail_in: np.ndarray  # (S, 2m): 1 on the tail samples, 0 before


@lru_cache(maxsize=16)
def _part_geometry(window: tuple, n: int, parts: int, m: int) -> _PartGeometry:
    """:class:`_PartGeometry` of ``parts`` parts of an ``n``-sample record in blocks of ``m``; the
    window's polynomial on each block by least squares in ``t = (b - (m-1)/2)/(m/2)``."""
    length = n // parts
    w = cached_window(window, length)
    start = np.arange(parts) * length
    first = -(-start // m)
    head = first * m - start
    count = (length - (m - 1)) // m
    t = (np.arange(m) - (m - 1) / 2.0) / (m / 2.0)
    fit = np.linalg.pinv(np.vander(t, PART_DEGREE + 1, increasing=True))  # (deg+1, m)
    inner = head[:, None, None] + np.arange(count)[None, :, None] * m + np.arange(m)[None, None, :]
    poly = w[inner] @ fit.T  # (S, count, deg+1)
    head_in = (np.arange(m)[None, :] < head[:, None]).astype(np.float64)
    tail_in = (np.arange(2 * m)[None, :] >= (head + count * m - (length - 2 * m))[:, None]).astype(np.float64)
    head_w = head_in * w[None, :m]
    tail_w = tail_in * w[None, length - 2 * m:]
    for a in (first, head, poly, head_w, tail_w, head_in, tail_in):
        a.setflags(write=False)
    return _PartGeometry(first, head, count, poly, head_w, tail_w, head_in, tail_in)


class PartDFTs:
    """The windowed, mean-removed DFTs of a record's consecutive parts at a few lines, for any
    number of parts, from one pass over the record.

    ``z[s, k] = sum_j (x[s*L + j] - mean_s) * w[j] * exp(-2j*pi*f_k*(j - (L-1)/2)/fs)``, ``L = N // S``
    (the Doppler refinement's parts: :func:`mtcw_core.dsp.doppler.phase_advance`). The record is
    cut into blocks of ``M`` samples (:data:`PART_BLOCK_FRACTION` of the shortest part); one
    product gives every block's moments ``Y_n[a, k] = sum_b x[a*M + b] * t_b^n *
    exp(-2j*pi*r_k*(b - (M-1)/2))`` (``t_b`` the scaled index within the block, ``n`` up to
    :data:`PART_DEGREE`) and its sum. The window across a block, times the turn of a frequency a
    little off the moments' ``r_k`` (Taylor series), is a polynomial in ``t_b``, so a part's DFT
    is a combination of its whole blocks' moments, each turned by its centre's phase, plus the
    few samples at its ends read exactly (:class:`_PartGeometry`). The refinement's first step
    (8-32 parts), its quarters at the refined Doppler and the common phase's 6-16 parts then cost
    one pass over the record where each used to cost one and a windowed copy. Lines further from
    every frequency read than :data:`PART_OFFSET_RAD` take a pass of their own; a record too short
    for blocks of :data:`PART_MIN_BLOCK` is computed part by part, exactly.

    Parameters
    ----------
    x : ndarray, shape (N,), float64 or complex128, V
    fs_hz : float
    beta : float, the Kaiser window's beta
    max_parts : the most parts asked for (sets the block length)
    """

    def __init__(self, x: np.ndarray, fs_hz: float, beta: float, max_parts: int = 32) -> None:
        self.x, self.fs, self.window = x, fs_hz, ("kaiser", beta)
        m = int(x.size // max_parts * PART_BLOCK_FRACTION)
        self.m = m if m >= PART_MIN_BLOCK else 0
        # per pass: its lines (cycles per sample), every block's moments (K, A, deg+1) and the
        # same moments of a constant 1 (K, deg+1)
        self._passes: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._sums: np.ndarray | None = None  # each block's sum, shape (A,)

    def __call__(self, parts: int, freqs_hz) -> np.ndarray:
        """The parts' DFTs, shape (parts, K), complex128 (each about its own centre)."""
        f = np.atleast_1d(np.asarray(freqs_hz, dtype=np.float64))
        n = self.x.size
        length = n // parts
        if not self.m or length < 4 * self.m:
            return self._exact(parts, length, f)
        r = f / self.fs
        m, deg, c = self.m, PART_DEGREE, (length - 1) / 2.0
        geo = _part_geometry(self.window, n, parts, m)
        where, col = self._locate(r)  # (a pass over the record for lines not yet read)
        blocks = geo.first[:, None] + np.arange(geo.count)[None, :]  # (S, count)
        # each whole block's centre about its part's, head[s] + i*M + (M-1)/2 - c samples, as a
        # turn: the part's factor (K, S) times the block's (K, count), cycles reduced modulo 1
        turn = (np.exp(-2j * np.pi * np.mod(np.outer(r, geo.head + (m - 1) / 2.0 - c), 1.0))[:, :, None]
                * phasors(0.0, geo.count, r * m).T[:, None, :])  # (K, S, count)
        z = np.empty((parts, r.size), dtype=np.complex128)
        wdft = np.empty((parts, r.size), dtype=np.complex128)
        for p, (rp, mom, const) in enumerate(self._passes):
            ks = np.flatnonzero(where == p)
            if not ks.size:
                continue
            cs = col[ks]
            theta = 2 * np.pi * (r[ks] - rp[cs]) * m / 2  # each line's offset, phase across half a block
            shift = np.zeros((ks.size, deg + 1, deg + 1), dtype=np.complex128)
            for i in range(deg + 1):
                for j in range(deg + 1 - i):
                    shift[:, i, i + j] = (-1j * theta) ** j / math.factorial(j)
            # the window's polynomial times each line's offset, truncated, turned: (K, S, count, deg+1)
            g = np.matmul(geo.poly.reshape(1, -1, deg + 1), shift).reshape(ks.size, parts, geo.count, deg + 1)
            g *= turn[ks, :, :, None]
            y = mom[:, blocks] if np.array_equal(cs, np.arange(rp.size)) else mom[cs[:, None, None], blocks[None]]
            z[:, ks] = np.sum((y * g).reshape(ks.size, parts, -1), axis=2).T
            # the window's DFT the same way, from the constant's moments: (K, S)
            v = np.matmul(geo.poly.reshape(1, -1, deg + 1), np.matmul(shift, const[cs, :, None]))
            wdft[:, ks] = np.sum(v.reshape(ks.size, parts, geo.count) * turn[ks], axis=2).T
        # the ends of each part, exactly: its first M samples (the head's, weighted) and its last 2M
        # (the tail's), strided views of the record (phase r*(j - c) at sample j of the part)
        st = self.x.strides[0]
        hx = np.lib.stride_tricks.as_strided(self.x, (parts, m), (length * st, st), writeable=False)
        tx = np.lib.stride_tricks.as_strided(self.x[length - 2 * m:], (parts, 2 * m), (length * st, st),
                                             writeable=False)
        h_tab, t_tab = phasors(-c, m, r), phasors(length - 2 * m - c, 2 * m, r)
        z += _times_table(hx * geo.head_w, h_tab) + _times_table(tx * geo.tail_w, t_tab)
        wdft += _times_table(geo.head_w, h_tab) + _times_table(geo.tail_w, t_tab)
        ends = np.sum(hx * geo.head_in, axis=1) + np.sum(tx * geo.tail_in, axis=1)
        mean = (self._sums[blocks].sum(axis=1) + ends) / length
        return z - mean[:, None] * wdft

    def _locate(self, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The pass and column of each line ``r`` (cycles per sample): the first pass that read a
        line within :data:`PART_OFFSET_RAD` of it, or a new pass for those no pass has read."""
        tol = PART_OFFSET_RAD / (np.pi * self.m)
        where = np.full(r.size, -1)
        col = np.zeros(r.size, dtype=int)
        for p, (rp, _, _) in enumerate(self._passes):
            d = np.abs(r[:, None] - rp[None, :])
            hit = (where < 0) & (d.min(axis=1) <= tol)
            where[hit], col[hit] = p, d.argmin(axis=1)[hit]
        miss = where < 0
        if np.any(miss):
            _, first = np.unique(r[miss], return_index=True)
            new = r[miss][np.sort(first)]  # in the order asked (a later ask in that order reads in place)
            self._read(new)
            where[miss] = len(self._passes) - 1
            col[miss] = np.argmin(np.abs(r[miss, None] - new[None, :]), axis=1)
        return where, col

    def _read(self, r: np.ndarray) -> None:
        """Every block's moments at the lines ``r`` (cycles per sample), in one product: the
        record's blocks (A, M) times a table (M, (deg+1)K [+1]) of ``t^n`` times the lines'
        phasors (and a column of ones for the blocks' sums on the first pass)."""
        m, deg = self.m, PART_DEGREE
        t = (np.arange(m) - (m - 1) / 2.0) / (m / 2.0)
        e = phasors(-(m - 1) / 2.0, m, r)  # (M, K)
        cols = [e * (t**i)[:, None] for i in range(deg + 1)]
        first = self._sums is None
        table = np.concatenate(cols + [np.ones((m, 1), dtype=np.complex128)] * first, axis=1)
        a = self.x.size // m
        body = self.x[:a * m].reshape(a, m)
        y = _times_table(body, table)
        if first:
            self._sums = y[:, -1] if np.iscomplexobj(body) else y[:, -1].real
        # line by line, every block's moments in a row: (K, A, deg+1)
        mom = np.ascontiguousarray(y[:, :(deg + 1) * r.size].reshape(a, deg + 1, r.size).transpose(2, 0, 1))
        const = np.array([q.sum(axis=0) for q in cols]).T  # (K, deg+1)
        self._passes.append((r, mom, const))

    def _exact(self, parts: int, length: int, f: np.ndarray) -> np.ndarray:
        """Part by part through one reused buffer (mean removed, windowed, :func:`exact_dft`)."""
        w = cached_window(self.window, length)
        z = np.empty((parts, f.size), dtype=np.complex128)
        buf = np.empty(length, dtype=self.x.dtype)
        for s in range(parts):
            seg = self.x[s * length:(s + 1) * length]
            np.subtract(seg, seg.mean(), out=buf)
            buf *= w
            z[s] = exact_dft(buf, f, self.fs)
        return z


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
    """The cosine block with a DC column (shape (..., K+1, K+1)) and the sine block (..., K, K) of the
    real line fit (``w``: shape (..., K), rad per sample): ``(D(a - b) +- D(a + b))/2`` over the
    centred index, the sine block's kernels being the cosine block's without the DC row and column
    (two kernel evaluations, not four)."""
    wc = np.concatenate([np.zeros(w.shape[:-1] + (1,)), w], axis=-1)
    dm = _dirichlet(wc[..., :, None] - wc[..., None, :], n)
    dp = _dirichlet(wc[..., :, None] + wc[..., None, :], n)
    return 0.5 * (dm + dp), 0.5 * (dm[..., 1:, 1:] - dp[..., 1:, 1:])


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


def line_response(freqs_hz: np.ndarray, true_hz: np.ndarray, fs_hz: float, n: int) -> np.ndarray:
    """The complex (IQ) line fit's amplitudes at ``freqs_hz`` for a unit line at each of ``true_hz``
    (phase 0 at the record's centre), shape (K, J), real: ``G^-1 D``, ``G`` the fit's Gram matrix
    and ``D[k, j]`` the DFT at ``freqs_hz[k]`` of the line at ``true_hz[j]`` (Dirichlet kernels of the
    centred index). Column ``j`` is what the fit reads of a line it models elsewhere: its own row
    the line's share, the others its leak into them."""
    w = 2 * np.pi * np.asarray(freqs_hz, dtype=np.float64) / fs_hz
    wt = 2 * np.pi * np.asarray(true_hz, dtype=np.float64) / fs_hz
    return linalg.solve(_dirichlet(w[:, None] - w[None, :], n), _dirichlet(wt[None, :] - w[:, None], n),
                        assume_a="sym")


def fit_noise_gain(freqs_hz: np.ndarray, fs_hz: float, n: int, iq: bool) -> np.ndarray:
    """The variance of each line's fitted complex amplitude (:func:`fit_lines` on ``n`` samples)
    per unit of the white noise's per-sample variance, shape (K,): the diagonal of the inverse
    Gram matrix (both blocks of a real fit's), which grows where lines lie closer than a bin and
    their fits share the noise (``1/n`` and ``4/n`` for lines far apart, IQ and real)."""
    w = 2 * np.pi * np.asarray(freqs_hz, dtype=np.float64) / fs_hz
    if iq:
        return np.real(np.diag(linalg.inv(_dirichlet(w[:, None] - w[None, :], n))))
    gc, gs = _gram_real(w, n)
    return np.diag(linalg.inv(gc))[1:] + np.diag(linalg.inv(gs))


def solve_lines_many(dft: np.ndarray, freqs_hz: np.ndarray, fs_hz: float, n: int, total: float, iq: bool
                     ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`solve_lines` for several line sets of one record at once (trials of a fit), one
    batched solve per block instead of two solver calls per set (each ~0.1 ms of call overhead on
    the few-by-few matrices).

    Parameters
    ----------
    dft, freqs_hz : ndarray, shape (B, K): each set's exact DFTs and frequencies (Hz)
    fs_hz, n, total, iq : as :func:`solve_lines`

    Returns
    -------
    energy : ndarray, shape (B,), V^2
    c : ndarray, shape (B, K), complex128
    """
    dft = np.asarray(dft)
    w = 2 * np.pi * np.asarray(freqs_hz, dtype=np.float64) / fs_hz
    if iq:
        c = np.linalg.solve(_dirichlet(w[:, :, None] - w[:, None, :], n), dft[:, :, None])[:, :, 0]
        return np.real(np.einsum("bk,bk->b", dft.conj(), c)), c
    gc, gs = _gram_real(w, n)
    pc = np.concatenate([np.full((w.shape[0], 1), total), dft.real], axis=1)
    ps = -dft.imag
    alpha = np.linalg.solve(gc, pc[:, :, None])[:, :, 0]
    beta = np.linalg.solve(gs, ps[:, :, None])[:, :, 0]
    return np.einsum("bk,bk->b", pc, alpha) + np.einsum("bk,bk->b", ps, beta), alpha[:, 1:] - 1j * beta


def _schur_gains(gram: np.ndarray, proj: np.ndarray, moved: np.ndarray, kernel: np.ndarray, diag: np.ndarray,
                 trial_proj: np.ndarray) -> np.ndarray:
    """One block of :func:`line_gains`: what row ``moved[i]`` of the normal equations ``gram @ c =
    proj`` adds to the energy ``proj @ c`` when that row's line is at each trial, the other rows held
    (the Schur complement of the row: ``|q|^2 / s`` with ``q = trial_proj - k.G_r^-1 proj_r`` and
    ``s = diag - k.G_r^-1 k``; every moved row and trial in one batched solve).

    Shapes: ``gram`` (K, K) real symmetric, ``proj`` (K,) real or complex, ``moved`` (J,) int,
    ``kernel`` (J, P, K) the trial line's Gram entries against every row (the moved row's own
    ignored), ``diag`` (J, P) its own, ``trial_proj`` (J, P) its projection; returns (J, P), real.
    """
    k = gram.shape[0]
    if k == 1:
        return np.abs(trial_proj) ** 2 / diag
    keep = np.array([np.delete(np.arange(k), j) for j in moved], dtype=np.intp).reshape(len(moved), k - 1)
    g_rest = gram[keep[:, :, None], keep[:, None, :]]  # (J, K-1, K-1)
    kr = np.take_along_axis(kernel, keep[:, None, :], axis=2)  # (J, P, K-1)
    sol = np.linalg.solve(g_rest, np.concatenate([proj[keep][:, :, None], kr.transpose(0, 2, 1)], axis=2))
    q = trial_proj - np.einsum("jpk,jk->jp", kr, sol[:, :, 0])
    s = diag - np.einsum("jpk,jkp->jp", kr, sol[:, :, 1:].real)
    return np.abs(q) ** 2 / s


def line_gains(dft: np.ndarray, freqs_hz: np.ndarray, fs_hz: float, n: int, total: float, iq: bool,
               moved: np.ndarray, trial_hz: np.ndarray, trial_dft: np.ndarray) -> np.ndarray:
    """The energy (V^2) line ``moved[i]`` of :func:`solve_lines`' fit adds to what the other lines
    explain, when it alone is at ``trial_hz[i, p]``, the other lines held at ``freqs_hz``.

    The fit's total energy is then the other lines' (fixed) plus this gain, so the gain alone
    carries how the fit changes with one line's frequency, without the rounding of the static
    lines' far larger energy (a parabola's vertex and curvature over ``4e-4`` bin of a line ``40 dB``
    under the static ones). Equal to differencing :func:`solve_lines` (the Schur complement of the
    line's rows of the normal equations; every line and trial in one batched solve per block).

    Parameters
    ----------
    dft, freqs_hz, fs_hz, n, total, iq : as :func:`solve_lines`, shape (K,) for the arrays
    moved : ndarray, shape (J,), int: the lines moved, one at a time
    trial_hz : ndarray, shape (J, P), Hz: each moved line's trial frequencies
    trial_dft : ndarray, shape (J, P), complex: :func:`exact_dft` of the record there

    Returns
    -------
    ndarray, shape (J, P), V^2
    """
    moved = np.asarray(moved, dtype=np.intp)
    w = 2 * np.pi * np.asarray(freqs_hz, dtype=np.float64) / fs_hz
    wt = (2 * np.pi / fs_hz) * np.asarray(trial_hz, dtype=np.float64)[:, :, None]  # (J, P, 1)
    if iq:
        gram = _dirichlet(w[:, None] - w[None, :], n)
        return _schur_gains(gram, np.asarray(dft), moved, _dirichlet(wt - w, n), np.full(wt.shape[:2], float(n)),
                            np.asarray(trial_dft))
    gc, gs = _gram_real(w, n)
    wc = np.concatenate([[0.0], w])
    dm, dp = _dirichlet(wt - wc, n), _dirichlet(wt + wc, n)  # (J, P, K+1)
    d2 = _dirichlet(2 * wt[:, :, 0], n)
    cos_gain = _schur_gains(gc, np.concatenate([[total], dft.real]), moved + 1, 0.5 * (dm + dp), 0.5 * (n + d2),
                            trial_dft.real)
    sin_gain = _schur_gains(gs, -dft.imag, moved, 0.5 * (dm - dp)[:, :, 1:], 0.5 * (n - d2), -trial_dft.imag)
    return cos_gain + sin_gain


def lines_signal(amps: np.ndarray, freqs_hz: np.ndarray, fs_hz: float, n: int, iq: bool,
                 chunk: int = 1 << 16) -> np.ndarray:
    """The record of :func:`fit_lines`' model without its DC: ``sum_l Re(c_l * exp(j*w_l*(k - (N-1)/2)))``
    (complex, without ``Re``, for IQ), built ``chunk`` samples at a time (a line's phasors over a
    1e6-sample record would be 16 MB each), every phase from the integer index modulo one cycle.

    Parameters
    ----------
    amps : ndarray, shape (K,), complex (V, phase at the record's centre)
    freqs_hz : ndarray, shape (K,), Hz

    Returns
    -------
    ndarray, shape (n,), float64 (complex128 for IQ), V
    """
    r = np.atleast_1d(np.asarray(freqs_hz, dtype=np.float64)) / fs_hz
    amps = np.atleast_1d(np.asarray(amps, dtype=np.complex128))
    out = np.empty(n, dtype=np.complex128 if iq else np.float64)
    c = (n - 1) / 2.0
    for start in range(0, n, chunk):
        count = min(chunk, n - start)
        z = np.conj(phasors(start - c, count, r)) @ amps  # (count,)
        out[start:start + count] = z if iq else z.real
    return out


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
                       dft: np.ndarray | None = None, sums: np.ndarray | None = None) -> np.ndarray:
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
    sums : ndarray, shape (S,), optional: a real record's segment sums if already computed (the
        DC column's projection; :func:`exact_dft_tiled` at 0 Hz)

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
    pc = np.concatenate([(seg.sum(axis=1) if sums is None else sums)[:, None], dft.real], axis=1)  # (S, K+1)
    alpha = linalg.solve(gc, pc.T, assume_a="sym").T[:, 1:]
    beta = linalg.solve(gs, (-dft.imag).T, assume_a="sym").T
    return alpha - 1j * beta
