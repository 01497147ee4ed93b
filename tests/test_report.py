"""The benchmark's report (mtcw_bench/report.py) on synthetic cells: every issue-16 target row
is rendered with met or missed by how much, noisy ratios are marked, the stage table has every
stage and the unaccounted column, memory is judged against 4x the frame in float64 (seed
exempt), and stream.json is read defensively."""

from __future__ import annotations

import csv

import pytest

from mtcw_bench.grid import UNACCOUNTED
from mtcw_bench.report import (MEMORY_LIMIT_X_F64, SPEED_TARGETS, memory_target_rows, speed_target_rows,
                               stage_table, stream_section, target_cell, verdict, write_report)
from mtcw_core.chain import STAGE_NAMES

N = 1_000_000
RFFT_S = 0.010


def cell(scene="cw-bench", profile="balanced", method="ml", loss=20.0, ratio=1.0, spread=0.05, mem_x=3.0,
         samples=N) -> dict:
    """A cell as run_cell makes one, with round numbers: stages share the chain time equally."""
    t = ratio * RFFT_S
    stages = {k: t / len(STAGE_NAMES) * 0.9 for k in STAGE_NAMES}
    stages[UNACCOUNTED], stages["total"] = 0.1 * t, t
    c = {"scene": scene, "profile": profile, "method": method, "loss_db": loss, "samples": samples, "frames": 4,
         "repeats": 8, "status": {"ok": 4}, "median_time_s": t, "time_spread": spread, "frames_per_s": 1 / t,
         "time_over_rfft": ratio, "ratio_spread": spread, "ratio_noisy": spread > 0.10, "ratios": [ratio] * 8,
         "time_over_rfft_volts": ratio, "time_over_rfft_raw": ratio, "time_over_pass": 20 * ratio,
         "reference_s": {"pass": RFFT_S / 20, "fft_f64": RFFT_S, "fft_volts": RFFT_S, "fft_raw": RFFT_S},
         "volts_dtype": "float64", "raw_dtype": "float32", "stage_s": stages,
         "range_bias_m": 1e-6, "range_sigma_m": 1e-5, "reported_sigma_m": 1.2e-5, "outlier_rate": 0.0,
         "speed_bias_mps": 0.0, "speed_sigma_mps": 0.0, "crb_range_m": 9e-6, "crb_speed_mps": None,
         "line_snr_db": 80.0, "sigma_over_crb": 1.1, "peak_memory_mb": mem_x * samples * 8 / 2**20,
         "peak_memory_x_f64": mem_x, "frame_f64_mb": samples * 8 / 2**20, "warmup_retained_mb": 0.5,
         "sim_s_per_frame": 0.1}
    for k, v in stages.items():
        c[f"stage_{k}_s"] = v
    return c


def grid_result(cells: list[dict]) -> dict:
    return {"cells": cells, "noisy_spread": 0.10,
            "reference_costs": {str(N): {"pass_s": RFFT_S / 20, "fft_f64_s": RFFT_S, "fft_volts_s": RFFT_S,
                                         "fft_raw_s": RFFT_S, "rfft_s": RFFT_S, "fft_f64_spread": 0.02,
                                         "volts_dtype": "float64", "raw_dtype": "float32"}},
            "machine": {"cpu": "Test CPU", "arch": "x86_64", "cores": 2, "usable_cores": 2, "load_avg": [0.1, 0.1, 0.1],
                        "load_avg_end": [0.2, 0.1, 0.1], "python": "3.11", "numpy": "2", "scipy": "1.17",
                        "fft_backend": "scipy default (pocketfft)", "scipy_fft_workers": 1}}


RATIOS = {"fast": 0.4, "balanced": 1.3, "accurate": 2.0, "seed": 60.0}


def full_cells() -> list[dict]:
    cs = []
    for scene in ("cw-bench", "moving-target", "six-tone"):
        for prof, r in RATIOS.items():
            for method in ("ml", "seed"):
                for loss in (20.0, 80.0):
                    cs.append(cell(scene, prof, method, loss, ratio=r if loss == 20 else r / 2,
                                   spread=0.25 if (scene, prof) == ("six-tone", "fast") else 0.04,
                                   mem_x={"fast": 1.5, "balanced": 3.5, "accurate": 4.4, "seed": 70.0}[prof]))
    return cs


