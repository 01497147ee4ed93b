"""mtcw_core.dsp.spectrum: windowed periodogram, local noise floor, line widths, the stage."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.fft
from scipy.signal import get_window

from mtcw_core.dsp.spectrum import (PackedPower, Spectrum, line_width_bins, local_floor, power_spectrum, real_power,
                                    real_power_packed, search_spectrum, sliding_sums, widths_at)

FS = 1.0e9


def tone(n, f, a=1.0, p=0.0):
    return a * np.cos(2 * np.pi * np.mod(np.arange(n) * (f / FS), 1.0) + p)


class TestPowerSpectrum:
    def test_impulse_is_flat_boxcar(self):
        n = 1024
        x = np.zeros(n)
        x[100] = 1.0
        sp = power_spectrum(x, FS, "boxcar")
        # (delta - 1/N): |X|^2 = 1 at every bin but DC, which the mean removal empties
        np.testing.assert_allclose(sp.power[1:], 1.0, rtol=1e-12)
        assert sp.power[0] == pytest.approx(0.0, abs=1e-24)

    def test_impulse_is_flat_kaiser_away_from_dc(self):
        n = 1024
        x = np.zeros(n)
        k0 = 300
        x[k0] = 1.0
        sp = power_spectrum(x, FS)  # Kaiser(14)
        w = get_window(("kaiser", 14.0), n, fftbins=False)
        # the window's weight at the impulse, everywhere past the DC main lobe (the mean's notch)
        np.testing.assert_allclose(sp.power[10:], w[k0] ** 2, rtol=1e-6)

    def test_attributes_real(self):
        n = 2048
        sp = power_spectrum(np.random.default_rng(0).standard_normal(n), FS)
        w = get_window(("kaiser", 14.0), n, fftbins=False)
        assert sp.power.shape == (n // 2 + 1,)
        assert sp.df_hz == FS / n and sp.f0_hz == 0.0 and sp.n == n and not sp.complex_input
        assert sp.window_power == pytest.approx(np.sum(w**2), rel=1e-12)

    @pytest.mark.parametrize("n", [1024, 1025])
    def test_attributes_complex(self, n):
        rng = np.random.default_rng(1)
        sp = power_spectrum(rng.standard_normal(n) + 1j * rng.standard_normal(n), FS)
        assert sp.power.shape == (n,) and sp.complex_input
        # fftshifted: bin 0 is the most negative frequency of the fft grid
        assert sp.f0_hz == pytest.approx(np.fft.fftshift(np.fft.fftfreq(n, 1 / FS))[0], rel=1e-12)

    def test_real_tone_lands_in_its_bin(self):
        n = 4096
        f = 777 * FS / n
        sp = power_spectrum(tone(n, f, 0.5), FS)
        assert int(np.argmax(sp.power)) == 777 == int(sp.bin_of(f))
        # a coherent on-grid tone: |X|^2 = (A/2 * sum w)^2 at its bin
        w = get_window(("kaiser", 14.0), n, fftbins=False)
        assert sp.power[777] == pytest.approx((0.25 * w.sum()) ** 2, rel=1e-9)

    def test_complex_negative_tone_lands_in_its_bin(self):
        n = 4096
        f = -1234 * FS / n
        x = np.exp(2j * np.pi * np.mod(np.arange(n) * f / FS, 1.0))
        sp = power_spectrum(x, FS)
        k = int(np.argmax(sp.power))
        assert k == int(sp.bin_of(f))
        assert sp.f0_hz + k * sp.df_hz == pytest.approx(f)

    def test_first_n_samples_only(self):
        x = np.random.default_rng(2).standard_normal(4096)
        a = power_spectrum(x, FS, n=1024)
        b = power_spectrum(x[:1024], FS)
        assert a.n == 1024
        np.testing.assert_array_equal(a.power, b.power)

    @pytest.mark.parametrize("cplx", [False, True])
    def test_single_precision(self, cplx):
        rng = np.random.default_rng(3)
        x = rng.standard_normal(2048) + (1j * rng.standard_normal(2048) if cplx else 0)
        a = power_spectrum(x, FS, single=True)
        b = power_spectrum(x, FS)
        assert a.power.dtype == np.float32
        np.testing.assert_allclose(a.power, b.power, rtol=1e-3, atol=1e-5 * b.power.max())

    def test_float32_input(self):
        x = tone(1024, 100 * FS / 1024).astype(np.float32)
        assert int(np.argmax(power_spectrum(x, FS).power)) == 100

    def test_unknown_window(self):
        with pytest.raises(ValueError):
            power_spectrum(np.ones(256), FS, "no-such-window")


class TestSpectrumMethods:
    def test_bin_of(self):
        sp = Spectrum(np.zeros(513), 1e6, 0.0, 1.0, 1024, False)
        np.testing.assert_array_equal(sp.bin_of(np.array([0.0, 1.4e6, 1.6e6, 512e6])), [0, 1, 2, 512])
        sc = Spectrum(np.zeros(1024), 1e6, -512e6, 1.0, 1024, True)
        assert int(sc.bin_of(0.0)) == 512 and int(sc.bin_of(-512e6)) == 0

    @pytest.mark.parametrize("s2", [1e-4, 2.5])
    def test_noise_variance_real(self, s2):
        x = np.sqrt(s2) * np.random.default_rng(4).standard_normal(2**14)
        sp = power_spectrum(x, FS)
        est = sp.noise_variance(200e6, [], half_width=2048)
        assert est == pytest.approx(s2, rel=0.08)

    def test_noise_variance_complex_is_total_per_sample_variance(self):
        rng = np.random.default_rng(5)
        s2 = 0.3  # E|x|^2, s2/2 per quadrature
        x = np.sqrt(s2 / 2) * (rng.standard_normal(2**14) + 1j * rng.standard_normal(2**14))
        sp = power_spectrum(x, FS)
        assert sp.noise_variance(-100e6, [], half_width=2048) == pytest.approx(s2, rel=0.08)

    def test_noise_variance_excludes_lines(self):
        n = 2**14
        f = 3001 * FS / n
        x = tone(n, f, 1.0) + 0.01 * np.random.default_rng(6).standard_normal(n)
        sp = power_spectrum(x, FS)
        est = sp.noise_variance(f, [f], half_width=1024)
        assert est == pytest.approx(1e-4, rel=0.1)

    def test_noise_variance_nan_when_nothing_left(self):
        sp = Spectrum(np.ones(8), 1.0, 0.0, 1.0, 14, False)
        # the whole neighbourhood excluded: falls back to all bins (finite), never raises
        assert np.isfinite(sp.noise_variance(4.0, [4.0], half_width=2, guard=5))


class TestLocalFloor:
    @pytest.mark.parametrize("window", ["boxcar", ("kaiser", 14.0)])
    def test_white_noise_floor_is_its_mean_power(self, window):
        n = 2**15
        s2 = 0.7
        x = np.sqrt(s2) * np.random.default_rng(7).standard_normal(n)
        sp = power_spectrum(x, FS, window)
        fl = local_floor(sp.power, mirror_dc=True)
        assert fl.shape == sp.power.shape
        expected = s2 * sp.window_power  # E|X|^2 of white noise
        assert np.mean(fl) == pytest.approx(expected, rel=0.04)
        assert np.mean(fl) == pytest.approx(np.mean(sp.power[2:]), rel=0.05)

    def test_complex_white_noise(self):
        rng = np.random.default_rng(8)
        n = 2**14
        x = rng.standard_normal(n) + 1j * rng.standard_normal(n)
        sp = power_spectrum(x, FS)
        fl = local_floor(sp.power)
        assert np.mean(fl) == pytest.approx(2.0 * sp.window_power, rel=0.04)

    def test_a_line_does_not_raise_its_own_floor(self):
        n = 2**14
        k = 4000
        x = tone(n, k * FS / n, 1.0) + 1e-3 * np.random.default_rng(9).standard_normal(n)
        sp = power_spectrum(x, FS)
        fl = local_floor(sp.power, mirror_dc=True)
        # the ring skips the line's main lobe: its floor is the noise's, not the line's
        assert fl[k] == pytest.approx(1e-6 * sp.window_power, rel=0.35)
        assert sp.power[k] / fl[k] > 1e6

    def test_follows_a_coloured_floor(self):
        # a floor that steps by 100x: the local estimate follows it away from the step
        rng = np.random.default_rng(10)
        p = rng.exponential(1.0, 4000)
        p[2000:] *= 100.0
        fl = local_floor(p)
        assert np.median(fl[200:1800]) == pytest.approx(1.0, rel=0.1)
        assert np.median(fl[2200:3800]) == pytest.approx(100.0, rel=0.1)

    def test_float32_power(self):
        p = np.random.default_rng(11).exponential(2.0, 4096).astype(np.float32)
        fl = local_floor(p)
        assert np.all(np.isfinite(fl))
        assert np.mean(fl) == pytest.approx(2.0, rel=0.05)

    def test_zeros_do_not_give_nan(self):
        fl = local_floor(np.zeros(512))
        assert np.all(np.isfinite(fl)) and np.all(fl >= 0)


class TestLineWidths:
    def test_coherent_line_is_narrow(self):
        n = 2**14
        sp = power_spectrum(tone(n, (3000 + 0.37) * FS / n), FS)
        w = widths_at(sp, [(3000 + 0.37) * FS / n])
        # Kaiser(14)'s main lobe: sum(P)/max(P) about 2.2 bins on the grid, 2.5 half a bin off it
        assert 2.0 <= w <= 2.7

    def test_incoherent_line_is_wide(self):
        n = 2**14
        df = FS / n
        fwhm = 20 * df
        rng = np.random.default_rng(12)
        phase = np.cumsum(rng.standard_normal(n) * np.sqrt(2 * np.pi * fwhm / FS))
        f = 4000 * df
        x = np.cos(2 * np.pi * np.mod(np.arange(n) * f / FS, 1.0) + phase)
        sp = power_spectrum(x, FS)
        assert widths_at(sp, [f]) > 8.0

    def test_line_width_bins_median_over_tones(self):
        n = 2**14
        df = FS / n
        t = [2000 * df, 3000 * df, 5000 * df]
        x = sum(tone(n, f) for f in t)
        sp = power_spectrum(x, FS)
        assert 2.0 <= line_width_bins(sp, t) <= 2.7

    def test_no_line_gives_default(self):
        sp = Spectrum(np.zeros(513), 1e6, 0.0, 1.0, 1024, False)
        assert widths_at(sp, [100e6]) == 1.0


class TestSearchSpectrum:
    def test_whole_record_fraction_one(self):
        x = np.random.default_rng(13).standard_normal(4096)
        a = search_spectrum(x, FS, 14.0, 1.0, False)
        b = power_spectrum(x, FS, ("kaiser", 14.0))
        np.testing.assert_array_equal(a.power, b.power)

    def test_fraction_of_record_and_never_under_its_minimum(self):
        """A fraction of the record, never fewer than SEARCH_MIN_SAMPLES (2^16) samples: a 2^20-sample
        record's eighth (2^17), a 2^18-sample record's quarter, a 2^16-sample record whole."""
        from mtcw_core.dsp.spectrum import SEARCH_MIN_SAMPLES

        assert SEARCH_MIN_SAMPLES == 2**16
        x = np.random.default_rng(14).standard_normal(2**20)
        assert search_spectrum(x, FS, 14.0, 1 / 8, True).n == 2**17
        assert search_spectrum(x[:2**18], FS, 14.0, 1 / 8, True).n == 2**16
        sp = search_spectrum(x[:2**16], FS, 14.0, 1 / 8, False)
        assert sp.n == 2**16 and sp.record_n is None
        np.testing.assert_array_equal(sp.power, power_spectrum(x[:2**16], FS, ("kaiser", 14.0)).power)
        assert search_spectrum(x[:4096], FS, 14.0, 0.25, False).n == 4096
        # the rule itself, which the target stage's pedestal-ghost odds count the searched bins by
        from mtcw_core.dsp.spectrum import search_length
        assert [search_length(n, 1 / 8) for n in (2**20, 2**18, 2**16, 4096)] == [2**17, 2**16, 2**16, 4096]

    def test_windows_use_the_longest(self):
        x = np.random.default_rng(15).standard_normal(8192)
        wins = [(0, 1000), (2000, 5000), (6000, 7000)]
        sp = search_spectrum(x, FS, 8.0, 1.0, False, wins)
        ref = power_spectrum(x[2000:5000], FS, ("kaiser", 8.0))
        assert sp.n == 3000
        np.testing.assert_array_equal(sp.power, ref.power)

    def test_a_fraction_measures_the_floor_over_the_same_band_in_hz(self, monkeypatch):
        """Noise 5x denser within +-5 MHz of a line than elsewhere (known by construction): the
        floor at the line is that density whether the spectrum is of the whole record or of its
        eighth (`fast`), whose bins are 8x wider -- a ring of 256 of *its* bins (+-31 MHz) would
        have measured mostly the thinner noise outside."""
        import mtcw_core.dsp.spectrum as spectrum_module

        monkeypatch.setattr(spectrum_module, "SEARCH_MIN_SAMPLES", 256)  # an eighth of this short record
        n, f0 = 2**16, 200e6
        rng = np.random.default_rng(21)
        white = rng.standard_normal(n)
        f = scipy.fft.rfftfreq(n, 1 / FS)
        band = np.abs(f - f0) < 5e6
        spec = np.zeros(f.size, complex)
        spec[band] = rng.standard_normal(band.sum()) + 1j * rng.standard_normal(band.sum())
        extra = scipy.fft.irfft(spec, n)
        # per-sample variance the band's density stands for, over the whole band 0..fs/2
        extra *= math.sqrt(4.0 * band.sum() / f.size / np.var(extra))
        x = white + extra + tone(n, f0, 3.0)
        want = 1.0 + 4.0
        whole = search_spectrum(x, FS, 14.0, 1.0, False)
        eighth = search_spectrum(x, FS, 14.0, 1 / 8, False)
        assert whole.record_n is None and eighth.record_n == n
        assert whole.floor_half_width() == 256 and eighth.floor_half_width() == 32
        for sp in (whole, eighth):
            assert sp.noise_variance(f0, [f0]) == pytest.approx(want, rel=0.3)
        assert eighth.noise_variance(f0, [f0], half_width=256) < 0.5 * want  # the old ring

    def test_beta_sets_the_window(self):
        x = np.random.default_rng(16).standard_normal(1024)
        sp = search_spectrum(x, FS, 0.0, 1.0, False)  # Kaiser(0) is the rectangular window
        np.testing.assert_allclose(sp.power, power_spectrum(x, FS, "boxcar").power, rtol=1e-12)


class TestPackedRealFFT:
    """``real_power`` (one complex FFT of half the length) is ``|rfft|^2``, in both precisions."""

    @pytest.mark.parametrize("m", [2, 4, 10, 1000, 4096, 2 * 3 * 5 * 7 * 11])
    @pytest.mark.parametrize("dtype, rtol", [(np.float64, 1e-12), (np.float32, 2e-5)])
    def test_equals_the_rfft_power(self, m, dtype, rtol):
        y = np.random.default_rng(m).standard_normal(m)
        ref = np.abs(np.fft.rfft(y)) ** 2
        got = real_power(y.astype(dtype))
        assert got.shape == ref.shape and got.dtype == dtype
        np.testing.assert_allclose(got, ref, rtol=0, atol=rtol * ref.mean())

    def test_a_tone_lands_in_its_bin_and_nyquist_is_kept(self):
        m = 1024
        k = np.arange(m)
        y = 3.0 * np.cos(2 * np.pi * 100 * k / m) + 0.5 * (-1.0) ** k  # a tone in bin 100, a Nyquist line
        p = real_power(y.copy())
        assert np.argmax(p[:-1]) == 100 and p[100] == pytest.approx((3.0 * m / 2) ** 2, rel=1e-12)
        assert p[-1] == pytest.approx((0.5 * m) ** 2, rel=1e-12)

    def test_odd_lengths_take_scipys_rfft(self):
        x = np.random.default_rng(3).standard_normal(1001)
        sp = power_spectrum(x, FS, "boxcar")
        np.testing.assert_allclose(sp.power, np.abs(np.fft.rfft(x - x.mean())) ** 2, rtol=1e-10)


class TestComplexBins:
    """The complex transform behind the power, referred to the centre of the samples, and the
    lines' noise rings read from it (:meth:`Spectrum.complex_at`, :meth:`Spectrum.line_rings`)."""

    @pytest.mark.parametrize("n, iq, single", [(2**16, False, False), (2**18, False, False), (2**16 + 1, False, False),
                                               (2**16, False, True), (4096, True, False), (4097, True, False)])
    def test_complex_at_is_the_centre_referred_transform(self, n, iq, single):
        """Packed and unpacked at once (short), packed and lazy (long), odd (scipy's rfft), IQ."""
        rng = np.random.default_rng(n)
        x = rng.normal(size=n) + (1j * rng.normal(size=n) if iq else 0.0)
        sp = power_spectrum(x, FS, single=single)
        y = (x - x.mean()) * get_window(("kaiser", 14.0), n, fftbins=False)
        X = np.fft.fftshift(np.fft.fft(y)) if iq else np.fft.rfft(y)
        k = np.concatenate([[0, X.size - 1], rng.integers(0, X.size, 300)])
        f = sp.f0_hz + k * sp.df_hz
        want = X[k] * np.exp(2j * np.pi * f * (n - 1) / (2 * FS))
        tol = (2e-6 if single else 1e-10) * np.abs(X).max()
        np.testing.assert_allclose(sp.complex_at(k), want, rtol=0, atol=tol)
        np.testing.assert_allclose(np.abs(sp.complex_at(k)) ** 2, np.asarray(sp.power)[k], rtol=0,
                                   atol=tol * np.abs(X).max() * 4)

    def test_a_lines_bin_holds_its_own_phase(self):
        """Referred to the centre, the symmetric window's response is real: an off-bin line's bin
        holds the line's phase at the centre of the record (not turned by its fractional bin)."""
        n, f, p = 2**16, 123.4567e6, 0.7
        t = np.arange(n) / FS
        sp = power_spectrum(np.cos(2 * np.pi * f * t + p), FS)
        at_centre = p + 2 * np.pi * f * (n - 1) / (2 * FS)
        got = sp.complex_at(sp.bin_of(f))
        assert abs(np.angle(got * np.exp(-1j * at_centre))) < 1e-6

    def test_no_transform_kept_gives_none(self):
        sp = power_spectrum(np.random.default_rng(1).normal(size=4096), FS)
        bare = Spectrum(sp.power, sp.df_hz, sp.f0_hz, sp.window_power, sp.n, False)
        assert bare.complex_at(np.array([3])) is None
        assert bare.line_rings(np.array([1e8, 2e8]), np.zeros(2, bool), np.array([1e8, 2e8]), 12, 44) is None

    def test_lines_whose_rows_come_within_the_guard_are_not_read_together(self):
        """Two lines 2 bins apart: their rows at one offset are 2 bins apart, correlated by the
        window itself (0.5 for Kaiser(14)), whatever their noise does; so no rings. 20 bins apart
        they are read; a mirror line's rows run backward and cross the other's (none)."""
        sp = power_spectrum(np.random.default_rng(2).normal(size=2**16), FS)
        f0 = 1000 * sp.df_hz
        no = np.zeros(2, bool)
        assert sp.line_rings(np.array([f0, f0 + 2 * sp.df_hz]), no, np.array([f0]), 12, 256) is None
        assert sp.line_rings(np.array([f0, f0 + 20 * sp.df_hz]), no, np.array([f0]), 12, 256) is not None
        assert sp.line_rings(np.array([f0, f0 + 100 * sp.df_hz]), np.array([False, True]), np.array([f0]), 12,
                             256) is None

    def test_a_line_beyond_the_band_reads_no_ring(self):
        """A line past fs/2 (or below -fs/2 for IQ) has no bin of its own here: no rings (its
        bin once indexed past the spectrum's end, or wrapped to another bin in the packed one)."""
        rng = np.random.default_rng(3)
        for x in (rng.normal(size=2**16), rng.normal(size=2**16) + 1j * rng.normal(size=2**16)):
            sp = power_spectrum(x, FS)
            for beyond in (0.5 * FS + 3 * sp.df_hz, -0.5 * FS - 3 * sp.df_hz):
                f = np.array([1e8, beyond])
                assert sp.line_rings(f, np.zeros(2, bool), f, 12, 44) is None
            assert sp.line_rings(np.array([1e8, 2e8]), np.zeros(2, bool), np.array([1e8, 2e8]), 12, 44) is not None

    def test_rings_of_a_carriers_phase_noise_move_a_tones_two_lines_oppositely(self):
        """IQ: a carrier with broadband phase noise and a tone's two sidebands (the lower one read
        conjugated, as a mirror line). The carrier's noise at the tone's offset is a pair of
        phase-modulation sidebands: it moves the two lines' phases oppositely, and white noise
        does not move them together at all."""
        rng = np.random.default_rng(7)
        n, f1 = 2**16, 200e6
        t = np.arange(n) / FS
        phi = 3e-3 * rng.normal(size=n)  # broadband phase noise on the carrier
        am = 1 + 0.1 * np.cos(2 * np.pi * f1 * t)
        x = np.exp(1j * phi) * am * 10 + 1e-3 * (rng.normal(size=n) + 1j * rng.normal(size=n))
        sp = power_spectrum(x, FS)
        lines = np.array([f1, -f1])
        ring, shift, offset = sp.line_rings(lines, np.array([False, True]), np.array([0.0, f1, -f1]), 12, 44)
        assert ring.shape[1] == 2 and 48 <= ring.shape[0] <= 64 and shift.shape == (2,)
        assert offset.shape == (ring.shape[0],) and np.all((np.abs(offset) > 12) & (np.abs(offset) <= 44))
        coh = np.real(np.vdot(ring[:, 1], ring[:, 0])) / np.sqrt(np.vdot(ring[:, 0], ring[:, 0]).real
                                                                  * np.vdot(ring[:, 1], ring[:, 1]).real)
        assert coh < -0.9
        # white noise alone: the two lines' rings are not coherent
        sp = power_spectrum(am * 10 + 1e-1 * (rng.normal(size=n) + 1j * rng.normal(size=n)), FS)
        ring, _, _ = sp.line_rings(lines, np.array([False, True]), np.array([0.0, f1, -f1]), 12, 44)
        coh = np.real(np.vdot(ring[:, 1], ring[:, 0])) / np.sqrt(np.vdot(ring[:, 0], ring[:, 0]).real
                                                                  * np.vdot(ring[:, 1], ring[:, 1]).real)
        assert abs(coh) < 0.35


