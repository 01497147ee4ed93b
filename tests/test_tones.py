"""mtcw_core.dsp.tones: exact DFT at arbitrary frequencies and joint least-squares line fits."""

from __future__ import annotations

import numpy as np
import pytest

from mtcw_core.dsp import tones
from mtcw_core.dsp.tones import (exact_dft, exact_dft_parts, exact_dft_tiled, fit_lines, fit_lines_segments, mean_leak,
                                  phasors)

FS = 1.0e9


def centred(n: int) -> np.ndarray:
    return np.arange(n) - (n - 1) / 2.0


def real_tones(n, freqs, amps, phases, dc=0.0, ref=None):
    """sum A cos(2*pi*f*(k - ref)/fs + p) + dc, ref the record's centre by default."""
    k = np.arange(n) - ((n - 1) / 2.0 if ref is None else ref)
    x = np.full(n, dc, float)
    for f, a, p in zip(freqs, amps, phases):
        x += a * np.cos(2 * np.pi * np.mod(k * (f / FS), 1.0) + p)
    return x


def complex_tones(n, freqs, amps, phases):
    k = centred(n)
    x = np.zeros(n, complex)
    for f, a, p in zip(freqs, amps, phases):
        x += a * np.exp(1j * (2 * np.pi * np.mod(k * (f / FS), 1.0) + p))
    return x


def direct_dft(x, freqs):
    k = centred(x.size)
    return np.array([np.sum(x * np.exp(-2j * np.pi * np.mod(k * (f / FS), 1.0))) for f in freqs])


class TestExactDft:
    @pytest.mark.parametrize("n", [1000, 1024, 3001, 4096])
    def test_matches_direct_sum(self, n):
        rng = np.random.default_rng(n)
        x = rng.standard_normal(n)
        freqs = np.array([0.0, 12.3e6, -77.7e6, 250.000001e6, 499e6])
        got = exact_dft(x, freqs, FS)
        want = direct_dft(x, freqs)
        assert got.shape == (freqs.size,) and got.dtype == np.complex128
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * np.sqrt(n))

    def test_complex_input(self):
        rng = np.random.default_rng(1)
        x = rng.standard_normal(2000) + 1j * rng.standard_normal(2000)
        freqs = [-300e6, 1.5e6, 333.3e6]
        np.testing.assert_allclose(exact_dft(x, freqs, FS), direct_dft(x, freqs), atol=1e-9 * 50)

    def test_scalar_frequency(self):
        x = np.ones(256)
        np.testing.assert_allclose(exact_dft(x, 0.0, FS), [256.0], rtol=1e-14)

    def test_on_bin_tone_is_n_times_half_amplitude(self):
        n = 1024
        f = 37 * FS / n
        x = real_tones(n, [f], [2.0], [0.4])
        y = exact_dft(x, [f], FS)[0]
        # sum_k 2 cos(w k' + p) e^{-j w k'} = N e^{jp} (the image sums to 0 on the grid)
        assert y == pytest.approx(n * np.exp(0.4j), rel=1e-12)

    def test_float32_input(self):
        rng = np.random.default_rng(2)
        x = rng.standard_normal(1024).astype(np.float32)
        freqs = [10.1e6, 200.7e6]
        np.testing.assert_allclose(exact_dft(x, freqs, FS), direct_dft(x.astype(float), freqs), atol=1e-4)


