"""mtcw_core.ranging.targets: velocity, one candidate's solution, and the selection policy."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from mtcw_core.dsp.doppler import DopplerEstimate
from mtcw_core.dsp.extract import LineFamily
from mtcw_core.frame import Frame
from mtcw_core.phase import C
from mtcw_core.profiles import ChainSettings, get_profile
from mtcw_core.ranging import targets
from mtcw_core.ranging.mixing import mix
from mtcw_core.chain import process_frame
from mtcw_core.ranging.targets import (SPEED_FLOOR_BINS, Reference, median_snr, resolve_targets, select_targets,
                                       phase_psd, shared_phase_psd, solve_target, velocity, wings_level_db)
from mtcw_core.ranging.triangulation import fisher_sigma, unambiguous_range
from mtcw_core.results import TargetPoint
from mtcw_core.simulate import Simulator

from .conftest import make_scene

LAM = 1.064e-6
FS = 1e9
N = 2**14
TONES = np.array([100e6, 170e6, 260e6])
PHI = {100e6: 0.3, 170e6: -1.2, 260e6: 2.5}


def frame(receiver="single"):
    if receiver == "iq":
        return Frame(np.zeros((2, N)), FS, tuple(TONES), LAM, receiver="iq", channels=("i", "q"))
    return Frame(np.zeros((1, N)), FS, tuple(TONES), LAM)


def dop(fd, detected=True, refine=0.0, wander=0.0, method="", gain=0.0):
    return DopplerEstimate(fd, detected, 100.0 if detected else 0.0, 50.0, 4 * FS / N, refine, wander, method, gain)


def fam(name="S", target=0, var=(1e-4, 2e-4, 4e-4), range_m=3.7, fd=0.0, extra=(0.0, 0.0, 0.0), tau0=0.0):
    tau = tau0 + 2 * range_m / C
    centre = np.array([(N - 1) / (2 * FS)])
    line = TONES + fd
    ph = np.array([PHI[f] for f in TONES]) - 2 * np.pi * np.mod(TONES * tau, 1.0) + np.asarray(extra)
    z = np.exp(1j * (ph + 0.77 + 2 * np.pi * np.mod(line * centre[0], 1.0)))[None, :]
    return LineFamily(name, TONES.copy(), line, z, centre, np.asarray(var, float), target)


def point(range_m, snrs, sigma=1e-4, residual=0.01, snr_db=None):
    tone = {f"{f:.0f}": s for f, s in zip(TONES, snrs)}
    return TargetPoint(range_m=range_m, range_sigma_m=sigma, velocity_mps=0.0, velocity_sigma_mps=1e-3,
                       direction="static", snr_db=max(snrs) if snr_db is None else snr_db, margin=0.5,
                       residual_rms_rad=residual, tone_snr_db=tone)


class TestVelocity:
    def test_static_is_zero_with_min_detectable_speed(self):
        d = dop(0.0, detected=False)
        v, s, direction, _ = velocity(d, frame(), [fam()], False)
        assert v == 0.0 and direction == "static"
        assert s == pytest.approx(d.min_detectable_hz * LAM / 2)

    def test_real_doppler_is_2v_over_lambda(self):
        fd = 7.5e6
        v, s, direction, _ = velocity(dop(fd), frame(), [fam("U", 1, fd=fd), fam("L", 1, fd=-fd)], False)
        assert v == pytest.approx(fd * LAM / 2, rel=1e-15)  # f_d = 2v/lambda
        assert direction == "unknown" and s > 0

    @pytest.mark.parametrize("fd,direction", [(7.5e6, "approaching"), (-7.5e6, "receding")])
    def test_iq_sign_gives_direction(self, fd, direction):
        """f_d = -2v/lambda: a positive Doppler is an approaching target (v < 0)."""
        v, _, d, _ = velocity(dop(fd), frame("iq"), [fam("U", 1, fd=fd)], True)
        assert d == direction
        assert v == pytest.approx(-fd * LAM / 2)

    def test_sigma_from_the_frequency_crb(self):
        """Real lines: var_f = 3*s2*fs^2/(pi^2*A^2*N^3) = 1.5*var_phase*fs^2/(pi^2*N^2) per line,
        combined by inverse variance over the Doppler-shifted lines (S lines do not count)."""
        var = np.array([1e-4, 2e-4, 4e-4])
        fams = [fam("S", 1, var=(1e-9,) * 3), fam("U", 1, var=var), fam("L", 1, var=var)]
        _, s, _, _ = velocity(dop(7.5e6), frame(), fams, False)
        var_f = 1.5 * var * FS**2 / (np.pi**2 * N**2)
        sig_f = 1 / math.sqrt(2 * np.sum(1 / var_f))
        assert s == pytest.approx(sig_f * LAM / 2, rel=1e-12)

    def test_sigma_includes_refinement_and_wander(self):
        var = np.full(3, 1e-8)
        sig_f = 1 / math.sqrt(np.sum(1 / (1.5 * var * FS**2 / (np.pi**2 * N**2))))
        d = dop(7.5e6, refine=3e3, wander=4e3)
        s = velocity(d, frame(), [fam("U", 1, var=var)], False)[1]
        assert s == pytest.approx(math.hypot(sig_f, 3e3, 4e3) * LAM / 2, rel=1e-12)

    def test_a_refined_doppler_carries_its_own_error(self):
        """The refinement's stated error covers every line it used (the carrier's baseband line
        among them) and the shared phase's wander: neither the sidebands' bound nor the width's
        wander guess is added."""
        var = np.full(3, 1e-4)
        d = dop(7.5e6, refine=30.0, wander=4e3, method="phase")
        s = velocity(d, frame(), [fam("U", 1, var=var), fam("L", 1, var=var)], False)[1]
        assert s == pytest.approx(30.0 * LAM / 2, rel=1e-12)

    def test_a_phase_refinement_states_at_least_the_declared_lasers_shared_phase(self):
        """A refinement by phase advance measures the shared phase on a few parts; a low draw of
        that scatter must not state less than the declared laser makes of it through the
        refinement's own gain (the envelope probe's scene 2816: 2.3 kHz off at a stated 0.34 kHz,
        0.67 kHz expected); a larger measured error stands."""
        from mtcw_core.dsp.doppler import part_phase_gain
        gain = part_phase_gain(4, N // 4, FS)
        psd = shared_phase_psd(ChainSettings(laser_linewidth_hz=1e5), 7.5)
        floor = math.sqrt(gain * psd)
        fams = [fam("U", 1, var=np.full(3, 1e-4))]
        d = replace(dop(7.5e6, refine=0.3 * floor, method="phase"), measured_phase_gain=gain)
        assert velocity(d, frame(), fams, False, phase_psd=psd)[1] == pytest.approx(floor * LAM / 2, rel=1e-12)
        d = replace(d, refine_error_hz=3 * floor)
        assert velocity(d, frame(), fams, False, phase_psd=psd)[1] == pytest.approx(3 * floor * LAM / 2, rel=1e-12)
        assert velocity(replace(d, refine_error_hz=0.3 * floor), frame(), fams, False)[1] == pytest.approx(
            0.3 * floor * LAM / 2, rel=1e-12)  # a laser declared coherent: no floor

    def test_a_reassigned_error_holding_the_pedestal_meets_the_lasers_term_once(self):
        """A reassigned line's local floors held the declared laser's pedestal
        (``shared_overlap_var_hz2``, the error less its white-floor twin): the sigma is the white
        error with the laser's term, never less than the local floors' error; with no overlap stated
        (or the laser declared coherent) the two add as before."""
        fams = [fam("U", 1, var=np.full(3, 1e-4))]
        gain, psd = 2e13, 1e-9  # the laser's term: sqrt(2e4) = 141 Hz
        d = replace(dop(7.5e6, refine=100.0, method="reassigned"), shared_phase_gain=gain)
        assert velocity(d, frame(), fams, False, phase_psd=psd)[1] == pytest.approx(
            math.sqrt(100.0**2 + gain * psd) * LAM / 2, rel=1e-12)
        d = replace(d, shared_overlap_var_hz2=100.0**2 - 10.0**2)  # a 10 Hz white error
        assert velocity(d, frame(), fams, False, phase_psd=psd)[1] == pytest.approx(
            math.sqrt(10.0**2 + gain * psd) * LAM / 2, rel=1e-12)
        assert velocity(d, frame(), fams, False, phase_psd=0.1 * psd)[1] == pytest.approx(
            100.0 * LAM / 2, rel=1e-12)  # the local floors' error stands where it is the larger
        assert velocity(d, frame(), fams, False)[1] == pytest.approx(100.0 * LAM / 2, rel=1e-12)

    def test_a_phase_refinements_margin_is_left_to_a_floor_that_explains_the_measured_phase(self):
        """The common-mode margin's excess (``shared_overlap_var_hz2``) comes off where the floor (the
        laser's, or the pedestal's, through the refinement's gain) is at least half the error
        without it; a measured phase far above the floor keeps its margin, and no floor keeps it."""
        from mtcw_core.ranging.targets import SHARED_FLOOR_AGREES
        gain, psd = 1e12, 1e-9  # floor sqrt(1e3) = 31.6 Hz
        floor = math.sqrt(gain * psd)
        fams = [fam("U", 1, var=np.full(3, 1e-4))]
        d = replace(dop(7.5e6, refine=50.0, method="phase"), measured_phase_gain=gain,
                    shared_overlap_var_hz2=50.0**2 - 40.0**2)  # 40 Hz without the margin
        assert velocity(d, frame(), fams, False, phase_psd=psd)[1] == pytest.approx(40.0 * LAM / 2, rel=1e-12)
        low = 30.0 / SHARED_FLOOR_AGREES / floor  # a floor under half the 40 Hz: the margin stays
        assert velocity(d, frame(), fams, False, phase_psd=psd * low**2)[1] == pytest.approx(50.0 * LAM / 2, rel=1e-12)
        assert velocity(d, frame(), fams, False)[1] == pytest.approx(50.0 * LAM / 2, rel=1e-12)
        d = replace(d, shared_overlap_var_hz2=50.0**2 - 20.0**2)  # 20 Hz without it: the floor stands
        assert velocity(d, frame(), fams, False, phase_psd=psd)[1] == pytest.approx(floor * LAM / 2, rel=1e-12)

    def test_the_phase_gain_is_the_end_parts_windowed_mean_phase(self):
        """``part_phase_gain`` against a simulation: a white phase of two-sided PSD ``p`` on the lines
        moves the quarters' phase advance by ``sqrt(gain*p)`` Hz rms."""
        from mtcw_core.dsp.doppler import PHASE_WINDOW_BETA, part_phase_gain
        n, seg, fs, p = 2**14, 4, 1e9, 1e-11  # 0.01 rad^2 a sample: the linear regime
        length = n // seg
        w = np.kaiser(length, PHASE_WINDOW_BETA)
        rng = np.random.default_rng(3)
        est = []
        for _ in range(400):
            phi = rng.standard_normal(n) * math.sqrt(p * fs)  # white: variance PSD*fs per sample
            z = np.exp(1j * phi).reshape(seg, length) @ w  # each part's windowed mean phasor
            est.append(np.angle(np.sum(z[1:] * np.conj(z[:-1]))) / (2 * np.pi * length / fs))
        assert np.std(est) == pytest.approx(math.sqrt(part_phase_gain(seg, length, fs) * p), rel=0.1)

    def test_a_reassigned_doppler_adds_the_shared_phase_and_the_wander(self):
        """Reassigned over one window: its white-noise error, the declared laser's phase noise over
        the echo delay (which it cannot see) through its gain, and the width's wander."""
        var = np.full(3, 1e-4)
        d = dop(7.5e6, refine=30.0, wander=40.0, method="reassigned", gain=2e10)
        st = ChainSettings(laser_linewidth_hz=1e5, lo_path_difference_m=0.5)
        psd = shared_phase_psd(st, 3.0)
        assert psd == pytest.approx(2 * math.pi * 1e5 * ((6.0 - 0.5) / C) ** 2, rel=1e-12)
        s = velocity(d, frame(), [fam("U", 1, var=var)], False, phase_psd=psd)[1]
        assert s == pytest.approx(math.sqrt(30.0**2 + 2e10 * psd + 40.0**2) * LAM / 2, rel=1e-12)
        assert shared_phase_psd(ChainSettings(), 3.0) == 0.0  # a laser declared coherent

    def test_the_pedestal_stands_for_a_delay_the_range_cannot_tell(self):
        """A range known modulo the unambiguous range gives the declared laser's phase noise at the
        folded range only; the pedestal the lines show (``pedestal_psd``, a real record's low line
        counting its image's too: over the gain's 1.5) stands for it where it is more. A laser
        declared coherent has no pedestal to show: none is taken."""
        st = ChainSettings(laser_linewidth_hz=1e5)
        folded = shared_phase_psd(st, 1.855)
        d = replace(dop(7.5e6, method="reassigned", gain=2e10), pedestal_psd=60 * folded)
        assert phase_psd(st, 1.855, d, iq=False) == pytest.approx(40 * folded, rel=1e-12)
        assert phase_psd(st, 1.855, d, iq=True) == pytest.approx(60 * folded, rel=1e-12)
        assert phase_psd(st, 1.855, replace(d, pedestal_psd=0.5 * folded), iq=True) == folded
        assert phase_psd(ChainSettings(), 1.855, d, iq=True) == 0.0

    def test_a_sub_guard_fit_adds_the_shared_phase_like_a_reassigned_one(self):
        """The sub-guard fit (method ``fit``) is one record-long window too: the declared laser's
        phase noise over the echo delay enters through its gain."""
        d = dop(2.5 * FS / N, refine=3.0, method="fit", gain=4e11)
        psd = shared_phase_psd(ChainSettings(laser_linewidth_hz=1e5), 1.5)
        s = velocity(d, frame(), [fam("U", 1, var=np.full(3, 1e-4))], False, phase_psd=psd)[1]
        assert s == pytest.approx(math.sqrt(3.0**2 + 4e11 * psd) * LAM / 2, rel=1e-12)

    def test_sigma_floor(self):
        _, s, _, _ = velocity(dop(7.5e6), frame(), [fam("U", 1, var=(1e-30,) * 3)], False)
        assert s == pytest.approx(SPEED_FLOOR_BINS * FS / N * LAM / 2)
        assert SPEED_FLOOR_BINS <= 1e-4  # far below the phase refinement's errors (4e-5 bin at 40 dB)

    def test_speed_sigma_covers_the_error_and_no_more(self):
        """Against truth: a coherent mover's speed over 8 frames (2^15 samples, balanced). Each
        error within 5 of its sigma, and the z-scores' rms not far below 1 -- a sigma 10x too
        large (the sidebands' bound on a refined Doppler) gives an rms of ~0.1."""
        sc = make_scene(targets=[{"range_m": 1.7, "velocity_mps": 1.62, "loss_db": 55.0}],
                        digitizer={"samples": 2**15}, noise={"shot": True, "thermal": True})
        z = []
        for fr in Simulator(sc, seed=11).frames(8):
            res = process_frame(fr, get_profile("balanced"))
            movers = [t for t in res.targets if t.direction != "static"]
            assert res.status == "ok" and len(movers) == 1
            z.append((movers[0].velocity_mps - abs(fr.truth[0].velocity_mps)) / movers[0].velocity_sigma_mps)
        z = np.array(z)
        assert np.max(np.abs(z)) < 5
        assert 0.35 < np.sqrt(np.mean(z**2)) < 2.5


