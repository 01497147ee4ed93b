"""The honesty map (issue 12): its bookkeeping on hand-made results, its loss ladder against the
bound and the self-beat's physics, and the quick map end to end (as in CI)."""

from __future__ import annotations

import csv
import gzip
import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from mtcw_bench.honesty import (Config, MapSpec, case_scenes, check_targets, declared, grid, must_find, plan,
                                predicted_bound, run_map, self_beat_amplitude_v, summarise, with_targets)
from mtcw_bench.honesty_report import (monotonic_violations, write_honesty_report, z_band_probability,
                                       z_scatter_inconsistent)
from mtcw_core.chain import process_frame
from mtcw_core.evaluate import judge_frame, range_bound
from mtcw_core.frame import TruthTarget
from mtcw_core.results import FrameResult, TargetPoint
from mtcw_core.scene import load_scene, scene_variant
from mtcw_core.simulate import Simulator
from services.cli import app

from .conftest import make_scene

LU = 2.99792458  # unambiguous range of 500/700/950 MHz (gcd of the differences 50 MHz), m


def pt(range_m: float, v: float = 0.0, sigma: float = 1e-3, v_sigma: float = 1e-3, direction: str = "unknown",
       **flags) -> TargetPoint:
    return TargetPoint(range_m=range_m, range_sigma_m=sigma, velocity_mps=v, velocity_sigma_mps=v_sigma,
                       direction=direction, snr_db=40.0, margin=0.5, **flags)


def res(*points: TargetPoint, status: str = "ok") -> FrameResult:
    return FrameResult(status=status, profile="test", targets=list(points), unambiguous_range_m=LU)


