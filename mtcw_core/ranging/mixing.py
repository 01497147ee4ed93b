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

import numpy as np

from ..dsp.extract import LineFamily
from ..phase import wrap_pi
from .triangulation import Observations


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
        for a in range(ok.size):
            for b in range(a):
                i, j = ok[a], ok[b]
                fi, fj = fam.tone_hz[i], fam.tone_hz[j]
                if fi < fj:
                    i, j, fi, fj = j, i, fj, fi
                d = fi - fj
                prod = np.sum(fam.z[:, i] * np.conj(fam.z[:, j]) * np.exp(-2j * np.pi * d * fam.seg_centre_s))
                phase = np.angle(prod) - (tone_phases_rad[fi] - tone_phases_rad[fj])
                df.append(d)
                ph.append(float(wrap_pi(phase)))
                w.append(1.0 / (fam.phase_var[i] * fam.phase_var[j]))
    return Observations(np.asarray(df, float), np.asarray(ph, float), np.asarray(w, float))


def consistency(families: list[LineFamily], tone_phases_rad: dict[float, float], tau_s: float,
                min_snr_db: float = -np.inf) -> tuple[float, int]:
    """Chi-square of the line phases against one range, and its degrees of freedom.

    Per family, every used line is paired with the family's strongest line ``r``; the pair
    phases ``d_i`` (segment-averaged, calibrated) should equal ``-2*pi*(f_i - f_r)*tau`` with
    covariance ``diag(v_i) + v_r`` (the reference line's noise is shared). ``chi2/dof`` near 1
    means one target explains the phases; far above, either several static targets share the
    lines (blended) or something the noise floor does not show (quantisation, spurs) moves them.

    Parameters
    ----------
    tau_s : float, the solution's round-trip delay ``tau0 + 2*L/c`` (s)

    Returns
    -------
    (chi2, dof); dof counts independent pair phases minus one (the range)
    """
    chi2, dof = 0.0, -1
    for fam in families:
        ok = np.flatnonzero(fam.snr_db >= min_snr_db)
        if ok.size < 2:
            continue
        r = ok[np.argmax(fam.snr_db[ok])]
        others = ok[ok != r]
        res = []
        for i in others:
            d = fam.tone_hz[i] - fam.tone_hz[r]
            prod = np.sum(fam.z[:, i] * np.conj(fam.z[:, r]) * np.exp(-2j * np.pi * d * fam.seg_centre_s))
            model = -2 * np.pi * d * tau_s + (tone_phases_rad[fam.tone_hz[i]] - tone_phases_rad[fam.tone_hz[r]])
            res.append(np.angle(prod * np.exp(-1j * model)))
        res = np.asarray(res)
        cov = np.diag(fam.phase_var[others]) + fam.phase_var[r]
        chi2 += float(res @ np.linalg.solve(cov, res))
        dof += others.size
    return chi2, dof


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

