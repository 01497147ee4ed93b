"""mtcw_core.dsp.validate: codes to volts, and every reason a frame is rejected."""

from __future__ import annotations

import numpy as np
import pytest

from mtcw_core.calibration import Calibration
from mtcw_core.dsp.validate import rail_fraction, validate
from mtcw_core.frame import Frame
from mtcw_core.profiles import ChainSettings
from mtcw_core.results import Rejected

FS = 1e9
TONES = (100e6, 170e6)
N = 1024


def signal(n=N):
    k = np.arange(n)
    return 0.3 * np.cos(2 * np.pi * 0.1 * k) + 0.2 * np.cos(2 * np.pi * 0.17 * k + 1.0)


def make(x=None, **kw):
    x = signal() if x is None else x
    base = dict(samples=np.atleast_2d(x), fs_hz=FS, tones_hz=TONES, wavelength_m=1.064e-6)
    base.update(kw)
    return Frame(**base)


def reason(frame, settings=None, cal=None):
    with pytest.raises(Rejected) as e:
        validate(frame, settings or ChainSettings(), cal)
    return e.value.reason


class TestRailFraction:
    def test_isolated_extreme_is_zero(self):
        r = signal()
        assert rail_fraction(r, r.max()) == 0.0
        assert rail_fraction(r, r.min()) == 0.0

    def test_two_in_a_row_are_not_a_run(self):
        r = np.zeros(100)
        r[[10, 11, 50, 51]] = 1.0
        assert rail_fraction(r, 1.0) == 0.0

    def test_clipped_run_is_its_fraction(self):
        r = signal(1000)
        r[200:230] = 5.0  # a run of 30 stuck samples
        r[500] = 5.0  # an isolated touch does not count
        assert rail_fraction(r, 5.0) == pytest.approx(30 / 1000)

    def test_several_runs(self):
        r = np.zeros(100)
        r[0:3] = -1
        r[97:100] = -1
        r[40:50] = -1
        assert rail_fraction(r, -1) == pytest.approx(16 / 100)

    def test_integer_codes(self):
        r = np.array([0, 127, 127, 127, 127, 5, -128, -128, 3, 0], np.int8)
        assert rail_fraction(r, np.int8(127)) == pytest.approx(0.4)
        assert rail_fraction(r, np.int8(-128)) == 0.0


