"""The benchmark's measurement (mtcw_bench/grid.py): the spread and noisy flag on synthetic
timings, per-repeat pairing of chain and reference, the stage breakdown's bookkeeping, the
memory multiple against N x 8 B, and the references transforming the frame they say. No timed
assertions: times are only checked for being there and positive."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from mtcw_bench import grid, report
from mtcw_bench.grid import (NOISY_SPREAD, REFERENCES, UNACCOUNTED, GridSpec, peak_memory, ratio_stats,
                             reference_tasks, run_cell, spread, stage_breakdown)
from mtcw_core.chain import STAGE_NAMES, get_profile
from mtcw_core.simulate import Simulator

from .conftest import make_scene


def test_spread_is_iqr_over_median():
    # numpy's linear percentiles of 1..5: p25 = 2, p50 = 3, p75 = 4
    assert spread([5, 1, 4, 2, 3]) == pytest.approx(2 / 3)
    assert spread([7.0, 7.0, 7.0]) == 0.0
    assert spread([1.0]) is None and spread([]) is None


@pytest.mark.parametrize("half_iqr, noisy", [(0.045, False), (0.055, True)])
def test_ratio_over_ten_percent_spread_is_noisy(half_iqr, noisy):
    # five repeats with ratios 1 -+ 2*h, 1 -+ h, 1: IQR = 2h, median 1, so the spread is 2h
    ratios = np.array([1 - 2 * half_iqr, 1 - half_iqr, 1.0, 1 + half_iqr, 1 + 2 * half_iqr])
    ref = np.array([0.010, 0.013, 0.007, 0.016, 0.009])  # the machine's state differs per repeat
    st = ratio_stats(list(ratios * ref), list(ref))
    assert st["spread"] == pytest.approx(2 * half_iqr)
    assert st["noisy"] is noisy and (st["spread"] > NOISY_SPREAD) is noisy
    assert st["median"] == pytest.approx(1.0) and st["repeats"] == 5


def test_ratios_pair_chain_and_reference_repeat_by_repeat():
    """A machine state that slows chain and reference alike (a fresh heap: ~2x) moves no ratio:
    paired per repeat the spread is 0, while the chain's own times spread by ~50 %."""
    ref = np.array([0.007, 0.014, 0.007, 0.013, 0.007, 0.014])
    chain = 0.73 * ref
    st = ratio_stats(list(chain), list(ref))
    assert st["median"] == pytest.approx(0.73) and st["spread"] == pytest.approx(0.0, abs=1e-12)
    assert not st["noisy"]
    assert spread(chain) > 0.4  # unpaired, the same timings would read as noise


def test_ratio_stats_refuses_unpaired_lists_and_flags_one_repeat():
    with pytest.raises(ValueError, match="pair"):
        ratio_stats([1.0, 2.0], [1.0])
    assert ratio_stats([0.5], [1.0])["noisy"] is True  # no spread can be measured from one repeat


def test_stage_breakdown_has_every_stage_and_the_unaccounted_time():
    stages = [{"validate": 0.001, "spectrum": 0.004, "extract": 0.002},
              {"validate": 0.002, "spectrum": 0.006, "extract": 0.003, "select": 0.001},
              {"validate": 0.001, "spectrum": 0.005}]  # a frame that ended early
    total = [0.008, 0.013, 0.0065]
    b = stage_breakdown(stages, total)
    assert list(b)[:len(STAGE_NAMES)] == list(STAGE_NAMES) and UNACCOUNTED in b and "total" in b
    assert b["spectrum"] == pytest.approx(0.005) and b["extract"] == pytest.approx(0.002)
    assert b["gate"] == 0.0 and b["select"] == 0.0  # did not run in 2 of 3 repeats: median 0
    # unaccounted per repeat: 0.001, 0.001, 0.0005 -> median 0.001
    assert b[UNACCOUNTED] == pytest.approx(0.001) and b["total"] == pytest.approx(0.008)


def _frames(n: int = 2**14, count: int = 3, **over):
    sc = make_scene(noise={"shot": True, "thermal": True}, digitizer={"samples": n}, **over)
    sim = Simulator(sc, 3)
    return sc, [sim.next_frame() for _ in range(count)]


def test_references_transform_the_frames_volts():
    _, (fr, *_) = _frames()
    tasks = reference_tasks(fr, get_profile("balanced"))
    x = fr.signal()
    assert x.dtype == np.float64 and "fft_volts" not in tasks  # float64 volts: one transform serves both
    assert set(tasks) == set(REFERENCES) - {"fft_volts"}
    np.testing.assert_allclose(tasks["fft_f64"](), np.fft.rfft(x), rtol=1e-9, atol=1e-9 * np.abs(x).sum())
    raw = fr.samples[fr.channels.index("pd")]
    np.testing.assert_allclose(tasks["fft_raw"](), np.fft.rfft(raw.astype(np.float64)), rtol=1e-4,
                               atol=1e-5 * np.abs(raw).sum())
    assert tasks["pass"]() == pytest.approx(float(np.sum(x)))