class TestJudgeFrame:
    def test_a_right_answer_is_not_wrong(self):
        v = judge_frame(res(pt(1.0015)), [TruthTarget(1.0, 0.0)])
        assert v.points[0].range_z == pytest.approx(1.5)
        assert not v.confident_wrong and not v.confident_false and v.missed == () and v.false_targets == 0

    def test_a_deliberately_wrong_range_is_confident_wrong(self):
        v = judge_frame(res(pt(1.0 + 0.012)), [TruthTarget(1.0, 0.0)])  # 12 sigma off, no flag
        assert v.points[0].range_z == pytest.approx(12.0)
        assert v.confident_wrong and v.flagged_wrong == 0

    @pytest.mark.parametrize("flag", ["blended", "near_edge", "cycle_ambiguous"])
    def test_the_same_error_with_a_flag_is_flagged_wrong_not_confident(self, flag):
        v = judge_frame(res(pt(1.012, **{flag: True})), [TruthTarget(1.0, 0.0)])
        assert not v.confident_wrong and v.flagged_wrong == 1 and v.flagged_points == 1
        assert v.points[0].flags == (flag,)

    def test_just_inside_five_sigma_is_not_wrong_and_just_outside_is(self):
        assert not judge_frame(res(pt(1.00499)), [TruthTarget(1.0, 0.0)]).confident_wrong
        assert judge_frame(res(pt(1.00501)), [TruthTarget(1.0, 0.0)]).confident_wrong

    def test_a_whole_unambiguous_range_off_is_right(self):
        v = judge_frame(res(pt(1.001 + 2 * LU)), [TruthTarget(1.0, 0.0)])
        assert v.points[0].range_error_m == pytest.approx(0.001, abs=1e-9) and not v.confident_wrong

    def test_a_mover_reported_static_far_below_its_speed_is_confident_wrong(self):
        # a static point says v = 0 with the smallest detectable speed as its sigma
        v = judge_frame(res(pt(1.0, 0.0, v_sigma=0.016, direction="static")), [TruthTarget(1.0, 0.10)])
        p = v.points[0]
        assert not p.speed_measured and p.speed_z == pytest.approx(-0.10 / 0.016)
        assert v.confident_wrong
        # ... but not when the speed is below what it says it can detect
        v = judge_frame(res(pt(1.0, 0.0, v_sigma=0.04, direction="static")), [TruthTarget(1.0, 0.035)])
        assert not v.confident_wrong

    def test_a_speed_that_could_not_be_measured_is_a_bound_not_an_estimate(self):
        # laser incoherent at the range: 0 with the search's largest speed as sigma and speed_min
        v = judge_frame(res(pt(1.0, 0.0, v_sigma=5.0, speed_min_mps=5.0)), [TruthTarget(1.0, 0.10)])
        assert not v.points[0].speed_measured and not v.confident_wrong
        assert summarise([v], 1)["speed_z_n"] == 0
        # a real detector's measured |v| also says `unknown`: an estimate
        v = judge_frame(res(pt(1.0, 0.1001, v_sigma=1e-3, speed_min_mps=0.05)), [TruthTarget(1.0, 0.10)])
        assert v.points[0].speed_measured and summarise([v], 1)["speed_z_n"] == 1

    def test_a_real_detector_compares_speeds_an_iq_one_velocities(self):
        truth = [TruthTarget(1.0, -0.5)]  # approaching
        assert not judge_frame(res(pt(1.0, 0.5)), truth).confident_wrong  # |v| right, direction unknown
        v = judge_frame(res(pt(1.0, 0.5, direction="receding")), truth)  # IQ says receding: wrong sign
        assert v.points[0].speed_error_mps == pytest.approx(1.0) and v.confident_wrong

    def test_a_missed_target_and_a_ghost_are_counted(self):
        truths = [TruthTarget(0.81, 0.0), TruthTarget(2.46, 0.35)]
        ghost = pt(1.7, 62.0)
        v = judge_frame(res(pt(2.461, 0.35), ghost), truths)
        assert v.missed == (0,) and v.false_targets == 1 and v.confident_false and not v.confident_wrong
        assert [p.truth_index for p in v.points] == [1, None]

    def test_a_flagged_ghost_is_a_false_target_but_not_confident(self):
        v = judge_frame(res(pt(1.0, 0.0), pt(1.7, 62.0, blended=True)), [TruthTarget(1.0, 0.0)])
        assert v.false_targets == 1 and not v.confident_false

    def test_points_pair_with_truths_one_to_one_by_speed(self):
        truths = [TruthTarget(0.81, 0.0), TruthTarget(2.46, 0.35)]
        v = judge_frame(res(pt(2.4605, 0.3501), pt(0.8102, 0.0, direction="static", v_sigma=0.05)), truths)
        assert [p.truth_index for p in v.points] == [1, 0] and v.missed == () and not v.confident_wrong

    @pytest.mark.parametrize("status", ["no_target", "rejected"])
    def test_a_frame_without_points_misses_every_truth(self, status):
        v = judge_frame(res(status=status), [TruthTarget(1.0, 0.0), TruthTarget(2.0, 1.0)])
        assert v.missed == (0, 1) and v.points == () and not v.confident_wrong

    def test_a_real_frame_right_then_made_wrong(self):
        sc = make_scene(targets=[{"range_m": 1.234, "loss_db": 30.0}], noise={"shot": True, "thermal": True})
        fr = Simulator(sc, 3).frame(0)
        r = process_frame(fr, "balanced")
        assert r.status == "ok"
        assert not judge_frame(r, fr.truth).confident_wrong
        p = r.targets[0]
        p.range_m += 8 * p.range_sigma_m
        v = judge_frame(r, fr.truth)
        assert v.confident_wrong and abs(v.points[0].range_z) > 5


