"""mtcw_core.phase: the speed of light, exact fractional cycles, phase wrapping."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest

from mtcw_core.phase import C, frac, tone_cycles, wrap_pi


class TestC:
    def test_si_value(self):
        assert C == 299_792_458.0

    def test_is_the_one_used_by_ranging(self):
        from mtcw_core.ranging import triangulation

        assert triangulation.C is C


class TestFrac:
    @pytest.mark.parametrize("x,want", [(0.0, 0.0), (0.25, 0.25), (1.75, 0.75), (-0.25, 0.75), (-3.0, 0.0),
                                        (12345.5, 0.5)])
    def test_values(self, x, want):
        assert frac(x) == want

    def test_range_half_open(self):
        rng = np.random.default_rng(0)
        for x in rng.uniform(-1e6, 1e6, 200):
            f = frac(float(x))
            assert 0.0 <= f < 1.0
            assert f == pytest.approx(float(x) - math.floor(float(x)), abs=0)


class TestToneCycles:
    def test_integer_plan_is_exact(self):
        # k*f/fs mod 1 with integers: compare to exact rational arithmetic
        f, fs, n, start = 950_000_001, 5_000_000_000, 1000, 2**24 - 7
        got = tone_cycles(f, fs, n, start=start)
        want = np.array([float(Fraction((start + k) * f % fs, fs)) for k in range(n)])
        np.testing.assert_array_equal(got, want)

    def test_offset_reduced_and_added(self):
        f, fs = 700e6, 5e9
        base = tone_cycles(f, fs, 64)
        shifted = tone_cycles(f, fs, 64, offset_cycles=3.25)
        np.testing.assert_allclose(np.mod(base + 0.25, 1.0), shifted, atol=1e-15)

    def test_non_integer_frequency(self):
        f, fs, n = 123.456789e6 + 0.5, 5e9, 256
        got = tone_cycles(f, fs, n)
        want = np.array([float(Fraction(k) * Fraction(f) / Fraction(fs) % 1) for k in range(n)])
        np.testing.assert_allclose(got, want, atol=1e-12)

    def test_in_unit_interval_and_shape(self):
        cyc = tone_cycles(1.23e9, 5e9, 1024, offset_cycles=-0.3, start=5)
        assert cyc.shape == (1024,) and cyc.dtype == np.float64
        assert np.all((cyc >= 0) & (cyc < 1))

    def test_start_continues_the_sequence(self):
        a = tone_cycles(310e6, 5e9, 200)
        b = tone_cycles(310e6, 5e9, 100, start=100)
        np.testing.assert_allclose(a[100:], b, atol=1e-15)

    def test_exact_where_float32_time_is_not(self):
        """The hazard the module exists for: at 2^24 samples and GHz, float32 t loses the phase."""
        f, fs, start = 950e6, 5e9, 2**24 - 16
        exact = tone_cycles(f, fs, 16, start=start)
        t32 = (np.arange(start, start + 16) / np.float32(fs)).astype(np.float32)
        naive = np.mod(t32.astype(np.float64) * f, 1.0)
        d = np.abs(wrap_pi(2 * np.pi * (naive - exact)))
        assert np.max(d) > 0.1  # float32 time: phase error of radians
        k = np.arange(start, start + 16)
        np.testing.assert_allclose(exact, (k * 950) % 5000 / 5000, atol=0)


class TestWrapPi:
    def test_range(self):
        x = np.linspace(-50, 50, 10001)
        w = wrap_pi(x)
        assert np.all(w >= -np.pi) and np.all(w < np.pi)
        np.testing.assert_allclose(np.cos(w), np.cos(x), atol=1e-12)
        np.testing.assert_allclose(np.sin(w), np.sin(x), atol=1e-12)

    def test_values(self):
        assert wrap_pi(0.0) == 0.0
        assert wrap_pi(np.pi) == pytest.approx(-np.pi)
        assert wrap_pi(3 * np.pi / 2) == pytest.approx(-np.pi / 2)
        assert wrap_pi(-3 * np.pi / 2) == pytest.approx(np.pi / 2)
        assert wrap_pi(2 * np.pi + 0.1) == pytest.approx(0.1)

    def test_float32(self):
        w = wrap_pi(np.array([7.0, -7.0], np.float32))
        np.testing.assert_allclose(w, [7 - 2 * np.pi, -7 + 2 * np.pi], rtol=1e-5)
