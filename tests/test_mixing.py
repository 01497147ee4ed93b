"""mtcw_core.ranging.mixing: IF mixing of hand-built line families into pair observations."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from mtcw_core.dsp.extract import LineFamily
from mtcw_core.phase import C, wrap_pi
from mtcw_core.ranging.mixing import consistency, mix, pair_observations, realness_chi2, sideband_products

TONES = np.array([100e6, 170e6, 260e6])
PHI = {100e6: 0.3, 170e6: -1.2, 260e6: 2.5}  # RF drive phases (calibration)
L_M = 3.7
TAU = 2 * L_M / C


def family(tau=TAU, var=(1e-4, 2e-4, 4e-4), name="S", target=0, segments=4, fd=0.0, extra_phase=(0.0, 0.0, 0.0),
           seed=0, amps=(1.0, 0.5, 0.25)):
    """Lines at f_i + fd with phase phi_i - 2*pi*f_i*tau (+ a nuisance psi per segment), each
    referred to its segment's centre (so it advances by 2*pi*line*t_c)."""
    rng = np.random.default_rng(seed)
    centres = (np.arange(segments) + 0.5) * 1e-6
    psi = rng.uniform(-np.pi, np.pi, segments)  # carrier / laser phase: common to the family
    line = TONES + fd
    ph = np.array([PHI[f] for f in TONES]) - 2 * np.pi * np.mod(TONES * tau, 1.0) + np.asarray(extra_phase)
    z = np.asarray(amps)[None, :] * np.exp(1j * (ph[None, :] + psi[:, None]
                                                 + 2 * np.pi * np.mod(np.outer(centres, line), 1.0)))
    return LineFamily(name, TONES.copy(), line, z, centres, np.asarray(var, float), target)


class TestPairObservations:
    def test_wrapped_phases_and_weights(self):
        fam = family()
        obs = pair_observations([fam], PHI)
        assert obs.df_hz.size == 3
        got = {round(d): (p, w) for d, p, w in zip(obs.df_hz, obs.phase_rad, obs.weight)}
        for i, j in itertools.combinations(range(3), 2):
            hi, lo = max(i, j), min(i, j)
            d = TONES[hi] - TONES[lo]
            p, w = got[round(d)]
            assert wrap_pi(p + 2 * np.pi * d * TAU) == pytest.approx(0.0, abs=1e-9)
            assert -np.pi <= p < np.pi
            assert w == pytest.approx(1 / (fam.phase_var[hi] * fam.phase_var[lo]), rel=1e-12)
        assert np.all(obs.df_hz > 0)

    def test_doppler_shifted_family_same_phases(self):
        """U lines at f_i + f_d, each referred to its segment's centre: the pair phase still
        carries -2*pi*(f_i - f_j)*tau (the common f_d and psi cancel)."""
        fam = family(name="U", fd=5.3e6, target=1, seed=3)
        obs = pair_observations([fam], PHI)
        np.testing.assert_allclose(wrap_pi(obs.phase_rad + 2 * np.pi * obs.df_hz * TAU), 0.0, atol=1e-9)

    def test_tones_in_any_order(self):
        """Lines listed highest tone first: every pair still has df > 0 and its phase -2*pi*df*tau."""
        fam = family(seed=5)
        rev = LineFamily("S", fam.tone_hz[::-1].copy(), fam.line_hz[::-1].copy(), fam.z[:, ::-1].copy(),
                         fam.seg_centre_s, fam.phase_var[::-1].copy())
        obs = pair_observations([rev], PHI)
        assert np.all(obs.df_hz > 0) and obs.df_hz.size == 3
        np.testing.assert_allclose(wrap_pi(obs.phase_rad + 2 * np.pi * obs.df_hz * TAU), 0.0, atol=1e-9)
        np.testing.assert_allclose(sorted(obs.weight), sorted(pair_observations([fam], PHI).weight), rtol=1e-15)

    def test_families_concatenate(self):
        obs = pair_observations([family(name="U", seed=1), family(name="L", seed=2)], PHI)
        assert obs.df_hz.size == 6

    def test_snr_threshold_drops_weak_lines(self):
        fam = family(var=(1e-4, 1e-4, 1.0))  # third line at 0 dB
        obs = pair_observations([fam], PHI, min_snr_db=10.0)
        np.testing.assert_allclose(obs.df_hz, [70e6])

    def test_calibration_phases_removed(self):
        fam = family()
        wrong = {f: 0.0 for f in TONES}
        obs = pair_observations([fam], wrong)
        # without the calibration the drive phase difference stays in
        d = obs.df_hz
        i = np.searchsorted(TONES, 170e6)
        k = int(np.argmin(np.abs(d - 70e6)))
        want = wrap_pi(-2 * np.pi * 70e6 * TAU + PHI[170e6] - PHI[100e6])
        assert wrap_pi(obs.phase_rad[k] - want) == pytest.approx(0.0, abs=1e-9)
        assert i == 1

    def test_empty(self):
        obs = pair_observations([], PHI)
        assert obs.df_hz.size == obs.phase_rad.size == obs.weight.size == 0


