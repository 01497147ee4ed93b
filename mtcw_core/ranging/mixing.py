"""Stage ``mix``: IF mixing of the extracted lines into pair observations.

A *family* (:class:`~mtcw_core.dsp.extract.LineFamily`) is a set of lines, one per tone, that share the same nuisance phase:

- ``S`` (static / self-beat): lines at ``f_i``. For a static target the two LO x sideband
  beats fall here with the common factor ``2*cos(psi)``; the echo self-beat always does and
  survives beyond the coherence length.
- ``U``: ``f_i + f_d`` (LO x upper sideband, common phase ``+psi``).
- ``L``: ``f_i - f_d`` (LO x lower sideband, ``-psi``; conjugated when it folds through 0 Hz).

Within a family the pair product ``z_i * conj(z_j)`` cancels the nuisance phase (carrier,
laser phase noise, the sign of ``cos(psi)``), leaving ``(phi_i - phi_j) - 2*pi*(f_i - f_j)*tau``.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..dsp.extract import LineFamily
from ..phase import wrap_pi
from .triangulation import Observations


@lru_cache(maxsize=32)
def _pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Every pair (a, b) with b < a < n, in the order of a double loop over a then b (read-only)."""
    a, b = np.tril_indices(n, -1)
    a.setflags(write=False)
    b.setflags(write=False)
    return a, b


def pair_observations(
    families: list[LineFamily], tone_phases_rad: dict[float, float], min_snr_db: float = -np.inf
) -> Observations:
    """IF mixing: every pair of lines within each family, averaged over segments.

    Parameters
    ----------
    families : list of LineFamily
    tone_phases_rad : dict tone_hz -> phase (rad) of the RF drive (from calibration)
    min_snr_db : float
        Lines below this post-integration SNR are left out.
    """
    df, ph, w = [], [], []
    for fam in families:
        ok = np.flatnonzero(fam.snr_db >= min_snr_db)
        if ok.size < 2:
            continue
        # every pair (a, b), b < a, in the order of a double loop over a then b
        a_, b_ = _pairs(ok.size)
        i, j = ok[a_], ok[b_]
        swap = fam.tone_hz[i] < fam.tone_hz[j]  # the higher tone first
        i, j = np.where(swap, j, i), np.where(swap, i, j)
        fi, fj = fam.tone_hz[i], fam.tone_hz[j]
        d = fi - fj
        # (S, pairs): z_i * conj(z_j) * exp(-2j*pi*d*t_s), summed over the segments
        prod = np.sum(fam.z[:, i] * np.conj(fam.z[:, j]) * np.exp((-2j * np.pi * d)[None, :] * fam.seg_centre_s[:, None]),
                      axis=0)
        rf = np.array([tone_phases_rad[f] for f in fam.tone_hz])
        phase = np.angle(prod) - (rf[i] - rf[j])
        df.append(d)
        ph.append(wrap_pi(phase))
        w.append(1.0 / (fam.phase_var[i] * fam.phase_var[j]))
    if not df:
        return Observations(np.empty(0), np.empty(0), np.empty(0))
    return Observations(np.concatenate(df).astype(float), np.concatenate(ph).astype(float),
                        np.concatenate(w).astype(float))


#: :func:`consistency` with a shared drift takes each family's own line noise as at least this
#: share of the drift's variance: how far two families' readings of one tone's drift may differ
SHARED_NOISE_FLOOR = 0.01


