"""``mtcw bench``: the quick grid runs (as in CI) and writes its table, figures and report; the
bound it compares against agrees with one computed independently."""

from __future__ import annotations

import csv
import json

import pytest
from typer.testing import CliRunner

from mtcw_core.evaluate import range_bound
from services.cli import app

from .conftest import make_scene
from .test_chain import true_range_crb


def test_bound_agrees_with_an_independent_crb():
    sc = make_scene(targets=[{"range_m": 1.7, "loss_db": 45.0}], noise={"shot": True, "thermal": True},
                    digitizer={"samples": 2**12})
    b = range_bound(sc, seed=11)
    assert b.range_sigma_m == pytest.approx(true_range_crb(sc, seed=11), rel=0.1)
    assert b.speed_sigma_mps is None


def test_moving_bound_has_a_speed_bound():
    sc = make_scene(targets=[{"range_m": 1.7, "velocity_mps": 2.0, "loss_db": 30.0}],
                    noise={"shot": True, "thermal": True}, digitizer={"samples": 2**14})
    b = range_bound(sc)
    assert b.speed_sigma_mps is not None and 0 < b.speed_sigma_mps < 1e-2


def test_mtcw_bench_quick_writes_table_figures_and_report(tmp_path):
    out = tmp_path / "bench"
    r = CliRunner().invoke(app, ["bench", "--quick", "-o", str(out), "--scenes", "cw-bench", "--losses", "30",
                                 "--profiles", "fast,balanced", "--repeats", "4"])
    assert r.exit_code == 0, r.output
    rows = list(csv.DictReader(open(out / "results.csv")))
    assert {(x["profile"], x["method"]) for x in rows} == {("fast", "ml"), ("fast", "seed"), ("balanced", "ml"),
                                                         ("balanced", "seed")}
    res = json.loads((out / "results.json").read_text())
    cell = next(c for c in res["cells"] if c["profile"] == "balanced" and c["method"] == "ml")
    assert cell["median_time_s"] > 0 and cell["time_over_rfft"] > 0 and cell["peak_memory_mb"] > 0
    assert cell["repeats"] == 4 and len(cell["ratios"]) == 4 and cell["ratio_spread"] is not None
    assert cell["peak_memory_x_f64"] == pytest.approx(cell["peak_memory_mb"] * 2**20 / (65536 * 8))
    assert cell["outlier_rate"] == 0 and cell["crb_range_m"] > 0
    assert res["reference_costs"]["65536"]["rfft_s"] > 0
    assert res["simulation_costs"][0]["sim_s_per_frame"] > 0
    assert res["machine"]["fft_backend"] and res["machine"]["cores"] >= 1
    for png in ("pareto.png", "sigma_vs_snr.png", "outliers_vs_snr.png", "sim_cost.png", "stages.png"):
        assert (out / png).stat().st_size > 1000
    report = (out / "report.md").read_text()
    assert "mtcw bench --quick" in report and "--repeats 4" in report and "## Targets (issue 16)" in report
    assert "| `balanced` ≤ 1× one float64 rfft | cw-bench | 30 dB, ml, 65536 samples, 4 repeats |" in report
    assert "indicative: 65536 samples" in report  # --quick is not at the targets' 1e6 samples


def test_bench_reads_a_stream_json_and_refuses_a_broken_one(tmp_path):
    stream = tmp_path / "stream.json"
    stream.write_text(json.dumps({"command": "mtcw-bench-stream --seconds 1", "rows": [
        {"workers": 1, "throughput": {"frames_per_s": 10.0}}, {"workers": 2, "throughput": {"frames_per_s": 17.0}}]}))
    args = ["bench", "--quick", "-o", str(tmp_path / "b"), "--scenes", "cw-bench", "--losses", "30", "--profiles", "fast"]
    r = CliRunner().invoke(app, args + ["--stream-json", str(stream)])
    assert r.exit_code == 0, r.output
    assert "17.0 / 10.0 frames/s = 1.70× (met)" in (tmp_path / "b" / "report.md").read_text()
    stream.write_text("[1, 2]")
    r = CliRunner().invoke(app, args + ["--stream-json", str(stream)])
    assert r.exit_code != 0 and "stream-json" in r.output


def test_bench_names_a_bad_profile(tmp_path):
    r = CliRunner().invoke(app, ["bench", "--quick", "-o", str(tmp_path), "--profiles", "warp"])
    assert r.exit_code != 0 and "warp" in r.output