class TestMedianSnr:
    def test_median_of_tone_snrs(self):
        assert median_snr(point(1.0, [10.0, 50.0, 20.0], snr_db=50.0)) == 20.0


class TestSolveTarget:
    def test_static_family_range_and_fisher_sigma(self):
        f = fam(range_m=3.7)
        obs = mix([f], PHI, 10.0)[0]
        p = solve_target([f], obs, dop(0.0, False), frame(), ChainSettings(), Reference(PHI, 0.0), None)
        assert p.range_m == pytest.approx(3.7, abs=1e-9)
        assert p.range_sigma_m == pytest.approx(fisher_sigma([TONES], [f.phase_var]), rel=1e-12)
        assert p.direction == "static" and p.velocity_mps == 0.0
        assert not p.blended and not p.cycle_ambiguous
        assert p.tone_snr_db == {"100000000": pytest.approx(40.0), "170000000": pytest.approx(-10 * np.log10(2e-4)),
                                 "260000000": pytest.approx(-10 * np.log10(4e-4))}

    def test_the_static_lines_ring_widens_their_sigma_never_narrows_it(self):
        """Beside a mover the static candidate's lines carry their noise ring (its pedestal moves
        them together, tone by tone as it moves its own: the envelope probe's scene 9322); the
        sigma is the ring's where that is wider than independent lines', else the independent one
        (one common draw at every line, the carrier's own noise, would cancel to nothing)."""
        from dataclasses import replace

        from mtcw_core.dsp.extract import NoiseRing

        f = fam(range_m=3.7)
        obs = mix([f], PHI, 10.0)[0]
        alone = fisher_sigma([TONES], [f.phase_var])
        rng = np.random.default_rng(5)
        draw = (rng.standard_normal((400, 1)) + 1j * rng.standard_normal((400, 1))) * np.sqrt(2e-4)
        common = replace(f, ring=NoiseRing(np.repeat(draw, 3, axis=1), np.zeros(3), np.ones(400, bool)))
        p = solve_target([common], obs, dop(0.0, False), frame(), ChainSettings(), Reference(PHI, 0.0), None)
        assert p.range_sigma_m == pytest.approx(alone, rel=1e-12)
        # a pedestal a range shift's pattern moves: each line by its tone's share of one draw
        k = TONES / TONES.mean()
        shift = replace(f, ring=NoiseRing(np.imag(draw) * k * 1j * 3, np.zeros(3), np.ones(400, bool)))
        p = solve_target([shift], obs, dop(0.0, False), frame(), ChainSettings(), Reference(PHI, 0.0), None)
        assert p.range_sigma_m > 1.5 * alone

    def test_internal_delay(self):
        tau0 = 7e-9
        f = fam(range_m=2.2, tau0=tau0)
        obs = mix([f], PHI, 10.0)[0]
        p = solve_target([f], obs, dop(0.0, False), frame(), ChainSettings(), Reference(PHI, tau0), None)
        assert p.range_m == pytest.approx(2.2, abs=1e-9)

    def test_inconsistent_phases_flag_blended_and_widen_sigma(self):
        f = fam(range_m=3.7, var=(1e-4,) * 3, extra=(0.0, 0.0, 0.5))
        obs = mix([f], PHI, 10.0)[0]
        p = solve_target([f], obs, dop(0.0, False), frame(), ChainSettings(), Reference(PHI, 0.0), None)
        assert p.blended and p.chi2_per_dof > 10
        assert p.range_sigma_m == pytest.approx(fisher_sigma([TONES], [f.phase_var]) * math.sqrt(p.chi2_per_dof),
                                                rel=1e-9)

    def test_phases_that_fit_one_range_improbably_widen_the_sigma(self):
        """Three tones: a phase 0.06 rad off on one (6 of its sigmas) gives a chi2 of p ~0.03 --
        improbable for one target, too little to flag a blend. The sigma is scaled by the Birge
        ratio from p < 0.05 on (it was 1e-3: the envelope probe's scene 2706, two static targets on
        three tones, p 1e-3 to 0.014, ranged 6 mm off at 0.8-1.1 mm). With a declared drift of the
        tone phases the chi2 counts it, and the ratio scales it with the white noise's part."""
        from dataclasses import replace as rep

        from scipy.special import chdtrc

        from mtcw_core.ranging.mixing import consistency
        from mtcw_core.ranging.triangulation import tone_phase_sigma

        def p_value(f, settings, p):
            var = f.phase_var + settings.tone_phase_sigma_rad**2
            chi2, dof = consistency([rep(f, phase_var=var)], PHI, 2 * p.range_m / C, settings.min_line_snr_db)
            return chdtrc(dof, chi2)

        for extra, st in ((0.06, ChainSettings()), (0.08, ChainSettings(tone_phase_sigma_rad=0.005))):
            f = fam(range_m=3.7, var=(1e-4,) * 3, extra=(0.0, 0.0, extra))
            p = solve_target([f], mix([f], PHI, 10.0)[0], dop(0.0, False), frame(), st, Reference(PHI, 0.0), None)
            assert 1e-3 < p_value(f, st, p) < 0.05 and not p.blended
            unscaled = math.hypot(fisher_sigma([TONES], [f.phase_var]),
                                  tone_phase_sigma([TONES], [f.phase_var], st.tone_phase_sigma_rad))
            assert p.range_sigma_m == pytest.approx(unscaled * math.sqrt(p.chi2_per_dof), rel=1e-9)
        # consistent phases: nothing scaled
        f0 = fam(range_m=3.7, var=(1e-4,) * 3, extra=(0.0, 0.0, 0.01))
        p0 = solve_target([f0], mix([f0], PHI, 10.0)[0], dop(0.0, False), frame(), ChainSettings(), Reference(PHI, 0.0),
                          None)
        assert p_value(f0, ChainSettings(), p0) > 0.05
        assert p0.range_sigma_m == pytest.approx(fisher_sigma([TONES], [f0.phase_var]), rel=1e-9)

    def test_seed_method(self):
        f = fam(range_m=5.5)
        obs = mix([f], PHI, 10.0)[0]
        p = solve_target([f], obs, dop(0.0, False), frame(), ChainSettings(method="seed"), Reference(PHI, 0.0), None)
        assert p.range_m == pytest.approx(5.5, abs=1e-9)
        assert p.seed_sigma_k_m == pytest.approx(0.0, abs=1e-9)

    def test_coarse_interval_picks_the_period(self):
        lu = unambiguous_range([70e6, 90e6])
        truth = 3.7 + 40 * lu
        f = fam(range_m=truth)
        obs = mix([f], PHI, 10.0)[0]
        coarse = (truth - 1.0, truth + 1.5)
        p = solve_target([f], obs, dop(0.0, False), frame(), ChainSettings(), Reference(PHI, 0.0), coarse)
        assert p.range_m == pytest.approx(truth, abs=1e-7)
        assert not p.cycle_ambiguous
        wide = (truth - lu, truth + lu)
        assert solve_target([f], obs, dop(0.0, False), frame(), ChainSettings(), Reference(PHI, 0.0),
                            wide).cycle_ambiguous


