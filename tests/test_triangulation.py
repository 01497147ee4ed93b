"""mtcw_core.ranging.triangulation: unambiguous range, cycle resolution (ml, seed), Fisher sigma."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from mtcw_core.dsp.extract import NoiseRing
from mtcw_core.phase import C, wrap_pi
from mtcw_core.ranging.triangulation import (Observations, _newton_polish, cost, fisher_sigma, grid_cost, range_sigma,
                                             resolve_ml, resolve_seed, tone_phase_sigma, unambiguous_range)

TONES = np.array([100e6, 170e6, 260e6])
PAIRS = [(i, j) for i, j in itertools.combinations(range(3), 2)]
DF = np.array([TONES[j] - TONES[i] for i, j in PAIRS])  # 70, 160, 90 MHz
L_UNAMB = C / (2 * 10e6)  # gcd 10 MHz: 14.99 m


def observations(range_m, tau0_s=0.0, line_noise=None, rng=None):
    """Pair phases -2*pi*df*tau (wrapped) from line phases -2*pi*f_i*tau (+ noise of variance v_i)."""
    tau = tau0_s + 2 * range_m / C
    ph = -2 * np.pi * np.mod(TONES * tau, 1.0)
    if line_noise is not None:
        ph = ph + rng.standard_normal(3) * np.sqrt(line_noise)
    v = np.ones(3) if line_noise is None else np.asarray(line_noise)
    phase = np.array([wrap_pi(ph[j] - ph[i]) for i, j in PAIRS])
    w = np.array([1 / (v[i] * v[j]) for i, j in PAIRS])
    return Observations(DF.copy(), phase, w)


class TestObservations:
    def test_synthetic_wavelengths(self):
        obs = observations(1.0)
        np.testing.assert_allclose(obs.synthetic_wavelengths_m, C / (2 * DF))


class TestUnambiguousRange:
    @pytest.mark.parametrize("df,g", [([70e6, 90e6, 160e6], 10e6), ([200e6], 200e6), ([30e6, 45e6], 15e6),
                                      ([410e6, 200e6], 10e6), ([7e6, 11e6], 1e6)])
    def test_c_over_2_gcd(self, df, g):
        assert unambiguous_range(df) == pytest.approx(C / (2 * g), rel=1e-15)

    def test_resolution_grid(self):
        assert unambiguous_range([1.5, 2.5], resolution_hz=0.5) == pytest.approx(C / (2 * 0.5))

    def test_near_integers_rounded_to_the_grid(self):
        assert unambiguous_range([70e6 + 1e-4, 90e6 - 1e-4]) == pytest.approx(C / (2 * 10e6))

    def test_scalar(self):
        assert unambiguous_range(150e6) == pytest.approx(C / 3e8)


class TestResolveMl:
    @pytest.mark.parametrize("range_m", [0.0123, 0.3, 3.7, 7.77, 11.111, 14.5])
    def test_noiseless_exact(self, range_m):
        sol = resolve_ml(observations(range_m), 0.0, (-0.05, L_UNAMB - 0.05))
        assert sol.range_m == pytest.approx(range_m, abs=1e-9)
        assert sol.residual_rms_rad == pytest.approx(0.0, abs=1e-8)
        assert 0.0 < sol.margin <= 1.0

    def test_internal_delay_removed(self):
        tau0 = 12.345e-9
        sol = resolve_ml(observations(4.2, tau0), tau0, (0.0, L_UNAMB))
        assert sol.range_m == pytest.approx(4.2, abs=1e-9)

    def test_periodic_in_the_unambiguous_range(self):
        """A search interval one period further gives the same range plus one period."""
        sol = resolve_ml(observations(3.7), 0.0, (L_UNAMB, 2 * L_UNAMB))
        assert sol.range_m == pytest.approx(3.7 + L_UNAMB, abs=1e-9)

    def test_slightly_negative_range(self):
        sol = resolve_ml(observations(-0.02), 0.0, (-0.05, L_UNAMB - 0.05))
        assert sol.range_m == pytest.approx(-0.02, abs=1e-9)
        assert sol.near_edge  # within half the finest synthetic wavelength of the interval's end

    def test_far_from_edge(self):
        assert not resolve_ml(observations(7.0), 0.0, (0.0, L_UNAMB)).near_edge

    def test_sigma_matches_fisher_bound(self):
        """Monte Carlo: the spread of the ML range in line-phase noise is near the Fisher sigma."""
        rng = np.random.default_rng(0)
        v = np.array([1e-3, 2e-3, 1.5e-3])
        est = [resolve_ml(observations(5.0, line_noise=v, rng=rng), 0.0, (0.0, L_UNAMB)).range_m
               for _ in range(300)]
        sig = fisher_sigma([TONES], [v])
        assert np.std(est) / sig == pytest.approx(1.0, abs=0.2)
        assert abs(np.mean(est) - 5.0) < 4 * sig / np.sqrt(300)


class TestResolveSeed:
    @pytest.mark.parametrize("range_m", [0.0123, 0.3, 3.7, 7.77, 11.111, 14.5])
    def test_noiseless_exact(self, range_m):
        sol = resolve_seed(observations(range_m), 0.0, L_UNAMB)
        assert sol.range_m == pytest.approx(range_m, abs=1e-9)
        assert sol.seed_sigma_k_m == pytest.approx(0.0, abs=1e-9)

    def test_internal_delay_removed(self):
        tau0 = 3.3e-9
        sol = resolve_seed(observations(9.1, tau0), tau0, L_UNAMB)
        assert sol.range_m == pytest.approx(9.1, abs=1e-9)

    def test_row_spread_is_the_plain_std(self):
        """With phase noise the quality figure is the published ddof=0 std of the chosen row."""
        obs = observations(6.0, line_noise=np.full(3, 1e-3), rng=np.random.default_rng(1))
        sol = resolve_seed(obs, 0.0, L_UNAMB)
        lam = C / (2 * obs.df_hz)
        r = lam * np.mod(-obs.phase_rad / (2 * np.pi), 1.0)
        fine = int(np.argmin(lam))
        row = [sol.range_m] + [r[i] + np.rint((sol.range_m - r[i]) / lam[i]) * lam[i]
                               for i in range(3) if i != fine]
        assert sol.seed_sigma_k_m == pytest.approx(np.std(row), rel=1e-9)
        assert abs(sol.range_m - 6.0) < 0.05


class TestFisherSigma:
    def test_two_lines_is_the_phase_difference_bound(self):
        """One family (one unknown common phase), lines f1, f2 with phase variances v1, v2: the
        pair phase d = phi2 - phi1 has variance v1 + v2 and slope dd/dL = -2*pi*(f2 - f1)*2/c,
        so sigma_L = sqrt(v1 + v2) / (2*pi*|f2 - f1|*2/c)."""
        f = np.array([100e6, 270e6])
        v1, v2 = 2e-4, 5e-4
        want = math.sqrt(v1 + v2) / (2 * math.pi * 170e6 * 2 / C)
        assert fisher_sigma([f], [np.array([v1, v2])]) == pytest.approx(want, rel=1e-12)

    def test_families_add_information(self):
        f, v = np.array([100e6, 270e6]), np.array([1e-4, 1e-4])
        one = fisher_sigma([f], [v])
        assert fisher_sigma([f, f], [v, v]) == pytest.approx(one / math.sqrt(2), rel=1e-12)

    def test_single_line_family_carries_nothing(self):
        assert fisher_sigma([np.array([100e6])], [np.array([1e-4])]) == math.inf
        assert fisher_sigma([], []) == math.inf

    def test_common_shift_of_frequencies_irrelevant(self):
        """The common phase per family absorbs a common frequency shift (a Doppler family)."""
        f, v = TONES, np.array([1e-4, 3e-4, 2e-4])
        assert fisher_sigma([f + 5e6], [v]) == pytest.approx(fisher_sigma([f], [v]), rel=1e-9)


def _circular(rng, shape) -> np.ndarray:
    """Circular complex normal samples of unit mean power."""
    return (rng.normal(size=shape) + 1j * rng.normal(size=shape)) / math.sqrt(2)


def _rings(rows_by_family, shifts=None, near=None):
    """NoiseRings of the families' rows (every row near, no shift unless given)."""
    w = rows_by_family[0].shape[0]
    near = np.ones(w, bool) if near is None else near
    shifts = shifts or [np.zeros(r.shape[1]) for r in rows_by_family]
    return [NoiseRing(r, sh, near) for r, sh in zip(rows_by_family, shifts)]


