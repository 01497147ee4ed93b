"""Line extraction per family and IF mixing into pair observations.

A *family* is a set of lines, one per tone, that share the same nuisance phase:

- ``S`` (static / self-beat): lines at ``f_i``. For a static target the two LO x sideband
  beats fall here with the common factor ``2*cos(psi)``; the echo self-beat always does and
  survives beyond the coherence length.
- ``U``: ``f_i + f_d`` (LO x upper sideband, common phase ``+psi``).
- ``L``: ``f_i - f_d`` (LO x lower sideband, ``-psi``; conjugated when it folds through 0 Hz).

Within a family the pair product ``z_i * conj(z_j)`` cancels the nuisance phase (carrier,
laser phase noise, the sign of ``cos(psi)``), leaving ``(phi_i - phi_j) - 2*pi*(f_i - f_j)*tau``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..ranging.triangulation import Observations


@dataclass
class LineFamily:
    """Extracted lines of one family.

    Attributes
    ----------
    name : str
        ``"S"``, ``"U"`` or ``"L"``.
    tone_hz : ndarray, shape (T,)
        The tone each line belongs to (Hz).
    line_hz : ndarray, shape (T,)
        Where the line was measured (Hz, signed for IQ).
    z : ndarray, shape (S, T), complex
        Complex amplitude per segment, referred to each segment's centre, conjugated where the
        line is a mirror image so that every line carries ``+ (phi_i - 2*pi*f_i*tau)``.
    seg_centre_s : ndarray, shape (S,)
        Segment centres relative to the record's first sample (s).
    phase_var : ndarray, shape (T,)
        Variance of each line's whole-record phase (rad^2) from the local noise floor.
    """

    name: str
    tone_hz: np.ndarray
    line_hz: np.ndarray
    z: np.ndarray
    seg_centre_s: np.ndarray
    phase_var: np.ndarray

    @property
    def snr_db(self) -> np.ndarray:
        """Post-integration line SNR, ``1/phase_var`` in dB (``N*A^2/(2*sigma^2)`` for a real tone)."""
        return -10 * np.log10(self.phase_var)


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
                ph.append(float(np.angle(np.exp(1j * phase))))
                w.append(1.0 / (fam.phase_var[i] * fam.phase_var[j]))
    return Observations(np.asarray(df, float), np.asarray(ph, float), np.asarray(w, float))
