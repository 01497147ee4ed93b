"""The chain's settings, grouped by stage, and the named profiles users pick from.

A profile is a named :class:`ChainSettings`: the speed–accuracy knob (``mtcw bench`` measures
the trade). Sections follow the stage order of :data:`mtcw_core.chain.STAGES`.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from .scene import field_path  # the one rendering of an error's field path


class ChainSettings(BaseModel):
    """Choices of every stage. A profile is a named ChainSettings."""

    # NaN and inf are refused: a NaN bound or threshold compares false and switches a check off
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    profile: str = "custom"
    technique: Literal["pb", "ab", "pe", "ptof"] = Field(
        "pb", description="pb: phase-based MTCW (the chain below); ab: amplitude-based, pe: phase-extraction "
                          "(modulated reference arm), ptof: pulsed time of flight (the dissertation's Ch. 3-4); "
                          "each has its own stage table in mtcw_core.chain.TECHNIQUES")
    # -- validate
    max_clip_fraction: float = Field(1e-3, ge=0, le=1)
    expected_tones_hz: tuple[float, ...] | None = None
    expected_samples: int | None = None
    # limits on what a frame may ask of a worker, checked before any work (a frame's header sets
    # the tone plan and the record length; one hostile frame must not hold a worker for minutes)
    max_tones: int = Field(16, ge=2, description="tones in a frame's plan")
    max_samples: int = Field(2**25, ge=256, description="samples per channel")
    max_grid_points: int = Field(2**22, ge=1024, description="cycle-search grid: the searched range span over "
                                                              "the grid step (finest synthetic wavelength / "
                                                              "points_per_cycle); a tone plan whose gcd is a few Hz "
                                                              "spans millions of km")
    # -- gate (quasi-CW frames only)
    gate: Literal["auto", "off"] = "auto"
    gate_k_sigma: float = Field(3.0, gt=0, description="the period is certain when k coarse sigmas stay within "
                                                       "half the unambiguous range")
    gate_min_snr: float = Field(8.0, gt=0)
    # -- spectrum
    doppler_fraction: float = Field(0.25, gt=0, le=1, description="part of the record used for the Doppler FFT")
    window_beta: float = Field(14.0, ge=0)
    spectrum_single: bool = Field(False, description="Doppler-search spectrum in single precision (~2x faster; "
                                                     "line phases are fitted in float64 regardless)")
    # -- doppler
    doppler_min_bins: int = Field(4, ge=1)
    sideband_direction: bool = Field(False, description=(
        "a single or balanced photodiode: report the direction of motion where the sidebands' own Doppler "
        "shift (f_i*f_d/f0: the RF tones are Doppler-shifted too) decides its sign (receding/approaching); off, "
        "such a detector reports direction 'unknown' as the interface states. Measured on the honesty map "
        "(notes), not yet on a bench"))
    doppler_threshold: float = Field(8.0, gt=0)
    fd_max_hz: float | None = Field(None, gt=0, description="default: half the smallest tone spacing")
    doppler_phase_lines: int | None = Field(None, ge=1, description="phase refinement: the strongest lines only")
    doppler_refine: Literal["parabolic", "phase", "exact"] = Field(
        "parabolic", description="below one Doppler-spectrum bin: parabola through the search scores, then "
                                 "(phase) the phase advance of the lines across record quarters, or (exact) "
                                 "that, then maximising the windowed exact line power (its stated error is "
                                 "the phase refinement's)")
    max_targets: int = Field(3, ge=1, le=8, description="Doppler lines (moving targets) looked for")
    # -- extract
    extraction: Literal["ls", "filter"] = "ls"
    model_products: bool = False
    segments: int = Field(1, ge=1)
    gate_segment_s: float = Field(100e-9, gt=0, description="segment length in quasi-CW echo windows; short "
                                                          "enough for the laser to stay coherent")
    seed_points: int = Field(2**23, ge=2**10, description="the seed's extraction path: resampled length")
    seed_bandwidth_hz: float = Field(1e6, gt=0, description="the seed's extraction path: band-pass width")
    # -- mix
    min_line_snr_db: float = Field(10.0, description="post-integration SNR for a line to be used")
    # -- resolve
    method: Literal["ml", "seed"] = "ml"
    points_per_cycle: int = Field(16, ge=4)
    range_min_m: float = -0.05
    range_max_m: float | None = None
    timing_jitter_s: float = Field(0.0, ge=0, le=1e-6, description=(
        "the digitizer's known rms trigger/timing jitter (s): it shifts every tone phase alike, as a range "
        "shift of c*dt/2 that one frame cannot see, so it enters the range sigma in quadrature"))
    tone_phase_sigma_rad: float = Field(0.0, ge=0, le=math.pi, description=(
        "the RF synthesizers' known rms phase error per tone (rad) against the tone phases in force (their "
        "drift since calibration, independent per tone): one frame cannot see it, so what it does to the "
        "range fit enters the range sigma in quadrature"))
    laser_linewidth_hz: float = Field(0.0, ge=0, le=1e12, description=(
        "the laser's Lorentzian FWHM (Hz); with lo_path_difference_m it says at which ranges the LO x echo "
        "carrier beat is a line at all: where it is not, a mover shows no Doppler line and its speed is "
        "reported unknown, not zero; a static point's segments are checked against one echo's envelope only where "
        "it is coherent. 0: assumed coherent at every range (one frame cannot tell; a partly coherent laser left "
        "undeclared may then flag a lone still echo blended)"))
    lo_path_difference_m: float = Field(0.0, ge=-1e4, le=1e4, description="optical path of the LO minus the "
                                                                         "echo's internal path (m)")
    tone_amplitudes: tuple[Annotated[float, Field(gt=0)], ...] | None = Field(None, min_length=2, description=(
        "one target's line amplitude at each tone, in the frame's tone order, any common scale (a calibration "
        "holding them, `mtcw calibrate`, takes precedence): the static point's lines must keep these ratios, "
        "or it is flagged blended (two echoes on one Doppler-0 line set can fit one wrong range by their "
        "phases, not by their amplitudes). None: unknown, not checked"))
    tone_amplitude_tolerance: float = Field(0.01, ge=0, le=1, description=(
        "the relative rms error of tone_amplitudes (their drift since they were measured, the front end's): "
        "it widens each line's amplitude sigma in that check"))
    sideband_tolerance: float = Field(0.05, ge=0, le=1, description=(
        "an IQ receiver's upper and lower sideband sizes of one echo agree within this, relative (its "
        "hybrid's balance and image rejection, the modulator's symmetry): a static point whose sidebands "
        "differ beyond it and their noise is flagged blended (two echoes on one line set)"))
    cycle_slip_max: float = Field(1e-3, gt=0, le=1, description="the line phases give another cycle odds above "
                                                                "this: the point is flagged cycle_ambiguous")
    blended_chi2: float = Field(10.0, gt=1, description="chi2/dof of the line phases above which one point "
                                                        "cannot explain them: flagged blended")
    blended_lines_chi2: float = Field(300.0, gt=1, description=(
        "chi2/dof of a Doppler line's own lines (their Doppler corrections about their mean) above which "
        "it is taken for two movers the search could not resolve: flagged blended. One mover: 0.1-90 "
        "(leakage and phase-noise pedestals included); two movers 2-6 bins apart: 170-1e7"))
    # .. technique pe only (its stages pe_lines, pe_resolve; mtcw_core/ranging/pe.py)
    reference_range_m: float | None = Field(
        None, ge=0, description="pe: one-way range of the reference mirror (m); None: measured in each frame "
                                "from the reference self-beat phases and the tone phases in force")
    pe_second_order: bool = Field(False, description="pe: also use the 2f_i +- f_d lines (each only where it agrees "
                                                     "with the f_i +- f_d solution within 3 sigma)")
    pe_min_log_odds: float = Field(12.0, gt=0, description="pe: log-likelihood of the chosen cycle over the runner-up "
                                                           "below which the point is flagged cycle_ambiguous")
    # -- select
    self_beat_margin_db: float = Field(15.0, ge=0, description="a static candidate this far below the movers' "
                                                               "lines is taken for their self-beat")
    incoherent_residual_rad: float = Field(0.25, gt=0, description="a moving candidate whose line phases miss one "
                                                                   "range by this much (rms) at > 25 dB is noise")
    # -- square (CW frames, a laser declared incoherent: when select found no target, or one point where the laser
    # is incoherent)
    squared_lines: bool = Field(True, description=(
        "when the chain's own lines give no target, or one point where the declared laser (laser_linewidth_hz > 0) "
        "is incoherent (the echo's self-beat; replaced when the squared record's point is unflagged against a "
        "flagged one or has the smaller sigma), range "
        "from the lines of the squared record (whole-band digital IF mixing: LO power x echo intensity, no "
        "laser phase, no Doppler), which reach beyond the laser's coherence, where that laser is incoherent at "
        "the range they give; the point's speed is unknown. A calibration taken through the chain's lines holds "
        "for these only when the front end is flat over the band (docs/reach.md)"))


PROFILES: dict[str, ChainSettings] = {
    # Doppler from 1/8 of the record, plain LS at known lines, coarse ML grid.
    "fast": ChainSettings(profile="fast", doppler_fraction=1 / 8, points_per_cycle=8, spectrum_single=True,
                          doppler_refine="phase", doppler_phase_lines=3),
    # Doppler from the whole record, joint LS of all used lines, ML on a 16-point grid.
    "balanced": ChainSettings(profile="balanced", doppler_fraction=1.0, spectrum_single=True, doppler_refine="phase"),
    # Full-record spectrum, phase-advance Doppler refinement over all lines, MZM products modelled
    # in the LS fit, ML on a 32-point grid. The search spectrum is single precision as in
    # `balanced` (issue 16: its float64 transform cost a third of the frame and moved no cell of
    # the honesty map; every phase is fitted in float64 regardless).
    "accurate": ChainSettings(profile="accurate", doppler_fraction=1.0, doppler_refine="phase", spectrum_single=True,
                              model_products=True, points_per_cycle=32),
    # The dissertation: resample to 2^23, 1 MHz 2nd-order Butterworth filtfilt per line,
    # correlation with zero-phase cosines, candidate-matrix triangulation.
    "seed": ChainSettings(profile="seed", doppler_fraction=1.0, extraction="filter", method="seed"),
}


def get_profile(name: str, **overrides) -> ChainSettings:
    """A named profile, with ``overrides`` validated like the profile itself.

    Raises
    ------
    ValueError
        Unknown profile, or an override that is not a valid setting (the message names it).
    """
    if not isinstance(name, str) or name not in PROFILES:
        raise ValueError(f"profile: unknown {name!r} (one of {', '.join(PROFILES)})")
    base = PROFILES[name]
    if not overrides:
        return base
    try:
        return ChainSettings.model_validate({**base.model_dump(), **overrides})
    except ValidationError as err:
        e = err.errors()[0]
        raise ValueError(f"profile {name}: {field_path(e['loc'])}: {e['msg']}") from None
