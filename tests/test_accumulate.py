"""Reach beyond the laser's coherence (issue 12 case 9): whole-band digital IF mixing and
accumulation over frames (``mtcw_core.ranging.accumulate``), judged against the simulator's truth
and against the closed form of the squared line.

The scene is the bundled ``low-coherence`` one (5.3 GHz linewidth, LO 9 m longer: ~500x the
coherence length), target at 0.55 m, shortened to 2^16 samples.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.special import j0, j1

from mtcw_core.chain import get_profile, process_frame
from mtcw_core.evaluate import judge_frame
from mtcw_core.phase import C
from mtcw_core.ranging.accumulate import (AccumulateSettings, Accumulator, better_point, mean_truth, same_phasors_p,
                                          square_can_range, square_lines, square_point, square_rivals,
                                          weighted_mean)
from mtcw_core.ranging.targets import Reference
from mtcw_core.results import NoTarget, TargetPoint
from mtcw_core.scene import load_scene, scene_variant
from mtcw_core.simulate import Simulator

N = 2**16
PROFILE = get_profile("balanced", laser_linewidth_hz=5.3e9, lo_path_difference_m=9.0)


def low(loss_db: float, samples: int = N, **over):
    return scene_variant(load_scene("low-coherence"), targets=[{"loss_db": loss_db}], digitizer={"samples": samples},
                         **over)


def feed(acc: Accumulator, frames):
    """Every frame through ``acc``: (result, the truth its point answers) per frame."""
    truths, out = {}, []
    for fr in frames:
        r = acc.add(fr)
        truths[fr.seq] = fr.truth
        out.append((r, mean_truth([truths[s] for s in acc.window_seqs()])))
    return out


def z_of(res, truth) -> float:
    p = res.targets[0]
    return (p.range_m - truth[0].range_m) / p.range_sigma_m


def test_squared_line_is_the_closed_form_lo_power_times_echo_intensity():
    """The tone line of the squared record is ``2*R^2*beta*(1-beta)*P0^2*a^2*G^2*J1(m_i)*prod J0(m_j)``
    (the LO x echo beat squared: LO power times the echo's intensity, the exact MZM's fundamental)
    with phase ``phi_i - 2*pi*f_i*tau`` -- within the module's own noise estimate."""
    sc = low(40.0, noise={"shot": True, "thermal": True})
    fr = Simulator(sc, 4).frame(0)
    sl = square_lines(fr.volts("pd"), fr.fs_hz, fr.tones_hz)
    rx = sc.receiver
    m = np.array([t.modulation_index for t in sc.modulator.tones])
    beta, p0, a2 = sc.lo_fraction, sc.laser.power_w, 10 ** (-40.0 / 10)
    amp = np.array([2 * (rx.responsivity_a_per_w * rx.load_ohm * rx.gain) ** 2 * beta * (1 - beta) * p0**2 * a2
                     * j1(m[i]) * np.prod(j0(np.delete(m, i))) for i in range(m.size)])
    tau = 2 * fr.truth[0].range_m / C
    expect = amp * np.exp(1j * (np.asarray(fr.tone_phases_rad) - 2 * np.pi * np.asarray(fr.tones_hz) * tau))
    dev = np.abs(sl.z_start - expect) / np.sqrt(sl.var_z)
    assert np.all(dev < 5), dev
    assert np.all(sl.snr_db > 15)  # ~22 dB at 2^16: the self-beat is below 0 dB here


def test_noise_estimate_is_the_scatter_of_the_amplitudes():
    """``var_z`` (from the local noise floor) against the scatter of the amplitude over frames."""
    frames = list(Simulator(low(70.0), 11).frames(24))
    lines = [square_lines(f.volts("pd"), f.fs_hz, f.tones_hz) for f in frames]
    z = np.stack([s.z_start for s in lines])
    scatter = np.mean(np.abs(z - z.mean(axis=0)) ** 2, axis=0) * 24 / 23
    stated = np.mean(np.stack([s.var_z for s in lines]), axis=0)
    assert np.all((scatter / stated > 0.6) & (scatter / stated < 1.6)), scatter / stated


def test_one_frame_reaches_60_db_where_the_chain_finds_nothing():
    frames = list(Simulator(low(60.0), 1).frames(3))
    own_lines = PROFILE.model_copy(update={"squared_lines": False})
    assert all(process_frame(f, own_lines).status == "no_target" for f in frames)  # the chain's own lines (case 9)
    chain = [process_frame(f, PROFILE) for f in frames]  # its square stage: the same squared lines, one frame
    for (r, truth), c in zip(feed(Accumulator(AccumulateSettings(frames=1), PROFILE), frames), chain):
        assert c.status == "ok" and c.targets[0].range_m == r.targets[0].range_m, c.reason
        # its range is given modulo c/(2 gcd) of the pairs used (500/700/950 MHz: 50 MHz, 3 m)
        assert c.unambiguous_range_m == r.unambiguous_range_m == pytest.approx(C / (2 * 50e6))
        assert r.status == "ok", r.reason
        p = r.targets[0]
        assert p.accumulated_frames == 1 and p.range_sigma_m <= 0.01 and abs(z_of(r, truth)) < 5
        # the squared lines carry no Doppler: the speed is unknown, never a claimed "static"
        assert p.direction == "unknown" and p.velocity_sigma_mps >= 0.1
        assert not judge_frame(r, truth).confident_wrong