def test_peak_memory_is_a_multiple_of_n_times_8_bytes_and_leaves_tracing_as_found():
    n = 2**15
    _, frames = _frames(n, 2)
    m = peak_memory(frames[1], get_profile("fast"), warmup=frames[0])
    assert m["frame_f64_bytes"] == n * 8
    assert m["peak_over_frame_f64"] == pytest.approx(m["peak_bytes"] / (n * 8))
    # validate turns the float32 codes into float64 volts: the chain holds at least that copy
    assert m["peak_bytes"] >= n * 8
    assert not tracemalloc.is_tracing()
    tracemalloc.start()
    try:
        peak_memory(frames[1], get_profile("fast"))
        assert tracemalloc.is_tracing()
    finally:
        tracemalloc.stop()


def test_run_cell_times_every_repeat_and_counts_accuracy_once_per_frame():
    sc, frames = _frames(2**14, 3)
    spec = GridSpec(scenes=[], losses_db=[], profiles=["fast"], methods=["ml"], frames=3, repeats=5)
    c = run_cell(frames, sc, "fast", "ml", spec, None)
    assert c["repeats"] == 5 and len(c["ratios"]) == 5 and sum(c["status"].values()) == 3
    assert c["median_time_s"] > 0 and c["time_over_rfft"] == pytest.approx(float(np.median(c["ratios"])))
    assert set(c["reference_s"]) == set(REFERENCES) and all(v > 0 for v in c["reference_s"].values())
    assert set(c["stage_s"]) >= set(STAGE_NAMES) | {UNACCOUNTED, "total"}
    assert c["peak_memory_x_f64"] == pytest.approx(c["peak_memory_mb"] * 2**20 / (2**14 * 8))
    assert c["volts_dtype"] == "float64" and c["raw_dtype"] == str(frames[0].samples.dtype)


def test_a_profile_with_its_own_frame_count_is_not_repeated_past_it():
    sc, frames = _frames(2**14, 3)
    spec = GridSpec(scenes=[], losses_db=[], profiles=["fast"], methods=["ml"], frames=3, repeats=6,
                    profile_frames={"fast": 2})
    c = run_cell(frames, sc, "fast", "ml", spec, None)
    assert c["frames"] == 2 and c["repeats"] == 2 and sum(c["status"].values()) == 2


def test_cell_count_follows_per_profile_losses():
    spec = GridSpec(scenes=["a", "b"], losses_db=[20.0, 60.0, 94.0], profiles=["fast", "seed"], methods=["ml", "seed"],
                    profile_losses={"seed": [20.0, 94.0]})
    assert grid.cell_count(spec) == 2 * 2 * (3 + 2)


def test_fft_backend_asks_mtcw_core_and_falls_back(monkeypatch):
    from mtcw_core.dsp import spectrum

    monkeypatch.delattr(spectrum, "fft_backend", raising=False)
    assert grid.fft_backend() == "scipy default (pocketfft)"
    monkeypatch.setattr(spectrum, "fft_backend", lambda: "pyfftw 0.14 (via scipy.fft.set_backend)", raising=False)
    assert grid.fft_backend() == "pyfftw 0.14 (via scipy.fft.set_backend)"

    def broken():
        raise RuntimeError("no plan")

    monkeypatch.setattr(spectrum, "fft_backend", broken, raising=False)
    assert grid.fft_backend().startswith("unknown") and "no plan" in grid.fft_backend()


def test_machine_info_names_what_timings_depend_on():
    m = grid.machine_info()
    assert {"cpu", "cores", "python", "numpy", "scipy", "fft_backend", "scipy_fft_workers"} <= set(m)
    assert m["numpy"] == np.__version__ and m["cores"] >= 1


def test_on_another_fft_backend_the_cell_also_times_pocketffts_rfft():
    """``--fft-backend pyfftw``: the references run on FFTW, and the float64 rfft is timed on
    pocketfft too (the same transform), its ratio kept beside the target's own; none on the default."""
    pytest.importorskip("pyfftw")
    from mtcw_core.dsp.spectrum import use_fft_backend

    sc, frames = _frames(2**14, 2)
    spec = GridSpec(scenes=[], losses_db=[], profiles=["fast"], methods=["ml"], frames=2, repeats=3)
    plain = run_cell(frames, sc, "fast", "ml", spec, None)
    assert plain["time_over_rfft_pocketfft"] is None
    before = use_fft_backend("pyfftw")
    try:
        tasks = reference_tasks(frames[0], get_profile("fast"))
        assert grid.POCKETFFT_REFERENCE in tasks
        x = frames[0].signal()
        np.testing.assert_allclose(tasks[grid.POCKETFFT_REFERENCE](), tasks["fft_f64"](), rtol=0,
                                   atol=1e-9 * np.abs(x).sum())
        c = run_cell(frames, sc, "fast", "ml", spec, None)
    finally:
        use_fft_backend(before)
    assert c["time_over_rfft_pocketfft"] > 0 and c["pocketfft_rfft_s"] > 0
    row = [r for r in report.speed_target_rows([{**c, "scene": "cw-bench", "profile": "fast", "loss_db": 20.0,
                                                 "method": "ml", "samples": 2**14}]) if r["scene"] == "cw-bench"
           and r["profile"] == "fast"][0]
    assert "pocketfft's float64 rfft" in row["why"]