def consistency(families: list[LineFamily], tone_phases_rad: dict[float, float], tau_s: float,
                min_snr_db: float = -np.inf, shared_var: float = 0.0) -> tuple[float, int]:
    """Chi-square of the line phases against one range, and its degrees of freedom.

    Per family, every used line is paired with the family's strongest line ``r``; the pair
    phases ``d_i`` (segment-averaged, calibrated) should equal ``-2*pi*(f_i - f_r)*tau`` with
    covariance ``diag(v_i) + v_r`` (the reference line's noise is shared). ``chi2/dof`` near 1
    means one target explains the phases; far above, either several static targets share the
    lines (blended) or something the noise floor does not show (quantisation, spurs) moves them.

    ``shared_var`` (rad^2): a phase error per tone that every family of the target carries alike --
    the tones' own phase drift, which moves the calibration every line is read against (a mover's
    ``f_i + f_d`` and ``f_i - f_d`` lines turn together: the envelope probe's scene 33007). Each
    family's ``phase_var`` holds it already; this adds its covariance across the families, which
    counted apart would weigh it as independent draws: twice the evidence from a mover's two
    sidebands. Each family's own noise beyond it is floored at :data:`SHARED_NOISE_FLOOR` of it.
    0: the families independent.

    Parameters
    ----------
    tau_s : float, the solution's round-trip delay ``tau0 + 2*L/c`` (s)

    Returns
    -------
    (chi2, dof); dof counts independent pair phases minus one (the range)
    """
    parts = [p for p in (_pair_residuals(f, tone_phases_rad, tau_s, min_snr_db) for f in families) if p is not None]
    dof = sum(res.size for res, *_ in parts) - 1
    if shared_var > 0 and len(parts) > 1:
        res = np.concatenate([r for r, *_ in parts])
        cov = shared_var * _tone_incidence(parts)
        # each family's own noise beyond the drift, at least SHARED_NOISE_FLOOR of it (a noiseless
        # line's variance is the drift's to the last digit: the U and L lines would then have to
        # agree exactly, and the covariance, of rank T - 1 for 2(T - 1) pairs, is singular)
        floor = SHARED_NOISE_FLOOR * shared_var
        at = 0
        for r, v, vr, _ in parts:
            blk = slice(at, at + r.size)
            cov[blk, blk] += np.diag(np.maximum(v - shared_var, floor)) + max(vr - shared_var, floor)
            at += r.size
        return float(res @ np.linalg.solve(cov, res)), dof
    chi2 = 0.0
    for res, v, vr, _ in parts:
        if np.all(v > 0):
            # res' (diag(v) + vr*1 1')^-1 res in closed form (Sherman-Morrison): no solve per call
            u = res / v
            chi2 += float(res @ u - vr * np.sum(u) ** 2 / (1.0 + vr * np.sum(1.0 / v)))
        else:
            chi2 += float(res @ np.linalg.solve(np.diag(v) + vr, res))
    return chi2, dof


