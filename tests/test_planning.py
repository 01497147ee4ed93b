"""Tone planning (``mtcw_core.planning``) against facts: gcds, products, a Monte Carlo of the chain's
own cycle resolver, and a planned set simulated and ranged by the chain."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mtcw_core.chain import process_frame
from mtcw_core.phase import C
from mtcw_core.planning import (check_plan, cost_profile, line_conflicts, outlier_probability, outlier_threshold_db,
                                plan_tones)
from mtcw_core.ranging.triangulation import Observations, resolve_ml
from mtcw_core.simulate import simulate_frame

from .conftest import make_scene

SIX = (20e6, 500e6, 670e6, 700e6, 890e6, 950e6)  # the dissertation's 6-tone plan


def test_check_quasi_cw_set_gives_7_5_m_from_differences():
    """130/510/710/950 MHz: differences 380, 580, 820, 200, 440, 240 MHz, gcd 20 MHz -> c/(2*20 MHz);
    the tones' own gcd is 10 MHz (15 m), which only single-tone phases would give."""
    rep = check_plan([130e6, 510e6, 710e6, 950e6], detector_bandwidth_hz=2.5e9)
    assert rep.unambiguous_range_m == pytest.approx(C / (2 * 20e6), rel=1e-12)
    assert round(rep.unambiguous_range_m, 1) == 7.5
    assert rep.unambiguous_range_single_tone_m == pytest.approx(C / (2 * 10e6), rel=1e-12)
    assert rep.ok and "7.495 m from the pair differences" in rep.notes[1]


def test_six_tone_plan_lowers_the_side_peaks_of_500_700_950():
    """The 3-tone plan's cost has side peaks (side minima of 1 - J) the 6-tone plan removes: at the
    3-tone plan's strongest side peaks the 6-tone cost is far lower, and so is its threshold."""
    three = check_plan([500e6, 700e6, 950e6])
    six = check_plan(SIX)
    assert three.unambiguous_range_m == pytest.approx(C / (2 * 50e6)) and six.unambiguous_range_m == pytest.approx(C / (2 * 10e6))
    l3, j3 = cost_profile([500e6, 700e6, 950e6])
    l6, j6 = cost_profile(SIX)
    # the 3-tone cost at its own side peaks vs the 6-tone cost at the same offsets
    side = (j3 > 0.6) & (np.minimum(l3, l3[-1] - l3) > 0.5 * three.finest_wavelength_m)
    assert side.any()
    j6_there = np.interp(l3[side], l6, j6)
    assert np.max(j6_there) < np.max(j3[side]) - 0.2
    assert six.side_peak < three.side_peak
    assert six.outlier_threshold_db < three.outlier_threshold_db - 3


def test_products_and_separations_are_flagged():
    bad = line_conflicts([500e6, 1000e6, 1300e6], detector_bandwidth_hz=1.2e9)
    text = " ".join(bad)
    assert "2x500 = 1000 MHz lands on the line of 1000 MHz" in text
    assert "1300 MHz is above the detector bandwidth" in text
    near = line_conflicts([100e6, 108e6, 400e6], max_doppler_hz=5e6)
    assert any("100 and 108 MHz are 8 MHz apart" in c for c in near)
    assert any("lowest tone" in c for c in line_conflicts([8e6, 300e6, 500e6], max_doppler_hz=5e6))
    # third order: 2*f1 - f2 onto f3
    assert any("|2x300-200|" in c or "2x300" in c for c in line_conflicts([200e6, 300e6, 400e6, 1000e6]))
    assert line_conflicts([130e6, 510e6, 710e6, 950e6], detector_bandwidth_hz=1e9) == []
    # with 10 MHz of Doppler the third-order product 2*130 + 710 = 970 MHz comes within 2*f_d + 1 MHz of 950
    fast = line_conflicts([130e6, 510e6, 710e6, 950e6], max_doppler_hz=10e6, detector_bandwidth_hz=1e9)
    assert any("2x130+710 = 970 MHz lands on the line of 950 MHz" in c for c in fast)


@pytest.mark.parametrize("tones", [(130e6, 510e6, 710e6, 950e6), (500e6, 700e6, 950e6)])
def test_predicted_outlier_threshold_matches_monte_carlo_of_the_chain_resolver(tones):
    """Noisy line phases (variance 1/SNR) -> pair phases -> the chain's resolve_ml: the wrong-cycle
    rate 3 dB below the predicted threshold is within a factor 3 of the prediction, 3 dB above it is
    (near) zero."""
    f = np.asarray(tones)
    rep = check_plan(f)
    i, j = np.tril_indices(f.size, -1)
    df = f[i] - f[j]
    rng = np.random.default_rng(7)
    l0, trials = 1.234, 1200
    rates = []
    for snr in (rep.outlier_threshold_db - 3, rep.outlier_threshold_db + 3):
        v = 10 ** (-snr / 10)
        bad = 0
        for _ in range(trials):
            n = rng.normal(0, math.sqrt(v), f.size)
            sol = resolve_ml(Observations(df, -2 * np.pi * df * 2 * l0 / C + n[i] - n[j], np.ones(df.size)), 0.0,
                             (0.0, rep.unambiguous_range_m))
            lu = rep.unambiguous_range_m
            bad += abs((sol.range_m - l0 + lu / 2) % lu - lu / 2) > rep.finest_wavelength_m / 4
        rates.append(bad / trials)
    pred = float(outlier_probability(f, rep.outlier_threshold_db - 3))
    assert pred / 3 < rates[0] < pred * 3, (rates, pred)
    assert rates[1] <= 2 / trials
    assert outlier_threshold_db(f, 1e-3) == pytest.approx(rep.outlier_threshold_db)


