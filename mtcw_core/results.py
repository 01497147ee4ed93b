"""What the chain returns for a frame, and the two ways a frame ends early.

A leaf module: every stage may raise :class:`Rejected` or :class:`NoTarget`, and the runner
(:mod:`mtcw_core.chain`) turns them into a :class:`FrameResult`; nothing imports back.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Literal

#: ``ok``: at least one target; ``no_target``: a valid frame with nothing rangeable in it;
#: ``rejected``: the frame itself is bad (``reason`` says why).
Status = Literal["ok", "no_target", "rejected"]

#: ``receding``/``approaching`` need the sign of the Doppler (IQ receiver); a single or balanced
#: detector sees ``|f_d|`` only (``unknown``); ``static`` when no Doppler line was found.
Direction = Literal["receding", "approaching", "unknown", "static"]


class Rejected(Exception):
    """A frame that cannot be processed; ``reason`` is a short machine-readable key."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason
        self.detail = detail


class NoTarget(Exception):
    """A valid frame in which nothing can be ranged (no echo pulse, too few lines); the message says why."""


#: The flags of a point that tell the user not to trust its number as stated.
FLAGS: tuple[str, ...] = ("near_edge", "cycle_ambiguous", "blended")


@dataclass
class TargetPoint:
    """One target's range and speed with their one-sigma uncertainties.

    Attributes
    ----------
    range_m, range_sigma_m : float
        Range (m, from the calibration's zero) and its standard deviation (m).
    velocity_mps, velocity_sigma_mps : float
        Radial speed (m/s; signed only for an IQ receiver, positive receding) and its sigma. A
        static target reports 0 with the smallest detectable speed as its sigma; a target whose
        speed cannot be measured (laser incoherent at its range) 0 with the largest speed searched
        as its sigma, direction ``unknown``.
    direction : Direction
    snr_db : float
        Post-integration SNR of the target's strongest line (dB).
    margin : float
        ``1 - J(second peak)/J(best)`` of the cycle-resolution cost, in [0, 1].
    residual_rms_rad : float
        RMS of the pair-phase residuals at the solution (rad).
    near_edge, cycle_ambiguous, blended : bool
        The solution lies near the search interval's edge; the cycle is in doubt (the coarse
        range could not pick one, or the line phases give another cycle odds above
        ``ChainSettings.cycle_slip_max``); the line phases are not those of one target (sigma
        Birge-scaled).
    speed_min_mps : float
        The smallest speed this frame could have measured (m/s). Where the static lines are
        coherent and the whole record was searched, one record bin (``fs/N * lambda/2``; closer to
        0 Hz a line is a slope of the mean) and no less than a fifth of the search's guard -- a
        mover found below the guard is measured by the sub-guard fit, one missed there lies within
        5 of this sigma of a ``static`` claim; beside a mover found there, no less than its speed.
        Otherwise (lines broadened by the laser's phase noise, the ``fast`` profile's partial
        spectrum, a quasi-CW record) the guard itself. When the laser is not coherent at the
        target's range, the search's largest speed (nothing could have shown).
    cycle_slip_prob : float
        The summed likelihood odds of the runner-up cycles against the one reported, in [0, 1]
        (AB: the odds that noise swapped the sine fit's best period with its runner-up).
    doppler_hz : float
        The target's Doppler line (Hz; signed for IQ; 0 for the static target).
    chi2_per_dof : float
        Line-phase consistency; the sigma is scaled by its root when significant.
    tone_snr_db : dict
        Best line SNR per tone (key: tone frequency in Hz, formatted ``%.0f``).
    seed_sigma_k_m : float or None
        The dissertation's candidate-matrix row spread (m), ``seed`` method only.
    fit_r2 : float or None
        R^2 of the AB-MTCW sine fit of the normalised tone powers (the dissertation's quality
        figure), ``ab`` technique only.
    accumulated_frames : int
        How many frames the point rests on: 1 for the chain's per-frame points; K for a point of
        :class:`mtcw_core.ranging.accumulate.Accumulator` (its range is the mean over those frames).
    track_id : int or None
        The track of :class:`mtcw_core.ranging.track.Tracker` the point joined (per source; None:
        no tracking, or a flagged point).
    track_frames : int
        Points of that track its range rate rests on, this one included (0: no track).
    range_rate_mps : float or None
        The track's range rate (m/s, positive receding), the weighted slope of its points' ranges
        over their trigger times; None below the tracker's ``min_frames``.
    range_rate_sigma_mps : float or None
        Its sigma (m/s), from the points' range sigmas, scaled by the residuals' Birge ratio when
        above 1.
    """

    range_m: float
    range_sigma_m: float
    velocity_mps: float
    velocity_sigma_mps: float
    direction: Direction
    snr_db: float
    margin: float
    residual_rms_rad: float = 0.0
    near_edge: bool = False
    cycle_ambiguous: bool = False
    blended: bool = False
    doppler_hz: float = 0.0
    chi2_per_dof: float = 1.0
    cycle_slip_prob: float = 0.0
    speed_min_mps: float = 0.0
    tone_snr_db: dict[str, float] = field(default_factory=dict)
    seed_sigma_k_m: float | None = None
    fit_r2: float | None = None
    accumulated_frames: int = 1
    track_id: int | None = None
    track_frames: int = 0
    range_rate_mps: float | None = None
    range_rate_sigma_mps: float | None = None

    @property
    def flagged(self) -> bool:
        """The point says its number may be wrong (any of :data:`FLAGS`)."""
        return any(getattr(self, f) for f in FLAGS)

    @property
    def speed_measured(self) -> bool:
        """Whether the speed is an estimate, not a bound: not ``static``, and not the 0 of a speed
        that could not be measured (direction ``unknown``, its sigma the smallest speed the frame
        could have measured, which is then the search's largest: the laser incoherent at its range)."""
        if self.direction == "static":
            return False
        return not (self.direction == "unknown" and self.velocity_mps == 0.0
                    and self.velocity_sigma_mps >= self.speed_min_mps > 0)


@dataclass
class FrameResult:
    """The chain's answer for one frame.

    ``targets`` are sorted strongest first. ``stage_seconds`` holds the wall time of every stage
    that ran, keyed by the stage names of :data:`mtcw_core.chain.STAGES`, in their order.
    ``coarse_range_m``/``coarse_sigma_m`` (m) come from quasi-CW gating; ``doppler_hz`` is the
    strongest target's Doppler line (Hz).
    """

    status: Status
    profile: str
    technique: str = "pb"
    seq: int = 0
    t_ns: int = 0
    source: str = ""
    reason: str | None = None
    targets: list[TargetPoint] = field(default_factory=list)
    unambiguous_range_m: float | None = None
    coarse_range_m: float | None = None
    coarse_sigma_m: float | None = None
    doppler_hz: float | None = None
    calibrated: bool = False
    clip_fraction: float = 0.0
    stage_seconds: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)