def test_the_squared_lines_are_not_held_to_the_lo_beats_tone_amplitudes():
    """Tone amplitudes describe the LO-beat lines; the squared record's are the echo's intensity
    (``a_0*a_i`` and the tones' products on ``f_i``): amplitudes declared far from the squared
    lines' own ratios flag no squared point."""
    fr = next(iter(Simulator(low(40.0), 2).frames(1)))
    plain = process_frame(fr, PROFILE)
    odd = process_frame(fr, PROFILE.model_copy(update={"tone_amplitudes": (1.0, 3.0, 0.3)}))
    assert plain.status == odd.status == "ok" and "square" in odd.stage_seconds
    assert odd.targets[0].blended == plain.targets[0].blended is False


def test_the_square_stage_is_skipped_where_the_declared_laser_is_coherent_over_the_whole_interval():
    tones = (500e6, 700e6, 950e6)  # 3 m unambiguous
    assert not square_can_range(get_profile("balanced"), tones)  # undeclared: coherent everywhere
    assert not square_can_range(get_profile("balanced", laser_linewidth_hz=1e5), tones)  # exp(-2pi 1e5 20 ns) = 0.99
    assert square_can_range(PROFILE, tones)  # 5.3 GHz, LO 9 m longer: ~0 everywhere in 0-3 m
    # coherent at the near end, not at the far end of a long interval (1 MHz, 150 m: 1 us)
    far = get_profile("balanced", laser_linewidth_hz=1e6, range_max_m=150.0)
    assert square_can_range(far, tones) and not square_can_range(far.model_copy(update={"range_max_m": 3.0}), tones)


def test_which_point_the_squared_record_may_replace():
    """Only one point, at a range where the declared laser is incoherent (the echo's self-beat);
    it is replaced by an unflagged point against a flagged one, else by a smaller sigma."""
    pt = TargetPoint(1.234, 0.01, 0.0, 1.0, "unknown", 15.0, 0.2)
    assert square_rivals([pt], PROFILE) and not square_rivals([pt, pt], PROFILE)
    assert not square_rivals([pt], get_profile("balanced", laser_linewidth_hz=1e5))  # coherent at 1.234 m
    assert better_point(pt, replace(pt, range_sigma_m=0.004)) and not better_point(pt, replace(pt, range_sigma_m=0.02))
    flagged = replace(pt, range_sigma_m=0.004, cycle_ambiguous=True)
    assert flagged.flagged and not better_point(pt, flagged) and better_point(flagged, replace(pt, range_sigma_m=0.05))


def test_the_square_stage_refuses_a_range_where_the_declared_laser_is_coherent():
    """The squared lines sum every target's intensity: where the declared laser is coherent, one
    target would have shown in the chain's own lines, so squared lines there are a blend (the
    honesty map's two and three movers with ``fast``: 8-137 sigma off, unflagged, before this)."""
    # a mover (its carrier beat squared sits at 2 f_d, away from the tones) and a coherent laser
    sc = scene_variant(low(20.0), laser={"linewidth_hz": 1e5}, paths={"lo_path_difference_m": 0.0},
                       targets=[{"loss_db": 20.0, "velocity_mps": 0.5}])
    fr = next(Simulator(sc, 1).frames(1))
    x = fr.volts("pd")
    ref = Reference(dict(zip(fr.tones_hz, fr.tone_phases_rad)), 0.0)
    coherent = get_profile("balanced", laser_linewidth_hz=1e5)
    with pytest.raises(NoTarget, match="coherent"):
        square_point(x, fr, coherent, ref, "none")
    (p,), l_unamb, why = square_point(x, fr, PROFILE, ref, "none")  # the same lines, a laser declared incoherent
    assert abs(p.range_m - fr.truth[0].range_m) < 5 * p.range_sigma_m and why.startswith("squared record")
    # an undeclared laser (linewidth 0: coherent everywhere) never reaches the square stage
    assert "square" not in process_frame(next(Simulator(low(60.0), 1).frames(1)), "balanced").stage_seconds


def test_accumulation_reaches_where_one_frame_cannot():
    """80 dB at 2^16: one frame is below the line threshold (or cycle-ambiguous); 24 frames range it
    within its sigma, sigma <= 1 cm."""
    frames = list(Simulator(low(80.0), 2).frames(24))
    one = feed(Accumulator(AccumulateSettings(frames=1), PROFILE), frames[:4])
    assert all(r.status != "ok" or r.targets[0].range_sigma_m > 0.01 or r.targets[0].cycle_ambiguous
               for r, _ in one)
    out = feed(Accumulator(AccumulateSettings(frames=24), PROFILE), frames)
    r, truth = out[-1]
    assert r.status == "ok", r.reason
    p = r.targets[0]
    assert p.accumulated_frames == 24 and p.range_sigma_m <= 0.01 and not p.cycle_ambiguous
    assert abs(z_of(r, truth)) < 5
    assert all(not judge_frame(r, t).confident_wrong for r, t in out)