def test_verdict_says_met_or_missed_by_how_much():
    assert verdict(0.4, 0.5) == "met (20 % under)"
    assert verdict(1.3, 1.0) == "missed by 30 % (1.30× the limit)"
    assert verdict(2.0, 2.0).startswith("met")
    assert verdict(None, 1.0) == "not measured"
    assert verdict(4.0012, 4.0) == "missed by 0.030 % (1.0003× the limit)"  # a near miss is not rounded to 0


def test_target_cell_takes_the_profiles_own_method_at_the_lowest_loss():
    cs = full_cells()
    c = target_cell(cs, "cw-bench", "seed")
    assert (c["method"], c["loss_db"]) == ("seed", 20.0)  # the seed profile resolves with 'seed'
    c = target_cell(cs, "cw-bench", "balanced")
    assert (c["method"], c["loss_db"]) == ("ml", 20.0)
    assert target_cell(cs, "low-coherence", "fast") is None


def test_every_speed_target_row_with_met_or_missed():
    rows = speed_target_rows(full_cells())
    assert [(r["scene"], r["profile"]) for r in rows] == [(s, p) for s, p, _ in SPEED_TARGETS]
    assert len(rows) == 9
    by = {(r["scene"], r["profile"]): r for r in rows}
    assert by["cw-bench", "fast"]["verdict"] == "met (20 % under)"
    assert by["moving-target", "balanced"]["verdict"] == "missed by 30 % (1.30× the limit)"
    assert by["six-tone", "accurate"]["verdict"].startswith("met")
    assert by["six-tone", "fast"]["noisy"] is True and by["cw-bench", "fast"]["noisy"] is False
    assert "largest stage" in by["cw-bench", "balanced"]["why"]


def test_a_target_not_run_or_off_length_says_so():
    rows = speed_target_rows([cell("cw-bench", "fast", ratio=0.3, samples=65536)])
    by = {(r["scene"], r["profile"]): r for r in rows}
    assert "indicative: 65536 samples" in by["cw-bench", "fast"]["verdict"]
    assert by["six-tone", "balanced"]["verdict"] == "not run"


def test_memory_rows_judge_the_worst_cell_against_4x_and_exempt_seed():
    cs = full_cells() + [cell("six-tone", "fast", loss=94.0, mem_x=4.2)]
    rows = {r["profile"]: r for r in memory_target_rows(cs)}
    assert MEMORY_LIMIT_X_F64 == 4.0
    assert rows["fast"]["worst_x"] == pytest.approx(4.2) and "94 dB" in rows["fast"]["cell"]
    assert rows["fast"]["verdict"] == "missed by 5.0 % (1.05× the limit)"
    assert rows["balanced"]["verdict"].startswith("met")
    assert rows["seed"]["verdict"] == "exempt"


def test_stage_table_has_every_stage_and_the_unaccounted_column():
    lines = stage_table(full_cells(), "cw-bench")
    header = [h.strip() for h in lines[0].strip("|").split("|")]
    assert header[1:] == [*STAGE_NAMES, UNACCOUNTED, "total"]
    assert [ln.split("|")[1].split()[0] for ln in lines[2:]] == ["fast", "balanced", "accurate", "seed"]
    balanced = next(ln for ln in lines if ln.startswith("| balanced"))
    assert "13.00 (1.30×)" in balanced  # the total in ms and in float64 rffts


def test_stream_section_reads_scaling_and_latency():
    stream = {"command": "mtcw-bench-stream", "rows": [
        {"workers": 1, "throughput": {"frames_per_s": 25.8, "chain_median_s": 0.035},
         "latency_at_80pct": {"latency_p50_s": 0.041, "latency_p99_s": 0.061}},
        {"workers": 2, "throughput": {"frames_per_s": 25.3, "chain_median_s": 0.075, "cpu_s_per_frame": 0.04},
         "latency_at_80pct": {"latency_p50_s": 0.079, "latency_p99_s": 0.096}},
        {"workers": 4, "throughput": {"frames_per_s": 26.0}}]}
    targets, table = stream_section(stream)
    t = dict(targets)
    assert t["replay -> 2 workers ≥ 1.6× one worker's frames/s"].startswith("25.3 / 25.8 frames/s = 0.98×")
    assert "missed" in t["replay -> 2 workers ≥ 1.6× one worker's frames/s"]
    assert "met" in t["p99 latency < 3× median (2 workers, at 80 % of their rate)"]
    assert len(table) == 2 + 3 and "cpu_s_per_frame 40.0 ms" in table[3]