def _pair_estimator_weights(freqs_by_family, var_by_family) -> np.ndarray:
    """The range (m) the pair estimator weighted 1/(v_i v_j) puts on each line's phase, written out
    from its normal equation: L = sum over pairs w_ij (k_i - k_j)(phi_i - phi_j) / sum w_ij (k_i - k_j)^2."""
    num_rows, den = [], 0.0
    for f, v in zip(freqs_by_family, var_by_family):
        k = 4 * np.pi * f / C
        row = np.zeros(f.size)
        for i, j in itertools.combinations(range(f.size), 2):
            w = 1 / (v[i] * v[j])
            row[i] += w * (k[i] - k[j])
            row[j] -= w * (k[i] - k[j])
            den += w * (k[i] - k[j]) ** 2
        num_rows.append(row)
    return np.concatenate(num_rows) / den


class TestRangeSigma:
    """The pair estimator's own variance from the lines' noise rings (:func:`range_sigma`)."""

    V = np.array([1e-4, 3e-4, 2e-4])

    def test_independent_noise_gives_the_bound(self):
        """White noise, independent line to line: the estimator's variance is the bound's."""
        rng = np.random.default_rng(1)
        rings = [_circular(rng, (20000, 3)) * np.sqrt(self.V) for _ in range(2)]
        got = range_sigma([TONES, TONES], [self.V, self.V], _rings(rings))
        assert got == pytest.approx(fisher_sigma([TONES, TONES], [self.V, self.V]), rel=0.03)

    def test_without_rings_it_is_the_bound_for_families_alike(self):
        assert range_sigma([TONES], [self.V], [None]) == pytest.approx(fisher_sigma([TONES], [self.V]),
                                                                               rel=1e-12)
        assert range_sigma([TONES, TONES + 5e6], [self.V, self.V], [None, None]) == pytest.approx(
            fisher_sigma([TONES, TONES], [self.V, self.V]), rel=1e-9)

    def test_families_unalike_weigh_as_the_pairs_do_not_as_the_bound(self):
        """A family 4x noisier: its pairs weigh 1/16 as much, where the bound weighs it 1/4; the
        estimator's variance (independent noise) is then above the bound, and is what is reported."""
        g = _pair_estimator_weights([TONES, TONES], [self.V, 4 * self.V])
        want = math.sqrt(np.sum(g**2 * np.concatenate([self.V, 4 * self.V])))
        got = range_sigma([TONES, TONES], [self.V, 4 * self.V], [None, None])
        assert got == pytest.approx(want, rel=1e-9)
        assert got > 1.02 * fisher_sigma([TONES, TONES], [self.V, 4 * self.V])

    def test_noise_that_turns_a_family_alike_cancels(self):
        """The carrier's own phase noise turns every line of a family by one angle: the pair
        phases cancel it, so only the small white part is left (not the ring's whole floor)."""
        rng = np.random.default_rng(2)
        white = self.V / 100
        v = 1e-4 + white  # each line's floor: mostly the common turn
        rings = [_circular(rng, (20000, 1)) * 1e-2 + _circular(rng, (20000, 3)) * np.sqrt(white)]
        g = _pair_estimator_weights([TONES], [v])
        want = math.sqrt(np.sum(g**2 * white))
        assert range_sigma([TONES], [v], _rings(rings)) == pytest.approx(want, rel=0.05)
        assert want < 0.2 * fisher_sigma([TONES], [v])

    def test_a_tones_upper_and_lower_lines_moved_oppositely_cancel_in_their_mean(self):
        """The carrier's noise at a tone's offset moves the upper line's phase one way and the
        (conjugated) lower line's the other: the two families' ranges err oppositely."""
        rng = np.random.default_rng(3)
        pm = _circular(rng, (20000, 3)) * np.sqrt(self.V)
        white_u, white_l = (_circular(rng, (20000, 3)) * np.sqrt(self.V / 100) for _ in range(2))
        got = range_sigma([TONES, TONES], [self.V, self.V], _rings([pm + white_u, -pm + white_l]))
        bound = fisher_sigma([TONES, TONES], [self.V, self.V])
        assert got == pytest.approx(bound * 0.1, rel=0.05)

    def test_noise_that_moves_the_lines_like_a_range_shift_is_counted_in_full(self):
        """One phasor moving each line's phase in proportion to its weight (a neighbour's pedestal
        turned by its own tone phases can): the range error is its projection, far above the
        bound."""
        rng = np.random.default_rng(4)
        shape = np.array([1.0, -0.2, -0.8])
        rings = [_circular(rng, (20000, 1)) * shape * 0.05 + _circular(rng, (20000, 3)) * np.sqrt(self.V / 100)]
        g = _pair_estimator_weights([TONES], [self.V])
        want = math.sqrt((g @ (shape * 0.05)) ** 2 + np.sum(g**2 * self.V / 100))
        assert range_sigma([TONES], [self.V], _rings(rings)) == pytest.approx(want, rel=0.03)
        assert want > 3 * fisher_sigma([TONES], [self.V])

    def test_rows_a_fraction_of_a_bin_apart_are_taken_as_the_window_decorrelated_them(self):
        """Two lines whose rows stand half a bin apart in offset: the window keeps their noise
        exp(-(s_i - s_j)^2) as coherent; the coherence read is scaled back up by that."""
        rng = np.random.default_rng(5)
        f, v = TONES[:2], np.array([1e-4, 1e-4])
        shift = np.array([0.0, 0.2])
        keep = math.exp(-0.04)
        c = _circular(rng, (40000, 1))
        rings = [np.concatenate([c, keep * c + math.sqrt(1 - keep**2) * _circular(rng, (40000, 1))], axis=1)
                 * 1e-2]
        # the lines' noise is in truth one phasor (common to the family: cancelled); read as the
        # window left it, 4 % of its variance would seem to move the range (0.2 of the bound)
        got = range_sigma([f], [v], _rings(rings, [shift]))
        assert got < 0.1 * fisher_sigma([f], [v])
        assert range_sigma([f], [v], _rings(rings)) > 0.15 * fisher_sigma([f], [v])

    def test_a_floor_rising_toward_the_lines_is_read_where_it_is_highest(self):
        """A neighbour's pedestal: in the rows nearest the lines, noise 9x the far rows' that moves
        the lines together like a range shift. The whole ring's mean reads it diluted; the near
        rows read it whole, and the larger is taken."""
        rng = np.random.default_rng(8)
        shape = np.array([1.0, -0.2, -0.8]) * 0.02
        near = np.zeros(2000, bool)
        near[:200] = True
        rows = _circular(rng, (2000, 3)) * np.sqrt(self.V)
        rows[near] += _circular(rng, (200, 1)) * shape * 3
        g = _pair_estimator_weights([TONES], [self.V])
        want = math.sqrt(np.sum(g**2 * self.V) + (g @ shape * 3) ** 2)
        got = range_sigma([TONES], [self.V], _rings([rows], near=near))
        assert got == pytest.approx(want, rel=0.1)
        assert range_sigma([TONES], [self.V], _rings([rows])) < 0.7 * want  # the whole ring alone

    def test_the_weights_are_the_pair_estimators(self):
        """The weights range_sigma projects on are the 1/(v_i v_j) pair estimator's (its normal
        equation written out): one line's noise alone gives that line's weight times its sigma."""
        rng = np.random.default_rng(6)
        g = _pair_estimator_weights([TONES, TONES], [self.V, 2 * self.V])
        for line in range(6):
            noise = np.zeros((20000, 6), complex)
            noise[:, line] = _circular(rng, 20000) * 0.01
            got = range_sigma([TONES, TONES], [self.V, 2 * self.V], _rings([noise[:, :3], noise[:, 3:]]))
            assert got == pytest.approx(abs(g[line]) * 0.01, rel=0.03)