class TestResolveTargets:
    def test_static_and_mover(self):
        fd = 7.5e6
        fams = [fam(range_m=3.7), fam("U", 1, range_m=9.1, fd=fd), fam("L", 1, range_m=9.1, fd=-fd)]
        obs = mix(fams, PHI, 10.0)
        pts, lu = resolve_targets(fams, obs, [dop(fd)], frame(), ChainSettings(), Reference(PHI, 0.0), None)
        assert [k for k, _ in pts] == [0, 1]
        assert pts[0][1].range_m == pytest.approx(3.7, abs=1e-9)
        assert pts[1][1].range_m == pytest.approx(9.1, abs=1e-9)
        assert pts[1][1].velocity_mps == pytest.approx(fd * LAM / 2)
        assert pts[1][1].doppler_hz == fd
        assert lu == pytest.approx(C / (2 * 10e6))

    def test_a_point_whose_lines_repeat_sooner_than_the_frames_is_cycle_ambiguous(self):
        """A weak mover whose 100 MHz line fell under the threshold (a random probe of the
        envelope: a stronger mover's phase-noise pedestal over it) ranges from 170/260 MHz alone,
        which repeat every c/(2*90 MHz) = 1.67 m; the frame's unambiguous range, from the static
        target's three lines, is 15 m. Its range is right modulo 1.67 m only: which of the frame's
        nine cycles holds it, it cannot say."""
        fd = 7.5e6
        fams = [fam(range_m=3.7), fam("U", 1, range_m=9.1, fd=fd, var=(1.0, 2e-4, 4e-4)),
                fam("L", 1, range_m=9.1, fd=-fd, var=(1.0, 2e-4, 4e-4))]
        pts, lu = resolve_targets(fams, mix(fams, PHI, 10.0), [dop(fd)], frame(), ChainSettings(),
                                  Reference(PHI, 0.0), None)
        (_, static), (_, mover) = pts
        assert lu == pytest.approx(C / (2 * 10e6)) and not static.cycle_ambiguous
        assert mover.cycle_ambiguous
        assert mover.range_m == pytest.approx((9.1 + 0.05) % (C / (2 * 90e6)) - 0.05, abs=1e-6)
        # a declared range interval shorter than the point's own period: one cycle, no doubt
        pts, _ = resolve_targets(fams, mix(fams, PHI, 10.0), [dop(fd)], frame(), ChainSettings(range_max_m=1.5),
                                 Reference(PHI, 0.0), None)
        assert not pts[1][1].cycle_ambiguous


    def test_static_beside_a_sub_guard_mover_claims_no_less_than_its_doppler(self):
        """A mover found below the guard (``fit``, 2.5 bins; the search's floor 4 bins stated as 1):
        the static candidate -- which may be that mover's own self-beat, kept in its place by
        select -- states no smaller speed than the mover's."""
        fd = 2.5 * FS / N
        fams = [fam(range_m=3.7), fam("U", 1, range_m=9.1, fd=fd), fam("L", 1, range_m=9.1, fd=-fd)]
        sub = DopplerEstimate(fd, True, 1e4, 100.0, FS / N, 3.0, 0.0, "fit", 0.0)
        pts, _ = resolve_targets(fams, mix(fams, PHI, 10.0), [sub], frame(), ChainSettings(), Reference(PHI, 0.0),
                                 None)
        static = dict(pts)[0]
        assert static.direction == "static" and static.speed_min_mps == pytest.approx(fd * LAM / 2)
        assert static.velocity_sigma_mps == static.speed_min_mps

    def test_single_receiver_self_beat_kept_for_a_sub_guard_mover_answers_it(self):
        """Against truth: a single photodiode at 0 dB loss (the echo's self-beat as strong as its LO
        beats, and select keeps it in the mover's place), the mover 4.5 bins out: the point's speed
        error within 1.5 of its sigma (1 bin stated there would put the truth at 4.5 sigma)."""
        from mtcw_bench.honesty import issue_scene
        from mtcw_core.evaluate import judge_frame
        bin_mps = 0.65536e9 / 2**16 * 1.55e-6 / 2
        sc = issue_scene([{"range_m": 1.5, "velocity_mps": 4.5 * bin_mps, "loss_db": 0.0}], 2**16,
                         (150e6, 200e6, 270e6), laser={"wavelength_m": 1.55e-6},
                         digitizer={"sample_rate_hz": 0.65536e9})
        for fr in Simulator(sc, seed=7).frames(2):
            res = process_frame(fr, "balanced")
            v = judge_frame(res, fr.truth)
            assert res.status == "ok" and v.points[0].truth_index == 0
            assert abs(v.points[0].speed_z) <= 1.5, (res.targets[0], v.points[0])