class TestSummarise:
    def test_a_range_rate_far_from_the_velocity_is_confident_wrong(self):
        """A tracked point's range rate (mtcw_core.ranging.track) is judged against the truth's
        velocity (positive receding): 0.10 +- 0.004 against 0.10 is right, against -0.10 (the wrong
        direction) 50 sigma off and confident wrong; an untracked point has no rate z."""
        p = pt(1.0, 0.10, range_rate_mps=0.10, range_rate_sigma_mps=0.004, track_id=1, track_frames=12)
        v = judge_frame(res(p), [TruthTarget(1.0, 0.10)])
        assert v.points[0].rate_z == pytest.approx(0.0) and not v.confident_wrong
        v = judge_frame(res(p), [TruthTarget(1.0, -0.10)])
        assert v.points[0].rate_z == pytest.approx(50.0) and v.confident_wrong
        assert judge_frame(res(pt(1.0)), [TruthTarget(1.0, 0.0)]).points[0].rate_z is None
        s = summarise([judge_frame(res(p), [TruthTarget(1.0, 0.10)])] * 2, 1)
        assert s["rate_z_n"] == 2 and s["rate_z_max"] == pytest.approx(0.0)

    def test_counts_and_z_statistics(self):
        truths = [TruthTarget(1.0, 0.0)]
        zs = [0.5, -1.0, 2.0, 12.0]
        verdicts = [judge_frame(res(pt(1.0 + z * 1e-3)), truths) for z in zs]
        verdicts.append(judge_frame(res(status="no_target"), truths))
        verdicts.append(judge_frame(res(pt(1.0), pt(2.0, 9.0)), truths))  # right + a ghost
        s = summarise(verdicts, 1)
        assert s["frames"] == 6 and s["ok"] == 5 and s["no_target"] == 1
        assert s["missed"] == 1 and s["false_targets"] == 1 and s["truths"] == 6
        assert s["confident_wrong"] == 1 and s["confident_false"] == 1 and s["confident_any"] == 2
        all_z = zs + [0.0]
        assert s["range_z_n"] == 5
        assert s["range_z_mean"] == pytest.approx(np.mean(all_z))
        assert s["range_z_std"] == pytest.approx(np.std(all_z, ddof=1))
        assert s["range_z_max"] == pytest.approx(12.0)
        assert s["speed_z_n"] == 5 and s["speed_z_std"] == pytest.approx(0.0)

    def test_unflagged_points_have_z_statistics_of_their_own(self):
        """A flagged wrong cycle (z 40) counts in the cell's range z std, not in the unflagged one's."""
        truths = [TruthTarget(1.0, 0.0)]
        zs = [0.5, -1.0, 2.0]
        verdicts = [judge_frame(res(pt(1.0 + z * 1e-3)), truths) for z in zs]
        verdicts.append(judge_frame(res(pt(1.04, cycle_ambiguous=True)), truths))
        s = summarise(verdicts, 1)
        assert s["range_z_n"] == 4 and s["range_z_std"] == pytest.approx(np.std(zs + [40.0], ddof=1))
        assert s["range_z_unflagged_n"] == 3
        assert s["range_z_unflagged_mean"] == pytest.approx(np.mean(zs))
        assert s["range_z_unflagged_std"] == pytest.approx(np.std(zs, ddof=1))
        assert s["speed_z_unflagged_n"] == 3 and s["speed_z_n"] == 4

    def test_static_claims_count_for_the_largest_speed_z_only(self):
        truths = [TruthTarget(1.0, 0.1)]
        v = [judge_frame(res(pt(1.0, 0.0, v_sigma=0.01, direction="static")), truths) for _ in range(3)]
        s = summarise(v, 1)
        assert s["speed_z_n"] == 0 and s["speed_z_mean"] is None
        assert s["speed_z_max"] == pytest.approx(10.0) and s["confident_wrong"] == 3


