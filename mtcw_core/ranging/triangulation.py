"""Cycle resolution ("triangulation"): range from wrapped pair phases.

An observation is a pair phase ``dphi`` at frequency difference ``df > 0`` whose model is
``dphi = -2*pi*df*tau(L) (mod 2*pi)``, ``tau(L) = tau0 + 2*L/c``. Two methods:

- ``ml``: maximise ``J(L) = sum_l w_l*cos(dphi_l + 2*pi*df_l*tau(L))`` on a grid fine enough
  not to miss the peak (a fixed fraction of the finest synthetic wavelength), then refine with
  a bounded scalar optimiser to full precision.
- ``seed``: the dissertation's candidate matrix (sections 4.2.2 and 5.2.4, Fig. 18) with the
  plain row standard deviation, reproduced as published.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import minimize_scalar

from ..phase import C, unambiguous_range, wrap_pi

if TYPE_CHECKING:  # the lines' noise rings, read in the extract stage (which imports this module's users)
    from ..dsp.extract import NoiseRing


@dataclass(frozen=True)
class Observations:
    """Pair observations of one target.

    Attributes
    ----------
    df_hz : ndarray, shape (P,)
        Frequency differences (Hz), > 0.
    phase_rad : ndarray, shape (P,)
        Calibrated wrapped phases (rad), model ``-2*pi*df*tau(L)``.
    weight : ndarray, shape (P,)
        Non-negative weights (``1/(var_i*var_j)`` for a pair of lines).
    """

    df_hz: np.ndarray
    phase_rad: np.ndarray
    weight: np.ndarray

    @property
    def synthetic_wavelengths_m(self) -> np.ndarray:
        return C / (2 * self.df_hz)


@dataclass(frozen=True)
class RangeSolution:
    range_m: float
    margin: float  # 1 - J(second peak)/J(best), in [0, 1]
    residual_rms_rad: float
    near_edge: bool
    seed_sigma_k_m: float | None = None  # the dissertation's row standard deviation (seed only)
    #: the next-best cycles (m), best first: the local maxima of J (ml) or rows (seed) that come
    #: closest, for the caller to weigh by the line phases' likelihood
    alternatives_m: tuple[float, ...] = ()


#: runners-up of the cycle resolution handed to the caller (their likelihood decides a flag)
ALTERNATIVES = 4
#: :func:`resolve_ml` refines at most this many of the grid's highest local maxima
MAX_REFINED = 16


def _cost(obs: Observations, tau0_s: float):
    k = 2 * np.pi * obs.df_hz
    wsum = float(np.sum(obs.weight))

    def j(l_m):
        l_m = np.atleast_1d(l_m)
        arg = obs.phase_rad[None, :] + k[None, :] * (tau0_s + 2 * l_m[:, None] / C)
        return (np.cos(arg) @ obs.weight) / wsum

    return j


def cost(obs: Observations, l_m, tau0_s: float = 0.0) -> np.ndarray:
    """The ``ml`` cost J(L) at ranges ``l_m`` (m): 1 where every pair phase agrees; shape (len(l_m),)."""
    return _cost(obs, tau0_s)(l_m)


def grid_cost(obs: Observations, tau0_s: float, lo_m: float, step_m: float, count: int) -> np.ndarray:
    """J(L) on the uniform grid ``L_g = lo_m + g*step_m``, ``g < count``, shape (count,).

    The same cost as :func:`cost`, as one complex matrix product: with ``g = a*B + b``,
    ``cos(theta_l + g*delta_l) = Re(exp(j*theta_l) * exp(j*a*B*delta_l) * exp(j*b*delta_l))``, so
    ``J`` reshaped to (A, B) is ``Re(C @ F.T)`` with ``C[a, l] = w_l*exp(j*(theta_l + a*B*delta_l))``
    and ``F[b, l] = exp(j*b*delta_l)``: ``(A + B)*P`` exponentials instead of ``count*P`` cosines
    (P pairs). Every factor's phase is taken in cycles reduced modulo 1 in float64 first; J
    agrees with :func:`cost` to ~1e-12 (the rounding of the argument at thousands of cycles, in
    either form).
    """
    if count <= 0:
        return np.empty(0)
    w = obs.weight / float(np.sum(obs.weight))
    # cycles: theta_l/(2*pi) at L = lo, and the advance per grid point
    theta = np.mod(obs.phase_rad / (2 * np.pi) + obs.df_hz * (tau0_s + 2 * lo_m / C), 1.0)  # (P,)
    delta = obs.df_hz * (2 * step_m / C)  # (P,)
    b_count = int(math.ceil(math.sqrt(count)))
    a_count = -(-count // b_count)
    a = np.arange(a_count, dtype=np.float64)[:, None] * b_count
    rows = w * np.exp(2j * np.pi * np.mod(theta + np.mod(a * delta, 1.0), 1.0))  # (A, P)
    fine = np.exp(2j * np.pi * np.mod(np.arange(b_count, dtype=np.float64)[:, None] * delta, 1.0))  # (B, P)
    return (rows @ fine.T).real.reshape(-1)[:count]


def _newton_polish(obs: Observations, tau0_s: float, l_m, iterations: int = 4, limit_m: float | None = None
                   ) -> np.ndarray:
    """Newton steps on dJ/dL = 0 with analytic derivatives, from each start in ``l_m`` at once.

    A start within half a grid step of a peak (the grid has ``points_per_cycle`` >= 4 points per
    finest synthetic wavelength) lies well inside the peak's concave part, where Newton's method
    reaches it to float precision in a few steps. A start where J is not concave, or a step longer
    than ``limit_m`` (default: a thousandth of the finest synthetic wavelength), stops that start
    where it is (the caller checks).

    Returns
    -------
    ndarray, shape (len(l_m),), the refined ranges (m)
    """
    l_m = np.atleast_1d(np.asarray(l_m, dtype=float)).copy()
    k = 2 * np.pi * obs.df_hz * 2 / C  # d(arg)/dL, shape (P,)
    limit = 1e-3 * float(np.min(obs.synthetic_wavelengths_m)) if limit_m is None else limit_m
    active = np.ones(l_m.size, bool)
    wk, wk2 = obs.weight * k, obs.weight * k**2
    for _ in range(iterations):
        arg = obs.phase_rad[None, :] + 2 * np.pi * obs.df_hz[None, :] * (tau0_s + 2 * l_m[:, None] / C)
        d1 = -(np.sin(arg) @ wk)
        d2 = -(np.cos(arg) @ wk2)
        concave = d2 < 0
        step = -d1 / np.where(concave, d2, -1.0)
        active &= concave & (np.abs(step) <= limit)
        l_m[active] += step[active]
        # a start stops once its step is below float precision: each start walks as it would alone
        active &= np.abs(step) > 1e-15 * np.abs(l_m) + 1e-18
        if not active.any():
            break  # converged (or stopped) everywhere
    return l_m


def _peaks(obs: Observations, tau0_s: float, j, starts_m: np.ndarray, step_m: float, xatol_m: float) -> np.ndarray:
    """The local maximum of J near each grid point of ``starts_m`` (shape (S,), m): Newton's method
    from the grid points, all at once (:func:`_newton_polish`), or, for a start that does not
    stay within its grid cell, the bounded scalar search over that cell (then polished)."""
    starts = np.atleast_1d(np.asarray(starts_m, dtype=float))
    best = _newton_polish(obs, tau0_s, starts, iterations=8, limit_m=step_m)
    for i in np.flatnonzero(np.abs(best - starts) > step_m):
        s0 = float(starts[i])
        res = minimize_scalar(lambda l: -j(l)[0], bounds=(s0 - step_m, s0 + step_m), method="bounded",
                              options={"xatol": xatol_m})
        best[i] = _newton_polish(obs, tau0_s, float(res.x))[0]
    return best


def _residual(obs: Observations, tau0_s: float, l_m: float) -> float:
    r = wrap_pi(obs.phase_rad + 2 * np.pi * obs.df_hz * (tau0_s + 2 * l_m / C))
    return float(np.sqrt(np.sum(obs.weight * r**2) / np.sum(obs.weight)))


def resolve_ml(
    obs: Observations, tau0_s: float, interval_m: tuple[float, float], points_per_cycle: int = 16
) -> RangeSolution:
    """Maximum of the weighted cost J(L) over ``interval_m``.

    The grid step is ``Lambda_min/points_per_cycle`` (Lambda_min the finest synthetic
    wavelength): with 16 points J is sampled within 2 % of its peak value, so the coarse
    maximum cannot miss the true cycle at useful SNR; the grid's highest local maxima are each
    refined and the highest refined peak is the range (two cycles within the grid's sampling loss
    of each other are ranked by J itself).
    """
    lo, hi = interval_m
    step = float(np.min(obs.synthetic_wavelengths_m)) / points_per_cycle
    grid = np.arange(lo, hi + step, step)
    j = _cost(obs, tau0_s)
    # evaluate in blocks to bound memory for long intervals; np.arange's points are
    # grid[0] + g*(grid[1] - grid[0]), which the blocks follow
    delta = float(grid[1] - grid[0]) if grid.size > 1 else step
    vals = np.concatenate([grid_cost(obs, tau0_s, float(grid[i]), delta, min(65536, grid.size - i))
                           for i in range(0, grid.size, 65536)])
    is_max = np.zeros(vals.size, bool)
    is_max[1:-1] = (vals[1:-1] >= vals[:-2]) & (vals[1:-1] >= vals[2:])
    # every local maximum the grid may have sampled up to its sampling loss under the top -- J =
    # sum w*cos(...)/sum(w) loses up to ~(pi/ppc)^2/2 half a step off a peak: ~2 % at 16 points
    # per cycle, ~8 % at ``fast``'s 8 -- refined to its own peak, and the highest is the range (the
    # grid's order is not the cost's: the envelope probe's scene 6729, two cycles 0.9 % apart; the
    # loss was scaled by sum(w) again, on a cost already divided by it, so that every maximum up to
    # MAX_REFINED was refined: found in review)
    loss = 0.75 * (np.pi / points_per_cycle) ** 2
    ib = int(np.argmax(vals))
    idx = np.union1d(np.flatnonzero(is_max & (vals >= vals[ib] - loss)), [ib])
    # with the grid's next highest maxima, the runners-up's likely candidates, in the same pass
    tops = np.union1d(np.flatnonzero(is_max), [ib])
    top = np.union1d(idx[np.argsort(vals[idx])[::-1][:MAX_REFINED]],
                     tops[np.argsort(vals[tops])[::-1][:ALTERNATIVES + 1]])
    peaks = _peaks(obs, tau0_s, j, grid[top], step, 1e-9)
    jp = j(peaks)
    best, jbest = float(peaks[int(np.argmax(jp))]), float(np.max(jp))
    # J is periodic in the unambiguous range: a peak refined across an end of the interval is
    # the same solution, reported inside it (never a jump of one synthetic wavelength)
    period = unambiguous_range(obs.df_hz)
    if best < lo and best + period < hi + step:
        best += period
    elif best >= hi and best - period >= lo - step:
        best -= period
    # the runners-up: local maxima at least half the finest synthetic wavelength away (across the
    # ends, within one period, the same solution is no runner-up), each refined to its own peak
    half = 0.5 * float(np.min(obs.synthetic_wavelengths_m))
    dist = np.abs(grid - best)
    if hi - lo <= period + step:
        dist = np.minimum(dist % period, period - dist % period)
    # -- the grid's highest, and every one it may have sampled up to its sampling loss under the top
    # (the solution's candidates, refined already), ranked by J itself: ``fast``'s 8 points per cycle
    # had sampled a runner-up 0.3 chi2 from the solution below four others, and its odds were left out
    # (the envelope probe's 50844: a mover's wrong cycle at odds 8e-4, 1109 sigmas off, unflagged)
    far = np.flatnonzero(is_max & (dist > half))
    order = far[np.argsort(vals[far])[::-1]]
    done = np.isin(top, far)
    more = np.setdiff1d(order[:ALTERNATIVES], top[done])
    cand = np.concatenate([peaks[done], _peaks(obs, tau0_s, j, grid[more], step, 1e-6 * step) if more.size else []])
    kept: list[float] = []
    for a in cand[np.argsort(j(cand))[::-1]]:  # two grid maxima refined onto one peak count once
        if len(kept) < ALTERNATIVES and all(abs(a - b) > 1e-3 * step for b in kept):
            kept.append(float(a))
    alts = tuple(kept)
    j2 = float(np.max(j(np.array(alts)))) if alts else -1.0
    margin = float(np.clip(1 - max(j2, 0.0) / jbest, 0, 1)) if jbest > 0 else 0.0
    edge = min(best - lo, hi - best) < half
    return RangeSolution(best, margin, _residual(obs, tau0_s, best), bool(edge), alternatives_m=alts)


def candidate_matrix(obs: Observations, tau0_s: float, max_range_m: float, min_range_m: float = 0.0
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The seed's candidate matrix (see :func:`resolve_seed`), its row spreads and the wavelengths.

    Returns
    -------
    m : ndarray, shape (K, P), candidate ranges (m); column 0 the finest observation's cycles
    sigma_k : ndarray, shape (K,), plain row standard deviation (m)
    lam : ndarray, shape (P,), the columns' synthetic wavelengths (m), finest first
    """
    lam = obs.synthetic_wavelengths_m
    # residual range in the first cycle, after removing the internal delay tau0
    r = lam * np.mod(-obs.phase_rad / (2 * np.pi) - obs.df_hz * tau0_s, 1.0)
    order = np.argsort(lam)  # finest (largest df) first
    lam, r = lam[order], r[order]
    n0 = math.floor((min_range_m - r[0]) / lam[0])
    n_max = math.ceil((max_range_m - r[0]) / lam[0])
    col1 = r[0] + np.arange(n0, n_max + 1) * lam[0]
    m = np.empty((col1.size, lam.size))
    m[:, 0] = col1
    for i in range(1, lam.size):
        m[:, i] = r[i] + np.rint((col1 - r[i]) / lam[i]) * lam[i]
    return m, np.std(m, axis=1), lam  # plain, unweighted, ddof = 0 as published