class TestConsistency:
    def test_consistent_family_chi2_zero(self):
        chi2, dof = consistency([family()], PHI, TAU)
        assert chi2 == pytest.approx(0.0, abs=1e-12)
        assert dof == 1  # 3 lines -> 2 pair phases, minus the range

    def test_two_families_dof(self):
        chi2, dof = consistency([family(seed=1), family(name="U", fd=4e6, seed=2)], PHI, TAU)
        assert chi2 == pytest.approx(0.0, abs=1e-12) and dof == 3

    def test_inconsistent_family_analytic_chi2(self):
        """Line 3 off by delta, equal variances v, reference line 1: residuals (0, delta) with
        covariance v*(I + 11^T), whose inverse is (I - 11^T/3)/v: chi2 = 2*delta^2/(3v)."""
        v, delta = 1e-4, 0.2
        fam = family(var=(v, v, v), extra_phase=(0.0, 0.0, delta))
        chi2, dof = consistency([fam], PHI, TAU)
        assert chi2 == pytest.approx(2 * delta**2 / (3 * v), rel=1e-9)
        assert chi2 > 100

    def test_wrong_range_is_inconsistent(self):
        chi2, _ = consistency([family()], PHI, TAU + 2 * 0.1 / C)  # 0.3-0.5 rad off
        assert chi2 > 300

    def test_tone_drift_shared_by_a_movers_sidebands(self):
        """The tones' phase drift moves a mover's U and L lines alike (one draw per tone): counted
        apart, the two families give its chi2 twice its 2 degrees of freedom on average -- a wrong
        cycle's excess twice the evidence (the envelope probe's scene 33007). With the drift shared
        its chi2 has the mean of its dof and the chi2 distribution's spread, over 400 draws."""
        v_line, v_tone = 1e-8, 1e-4
        rng = np.random.default_rng(7)
        apart, shared = [], []
        for k in range(400):
            drift = tuple(rng.normal(0.0, np.sqrt(v_tone), 3))
            fams = [family(var=(v_line + v_tone,) * 3, name=nm, target=1, fd=sg * 4e6, extra_phase=drift, seed=k)
                    for nm, sg in (("U", 1), ("L", -1))]
            c_apart, dof = consistency(fams, PHI, TAU)
            c_shared, dof2 = consistency(fams, PHI, TAU, shared_var=v_tone)
            assert dof == dof2 == 3
            apart.append(c_apart)
            shared.append(c_shared)
        # the drift has 2 degrees of freedom here (3 tones, less their common phase): chi2_2 has mean
        # 2 and variance 4; counted apart it reads 2 x chi2_2 (mean 4)
        assert np.mean(shared) == pytest.approx(2.0, abs=0.35)
        assert np.var(shared) == pytest.approx(4.0, rel=0.4)
        assert np.mean(apart) == pytest.approx(4.0, abs=0.7)
        # (each family keeps 1 % of the drift as its own noise: SHARED_NOISE_FLOOR)
        np.testing.assert_allclose(np.asarray(apart), 2 * np.asarray(shared), rtol=0.02)

    def test_shared_drift_on_noiseless_lines_is_no_singular_covariance(self):
        """A noiseless line's variance is the drift's to the last digit: the shared covariance alone
        has rank T - 1 for 2(T - 1) pairs. Each family keeps 1 % of the drift as its own noise: a
        finite chi2, under the one that counts the drift twice."""
        fams = [family(var=(1e-30 + 1e-4,) * 3, name=nm, target=1, fd=sg * 4e6, extra_phase=(0.01, -0.02, 0.005))
                for nm, sg in (("U", 1), ("L", -1))]
        shared, dof = consistency(fams, PHI, TAU, shared_var=1e-4)
        apart, _ = consistency(fams, PHI, TAU)
        assert dof == 3 and np.isfinite(shared) and 0 < shared < apart

    def test_shared_drift_without_effect_on_one_family(self):
        fam = family(extra_phase=(0.0, 0.1, -0.05))
        assert consistency([fam], PHI, TAU, shared_var=1e-2) == consistency([fam], PHI, TAU)

    def test_family_with_one_usable_line_skipped(self):
        chi2, dof = consistency([family(var=(1e-4, 1.0, 1.0))], PHI, TAU, min_snr_db=10.0)
        assert (chi2, dof) == (0.0, -1)


