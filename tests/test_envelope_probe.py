"""The envelope probe (``python -m mtcw_bench.envelope_probe``): its draws, and two scenes it found."""

from __future__ import annotations

import pytest

from mtcw_bench import envelope_probe as ep
from mtcw_core.scene import load_scene, scene_variant


def test_the_draws_are_reproducible_scenes_across_the_axes():
    base = load_scene("moving-target")
    scenes = [scene_variant(base, **ep.draw(i)) for i in range(60)]
    assert ep.draw(17) == ep.draw(17)
    assert {s.receiver.kind for s in scenes} == {"single", "balanced", "iq"}
    assert {len(s.targets) for s in scenes} == {1, 2} and {s.laser.linewidth_hz for s in scenes} == {0.0, 1e5, 1e6}
    assert any(s.digitizer.adc_bits for s in scenes) and any(s.noise.rf_phase_drift_rad for s in scenes)


def test_a_target_reaching_the_sensor_is_refused_and_counted():
    """Scene 68: 3.1 m at -31 m/s, behind the sensor by its second frame (the simulator had
    crashed with numpy's broadcast error)."""
    counts, lines = ep.judge_scene(68, 2)
    assert counts["refused"] == 1 and counts["frames"] == 0 and not lines


def test_a_weak_mover_known_modulo_a_shorter_period_is_not_confident():
    """Scene 106: two movers on one photodiode, 1 MHz laser; the weak one lost its 130 MHz line
    under the strong one's phase-noise pedestal and ranged modulo 3.75 m in a 7.49 m frame
    (range z ~600, unflagged, in every profile): now flagged ``cycle_ambiguous``."""
    counts, lines = ep.judge_scene(106, 1)
    assert counts["frames"] == 3 and counts["cw"] == 0 and not lines, lines


def test_the_slips_the_chain_expects_are_its_unflagged_points_cycle_slip_probabilities(capsys):
    """The summary's expected slips are the sum of ``cycle_slip_prob`` over the unflagged points,
    each under the profile's ``cycle_slip_max``: scene 2887 (two fast movers behind a 12-bit ADC,
    one photodiode, a 100 kHz laser), 2.4e-3 over its 6 frames. (Scene 2838, whose one unflagged range in ``fast``'s
    first frame slipped a cycle at a stated 7.8e-4, has none since the seventeenth session: its
    8-bit record spans fewer than 16 codes, and every point of it is ``blended``.)"""
    from mtcw_bench.honesty import declared
    from mtcw_core.chain import process_frame
    from mtcw_core.evaluate import Z_WRONG, judge_frame
    from mtcw_core.profiles import get_profile
    from mtcw_core.simulate import Simulator

    counts, _ = ep.judge_scene(2887, 2)
    sc = scene_variant(load_scene("moving-target"), **ep.draw(2887))
    want = 0.0
    for j, fr in enumerate(Simulator(sc, 2887).frames(2)):
        for prof in ep.PROFILES:
            st = get_profile(prof, tone_phase_sigma_rad=sc.noise.rf_phase_drift_rad * (j + 1) ** 0.5, **declared(sc))
            res = process_frame(fr, st)
            v = judge_frame(res, fr.truth, Z_WRONG)
            unflagged = [t.cycle_slip_prob for t, q in zip(res.targets, v.points) if not q.flagged]
            assert all(p <= st.cycle_slip_max for p in unflagged)
            want += sum(unflagged)
    assert want > 1e-4 and counts["slips_expected"] == pytest.approx(want, rel=1e-12)
    ep.main(["--first", "2887", "--scenes", "1"])
    out = capsys.readouterr().out
    assert float(out.rsplit("(the sum of their cycle_slip_prob) ", 1)[1].split()[0]) == pytest.approx(want, rel=1e-2)