def resolve_seed(obs: Observations, tau0_s: float, max_range_m: float, min_range_m: float = 0.0) -> RangeSolution:
    """The dissertation's candidate-matrix triangulation.

    For every observation l with synthetic wavelength ``Lambda_l`` the residual ``r_l`` is the
    range its wrapped phase gives in the first cycle. Column 1 holds the finest observation's
    candidates ``r_1 + n*Lambda_1`` for ``n = 0..n_max`` (``n_max`` from the largest expected
    range); every other column holds, per row, its own candidate nearest to column 1. The row
    of least plain standard deviation gives the range as its column-1 value.
    """
    m, sigma_k, lam = candidate_matrix(obs, tau0_s, max_range_m, min_range_m)
    col1 = m[:, 0]
    k = int(np.argmin(sigma_k))
    s_sorted = np.sort(sigma_k)
    margin = float(1 - s_sorted[0] / s_sorted[1]) if s_sorted.size > 1 and s_sorted[1] > 0 else 1.0
    best = float(col1[k])
    half = 0.5 * lam[0]
    edge = min(best - min_range_m, max_range_m - best) < half
    alts = tuple(float(col1[i]) for i in np.argsort(sigma_k)[1:1 + ALTERNATIVES])
    return RangeSolution(best, margin, _residual(obs, tau0_s, best), bool(edge), float(sigma_k[k]), alts)