class TestTonePhaseSigma:
    """An rms error of each tone's phase in force (synthesizer drift since calibration)."""

    def test_one_family_of_equal_lines_is_the_bound_at_that_variance(self):
        """Lines of equal noise: the fit is unweighted, and a per-tone error sigma moves it as much
        as line noise of that variance would -- the Fisher sigma at variance sigma^2."""
        f, sig = np.array([20e6, 500e6, 700e6, 950e6]), 0.01
        want = fisher_sigma([f], [np.full(4, sig**2)])
        assert tone_phase_sigma([f], [np.full(4, 3e-5)], sig) == pytest.approx(want, rel=1e-12)

    def test_a_tones_error_enters_every_family_alike(self):
        """Two families (a mover's U and L) of the same tones: line noise averages over them
        (1/sqrt(2)), a tone's own error does not -- it moves both families' lines alike."""
        f, v = np.array([100e6, 270e6, 500e6]), np.array([1e-4, 2e-4, 1e-4])
        one = tone_phase_sigma([f], [v], 0.02)
        assert tone_phase_sigma([f, f], [v, v], 0.02) == pytest.approx(one, rel=1e-12)
        assert tone_phase_sigma([f], [v], 0.0) == 0.0

    def test_against_the_weighted_fit_itself(self):
        """Monte Carlo: per-tone errors through the weighted least-squares fit of the lines' phases
        (one range, one phase per family: ``phi = k*L + c_F``, solved by ``lstsq``) of two families
        with unequal noise; the range's spread is the formula's."""
        rng = np.random.default_rng(3)
        tones = np.array([20e6, 500e6, 700e6, 950e6])
        f = [tones, tones[1:]]
        v = [np.array([4e-4, 1e-4, 2e-4, 1e-4]), np.array([3e-4, 1e-4, 5e-5])]
        rows = [(4 * np.pi * t / C, fam, np.searchsorted(tones, t), 1 / math.sqrt(var))
                for fam, (ff, vv) in enumerate(zip(f, v)) for t, var in zip(ff, vv)]
        design = np.array([[k * s, s * (fam == 0), s * (fam == 1)] for k, fam, _, s in rows])
        sig, draws = 0.01, 20000
        errs = rng.normal(0.0, sig, (len(tones), draws))  # one error per tone, shared by the families
        phases = np.array([errs[i] * s for _, _, i, s in rows])  # weighted, (lines, draws)
        fit_l = np.linalg.lstsq(design, phases, rcond=None)[0][0]
        assert np.std(fit_l) == pytest.approx(tone_phase_sigma(f, v, sig), rel=0.02)