class TestSelectTargets:
    ST = ChainSettings()  # self_beat_margin_db 15, incoherent_residual_rad 0.25

    def test_self_beat_static_dropped_beside_a_loud_mover(self):
        static = point(4.0, [20.0, 21.0, 19.0])
        mover = point(9.0, [50.0, 52.0, 48.0])
        assert select_targets([(0, static), (1, mover)], self.ST) == [mover]

    def test_static_at_a_stronger_movers_range_dropped(self):
        static = point(9.0, [40.0, 40.0, 40.0])
        mover = point(9.0, [45.0, 45.0, 45.0])
        assert select_targets([(0, static), (1, mover)], self.ST) == [mover]

    def test_a_copy_of_a_mover_is_flagged(self):
        """A mover at a stronger mover's range, its lines >= 6 dB weaker, may be a copy of that
        mover's lines (the quantizer's products with its carrier's harmonics: the envelope probe's
        8/12-bit ghosts at 2x and 41x a mover's Doppler, 8-31 dB under it; on float volts too, scene
        3275's 19 dB under a mover): flagged ``blended``, not dropped. A weaker mover elsewhere, or
        one under 6 dB weaker: left as they are."""
        strong = replace(point(3.58, [46.0, 47.0, 46.0]), velocity_mps=0.15, direction="unknown")
        copy = replace(point(3.58 + 1e-4, [28.0, 30.0, 27.0]), velocity_mps=6.2, direction="unknown")
        apart = replace(point(7.0, [28.0, 30.0, 27.0]), velocity_mps=1.0, direction="unknown")
        close = replace(point(3.58 - 1e-4, [43.0, 44.0, 42.0]), velocity_mps=3.0, direction="unknown")
        cands = [(1, strong), (2, copy), (3, apart), (4, close)]
        assert select_targets(cands, self.ST) == [strong, close, replace(copy, blended=True), apart]
        # at twice the mover's speed (within 5 sigmas) a copy only 2 dB weaker is one too (scene
        # 2267: 8-bit codes, 15 m/s, its copy at 29.99 m/s 5 dB under it), and one up to 3 dB stronger
        # (scene 7816: 8-bit codes, a 3.72 m/s mover's copy at 11.17 m/s 1.2 dB above it: a
        # quantizer's products lie at multiples of a line, never at a fraction), not one 4 dB
        # stronger; 2.3x is not, nor is 3.0 m/s above (20x, but 5 sigmas of 20x reach 0.1 m/s: any
        # speed would be a multiple)
        double = replace(close, velocity_mps=0.3 + 4e-3)
        off = replace(close, velocity_mps=0.345)
        assert select_targets([(1, strong), (2, double)], self.ST) == [
            strong, replace(double, blended=True)]
        assert select_targets([(1, strong), (2, off)], self.ST) == [strong, off]
        louder = replace(strong, velocity_mps=0.3, tone_snr_db={k: 48.0 for k in strong.tone_snr_db})
        assert select_targets([(1, strong), (2, louder)], self.ST) == [replace(louder, blended=True), strong]
        loudest = replace(louder, tone_snr_db={k: 50.0 for k in strong.tone_snr_db})
        assert select_targets([(1, strong), (2, loudest)], self.ST) == [loudest, strong]
        # a strong mover is no copy of a faint point at a third of its speed (its range sigma wide)
        faint = replace(point(3.58, [14.0, 14.0, 14.0]), velocity_mps=0.31, velocity_sigma_mps=4e-3,
                        range_sigma_m=0.05, direction="unknown")
        fast = replace(strong, velocity_mps=0.9)
        assert select_targets([(1, fast), (2, faint)], self.ST)[0] == fast

    def test_a_weak_twin_at_the_static_range_leaves_its_speed_unmeasured(self):
        """No laser declared: the weak twin may be the static target's wings or a mover whose
        self-beat the static lines are; the static point stays, its speed not measured (0,
        ``unknown``, a sigma covering the twin's 0.25 m/s by 5 of its sigmas)."""
        static = point(5.0, [40.0, 42.0, 38.0])
        ghost = replace(point(5.0 + 1e-4, [30.0, 31.0, 29.0]), velocity_mps=0.25, direction="unknown")
        other = point(12.0, [35.0, 36.0, 34.0])
        got = select_targets([(0, static), (1, ghost), (2, other)], self.ST)
        assert got == [replace(static, direction="unknown", velocity_sigma_mps=0.255, speed_min_mps=0.255), other]
        assert not got[0].speed_measured and static.velocity_mps == got[0].velocity_mps == 0.0

    def test_a_twin_above_the_declared_lasers_wings_is_the_target(self):
        """An echo stronger than the LO (one photodiode): its self-beat at the tones stands 10 dB
        above its own Doppler lines, at one range. A 100 kHz laser's wings at 5 m in a 5 kHz bin lie
        55 dB below the static lines, so a twin 10 dB below them is a Doppler line and the static
        lines its self-beat: the mover is the target. Within 20 dB of the wings it may be them: the
        static target stays, ``static``, as before the rule."""
        static = point(5.0, [50.0] * 3)
        mover = replace(point(5.0 + 1e-4, [40.0] * 3), velocity_mps=0.1, direction="unknown")
        dfb = get_profile("balanced", laser_linewidth_hz=100e3)
        assert select_targets([(0, static), (1, mover)], dfb, 5e3) == [mover]
        # a flagged twin (a wrong cycle's wide sigma can put it at any range: the honesty map's
        # static + mover at 2^16, 20 dB) claims nothing: the static target stays
        # but may have put its self-beat there: the static point's speed is not measured
        lost = replace(mover, cycle_ambiguous=True)
        (kept,) = select_targets([(0, static), (1, lost)], dfb, 5e3)
        assert kept.range_m == static.range_m and not kept.speed_measured and kept.velocity_sigma_mps > 0.1
        # 3 MHz (the carrier beat still 53 % a line): the wings -39 dB beside the line (the test's
        # points have no Doppler: the wings' peak), within 20 dB of a twin 25 dB down but 14 dB
        # above them: perhaps a Doppler line, perhaps their bump -- the static point keeps its range,
        # not its speed; 30 dB down (9 dB above the wings: a bump of them) it stays ``static``
        wide = get_profile("balanced", laser_linewidth_hz=3e6)
        assert wings_level_db(wide, static, 5e3) == pytest.approx(-38.8, abs=0.1)
        faint = replace(mover, tone_snr_db={k: 25.0 for k in mover.tone_snr_db})
        (kept,) = select_targets([(0, static), (1, faint)], wide, 5e3)
        assert kept.range_m == static.range_m and not kept.speed_measured and kept.velocity_sigma_mps > 0.1
        fainter = replace(mover, tone_snr_db={k: 20.0 for k in mover.tone_snr_db})
        assert select_targets([(0, static), (1, fainter)], wide, 5e3) == [static]
        # balanced and IQ receivers cancel the self-beat: the static lines are a static target's
        for rx in ("balanced", "iq"):
            assert select_targets([(0, static), (1, mover)], dfb, 5e3, rx) == [static]
            assert select_targets([(0, static), (1, mover)], self.ST, None, rx) == [static]
        assert select_targets([(0, static), (1, mover)], wide, 5e3) == [mover]

    def test_the_wings_fall_off_with_the_doppler_offset(self):
        """The static lines' wings at a twin's Doppler, not beside the line: the envelope probe's
        scene 3338 (one photodiode, the LO 1 % of the power, an echo at 8 dB loss: its self-beat
        18.5 dB above its own Doppler lines at 30.8 MHz, a 1 MHz laser at 7.92 m, 76.3 kHz bins).
        Beside the line the wings lie 28 dB under it -- within 20 dB of the twin, which was dropped
        and the echo reported ``static``, 81 sigmas off; at 30.8 MHz they lie 42 dB under it, and
        the twin is the Doppler line (the static lines its self-beat)."""
        dfb = get_profile("balanced", laser_linewidth_hz=1e6)
        static = point(7.924, [51.9] * 3)
        mover = replace(point(7.924 + 1e-4, [33.4] * 3), velocity_mps=16.374, direction="unknown", doppler_hz=30.78e6)
        bin_hz = 5e9 / 65536
        assert wings_level_db(dfb, static, bin_hz) == pytest.approx(-28.2, abs=0.1)
        assert wings_level_db(dfb, static, bin_hz, 30.78e6) == pytest.approx(-42.1, abs=0.2)
        assert select_targets([(0, static), (1, mover)], dfb, bin_hz) == [mover]
        near = replace(mover, doppler_hz=300e3)  # 4 bins off the line: the wings' peak, as before
        assert select_targets([(0, static), (1, near)], dfb, bin_hz) == [static]

    def test_wings_bound_a_monte_carlo_laser(self):
        """The wings at an offset bound the delayed self-heterodyne pedestal of a Wiener-phase laser
        (1 MHz, an echo 54 ns late), measured: the mean periodogram of ``exp(j*(phi(t) - phi(t -
        dtau)))`` over 300 records, in rings about 0.5, 5 and 30 MHz (-32.0, -33.0, -46.5 dB of the
        line in a 30.5 kHz bin), stays under the stated wings (-32.0, -32.0, -45.9) and within 1.5 dB
        of them: flat beside the line out to ~1/(2*pi*dtau), then the envelope's 1/f^2. The
        pedestal's power is the line's loss, 1 - exp(-2*pi*dnu*dtau), within 1 %."""
        fs, n, lag, dnu = 500e6, 2**14, 27, 1e6
        dtau = lag / fs
        rng = np.random.default_rng(7)
        steps = rng.normal(0.0, math.sqrt(2 * math.pi * dnu / fs), (300, n + lag))
        phi = np.cumsum(steps, axis=1)
        beat = np.exp(1j * (phi[:, lag:] - phi[:, :-lag]))
        psd = np.mean(np.abs(np.fft.fft(beat, axis=1)) ** 2, axis=0) / n / fs  # per Hz of unit power
        freqs = np.fft.fftfreq(n, 1 / fs)
        st = get_profile("balanced", laser_linewidth_hz=dnu, lo_path_difference_m=0.0)
        static = point(C * dtau / 2, [50.0] * 3)
        line = math.exp(-2 * math.pi * dnu * dtau)
        assert np.sum(psd[1:]) * fs / n == pytest.approx(1 - line, rel=0.01)
        for f0 in (0.5e6, 5e6, 30e6):
            ring = (np.abs(np.abs(freqs) - f0) < 0.1 * f0 + 2e5) & (np.abs(freqs) > 3 * fs / n)
            measured = 10 * math.log10(np.mean(psd[ring]) * fs / n / line)
            stated = wings_level_db(st, static, fs / n, f0)
            assert measured < stated + 0.5
            assert measured > stated - 1.5

    def test_same_range_uses_the_sigmas(self):
        static = point(5.0, [40.0] * 3, sigma=1e-3)
        mover = point(5.02, [30.0] * 3, sigma=1e-3)  # 20 mm apart, 5 sigma = 7 mm: another range
        assert select_targets([(0, static), (1, mover)], self.ST) == [static, mover]

    def test_static_and_mover_both_kept_strongest_first(self):
        static = point(5.0, [30.0] * 3)
        mover = point(11.0, [35.0] * 3)
        assert select_targets([(0, static), (1, mover)], self.ST) == [mover, static]

    def test_order_by_median_tone_snr_not_the_strongest_line(self):
        a = point(2.0, [60.0, 20.0, 20.0])  # one loud line, median 20
        b = point(7.0, [30.0, 30.0, 30.0])
        c = point(11.0, [25.0, 25.0, 25.0])
        assert select_targets([(1, a), (2, b), (3, c)], self.ST) == [b, c, a]

    def test_incoherent_mover_dropped_beside_a_static_target(self):
        static = point(5.0, [40.0] * 3)
        skirt = point(8.0, [38.0] * 3, residual=1.0)
        assert select_targets([(0, static), (1, skirt)], self.ST) == [static]

    def test_a_mover_far_above_the_declared_lasers_wings_is_kept(self):
        """Random-looking phases (a blend) do not make a candidate the static lines' wings where the
        declared laser's wings in one bin stay 20 dB below it: 100 kHz at 5 m, 5 kHz bins, the
        wings 55 dB below the static lines (the delayed self-heterodyne pedestal beside the line,
        2*pi*linewidth*dtau^2 per Hz); a 5.3 GHz laser's wings are its whole line."""
        from mtcw_core.ranging.targets import shared_phase_psd, wings_level_db

        static = point(5.0, [40.0] * 3)
        mover = point(8.0, [38.0] * 3, residual=1.0)
        dfb = get_profile("balanced", laser_linewidth_hz=100e3)
        want = 10 * math.log10(shared_phase_psd(dfb, 5.0) * 5e3)
        assert want == pytest.approx(-54.6, abs=0.1)
        assert wings_level_db(dfb, static, 5e3) == pytest.approx(want, abs=0.05)
        assert select_targets([(0, static), (1, mover)], dfb, 5e3) == [static, mover]
        low = get_profile("balanced", laser_linewidth_hz=5.3e9)
        assert wings_level_db(low, static, 5e3) == 0.0
        assert select_targets([(0, static), (1, mover)], low, 5e3) == [static]
        assert select_targets([(0, static), (1, mover)], dfb) == [static]  # no bin: nothing bounds the wings
        # 2 MHz (the carrier beat at 8 m still 51 % a line): the wings -40.9 dB; a "mover" 24 dB
        # under static lines at 50 dB is dropped as them but stands 17 dB over them -- perhaps a
        # Doppler line whose self-beat the static lines are: the static point keeps its range, its
        # speed not measured (one photodiode only); 34 dB under them, a bump of them: ``static``
        wide = get_profile("balanced", laser_linewidth_hz=2e6)
        strong = point(5.0, [50.0] * 3)
        assert wings_level_db(wide, strong, 5e3) == pytest.approx(-40.9, abs=0.1)
        fast = replace(point(8.0, [26.0] * 3, residual=1.0), velocity_mps=0.3, direction="unknown")
        (kept,) = select_targets([(0, strong), (1, fast)], wide, 5e3)
        assert kept.range_m == strong.range_m and not kept.speed_measured and kept.velocity_sigma_mps > 0.3
        assert select_targets([(0, strong), (1, fast)], wide, 5e3, "balanced") == [strong]
        louder = point(5.0, [60.0] * 3)
        assert select_targets([(0, louder), (1, fast)], wide, 5e3) == [louder]

    def test_incoherent_residual_kept_without_static(self):
        mover = point(8.0, [38.0] * 3, residual=1.0)
        assert select_targets([(1, mover)], self.ST) == [mover]

    def test_empty(self):
        assert select_targets([], self.ST) == []


