"""Tone planning: choose (or check) a tone set for a required range, precision, band and Doppler.

A plan is judged by what the chain will do with it (the same pair phases, cost and bound):

- **Unambiguous range** ``c/(2*g)``, ``g`` the gcd of the frequency *differences* the chain pairs
  (every pair within a family, :mod:`mtcw_core.ranging.mixing`); single-tone phases would give
  ``c/(2*gcd(f_i))`` but the chain does not use them.
- **Precision**: the Cramér–Rao range sigma at a design line SNR, from the chain's own
  :func:`~mtcw_core.ranging.triangulation.fisher_sigma` (two Doppler families for a mover).
- **Lines kept clear**: a used line is ``f_i`` and ``f_i +- f_d`` for any ``|f_d| <= max Doppler``;
  the modulator's products (``2f_i``, ``3f_i``, ``f_i +- f_j``, ``2f_i +- f_j``, each with its own
  Doppler pair) must not land within ``2*f_d + guard`` of one; tones must be more than
  ``2*f_d + guard`` apart (else ``f_i + f_d`` meets ``f_j - f_d``) and the lowest above
  ``2*f_d + guard`` (else ``f_i - f_d`` meets the carrier line at ``f_d``); the highest line below
  the detector bandwidth.
- **Cycle resolution**: the noiseless cost ``J(L)`` of the chain's ``ml`` resolver
  (:func:`~mtcw_core.ranging.triangulation.cost`, equal weights) over one unambiguous range; its
  largest side peak (1 = a second range fits as well as the true one) and a predicted outlier
  threshold: with line phase variance ``1/SNR`` (the bound), ``J(L0) - J(L_k)`` at each side peak
  ``k`` is Gaussian to first order with a mean and variance computed from the pair geometry; the
  union bound ``sum_k Q(mean_k/sd_k)`` is the probability of a wrong cycle, and the threshold is
  the line SNR (post-integration, as the chain reports it) at which it reaches ``p_outlier``.

:func:`plan_tones` searches tone sets on the reference-clock grid that meet the range and band
and keep the lines clear, and picks the lowest outlier threshold among those meeting the
precision; :func:`check_plan` evaluates any set. Both explain themselves in ``notes``.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from functools import reduce

import numpy as np
from scipy.special import ndtr

from .phase import C
from .ranging.triangulation import Observations, cost, fisher_sigma


@dataclass(frozen=True)
class PlanReport:
    """A tone set judged.

    Attributes
    ----------
    tones_hz : the tones (Hz), ascending
    unambiguous_range_m : ``c/(2*gcd of the differences)`` (m), what the chain's pairs determine
    unambiguous_range_single_tone_m : ``c/(2*gcd of the tones)`` (m), only with single-tone phases
    finest_wavelength_m : ``c/(2*(f_max - f_min))`` (m)
    range_sigma_m : Cramér–Rao range sigma at ``design_snr_db`` (m)
    design_snr_db : post-integration line SNR the sigma is for (dB)
    side_peak : largest side peak of the noiseless cost J over one unambiguous range (main peak 1)
    side_peak_range_m : where it is (m from the true range)
    outlier_threshold_db : line SNR (dB) at which the predicted wrong-cycle probability is ``p_outlier``
    p_outlier : that probability
    conflicts : what breaks the rules (empty: none)
    notes : the explanation, one line each
    """

    tones_hz: tuple[float, ...]
    unambiguous_range_m: float
    unambiguous_range_single_tone_m: float
    finest_wavelength_m: float
    range_sigma_m: float
    design_snr_db: float
    side_peak: float
    side_peak_range_m: float
    outlier_threshold_db: float
    p_outlier: float
    conflicts: tuple[str, ...]
    notes: tuple[str, ...]

    @property
    def ok(self) -> bool:
        return not self.conflicts


def _gcd_hz(values_hz, resolution_hz: float) -> float:
    ints = [int(round(v / resolution_hz)) for v in values_hz]
    return reduce(math.gcd, ints) * resolution_hz


def _pairs(tones_hz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every pair (i, j), i > j, as the chain forms them: indices and differences (Hz)."""
    ij = np.array(list(itertools.combinations(range(tones_hz.size), 2)))[:, ::-1]
    return ij[:, 0], ij[:, 1], tones_hz[ij[:, 0]] - tones_hz[ij[:, 1]]


def cost_profile(tones_hz, step_fraction: float = 1 / 32) -> tuple[np.ndarray, np.ndarray]:
    """The noiseless ``ml`` cost J over one unambiguous range, the true range at 0.

    Returns
    -------
    (l_m, j) : ndarrays, shape (K,): offsets from the true range (m) and J there (equal weights)
    """
    f = np.sort(np.asarray(tones_hz, float))
    _, _, df = _pairs(f)
    obs = Observations(df, np.zeros(df.size), np.ones(df.size))
    lu = C / (2 * _gcd_hz(df, 1.0))
    step = float(np.min(obs.synthetic_wavelengths_m)) * step_fraction
    l_m = np.arange(0.0, lu, step)
    return l_m, cost(obs, l_m)


