"""mtcw-bench-techniques (mtcw_bench/techniques.py) in its --quick form: it runs, and its numbers are physics."""

from __future__ import annotations

import json

import pytest

from mtcw_bench import techniques


def test_quick_report_and_its_numbers(tmp_path):
    assert techniques.main(["--quick", "--out", str(tmp_path)]) == 0
    for name in ("report.md", "results.json", "fig10.png", "fig11.png", "fig14.png", "fig16.png"):
        assert (tmp_path / name).stat().st_size > 0, name
    res = json.loads((tmp_path / "results.json").read_text())
    f10 = {round(r["dl_m"], 2): r for r in res["fig10"]["rows"]}
    assert f10[0.1]["most_degraded_hz"] == 650e6 and f10[0.0]["status"] == "no_target"
    assert f10[0.3]["fit_dl_m"] == pytest.approx(0.3, abs=1e-4)
    # Fig. 11: the static depth against the closed form where the pattern is strong
    for r in res["fig11"]["rows"]:
        if r["imbalance_db"] <= 10 and r["velocity_mps"] == 0.0:
            assert r["depth_mean"] == pytest.approx(r["depth_closed_form_cos1"], rel=0.15)
        assert r["confident_wrong"] == 0
    # Sec. 5.5: 1862.3 m of total path
    assert all(abs(2 * q["range_m"] - 1862.3) < 0.05 for q in res["quasi_cw"]["rows"])
    assert "| Sec. 5.5" not in (tmp_path / "report.md").read_text()  # sections are headings, not table rows