class TestCrossBeaten:
    """One photodiode: a static echo's beat with a mover, on the mover's own lines."""

    @staticmethod
    def fams(bound):
        f = fam("U", 1, var=(1e-6,) * 3, fd=7.5e6)
        return [LineFamily(f.name, f.tone_hz, f.line_hz, f.z, f.seg_centre_s, f.phase_var, 1, None,
                           np.full(3, bound))]

    def test_a_mover_the_static_echo_could_turn_is_flagged_where_it_lies_elsewhere(self):
        """Lines of unit size at phase sigma 1e-3: a beat of 0.01 turns them 10 sigmas (flagged); of
        1e-3, 1 sigma (not). Of 2.5e-3, 2.5 sigmas each, under the per-line rule, but together they
        can move the range by 0.77 mm, more than 3 of the mover's 0.2 mm (its lines' own sigma on
        these tones: flagged), not of 1 mm. At the static
        point's own range the static lines are the mover's self-beat left over, no second echo: not
        flagged."""
        from mtcw_core.ranging.targets import _cross_beaten

        static = point(1.98, [40.0] * 3)
        mover = replace(point(5.0, [35.0] * 3, sigma=2e-4), velocity_mps=4.8, direction="unknown")
        st = get_profile("balanced")
        (_, s), (_, m) = _cross_beaten([(0, static), (1, mover)], self.fams(0.01), st)
        assert m.blended and not s.blended
        assert not _cross_beaten([(0, static), (1, mover)], self.fams(1e-3), st)[1][1].blended
        assert _cross_beaten([(0, static), (1, mover)], self.fams(2.5e-3), st)[1][1].blended
        wide = replace(mover, range_sigma_m=1e-3)
        assert not _cross_beaten([(0, static), (1, wide)], self.fams(2.5e-3), st)[1][1].blended
        twin = replace(mover, range_m=1.98 + 1e-5)
        assert not _cross_beaten([(0, static), (1, twin)], self.fams(0.01), st)[1][1].blended
        assert not _cross_beaten([(1, mover)], self.fams(0.01), st)[0][1].blended  # no static point
        # ... unless the static lines stood mostly above what the self-beat's prediction took out:
        # a static echo's own lines (LineFamily.static_echo), whatever range they fit
        echo = fam("S", 0, var=(1e-6,) * 3)
        echo = replace(echo, static_echo=True, self_beats={1: np.zeros_like(echo.z)})  # one photodiode's
        assert _cross_beaten([(0, static), (1, twin)], self.fams(0.01) + [echo], st)[1][1].blended
        assert not _cross_beaten([(0, static), (1, twin)], self.fams(0.01) + [replace(echo, static_echo=False)],
                                 st)[1][1].blended
        # IQ and balanced: no self-beat (none predicted on the static lines), the bound is an echo's
        # leak: a mover at the static point's range is flagged, and so is one with no static point
        leak = replace(echo, static_echo=False, self_beats=None)
        assert _cross_beaten([(0, static), (1, twin)], self.fams(0.01) + [leak], st)[1][1].blended
        assert _cross_beaten([(1, mover)], self.fams(0.01) + [leak], st)[0][1].blended
        assert not _cross_beaten([(1, mover)], self.fams(1e-3) + [leak], st)[0][1].blended


    def test_the_static_echos_beat_pulls_the_movers_doppler_within_the_stated_bound(self):
        """The beat lies at the mover's lines less the static echo's Doppler ``f_s``: a phasor
        ``rho`` of the line's size ``f_s`` away. Over ``f_s`` from 0.05 to 4 record bins and every
        phase, neither the least-squares phase slope of the line (its frequency over the record;
        peak 0.42 bin per unit ``rho``) nor the Kaiser(14) reassignment (``refine_reassigned``'s
        estimator; peak 0.74) moves by more than ``cross_pull_hz``, which the reassignment nearly
        reaches; that bound enters the speed sigma (the envelope probe's scene 5081: a 66 dB echo
        0.39 bin from zero Doppler pulled a 26 dB mover by 7 Hz at a stated 0.6 Hz, speed z -10 and
        +12), and with the echo's Doppler bounded (``cross_x``) it is ``rho*f_s`` at most."""
        from dataclasses import replace as dc_replace

        from scipy.signal import get_window

        from mtcw_core.ranging.targets import cross_pull_hz, velocity

        rho, m = 1e-3, 4096
        t = (np.arange(m) + 0.5) / m
        w = get_window(("kaiser", 14.0), m, fftbins=False)
        dw = np.gradient(w)
        slope = reassigned = 0.0
        for x in np.linspace(0.05, 4.0, 40):
            for ph in np.linspace(0, 2 * np.pi, 8, endpoint=False):
                line = 1 + rho * np.exp(1j * (2 * np.pi * x * t + ph))
                slope = max(slope, abs(np.polyfit(t, np.unwrap(np.angle(line)), 1)[0]) / (2 * np.pi))
                f = 0.0  # record bins, the reassignment's three steps
                for _ in range(3):
                    e = line * np.exp(-2j * np.pi * f * t)
                    f -= m / (2 * np.pi) * np.imag(np.sum(e * dw) / np.sum(e * w))
                reassigned = max(reassigned, abs(f))
        fams = self.fams(rho / 2)  # the lines are of unit size: rho is twice the bound over them
        bin_hz = FS / N
        bound = cross_pull_hz(fams, bin_hz)
        assert slope * bin_hz < reassigned * bin_hz <= bound < 1.1 * reassigned * bin_hz, (slope, reassigned)
        near = [dc_replace(f, cross_x=0.2) for f in fams]
        assert cross_pull_hz(near, bin_hz) == pytest.approx(rho * 0.2 * bin_hz)
        d = dop(3e5, refine=1.0, method="reassigned")
        _, sig, _, _ = velocity(d, frame(), fams, False)
        assert sig == pytest.approx(math.hypot(1.0, bound) * LAM / 2)
        assert velocity(d, frame(), self.fams(0.0), False)[1] == pytest.approx(LAM / 2)


class TestSpeedNotMeasurable:
    """Issue 12 case 4: a speed that cannot be measured is not zero."""

    def test_carrier_coherence_is_one_line_only_within_coherence(self):
        from mtcw_core.ranging.targets import carrier_coherence

        ideal = get_profile("balanced")
        assert carrier_coherence(ideal, 100.0) == 1.0
        dfb = get_profile("balanced", laser_linewidth_hz=100e3)  # 100 kHz at 6.8 m: 2*pi*dv*dtau = 0.03
        assert carrier_coherence(dfb, 6.789) == pytest.approx(math.exp(-2 * math.pi * 100e3 * 2 * 6.789 / C))
        low = get_profile("balanced", laser_linewidth_hz=5.3e9, lo_path_difference_m=9.0)
        assert carrier_coherence(low, 1.12) < 1e-100
        assert carrier_coherence(low, 4.5) == 1.0  # the echo path equals the LO's

    def test_no_doppler_line_beyond_coherence_is_unknown_not_static(self):
        d = DopplerEstimate(0.0, False, 0.0, 10.0, 4e5)
        v, s, direction, vmin = velocity(d, frame(), [fam()], False, coherence=0.0, fd_max_hz=50e6)
        assert (v, direction) == (0.0, "unknown") and s == vmin == pytest.approx(50e6 * LAM / 2)
        v, s, direction, vmin = velocity(d, frame(), [fam()], False, coherence=1.0, fd_max_hz=50e6)
        assert direction == "static" and s == vmin == pytest.approx(4e5 * LAM / 2)


class TestScaledCopy:
    """A strong mover's phase-noise pedestal puts a weak "mover" beside it whose lines are the
    mover's times one complex number (issue 12 case 5: a ghost at 62 m/s beside 60 m/s)."""

    @staticmethod
    def noisy(f, ratio, var, seed):
        from dataclasses import replace
        rng = np.random.default_rng(seed)
        z = ratio * f.z
        sigma = np.sqrt(2 * np.asarray(var) * np.abs(z) ** 2 / 2)  # per quadrature
        z = z + sigma * (rng.standard_normal(z.shape) + 1j * rng.standard_normal(z.shape))
        return replace(f, z=z, phase_var=np.asarray(var, float), target=2)

    def parent(self):
        return [fam("U", 1, fd=5e6, range_m=3.7), fam("L", 1, fd=-5e6, range_m=3.7)]

    def test_a_pedestal_copy_is_one(self):
        from mtcw_core.ranging.targets import is_scaled_copy
        p = self.parent()
        r = 0.02 * np.exp(0.7j)
        for seed in range(5):
            ghost = [self.noisy(p[0], r, (0.05,) * 3, seed), self.noisy(p[1], np.conj(r), (0.05,) * 3, seed + 10)]
            assert is_scaled_copy(ghost, p)

    def test_a_target_at_another_range_is_not(self):
        from mtcw_core.ranging.targets import is_scaled_copy
        other = [fam("U", 2, fd=5.3e6, range_m=1.3), fam("L", 2, fd=-5.3e6, range_m=1.3)]
        weak = [self.noisy(f, 0.02, (0.01,) * 3, i) for i, f in enumerate(other)]
        assert not is_scaled_copy(weak, self.parent())

    def test_a_strong_candidate_is_not(self):
        from mtcw_core.ranging.targets import is_scaled_copy
        p = self.parent()
        assert not is_scaled_copy([self.noisy(f, 0.5, (1e-4,) * 3, 1) for f in p], p)