class TestFitLines:
    # two tones 0.3 and 0.71 of a bin off the grid, and 1.41 bins apart (their leakage overlaps)
    N = 4096
    DF = FS / N
    F = np.array([(100 + 0.3) * DF, (101 + 0.71) * DF])
    A = np.array([1.3, 0.45])
    P = np.array([0.7, -2.4])

    def check(self, z, amps, phases, rtol=1e-12):
        np.testing.assert_allclose(np.abs(z), amps, rtol=rtol)
        np.testing.assert_allclose(np.angle(z * np.exp(-1j * np.asarray(phases))), 0.0, atol=rtol)

    def test_real_two_close_tones_off_grid(self):
        x = real_tones(self.N, self.F, self.A, self.P, dc=0.37)
        self.check(fit_lines(x, self.F, FS), self.A, self.P)

    def test_real_tones_far_apart(self):
        f = np.array([(211 + 0.3) * self.DF, (1500 + 0.71) * self.DF, 7.77 * self.DF])
        a, p = np.array([1.0, 0.01, 3.0]), np.array([3.0, -3.0, 0.1])
        x = real_tones(self.N, f, a, p, dc=-2.0)
        self.check(fit_lines(x, f, FS), a, p)

    def test_complex_signed_frequencies(self):
        f = np.array([self.F[0], -self.F[1], 0.0])
        a, p = np.array([1.3, 0.45, 0.2]), np.array([0.7, -2.4, 1.0])
        x = complex_tones(self.N, f, a, p)
        self.check(fit_lines(x, f, FS), a, p)

    def test_odd_length(self):
        n = 3001
        f = np.array([(50 + 0.3) * FS / n, (52 + 0.71) * FS / n])
        x = real_tones(n, f, self.A, self.P, dc=1.0)
        self.check(fit_lines(x, f, FS), self.A, self.P)

    def test_dft_argument_reused(self):
        x = real_tones(self.N, self.F, self.A, self.P)
        d = exact_dft(x, self.F, FS)
        np.testing.assert_array_equal(fit_lines(x, self.F, FS, dft=d), fit_lines(x, self.F, FS))

    def test_total_argument_reused(self):
        """The record's sum handed in (as the extract stage does, sharing it with the record's
        mean) gives the fit of the sum computed inside, and a wrong sum moves the fit."""
        x = np.random.default_rng(11).standard_normal(5000) + 0.3
        f = [1.4 * FS / 5000, 0.23 * FS]  # a line 1.4 bins from DC: the DC column matters to it
        ref = fit_lines(x, f, FS)
        np.testing.assert_array_equal(fit_lines(x, f, FS, total=float(np.sum(x))), ref)
        assert abs(fit_lines(x, f, FS, total=float(np.sum(x)) + 500.0)[0] - ref[0]) > 1e-3

    def test_phase_referred_to_the_centre(self):
        """A tone with phase p at sample 0 has phase p + 2*pi*f*(N-1)/(2*fs) at the centre."""
        f, p0 = self.F[0], 0.3
        x = real_tones(self.N, [f], [1.0], [p0], ref=0.0)
        z = fit_lines(x, [f], FS)[0]
        want = p0 + 2 * np.pi * np.mod(f / FS * (self.N - 1) / 2, 1.0)
        assert np.angle(z * np.exp(-1j * want)) == pytest.approx(0.0, abs=1e-11)

    @pytest.mark.parametrize("dtype", [np.float32, np.complex64])
    def test_single_precision_input(self, dtype):
        if dtype is np.float32:
            x = real_tones(self.N, self.F, self.A, self.P)
            f = self.F
        else:
            f = np.array([self.F[0], -self.F[1]])
            x = complex_tones(self.N, f, self.A, self.P)
        z = fit_lines(x.astype(dtype), f, FS)
        assert z.dtype == np.complex128
        self.check(z, self.A, self.P, rtol=2e-6)

    def test_white_noise_phase_variance(self):
        """Least squares in white noise: var(phase) ~ 2*s2/(N*A^2) for a real tone."""
        rng = np.random.default_rng(5)
        n, s, a = 1024, 0.5, 1.0
        f = (40 + 0.3) * FS / n
        clean = real_tones(n, [f], [a], [0.0])
        ph = [np.angle(fit_lines(clean + s * rng.standard_normal(n), [f], FS)[0]) for _ in range(400)]
        want = 2 * s**2 / (n * a**2)
        assert np.var(ph) == pytest.approx(want, rel=0.2)

    def test_duplicate_frequencies_are_singular(self):
        x = real_tones(self.N, self.F, self.A, self.P)
        with pytest.raises(np.linalg.LinAlgError):
            fit_lines(x, [self.F[0], self.F[0]], FS)