def realness_chi2(fam: LineFamily, tone_phases_rad: dict[float, float], tau_s: float, min_snr_db: float = -np.inf,
                  tone_var: float = 0.0, aliases: tuple[float, np.ndarray] = (0.0, np.zeros(1)), power: int = 1
                  ) -> tuple[float, int]:
    """Chi-square (1 dof) of a static family's common phase against the real envelope of one echo.

    On one photodiode or a balanced pair with an unmodulated LO, a still echo's two LO x sideband
    beats fall on ``f_i`` together as ``2*cos(psi)*exp(j*(phi_i - 2*pi*f_i*tau))`` (physics.md) and
    its self-beat as a positive multiple of the same: referred to one range, every line is real,
    its common phase 0 modulo pi, whatever the fading. The pair phases (:func:`consistency`) cancel
    that common phase; a blend of two echoes with real factors ``c_1, c_2`` adds
    ``c_1*exp(j*theta_1i) + c_2*exp(j*theta_2i)``, complex, whose phases may still fit one wrong range
    and whose sizes one target (the envelope probe's scene 36853: two still echoes 0.4 dB apart on
    three tones, a common phase of -1.0 rad, ranged 1.14 m off at 4 mm). The line phases against
    ``phi_i - 2*pi*f_i*tau_s`` (each segment's at its centre; the strongest line's read from its
    segments' squares, so a sign of ``cos(psi)`` that changes between segments cancels nothing, the
    others through their pair with it) fitted by ``beta + 2*pi*f_i*dtau`` with weights ``1/(v_i +
    tone_var)`` (``v_i`` with the noises' product a sum of ``S`` segments' products carries, ``S*v_i*v_r``
    for the reference line's squares, ``2*S*v_i*v_r`` for a pair with it): ``chi2 = beta^2/var(beta)`` with ``beta`` wrapped to ``[-pi/2, pi/2)`` -- the
    intercept at 0 Hz, whose variance the tones' spread against their distance from 0 Hz sets.

    The pairs fix the delay only modulo their period ``1/g`` (``g`` the gcd of the tone spacings):
    an echo at ``tau_s + k/g`` turns every line by the same ``-2*pi*f_r*k/g`` against the model at
    ``tau_s`` (``f_r`` any used tone: the others lie whole multiples of ``g`` from it), the pairs see
    nothing, and ``beta`` moves by it. ``aliases``: ``(1/g, k)`` (s; the integers ``k`` the range may take,
    shape (K,)): the smallest chi2 over them is taken -- where the tones sit on ``g``'s grid
    (``f_r*k/g`` whole) the test keeps its full strength, elsewhere it weakens to the lattice the
    ``k`` reach (the envelope probe's scene 36853: 220/730/880 MHz, ``g`` 30 MHz, ``beta``
    known modulo pi/3 only, and that blend fits a real echo 5 m on within its noise).

    ``power`` 2: ``fam`` holds an IQ record's sideband products (:func:`sideband_products`), one
    echo's ``|c|^2*exp(2j*theta_i)`` whatever its carrier's phase: their phases, halved, are read
    alike (a product's sign is known, so none is squared away), with a quarter of their variance.

    Returns
    -------
    (chi2, dof): 0, 0 with fewer than two used lines
    """
    phases = {f: power * p for f, p in tone_phases_rad.items()}
    parts = _pair_residuals(fam, phases, power * tau_s, min_snr_db)
    if parts is None:
        return 0.0, 0
    res, v, vr, (fi, fr) = parts
    r = int(np.flatnonzero(fam.tone_hz == fr)[0])
    model = -2 * np.pi * fr * (power * tau_s - fam.seg_centre_s) + phases[fr]
    own = 0.5 * float(np.angle(np.sum((fam.z[:, r] * np.exp(-1j * model)) ** (3 - power))))  # (-pi/2, pi/2]
    rho = np.concatenate([[own], own + res / power])
    f = np.concatenate([[fr], fi])
    # a product of two noisy lines summed over S segments carries their noises' product too, S*v_a*v_b
    # beyond v_a + v_b (the reference line's squares, the pairs with it): weak per segment, it dominates
    segs = fam.z.shape[0]
    line_var = np.concatenate([[vr * (1 + segs * vr) if power == 1 else vr], v * (1 + 2 * segs * vr)])
    w = 1.0 / (line_var / power**2 + tone_var)
    if not np.all(np.isfinite(w)):
        return 0.0, 0
    fbar = float(np.sum(w * f) / np.sum(w))
    u = f - fbar
    slope = float(np.sum(w * u * rho) / np.sum(w * u * u))
    beta = float(np.sum(w * rho) / np.sum(w)) - slope * fbar
    var = 1.0 / float(np.sum(w)) + fbar**2 / float(np.sum(w * u * u))
    # at tau_s + k/g every line reads -2*pi*f_r*k/g (mod 2*pi) against the model at tau_s: undone
    period, k = aliases
    beta = beta + 2 * np.pi * ((fr * period * np.asarray(k, float)) % 1.0)
    beta = (beta + np.pi / 2) % np.pi - np.pi / 2
    return float(np.min(beta**2)) / var, 1