class TestMix:
    def test_candidates_keyed_by_target(self):
        fams = [family(target=0), family(name="U", target=1, fd=5e6, seed=4), family(name="L", target=1, fd=-5e6,
                                                                                       seed=5)]
        out = mix(fams, PHI, 10.0)
        assert sorted(out) == [0, 1]
        assert out[0].df_hz.size == 3 and out[1].df_hz.size == 6
        for obs in out.values():
            np.testing.assert_allclose(wrap_pi(obs.phase_rad + 2 * np.pi * obs.df_hz * TAU), 0.0, atol=1e-9)

    def test_candidate_with_fewer_than_two_lines_left_out(self):
        weak = (1e-4, 1.0, 1.0)  # one line at 40 dB, two at 0 dB
        fams = [family(target=0), family(name="U", target=1, var=weak), family(name="L", target=1, var=weak)]
        out = mix(fams, PHI, 10.0)
        assert list(out) == [0]

    def test_nothing_above_threshold(self):
        assert mix([family(var=(1.0, 1.0, 1.0))], PHI, 10.0) == {}


@pytest.mark.parametrize("seed", range(3))
def test_chi2_is_the_quadratic_form_of_the_pair_covariance(seed):
    """chi2 against a plain solve of the covariance diag(v_i) + v_r (the shared reference line)."""
    rng = np.random.default_rng(seed)
    var = tuple(rng.uniform(1e-4, 1e-2, 3))
    fam = family(var=var, extra_phase=tuple(rng.normal(0, 0.1, 3)), seed=seed)
    chi2, dof = consistency([fam], PHI, TAU)
    r = int(np.argmax(fam.snr_db))
    others = [i for i in range(3) if i != r]
    res = []
    for i in others:
        d = fam.tone_hz[i] - fam.tone_hz[r]
        prod = np.sum(fam.z[:, i] * np.conj(fam.z[:, r]) * np.exp(-2j * np.pi * d * fam.seg_centre_s))
        res.append(wrap_pi(np.angle(prod) + 2 * np.pi * d * TAU - (PHI[fam.tone_hz[i]] - PHI[fam.tone_hz[r]])))
    res = np.array(res)
    cov = np.diag(fam.phase_var[others]) + fam.phase_var[r]
    assert dof == 1
    assert chi2 == pytest.approx(float(res @ np.linalg.solve(cov, res)), rel=1e-12)