class TestFitLinesSegments:
    N = 4096
    F = np.array([(60 + 0.3) * FS / 1024, (75 + 0.71) * FS / 1024])
    A = np.array([1.0, 0.25])
    P = np.array([0.4, 2.9])

    def expected(self, starts, length):
        """Each segment's phasor: the record-centre phase advanced to the segment's centre."""
        c_full = (self.N - 1) / 2
        out = []
        for s in starts:
            dt = s + (length - 1) / 2 - c_full
            out.append(self.A * np.exp(1j * (self.P + 2 * np.pi * np.mod(self.F / FS * dt, 1.0))))
        return np.array(out)

    def test_real_segments_referred_to_their_centres(self):
        x = real_tones(self.N, self.F, self.A, self.P, dc=0.2)
        starts, length = np.array([0, 1024, 2048, 3072, 100]), 1024
        z = fit_lines_segments(x, starts, length, self.F, FS)
        assert z.shape == (5, 2)
        np.testing.assert_allclose(z, self.expected(starts, length), rtol=0, atol=1e-11)

    def test_complex_segments(self):
        f = np.array([self.F[0], -self.F[1]])
        k = np.arange(self.N) - (self.N - 1) / 2
        x = sum(a * np.exp(1j * (2 * np.pi * np.mod(k * fi / FS, 1.0) + p)) for fi, a, p in zip(f, self.A, self.P))
        starts, length = np.array([7, 2000]), 2000
        z = fit_lines_segments(x, starts, length, f, FS)
        c_full = (self.N - 1) / 2
        want = np.array([self.A * np.exp(1j * (self.P + 2 * np.pi * np.mod(f / FS * (s + (length - 1) / 2 - c_full),
                                                                             1.0))) for s in starts])
        np.testing.assert_allclose(z, want, atol=1e-11)

    def test_one_whole_segment_equals_fit_lines(self):
        x = real_tones(self.N, self.F, self.A, self.P, dc=0.2)
        z1 = fit_lines_segments(x, np.array([0]), self.N, self.F, FS)[0]
        np.testing.assert_allclose(z1, fit_lines(x, self.F, FS), atol=1e-12)

    def test_float32_input(self):
        x = real_tones(self.N, self.F, self.A, self.P).astype(np.float32)
        starts = np.array([0, 2048])
        z = fit_lines_segments(x, starts, 2048, self.F, FS)
        np.testing.assert_allclose(z, self.expected(starts, 2048), atol=1e-5)


def _direct_dft(x, f, fs):
    k = np.arange(x.size) - (x.size - 1) / 2
    return np.array([np.sum(x * np.exp(-2j * np.pi * np.mod(fi / fs * k, 1.0))) for fi in f])


@pytest.mark.parametrize("n", [1, 7, 64, 65, 1000, 4097, 2**16 + 3])
def test_exact_dft_is_the_direct_sum_for_any_length(n):
    """The factorised DFT (blocks, no padding, a tail of n mod M samples) equals the direct sum."""
    rng = np.random.default_rng(n)
    f = np.array([0.0, 123.4567e6, -7.3e6, 2.4e9])
    for x in (rng.standard_normal(n), rng.standard_normal(n) + 1j * rng.standard_normal(n)):
        np.testing.assert_allclose(exact_dft(x, f, 5e9), _direct_dft(x, f, 5e9), rtol=0, atol=1e-10 * np.sqrt(n))