class TestIncoherentMover:
    def test_no_doppler_line_where_the_carrier_beat_is_no_line(self):
        """Issue 12's quasi-CW target at 930 m with a 100 kHz laser: the carrier beat keeps
        exp(-2*pi*1e5*2*930/c) = 2 % of its power in a line, so a "mover" found at that range is a
        bump of the static lines' Lorentzian wings; declared coherent (linewidth 0), the twin rule
        decides as before."""
        static, ghost = point(930.0, (26.0, 26.1, 22.0)), point(930.0, (28.4, 29.3, 25.7))
        declared = ChainSettings(laser_linewidth_hz=1e5)
        assert select_targets([(0, static), (1, ghost)], declared) == [static]
        assert select_targets([(0, static), (1, ghost)], ChainSettings()) == [ghost]
        # a mover at 3 m keeps 99.6 % of its carrier beat: it stays
        near = point(3.0, (28.4, 29.3, 25.7))
        assert near in select_targets([(0, static), (1, near)], declared)


class TestToneAmplitudes:
    """``amplitude_chi2``: a static point's line sizes against one target's (two echoes on one
    Doppler-0 line set can fit one wrong range by their phases, not by their sizes)."""

    G = np.array([1.0, 0.8, 1.3])  # the bench's line amplitudes, any scale

    def lines(self, echoes, var, seed, segments=1):
        """A static family of ``echoes`` [(amplitude, range_m)], each line ``G_i`` times their sum,
        with complex noise of phase variance ``var`` at each line's own size."""
        rng = np.random.default_rng(seed)
        z = sum(a * self.G * fam(range_m=r).z[0] for a, r in echoes)
        v = var * np.abs(z) ** 2  # each component's variance, whole record
        noise = rng.normal(size=(segments, 3, 2)) @ np.array([1, 1j]) * np.sqrt(v * segments)
        f = fam(var=var * np.ones(3))
        return replace(f, z=z[None, :] + noise, seg_centre_s=np.full(segments, f.seg_centre_s[0]))

    def ref(self, rel=0.0):
        return {float(t): (float(g) * 7.0, rel) for t, g in zip(TONES, self.G)}  # any common scale

    def test_one_echo_fits_at_its_noise(self):
        """Over many noise draws the chi2 has its 2 degrees of freedom's mean, and p < 1e-4 (the
        flag) stays as rare as chance -- one line set at a time and cut into segments alike."""
        from mtcw_core.ranging.targets import amplitude_chi2
        for segments in (1, 8):
            c2 = [amplitude_chi2([self.lines([(1.0, 3.7)], 1e-3, s, segments)], self.ref(), 10.0)
                  for s in range(2000)]
            assert all(d == 2 for _, d in c2)
            assert np.mean([c for c, _ in c2]) == pytest.approx(2.0, rel=0.15)
            assert sum(c > 18.4 for c, _ in c2) <= 2  # chi2(2) exceeds 18.4 with p 1e-4

    def test_two_echoes_on_one_line_set_do_not(self):
        """A second echo 20 dB under the first, 3 m behind it: their phases fit one range (chi2/dof
        5, p 0.02: the Birge ratio widens the sigma, no flag), but each tone's sum differs in size
        by up to +-10 % (chi2 168 on 2 dof at 40 dB of line SNR): flagged ``blended`` where the
        amplitudes are known."""
        from mtcw_core.ranging.targets import amplitude_chi2
        f = self.lines([(1.0, 3.7), (0.1, 6.7)], 1e-4, 0)
        chi2, dof = amplitude_chi2([f], self.ref(), 10.0)
        assert dof == 2 and chi2 > 100
        obs = mix([f], PHI, 10.0)[0]
        blind = solve_target([f], obs, dop(0.0, False), frame(), ChainSettings(), Reference(PHI, 0.0), None)
        known = solve_target([f], obs, dop(0.0, False), frame(), ChainSettings(), Reference(PHI, 0.0, self.ref()), None)
        assert known.blended and not blind.blended

    def test_a_blend_the_sizes_show_widens_the_range_sigma(self, monkeypatch):
        """A second echo 30 dB under the first (rho 0.03) against sizes declared to 1 %, lines at
        0.003 rad of phase noise: each tone's size moves by ``rho*cos`` and its phase by ``rho*sin``
        of their phase difference, so where the sizes' scatter is improbable for one target but not
        flagged (``blend_phase_var``) its excess enters the range sigma as a phase variance per tone.
        Over 300 second-echo ranges, the 47 unflagged points whose sizes show it: range z rms 1.14,
        largest 2.5 with it; rms 6.1 and 16 beyond 5 sigmas without (the phases alone fit one range
        within chance). The flags, read from the phases as they are, do not move."""
        from mtcw_core.ranging import targets as tg
        assert tg.blend_phase_var(2.0, 2, 1e-4) == 0.0  # p 0.37: one target's scatter
        assert tg.blend_phase_var(12.0, 2, 1e-4) == pytest.approx(5e-4)  # p 0.0025: (6 - 1) x 1e-4
        assert tg.blend_phase_var(30.0, 3, 1e-4) == 0.0  # p 1e-6: flagged by the sizes, no sigma
        real = tg.blend_phase_var
        z = {True: [], False: []}
        for k in range(300):
            f = self.lines([(1.0, 3.7), (0.03, 3.7 + 0.37 + 0.91 * k)], 1e-5, k)
            obs = mix([f], PHI, 10.0)[0]
            if real(*tg._amplitude_fit([f], self.ref(0.01), 10.0)) == 0:
                continue
            flags, sigmas = [], []
            for on in (True, False):
                monkeypatch.setattr(tg, "blend_phase_var", real if on else (lambda *a: 0.0))
                p = solve_target([f], obs, dop(0.0, False), frame(), ChainSettings(), Reference(PHI, 0.0, self.ref(0.01)),
                                 None)
                flags.append((p.blended, p.cycle_ambiguous))
                sigmas.append(p.range_sigma_m)
                if not (p.blended or p.cycle_ambiguous):
                    z[on].append((p.range_m - 3.7) / p.range_sigma_m)
            assert flags[0] == flags[1] and sigmas[0] >= sigmas[1]
        with_var, without = np.array(z[True]), np.array(z[False])
        assert with_var.size >= 30
        assert np.max(np.abs(with_var)) < 5 and 0.7 < np.sqrt(np.mean(with_var**2)) < 1.6, with_var
        assert np.sum(np.abs(without) > 5) >= 10, without

    def test_the_allowed_size_variance_is_the_harmonic_mean_over_the_tones(self):
        """``_amplitude_fit``'s ``allowed``: each tone's chi2 term is its relative excess over its own
        allowed variance, so the excess they share is ``chi2/dof - 1`` times the harmonic mean of
        those (the arithmetic one follows the noisiest tone: a blend's sigma ~3x wide there)."""
        from mtcw_core.ranging import targets as tg
        f = self.lines([(1.0, 3.7)], 1e-8, 0)
        f = replace(f, phase_var=np.array([1e-8, 1e-8, 3e-3]))
        _, dof, allowed = tg._amplitude_fit([f], self.ref(0.01), 10.0)
        each = 0.01**2 + f.phase_var * (1 + f.phase_var)  # rel^2 + the size's noise (x 1 + S*v), relative
        assert dof == 2
        assert allowed == pytest.approx(1 / np.mean(1 / each), rel=0.05)
        assert allowed < 0.5 * np.mean(each)

    def test_the_relative_sigma_widens_the_check(self):
        """The amplitudes' own error (a calibration's spread, their drift since) enters each line's
        sigma: a 3 % error passes at 5 % and fails at 0.1 %."""
        from mtcw_core.ranging.targets import amplitude_chi2
        f = self.lines([(1.0, 3.7)], 1e-8, 0)
        f = replace(f, z=f.z * np.array([1.03, 1.0, 0.97]))
        assert amplitude_chi2([f], self.ref(0.05), 10.0)[0] < 2.0
        assert amplitude_chi2([f], self.ref(0.001), 10.0)[0] > 100

    def test_no_amplitudes_or_too_few_lines_check_nothing(self):
        from mtcw_core.ranging.targets import amplitude_chi2
        f = self.lines([(1.0, 3.7), (0.5, 5.6)], 1e-4, 0)
        assert amplitude_chi2([f], None, 10.0) == (0.0, 0)
        weak = replace(f, phase_var=np.array([1e-4, 1.0, 1.0]))  # two lines under 10 dB
        assert amplitude_chi2([weak], self.ref(), 10.0) == (0.0, 0)
        # segments whose noise is most of their power (400 quasi-CW windows at 5 dB each): the size
        # left after its share is taken out carries the floor's own error
        noisy = self.lines([(1.0, 3.7), (0.5, 5.6)], 1e-3, 0, segments=400)
        assert amplitude_chi2([noisy], self.ref(), 10.0) == (0.0, 0)

    def test_a_noiseless_line_weighs_most_and_still_flags_a_blend(self):
        from mtcw_core.ranging.targets import amplitude_chi2
        f = self.lines([(1.0, 3.7), (0.1, 6.7)], 1e-4, 0)
        f = replace(f, phase_var=np.array([0.0, 1e-4, 1e-4]))
        chi2, dof = amplitude_chi2([f], self.ref(), 10.0)
        assert dof == 2 and np.isfinite(chi2) and chi2 > 100
        assert amplitude_chi2([], self.ref(), 10.0) == (0.0, 0)

    def test_the_calibrations_amplitudes_come_before_the_settings(self):
        from mtcw_core.calibration import Calibration
        fr = frame()
        st = ChainSettings(tone_amplitudes=(1.0, 2.0, 3.0), tone_amplitude_tolerance=0.02)
        assert Reference.of(fr, st, None).tone_amplitudes == {100e6: (1.0, 0.02), 170e6: (2.0, 0.02),
                                                             260e6: (3.0, 0.02)}
        cal = Calibration(tones_hz=tuple(TONES), tone_phases_rad=(0.0,) * 3, tau0_s=0.0,
                          tone_amplitudes=(0.9, 1.0, 1.1), tone_amplitude_std=(0.0, 0.03, 0.04))
        amps = Reference.of(fr, st, cal).tone_amplitudes
        assert amps[170e6] == (1.0, pytest.approx(math.hypot(0.03, 0.02)))
        assert amps[260e6] == (1.1, pytest.approx(math.hypot(0.04 / 1.1, 0.02)))  # relative to its amplitude
        assert amps[100e6] == (0.9, pytest.approx(0.02))
        assert Reference.of(fr, ChainSettings(), None).tone_amplitudes is None