def tone_phase_sigma(freqs_by_family: list[np.ndarray], var_by_family: list[np.ndarray], sigma_rad: float) -> float:
    """Range sigma (m) that an rms error ``sigma_rad`` of each tone's phase in force (the RF
    synthesizers' drift since calibration, independent per tone) gives the range of
    :func:`fisher_sigma`'s weighted fit.

    The fit is ``L = sum_F sum_i a_Fi * phi_Fi`` with ``a_Fi = w_i*(k_i - kbar_F)/I`` (``w = 1/v``,
    ``kbar_F`` the family's weighted mean ``k``, ``I`` the information); a tone's error enters
    every family that holds its line alike (each line carries ``+phi_i``), so the variance is
    ``sigma_rad^2 * sum_t (sum_F a_Ft)^2`` over the tones ``t``. 0 when ``sigma_rad`` is 0.

    Parameters
    ----------
    freqs_by_family, var_by_family : per family, its used lines' tones (Hz) and phase variances (rad^2)
    sigma_rad : float, rad
    """
    if sigma_rad <= 0:
        return 0.0
    gains: dict[float, float] = {}
    info = 0.0
    for f, v in zip(freqs_by_family, var_by_family):
        if f.size < 2:
            continue
        k, w = 4 * np.pi * f / C, 1 / v
        dk = k - np.sum(w * k) / np.sum(w)
        info += float(np.sum(w * dk**2))
        for tone, g in zip(f.tolist(), (w * dk).tolist()):
            gains[tone] = gains.get(tone, 0.0) + g
    if info <= 0:
        return math.inf
    return sigma_rad * math.sqrt(sum(g * g for g in gains.values())) / info


