"""Stage ``spectrum``: the windowed power spectrum, its local noise floor and line widths.

The spectrum serves the Doppler search (``doppler``) and the lines' noise floors (``extract``):
their size, and how the noise about several lines moves together (:meth:`Spectrum.line_rings`).
No line's phase is ever taken from it (the line fits are float64 exact DFTs, :mod:`.tones`).
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, field, replace
from functools import cached_property, lru_cache

import numpy as np
import scipy.fft
from scipy.signal import get_window

LN2 = float(np.log(2.0))
EULER_GAMMA = float(np.euler_gamma)


#: the FFT implementations every ``scipy.fft`` call of the chain may run on: scipy's own
#: (pocketfft, BSD, the default) and FFTW through pyFFTW (``pip install 'mtcw[fftw]'``; pyFFTW is
#: BSD, FFTW itself GPL-2+: an optional extra, never a dependency)
FFT_BACKENDS = ("pocketfft", "pyfftw")
#: the backend in force (:func:`use_fft_backend`)
_fft_backend = "pocketfft"


def use_fft_backend(name: str) -> str:
    """Run every ``scipy.fft`` call of this process on ``name`` (one of :data:`FFT_BACKENDS`);
    returns the name of the backend it replaces (to restore it).

    A process-wide choice (``scipy.fft.set_global_backend``), made once at start-up by a worker
    (``MTCW_FFT_BACKEND``) or the benchmark (``--fft-backend``). Either runs on ``scipy.fft``'s
    workers (one thread unless ``scipy.fft.set_workers`` says more: a worker takes one core).
    FFTW's plans are cached between frames of one shape (``pyfftw.interfaces.cache``) and made
    with ``FFTW_ESTIMATE`` (``FFTW_MEASURE`` ran no faster at these lengths and plans for
    seconds at each new one). Where the backend's real transform is
    fast (FFTW: a 1e6-sample single-precision ``rfft`` in ~3 ms on the bench machine, pocketfft's
    ~12 ms), :func:`power_spectrum` takes it instead of its packed complex route (:class:`PackedPower`).

    Raises
    ------
    ValueError naming ``fft_backend`` for an unknown name, or for ``pyfftw`` when pyFFTW is not installed
    """
    global _fft_backend
    before = _fft_backend
    backend = fft_backend_module(name)
    if name == "pyfftw":
        import pyfftw

        pyfftw.interfaces.cache.enable()
        pyfftw.interfaces.cache.set_keepalive_time(60.0)
        pyfftw.config.PLANNER_EFFORT = "FFTW_ESTIMATE"
    scipy.fft.set_global_backend(backend)
    _fft_backend = name
    return before


def fft_backend_module(name: str):
    """What ``scipy.fft.set_global_backend`` takes for the backend ``name``: ``"scipy"``, or
    pyFFTW's ``scipy_fft`` interface (imported here). The check a setting makes at start-up.

    Raises
    ------
    ValueError naming ``fft_backend`` for an unknown name, or for ``pyfftw`` when pyFFTW is not installed
    """
    if name not in FFT_BACKENDS:
        raise ValueError(f"fft_backend={name!r}: one of {', '.join(FFT_BACKENDS)}")
    if name == "pocketfft":
        return "scipy"
    try:
        import pyfftw.interfaces.scipy_fft as fftw_scipy
    except ImportError as err:
        raise ValueError(f"fft_backend='pyfftw' needs pyFFTW (pip install 'mtcw[fftw]'): {err}") from err
    return fftw_scipy


def fft_backend_name() -> str:
    """The name (one of :data:`FFT_BACKENDS`) of the backend in force."""
    return _fft_backend


def _aligned_empty(m: int, dtype) -> np.ndarray:
    """An uninitialised array of ``m`` elements aligned as FFTW's SIMD kernels want it."""
    import pyfftw

    return pyfftw.empty_aligned(m, dtype=dtype)


def fft_backend() -> str:
    """The FFT implementation in force, for reports: its name and version."""
    if _fft_backend == "pyfftw":
        import pyfftw

        return f"pyfftw {pyfftw.__version__} (FFTW, via scipy.fft.set_global_backend)"
    return "scipy default (pocketfft)"


#: the noise floor's ring around a line, in bins of the whole record (:meth:`Spectrum.floor_half_width`)
FLOOR_HALF_WIDTH_RECORD_BINS = 256
#: :meth:`Spectrum.line_rings` wants at least this many offsets every line keeps
RING_MIN_BINS = 24
#: the bins an extracted line's floor keeps clear of every line, in bins of the whole record
#: (:meth:`Spectrum.line_floor_guard`) ...
LINE_FLOOR_GUARD_RECORD_BINS = 12
#: ... and at least this many of the spectrum's own bins: the Kaiser(14) main lobe (first null
#: 4.6 bins out)
LINE_FLOOR_GUARD_MIN_BINS = 6


