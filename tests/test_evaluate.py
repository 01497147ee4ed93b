"""mtcw_core.evaluate: matching points to truth and the error summary."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from mtcw_core.evaluate import ErrorLog, match_truth, range_bound
from mtcw_core.phase import C
from mtcw_core.scene import scene_variant
from mtcw_core.frame import TruthTarget
from mtcw_core.results import FrameResult, TargetPoint

LU = 14.9896229  # an unambiguous range (m)


def pt(range_m, v=0.0, sigma=1e-3):
    return TargetPoint(range_m=range_m, range_sigma_m=sigma, velocity_mps=v, velocity_sigma_mps=1e-3,
                       direction="unknown", snr_db=40.0, margin=0.5)


def result(*points, status="ok", lu=LU, coarse=None):
    return FrameResult(status=status, profile="test", targets=list(points), unambiguous_range_m=lu,
                       coarse_range_m=coarse)


class TestMatchTruth:
    def test_no_point(self):
        assert match_truth(result(), TruthTarget(1.0, 0.0)) is None

    @pytest.mark.parametrize("cycles", [-2, -1, 0, 1, 3])
    def test_cw_error_wrapped_into_half_the_unambiguous_range(self, cycles):
        p = pt(1.0 + 0.003 + cycles * LU)
        got, e = match_truth(result(p), TruthTarget(1.0, 0.0))
        assert got is p
        assert e == pytest.approx(0.003, abs=1e-9)

    def test_wrapped_error_in_half_open_interval(self):
        for err in np.linspace(-3 * LU, 3 * LU, 101):
            _, e = match_truth(result(pt(2.0 + err)), TruthTarget(2.0, 0.0))
            assert -LU / 2 <= e < LU / 2 + 1e-9
            assert math.remainder(e - err, LU) == pytest.approx(0.0, abs=1e-9)

    def test_gated_error_is_plain(self):
        p = pt(930.0 + LU + 0.01)
        _, e = match_truth(result(p, coarse=930.0), TruthTarget(930.0, 0.0))
        assert e == pytest.approx(LU + 0.01)

    def test_no_unambiguous_range_plain(self):
        _, e = match_truth(result(pt(20.0), lu=None), TruthTarget(1.0, 0.0))
        assert e == pytest.approx(19.0)

    def test_nearest_speed_picked(self):
        a, b = pt(3.0, v=0.0), pt(7.0, v=-5.0)  # |v| compared: a real receiver's speed is unsigned
        got, e = match_truth(result(a, b), TruthTarget(7.001, 5.0))
        assert got is b and e == pytest.approx(-0.001)
        assert match_truth(result(a, b), TruthTarget(3.0, 0.1))[0] is a


class TestErrorLog:
    ERR = np.array([0.001, -0.002, 0.0035, 0.0, 0.0007])
    SIG = np.array([1e-3, 2e-3, 1.5e-3, 1e-3, 3e-3])
    V = np.array([1.0, 1.1, 0.9, 1.05, 0.97])

    def filled(self, outlier_m=math.inf):
        log = ErrorLog(outlier_m=outlier_m)
        for e, s, v in zip(self.ERR, self.SIG, self.V):
            log.add(result(pt(5.0 + e, v=v, sigma=s)), TruthTarget(5.0, 1.0))
        return log

    def test_summary_matches_numpy(self):
        s = self.filled().summary()
        sv = self.V - 1.0
        assert s["matched"] == 5 and s["outliers"] == 0
        assert s["range_bias_m"] == pytest.approx(np.mean(self.ERR), abs=1e-12)
        assert s["range_std_m"] == pytest.approx(np.std(self.ERR, ddof=1), rel=1e-9)
        assert s["median_reported_sigma_m"] == pytest.approx(np.median(self.SIG))
        assert s["max_abs_range_error_m"] == pytest.approx(np.max(np.abs(self.ERR)), abs=1e-12)
        assert s["speed_bias_mps"] == pytest.approx(np.mean(sv), abs=1e-12)
        assert s["speed_std_mps"] == pytest.approx(np.std(sv, ddof=1), rel=1e-9)

    def test_outliers_counted_and_kept_out(self):
        log = self.filled(outlier_m=0.003)
        s = log.summary()
        assert s["outliers"] == 1 and s["matched"] == 4
        kept = self.ERR[np.abs(self.ERR) <= 0.003]
        assert s["range_bias_m"] == pytest.approx(np.mean(kept), abs=1e-12)

    def test_only_ok_results_counted(self):
        log = ErrorLog()
        log.add(result(pt(5.0), status="no_target"), TruthTarget(5.0, 0.0))
        log.add(result(status="ok"), TruthTarget(5.0, 0.0))  # ok but empty: nothing to match
        assert log.summary()["matched"] == 0 and log.outliers == 0

    def test_too_few_points(self):
        s = ErrorLog().summary()
        assert s["matched"] == 0
        assert all(s[k] is None for k in ("range_bias_m", "range_std_m", "median_reported_sigma_m",
                                          "max_abs_range_error_m", "speed_bias_mps", "speed_std_mps"))
        log = ErrorLog()
        log.add(result(pt(5.001)), TruthTarget(5.0, 0.0))
        s = log.summary()
        assert s["range_bias_m"] == pytest.approx(0.001) and s["range_std_m"] is None
        assert s["speed_std_mps"] is None


    def test_an_unmeasured_speed_is_no_error_and_range_rates_are_judged(self):
        """A point whose speed could not be measured (``unknown``, 0, the search's largest speed as
        its sigma) adds no speed error (a 10 cm/s mover would read -0.1 m/s of bias); a static claim
        does (it is an answer). Range rates over frames: their bias, spread and largest |z|."""
        log = ErrorLog()
        unknown = TargetPoint(range_m=1.0, range_sigma_m=1e-3, velocity_mps=0.0, velocity_sigma_mps=53.0,
                              direction="unknown", snr_db=30.0, margin=1.0, speed_min_mps=53.0)
        for rate in (0.098, 0.104):
            log.add(result(replace(unknown, range_rate_mps=rate, range_rate_sigma_mps=0.002)), TruthTarget(1.0, 0.1))
        log.add(result(replace(unknown, direction="static", velocity_sigma_mps=0.01)), TruthTarget(1.0, 0.0))
        s = log.summary()
        assert s["matched"] == 3 and s["speed_bias_mps"] == 0.0
        assert s["range_rates"] == 2 and s["range_rate_bias_mps"] == pytest.approx(0.001)
        assert s["range_rate_std_mps"] == pytest.approx(np.std([-0.002, 0.004], ddof=1))
        assert s["range_rate_max_abs_z"] == pytest.approx(2.0)
        assert "range_rates" not in self.filled().summary()


class TestPhaseNoiseBound:
    """``phase_noise_bound``: the white-noise bound plus the laser's phase-noise leakage between lines."""

    @staticmethod
    def six_tone_mover(linewidth_hz: float):
        from tests.conftest import make_scene

        return make_scene(laser={"linewidth_hz": linewidth_hz},
                          modulator={"tones": [{"frequency_hz": f} for f in (20e6, 500e6, 670e6, 700e6, 890e6, 950e6)]},
                          targets=[{"range_m": 7.89, "velocity_mps": 1.62, "loss_db": 40.0}],
                          noise={"shot": True, "thermal": True})

    def test_ideal_laser_is_the_white_noise_bound(self):
        from mtcw_core.evaluate import phase_noise_bound

        sc = self.six_tone_mover(0.0)
        b = phase_noise_bound(sc, seed=3, frames=2)
        assert np.all(b.leak_var_rad2 == 0)
        assert b.range_sigma_m == pytest.approx(range_bound(sc, 3).range_sigma_m, rel=1e-9)

    def test_leakage_of_the_baseband_line_onto_a_20_mhz_tone(self):
        """The 20 MHz tone's lines sit 14-26 MHz from the mover's baseband line B (and its mirror at
        -f_d), ~35 dB stronger; B's phase-noise pedestal there, from the delayed self-heterodyne
        spectrum ``linewidth*(1 - cos(2*pi*f*tau))/(pi*f^2)`` (two-sided, per Hz), gives each line a
        phase variance ``|B|^2*sum S(offset)/(2*A^2*T)`` -- the measured leakage within 3 dB. The
        bound then rises well above the white-noise one (which ignores it)."""
        import math

        from mtcw_core.dsp.tones import fit_lines
        from mtcw_core.evaluate import phase_noise_bound
        from mtcw_core.simulate import Simulator

        lw = 100e3
        sc = self.six_tone_mover(lw)
        b = phase_noise_bound(sc, seed=3, frames=16)
        fd = 2 * 1.62 / sc.laser.wavelength_m
        lines = np.array([fd, 20e6 + fd, 20e6 - fd])
        ideal = Simulator(scene_variant(sc, laser={"linewidth_hz": 0.0}, noise={"shot": False, "thermal": False}),
                          3).frame(0)
        z = np.abs(fit_lines(ideal.volts("pd"), lines, ideal.fs_hz))
        t_rec, tau = ideal.n / ideal.fs_hz, 2 * 7.89 / C

        def pedestal(f):  # two-sided PSD of the carrier phase over the delay tau, per Hz
            return lw * (1 - math.cos(2 * math.pi * f * tau)) / (math.pi * f**2)

        for k, line in ((0, lines[1]), (6, lines[2])):  # U and L of the 20 MHz tone
            predicted = z[0] ** 2 * (pedestal(abs(line - fd)) + pedestal(line + fd)) / (2 * z[1 + (k > 0)] ** 2 * t_rec)
            assert abs(10 * np.log10(b.leak_var_rad2[k] / predicted)) < 3.0, (k, b.leak_var_rad2[k], predicted)
        assert b.range_sigma_m > 1.5 * b.white_sigma_m
