"""The techniques probe (``python -m mtcw_bench.techniques_probe``): its draws, and scenes it found."""

from __future__ import annotations

from mtcw_bench import techniques_probe as tp
from mtcw_core.scene import load_scene, scene_variant


def test_the_draws_are_reproducible_scenes_across_their_axes():
    pe = [scene_variant(load_scene("pe-fast-target"), **tp.draw("pe", i)) for i in range(40)]
    ab = [scene_variant(load_scene("ab-bench"), **tp.draw("ab", i)) for i in range(40)]
    assert tp.draw("pe", 7) == tp.draw("pe", 7) and tp.draw("ab", 7) == tp.draw("ab", 7)
    assert {s.laser.linewidth_hz for s in pe} == {0.0, 1e5, 1e6} and {len(s.targets) for s in pe} == {1, 2}
    assert all(t.velocity_mps != 0 for s in pe for t in s.targets)
    assert {s.digitizer.samples for s in ab} == {2**16, 2**18} and {len(s.targets) for s in ab} == {1, 2}
    assert any(t.velocity_mps == 0 for s in ab for t in s.targets) and any(t.velocity_mps for s in ab for t in s.targets)


def test_a_pe_mover_far_beyond_the_folded_range_states_the_laser_in_its_speed_sigma():
    """Scene 206: 103.5 m at 39 m/s, 100 kHz laser, read 1.58 m in a 6 m period: its speed was 10
    and 17 sigmas off in both frames (the laser's phase over a delay the range cannot tell)."""
    counts, lines, z = tp.judge_scene("pe", 206, 2)
    assert counts["ok"] == 2 and counts["cw"] == 0 and not lines, lines
    assert all(abs(v) < 5 for v in z)


def test_an_ab_still_target_is_not_moved_by_the_tones_products():
    """Scene 11: a target at 8.06 m moving 5.7 cm/s read 3.85 m/s -- the 5 MHz product of the AB
    bench's tones (971 + 1657 - 2623 MHz) taken for its Doppler line, 4000 sigmas off."""
    counts, lines, z = tp.judge_scene("ab", 11, 2)
    assert counts["ok"] == 2 and counts["cw"] == 0 and not lines, lines


def test_an_ab_pedestal_bump_beside_a_product_is_no_doppler_line():
    """Scene 70: 500 kHz laser, a target at 6.87 m moving 0.28 MHz (under the search's lowest bin):
    a bump of the 32 MHz product's phase-noise pedestal stood 19x over the floor and the target read
    25 m/s, 2400 sigmas off. It is no coherent line (wider than 3.2 bins): the speed is unknown."""
    counts, lines, z = tp.judge_scene("ab", 70, 2)
    assert counts["ok"] == 2 and counts["cw"] == 0 and not lines, lines


def test_a_ptof_echo_s_own_shape_beside_it_is_no_second_echo():
    """Scene 11: one mirror at 1.72 m through a 5 GHz detector at 20 GS/s (the pulse aliased: its
    spectrum at Nyquist half its value at 0); the echo, sampled at another sub-sample phase than the
    template, left a copy ~3 samples away, reported as a second target 2.2 cm off in both frames."""
    counts, lines, _ = tp.judge_scene("ptof", 11, 2)
    assert counts["ok"] == 2 and counts["cf"] == 0 and counts["cw"] == 0 and not lines, lines


def test_a_weak_ptof_echo_is_not_pulled_by_the_reference_pulse_through_the_template_s_tails():
    """Scene 195: a mirror at 5.23 m, 27 dB under the reference mirror's pulse; the fractional shift
    of the aliased template rings across the period, and through its tails the reference pulse
    pulled the echo 6.3 mm, 7.4 of its sigmas, in both frames."""
    counts, lines, _ = tp.judge_scene("ptof", 195, 2)
    assert counts["ok"] == 2 and counts["cw"] == 0 and counts["cf"] == 0 and not lines, lines


