"""mtcw_core.evaluate: matching points to truth and the error summary."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mtcw_core.evaluate import ErrorLog, match_truth
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