class TestPackedPower:
    """The spectrum unpacked where read: every read gives the numbers of ``|rfft|^2`` there, the
    same whatever was read before, and the search reads a part of it only."""

    @staticmethod
    def _record(m, seed=0):
        k = np.arange(m)
        return np.random.default_rng(seed).standard_normal(m) + 5 * np.cos(2 * np.pi * 0.123 * k)

    @pytest.mark.parametrize("m", [4096, 2 * 3 * 5 * 7 * 11 * 13, 100_000])
    @pytest.mark.parametrize("dtype, rtol", [(np.float64, 1e-12), (np.float32, 1e-5)])
    def test_reads_are_the_rfft_power(self, m, dtype, rtol):
        y = self._record(m)
        ref = np.abs(scipy.fft.rfft(y)) ** 2  # float64, scipy's own real transform
        p = real_power_packed(y.astype(dtype))
        assert isinstance(p, PackedPower) and p.shape == ref.shape and p.size == ref.size and p.dtype == dtype
        atol = rtol * ref.mean()
        h = m // 2
        np.testing.assert_allclose(p[h - 50:], ref[h - 50:], rtol=rtol, atol=atol)  # the top, Nyquist included
        np.testing.assert_allclose(p[:37], ref[:37], rtol=rtol, atol=atol)  # DC and the first bins
        idx = np.random.default_rng(1).integers(0, h + 1, size=(7, 33))  # any shape of indices
        np.testing.assert_allclose(p[idx], ref[idx], rtol=rtol, atol=atol)
        assert p[idx].shape == (7, 33)
        assert p[h] == pytest.approx(ref[h], rel=rtol, abs=atol) and p[-1] == p[h]
        np.testing.assert_allclose(np.asarray(p), ref, rtol=rtol, atol=atol)

    @pytest.mark.parametrize("dtype", [np.float32, np.float64])
    def test_read_order_does_not_change_a_number(self, dtype):
        """Bands read in any order (overlapping, across block edges, single bins, strided, masks)
        are bit for bit the whole spectrum's; nothing read is writable."""
        y = self._record(50_000, 3).astype(dtype)
        whole = np.asarray(real_power_packed(y.copy()))
        p = real_power_packed(y.copy())
        rng = np.random.default_rng(4)
        for _ in range(40):
            a = int(rng.integers(0, p.size))
            b = int(rng.integers(a, min(a + 3000, p.size) + 1))
            np.testing.assert_array_equal(p[a:b], whole[a:b])
            assert p[a] == whole[a]
        np.testing.assert_array_equal(p[::7], whole[::7])
        mask = rng.random(p.size) < 0.01
        np.testing.assert_array_equal(p[mask], whole[mask])
        np.testing.assert_array_equal(np.asarray(p), whole)
        with pytest.raises(ValueError):
            p[10:20][0] = 1.0

    def test_block_aligned_top_and_nyquist_read_last(self):
        """h a multiple of the block: everything below Nyquist read first, Nyquist after."""
        m = 8 * PackedPower.BLOCK
        y = self._record(m, 7)
        whole = np.asarray(real_power_packed(y.copy()))
        p = real_power_packed(y.copy())
        np.testing.assert_array_equal(p[:m // 2], whole[:m // 2])
        assert p[m // 2] == whole[m // 2]
        np.testing.assert_array_equal(np.asarray(p), whole)

    def test_only_what_is_read_is_unpacked(self):
        p = real_power_packed(self._record(1 << 18).astype(np.float32))
        assert p.unpacked_fraction == 0.0
        p[1000:1100]
        assert 0 < p.unpacked_fraction <= 2 * PackedPower.BLOCK / p.size
        assert p.max() == np.asarray(p).max() and p.unpacked_fraction == 1.0

    def test_short_records_are_unpacked_at_once(self):
        """Below LAZY_MIN_SAMPLES the spectrum is a plain array, with the packed one's numbers."""
        from mtcw_core.dsp.spectrum import LAZY_MIN_SAMPLES

        for m in (LAZY_MIN_SAMPLES // 2, LAZY_MIN_SAMPLES):
            x = self._record(m, 6)
            sp = power_spectrum(x, FS, single=True)
            assert isinstance(sp.power, np.ndarray) == (m < LAZY_MIN_SAMPLES)
            y = ((x - x.mean()).astype(np.float32) * get_window(("kaiser", 14.0), m, fftbins=False).astype(np.float32))
            np.testing.assert_array_equal(np.asarray(sp.power), np.asarray(real_power_packed(y)))

    def test_out_of_range_is_an_index_error(self):
        p = real_power_packed(self._record(1024))
        with pytest.raises(IndexError):
            p[513]
        with pytest.raises(IndexError):
            p[np.array([3, 600])]

    def test_chain_reads_a_part_of_the_search_spectrum(self):
        """A 2^18-sample six-tone frame: the Doppler search and the floors read the bands around
        0 Hz and the tones, not the whole spectrum (measured: 8-15 %)."""
        from mtcw_core.chain import run_stages
        from mtcw_core.scene import load_scene, scene_variant
        from mtcw_core.simulate import Simulator
        sc = scene_variant(load_scene("six-tone"), digitizer={"samples": 1 << 18})
        st = run_stages(Simulator(sc, seed=1).frame(0), "balanced")
        assert isinstance(st.spectrum.power, PackedPower)
        assert st.spectrum.power.unpacked_fraction < 0.5


@pytest.mark.parametrize("mirror_dc", [True, False])
def test_local_floor_on_ranges_is_the_whole_spectrums(mirror_dc):
    """The search's floor, computed on bands only (both ends, overlapping and tiny ranges
    included), equals the whole-spectrum floor there; bins outside are NaN."""
    rng = np.random.default_rng(5)
    p = rng.exponential(size=20001) * (1 + np.arange(20001) / 1e3)
    full = local_floor(p, mirror_dc=mirror_dc)
    ranges = [(-5, 30), (20, 400), (19950, 20050), (5000, 5001), (7000, 6990)]
    part = local_floor(p, mirror_dc=mirror_dc, ranges=ranges)
    inside = np.zeros(p.size, bool)
    for a, b in ranges:
        inside[max(a, 0):max(min(b, p.size), 0)] = True
    np.testing.assert_allclose(part[inside], full[inside], rtol=1e-12)
    assert np.isnan(part[~inside]).all()


def test_noise_variances_equal_the_scalar_statistic():
    """The vectorised floors are the median statistic, line by line: with and without excluded lines,
    at both ends of the spectrum, and when the exclusions leave no bin (then every bin counts)."""
    n = 20000
    k = np.arange(n)
    x = np.random.default_rng(8).standard_normal(n) + 3 * np.cos(2 * np.pi * 0.1 * k)
    for single in (False, True):
        sp = power_spectrum(x, FS, single=single)
        fs = [0.0, 1e8, 2e8, 4.99e8, 5e8, 1e8 + 3e5]
        for ex in ([1e8, 0.0, 2e8 + 1e5], [], fs, list(np.linspace(0, 5e8, 3000))):
            ref = np.array([_median_floor(sp, f, ex) for f in fs])
            np.testing.assert_allclose(sp.noise_variances(fs, ex), ref, rtol=1e-6)
            assert sp.noise_variance(fs[1], ex) == sp.noise_variances(fs[1:2], ex)[0]


def _median_floor(sp, f, exclude, half_width=256, guard=12):
    """The statistic written out plainly: the median of the bins around f farther than guard
    from every excluded line (all of them when that leaves none), as a per-sample variance."""
    b = int(sp.bin_of(f))
    idx = np.arange(max(b - half_width, 0), min(b + half_width + 1, sp.power.size))
    ex = sp.bin_of(np.asarray(exclude, float)) if len(exclude) else np.empty(0, int)
    keep = np.all(np.abs(idx[:, None] - ex[None, :]) > guard, axis=1) if ex.size else np.ones(idx.size, bool)
    vals = sp.power[idx[keep]] if keep.any() else sp.power[idx]
    return float(np.median(vals.astype(np.float64))) / np.log(2) / sp.window_power


@pytest.mark.parametrize("width", [1, 2, 3, 7, 8, 41, 64, 100])
def test_sliding_sums_are_the_window_sums(width):
    v = np.random.default_rng(width).standard_normal(300) * 10
    want = np.array([math.fsum(v[i:i + width]) for i in range(v.size - width + 1)])  # exactly rounded
    np.testing.assert_allclose(sliding_sums(v, width), want, rtol=0, atol=1e-12 * width)


def test_local_floor_is_the_ring_mean_written_out():
    """The floor at a few bins against its definition: exp(mean of log power over the bins
    inner..outer away on both sides (mirrored about 0 Hz) + Euler's gamma)."""
    p = np.random.default_rng(9).exponential(size=4001) + 0.1
    fl = local_floor(p, inner=8, outer=48, mirror_dc=True)
    for k in (0, 3, 60, 2000, 3990, 4000):
        ring = [j for d in range(8, 49) for j in (k - d, k + d)]
        ring = [abs(j) if j < 0 else (2 * 4000 - j if j > 4000 else j) for j in ring]
        want = math.exp(math.fsum(math.log(p[j]) for j in ring) / len(ring) + np.euler_gamma)
        assert fl[k] == pytest.approx(want, rel=1e-12)


class TestLowBand:
    """LowBand: the DFT near 0 Hz from block sums -- what the sub-guard scan reads."""

    @pytest.mark.parametrize("iq", [False, True])
    def test_a_low_line_beside_strong_high_lines_is_the_exact_dft(self, iq):
        from mtcw_core.dsp.spectrum import LowBand
        from mtcw_core.dsp.tones import exact_dft

        n = 1_000_003  # no block count divides it: the tail counts too
        df = FS / n
        rng = np.random.default_rng(4)
        x = 2.0 + 1e-3 * tone(n, 3.3 * df, p=0.4) + tone(n, 100e6) + 0.5 * tone(n, 310e6 + 2.1 * df)
        x = x + 0.01 * rng.standard_normal(n)
        if iq:
            x = x + 1j * (0.01 * rng.standard_normal(n) + 1e-3 * tone(n, 2.2 * df))
        f = np.arange(1.0, 8.0, 0.25) * df
        f = np.concatenate([f, -f]) if iq else f
        exact = exact_dft(x - x.mean(), f, FS)
        low = LowBand.of(x, FS, 8.0)
        assert low.sums.size * low.block + low.tail.size == n
        approx = low.dft(f)
        # the block sums' error is the noise's content within each block (a few %), not the lines'
        assert np.max(np.abs(approx - exact)) < 0.03 * np.max(np.abs(exact))
        k = int(np.argmin(np.abs(f - 3.3 * df)))
        assert abs(approx[k]) == pytest.approx(abs(exact[k]), rel=0.01)
        assert abs(abs(exact[k]) - 1e-3 * n / 2) < 0.1 * 1e-3 * n / 2  # the line itself: A*N/2 (noise ~ 10)

    def test_white_noise_keeps_the_dfts_statistics(self):
        """E|X(f)|^2 = N*s2 at the band's frequencies, as for the record's own DFT (the snr the
        sub-guard gate compares against the fit's)."""
        from mtcw_core.dsp.spectrum import LowBand

        n, s = 2**16, 0.3
        rng = np.random.default_rng(9)
        f = np.arange(1, 9) * FS / n
        p = np.concatenate([np.abs(LowBand.of(s * rng.standard_normal(n), FS, 8).dft(f)) ** 2 for _ in range(200)])
        assert np.mean(p) / (n * s**2) == pytest.approx(1.0, abs=0.08)

    @pytest.mark.parametrize("iq", [False, True])
    def test_a_lines_width_at_the_records_resolution(self, iq):
        """LowBand.line_at: the equivalent width the whole record's Kaiser(14) spectrum gives
        (:func:`widths_at`), from the block sums; a coherent line stands out of the bins about it by
        its SNR, a laser's Lorentzian (a random-walk phase, 1 MHz over 10 kHz bins) by ~5."""
        from mtcw_core.dsp.spectrum import LowBand, widths_at

        n = 2**16
        df = FS / n
        rng = np.random.default_rng(3)
        t = np.arange(n)
        for k in (40.3, 80.0, 120.5):
            f = -k * df if iq else k * df
            x = (np.exp(2j * np.pi * f * t / FS) if iq else tone(n, f, p=0.3)) + 0.01 * rng.standard_normal(n)
            width, contrast = LowBand.of(x, FS, 160).line_at(f)
            assert width == pytest.approx(widths_at(power_spectrum(x, FS), [f], half_span=16), rel=1e-4)
            assert width < 2.6 and contrast > 1e5
        for _ in range(5):
            phase = np.cumsum(rng.standard_normal(n) * np.sqrt(2 * np.pi * 1e6 / FS))
            x = np.cos(2 * np.pi * 60 * t / n + phase)
            assert LowBand.of(x, FS, 160).line_at(60 * df)[1] < 50

    @pytest.mark.parametrize("iq", [False, True])
    def test_the_scan_is_the_dft_on_its_grid(self, iq):
        """LowBand.scan: one zero-padded FFT of the block sums, the same values as :meth:`dft` (and
        so the record's exact DFT) on its grid, within the tail it leaves out."""
        from mtcw_core.dsp.spectrum import LowBand
        from mtcw_core.dsp.tones import exact_dft

        n = 2**16 + 37
        df = FS / n
        rng = np.random.default_rng(8)
        x = 1.0 + 1e-2 * tone(n, 5.3 * df, p=1.0) + tone(n, 200e6) + 0.01 * rng.standard_normal(n)
        if iq:
            x = x + 1j * 0.01 * rng.standard_normal(n)
        low = LowBand.of(x, FS, 12.0)
        f, xs = low.scan(1.0 * df, 12.0 * df, 0.25, iq)
        assert np.all(np.abs(f) >= df) and np.all(np.abs(f) <= 12 * df)
        assert np.max(np.diff(f[f > 0])) <= 0.25 * df * 1.001
        assert (np.sum(f < 0) > 0) == iq
        exact = exact_dft(x - x.mean(), f, FS)
        assert np.max(np.abs(xs - exact)) < 0.02 * np.max(np.abs(exact))
        k = int(np.argmax(np.abs(xs)))
        assert abs(abs(f[k]) - 5.3 * df) < 0.25 * df  # a real cosine: both signs alike for IQ


class TestFFTBackend:
    """The optional FFTW backend (``use_fft_backend``): every transform of the chain on it, the same
    spectra to single precision and the same points, and the default restored."""

    @pytest.fixture
    def fftw(self):
        pytest.importorskip("pyfftw")
        from mtcw_core.dsp.spectrum import use_fft_backend

        before = use_fft_backend("pyfftw")
        yield
        use_fft_backend(before)

    def test_unknown_backend_names_the_setting(self):
        from mtcw_core.dsp.spectrum import fft_backend, use_fft_backend

        with pytest.raises(ValueError, match="fft_backend='mkl'"):
            use_fft_backend("mkl")
        assert fft_backend() == "scipy default (pocketfft)"

    def test_fftw_runs_scipy_fft_and_reports_itself(self, fftw):
        from mtcw_core.dsp.spectrum import fft_backend

        assert fft_backend().startswith("pyfftw ")
        x = np.random.default_rng(1).standard_normal(1000)
        with scipy.fft.set_backend("scipy", only=True):  # pocketfft alone, for the reference
            want = scipy.fft.rfft(x)
        got = scipy.fft.rfft(x)
        assert np.allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())

    @pytest.mark.parametrize("n", [2**14, 2**18 + 2, 2**18 + 1])
    def test_the_spectrum_is_pocketffts_to_single_precision(self, n):
        """The real spectrum of an even record takes FFTW's own real transform (not the packed
        complex route: no :class:`PackedPower`), the same powers to float32's rounding (~1e-7 of the
        strongest bin, the single-precision floor the chain's spectrum has anyway)."""
        pytest.importorskip("pyfftw")
        from mtcw_core.dsp.spectrum import use_fft_backend

        rng = np.random.default_rng(2)
        t = np.arange(n)
        x = 0.3 + np.cos(2 * np.pi * 0.1234567 * t) + 1e-3 * rng.standard_normal(n)
        ref = power_spectrum(x, 1e9, single=True)
        before = use_fft_backend("pyfftw")
        try:
            got = power_spectrum(x, 1e9, single=True)
        finally:
            use_fft_backend(before)
        assert not isinstance(got.power, PackedPower)
        a, b = np.asarray(ref.power, dtype=np.float64), np.asarray(got.power, dtype=np.float64)
        assert a.shape == b.shape and got.df_hz == ref.df_hz and got.total == ref.total
        assert np.max(np.abs(a - b)) < 1e-6 * a.max()

    def test_the_chain_gives_the_same_points(self, fftw):
        from mtcw_core.chain import process_frame
        from mtcw_core.dsp.spectrum import use_fft_backend
        from mtcw_core.scene import load_scene, scene_variant
        from mtcw_core.simulate import Simulator

        sc = scene_variant(load_scene("moving-target"), digitizer={"samples": 2**16})
        fr = next(Simulator(sc, seed=4).frames(1))
        on = process_frame(fr, "balanced")
        use_fft_backend("pocketfft")
        off = process_frame(fr, "balanced")
        assert on.status == off.status == "ok" and len(on.targets) == len(off.targets) >= 1
        for a, b in zip(on.targets, off.targets):
            assert abs(a.range_m - b.range_m) < 1e-3 * b.range_sigma_m
            assert abs(a.velocity_mps - b.velocity_mps) < 1e-3 * b.velocity_sigma_mps


@pytest.mark.parametrize("n", [2**16, 2**18 + 2])
def test_a_moving_echos_line_is_wider_than_a_still_ones(n):
    """One photodiode: an echo moving ``x`` record bins puts a real envelope ``cos(2*pi*x*t/T + Phi)``
    on its lines (two lines at +-x). ``still_line_doppler_bins`` reads ``x`` back from the lines'
    width in the Kaiser(14) search spectrum as an upper bound: at least ``x`` for every ``Phi``
    (0.1-0.5 bin), and under 0.05 bin for a still line at any offset from the bins' centres (the
    bound issue 12 case 3's still target gives its mover's cross-beat pull)."""
    from mtcw_core.dsp.spectrum import still_line_doppler_bins

    t = np.arange(n)
    tones = np.array([120.37, 301.81, 455.5]) * FS / n * 97  # off the bins' centres
    rng = np.random.default_rng(5)
    still = sum(np.cos(2 * np.pi * np.mod(t * f / FS, 1.0) + k) for k, f in enumerate(tones))
    still = still + 1e-4 * rng.standard_normal(n)
    assert still_line_doppler_bins(power_spectrum(still, FS), tones, 14.0) < 0.05
    for x in (0.1, 0.3, 0.5):
        for phi in np.linspace(0, np.pi, 5):
            env = np.cos(2 * np.pi * x * t / n + phi)
            rec = env * sum(np.cos(2 * np.pi * np.mod(t * f / FS, 1.0) + k) for k, f in enumerate(tones))
            rec = rec + 1e-4 * rng.standard_normal(n)
            bound = still_line_doppler_bins(power_spectrum(rec, FS), tones, 14.0)
            assert bound >= x, (x, phi, bound)


def test_a_line_whose_neighbourhood_peaks_elsewhere_gives_no_still_bound():
    """An echo moving 3 record bins shows two narrow lines at +-3 bins, each as narrow as a still
    line; a mover 10 dB stronger 10 bins from a static line is the strongest within reach. Neither
    may be read as a still line's width (the bound would be ~0 and the cross-beat pull with it):
    ``still_line_doppler_bins`` gives none."""
    from mtcw_core.dsp.spectrum import still_line_doppler_bins

    n = 2**16
    t = np.arange(n)
    tone = 301.81 * FS / n * 97
    rng = np.random.default_rng(6)
    split = np.cos(2 * np.pi * 3 * t / n) * np.cos(2 * np.pi * np.mod(t * tone / FS, 1.0)) + 1e-4 * rng.standard_normal(n)
    assert still_line_doppler_bins(power_spectrum(split, FS), [tone], 14.0) is None
    beside = (np.cos(2 * np.pi * np.mod(t * tone / FS, 1.0)) + 3.2 * np.cos(2 * np.pi * np.mod(t * (tone / FS + 10 / n), 1.0))
              + 1e-4 * rng.standard_normal(n))
    assert still_line_doppler_bins(power_spectrum(beside, FS), [tone], 14.0) is None
