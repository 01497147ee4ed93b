"""PToF (mtcw_core.ranging.ptof): pulse cross-correlation against truth and its sigma against the errors."""

from __future__ import annotations


import numpy as np
import pytest

from mtcw_core.calibration import Calibration
from mtcw_core.chain import TECHNIQUES, process_frame
from mtcw_core.phase import C
from mtcw_core.profiles import get_profile
from mtcw_core.ranging import ptof
from mtcw_core.scene import load_scene, scene_variant
from mtcw_core.simulate import Simulator

PT = get_profile("balanced", technique="ptof")


def test_registered_as_a_technique():
    assert [s.name for s in TECHNIQUES["ptof"]] == ["ptof_validate", "ptof_reference", "ptof_correlate",
                                                    "ptof_select"]


def _gauss(n: int, centre: float, sigma: float) -> np.ndarray:
    k = np.arange(n)
    d = (k - centre + n / 2) % n - n / 2  # circular
    return np.exp(-0.5 * (d / sigma) ** 2)


def test_find_echoes_delay_and_sigma_against_truth_in_white_noise():
    """A well-sampled pulse (sigma 3 samples), known fractional delays: z-scores of the delays."""
    rng = np.random.default_rng(2)
    n, sd = 512, 0.02
    z, zq = [], []
    for _ in range(300):
        d = rng.uniform(100, 300)
        tpl = _gauss(n, 40.0, 3.0)
        sig = 0.6 * _gauss(n, 40.0 + d, 3.0) + rng.normal(0, sd, n)
        (e,) = ptof.find_echoes(sig, tpl, sd, template_noisy=False, max_pulses=1)
        z.append((e.delay_s - d) / e.sigma_s)
        assert e.amplitude == pytest.approx(0.6, abs=5 * sd)
        (q,) = ptof.find_echoes(sig, tpl, sd, template_noisy=False, max_pulses=1, quantize=True)
        assert q.delay_s == round(q.delay_s)
        zq.append((q.delay_s - d) / q.sigma_s)
    assert abs(np.mean(z)) < 0.15 and 0.85 < np.std(z) < 1.15, (np.mean(z), np.std(z))
    assert np.std(zq) < 1.2  # the dissertation's estimator: one sample of resolution, sigma sqrt(1/12) and noise


def test_a_noisy_template_widens_the_sigma_as_it_should():
    rng = np.random.default_rng(3)
    n, sd = 512, 0.03
    z = []
    for _ in range(300):
        d = rng.uniform(100, 300)
        tpl = _gauss(n, 40.0, 3.0) + rng.normal(0, sd, n)
        tpl[np.abs((np.arange(n) - 40 + n / 2) % n - n / 2) > 15] = 0.0  # a windowed echo, as the chain cuts it
        sig = 0.8 * _gauss(n, 40.0 + d, 3.0) + rng.normal(0, sd, n)
        (e,) = ptof.find_echoes(sig, tpl, sd, template_noisy=True, exclude=(-16, 17), max_pulses=1)
        z.append((e.delay_s - d) / e.sigma_s)
    assert 0.75 < np.std(z) < 1.2, np.std(z)


def test_mode_locked_bench_path_difference_between_the_mirrors():
    sc = load_scene("ptof-bench")
    ref = sc.architecture.reference_range_m
    for dl in (0.877, 1.0, 1.267):  # the stage's extent in the dissertation (87.7 - 126.7 cm)
        s = scene_variant(sc, targets=[{"range_m": ref + dl}])
        for fr in Simulator(s).frames(3):
            r = process_frame(fr, PT, None)
            assert r.status == "ok" and r.technique == "ptof", r.reason
            (t,) = r.targets  # the reference mirror is the template, not a target
            assert abs(t.range_m - dl) < 3 * t.range_sigma_m
            assert t.range_sigma_m < 2e-3  # far below the 7.5 mm sample step
    # with a calibration made at the reference mirror (tau0 = -2*L_ref/c), ranges are from the zero
    cal = Calibration(tones_hz=(1e6, 2e6), tone_phases_rad=(0.0, 0.0), tau0_s=-2 * ref / C)
    r = process_frame(next(Simulator(sc).frames(1)), PT, cal)
    assert abs(r.targets[0].range_m - sc.targets[0].range_m) < 3 * r.targets[0].range_sigma_m


def test_quasi_cw_reference_pulse_against_the_generator_channel():
    """The dissertation's Sec. 5.5: a 4 ns pulse, 1862.3 m of total path (931.15 m one way)."""
    sc = scene_variant(load_scene("ptof-quasi-cw"), digitizer={"samples": 2**17})  # 26 us hold the 6.2 us echo
    z = []
    for fr in Simulator(sc).frames(6):
        r = process_frame(fr, PT, None)
        assert r.status == "ok", r.reason
        t = r.targets[0]
        z.append((t.range_m - 931.15) / t.range_sigma_m)
        assert t.range_sigma_m < 0.05
    assert np.max(np.abs(z)) < 4


def test_what_ptof_cannot_range_is_rejected_or_no_target():
    sc = load_scene("ptof-bench")
    fr = next(Simulator(sc).frames(1))
    # no reference pulse at all: an unmodulated-LO frame without a pulse_ref channel
    r = process_frame(fr.with_(architecture="unmodulated_lo"), PT, None)
    assert r.status == "rejected" and "reference pulse" in r.reason
    # a period of a fraction of a sample: nothing to fold
    r = process_frame(fr.with_(pulse=fr.pulse.__class__(41.31e-9, 0.001, 0.0)), PT, None)
    assert r.status == "rejected" and r.reason.startswith("bad_pulse")
    # the target blocked: the reference mirror alone
    alone = next(Simulator(scene_variant(sc, targets=[{"loss_db": 300.0}])).frames(1))
    r = process_frame(alone, PT, None)
    assert r.status == "no_target"
    # a PB chain refuses a PToF frame (no tones) rather than ranging it
    assert process_frame(fr, "balanced").status == "rejected"


def test_stream_a_worker_with_technique_ptof_serves_points_at_the_api(tmp_path):
    """Simulate (PToF mode) -> acquisition node -> ``mtcw worker --technique ptof`` -> API, over loopback."""
    from .test_services import Bench

    b = Bench(tmp_path)
    try:
        h, pts = b.stream_scene(load_scene("ptof-bench"), 4, 10, "--technique", "ptof")
        assert h["processed"] == 4 and h["dropped"] == 0
        assert [p["technique"] for p in pts] == ["ptof"] * 4 and all(p["status"] == "ok" for p in pts)
        for p in pts:
            t = p["targets"][0]
            assert abs(t["range_m"] - 1.10) < 3 * t["range_sigma_m"]  # the path difference to the 3 cm mirror
    finally:
        b.close()
