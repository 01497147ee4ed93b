"""AB-MTCW (mtcw_core.ranging.ab): against the closed form of the tone powers, truth and z-scores.

The closed form (:func:`ab.pattern`) is derived from the fields in the module's docstring; the
simulator computes ``|E_ref + E_echo|^2`` of the fields themselves, so their agreement is a check
of both. Records are small (2^14-2^18 samples).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mtcw_core.calibration import Calibration, CalibrationError
from mtcw_core.chain import TECHNIQUES, process_frame, run_stages
from mtcw_core.phase import C
from mtcw_core.profiles import get_profile
from mtcw_core.ranging import ab
from mtcw_core.scene import load_scene, scene_variant
from mtcw_core.simulate import Simulator

from .conftest import make_scene

FIG10_TONES = (150e6, 650e6, 1250e6, 1500e6, 2100e6)
BENCH_TONES = (79e6, 391e6, 971e6, 1657e6, 2159e6, 2623e6)
AB = get_profile("balanced", technique="ab")


def fig10_scene(dl: float, wavelength: float = 1e-6, ref_loss: float = 0.0, loss: float = 0.0, **over):
    """The dissertation's Fig. 10: 5 tones, 10 % depth, no losses, reference mirror at 0, noiseless."""
    return make_scene(laser={"wavelength_m": wavelength, "power_w": 0.01, "linewidth_hz": 0.0},
                      modulator={"transfer": "small_signal",
                                 "tones": [{"frequency_hz": f, "modulation_index": 0.1} for f in FIG10_TONES]},
                      architecture={"kind": "modulated_reference", "reference_range_m": 0.0,
                                    "reference_loss_db": ref_loss},
                      targets=[{"range_m": dl, "loss_db": loss}], **over)


def blocked(sc):
    """The same bench with the measurement arm blocked (the reference-only measurement)."""
    return scene_variant(sc, targets=[{"loss_db": 300.0}])


def normalised(sc, frames: int = 1):
    """Normalised tone powers the chain measures on ``sc`` (sorted by frequency), and the calibration."""
    cal = ab.derive_reference(Simulator(blocked(sc)).frames(frames))
    fr = next(Simulator(sc).frames(1))
    st = run_stages(fr, AB, cal, until="ab_powers").technique_state
    ref, _ = ab.reference_powers(cal, fr.tones_hz)
    return st.powers.tones_hz, st.powers.power_v2 / ref, cal


def test_registered_as_a_technique():
    assert [s.name for s in TECHNIQUES["ab"]] == ["validate", "spectrum", "ab_doppler", "ab_powers", "ab_fit",
                                                  "ab_select"]


@pytest.mark.parametrize("dl", [0.10, 0.20, 0.30])
def test_fig10_simulated_tone_powers_follow_the_closed_form(dl):
    f, y, _ = normalised(fig10_scene(dl))
    expect = ab.pattern(f, 2 * dl / C, 1.0, 1.0, 1.0)  # lossless arms; 2*dl/lambda integer: cos(Theta) = 1
    np.testing.assert_allclose(y, expect, rtol=2e-3, atol=2e-3 * expect.max())


def test_fig10_at_10_cm_650_mhz_is_most_degraded_and_peaks_repeat_every_1_5_ghz():
    f, y, _ = normalised(fig10_scene(0.10))
    assert f[np.argmin(y)] == 650e6
    assert y[list(f).index(1500e6)] == pytest.approx(y.max(), rel=1e-3)  # a peak: 1.5 GHz = c/(2*0.1 m)
    assert C / (2 * 0.10) == pytest.approx(1.5e9, rel=1e-3)
    # the chain's period: the fit gives 10 cm, and 20 / 30 cm give shorter periods
    for dl in (0.10, 0.20, 0.30):
        sc = fig10_scene(dl)
        cal = ab.derive_reference(Simulator(blocked(sc)).frames(1))
        r = process_frame(next(Simulator(sc).frames(1)), AB, cal)
        assert r.status == "ok", r.reason
        t = r.targets[0]
        assert abs(t.range_m - dl) < min(5 * t.range_sigma_m, 1e-5)
        assert t.fit_r2 > 0.9999


def test_unambiguous_path_difference():
    assert ab.unambiguous_path(FIG10_TONES) == pytest.approx(C / (4 * 50e6))  # 1.5 m, not the dissertation's 3 m
    assert ab.unambiguous_path(BENCH_TONES) == pytest.approx(C / (8 * 1e6))  # all odd multiples of 1 MHz: 37.5 m
    f = np.array(BENCH_TONES)
    g = 1e6
    tau = 2 * 1.1 / C
    # the symmetries behind it, in the closed form: Dtau <-> 1/g - Dtau, and 1/(2g) - Dtau flips the depth's sign
    np.testing.assert_allclose(np.cos(2 * np.pi * f * tau), np.cos(2 * np.pi * f * (1 / g - tau)), atol=1e-9)
    np.testing.assert_allclose(np.cos(2 * np.pi * f * tau), -np.cos(2 * np.pi * f * (1 / (2 * g) - tau)), atol=1e-9)


