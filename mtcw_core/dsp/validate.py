"""Stage ``validate``: digitizer codes to volts, and the checks a frame must pass first.

A frame that fails raises :class:`~mtcw_core.results.Rejected` with a short reason key
(``bad_fs``, ``bad_wavelength``, ``bad_shape``, ``too_short``, ``too_long``, ``length_mismatch``, ``tone_plan``,
``calibration_mismatch``, ``bad_channels``, ``non_finite``, ``bad_scale``, ``bad_pulse``, ``flat``,
``clipped``). The limits on what a frame may ask for (tones, record length, cycle-search grid,
gate periods) are checked first, before any work that grows with them.
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


#: integer codes spanning fewer ADC steps than this are under-resolved: a weak signal on a large DC
#: (an 8-bit digitizer behind one photodiode) dwells on its top code as a clipped one does
MIN_RAIL_SPAN_STEPS = 16


def code_steps(r: np.ndarray, hi=None, lo=None, stride: int = 1) -> tuple[int, int]:
    """How many ADC steps integer codes ``r`` (extremes ``hi``, ``lo``; taken from ``r`` when not
    given) span, and the step (codes): their range over the gcd of the gaps between the codes
    present (8-bit codes sent as 16-bit words step by 256), read in every ``stride``-th code (a
    subset's step is a multiple of the whole's: the same unless codes off it are rare; 16-bit words
    of 1e6 samples take ~9 ms read whole, ~1 ms at a stride of 16)."""
    hi = int(np.max(r)) if hi is None else int(hi)
    lo = int(np.min(r)) if lo is None else int(lo)
    present = np.flatnonzero(np.bincount((r[..., ::stride].astype(np.int64) - lo).ravel()))
    step = max(int(np.gcd.reduce(np.diff(present))) if present.size > 1 else 1, 1)
    return (hi - lo) // step, step


def clip_fraction(r: np.ndarray, hi, lo, limit: float) -> float:
    """The fraction of ``r`` (extremes ``hi``, ``lo``) stuck at a digitizer's rails.

    The record's own extremes are taken for the rails (:func:`rail_fraction`): the ADC's range is
    not on the frame. Where that finds more than ``limit`` in integer codes, the codes are looked
    at once more: spanning fewer than :data:`MIN_RAIL_SPAN_STEPS` ADC steps (the gcd of the gaps
    between the codes present: 8-bit codes sent as 16-bit words step by 256) the record is
    under-resolved and its extremes are no rails, unless they are the dtype's own limits (int8's
    -128 and 127, int16's): a record whose top code is 121 of 127 was never clipped, however long
    it dwells there.
    """
    frac = max(rail_fraction(r, hi), rail_fraction(r, lo))
    if frac <= limit or r.dtype.kind not in "iu":
        return frac
    if code_steps(r, hi, lo)[0] >= MIN_RAIL_SPAN_STEPS:
        return frac
    lim = np.iinfo(r.dtype)
    return max([0.0] + [rail_fraction(r, v) for v in (hi, lo) if v in (lim.max, lim.min)])


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


#: tones (and the lowest tone from 0) at least this many bins of the record apart
MIN_TONE_GAP_BINS = 2
#: quasi-CW gate timing the gate stage can work with: a period of at least this many samples ...
MIN_PERIOD_SAMPLES = 64
#: ... and at most this many gate periods in one record (the gate stage loops over them)
MAX_GATES = 4096
#: ... and a gate on, and off, for at least this many samples of each period (its edges are timed
#: on 16-sample blocks of the envelope; a duty of 1 never switches off)
MIN_GATE_SAMPLES = 16


def _check_limits(frame: Frame, settings: ChainSettings) -> None:
    """What a frame may ask of a worker, before anything is computed."""
    if frame.n > settings.max_samples:
        raise Rejected("too_long", f"{frame.n} samples per channel (limit {settings.max_samples})")
    if frame.pulse is not None and settings.gate != "off" and math.isfinite(frame.fs_hz):
        # the gate stage correlates over one period and walks every gate in the record: a period
        # of a fraction of a sample, or of days, would hold a worker for ever
        per = frame.pulse.period_s * frame.fs_hz
        if not (max(MIN_PERIOD_SAMPLES, frame.n / MAX_GATES) <= per <= settings.max_samples):
            raise Rejected("bad_pulse", f"gate period {frame.pulse.period_s:.3g} s is {per:.3g} samples (from "
                                        f"{MIN_PERIOD_SAMPLES} and {frame.n / MAX_GATES:.3g} = n/{MAX_GATES} "
                                        f"to {settings.max_samples})")
        on, off = frame.pulse.duty * per, (1.0 - frame.pulse.duty) * per
        if min(on, off) < MIN_GATE_SAMPLES:  # no edge to time: a gate that never switches (duty 1)
            raise Rejected("bad_pulse", f"gate on for {on:.3g} and off for {off:.3g} samples per period (each must "
                                        f"be at least {MIN_GATE_SAMPLES} samples to show its edges)")
    tones = frame.tones_hz
    if len(tones) > settings.max_tones:
        raise Rejected("tone_plan", f"{len(tones)} tones (limit {settings.max_tones})")
    if not all(isinstance(f, (int, float)) and math.isfinite(f) for f in tones) or len(set(tones)) != len(tones):
        raise Rejected("tone_plan", f"tones {list(tones)} must be finite and distinct")
    if len(tones) >= 2 and all(0 < f < frame.fs_hz / 2 for f in tones):
        t = sorted(tones)
        if min(b - a for a, b in zip(t, t[1:])) < 1.0:  # the plan's gcd is taken on a 1 Hz grid
            raise Rejected("tone_plan", f"tones {list(tones)} are less than 1 Hz apart")
        l_unamb = plan_unambiguous_range(tones)
        pts = search_grid_points(tones, settings, frame.pulse is not None, l_unamb)
        if pts > settings.max_grid_points:
            raise Rejected("tone_plan", f"tones {list(tones)} repeat only every {l_unamb:.3g} m: "
                                        f"the cycle search would need {pts:.3g} grid points "
                                        f"(limit {settings.max_grid_points}; put the tones on a coarser grid, "
                                        f"or set range_max_m)")


#: the largest tone phase a frame or calibration may state (rad): any wrapped or unwrapped phase a
#: bench reports is far below, and float64 still resolves 1e-10 rad there; beyond it the pair
#: differences lose every digit (1e300 - (-1.8e308) is inf: found by fuzzing the worker)
MAX_PHASE_RAD = 1e6


#: the optical wavelengths a frame may state (m), deep ultraviolet to far infrared: the Doppler
#: (``2v/lambda``) and the sidebands' own shift (``f_i*f_d/f0``) are computed from it, and an absurd
#: one (9.5e297 m: found by fuzzing the worker) overflowed the refinement's sums
WAVELENGTH_RANGE_M = (1e-7, 1e-3)


def _check_plan(frame: Frame, settings: ChainSettings, calibration: Calibration | None) -> None:
    """Sample rate, wavelength, shape, length, tone plan and channels against the frame and the
    settings."""
    if not (frame.fs_hz > 0 and math.isfinite(frame.fs_hz)):
        raise Rejected("bad_fs", f"fs_hz={frame.fs_hz!r}")
    lo, hi = WAVELENGTH_RANGE_M
    if not lo <= frame.wavelength_m <= hi:
        raise Rejected("bad_wavelength", f"wavelength_m={frame.wavelength_m!r} (from {lo:g} to {hi:g} m)")
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
    gap = min(min(tones), *(b - a for a, b in zip(sorted(tones), sorted(tones)[1:])))
    if gap < MIN_TONE_GAP_BINS * frame.fs_hz / frame.n:
        raise Rejected("tone_plan", f"tones {list(tones)} are {gap:.3g} Hz from each other or from 0: less than "
                                    f"{MIN_TONE_GAP_BINS} bins of a {frame.n}-sample record at {frame.fs_hz:.3g} S/s "
                                    f"(their lines cannot be told apart)")
    if settings.expected_tones_hz is not None and tuple(tones) != tuple(settings.expected_tones_hz):
        raise Rejected("tone_plan", f"frame tones {list(tones)} != configured {list(settings.expected_tones_hz)}")
    if settings.tone_amplitudes is not None and len(settings.tone_amplitudes) != len(tones):
        raise Rejected("tone_plan", f"tone_amplitudes has {len(settings.tone_amplitudes)} values for the frame's "
                                    f"{len(tones)} tones")
    if calibration is not None and tuple(calibration.tones_hz) != tuple(tones):
        raise Rejected("calibration_mismatch", f"calibration tones {list(calibration.tones_hz)} != frame {list(tones)}")
    phases = calibration.tone_phases_rad if calibration is not None else frame.tone_phases_rad
    for i, ph in enumerate(phases or ()):
        if not abs(ph) <= MAX_PHASE_RAD:  # NaN-safe
            where = "calibration tone_phases_rad" if calibration is not None else "tone_phases_rad"
            raise Rejected("tone_phases", f"{where}[{i}] = {ph!r} rad is not a phase (|phase| <= {MAX_PHASE_RAD:g} rad)")
    if frame.receiver == "iq" and not {"i", "q"} <= set(frame.channels):
        raise Rejected("bad_channels", "iq receiver needs channels 'i' and 'q'")
    if frame.receiver != "iq" and "pd" not in frame.channels:
        raise Rejected("bad_channels", "channel 'pd' missing")


#: volts (code*scale + offset) a record may reach, and the least span of its samples: far beyond
#: any digitizer, and within what the chain's spectra hold (the Doppler spectrum may be single
#: precision: line powers over 2^25 samples must neither overflow nor underflow float32)
MAX_VOLTS = 1e6
MIN_SPAN_VOLTS = 1e-12


def _check_volts(frame: Frame, hi: float, lo: float) -> None:
    """The extreme codes ``hi``, ``lo`` in volts (linear, so they bound every sample): finite,
    within :data:`MAX_VOLTS`, and apart by at least :data:`MIN_SPAN_VOLTS`."""
    v = [c * frame.scale + frame.offset for c in (hi, lo)]
    peak, span = max(abs(v[0]), abs(v[1])), abs(v[0] - v[1])
    if not peak <= MAX_VOLTS:  # NaN-safe
        raise Rejected("bad_scale", f"scale {frame.scale:g}, offset {frame.offset:g} put samples at {peak:.3g} V "
                                    f"(limit {MAX_VOLTS:g} V)")
    if not span >= MIN_SPAN_VOLTS:
        raise Rejected("flat" if span == 0 else "bad_scale",
                       f"scale {frame.scale:g}: the samples span {span:.3g} V (at least {MIN_SPAN_VOLTS:g} V needed)")


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
    # the extremes of every channel first: a NaN anywhere makes max and min NaN, an inf makes one
    # of them infinite, so finite extremes prove every sample finite (no pass of its own)
    extremes = [(r.max(), r.min()) for r in raw]
    for r, (hi, lo) in zip(raw, extremes):
        if r.dtype.kind == "f" and not (np.isfinite(hi) and np.isfinite(lo)):
            raise Rejected("non_finite", f"{int(np.sum(~np.isfinite(r)))} NaN/inf samples")
    clip = 0.0
    for r, (hi, lo) in zip(raw, extremes):
        if hi == lo:
            raise Rejected("flat", "all samples equal (no signal)")
        _check_volts(frame, float(hi), float(lo))
        clip = max(clip, clip_fraction(r, hi, lo, settings.max_clip_fraction))
    if clip > settings.max_clip_fraction:
        raise Rejected("clipped", f"{clip:.2%} of samples at the rails (max {settings.max_clip_fraction:.2%})")
    return frame.signal(), clip