class TestPedestalGhostOdds:
    """:func:`pedestal_ghost_odds`: a Doppler line's odds of being noise, its lines counted as their
    rings show their noise moving together."""

    @staticmethod
    def fams(rows: np.ndarray) -> list[LineFamily]:
        from mtcw_core.dsp.extract import NoiseRing

        t = np.array([5e8, 7e8, 9.5e8])
        out = []
        for name, cols in (("U", rows[:, :3]), ("L", rows[:, 3:])):
            ring = NoiseRing(cols, np.zeros(3), np.ones(cols.shape[0], bool))
            out.append(LineFamily(name, t, t, np.ones((1, 3), complex), np.zeros(1), np.full(3, 1e-2), 1, ring=ring))
        return out

    def test_independent_lines_at_the_threshold_are_no_ghost_one_process_is(self):
        from mtcw_core.ranging.targets import pedestal_ghost_odds

        rng = np.random.default_rng(3)
        w = 400
        white = (rng.standard_normal((w, 6)) + 1j * rng.standard_normal((w, 6))) * np.sqrt(0.5e-2)
        # one process at every line: each row one complex draw, the same at all six lines
        one = np.repeat(white[:, :1], 6, axis=1)
        # six lines and the baseband, 1.5x the search's threshold of 8 per line
        dop = DopplerEstimate(2e6, True, 1.5 * 8.0 * 7, 8.0 * 7, 1e4)
        apart = pedestal_ghost_odds(dop, self.fams(white), 8.0, 1e5)
        together = pedestal_ghost_odds(dop, self.fams(one), 8.0, 1e5)
        # independent: the search's own statistic, a Gamma(7) tail at 84 over 1e5 bins; one process:
        # a single line's ratio at 12 (e^-12 ~ 6e-6, times 1e5 bins)
        assert apart < 1e-12
        assert 0.1 < together <= 1.0
        # noise that the rings show 2x above the floor the lines were judged on halves each ratio
        assert pedestal_ghost_odds(dop, self.fams(one * math.sqrt(2)), 8.0, 1.0) > 10 * pedestal_ghost_odds(
            dop, self.fams(one), 8.0, 1.0)
        # no rings, or no Doppler line: nothing to say; nor for a sub-guard fit (its score is one
        # line's SNR against a threshold of its own), nor over a ring of a few rows
        bare = [replace(f, ring=None) for f in self.fams(one)]
        assert pedestal_ghost_odds(dop, bare, 8.0, 1e5) == 0.0
        assert pedestal_ghost_odds(replace(dop, detected=False), self.fams(one), 8.0, 1e5) == 0.0
        assert pedestal_ghost_odds(replace(dop, method="fit", threshold=100.0, score=150.0), self.fams(one),
                                   8.0, 1e5) == 0.0
        assert pedestal_ghost_odds(dop, self.fams(one[:1]), 8.0, 1e5) == 0.0


class TestWholeSelfBeats:
    """:func:`whole_self_beats`: the rest of a mover's self-beat (its prediction keeps the carrier's
    coherence at its delay) taken out of the static lines once its range is known."""

    @staticmethod
    def static(pred: np.ndarray) -> LineFamily:
        f = fam(range_m=1.3, var=(1e-4,) * 3)
        return replace(f, self_beats={1: pred})

    @staticmethod
    def mover(range_m: float) -> tuple[int, TargetPoint, float]:
        return 1, replace(point(range_m, [30.0] * 3), direction="receding", velocity_mps=0.2), 3.0

    def test_the_rest_at_the_movers_coherence_is_taken_out(self):
        from mtcw_core.ranging.targets import SELF_BEAT_SCATTER, carrier_coherence, whole_self_beats

        pred = 0.05 * np.exp(1j * np.array([[0.3, -1.1, 2.0]]))
        st = ChainSettings(laser_linewidth_hz=1e6, lo_path_difference_m=20.0)
        f = self.static(pred)
        movers = [replace(g, phase_var=np.full(3, 1e-3)) for g in (fam("U", 1), fam("L", 1))]
        out = whole_self_beats([f], [self.mover(2.0)], [f, *movers], st, (-0.05, 2.95))[0]
        c = carrier_coherence(st, 2.0)  # |2*2 - 20| m of delay under 1 MHz: 0.81
        assert 0.7 < c < 0.9
        np.testing.assert_allclose(out.z, f.z - (1 / c - 1) * pred, rtol=1e-12)
        # the mover's lines' noise and the prediction's scatter about c on what was taken
        amp2 = np.abs(out.z[0]) ** 2
        added = (0.05 * (1 / c - 1)) ** 2 * (2e-3 + SELF_BEAT_SCATTER ** 2) / amp2
        np.testing.assert_allclose(out.phase_var, f.phase_var * np.abs(f.z[0]) ** 2 / amp2 + added, rtol=1e-9)
        assert not np.any(out.unexplained_v)  # one period searched: no other cycle

    @pytest.mark.parametrize("reported", [2.0, 8.0])
    def test_other_cycles_within_a_declared_range_bound_the_rest(self, reported):
        """A mover reported at 2 or at 8 m with a 3 m period and 12 m declared: it could be at 2, 5,
        8 or 11 m (the pair cost repeats: its point is any of them), the least at 2 m, the most at 11."""
        from mtcw_core.ranging.targets import self_beat_scales, whole_self_beats

        pred = 0.05 * np.ones((1, 3), complex)
        st = ChainSettings(laser_linewidth_hz=1e6, range_max_m=12.0)
        least, most = self_beat_scales(st, reported, 3.0, (-0.05, 12.0))
        assert least == pytest.approx(math.exp(2 * math.pi * 1e6 * 4.0 / C))
        assert most == pytest.approx(math.exp(2 * math.pi * 1e6 * 22.0 / C))
        out = whole_self_beats([self.static(pred)], [self.mover(reported)], [], st, (-0.05, 12.0))[0]
        np.testing.assert_allclose(out.unexplained_v, (most - least) * 0.05, rtol=1e-12)

    def test_a_mover_known_modulo_a_shorter_period_is_bounded_over_the_frames(self):
        """No range declared: the frame's period is searched, and a mover whose own lines repeat
        sooner (one lost) could be in any of its cycles within it."""
        from mtcw_core.ranging.targets import self_beat_scales

        st = ChainSettings(laser_linewidth_hz=1e6)
        assert self_beat_scales(st, 2.0, 3.0, (-0.05, 2.95))[0] == self_beat_scales(st, 2.0, 3.0, (-0.05, 2.95))[1]
        least, most = self_beat_scales(st, 2.0, 3.0, (-0.05, 14.95))
        assert most == pytest.approx(math.exp(2 * math.pi * 1e6 * 2 * 14.0 / C)) and least < most

    def test_nothing_without_a_declared_laser_or_a_prediction(self):
        from mtcw_core.ranging.targets import whole_self_beats

        f = self.static(0.05 * np.ones((1, 3), complex))
        span = (-0.05, 2.95)
        assert whole_self_beats([f], [self.mover(2.0)], [f], ChainSettings(), span)[0] is f
        plain = fam(range_m=1.3)
        fams = [plain]
        assert whole_self_beats(fams, [self.mover(2.0)], fams, ChainSettings(laser_linewidth_hz=1e6), span) is fams


class TestSidebandChi2:
    """:func:`sideband_chi2`: an IQ record's static lines, upper against lower sideband per tone."""

    @staticmethod
    def fams(upper: np.ndarray, lower: np.ndarray, var: float = 1e-4) -> list[LineFamily]:
        t = np.array([2.7e8, 4.6e8, 6.4e8])
        return [LineFamily(name, t, s * t, np.asarray(a, complex)[None, :] * np.exp(1j * 0.4), np.zeros(1),
                           np.full(3, var), 0) for name, s, a in (("U", 1, upper), ("L", -1, lower))]

    def test_one_echo_is_symmetric_two_are_not(self):
        from scipy.special import chdtrc

        from mtcw_core.ranging.targets import BLENDED_P, sideband_chi2

        one = self.fams(np.array([1.0, 1.3, 0.8]), np.array([1.0, 1.3, 0.8]) * (1 + 0.01 * np.array([1, -1, 0.5])))
        c, dof = sideband_chi2(one, 0.01, 10.0)
        assert dof == 3 and chdtrc(dof, c) > 0.05
        # the envelope probe's scene 10319: two echoes, sizes 1.2 / 1.5, 1.9 / 0.1, 0.8 / 1.7
        two = self.fams(np.array([1.2, 1.9, 0.8]), np.array([1.5, 0.1, 1.7]))
        c, dof = sideband_chi2(two, 0.01, 10.0)
        assert dof == 3 and chdtrc(dof, c) < BLENDED_P

    def test_one_sideband_or_weak_lines_say_nothing(self):
        from mtcw_core.ranging.targets import sideband_chi2

        two = self.fams(np.array([1.2, 1.9, 0.8]), np.array([1.5, 0.1, 1.7]))
        assert sideband_chi2(two[:1], 0.01, 10.0) == (0.0, 0)
        assert sideband_chi2(self.fams(np.ones(3), np.ones(3), var=0.5), 0.01, 10.0) == (0.0, 0)