def fisher_sigma(freqs_by_family: list[np.ndarray], var_by_family: list[np.ndarray]) -> float:
    """Range sigma (m) from per-line phase variances, a common unknown phase per family.

    ``I = sum_F [sum_i k_i^2/v_i - (sum_i k_i/v_i)^2 / sum_i 1/v_i]``, ``k_i = 4*pi*f_i/c``;
    the Cramér–Rao bound when the variances are the true ones.
    """
    info = 0.0
    for f, v in zip(freqs_by_family, var_by_family):
        if f.size < 2:
            continue
        k = 4 * np.pi * f / C
        w = 1 / v
        info += float(np.sum(w * k**2) - np.sum(w * k) ** 2 / np.sum(w))
    return 1 / math.sqrt(info) if info > 0 else math.inf


def range_sigma(freqs_by_family: list[np.ndarray], var_by_family: list[np.ndarray],
                rings_by_family: list[NoiseRing | None]) -> float:
    """Range sigma (m) of the pair estimator: the first of :func:`range_sigmas`."""
    return range_sigmas(freqs_by_family, var_by_family, rings_by_family)[0]


def range_sigmas(freqs_by_family: list[np.ndarray], var_by_family: list[np.ndarray],
                 rings_by_family: list[NoiseRing | None]) -> tuple[float, float]:
    """Range sigma (m) of the pair estimator (:func:`resolve_ml`) where the lines' noise moves
    together, and what it would be were the lines independent (the same weights, ``C = diag(v)``).

    The pair phases weighted ``1/(v_i*v_j)`` put the range at ``sum_i g_i*phi_i`` with, per family,
    ``g_i = S_F*(k_i - kbar_F)/(v_i*sum_F S_F*I_F)`` (``kbar_F`` the family's ``1/v``-weighted mean
    of ``k = 4*pi*f/c``, ``S_F = sum 1/v`` over its lines, ``I_F`` its information, as in
    :func:`fisher_sigma`): with independent noise its variance is the bound's where the families'
    ``S_F`` are alike, and more where they are not (the pairs weigh the quieter family ``S_F``
    times more than the bound would). The lines' noise is not independent where the laser's phase
    noise dominates the floor: the carrier's own noise turns every line of a family alike (``g``
    sums to 0 in each: it cancels), and the carrier's noise at a tone's offset moves that tone's
    upper and lower lines' phases oppositely (it cancels in their mean, which the two families
    weigh alike). The variance is then ``g' Cphi g``, ``Cphi`` the lines' phase covariance read
    from their noise rings (:attr:`~mtcw_core.dsp.extract.LineFamily.ring`: one row per offset,
    each line's column in its own frame and in phase units, so that ``Cphi = Re(ring' conj(ring))/W``
    where the noise is circular), each pair's coherence scaled back up by what the window took
    from rows a fraction of a bin apart (``NoiseRing.shift``). Read from W offsets, ``g' Cphi g``
    has W's scatter: it is kept above ``1/W`` of its value were the noise independent (how far a
    cancellation can be read from W offsets). It is read twice, over the whole ring (the noise
    floor's +-256 record bins: many rows, little scatter) and over its rows nearest the lines
    (``NoiseRing.near``: where a floor rises toward the line, the pedestal of a strong echo's line
    a few MHz off, the whole ring reads it low), and the larger is taken. Without rings the noise is
    taken as independent: ``Cphi = diag(v)``.

    Parameters
    ----------
    freqs_by_family, var_by_family : per family, the used lines' tones (Hz) and phase variances
        (rad^2), shapes (T_F,)
    rings_by_family : per family, the used lines' :class:`~mtcw_core.dsp.extract.NoiseRing`
        (W rows, T_F columns), or None: then the noise is taken as independent

    Returns
    -------
    (sigma, independent) : m; both inf where the lines carry no range information
    """
    rings = (not any(r is None for r in rings_by_family)
             and len({r.rows.shape[0] for r in rings_by_family}) == 1)
    info, gs, vs, rs, ss = 0.0, [], [], [], []
    for f, v, r in zip(freqs_by_family, var_by_family, rings_by_family):
        if f.size < 2:
            continue
        k = 4 * np.pi * f / C
        w = 1 / v
        # the family's pairs sum to S*(its GLS normal equation), S = sum(1/v): families weigh S*I_F
        scale = float(np.sum(w))
        info += scale * float(np.sum(w * k**2) - np.sum(w * k) ** 2 / scale)
        gs.append(scale * (k - np.sum(w * k) / scale) * w)
        vs.append(v)
        if rings:
            rs.append(r.rows)
            ss.append(r.shift)
    if info <= 0:
        return math.inf, math.inf
    g = np.concatenate(gs) / info
    independent = math.sqrt(float(np.sum(g**2 * np.concatenate(vs))))
    if not rings:
        return independent, independent
    ring, shift = np.concatenate(rs, axis=1), np.concatenate(ss)
    # two lines' rows stand at offsets up to a bin apart: the window decorrelated them that much
    decorrelated = np.exp(-np.subtract.outer(shift, shift) ** 2)
    var = 0.0
    for rows in (ring, ring[rings_by_family[0].near]):  # the whole ring, and its rows nearest the lines
        if rows.shape[0] == 0:
            continue
        c = np.real(rows.T @ rows.conj()) / rows.shape[0] / decorrelated  # (T, T): phase covariance, rad^2
        # the estimate's own scatter (W rows) bounds how far the lines' noise can be taken to cancel
        var = max(var, float(g @ c @ g), float(np.sum(g**2 * np.diag(c))) / rows.shape[0])
    return math.sqrt(var), independent
