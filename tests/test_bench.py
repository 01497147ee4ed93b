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
                                 "--profiles", "fast,balanced"])
    assert r.exit_code == 0, r.output
    rows = list(csv.DictReader(open(out / "results.csv")))
    assert {(x["profile"], x["method"]) for x in rows} == {("fast", "ml"), ("fast", "seed"), ("balanced", "ml"),
                                                         ("balanced", "seed")}
    res = json.loads((out / "results.json").read_text())
    cell = next(c for c in res["cells"] if c["profile"] == "balanced" and c["method"] == "ml")
    assert cell["median_time_s"] > 0 and cell["time_over_rfft"] > 0 and cell["peak_memory_mb"] > 0
    assert cell["outlier_rate"] == 0 and cell["crb_range_m"] > 0
    assert res["reference_costs"]["65536"]["rfft_s"] > 0
    assert res["simulation_costs"][0]["sim_s_per_frame"] > 0
    for png in ("pareto.png", "sigma_vs_snr.png", "outliers_vs_snr.png", "sim_cost.png"):
        assert (out / png).stat().st_size > 1000
    report = (out / "report.md").read_text()
    assert "mtcw bench --quick" in report and "| target | measured |" in report


def test_bench_names_a_bad_profile(tmp_path):
    r = CliRunner().invoke(app, ["bench", "--quick", "-o", str(tmp_path), "--profiles", "warp"])
    assert r.exit_code != 0 and "warp" in r.output
