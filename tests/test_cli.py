"""The offline commands, as a user runs them: ``mtcw simulate`` -> ``mtcw process`` ->
``mtcw calibrate``, on small recordings, judged against the simulator's truth."""

from __future__ import annotations

import csv
import json
import sys

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
    assert list(s["median_ms_per_stage"]) == [n for n in STAGE_NAMES if n not in ("gate", "square")]  # and a target: no square
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


def test_logs_are_json_lines_when_asked_and_a_bad_format_is_named():
    import os
    import subprocess
    import sys

    env = {**os.environ, "MTCW_LOG_FORMAT": "json", "MTCW_WAIT_FOR_WORKER_S": "0", "MTCW_END_TIMEOUT_S": "0",
           "MTCW_FRAMES_ENDPOINT": "tcp://127.0.0.1:0", "MTCW_MONITOR_ENDPOINT": "tcp://127.0.0.1:0"}
    r = subprocess.run([sys.executable, "-m", "services.cli", "acquire", "--frames", "2", "--rate", "0"],
                       env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    lines = [json.loads(line) for line in r.stderr.splitlines()]  # every line is one JSON object
    assert len(lines) >= 3 and all({"time", "level", "logger", "message"} <= set(x) for x in lines)
    assert any(x["logger"] == "mtcw.sockets" and '"curve": "off"' in x["message"] for x in lines)
    r = subprocess.run([sys.executable, "-m", "services.cli", "acquire"], env={**env, "MTCW_LOG_FORMAT": "xml"},
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "MTCW_LOG_FORMAT: 'xml'" in r.stderr and "Traceback" not in r.stderr


def test_keys_command_makes_an_allow_list_and_is_idempotent(tmp_path):
    d = tmp_path / "k"
    r1 = CliRunner().invoke(app, ["keys", str(d)])
    r2 = CliRunner().invoke(app, ["keys", str(d), "--client", "scope-box"])
    assert r1.exit_code == 0 and r2.exit_code == 0, r1.output + r2.output
    assert _summary(r1.output)["made"] == ["recorder", "server", "worker"]
    assert _summary(r2.output) == {"curve_dir": str(d), "made": ["scope-box"],
                                   "authorized": ["recorder", "scope-box", "worker"]}


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


@pytest.mark.parametrize("cmd", [["worker"], ["record", "-o", "unused", "-n", "1"], ["acquire", "--frames", "1"]])
def test_an_endpoint_that_cannot_be_used_is_a_settings_error_naming_the_field(cmd, tmp_path):
    import os
    import subprocess
    import sys

    field = "monitor_endpoint" if cmd[0] == "record" else "frames_endpoint"
    env = {**os.environ, f"MTCW_{field.upper()}": "tcp://127.0.0.1:x"}
    r = subprocess.run([sys.executable, "-m", "services.cli", *cmd], env=env, capture_output=True, text=True,
                       timeout=120, cwd=tmp_path)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert f"settings: {field}: " in r.stderr and "tcp://127.0.0.1:x" in r.stderr, r.stderr


def test_process_track_gives_the_range_rate_and_names_a_bad_window(tmp_path):
    """``mtcw process --track K`` on the moving target (one photodiode, 10 cm/s, 2^15 samples): every
    row carries its track; from the third frame on a range rate within 5 sigma of the truth's
    velocity; the summary counts what the tracker ended; a bad K or speed names its option."""
    from importlib.resources import files

    scene = tmp_path / "mt.toml"
    scene.write_text(files("mtcw_core.scenes").joinpath("moving-target.toml").read_text())
    rec = tmp_path / "mt"
    r = CliRunner().invoke(app, ["simulate", str(scene), "-o", str(rec), "-n", "5", "--samples", str(2**15)])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(app, ["process", str(rec), "--profile", "fast", "--track", "4", "-o", str(tmp_path / "p.csv")])
    assert r.exit_code == 0, r.output
    s = _summary(r.stdout)
    assert s["track"] == {"frames": 4, "ended": {}, "restarts": 0, "withheld_disagreeing_with_doppler": 0,
                          "steps_of_unknown_cycle": 0}
    rows = list(csv.DictReader(open(tmp_path / "p.csv")))
    assert [int(row["track_frames"]) for row in rows] == [1, 2, 3, 4, 4] and len({row["track_id"] for row in rows}) == 1
    for row in rows[2:]:
        assert abs(float(row["range_rate_mps"]) - 0.10) < 5 * float(row["range_rate_sigma_mps"])
    for bad, name in ((["--track", "2"], "--track"), (["--track", "4", "--track-max-speed", "-1"], "--track-max-speed")):
        out = CliRunner().invoke(app, ["process", str(rec), *bad])
        assert out.exit_code != 0 and name in out.output and "Traceback" not in out.output, out.output


def test_process_accumulate_ranges_beyond_coherence_and_names_a_bad_k(tmp_path):
    """``mtcw process --accumulate K`` on the low-coherence scene at 70 dB (the chain: no target);
    the errors are against the truth averaged over each point's frames."""
    from importlib.resources import files

    scene = tmp_path / "low70.toml"
    text = files("mtcw_core.scenes").joinpath("low-coherence.toml").read_text()
    scene.write_text(text.replace("loss_db = 20.0", "loss_db = 70.0"))
    rec = tmp_path / "low"
    r = CliRunner().invoke(app, ["simulate", str(scene), "-o", str(rec), "-n", "6", "--samples", str(2**15)])
    assert r.exit_code == 0, r.output
    assert _summary(CliRunner().invoke(app, ["process", str(rec)]).stdout)["status"] == {"no_target": 6}
    r = CliRunner().invoke(app, ["process", str(rec), "--accumulate", "4", "-o", str(tmp_path / "p.csv")])
    assert r.exit_code == 0, r.output
    s = _summary(r.stdout)
    assert s["status"] == {"ok": 6} and s["matched"] == 6 and s["accumulate"]["frames"] == 4
    assert s["max_abs_range_error_m"] < 5 * s["median_reported_sigma_m"]
    rows = list(csv.DictReader(open(tmp_path / "p.csv")))
    assert [int(row["accumulated_frames"]) for row in rows] == [1, 2, 3, 4, 4, 4]
    bad = CliRunner().invoke(app, ["process", str(rec), "--accumulate", "40"])
    assert bad.exit_code != 0 and "--accumulate" in bad.output and "Traceback" not in bad.output
    # the bench's laser declared: the chain's square stage ranges each frame from its squared record
    r = CliRunner().invoke(app, ["process", str(rec), "--laser-linewidth-hz", "5.3e9", "--lo-path-difference-m", "9"])
    assert r.exit_code == 0, r.output
    s = _summary(r.stdout)
    assert s["status"] == {"ok": 6} and s["matched"] == 6, s
    assert s["max_abs_range_error_m"] < 5 * s["median_reported_sigma_m"]


def test_process_sideband_direction_says_which_way_one_photodiode_moves(tmp_path):
    """``mtcw process --sideband-direction`` on one photodiode: a 47.9 m/s receding target at 40 dB
    (2^18 samples) comes out ``receding`` with a positive velocity; without the flag, ``unknown``."""
    import csv

    from .conftest import fast_mover_scene

    sc = fast_mover_scene()
    scene = tmp_path / "fast.json"
    scene.write_text(sc.model_dump_json())
    rec = tmp_path / "fast"
    r = CliRunner().invoke(app, ["simulate", str(scene), "-o", str(rec), "-n", "2", "--seed", "4"])
    assert r.exit_code == 0, r.output
    for flag, want in (([], "unknown"), (["--sideband-direction"], "receding")):
        r = CliRunner().invoke(app, ["process", str(rec), "-o", str(tmp_path / "p.csv"), *flag])
        assert r.exit_code == 0, r.output
        rows = list(csv.DictReader(open(tmp_path / "p.csv")))
        assert [row["direction"] for row in rows] == [want] * 2, rows
        assert all(float(row["velocity_mps"]) > 0 for row in rows)


@pytest.mark.parametrize("command", ["bench", "worker"])
def test_help_shows_the_fftw_extras_install_line(command):
    """The FFT backend's help names the extra to install, ``mtcw[fftw]``: rich's markup would read a
    bare ``[fftw]`` as a style tag and print ``pip install 'mtcw'``."""
    r = CliRunner().invoke(app, [command, "--help"], env={"COLUMNS": "200"})
    assert r.exit_code == 0
    assert "mtcw[fftw]" in r.stdout


def test_process_tone_phase_sigma_enters_the_range_sigma(tmp_path):
    """``mtcw process --tone-phase-sigma-rad``: the synthesizers' known drift since calibration widens
    every range sigma (the 6-tone plan, 0.03 rad per tone); a value out of bounds names the flag."""
    import csv

    from mtcw_bench.honesty import SIX_TONES
    from mtcw_core.scene import load_scene, scene_variant

    sc = scene_variant(load_scene("cw-bench"), digitizer={"samples": 2**14},
                       modulator={"tones": [{"frequency_hz": f} for f in SIX_TONES]})
    scene = tmp_path / "six.json"
    scene.write_text(sc.model_dump_json())
    rec = tmp_path / "six"
    assert CliRunner().invoke(app, ["simulate", str(scene), "-o", str(rec), "-n", "2"]).exit_code == 0
    sig = {}
    for flag in ("0", "0.03"):
        out = tmp_path / f"p{flag}.csv"
        r = CliRunner().invoke(app, ["process", str(rec), "--tone-phase-sigma-rad", flag, "-o", str(out)])
        assert r.exit_code == 0, r.output
        sig[flag] = [float(row["range_sigma_m"]) for row in csv.DictReader(open(out))]
    assert all(b > 3 * a for a, b in zip(sig["0"], sig["0.03"])), sig
    bad = CliRunner().invoke(app, ["process", str(rec), "--tone-phase-sigma-rad", "9"])
    assert bad.exit_code != 0 and "tone_phase_sigma_rad" in bad.output and "Traceback" not in bad.output


def test_simulate_stops_cleanly_where_a_target_reaches_the_sensor(tmp_path):
    """2 m at -15 m/s, 10 frames/s, asked for 5 frames: the third would put the target behind the
    sensor; ``mtcw simulate`` names the target and the frame, no traceback."""
    scene = tmp_path / "approach.toml"
    scene.write_text('[modulator]\ntones = [{ frequency_hz = 500e6 }, { frequency_hz = 700e6 }]\n'
                     '[[targets]]\nrange_m = 2.0\nvelocity_mps = -15.0\n[digitizer]\nsamples = 1024\n')
    r = CliRunner().invoke(app, ["simulate", str(scene), "-o", str(tmp_path / "rec"), "-n", "5"])
    assert r.exit_code != 0 and "targets.0.range_m" in r.output and "frame 2" in r.output, r.output
    assert "Traceback" not in r.output


def test_asking_for_stacks_on_sigusr1_never_breaks_a_service_without_a_real_stderr(monkeypatch):
    """Every service registers faulthandler on SIGUSR1 when it sets up its logging; where stderr has
    no file descriptor (embedded use, Typer's CliRunner) that is skipped, not an exception."""
    import io

    from services import cli

    monkeypatch.setattr(sys, "stderr", io.StringIO())
    cli._stacks_on_sigusr1()
    monkeypatch.setattr(sys, "stderr", None)
    cli._stacks_on_sigusr1()


def test_a_stop_signal_arms_a_stack_dump_in_case_the_stop_hangs(monkeypatch):
    """SIGTERM to a service sets its stop event, ignores further stop signals and arms faulthandler to
    write every thread's stack to stderr if the process is still there ``STOP_STACKS_AFTER_S`` later
    (the acquisition node's intermittent stop hang of 2026-11-27, undiagnosed)."""
    import faulthandler
    import os
    import signal

    from services import cli

    armed = []
    monkeypatch.setattr(faulthandler, "dump_traceback_later", lambda t, **kw: armed.append((t, kw)))
    old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        stop = cli._stop_on_signals()
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.wait(5)
        assert armed and armed[0][0] == cli.STOP_STACKS_AFTER_S and armed[0][1]["exit"] is False
        assert signal.getsignal(signal.SIGTERM) == signal.SIG_IGN
    finally:
        for s, h in old.items():
            signal.signal(s, h)