@pytest.mark.parametrize("seed", range(5))
def test_ml_peak_and_runners_up_are_the_costs_own_maxima(seed):
    """resolve_ml's range (Newton from the grid) is the maximum of J to 1e-9 m against a dense
    scan of its cell, and each runner-up is a local maximum (J lower on both sides)."""
    rng = np.random.default_rng(seed)
    truth = rng.uniform(0.2, 5.0)
    noisy = wrap_pi(-2 * np.pi * DF * (2 * truth / C) + rng.normal(0, 0.3, DF.size))
    obs = Observations(DF.copy(), noisy, np.ones(DF.size))
    sol = resolve_ml(obs, 0.0, (0.0, 6.0), 16)
    lam = float(np.min(obs.synthetic_wavelengths_m))
    dense = np.linspace(sol.range_m - lam / 16, sol.range_m + lam / 16, 20001)
    j = cost(obs, dense)
    assert abs(dense[np.argmax(j)] - sol.range_m) < 1e-9 + (dense[1] - dense[0])
    for alt in sol.alternatives_m:
        ja, jl, jr = cost(obs, [alt, alt - 1e-6 * lam, alt + 1e-6 * lam])
        assert ja >= jl and ja >= jr


@pytest.mark.parametrize("seed", range(4))
def test_grid_cost_is_the_cost_on_the_grid(seed):
    """The factorised grid evaluation of J against the cosines written out plainly, on grids of
    10^2-10^5 points (far from their start too: the phases there are thousands of cycles)."""
    rng = np.random.default_rng(seed)
    p = int(rng.integers(1, 16))
    df = rng.uniform(1e6, 2e9, p)
    phase, w = rng.uniform(-np.pi, np.pi, p), rng.uniform(0.1, 3.0, p)
    obs = Observations(df, phase, w)
    tau0, lo = float(rng.uniform(0, 1e-8)), float(rng.uniform(-1, 1))
    step = float(np.min(obs.synthetic_wavelengths_m)) / 16
    count = int(10 ** rng.uniform(2, 5))
    got = grid_cost(obs, tau0, lo, step, count)
    lm = lo + step * np.arange(count)
    want = np.array([np.sum(w * np.cos(phase + 2 * np.pi * df * (tau0 + 2 * l / C))) / np.sum(w) for l in lm[::97]])
    assert got.shape == (count,)
    np.testing.assert_allclose(got[::97], want, rtol=0, atol=1e-9)