def test_the_baseband_line_s_pedestal_beside_a_weak_pe_sideband_is_in_its_variance():
    """Scene 1348: a target at 102.6 m moving 18.4 m/s (its Doppler 36.8 MHz) under a 100 kHz laser;
    the 75 MHz tone's lower line lies 1.5 MHz from the baseband Doppler line, whose phase-noise
    pedestal turned it and put the range half a period off, 11600 sigmas, unflagged."""
    counts, lines, _ = tp.judge_scene("pe", 1348, 2)
    assert counts["frames"] == 2 and counts["cw"] == 0 and not lines, lines


def test_pe_tones_that_disagree_beyond_chance_flag_the_point():
    """Scene 1823, frame 0: a slow mover (1.06 MHz, under the search's guard) 10 dB stronger than a
    fast one leaks onto its weak 75 MHz sideband through the fit's sidelobes; the fast one's range
    came out 290 sigmas off with its tones' chi2 23 on 3 degrees of freedom (under the chi2/dof of
    10 that flagged it): at p < 1e-4 it is ``blended``, as the PB chain reads it."""
    counts, lines, _ = tp.judge_scene("pe", 1823, 1)
    assert counts["ok"] == 1 and counts["cw"] == 0 and not lines, lines


def test_a_weaker_ptof_echo_is_not_pulled_by_a_stronger_one_through_the_template_s_tails():
    """Scene 1167: two still mirrors at 2.34 and 5.05 m; the weaker one's delay, refined with the
    stronger echo still in the record, came out 9 of its sigmas off in both frames."""
    counts, lines, _ = tp.judge_scene("ptof", 1167, 2)
    assert counts["ok"] == 2 and counts["cw"] == 0 and counts["cf"] == 0 and not lines, lines


def test_an_ab_period_noise_could_swap_is_flagged_at_the_chain_s_cycle_odds():
    """Scene 1060, frame 0: a still-looking echo at 31.7 m under a 500 kHz laser; the sine fit's
    runner-up (the right period) lay 26.2 in chi2 behind, just past the old fixed 25 (0.6 % odds of a
    swap): read against ``cycle_slip_max`` (1e-3) it is ``cycle_ambiguous``, with its odds stated."""
    counts, lines, _ = tp.judge_scene("ab", 1060, 1)
    assert counts["ok"] == 1 and counts["cw"] == 0 and not lines, lines


def test_a_ptof_echo_s_copy_past_the_autocorrelation_is_not_a_second_mirror():
    """Scene 1265: one mirror at 4.85 m, its echo 7x the reference pulse; a copy 5.25 samples out,
    past the template autocorrelation's support, had stood in the correlation as a second mirror
    3.9 cm away. Refined on the record without the stronger echo it keeps nothing: dropped."""
    counts, lines, _ = tp.judge_scene("ptof", 1265, 1)
    assert counts["ok"] == 1 and counts["cf"] == 0 and not lines, lines


def test_a_pe_point_known_modulo_a_shorter_period_than_the_frame_s_is_flagged():
    """Scene 2478: two movers; the weaker one's 75 MHz lines fell under the threshold, so its three
    tones (multiples of 50 MHz) repeat every 2.998 m in a frame stating 5.996 m: it came out half a
    period off, 6000 sigmas, unflagged. Known only modulo its own period, it is ``cycle_ambiguous``."""
    counts, lines, _ = tp.judge_scene("pe", 2478, 2)
    assert counts["cw"] == 0 and not lines, lines


def test_a_pe_mover_unfound_below_the_guard_is_fitted_as_a_line_no_plan_models():
    """Scene 1426, ideal laser: movers at 0.21 m/s (0.42 MHz, under the search's guard, which PE's
    parabolic search does not look below) and 1.10 m/s. The slow one's baseband line, as strong as
    the fast one's and hundreds of times its sidebands, leaked through the rectangular fit ~290 bins
    into the 75 MHz lines: 0.41 rad, the range 1.8 m off, 800 sigmas, unflagged in frame 0. Fitted
    as a line no plan models (``pe.unmodelled_lines``), in the refinement and with the lines."""
    counts, lines, z = tp.judge_scene("pe", 1426, 2)
    assert counts["ok"] == 2 and counts["cw"] == 0 and not lines, lines
    assert z and all(abs(v) < 5 for v in z)