def test_planned_set_meets_its_requirements():
    rep = plan_tones(unambiguous_range_m=15.0, resolution_m=1e-3, detector_bandwidth_hz=1e9, max_doppler_hz=5e6,
                     grid_hz=1e6, n_tones=4, candidates=120)
    f = np.asarray(rep.tones_hz)
    assert rep.ok and f.size == 4
    assert np.all(f % 1e6 == 0)  # on the reference-clock grid
    diffs = (f[1:] - f[0]).astype(np.int64)
    g = int(np.gcd.reduce(diffs))
    assert rep.unambiguous_range_m == pytest.approx(C / (2 * g)) and rep.unambiguous_range_m >= 15.0
    assert f[-1] + 5e6 <= 1e9 and np.min(np.diff(f)) > 2 * 5e6 and f[0] > 2 * 5e6
    assert rep.range_sigma_m <= 1e-3
    assert line_conflicts(f, 5e6, 1e9) == []
    assert rep.notes[0].startswith("chosen from")


def test_impossible_requirements_name_the_requirement():
    with pytest.raises(ValueError, match="unambiguous_range_m"):
        plan_tones(unambiguous_range_m=1e3, resolution_m=1e-3, detector_bandwidth_hz=1e9, grid_hz=1e6)
    with pytest.raises(ValueError, match="detector_bandwidth_hz"):
        plan_tones(unambiguous_range_m=15.0, resolution_m=1e-3, detector_bandwidth_hz=30e6, grid_hz=1e6)
    with pytest.raises(ValueError, match="resolution_m"):
        plan_tones(unambiguous_range_m=15.0, resolution_m=1e-7, detector_bandwidth_hz=1e9, candidates=30)
    with pytest.raises(ValueError, match="tones_hz"):
        check_plan([5e8, 5e8])


def test_planned_tones_simulated_and_processed_by_the_chain_range_correctly():
    """End to end: a plan for 15 m, 1 mm, 1 GHz, 5 MHz Doppler; a mover at 11.3 m (f_d 3 MHz) simulated
    with shot noise and ranged by the chain: the chain's unambiguous range is the planner's and the
    range is right within its sigma."""
    rep = plan_tones(unambiguous_range_m=15.0, resolution_m=1e-3, detector_bandwidth_hz=1e9, max_doppler_hz=5e6,
                     candidates=120)
    lam = 1.064e-6
    v = 3e6 * lam / 2
    sc = make_scene(modulator={"tones": [{"frequency_hz": x} for x in rep.tones_hz]},
                    targets=[{"range_m": 11.3, "velocity_mps": v, "loss_db": 30.0}], noise={"shot": True},
                    digitizer={"sample_rate_hz": 2.5e9, "samples": 2**16})
    fr = simulate_frame(sc)
    res = process_frame(fr, "balanced")
    assert res.status == "ok", res.reason
    assert res.unambiguous_range_m == pytest.approx(rep.unambiguous_range_m, rel=1e-9)
    p = max(res.targets, key=lambda t: abs(t.velocity_mps))
    truth = fr.truth[0]
    lu = rep.unambiguous_range_m
    err = (p.range_m - truth.range_m + lu / 2) % lu - lu / 2
    assert abs(err) < 5 * p.range_sigma_m + 1e-4, (p.range_m, truth.range_m, p.range_sigma_m)
    assert abs(abs(p.velocity_mps) - v) < 0.01


def test_cli_plan_tones_check_and_plan():
    from typer.testing import CliRunner

    from services.cli import app

    r = CliRunner().invoke(app, ["plan-tones", "--check", "130e6,510e6,710e6,950e6"])
    assert r.exit_code == 0 and "7.495 m from the pair differences" in r.output
    r = CliRunner().invoke(app, ["plan-tones", "--check", "500e6,1000e6,1300e6", "--bandwidth", "1.2e9"])
    assert r.exit_code == 1 and "lands on the line of 1000 MHz" in r.output
    r = CliRunner().invoke(app, ["plan-tones", "--range", "15", "--doppler", "5e6", "--candidates", "60", "--json"])
    assert r.exit_code == 0, r.output
    import json

    out = json.loads(r.output)
    assert out["ok"] and out["unambiguous_range_m"] >= 15.0
    bad = CliRunner().invoke(app, ["plan-tones", "--check", "5e8,abc"])
    assert bad.exit_code == 2 and "check" in bad.output and "Traceback" not in bad.output