def _side_peaks(tones_hz) -> tuple[np.ndarray, np.ndarray]:
    """Local maxima of the noiseless J away from the main lobe: ranges (m) and values."""
    f = np.sort(np.asarray(tones_hz, float))
    l_m, j = cost_profile(f)
    lam_min = C / (2 * (f[-1] - f[0]))
    lu = l_m[-1] + (l_m[1] - l_m[0])
    is_max = (j >= np.roll(j, 1)) & (j >= np.roll(j, -1))
    dist = np.minimum(l_m, lu - l_m)
    keep = is_max & (dist > 0.5 * lam_min)
    return l_m[keep], j[keep]


def _outlier_geometry(f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per side peak k: the mean of ``J(L0) - J(L_k)`` and its sd per unit line-phase sd."""
    i, j, df = _pairs(f)
    lk, _ = _side_peaks(f)
    t = 2 * np.pi * df[None, :] * 2 * lk[:, None] / C  # (K, P)
    npair = df.size
    mean = np.sum(1 - np.cos(t), axis=1) / npair
    s = np.sin(t)
    c = np.zeros((lk.size, f.size))
    np.add.at(c.T, i, s.T)
    np.add.at(c.T, j, -s.T)
    return mean, np.sqrt(np.sum(c**2, axis=1)) / npair


def _union_bound(mean: np.ndarray, geom: np.ndarray, line_snr_db) -> np.ndarray:
    v = 10 ** (-np.asarray(line_snr_db, float) / 10)
    z = mean[:, None] / (geom[:, None] * np.sqrt(np.atleast_1d(v))[None, :] + 1e-300)
    return np.minimum(np.sum(ndtr(-z), axis=0), 1.0).reshape(np.shape(line_snr_db))


def outlier_probability(tones_hz, line_snr_db) -> np.ndarray:
    """Predicted probability that ``ml`` picks a wrong cycle (union bound over the side peaks).

    Every line has phase variance ``v = 1/SNR`` (the Cramér–Rao bound at post-integration SNR
    ``N*A^2/(2*sigma^2)``); pair phase ``p = (i, j)`` has noise ``n_i - n_j``. At a side peak
    ``L_k`` (pair phase offsets ``t_p``), ``J(L0) - J(L_k) ~ N(mean_k, v*sum_i c_i^2/P^2)`` with
    ``mean_k = sum_p (1 - cos t_p)/P`` and ``c_i = sum_p sin(t_p)*([i first] - [i second])``.

    Parameters
    ----------
    tones_hz : sequence of float (Hz)
    line_snr_db : float or ndarray, post-integration line SNR (dB), equal for every line
    """
    mean, geom = _outlier_geometry(np.sort(np.asarray(tones_hz, float)))
    return _union_bound(mean, geom, line_snr_db)


def outlier_threshold_db(tones_hz, p_outlier: float = 1e-3) -> float:
    """The line SNR (dB) at which :func:`outlier_probability` falls to ``p_outlier`` (bisection)."""
    mean, geom = _outlier_geometry(np.sort(np.asarray(tones_hz, float)))
    lo, hi = -20.0, 80.0
    if _union_bound(mean, geom, hi) > p_outlier:
        return math.inf
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if _union_bound(mean, geom, mid) > p_outlier:
            lo = mid
        else:
            hi = mid
    return hi


def range_sigma_m(tones_hz, line_snr_db: float, moving: bool = False) -> float:
    """Cramér–Rao range sigma (m) with every line at ``line_snr_db`` (one family; two when moving)."""
    f = np.asarray(tones_hz, float)
    v = np.full(f.size, 10 ** (-line_snr_db / 10))
    fams = 2 if moving else 1
    return fisher_sigma([f] * fams, [v] * fams)


def line_conflicts(tones_hz, max_doppler_hz: float = 0.0, detector_bandwidth_hz: float | None = None,
                   guard_hz: float = 1e6) -> list[str]:
    """Every broken rule of a tone set (module docstring), as readable sentences."""
    f = np.sort(np.asarray(tones_hz, float))
    fd = abs(max_doppler_hz)
    clear = 2 * fd + guard_hz
    out = []
    for a, b in itertools.combinations(f, 2):
        if abs(b - a) <= clear:
            out.append(f"{a / 1e6:g} and {b / 1e6:g} MHz are {abs(b - a) / 1e6:g} MHz apart: "
                       f"need more than 2*Doppler + guard = {clear / 1e6:g} MHz")
    if f[0] <= clear:
        out.append(f"lowest tone {f[0] / 1e6:g} MHz: its line f - f_d meets the carrier line at f_d "
                   f"(need above {clear / 1e6:g} MHz)")
    if detector_bandwidth_hz is not None and f[-1] + fd > detector_bandwidth_hz:
        out.append(f"highest line {(f[-1] + fd) / 1e6:g} MHz is above the detector bandwidth "
                   f"{detector_bandwidth_hz / 1e6:g} MHz")
    top = (detector_bandwidth_hz if detector_bandwidth_hz is not None else math.inf) + fd
    products = []
    for a in range(f.size):
        products += [(2 * f[a], f"2x{f[a] / 1e6:g}"), (3 * f[a], f"3x{f[a] / 1e6:g}")]
        for b in range(f.size):
            if a == b:
                continue
            if a < b:
                products += [(f[a] + f[b], f"{f[a] / 1e6:g}+{f[b] / 1e6:g}"),
                             (abs(f[b] - f[a]), f"{f[b] / 1e6:g}-{f[a] / 1e6:g}")]
            products += [(2 * f[a] + f[b], f"2x{f[a] / 1e6:g}+{f[b] / 1e6:g}"),
                         (abs(2 * f[a] - f[b]), f"|2x{f[a] / 1e6:g}-{f[b] / 1e6:g}|")]
    for p, name in products:
        if p > top:
            continue
        hit = f[np.abs(f - p) <= clear]
        for u in hit:
            out.append(f"product {name} = {p / 1e6:g} MHz lands on the line of {u / 1e6:g} MHz "
                       f"(within {clear / 1e6:g} MHz)")
    return out


def check_plan(tones_hz, *, max_doppler_hz: float = 0.0, detector_bandwidth_hz: float | None = None,
               design_snr_db: float = 30.0, guard_hz: float = 1e6, p_outlier: float = 1e-3,
               resolution_hz: float = 1.0) -> PlanReport:
    """Evaluate a tone set: ranges, precision, clear lines, cost side peaks, outlier threshold.

    Parameters
    ----------
    tones_hz : sequence of float, at least 2 distinct tones (Hz)
    max_doppler_hz : largest |f_d| expected (Hz)
    detector_bandwidth_hz : the detector/digitizer band (Hz), None: not checked
    design_snr_db : post-integration line SNR for the precision (dB)
    guard_hz : extra clearance between lines (Hz)
    p_outlier : wrong-cycle probability that defines the threshold
    resolution_hz : grid on which the gcd is taken (Hz)

    Raises
    ------
    ValueError
        Fewer than 2 tones, a repeated tone or a non-positive one (the message names ``tones_hz``).
    """
    f = np.sort(np.asarray(tones_hz, float))
    if f.size < 2 or np.any(f <= 0) or np.unique(f).size != f.size or not np.all(np.isfinite(f)):
        raise ValueError("tones_hz: need at least 2 distinct positive finite tones")
    _, _, df = _pairs(f)
    g = _gcd_hz(df, resolution_hz)
    g1 = _gcd_hz(f, resolution_hz)
    lu, lu1 = C / (2 * g), C / (2 * g1)
    lam = C / (2 * (f[-1] - f[0]))
    sig = range_sigma_m(f, design_snr_db, moving=max_doppler_hz > 0)
    lk, jk = _side_peaks(f)
    k = int(np.argmax(jk)) if jk.size else -1
    side, side_at = (float(jk[k]), float(min(lk[k], lu - lk[k]))) if k >= 0 else (0.0, 0.0)
    thr = outlier_threshold_db(f, p_outlier)
    conflicts = line_conflicts(f, max_doppler_hz, detector_bandwidth_hz, guard_hz)
    notes = [
        f"tones {', '.join(f'{x / 1e6:g}' for x in f)} MHz",
        f"unambiguous range {lu:.4g} m from the pair differences (gcd {g / 1e6:g} MHz; the chain pairs lines); "
        f"{lu1:.4g} m only with single-tone phases (gcd of the tones {g1 / 1e6:g} MHz)",
        f"finest synthetic wavelength {lam:.4g} m (span {(f[-1] - f[0]) / 1e6:g} MHz); Cramér–Rao range sigma "
        f"{sig:.3g} m at a line SNR of {design_snr_db:g} dB",
        f"cycle-resolution cost J: largest side peak {side:.3f} of the main peak, {side_at:.4g} m from it",
        f"predicted wrong-cycle probability {p_outlier:g} at a line SNR of {thr:.1f} dB (union bound over "
        f"{jk.size} side peaks, phase variance 1/SNR)",
    ]
    notes.append("lines clear: no product on a used line, separations and band as required" if not conflicts
                 else f"{len(conflicts)} conflict(s): " + "; ".join(conflicts[:5]) + (" ..." if len(conflicts) > 5 else ""))
    return PlanReport(tuple(float(x) for x in f), lu, lu1, lam, sig, design_snr_db, side, side_at, thr, p_outlier,
                      tuple(conflicts), tuple(notes))


def plan_tones(*, unambiguous_range_m: float, resolution_m: float, detector_bandwidth_hz: float,
               max_doppler_hz: float = 0.0, grid_hz: float = 1e6, n_tones: int = 4, design_snr_db: float = 30.0,
               guard_hz: float = 1e6, p_outlier: float = 1e-3, candidates: int = 400, seed: int = 0) -> PlanReport:
    """Choose ``n_tones`` tones on the reference-clock grid ``grid_hz``.

    The tones are multiples of ``g``, the largest multiple of ``grid_hz`` not above
    ``c/(2*unambiguous_range_m)``, with differences whose gcd is exactly ``g``; the highest line
    stays inside the detector band, the lowest above ``2*f_d + guard``. Among ``candidates``
    random sets (seeded, so the answer is reproducible) that keep every line clear and reach
    ``resolution_m`` (Cramér–Rao sigma at ``design_snr_db``) the lowest outlier threshold wins,
    then the lower side peak.

    Raises
    ------
    ValueError
        When the requirements cannot be met (the message names the requirement).
    """
    if unambiguous_range_m <= 0 or resolution_m <= 0 or detector_bandwidth_hz <= 0 or grid_hz <= 0:
        raise ValueError("unambiguous_range_m, resolution_m, detector_bandwidth_hz, grid_hz: must be > 0")
    if n_tones < 2 or n_tones > 16:
        raise ValueError("n_tones: 2..16")
    fd = abs(max_doppler_hz)
    g = grid_hz * math.floor(C / (2 * unambiguous_range_m) / grid_hz)
    if g <= 0:
        raise ValueError(f"unambiguous_range_m: {unambiguous_range_m:g} m needs a tone spacing below the grid "
                         f"({grid_hz / 1e6:g} MHz gives at most {C / (2 * grid_hz):.4g} m)")
    k_lo = math.floor((2 * fd + guard_hz) / g) + 1
    k_hi = math.floor((detector_bandwidth_hz - fd) / g)
    if k_hi - k_lo + 1 < n_tones:
        raise ValueError(f"detector_bandwidth_hz: {detector_bandwidth_hz / 1e6:g} MHz holds only {max(k_hi - k_lo + 1, 0)} "
                         f"tones on the {g / 1e6:g} MHz spacing the range needs, above the Doppler clearance")
    rng = np.random.default_rng(seed)
    best, best_key, seen = None, None, set()
    for _ in range(candidates):
        ks = {k_hi}
        ks.add(int(rng.integers(k_lo, k_lo + max(1, (k_hi - k_lo) // 8) + 1)))  # a wide span: precision
        while len(ks) < n_tones:
            ks.add(int(rng.integers(k_lo, k_hi + 1)))
        key = tuple(sorted(ks))
        if key in seen or len(key) != n_tones:
            continue
        seen.add(key)
        if reduce(math.gcd, [k - key[0] for k in key[1:]]) != 1:
            continue
        f = np.asarray(key, float) * g
        if line_conflicts(f, fd, detector_bandwidth_hz, guard_hz):
            continue
        if range_sigma_m(f, design_snr_db, moving=fd > 0) > resolution_m:
            continue
        _, jk = _side_peaks(f)
        side = float(jk.max()) if jk.size else 0.0
        thr = outlier_threshold_db(f, p_outlier)
        rank = (thr, side)
        if best_key is None or rank < best_key:
            best, best_key = f, rank
    if best is None:
        raise ValueError(f"resolution_m: no {n_tones}-tone set on the {g / 1e6:g} MHz spacing within "
                         f"{detector_bandwidth_hz / 1e6:g} MHz keeps its lines clear and reaches {resolution_m:g} m at "
                         f"{design_snr_db:g} dB (more tones, a wider band or a higher SNR)")
    rep = check_plan(best, max_doppler_hz=fd, detector_bandwidth_hz=detector_bandwidth_hz, design_snr_db=design_snr_db,
                     guard_hz=guard_hz, p_outlier=p_outlier)
    why = (f"chosen from {len(seen)} sets of {n_tones} tones on a {g / 1e6:g} MHz spacing (the largest multiple of "
           f"the {grid_hz / 1e6:g} MHz grid giving >= {unambiguous_range_m:g} m), between {k_lo * g / 1e6:g} and "
           f"{k_hi * g / 1e6:g} MHz: lowest predicted outlier threshold among those with clear lines and sigma <= "
           f"{resolution_m:g} m")
    return PlanReport(**{**rep.__dict__, "notes": (why, *rep.notes)})


__all__ = ["PlanReport", "check_plan", "plan_tones", "cost_profile", "outlier_probability", "outlier_threshold_db",
           "range_sigma_m", "line_conflicts"]