def test_a_pe_movers_baseband_line_beside_a_static_product_is_fitted_apart_from_it():
    """Scene 1709: a 25 m/s mover's baseband line at 50.033 MHz, 0.13 bins from the reference's
    50 MHz product, was fitted as that product alone (lines within 1.1 bins were one); its +-1-bin
    residual, 9 % of a line three times the reference lines, leaked 0.6 rad into the other mover's
    75 MHz lines 54 bins away: 0.55 m off, 411 sigmas, unflagged. Both are fitted now
    (``pe.FIT_APART_BINS``)."""
    counts, lines, z = tp.judge_scene("pe", 1709, 2)
    assert counts["cw"] == 0 and not lines, lines


def test_pe_movers_are_refined_with_each_others_refined_lines_held():
    """Scene 2631: a strong mover (13 dB of loss, 3.26 m/s) held at its search estimate while the
    other (-11.3 m/s) was refined: its baseband residual pulled the weaker one's Doppler 17.6 kHz
    (speed z 6.2, range 98 sigmas off, unflagged). Refined again with the others where their
    refinement put them. Scene 2564: a strong unfound slow mover pulled a found one's refinement
    (z 6.1) until the lines no plan models were held in it too; scene 2943's 38 m/s ghost is gone."""
    for scene in (2631, 2564, 2943):
        counts, lines, z = tp.judge_scene("pe", scene, 2)
        assert counts["cw"] == 0 and counts["cf"] == 0 and not lines, (scene, lines)


def test_a_pe_target_whose_sidebands_are_not_one_size_is_blended():
    """Scene 144: a mover at 0.27 m/s and 16 dB of loss, unfound below the guard, beside one at
    11.4 m/s: the fast one's 75 MHz sidebands stood 55 % apart (chi2 75 on 4 tones), its range 188
    sigmas off, unflagged in frame 0. A target's two sidebands of a tone are one size
    (``pe.sideband_sizes_p``); the point is ``blended``. Scene 283, one strong echo (10 dB, arm
    ratio 0.32) whose sidebands part by 1.2 %, stays unflagged and right."""
    counts, lines, z = tp.judge_scene("pe", 144, 2)
    assert counts["cw"] == 0 and not lines, lines
    counts, lines, z = tp.judge_scene("pe", 283, 2)
    assert counts["ok"] == 2 and counts["cw"] == 0 and z and all(abs(v) < 5 for v in z), (lines, z)


def test_a_pe_movers_carrier_the_search_did_not_find_has_its_lines_fitted():
    """Scene 3346: a mover 30 dB over a found one, unfound 5.5 bins below it (the parabolic search's
    guard); its sidebands lie 4 bins from the reference lines, inside their main lobe, where no peak
    is seen apart, and the found mover's point took its phases: 1359 sigmas off, unflagged. A strong
    line no plan models below the search's largest Doppler is taken as an unfound mover's carrier
    and its whole line family fitted (``pe._refine_movers``)."""
    counts, lines, z = tp.judge_scene("pe", 3346, 2)
    assert counts["cw"] == 0 and counts["cf"] == 0 and not lines, lines


def test_a_strong_line_beside_a_modelled_one_is_fitted_too():
    """Scene 4010: a mover's baseband line, 30 times the other mover's lower 75 MHz sideband and 4.7
    bins from it, stood inside the 5 bins about modelled lines where no unmodelled line was looked
    for; it turned that tone by pi, and the range came out half the 6 m period off (4743 sigmas),
    unflagged. A local maximum 1.5 bins out is no longer the modelled line's own peak."""
    counts, lines, z = tp.judge_scene("pe", 4010, 2)
    assert counts["cw"] == 0 and counts["cf"] == 0 and not lines, lines