class TestSidebandSplit:
    """:func:`sideband_split`: a mover's upper and lower sidebands, tone by tone, against one carrier."""

    T = np.array([1.5e8, 3.2e8, 6.7e8, 8.6e8])

    def fams(self, rng, blend: float = 0.0, drift: float = 0.0, laser: float = 0.0, pv: float = 1e-4,
             segments: int = 8, fd: float = 3e4) -> list[LineFamily]:
        """U and L of one mover (its range, a per-tone drift ``drift`` rad, a laser whose carrier
        phase wanders ``laser`` rad per segment, 2*f_d's turn across the segments) with noise of
        whole-record phase variance ``pv``; ``blend``: a second echo's phasor of that relative size
        with its own per-tone phase and its own carrier phases, on both sidebands (a static echo's
        beat)."""
        t_s = (np.arange(segments) + 0.5) * 1e-5
        theta = -2 * np.pi * np.mod(self.T * 2 * 7.3 / 299792458.0, 1.0) + drift * rng.standard_normal(self.T.size)
        psi = 0.7 + np.cumsum(laser * rng.standard_normal(segments))[:, None] + 2 * np.pi * fd * t_s[:, None]
        other = -2 * np.pi * np.mod(self.T * 2 * 2.1 / 299792458.0, 1.0) + 1.9
        sigma = np.sqrt(2 * pv * segments)  # per segment, complex: whole-record phase variance pv
        out = []
        for name, sign, chi in (("U", 1, 0.4), ("L", -1, 1.5)):
            z = np.exp(1j * (theta + sign * psi)) + blend * np.exp(1j * (other + sign * psi + chi))
            z = z + sigma * (rng.standard_normal(z.shape) + 1j * rng.standard_normal(z.shape)) / np.sqrt(2)
            out.append(LineFamily(name, self.T, self.T + sign * fd, z, t_s, np.full(self.T.size, pv), 1))
        return out

    def test_one_carrier_is_within_chance_whatever_drift_and_laser(self):
        """Over 400 draws with the tones drifting 0.3 rad and the carrier wandering 0.2 rad per
        segment, p < 0.05 about one time in twenty, and below the flag's 1e-4 hardly ever."""
        from scipy.special import chdtrc

        from mtcw_core.ranging.targets import BLENDED_P, sideband_split

        rng = np.random.default_rng(5)
        p = np.array([chdtrc(3, sideband_split(self.fams(rng, drift=0.3, laser=0.2), 3e4, 10.0)[0])
                      for _ in range(400)])
        assert 0.02 <= np.mean(p < 0.05) <= 0.09, np.mean(p < 0.05)
        assert np.sum(p < BLENDED_P) <= 1

    def test_the_drift_cancels_exactly(self):
        from mtcw_core.ranging.targets import sideband_split

        a = self.fams(np.random.default_rng(1))
        b = [replace(f, z=f.z * np.exp(1j * np.array([0.3, -1.1, 2.0, 0.05]))) for f in a]
        assert sideband_split(a, 3e4, 10.0) == pytest.approx(sideband_split(b, 3e4, 10.0), rel=1e-9)

    def test_a_second_echos_beat_on_the_sidebands_is_flagged(self):
        """Scene 22312's kind: a phasor 0.1 of the mover's lines, with the other echo's range, at line
        SNRs of 60 dB (at 40 dB a quarter of such draws turn the tones too nearly alike to tell)."""
        from scipy.special import chdtrc

        from mtcw_core.ranging.targets import BLENDED_P, sideband_split

        rng = np.random.default_rng(2)
        for _ in range(20):
            c, dof = sideband_split(self.fams(rng, blend=0.1, drift=0.3, pv=1e-6), 3e4, 10.0)
            assert dof == 3 and chdtrc(dof, c) < BLENDED_P, c

    def test_one_sideband_or_weak_lines_say_nothing(self):
        from mtcw_core.ranging.targets import sideband_split

        f = self.fams(np.random.default_rng(3))
        assert sideband_split(f[:1], 3e4, 10.0) == (0.0, 0)
        assert sideband_split(self.fams(np.random.default_rng(3), pv=0.5), 3e4, 10.0) == (0.0, 0)


class TestRangeTurn:
    """range_turn_m: the range shift per-line phase turns can make together through the range fit."""

    @staticmethod
    def fam(tones, sig, turn, bound, snr=30.0):
        from types import SimpleNamespace

        tones = np.asarray(tones, float)
        return SimpleNamespace(tone_hz=tones, snr_db=np.full(tones.size, snr), phase_var=np.asarray(sig, float) ** 2,
                               z=np.exp(1j * np.broadcast_to(np.asarray(turn, float), tones.shape))[None, :], seg_centre_s=np.zeros(1),
                               cross_v=None if bound is None else np.asarray(bound, float))

    def shift(self, fams) -> float:
        """The range the chain's own pair observations give, every line turned by its largest turn
        with the sign that moves the slope one way (each family's lines about their weighted mean)."""
        from mtcw_core.ranging.mixing import pair_observations

        turned = []
        for f in fams:
            w = 1 / f.phase_var
            sign = np.sign(f.tone_hz - np.sum(w * f.tone_hz) / np.sum(w))
            turn = 0.0 if f.cross_v is None else np.arcsin(f.cross_v) * sign
            turned.append(self.fam(f.tone_hz, np.sqrt(f.phase_var), turn, f.cross_v))
        obs = pair_observations(turned, {float(t): 0.0 for f in fams for t in f.tone_hz})
        slope = np.sum(obs.weight * obs.df_hz * obs.phase_rad) / np.sum(obs.weight * obs.df_hz**2)
        return abs(slope) * C / (4 * np.pi)

    def test_the_worst_turns_through_the_chains_pair_observations_give_the_bound(self):
        from mtcw_core.ranging.targets import range_turn_m

        tones = np.array([500e6, 670e6, 700e6, 890e6, 950e6])
        sig = np.array([0.02, 0.03, 0.02, 0.025, 0.02])
        bound = np.array([0.05, 0.02, 0.04, 0.03, 0.06])  # V, on lines of 1 V
        fams = [self.fam(tones, sig, 0, bound), self.fam(tones[1:], sig[1:], 0, bound[1:])]
        assert range_turn_m(fams, 10.0) == pytest.approx(self.shift(fams), rel=1e-9)
        # families of other lines and weights, one without a bound (a review's case: the bound 6.9x short
        # where each family's own weight was left out)
        fams = [self.fam(tones[[1, 2]], [0.01, 0.01], 0, [0.02, 0.02]), self.fam(tones[[0, 4]], [0.03, 0.03], 0, None)]
        assert range_turn_m(fams, 10.0) == pytest.approx(self.shift(fams), rel=1e-9)

    def test_no_bound_weak_lines_or_one_line_give_none(self):
        from mtcw_core.ranging.targets import range_turn_m

        tones = [500e6, 700e6, 950e6]
        assert range_turn_m([self.fam(tones, [0.02] * 3, 0, None)], 10.0) == 0.0
        assert range_turn_m([self.fam(tones, [0.02] * 3, 0, [0.1] * 3, snr=5.0)], 10.0) == 0.0
        assert range_turn_m([self.fam(tones[:1], [0.02], 0, [0.1])], 10.0) == 0.0


class TestAliases:
    """``targets._aliases``: the whole periods of the pairs the true range may lie from the solution,
    which the still lines' common phase is read over (``mixing.realness_chi2``)."""

    def test_no_bound_reaches_every_period_up_to_the_cap(self):
        from mtcw_core.ranging.targets import ALIAS_MAX, _aliases

        period, k = _aliases(1.2, 1.5, (0.0, None), None)
        assert period == pytest.approx(3.0 / C) and k[0] == 0 and k[-1] == ALIAS_MAX

    def test_a_declared_range_bound_limits_them_both_ways(self):
        from mtcw_core.ranging.targets import _aliases

        assert list(_aliases(1.2, 1.5, (0.0, 5.0), None)[1]) == [0, 1, 2]
        assert list(_aliases(4.0, 1.5, (0.5, 5.0), None)[1]) == [-2, -1, 0]

    def test_a_coarse_range_keeps_the_periods_it_leaves_in_doubt(self):
        from mtcw_core.ranging.targets import _aliases

        assert list(_aliases(1.2, 1.5, (0.0, None), (1.0, 1.6))[1]) == [0]
        assert list(_aliases(1.2, 1.5, (0.0, None), (0.0, 3.0))[1]) == [0, 1]


def test_slope_phase_var_against_a_monte_carlo_of_the_delayed_self_heterodyne_phase():
    """The least-squares frequency of ``phi(t) - phi(t - tau)`` (``phi`` a Wiener phase of rate
    2*pi*linewidth) drawn directly, against the closed form: flat-PSD limit, saturation, between."""
    rng = np.random.default_rng(3)
    lw, fs, n = 1e5, 1e9, 1000
    t = np.arange(n) / fs
    w = (t - t.mean()) / np.sum((t - t.mean()) ** 2) / (2 * np.pi)  # Hz per rad of slope
    for lag in (20, 200, 700, 2000):
        steps = rng.normal(0, np.sqrt(2 * np.pi * lw / fs), (4000, n + lag))
        phi = np.cumsum(steps, axis=1)
        est = (phi[:, lag:] - phi[:, :n]) @ w
        want = targets.slope_phase_var(lw, lag / fs, n / fs)
        assert np.var(est) == pytest.approx(want, rel=0.1), lag
    T, tau = 1e-5, 1e-8
    assert targets.slope_phase_var(lw, tau, T) == pytest.approx(3 * (2 * np.pi * lw * tau**2) / (np.pi**2 * T**3), rel=0.01)
    assert targets.slope_phase_var(lw, 3 * T, T) == targets.slope_phase_var(lw, T, T) == pytest.approx(2.4 * 2 * np.pi * lw / T / (4 * np.pi**2))