class TestMustFind:
    def test_each_target_against_its_own_bound(self):
        """Two targets, the second behind 25 dB more loss: the first's lines well above the 13 dB
        threshold, the second's below it -- only the first must be found, and a frame that misses
        the second counts no must-find miss."""
        sc = make_scene(targets=[{"range_m": 1.2, "loss_db": 60.0}, {"range_m": 2.1, "velocity_mps": 0.5, "loss_db": 85.0}],
                        noise={"shot": True, "thermal": True})
        first = predicted_bound(with_targets(sc, [sc.targets[0].model_dump()])).line_snr_db
        second = predicted_bound(with_targets(sc, [sc.targets[1].model_dump()])).line_snr_db
        assert first - second > 20.0  # 25 dB more loss (a mover's lines: also split into U and L)
        want = [first >= 13, second >= 13]
        assert must_find(sc, first, False) == want and want[0] and not want[1]
        v = judge_frame(res(pt(1.2)), [TruthTarget(1.2, 0.0), TruthTarget(2.1, 0.5)])
        s = summarise([v], 2, must_find(sc, first, False))
        assert s["missed"] == 1 and s["missed_must_find"] == 0
        assert summarise([v], 2)["missed_must_find"] == 1  # no mask: every miss counts


def _cell(**over) -> dict:
    base = {"profile": "balanced", "predicted_snr_db": 20.0, "confident_wrong": 0, "confident_false": 0, "missed": 0,
            "range_z_n": 10, "range_z_mean": 0.1, "range_z_std": 1.0, "speed_z_n": 0, "speed_z_mean": None,
            "speed_z_std": None, "range_std_over_crb": 1.1, "first_moves": True, "loss_db": [60.0]}
    return {**base, **over}


class TestCheckTargets:
    def test_an_honest_cell_meets_everything(self):
        assert check_targets(_cell()) == []

    def test_each_miss_is_named(self):
        assert check_targets(_cell(confident_wrong=1)) == ["confident_wrong"]
        assert check_targets(_cell(confident_false=2)) == ["confident_false"]
        assert check_targets(_cell(missed=1)) == ["missed"]
        assert check_targets(_cell(range_z_std=1.4)) == ["range_z"]
        assert check_targets(_cell(range_z_mean=-0.4)) == ["range_z"]
        assert check_targets(_cell(range_std_over_crb=5.3)) == ["crb"]

    def test_below_the_threshold_only_confident_answers_count(self):
        c = _cell(predicted_snr_db=12.0, missed=3, range_z_std=3.0)
        assert check_targets(c) == []
        assert check_targets({**c, "confident_wrong": 1}) == ["confident_wrong"]

    def test_only_targets_that_had_to_be_found_count_as_missed(self):
        # a weaker second mover below the threshold, missed: not a miss of the target
        assert check_targets(_cell(missed=3, missed_must_find=0)) == []
        assert check_targets(_cell(missed=3, missed_must_find=1)) == ["missed"]

    def test_too_few_z_values_are_not_judged(self):
        assert check_targets(_cell(range_z_n=4, range_z_std=9.0)) == []


class TestLadder:
    def test_rungs_put_the_bound_at_the_rung_snr(self):
        """The planned loss gives the rung's line SNR by the bound computed afresh (LO beats: 1 dB per dB)."""
        cfgs = [c for c in grid(quick=True) if c.slice == "length"][:1]
        groups = plan(cfgs, 2)
        assert [g.rung for g in groups] == ["snr=30", "snr=10"]
        for g in groups:
            assert predicted_bound(g.scene).line_snr_db == pytest.approx(g.snr_target_db, abs=0.5)
        assert groups[1].scene.targets[0].loss_db - groups[0].scene.targets[0].loss_db == pytest.approx(20, abs=0.5)

    def test_the_bound_scene_of_an_iq_cell_is_its_balanced_twin(self):
        sc = scene_variant(load_scene("moving-target"), receiver={"kind": "iq"}, digitizer={"samples": 2**12})
        assert range_bound(sc) is None
        assert predicted_bound(sc).line_snr_db > 0

    def test_self_beat_amplitude_follows_the_echo_power(self):
        """|E_echo|^2 = a^2 (1-beta) P0 |T|^2 with |T|^2 ~ (1 + sum m_i cos)/2: the line at f_i has
        current R a^2 (1-beta) P0 m_i/2 (small signal), volts x R_load; independent of the LO and coherence."""
        sc = scene_variant(load_scene("low-coherence"), digitizer={"samples": 2**14}, targets=[{"loss_db": 10.0}])
        a2, p0, beta = 10 ** (-10.0 / 10), sc.laser.power_w, sc.lo_fraction
        r, rl = sc.receiver.responsivity_a_per_w, sc.receiver.load_ohm
        expect = np.array([r * a2 * (1 - beta) * p0 * t.modulation_index / 2 * rl for t in sc.modulator.tones])
        got = self_beat_amplitude_v(sc)
        np.testing.assert_allclose(got, expect, rtol=0.02)
        # 6 dB more loss: a quarter of the amplitude (power squared)
        got2 = self_beat_amplitude_v(scene_variant(sc, targets=[{"loss_db": 16.0}]))
        np.testing.assert_allclose(got2 / got, 10 ** (-6 / 10), rtol=0.01)