@dataclass(frozen=True)
class Spectrum:
    """Windowed periodogram of (part of) a record.

    Attributes
    ----------
    power : ndarray or PackedPower, shape (B,)
        ``|X|^2`` of the windowed record (rfft for real, fftshifted fft for complex input), V^2;
        of an even-length real record a :class:`PackedPower`, which unpacks the bins it is asked
        for (index it, or ``np.asarray`` it for the whole array).
    df_hz : float
        Bin spacing (Hz).
    f0_hz : float
        Frequency of bin 0 (0 for real, ``-fs/2`` for complex input).
    window_power : float
        ``sum(w^2)``; white noise of per-sample variance s2 has ``E[power] = s2*window_power``
        (``2*s2*...`` counted over both quadratures for complex noise of total variance s2).
    n : int
        Samples transformed.
    total : float or complex or None
        ``np.sum`` of the samples transformed (the first ``n`` of the record handed in), before
        the mean is removed, V; the extract stage's DC projection when those are the whole
        record (one pass over it fewer).
    record_n : int or None
        Samples of the record this spectrum is the first part of (``fast`` transforms an eighth);
        None: the spectrum is of the whole record. The noise floor's ring is set in the record's
        bins (:data:`FLOOR_HALF_WIDTH_RECORD_BINS`), so it spans the same band in Hz either way.
    bins : ndarray, PackedPower or None
        The complex transform whose ``|X|^2`` is ``power`` (:meth:`complex_at` reads it), or None.
    window : tuple or str or None
        The window's :func:`scipy.signal.get_window` spec, or None (not known).
    """

    power: np.ndarray | PackedPower
    df_hz: float
    f0_hz: float
    window_power: float
    n: int
    complex_input: bool
    total: float | complex | None = None
    record_n: int | None = None
    #: what a later stage reads of what an earlier one found in this spectrum (the Doppler search's
    #: bins standing out of their floor, for the static lines' self-beat bound), keyed by what it
    #: was computed for
    memo: dict = field(default_factory=dict, repr=False, compare=False)
    #: the complex transform behind ``power`` (:meth:`complex_at`): the whole of it (complex input,
    #: a real transform not packed), or the :class:`PackedPower` that unpacks it; None: not kept
    bins: np.ndarray | PackedPower | None = field(default=None, repr=False, compare=False)
    #: the window the samples were weighted by (a :func:`scipy.signal.get_window` spec), or None
    window: tuple | str | None = None

    @property
    def fs_hz(self) -> float:
        """The record's sample rate (Hz): the bin spacing times the samples transformed."""
        return self.df_hz * self.n

    def bin_of(self, f_hz: float | np.ndarray) -> np.ndarray:
        return np.rint((np.asarray(f_hz) - self.f0_hz) / self.df_hz).astype(np.int64)

    def power_at(self, f_hz: np.ndarray) -> np.ndarray:
        """The power in the bin nearest each frequency (Hz, as the spectrum holds them: signed for a
        complex record's), clipped to the spectrum's ends; shape of ``f_hz``."""
        return np.asarray(self.power[np.clip(self.bin_of(f_hz), 0, self.power.size - 1)])

    def line_floor_guard(self) -> int:
        """The bins (of this spectrum) an extracted line's noise floor keeps clear of every line:
        :data:`LINE_FLOOR_GUARD_RECORD_BINS` bins of the whole record, at least
        :data:`LINE_FLOOR_GUARD_MIN_BINS` -- 12 for a whole-record spectrum, 6 of ``fast``'s
        eighth-record bins (48 record bins) rather than 12 of them (96): the noise rises toward the
        lines (the static lines' and the movers' pedestals), and 96 record bins out ``fast`` measured
        the six-tone movers' floors ~15 % low and ~30 % scattered (range z std 1.6-1.7)."""
        scale = self.n / self.record_n if self.record_n else 1.0
        return max(int(round(LINE_FLOOR_GUARD_RECORD_BINS * scale)), LINE_FLOOR_GUARD_MIN_BINS)

    def floor_half_width(self, guard: int = 12) -> int:
        """The noise floor ring's half width in this spectrum's bins: :data:`FLOOR_HALF_WIDTH_RECORD_BINS`
        bins of the whole record (the same band in Hz for a spectrum of part of the record, whose
        bins are wider: a ring 8x wider in Hz measured ``fast``'s floors up to ~2x low in variance
        where the noise is not white far from the lines), at least ``2*guard + 8``."""
        scale = self.n / self.record_n if self.record_n else 1.0
        return max(int(round(FLOOR_HALF_WIDTH_RECORD_BINS * scale)), 2 * guard + 8)

    def ring(self, f_hz, exclude_hz, half_width: int, guard: int) -> tuple[np.ndarray, np.ndarray]:
        """The bins within ``half_width`` of each frequency of ``f_hz`` (shape (L,)) and which of
        them lie in the spectrum and more than ``guard`` bins from every frequency of
        ``exclude_hz`` (Hz): shapes (L, 2*half_width + 1), int and bool."""
        f = np.atleast_1d(np.asarray(f_hz, dtype=float))
        idx = self.bin_of(f)[:, None] + np.arange(-half_width, half_width + 1)[None, :]  # (L, W)
        keep = (idx >= 0) & (idx < self.power.size)
        ex = np.sort(self.bin_of(np.asarray(exclude_hz, dtype=float))) if len(exclude_hz) else np.empty(0, np.int64)
        if ex.size:
            # distance of every bin to the nearest excluded bin, by sorted search
            j = np.clip(np.searchsorted(ex, idx), 1, max(ex.size - 1, 1))
            d = np.abs(idx - ex[j - 1]) if ex.size > 1 else np.abs(idx - ex[0])
            if ex.size > 1:
                d = np.minimum(d, np.abs(idx - ex[j]))
            keep &= d > guard
        return idx, keep

    def noise_variances(self, f_hz, exclude_hz, half_width: int | None = None, guard: int = 12,
                        counts: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """:meth:`noise_variance` at every frequency of ``f_hz`` (shape (L,)) at once, V^2.

        The same statistic, row by row: each line's ``+-half_width`` bins (default
        :meth:`floor_half_width`) less those within ``guard`` of an excluded frequency (all of
        them kept when that leaves none), median of the rest. ``counts``: also how many bins each
        median is of, shape (L,).
        """
        if half_width is None:
            half_width = self.floor_half_width(guard)
        f = np.atleast_1d(np.asarray(f_hz, dtype=float))
        if f.size == 0:
            return (np.empty(0), np.empty(0, np.int64)) if counts else np.empty(0)
        nb = self.power.size
        idx, keep = self.ring(f, exclude_hz, half_width, guard)
        valid = (idx >= 0) & (idx < nb)
        keep = np.where(keep.any(axis=1)[:, None], keep, valid)  # nothing left: every bin in reach
        vals = np.where(keep, self.power[np.clip(idx, 0, nb - 1)], np.inf).astype(self.power.dtype)
        vals.sort(axis=1)
        count = keep.sum(axis=1)
        rows = np.arange(f.size)
        lo, hi = vals[rows, np.maximum((count - 1) // 2, 0)], vals[rows, np.maximum(count // 2, 0)]
        med = ((lo + hi) / 2).astype(np.float64)  # as np.median does it, in the spectrum's precision
        out = np.where(count > 0, med, np.nan) / LN2 / self.window_power
        return (out, count) if counts else out

    def noise_variance(self, f_hz: float, exclude_hz: list[float], half_width: int | None = None,
                       guard: int = 12) -> float:
        """Per-sample noise variance (V^2) equivalent to the local noise density around f.

        Median of the periodogram over ``+-half_width`` bins (default :meth:`floor_half_width`), excluding ``+-guard`` bins around
        every frequency in ``exclude_hz`` (the lines); the median of an exponential variable is
        ``ln 2`` times its mean. One line of :meth:`noise_variances`.
        """
        return float(self.noise_variances([f_hz], exclude_hz, half_width, guard)[0])

    def complex_at(self, idx: np.ndarray) -> np.ndarray | None:
        """The complex transform at bins ``idx`` (any integer shape), each referred to the centre of
        the samples transformed, ``X[k]*exp(2j*pi*f_k*(n - 1)/(2*fs))``: the symmetric window's
        response is then real, so a line's bin holds the line's own phase and two bins a fraction
        apart are not turned against each other. None where the transform was not kept.
        """
        k = np.asarray(idx, dtype=np.int64)
        if self.bins is None:
            return None
        x = self.bins.complex_at(k) if isinstance(self.bins, PackedPower) else self.bins[k].astype(np.complex128)
        if x is None:
            return None
        # f_k/fs = (k + k0)/n with k0 = f0/df an integer (0 real; -n/2 or -(n-1)/2 fftshifted);
        # the angle from integers modulo its period 2n
        k0 = int(round(self.f0_hz / self.df_hz))
        return x * np.exp(1j * np.pi * (((k + k0) * (self.n - 1)) % (2 * self.n)) / self.n)

    def line_rings(self, f_hz: np.ndarray, mirror: np.ndarray, exclude_hz: np.ndarray, guard: int,
                   half_width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The noise about several lines at the offsets they share, turned into each line's frame:
        shape (W, L) complex, with each line's misalignment, shape (L,), and the rows' offsets
        (bins, shape (W,)); or None (no complex transform or window kept, a line beyond the band
        the spectrum holds, fewer than :data:`RING_MIN_BINS` shared offsets, or two lines whose
        rows come within ``guard`` bins of each other: the window correlates those rows whatever
        the noise does).

        Each line's ring is :meth:`ring`'s (``+-half_width`` bins less those within ``guard`` of
        every frequency of ``exclude_hz``), at offsets every line keeps; a ``mirror``
        line (its amplitude conjugated, as a line folded through 0 Hz is) is read at the opposite
        offsets and conjugated, so that row ``w`` holds every line's noise at one offset of the
        underlying process. Each column is turned by its line's own phase (its bin, centre-referred):
        the imaginary part moves the line's phase, the real part its size.

        A line lies a fraction of a bin off its bin, so one row's bins stand at offsets from their
        lines that differ by up to a bin: the window then correlates them less than the process
        does, ``exp(-(s_i - s_j)^2)`` times (the window's coherence over ``d`` bins,
        :func:`window_coherence_scale` ``a``: ``exp(-a*d^2)``), where ``s`` (the second array) is
        each line's offset from its bins in the direction its ring runs, times ``sqrt(a)``.

        Parameters
        ----------
        f_hz : ndarray, shape (L,), Hz, as the spectrum holds them (signed for complex input)
        mirror : ndarray of bool, shape (L,)
        exclude_hz : ndarray, Hz: every line the record holds
        guard, half_width : int, bins
        """
        f = np.atleast_1d(np.asarray(f_hz, dtype=float))
        mir = np.asarray(mirror, bool)[:, None]
        own = self.bin_of(f)
        if np.any((own < 0) | (own >= self.power.size)):  # a line beyond the band this spectrum holds
            return None
        idx, keep = self.ring(f, exclude_hz, half_width, guard)
        idx, keep = np.where(mir, idx[:, ::-1], idx), np.where(mir, keep[:, ::-1], keep)
        shared = keep.all(axis=0)
        if int(shared.sum()) < RING_MIN_BINS or self.bins is None or self.window is None:
            return None
        # two lines whose rows come within ``guard`` bins of each other share the window's own
        # correlation of neighbouring bins, not their noise's (U and L 1-2 bins apart in ``fast``'s
        # eighth-record spectrum read as -0.87 coherent; the record's own fit holds them apart)
        rows = idx[:, shared]
        gap = np.abs(rows[:, None, :] - rows[None, :, :]).min(axis=2) + guard * np.eye(f.size, dtype=np.int64)
        if int(gap.min()) < guard:
            return None
        vals = self.complex_at(np.concatenate([idx[:, shared], own[:, None]], axis=1))  # (L, W + 1)
        if vals is None:
            return None
        vals = np.where(mir, np.conj(vals), vals)
        line = vals[:, -1]
        turn = np.where(np.abs(line) > 0, np.conj(line) / np.maximum(np.abs(line), 1e-300), 1.0)
        # row w's bin is (w's offset) + (bin - f/df) from the line, read backward for a mirror line
        off = (own - (f - self.f0_hz) / self.df_hz) * np.where(mir[:, 0], -1.0, 1.0)
        return ((vals[:, :-1] * turn[:, None]).T, off * math.sqrt(window_coherence_scale(self.window, self.n)),
                np.arange(-half_width, half_width + 1)[shared])


@lru_cache(maxsize=8)
def cached_window(window: tuple | str, m: int, dtype: str = "float64") -> np.ndarray:
    """The (symmetric) window, cached: a stream's frames share one length, and a Kaiser window
    of 1e6 points costs more than the FFT it weights."""
    w = get_window(window, m, fftbins=False).astype(dtype)
    w.setflags(write=False)
    return w


def windowed_record(x: np.ndarray, window: tuple | str) -> np.ndarray:
    """The record less its mean, times the (cached) ``window`` over its whole length, shape (N,)
    (one new array: the exact DFTs that read a line and what stands beside it)."""
    y = np.subtract(x, x.mean())
    y *= cached_window(window, x.size)
    return y


@lru_cache(maxsize=8)
def window_sum(window: tuple | str, m: int, dtype: str = "float64") -> float:
    """``sum(w)`` of :func:`cached_window` (cached; summed in float64)."""
    return float(np.sum(cached_window(window, m, dtype), dtype=np.float64))


@lru_cache(maxsize=16)
def window_power(window: tuple | str, m: int) -> float:
    """``sum(w^2)`` of :func:`cached_window` (cached)."""
    return float(np.sum(cached_window(window, m) ** 2))


@lru_cache(maxsize=16)
def window_coherence_scale(window: tuple | str, m: int) -> float:
    """``a`` of ``exp(-a*d^2)``, the coherence of white noise's two bins ``d`` bins apart after this
    window (centre-referred: real), fitted at ``d = 1/2``: ``sum(w^2*cos(pi*t))/sum(w^2)`` with
    ``t = (n - (m-1)/2)/m``. Kaiser(14): 0.173 (coherence 0.958 at half a bin, 0.841 at one bin, both
    within 1e-3 of the window's own)."""
    w2 = cached_window(window, m) ** 2
    t = (np.arange(m) - (m - 1) / 2) / m
    return float(-np.log(np.sum(w2 * np.cos(np.pi * t)) / np.sum(w2)) / 0.25)


@lru_cache(maxsize=4)
def _half_twiddle(m: int, dtype: str) -> np.ndarray:
    """``exp(-2j*pi*k/m)`` for ``k < m/2`` (the split of a packed real FFT), cached per length;
    the angle from the integer ``k`` in float64, then cast."""
    w = np.exp(-2j * np.pi * (np.arange(m // 2, dtype=np.float64) / m)).astype(dtype)
    w.setflags(write=False)
    return w


class PackedPower:
    """``|rfft(y)|^2`` of a real record of even length ``m``, shape ``(m//2 + 1,)``, held as the
    complex FFT of half the length and unpacked only in the bins that are read.

    The pairs ``(y[2k], y[2k+1])`` taken as one complex sample have the FFT ``Z`` (length
    ``h = m/2``); with ``Zr[k] = conj(Z[-k mod h])`` and ``W = exp(-2j*pi/m)``,
    ``X[k] = ((Z + Zr) - j*W^k*(Z - Zr))/2`` and ``X[h] = Re Z[0] - Im Z[0]``. scipy's ``rfft``
    computes the same transform, but pocketfft's real kernels run at about half the speed of its
    complex ones at these lengths (1e6 samples: 7.4 ms against 3.3 ms for the complex FFT of half
    the length on the bench machine), hence this route to the same numbers.

    The unpacking costs about two thirds of that FFT again over the whole spectrum, and the
    chain reads a few bands of it (the Doppler search: +-its largest shift around 0 Hz and each
    tone; the noise floors: +-256 bins around each line), so it is done per block of
    :attr:`BLOCK` bins on the first read and kept: indexing (an integer, a slice, an integer
    array of any shape) returns exactly what indexing the whole ``|X|^2`` would, every block
    unpacked by the same arithmetic wherever the read starts. ``np.asarray`` (and any attribute
    of an ndarray, e.g. ``.max()``) gives the whole array, unpacking what is missing.

    Parameters
    ----------
    packed : ndarray, shape (h,), complex64 or complex128: the FFT of the record's pairs; kept
        (not copied), and written only when every bin is unpacked in one go (it is then released)
    keep : bool
        Never write or release the packed FFT: :meth:`complex_at` reads it after every bin is
        unpacked (the whole unpacking then costs one more buffer of ``h`` complex)

    Memory: the packed FFT (``m/2`` complex) is held with the ``m/2 + 1`` output bins until the
    spectrum is dropped (a 1e6-sample single-precision spectrum: 4 + 2 MB, where the unpacked
    spectrum alone held 2 MB).
    """

    #: bins unpacked together on the first read of any of them
    BLOCK = 1024
    #: runs of at least this many bins are unpacked each on its own, shorter ones batched
    LONG_RUN = 8 * BLOCK

    def __init__(self, packed: np.ndarray, keep: bool = False):
        self._z = packed
        self._keep = keep
        self._h = h = packed.size
        self.dtype = packed.real.dtype
        self.shape = (h + 1,)
        self.size = h + 1
        self.ndim = 1
        self._out = np.empty(h + 1, dtype=self.dtype)
        self._done = np.zeros(-(-(h + 1) // self.BLOCK), dtype=bool)
        self._tw = _half_twiddle(2 * h, str(packed.dtype))

    def __len__(self) -> int:
        return self.size

    def _unpack(self, runs: list[tuple[int, int]]) -> None:
        """Write bins ``[a, b)`` of ``|X|^2`` into the store for every ``(a, b)`` of ``runs``, all in
        one pass over their concatenated inputs (each numpy call costs microseconds: one call per
        step for all runs, not one per run)."""
        z, h, out = self._z, self._h, self._out
        parts = []
        nyquist_too = False
        for a, b in runs:
            if b > h:  # the Nyquist bin, from Z[0] alone
                nyquist_too = True
                nyquist = float(z[0].real) - float(z[0].imag)
                out[h] = nyquist * nyquist
                b = h
            if b > a:
                parts.append((a, b))
        if not parts:
            return
        n = sum(b - a for a, b in parts)
        # conj(Z[-k]) for every k of the runs: Z[h-k], walking down (Z[0] for k = 0)
        even = np.empty(n, dtype=z.dtype)
        zk = np.empty(n, dtype=z.dtype) if len(parts) > 1 else z[parts[0][0]:parts[0][1]]
        tw = np.empty(n, dtype=z.dtype) if len(parts) > 1 else self._tw[parts[0][0]:parts[0][1]]
        o = 0
        for a, b in parts:
            if a == 0:
                even[o] = z[0]
                even[o + 1:o + b] = z[h - b + 1:h][::-1]
            else:
                even[o:o + b - a] = z[h - b + 1:h - a + 1][::-1]
            if len(parts) > 1:
                zk[o:o + b - a] = z[a:b]
                tw[o:o + b - a] = self._tw[a:b]
            o += b - a
        np.conjugate(even, out=even)
        even += zk  # Z + conj(Z[-k])
        whole = nyquist_too and len(parts) == 1 and parts[0] == (0, h) and not self._keep
        if whole:  # every bin at once: Z is not read again, so work in its buffer
            odd = zk
            odd *= 2
            self._z = None
        else:
            odd = zk * 2
        odd -= even  # Z - conj(Z[-k])
        odd *= tw  # 2j * W^k * (DFT of the odd samples)
        # X = (even - j*odd)/2 = ((even.re + odd.im) + j*(even.im - odd.re))/2
        body = np.add(even.real, odd.imag) if len(parts) > 1 else out[parts[0][0]:parts[0][1]]
        if len(parts) == 1:
            np.add(even.real, odd.imag, out=body)
        body *= body
        scratch = even.real  # spent once the real part is summed: hold the imaginary part there
        np.subtract(even.imag, odd.real, out=scratch)
        scratch *= scratch
        body += scratch
        body *= 0.25
        if len(parts) > 1:
            o = 0
            for a, b in parts:
                out[a:b] = body[o:o + b - a]
                o += b - a

    def _ensure_blocks(self, need: np.ndarray) -> None:
        """Unpack the blocks marked in ``need`` (bool, one per block) that are not unpacked yet."""
        todo = need & ~self._done
        if not todo.any():
            return
        # runs of blocks still packed, unpacked together
        edges = np.flatnonzero(np.diff(np.concatenate([[False], todo, [False]]).astype(np.int8)))
        blk = self.BLOCK
        runs = [(int(r0) * blk, min(int(r1) * blk, self.size)) for r0, r1 in zip(edges[::2], edges[1::2])]
        # a long run is unpacked on its own (slices, no copies); the short ones together (one call each step)
        short = [r for r in runs if r[1] - r[0] < self.LONG_RUN]
        for r in runs:
            if r[1] - r[0] >= self.LONG_RUN:
                self._unpack([r])
        if short:
            self._unpack(short)
        self._done |= todo

    def _ensure(self, a: int, b: int) -> None:
        """Unpack every block that bins ``[a, b)`` touch."""
        if b <= a:
            return
        first, last = a // self.BLOCK, (b - 1) // self.BLOCK + 1
        if self._done[first:last].all():
            return
        need = np.zeros(self._done.size, bool)
        need[first:last] = True
        self._ensure_blocks(need)

    def prefetch(self, ranges: list[tuple[int, int]]) -> None:
        """Unpack the bins of every ``[a, b)`` of ``ranges`` (clipped to the spectrum) in one go:
        what a reader about to read several bands calls first."""
        need = np.zeros(self._done.size, bool)
        for a, b in ranges:
            a, b = max(int(a), 0), min(int(b), self.size)
            if b > a:
                need[a // self.BLOCK:(b - 1) // self.BLOCK + 1] = True
        self._ensure_blocks(need)

    def __getitem__(self, key):
        if isinstance(key, (int, np.integer)):
            k = int(key)
            k = k + self.size if k < 0 else k
            if not 0 <= k < self.size:
                raise IndexError(f"bin {int(key)} is outside a spectrum of {self.size} bins")
            self._ensure(k, k + 1)
            return self._out[k]
        if isinstance(key, slice):
            a, b, step = key.indices(self.size)
            if step == 1:
                self._ensure(a, b)
            else:
                self._ensure(0, self.size)
            view = self._out[key]
            view.flags.writeable = False
            return view
        idx = np.asarray(key)
        if idx.dtype.kind == "b":
            idx = np.flatnonzero(idx)
        if idx.dtype.kind not in "iu":
            raise IndexError(f"spectrum bins are indexed by integers, slices or masks, not {idx.dtype}")
        if idx.size == 0:
            return self._out[idx]
        # two passes over the indices, then the gather: the search reads bands of ~10^4 bins at once
        lo, hi = int(idx.min()), int(idx.max())
        if lo < 0:
            idx = np.where(idx < 0, idx + self.size, idx)
            lo, hi = int(idx.min()), int(idx.max())
        if lo < 0 or hi >= self.size:
            raise IndexError(f"bins {lo}..{hi} reach outside a spectrum of {self.size} bins")
        if hi - lo < 4 * idx.size + 4 * self.BLOCK:  # compact (a band, nearby windows): unpack the span
            self._ensure(lo, hi + 1)
        else:
            need = np.zeros(self._done.size, bool)
            need[idx.ravel() // self.BLOCK] = True
            self._ensure_blocks(need)
        return self._out[idx]

    def complex_at(self, idx: np.ndarray) -> np.ndarray | None:
        """``rfft(y)[idx]`` itself, complex128, shape of ``idx`` (bins ``0..h``), from the packed FFT
        by the split above; None once the packed FFT was released (every bin unpacked in its buffer)."""
        z, h = self._z, self._h
        if z is None:
            return None
        k = np.asarray(idx, dtype=np.int64)
        zk = z[k % h].astype(np.complex128)
        zr = np.conj(z[(-k) % h]).astype(np.complex128)
        tw = np.exp(-1j * np.pi * (k % (2 * h)) / h)  # W^k, W = exp(-2j*pi/m), m = 2h; angle from the integer
        return ((zk + zr) - 1j * tw * (zk - zr)) / 2

    def unpack_all(self) -> np.ndarray:
        """Every bin, unpacked in one pass in the FFT's own buffer (read-only view of the store)."""
        if not self._done.any():
            self._unpack([(0, self.size)])
            self._done[:] = True
        else:
            self._ensure(0, self.size)
        full = self._out.view()
        full.flags.writeable = False
        return full

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        full = self.unpack_all()
        if dtype is not None and np.dtype(dtype) != full.dtype:
            return full.astype(dtype)
        return full.copy() if copy else full

    def __getattr__(self, name: str):
        # any other ndarray attribute (max, argmax, sum, ...) on the whole spectrum
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self.__array__(), name)

    @property
    def unpacked_fraction(self) -> float:
        """Part of the spectrum unpacked so far (diagnostics)."""
        return float(np.mean(self._done))


def real_power(y: np.ndarray) -> np.ndarray:
    """``|rfft(y)|^2``, shape ``(m//2 + 1,)``, of a real record of even length ``m``: every bin
    of :func:`real_power_packed` unpacked.

    Parameters
    ----------
    y : ndarray, shape (m,), float32 or float64, C-contiguous, m even; overwritten
    """
    return np.array(real_power_packed(y))


def real_power_packed(y: np.ndarray, keep: bool = False) -> PackedPower:
    """``|rfft(y)|^2`` of a real record of even length ``m`` as a :class:`PackedPower`: one complex
    FFT of half the length, unpacked where read.

    Parameters
    ----------
    y : ndarray, shape (m,), float32 or float64, C-contiguous, m even; overwritten (the pairs
        ``(y[2k], y[2k+1])`` are taken as one complex sample, a view, and transformed in place)
    keep : bool, :class:`PackedPower`'s
    """
    return PackedPower(scipy.fft.fft(y.view(np.complex64 if y.dtype == np.float32 else np.complex128),
                                     overwrite_x=True), keep)


#: records at least this long keep their spectrum packed (:class:`PackedPower`, unpacked where
#: read); shorter ones are unpacked at once. Measured on the 2-core bench machine: at 1.25e5
#: samples (``fast``'s Doppler spectrum) the whole unpacking costs about what reading a third of
#: it block by block adds; at 1e6, where the search reads 8-30 % of 5e5 bins, the lazy spectrum
#: saves 0.6-1.3 ms a frame
LAZY_MIN_SAMPLES = 1 << 18


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
    dtype = (np.complex64 if single else np.complex128) if np.iscomplexobj(seg) else (
        np.float32 if single else np.float64)
    # (seg - mean) * w in one buffer of the transform's dtype (aligned for FFTW's SIMD kernels: an
    # unaligned input costs it a copy, 5.8 against 3.5 ms for a 1e6-sample rfft)
    y = np.empty(m, dtype=dtype) if _fft_backend == "pocketfft" else _aligned_empty(m, dtype)
    total = np.sum(seg)  # seg.mean() is this over m: the same numbers, and the sum kept
    np.subtract(seg, total / m, out=y, casting="same_kind")
    y *= cached_window(win, m, "float32" if single else "float64")
    wp = window_power(win, m)
    if np.iscomplexobj(y):
        X = scipy.fft.fftshift(scipy.fft.fft(y, overwrite_x=True))
        f0 = -fs_hz / 2 if m % 2 == 0 else -fs_hz / 2 + fs_hz / (2 * m)
        p = (X.real**2 + X.imag**2)
        # complex noise: E|X|^2 = s2_total * sum(w^2); keep the per-quadrature convention
        return Spectrum(p, fs_hz / m, f0, wp, m, True, complex(total), bins=X, window=win)
    if m % 2 == 0 and _fft_backend == "pocketfft":  # FFTW's own real transform is faster than the packing
        p = bins = real_power_packed(y, keep=m < LAZY_MIN_SAMPLES)
        if m < LAZY_MIN_SAMPLES:
            p = p.unpack_all()  # short: unpacking it all costs less than reading it block by block
    else:
        X = bins = scipy.fft.rfft(y, overwrite_x=True)
        p = X.real**2 + X.imag**2
    # real noise of variance s2: E|X|^2 = s2 * sum(w^2)
    return Spectrum(p, fs_hz / m, 0.0, wp, m, False, float(total), bins=bins, window=win)


def local_floor(power: np.ndarray, inner: int = 8, outer: int = 48, mirror_dc: bool = False,
                ranges: list[tuple[int, int]] | None = None) -> np.ndarray:
    """Mean noise power around every bin, from the bins ``inner..outer`` away on both sides.

    A geometric mean (mean of ``log power``) corrected by Euler's constant, the bias of the mean
    log of an exponential variable: robust to the odd line in the ring, and local enough to follow
    coloured floors such as the laser phase-noise pedestal around a strong line, which a Doppler
    candidate inside it must beat (a wide-block median sits below the pedestal and lets its
    slope pass for a line). The ring skips the candidate's own main lobe (Kaiser(14): +-4.6 bins).

    Parameters
    ----------
    power : ndarray, shape (B,), periodogram (V^2)
    ranges : list of (first, stop) bin ranges, optional
        Compute the floor there only (the Doppler search looks at the bands around 0 Hz and the
        tones alone; the rest of a 1e6-sample spectrum would cost more than the search). Bins
        outside are NaN. The values inside are those of the whole-spectrum computation.

    Returns
    -------
    ndarray, shape (B,), the local mean noise power (V^2)
    """
    nb = power.size
    if ranges is None:
        ranges = [(0, nb)]
    tiny = np.finfo(power.dtype).tiny if power.dtype.kind == "f" else 1e-300
    # a real signal's spectrum is even about 0 Hz and about fs/2: at both ends the ring continues
    # on the mirror side (one-sided, it would see only the falling side of a pedestal around
    # 0 Hz); an fftshifted complex spectrum is periodic: the ring wraps around +-fs/2
    merged = _merged(ranges, nb)
    out = np.empty(nb)
    edges = [0, *(e for r in merged for e in r), nb]
    for a, b in zip(edges[::2], edges[1::2]):  # NaN between the ranges (each range is written below)
        out[a:b] = np.nan
    if hasattr(power, "prefetch"):  # a PackedPower: unpack every band the rings reach at once
        reach = [(max(lo - outer, 0), min(hi + outer, nb)) for lo, hi in merged]
        if mirror_dc:
            reach += [(0, outer + 1)] if merged and merged[0][0] < outer else []
            reach += [(nb - outer - 1, nb)] if merged and merged[-1][1] > nb - outer else []
        else:
            reach += [(0, outer)] if merged and merged[-1][1] > nb - outer else []
            reach += [(nb - outer, nb)] if merged and merged[0][0] < outer else []
        power.prefetch(reach)
    for lo, hi in merged:
        if lo - outer >= 0 and hi + outer <= nb:  # the ring stays inside: a slice
            seg = power[lo - outer:hi + outer]
        else:
            idx = np.arange(lo - outer, hi + outer)
            if mirror_dc:
                idx = np.abs(idx)  # numpy's "reflect" padding, about bin 0 and bin B-1
                idx = np.where(idx > nb - 1, 2 * (nb - 1) - idx, idx)
            else:
                idx %= nb
            seg = power[idx]
        lp = np.log(np.maximum(seg, tiny)).astype(np.float64)  # lp[j]: bin lo - outer + j
        n = hi - lo
        ring = sliding_sums(lp, outer - inner + 1)  # ring[j] = sum(lp[j : j + outer - inner + 1])
        # bin lo + i: the left ring starts at lp[i] (bin - outer), the right one at lp[i + outer + inner]
        total = ring[:n] + ring[outer + inner: outer + inner + n]
        out[lo:hi] = np.exp(total / (2.0 * (outer - inner + 1)) + EULER_GAMMA)
    return out


def sliding_sums(v: np.ndarray, width: int) -> np.ndarray:
    """``sum(v[i : i + width])`` for every ``i <= v.size - width``, shape ``(v.size - width + 1,)``.

    By doubling: sums over 1, 2, 4, ... samples, each from the one before in one vector add, and
    the window as the sum of those its binary digits name -- ``log2(width) + popcount(width)``
    passes, vectorised (numpy's running sum is a scalar loop, and its differences lose the digits
    of the running total: this sums each window's own terms only).

    Parameters
    ----------
    v : ndarray, shape (L,), float64
    width : int, 1 <= width <= L
    """
    count = v.size - width + 1
    acc = np.zeros(count)
    part, span, offset = v, 1, 0  # part[i] = sum(v[i : i + span])
    while True:
        if width & 1:
            acc += part[offset:offset + count]
            offset += span
        width >>= 1
        if not width:
            return acc
        part = part[:-span] + part[span:]
        span *= 2


def _merged(ranges: list[tuple[int, int]], nb: int) -> list[tuple[int, int]]:
    """``ranges`` clipped to ``[0, nb)``, sorted, overlapping ones merged."""
    out: list[list[int]] = []
    for lo, hi in sorted((max(int(a), 0), min(int(b), nb)) for a, b in ranges):
        if hi <= lo:
            continue
        if out and lo <= out[-1][1]:
            out[-1][1] = max(out[-1][1], hi)
        else:
            out.append([lo, hi])
    return [(a, b) for a, b in out]


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
    if hasattr(p, "prefetch"):  # a PackedPower: every window unpacked in one go
        ks = [int(k) for k in spec.bin_of(np.asarray(centres, dtype=float))]
        p.prefetch([(k - half_span, k + half_span + 1) for k in ks])
    widths = []
    for f in centres:
        k0 = int(spec.bin_of(f))
        lo, hi = max(k0 - half_span, 0), min(k0 + half_span + 1, p.size)
        w = equivalent_width(p[lo:hi].copy(), dc - lo)
        if w is not None:
            widths.append(w)
    return float(np.median(widths)) if widths else 1.0


def equivalent_width(seg: np.ndarray, dc: int | None = None) -> float | None:
    """The equivalent width (bins) of the strongest line in ``seg`` (shape (K,), power, any unit):
    ``sum/max`` over its contiguous bins within 20 dB of its peak (a second line nearby, e.g. the
    other Doppler sideband, is not counted); ``dc``: the index of 0 Hz in ``seg``, whose bin and
    neighbours (the mean-removal notch) are no line; None where ``seg`` holds no power. Modifies
    ``seg`` in place."""
    if dc is not None and 0 <= dc < seg.size:
        seg[max(dc - 1, 0): dc + 2] = 0.0
    if not seg.size or seg.max() <= 0:
        return None
    k = int(np.argmax(seg))
    m = float(seg[k])
    above = seg >= 0.01 * m
    r = k + (int(np.argmin(above[k:])) if not above[k:].all() else seg.size - k)
    l_ = k - (int(np.argmin(above[: k + 1][::-1])) if not above[: k + 1].all() else k + 1) + 1
    return float(seg[l_:r].sum()) / m


#: a partial search spectrum (``doppler_fraction`` < 1: ``fast``) takes at least this many samples
#: (the whole record when shorter): below it the partial spectrum saves less than the whole
#: record's transform costs (~0.6 ms at 2^16) and loses 9 dB of a line's SNR (an eighth) -- the
#: honesty map's ``fast`` misses at 2^16 samples were further movers its eighth-record spectrum
#: held below threshold
SEARCH_MIN_SAMPLES = 2**16


def search_length(n: int, fraction: float) -> int:
    """The samples the search spectrum of an ``n``-sample record (or echo window) transforms: the
    first ``fraction`` of it, at least :data:`SEARCH_MIN_SAMPLES`, at most all of it."""
    return min(n, max(SEARCH_MIN_SAMPLES, int(n * fraction)))


def whole_record(spec: Spectrum, x: np.ndarray, fs_hz: float) -> Spectrum:
    """``spec`` where it is the whole record's (``record_n`` None), else the whole record ``x``'s
    spectrum in the same window, taken once per ``spec`` (kept in its ``memo``).

    Floors read within a few tens of bins of a line need the record's own resolution: ``fast``'s
    eighth-record bins are 8x wider, and its ring 5-32 bins out about a sub-guard mover 3 record
    bins up read 0.8-4.9 MHz where the whole record's read 0.1-0.6 MHz: 26x less of a static
    echo's pedestal about 0 Hz (the envelope probe's scene 42078, a 1 MHz laser: a sub-guard
    mover's speed 6 sigmas off at the eighth's floors, 1.2 at the record's).
    """
    if spec.record_n is None or spec.record_n != x.size:
        return spec
    kept = spec.memo.get("whole_record")
    if kept is None or kept[0]() is not x:  # taken of this very record (the memo outlives no frame, but say so)
        kept = (weakref.ref(x), power_spectrum(x, fs_hz, spec.window if spec.window is not None else ("kaiser", 14.0)))
        spec.memo["whole_record"] = kept
    return kept[1]


def search_spectrum(x: np.ndarray, fs_hz: float, beta: float, fraction: float, single: bool,
                    windows: list[tuple[int, int]] | None = None) -> Spectrum:
    """The stage: the Kaiser(``beta``) spectrum of the first ``fraction`` of the record, at least
    :data:`SEARCH_MIN_SAMPLES` of it.

    A quasi-CW record's spectrum is taken over its longest echo window alone: the gate's own
    harmonics around every line (multiples of 1/period) would otherwise pass for Doppler pairs.

    Parameters
    ----------
    x : ndarray, shape (N,), float64 or complex128, V
    windows : list of (start, stop) sample indices where the echo is on, or None (CW)
    """
    xs = x
    if windows:
        a, b = max(windows, key=lambda w: w[1] - w[0])
        xs = x[a:b]
    n = search_length(xs.size, fraction)
    spec = power_spectrum(xs, fs_hz, ("kaiser", beta), n, single)
    return replace(spec, record_n=xs.size) if n < xs.size else spec



#: :class:`LowBand` keeps at least this many blocks, and this many per record bin of its band
LOW_BAND_MIN_BLOCKS, LOW_BAND_BLOCKS_PER_BIN = 128, 16
#: the window :meth:`LowBand.line_at` reads a line's width through (the search spectrum's)
LOW_BAND_KAISER_BETA = 14.0


@dataclass(frozen=True)
class LowBand:
    """The record's lowest frequencies from its block sums: one pass over the record, then the
    DFT near 0 Hz from ``M`` block sums instead of ``N`` samples.

    Summing ``B`` consecutive samples is a boxcar filter of length ``B`` followed by decimation
    by ``B``. A line at ``f`` well inside ``fs/(2B)`` passes with the boxcar's droop
    ``G(f) = sin(pi*f*B/fs)/sin(pi*f/fs)`` (against ``B``), which :meth:`dft` divides out;
    whatever folds onto such an ``f`` from above lies ``f`` from a multiple of ``fs/B``, a null of
    the boxcar, and passes at ``|G| ~ pi*f/(fs*sin(pi*f_line/fs))`` -- a line 300 MHz away, folded
    onto 6 record bins of a 1e6-sample record, is 84 dB down. White noise keeps the statistics of
    the record's own DFT (``E|X(f)|^2 = N*s2``). Built for the questions asked of the band below a
    Doppler search's guard (is there a baseband line, does the carrier beat vary), not for phases.

    Attributes
    ----------
    sums : ndarray, shape (M,), V: block sums of the record less its mean
    tail : ndarray, shape (N - M*B,), V: the samples that fill no block, less the mean
    block : int, ``B``
    n : int, the record's length ``N``
    fs_hz : float
    """

    sums: np.ndarray
    tail: np.ndarray
    block: int
    n: int
    fs_hz: float

    @classmethod
    def of(cls, x: np.ndarray, fs_hz: float, band_bins: float) -> "LowBand":
        """The block sums of ``x`` (shape (N,), float64 or complex128, V) for a band of
        ``band_bins`` record bins (``fs/N``) about 0 Hz: :data:`LOW_BAND_BLOCKS_PER_BIN` blocks
        per bin (at least :data:`LOW_BAND_MIN_BLOCKS`, a power of two, at most ``N/4``); the
        record's mean from the sums themselves (one pass)."""
        n = x.size
        want = max(LOW_BAND_MIN_BLOCKS, LOW_BAND_BLOCKS_PER_BIN * band_bins)
        m = int(min(2 ** math.ceil(math.log2(want)), max(n // 4, 1)))
        b = n // m
        sums = x[:m * b].reshape(m, b).sum(axis=1)
        tail = x[m * b:]
        mean = (np.sum(sums) + np.sum(tail)) / n
        return cls(sums - mean * b, tail - mean, b, n, float(fs_hz))

    def _droop(self, r: np.ndarray) -> np.ndarray:
        """The block sum's gain at ``r`` cycles per sample against ``B``: ``sin(pi*r*B)/(B*sin(pi*r))``
        (1 at 0 Hz)."""
        b = self.block
        den = np.sin(np.pi * r)
        return np.where(den == 0, 1.0, np.sin(np.pi * r * b) / (b * np.where(den == 0, 1.0, den)))

    def dft(self, freqs_hz) -> np.ndarray:
        """``exact_dft(x - mean(x), f, fs)`` (phase about the record's centre) for frequencies in
        the band, shape (K,), complex128."""
        f = np.atleast_1d(np.asarray(freqs_hz, dtype=np.float64))
        r = f / self.fs_hz  # cycles per sample
        c = (self.n - 1) / 2.0
        m, b = self.sums.size, self.block
        centres = np.arange(m, dtype=np.float64) * b + (b - 1) / 2.0 - c  # block centres from the record's
        droop = self._droop(r)
        # the band's phases stay within a few hundred cycles over the record: no reduction needed
        out = (np.exp(-2j * np.pi * np.outer(r, centres)) @ self.sums) / droop
        if self.tail.size:
            t_idx = np.arange(m * b, self.n, dtype=np.float64) - c
            out = out + np.exp(-2j * np.pi * np.outer(r, t_idx)) @ self.tail
        return out

    @cached_property
    def _kaiser_spectrum(self) -> np.ndarray:
        """The FFT of the block sums through a Kaiser(:data:`LOW_BAND_KAISER_BETA`) window over the
        record, sampled at the blocks' centres (the window is near flat across a block: the record's
        windowed DFT to ~1e-5), shape (M,), complex, V; the grid is ``k*fs/(M*B)``."""
        m, b = self.sums.size, self.block
        pos = np.arange(m, dtype=np.float64) * b + (b - 1) / 2.0
        arg = 1.0 - (2.0 * pos / max(self.n - 1, 1) - 1.0) ** 2
        w = np.i0(LOW_BAND_KAISER_BETA * np.sqrt(np.clip(arg, 0.0, 1.0))) / np.i0(LOW_BAND_KAISER_BETA)
        return scipy.fft.fft(self.sums * w)

    def line_at(self, f_hz: float, half_span: int = 16) -> tuple[float, float]:
        """The strongest line within ``half_span`` record bins of ``f_hz`` (inside the band; signed
        for an IQ record), seen at the record's own resolution through the search spectrum's Kaiser
        window: its equivalent width (record bins, :func:`equivalent_width`: 1-2.3 bins for a
        coherent line) and its contrast, its peak over the median of the bins more than 3 from it
        (a coherent line stands out by its SNR; a laser's Lorentzian, whose periodogram at this
        resolution is a ragged top of spikes a bin or two wide, by ~5 typically and by up to 39 in
        900 draws of 0.3-10 MHz lasers at 2^16). For where a search spectrum of part of the record
        (``fast``'s eighth) reads neighbouring lines as one broad line."""
        m, b = self.sums.size, self.block
        spec = self._kaiser_spectrum
        k0 = int(round(f_hz * m * b / self.fs_hz))
        ks = np.arange(k0 - half_span, k0 + half_span + 1)
        r = ks / float(m * b)  # cycles per sample
        seg = np.abs(spec[ks % m]) ** 2 / self._droop(r) ** 2
        dc = np.flatnonzero(ks == 0)
        w = equivalent_width(seg, int(dc[0]) if dc.size else None)  # the DC notch zeroed in seg too
        if w is None:
            return 1.0, 0.0
        k = int(np.argmax(seg))
        ring = np.concatenate([seg[:max(k - 3, 0)], seg[k + 4:]])
        ring = ring[ring > 0]
        return w, (float(seg[k]) / float(np.median(ring)) if ring.size else math.inf)

    def scan(self, lo_hz: float, hi_hz: float, step_bins: float, both_signs: bool) -> tuple[np.ndarray, np.ndarray]:
        """``exact_dft(x - mean(x), f, fs)`` on a grid of about ``step_bins`` record bins over
        ``lo_hz <= |f| <= hi_hz`` (``f >= 0`` only unless ``both_signs``), by one zero-padded FFT of
        the block sums: the grid is ``k*fs/(P*M*B)`` with ``P*M`` a power of two (``M*B`` the
        samples in whole blocks, the record less its tail of fewer than ``M`` samples, which the
        scan leaves out); each value turned to the record's centre, as :meth:`dft`. For finding a
        peak, not for its phase's last digit.

        Returns
        -------
        f : ndarray, shape (G,), Hz, ascending (the negative half after the positive one for IQ)
        x : ndarray, shape (G,), complex, V
        """
        m, b = self.sums.size, self.block
        pad = int(2 ** math.ceil(math.log2(max(self.n / (b * step_bins), m))))
        spec = scipy.fft.fft(self.sums, pad)
        f = np.fft.fftfreq(pad, d=b / self.fs_hz)  # Hz
        keep = (np.abs(f) >= lo_hz) & (np.abs(f) <= hi_hz) & ((f > 0) | both_signs)
        f = f[keep]
        r = f / self.fs_hz
        droop = self._droop(r)
        turn = np.exp(-2j * np.pi * r * ((b - 1) / 2.0 - (self.n - 1) / 2.0))  # block 0's centre from the record's
        order = np.concatenate([np.flatnonzero(f > 0), np.flatnonzero(f < 0)])
        return f[order], (spec[keep] * turn / droop)[order]


#: a single-photodiode echo moving ``x`` record bins splits its line into two at ``+-x`` (a real
#: envelope ``cos(2*pi*x*t/T + Phi)``): its equivalent width grows by at least this times ``x^2``
#: bins over a still line's, at every ``Phi`` (0.6-1.0 from 0.1 to 0.5 bin, Kaiser(14))
WIDTH_PER_BIN2 = 0.6


@lru_cache(maxsize=64)
def _still_width(beta: float, offset: float) -> float:
    """The equivalent width (bins) of a still line ``offset`` bins from a bin's centre through a
    Kaiser(``beta``) window (shape-invariant in the record's length: a 4096-sample window)."""
    m = 4096
    w = get_window(("kaiser", beta), m, fftbins=False)
    k = np.arange(-32, 33) - offset
    p = np.abs(np.exp(-2j * np.pi * np.outer(k, np.arange(m)) / m) @ w) ** 2
    return float(equivalent_width(p) or 0.0)


def width_doppler_bins(width: float, beta: float, offset: float = 0.0) -> float:
    """The largest Doppler (record bins) of a one-photodiode echo whose line, ``offset`` bins from a
    bin's centre, shows an equivalent width ``width`` (bins) through a Kaiser(``beta``) window
    (:data:`WIDTH_PER_BIN2`)."""
    return math.sqrt(max(width - _still_width(beta, round(abs(offset), 2)), 0.0) / WIDTH_PER_BIN2)


def still_line_doppler_bins(spec: Spectrum, freqs_hz, beta: float) -> float | None:
    """The largest Doppler (record bins) an echo on one photodiode could have and still show its
    lines at ``freqs_hz`` as narrow as they are in the search spectrum (Kaiser(``beta``)): from the
    median of their widths' bounds (:func:`width_doppler_bins`); None where the spectrum is of part
    of the record (``fast``'s, whose bins are 8x wider) or no width is read -- a line whose
    neighbourhood peaks more than a bin from it gives none (an echo moving ~2.6 bins or more shows
    two narrow lines, a stronger mover beside it its own). Noise in the bins widens a line: the
    bound errs large."""
    if spec.record_n is not None:
        return None
    freqs = np.atleast_1d(np.asarray(freqs_hz, dtype=float))
    if not spec.complex_input:
        freqs = np.abs(freqs)
    p = spec.power
    dc = int(spec.bin_of(0.0))
    ks = [int(k) for k in spec.bin_of(freqs)]
    if hasattr(p, "prefetch"):
        p.prefetch([(k - 32, k + 33) for k in ks])
    excess = []
    for f, k0 in zip(freqs, ks):
        lo, hi = max(k0 - 32, 0), min(k0 + 33, p.size)
        seg = np.asarray(p[lo:hi], dtype=np.float64).copy()
        if 0 <= dc - lo < seg.size:
            seg[max(dc - lo - 1, 0):dc - lo + 2] = 0.0  # the mean's notch
        if not seg.size or abs(int(np.argmax(seg)) - (k0 - lo)) > 1:
            continue  # its peak is not the line's: split lines (an echo moving ~2.6 bins or more), a mover
        w = equivalent_width(seg)
        if w is not None:
            excess.append(width_doppler_bins(w, beta, (f - spec.f0_hz) / spec.df_hz - k0))
    return float(np.median(excess)) if excess else None
