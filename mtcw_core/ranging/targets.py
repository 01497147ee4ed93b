"""Stages ``resolve`` and ``select``: each candidate's range, speed and sigma; which candidates are targets.

``resolve`` (:func:`resolve_targets`) turns every target candidate's pair observations into a
:class:`~mtcw_core.results.TargetPoint`: cycle resolution (``ml`` or the dissertation's
``seed``), the Fisher sigma of the used lines, scaled by the Birge ratio when the line phases
disagree with one range beyond their noise, and the velocity from the Doppler line.

``select`` (:func:`select_targets`) is the policy that decides which candidates are real
targets: the static candidate beside movers is often their own self-beat, a weak "mover" at a
static target's range is its phase-noise sidebands, and a "mover" with random line phases at
high SNR is the skirt of an incoherent line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.special import chdtrc, gammaincc
from scipy.stats import chi2 as chi2_dist

from ..calibration import Calibration
from ..dsp.doppler import CROSS_PULL_BINS, MIN_CARRIER_COHERENCE, DopplerEstimate, fd_max, quarters_resolve_hz, within
from ..dsp.extract import FAST_FADE_PART, LineFamily
from ..dsp.spectrum import search_length
from ..frame import Frame
from ..phase import C
from ..profiles import ChainSettings
from ..results import TargetPoint
from .mixing import consistency, mix, realness_chi2, sideband_products
from .triangulation import (Observations, RangeSolution, range_sigmas, resolve_ml, resolve_seed, tone_phase_sigma,
                            unambiguous_range)


@dataclass(frozen=True)
class Reference:
    """What the calibration (or the frame) says of the instrument: each tone's RF phase (rad)
    and the internal delay ``tau0_s`` (s)."""

    tone_phases_rad: dict[float, float]
    tau0_s: float
    #: each tone's line amplitude for one target (any common scale) and its relative sigma, where
    #: the calibration or the settings know them (:func:`amplitude_chi2`); None: not checked
    tone_amplitudes: dict[float, tuple[float, float]] | None = None
    #: the phases are the tones' own at the record's first sample (modulo pi), not only their
    #: differences: the frame's, declared with no calibration, or a calibration's that says so
    #: (``Calibration.phases_absolute``); a still echo's lines on a real receiver are then real
    #: against one range (:func:`~.mixing.realness_chi2`)
    absolute: bool = False

    @classmethod
    def of(cls, frame: Frame, settings: ChainSettings, cal: Calibration | None) -> "Reference":
        """The calibration's phases, delay and amplitudes where it is given, else the frame's
        phases and no delay; amplitudes from ``settings.tone_amplitudes`` where the calibration
        holds none (validated against the frame's tone count by the validate stage)."""
        tones = tuple(frame.tones_hz)
        if cal is not None:
            phases, tau0 = dict(zip(cal.tones_hz, cal.tone_phases_rad)), cal.tau0_s
        else:
            phases, tau0 = dict(zip(tones, frame.tone_phases_rad or (0.0,) * len(tones))), 0.0
        tol = settings.tone_amplitude_tolerance
        amps = None
        if cal is not None and cal.tone_amplitudes:
            std = cal.tone_amplitude_std or (0.0,) * len(tones)
            amps = {f: (a, math.hypot(s / a, tol)) for f, a, s in zip(cal.tones_hz, cal.tone_amplitudes, std)}
        elif settings.tone_amplitudes is not None and len(settings.tone_amplitudes) == len(tones):
            amps = {f: (a, tol) for f, a in zip(tones, settings.tone_amplitudes)}
        absolute = cal.phases_absolute if cal is not None else frame.tone_phases_rad is not None
        return cls(phases, tau0, amps, absolute)


def echo_delay_s(settings: ChainSettings, range_m: float) -> float:
    """``|dtau|`` (s): the delay of an echo from ``range_m`` relative to the LO, ``|2*L - d_LO|/c``."""
    return abs(2 * range_m - settings.lo_path_difference_m) / C


#: the static lines' one-envelope test (:func:`~mtcw_core.dsp.extract.envelope_rank_chi2`) is read
#: where the declared laser keeps at least this part of the carrier beat one line at every range
#: the echo could be (:func:`carrier_coherence`, :func:`_carrier_kept`): one echo's LO beat is one
#: real envelope times the tones' phasors whatever the carrier's phase, but a partly coherent
#: laser's pedestal puts on each line's segments parts the floor beside it does not show (not
#: understood) -- one echo at 0.59 m on six tones, balanced, residual per degree of freedom 0.08 /
#: 0.3 / 0.85 / 2.2 under a 1 kHz / 10 kHz / 100 kHz / 1 MHz laser (coherence 0.99998 ... 0.976);
#: the envelope probe's scenes 183 and 185, one echo each at coherence 0.974-0.976, right within
#: their sigmas, read 2.2-3.6
ENVELOPE_MIN_COHERENCE = 0.99
#: ... and flags only a residual above this many times its degrees of freedom (besides p < 1e-4, as
#: the line phases' chi2/dof 10): a laser left undeclared is taken as ideal, and ``moving-target``'s
#: own 100 kHz laser, undeclared, put one echo fading 0.6 record bins at 2^14 samples at 2.5-8.9
#: (the static scenes 0.1-1.2): the segments' fits gather the carrier beat's pedestal through their
#: sidelobes, most where the envelope crosses zero, which the record's floor does not show (the honesty
#: notes, twenty-eighth session); the envelope probe's 20925 reads 19 in its frame 0, 3.6 in frame 1
ENVELOPE_MIN_RATIO = 10.0


def _carrier_kept(settings: ChainSettings) -> bool:
    """Whether the declared laser keeps :data:`ENVELOPE_MIN_COHERENCE` of the carrier beat one line
    at every range an echo could be: an ideal laser (linewidth 0) anywhere, a partly coherent one
    only within a declared ``range_max_m`` (a point's own range may be one cycle of many: the
    envelope probe's scene 183, ranged 0.40 m, where coherence is 0.998, lay at 6.39 m, 0.974).
    A laser left undeclared is taken as ideal: a partly coherent one then may flag one echo."""
    if settings.laser_linewidth_hz == 0:
        return True
    if settings.range_max_m is None:
        return False
    return min(carrier_coherence(settings, r) for r in (settings.range_min_m, settings.range_max_m)
               ) >= ENVELOPE_MIN_COHERENCE


def carrier_coherence(settings: ChainSettings, range_m: float) -> float:
    """The part of the LO x echo carrier beat that stays one line, ``exp(-2*pi*linewidth*|dtau|)``.

    ``dtau = (2*L - d_LO)/c`` is the echo's delay relative to the LO (Lorentzian laser, delay much
    shorter than the record); 1 for an ideal laser or one declared coherent (linewidth 0).
    """
    return math.exp(-2 * math.pi * settings.laser_linewidth_hz * echo_delay_s(settings, range_m))


#: :func:`whole_self_beats` reads a mover's self-beat as at most this many times its prediction
#: (its carrier coherence no lower than 0.1: below, the prediction is mostly its lines' noise)
SELF_BEAT_MAX_SCALE = 10.0
#: ... and its prediction as scattering about ``c`` times it by this times ``1 - c``, relative: the
#: product of two lines' record means of the laser's phase term, ``|<exp(j*Phi)>|^2``, is ``c``
#: only on average (measured in review: 10-15 % rms at ``c`` = 0.43, none at ``c`` = 1)
SELF_BEAT_SCATTER = 0.25


def self_beat_scales(settings: ChainSettings, range_m: float, period_m: float, span_m: tuple[float, float]
                     ) -> tuple[float, float]:
    """The least and the most a mover's self-beat can be over its prediction from its LO beats,
    ``1/c`` (:func:`carrier_coherence` ``c``), each at most :data:`SELF_BEAT_MAX_SCALE`, over the
    ranges its CW point could be at: ``range_m + n * period_m`` within ``span_m`` (m, the frame's
    searched interval: one of its periods without a declared ``range_max_m``, where a point whose
    own lines repeat sooner -- a mover that lost a line -- could be in any of its cycles)."""
    lo, hi = span_m
    if not period_m > 0 or not math.isfinite(period_m) or hi - lo <= period_m * (1 + 1e-9):
        n_min = n_max = 0
    else:
        n_min = min(math.ceil((lo - range_m) / period_m - 1e-9), 0)
        n_max = max(math.floor((hi - range_m) / period_m + 1e-9), 0)
    # |2L - d_LO| is least at the candidate nearest d_LO/2 and largest at an end
    near = min(max(round((settings.lo_path_difference_m / 2 - range_m) / period_m), n_min), n_max) if n_max > n_min else 0
    scales = [min(1.0 / max(carrier_coherence(settings, range_m + n * period_m), 1e-300), SELF_BEAT_MAX_SCALE)
              for n in {n_min, near, n_max}]
    return min(scales), max(scales)


def whole_self_beats(fams: list[LineFamily], movers: list[tuple[int, TargetPoint, float]],
                     families: list[LineFamily], settings: ChainSettings, span_m: tuple[float, float]
                     ) -> list[LineFamily]:
    """The static lines of one photodiode with the rest of each found mover's self-beat taken out
    and bounded, where the laser is declared.

    The extract stage takes out each mover's self-beat as its LO beats predict it
    (:attr:`~mtcw_core.dsp.extract.LineFamily.self_beats`): a product of two of its lines, each
    holding ``sqrt(c)`` of its size at the echo's delay, so the prediction keeps
    :func:`carrier_coherence` ``c`` of a self-beat that (the echo with itself) has all of it. The
    delay is known modulo the point's period (:func:`self_beat_scales`, over ``span_m``): ``(1/c -
    1)`` times the prediction at the least ``1/c`` the mover's ranges allow is taken out; that
    part's noise -- the mover's lines' relative noise, and the prediction's own scatter about ``c``
    (:data:`SELF_BEAT_SCATTER`) -- enters the static lines' phase variance; and what more its
    other cycles in the span would leave bounds them
    (:attr:`~mtcw_core.dsp.extract.LineFamily.unexplained_v`, the point ``blended`` where it could
    turn them by 3 sigmas). A mover at 18.9 m under a 1 MHz laser (``c`` = 0.45; the envelope
    probe's scene 6729) left 55 % of its self-beat on a static echo's lines of the same size,
    turning them 0.07-0.12 rad (3-4 sigmas) together, the static point one 0.47 m cycle off; its
    3-tone plan repeats every 15 m, and the mover's point, 3.87 m, is taken at its word: a mover
    beyond the searched interval is mended as if inside it.

    Parameters
    ----------
    fams : the static candidate's families; movers : the movers' (target, point, period m)
    families : every family (the movers' own, for their lines' noise)
    span_m : the frame's searched range interval (m)

    Returns
    -------
    ``fams`` itself where nothing was mended, else a new list
    """
    if settings.laser_linewidth_hz <= 0 or not any(f.self_beats for f in fams):
        return fams
    out, mended = [], False
    for f in fams:
        extra, noise, rest = np.zeros_like(f.z), np.zeros(f.z.shape[1]), np.zeros(f.z.shape[1])
        for k, p, period in movers:
            pred = (f.self_beats or {}).get(k)
            if pred is None or not math.isfinite(p.range_m):
                continue
            least, most = self_beat_scales(settings, p.range_m, period, span_m)
            own = [g.phase_var for g in families if g.target == k]
            rel = 2.0 * float(np.median(np.concatenate(own))) if own else 1.0  # its lines' noise, two in the product
            size = np.sqrt(np.mean(np.abs(pred) ** 2, axis=0))
            extra += (least - 1.0) * pred
            # what is taken out beyond the extract stage's prediction, (least - 1) of it: its lines' noise,
            # and the prediction's scatter about c (SCATTER*(1 - c)/c of it); not the first prediction's
            # noise, which the chi2 of lines it left corrupted reads (widening all of it unflagged the envelope
            # probe's scene 8143: echoes far above the LO, a static point on the mover's range, 722 sigmas)
            noise += ((least - 1.0) * size) ** 2 * (min(rel, 1.0) + SELF_BEAT_SCATTER ** 2)
            rest += (most - least) * size
        usable = np.isfinite(f.phase_var)
        if not np.any(extra[:, usable]) and not np.any(rest[usable]):
            out.append(f)
            continue
        z = np.where(usable, f.z - extra, f.z)
        amp2 = np.maximum(np.mean(np.abs(z) ** 2, axis=0), 1e-300)
        var = f.phase_var * np.mean(np.abs(f.z) ** 2, axis=0) / amp2 + noise / amp2
        bound = rest if f.unexplained_v is None else f.unexplained_v + rest
        out.append(replace(f, z=z, phase_var=np.where(usable, var, f.phase_var), unexplained_v=bound))
        mended = True
    return out if mended else fams


#: the smallest speed sigma, in record bins (fs/N): the errors the chain measures reach ~2.5e-6 bin
#: (0.05 Hz on a 47.9 m/s mover, 2^18 samples at 5 GS/s, 20 dB of loss), but at such SNRs what no
#: line statistic sees -- two strong echoes' cross-beats on one photodiode -- moves a speed by
#: ~5e-6 bin (the map's "beat before its parent" case: |z| 4.9 under a floor of 1e-6)
SPEED_FLOOR_BINS = 1e-5


def cross_pull_hz(families: list[LineFamily], bin_hz: float) -> float:
    """How far an echo among the static lines can pull a mover's Doppler (Hz) through what it adds
    to the mover's lines -- on one photodiode its beat with the mover's echo, on IQ and balanced
    records its leak, moving below one record bin (a phasor of relative size ``rho`` up to a bin
    off: the same reach); 0 where no bound is carried (:attr:`LineFamily.cross_v`).

    That beat lies at the mover's lines less the static echo's own Doppler ``f_s``, a phasor
    ``rho = A_s/A_L`` of each line's size (the mover's carrier with the static sideband, or its
    sideband with the static carrier; ``A_L`` the LO's amplitude): a phase wobble of ``rho`` at
    ``f_s``, which pulls the line by at most ``rho*f_s`` (record bins), and by at most
    :data:`CROSS_PULL_BINS` bins times ``rho`` whatever ``f_s`` is. ``f_s`` lies below the
    static guard: where the static lines are mostly that echo's own, their width in the search
    spectrum bounds it (:attr:`LineFamily.cross_x`; issue 12 case 3's still target: the mover's
    speed sigma was ~200x its error at the largest), else the bound takes the largest.
    :func:`~mtcw_core.dsp.extract.cross_beat_bound` is ``A_s*A_m*a_0*a_i``, the mover's sideband
    line ``2*A_L*A_m*a_i`` (``a_0 <= 1``): ``rho`` is at most twice their ratio, taken over the
    mover's lines by energy (one ``rho`` for all tones). The envelope probe's scene 5081: an ideal
    laser, a mover at 26 dB of loss and an echo 40 dB under it, 0.39 record bin from zero Doppler,
    that the chain does not report -- the mover's speed 5-12 sigmas off at a stated 0.6 Hz, the
    pull 3-7 Hz."""
    num = den = 0.0
    reach = CROSS_PULL_BINS
    for f in families:
        if f.cross_v is None:
            continue
        use = np.isfinite(f.phase_var)
        num += float(np.sum(f.cross_v[use] ** 2))
        den += float(np.sum(np.mean(np.abs(f.z[:, use]) ** 2, axis=0)))
        if f.cross_x is not None:
            reach = min(reach, f.cross_x)
    return 2.0 * math.sqrt(num / den) * reach * bin_hz if den > 0 else 0.0


def shared_phase_psd(settings: ChainSettings, range_m: float) -> float:
    """Low-frequency two-sided PSD (rad^2/Hz) of the phase a target's lines share: the declared
    laser's phase noise over the echo's delay relative to the LO, ``2*pi*linewidth*dtau^2``.

    A Lorentzian laser's phase is a Wiener process (``S_phi(f) = linewidth/(2*pi*f^2)``); its
    difference over ``dtau`` has ``S(f) = 4*sin^2(pi*f*dtau)*S_phi(f)``, flat at
    ``2*pi*linewidth*dtau^2`` for ``f << 1/dtau`` (its integral is the familiar
    ``2*pi*linewidth*dtau``). 0 for a laser declared coherent (linewidth 0).
    """
    return 2 * math.pi * settings.laser_linewidth_hz * echo_delay_s(settings, range_m) ** 2


def slope_phase_var(linewidth_hz: float, tau_s: float, duration_s: float) -> float:
    """Variance (Hz^2) of the least-squares frequency over ``duration_s`` of a line whose phase is
    the delayed self-heterodyne one, ``Phi(t) = phi(t) - phi(t - tau)`` of a Lorentzian laser
    (``phi`` a Wiener process of rate ``D = 2*pi*linewidth``, so ``Cov(Phi(t), Phi(t')) =
    D*max(0, tau - |t - t'|)``): with the slope's weights ``12*(t - T/2)/T^3`` it is
    ``D*(12*tau^2/T^3 - 12*tau^3/T^4 + 2.4*tau^5/T^6)/(4*pi^2)`` up to ``tau = T``
    (``12*D*tau^2/(4*pi^2*T^3)`` for a short delay: the flat PSD ``S = 2*pi*linewidth*tau^2``'s
    ``3*S/(pi^2*T^3)``) and ``2.4*D/(4*pi^2*T)`` beyond, two independent random walks."""
    r = min(tau_s / duration_s, 1.0)
    d = 2 * math.pi * linewidth_hz
    return d * (12 * r**2 - 12 * r**3 + 2.4 * r**5) / duration_s / (4 * math.pi**2)


#: a whole-record fit's frequency under that phase (PE's lines, AB's baseband line) is stated at this
#: many times :func:`slope_phase_var`: the maximum of a line's power is no least-squares slope where
#: the phase wanders a radian and more, and scattered 0.86 / 1.2 / 1.46 times its sigma for PE targets
#: 10 / 30 / 103.5 m away (100 kHz laser, 2^16 samples), 1.34 / 1.12 / 1.77 for AB targets 8.5 / 20 /
#: 35 m away (500 kHz; 14-30 frames each: ~13-19 % each)
SHARED_PHASE_MARGIN = 2.0


def shared_phase_error_hz(linewidth_hz: float, tau_s: float, duration_s: float) -> float:
    """The frequency error (Hz) a whole-record fit states for the phase its lines share over an
    echo delay ``tau_s``: :func:`slope_phase_var` times :data:`SHARED_PHASE_MARGIN`, its root."""
    return math.sqrt(SHARED_PHASE_MARGIN * slope_phase_var(linewidth_hz, tau_s, duration_s))


def phase_psd(settings: ChainSettings, range_m: float, dop: DopplerEstimate, iq: bool) -> float:
    """The low-frequency PSD (rad^2/Hz) of the phase a target's lines share, for the speed sigma:
    the declared laser's at the point's range (:func:`shared_phase_psd`), or what the pedestal
    about its lines shows (``dop.pedestal_psd``) where that is more -- a range known modulo the
    unambiguous range leaves the echo's delay, and so the declared laser's phase noise, unknown:
    a mover at 10.85 m ranged 1.855 m in a 3.0 m frame was given 34x too little, its speed z std
    3.5. The pedestal about a real record's low line carries its image's too, which the gain's 1.5
    already counts. 0 for a laser declared coherent (its lines have no pedestal; at ~90 dB the
    window's own skirt would pass for one)."""
    if settings.laser_linewidth_hz <= 0:
        return 0.0
    return max(shared_phase_psd(settings, range_m), dop.pedestal_psd / (1.0 if iq else 1.5))


#: a phase advance's measured shared phase counts as the one its floor states (its low-draw margin
#: then left to the floor, :func:`velocity`) when at most this many times that floor
SHARED_FLOOR_AGREES = 2.0


def velocity(dop: DopplerEstimate, frame: Frame, families: list[LineFamily], iq: bool, coherence: float = 1.0,
             fd_max_hz: float | None = None, phase_psd: float = 0.0, sideband_direction: bool = False
             ) -> tuple[float, float, str, float]:
    """Radial speed (m/s), its sigma (m/s), direction and the smallest measurable speed (m/s).

    The sigma combines the frequency Cramér–Rao bound of the target's Doppler-shifted lines, the
    refinement's own error (which includes the carrier phase all lines share: the laser's phase
    noise over the echo delay) and the line's wander (incoherent laser), with a floor of
    :data:`SPEED_FLOOR_BINS`. A Doppler refined by phase advance carries its whole error itself,
    the shared carrier phase's wander measured by the refinement -- but not less than what a
    declared laser's shared phase -- or the pedestal about its lines, where that shows more -- makes
    of it through the refinement's own gain (``dop.measured_phase_gain``: a few parts' scatter can
    draw low; where this floor explains what they measured, within :data:`SHARED_FLOOR_AGREES`,
    the margin their scatter carried against such a draw is left to it); one reassigned over the whole
    record -- or fitted on it below the search's guard (``fit``) -- adds what the shared phase's
    PSD ``phase_psd`` (:func:`phase_psd`) does to it, and the wander (once: where the lines' local
    floors held that phase's pedestal, ``dop.shared_overlap_var_hz2``, the error from the white
    floor carries it, and the local floors' error is the least stated).
    A target with no Doppler line is ``static``, with the smallest detectable speed as its sigma --
    unless the carrier beat is not a line at the target's range (``coherence`` below
    :data:`MIN_CARRIER_COHERENCE`), or the static lines' envelope turns faster than the static
    claim's sigma allows (:attr:`LineFamily.fast_fade` above
    :data:`~mtcw_core.dsp.extract.FAST_FADE_PART`: a mover whose Doppler lines stayed under the
    search's threshold): then no speed up to the search's limit
    ``fd_max_hz`` could have shown, and the point says 0 with that limit as its sigma, direction
    ``unknown``.
    A real detector reports ``unknown`` (spec: it sees ``|f_d|``), or with ``sideband_direction``
    the direction its sidebands' modulation Doppler decided (``dop.motion_sign``).
    """
    lam = frame.wavelength_m
    n, fs = frame.n, frame.fs_hz
    v_min = dop.min_detectable_hz * lam / 2
    if not dop.detected:
        fade = max((f.fast_fade or 0.0 for f in families if f.target == 0), default=0.0)
        if (coherence < MIN_CARRIER_COHERENCE or fade > FAST_FADE_PART) and fd_max_hz is not None:
            v_max = fd_max_hz * lam / 2
            return 0.0, v_max, "unknown", v_max
        return 0.0, v_min, "static", v_min
    if dop.method in ("reassigned", "fit"):
        # one window over the whole record: its own white-noise error and scatter, plus what the
        # phase the lines share (laser phase noise over the echo delay) does to it, from physics
        # (it cannot be measured there), and the wander the lines' width shows; where the lines'
        # local floors held that phase's pedestal, their error from the white floor with it, but
        # never less than theirs
        # (with no overlap stated the two simply add)
        own = max(dop.refine_error_hz**2,
                  dop.refine_error_hz**2 - dop.shared_overlap_var_hz2 + dop.shared_phase_gain * phase_psd)
        sig_f = math.sqrt(own + dop.wander_hz**2)
    elif dop.refined:
        # the refinement states the white-noise error of every line it used -- the carrier's
        # baseband line, far stronger than the sidebands, among them -- with their scatter and
        # the shared carrier phase measured across the record, which is the line's wander: the
        # sidebands' bound below would overstate it ~10x, the wander guessed from the line's width
        # (noise widens a weak line) up to 100x -- but not less than what a declared laser's shared
        # phase makes of it: measured on a few parts, a low draw stated too little (the envelope
        # probe's scene 2816, a 100 kHz laser: 2.3 kHz off at a stated 0.34 kHz, 0.67 kHz expected)
        floor = math.sqrt(dop.measured_phase_gain * phase_psd)
        # the measured shared phase's margin against a low draw of its few degrees of freedom is the
        # floor's job where that floor -- the declared laser, or the pedestal about the lines where
        # it shows more (many bins: no low draw) -- explains what was measured (within
        # SHARED_FLOOR_AGREES); a measured phase far above it keeps its margin
        alone = math.sqrt(max(dop.refine_error_hz**2 - dop.shared_overlap_var_hz2, 0.0))
        sig_f = max(alone if alone <= SHARED_FLOOR_AGREES * floor else dop.refine_error_hz, floor)
    else:
        inv_var = 0.0
        for fam in families:
            if fam.name == "S":
                continue
            # CRB of a sinusoid's frequency: var_f = 3*s2*fs^2/(pi^2*A^2*N^3) (real), 1.5 (complex)
            # expressed with the phase variance 2*s2/(N*A^2) (real) or s2/(2*N*A^2) (complex)
            c = 1.5 if not iq else 3.0
            var_f = c * fam.phase_var * fs**2 / (np.pi**2 * n**2)
            inv_var += float(np.sum(1 / var_f))
        sig_f = math.hypot(1 / math.sqrt(inv_var) if inv_var > 0 else math.inf, dop.refine_error_hz, dop.wander_hz)
    sig_f = max(math.hypot(sig_f, cross_pull_hz(families, fs / n), dop.beat_pull_hz), SPEED_FLOOR_BINS * fs / n)
    if iq or (sideband_direction and dop.motion_sign):
        # the sign of f_d = -2v/lambda: IQ carries it, one photodiode's sidebands' modulation
        # Doppler may have decided it
        v = -(dop.fd_hz if iq else dop.motion_sign * abs(dop.fd_hz)) * lam / 2
        return v, sig_f * lam / 2, "receding" if v > 0 else "approaching", v_min
    return abs(dop.fd_hz) * lam / 2, sig_f * lam / 2, "unknown", v_min


def median_snr(p: TargetPoint) -> float:
    """Median SNR of a point's lines (dB): one strong line does not make a target strong."""
    return float(np.median(list(p.tone_snr_db.values())))


def _search_interval(settings: ChainSettings, l_unamb: float, coarse: tuple[float, float] | None
                     ) -> tuple[float, float, bool]:
    """The range interval searched (m), and whether the coarse range leaves the period in doubt.

    The phases fix the range modulo ``l_unamb``; a quasi-CW coarse range interval picks the
    period centred on it.
    """
    if coarse is None:
        lo = settings.range_min_m
        hi = settings.range_max_m if settings.range_max_m is not None else lo + l_unamb
        return lo, hi, False
    centre, half = 0.5 * (coarse[0] + coarse[1]), 0.5 * (coarse[1] - coarse[0])
    return centre - 0.5 * l_unamb, centre + 0.5 * l_unamb, half >= 0.5 * l_unamb


def _tone_snr(fams: list[LineFamily]) -> dict[str, float]:
    out: dict[str, float] = {}
    for f in fams:
        for tone, snr in zip(f.tone_hz, f.snr_db):
            key = f"{tone:.0f}"
            out[key] = max(out.get(key, -np.inf), float(snr))
    return out


def cycle_slip_probability(fams: list[LineFamily], ref: Reference, sol: RangeSolution, chi2_best: float,
                           scale: float, min_snr_db: float, shared_var: float = 0.0) -> float:
    """The odds that another cycle is the true one, from the line phases' likelihood.

    For each runner-up range ``L_k`` of the cycle resolution, ``exp(-(chi2(L_k) - chi2(L))/(2*s))``
    with ``chi2`` the line phases' misfit (:func:`~mtcw_core.ranging.mixing.consistency`) and ``s``
    the Birge ratio (>= 1) when the phases are less consistent than their noise; summed. Near the
    detection threshold a wrong cycle is as likely as the right one and the margin of the cost
    alone does not say so. ``shared_var``: the tones' phase drift the families share
    (:func:`~mtcw_core.ranging.mixing.consistency`; ``chi2_best`` read alike).

    Returns
    -------
    float, the summed odds of the runners-up against the solution, clipped to [0, 1]
    """
    total = 0.0
    for alt in sol.alternatives_m:
        c2, _ = consistency(fams, ref.tone_phases_rad, ref.tau0_s + 2 * alt / C, min_snr_db, shared_var)
        total += math.exp(-max(c2 - chi2_best, 0.0) / (2 * scale))
    return float(min(total, 1.0))


#: the line phases' chi2 scales the range sigma by its Birge ratio where it is this improbable under
#: one range, white noise and the declared drift of the tone phases (it was 1e-3: the envelope
#: probe's scene 2706, two static targets on three tones whose blended phases miss one range by
#: chi2 8.5-13.6 on 2 dof, p 1e-3 to 0.014, ranged 6 mm off at 0.8-1.1 mm, z -6 and -8)
BIRGE_P = 0.05
#: ... and flags the point ``blended`` where it is this improbable (besides a chi2/dof above the
#: profile's ``blended_chi2``): a blend of two echoes on one line set fits a range far from both
#: (the envelope probe's scene 4314: two static echoes 4 dB apart on four tones, chi2 26.5 on 3
#: dof, p 8e-6, ranged 12 m off with a Birge-scaled sigma of 4 mm)
BLENDED_P = 1e-4


def solve_target(fams: list[LineFamily], obs: Observations, dop: DopplerEstimate, frame: Frame,
                 settings: ChainSettings, ref: Reference, coarse: tuple[float, float] | None,
                 l_unamb: float | None = None) -> TargetPoint:
    """One candidate's point: cycle resolution, sigma, consistency, velocity.

    Parameters
    ----------
    fams : the candidate's line families; obs : their pair observations (stage ``mix``)
    dop : the candidate's Doppler line (not detected for the static candidate)
    coarse : the quasi-CW coarse range interval (m), or None
    l_unamb : the unambiguous range of ``obs`` (m); computed from ``obs.df_hz`` when not given
    """
    if l_unamb is None:
        l_unamb = unambiguous_range(obs.df_hz)
    lo, hi, ambiguous = _search_interval(settings, l_unamb, coarse)
    if settings.method == "seed":
        sol = resolve_seed(obs, ref.tau0_s, hi, lo)
    else:
        sol = resolve_ml(obs, ref.tau0_s, (lo, hi), settings.points_per_cycle)
    ok = [f.snr_db >= settings.min_line_snr_db for f in fams]
    used = [(f, m) for f, m in zip(fams, ok) if np.sum(m) >= 2]
    freqs, variances = [f.tone_hz[m] for f, m in used], [f.phase_var[m] for f, m in used]
    # the pair estimator's own variance: over its lines' noise rings where they were read (a mover's:
    # the laser's phase noise about them moves them together), with the lines independent where not
    sigma, alone = range_sigmas(freqs, variances, [None if f.ring is None else f.ring.columns(m) for f, m in used])
    if not dop.detected:  # the static lines' ring only widens (extract._target_rings)
        sigma = max(sigma, alone)
    # noise the rings show moving the lines together, beyond what independent lines would give (a
    # strong echo's pedestal about a slow mover's lines), widens the cycle-slip odds as much
    together = (sigma / alone) ** 2 if 0 < alone < math.inf and math.isfinite(sigma) else 1.0
    # the static lines' sizes against one target's (two echoes on one Doppler-0 line set; on an IQ
    # record also its sidebands' sizes), and the phase variance per tone such a blend may add
    tau = ref.tau0_s + 2 * sol.range_m / C
    a_chi2, a_dof, blend_var, one_echo = _static_sizes(
        fams, dop, frame, ref, settings, (tau, _aliases(sol.range_m, l_unamb, (lo, settings.range_max_m), coarse)))
    u_chi2, u_dof = sideband_split(fams, dop.fd_hz, max(settings.min_line_snr_db, SPLIT_MIN_SNR_DB)) if (
        dop.detected) else (0.0, 0)  # a mover's carrier, 2*psi, on every tone
    # do the line phases agree with one range within their noise and the tones' declared drift?
    # (Birge ratio; the flags and the cycle odds read the phases without the blend's variance)
    tone_var = settings.tone_phase_sigma_rad ** 2
    cfams = [replace(f, phase_var=f.phase_var + tone_var) for f in fams] if tone_var else fams
    chi2, dof = consistency(cfams, ref.tone_phases_rad, tau, settings.min_line_snr_db)
    ratio = chi2 / dof if dof > 0 else 1.0
    # chdtrc is chi2.sf itself, without scipy.stats' ~40 us of argument handling per call
    p_fit = chdtrc(dof, chi2) if dof > 0 else 1.0
    sigma = _drift_and_blend(sigma, (freqs, variances), fams, (tone_var, blend_var), (chi2, dof), ref, tau, settings)
    # known timing jitter moves every tone phase as a range shift c*dt/2 (invisible in one frame)
    sigma = math.hypot(sigma, C * settings.timing_jitter_s / 2)
    p_slip = _slip_odds(cfams, (tone_var, blend_var), (chi2, dof), ref, sol, tau, together, settings.min_line_snr_db)
    unexplained = unexplained_sigmas(fams, settings.min_line_snr_db)
    # a "mover" one bump of a pedestal that moves every line together could have made
    # (the bins the search read: one sign of Doppler on a real record, both on IQ, in its part of the
    # record -- the whole of one up to 2^16 samples, whatever the profile's fraction; a quasi-CW
    # record's search reads its longest echo window, fewer: counted as the record's, the odds err high)
    bins = (2 if frame.receiver == "iq" else 1) * fd_max(frame.tones_hz, settings) * search_length(
        frame.n, settings.doppler_fraction) / frame.fs_hz
    ghost = pedestal_ghost_odds(dop, fams, settings.doppler_threshold, bins) > GHOST_ODDS_MAX
    v, vs, direction, v_min = velocity(dop, frame, fams, frame.receiver == "iq",
                                       carrier_coherence(settings, sol.range_m), fd_max(frame.tones_hz, settings),
                                       phase_psd(settings, sol.range_m, dop, frame.receiver == "iq"),
                                       settings.sideband_direction)
    return TargetPoint(
        range_m=sol.range_m, range_sigma_m=sigma, velocity_mps=v, velocity_sigma_mps=vs, direction=direction,
        snr_db=max(float(np.max(f.snr_db)) for f in fams), margin=sol.margin,
        residual_rms_rad=sol.residual_rms_rad, near_edge=sol.near_edge,
        cycle_ambiguous=bool(ambiguous or p_slip > settings.cycle_slip_max), cycle_slip_prob=p_slip,
        # blended: the line phases fit no one range, or the Doppler line's own lines disagree (two
        # movers the search could not resolve: the range from their mixed phases is neither's), or
        # the movers' beats come near their own lines (one photodiode, echoes near the LO's power, or
        # above it with two movers or more: ``echo_beats``), or
        # (the static lines, one photodiode) Doppler lines no mover found explains could have put
        # their self-beats on them, as large as several of their sigmas, or the static lines' sizes
        # are not one target's, or their common phase or their segments not one echo's (two echoes
        # fading apart), or a mover's sidebands not one carrier's (:func:`sideband_split`); a
        # Doppler line that hid a second mover (``dop.unresolved``) is judged in resolve_targets
        blended=bool((dof > 0 and (ratio > settings.blended_chi2 or p_fit < BLENDED_P))
                     or dop.lines_chi2 > settings.blended_lines_chi2
                     or dop.beat_ambiguous or any(f.echo_beats for f in fams) or unexplained > UNEXPLAINED_SIGMAS
                     or unexplained_sigmas(fams, settings.min_line_snr_db, "copy_v") > UNEXPLAINED_SIGMAS or ghost
                     or any(d > 0 and not chdtrc(d, c) >= BLENDED_P for c, d in
                            ((a_chi2, a_dof), *one_echo, (u_chi2, u_dof)))),
        chi2_per_dof=float(ratio), doppler_hz=dop.fd_hz,
        tone_snr_db=_tone_snr(fams), seed_sigma_k_m=sol.seed_sigma_k_m, speed_min_mps=v_min,
    )


#: a Doppler line is taken for noise that moved its lines together where the odds that noise alone
#: put it there (:func:`pedestal_ghost_odds`) exceed this
GHOST_ODDS_MAX = 1e-5
#: ... read over at least this many ring rows (fewer: no correlation to speak of)
GHOST_MIN_ROWS = 16


def pedestal_ghost_odds(dop: DopplerEstimate, fams: list[LineFamily], factor: float, search_bins: float) -> float:
    """The odds that noise alone made a found Doppler line, counting its lines' noise as the rings
    show it moving together (``factor``: the search's threshold per line; ``search_bins``: the
    Doppler bins it searched).

    The search sums ``L`` lines' ratios to their floors and asks ``factor*L``: for independent lines
    a Gamma(L) tail, astronomically small. Where a strong echo's phase-noise pedestal is the floor
    about every line, it is one process at every tone: the lines' powers rise and fall together, and
    one bump of it is a "mover" at every line at once, with the echo's own tone phases (the envelope
    probe's scene 6001: a static echo at 7 dB loss under a 100 kHz laser, its lines faded, a
    "mover" at its range at 1.3 m/s, 193 sigmas from 0, unflagged). Here the lines count as the
    participation ratio ``P`` of their rings' power correlations, ``(sum l)^2 / sum l^2`` over its
    eigenvalues (``L`` for independent lines, 1 for one process), and each line's ratio as measured
    against the noise the rings show about it (the floor the search used reads a pedestal rising
    toward the lines low): ``search_bins`` times the Gamma(P) tail at ``P`` times the mean ratio.
    0 where no rings were read.
    """
    rings = [(f.ring.rows, f.phase_var) for f in fams if f.ring is not None]
    lines = dop.threshold / factor if factor > 0 else 0.0
    # a sub-guard fit's score is its baseband line's SNR against a threshold of its own: not a sum
    if not dop.detected or dop.method == "fit" or not rings or lines < 1:
        return 0.0
    rows = np.concatenate([r for r, _ in rings], axis=1)
    var = np.concatenate([v for _, v in rings])
    use = np.isfinite(var) & (var > 0) & np.any(rows != 0, axis=0)
    if np.sum(use) < 2:
        return 0.0
    power = np.abs(rows[:, use]) ** 2
    if power.shape[0] < GHOST_MIN_ROWS:
        return 0.0
    corr = np.nan_to_num(np.corrcoef(power.T))
    np.fill_diagonal(corr, 1.0)  # a column of constant power correlates with nothing
    eig = np.linalg.eigvalsh(corr)
    p_eff = float(np.clip(np.sum(eig) ** 2 / np.sum(eig**2), 1.0, lines))
    kappa = max(float(np.mean(np.mean(power, axis=0) / var[use])), 1.0)
    return float(min(1.0, search_bins * gammaincc(p_eff, p_eff * dop.score / lines / kappa)))


def _slip_odds(cfams: list[LineFamily], var: tuple[float, float], fit: tuple[float, int], ref: Reference,
               sol: RangeSolution, tau: float, together: float, min_snr_db: float) -> float:
    """The odds of another cycle (:func:`cycle_slip_probability`) with the line phases' noise and the
    tones' declared drift (``cfams``, their chi2 and dof at the solution ``fit``; Birge-scaled, and
    widened by ``together``, the rings' shared noise) -- and a blend's pull on each tone's phase
    (``blend_var``, rad^2: :func:`blend_phase_var`). Where the sizes show a second echo it pulls the
    phases as far as it scatters the sizes, and a runner-up cycle it brings near is as likely as the
    solution (the envelope probe's scene 30119: two still echoes 2.4 dB apart on three tones, margin
    0.007, ranged 178 sigmas off) -- and a static echo's beat (one photodiode) or leak (IQ,
    balanced) on a mover's lines (:attr:`LineFamily.cross_v`, each line's turn as its sigma; both
    counted per line, though a beat may move a mover's two sidebands alike: scene 31334, a mover 44 dB under a
    static echo near the LO's power, turns of 1.1 sigmas on three tones, ranged two cycles of its
    finest pair off at 97 sigmas); the Birge ratio is then read with them, so each is counted once.
    ``var``: ``(tone_var, blend_var)``; the tones' drift ``tone_var`` (rad^2, in ``cfams`` already)
    is one draw per tone for all the families (:func:`~mtcw_core.ranging.mixing.consistency`'s
    ``shared_var``: a mover's two sidebands are not two readings of it -- scene 33007, 0.014 rad of
    drift declared on three tones, a wrong cycle 10.4 chi2 better counted twice, 11934 sigmas off)."""
    tone_var, blend_var = var
    chi2, dof = fit
    extra = [blend_var + (0.0 if f.cross_v is None else _turns(f, np.ones(f.tone_hz.size, bool), f.cross_v) ** 2)
             for f in cfams]
    widened = any(np.any(e > 0) for e in extra)
    if widened:
        cfams = [replace(f, phase_var=f.phase_var + e) for f, e in zip(cfams, extra)]
    if tone_var > 0 or widened:
        # (the lines a wider variance takes under the threshold leave the fit: its own dof)
        chi2, dof = consistency(cfams, ref.tone_phases_rad, tau, min_snr_db, tone_var)
    ratio = chi2 / dof if dof > 0 else 1.0
    return cycle_slip_probability(cfams, ref, sol, chi2, max(ratio, 1.0) * max(together, 1.0), min_snr_db,
                                  tone_var)


def _drift_and_blend(sigma: float, used: tuple[list, list], fams: list[LineFamily], var: tuple[float, float],
                     fit: tuple[float, int], ref: Reference, tau: float, settings: ChainSettings) -> float:
    """The range sigma (m) with the tones' declared drift and a blend's pull on each tone's phase
    (``var``: their variances, rad^2; :func:`blend_phase_var`), both independent per tone and
    invisible in one frame's phases (:func:`~.triangulation.tone_phase_sigma` through the fit's
    weights, ``used``: its lines' tones and phase variances per family), Birge-scaled where the
    line phases are improbable (p < :data:`BIRGE_P`) under one range with both (``fit``: their chi2
    and dof with the drift alone; with a blend, read again with it: its pull scatters the phases,
    and is counted once) -- and never under the sigma without the blend (read again, the Birge
    ratio may fall by more than the blend adds: a review's scene 536, 19.5 -> 12.4 mm)."""
    tone_var, blend_var = var

    def scaled(extra: float, chi2: float, dof: int) -> float:
        out = math.hypot(sigma, tone_phase_sigma(*used, math.sqrt(tone_var + extra)))
        return out * math.sqrt(chi2 / dof) if dof > 0 and chdtrc(dof, chi2) < BIRGE_P else out

    without = scaled(0.0, *fit)
    if blend_var <= 0:
        return without
    chi2, dof = consistency([replace(f, phase_var=f.phase_var + tone_var + blend_var) for f in fams],
                            ref.tone_phases_rad, tau, settings.min_line_snr_db)
    return max(without, scaled(blend_var, chi2, dof))


#: :func:`_aliases` lists at most this many periods of the pairs beyond the solution (a range with
#: no declared bound: the lattice ``f_r*k/g`` of integer tones repeats long before)
ALIAS_MAX = 4096


def _aliases(range_m: float, l_unamb: float, bounds: tuple[float, float | None], coarse: tuple[float, float] | None
             ) -> tuple[float, np.ndarray]:
    """The pairs' period in delay (s) and the whole periods ``k`` (shape (K,)) the true range may lie
    from ``range_m`` (m): within ``bounds`` (the search's start and ``range_max_m``, None: none, at
    most :data:`ALIAS_MAX`), or within a quasi-CW coarse range's interval (m; one period where it
    picks one, more where it leaves the period in doubt)."""
    period = 2 * l_unamb / C
    if not math.isfinite(l_unamb) or l_unamb <= 0:
        return period, np.zeros(1)
    if coarse is not None:
        k_lo, k_hi = math.ceil((coarse[0] - range_m) / l_unamb), math.floor((coarse[1] - range_m) / l_unamb)
        return period, np.arange(min(k_lo, 0), max(k_hi, 0) + 1)
    lo, hi = bounds
    k_lo = -math.floor(max(range_m - lo, 0.0) / l_unamb)
    k_hi = ALIAS_MAX if hi is None else max(math.floor((hi - range_m) / l_unamb), 0)
    return period, np.arange(k_lo, min(k_hi, ALIAS_MAX) + 1)


def _static_sizes(fams: list[LineFamily], dop: DopplerEstimate, frame: Frame, ref: Reference,
                  settings: ChainSettings, at: tuple[float, tuple[float, np.ndarray]]
                  ) -> tuple[float, int, float, list[tuple[float, int]]]:
    """A static candidate's line sizes: :func:`amplitude_chi2` (chi2, dof), the phase variance per
    tone (rad^2) a second echo on its line set may put on it (:func:`blend_phase_var`) and what one
    echo's real envelope implies, as (chi2, dof) pairs: on an IQ record its sidebands' sizes
    (:func:`sideband_chi2`), and with an unmodulated LO and the tones' own phases known
    (``ref.absolute``) its lines' common phase (:func:`_real_envelope`) at ``at``: the round-trip
    delay (s) and its aliases (:func:`_aliases`), pooled; and on a real record its lines' segments
    against one envelope (:attr:`~mtcw_core.dsp.extract.LineFamily.envelope_chi2`) where the
    declared laser keeps the carrier one line (:func:`_carrier_kept`) and the residual exceeds
    :data:`ENVELOPE_MIN_RATIO` times its dof; zeros and no pairs for a mover. The blend's phase
    variance is read from the sizes and, where it is read, from the common phase alike: a second
    echo of relative size ``rho`` moves the sizes by ``rho*cos(dphi_i)`` and the phases by
    ``rho*sin(dphi_i)``, and the lines' common phase is the part of the latter one range leaves
    (the envelope probe's scene 37755: a still echo beside a slow mover's self-beat, one
    photodiode, chi2 7.7 on 1 dof, ranged 4.2 sigmas off); the larger is taken."""
    if dop.detected:
        return 0.0, 0, 0.0, []
    a_chi2, a_dof, allowed = _amplitude_fit(fams, ref.tone_amplitudes, settings.min_line_snr_db)
    blend = blend_phase_var(a_chi2, a_dof, allowed)
    s_chi2, s_dof = 0.0, 0
    if frame.receiver == "iq":
        s_chi2, s_dof = sideband_chi2(fams, settings.sideband_tolerance, settings.min_line_snr_db)
    # (not on a quasi-CW record: its windows' lines at 65-75 dB of loss read a common phase twice
    # its stated noise, chi2 mean 2.3-2.9 on 1 dof with their pairs' near 1, unexplained -- left out)
    if ref.absolute and frame.architecture == "unmodulated_lo" and frame.pulse is None:
        r_chi2, r_dof, r_allowed = _real_envelope(fams, frame.receiver == "iq", ref, settings, at)
        blend = max(blend, blend_phase_var(r_chi2, r_dof, r_allowed))
        s_chi2, s_dof = s_chi2 + r_chi2, s_dof + r_dof
    envelope = [(c, d) for c, d in (f.envelope_chi2 for f in fams if f.envelope_chi2)
                if c > ENVELOPE_MIN_RATIO * d] if _carrier_kept(settings) else []
    return a_chi2, a_dof, blend, [(s_chi2, s_dof)] + envelope[:1]


def _sidebands(fams: list[LineFamily]) -> dict[str, LineFamily]:
    """A candidate's upper (``"U"``) and lower (``"L"``) line families by name, those it has."""
    return {f.name: f for f in fams if f.name in ("U", "L")}


def _real_envelope(fams: list[LineFamily], iq: bool, ref: Reference, settings: ChainSettings,
                   at: tuple[float, tuple[float, np.ndarray]]) -> tuple[float, int, float]:
    """:func:`~.mixing.realness_chi2` over a static candidate's families (on an IQ record its
    sidebands' products, :func:`~.mixing.sideband_products`, ``power`` 2) at ``at`` (delay, s, and
    aliases): (chi2, dof) and the harmonic mean of the lines' phase variances it read (rad^2; each
    weighs its own excess, :func:`blend_phase_var`)."""
    tone_var = settings.tone_phase_sigma_rad**2
    power, read = 1, fams
    if iq:
        sides = _sidebands(fams)
        prod = sideband_products(sides["U"], sides["L"]) if len(sides) == 2 else None
        power, read = 2, [] if prod is None else [prod]
    chi2, dof, weight = 0.0, 0, []
    for f in read:
        c, d = realness_chi2(f, ref.tone_phases_rad, at[0], settings.min_line_snr_db, tone_var, at[1], power)
        if d:
            chi2, dof = chi2 + c, dof + d
            weight.append(1.0 / (f.phase_var[f.snr_db >= settings.min_line_snr_db] / power**2 + tone_var))
    return chi2, dof, (1.0 / float(np.mean(np.concatenate(weight))) if dof else 0.0)


def blend_phase_var(chi2: float, dof: int, allowed: float) -> float:
    """The phase variance per tone (rad^2) that a second echo on one line set may put on a static
    point's lines, read from their sizes: ``(chi2/dof - 1) * allowed`` where the sizes' chi2 against
    one target's (:func:`amplitude_chi2`, ``allowed`` the relative variance it allows a size: the
    harmonic mean over the tones, as each tone's term weighs its excess) is improbable at
    :data:`BIRGE_P`, else 0 -- and 0 where they are improbable at :data:`BLENDED_P`: the point is
    flagged ``blended`` there, the blend may be as strong as the echo (``rho`` near 1, where sizes
    and phases no longer move alike), and a sigma of metres (a review's scene 20085: 9.8 mm ->
    23.7 m) moved the selections that read it (:func:`_same_range`).

    A second echo of relative size ``rho`` adds ``rho*exp(j*dphi_i)`` to every line (``dphi_i`` its
    range and carrier phase against the first's, spread over the tones): each line's size moves by
    ``rho*cos(dphi_i)`` and its phase by ``rho*sin(dphi_i)``, the same variance ``rho^2/2`` each, so
    the sizes' scatter beyond what one target allows is the phases' too -- and those may still fit
    one range (the envelope probe's scene 19958: a mover 0.12 bin up on one photodiode, read as
    static, a static echo 33 dB under it; sizes 2 % apart against a declared 1 %, chi2 13.9 on 3 dof,
    p 0.003; the phases fit one range 0.85 mm off at a sigma of 0.05 mm, z -18).
    """
    p = chdtrc(dof, chi2) if dof > 0 else 1.0
    if not BLENDED_P <= p < BIRGE_P:
        return 0.0
    return max(chi2 / dof - 1.0, 0.0) * allowed


#: :func:`amplitude_chi2` uses a line whose segments' noise (``2*S*phase_var`` of its mean power)
#: is at most this share of it
AMPLITUDE_NOISE_SHARE = 0.2


def line_powers(fams: list[LineFamily], keep=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per tone, the power of its lines in ``fams`` (rms over the segments, squared, less the noise's
    share ``2*S*v``, ``v = phase_var*|z|^2`` each component's noise variance) averaged over the
    families that have it (an IQ record's two sidebands pooled), and that mean's variance as a
    size (``v*(1 + S*phase_var)`` per line: the segments' noise squared too).

    Parameters
    ----------
    fams : the line families (each ``z`` of shape (S, T))
    keep : callable, ``keep(family)`` -> bool mask of shape (T,), the lines to take; all if None

    Returns
    -------
    tones (U,) Hz sorted, power (U,) V^2, variance (U,) V^2
    """
    tones, power, var = [], [], []
    for f in fams:
        segs = f.z.shape[0]
        use = np.ones(f.tone_hz.size, dtype=bool) if keep is None else keep(f)
        amp2 = np.mean(np.abs(f.z[:, use]) ** 2, axis=0)
        v = f.phase_var[use] * amp2
        tones.append(f.tone_hz[use])
        power.append(amp2 - 2 * segs * v)
        var.append(v * (1.0 + segs * f.phase_var[use]))
    uniq, inv = np.unique(np.concatenate(tones), return_inverse=True)
    count = np.bincount(inv, minlength=uniq.size)
    return (uniq, np.bincount(inv, np.concatenate(power), uniq.size) / count,
            np.bincount(inv, np.concatenate(var), uniq.size) / count**2)


def _sizable(f: LineFamily, min_snr_db: float) -> np.ndarray:
    """The lines of ``f`` whose size can be read: at ``min_snr_db`` or more, their segments' noise
    at most :data:`AMPLITUDE_NOISE_SHARE` of their power; shape (T,), bool."""
    return (f.snr_db >= min_snr_db) & (2 * f.z.shape[0] * f.phase_var <= AMPLITUDE_NOISE_SHARE)


def amplitude_chi2(fams: list[LineFamily], amplitudes: dict[float, tuple[float, float]] | None,
                   min_snr_db: float) -> tuple[float, int]:
    """The chi2 (and its degrees of freedom) of a candidate's line sizes against one target's
    (``Reference.tone_amplitudes``: per tone the amplitude, any scale, and its relative sigma).

    One echo puts the same ratios on its lines at every range and fading (a real envelope shared by
    every tone); two echoes on one line set add at each tone with a phase ``2*pi*f_i*dtau`` between
    them, so their sum's size changes from tone to tone: by 5-175 % in the envelope probe's blended
    static scenes, whose phases fitted one wrong range within chance. Per tone, the power of its
    lines at ``min_snr_db`` or more (rms over the segments, less the noise's share ``2*S*v``; an IQ
    record's two sidebands pooled: an echo's self-beat, real on I and on Q, adds to one and takes
    from the other, +5 / -4 % at a 20 MHz tone with the echo 13 dB under the LO) against
    ``alpha*g_i``, ``alpha`` fitted, each weighted by ``1/(v_i + (rel_i*alpha*g_i)^2)``, ``v_i``
    the pooled amplitude's noise variance (``phase_var*|z|^2`` per line and component, V^2, times
    ``1 + S*phase_var``: the segments' noise squared). A line whose segments' noise is more than
    :data:`AMPLITUDE_NOISE_SHARE` of its power is not used: taking that share out leaves the floor's
    own error in the size (a quasi-CW record's 400 short windows at 5 dB each, 75 dB of loss: the
    chi2 twice its degrees of freedom, a right point flagged in 3-5 of 16 frames).

    Returns
    -------
    (chi2, dof): 0, 0 where nothing is known or fewer than two tones are used
    """
    return _amplitude_fit(fams, amplitudes, min_snr_db)[:2]


def _amplitude_fit(fams: list[LineFamily], amplitudes: dict[float, tuple[float, float]] | None,
                   min_snr_db: float) -> tuple[float, int, float]:
    """:func:`amplitude_chi2`'s chi2 and dof, and the harmonic mean over its tones of the variance
    it allows each size relative to its fitted size, ``(v_i + (rel_i*alpha*g_i)^2)/(alpha*g_i)^2``
    (each tone's chi2 term is its relative excess over its own: ``chi2/dof - 1`` times this mean is
    the excess they share; 0, 0, 0 where nothing is known)."""
    if not amplitudes or not fams:
        return 0.0, 0, 0.0
    uniq, a2, v = line_powers(fams, lambda f: _sizable(f, min_snr_db)
                              & np.array([float(t) in amplitudes for t in f.tone_hz], dtype=bool))
    if uniq.size < 2:
        return 0.0, 0, 0.0
    a = np.sqrt(np.maximum(a2, 0.0))
    g, rel = np.array([amplitudes[float(t)] for t in uniq]).T
    v = np.maximum(v, 1e-24 * np.maximum(a, 1e-150) ** 2)  # a noiseless line (phase_var 0) weighs most, finitely
    w = 1.0 / v
    for _ in range(3):  # alpha, then the weights with the relative sigma at that alpha
        alpha = float(np.sum(w * a * g) / np.sum(w * g * g))
        w = 1.0 / (v + (rel * alpha * g) ** 2)
    allowed = 1.0 / float(np.mean(w * (alpha * g) ** 2)) if alpha > 0 else 0.0
    return float(np.sum(w * (a - alpha * g) ** 2)), int(uniq.size) - 1, allowed


def sideband_chi2(fams: list[LineFamily], tolerance: float, min_snr_db: float) -> tuple[float, int]:
    """The chi2 (and its degrees of freedom) of an IQ record's static lines' sizes, upper (``+f_i``)
    against lower (``-f_i``), tone by tone.

    An IQ receiver keeps ``conj(E_lo)*E``: one echo's real modulation envelope puts the same size
    on a tone's two sidebands, at every range and fading. Two echoes on one line set add there with
    their carriers' phase difference ``dtheta`` and the tone's ``dphi_i``, ``|U_i|^2 - |L_i|^2 =
    -4*A_1*A_2*sin(dtheta)*sin(dphi_i)``: the envelope probe's scene 10319, two static echoes at 55
    dB loss 5.3 m apart, sizes 1.2 / 1.5, 1.9 / 0.1 and 0.8 / 1.7 (x 1e-5 V) on 270, 460 and 640
    MHz, whose phases fitted one range 3600-8300 sigmas off; pooled per tone against the bench's
    declared sizes (:func:`amplitude_chi2`) they stood within chance (p 0.018). Each tone whose two
    lines are at ``min_snr_db`` or more, their noise's share of each at most
    :data:`AMPLITUDE_NOISE_SHARE`: ``(|U_i| - |L_i|)^2`` over their sizes' noise variances
    (:func:`line_powers`) plus ``tolerance`` of their mean size squared (``sideband_tolerance``: the
    hybrid's balance and image rejection, the modulator's symmetry). Needs no declared sizes.

    Returns
    -------
    (chi2, dof): 0, 0 where the candidate has not both sidebands of a tone
    """
    sides = _sidebands(fams)
    if len(sides) < 2:
        return 0.0, 0
    got = [line_powers([sides[k]], lambda f: _sizable(f, min_snr_db)) for k in ("U", "L")]
    (tu, pu, vu), (tl, pl, vl) = got
    both, iu, il = np.intersect1d(tu, tl, return_indices=True)
    if both.size == 0:
        return 0.0, 0
    au, al = np.sqrt(np.maximum(pu[iu], 0.0)), np.sqrt(np.maximum(pl[il], 0.0))
    var = vu[iu] + vl[il] + (tolerance * 0.5 * (au + al)) ** 2
    return float(np.sum((au - al) ** 2 / np.maximum(var, 1e-300))), int(both.size)


#: :func:`sideband_split` reads lines at this SNR or more (dB): a phase near the 10 dB floor has heavier
#: tails than its Gaussian variance (4 tones at 10 dB, one segment: p < 1e-4 in 0.28 % of clean
#: movers; at 15 dB as often as chance)
SPLIT_MIN_SNR_DB = 15.0


def sideband_split(fams: list[LineFamily], fd_hz: float, min_snr_db: float) -> tuple[float, int]:
    """The chi2 (and its degrees of freedom) of a mover's two sidebands' phase difference, tone by
    tone, against one carrier.

    Each tone's upper and lower LO beats carry the same tone phase ``phi_i - 2*pi*f_i*tau`` and the
    carrier's ``+psi`` and ``-psi`` (:class:`LineFamily`'s conjugation): their difference is ``2*psi``
    for every tone, whatever the range, the tones' drift and the trigger's jitter (they cancel) and
    the laser's phase noise (common to the tones in each segment) -- a test the range's own chi2,
    which carries the drift, cannot make as sharply. A second echo's beat or another line's leak
    turns a tone's two sidebands differently: the envelope probe's scene 22312 (one photodiode,
    the LO 1 % of the power, a mover at 16 dB of loss and a static echo at 35 dB faded out of its
    own lines) put the static echo's beat with the mover on the mover's lines, 2*psi spread 0.02 rad
    over three tones at line sigmas of 2e-4 rad (chi2 ~3000 on 2 dof); the range's chi2 against
    the declared 0.01 rad drift stood at 0.6 per dof, and the point 9.7 m off on a near-alias of
    the plan, 1740 sigmas, unflagged. Per tone, ``sum_s U_si*conj(L_si)`` turned back by the
    lines' ``2*f_d`` across the segments' centres; its phase's variance is the two lines'
    whole-record variances summed, over the sum's coherence squared (``|sum|/sum|.|``: ``2*psi``
    wandering across the segments shrinks it against its noise); the phases about their weighted
    mean, ``T - 1`` dof.

    Not a test of an unknown front end's phase across the band: a low-pass filter's phase at
    ``f_i +- f_d`` differs per tone (a 2nd-order Butterworth at 1 GHz: ~0.013 rad of spread at
    ``f_d`` = 10 MHz), which the range's own chi2 flags as well.

    Returns
    -------
    (chi2, dof): 0, 0 where fewer than two tones have both sidebands at ``min_snr_db`` or more
    """
    sides = _sidebands(fams)
    if len(sides) < 2:
        return 0.0, 0
    u, lo = sides["U"], sides["L"]
    ok = [(f.snr_db >= min_snr_db) & np.isfinite(f.phase_var) & (f.phase_var > 0) for f in (u, lo)]
    _, iu, il = np.intersect1d(u.tone_hz[ok[0]], lo.tone_hz[ok[1]], return_indices=True)
    iu, il = np.flatnonzero(ok[0])[iu], np.flatnonzero(ok[1])[il]
    if iu.size < 2 or u.z.shape[0] != lo.z.shape[0]:
        return 0.0, 0
    turn = np.exp(-2j * np.pi * np.mod(2.0 * fd_hz * u.seg_centre_s, 1.0))[:, None]
    prod = u.z[:, iu] * np.conj(lo.z[:, il]) * turn
    w = np.sum(prod, axis=0)
    # 2*psi wandering across the segments (a laser's noise, the Doppler's error) shrinks the sum
    # against its noise: the variance over the sum's coherence squared
    coherence = np.abs(w) / np.maximum(np.sum(np.abs(prod), axis=0), 1e-300)
    v = (u.phase_var[iu] + lo.phase_var[il]) / np.maximum(coherence, 1e-3) ** 2
    d = np.angle(w * np.exp(-1j * np.angle(np.sum(w / np.maximum(np.abs(w), 1e-300) / v))))
    return float(np.sum((d - np.sum(d / v) / np.sum(1.0 / v)) ** 2 / v)), int(iu.size) - 1


#: the static lines (one photodiode) are taken for a blend when the self-beats of Doppler lines no
#: mover found explains could turn one of them by more than this many of its phase sigmas
UNEXPLAINED_SIGMAS = 3.0


def unexplained_sigmas(fams: list[LineFamily], min_snr_db: float, attr: str = "unexplained_v") -> float:
    """The largest phase turn (in the line's phase sigmas) that the unexplained Doppler lines could
    give a used line of ``fams``: ``bound / (|z| * sigma_phase)`` (a phasor of size ``b`` added
    to one of size ``a`` turns it by up to ``asin(b/a)``), over the lines at ``min_snr_db`` or
    more of the families that carry a bound (``attr``: :attr:`LineFamily.unexplained_v`, or
    :attr:`LineFamily.cross_v` for a static echo's beat on a mover's lines); 0 if none."""
    worst = 0.0
    for f in fams:
        bound = getattr(f, attr)
        if bound is None:
            continue
        use = f.snr_db >= min_snr_db
        if not use.any():
            continue
        worst = max(worst, float(np.max(_turns(f, use, bound) / np.sqrt(f.phase_var[use]))))
    return worst


def _turns(f: LineFamily, use: np.ndarray, bound: np.ndarray) -> np.ndarray:
    """How far (rad) a phasor of size ``bound`` (per line, V) can turn each used line of ``f``:
    ``asin(bound/|z|)``, ``|z|`` the line's rms size over the segments; shape (use.sum(),)."""
    amp = np.sqrt(np.mean(np.abs(f.z[:, use]) ** 2, axis=0))
    return np.arcsin(np.minimum(bound[use] / np.maximum(amp, 1e-300), 1.0))


def range_turn_m(fams: list[LineFamily], min_snr_db: float, attr: str = "cross_v") -> float:
    """The largest range shift (m) the per-line phase turns of :func:`unexplained_sigmas` could make
    together, through the range's fit: the pairs of each family's lines weighted
    ``1/(phase_var_i*phase_var_j)`` (:func:`~mtcw_core.ranging.mixing.pair_observations`), which is
    the lines' phase slope across their tones weighted ``w_i = 1/phase_var_i``, each family with
    its own offset (its nuisance phase) and weighted as a whole by ``W_F = sum_i w_i``:
    ``c/(4*pi)*sum_F W_F*sum_i |w_i*(f_i - fbar_F)|*b_i / sum_F W_F*sum_i w_i*(f_i - fbar_F)^2``
    (``b_i`` the line's turn; a family with no bound has none but weighs in). Each turn may
    stay under :data:`UNEXPLAINED_SIGMAS` of its line's sigma while they move the range together:
    the envelope probe's scene 10771, a 1 MHz laser, a static echo 7 dB over a mover 0.22 m from
    it, one photodiode: turns of 2.0-2.7 sigmas on six tones, the mover 3-6 range sigmas off, the
    bound 7.6-8.3 mm at sigmas of 1.5-3.5 mm. 0 where no family carries a bound."""
    num = den = 0.0
    for f in fams:
        bound = getattr(f, attr)
        use = (f.snr_db >= min_snr_db) & np.isfinite(f.phase_var) & (f.phase_var > 0)
        if np.count_nonzero(use) < 2:
            continue
        w, tone = 1.0 / f.phase_var[use], f.tone_hz[use]
        dev = tone - np.sum(w * tone) / np.sum(w)
        den += float(np.sum(w) * np.sum(w * dev**2))
        if bound is not None:
            num += float(np.sum(w) * np.sum(np.abs(w * dev) * _turns(f, use, bound)))
    return C / (4 * math.pi) * num / den if den > 0 and num > 0 else 0.0


#: a candidate this much weaker than a mover (amplitude) may be a copy of its lines
COPY_MAX_RATIO = 0.1
#: ... and is one when its lines miss a scaled copy by less than this chi-square quantile
COPY_QUANTILE = 0.999


def is_scaled_copy(fams: list[LineFamily], parent: list[LineFamily]) -> bool:
    """Are the lines of a Doppler candidate ``fams`` one complex multiple of a stronger mover's?

    A mover's LO beats all carry the laser's phase noise over its delay, ``exp(j*dphi(t))``, whose
    spectrum is a line and a pedestal around it: at an offset ``delta`` every line of the mover
    (baseband, ``f_i + f_d``, ``|f_i - f_d|``) has the same pedestal value beside it, and the search
    finds a "mover" at ``f_d + delta`` whose U lines are the mover's times ``P(delta)`` and whose L
    lines its times ``P*(delta)``. A second target at another range (modulo the unambiguous range)
    has U lines whose ratio to the mover's turns with ``f_i``. The test: per family, the
    least-squares complex ratio, at most :data:`COPY_MAX_RATIO`, and the chi-square of the
    candidate's lines about the scaled copy (their own noise, ``2 * phase_var * |z|^2`` per line)
    within its :data:`COPY_QUANTILE` quantile, with ``2*(T - 1)`` degrees of freedom per family.

    Parameters
    ----------
    fams, parent : the candidate's and the mover's line families (U and L)
    """
    by_name = {f.name: f for f in parent}
    chi2, dof = 0.0, 0
    for f in fams:
        p = by_name.get(f.name)
        if p is None:
            continue
        ok = np.isfinite(f.phase_var) & np.isfinite(p.phase_var) & (np.abs(p.z).min(axis=0) > 0)
        if ok.sum() < 2:
            continue
        zc, zp = f.z[:, ok].ravel(), p.z[:, ok].ravel()
        ratio = np.sum(zc * np.conj(zp)) / np.sum(np.abs(zp) ** 2)
        if not abs(ratio) <= COPY_MAX_RATIO:
            return False
        noise = 2 * np.repeat(f.phase_var[ok][None, :], f.z.shape[0], axis=0).ravel() * np.abs(zc) ** 2
        noise = np.maximum(noise, np.finfo(float).tiny)
        chi2 += float(np.sum(np.abs(zc - ratio * zp) ** 2 / (noise / 2)))
        dof += 2 * (zc.size - 1)
    return dof > 0 and chi2 <= float(chi2_dist.ppf(COPY_QUANTILE, dof))


def resolve_targets(families: list[LineFamily], observations: dict[int, Observations], dops: list[DopplerEstimate],
                    frame: Frame, settings: ChainSettings, ref: Reference, coarse: tuple[float, float] | None
                    ) -> tuple[list[tuple[int, TargetPoint]], float | None]:
    """The stage: a point per candidate that has observations, and the largest unambiguous range (m).

    Candidate 0 is static; candidate k >= 1 belongs to the k-th detected Doppler line. The frame's
    unambiguous range is the largest of its points'; a CW point whose own lines repeat sooner is
    ``cycle_ambiguous``. A Doppler
    candidate whose lines are a scaled copy of a stronger mover's (:func:`is_scaled_copy`: that
    mover's phase-noise pedestal) gets no point; nor does one found inside a mover's search lobe
    (``DopplerEstimate.beside``) at that mover's range (the bumps of its pedestal there).
    """
    moving = [d for d in dops if d.detected]
    # the static candidate's smallest measurable speed: the search's; beside a mover found below
    # the guard, no less than that mover's Doppler (the static lines may be its own self-beat, and
    # select may keep them in its place: they then answer it within one sigma)
    floor = max([dops[0].min_detectable_hz] + [abs(d.fd_hz) for d in moving if d.method == "fit"])
    # on one photodiode every echo beats with itself onto the static lines; the extract stage takes
    # out the self-beat of each mover found, but not of movers the search could not tell apart (a
    # Doppler line whose own lines disagree) nor where beats blur which line is a mover: the static
    # lines then may be such a mover's self-beat, and their point is flagged like the movers'
    single = frame.receiver == "single"
    static = DopplerEstimate(0.0, False, 0.0, dops[0].threshold, floor,
                             lines_chi2=max([d.lines_chi2 for d in moving if single], default=0.0),
                             beat_ambiguous=single and any(d.beat_ambiguous for d in moving))
    points: list[tuple[int, TargetPoint]] = []
    periods: list[float] = []
    l_unamb = None
    # the movers first: the rest of their self-beats is taken from the static lines by their ranges
    for k, obs in sorted(observations.items(), key=lambda kv: (kv[0] == 0, kv[0])):
        fam_k = [f for f in families if f.target == k]
        if k >= 2 and any(is_scaled_copy(fam_k, [f for f in families if f.target == j]) for j in range(1, k)):
            continue  # the phase-noise pedestal of a stronger mover, not a target
        lu = unambiguous_range(obs.df_hz)
        if k == 0:
            span = _search_interval(settings, max([lu, *periods]), coarse)[:2]
            mended = whole_self_beats(fam_k, [(j, q, lj) for (j, q), lj in zip(points, periods)], families, settings,
                                      span)
            remixed = mix(mended, ref.tone_phases_rad, settings.min_line_snr_db) if mended is not fam_k else {}
            if 0 in remixed:  # (mended lines too weak to pair: left as they were)
                fam_k, obs = mended, remixed[0]
                lu = unambiguous_range(obs.df_hz)
        point = solve_target(fam_k, obs, moving[k - 1] if k else static, frame, settings, ref, coarse, lu)
        if k and moving[k - 1].beside:
            # beside a mover, at its range: the weaker is the other's phase-noise pedestal (issue 12
            # case 5 in fast) -- this one, or the mover the search took for a line on its pedestal's
            # bump (the envelope probe's 55012, ``fast``: a bump at 445 kHz, 16 dB, kept, and the
            # mover at 82 kHz, 42 dB, dropped beside it; the speed 74 sigmas off)
            same = [i for i, (j, q) in enumerate(points) if j and _same_range(point, q)]
            if same and point.snr_db <= max(points[i][1].snr_db for i in same):
                continue
            points, periods = ([v for i, v in enumerate(points) if i not in same],
                               [v for i, v in enumerate(periods) if i not in same])
        points.append((k, point))
        periods.append(lu)
        l_unamb = max(periods)
    order = sorted(range(len(points)), key=lambda i: points[i][0])
    points, periods = [points[i] for i in order], [periods[i] for i in order]
    if coarse is None and l_unamb is not None:
        # a point whose own lines repeat sooner than the frame's (a weak target that lost a line:
        # 510/710/950 MHz repeat every 3.75 m, with 130 MHz every 7.49 m) is known only modulo its
        # own period: which of the frame's l_unamb/lu cycles (or of a declared range interval) it
        # is in, is in doubt
        span = l_unamb if settings.range_max_m is None else min(l_unamb, settings.range_max_m - settings.range_min_m)
        points = [(k, replace(p, cycle_ambiguous=True)) if lu < span * (1 - 1e-9) else (k, p)
                  for (k, p), lu in zip(points, periods)]
    # a Doppler line that hid a second mover (one found beside it, closer than the refinement
    # resolves: its refinement saw both) is a blend, and so is that neighbour -- unless the
    # neighbour gave no point of its own (its pedestal, a copy, lines it could not have alone)
    kept = [moving[k - 1] for k, _ in points if k and moving[k - 1].beside]
    sep = quarters_resolve_hz(frame.fs_hz, frame.n)
    points = [(k, replace(p, blended=True)) if k and moving[k - 1].unresolved and (
        moving[k - 1].beside or within(moving[k - 1], kept, sep)) else (k, p) for k, p in points]
    return _cross_beaten(_beside_a_blend(points, moving, frame, settings), families, settings), l_unamb


#: a sub-guard fit's mover this close (record bins, in ``|f_d|``) to a found mover whose own lines
#: are a blend (``lines_chi2`` above the profile's ``blended_lines_chi2``) is ``blended`` too: the fit
#: held that one's lines where no one mover's are (:func:`_beside_a_blend`)
HELD_BLEND_BINS = 4.0


def _beside_a_blend(points: list[tuple[int, TargetPoint]], moving: list[DopplerEstimate], frame: Frame,
                    settings: ChainSettings) -> list[tuple[int, TargetPoint]]:
    """Movers found by the sub-guard fit (``method == "fit"``) within :data:`HELD_BLEND_BINS` record
    bins of another found mover whose lines disagree as no one mover's do (two movers unresolved in
    one Doppler line), flagged ``blended``: the fit held that line set at one Doppler, the residual
    of the blend it left can make a "mover" beside it (the envelope probe's scene 22284, ``fast``:
    movers 3.6 and 4.8 bins up on one photodiode, found as one at 3.6 with lines chi2 301, and a
    second "mover" at 6.35 bins whose lines ranged as the weaker's, its speed 1.5 bins off, 17.6
    sigmas) -- a point beside a blend is not measured alone."""
    bin_hz = frame.fs_hz / frame.n
    blends = [d for d in moving if d.lines_chi2 > settings.blended_lines_chi2]

    def beside(d: DopplerEstimate) -> bool:
        return d.method == "fit" and any(b is not d and abs(abs(b.fd_hz) - abs(d.fd_hz)) < HELD_BLEND_BINS * bin_hz
                                         for b in blends)

    return [(k, replace(p, blended=True)) if k and beside(moving[k - 1]) else (k, p) for k, p in points]


def _cross_beaten(points: list[tuple[int, TargetPoint]], families: list[LineFamily], settings: ChainSettings
                  ) -> list[tuple[int, TargetPoint]]:
    """Movers whose lines a static echo's beat with them (one photodiode), or its leak (IQ,
    balanced), could turn by more than :data:`UNEXPLAINED_SIGMAS` of their phase sigmas
    (:attr:`LineFamily.cross_v`),
    or whose range those turns together could move by more than as many of its sigmas
    (:func:`range_turn_m`), flagged ``blended`` -- where the static point lies at another range
    than the mover's (at its range the static lines may be the mover's own self-beat, left over
    where its prediction missed: no second echo; the envelope probe's scenes 725, 1385 and 1937,
    static echoes at 0-10 dB loss with the LO a tenth of the power, had their movers ranged
    200-1000 sigmas off, unflagged), or at the same range where the static lines stood mostly
    above what the movers' self-beats' prediction took out (:attr:`LineFamily.static_echo`: a
    static echo's own, no leftover; 725's first frame: two echoes at 10-12 dB under a 1 MHz laser
    whose corrupted lines fit one range, neither's, the mover 722 sigmas off)."""
    static = next((p for k, p in points if k == 0), None)
    # IQ and balanced records have no self-beat: a mover's bound is an echo's leak (the static lines
    # carry no self-beat's prediction), which needs no static point (an echo moving under a bin is
    # read at a fraction of its size) and excuses no mover at the static lines' range (16541's mover
    # was pulled toward the echo's)
    statics = [f for f in families if f.target == 0]
    leak = bool(statics) and all(f.self_beats is None for f in statics)
    if static is None and not leak:
        return points
    echo = leak or any(f.static_echo for f in families if f.target == 0)

    def beaten(k: int, p: TargetPoint) -> bool:
        # the static candidate, a point already flagged, and a mover at the static lines' own range
        # where those lines may be its self-beat left over (no static echo's own lines there)
        if not k or p.blended or (not echo and _same_range(p, static)):
            return False
        own = [f for f in families if f.target == k]
        # line by line, and through the range they make together
        return (unexplained_sigmas(own, settings.min_line_snr_db, "cross_v") > UNEXPLAINED_SIGMAS
                or range_turn_m(own, settings.min_line_snr_db) > UNEXPLAINED_SIGMAS * p.range_sigma_m)

    return [(k, replace(p, blended=True)) if beaten(k, p) else (k, p) for k, p in points]


def _same_range(a: TargetPoint, b: TargetPoint) -> bool:
    return abs(a.range_m - b.range_m) < max(5 * math.hypot(a.range_sigma_m, b.range_sigma_m), 1e-3)


def is_finite(p: TargetPoint) -> bool:
    """Range, speed and both sigmas are finite numbers (a sigma of inf is no measurement)."""
    return all(math.isfinite(v) for v in (p.range_m, p.range_sigma_m, p.velocity_mps, p.velocity_sigma_mps))


#: a "mover" this far (dB) above the highest level the static target's wings reach in one record
#: bin cannot be made of them: a periodogram's largest bin over 1e6 bins of a flat pedestal stands
#: ~11 dB above its mean (exponential), the margin leaves 9 dB more
WINGS_MARGIN_DB = 20.0
#: ... and one this far above them may still be a bump of them (that largest bin's ~11 dB, 1 dB
#: spare): between the two the static point keeps its range but not its speed (the envelope probe's
#: scene 1807: a 1 MHz laser's mover 14 dB above the static lines' wings at its Doppler, the range
#: folded, had been dropped as their bump and the static point reported ``static``, 250 sigmas off)
WINGS_BUMP_DB = 12.0


def wings_level_db(settings: ChainSettings, static: TargetPoint, bin_hz: float | None,
                   offset_hz: float = 0.0) -> float | None:
    """The static target's phase-noise wings in one record bin (``bin_hz``) ``offset_hz`` from its
    lines, dB relative to its line there, at most 0 dB (an incoherent echo's line is all wings).
    None where nothing bounds them: no laser declared (linewidth 0) or no bin width given.

    The LO x echo beat of a Lorentzian laser (FWHM ``dnu``), delayed ``dtau``
    (:func:`carrier_coherence`), keeps ``exp(-a)`` of its power in the line (``a = 2*pi*dnu*dtau``);
    the rest is the delayed self-heterodyne pedestal, per Hz of the beat's power at an offset ``f``::

        S(f) = dnu/pi / (f^2 + dnu^2) * (1 - exp(-a)*(cos(2*pi*f*dtau) + dnu/f*sin(2*pi*f*dtau)))

    highest beside the line, ``(1 - exp(-a)*(1 + a))/(pi*dnu)`` (``2*pi*dnu*dtau^2`` for a coherent
    echo, :func:`shared_phase_psd`; a Lorentzian's ``1/(pi*dnu)`` for an incoherent one). Taken as the
    lesser of that peak and the envelope of ``S`` at ``offset_hz`` (its cosine and sine at their
    worst, ``1 + exp(-a)*sqrt(1 + (dnu/f)^2)``): a mover 30 MHz off a 1 MHz laser's static line
    meets wings ~14 dB below their peak (the envelope probe's scene 3338: a strong single-photodiode
    echo whose self-beat stood 18 dB above its Doppler lines was reported ``static``)."""
    dnu = settings.laser_linewidth_hz
    if dnu <= 0 or not bin_hz:
        return None
    a = 2 * math.pi * dnu * echo_delay_s(settings, static.range_m)
    density = (-math.expm1(-a) - a * math.exp(-a)) / (math.pi * dnu)  # 1 - exp(-a)*(1 + a): no cancellation
    f = abs(offset_hz)
    if f > 0:
        envelope = dnu / math.pi / (f * f + dnu * dnu) * (1 + math.exp(-a) * math.hypot(1.0, dnu / f))
        density = min(density, envelope)
    level = density * bin_hz / max(math.exp(-a), 1e-300)
    return 10.0 * math.log10(min(level, 1.0)) if level > 0 else -math.inf


def select_targets(points: list[tuple[int, TargetPoint]], settings: ChainSettings,
                   bin_hz: float | None = None, receiver: str = "single"
                   ) -> list[TargetPoint]:
    """The stage: which candidates are targets, strongest first (by the median SNR of their lines).

    - A candidate without a finite range, speed and sigmas is no measurement: never reported.
    - A "mover" at a range where the declared laser keeps less than
      :data:`~mtcw_core.dsp.doppler.MIN_CARRIER_COHERENCE` of the carrier beat in one line has no
      Doppler line to be found: it is the Lorentzian wings of the static lines, never reported.

    - A "moving target" whose line phases are random at high SNR is the wings of the static
      lines (a laser incoherent at the echo's delay), not a target: dropped when a static
      target is there -- unless the declared laser's wings (:func:`wings_level_db` in a record bin
      of ``bin_hz``) stay :data:`WINGS_MARGIN_DB` below its lines (issue 12 case 3: a mover 6 dB
      above the static target, 100 kHz laser, whose blended lines miss one range by 0.26 rad; the
      wings there lie 70 dB below the static lines in a 5 kHz bin). One :data:`WINGS_BUMP_DB` above
      them may be a Doppler line whose self-beat the static lines are (one photodiode): the static
      point's speed is then not measured.
    - The static candidate of a frame with moving targets is often their own self-beat
      (``|E_echo|^2`` has no Doppler): at a mover's range, or far weaker than the movers' LO
      beats (a self-beat is ``sqrt(P_echo/P_lo)`` below them), it is not a second target.
    - A weak "mover" at the static target's range is that target's own phase-noise sidebands
      (they carry its tone phases): of two candidates at one range, the stronger is the target --
      unless the declared laser's wings there stay :data:`WINGS_MARGIN_DB` below the "mover": it
      is then a Doppler line and the static lines its self-beat (an echo stronger than the LO on
      one photodiode: the self-beat ``sqrt(P_echo/P_lo)`` above the LO beats), not a target. With
      no laser declared, or a "mover" :data:`WINGS_BUMP_DB` but not :data:`WINGS_MARGIN_DB` above
      the wings, the static point stays, its speed not measured (``unknown``, a sigma that covers
      the twin's speed): its lines are either's, at one range. Only on one photodiode
      (``receiver``): balanced and IQ receivers cancel the self-beat.
    - A "mover" at a stronger mover's range, its lines :data:`COPY_MARGIN_DB` weaker (or at a whole
      multiple of its speed), may be a copy of that mover's line family at another Doppler, with
      its tone phases (the quantizer's products on integer ADC codes; on float volts too, the
      envelope probe's scene 3275), and is flagged ``blended`` (:func:`_copies`).
    """
    points = [(k, p) for k, p in points if is_finite(p)]
    # no Doppler line where the carrier beat is no line: a "mover" there is the wings of the
    # static lines (a laser declared incoherent at that range; issue 12's quasi-CW target at 930 m)
    points = [(k, p) for k, p in points if k == 0 or carrier_coherence(settings, p.range_m) >= MIN_CARRIER_COHERENCE]
    static = next((p for k, p in points if k == 0), None)
    def wings(p: TargetPoint) -> float | None:  # the static lines' wings at the candidate's Doppler
        return wings_level_db(settings, static, bin_hz, p.doppler_hz)

    doubt: list[TargetPoint] = []
    if static is not None:
        wild = [p for k, p in points if k and p.residual_rms_rad > settings.incoherent_residual_rad
                and median_snr(p) > 25.0 and not _above_wings(p, static, wings(p))]
        points = [(k, p) for k, p in points if not any(p is q for q in wild)]
        # one WINGS_BUMP_DB above them may be a Doppler line whose self-beat the static lines are
        doubt = [p for p in wild if receiver == "single" and _above_wings(p, static, wings(p), WINGS_BUMP_DB)]
    movers = [p for k, p in points if k > 0]
    if static is not None and movers:
        loudest = max(median_snr(m) for m in movers)
        twins = [m for m in movers if _same_range(static, m)]
        # only one photodiode keeps an echo's self-beat (balanced and IQ receivers cancel it)
        lines = [m for m in twins if receiver == "single" and (wings(m) is None or _above_wings(m, static, wings(m)))]
        maybe = [m for m in twins if receiver == "single" and (
            wings(m) is None or _above_wings(m, static, wings(m), WINGS_BUMP_DB))]
        if median_snr(static) < loudest - settings.self_beat_margin_db or any(
                median_snr(m) >= median_snr(static) for m in twins) or any(
                wings(m) is not None and not m.flagged for m in lines):
            points = [(k, p) for k, p in points if k > 0]
        elif twins:
            # a twin that may be a Doppler line (no laser declared, or a flagged one above the
            # wings: a wrong cycle's sigma can put it at any range) may have put its self-beat on
            # the static lines: the range is either's, the speed 0 or the twin's: not measured
            points = [(k, _speed_unknown(p, maybe) if k == 0 and maybe else p) for k, p in points
                      if not any(p is m for m in twins)]
    if doubt:
        points = [(k, _speed_unknown(p, doubt) if k == 0 and p.direction == "static" else p) for k, p in points]
    points = _copies(points)
    return [p for _, p in sorted(points, key=lambda kp: -median_snr(kp[1]))]


#: a copy of a mover's line family stands this far (dB) below the mover's own lines at least (the
#: envelope probe's ghosts: 8-31 dB below)
COPY_MARGIN_DB = 6.0
#: ... and a copy at a whole multiple of a mover's speed may stand up to this far (dB) above it (the
#: envelope probe's scene 7816: 1.2 dB); a mover far above a weak point at a fraction of its speed is
#: no copy of it
COPY_STRONGER_DB = 3.0


def _copies(points: list[tuple[int, TargetPoint]]) -> list[tuple[int, TargetPoint]]:
    """Movers that may be copies of a stronger mover's lines, flagged ``blended``.

    Integer ADC codes quantize the whole record, where one photodiode's or a strong
    echo's carrier beat sweeps many codes: the quantization error is a function of the carrier, with
    harmonics ``k*f_d`` up to ``k ~ 2*pi*A/LSB``, and its products with the sidebands ``f_i +- f_d``
    are lines at ``f_i +- (1 + k)*f_d`` whose phases are the mover's own tone phases -- a "mover" at
    another speed and the same range. The envelope probe's ghosts (four scenes, 15 confident-false
    frames): 8- and 12-bit ADCs, at 2x and 41x a mover's Doppler and at other offsets, 8-31 dB under
    its lines, at its range within its sigma. A copy at a whole multiple of the mover's speed (``k +
    1 >= 2``, within 5 sigmas) is one whenever it is weaker (scene 2267: 8-bit codes, a 15 m/s
    mover's copy at 29.99 m/s only 5 dB under it), or stronger: the quantizer's products of a line
    at ``f_d`` fall at whole multiples of ``f_d``, never at a fraction of another's (scene 7816: 8-bit
    codes, a 3.72 m/s mover's copy at 11.17 m/s, 1.2 dB above it, unflagged): up to
    :data:`COPY_STRONGER_DB` above it. Float volts hold such copies too (scene 3275: one
    photodiode, a 1 MHz laser, an echo at 7.7 dB loss with the LO a tenth of the power: a "mover" at
    4.5 m/s, 19 dB under a 0.08 m/s mover, at its range), and are judged alike (the rule had looked
    at integer codes only). A real second target at the same range and another speed (a
    spinning part) cannot be told from such a copy in one frame: flagged, not dropped."""
    movers = [p for k, p in points if k > 0]
    return [(k, replace(p, blended=True) if k > 0 and any(
        q is not p and _same_range(p, q) and (median_snr(q) >= median_snr(p) + COPY_MARGIN_DB or (
            median_snr(q) >= median_snr(p) - COPY_STRONGER_DB and _speed_multiple(p, q))) for q in movers) else p)
        for k, p in points]


def _speed_multiple(p: TargetPoint, q: TargetPoint) -> bool:
    """Is ``p``'s speed a whole multiple (2 or more) of ``q``'s, within 5 sigmas of the two? Not
    where those 5 sigmas reach a quarter of the way to the next multiple (any speed would be one)."""
    ratio = abs(p.velocity_mps) / abs(q.velocity_mps) if q.velocity_mps else math.inf
    if not math.isfinite(ratio):
        return False
    k = round(ratio)
    tol = 5 * math.hypot(p.velocity_sigma_mps, k * q.velocity_sigma_mps)
    return k >= 2 and tol < 0.25 * abs(q.velocity_mps) and abs(abs(p.velocity_mps) - k * abs(q.velocity_mps)) <= tol


def _above_wings(mover: TargetPoint, static: TargetPoint, wings: float | None,
                  margin_db: float = WINGS_MARGIN_DB) -> bool:
    """A candidate at the static target's range whose lines stand ``margin_db`` above the declared
    laser's wings there (``wings``, dB relative to the static lines, at the mover's Doppler; None:
    no laser declared, nothing bounds them): by :data:`WINGS_MARGIN_DB` a Doppler line, not the
    wings (whether the static lines are then its self-beat, its flags decide:
    :func:`select_targets`); by :data:`WINGS_BUMP_DB`, perhaps one."""
    return wings is not None and median_snr(mover) - median_snr(static) >= wings + margin_db


def _speed_unknown(static: TargetPoint, twins: list[TargetPoint]) -> TargetPoint:
    """The static point with its speed not measured: 0, direction ``unknown``, a sigma that covers
    every twin's speed (5 of its sigmas beyond it) -- the static lines may be a twin's self-beat --
    and as its smallest measurable speed (the frame could not tell 0 from the twin's)."""
    cover = max([abs(m.velocity_mps) + 5 * m.velocity_sigma_mps for m in twins]
                + [static.velocity_sigma_mps, static.speed_min_mps, 1e-12])  # > 0: not measured
    return replace(static, velocity_mps=0.0, direction="unknown", velocity_sigma_mps=cover, speed_min_mps=cover)