def sideband_products(upper: LineFamily, lower: LineFamily) -> LineFamily | None:
    """An IQ record's still lines, each tone's upper times its lower line segment by segment: one
    echo's ``exp(j*(theta_i + psi))`` times ``exp(j*(theta_i - psi))`` (the lower conjugated as
    a mirror image), ``|c|^2*exp(2j*theta_i)`` -- the carrier's phase gone, the tone's own phase
    doubled. Referred to each segment's centre ``t_s`` they turn as ``2*f_i*t_s``: the family's
    ``seg_centre_s`` is ``2*t_s``; ``phase_var`` the two lines' summed, with their noises' product
    over the ``S`` segments, ``2*S*v_u*v_l`` (:func:`realness_chi2` with ``power`` 2). None where no
    tone has both lines or the segments differ."""
    both, iu, il = np.intersect1d(upper.tone_hz, lower.tone_hz, return_indices=True)
    if both.size == 0 or not np.array_equal(upper.seg_centre_s, lower.seg_centre_s):
        return None
    vu, vl = upper.phase_var[iu], lower.phase_var[il]
    return LineFamily("UL", both, both.copy(), upper.z[:, iu] * lower.z[:, il], 2 * upper.seg_centre_s,
                      vu + vl + 2 * upper.z.shape[0] * vu * vl, upper.target)


def _pair_residuals(fam: LineFamily, tone_phases_rad: dict[float, float], tau_s: float, min_snr_db: float
                    ) -> tuple[np.ndarray, np.ndarray, float, tuple[np.ndarray, float]] | None:
    """:func:`consistency`'s pairs of one family: the residuals (rad, shape (O,)) of its used lines
    against its strongest ``r`` at ``tau_s``, their variances ``v`` (O,) and ``v_r``, and the tones
    (Hz) of the pairs, ``(f_i (O,), f_r)``; None with fewer than two used lines."""
    ok = np.flatnonzero(fam.snr_db >= min_snr_db)
    if ok.size < 2:
        return None
    r = ok[np.argmax(fam.snr_db[ok])]
    others = ok[ok != r]
    d = fam.tone_hz[others] - fam.tone_hz[r]  # (O,)
    prod = np.sum(fam.z[:, others] * np.conj(fam.z[:, r])[:, None]
                  * np.exp((-2j * np.pi * d)[None, :] * fam.seg_centre_s[:, None]), axis=0)
    rf = np.array([tone_phases_rad[f] for f in fam.tone_hz])
    model = -2 * np.pi * d * tau_s + (rf[others] - rf[r])
    res = np.angle(prod * np.exp(-1j * model))
    return res, fam.phase_var[others], float(fam.phase_var[r]), (fam.tone_hz[others], float(fam.tone_hz[r]))


def _tone_incidence(parts: list[tuple]) -> np.ndarray:
    """``E E'`` for the pairs of :func:`_pair_residuals` (``parts``): ``E`` has a row per pair, +1 at
    its tone and -1 at its family's strongest, so two pairs share ``[f_i = f_j] - [f_i = r_j] -
    [r_i = f_j] + [r_i = r_j]``; shape (P, P), the covariance of one unit of phase drift per tone."""
    tone = np.concatenate([fi for *_, (fi, _) in parts])
    ref = np.concatenate([np.full(fi.size, fr) for *_, (fi, fr) in parts])

    def same(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return (a[:, None] == b[None, :]).astype(np.float64)

    return same(tone, tone) - same(tone, ref) - same(ref, tone) + same(ref, ref)


def mix(families: list[LineFamily], tone_phases_rad: dict[float, float], min_snr_db: float) -> dict[int, Observations]:
    """The stage: pair observations of every target candidate (key: ``LineFamily.target``).

    A candidate with no pair of lines above ``min_snr_db`` gets no entry.
    """
    out: dict[int, Observations] = {}
    for k in sorted({f.target for f in families}):
        obs = pair_observations([f for f in families if f.target == k], tone_phases_rad, min_snr_db)
        if obs.df_hz.size:
            out[k] = obs
    return out