@pytest.mark.parametrize("stream", [{"rows": "nope"}, {"rows": [{"workers": 2}]}, {"rows": [{"x": 1}]},
                                    {"rows": [{"workers": 1, "throughput": {"frames_per_s": "fast"}},
                                              {"workers": 2, "throughput": {}, "latency_at_80pct": None}]}])
def test_stream_section_never_raises_on_odd_content(stream):
    targets, table = stream_section(stream)
    assert targets or table


def test_write_report_renders_every_target_stage_memory_and_noisy_mark(tmp_path):
    cs = full_cells()
    res = grid_result(cs)
    res["stream"] = {"rows": [{"workers": 1, "throughput": {"frames_per_s": 20.0}},
                              {"workers": 2, "throughput": {"frames_per_s": 34.0}}]}
    path = write_report(res, tmp_path, "mtcw bench -o x")
    text = path.read_text()
    assert "Command: `mtcw bench -o x`" in text and "FFT backend: scipy default (pocketfft)" in text
    assert "Test CPU" in text and "numpy 2" in text
    for scene, prof, lim in SPEED_TARGETS:
        assert any(ln.startswith(f"| `{prof}` ≤ {lim:g}× one float64 rfft | {scene} |") for ln in text.splitlines())
    assert "missed by 30 %" in text and "| noisy |" in text
    assert "interquartile range over the median" in text
    for p in ("fast", "balanced", "accurate"):
        assert f"| `{p}` peak memory ≤ 4× the frame in float64 |" in text
    assert "(exempt: resamples to 2^23 by design)" in text
    assert "| 34.0 / 20.0 frames/s = 1.70× (met) |" in text
    for scene in ("cw-bench", "moving-target", "six-tone"):
        assert f"### {scene}" in text
    assert (tmp_path / "stages.png").stat().st_size > 1000
    rows = list(csv.DictReader(open(tmp_path / "results.csv")))
    assert len(rows) == len(cs) and f"stage_{UNACCOUNTED}_s" in rows[0] and "ratio_spread" in rows[0]


def test_stream_section_reads_mtcw_bench_streams_windows_and_cpu():
    """stream.json from ``mtcw-bench-stream --threads 1 0 --windows 3``: the targets are the
    one-thread rows', the 2-worker ratio comes with its windows' range and spread, and the CPU
    column gives each process's median CPU per published frame."""
    from mtcw_bench.report import stream_section

    def row(workers, threads, fps, cpu_ms):
        return {"workers": workers, "threads": threads,
                "throughput": {"frames_per_s": fps, "chain_median_s": 0.03,
                               "cpu": {"acq": {"cpu_s_per_frame": {"median": 1.1e-3}},
                                       "w0": {"cpu_s_per_frame": {"median": cpu_ms * 1e-3}}}},
                "latency_at_80pct": {"latency_p50_s": 0.03, "latency_p99_s": 0.06}}

    stream = {"rows": [row(1, 1, 36.8, 28.0), row(2, 1, 59.7, 15.6), row(1, 0, 32.7, 60.0), row(2, 0, 31.8, 30.0)],
              "scaling": [{"workers": 2, "threads": 0, "ratio": {"ratio": 0.97, "lo": 0.9, "hi": 1.0, "spread": 0.05}},
                          {"workers": 2, "threads": 1, "ratio": {"ratio": 1.63, "lo": 1.51, "hi": 1.71,
                                                                 "spread": 0.12, "noisy": True}}]}
    targets, table = stream_section(stream)
    scaling = dict(targets)["replay -> 2 workers ≥ 1.6× one worker's frames/s"]
    assert scaling.startswith("1.63×") and "1.51–1.71" in scaling and "noisy" in scaling and "met" in scaling
    assert len(table) == 2 + 2  # header, rule, and the one-thread rows only
    assert "acq 1.1, w0 28.0 ms" in table[2]