class TestGrid:
    def test_the_full_grid_has_every_axis_of_the_issue(self):
        cfgs = grid(quick=False)
        scenes = [c.scene for c in cfgs]
        assert {c.slice for c in cfgs} == {"length", "receiver", "laser", "targets", "six-tone", "jitter", "quasi-cw"}
        assert {s.digitizer.samples for s in scenes} >= {2**16, 2**18, 2**20}
        assert {s.receiver.kind for s in scenes} == {"single", "balanced", "iq"}
        assert {s.laser.linewidth_hz for s in scenes} == {0.0, 100e3, 5.3e9}
        assert {len(s.targets) for s in scenes} == {1, 2, 3}
        assert any(s.noise.trigger_jitter_s > 0 for s in scenes) and any(s.pulsing for s in scenes)
        # speeds: 0, below a bin, a few bins, 0.45 x the smallest tone spacing (Doppler = 2v/lambda)
        b16 = [s for c, s in zip(cfgs, scenes) if c.slice == "length" and s.digitizer.samples == 2**16]
        fd_bins = sorted(2 * s.targets[0].velocity_mps / s.laser.wavelength_m / (s.digitizer.sample_rate_hz / 2**16)
                         for s in b16)
        assert fd_bins[0] == 0 and 0 < fd_bins[1] < 1 and 3 <= fd_bins[2] <= 10
        fd_top = 2 * max(s.targets[0].velocity_mps for s in b16) / b16[0].laser.wavelength_m
        assert fd_top == pytest.approx(0.45 * 200e6)
        # 5.3 GHz at 500 x the coherence length: the LO is 9 m longer, L_coh = c/(pi*linewidth)
        low = next(s for s in scenes if s.laser.linewidth_hz == 5.3e9)
        assert low.paths.lo_path_difference_m / low.laser.coherence_length_m == pytest.approx(500, rel=0.01)

    def test_the_cases_are_the_issues(self):
        cases = case_scenes()
        assert len({k.split()[0] for k in cases if not k.startswith("movers:")}) == 9
        # and the several-movers probe's telling cases (mtcw_bench.movers_probe), on their own rows
        assert sum(k.startswith("movers:") for k in cases) == 5
        _, sc, _ = cases["1 3-tone 70 dB"]
        t = sc.targets[0]
        assert (t.range_m, t.velocity_mps, t.loss_db, sc.digitizer.samples) == (6.789, 0.21, 70.0, 2**18)
        _, sc, _ = cases["6 small Doppler"]
        fd = 2 * sc.targets[0].velocity_mps / sc.laser.wavelength_m
        assert fd == pytest.approx(45e3, rel=0.01) and sc.digitizer.sample_rate_hz / sc.digitizer.samples == 10e3


    def test_the_tracked_cases_run_balanced_and_its_range_rate(self):
        """The tracked configurations (case 4's mover among them) give a ``balanced`` cell and a
        ``balanced+trk12`` cell over the same results; the tracked cell's rate z counts."""
        from mtcw_bench.honesty import TRACK_FRAMES, run_group, track_configs, track_label

        cfgs = track_configs()
        assert cfgs[0].label.startswith("4 low-coherence mover") and all(c.track == TRACK_FRAMES for c in cfgs)
        small = Config("cases", "mover trk3", scene_variant(load_scene("moving-target"), digitizer={"samples": 2**14}),
                       frames=5, track=3)
        (g,) = plan([small], 2)
        out = run_group(g, ("fast", "balanced"))
        a, b = out["cells"]
        assert (a["profile"], b["profile"]) == ("balanced", track_label(3))
        assert a["rate_z_n"] == 0 and b["rate_z_n"] == 3 and b["confident_wrong"] == 0 and b["rate_z_max"] < 5
        assert (a["range_z_mean"], a["ok"]) == (b["range_z_mean"], b["ok"])  # the same points, with a rate