def still_lines(tones, ranges, factors, var, seed, segments=1):
    """A still echo's lines on a real receiver, ``sum_k c_k*exp(j*(phi_i - 2*pi*f_i*tau_k))`` with
    the real factors ``c_k`` (``cos(psi)``, any sign), referred to each segment's centre, plus
    complex noise of phase variance ``var`` per line."""
    rng = np.random.default_rng(seed)
    tones = np.asarray(tones, float)
    centres = (np.arange(segments) + 0.5) * 1e-6
    phi = np.array([0.4 * k for k in range(tones.size)])
    z = np.zeros((segments, tones.size), complex)
    for r, c in zip(ranges, factors):
        z += c * np.exp(1j * (phi - 2 * np.pi * np.mod(tones * 2 * r / C, 1.0)))[None, :]
    z = z * np.exp(2j * np.pi * np.mod(np.outer(centres, tones), 1.0))
    amp = np.abs(z).mean(axis=0)
    z = z + amp * np.sqrt(np.asarray(var) * segments) * (rng.standard_normal(z.shape) + 1j * rng.standard_normal(z.shape))
    return LineFamily("S", tones, tones.copy(), z, centres, np.asarray(var, float), 0), dict(zip(tones, phi))


class TestRealness:
    def test_one_still_echo_gives_chi2_of_one_dof(self):
        """Over 2000 noise draws and fadings of either sign, chi2 has mean 1 and its 5 % tail."""
        rng = np.random.default_rng(5)
        chi = []
        for k in range(2000):
            c = rng.uniform(0.2, 1.0) * rng.choice([-1, 1])
            fam, phi = still_lines(TONES, [L_M], [c], (1e-3, 2e-3, 4e-3), k)
            chi.append(realness_chi2(fam, phi, 2 * L_M / C)[0])
        chi = np.asarray(chi)
        assert 0.9 < chi.mean() < 1.1
        assert 0.035 < np.mean(chi > 3.84) < 0.065

    def test_a_sign_flip_between_segments_changes_nothing(self):
        fam, phi = still_lines(TONES, [L_M], [1.0], (1e-8,) * 3, 0, segments=4)
        fam.z[1::2] *= -1.0  # cos(psi) changing sign from segment to segment: the lines sum to ~0
        chi2, dof = realness_chi2(fam, phi, 2 * L_M / C)
        assert dof == 1 and chi2 < 4.0

    def test_two_still_echoes_are_complex_where_their_phases_fit_one_range(self):
        """A second echo 0.8 as large, of the other sign, 1.23 m on: the lines' common phase is far
        from 0 or pi at the range the pairs fit best (the one the chain would report)."""
        fam, phi = still_lines(TONES, [L_M, L_M + 1.23], [1.0, -0.8], (1e-6,) * 3, 1)
        grid = 2 * np.linspace(0, C / 2 / 10e6, 20001) / C
        best = min(grid, key=lambda t: consistency([fam], phi, t)[0])
        assert realness_chi2(fam, phi, best)[0] > 1000

    def test_an_echo_a_whole_pair_period_on_turns_every_line_alike(self):
        """220/730/880 MHz: the pairs' period is c/(2*30 MHz), 4.997 m, and an echo one period on
        turns every line by -2*pi*(220/30 - 7) = -2*pi/3: read at the reported (folded) range its
        lines are complex unless the period it lies on is tried (k = 1; k = -1 turns them the other
        way, and leaves them complex)."""
        tones = (220e6, 730e6, 880e6)
        period = 1 / 30e6
        fam, phi = still_lines(tones, [1.7 + C * period / 2], [0.9], (1e-6,) * 3, 2)
        tau = 2 * 1.7 / C
        assert realness_chi2(fam, phi, tau)[0] > 1000
        assert realness_chi2(fam, phi, tau, aliases=(period, np.array([-1, 0])))[0] > 1000
        chi2, dof = realness_chi2(fam, phi, tau, aliases=(period, np.arange(0, 2)))
        assert chi2 < 10 and dof == 1

    def test_one_line_gives_nothing(self):
        fam, phi = still_lines(TONES, [L_M], [1.0], (1e-4, 1e10, 1e10), 3)
        assert realness_chi2(fam, phi, 2 * L_M / C, min_snr_db=10.0) == (0.0, 0)