def test_fit_sine_recovers_a_noiseless_pattern_and_its_sigma_scales_with_the_noise():
    f = np.array(BENCH_TONES)
    tau = 2 * 1.1 / C
    y = ab.pattern(f, tau, 1.0, 0.7, 0.3)
    fit = ab.fit_sine(f, y, np.full(f.size, 1e-6), 0.0, 2 * 30 / C)
    assert C * fit.dtau_s / 2 == pytest.approx(1.1, abs=1e-9)
    assert fit.r2 == pytest.approx(1.0, abs=1e-9)
    fit2 = ab.fit_sine(f, y, np.full(f.size, 4e-6), 0.0, 2 * 30 / C)
    assert fit2.sigma_s == pytest.approx(2 * fit.sigma_s, rel=1e-6)
    # noisy patterns: the Fisher sigma covers the error (z-scores over 400 draws)
    rng = np.random.default_rng(1)
    sd = 0.02
    z = []
    for _ in range(400):
        fit = ab.fit_sine(f, y + rng.normal(0, sd, f.size), np.full(f.size, sd**2), 2 * 0.9 / C, 2 * 1.3 / C)
        z.append((fit.dtau_s - tau) / fit.sigma_s)
    assert abs(np.mean(z)) < 0.2 and 0.8 < np.std(z) < 1.25


@pytest.mark.parametrize("imbalance_db", [0.0, 10.0, 20.0, 30.0])
def test_fig11_depth_against_the_power_imbalance_follows_the_closed_form(imbalance_db):
    sc = fig10_scene(0.10, loss=imbalance_db)
    cal = ab.derive_reference(Simulator(blocked(sc)).frames(1))
    s = run_stages(next(Simulator(sc).frames(1)), AB, cal, until="ab_fit")
    fit = s.technique_state.fit
    expect = ab.pattern_depth(1.0, 10 ** (-imbalance_db / 20), 1.0)  # 2*sqrt(rho)/(1+rho) at cos(Theta) = 1
    assert fit.beta / fit.alpha == pytest.approx(expect, rel=1e-2)
    assert C * fit.dtau_s / 2 == pytest.approx(0.10, abs=1e-5)


def test_the_carrier_phase_moves_the_levels_but_not_the_range_and_its_null_is_no_target():
    dl, k = 0.30, 300_000  # 2*dl/lambda = k + theta/(2*pi): lambda ~ 2 um; echo 6 dB under the reference
    results = {}
    for theta in (0.0, math.pi / 2, 2 * math.pi / 3):
        lam = 2 * dl / (k + theta / (2 * np.pi))
        sc = fig10_scene(dl, wavelength=lam, loss=6.0, noise={"thermal": True},
                         digitizer={"samples": 2**16})
        cal = ab.derive_reference(Simulator(blocked(sc)).frames(2))
        results[theta] = process_frame(next(Simulator(sc).frames(1)), AB, cal)
    for theta in (0.0, math.pi / 2):
        t = results[theta].targets[0]
        assert abs(t.range_m - dl) < 5 * t.range_sigma_m
    # cos(Theta) = -1/2 = -a_m/a_r: Q = 0, the pattern vanishes -> no target, not a guess
    assert results[2 * math.pi / 3].status == "no_target"
    assert "faded" in results[2 * math.pi / 3].reason
    # 0.1 pm at 1540 nm and 1 m moves Theta by 0.53 rad: the closed form's levels move by percents
    f = np.array(BENCH_TONES)
    dtheta = 2 * np.pi * 2 * 1.0 * 0.1e-12 / 1540.2e-9**2
    assert dtheta == pytest.approx(0.53, abs=0.01)
    a, b = ab.pattern(f, 2 / C, 1.0, 0.5, 1.0), ab.pattern(f, 2 / C, 1.0, 0.5, math.cos(dtheta))
    assert np.max(np.abs(b / a - 1)) > 0.05


def bench_scene(**over):
    return scene_variant(load_scene("ab-bench"), **{"digitizer": {"samples": 2**18}, **over})


def test_six_tone_bench_ranges_within_its_sigma_over_frames():
    sc = bench_scene()
    cal = ab.derive_reference(Simulator(blocked(sc)).frames(8), 0.03)
    z = []
    for fr in Simulator(sc).frames(24):
        r = process_frame(fr, AB, cal)
        assert r.status == "ok" and r.technique == "ab", r.reason
        t = r.targets[0]
        assert not (t.cycle_ambiguous or t.blended or t.near_edge)
        assert t.fit_r2 > 0.99 and t.direction == "static" and t.velocity_mps == 0.0
        z.append((t.range_m - fr.truth[0].range_m) / t.range_sigma_m)
    assert r.unambiguous_range_m == pytest.approx(C / 8e6)
    assert abs(np.mean(z)) < 1.0 and 0.4 < np.std(z) < 1.3, (np.mean(z), np.std(z))


