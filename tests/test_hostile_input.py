"""Hostile or malformed input to the core: refused early with a reason naming the field, never a
long computation, a huge allocation or a raw traceback. (Fuzzing of every parser, services
included: tests/test_fuzz.py.)"""

from __future__ import annotations

import json
import math
from math import comb

import pytest

from mtcw_core.calibration import Calibration, CalibrationError
from mtcw_core.chain import process_frame
from mtcw_core.dsp.doppler import l1_ball
from mtcw_core.dsp.validate import search_grid_points
from mtcw_core.profiles import get_profile
from mtcw_core.ranging.targets import select_targets
from mtcw_core.results import TargetPoint
from mtcw_core.scene import SceneError, scene_from_dict
from mtcw_core.simulate import simulate_frame

from .conftest import make_scene, tones


@pytest.mark.parametrize("offset_hz", [100.0, 30.0, 1.0])
def test_tone_off_its_grid_is_refused_before_the_cycle_search(offset_hz):
    """A tone 100 Hz off the plan's grid made the cycle search span 1.5e6 m (9 s, 2.4 GB); 1 Hz
    asked for a 54 GB grid. The plan is refused with the grid size it would need."""
    fr = simulate_frame(make_scene(modulator=tones(500e6, 700e6, 950e6 + offset_hz)))
    res = process_frame(fr, "balanced")
    assert res.status == "rejected"
    assert res.reason.startswith("tone_plan") and "grid points" in res.reason
    assert set(res.stage_seconds) == {"validate"}  # nothing else ran


def test_grid_size_is_the_span_over_the_step():
    s = get_profile("balanced")
    # 500/700/950 MHz: gcd 50 MHz -> 3 m; step = c/(2*450 MHz)/16
    want = (299_792_458.0 / (2 * 50e6)) / (299_792_458.0 / (2 * 450e6) / s.points_per_cycle)
    assert search_grid_points((500e6, 700e6, 950e6), s, pulsed=False) == pytest.approx(want, rel=1e-12)
    bounded = get_profile("balanced", range_max_m=0.95)  # span 1 m (from -0.05 m)
    assert search_grid_points((500e6, 700e6, 950e6), bounded, pulsed=False) == pytest.approx(
        want * 1.0 / (299_792_458.0 / (2 * 50e6)), rel=1e-12)


def test_ten_tones_are_ranged_and_their_intermodulation_table_is_small():
    """The intermodulation table was enumerated over the whole cube 9**tones (8 tones: 20 s;
    10: over a minute); it walks the L1 ball now."""
    plan = tuple(100e6 * k + 7e6 for k in range(1, 11))
    d, r = 10, 4
    ball = sum(2**k * comb(d, k) * comb(r, k) for k in range(0, min(d, r) + 1))  # lattice points, |n|_1 <= r
    assert sum(1 for _ in l1_ball(d, r)) == ball < 10_000
    res = process_frame(simulate_frame(make_scene(modulator=tones(*plan))), "balanced")
    assert res.status == "ok" and abs(res.targets[0].range_m - 1.234) < 1e-3


def test_too_many_tones_and_too_long_records_are_refused():
    fr = simulate_frame(make_scene(modulator=tones(500e6, 700e6, 950e6)))
    assert process_frame(fr, get_profile("balanced", max_tones=2)).reason.startswith("tone_plan: 3 tones")
    assert process_frame(fr, get_profile("balanced", max_samples=2**12)).reason.startswith("too_long")
    dup = fr.with_(tones_hz=(500e6, 500e6, 950e6))
    assert "distinct" in process_frame(dup, "balanced").reason


GOOD = {"tones_hz": [5e8, 7e8], "tone_phases_rad": [0.1, 0.2], "tau0_s": 1e-9}


@pytest.mark.parametrize("text, field", [
    (json.dumps({**GOOD, "tau0_s": "abc"}), "tau0_s"),
    (json.dumps([1, 2]), "(file)"),
    (json.dumps({**GOOD, "extra_key": 1}), "extra_key"),
    (json.dumps({"tones_hz": [5e8, 7e8], "tau0_s": 0.0}), "tone_phases_rad"),
    (json.dumps({**GOOD, "tone_phases_rad": [0.1]}), "differ in length"),
    ('{"tones_hz": [5e8, 7e8], "tone_phases_rad": [0.1, NaN], "tau0_s": 0}', "tone_phases_rad.1"),
    (json.dumps({**GOOD, "tones_hz": ["5e8", 7e8]}), "tones_hz.0"),
    (json.dumps({**GOOD, "version": 7}), "version"),
    (json.dumps({**GOOD, "tone_amplitudes": [1.0]}), "tone_amplitudes"),
    (json.dumps({**GOOD, "tone_amplitudes": [1.0, -0.5]}), "tone_amplitudes"),
    (json.dumps({**GOOD, "tone_amplitude_std": [0.01, -0.01]}), "tone_amplitude_std"),
    (json.dumps({**GOOD, "tone_amplitude_std": [0.01, 0.01]}), "tone_amplitude_std: .*without .*tone_amplitudes"),
    ("{{{", "Invalid JSON"),
])
def test_malformed_calibrations_name_the_field(tmp_path, text, field):
    p = tmp_path / "cal.json"
    p.write_text(text)
    with pytest.raises(CalibrationError, match=f"calibration .*{field.replace('(', '[(]').replace(')', '[)]')}"):
        Calibration.load(p)


def test_calibration_round_trip(tmp_path):
    cal = Calibration(tones_hz=(5e8, 7e8), tone_phases_rad=(0.1, -0.2), tau0_s=3.3e-9, frames_used=4)
    cal.save(tmp_path / "c.json")
    assert Calibration.load(tmp_path / "c.json") == cal


@pytest.mark.parametrize("where", ["range", "loss", "linewidth"])
def test_scenes_refuse_nan_and_inf(where):
    base = make_scene().model_dump()
    if where == "range":
        base["targets"][0]["range_m"] = math.nan
    elif where == "loss":
        base["targets"][0]["loss_db"] = math.inf
    else:
        base["laser"]["linewidth_hz"] = math.nan
    with pytest.raises(SceneError, match="finite"):
        scene_from_dict(base)


def test_an_ok_point_is_finite():
    settings = get_profile("balanced")
    good = TargetPoint(1.0, 1e-4, 0.0, 1e-3, "static", 40.0, 0.9, tone_snr_db={"5e8": 40.0})
    bad = TargetPoint(2.0, math.inf, 0.0, 1e-3, "static", 40.0, 0.9, tone_snr_db={"5e8": 40.0})
    assert select_targets([(0, bad)], settings) == []
    assert select_targets([(0, good), (1, bad)], settings) == [good]
