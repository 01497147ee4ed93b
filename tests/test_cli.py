"""The offline commands, as a user runs them: ``mtcw simulate`` -> ``mtcw process`` ->
``mtcw calibrate``, on small recordings, judged against the simulator's truth."""

from __future__ import annotations

import csv
import json

import pytest
from typer.testing import CliRunner

from mtcw_core.calibration import Calibration
from mtcw_core.chain import STAGE_NAMES
from services.cli import app


def _summary(out: str) -> dict:
    return json.loads(out[out.index("{"):])


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    out = tmp_path_factory.mktemp("cli") / "mt"
    r = CliRunner().invoke(app, ["simulate", "moving-target", "-o", str(out), "-n", "4", "--samples", str(2**16)])
    assert r.exit_code == 0, r.output
    return out


def test_process_reports_truth_errors_and_stage_times(recording, tmp_path):
    r = CliRunner().invoke(app, ["process", str(recording), "--profile", "balanced", "-o", str(tmp_path / "p.csv")])
    assert r.exit_code == 0, r.output
    s = _summary(r.stdout)
    assert s["status"] == {"ok": 4} and s["matched"] == 4
    assert abs(s["range_bias_m"]) < 5 * s["median_reported_sigma_m"]
    # every stage that ran, in the chain's order (a CW scene has no gate)
    assert list(s["median_ms_per_stage"]) == [n for n in STAGE_NAMES if n != "gate"]
    rows = list(csv.DictReader(open(tmp_path / "p.csv")))
    assert len(rows) == 4 and all(row["status"] == "ok" for row in rows)


def test_process_json_output_and_bad_inputs(recording, tmp_path):
    r = CliRunner().invoke(app, ["process", str(recording), "--profile", "fast", "-o", str(tmp_path / "p.json")])
    assert r.exit_code == 0, r.output
    assert len(json.loads((tmp_path / "p.json").read_text())) == 4
    bad = CliRunner().invoke(app, ["process", str(recording), "--profile", "warp"])
    assert bad.exit_code != 0 and "profile" in bad.output and "Traceback" not in bad.output
    (tmp_path / "cal.json").write_text('{"tones_hz": [1, 2], "tone_phases_rad": [0, 0], "tau0_s": "abc"}')
    bad = CliRunner().invoke(app, ["process", str(recording), "--calibration", str(tmp_path / "cal.json")])
    assert bad.exit_code != 0 and "tau0_s" in bad.output and "Traceback" not in bad.output


def test_calibrate_writes_a_file_that_loads(tmp_path):
    rec = tmp_path / "mirror"
    r = CliRunner().invoke(app, ["simulate", "cw-bench", "-o", str(rec), "-n", "2", "--samples", str(2**14)])
    assert r.exit_code == 0, r.output
    assert _summary(CliRunner().invoke(app, ["process", str(rec)]).stdout)["status"] == {"ok": 2}
    out = tmp_path / "cal.json"
    r = CliRunner().invoke(app, ["calibrate", str(rec), "--known-range", "1.2", "-o", str(out)])
    assert r.exit_code == 0, r.output
    cal = Calibration.load(out)
    assert cal.frames_used == 2 and len(cal.tones_hz) == len(cal.tone_phases_rad) == 3


def test_info_and_a_malformed_recording_named_without_a_traceback(recording, tmp_path):
    r = CliRunner().invoke(app, ["info", str(recording)])
    assert r.exit_code == 0, r.output
    info = _summary(r.stdout)
    assert info["frames"] == 4 and info["receiver"] == "single" and len(info["truth_first_frame"]) == 1
    meta = json.loads(recording.with_name(recording.name + ".sigmf-meta").read_text())
    meta["global"]["mtcw:frame_samples"] = "abc"
    (tmp_path / "bad.sigmf-meta").write_text(json.dumps(meta))
    (tmp_path / "bad.sigmf-data").symlink_to(recording.with_name(recording.name + ".sigmf-data"))
    for cmd in ("info", "process", "calibrate"):
        args = [cmd, str(tmp_path / "bad")] + (["--known-range", "1"] if cmd == "calibrate" else [])
        bad = CliRunner().invoke(app, args)
        assert bad.exit_code == 2 and "Traceback" not in bad.output, bad.output
        assert "bad.sigmf-meta: global.mtcw:frame_samples: Input should be a valid integer, got 'abc'" in bad.output