class TestValidate:
    def test_float_volts_pass_through(self):
        x = signal()
        v, clip = validate(make(x), ChainSettings(), None)
        assert v.dtype == np.float64 and clip == 0.0
        np.testing.assert_array_equal(v, x)

    def test_float32_converted(self):
        x = signal().astype(np.float32)
        v, _ = validate(make(x), ChainSettings(), None)
        assert v.dtype == np.float64
        np.testing.assert_array_equal(v, x.astype(np.float64))

    def test_codes_to_volts(self):
        codes = np.round(signal() * 1000).astype(np.int16)
        v, _ = validate(make(codes, scale=1e-3, offset=0.25), ChainSettings(), None)
        np.testing.assert_allclose(v, codes * 1e-3 + 0.25, rtol=1e-15)

    def test_iq_is_i_plus_jq(self):
        i, q = signal(), signal()[::-1].copy()
        v, _ = validate(make(np.stack([i, q]), receiver="iq", channels=("i", "q")), ChainSettings(), None)
        assert np.iscomplexobj(v)
        np.testing.assert_array_equal(v, i + 1j * q)

    def test_pulse_ref_channel_ignored_for_signal(self):
        x = signal()
        ref = np.where(np.arange(N) < 100, 1.0, 0.0)  # a rectangular gate: not clipping
        v, clip = validate(make(np.stack([x, ref]), channels=("pd", "pulse_ref")), ChainSettings(), None)
        np.testing.assert_array_equal(v, x)
        assert clip == 0.0

    def test_clip_fraction_reported_below_the_limit(self):
        x = signal()
        x[10:13] = x.max()
        v, clip = validate(make(x), ChainSettings(max_clip_fraction=0.01), None)
        assert clip == pytest.approx(3 / N)

    @pytest.mark.parametrize("fs", [0.0, -1e9, float("nan"), float("inf")])
    def test_bad_fs(self, fs):
        assert reason(make(fs_hz=fs)) == "bad_fs"

    @pytest.mark.parametrize("wl", [0.0, -1.064e-6, 5e-8, 2e-3, 9.5e297, float("nan"), float("inf")])
    def test_bad_wavelength(self, wl):
        """The Doppler and the sidebands' shift are computed from it: an absurd wavelength (9.5e297 m,
        a decodable frame the worker fuzzing drew) is rejected, naming the field, not an internal error."""
        with pytest.raises(Rejected) as e:
            validate(make(wavelength_m=wl), ChainSettings(), None)
        assert e.value.reason == "bad_wavelength" and "wavelength_m" in str(e.value)

    @pytest.mark.parametrize("wl", [2.5e-7, 1.064e-6, 1.55e-6, 1.06e-5])
    def test_optical_wavelengths_pass(self, wl):
        validate(make(wavelength_m=wl), ChainSettings(), None)

    def test_bad_shape(self):
        assert reason(make(np.stack([signal(), signal()]))) == "bad_shape"  # 2 rows, 1 channel name

    def test_too_short(self):
        assert reason(make(signal(255))) == "too_short"

    def test_256_is_long_enough(self):
        validate(make(signal(256)), ChainSettings(), None)

    def test_length_mismatch(self):
        assert reason(make(), ChainSettings(expected_samples=2048)) == "length_mismatch"

    @pytest.mark.parametrize("tones", [(100e6,), (100e6, 500e6), (100e6, 600e6), (0.0, 100e6), (-5e6, 100e6)])
    def test_tone_plan(self, tones):
        assert reason(make(tones_hz=tones)) == "tone_plan"

    def test_tone_plan_against_settings(self):
        assert reason(make(), ChainSettings(expected_tones_hz=(100e6, 180e6))) == "tone_plan"
        validate(make(), ChainSettings(expected_tones_hz=TONES), None)

    def test_calibration_mismatch(self):
        cal = Calibration(tones_hz=(100e6, 180e6), tone_phases_rad=(0.0, 0.0), tau0_s=0.0)
        assert reason(make(), cal=cal) == "calibration_mismatch"
        ok = Calibration(tones_hz=TONES, tone_phases_rad=(0.0, 0.0), tau0_s=0.0)
        validate(make(), ChainSettings(), ok)

    @pytest.mark.parametrize("phases", [(0.0, 1e300), (-1.797e308, 0.0), (0.0, float("nan")), (2e6, 0.0)])
    def test_tone_phases_that_are_no_phase(self, phases):
        """Stated tone phases beyond 1e6 rad (or NaN) are refused, naming the field: their pair
        differences overflowed into a NaN chi2 and a point the wire refused (found by fuzzing)."""
        with pytest.raises(Rejected, match=r"tone_phases_rad\[\d\]"):
            validate(make(tone_phases_rad=phases), ChainSettings(), None)
        validate(make(tone_phases_rad=(-3.1, 1e5)), ChainSettings(), None)

    def test_bad_channels_single(self):
        assert reason(make(channels=("x",))) == "bad_channels"

    def test_bad_channels_iq(self):
        assert reason(make(np.stack([signal(), signal()]), receiver="iq", channels=("i", "pd"))) == "bad_channels"

    @pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
    def test_non_finite(self, bad):
        x = signal()
        x[7] = bad
        assert reason(make(x)) == "non_finite"

    def test_non_finite_in_q(self):
        i, q = signal(), signal()
        q[3] = np.nan
        assert reason(make(np.stack([i, q]), receiver="iq", channels=("i", "q"))) == "non_finite"

    def test_non_finite_in_q_beats_a_flat_i(self):
        i, q = np.full(N, 0.5), signal()  # every channel's finiteness is checked before flatness
        q[3] = -np.inf
        assert reason(make(np.stack([i, q]), receiver="iq", channels=("i", "q"))) == "non_finite"

    def test_non_finite_message_counts_the_samples(self):
        x = signal().astype(np.float32)
        x[[1, 5, 9]] = [np.nan, np.inf, np.nan]
        with pytest.raises(Rejected, match=r"^non_finite: 3 NaN/inf samples"):
            validate(make(x), ChainSettings(), None)

    def test_flat(self):
        assert reason(make(np.full(N, 0.5))) == "flat"

    def test_flat_codes(self):
        assert reason(make(np.zeros(N, np.int16), scale=1e-3)) == "flat"

    def test_clipped(self):
        x = np.clip(3 * signal(), -0.5, 0.5)  # the sum of tones dwells on both rails
        assert rail_fraction(x, 0.5) > 1e-3
        assert reason(make(x)) == "clipped"

    def test_an_under_resolved_record_is_not_clipped(self):
        """A weak echo on a large DC through an 8-bit digitizer auto-ranged to 1.05x the peak: the
        codes dwell on 121-122 (a random probe of the envelope saw 10-79 % "at the rails" and the
        frame refused). 8-bit rails are -128 and 127; wider codes spanning under 16 steps cannot show
        a rail. Codes pinned at 127 are still clipped."""
        rng = np.random.default_rng(2)
        dc = 121.4 + 0.3 * signal() / np.max(np.abs(signal())) + 0.2 * rng.standard_normal(signal().size)
        codes = np.rint(dc).astype(np.int8)
        assert rail_fraction(codes, codes.max()) > 0.05  # the old test's premise: the top code dwells
        for c in (codes, codes.astype(np.int16)):
            _, clip = validate(make(c, scale=1e-3), ChainSettings(), None)
            assert clip == 0.0
        pinned = codes.copy()
        pinned[100:160] = 127
        assert reason(make(pinned, scale=1e-3)) == "clipped"
        # 8-bit codes sent as 16-bit words (x256, as a scope's DATa:WIDth 2): 1-2 steps of 256
        wide = codes.astype(np.int16) * 256
        assert validate(make(wide, scale=1e-5), ChainSettings(), None)[1] == 0.0
        # a 16-bit record pinned at its dtype's limit with small dips is still clipped
        stuck = np.full(signal().size, 32767, np.int16)
        stuck[::7] = 32760
        assert reason(make(stuck, scale=1e-6)) == "clipped"

    def test_code_span_counts_adc_steps(self):
        """``code_steps``: the codes' range over the step between the codes present."""
        from mtcw_core.dsp.validate import code_steps

        def code_span_steps(r):
            return code_steps(r)[0]

        codes = np.array([120, 121, 123, 121, 122], np.int8)
        assert code_span_steps(codes) == 3
        assert code_span_steps(codes.astype(np.int16) * 256) == 3  # 8-bit codes in 16-bit words
        assert code_span_steps(np.array([-100, 0, 100], np.int16)) == 2  # steps of 100
        assert code_span_steps(np.full(5, 7, np.int16)) == 0

    def test_a_clipped_6_bit_record_is_clipped(self):
        """4-8-bit ADCs travel as int8: a 6-bit record's rails are -32 and 31, the record's own
        extremes, not int8's; it spans 63 steps, so they count."""
        codes = np.clip(np.rint(96 * signal() / np.max(np.abs(signal()))), -32, 31).astype(np.int8)
        assert rail_fraction(codes, 31) > 1e-3
        assert reason(make(codes, scale=1e-2)) == "clipped"

    def test_clipped_limit_is_a_setting(self):
        x = signal()
        x[100:120] = x.max()
        assert reason(make(x)) == "clipped"  # 20/1024 > 1e-3
        _, clip = validate(make(x), ChainSettings(max_clip_fraction=0.05), None)
        assert clip == pytest.approx(20 / N)

    def test_rejected_message_names_reason(self):
        with pytest.raises(Rejected, match=r"^too_short: 100 samples"):
            validate(make(signal(100)), ChainSettings(), None)
