"""Stage ``validate``: digitizer codes to volts, and the checks a frame must pass first.

A frame that fails raises :class:`~mtcw_core.results.Rejected` with a short reason key
(``bad_fs``, ``bad_shape``, ``too_short``, ``too_long``, ``length_mismatch``, ``tone_plan``,
``calibration_mismatch``, ``bad_channels``, ``non_finite``, ``flat``, ``clipped``). The limits on
what a frame may ask for (tones, record length, cycle-search grid) are checked first, before any
work that grows with them.
"""

from __future__ import annotations

import math

import numpy as np

from ..calibration import Calibration
from ..frame import Frame
from ..phase import C, unambiguous_range
from ..profiles import ChainSettings
from ..results import Rejected


def rail_fraction(r: np.ndarray, rail) -> float:
    """Fraction of samples in runs of >= 3 consecutive samples stuck at ``rail``.

    A signal (even a periodic or coarsely quantised one) touches its extremes in isolated
    samples at GHz tones; a clipped one dwells on the rail.

    Parameters
    ----------
    r : ndarray, shape (N,), raw codes or volts
    rail : scalar, the value taken for the rail (the record's max or min)
    """
    at = r == rail
    if np.count_nonzero(at) < 3:
        return 0.0
    run = at[:-2] & at[1:-1] & at[2:]
    stuck = np.zeros(r.size, bool)
    stuck[:-2] |= run
    stuck[1:-1] |= run
    stuck[2:] |= run
    return float(np.count_nonzero(stuck)) / r.size


def plan_unambiguous_range(tones_hz) -> float:
    """The unambiguous range (m) of a tone plan: ``c/(2*gcd)`` of its tone spacings."""
    t = sorted(float(f) for f in tones_hz)
    return unambiguous_range([b - a for a, b in zip(t, t[1:])])


def search_grid_points(tones_hz, settings: ChainSettings, pulsed: bool, l_unamb: float | None = None) -> float:
    """Points of the cycle-resolution grid a tone plan asks for: the searched span (the
    configured range interval for CW frames when set, else the plan's unambiguous range
    ``l_unamb``, computed when not given) over the grid step (the finest synthetic wavelength
    over ``points_per_cycle``)."""
    span = plan_unambiguous_range(tones_hz) if l_unamb is None else l_unamb
    if settings.range_max_m is not None and not pulsed:
        span = min(span, settings.range_max_m - settings.range_min_m)
    step = C / (2 * (max(tones_hz) - min(tones_hz))) / settings.points_per_cycle
    return span / step


def _check_limits(frame: Frame, settings: ChainSettings) -> None:
    """What a frame may ask of a worker, before anything is computed."""
    if frame.n > settings.max_samples:
        raise Rejected("too_long", f"{frame.n} samples per channel (limit {settings.max_samples})")
    tones = frame.tones_hz
    if len(tones) > settings.max_tones:
        raise Rejected("tone_plan", f"{len(tones)} tones (limit {settings.max_tones})")
    if not all(isinstance(f, (int, float)) and math.isfinite(f) for f in tones) or len(set(tones)) != len(tones):
        raise Rejected("tone_plan", f"tones {list(tones)} must be finite and distinct")
    if len(tones) >= 2 and all(0 < f < frame.fs_hz / 2 for f in tones):
        l_unamb = plan_unambiguous_range(tones)
        pts = search_grid_points(tones, settings, frame.pulse is not None, l_unamb)
        if pts > settings.max_grid_points:
            raise Rejected("tone_plan", f"tones {list(tones)} repeat only every {l_unamb:.3g} m: "
                                        f"the cycle search would need {pts:.3g} grid points "
                                        f"(limit {settings.max_grid_points}; put the tones on a coarser grid, "
                                        f"or set range_max_m)")


def _check_plan(frame: Frame, settings: ChainSettings, calibration: Calibration | None) -> None:
    """Sample rate, shape, length, tone plan and channels against the frame and the settings."""
    if not (frame.fs_hz > 0 and math.isfinite(frame.fs_hz)):
        raise Rejected("bad_fs", f"fs_hz={frame.fs_hz!r}")
    if frame.samples.ndim != 2 or frame.samples.shape[0] != len(frame.channels):
        raise Rejected("bad_shape", f"samples shape {frame.samples.shape} vs channels {list(frame.channels)}")
    _check_limits(frame, settings)
    if frame.n < 256:
        raise Rejected("too_short", f"{frame.n} samples (need >= 256)")
    if settings.expected_samples is not None and frame.n != settings.expected_samples:
        raise Rejected("length_mismatch", f"{frame.n} samples, expected {settings.expected_samples}")
    tones = frame.tones_hz
    if len(tones) < 2:
        raise Rejected("tone_plan", "at least two tones are needed for pair phases")
    if any(not (0 < f < frame.fs_hz / 2) for f in tones):
        raise Rejected("tone_plan", f"tones {list(tones)} must lie in (0, fs/2)")
    if settings.expected_tones_hz is not None and tuple(tones) != tuple(settings.expected_tones_hz):
        raise Rejected("tone_plan", f"frame tones {list(tones)} != configured {list(settings.expected_tones_hz)}")
    if calibration is not None and tuple(calibration.tones_hz) != tuple(tones):
        raise Rejected("calibration_mismatch", f"calibration tones {list(calibration.tones_hz)} != frame {list(tones)}")
    if frame.receiver == "iq" and not {"i", "q"} <= set(frame.channels):
        raise Rejected("bad_channels", "iq receiver needs channels 'i' and 'q'")
    if frame.receiver != "iq" and "pd" not in frame.channels:
        raise Rejected("bad_channels", "channel 'pd' missing")


def validate(frame: Frame, settings: ChainSettings, calibration: Calibration | None) -> tuple[np.ndarray, float]:
    """Check a frame and convert its signal channel(s) to volts.

    Returns
    -------
    x : ndarray, shape (N,), float64 (single/balanced) or complex128 (IQ: i + jq), V
    clip_fraction : float, the larger rail fraction over the signal channels

    Raises
    ------
    Rejected
    """
    _check_plan(frame, settings, calibration)
    raw = [frame.samples[frame.channels.index(c)] for c in (("i", "q") if frame.receiver == "iq" else ("pd",))]
    for r in raw:
        if r.dtype.kind == "f" and not np.all(np.isfinite(r)):
            raise Rejected("non_finite", f"{int(np.sum(~np.isfinite(r)))} NaN/inf samples")
    clip = 0.0
    for r in raw:
        hi, lo = r.max(), r.min()
        if hi == lo:
            raise Rejected("flat", "all samples equal (no signal)")
        clip = max(clip, rail_fraction(r, hi), rail_fraction(r, lo))
    if clip > settings.max_clip_fraction:
        raise Rejected("clipped", f"{clip:.2%} of samples at the rails (max {settings.max_clip_fraction:.2%})")
    return frame.signal(), clip
