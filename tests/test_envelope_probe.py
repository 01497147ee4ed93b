"""The envelope probe (``python -m mtcw_bench.envelope_probe``): its draws, and two scenes it found."""

from __future__ import annotations

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
