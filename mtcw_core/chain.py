"""The PB-MTCW chain: the stage table and the runner that walks and times it.

One frame in, one :class:`~mtcw_core.results.FrameResult` out; nothing escapes as an exception.
The stages, in order (:data:`STAGES`; the same names key ``FrameResult.stage_seconds``, the
``stage`` label of ``mtcw_stage_duration_seconds`` and the sections of
:class:`~mtcw_core.profiles.ChainSettings`):

========  ==============================================  ==================================
stage     what it does                                    where its maths lives
========  ==============================================  ==================================
validate  codes -> volts, clipping, tone plan, channels   :mod:`mtcw_core.dsp.validate`
gate      quasi-CW coarse range and echo windows          :mod:`mtcw_core.ranging.gating`
spectrum  windowed spectrum of the (gated) record         :mod:`mtcw_core.dsp.spectrum`
doppler   Doppler lines of the moving targets             :mod:`mtcw_core.dsp.doppler`
extract   complex amplitude of every planned line         :mod:`mtcw_core.dsp.extract`
mix       IF mixing: pair phases per target candidate     :mod:`mtcw_core.ranging.mixing`
resolve   cycle resolution, sigma, velocity per candidate :mod:`mtcw_core.ranging.targets`
select    which candidates are targets, strongest first   :mod:`mtcw_core.ranging.targets`
square    beyond coherence: the squared record's point    :mod:`mtcw_core.ranging.accumulate`
          (whole-band IF mixing), if none or a worse one
========  ==============================================  ==================================

Each stage here is a two-line adapter: it reads what earlier stages left in the
:class:`FrameState` and stores its own output there. ``gate`` runs only for pulsed frames. A
stage ends a frame early by raising :class:`~mtcw_core.results.Rejected` (a bad frame) or
:class:`~mtcw_core.results.NoTarget` (nothing to range). The runner does the timing; no stage
sees a clock.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .calibration import Calibration
from .dsp.doppler import DopplerEstimate, estimate_doppler
from .dsp.extract import LineFamily, extract_lines
from .dsp.spectrum import Spectrum, search_spectrum
from .dsp.validate import validate
from .frame import Frame
from .phase import C
from .profiles import PROFILES, ChainSettings, get_profile
from .ranging.gating import GateEstimate, gate_frame, is_gated
from .ranging import ab, pe, ptof
from .ranging.accumulate import square_can_range, square_point, square_rival, square_rivals
from .ranging.mixing import mix
from .ranging.pe import PeLines
from .ranging.targets import Reference, resolve_targets, select_targets
from .ranging.triangulation import Observations
from .results import Direction, FrameResult, NoTarget, Rejected, Status, TargetPoint


@dataclass
class FrameState:
    """What the stages hand each other for one frame (filled in stage order)."""

    frame: Frame
    settings: ChainSettings
    calibration: Calibration | None
    result: FrameResult
    x: np.ndarray | None = None  # validate: signal in volts, shape (N,), float64 or complex128
    reference: Reference | None = None  # validate: tone phases and tau0 in force
    gate: GateEstimate | None = None  # gate
    coarse: tuple[float, float] | None = None  # gate: the coarse range interval (m)
    spectrum: Spectrum | None = None  # spectrum
    dopplers: list[DopplerEstimate] = field(default_factory=list)  # doppler
    families: list[LineFamily] = field(default_factory=list)  # extract
    observations: dict[int, Observations] = field(default_factory=dict)  # mix, per candidate
    candidates: list[tuple[int, TargetPoint]] = field(default_factory=list)  # resolve
    no_target_why: str | None = None  # select: why the chain's own lines gave no target
    pe_lines: list[PeLines] = field(default_factory=list)  # pe_lines (technique pe)
    technique_state: Any = None  # what another technique's stages hand each other (e.g. ranging.ab.ABState)

    @property
    def windows(self) -> list[tuple[int, int]] | None:
        return self.gate.windows if self.gate is not None else None


def _validate(s: FrameState) -> None:
    s.x, s.result.clip_fraction = validate(s.frame, s.settings, s.calibration)
    s.reference = Reference.of(s.frame, s.settings, s.calibration)


def _gate(s: FrameState) -> None:
    s.gate = g = gate_frame(s.x, s.frame, s.settings)
    r = s.result
    r.coarse_range_m, r.coarse_sigma_m = C * (g.tau_s - s.reference.tau0_s) / 2, C * g.sigma_s / 2
    if not g.detected:
        raise NoTarget(f"no echo pulse (gate snr {g.snr:.1f} < {s.settings.gate_min_snr})" if not g.snr >= s.settings.gate_min_snr
                       else "no echo pulse (the gate fit gives no finite delay)")
    half = s.settings.gate_k_sigma * r.coarse_sigma_m
    s.coarse = (r.coarse_range_m - half, r.coarse_range_m + half)


def _spectrum(s: FrameState) -> None:
    st = s.settings
    s.spectrum = search_spectrum(s.x, s.frame.fs_hz, st.window_beta, st.doppler_fraction, st.spectrum_single,
                                 s.windows)


def _doppler(s: FrameState) -> None:
    s.dopplers = estimate_doppler(s.x, s.frame, s.spectrum, s.settings, gated=bool(s.windows))
    s.result.doppler_hz = s.dopplers[0].fd_hz


def _extract(s: FrameState) -> None:
    s.families = extract_lines(s.x, s.frame, s.dopplers, s.spectrum, s.settings, s.windows)


def _mix(s: FrameState) -> None:
    s.observations = mix(s.families, s.reference.tone_phases_rad, s.settings.min_line_snr_db)


def _resolve(s: FrameState) -> None:
    s.candidates, s.result.unambiguous_range_m = resolve_targets(
        s.families, s.observations, s.dopplers, s.frame, s.settings, s.reference, s.coarse)


def _square_applies(s: FrameState) -> bool:
    """A CW PB frame, a laser declared incoherent somewhere; no target, or one the square stage may better."""
    st = s.settings
    able = st.technique == "pb" and st.squared_lines and s.gate is None and square_can_range(st, s.frame.tones_hz)
    return able and (not s.result.targets or square_rivals(s.result.targets, st))


def _select(s: FrameState) -> None:
    targets = select_targets(s.candidates, s.settings, s.frame.fs_hz / s.frame.n, s.frame.receiver)
    if not targets:
        s.no_target_why = f"fewer than two lines above {s.settings.min_line_snr_db} dB"
        if _square_applies(s):
            return  # the square stage has the last word
        raise NoTarget(s.no_target_why)
    s.result.targets = targets
    s.result.doppler_hz = targets[0].doppler_hz
    s.result.status = "ok"


def _square(s: FrameState) -> None:
    r = s.result
    if r.targets:  # the chain's own point beyond coherence: the squared record's, where better
        if (better := square_rival(s.x, s.frame, s.settings, s.reference, r.targets[0])) is not None:
            (r.targets, r.unambiguous_range_m, r.reason), r.doppler_hz = better, 0.0
        return
    r.targets, r.unambiguous_range_m, r.reason = square_point(s.x, s.frame, s.settings, s.reference, s.no_target_why)
    r.doppler_hz, r.status = 0.0, "ok"


@dataclass(frozen=True)
class Stage:
    """One row of the stage table: its name, its adapter, and when it applies."""

    name: str
    run: Callable[[FrameState], None]
    applies: Callable[[FrameState], bool] = lambda s: True


#: The chain, in order. Names are the vocabulary of timings, metrics and settings.
STAGES: tuple[Stage, ...] = (
    Stage("validate", _validate),
    Stage("gate", _gate, lambda s: is_gated(s.frame, s.settings)),
    Stage("spectrum", _spectrum),
    Stage("doppler", _doppler),
    Stage("extract", _extract),
    Stage("mix", _mix),
    Stage("resolve", _resolve),
    Stage("select", _select),
    Stage("square", _square, _square_applies),
)
STAGE_NAMES: tuple[str, ...] = tuple(st.name for st in STAGES)


#: One stage table per technique (``ChainSettings.technique``); ``pb`` is :data:`STAGES`.
TECHNIQUES: dict[str, tuple[Stage, ...]] = {"pb": STAGES, "ab": ab.stages(STAGES), "pe": pe.stages(STAGES),
                                            "ptof": ptof.stages(STAGES)}


def stages_of(technique: str) -> tuple[Stage, ...]:
    """The stage table of ``technique`` (one of ``ChainSettings.technique``'s values, all in :data:`TECHNIQUES`)."""
    return TECHNIQUES[technique]


def _start(frame: Frame, settings: ChainSettings | str, calibration: Calibration | None) -> FrameState:
    if isinstance(settings, str):
        settings = get_profile(settings)
    res = FrameResult(status="rejected", profile=settings.profile, technique=settings.technique, seq=frame.seq,
                      t_ns=frame.t_ns, source=frame.source, calibrated=calibration is not None)
    return FrameState(frame, settings, calibration, res)


def _walk(state: FrameState, until: str | None = None) -> None:
    """Run the stages that apply, in order, timing each into ``result.stage_seconds``."""
    for stage in stages_of(state.settings.technique):
        if stage.applies(state):
            t0 = time.perf_counter()
            try:
                stage.run(state)
            finally:
                state.result.stage_seconds[stage.name] = time.perf_counter() - t0
        if stage.name == until:
            return


def run_stages(frame: Frame, settings: ChainSettings | str = "balanced", calibration: Calibration | None = None,
               until: str | None = None) -> FrameState:
    """Walk the stage table up to and including ``until`` (all by default); the state they leave.

    Raises :class:`~mtcw_core.results.Rejected` or :class:`~mtcw_core.results.NoTarget` as the
    stages do (for tools that need the intermediate lines, e.g. calibration);
    :func:`process_frame` is the total version.
    """
    state = _start(frame, settings, calibration)
    names = [st.name for st in stages_of(state.settings.technique)]
    if until is not None and until not in names:
        raise ValueError(f"until: unknown stage {until!r} (one of {', '.join(names)})")
    _walk(state, until)
    return state


def process_frame(frame: Frame, settings: ChainSettings | str = "balanced",
                  calibration: Calibration | None = None) -> FrameResult:
    """Run the chain on one frame. Never raises: a bad frame comes back ``rejected`` with a reason,
    a frame with nothing to range ``no_target`` with a reason."""
    state = _start(frame, settings, calibration)
    walk_total(state)
    return state.result


def walk_total(state: FrameState) -> None:
    """Walk the stages; a stage's end (``NoTarget``, ``Rejected``, any error) becomes the result's status."""
    res = state.result
    try:
        _walk(state)
    except NoTarget as why:
        res.status, res.reason = "no_target", str(why)
    except Rejected as rej:
        res.status, res.reason = "rejected", str(rej)
    except Exception as err:  # the chain never lets an exception escape
        res.status, res.reason = "rejected", f"internal_error: {type(err).__name__}: {err}"


__all__ = ["STAGES", "STAGE_NAMES", "TECHNIQUES", "stages_of", "Stage", "FrameState", "run_stages", "process_frame", "ChainSettings",
           "PROFILES", "get_profile", "FrameResult", "TargetPoint", "Rejected", "NoTarget", "Status", "Direction"]