def test_newton_from_many_starts_is_each_start_alone():
    """Newton steps from several starts at once walk each start exactly as it would alone."""
    rng = np.random.default_rng(7)
    obs = Observations(DF.copy(), wrap_pi(-2 * np.pi * DF * (2 * 2.3 / C) + rng.normal(0, 0.3, 3)), np.ones(3))
    lam = float(np.min(obs.synthetic_wavelengths_m))
    starts = rng.uniform(0, 6, 40)
    together = _newton_polish(obs, 0.0, starts, iterations=8, limit_m=lam / 16)
    alone = [float(_newton_polish(obs, 0.0, s, iterations=8, limit_m=lam / 16)[0]) for s in starts]
    np.testing.assert_array_equal(together, alone)


@pytest.mark.parametrize("ppc", [8, 16])
def test_ml_range_is_the_highest_peak_not_the_grids(ppc):
    """Two cycles 0.9 % apart in J (the envelope probe's scene 6729: 400/720/730 MHz, pairs 320,
    330 and 10 MHz): at 8 points per cycle (``fast``) the grid sampled a lower peak higher (13.19
    m; at 16 another, 14.11 m), and the range was that peak refined, the highest (13.65 m) among
    its runners-up.
    The range is the highest of the refined peaks, whatever the grid."""
    obs = Observations(np.array([3.2e8, 3.3e8, 1e7]), np.array([-0.8861, -0.3523, 0.5338]),
                       np.array([2284730.99, 2255638.49, 1902372.65]))
    sol = resolve_ml(obs, 0.0, (-0.05, 14.9396229), ppc)
    assert sol.range_m == pytest.approx(13.6515, abs=1e-3)
    assert all(cost(obs, [sol.range_m])[0] >= cost(obs, [a])[0] for a in sol.alternatives_m)
    assert any(abs(a - 13.1905) < 1e-3 for a in sol.alternatives_m)