@pytest.mark.parametrize("n", [1000, 4097, 2**16 + 3])
def test_one_line_is_the_direct_sum(n):
    """A single line on one real record (and one row of parts) takes matrix-vector products instead
    of the two-column matrix product: the same sums as the direct ones, and as several rows' batched
    product (the 2-D path of the parts' ends: ``TestPartDFTs.test_one_line``)."""
    rng = np.random.default_rng(n)
    x = rng.standard_normal(n)
    for f in ([0.0], [123.4567e6], [-7.3e6]):
        got = exact_dft(x, f, 5e9)
        assert got.shape == (1,) and got.dtype == np.complex128
        np.testing.assert_allclose(got, _direct_dft(x, f, 5e9), rtol=0, atol=1e-10 * np.sqrt(n))
        rows = x[:3 * (n // 3)].reshape(3, n // 3)
        np.testing.assert_allclose(exact_dft_parts(rows, f, 5e9)[:, 0],
                                   [_direct_dft(r, f, 5e9)[0] for r in rows], rtol=0, atol=1e-10 * np.sqrt(n))
        np.testing.assert_allclose(exact_dft_parts(x[None, :], f, 5e9)[0], got, rtol=1e-13)


@pytest.mark.parametrize("chunk", [8, 1000, 1 << 30])
def test_rows_times_table_in_chunks_is_the_product(monkeypatch, chunk):
    """Long products run a few rows at a time (``ROW_CHUNK_BYTES``): every row's sums are those of
    the whole product, for real and complex rows, 2-D and batched 3-D (strided rows, a last chunk
    shorter than the rest), and the DFTs built on them stay the direct sums."""
    monkeypatch.setattr(tones, "ROW_CHUNK_BYTES", chunk)
    rng = np.random.default_rng(chunk)
    table = rng.standard_normal((50, 3)) + 1j * rng.standard_normal((50, 3))
    record = rng.standard_normal(3 * 37 * 50 + 11)
    for a in (record[:37 * 50].reshape(37, 50), record[:3 * 37 * 50].reshape(3, 37, 50),
              record[5:5 + 3 * 37 * 50].reshape(3, 37, 50)[:, ::2],
              (record + 1j * record[::-1])[:37 * 50].reshape(37, 50)):
        np.testing.assert_allclose(tones._times_table(a, table), a @ table, rtol=1e-13, atol=1e-12)
    f = np.array([0.0, 123.4567e6, -7.3e6, 2.4e9])
    np.testing.assert_allclose(exact_dft(record, f, 5e9), _direct_dft(record, f, 5e9), rtol=0, atol=1e-9)


@pytest.mark.parametrize("macs, columns", [(500, 4), (20_000, 32), (10**9, 10**6)])
def test_wide_tables_in_column_groups_and_complex_rows_as_real_are_the_product(monkeypatch, macs, columns):
    """A real table runs at most ``PRODUCT_MAX_COLUMNS`` columns and ``PRODUCT_MAX_MACS``
    multiply-adds at a time, and complex rows meet the table's real form (``_real_pair``): every
    sum is the product's, for 1-21 lines, real and complex rows (contiguous, batched, strided
    rows, a complex view whose samples are not adjacent, which keeps the complex product)."""
    monkeypatch.setattr(tones, "ROW_CHUNK_BYTES", 4000)
    monkeypatch.setattr(tones, "PRODUCT_MAX_MACS", macs)
    monkeypatch.setattr(tones, "PRODUCT_MAX_COLUMNS", columns)
    rng = np.random.default_rng(macs)
    record = rng.standard_normal(3 * 37 * 50 + 11)
    iq = record + 1j * record[::-1]
    for k in (1, 2, 7, 21):
        table = rng.standard_normal((50, k)) + 1j * rng.standard_normal((50, k))
        for a in (record[:37 * 50].reshape(37, 50), record[5:5 + 3 * 37 * 50].reshape(3, 37, 50)[:, ::2],
                  iq[:37 * 50].reshape(37, 50), iq[:3 * 37 * 50].reshape(3, 37, 50)[:, 1::3],
                  iq[:2 * 37 * 50:2].reshape(37, 50)):
            got = tones._times_table(a, table)
            assert got.shape == a.shape[:-1] + (k,) and got.dtype == np.complex128
            np.testing.assert_allclose(got, a @ table, rtol=1e-13, atol=1e-12)
    table = rng.standard_normal((50, 21)) + 1j * rng.standard_normal((50, 21))
    pair = tones._real_pair(table)
    row = iq[:50]
    np.testing.assert_allclose((row.view(np.float64) @ pair).view(np.complex128), row @ table, rtol=1e-13)


def test_line_response_is_what_the_iq_fit_reads_of_a_line_it_models_elsewhere():
    """Each column of ``line_response`` is the complex fit's amplitudes for a unit line at a
    frequency it does not model: its own row the share it reads (``sinc`` of the offset for lines
    far apart), the others the leak the fit no longer takes out."""
    from mtcw_core.dsp.tones import line_response

    n, fs = 4096, 5e9
    freqs = np.array([0.0, 120e6, -330e6, 420e6])
    true = freqs + np.array([0.8, 0.3, -0.5, 0.0]) * fs / n
    got = line_response(freqs, true, fs, n)
    k = np.arange(n) - (n - 1) / 2
    for j, f in enumerate(true):
        want = fit_lines(np.exp(2j * np.pi * np.mod(f / fs * k, 1.0)), freqs, fs)
        np.testing.assert_allclose(got[:, j], want, atol=1e-9)
    np.testing.assert_allclose(np.diag(got)[:3], np.sinc([0.8, 0.3, 0.5]), rtol=2e-3)
    # the carrier 0.8 bin off the DC leaks into the 120 MHz line, k bins away, by the order of the
    # rectangular window's far skirt there, 1/(pi*k), which the fit no longer takes out
    k = 120e6 / (fs / n)
    assert 0.3 / (np.pi * k) < abs(got[1, 0]) < 2 / (np.pi * k)


def test_exact_dft_parts_refers_each_row_to_its_own_centre():
    rng = np.random.default_rng(2)
    parts = rng.standard_normal((4, 2501))
    f = [1e6, 333.3e6]
    got = exact_dft_parts(parts, f, 5e9)
    assert got.shape == (4, 2)
    np.testing.assert_allclose(got, [_direct_dft(p, f, 5e9) for p in parts], atol=1e-10)


def test_phasors_keep_float64_phase_at_large_indices():
    """exp(-2j*pi*((offset + i)*step mod 1)) from two small tables: the phase error stays at the
    float64 rounding of the reduced cycles, also half a million samples from the origin."""
    step = np.array([0.1234567891234, 0.4999999, 1e-7])
    got = phasors(-499999.5, 5000, step)
    i = -499999.5 + np.arange(5000)
    ref = np.exp(-2j * np.pi * np.mod(np.outer(i, step), 1.0))
    assert np.max(np.abs(np.angle(got * np.conj(ref)))) < 1e-9


def test_dirichlet_kernel_is_scipys():
    """The Gram matrices' kernel equals N * scipy.special.diric, at its limits (w = 2*pi*k) too."""
    from scipy.special import diric

    from mtcw_core.dsp.tones import _dirichlet

    w = np.concatenate([np.random.default_rng(0).uniform(-10, 10, 500), 2 * np.pi * np.arange(-3, 4),
                        2 * np.pi * np.arange(-3, 4) + 1e-9, [0.0, 1e-12]])
    for n in (1, 2, 7, 1000, 999_999):
        np.testing.assert_allclose(_dirichlet(w, n), n * diric(w, n), rtol=0, atol=1e-12 * n)


@pytest.mark.parametrize("n", [64, 257])
def test_real_gram_blocks_are_the_sums_of_products(n):
    """The real fit's Gram blocks against the sums written out over the centred index: cosines
    (with the DC column) and sines, lines near DC and near each other included."""
    from mtcw_core.dsp.tones import _gram_real

    w = 2 * np.pi * np.array([1.3, 2.1, 17.77, 0.43 * n]) / n
    k = np.arange(n) - (n - 1) / 2
    cos = np.cos(np.outer(k, np.concatenate([[0.0], w])))  # (n, K+1): DC, then the cosines
    sin = np.sin(np.outer(k, w))
    gc, gs = _gram_real(w, n)
    np.testing.assert_allclose(gc, cos.T @ cos, rtol=0, atol=1e-9 * n)
    np.testing.assert_allclose(gs, sin.T @ sin, rtol=0, atol=1e-9 * n)



@pytest.mark.parametrize("iq", [False, True])
def test_line_gains_are_the_fits_energy_differences(iq):
    """What one moved line adds to the fit, the others held, against two full solves differenced
    (the fit with the line at each trial minus the fit without it): real records (cosine block with
    the DC, sine block) and IQ, lines 1.5 bins apart, one near 0 Hz (its image) and a trial a
    fraction of a bin off."""
    from mtcw_core.dsp.tones import line_gains, solve_lines

    n, fs = 4096, 1e6
    rng = np.random.default_rng(1)
    f = np.array([150.0, 50e3, 120e3, 120e3 + 1.5 * fs / n, 300e3]) * (np.array([1, -1, 1, 1, -1]) if iq else 1)
    t = np.arange(n)
    x = sum(np.cos(2 * np.pi * ff * t / fs + k) for k, ff in enumerate(f)) + rng.standard_normal(n)
    if iq:
        x = x + 1j * rng.standard_normal(n)
    total = 0.0 if iq else float(np.sum(x))
    d = exact_dft(x, f, fs)
    moved = np.array([0, 2, 3, 4])
    trial = f[moved][:, None] + np.array([-0.3, 0.0, 0.02, 0.4]) * fs / n
    d_trial = exact_dft(x, trial.ravel(), fs).reshape(trial.shape)
    gains = line_gains(d, f, fs, n, total, iq, moved, trial, d_trial)
    for i, j in enumerate(moved):
        rest = np.delete(np.arange(f.size), j)
        without = solve_lines(d[rest], f[rest], fs, n, total, iq)[0]
        for p in range(trial.shape[1]):
            f2, d2 = f.copy(), d.copy()
            f2[j], d2[j] = trial[i, p], d_trial[i, p]
            assert gains[i, p] > 0
            np.testing.assert_allclose(gains[i, p], solve_lines(d2, f2, fs, n, total, iq)[0] - without, rtol=1e-9)



@pytest.mark.parametrize("iq", [False, True])
def test_solve_lines_many_is_solve_lines_per_set(iq):
    """The batched fit of several trial line sets against :func:`solve_lines` on each alone."""
    from mtcw_core.dsp.tones import solve_lines, solve_lines_many

    n, fs = 2048, 1e6
    rng = np.random.default_rng(2)
    x = rng.standard_normal(n) + (1j * rng.standard_normal(n) if iq else 0)
    total = 0.0 if iq else float(np.sum(x))
    base = np.array([40e3, 41e3, 200e3]) * (np.array([1, -1, 1]) if iq else 1)
    f = np.stack([base + d for d in (-300.0, 0.0, 250.0)])
    d = exact_dft(x, f.ravel(), fs).reshape(f.shape)
    energy, c = solve_lines_many(d, f, fs, n, total, iq)
    for b in range(f.shape[0]):
        e1, c1 = solve_lines(d[b], f[b], fs, n, total, iq)
        np.testing.assert_allclose(energy[b], e1, rtol=1e-10)
        np.testing.assert_allclose(c[b], c1, rtol=1e-9)



@pytest.mark.parametrize("iq", [False, True])
def test_lines_signal_is_the_fit_models_record(iq):
    """The record of known lines (chunked, phases from the integer index) against the model's sum
    written out, and fitted back to its amplitudes."""
    from mtcw_core.dsp.tones import lines_signal

    n, fs = 100_003, 1e6
    f = np.array([1234.5, 250e3, 251.7e3]) * (np.array([1, -1, 1]) if iq else 1)
    amps = np.array([1 + 2j, 0.3 - 0.1j, -0.5j])
    x = lines_signal(amps, f, fs, n, iq, chunk=4096)
    k = np.arange(n) - (n - 1) / 2
    want = (amps[None, :] * np.exp(2j * np.pi * np.outer(k, f) / fs)).sum(axis=1)
    np.testing.assert_allclose(x, want if iq else want.real, rtol=0, atol=1e-10)
    np.testing.assert_allclose(fit_lines(x, f, fs), amps, rtol=0, atol=1e-10)


def test_cached_tables_serve_repeated_frequencies_only():
    """A second transform at the same frequencies (a stream's static lines) reuses the tables and
    gives the same numbers; other frequencies get their own (checked against the direct sum)."""
    from mtcw_core.dsp.tones import _tables

    x = np.random.default_rng(12).standard_normal(10_007)
    k = np.arange(x.size) - (x.size - 1) / 2
    f1, f2 = np.array([0.1, 0.2]) * FS, np.array([0.1, 0.2 + 1e-9]) * FS
    a = exact_dft(x, f1, FS)
    hits = _tables.cache_info().hits
    np.testing.assert_array_equal(exact_dft(x, f1, FS), a)
    assert _tables.cache_info().hits == hits + 1
    b = exact_dft(x, f2, FS)
    direct = np.array([np.sum(x * np.exp(-2j * np.pi * f / FS * k)) for f in f2])
    np.testing.assert_allclose(b, direct, rtol=0, atol=1e-9 * np.abs(direct).max())
    eb, _, _ = _tables(x.size, (f1 / FS).tobytes())
    with pytest.raises(ValueError):
        eb[0, 0] = 0


class TestTiled:
    """exact_dft_tiled: the whole record's DFT and its parts' from one pass."""

    @pytest.mark.parametrize("n,parts", [(2**14, 8), (10_007, 16), (1000, 1)])
    def test_equals_the_direct_transforms(self, n, parts):
        rng = np.random.default_rng(n)
        f = np.array([3.3e6, 117.25e6, 301.0e6, 0.47e9])
        for x in (rng.standard_normal(n), rng.standard_normal(n) + 1j * rng.standard_normal(n)):
            whole, each = exact_dft_tiled(x, parts, f, FS)
            length = n // parts
            direct = exact_dft(x, f, FS)
            assert np.max(np.abs(whole - direct)) < 1e-9 * np.max(np.abs(direct))
            assert np.allclose(each, exact_dft_parts(x[:parts * length].reshape(parts, length), f, FS),
                               rtol=0, atol=1e-12 * np.max(np.abs(each)))

    def test_segment_fit_from_the_tiled_dfts_is_the_direct_fit(self):
        n, parts = 2**14, 16
        f = np.array([50e6, 120e6, 200e6])
        x = real_tones(n, f, [1.0, 0.5, 0.25], [0.1, 1.0, -2.0], dc=0.3)
        x = x + 0.01 * np.random.default_rng(2).standard_normal(n)
        length = n // parts
        starts = np.arange(parts) * length
        _, each = exact_dft_tiled(x, parts, f, FS)
        assert np.allclose(fit_lines_segments(x, starts, length, f, FS, each),
                           fit_lines_segments(x, starts, length, f, FS), rtol=0, atol=1e-12)


class TestPartDFTs:
    """PartDFTs: the Doppler refinement's windowed part DFTs, every part count from one pass."""

    N = 600_011  # blocks of 375 for up to 16 parts; no part count divides it

    @staticmethod
    def direct(x, parts, f, fs, beta=8.0):
        """Each part's (x - mean) * Kaiser(beta), summed against exp(-2j*pi*f*(j - (L-1)/2)/fs)."""
        from scipy.signal import get_window

        length = x.size // parts
        w = get_window(("kaiser", beta), length, fftbins=False)
        j = np.arange(length) - (length - 1) / 2
        e = np.exp(-2j * np.pi * np.mod(np.outer(j, np.asarray(f) / fs), 1.0))
        seg = x[:parts * length].reshape(parts, length)
        return ((seg - seg.mean(axis=1, keepdims=True)) * w) @ e

    def record(self, iq: bool):
        """A DC 40 dB above a strong line, and a line 60 dB below that, in a little noise."""
        rng = np.random.default_rng(5)
        k = np.arange(self.N)
        f = np.array([123.456e6, 123.456e6 + 2.1e6, 7.7e5])
        amp = np.array([1.0, 1e-3, 0.3])
        if iq:
            x = 100.0 + np.exp(2j * np.pi * np.mod(np.outer(k, f / FS), 1.0)) @ amp
            return x + 1e-4 * (rng.standard_normal(self.N) + 1j * rng.standard_normal(self.N)), f
        x = 100.0 + np.cos(2 * np.pi * np.mod(np.outer(k, f / FS), 1.0)) @ amp
        return x + 1e-4 * rng.standard_normal(self.N), f

    @pytest.mark.parametrize("iq", [False, True])
    def test_every_part_count_from_one_pass(self, iq):
        """Parts that start on no block edge (7, 9 parts) and frequencies a little off those read
        (the quarters at a refined Doppler) come from the first pass: every line within 1e-8 of the
        strongest's amplitude (-160 dB) of the direct sum, and within 1e-5 of its own -- the weak one
        too, 60 dB below a line 2.1 MHz away and 100 dB below the DC."""
        from mtcw_core.dsp.tones import PartDFTs

        x, f = self.record(iq)
        pd = PartDFTs(x, FS, 8.0, max_parts=16)
        assert pd.m == 375
        for parts, off in ((8, 0.0), (4, 3e3), (9, -2e3), (7, 1e3), (16, 0.0)):
            got, ref = pd(parts, f + off), self.direct(x, parts, f + off, FS)
            assert got.shape == (parts, 3)
            assert np.max(np.abs(got - ref)) < 1e-8 * np.max(np.abs(ref))
            np.testing.assert_array_less(np.abs(got - ref) / np.abs(ref), 1e-5)
        assert len(pd._passes) == 1

    def test_a_line_far_from_those_read_takes_a_pass_of_its_own(self):
        from mtcw_core.dsp.tones import PartDFTs

        x, f = self.record(False)
        pd = PartDFTs(x, FS, 8.0, max_parts=16)
        pd(4, f[:2])
        got = pd(4, f)  # the third line was not read: a second pass, for it alone
        assert len(pd._passes) == 2 and pd._passes[1][0].size == 1
        np.testing.assert_array_less(np.abs(got - self.direct(x, 4, f, FS)) / np.abs(got), 1e-5)

    def test_one_line(self):
        """A single line's parts (their ends read by matrix-vector products) as the direct sums."""
        from mtcw_core.dsp.tones import PartDFTs

        x, f = self.record(False)
        pd = PartDFTs(x, FS, 8.0, max_parts=16)
        for parts in (4, 9):
            got, ref = pd(parts, f[2:]), self.direct(x, parts, f[2:], FS)
            assert got.shape == (parts, 1)
            np.testing.assert_array_less(np.abs(got - ref) / np.abs(ref), 1e-5)

    def test_short_records_are_read_part_by_part(self):
        """Below blocks of PART_MIN_BLOCK samples the parts are summed exactly, one at a time."""
        from mtcw_core.dsp.tones import PartDFTs

        x = np.random.default_rng(1).standard_normal(2**16) + 3.0
        pd = PartDFTs(x, FS, 8.0, max_parts=16)
        assert pd.m == 0
        f = [1.1e6, 250e6]
        np.testing.assert_allclose(pd(9, f), self.direct(x, 9, f, FS), rtol=0, atol=1e-9)
        assert not pd._passes


@pytest.mark.parametrize("iq", [False, True])
def test_fit_noise_gain_is_the_fitted_amplitudes_variance_in_white_noise(iq):
    """Lines 0.4 bin apart share the noise (their variance ~2.3x a lone line's); one far from them
    has 4/n (real) or 1/n (IQ) per unit of the per-sample variance, as many noise draws show."""
    from mtcw_core.dsp.tones import fit_noise_gain

    fs, n = 5e9, 1024
    f = np.array([500e6, 500e6 + 0.4 * fs / n, 700e6])
    rng = np.random.default_rng(3)
    noise = rng.standard_normal((3000, n)) if not iq else \
        (rng.standard_normal((3000, n)) + 1j * rng.standard_normal((3000, n))) / np.sqrt(2)
    z = np.array([fit_lines(x, f, fs) for x in noise])
    gain = fit_noise_gain(f, fs, n, iq)
    np.testing.assert_allclose(np.var(z, axis=0), gain, rtol=0.1)
    assert gain[0] > 2.0 * gain[2]
    np.testing.assert_allclose(gain[2] * n, 1.0 if iq else 4.0, rtol=0.01)


@pytest.mark.parametrize("n", [4096, 4097])
def test_mean_leak_is_the_exact_dft_of_the_records_mean(n):
    """``mean_leak`` is ``exact_dft`` of a constant record: subtracted, a line's amplitude is read as
    from the mean-free record (real and complex, even and odd lengths)."""
    f = np.array([0.0, 3.3e5, 7.25e6, -1.1e6])
    for mean in (0.7, 0.3 - 0.4j):
        const = np.full(n, mean) if isinstance(mean, float) else np.full(n, mean, dtype=np.complex128)
        np.testing.assert_allclose(mean_leak(const, f, FS), exact_dft(const, f, FS), rtol=1e-9, atol=1e-9 * n)
        rng = np.random.default_rng(n)
        x = const + rng.normal(0.0, 1.0, n)
        np.testing.assert_allclose(exact_dft(x, f, FS) - mean_leak(x, f, FS), exact_dft(x - np.mean(x), f, FS),
                                   rtol=1e-9, atol=1e-9 * n)