@pytest.mark.parametrize("loss_db,k", [(60.0, 8), (78.0, 16)])
def test_accumulated_sigma_covers_the_error_over_independent_runs(loss_db, k):
    """Independent runs (seeds): the last point of each window, z = error / sigma."""
    zs = []
    for seed in range(10):
        frames = list(Simulator(low(loss_db), 100 + seed).frames(k))
        r, truth = feed(Accumulator(AccumulateSettings(frames=k), PROFILE), frames)[-1]
        assert r.status == "ok", r.reason
        assert r.targets[0].accumulated_frames == k
        zs.append(z_of(r, truth))
    zs = np.asarray(zs)
    assert np.max(np.abs(zs)) < 4, zs
    assert 0.4 < np.std(zs, ddof=1) < 1.6 and abs(np.mean(zs)) < 1.0, zs


def test_a_mover_resets_and_is_never_a_confident_wrong_average():
    """A target receding at 5 cm/s (5 mm per frame at 10 frames/s), beyond coherence: the drift test
    starts new windows; every point is within 5 sigma of the truth averaged over its frames."""
    sc = scene_variant(low(60.0), targets=[{"velocity_mps": 0.05}])
    acc = Accumulator(AccumulateSettings(frames=16), PROFILE)
    out = feed(acc, Simulator(sc, 5).frames(16))
    assert acc.resets.get("moved", 0) >= 3, acc.resets
    assert max(r.targets[0].accumulated_frames for r, _ in out if r.status == "ok") < 8
    for r, truth in out:
        assert r.status == "ok" and abs(z_of(r, truth)) < 5, (r.reason, r.targets and z_of(r, truth))


def test_a_jump_in_range_resets():
    a = list(Simulator(low(60.0), 6).frames(6))
    b = [f for f in Simulator(scene_variant(low(60.0), targets=[{"range_m": 0.62}]), 7).frames(12)][6:]
    acc = Accumulator(AccumulateSettings(frames=16), PROFILE)
    out = feed(acc, a + b)
    assert acc.resets == {"moved": 1}, acc.resets
    r, truth = out[-1]
    assert r.targets[0].accumulated_frames == 6 and abs(z_of(r, truth)) < 5 and abs(truth[0].range_m - 0.62) < 1e-9


def test_a_tone_plan_change_resets():
    a = list(Simulator(low(60.0), 8).frames(4))
    sc = scene_variant(low(60.0), modulator={"tones": [{"frequency_hz": 500e6}, {"frequency_hz": 650e6},
                                                       {"frequency_hz": 950e6}]})
    b = [f for f in Simulator(sc, 9).frames(7)][4:]
    acc = Accumulator(AccumulateSettings(frames=16), PROFILE)
    out = feed(acc, a + b)
    assert acc.resets == {"changed": 1}, acc.resets
    assert [r.targets[0].accumulated_frames for r, _ in out] == [1, 2, 3, 4, 1, 2, 3]
    assert all(abs(z_of(r, t)) < 5 for r, t in out)


def test_drift_test_is_exact_under_the_null():
    """``same_phasors_p`` of two draws of one line set is uniform: ~1 % below 0.01."""
    rng = np.random.default_rng(0)
    from mtcw_core.ranging.accumulate import SquaredLines

    t = np.array([5e8, 7e8, 9.5e8])
    v = np.array([1.0, 2.0, 0.5])
    z0 = np.array([0.3 + 0.1j, -0.2j, 1.0])

    def draw():
        return SquaredLines(t, z0 + np.sqrt(v / 2) * (rng.standard_normal(3) + 1j * rng.standard_normal(3)), v, N)

    ps = np.array([same_phasors_p(draw(), draw()) for _ in range(4000)])
    assert 0.005 < np.mean(ps < 0.01) < 0.017 and 0.45 < np.mean(ps < 0.5) < 0.55
    m = weighted_mean([draw() for _ in range(4)])
    assert np.allclose(m.var_z, v / 4)


def test_settings_and_bad_frames():
    with pytest.raises(ValidationError, match="frames"):
        AccumulateSettings(frames=33)
    with pytest.raises(ValueError, match="technique"):
        Accumulator(AccumulateSettings(), get_profile("balanced", technique="pe"))
    fr = Simulator(low(60.0, samples=2**12), 1).frame(0)
    bad = type(fr)(**{**fr.__dict__, "samples": np.full_like(fr.samples, np.nan)})
    r = Accumulator(AccumulateSettings(frames=4), PROFILE).add(bad)
    assert r.status == "rejected" and "non_finite" in r.reason
    far = Accumulator(AccumulateSettings(frames=1), PROFILE).add(Simulator(low(130.0, samples=2**12), 1).frame(0))
    assert far.status == "no_target" and "squared lines" in far.reason
