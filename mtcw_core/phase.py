"""Exact phase arithmetic, and the one speed of light.

Phases are carried as fractional cycles in float64, computed from the integer sample index
modulo the period. ``cos(2*pi*f*t)`` with float32 ``t`` (or float64 ``t`` for long records at GHz)
loses the phase; see ``tests/test_phase.py`` for the hazard measured.
"""

from __future__ import annotations

import math
from functools import reduce

import numpy as np

#: Speed of light in vacuum (m/s), exact by the SI definition of the metre. The only definition.
C = 299_792_458.0


def frac(x: float) -> float:
    """x mod 1 in [0, 1) for a Python float (exact for the float's value)."""
    return x - math.floor(x)


def _as_int(x: float) -> int | None:
    return int(x) if float(x).is_integer() and abs(x) < 2**53 else None


def tone_cycles(f_hz: float, fs_hz: float, n: int, offset_cycles: float = 0.0, start: int = 0) -> np.ndarray:
    """Phase of a tone in cycles, ``mod(f*(start+k)/fs + offset, 1)``, k = 0..n-1.

    Parameters
    ----------
    f_hz, fs_hz : float
        Tone frequency and sample rate (Hz). When both are integers the product ``k*f`` is
        reduced modulo ``fs`` in exact integer arithmetic.
    n : int
        Number of samples.
    offset_cycles : float
        Constant phase offset (cycles), reduced modulo 1 first.
    start : int
        Index of the first sample.

    Returns
    -------
    ndarray, shape (n,), float64 in [0, 1)
    """
    k = np.arange(start, start + n, dtype=np.int64)
    fi, fsi = _as_int(f_hz), _as_int(fs_hz)
    off = frac(offset_cycles)
    if fi is not None and fsi is not None and (abs(fi) < 2**62 // max(abs(start) + n, 1)):
        cyc = np.mod(k * (fi % fsi), fsi).astype(np.float64) / fsi
    else:
        cyc = np.mod(k * (f_hz / fs_hz), 1.0)
    cyc += off
    cyc -= np.floor(cyc)
    return cyc


def wrap_pi(x: np.ndarray | float) -> np.ndarray | float:
    """Wrap a phase (rad) into [-pi, pi)."""
    return (np.asarray(x) + np.pi) % (2 * np.pi) - np.pi


def unambiguous_range(df_hz, resolution_hz: float = 1.0) -> float:
    """``c / (2*g)`` (m) with g the gcd of the frequency differences ``df_hz`` (Hz), on a
    ``resolution_hz`` grid: the range over which pair phases at those differences repeat."""
    ints = [int(round(d / resolution_hz)) for d in np.atleast_1d(df_hz)]
    g = reduce(math.gcd, ints) * resolution_hz
    return C / (2 * g)