class TestQuickMap:
    def test_a_small_map_books_balance_and_the_report_is_written(self, tmp_path):
        result = run_map(MapSpec(quick=True, frames=2, profiles=("balanced",), slices=["length", "jitter"], jobs=1))
        cells, rows = result["cells"], result["frames"]
        assert result["size"]["processed_frames"] == len(rows) == sum(c["frames"] for c in cells) == 2 * len(cells)
        for c in cells:
            mine = [r for r in rows if (r["config"], r["rung"], r["profile"]) == (c["config"], c["rung"], c["profile"])]
            assert c["confident_wrong"] == sum(r["confident_wrong"] for r in mine)
            assert c["missed"] == sum(r["missed"] for r in mine)
            assert c["ok"] == sum(r["status"] == "ok" for r in mine)
            assert c["ok"] + c["no_target"] + c["rejected"] == c["frames"]
            assert c["predicted_snr_db"] == pytest.approx(float(c["rung"][4:]), abs=3.0)
        path = write_honesty_report({**result, "command": "mtcw-bench-honesty --quick", "machine": "test"}, tmp_path)
        text = path.read_text()
        assert "mtcw-bench-honesty --quick" in text and "| target | measured | met? |" in text
        assert "| ... range, unflagged points only" in text and "| ... speed, unflagged points only" in text
        for png in ("confident_wrong.png", "range_z_std.png", "speed_z_std.png", "missed.png"):
            assert (tmp_path / png).stat().st_size > 5000
        back = list(csv.DictReader(gzip.open(tmp_path / "frames.csv.gz", "rt")))
        assert len(back) == len(rows)
        assert json.loads((tmp_path / "cells.json").read_text())["size"]["cells"] == len(cells)

    def test_mtcw_bench_honesty_quick_runs(self, tmp_path):
        r = CliRunner().invoke(app, ["bench", "--honesty", "--quick", "-o", str(tmp_path), "--frames", "1",
                                     "--profiles", "fast"])
        assert r.exit_code == 0, r.output
        rows = list(csv.DictReader(open(tmp_path / "cells.csv")))
        assert {x["slice"] for x in rows} == {"length", "receiver", "laser", "targets", "six-tone", "jitter"}
        assert {x["profile"] for x in rows} == {"fast"}
        assert "mtcw-bench-honesty --quick" in (tmp_path / "report.md").read_text()

    def test_a_bad_profile_is_named(self, tmp_path):
        r = CliRunner().invoke(app, ["bench", "--honesty", "--quick", "-o", str(tmp_path), "--profiles", "warp"])
        assert r.exit_code != 0 and "warp" in r.output


def test_monotonic_violations_compare_the_same_target_at_the_same_loss():
    def cell(n, missed, speed="v=0", loss=70.0):
        return {"slice": "length", "config": f"N=2^{int(math.log2(n))} {speed}", "rung": "snr=10", "profile": "fast",
                "loss_db": [loss], "samples": n, "missed": missed, "truths": 4}
    v = monotonic_violations([cell(2**16, 0), cell(2**18, 3), cell(2**20, 0)])
    assert [(x["short"], x["long"], x["large"]) for x in v] == [(2**16, 2**18, True)]
    # a speed defined in bins is a different target at each length: not compared
    assert monotonic_violations([cell(2**16, 0, "v=6 bins"), cell(2**18, 4, "v=6 bins")]) == []
    assert monotonic_violations([cell(2**16, 0), cell(2**18, 4, loss=80.0)]) == []