def test_runners_up_are_the_highest_refined_peaks_not_the_grids():
    """A mover's pair phases on 230/350/820 MHz (the envelope probe's 50844, ``fast``): the cycle
    1.27 m away fits within 0.3 chi2 of the solution, but at 8 points per cycle the grid sampled it
    below four other maxima, so it was no runner-up and the point's cycle odds were 8e-4 -- a wrong
    cycle 1109 sigmas off, unflagged. The runners-up are the highest refined peaks, whatever the
    grid: the same near-equal cycle is among them at 8 and 16 points per cycle, first."""
    obs = Observations(np.array([1.2e8, 5.9e8, 4.7e8, 1.2e8, 5.9e8, 4.7e8]),
                       np.array([2.22721, 0.84858, -1.37863, 2.29250, 0.90318, -1.38933]),
                       np.array([501951.0, 1110785.0, 3745431.0, 295925.0, 875736.0, 3150642.0]))
    for ppc in (8, 16):
        sol = resolve_ml(obs, 0.0, (-0.05, 14.9396229), ppc)
        assert sol.range_m == pytest.approx(4.5361, abs=1e-3)
        assert sol.alternatives_m[0] == pytest.approx(5.8100, abs=1e-3), sol.alternatives_m
        j = cost(obs, list(sol.alternatives_m))
        assert np.all(np.diff(j) <= 0)  # ranked by J itself
        assert sol.margin < 0.01


@pytest.mark.parametrize("range_m", [-0.047, 0.01, L_UNAMB - 0.06, L_UNAMB - 0.0505])
def test_a_peak_at_an_end_of_the_interval_is_not_its_own_runner_up(range_m):
    """A range within a grid step of the interval's ends (one period): its peak refined across an
    end is reported inside it, and the grid's samples by that end are the same solution, not a
    runner-up (a first version counted them: margin ~0, the same range among the alternatives,
    ``cycle_ambiguous`` -- found in review)."""
    sol = resolve_ml(observations(range_m), 0.0, (-0.05, L_UNAMB - 0.05))
    assert sol.range_m == pytest.approx(range_m if range_m >= -0.05 else range_m + L_UNAMB, abs=1e-9)
    assert sol.margin > 0.02
    lam = float(np.min(observations(range_m).synthetic_wavelengths_m))
    for a in sol.alternatives_m:
        d = abs(a - sol.range_m) % L_UNAMB
        assert min(d, L_UNAMB - d) > lam / 2