def iq_sides(tones, ranges, factors, var, seed, segments=4):
    """An IQ record's still lines: upper ``sum_k c_k*exp(j*(theta_ki + psi_k))`` and lower (the
    mirror, conjugated) ``sum_k c_k*exp(j*(theta_ki - psi_k))``, each echo's carrier phase ``psi_k``
    random per segment, referred to each segment's centre, with complex noise of phase variance
    ``var`` per line."""
    rng = np.random.default_rng(seed)
    tones = np.asarray(tones, float)
    centres = (np.arange(segments) + 0.5) * 1e-6
    phi = np.array([0.4 * k for k in range(tones.size)])
    up = np.zeros((segments, tones.size), complex)
    lo = np.zeros((segments, tones.size), complex)
    for r, c in zip(ranges, factors):
        theta = phi - 2 * np.pi * np.mod(tones * 2 * r / C, 1.0)
        psi = rng.uniform(-np.pi, np.pi, segments)[:, None]
        up += c * np.exp(1j * (theta[None, :] + psi))
        lo += c * np.exp(1j * (theta[None, :] - psi))
    turn = np.exp(2j * np.pi * np.mod(np.outer(centres, tones), 1.0))
    out = []
    for name, z in (("U", up * turn), ("L", lo * turn)):
        amp = np.abs(z).mean(axis=0)
        z = z + amp * np.sqrt(np.asarray(var) * segments) * (rng.standard_normal(z.shape)
                                                              + 1j * rng.standard_normal(z.shape))
        out.append(LineFamily(name, tones, tones.copy(), z, centres, np.asarray(var, float), 0))
    return out[0], out[1], dict(zip(tones, phi))


class TestSidebandProducts:
    def test_one_echo_on_an_iq_record_is_real_whatever_its_carrier(self):
        """Over 1000 draws of noise and carrier phases, the products' common phase gives chi2 of 1 dof."""
        chi = []
        for k in range(1000):
            up, lo, phi = iq_sides(TONES, [L_M], [0.7], (1e-3, 2e-3, 4e-3), k)
            prod = sideband_products(up, lo)
            assert prod is not None and np.allclose(prod.seg_centre_s, 2 * up.seg_centre_s)
            chi.append(realness_chi2(prod, phi, 2 * L_M / C, power=2)[0])
        assert 0.85 < np.mean(chi) < 1.15
        assert 0.03 < np.mean(np.asarray(chi) > 3.84) < 0.07

    def test_two_echoes_on_an_iq_record_are_complex(self):
        up, lo, phi = iq_sides(TONES, [L_M, L_M + 1.23], [1.0, 0.8], (1e-6,) * 3, 1)
        prod = sideband_products(up, lo)
        grid = 2 * np.linspace(0, C / 2 / 10e6, 20001) / C
        best = min(grid, key=lambda t: consistency([up, lo], phi, t)[0])
        assert realness_chi2(prod, phi, best, power=2)[0] > 1000

    def test_no_common_tone_gives_none(self):
        up, lo, _ = iq_sides(TONES, [L_M], [1.0], (1e-4,) * 3, 2)
        lo = LineFamily("L", lo.tone_hz[:1], lo.line_hz[:1], lo.z[:, :1], lo.seg_centre_s, lo.phase_var[:1], 0)
        up = LineFamily("U", up.tone_hz[1:], up.line_hz[1:], up.z[:, 1:], up.seg_centre_s, up.phase_var[1:], 0)
        assert sideband_products(up, lo) is None