def test_moving_target_speed_from_the_baseband_line_within_its_sigma():
    sc = bench_scene(targets=[{"velocity_mps": 0.5}])
    cal = ab.derive_reference(Simulator(blocked(sc)).frames(4), 0.03)
    zr, zv = [], []
    for fr in Simulator(sc).frames(16):
        r = process_frame(fr, AB, cal)
        assert r.status == "ok", r.reason
        t = r.targets[0]
        assert t.direction == "unknown" and t.doppler_hz > 0
        zr.append((t.range_m - fr.truth[0].range_m) / t.range_sigma_m)
        zv.append((t.velocity_mps - 0.5) / t.velocity_sigma_mps)
    assert abs(np.mean(zv)) < 1.0 and np.std(zv) < 1.6, (np.mean(zv), np.std(zv))
    assert np.max(np.abs(zr)) < 4


def test_without_the_reference_measurement_or_with_a_balanced_receiver_the_frame_is_rejected():
    sc = bench_scene(digitizer={"samples": 2**16})
    fr = next(Simulator(sc).frames(1))
    r = process_frame(fr, AB, None)
    assert r.status == "rejected" and r.reason.startswith("calibration")
    pb_cal = Calibration(tones_hz=fr.tones_hz, tone_phases_rad=(0.0,) * 6, tau0_s=0.0)
    assert process_frame(fr, AB, pb_cal).reason.startswith("calibration")
    cal = ab.derive_reference([fr])
    bal = next(Simulator(scene_variant(sc, receiver={"kind": "balanced"})).frames(1))
    assert process_frame(bal, AB, cal).reason.startswith("receiver")
    with pytest.raises(CalibrationError, match="single photodiode"):
        ab.derive_reference([bal])
    # the reference arm alone: no pattern
    alone = next(Simulator(blocked(sc)).frames(1))
    assert process_frame(alone, AB, cal).status == "no_target"


def test_reference_calibration_round_trip_and_validation(tmp_path):
    sc = bench_scene(digitizer={"samples": 2**16})
    cal = ab.derive_reference(Simulator(blocked(sc)).frames(2), 0.03)
    assert cal.tones_hz == BENCH_TONES and len(cal.reference_powers_v2) == 6
    assert cal.tau0_s == pytest.approx(-2 * 0.03 / C)
    p = tmp_path / "cal.json"
    cal.save(p)
    assert Calibration.load(p) == cal
    with pytest.raises(ValueError, match="reference_powers_v2"):
        Calibration(tones_hz=(1e6, 2e6), tone_phases_rad=(0.0, 0.0), tau0_s=0.0, reference_powers_v2=(1.0,))


def test_stream_a_worker_with_technique_ab_serves_points_at_the_api(tmp_path):
    """Simulate -> acquisition node -> ``mtcw worker --technique ab`` -> API, over loopback."""
    from .test_services import Bench

    b = Bench(tmp_path)
    try:
        sc = bench_scene(digitizer={"samples": 2**16})
        cal = tmp_path / "ab-cal.json"
        ab.derive_reference(Simulator(blocked(sc)).frames(2), 0.03).save(cal)
        h, pts = b.stream_scene(sc, 4, 10, "--technique", "ab", "--calibration", str(cal))
        assert h["processed"] == 4 and h["dropped"] == 0
        assert [p["technique"] for p in pts] == ["ab"] * 4 and all(p["status"] == "ok" for p in pts)
        for p in pts:
            t = p["targets"][0]
            assert abs(t["range_m"] - 1.13) < 5 * t["range_sigma_m"] and t["fit_r2"] > 0.99
        assert 'stage="ab_fit"' in b.get("/metrics").text
    finally:
        b.close()


def test_swap_odds_are_the_gaussian_log_likelihood_ratio_s():
    """Two hypotheses D apart in chi2: their log-likelihood ratio ~ N(D, 4D), swapped with Phi(-sqrt(D)/2)."""
    rng = np.random.default_rng(0)
    for d in (4.0, 16.0, 25.0):
        llr = rng.normal(d, 2 * np.sqrt(d), 400_000)
        assert ab.swap_odds(d) == pytest.approx(np.mean(llr < 0), rel=0.05, abs=2e-4)
    assert ab.swap_odds(38.2) == pytest.approx(1e-3, rel=0.01) and ab.swap_odds(math.inf) == 0.0