class TestWhatAnswersATruth:
    def test_right_speed_wrong_cycle_answers_and_is_wrong(self):
        v = judge_frame(res(pt(1.4, 0.21)), [TruthTarget(1.0, 0.21)])
        assert v.points[0].truth_index == 0 and v.confident_wrong

    def test_right_range_speed_reported_zero_answers_and_is_wrong(self):
        v = judge_frame(res(pt(1.12, 0.0, v_sigma=0.016, direction="static")), [TruthTarget(1.12, 0.10)])
        assert v.points[0].truth_index == 0 and v.confident_wrong and v.missed == ()

    def test_a_point_agreeing_on_both_answers_that_truth_before_one_agreeing_on_speed(self):
        """A mover at 1.08 record bins reported ``static`` within its speed floor, at its own
        range, beside a static target 7 m away 47 dB weaker (a random probe of the envelope, 6
        tones at 1550 nm): it answers the mover (range z 0.5, speed z 1.1), not the static
        target it agrees with on speed alone (range z -2442: a confident wrong the chain never
        made); the static target is missed."""
        p = pt(2.9916, 0.0, sigma=3e-3, v_sigma=0.0148, direction="static")
        v = judge_frame(res(p), [TruthTarget(2.9901, 0.016), TruthTarget(10.3458, 0.0)])
        assert v.points[0].truth_index == 0 and not v.confident_wrong and v.missed == (1,)
        assert abs(v.points[0].range_z) < 1 and abs(v.points[0].speed_z) < 1.2

    def test_wrong_on_both_is_a_ghost_and_the_truth_is_missed(self):
        v = judge_frame(res(pt(1.7, 62.0)), [TruthTarget(0.81, 0.0)])
        assert v.points[0].truth_index is None and v.missed == (0,) and v.confident_false


class TestZStatistics:
    """What a cell's few z-values can say: the chance an exactly right sigma misses the z band,
    and a two-sided chi2 test of their scatter."""

    @pytest.mark.parametrize("n", [5, 16])
    def test_band_probability_against_draws(self, n):
        z = np.random.default_rng(5).standard_normal((40000, n))
        m, sd = z.mean(axis=1), z.std(axis=1, ddof=1)
        frac = np.mean((np.abs(m) < 0.3) & (sd >= 0.8) & (sd <= 1.25))
        assert z_band_probability(n) == pytest.approx(frac, abs=0.01)
        assert z_band_probability(16) < 0.8  # 16 frames: a right sigma misses the band often

    def test_scatter_test(self):
        assert not z_scatter_inconsistent(16, 0.0, 1.0)
        assert z_scatter_inconsistent(16, 0.0, 0.3)  # sigma ~3x too large
        assert z_scatter_inconsistent(16, 0.0, 2.5)  # ~2.5x too small
        assert not z_scatter_inconsistent(1, 0.0, None)
        rng = np.random.default_rng(6)
        hits = sum(z_scatter_inconsistent(16, float(z.mean()), float(z.std(ddof=1)))
                   for z in rng.standard_normal((4000, 16)))
        assert hits / 4000 == pytest.approx(0.01, abs=0.006)


@pytest.mark.parametrize("name", ["cw-bench", "moving-target", "six-tone", "quasi-cw-long-range", "two-targets"])
def test_the_bench_declares_its_tone_amplitudes_for_every_scene_of_the_map(name):
    """``declared`` measures the tone amplitudes on a reflector of the scene's bench (equal drives:
    equal amplitudes); the quasi-CW bench's record, noiseless, sat at its extremes between the
    pulses and was refused as clipped (the map lost its 930 m rows)."""
    sc = load_scene(name)
    amps = declared(sc)["tone_amplitudes"]
    assert len(amps) == len(sc.tones_hz)
    np.testing.assert_allclose(amps, 1.0, atol=1e-3)
