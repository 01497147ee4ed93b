"""Stage ``doppler``: the Doppler lines of the moving targets, and the line layout they imply.

A target moving at radial speed ``v`` shifts the echo's optical carrier by ``f_d = 2v/lambda``.
Beating with the (unshifted) LO, it puts a *baseband* line at ``|f_d|`` and, around every tone,
a pair of lines at ``f_i + f_d`` (family ``U``) and ``|f_i - f_d|`` (family ``L``; an IQ
receiver keeps the sign: ``f_d +- f_i``). The search (:func:`search_doppler`) scores every
candidate shift by all of those lines together against the local noise floor; the refinement
(:func:`estimate_doppler`) takes the peak below one spectrum bin, by a parabola, the lines'
phase advance across the record (:func:`refine_by_phase`) or the exact line power. Below the
search's guard (a few bins, where the static lines' window skirts would pass for Doppler pairs),
:func:`search_small_doppler` fits the record's lines themselves, down to one record bin.
"""

from __future__ import annotations

import math
import threading
import weakref
from dataclasses import dataclass, replace
from functools import cached_property, lru_cache

import numpy as np
import scipy.fft
from scipy.optimize import minimize_scalar
from scipy.special import chdtrc
from scipy.stats import chi2 as chi2_dist
from scipy.stats import t as student_t

from ..frame import Frame
from ..phase import C
from ..profiles import ChainSettings
from .spectrum import (LowBand, Spectrum, cached_window, line_width_bins, local_floor, whole_record, widths_at,
                       window_power, windowed_record, window_sum)
from .tones import (PartDFTs, _dirichlet, exact_dft, exact_dft_parts, line_gains, lines_signal, mean_leak, solve_lines,
                    solve_lines_many)


@dataclass(frozen=True)
class DopplerEstimate:
    """Result of the Doppler search.

    ``fd_hz`` is signed for complex (IQ) input and >= 0 for real input; 0 when no Doppler line
    was detected (``detected`` False). ``score`` is the summed line-to-noise ratio at the peak.
    """

    fd_hz: float
    detected: bool
    score: float
    threshold: float
    min_detectable_hz: float
    #: systematic error of the sub-bin refinement (Hz): the log-parabola through a Kaiser(14)
    #: main lobe is biased by up to ~0.1 bin; an exact refinement sets it to 0
    refine_error_hz: float = 0.0
    #: the line's own wander (Hz): a laser incoherent at the echo's delay broadens the beat into
    #: a Lorentzian of FWHM ``G``, whose centre over ``T`` seconds wanders by ``sqrt(G/(2*pi*T))``
    #: (the phase random walk's end-to-end change over ``2*pi*T``); 0 for a coherent line
    wander_hz: float = 0.0
    #: how ``fd_hz`` was refined past the search's parabola: ``"phase"`` (phase advance across
    #: parts, or exact power from it: ``refine_error_hz`` is then its whole error over every line
    #: it used -- the carrier's baseband line among them --, their scatter and the carrier phase
    #: they share, measured across the record), ``"reassigned"`` (the whole record's reassigned
    #: frequency, where lines are too close for parts: the same, less the shared phase, which one
    #: window cannot see -- ``shared_phase_gain`` says what it adds), ``"fit"`` (below the search's
    #: guard, :func:`search_small_doppler`: each line's frequency fitted on the whole record jointly
    #: with the static lines, combined like the reassigned ones, the shared phase likewise left to
    #: ``shared_phase_gain``), or ``""`` (the parabola)
    method: str = ""
    #: var(fd) per unit two-sided PSD of a phase all the lines share (Hz^2 per rad^2/Hz), for a
    #: refinement that cannot measure that phase itself; 0 otherwise
    shared_phase_gain: float = 0.0
    #: chi2 per degree of freedom of the refined lines' own Doppler corrections about their mean
    #: (:func:`_combine_lines`): ~1 for the lines of one mover (up to ~90 with leakage and a laser's
    #: phase-noise pedestal); far above where the line the search found is two movers it could not
    #: resolve (each tone then carries both echoes' phases, mixed differently: the lines disagree,
    #: and the range from them is neither's; ``ChainSettings.blended_lines_chi2``); 0 when not refined
    lines_chi2: float = 0.0
    #: one photodiode, echoes near the LO's power: the movers' beats with each other come near their
    #: own lines, and which line is a mover cannot be told (:data:`BEAT_AMBIGUOUS`)
    beat_ambiguous: bool = False
    #: found inside the search lobe of a mover the search found (:func:`_lobe_neighbours`): at that
    #: mover's range it is that mover's phase-noise pedestal (``resolve`` drops it), not a target
    beside: bool = False
    #: the search's line hid another mover (one found inside its lobe, closer than the phase
    #: refinement's parts can tell apart): its refinement saw both, its point is ``blended``
    unresolved: bool = False
    #: a real detector: the sign of the carrier Doppler ``f_d`` that its sidebands' modulation
    #: Doppler decides (:func:`_combine_lines`: +1, ``f_d > 0``, approaching; -1 receding), 0 when
    #: undecided; IQ: 0 (``fd_hz`` carries its sign)
    motion_sign: int = 0
    #: the shared phase's low-frequency two-sided PSD (rad^2/Hz) as the pedestal about the target's
    #: strongest line shows it (:func:`pedestal_phase_psd`; a real record's low line counts its
    #: image's pedestal too: up to twice the phase's own); with ``shared_phase_gain`` it gives the
    #: error the declared laser cannot where the echo's delay is not known (a range known modulo the
    #: unambiguous range), and with ``measured_phase_gain`` a phase advance's floor; 0 where not
    #: measured or no pedestal stands above the white floor
    pedestal_psd: float = 0.0
    #: for a refinement by phase advance, which measures the phase all its lines share itself, on
    #: a few parts (its scatter on 2-14 degrees of freedom, so that a low draw states too little):
    #: var(fd) per unit two-sided PSD of that phase through the quarters' own estimate
    #: (:func:`part_phase_gain`), through which a declared laser's PSD floors the error
    #: (:func:`~mtcw_core.ranging.targets.velocity`; :func:`refine_exact` keeps the quarters' error
    #: and gain, an upper bound for its whole-record maximum); 0 otherwise
    measured_phase_gain: float = 0.0
    #: with a laser declared partly coherent, the part of ``refine_error_hz**2`` (Hz^2) that the
    #: target stage's own term for the phase the lines share (the declared laser's PSD, or the
    #: pedestal's where more) stands for (:func:`~mtcw_core.ranging.targets.velocity` takes it out
    #: there): for a line reassigned over the whole record, what the laser's phase-noise pedestal in
    #: the lines' local floors added as if it were white noise (:func:`refine_reassigned`: counted
    #: twice, the speed's z std was 0.36-0.77 on the honesty map's 100 kHz rows); for a phase
    #: advance, what :func:`common_mode_margin` added to the measured shared phase against a low
    #: draw of its few degrees of freedom, which that term guards against too. 0 otherwise
    shared_overlap_var_hz2: float = 0.0
    #: one photodiode: how far (Hz) the beat of two movers found, lying inside this line's
    #: refinement lobe, can pull it (:func:`beat_pulls`); 0 where none lies there
    beat_pull_hz: float = 0.0
    #: a phase advance: the odds that white noise alone scattered its lines' sizes across the parts
    #: as much as they are (:func:`_amplitude_chi2`; 1 where not measured). One mover's lines keep
    #: their size; a second echo beating on them moves size and phase alike. Last of the fields:
    #: the constructors pass the earlier ones by position
    amplitude_p: float = 1.0

    @property
    def refined(self) -> bool:
        """Refined past the search's parabola."""
        return bool(self.method)


#: below this part of the carrier beat in one line, a mover's Doppler line is not there to find
#: (the LO x echo carrier beat keeps exp(-2*pi*linewidth*|dtau|) of its power in the line)
MIN_CARRIER_COHERENCE = 0.5


# ---------------------------------------------------------------------------------------------
# the line layout of a target at Doppler fd
def doppler_families(tones, fd: float, iq: bool) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """The U and L lines of a target at Doppler ``fd``: (name, frequencies (Hz), conjugate mask).

    IQ: ``fd +- f_i`` (signed; L is the mirror image, conjugated). Real detector: ``f_i + fd``
    and ``|f_i - fd|`` (conjugated where it folds through 0 Hz).
    """
    t = np.asarray(tones, float)
    if iq:
        return [("U", fd + t, np.zeros(t.size, bool)), ("L", fd - t, np.ones(t.size, bool))]
    lo = t - fd
    return [("U", t + fd, np.zeros(t.size, bool)), ("L", np.abs(lo), lo < 0)]


def target_lines(tones, fd: float, iq: bool) -> tuple[np.ndarray, np.ndarray]:
    """Every line of a target at Doppler ``fd`` -- baseband, then U and L -- (Hz), and how each
    moves with ``fd`` (+-1: a real detector's L line ``|f_i - fd|`` moves down until it folds
    through 0 Hz; baseband ``|fd|`` moves down for a negative ``fd``)."""
    freqs, slope = [fd if iq else abs(fd)], [1.0 if (iq or fd >= 0) else -1.0]
    for name, f, conj in doppler_families(tones, fd, iq):
        freqs.extend(f)
        slope.extend(np.where(conj, 1.0, -1.0) if (name == "L" and not iq) else np.ones(len(f)))
    return np.asarray(freqs, float), np.asarray(slope)


def modulation_doppler(tones, fd: float, iq: bool, wavelength_m: float) -> np.ndarray:
    """How far each line of :func:`target_lines` lies from where ``fd`` puts it, times its slope
    (Hz), per sign of the motion: the RF tones are Doppler-shifted too.

    The echo's field is the transmitted one at ``t - tau(t)``: its sideband at ``f0 + f_i`` comes
    back at ``(f0 + f_i)*(1 - 2v/c)``, so the U line lies at ``f_i + f_d*(1 + f_i/f0)`` and the L
    line at ``f_d*(1 - f_i/f0) - f_i`` (``f_d = -2v*f0/c``, ``f0 = c/lambda``; spec physics.md).
    In the units the refinement combines (``slope*(line error)``): 0 for the baseband line,
    ``+f_i*F/f0`` for U and ``-f_i*F/f0`` for L, ``F`` = ``fd`` for IQ (signed, the sign known),
    ``|fd|`` times the unknown sign of ``f_d`` for a real detector. 0.4-300 Hz on the honesty
    map's movers (6 bins at 2^16 to 0.45x the tone spacing): far above the phase advance's
    per-line error at high SNR, where ignoring it made the lines disagree (chi2/dof up to ~1400)
    and inflated the stated error 4-40x by Birge's ratio.

    Returns
    -------
    ndarray, shape (1 + 2T,), Hz
    """
    t = np.asarray(tones, float)
    f = (fd if iq else abs(fd)) * wavelength_m / C
    return np.concatenate([[0.0], t * f, -t * f])


def sideband_freqs(tones, fd: float, iq: bool) -> np.ndarray:
    """The U then L line frequencies (Hz) of a target at Doppler ``fd``, shape (2T,)."""
    return np.concatenate([f for _, f, _ in doppler_families(tones, fd, iq)])


def fd_max(tones: tuple[float, ...], settings: ChainSettings) -> float:
    """The largest Doppler searched (Hz): the setting, else half the smallest tone spacing
    (beyond it a target's lines cross the neighbouring tone's)."""
    if settings.fd_max_hz is not None:
        return settings.fd_max_hz
    t = sorted(tones)
    return 0.5 * min(b - a for a, b in zip(t, t[1:]))


def l1_ball(dims: int, radius: int):
    """Every integer vector of length ``dims`` with ``sum|n_i| <= radius`` (a few thousand for 10
    tones at radius 4, where the cube ``(2*radius + 1)**dims`` holds 3.5e9)."""
    if dims == 0:
        yield ()
        return
    for n0 in range(-radius, radius + 1):
        for rest in l1_ball(dims - 1, radius - abs(n0)):
            yield (n0, *rest)


@lru_cache(maxsize=64)
def intermod_frequencies(tones_hz: tuple[float, ...], f_max_hz: float, order: int | None = None,
                         fs_hz: float | None = None) -> np.ndarray:
    """|sum_i n_i*f_i| for integer n with sum|n_i| <= order (5 for up to 4 tones, else 4), below f_max.

    These static lines (MZM harmonics and intermodulation) sit at fixed frequencies; a Doppler
    candidate whose baseband line falls on one of them is a blind speed of the tone plan.

    ``fs_hz``: the record's sample rate; a product above half of it is seen folded back, at
    ``|f - k*fs|`` (a real record's spectrum and a complex one's alike, the products coming in
    +- pairs): tones near Nyquist put such products anywhere in the band (150/200/270 MHz at
    0.65536 GS/s: 270 + 2*200 MHz shows at 14.64 MHz, off the plan's 10 MHz grid).

    Returns
    -------
    ndarray, sorted unique frequencies (Hz) in ``(0, f_max_hz]``
    """
    t = np.asarray(tones_hz, float)
    if order is None:
        order = 5 if t.size <= 4 else 4
    out = set()
    for n in l1_ball(t.size, order):
        if any(n):
            f = abs(float(np.dot(n, t)))
            if fs_hz:
                f = math.fmod(f, fs_hz)
                f = min(f, fs_hz - f)
            if 0 < f <= f_max_hz:
                out.add(f)
    return np.array(sorted(out))


def blind_spurs(spec: Spectrum, tones, fd_max_hz: float) -> np.ndarray:
    """The static products a Doppler line may sit on (Hz, up to ``2*fd_max_hz``): the tones' products
    as ``spec``'s record shows them, folded at its sample rate. The spur tests of the search and of
    the sub-guard fit read this one list (the ghost list does not fold: :func:`_ghost_base`)."""
    return intermod_frequencies(tuple(float(f) for f in tones), 2.0 * float(fd_max_hz), fs_hz=spec.fs_hz)


def _near(x: np.ndarray, marks: np.ndarray, tol: float) -> np.ndarray:
    """``|x - nearest mark| < tol`` for every x, by sorted search (x: many bins, marks: a few hundred)."""
    m = np.sort(np.asarray(marks, float))
    if m.size == 0:
        return np.zeros(x.shape, bool)
    i = np.clip(np.searchsorted(m, x), 1, m.size - 1)
    d = np.minimum(np.abs(x - m[i - 1]), np.abs(x - m[i]))
    if m.size == 1:
        d = np.abs(x - m[0])
    return d < tol


# ---------------------------------------------------------------------------------------------
# the search
def _static_lines(tones: np.ndarray, iq: bool, dc: bool = True) -> np.ndarray:
    """The static lines (Hz) of a record: 0 Hz and the tones, ``+-f_i`` for IQ; ``dc=False`` leaves
    a real record's 0 Hz out (a fit that holds it as its own column)."""
    t = np.asarray(tones, dtype=float)
    if iq:
        return np.concatenate([[0.0], t, -t])
    return np.concatenate([[0.0], t]) if dc else t.copy()


def _guard_bins(spec: Spectrum, tones_hz, min_bins: int, width: float | None = None) -> int:
    """How far (bins) a Doppler line must lie from the static lines to be told from their skirts.

    With a laser incoherent at the echo's delay every line is a Lorentzian whose wings carry
    random bumps that would pass for Doppler pairs; a coherent line is ~2.3 bins wide here (clear
    its main lobe); a Lorentzian's wings reach ~2.5 FWHM at -15 dB, so keep ~5 FWHM, 4 equivalent
    widths, away.
    """
    w = line_width_bins(spec, tones_hz) if width is None else width
    return max(min_bins, int(math.ceil(w + 2 if w < 4 else 4 * w)))


#: a Doppler line's width (:func:`_line_wander`) is read over this many search bins either side of it
WANDER_HALF_SPAN = 16


def _line_wander(spec: Spectrum, tones_hz, fd: float) -> float:
    """The Doppler line's own wander (Hz) from the width of its lines (baseband, f_i +- f_d).

    A Lorentzian's equivalent width is pi/2 FWHM on top of the window's ~2.3 bins; a coherent
    line measures 2.3-3 bins (scalloping), so only wider lines count. A line whose window
    (:data:`WANDER_HALF_SPAN` bins, and 2 more for a static line's main lobe) reaches a static line
    (a tone, 0 Hz) is not read: the window's strongest line is then the static one, whose width is
    not the Doppler line's (a mover 6 bins from its tones at 2^16, 100 kHz laser, read a 36 kHz
    wander, 100x its error); with none left, no wander is read -- a line that close to the static
    ones is narrow, or the search's guard (:func:`_guard_bins`) would have kept it out.
    """
    t = np.asarray(tones_hz, float)
    centres = np.concatenate([[fd], fd + t, fd - t]) if spec.complex_input else np.abs(
        np.concatenate([[fd], t + fd, t - fd]))
    static = _static_lines(t, spec.complex_input)
    clear = (WANDER_HALF_SPAN + 2) * spec.df_hz
    centres = [float(c) for c in centres if np.min(np.abs(static - c)) > clear]
    if not centres:
        return 0.0
    wd = widths_at(spec, centres, half_span=WANDER_HALF_SPAN)
    fwhm_hz = (wd - 2.3) * spec.df_hz * 2 / math.pi if wd > 3.2 else 0.0
    return math.sqrt(fwhm_hz * spec.df_hz / (2 * math.pi)) if fwhm_hz > 0 else 0.0  # over T ~ 1/df


@dataclass
class _Scores:
    """Every candidate shift of one sign: its Doppler (Hz), score, validity, pairs above threshold
    and its baseband line's power (the search spectrum's, V^2)."""

    fd_hz: np.ndarray
    score: np.ndarray
    valid: np.ndarray
    n_pairs: np.ndarray
    base_p: np.ndarray
    base_ratio: np.ndarray  # the baseband line's power over its local floor


def _score_candidates(spec: Spectrum, floor: np.ndarray, tones: np.ndarray, sign: int, bmax: int, min_bins: int,
                      fd_max_hz: float, threshold_factor: float, use_baseband: bool) -> _Scores:
    """Score the shifts ``sign*b*df``, b = 0..bmax: the sum over lines of power over the local
    ``floor`` (shape of ``spec.power``)."""
    nb = spec.power.size

    def power(f_hz: np.ndarray) -> np.ndarray:
        idx = spec.bin_of(f_hz)
        ok = (idx >= 0) & (idx < nb)
        out = np.zeros(idx.size)
        out[ok] = spec.power[idx[ok]]
        return out

    def line(f_hz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Power at f, and power over the local floor (0 beyond the spectrum; the search's hot path)."""
        idx = spec.bin_of(f_hz)
        ok = (idx >= 0) & (idx < nb)
        if ok.all():
            # the shifts step one bin, so a band's bins are consecutive (up, or down for a lower
            # line): read as a slice, not gathered (the same values, without the gather's cost)
            step = int(idx[1] - idx[0]) if idx.size > 1 else 1
            if step in (1, -1) and np.all(np.diff(idx) == step):
                lo = int(min(idx[0], idx[-1]))
                p = spec.power[lo:lo + idx.size].astype(np.float64)[::step]
                return p, p / floor[lo:lo + idx.size][::step]
            p = spec.power[idx].astype(np.float64)
            return p, p / floor[idx]
        p, ratio = np.zeros(idx.size), np.zeros(idx.size)
        p[ok] = spec.power[idx[ok]]
        ratio[ok] = p[ok] / floor[idx[ok]]
        return p, ratio

    b = np.arange(0, bmax + 1)
    fd = sign * b * spec.df_hz
    score = np.zeros(b.size)
    base_p, base = line(fd if spec.complex_input else np.abs(fd))
    # a real record's bands, what stands out of their floor (self_beat_bound reads it)
    stand_out = {"guard": min_bins, "B": _standing_out(base_p, base)} if not spec.complex_input else None
    if use_baseband:
        score += base
    strongest_pair = np.zeros(b.size)  # raw power of the strongest sideband pair
    n_pairs = np.zeros(b.size, int)  # sideband pairs above the threshold
    for f in tones:
        up_p, up = line(fd + f)
        # the lower line: signed for IQ, folded through 0 Hz for a real detector
        down_p, down = line(fd - f if spec.complex_input else np.abs(f - fd))
        if stand_out is not None:
            stand_out["U", float(f)], stand_out["L", float(f)] = _standing_out(up_p, up), _standing_out(down_p, down)
        # a Doppler pair is symmetric; a spur (IMD product) usually sits on one side only
        pair = np.minimum(up, down)
        score += 2 * pair
        n_pairs += pair > threshold_factor
        strongest_pair = np.maximum(strongest_pair, np.minimum(up_p, down_p))
    valid = np.ones(b.size, bool)
    valid[:min_bins] = False
    if use_baseband:
        # the LO x echo-carrier beat is the strongest line of a moving target: require it,
        # and ignore candidates sitting on a static intermodulation product
        valid &= (base > threshold_factor) & (base_p > strongest_pair)
        # one cached enumeration per tone plan and search range (min_bins varies per frame)
        spurs = blind_spurs(spec, tones, fd_max_hz)
        spurs = spurs[spurs <= (bmax + min_bins) * spec.df_hz]
        if spurs.size:
            # on a static intermodulation product, a candidate counts only when its line is
            # stronger than every static first-order line (a product never is; a moving
            # target's carrier beat is stronger than its own sidebands)
            near = _near(np.abs(fd), spurs, min_bins * spec.df_hz)
            valid &= ~near | (base_p > float(np.max(power(tones))))
    if stand_out is not None:
        spec.memo[_stand_out_key(tones, bmax)] = stand_out
    return _Scores(fd, score, valid, n_pairs, base_p, base)


def _stand_out_key(tones: np.ndarray, bmax: int) -> tuple:
    return ("stand_out", tuple(float(f) for f in tones), bmax)


def _standing_out(p: np.ndarray, ratio: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Of one band's shifts: those (indices) where its power ``p`` stands :data:`SELF_BEAT_LINE_RATIO`
    above its floor (``ratio`` = power over floor), and the power above the floor there (V^2)."""
    k = np.flatnonzero(ratio > SELF_BEAT_LINE_RATIO)
    return k, p[k] * (1.0 - 1.0 / ratio[k])


def _allowed(sc: _Scores, sign: int, found: list[DopplerEstimate], taken: list[tuple[int, int]],
             ghost_base: np.ndarray, min_bins: int, df_hz: float, complex_input: bool,
             threshold: float = np.inf, beats=None) -> np.ndarray:
    """Candidates still open after ``found``: away from the lines taken, and no ghost of them.

    Within one guard of a line taken, none; between one and two guards, only a line standing apart
    from it (:func:`_apart`). ``beats``: on one photodiode, ``beats(found)`` gives every pair of
    targets found, ``(f_a, f_b, P)``, with ``P`` their beat's predicted power (:class:`_BeatModel`);
    a candidate at ``|f_a +- f_b|`` no stronger than :data:`BEAT_MARGIN` times that is their beat. A strong mover's phase-noise pedestal carries bumps past one guard
    (issue 12 case 5: one guard let such a bump in as a second target, the mover 60-70 sigma off:
    bumps 20 dB below the line, a valley of 1.5-5 dB before them); a second mover 1-2 guards away
    (``fast``'s coarse bins: movers 40 and 120 record bins up at 2^16 are 10 search bins apart,
    its guard 5) stands 4 dB below the first, 25 dB above the noise between them.
    """
    ok = sc.valid.copy()
    score = sc.score
    for ts, tb in taken:
        if ts == sign or not complex_input:
            ok[max(tb - min_bins, 0): tb + min_bins + 1] = False
            for lo, hi in ((max(tb - 2 * min_bins, 0), tb - min_bins), (tb + min_bins + 1, tb + 2 * min_bins + 1)):
                hi = min(hi, score.size)
                if hi > lo:
                    ok[lo:hi] &= _apart(score, tb, lo, hi, threshold)
    if found:
        # rangeable (two pairs above the per-line threshold), or a line that alone passes the
        # search's whole threshold: the map's three movers on one photodiode (40/120/250 bins,
        # 2^16), the weaker two's baseband lines 33-36 dB over the floor and their sidebands
        # 3-12 dB, were missed in 22 of 48 truths at the 20 dB rung
        ok &= (sc.n_pairs >= 2) | (sc.base_ratio >= threshold)
        # not a ghost of a target already found: its lines and intermodulation products (tones,
        # IMD, 0 Hz) shifted by that target's Doppler -- and, on one photodiode (``beats``), the
        # beat of two targets found (one acts as the other's LO: lines at the difference and, a
        # real record not telling the signs, the sum of their Dopplers); a balanced or IQ receiver
        # keeps only the LO's beats, and a mover there is a mover
        base_f = np.abs(sc.fd_hz)
        for sh in [d.fd_hz for d in found]:
            ghosts = np.abs(np.concatenate([ghost_base + sh, ghost_base - sh]))
            ok &= ~_near(base_f, ghosts, min_bins * df_hz)
        if beats:
            for a, b, p_beat in beats(found):
                at = _near(base_f, np.abs(np.array([a + b, a - b])), min_bins * df_hz)
                ok &= ~(at & (sc.base_p <= BEAT_MARGIN * p_beat))
    return ok


#: the largest frequency error (record bins) a neighbour phasor of unit relative size ``x`` bins
#: away puts on a Doppler line's estimate: the least-squares phase slope over the record peaks at
#: 0.42 bin (``x`` = 0.66), the Kaiser(14) reassignment's weighted mean at 0.74 (``x`` = 1.2);
#: both below ``x`` for every ``x`` (slower wobbles are mostly a constant, faster ones average out
#: over the whole record; a phase advance over parts aliases them instead: :func:`beat_pulls`)
CROSS_PULL_BINS = 0.75

#: ... and a parabola through the search spectrum's Kaiser(14) lobe, by up to 0.81 bin (``x`` = 1.5)
PARABOLA_PULL_BINS = 0.85
#: :func:`beat_pulls` takes the beat's size this many times its prediction: the record's mean, from
#: which the LO's power is read, also holds a static echo's carrier beat at 0 Hz (``2|E_s|/|E_LO|``
#: of it times the echo's fading, ``cos(psi)``): a static echo 12 dB under the LO moves it by up
#: to half
BEAT_PULL_MARGIN = 2.0

#: one photodiode: a line at the beat of two movers found is taken for their beat when its power is
#: at most this times the beat's predicted power (:class:`_BeatModel`; its own error -- the tones'
#: modulation of both echoes, the carrier's coherence -- lies well inside it); a stronger line there
#: is a mover of its own
BEAT_MARGIN = 10.0
#: ... and which line is a mover and which a beat cannot be told (every mover's point is flagged
#: ``blended``) once a pair's predicted beat comes within this part of the weaker mover's own line:
#: an echo within ~10 dB of the LO's power
BEAT_AMBIGUOUS = 0.1


def lo_part(mean: float, carriers_sq: float) -> float:
    """The LO's part ``L`` of a square-law record's mean ``DC = L + sum_k A_k^2/(4L)``, where each
    mover's carrier line ``A_k`` (``sum_k A_k^2 = carriers_sq``, in the mean's units squared) puts
    ``A_k^2/(4L)`` of echo power into it: ``(DC + sqrt(DC^2 - sum A_k^2))/2``, the LO the larger
    part; 0 where the echoes hold half the mean or more, or the mean is not above 0 (no LO to tell)."""
    disc = mean**2 - carriers_sq
    return 0.5 * (mean + math.sqrt(disc)) if mean > 0 and disc > 0 else 0.0


class _BeatModel:
    """One photodiode: the predicted power, in the search spectrum, of the beat of two movers.

    Mover ``k``'s carrier beat with the LO has the amplitude ``A_k = 2R|E_LO||E_k|`` (V); two echoes
    beat with each other at ``|f_a -+ f_b|`` (a real record does not tell the signs) with
    ``C = 2R|E_a||E_b| = A_a*A_b/(2R|E_LO|^2)``, and ``R|E_LO|^2`` is the record's mean (the LO's
    power; the echoes' own lie far below it wherever the beats are weak). A line of amplitude ``A``
    has the windowed spectrum's power ``(A*W/2)^2`` (``W = sum(w)``), so ``P_C = P_a*P_b/(W*L)^2``
    with ``L`` the LO's part of the mean (:meth:`lo_w`: the mean less the movers' echo power; the
    static echoes' share stays in it, which lowers the prediction: hence :data:`BEAT_MARGIN`).

    Parameters
    ----------
    spec : the search spectrum (real)
    dc_w : the record's mean times ``sum(w)`` of the spectrum's window (V); not above 0 (an AC-coupled
        front end): every beat predicted as strong as can be (the former rule: a line there is a beat)
    """

    def __init__(self, spec: Spectrum, dc_w: float):
        self.spec, self.dc_w = spec, float(dc_w)

    def power(self, fd_hz: float) -> float:
        """The baseband line's power at ``|fd_hz|`` (the largest of its bin and the two beside)."""
        b = int(self.spec.bin_of(np.array([abs(fd_hz)]))[0])
        lo, hi = max(b - 1, 0), min(b + 2, self.spec.power.size)
        return float(np.max(np.asarray(self.spec.power[lo:hi], dtype=np.float64))) if hi > lo else 0.0

    def lo_w(self, found: list[DopplerEstimate]) -> float:
        """``R|E_LO|^2 * W`` (V): the record's mean less the echoes' own power. Each mover's carrier
        line ``A_k`` puts ``A_k^2/(4L)`` of echo power into the mean ``DC = L + sum_k A_k^2/(4L)``,
        so ``L = (DC + sqrt(DC^2 - sum A_k^2))/2`` (the LO the larger part; in spectrum units
        ``A_k^2 W^2 = 4 P_k``); 0 where the echoes hold half the mean or more (no LO to tell)."""
        return lo_part(self.dc_w, 4.0 * sum(self.power(d.fd_hz) for d in found))

    def beat_power(self, a: float, b: float, lo_w: float | None = None) -> float:
        lw = self.dc_w if lo_w is None else lo_w
        return self.power(a) * self.power(b) / lw**2 if lw > 0 else np.inf

    def __call__(self, found: list[DopplerEstimate]) -> list[tuple[float, float, float]]:
        """Every pair of ``found``: ``(f_a, f_b, predicted beat power)``."""
        lw = self.lo_w(found)
        return [(a.fd_hz, b.fd_hz, self.beat_power(a.fd_hz, b.fd_hz, lw)) for i, a in enumerate(found)
                for b in found[i + 1:]]

    def explains(self, x: DopplerEstimate, others: list[DopplerEstimate], tol_hz: float) -> bool:
        """Whether ``x`` lies at the beat of two of ``others`` and is no stronger than
        :data:`BEAT_MARGIN` times it."""
        return any(np.min(np.abs(abs(x.fd_hz) - np.abs([a + b, a - b]))) < tol_hz and
                   self.power(x.fd_hz) <= BEAT_MARGIN * p for a, b, p in self(others))

    def hidden_neighbour(self, x: DopplerEstimate, found: list[DopplerEstimate], static_hz: np.ndarray,
                         tol_hz: float) -> int | None:
        """Which mover of ``found`` (index) ``x`` may be the beat of with a line the search did not
        take -- whatever the spectrum holds at ``|f_m| +- |f_x|`` (a neighbour inside the mover's
        two guards, where only a line standing apart counts) -- being no stronger than
        :data:`BEAT_MARGIN` times that beat; None when none. Places within ``tol_hz`` of a mover
        found (:meth:`explains` judges those) or of a static line ``static_hz`` (0 Hz, the tones'
        products: no echo) are not such a neighbour, nor one whose beat with the mover is
        :meth:`ambiguous` (every line is marked then)."""
        lw = self.lo_w([*found, x])
        px = self.power(x.fd_hz)
        taken = np.abs(np.concatenate([[d.fd_hz for d in found], static_hz]))
        worst, who = 0.0, None
        for i, m in enumerate(found):
            for nb in (abs(m.fd_hz) + abs(x.fd_hz), abs(m.fd_hz) - abs(x.fd_hz)):
                if np.min(np.abs(taken - abs(nb))) < tol_hz:
                    continue
                p = self.beat_power(m.fd_hz, nb, lw)
                if p >= BEAT_AMBIGUOUS * min(self.power(m.fd_hz), self.power(nb)):
                    continue  # echoes near the LO's power: no line can be told for a beat (mark)
                if p > worst:
                    worst, who = p, i
        return who if who is not None and px <= BEAT_MARGIN * worst else None

    def ambiguous(self, found: list[DopplerEstimate]) -> bool:
        """Whether a pair's predicted beat comes within :data:`BEAT_AMBIGUOUS` of the weaker line
        (always, with two movers or more, where the echoes hold half the record's mean)."""
        return any(p >= BEAT_AMBIGUOUS * min(self.power(a), self.power(b)) for a, b, p in self(found))

    def mark(self, found: list[DopplerEstimate]) -> list[DopplerEstimate]:
        """``found``, every one marked ``beat_ambiguous`` where they are :meth:`ambiguous` (and none
        is marked yet: a set already marked was judged on its own)."""
        if any(d.beat_ambiguous for d in found) or not self.ambiguous(found):
            return found
        return [replace(d, beat_ambiguous=True) for d in found]


#: a candidate 1-2 guards from a line taken counts when the score between them falls this far
#: below it (a valley, not a bump on the line's skirt) ...
APART_VALLEY = 0.1
#: ... and below the threshold, and when it is at least this part of the line taken's score
#: (a phase-noise pedestal's bumps are ~1 % of it)
APART_RATIO = 0.1


def _apart(score: np.ndarray, tb: int, lo: int, hi: int, threshold: float) -> np.ndarray:
    """For each candidate bin in ``[lo, hi)`` on one side of the line taken at bin ``tb``: whether
    it stands apart from that line -- the lowest score between them below ``threshold`` and below
    :data:`APART_VALLEY` of the candidate's own, and the candidate at least :data:`APART_RATIO` of
    the line's score. Shape ``(hi - lo,)``, bool."""
    if lo > tb:  # right of the line: the lowest score over tb+1 .. k-1
        run = np.minimum.accumulate(score[tb + 1:hi])
        valley = run[lo - tb - 2:hi - tb - 2]
    else:  # left: over k+1 .. tb-1
        run = np.minimum.accumulate(score[lo + 1:tb][::-1])[::-1]
        valley = run[:hi - lo]
    cand = score[lo:hi]
    return (valley < threshold) & (valley < APART_VALLEY * cand) & (cand >= APART_RATIO * score[tb])


def _parabola_offset(score: np.ndarray, k: int) -> float:
    """Sub-bin offset of a peak at ``k`` from a parabola through the log of three scores, in [-0.5, 0.5]."""
    y0, y1, y2 = np.log(np.maximum(score[k - 1: k + 2], 1e-300))
    den = y0 - 2 * y1 + y2
    delta = 0.5 * (y0 - y2) / den if den < 0 else 0.0
    return float(np.clip(delta, -0.5, 0.5))


def _take_lines(spec: Spectrum, results: dict, tones: np.ndarray, ghost_base: np.ndarray, min_bins: int,
                threshold: float, max_targets: int, beats: "_BeatModel | None") -> list[DopplerEstimate]:
    """The search's lines, strongest first: each candidate (``results``: :class:`_Scores` per sign)
    a local maximum of its score above ``threshold`` that :func:`_allowed` leaves open; with
    ``beats`` (one photodiode), a line found before both its parents is dropped once they are found,
    and every line is marked ``beat_ambiguous`` when the beats come near the movers' own lines."""
    df = spec.df_hz
    found: list[DopplerEstimate] = []
    taken: list[tuple[int, int]] = []  # (sign, bin)
    blocked: list[tuple[int, int]] = []  # lines taken for a beat with a neighbour not found
    # local maxima only: the skirt of a line inside the guard (a mover below it) is no candidate,
    # and must not hide one beyond it
    local = {s: np.concatenate([[False], (sc.score[1:-1] >= sc.score[:-2]) & (sc.score[1:-1] >= sc.score[2:]),
                                [False]]) for s, sc in results.items()}
    for _ in range(2 * max_targets):  # room for lines dropped as beats
        if len(found) >= max_targets:
            break
        best = None
        for s, sc in results.items():
            ok = _allowed(sc, s, found, taken + blocked, ghost_base, min_bins, df, spec.complex_input, threshold,
                          beats) & local[s]
            if not ok.any():
                continue
            k = int(np.flatnonzero(ok)[np.argmax(sc.score[ok])])
            if best is None or sc.score[k] > best[0]:
                best = (float(sc.score[k]), k, s)
        if best is None or best[0] < threshold:
            break
        peak, k, s = best
        fd = s * (k + _parabola_offset(results[s].score, k)) * df
        found.append(DopplerEstimate(fd, True, peak, threshold, min_bins * df, 0.1 * df, _line_wander(spec, tones, fd)))
        taken.append((s, k))
        if beats is not None:
            # a line found before both its parents: the beat of two others found since
            keep = [i for i, d in enumerate(found) if i == len(found) - 1
                    or not beats.explains(d, found[:i] + found[i + 1:], min_bins * df)]
            found, taken = [found[i] for i in keep], [taken[i] for i in keep]
            j = beats.hidden_neighbour(found[-1], found[:-1], ghost_base, min_bins * df) if len(found) > 1 else None
            if j is not None:
                # the beat of a mover found with a neighbour the search did not take (inside its
                # 2 guards): no mover; that mover's line may hide the neighbour (its point, and the
                # static point, blended)
                found[j] = replace(found[j], beat_ambiguous=True)
                blocked.append(taken.pop())
                found.pop()
    return beats.mark(found) if beats is not None else found


def search_bmax(spec: Spectrum, fd_max_hz: float) -> int:
    """The search's largest shift (bins of ``spec``): two bins beyond the limit, so that a line
    exactly at it is still a local maximum."""
    return int(min(np.floor(fd_max_hz / spec.df_hz) + 2, spec.power.size // 2 - 1))


def search_floor(spec: Spectrum, tones: np.ndarray, bmax: int) -> np.ndarray:
    """The local noise floor (:func:`~.spectrum.local_floor`) where the search looks: about 0 Hz
    and about every tone (+-f_i for IQ), +-``bmax`` bins; NaN elsewhere. Shape of ``spec.power``."""
    centres = _static_lines(tones, spec.complex_input)
    around = [(int(b) - bmax - 2, int(b) + bmax + 3) for b in spec.bin_of(centres)]
    return local_floor(spec.power, mirror_dc=not spec.complex_input, ranges=around)


def _ghost_base(tones: np.ndarray, fd_max_hz: float) -> np.ndarray:
    """The static lines a Doppler line's lines may fall on (Hz, both signs): 0 Hz, the tones and
    their intermodulation products up to the highest tone plus ``fd_max_hz``.

    Not folded at the sample rate (the spur test of :func:`_score_candidates` is): the folded
    products of tones near Nyquist fill the band, and each shifted by every mover found would
    blind the search (movers 150 and 300 bins up at 0.65536 GS/s: 4.64 MHz - 1.5 MHz lies within
    the guard of the second, which was then missed in every frame, every receiver)."""
    base = np.concatenate([[0.0], tones, -tones, intermod_frequencies(tuple(float(f) for f in tones),
                                                                      float(np.max(tones)) + fd_max_hz)])
    return np.concatenate([base, -base])


def search_doppler(
    spec: Spectrum,
    tones_hz: list[float],
    fd_max_hz: float,
    min_bins: int = 4,
    threshold_factor: float = 8.0,
    use_baseband: bool = True,
    max_targets: int = 1,
    width: float | None = None,
    beat_scale: float | None = None,
) -> list[DopplerEstimate]:
    """Find the Doppler shift from the baseband line and the symmetric lines ``f_i +- f_d``.

    Every candidate shift ``b`` (in bins) is scored by the sum over lines of power over the local
    noise floor: baseband ``|f_d|``, ``f_i + f_d`` and ``|f_i - f_d|`` (folding through 0 Hz for a
    real detector). The peak is accepted when it is a local maximum above ``threshold_factor``
    times the score expected from noise alone; its position is refined below one bin by a
    parabola through the logarithm of the three scores around it (the Kaiser window's main lobe is
    close to Gaussian). Zero Doppler is a valid answer.

    Several targets: after the strongest line, further candidates (up to ``max_targets``) at
    least ``2*min_bins`` away from those found are accepted when they pass the same tests and,
    in addition, at least two of their sideband pairs stand above the threshold (a second
    target must be rangeable, not a stray line) or their baseband line alone passes the whole
    threshold (a mover's strongest line, its sidebands 20-30 dB weaker on one photodiode: the
    first target needs no more, and the extract stage decides, as for it, whether its lines
    range).

    ``width``: :func:`~.spectrum.line_width_bins` of ``spec`` if already read (it sets the guard).
    ``beat_scale``: on one photodiode (the echoes beat with each other), the record's mean times the
    window's sum (V, :class:`_BeatModel`); a line at the sum or the difference of two targets found
    is their beat, not a target, unless it is stronger than their beat can be (:data:`BEAT_MARGIN`);
    a line found before both its parents is dropped once they are found, and when the beats come
    near the movers' own lines (:data:`BEAT_AMBIGUOUS`) every target found is marked
    ``beat_ambiguous``. None: no beats (balanced, IQ).

    Returns
    -------
    list of DopplerEstimate, strongest first; ``[not detected]`` when there is none
    """
    df = spec.df_hz
    width = line_width_bins(spec, tones_hz) if width is None else width
    min_bins = _guard_bins(spec, tones_hz, min_bins, width)
    bmax = search_bmax(spec, fd_max_hz)
    tones = np.asarray(tones_hz, dtype=float)
    if bmax <= min_bins + 1:
        return [DopplerEstimate(0.0, False, 0.0, 0.0, min_bins * df)]
    signs = (1, -1) if spec.complex_input else (1,)
    floor = search_floor(spec, tones, bmax)
    results = {s: _score_candidates(spec, floor, tones, s, bmax, min_bins, fd_max_hz, threshold_factor, use_baseband)
               for s in signs}
    threshold = threshold_factor * (2 * tones.size + (1 if use_baseband else 0))
    ghost_base = _ghost_base(tones, fd_max_hz)
    beats = _BeatModel(spec, beat_scale) if beat_scale is not None and not spec.complex_input else None
    found = _take_lines(spec, results, tones, ghost_base, min_bins, threshold, max_targets, beats)
    return found or [DopplerEstimate(0.0, False, 0.0, threshold, min_bins * df)]


# ---------------------------------------------------------------------------------------------
# below one bin
#: window of the phase refinement's segments: Kaiser(8) leaks < -58 dB beyond 2.7 segment bins,
#: where the rectangular window's -13 dB sidelobes let the LO's DC (30-40 dB above a weak Doppler
#: line) and the line's own negative-frequency image into its phase
PHASE_WINDOW_BETA = 8.0
#: the shared-phase (laser phase noise) error rests on segments - 2 = 2 degrees of freedom: its
#: estimate is widened by this so that its low draws leave no |z| > 5 (measured on 100 kHz lasers
#: at 1-50 m: z std 0.8-1.8 before, largest |z| 6.3)
COMMON_MODE_MARGIN = 1.5
#: lines closer than this (segment bins) to another line, or to their own image, are left out
PHASE_SEPARATION_BINS = 4.0
#: ... and so are lines into whose parts a stronger line leaks more than their own phase noise
#: (:func:`sidelobe_leak`); where those hold more than half the lines' power, no part count is used
LEAK_KEEP_POWER = 0.5
#: ... but a leak under this (rad per part) is only stated, whatever the noise (a line far above
#: it would otherwise lose every part count to leaks of 1e-6 rad)
LEAK_FLOOR_RAD = 1e-3


def _other_lines(tones, fd: float, others: list[float], iq: bool) -> np.ndarray:
    """Every line (Hz) there may be besides the target's at ``fd``: the static target's (and 0 Hz),
    the other targets'."""
    return np.concatenate([target_lines(tones, o, iq)[0] for o in [0.0, *others] if o != fd])


def _separable(freqs: np.ndarray, own: np.ndarray, near: np.ndarray, sep_hz: float, iq: bool) -> np.ndarray:
    """Which of ``freqs`` (Hz) lie more than ``sep_hz`` from every line in ``near``, from every other
    line of ``own`` (the target's lines, ``freqs`` among them) and, for a real record, from their
    own image at ``-f``: shape (K,), bool."""
    f = np.asarray(freqs, dtype=float)[:, None]
    ok = np.all(np.abs(np.asarray(near, dtype=float)[None, :] - f) > sep_hz, axis=1)
    ok &= np.sum(np.abs(np.asarray(own, dtype=float)[None, :] - f) < sep_hz, axis=1) == 1
    return ok if iq else ok & (2 * np.abs(f[:, 0]) > sep_hz)


def _leak_bias(leak: np.ndarray, wt: np.ndarray, slope: np.ndarray, segments: int, part_s: float) -> float:
    """What the kept lines' leaks (rad per part, shape (K,)) could still do to :func:`phase_advance`'s
    combined Doppler (Hz; ``wt``, ``slope`` its weights and the lines' moves with it): each part's
    phase off by up to ``leak``, the estimate -- its end parts' phase difference over the
    ``segments - 1`` steps of ``part_s`` seconds -- by twice that."""
    bias = 2 * leak / max(segments - 1, 1) / (2 * np.pi * part_s)
    return float(np.sum(wt * np.abs(slope) * bias) / np.sum(wt))


def _leak_kept(spec: Spectrum, lines: tuple, others: np.ndarray, length: int, fs: float, iq: bool,
               segments: int) -> tuple | None:
    """The lines :func:`phase_advance` keeps, a far stronger line beside one leaking into its parts
    through the window's sidelobes (:func:`sidelobe_leak`): ``lines`` (its per-line arrays, the
    frequencies first, the phase noise per part ``var_phi`` (rad^2) and the power ``amp2`` last)
    where the leak is within their own phase noise or :data:`LEAK_FLOOR_RAD`, with their leaks
    (rad) appended; None where they hold under :data:`LEAK_KEEP_POWER` of the lines' power: parts
    are then no way to measure them, and the caller reassigns over the whole record."""
    leak = sidelobe_leak(spec, lines[0], others, length, fs, iq, segments)
    var_phi, amp2 = lines[-2], lines[-1]
    keep = leak <= np.fmax(np.sqrt(var_phi), LEAK_FLOOR_RAD)  # a NaN noise estimate: the floor
    if not np.sum(amp2[keep]) >= LEAK_KEEP_POWER * np.sum(amp2):
        return None
    return tuple(a[..., keep] for a in (*lines, leak))


def sidelobe_leak(spec: Spectrum, freqs: np.ndarray, others: np.ndarray, length: int, fs: float,
                  iq: bool, segments: int) -> np.ndarray:
    """How far (rad) the lines ``others`` (Hz) -- and, on a real record, each line's own image -- can
    move each line of ``freqs`` (Hz) in :func:`phase_advance` over ``segments`` parts of ``length``
    samples, as half the most they move its end parts' phase difference.

    A neighbour (on a real record its image at ``-f`` too) of amplitude ratio ``r`` (its amplitude
    over the line's, both read in the search spectrum ``spec``) ``x`` part bins away turns each part's phase by up to ``r*E(x)`` through the
    Kaiser(:data:`PHASE_WINDOW_BETA`) window's sidelobe envelope ``E(x) =
    beta/sinh(beta)/sqrt((pi*x)^2 - beta^2)`` (the continuous Kaiser window's transform; 1 inside the
    main lobe), a turn that rotates by ``2*pi*x`` from part to part: the end parts' difference is
    at most ``2*r*E(x)*|sin(pi*x*(S - 1))|`` (0 for a neighbour a whole number of part bins away,
    the same in every part). Summed over the neighbours. 0 Hz is none (each part's mean is removed).

    The separation rule (:data:`PHASE_SEPARATION_BINS`) alone lets a far stronger neighbour through:
    the envelope probe's scene 5249, a mover 41.5 dB under another 36.5 record bins away (9 bins of
    a quarter record, where the envelope is -74 dB), had every line's phase turned by ~0.02 rad a
    part and its Doppler 110-120 Hz off at a stated 24-81 Hz (speed z 5), in every frame.

    Returns
    -------
    ndarray, shape (K,): the bound per line (rad)
    """
    f = np.asarray(freqs, dtype=float)
    o = np.asarray(others, dtype=float)
    o = o[np.abs(o) > 0.5 * fs / length]
    def amp(v: np.ndarray) -> np.ndarray:
        return np.sqrt(spec.power_at(v if spec.complex_input else np.abs(v)).astype(np.float64))

    a_f = amp(f)
    if not iq:  # a real record: every line's image at -f too, the line's own among them
        o = np.concatenate([o, -o])
    dist = np.abs(o[None, :] - f[:, None])
    a_o = np.broadcast_to(amp(o)[None, :], dist.shape)
    if not iq:
        dist, a_o = np.hstack([dist, 2 * np.abs(f)[:, None]]), np.hstack([a_o, a_f[:, None]])
    x = dist * length / fs  # part bins
    beta = PHASE_WINDOW_BETA
    arg = (np.pi * x) ** 2 - beta**2
    env = np.where(arg > 0, beta / math.sinh(beta) / np.sqrt(np.maximum(arg, 1e-300)), 1.0)
    # a line itself among ``others`` (its own lines, a static line it sits on) is no neighbour
    env = np.where(x < 0.5, 0.0, np.minimum(env, 1.0)) * np.abs(np.sin(np.pi * x * (segments - 1)))
    # a line of no power in the spectrum: any neighbour turns it wholly (inf), never NaN
    return np.sum(a_o * env, axis=1) / np.maximum(a_f, 1e-300)


def _part_steps(parts_dft: PartDFTs, parts: int, freqs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The lines ``freqs`` (Hz) on ``parts`` consecutive parts of the record, and their phase steps
    from part to part less the expected advance.

    Each part's windowed (Kaiser :data:`PHASE_WINDOW_BETA`) exact DFT with its mean removed,
    ``DFT((part - mean) * w)``, each part referred to its own centre (:class:`PartDFTs`: every
    part count of one refinement from one pass over the record).

    Returns
    -------
    z : ndarray, shape (parts, K), complex
    prod : ndarray, shape (parts - 1, K), complex: ``z[s+1] * conj(z[s]) * exp(-2j*pi*f*length/fs)``
    """
    z = parts_dft(parts, freqs)
    advance = np.mod(freqs * (parts_dft.x.size // parts) / parts_dft.fs, 1.0)  # cycles per part (float64)
    return z, z[1:] * np.conj(z[:-1]) * np.exp(-2j * np.pi * advance)


def _common_residual(steps: np.ndarray, slope: np.ndarray, wt: np.ndarray) -> np.ndarray:
    """The lines' common phase across the parts about a straight line (rad), shape (S,).

    ``steps`` (S - 1, K): each line's phase step between parts (rad), summed into its unwrapped
    phase, signed by how the line moves with ``f_d`` (``slope``), averaged with weights ``wt``.
    """
    cum = np.vstack([np.zeros(steps.shape[1]), np.cumsum(steps, axis=0)])  # (S, K), unwrapped
    common = (cum * slope) @ wt / np.sum(wt)
    k = np.arange(common.size, dtype=float)
    return common - np.polyval(np.polyfit(k, common, 1), k)


#: a refinement's parts are short enough that its start lies within this fraction of the phase
#: advance's unambiguous interval +-fs/(2L) (in start sigmas: 0.1 bin of a parabola plus the wander)
WRAP_SIGMAS = 4.0
#: ... and never more parts than this in the first step
MAX_FIRST_PARTS = 32


def refine_by_phase(x: np.ndarray, frame: Frame, est: DopplerEstimate, iq: bool, others: list[float],
                    spec: Spectrum, max_lines: int | None = None, segments: int = 4,
                    pedestal: float = 0.0) -> DopplerEstimate:
    """The Doppler line's frequency from the phase advance of its lines across ``segments`` parts
    (:func:`phase_advance`), starting close enough for the advance not to wrap.

    The advance over a part of ``L`` samples is unambiguous within ``+-fs/(2L)``. A parabola
    through a spectrum of a fraction of the record (the ``fast`` profile's eighth) is known to
    ~0.1 of *its* bin, and a line broadened by the laser's phase noise wanders further: where
    :data:`WRAP_SIGMAS` times that exceeds the interval of ``segments`` parts, a first step on as
    many more parts as it takes (up to :data:`MAX_FIRST_PARTS`) brings the start close; when even
    that leaves the quarters' interval in doubt, the first step's answer stands (a slipped cycle of
    the advance would be a confident error of ``fs/L``); when the quarters then move the first
    step's answer by more than :data:`WRAP_SIGMAS` of its error, the first step may have slipped
    (its start further off than the parabola said), and the error is one cycle of its advance.
    ``pedestal``: the declared laser's linewidth (Hz; 0 for none); the pedestal about the lines then witnesses the phase they share
    (:func:`phase_advance`; a laser declared partly coherent), not in the first step.
    """
    fs, n = frame.fs_hz, x.size
    start_err = est.refine_error_hz + est.wander_hz
    parts = segments
    while WRAP_SIGMAS * start_err > fs * parts / (2 * n) and parts < MAX_FIRST_PARTS:
        parts *= 2
    # every part count below from one pass over the record (the first step's, the quarters', the
    # common phase's), as long as the lines stay near those it read
    parts_dft = PartDFTs(x, fs, PHASE_WINDOW_BETA, max(parts, COMMON_MODE_MAX_PARTS))
    if parts == segments:
        return phase_advance(x, frame, est, iq, others, spec, max_lines, segments, parts_dft, pedestal) or est
    first = phase_advance(x, frame, est, iq, others, spec, max_lines, parts, parts_dft, pedestal=0.0, leaks=False)
    if first is est:
        return est
    if WRAP_SIGMAS * (first.refine_error_hz + first.wander_hz) > fs * segments / (2 * n):
        return first
    # the other targets' lines, not this one's own at its former estimate (which would sit a
    # fraction of a bin from every line it has and leave none separable)
    others = [first.fd_hz if o == est.fd_hz else o for o in others]
    out = phase_advance(x, frame, first, iq, others, spec, max_lines, segments, parts_dft, pedestal)
    if out is None:  # a far stronger line leaks into the quarters: the start is handed back (reassigned)
        return est
    if out is not first and abs(out.fd_hz - first.fd_hz) > WRAP_SIGMAS * first.refine_error_hz:
        # the quarters moved the first step's answer far beyond its stated error: its advance may
        # have slipped a cycle (a start further off than the parabola said), so the answer is
        # known to one cycle of it
        cycle = fs * parts / n
        return out if out.refine_error_hz >= cycle else replace(out, refine_error_hz=cycle, shared_overlap_var_hz2=0.0)
    return out


def phase_advance(x: np.ndarray, frame: Frame, est: DopplerEstimate, iq: bool, others: list[float],
                  spec: Spectrum, max_lines: int | None = None, segments: int = 4,
                  parts_dft: PartDFTs | None = None, pedestal: float = 0.0, leaks: bool = True
                  ) -> DopplerEstimate | None:
    """The Doppler line's frequency from the phase advance of its lines across ``segments`` parts.

    Each line of the target (baseband, U, L) is measured on every part (windowed exact DFT of the
    part with its mean removed, centred phase); its phase advances by ``2*pi*f_line*L/fs`` per part
    of ``L`` samples, so the excess advance gives its frequency error -- without ambiguity within
    +-``fs/(2L)`` (two record bins for quarters; a parabola through a coarse spectrum is well
    inside). ``f_line`` moves with ``+-f_d``; the lines' estimates are combined with power weights.
    Lines within :data:`PHASE_SEPARATION_BINS` part bins of another line (a static line, 0 Hz,
    another target's) or of their own image (``-f`` for a real record) are left out, and the
    Kaiser window keeps what lies further away from leaking in: the DC of the LO is 30-40 dB above
    a weak Doppler line, and an unwindowed part lets -13 dB of it through.
    ``max_lines``: only the strongest lines in ``spec`` (each costs about an eighth of a pass).

    The stated error (``refine_error_hz``) is the white-noise error of the combination, scaled by
    the lines' scatter about their mean when that exceeds what noise explains (Birge ratio).

    Parameters
    ----------
    x : ndarray, shape (N,), float64 or complex128, V
    others : the Doppler lines of the other targets (Hz)
    parts_dft : the record's :class:`PartDFTs` (one for every refinement of one target)
    pedestal : the declared laser's linewidth (Hz; 0 for none): the pedestal about the strongest
        line witnesses the shared phase too (:func:`_with_shared_phase`): for a laser declared
        partly coherent (a coherent one puts no
        pedestal there, and at ~90 dB the window's own skirt would pass for one); not in a first
        step from a start that may be bins off, whose ring about the line's frequency would hold
        the line itself (and whose error decides whether the quarters' answer slipped a cycle)
    leaks : lines into which a far stronger one leaks are left out (:func:`_leak_kept`), the rest's
        leaks stated; not in a first step (a start bins off misreads the lines' sizes). Returns
        ``est`` where nothing could be measured, None where the leaks leave too few lines.
    """
    fs = frame.fs_hz
    if parts_dft is None:
        parts_dft = PartDFTs(x, fs, PHASE_WINDOW_BETA, max(segments, COMMON_MODE_MAX_PARTS))
    fd = est.fd_hz
    length = x.size // segments
    if length < 64:
        return est
    freqs, slope = target_lines(frame.tones_hz, fd, iq)
    all_freqs = freqs
    shift = modulation_doppler(frame.tones_hz, fd, iq, frame.wavelength_m)
    near = _other_lines(frame.tones_hz, fd, others, iq)
    use = _separable(freqs, freqs, near, PHASE_SEPARATION_BINS * fs / length, iq)
    if not use.any():
        return est
    freqs, slope, shift = freqs[use], slope[use], shift[use]
    if max_lines is not None and freqs.size > max_lines:
        top = np.argsort(spec.power_at(freqs))[::-1][:max_lines]
        freqs, slope, shift = freqs[top], slope[top], shift[top]
    z, prod = _part_steps(parts_dft, segments, freqs)
    if not np.any(np.abs(prod) > 0):
        return est
    d_line = np.angle(prod.sum(axis=0)) / (2 * np.pi * length / fs)  # Hz, per line
    # white noise per line: phase variance s2*sum(w^2)/(2|Z|^2) per part (step_sum_phase_variance)
    s2 = spec.noise_variances(freqs, list(freqs) + list(near))
    amp2 = np.mean(np.abs(z) ** 2, axis=0)
    wp = window_power(("kaiser", PHASE_WINDOW_BETA), length)
    var_phi = s2 * wp / (2 * np.maximum(amp2, 1e-300))
    kept = _leak_kept(spec, (freqs, slope, shift, z, prod, d_line, s2, var_phi, amp2),
                      np.concatenate([near, all_freqs]), length, fs, iq, segments) if leaks else None
    if leaks and kept is None:
        return None
    freqs, slope, shift, z, prod, d_line, s2, var_phi, amp2, leak = kept or (
        freqs, slope, shift, z, prod, d_line, s2, var_phi, amp2, np.zeros(freqs.size))
    var_line = step_sum_phase_variance(var_phi, segments) / (2 * np.pi * length / fs) ** 2
    wt = np.abs(prod).sum(axis=0)
    delta, spread, lines_chi2, sign = _combine_lines(wt, slope, d_line, var_line, shift, iq)
    spread = math.hypot(spread, _leak_bias(leak, wt, slope, segments, length / fs))
    amp_chi2 = _amplitude_chi2(z, s2 * wp / 2)
    lines_chi2 = max(lines_chi2, amp_chi2)
    amp_dof = z.size - z.shape[1]
    # chi2.sf's own function (the distribution object's call costs ~30 us, twice a refinement)
    amp_p = float(chdtrc(amp_dof, amp_chi2 * amp_dof)) if amp_dof > 0 else 1.0
    overlap = ped = 0.0
    if segments >= 3:
        moved = target_lines(frame.tones_hz, fd + delta, iq)[0] if pedestal else None
        spread, overlap, ped = _with_shared_phase(spread, spec, parts_dft, prod, (freqs, slope, wt), var_phi, amp2,
                                                  segments, all_freqs, near, iq, delta, moved, pedestal)
    return replace(est, fd_hz=fd + delta, refine_error_hz=spread, lines_chi2=lines_chi2, motion_sign=sign,
                   measured_phase_gain=part_phase_gain(segments, length, fs) if segments >= 3 else 0.0,
                   shared_overlap_var_hz2=overlap, pedestal_psd=ped, amplitude_p=amp_p)


def _amplitude_chi2(z: np.ndarray, radial_var: np.ndarray) -> float:
    """chi2 per degree of freedom of each line's amplitude across the parts about its mean (``z``:
    the parts' line phasors, shape (S, K); ``radial_var``: each line's radial noise variance per
    part, shape (K,), ``s2*sum(w^2)/2``); 0 for one part. One mover's amplitude stays (a laser's
    phase noise moves its phase only); two movers the search could not resolve beat, and every
    line's amplitude with them -- equally strong ones a bin apart even agree in their phase steps
    (each line's phase is the mean of the two echoes'), and only this shows them."""
    mag = np.abs(z)
    if mag.shape[0] < 2:
        return 0.0
    return float(np.sum((mag - mag.mean(axis=0)) ** 2 / np.maximum(radial_var, 1e-300))) / (mag.size - mag.shape[1])


def _with_shared_phase(spread: float, spec: Spectrum, parts_dft: PartDFTs, prod: np.ndarray, lines: tuple,
                       var_phi: np.ndarray, amp2: np.ndarray, segments: int, all_freqs: np.ndarray,
                       near: np.ndarray, iq: bool, delta: float, moved: np.ndarray | None,
                       linewidth: float = 0.0) -> tuple[float, float, float]:
    """:func:`phase_advance`'s error ``spread`` (Hz, its lines' white noise and scatter) with what
    every line shares: the laser's phase noise over the echo delay moves the carrier phase of all
    of them alike, and their agreement cannot show it. Returns that error (Hz), the variance (Hz^2)
    :func:`common_mode_margin` added to it (0 where it was not used, or where the pedestal does not
    pin the shared phase's low-frequency PSD: :func:`pedestal_is_flat`) and the pedestal's PSD
    (:attr:`DopplerEstimate.pedestal_psd`; 0 without ``moved``). ``linewidth``: the declared
    laser's (Hz).

    The common phase's wander across the record shows it (:func:`common_mode_error`). Where no
    part count leaves a line separable, the refinement's own parts must: ``segments - 2`` degrees
    of freedom, so few that a low draw would make a confident answer -- :data:`COMMON_MODE_MARGIN`
    on their whole scatter, and at least what the pedestal about the strongest line shows
    (:func:`pedestal_phase_psd`, tens of bins: a mover's 100 kHz laser at 13 m, 1.6 MHz of Doppler,
    whose quarters' scatter drew low, had its speed 7.7 sigmas off) through the estimate's gain
    for a shared white phase, ``var(fd) = 2*fs*sum(w^2)/sum(w)^2 / ((S - 1)*2*pi*L/fs)^2`` per unit
    PSD (the end parts' windowed mean phases, ``S`` parts of ``L`` samples).

    ``lines``: the refinement's lines (Hz), how each moves with ``f_d`` and its weight, each shape
    (K,); ``var_phi``: their white-noise phase variance per part (rad^2); ``amp2``: their mean part
    power; ``prod``: their part-to-part steps, shape (S - 1, K); ``delta``: the refinement's
    Doppler correction (Hz: the pedestal is read about the line where it now is); ``moved``: every
    line of the target there (Hz, kept out of the ring with the lines where they were), None for
    no pedestal witness. On a real record's line near 0 Hz the pedestal holds its image's too: the
    variance is then up to 4/3 of the phase's own (conservative; the target stage's
    :func:`~mtcw_core.ranging.targets.phase_psd` divides by the reassignment gain's 1.5 instead).
    """
    freqs, slope, wt = lines
    fs, length = parts_dft.fs, parts_dft.x.size // segments
    top = int(np.argmax(wt))
    ped = 0.0 if moved is None else pedestal_phase_psd(
        spec, float(freqs[top] + slope[top] * delta), float(amp2[top]) / window_sum(("kaiser", PHASE_WINDOW_BETA),
                                                                                    length) ** 2,
        np.concatenate([all_freqs, moved, near]))
    fine = common_mode_error(parts_dft, freqs, slope, wt, var_phi, segments, length, all_freqs, near, iq)
    if fine is not None:
        # the margin's part only where a pedestal was read and pins the PSD (else the floor is the
        # declared laser's at the reported range alone, short behind an unambiguous range)
        pinned = moved is not None and ped > 0 and pedestal_is_flat(ped, linewidth, spec.df_hz)
        return math.hypot(spread, fine[0]), fine[1] if pinned else 0.0, ped
    cycle = 2 * np.pi * length / fs
    res = _common_residual(np.angle(prod), slope, wt)
    var_slope = float(np.sum(res**2)) / (segments - 2) * 12 / (segments * (segments**2 - 1))
    out = max(spread, COMMON_MODE_MARGIN * math.sqrt(var_slope) / cycle)
    return max(out, math.hypot(spread, math.sqrt(part_phase_gain(segments, length, fs) * ped))), 0.0, ped


def part_phase_gain(segments: int, length: int, fs: float) -> float:
    """var(fd) (Hz^2) per unit two-sided PSD (rad^2/Hz) of a white phase every line shares, for the
    phase advance over ``segments`` Kaiser-windowed parts of ``length`` samples: the end parts'
    windowed mean phases, ``2*fs*sum(w^2)/sum(w)^2 / ((S - 1)*2*pi*L/fs)^2``."""
    wp = window_power(("kaiser", PHASE_WINDOW_BETA), length)
    sw = window_sum(("kaiser", PHASE_WINDOW_BETA), length)
    return 2 * fs * wp / sw**2 / ((segments - 1) * 2 * np.pi * length / fs) ** 2


def step_sum_phase_variance(var_phi: np.ndarray, segments: int) -> np.ndarray:
    """The variance (rad^2) of the phase of ``sum_s z[s+1]*conj(z[s])`` over ``segments`` parts, each
    line's part phasor with white-noise phase variance ``var_phi`` (rad^2, ``sigma^2/(2|A|^2)``, the
    noise power over the measured power), shape (K,).

    The signal-noise terms telescope to the two end parts: ``2*var_phi/(S-1)^2``. The noise-noise
    terms ``n[s+1]*conj(n[s])`` do not: ``S-1`` of them add ``2*var_phi^2/(S-1)`` -- at a part
    SNR of 4 dB on eight parts, more than the first. A measured power is signal plus noise, so
    ``|A|^2`` is taken as the measured power less the noise's. At most ``pi^2/3``: a line at the
    noise has a uniform phase.
    """
    v = np.asarray(var_phi, dtype=float)
    v = v / np.maximum(1.0 - 2.0 * v, 1e-12)  # sigma^2/(2(|Z|^2 - sigma^2))
    steps = max(segments - 1, 1)
    return np.minimum(2.0 * v / steps**2 * (1.0 + v * steps), np.pi**2 / 3.0)


def _combine_lines(wt: np.ndarray, slope: np.ndarray, d_line: np.ndarray, var_line: np.ndarray,
                   shift: np.ndarray | None = None, sign_known: bool = True) -> tuple[float, float, float, int]:
    """The lines' Doppler corrections combined: the weighted mean of ``slope*d_line - shift`` (Hz;
    the local floors that inverse-variance weights would trust are rough next to the strongest
    lines, so ``wt`` are power weights) and its error (Hz) -- the white-noise error of that mean,
    scaled by the lines' scatter about it when that exceeds what noise explains (Birge ratio:
    leakage, skirts), with the other lines' disagreement as a whole where they witness a bias of the
    strongest (:func:`_witness_gap`), and that scatter's chi2 per degree of freedom. All arrays
    shape (K,).

    ``shift``: the lines' modulation Doppler (:func:`modulation_doppler`) for ``f_d > 0``. With
    ``sign_known`` false (a real detector: the sign of the motion is unknown) both signs are
    tried and the one whose lines agree better (smaller chi2) is taken; unless the other's chi2 is
    larger by :data:`DIRECTION_DECISIVE_CHI2`, the two answers' half difference is added to the
    error. The sign is returned (the fourth value: +1 or -1, the sign of ``f_d``) where it is
    decisive and the lines agree under it (chi2/dof at most :data:`DIRECTION_MAX_CHI2`), else 0.

    A weak line hardly moves the mean, but its disagreement with the strong one still scales the
    error: it may be the only witness of a bias the strong line carries alone (issue 12 case 1 in
    ``accurate``: a baseband line 5 of its sigmas off, its six sidebands agreeing with the truth).
    Each line's variance must then be its real one (:func:`step_sum_phase_variance`), or noise
    alone inflates the error."""
    y = slope * d_line
    dof = max(len(wt) - 1, 1)
    stat = float(np.sqrt(np.sum(wt**2 * var_line)) / np.sum(wt))
    fits = []
    for sign in ((1, ) if shift is None or sign_known else (1, -1)):
        yy = y if shift is None else y - sign * shift
        delta = float(np.sum(wt * yy) / np.sum(wt))
        fits.append((float(np.sum((yy - delta) ** 2 / var_line)), delta, sign))
    chi2, delta, sign = min(fits)
    dof_chi2 = chi2 / dof
    err = math.hypot(stat * math.sqrt(max(dof_chi2, 1.0)), _witness_gap(wt, y - sign * (0 if shift is None else shift),
                                                                       var_line, delta))
    if len(fits) < 2:
        return delta, err, dof_chi2, 0
    if abs(fits[0][0] - fits[1][0]) < DIRECTION_DECISIVE_CHI2:
        return delta, math.hypot(err, 0.5 * abs(fits[0][1] - fits[1][1])), dof_chi2, 0
    return delta, err, dof_chi2, (sign if dof_chi2 <= DIRECTION_MAX_CHI2 else 0)


#: the other lines' mean must stand this many sigmas from the combined Doppler correction to witness a
#: bias the strongest line carries (:func:`_witness_gap`; the sigma of the other lines' mean less the
#: strongest line's: where the lines' powers are comparable the combined value lies between the two,
#: and the test is the stricter)
WITNESS_SIGMAS = 4.0


def _witness_gap(wt: np.ndarray, y: np.ndarray, var_line: np.ndarray, delta: float) -> float:
    """How far (Hz) the other lines, together, put the Doppler correction from ``delta``, the power-
    weighted mean the strongest line makes, where they disagree by more than :data:`WITNESS_SIGMAS`
    of their difference; else 0. The Birge ratio scales the strongest line's own error by the
    scatter, which is not enough when that line is far more precise than the rest and alone is
    biased: the envelope probe's scene 3413 (two movers 2.7 and 4.6 record bins up, one photodiode,
    each fitted below the guard with the other's lines 1.9 bins off) had baseband lines 1.1 and
    3.5 kHz off with errors of 2 and 22 Hz, their eight sidebands agreeing on the truth within
    ~300 Hz: chi2/dof 262 gave 27 Hz, speed z -11 and -33. All arrays shape (K,)."""
    top = int(np.argmax(wt))
    rest = np.arange(wt.size) != top
    w = 1.0 / var_line[rest]
    if not rest.any() or not np.sum(w) > 0:
        return 0.0
    mean = float(np.sum(w * y[rest]) / np.sum(w))
    gap = abs(mean - delta)
    return gap if gap > WITNESS_SIGMAS * math.sqrt(1.0 / np.sum(w) + var_line[top]) else 0.0


#: the lines' chi2 under the two signs of the motion must differ by this much for one sign's
#: Doppler to stand alone (a likelihood ratio of e^12.5, ~3e5) ...
DIRECTION_DECISIVE_CHI2 = 25.0
#: ... and, to say the direction, the lines agree under it within this chi2 per dof (a blend or
#: leakage that makes them disagree may also tilt them)
DIRECTION_MAX_CHI2 = 4.0


#: the common phase is measured on up to this many parts of the record, and at least this many
#: (more parts, more degrees of freedom in its scatter: 14 at 16 parts, where quarters leave 2)
COMMON_MODE_MAX_PARTS = 16
COMMON_MODE_MIN_PARTS = 6
#: ... each part's combined line phase at most this noisy from white noise (rad^2; ~10 dB SNR),
#: so that the phase steps between parts stay far from a wrap
COMMON_MODE_MAX_PHASE_VAR = 0.1
#: the tail the common-mode margin keeps: P(|z| > 5) from the scatter's few degrees of freedom
COMMON_MODE_TAIL = 1e-5
#: the common phase's scatter counts as phase noise when white noise alone would exceed it this
#: rarely (a chance excess in a coherent record would otherwise widen its sigma by the margin)
COMMON_MODE_SIGNIFICANCE = 0.01


@lru_cache(maxsize=64)
def _chi2_quantile(q: float, dof: int) -> float:
    """``chi2.ppf(q, dof)``, cached (scipy's ppf costs ~0.1 ms a call; a few dof recur every frame)."""
    return float(chi2_dist.ppf(q, dof))


@lru_cache(maxsize=64)
def common_mode_margin(dof: int) -> float:
    """The factor on a phase-noise sigma estimated with ``dof`` degrees of freedom that keeps the
    chance of a 5-sigma error at :data:`COMMON_MODE_TAIL`: the error over the estimate is
    Student-t distributed, ``P(|t_dof| > 5*m) = tail`` (4 dof: 5.6, 8: 2.0, 14: 1.34); at least 1."""
    return max(1.0, float(student_t.ppf(1 - COMMON_MODE_TAIL / 2, dof)) / 5.0)


def common_mode_error(parts_dft: PartDFTs, freqs: np.ndarray, slope: np.ndarray, wt: np.ndarray,
                      var_phi: np.ndarray, segments: int, length: int, all_freqs: np.ndarray, near: np.ndarray,
                      iq: bool) -> tuple[float, float] | None:
    """The Doppler error (Hz) of :func:`refine_by_phase` from the phase all its lines share.

    The laser's phase noise over the echo delay moves the carrier phase of every line alike; the
    lines' agreement cannot show it, the common phase's wander across the record does. It is
    measured on as many parts as the lines allow (from :data:`COMMON_MODE_MAX_PARTS` down to
    :data:`COMMON_MODE_MIN_PARTS`: each line still :data:`PHASE_SEPARATION_BINS` part bins from
    every other line and its image, and each part's combined phase within
    :data:`COMMON_MODE_MAX_PHASE_VAR` of white noise). The scatter of the common phase about a
    straight line, less what white noise explains (the refinement states that part already), is
    the phase noise per part. Scaled to the refinement's segments (the estimate is about
    ``(phi_S - phi_1)/(S - 1)``); where white noise alone would leave the scatter with odds below
    :data:`COMMON_MODE_SIGNIFICANCE`, widened by :func:`common_mode_margin` for its degrees of
    freedom; below that, counted as measured -- a low draw of a real laser's few degrees of
    freedom counted as none had left a speed 5.2-5.3 of its sigmas off (the map's `static+mover`
    2^16 row, 100 kHz laser, declared or not), while a coherent record's chance excess adds little
    (no margin on it).

    Parameters
    ----------
    parts_dft : the record's :class:`PartDFTs`
    freqs, slope, wt, var_phi : ndarray, shape (K,)
        The refinement's lines (Hz), how each moves with ``f_d``, its weight and its white-noise
        phase variance per segment (rad^2).
    segments, length : the refinement's segments and their length (samples)
    all_freqs : every line of the target (Hz); near: every other line there may be (Hz)

    Returns
    -------
    (error, margin_var): the error (Hz, 0 when the scatter is what white noise leaves) and the
    variance (Hz^2) the margin added to it (``(m**2 - 1)*var``:
    :attr:`DopplerEstimate.shared_overlap_var_hz2`), or None when no line allows
    :data:`COMMON_MODE_MIN_PARTS` parts
    """
    choice = None
    fs = parts_dft.fs
    for parts in range(COMMON_MODE_MAX_PARTS, COMMON_MODE_MIN_PARTS - 1, -1):
        lc = parts_dft.x.size // parts
        if lc < 64:
            continue
        use = _separable(freqs, all_freqs, near, PHASE_SEPARATION_BINS * fs / lc, iq)
        if not use.any():
            continue
        # white noise on a part's combined phase: a line's phase variance grows as its part shortens
        white = float(np.sum(wt[use] ** 2 * var_phi[use])) / float(np.sum(wt[use])) ** 2 * length / lc
        if white <= COMMON_MODE_MAX_PHASE_VAR:
            choice = parts, lc, use, white
            break
    if choice is None:
        return None
    parts, lc, use, white = choice
    _, prod = _part_steps(parts_dft, parts, freqs[use])
    res = _common_residual(np.angle(prod), slope[use], wt[use])
    dof = parts - 2
    scatter = float(np.sum(res**2)) / dof
    significant = scatter > white * _chi2_quantile(1 - COMMON_MODE_SIGNIFICANCE, dof) / dof
    per_segment = max(scatter - white, 0.0) * lc / length  # a segment averages length/lc parts' phase noise
    var_hz = 2.0 * per_segment / (segments - 1) ** 2 / (2 * np.pi * length / fs) ** 2
    margin = common_mode_margin(dof) if significant else 1.0
    return margin * math.sqrt(var_hz), (margin**2 - 1.0) * var_hz


def refine_exact(x: np.ndarray, frame: Frame, est: DopplerEstimate, iq: bool, others: list[float],
                 spec: Spectrum, pedestal: float = 0.0) -> DopplerEstimate:
    """The Doppler that maximises the exact windowed power of the target's lines.

    Starts from :func:`refine_by_phase` (whose error it keeps as its stated error, an upper bound:
    the full-record maximum uses the same lines without splitting the record) and maximises the
    summed power of the lines that refinement used -- mean removed, Kaiser-windowed
    (:data:`PHASE_WINDOW_BETA`) so that the DC and the lines' images do not pull the maximum --
    within three of its sigmas. ``pedestal``: as :func:`refine_by_phase`'s.
    """
    first = refine_by_phase(x, frame, est, iq, others, spec, pedestal=pedestal)
    if first is est:
        return est
    fd0, sig = first.fd_hz, first.refine_error_hz
    freqs0, _ = target_lines(frame.tones_hz, fd0, iq)
    near = _other_lines(frame.tones_hz, est.fd_hz, others, iq)
    sep = 2 * frame.fs_hz / x.size * 4  # record bins: the window's main lobe and a margin
    keep = np.array([np.all(np.abs(near - f) > sep) and (iq or 2 * abs(f) > sep) for f in freqs0])
    if not keep.any():
        return first
    xw = windowed_record(x, ("kaiser", PHASE_WINDOW_BETA))

    def neg_power(fd: float) -> float:
        f, _ = target_lines(frame.tones_hz, fd, iq)
        return -float(np.sum(np.abs(exact_dft(xw, f[keep], frame.fs_hz)) ** 2))

    half = max(3 * sig, 1e-3 * frame.fs_hz / x.size)
    r = minimize_scalar(neg_power, bounds=(fd0 - half, fd0 + half), method="bounded",
                        options={"xatol": 1e-3 * max(sig, 1e-6)})
    return replace(first, fd_hz=float(r.x))


def _neighbour_beats(model: _BeatModel, main: list[DopplerEstimate],
                     small: list[DopplerEstimate]) -> tuple[list[DopplerEstimate], list[DopplerEstimate]]:
    """One photodiode: the movers found below the guard beside movers found beyond it, less those
    that may be such a mover's beat with a neighbour inside its guard.

    The search does not resolve two movers within one guard (40 and 44 record bins at 2^16 in
    ``balanced``: one line at 44); their beat with each other, at the difference, then comes out
    below the guard as a mover of its own. A mover found below the guard at ``f_s`` is kept only
    where its line is stronger than :data:`BEAT_MARGIN` times the beat any mover ``m`` found
    beyond the guard could make with what the spectrum holds at ``m -+ f_s``
    (:class:`_BeatModel`); a mover that could so hide a neighbour is marked ``beat_ambiguous``
    (its neighbour's self-beat may lie on the static lines)."""
    lw = model.lo_w(main + small)
    keep, suspect = [], set()
    for sm in small:
        beats = [(model.beat_power(m.fd_hz, abs(m.fd_hz) + sg * abs(sm.fd_hz), lw), i)
                 for i, m in enumerate(main) if m.detected for sg in (-1, 1)]
        worst, who = max(beats)
        if model.power(sm.fd_hz) <= BEAT_MARGIN * worst:
            suspect.add(who)
        else:
            keep.append(sm)
    return [replace(m, beat_ambiguous=True) if i in suspect else m for i, m in enumerate(main)], keep


def _beat_scale(spec: Spectrum, settings: ChainSettings) -> float:
    """The search spectrum's record mean times its window's sum (V, :class:`_BeatModel`); 0 where
    the spectrum kept no sum."""
    if spec.total is None or spec.complex_input:
        return 0.0
    # the window the spectrum was taken with, in its dtype (the same cached array)
    return float(spec.total) / spec.n * window_sum(("kaiser", settings.window_beta), spec.n,
                                                     "float32" if settings.spectrum_single else "float64")


#: a bin of the Doppler bands counts as part of a line when it stands this far above its local
#: floor (white noise exceeds it with odds e^-10, ~4.5e-5 a bin)
SELF_BEAT_LINE_RATIO = 10.0


def unexplained_lines(spec: Spectrum, tones_hz, fd_max_hz: float, min_bins: int, fds: list[float]
                      ) -> dict | None:
    """What stands out of the local floor (:data:`SELF_BEAT_LINE_RATIO`) in the Doppler bands and no
    line explains, per band: ``"B"`` (``guard`` to ``fd_max_hz`` above 0 Hz) and ``("U", f_i)``,
    ``("L", f_i)`` (the same offsets above and below each tone) -- the guard the search's
    (:func:`_guard_bins`, at least ``min_bins``). Explained: the found movers' lines (``fds``, Hz),
    their beats with each other, 0 Hz, the tones and their intermodulation products, each within
    the guard. The search notes the bins as it scores (:func:`_standing_out`, ``spec.memo``).

    Returns
    -------
    dict: band -> (frequencies (Hz), shape (K,); each bin's amplitude^2 above the floor (V^2, a
    cosine's: a line's energy over its bins is ``N*sum(w^2)*A^2/4``, Parseval), shape (K,)), and
    ``"guard"`` (bins); None for a complex record
    """
    tones = np.asarray(tones_hz, dtype=float)
    if spec.complex_input:
        return None
    bmax = search_bmax(spec, fd_max_hz)
    key = _stand_out_key(tones, bmax)
    if key not in spec.memo:  # the search did not look at this spectrum (its scores note them)
        if bmax <= min_bins + 1:
            return None
        _score_candidates(spec, search_floor(spec, tones, bmax), tones, 1, bmax, _guard_bins(spec, tones, min_bins),
                          fd_max_hz, 1.0, True)
    bands = spec.memo[key]
    guard_bins = bands["guard"]
    df = spec.df_hz
    fds = [abs(f) for f in fds]
    ghosts = _ghost_base(tones, fd_max_hz)
    explained = [ghosts]
    for i, fa in enumerate(fds):
        explained.append(target_lines(tones, fa, False)[0])
        explained.append(ghosts[:, None] + np.array([-fa, fa])[None, :])
        for fb in fds[i + 1:]:
            beats = np.array([fa - fb, fa + fb])
            explained.append(np.concatenate([beats, (tones[:, None] + beats[None, :]).ravel(),
                                             (tones[:, None] - beats[None, :]).ravel()]))
    explained = np.sort(np.abs(np.concatenate([np.ravel(e) for e in explained])))
    scale = 4.0 / (spec.n * spec.window_power)

    def band(name, at) -> tuple[np.ndarray, np.ndarray]:
        k, excess = bands[name]
        keep = k >= guard_bins
        k, excess = k[keep], excess[keep]
        f = np.abs(at(k * df))
        j = np.clip(np.searchsorted(explained, f), 1, explained.size - 1)
        near = np.minimum(np.abs(f - explained[j - 1]), np.abs(f - explained[j]))
        far = near > guard_bins * df
        return f[far], excess[far] * scale

    out = {"guard": guard_bins, "B": band("B", lambda d: d)}
    for f in tones:
        out["U", float(f)] = band(("U", float(f)), lambda d, f=f: f + d)
        out["L", float(f)] = band(("L", float(f)), lambda d, f=f: f - d)
    return out


def self_beat_bound(spec: Spectrum, tones_hz, fd_max_hz: float, min_bins: int, fds: list[float]) -> np.ndarray:
    """One photodiode: per tone, the largest amplitude (V, a cosine's) that the self-beats of
    Doppler lines no mover found explains could put on the static line at ``f_i``.

    Every echo also beats with itself, ``|E_m|^2``, onto lines at the tones with no Doppler:
    ``S_i = sum_m U_im * conj(B_m) / A_L^2`` over the movers (``B_m`` a mover's baseband line,
    ``U_im`` its sideband at ``f_i + f_dm``, :func:`~.extract.self_beat_lines`). The extract
    stage takes out those of the movers found; movers the search could not resolve or did not
    find leave theirs. By Cauchy-Schwarz, ``|S_i| <= sqrt(sum_m |U_im|^2 * sum_m |B_m|^2) / A_L^2``,
    and the two sums are the energy of the Doppler bands' unexplained lines
    (:func:`unexplained_lines`). ``A_L^2`` is taken as the record's mean
    (the LO's DC and the echoes', slightly more: the bound is then slightly low).

    Parameters
    ----------
    spec : the search spectrum (real record)
    tones_hz : shape (T,), Hz
    min_bins : the search's least guard (bins of ``spec``, ``doppler_min_bins``)
    fds : the Doppler lines found (Hz)

    Returns
    -------
    ndarray, shape (T,), V (zeros for a complex record, or one without its sum or a positive mean)
    """
    tones = np.asarray(tones_hz, dtype=float)
    if spec.complex_input or spec.total is None or not float(spec.total) > 0:
        return np.zeros(tones.size)
    lines = unexplained_lines(spec, tones, fd_max_hz, min_bins, fds)
    if lines is None:
        return np.zeros(tones.size)
    base = float(np.sum(lines["B"][1]))
    if base <= 0:
        return np.zeros(tones.size)
    side = np.array([0.5 * (np.sum(lines["U", float(f)][1]) + np.sum(lines["L", float(f)][1])) for f in tones])
    return np.sqrt(side * base) / (float(spec.total) / spec.n)


def estimate_doppler(x: np.ndarray, frame: Frame, spec: Spectrum, settings: ChainSettings,
                     gated: bool = False) -> list[DopplerEstimate]:
    """The stage: Doppler lines, strongest first (``[not detected]`` when there is none), found and
    refined by :func:`find_doppler`; on one photodiode each with the pull the beats of the movers
    found with each other can put on it (:func:`beat_pulls`)."""
    found = find_doppler(x, frame, spec, settings, gated)
    return beat_pulls(x, found, frame.fs_hz, spec.df_hz, settings.window_beta) if frame.receiver == "single" else found


def beat_pulls(x: np.ndarray, found: list[DopplerEstimate], fs_hz: float, search_bin_hz: float, beta: float
               ) -> list[DopplerEstimate]:
    """One photodiode: ``found``, each with the pull (Hz) the beats of every pair of the movers
    found -- at ``|f_a| +- |f_b|``, one of the pair possibly the line itself (a mover at twice its
    speed, or one below the guard) -- can put on its estimate, summed over the beats (their worst
    case adds): ``rho*min(x, cap)`` bins, ``x`` their distance in bins and ``rho`` the beat's
    amplitude over the line's, ``A_a*A_b/(2*L*A_c)`` from the movers' baseband lines
    ``A_k = 2R|E_LO||E_k|`` (fitted together on the record with its mean: the search spectrum's
    bins misread a line below the guard beside another) and the LO's part ``L`` of the mean
    (:func:`lo_part`), times :data:`BEAT_PULL_MARGIN`. Where ``x`` is within the estimate's
    reach: for a phase advance the lobe of its parts' Kaiser(:data:`PHASE_WINDOW_BETA`) window,
    ``sqrt(1 + (beta/pi)^2)`` part bins of its 4 quarters (a wobble aliases through the parts'
    phases rather than averaging out: with a mover 40 record bins up, pulled by 0.05 / 0.20 /
    0.19 / 0.24 / 0.14 / 0.07 ``rho`` bins with the beat 0.1 / 0.6 / 1 / 2 / 3 / 6 bins away, under
    0.002 from 8 bins on; a review's simulation of the quarters' estimator: at most 0.42); one
    record bin for a line fitted below the guard (the fit holds the beats half a bin or more from
    its line: scene 13702's first mover was pulled by 0.03 / 0.06 / 0.06 / 0.20 ``rho`` bins with
    the beat 0.05 / 0.1 / 0.3 / 0.6 bin away, under 0.004 from 1 to 16 bins); the
    Kaiser(:data:`REASSIGN_BETA`) lobe's half width of the whole record for a reassigned line (its
    pull peaks at 0.74 at 1.2 bins); that of the search spectrum's Kaiser(``beta``) in its bins
    for a parabola (peaks at 0.81 at 1.5 bins: capped at :data:`PARABOLA_PULL_BINS`, the others
    at :data:`CROSS_PULL_BINS`). The envelope probe's scene 13702, 8-bit: movers at 2.35 and 4.78
    record bins, their beat 0.09 bin from the first at 1.2 % of its size: that speed 44 Hz off at
    a stated 4.7 Hz, 9 sigmas. Where the LO's part of the mean cannot be told (an AC-coupled front
    end, echoes holding half the mean) and a beat lies within a mover's reach, every mover is
    marked ``beat_ambiguous`` instead."""
    movers = [d for d in found if d.detected]
    if len(movers) < 2:
        return found
    n = x.size
    base = np.array([abs(d.fd_hz) for d in movers])
    pairs = [(i, j, abs(base[i] + sg * base[j])) for i in range(base.size) for j in range(i + 1, base.size)
             for sg in (-1, 1)]

    def bins(d: DopplerEstimate) -> tuple[float, float, float]:  # the estimate's bin (Hz), reach (bins), cap
        if d.method == "phase":
            return fs_hz / n, 4.0 * math.sqrt(1.0 + (PHASE_WINDOW_BETA / math.pi) ** 2), CROSS_PULL_BINS
        if d.method == "fit":
            return fs_hz / n, 1.0, CROSS_PULL_BINS
        if d.method:
            return fs_hz / n, math.sqrt(1.0 + (REASSIGN_BETA / math.pi) ** 2), CROSS_PULL_BINS
        return search_bin_hz, math.sqrt(1.0 + (beta / math.pi) ** 2), PARABOLA_PULL_BINS

    near = [(c, i, j, f) for c, d in enumerate(movers) for i, j, f in pairs
            if abs(f - base[c]) <= bins(d)[0] * bins(d)[1]]
    if not near:
        return found
    total = float(np.sum(x))
    amps = np.abs(solve_lines(_record_dft(x, base, fs_hz), base, fs_hz, n, total, False)[1])
    lo = lo_part(total / n, float(np.sum(amps**2)))
    if lo <= 0:
        return [replace(d, beat_ambiguous=True) if d.detected else d for d in found]
    pull = np.zeros(base.size)
    for c, i, j, f in near:
        rbin, _, cap = bins(movers[c])
        rho = BEAT_PULL_MARGIN * amps[i] * amps[j] / (2 * lo * max(amps[c], 1e-300))
        pull[c] += rho * min(abs(f - base[c]) / rbin, cap) * rbin
    pulled = {id(d): float(p) for d, p in zip(movers, pull) if p > 0}
    return [replace(d, beat_pull_hz=pulled[id(d)]) if id(d) in pulled else d for d in found]


def find_doppler(x: np.ndarray, frame: Frame, spec: Spectrum, settings: ChainSettings,
                 gated: bool = False) -> list[DopplerEstimate]:
    """Doppler lines, strongest first (``[not detected]`` when there is none).

    ``gated``: a quasi-CW record (echo in windows, laser incoherent at km delays): the phase
    refinement, which follows the lines' phases across the record, falls back to the parabola.

    In a CW record and a refining profile (``fast`` too, whose guard on an eighth of the record is
    8x wider in Hz), :func:`search_small_doppler` looks below the search's guard on the whole
    record, with the movers the search found beyond it held (a mover below the guard beside one
    above it: ``fast``'s movers 40 and 120 record bins up at 2^16, its guard 48); the movers found
    there follow the search's, strongest first. With nothing found anywhere, the estimate states
    :func:`small_doppler_floor_hz` as the smallest Doppler it could have measured.
    """
    width = line_width_bins(spec, frame.tones_hz)  # the lines' width, read once (search, guard, floor)
    # one photodiode: the echoes' beats with each other, predicted once for the frame
    beats = _BeatModel(spec, _beat_scale(spec, settings)) if frame.receiver == "single" else None
    ests = search_doppler(spec, list(frame.tones_hz), fd_max(frame.tones_hz, settings),
                          settings.doppler_min_bins, settings.doppler_threshold, max_targets=settings.max_targets,
                          width=width, beat_scale=beats.dc_w if beats is not None else None)
    # the movers beyond the guard, refined first: a mover below it is fitted with their lines held,
    # and a line held half a search bin off leaks into that fit (12 and 300 bins at 2^16 in fast:
    # the first's speed z 5-13 beside the second's parabola)
    iq = np.iscomplexobj(x)
    main_refined = ests
    if ests[0].detected and not (settings.doppler_refine == "parabolic" or (gated and settings.doppler_refine == "phase")):
        main_refined = _refine_found(x, frame, ests, iq, [e.fd_hz for e in ests], spec, settings)
    small: list[DopplerEstimate] = []
    if not gated and settings.doppler_refine != "parabolic":
        # below the guard, on the whole record: a mover there, alone or beside those found beyond it
        main = tuple(e.fd_hz for e in main_refined if e.detected)
        guard = _guard_bins(spec, frame.tones_hz, settings.doppler_min_bins, width)
        f_max = fd_max(frame.tones_hz, settings)
        band = small_band(spec, guard, f_max, frame.fs_hz, x.size)
        low = LowBand.of(x, frame.fs_hz, band[1] * x.size / frame.fs_hz)
        if main:
            # a guard short of the nearest mover found: nearer, its phase-noise pedestal (the laser's,
            # over the echo delay) carries bumps the search's own rule keeps out -- where it has one
            # (only where a whole guard's cut reaches into the band: the margin is never wider)
            band = (band[0], min([band[1], *(abs(m) - _pedestal_margin(spec, low, frame.tones_hz, m, guard, x.size)
                                             for m in main if abs(m) - guard * spec.df_hz < band[1])]))
        while band[1] > band[0] and len(main) + len(small) < settings.max_targets:
            more = search_small_doppler(x, frame, spec, guard, f_max, settings.doppler_threshold,
                                        (*main, *(d.fd_hz for d in small)), low, band[1])
            if more is None:
                break
            small.append(more)
        if main:
            # a mover inside the lobe of one the search found is one line there (``fast``'s eighth
            # of the record: movers 90 and 120 record bins apart), or lies within the guard rule's
            # reach of it (one to two guards: movers 8 and 16 record bins up at 2^16, in every
            # profile), and its lines leak into every other fit
            near = _lobe_neighbours(x, frame, spec, guard, f_max, settings.doppler_threshold, main, small,
                                    band[1], settings.max_targets - len(main) - len(small))
            # ... and where it lies closer than the refinement's quarters resolve, the line the
            # search found was both: its refined Doppler is neither's, and the neighbour's fit held
            # that line where no mover is
            sep = quarters_resolve_hz(frame.fs_hz, x.size)
            found = [m for m in main_refined if m.detected]
            main_refined = [replace(m, unresolved=True) if m.detected and within(m, near, sep) else m
                            for m in main_refined]
            small += [replace(d, unresolved=True) if within(d, found, sep) else d for d in near]
        if small and main and beats is not None:
            main_refined, small = _neighbour_beats(beats, main_refined, small)
        if len(small) > 1 or (small and main):
            small = remeasure_small(x, frame, spec, small, *band, held=main)
        if small and main:
            main_refined = _refine_beside_small(x, frame, ests, main_refined, small, iq, spec, settings)
        small.sort(key=lambda d: -d.score)
        if beats is not None:
            # the search's own check saw its movers only: with those found below the guard too
            movers = beats.mark([d for d in main_refined if d.detected] + small)
            main_refined, small = movers[:len(movers) - len(small)] if main else main_refined, movers[len(movers) - len(small):]
        if not main:
            return small or [replace(ests[0], min_detectable_hz=small_doppler_floor_hz(
                spec, frame.tones_hz, guard, frame.fs_hz, x.size, width))]
    return main_refined + small if ests[0].detected else ests


def _refine_found(x: np.ndarray, frame: Frame, ests: list[DopplerEstimate], iq: bool, others: list[float],
                  spec: Spectrum, settings: ChainSettings) -> list[DopplerEstimate]:
    """The search's movers refined (:func:`refine_by_phase` or :func:`refine_exact`, by the profile;
    where no line is separable there, :func:`refine_reassigned`), ``others`` (Hz) the Doppler lines
    of every mover the search found, whose lines each refinement keeps out."""
    # a laser declared partly coherent: the pedestal about the lines witnesses the phase they share
    # (where the refinement's own parts must measure it, or one window cannot); a coherent one puts
    # none there, and the target stage would not read it
    ped = settings.laser_linewidth_hz
    if settings.doppler_refine == "phase":
        out = [refine_by_phase(x, frame, est, iq, others, spec, settings.doppler_phase_lines, pedestal=ped)
               for est in ests]
    else:
        out = [refine_exact(x, frame, est, iq, others, spec, pedestal=ped) for est in ests]
    return [replace(new, method="phase") if new is not old else
            (refine_reassigned(x, frame, old, iq, others, spec, ped) if old.detected else old)
            for new, old in zip(out, ests)]


#: a mover found beyond the search's guard is refined again without the lines of those found below
#: it (:func:`_refine_beside_small`) where one of them lies within this many record bins of it: the
#: quarters' main lobe is 4 x 4.6 bins wide, the reassignment's 4.6
CLEAN_NEIGHBOUR_BINS = 20.0


def _refine_beside_small(x: np.ndarray, frame: Frame, ests: list[DopplerEstimate], refined: list[DopplerEstimate],
                         small: list[DopplerEstimate], iq: bool, spec: Spectrum, settings: ChainSettings
                         ) -> list[DopplerEstimate]:
    """The movers beyond the guard (``refined``, from ``ests``) refined again on the record without
    the lines of the movers found below it (``small``), where one of those lies within
    :data:`CLEAN_NEIGHBOUR_BINS` of it and further than :data:`WRAP_SIGMAS` of its own error (closer,
    the mover below the guard may be that one itself: taken out, it left a 2^16 ``fast`` mover at
    0.45x the tone spacing 15 sigmas off).

    They were refined before the movers below the guard were known, and those movers' lines leaked
    in (issue 12 case 6 in IQ: 20 and 65 kHz, 4.5 record bins apart at ~90 dB, the 65 kHz mover's
    reassignment 0.48 Hz off against a stated 0.009 Hz). Keeping those lines out leaves none to
    refine on; taking them out of the record does not: every mover's lines, the static lines and
    the movers' beats are fitted together on the whole record (:class:`_SmallFit`), and the lines
    of the movers below the guard are subtracted (:func:`~.tones.lines_signal`) before the
    refinement runs again. The other movers beyond the guard -- and these, where the joint fit
    cannot be made -- are refined again with the lines of the movers below the guard they are clear
    of held among the others (one more refinement each): their refinement keeps those lines out or
    states their leak. Each refined estimate keeps the flags the others' stages gave it.
    """
    fs, n = frame.fs_hz, x.size

    def clear(m: DopplerEstimate, d: DopplerEstimate) -> bool:
        # another mover, not within the refined one's own error (a first step known to a cycle: the
        # mover below the guard is then that mover), nor so close that the joint fit cannot tell
        # their lines apart (the sub-guard scan's own keep-out)
        return max(WRAP_SIGMAS * (m.refine_error_hz + m.wander_hz), SMALL_OTHER_BINS * fs / n) < abs(
            abs(m.fd_hz) - abs(d.fd_hz))

    def held(idx: list[int]) -> dict[int, DopplerEstimate]:
        # refined again on the record with the lines of the movers below the guard each is clear of
        # among the others: each keeps them out or states their leak (:func:`sidelobe_leak`)
        out = {}
        for i in idx:
            hold = [d.fd_hz for d in small if clear(refined[i], d)]
            if hold:
                out[i] = _refine_found(x, frame, [ests[i]], iq, [e.fd_hz for e in ests] + hold, spec, settings)[0]
        return out

    near = {i for i, m in enumerate(refined) if m.detected and any(
        clear(m, d) and abs(abs(m.fd_hz) - abs(d.fd_hz)) < CLEAN_NEIGHBOUR_BINS * fs / n for d in small)}
    # the rest, with the lines of those below the guard held (the envelope probe's scene 41314, IQ,
    # 2^18 samples: a mover 63 record bins from one below the guard 3.6 dB stronger, refined on
    # quarters that its sidelobes turned by ~1.6e-4 rad, 1.5 Hz off at a stated 0.12 Hz)
    again = held([i for i, m in enumerate(refined) if m.detected and i not in near])
    if not near:
        return _with_refined(refined, again)
    tones = np.asarray(frame.tones_hz, float)
    main = tuple(m.fd_hz for m in refined if m.detected)
    fit = _SmallFit(x, fs, tones, iq, main + tuple(d.fd_hz for d in small))
    gaps = np.abs(fit.static[:, None] - fit.static[None, :]) + np.eye(fit.static.size) * fs
    try:
        # two lines on one frequency (a sideband of one on another's): no joint fit
        amps = fit.held_amps if gaps.min() >= 0.5 * fs / n else None
    except np.linalg.LinAlgError:
        amps = None
    order = sorted(near)
    if amps is None:  # no joint fit: their lines held, as the rest's
        again.update(held(order))
        return _with_refined(refined, again)
    per = target_lines(tones, 0.0, iq)[0].size
    take = slice(fit.n_static + len(main) * per, fit.n_static + (len(main) + len(small)) * per)
    clean = x - lines_signal(amps[take], fit.static[take], fs, n, iq)
    again.update(zip(order, _refine_found(clean, frame, [ests[i] for i in order], iq, [e.fd_hz for e in ests],
                                          spec, settings)))
    return _with_refined(refined, again)


def _with_refined(refined: list[DopplerEstimate], again: dict[int, DopplerEstimate]) -> list[DopplerEstimate]:
    """``refined`` with the estimates refined again (``again``, by index), each keeping the flags
    the other stages gave it."""
    return [replace(m, fd_hz=again[i].fd_hz, refine_error_hz=again[i].refine_error_hz, method=again[i].method,
                    shared_phase_gain=again[i].shared_phase_gain, measured_phase_gain=again[i].measured_phase_gain,
                    pedestal_psd=again[i].pedestal_psd, shared_overlap_var_hz2=again[i].shared_overlap_var_hz2,
                    lines_chi2=again[i].lines_chi2, amplitude_p=again[i].amplitude_p,
                    motion_sign=again[i].motion_sign) if i in again else m for i, m in enumerate(refined)]


#: a mover's line has no phase-noise pedestal about it where its near floor is within this factor of
#: the wide ring's (:func:`_pedestal_margin`; white noise: the two medians agree within ~20 %)
PEDESTAL_FREE_RATIO = 2.0


def _pedestal_margin(spec: Spectrum, low: LowBand, tones_hz, fd: float, guard_bins: int, n: int) -> float:
    """How far (Hz) below a mover found beyond the guard, at ``fd`` (Hz), the sub-guard band ends:
    the search's guard where the mover's line may carry a phase-noise pedestal (the laser's, over
    the echo delay, whose bumps would pass for movers), :data:`SMALL_OTHER_BINS` + 1 record bins
    where it has none -- its baseband line coherent (:func:`_too_wide`) and the floor about it
    (:data:`SMALL_NEAR_HALF_WIDTH` bins) within :data:`PEDESTAL_FREE_RATIO` of the wide ring's.
    Two movers 2 and 6.5 record bins up (IQ, 2^16, coherent laser): ``balanced``'s guard of 6
    bins left the first no band at all, and it was missed in every frame. Only where the search
    spectrum is the whole record's: ``fast``'s eighth-record line may be two movers in one of its
    bins (40 and 60 record bins up at 2^16: one line at 47), which its lobe search separates; a
    band up to 3 bins short of it fitted the 40-bin mover with a line held where none is (the
    movers probe: 13 confident-wrong frames)."""
    if spec.record_n is not None:
        return guard_bins * spec.df_hz
    f = fd if spec.complex_input else abs(fd)
    excl = [0.0, *np.asarray(tones_hz, float), f]
    near = spec.noise_variances([f], excl, half_width=SMALL_NEAR_HALF_WIDTH, guard=SMALL_NEAR_GUARD)[0]
    wide = spec.noise_variances([f], excl)[0]
    if _too_wide(spec, low, fd) or not near <= PEDESTAL_FREE_RATIO * wide:
        return guard_bins * spec.df_hz
    return (SMALL_OTHER_BINS + 1) * spec.fs_hz / n


#: reassignment steps from the search's parabola (each one DFT pair of the target's lines)
REASSIGN_STEPS = 3
#: its window: Kaiser(14), sidelobes ~100 dB down -- the derivative window passes a neighbour's
#: leakage on, and Kaiser(8)'s let the mean-removed DC and a real line's image pull a line 6 bins
#: from 0 Hz by 20-100 Hz at 2^16 samples (where its noise sigma is 6 Hz)
REASSIGN_BETA = 14.0
#: ... and every line used at least this many record bins from every other (its main lobe: 4.6)
REASSIGN_SEPARATION_BINS = 5.0
#: a line's own frequency enters a combined estimate from this post-integration SNR (15 dB): below
#: it the line's frequency leaves its Cramér-Rao bound (the threshold effect) and its scatter would
#: inflate the combination's error by Birge's ratio for nothing
LINE_FREQUENCY_SNR = 30.0


@lru_cache(maxsize=4)
def _window_and_slope(n: int) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The reassignment's Kaiser window over ``n`` samples and its derivative per sample (read-only),
    and the sums of the window and of the derivative's square."""
    w = cached_window(("kaiser", REASSIGN_BETA), n)
    dw = np.gradient(w)
    dw.setflags(write=False)
    return w, dw, float(np.sum(w)), float(np.sum(dw**2))


def _above_threshold(snr: np.ndarray) -> np.ndarray:
    """Which lines (post-integration SNR ``snr``, shape (K,)) a frequency estimate may use: those
    at :data:`LINE_FREQUENCY_SNR` or more -- below it a line's frequency leaves its Cramér-Rao
    bound (the threshold effect: a ratio with noise in its denominator has heavy tails), and its
    scatter would move the combination and inflate its error by Birge's ratio for nothing -- or
    the strongest line alone when none is; shape (K,), bool."""
    keep = snr >= LINE_FREQUENCY_SNR
    if not keep.any():
        keep[int(np.argmax(snr))] = True
    return keep


def refine_reassigned(x: np.ndarray, frame: Frame, est: DopplerEstimate, iq: bool, others: list[float],
                      spec: Spectrum, pedestal: float = 0.0) -> DopplerEstimate:
    """The Doppler line's frequency by reassignment over the whole record, for lines too close to
    each other for :func:`phase_advance`'s parts (a mover a few bins from the static lines).

    With the record's mean removed, windowed (Kaiser, :data:`REASSIGN_BETA`) and weighted by
    the window's derivative ``w'``, a line at ``f + delta`` gives
    ``X_w'(f)/X_w(f) = -2j*pi*delta/fs`` (summation by parts; the window vanishes at its ends), so
    ``delta = -fs/(2*pi) * Im(X_w'/X_w)`` -- the frequency reassignment of time-frequency analysis
    (Auger & Flandrin 1995). It is applied :data:`REASSIGN_STEPS` times from the parabola to every
    target line at least :data:`REASSIGN_SEPARATION_BINS` record bins from every other line and its
    image, and the lines' estimates are combined as in :func:`phase_advance` (power weights, the
    white-noise error ``fs/(2*pi) * sqrt(s2*sum(w'^2)/(2|X_w|^2))`` per line, Birge-scaled by
    their scatter). A phase all the lines share (the laser's phase noise over the echo delay)
    moves them alike and one window cannot see it: ``shared_phase_gain`` =
    ``fs^3*sum(w'^2)/(4*pi^2*sum(w)^2)`` (x1.5 for a real record: the line's image carries the
    same phase, whose flat PSD reaches across ``2f``) turns its low-frequency PSD into var(fd) for
    the target stage, which knows the delay. With ``pedestal`` (the declared laser's linewidth, Hz; 0 for none)
    the pedestal about the strongest line is read too (``pedestal_psd``, :func:`pedestal_phase_psd`:
    the delay the range cannot tell). Returns ``est`` unchanged when no line is separable.

    Parameters
    ----------
    x : ndarray, shape (N,), float64 or complex128, V
    others : the Doppler lines of the other targets (Hz)
    """
    fs, n = frame.fs_hz, x.size
    fd = est.fd_hz
    freqs, slope = target_lines(frame.tones_hz, fd, iq)
    near = _other_lines(frame.tones_hz, fd, others, iq)
    use = _separable(freqs, freqs, near, REASSIGN_SEPARATION_BINS * fs / n, iq)
    if n < 256 or not use.any():
        return est
    w, dw, sw, sdw2 = _window_and_slope(n)
    # the record less its mean, windowed and weighted by the window's slope: two rows of one buffer,
    # read together by each step's transform
    rows = np.empty((2, n), dtype=np.result_type(x.dtype, np.float64))
    np.subtract(x, x.mean(), out=rows[1])
    np.multiply(rows[1], w, out=rows[0])
    rows[1] *= dw
    s2 = spec.noise_variances(freqs[use], list(freqs[use]) + list(near))
    for step in range(REASSIGN_STEPS):
        freqs, slope = target_lines(frame.tones_hz, fd, iq)
        zw, zd = exact_dft_parts(rows, freqs[use], fs)
        if not np.all(np.abs(zw) > 0):
            return est
        if step == 0:  # lines at the noise leave the estimate (the threshold effect)
            keep = _above_threshold(np.abs(zw) ** 2 / (s2 * window_power(("kaiser", REASSIGN_BETA), n)))
            use[np.flatnonzero(use)[~keep]] = False
            zw, zd, s2 = zw[keep], zd[keep], s2[keep]
        d_line = -fs / (2 * np.pi) * np.imag(zd / zw)  # Hz, per line
        wt = np.abs(zw) ** 2
        delta = float(np.sum(wt * slope[use] * d_line) / np.sum(wt))
        if not math.isfinite(delta) or abs(fd + delta - est.fd_hz) > REASSIGN_SEPARATION_BINS * fs / n:
            return est  # walked off the line the search found
        fd += delta
    var_line = (fs / (2 * np.pi)) ** 2 * s2 * sdw2 / (2 * wt)
    shift = modulation_doppler(frame.tones_hz, fd, iq, frame.wavelength_m)[use]
    combined, spread, lines_chi2, sign = _combine_lines(wt, slope[use], d_line, var_line, shift, iq)
    fd += combined - delta  # the last step's correction with the sidebands' own shift taken out
    # a real record's line has its image at -f, carrying the same phase with the opposite sign:
    # the difference phase's flat PSD reaches across 2f and adds half as much again
    gain = (1.0 if iq else 1.5) * fs**3 * sdw2 / (4 * np.pi**2 * sw**2)
    # the shared phase's PSD as its pedestal shows it, for an echo delay the range cannot tell
    top = int(np.argmax(wt))
    white = white_floor(spec, np.concatenate([freqs, near])) if pedestal else None
    ped = pedestal_phase_psd(spec, float(freqs[use][top]), float(wt[top]) / sw**2,
                             np.concatenate([freqs, near]), white) if pedestal else 0.0
    # a line under the search's threshold within the window's main lobe pulls the strongest line
    # beyond its white-noise error (the envelope probe's scene 4019): probed beside it
    line = float(freqs[use][top] + d_line[top])  # where the last step read it
    known = np.concatenate([near, freqs[np.arange(freqs.size) != np.flatnonzero(use)[top]]]
                           + ([] if iq else [[0.0, -line]]))
    pull = neighbour_pull(x, line, fs, float(s2[top]), known)
    # (where the pedestal pins the shared phase's PSD: a delay longer than the range says, behind an
    # unambiguous range, leaves the laser's term short, and the local floors' error counts too)
    overlap = _pedestal_overlap(white[0], (wt, slope[use], d_line, shift), s2, spread,
                                (fs / (2 * np.pi)) ** 2 * sdw2 / (2 * wt), iq) \
        if pedestal and pedestal_is_flat(ped, pedestal, spec.df_hz) else 0.0
    # a far stronger line's sidelobes pull every line (reassign_leak), combined as the lines are
    far = reassign_leak(rows[0], freqs[use], np.abs(zw), np.concatenate([near, freqs]), fs, iq, np.sqrt(var_line))
    return replace(est, fd_hz=fd, refine_error_hz=math.hypot(spread, pull, float(np.sum(wt * far) / np.sum(wt))),
                   method="reassigned",
                   shared_phase_gain=gain, pedestal_psd=ped, lines_chi2=lines_chi2, motion_sign=sign,
                   shared_overlap_var_hz2=overlap)


#: :func:`reassign_leak` reads a neighbour's pull exactly where this many times the window slope's
#: envelope (:func:`_slope_leak`) says it could reach ...
SLOPE_LEAK_SCREEN = 2.0
#: ... this share of the line's own error
REASSIGN_LEAK_SHARE = 0.1


@lru_cache(maxsize=2)
def _slope_leak(n: int) -> np.ndarray:
    """The envelope of ``|W'(D)|/W(0)``, the reassignment's window slope's DFT
    (:func:`_window_and_slope`), on a grid of half record bins, ``D = k*fs/(2n)`` for ``k = 0..n``,
    read-only: at each point the largest root-sum-square of two points half a bin apart within a
    bin of it (a sidelobe turning once a bin, ``|a*sin(pi*D + c)|``, is ``a`` on any such two; the
    main lobe's foot, 5-6.5 bins out, turns faster and stands up to 5.6x a narrower envelope).

    One zero-padded FFT of the slope per record length, cached: :func:`reassign_leak`'s screen. The
    continuous window's envelope overstated the slope's far sidelobes 4-500x beyond a few tens of
    bins, and every neighbour was then read exactly (~7 ms a 2^18-sample record)."""
    _, dw, sw, _ = _window_and_slope(n)
    mag2 = (np.abs(scipy.fft.rfft(dw, 2 * n)) / sw) ** 2
    pair = np.sqrt(np.concatenate([mag2[:-1] + mag2[1:], mag2[-1:]]))  # points k and k + 1
    out = pair.copy()
    for step in (1, 2):  # the largest within a bin either side (the main lobe's foot turns faster)
        out[step:] = np.maximum(out[step:], pair[:-step])
        out[:-step] = np.maximum(out[:-step], pair[step:])
    out.setflags(write=False)
    return out


def reassign_leak(xw: np.ndarray, freqs: np.ndarray, a_f: np.ndarray, others: np.ndarray, fs: float, iq: bool,
                  sigma_hz: np.ndarray) -> np.ndarray:
    """How far (Hz) the lines ``others`` (Hz; the target's own among them: a line itself is none)
    -- and, on a real record, their images at ``-f`` -- can pull each line of ``freqs`` (Hz, shape
    (K,)) in :func:`refine_reassigned`, through its window's sidelobes, shape (K,).

    A neighbour ``D`` Hz away, of amplitude ratio ``r`` (its amplitude over the line's), adds
    ``r*W(D)/W(0)`` to the line's windowed DFT and ``r*W'(D)/W(0)`` to its slope-weighted one (``W'``
    the DFT of the window's slope), so the reassigned frequency moves by up to
    ``fs/(2*pi) * r*|W'(D)|/W(0)``. The continuous window's ``|W'(D)|`` is ``2*pi*D/fs`` times its
    envelope (:func:`sidelobe_leak`'s): a pull that does not fall with distance. The discrete
    window's slope leaks less far out, so the pull is read exactly (one DFT of the slope over the
    record) wherever :data:`SLOPE_LEAK_SCREEN` times the slope's own envelope (:func:`_slope_leak`)
    reaches :data:`REASSIGN_LEAK_SHARE` of the line's own error ``sigma_hz`` (Hz, shape (K,)); summed
    over the neighbours. The sizes are the windowed record's own DFTs (a search spectrum of part of
    the record -- ``fast``'s eighth -- reads a neighbour within its main lobe into the line's bin).

    The envelope probe's scene 24726 (balanced, 2^18): a mover 33 dB under another whose lines lay
    41 record bins from its own had its speed pulled 4-6 Hz at a stated 0.9 Hz (z 6) in every
    profile.

    Parameters
    ----------
    xw : ndarray, shape (N,), the record less its mean, windowed (V); ``a_f`` its DFTs' sizes at
        ``freqs``
    """
    n = xw.size
    f = np.asarray(freqs, dtype=float)
    o = np.asarray(others, dtype=float)
    o = o[np.abs(o) > 0.5 * fs / n]  # the mean is removed: 0 Hz is no line
    o = np.unique(o if iq else np.abs(o))  # (a real record's U and L static lines coincide)
    a_o = np.abs(exact_dft(xw, o, fs))
    if not iq:  # a real record: every line's image at -f too (the line's own among ``others``)
        o, a_o = np.concatenate([o, -o]), np.concatenate([a_o, a_o])
    dist = np.abs(o[None, :] - f[:, None])
    r = a_o[None, :] / np.maximum(np.asarray(a_f, dtype=float)[:, None], 1e-300)
    k = np.rint(dist * 2 * n / fs).astype(np.int64) % (2 * n)  # the DFT repeats every fs ...
    env = _slope_leak(n)[np.where(k > n, 2 * n - k, k)]  # ... and a real slope's is even
    need = (dist * n / fs >= 0.5) & (
        SLOPE_LEAK_SCREEN * fs / (2 * np.pi) * r * env > REASSIGN_LEAK_SHARE * np.asarray(sigma_hz)[:, None])
    if not need.any():
        return np.zeros(f.size)
    _, dw, sw, _ = _window_and_slope(n)
    at, back = np.unique(dist[need], return_inverse=True)
    pull = np.zeros(dist.shape)
    pull[need] = fs / (2 * np.pi) * r[need] * np.abs(exact_dft(dw, at, fs))[back] / sw
    return pull.sum(axis=1)


def _pedestal_overlap(white: float, combine: tuple, s2: np.ndarray, spread: float, var_per_s2: np.ndarray,
                      iq: bool) -> float:
    """What a laser's phase-noise pedestal added to :func:`refine_reassigned`'s error (Hz^2): its
    lines' local floors ``s2`` (V^2, shape (K,)) hold the pedestal as if it were white noise, and the
    target stage states the shared phase itself (``shared_phase_gain`` times the declared laser's
    PSD): the error ``spread`` (Hz) less the same combination (:func:`_combine_lines`; ``combine``:
    its weights, slopes, corrections and shifts) with every floor at most the spectrum's white one
    ``white`` (V^2 per sample, :func:`white_floor` between the frame's lines). The honesty map's
    100 kHz rows (one mover a few bins up, 2^16-2^20 samples) had the two counted together: speed z
    std 0.6-0.77, the error stated ~1.4x. ``var_per_s2``: each line's variance (Hz^2) per unit
    floor, shape (K,)."""
    s2w = np.minimum(s2, white)
    if not (math.isfinite(white) and np.any(s2w < s2)):
        return 0.0
    wt, slope, d_line, shift = combine
    alone = _combine_lines(wt, slope, d_line, var_per_s2 * s2w, shift, iq)[1]
    return max(spread**2 - alone**2, 0.0)


def pedestal_is_flat(psd: float, linewidth_hz: float, df_hz: float) -> bool:
    """Whether a pedestal's PSD (rad^2/Hz, :func:`pedestal_phase_psd`) read on the ring of
    ``SMALL_NEAR_GUARD``-``SMALL_NEAR_HALF_WIDTH`` bins of ``df_hz`` about a line is the shared
    phase's low-frequency PSD, for a laser of ``linewidth_hz``: the delayed self-heterodyne phase's
    ``S(f) = 2*linewidth*sin^2(pi*f*dtau)/(pi*f^2)`` is flat at ``2*pi*linewidth*dtau^2`` only up
    to ``f ~ 1/(pi*dtau)``, beyond which it falls to ``~linewidth/(pi*f^2)``, whatever the delay. A
    reading under :data:`PEDESTAL_FLAT` times that far level at the ring's outer edge puts
    ``pi*f*dtau`` there below 0.87 (the ring's median within ~8 % of the flat level; a reading 20 %
    low passes up to ~11 %); above it, the delay -- and the PSD at the low frequencies the
    refinement feels -- may be any larger (the honesty map's mover at 47.9 m/s, 68 m away by its
    15th frame behind a 3 m unambiguous range: the ring read a quarter of the flat level, and a
    speed came out 4.4 of its sigmas off; a mover at 15 m, 100 ns, reads within 6 %). True for no
    pedestal (0)."""
    edge = SMALL_NEAR_HALF_WIDTH * df_hz
    return psd <= 0.0 or psd <= PEDESTAL_FLAT * linewidth_hz / (np.pi * edge**2)


#: :func:`pedestal_is_flat`: a pedestal pins the low-frequency PSD when at most this many times the
#: far level ``linewidth/(pi*f^2)`` at the ring's outer edge
PEDESTAL_FLAT = 1.5


#: the pedestal about a line counts where its near floor exceeds the white floor by this many
#: standard errors of their difference under no pedestal (a median of M independent exponential
#: bins is ~1.44/sqrt(M) of itself; a Kaiser(14) periodogram's bins are independent about every
#: :data:`PEDESTAL_RING_ENBW`): a pedestal below it goes uncounted, and the stated error -- whose
#: per-line floor holds it -- is then at most ~1.3x short
PEDESTAL_SIGNIFICANCE = 3.0
PEDESTAL_RING_ENBW = 2.2
#: the white floor: the lowest of the near-ring floors at the middle of this many of the widest gaps
#: between the frame's lines (a pedestal reaching into one of them -- a frame of few lines -- raises
#: that one only)
WHITE_FLOOR_GAPS = 3


def _median_error(count: np.ndarray | int) -> np.ndarray:
    """The relative standard error of a median of ``count`` periodogram bins (Kaiser(14))."""
    return 1.44 / np.sqrt(np.maximum(np.asarray(count, dtype=float), 1.0) / PEDESTAL_RING_ENBW)


def white_floor(spec: Spectrum, lines_hz: np.ndarray) -> tuple[float, float]:
    """The spectrum's white noise floor (V^2 per sample, :meth:`~.spectrum.Spectrum.noise_variances`'
    unit) where no line's pedestal reaches, and its relative standard error: the lowest of the
    near-ring floors (:data:`SMALL_NEAR_HALF_WIDTH`) at the middle of the :data:`WHITE_FLOOR_GAPS`
    widest gaps between ``lines_hz`` (every line the frame may have, Hz, shape (M,)), over the spectrum's span
    (``[0, fs/2]`` for a real record, ``[-fs/2, fs/2]`` for IQ); the error is one ring's (the lowest
    of three lies ~0.85 of it low: a pedestal's test errs toward counting one)."""
    half = spec.fs_hz / 2
    f = np.asarray(lines_hz, dtype=float)
    f = f if spec.complex_input else np.abs(f)
    edges = np.unique(np.concatenate([f[np.abs(f) < half], [-half if spec.complex_input else 0.0, half]]))
    gaps = np.diff(edges)
    wide = np.argsort(gaps)[::-1][:WHITE_FLOOR_GAPS]
    floors, count = spec.noise_variances(edges[wide] + gaps[wide] / 2, edges, half_width=SMALL_NEAR_HALF_WIDTH,
                                         guard=SMALL_NEAR_GUARD, counts=True)
    low = int(np.argmin(floors))
    return float(floors[low]), float(_median_error(count[low]))


def pedestal_phase_psd(spec: Spectrum, line_hz: float, line_density: float, lines_hz: np.ndarray,
                       white: tuple[float, float] | None = None) -> float:
    """The low-frequency two-sided PSD (rad^2/Hz) of a line's phase, from the pedestal about it.

    A laser partly coherent over the echo's delay puts the delayed self-heterodyne phase's spectrum
    about each of the target's lines, flat at ``2*pi*linewidth*dtau^2`` well inside ``1/dtau``, at
    the line's power times it (a real record's line near 0 Hz carries its image's pedestal too, up
    to twice that). The near floor about the line (``+-``:data:`SMALL_NEAR_HALF_WIDTH` bins, less
    :data:`SMALL_NEAR_GUARD` about every line) less the white floor (:func:`white_floor`), over the
    line's density, is that PSD -- counted only where it stands :data:`PEDESTAL_SIGNIFICANCE`
    standard errors above the white floor, else 0.

    Parameters
    ----------
    spec : the search spectrum
    line_hz : the line's frequency (Hz)
    line_density : its amplitude squared per side (V^2: ``|X_w|^2/sum(w)^2`` of a window ``w``)
    lines_hz : ndarray, shape (M,), every line the frame may have (Hz), kept out of both floors
    white : :func:`white_floor` of ``spec`` between ``lines_hz``, where the caller has it already
    """
    near, count = spec.noise_variances([line_hz], lines_hz, half_width=SMALL_NEAR_HALF_WIDTH,
                                       guard=SMALL_NEAR_GUARD, counts=True)
    near = float(near[0])
    white, white_err = white_floor(spec, lines_hz) if white is None else white
    if not (math.isfinite(near) and math.isfinite(white)) or line_density <= 0:
        return 0.0
    # under no pedestal the near floor is the white one, with its own median's error
    if near - white <= PEDESTAL_SIGNIFICANCE * white * math.hypot(float(_median_error(count[0])), white_err):
        return 0.0
    return (near - white) / spec.fs_hz / line_density


# ---------------------------------------------------------------------------------------------
# below the search's guard
#: the sub-guard search looks down to this many record bins (fs/N) from 0 Hz: there a line's
#: record-long cosine and sine are orthogonal to the mean (the Dirichlet kernel's first zero), a
#: real record's image of it lies 2 bins away and the lines U, L lie a bin either side of the
#: static line; closer, a line is a slope of the mean and U + L an amplitude beat of the static line
SMALL_MIN_BINS = 1.0
#: the scan's step (record bins)
SMALL_SCAN_STEP = 0.25
#: a further sub-guard mover's scan keeps this many record bins from the movers already found and
#: from their beats (:func:`_small_scan`)
SMALL_OTHER_BINS = 2.0
#: the static lines' half-bin neighbours held in :func:`_decisive_off_static` keep this many record
#: bins from the mover's own lines (nearer, the fit would be near-singular) ...
STATIC_FLANK_CLEAR_BINS = 0.75
#: ... and with them held a sub-guard mover's baseband line and pairs must keep this part of their SNR
#: (a slow echo's sidelobes kept 13 %, a real mover's lines nearly all)
STATIC_FLANK_KEEP = 0.25
#: several sub-guard movers are measured again in turn, each with the others' lines held
#: (:func:`remeasure_small`), until none moves by more than this part of its error, at most this
#: many rounds
SMALL_REMEASURE_TOL = 0.1
SMALL_REMEASURE_ROUNDS = 4
#: the scan's peak goes on to the joint fit when its lone baseband line is within this factor of
#: :data:`SMALL_MIN_SNR` (:func:`_small_worth_fitting`)
SMALL_SCAN_MARGIN = 4.0
#: a sub-guard mover is decisive when its baseband line's post-integration SNR reaches this (20 dB;
#: white noise's largest over the scan is ``ln(points)``, ~5) ...
SMALL_MIN_SNR = 100.0
#: ... its line is coherent: at most this wide in the search spectrum (bins; a Kaiser(14) line is
#: 2.3-3, the Lorentzian hump of a laser incoherent at the echo's delay ten and more) ...
SMALL_MAX_WIDTH = 3.2
#: ... and at least this many tones (all, with fewer) have both sidebands above the search's
#: per-line threshold (a mover must be rangeable)
SMALL_MIN_PAIRS = 2
#: the near floor about each line: +-this many bins of the search spectrum (the whole record's) ...
SMALL_NEAR_HALF_WIDTH = 32
#: ... less those within this many bins of a modelled line (the Kaiser(14) main lobe: +-4.6)
SMALL_NEAR_GUARD = 5
#: the step (record bins) of the energy's second difference about each line's fitted frequency
SMALL_CURVATURE_STEP = 0.02
#: ... and of the last parabola step (the vertex's bias), as a fraction of it
SMALL_FINAL_STEP_FRACTION = 0.02
#: a sub-guard fit's peak is a line's when its shape (:func:`_small_peak`) lies within these: a line
#: a few bins from 0 Hz and its image beat (1.2 record bins: 1.55, 1.3: 1.46, 1.7: 1.31, 2.0: 0.90,
#: from 2.5 bins up 0.81-1.02); a bump beside a held line or at a band's edge: ~3
SMALL_SHAPE = (0.5, 2.0)
#: the local floor's effect on a line's frequency, over white noise's: up to 2 when the floor is the
#: line's own phase-noise pedestal (all of it in the phase quadrature, half of white noise). With a
#: declared laser, whose phase noise the target stage adds from physics, a lone mover's fit counts it
#: twice (the map's 6-bin rows: speed z std 0.4-0.6); taken off there, fits beside another mover were
#: left 5.1 sigma off (``TestSmallDopplerSimulated.test_pedestal_factor_stays_beside_another_mover``)
PEDESTAL_FACTOR = 2.0
#: a ``static`` claim's sigma (the smallest measurable speed) covers a mover missed anywhere below
#: the search's guard within this many sigmas
STATIC_COVER_Z = 5.0


def _parabola_peaks(fun, count: int, h: float, lo: float, hi: float, steps: int,
                    x0: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The tops of ``count`` smooth peaks at once: ``steps`` times, each one's vertex of the parabola
    through ``fun`` at ``x - h, x, x + h`` (clipped to ``[lo, hi]``); returns them and each one's last
    parabola's second derivative (``>= 0``: no peak there, that one's walk stops). ``fun(idx, xs)``:
    the values at ``xs`` (shape (len(idx), 3)) of the peaks ``idx``. The last step's points are
    :data:`SMALL_FINAL_STEP_FRACTION` of ``h`` apart: a parabola's vertex through points ``h`` about
    an asymmetric peak misses it by ~``h^2`` (0.02 bin: 4e-4 bin near 0 Hz, where the line and its
    image make it asymmetric -- 15 sigma at 70 dB; 0.1 of it still 6 sigma at 110 dB)."""
    x = np.zeros(count) if x0 is None else np.array(x0, dtype=np.float64)
    curv, live = np.zeros(count), np.ones(count, dtype=bool)
    for k in range(steps):
        if k == steps - 1:
            h = h * SMALL_FINAL_STEP_FRACTION  # the vertex's bias grows as h^2 (an asymmetric peak)
        idx = np.flatnonzero(live)
        if not idx.size:
            break
        f = np.asarray(fun(idx, x[idx, None] + np.array([-h, 0.0, h])), dtype=np.float64)
        c = (f[:, 2] - 2 * f[:, 1] + f[:, 0]) / h**2
        curv[idx] = c
        top = c < 0
        x[idx[top]] = np.clip(x[idx[top]] - (f[top, 2] - f[top, 0]) / (2 * h) / c[top], lo, hi)
        live[idx[~top]] = False
    return x, curv


def small_doppler_floor_hz(spec: Spectrum, tones_hz, guard_bins: int, fs: float, n: int,
                           width: float | None = None) -> float:
    """The smallest Doppler (Hz) a frame searched below the guard states it could have measured: a
    line :data:`SMALL_MIN_BINS` record bins from 0 Hz, and no less than the guard over
    :data:`STATIC_COVER_Z` (a mover missed below the guard stays within that many sigmas of a static
    claim); the guard itself where the static lines are not coherent (the sub-guard search then
    finds nothing it may keep). ``width``: :func:`~.spectrum.line_width_bins` if already read."""
    guard_hz = guard_bins * spec.df_hz
    w = line_width_bins(spec, tuple(float(f) for f in tones_hz)) if width is None else width
    if w >= 4:
        return guard_hz
    return max(SMALL_MIN_BINS * fs / n, guard_hz / STATIC_COVER_Z)


def small_band(spec: Spectrum, guard_bins: int, fd_max_hz: float, fs: float, n: int) -> tuple[float, float]:
    """The band (Hz) :func:`search_small_doppler` scans: from :data:`SMALL_MIN_BINS` record bins
    up to one search bin past the guard (no further than the search's largest Doppler)."""
    return SMALL_MIN_BINS * fs / n, min((guard_bins + 1) * spec.df_hz, fd_max_hz)


def search_small_doppler(x: np.ndarray, frame: Frame, spec: Spectrum, guard_bins: int, fd_max_hz: float,
                         threshold_factor: float, others: tuple[float, ...] = (),
                         low: LowBand | None = None, below_hz: float | None = None,
                         band: tuple[float, float] | None = None) -> DopplerEstimate | None:
    """A mover whose Doppler lies below the search's guard, measured on the whole record.

    The search keeps ``guard_bins`` from the static lines, whose Kaiser main lobes would pass for
    Doppler pairs there. Here the record's own lines are fitted instead, by least squares at their
    exact frequencies (rectangular window, no leakage between modelled lines): a scan of the
    baseband line ``|f_d|`` (``f_d`` for IQ) from :data:`SMALL_MIN_BINS` record bins up to one
    search bin past the guard; at its peak (a local maximum inside the band, whose joint fit there
    could keep a mover: :func:`_small_may_peak`), every line of the
    mover -- baseband, ``f_i + f_d``, ``|f_i - f_d|`` -- fitted jointly with the static lines (``f_i``,
    the DC; ``+-f_i`` and 0 Hz for IQ), first all at one trial ``f_d`` (the joint energy's
    maximum), then each line's own frequency with the others held (:func:`_parabola_peaks`). Each
    line's error: the local floor -- the spectrum's wide ring, or the near one
    (:data:`SMALL_NEAR_HALF_WIDTH`) where a partly coherent carrier's pedestal lies -- times
    :data:`PEDESTAL_FACTOR`, over the fitted energy's curvature in that line's frequency (its
    Fisher information with every amplitude free: near 0 Hz, the line's image and the static line
    take some). The lines' estimates are combined with power weights and their error scaled by
    their scatter (:func:`_combine_lines`). The phase all the lines share (laser
    phase noise over the echo delay) is left to ``shared_phase_gain``: a straight-line fit of a
    phase over ``T = N/fs`` turns its flat two-sided PSD ``S`` into ``var(f) = 12*S/((2*pi)^2*T^3)``
    (x1.5 for a real record, as :func:`refine_reassigned`).

    The mover is kept only when the evidence is decisive: the baseband line's SNR at least
    :data:`SMALL_MIN_SNR`, stronger than any of its sidebands (the carrier beat of a mover is), a
    coherent line (:data:`SMALL_MAX_WIDTH`), :data:`SMALL_MIN_PAIRS` tones with both sidebands
    above ``threshold_factor``, and, on a static intermodulation product within the guard, stronger
    than every static line (the search's rule); and its lines keeping their evidence with the
    static lines let off their frequencies (:func:`_decisive_off_static`).

    Parameters
    ----------
    x : ndarray, shape (N,), float64 or complex128, V: the whole record
    spec : the search spectrum (of the whole record, or of its first part: ``fast``'s eighth)
    guard_bins : the search's guard (``spec`` bins)

    others : the Dopplers (Hz) of sub-guard movers already found in this record: their lines join
        the static ones in the fit, their baseband lines are taken out of the scan
        (:func:`_small_residual`), and the scan keeps :data:`SMALL_OTHER_BINS` from them and from
        their beats with each other (``|f_a +- f_b|``: one echo is the other's LO)
    low : the record's block sums for this search's band (:func:`small_band`), if already taken
    below_hz : the band's top (Hz) when lower than :func:`small_band`'s (a guard short of a mover
        the search found beyond the guard)
    band : ``(lo, hi)`` (Hz) instead of :func:`small_band`'s: beside a mover the search found, inside
        its search lobe (:func:`_lobe_neighbours`); the spectrum's width test then does not apply (it
        reads the found mover's lobe), and the scan's peak must stand out of the scan itself

    Returns
    -------
    DopplerEstimate (``method="fit"``), or None when there is no decisive sub-guard mover
    """
    iq = np.iscomplexobj(x)
    fs, n = frame.fs_hz, x.size
    dfr = fs / n
    tones = np.asarray(frame.tones_hz, float)
    lo, hi = small_band(spec, guard_bins, fd_max_hz, fs, n) if band is None else band
    hi = hi if below_hz is None else min(hi, below_hz)
    if hi <= lo + 2 * SMALL_SCAN_STEP * dfr or n < 256:
        return None
    beside = band is not None
    low = low or LowBand.of(x, fs, hi / dfr)
    found = _small_candidate(x, fs, spec, tones, others, low, lo, hi, beside, beats=frame.receiver == "single")
    if found is None:
        return None
    fd0, fit = found
    # a candidate: its fit reads floors at the record's own resolution (``fast``'s eighth is 8x coarser)
    full = whole_record(spec, x, fs)
    guard_bins, spec = guard_bins * spec.df_hz / full.df_hz, full
    if not _small_may_peak(fit, spec, fd0):
        return None
    fd, c, fm, dm, s2, snr, beats, shape = _small_peak(fit, spec, fd0, lo, hi)
    if not SMALL_SHAPE[0] <= shape <= SMALL_SHAPE[1] or not _small_decisive(
            spec, fd, c, snr, fit.static.size, fit.n_static, tones, guard_bins, fd_max_hz, threshold_factor,
            width_test=not beside, low=low) or not _decisive_off_static(fit, spec, fm, dm, beats, snr,
                                                                        threshold_factor):
        return None
    combined = _small_lines(fit, fd, fm, dm, c[fit.static.size:], s2, snr, beats, spec)
    if combined is None:
        return None
    gain = (1.0 if iq else 1.5) * 12 * fs**3 / (4 * np.pi**2 * n**3)
    # a coherent line (the width test): no wander of its own
    return DopplerEstimate(fd + combined[0], True, float(snr[0]), SMALL_MIN_SNR, lo, combined[1], 0.0, "fit", gain,
                           lines_chi2=combined[2])


def _decisive_off_static(fit: "_SmallFit", spec: Spectrum, fm: np.ndarray, dm: np.ndarray,
                         beats: tuple[np.ndarray, np.ndarray] | None, snr: np.ndarray, threshold_factor: float) -> bool:
    """Whether a sub-guard mover (its lines ``fm``, Hz, their exact DFTs ``dm``; its beats with the
    movers already found, :meth:`_SmallFit.beat_lines`; each line's SNR in the fit, ``snr``) keeps
    its evidence when the static lines may lie up to half a record bin off their frequencies: held
    with lines half a bin either side too (as :func:`_static_offset_gap` does; none within
    :data:`STATIC_FLANK_CLEAR_BINS` of the mover's lines or beats), its baseband line and at least
    :data:`SMALL_MIN_PAIRS` of the pairs that passed ``threshold_factor`` must each keep
    :data:`STATIC_FLANK_KEEP` of their SNR.

    An echo moving under a bin is held at 0 Hz and ``f_i`` exactly, and what the fit leaves of it
    rings through the rectangular window's sidelobes, ``(k + 1/2)`` bins from it, each ringing line
    carrying that echo's phases: the envelope probe's scene 21675 (one photodiode, six tones,
    2^16): an echo 0.25 bin up at 53 dB of loss beside a 30 dB mover left a line pattern 4.85 bins
    up that passed for a second mover at 0.29 m/s, 954 sigmas off, ranged at the slow echo's range;
    with the half-bin lines held its baseband line kept 13 % of its SNR and no pair stood. A real
    mover's lines keep nearly all of theirs; the test is relative, as one at the threshold (23168:
    77.6 dB of loss, 2.3 bins up, two pairs at 8) would lose a pair to any refit. One pass over the
    record, for a mover the fit would keep only."""
    t = fit.tones.size
    fb, db = beats if beats is not None else (np.empty(0), np.empty(0, dtype=np.complex128))
    lines = np.concatenate([fm, fb])
    extra = _static_flanks(fit, np.concatenate([fit.static, lines]), lines, fit.iq)
    if not extra.size:
        return True
    held = np.concatenate([fit.static, extra])
    _, c = solve_lines(np.concatenate([fit.d_static, exact_dft(fit.x, extra, fit.fs), dm, db]),
                       np.concatenate([held, lines]), fit.fs, fit.x.size, fit.total, fit.iq)
    # the held lines' amplitudes first, then the mover's (its beats' left out), as _small_snr reads them
    _, kept = _small_snr(fit, spec, np.concatenate([c[:fit.static.size], c[held.size:held.size + fm.size]]), fm)
    keep = kept >= STATIC_FLANK_KEEP * snr
    pairs = (np.minimum(snr[1:1 + t], snr[1 + t:]) >= threshold_factor) & keep[1:1 + t] & keep[1 + t:]
    return bool(keep[0] and np.sum(pairs) >= min(SMALL_MIN_PAIRS, t))


def _small_candidate(x: np.ndarray, fs: float, spec: Spectrum, tones: np.ndarray, others: tuple[float, ...],
                     low: LowBand, lo: float, hi: float, beside: bool = False, beats: bool = True
                     ) -> "tuple[float, _SmallFit] | None":
    """:func:`search_small_doppler`'s candidate: the scan's peak (Hz) where a joint fit could find a
    decisive mover, and that fit (the movers already found held), or None. ``beside``: the band lies
    about a mover found (its lobe in the search spectrum): the peak must stand out of the scan, and
    the spectrum's width test is not made."""
    iq = np.iscomplexobj(x)
    # the movers already found, fitted first only where one lies in the band (its baseband line is
    # then taken out of the scan); those the search found beyond the guard are held in the joint fit
    in_band = any(abs(o) <= hi + SMALL_OTHER_BINS * fs / x.size for o in others)
    # beside a mover found (its lobe), the joint fit waits for a candidate: the scan takes the
    # movers' baseband lines out from one DFT at them (each frame with a mover in ``fast`` scans there)
    fit = _SmallFit(x, fs, tones, iq, others, beats) if in_band and not beside else None
    # movers beyond the band: their baseband lines' leakage (the rectangular window's 1/(pi*distance))
    # taken out of the scan and the gate too, from one DFT at their lines (else a strong mover's
    # sidelobes pass the gate and the joint fit runs, ~30 ms a 1e6-sample frame, to reject them)
    leak = fit if fit is not None else (_FarMovers(x, fs, iq, others) if others else None)
    # beside movers beyond the band, a line also stands out of the scan itself: their phase-noise
    # pedestal fills the band (its floor, not the spectrum's rings about the band, is what a line
    # there must beat; moving-target at 1e6: a 21 dB 'line' of pedestal, 5 dB after the fit)
    contrast = SMALL_MIN_SNR / SMALL_SCAN_MARGIN if (fit is None and others) or beside else None
    fd0 = _small_scan(low, lo, hi, iq, leak, others, contrast, beats)
    if fd0 is None or not _small_worth_fitting(low, spec, fd0, tones, iq, leak):
        return None
    # a coherent line, before the fit (tens of passes over the record): the decisive test's width
    # rule at the scan's peak (a mover's phase-noise pedestal near 0 Hz passes the SNR gate beside it)
    if not beside and _too_wide(spec, low, fd0):
        return None
    return fd0, fit or _SmallFit(x, fs, tones, iq, others, beats)


def _too_wide(spec: Spectrum, low: LowBand | None, fd: float) -> bool:
    """Whether the line at ``fd`` (Hz) is wider than a coherent line (:data:`SMALL_MAX_WIDTH`): in
    the search spectrum, and where that holds part of the record only (``fast``'s eighth, its bins
    8x wider: movers 40/80/120 record bins up at 2^16 lie 5 of its bins apart and read as one line
    4.4 bins wide) at the record's own resolution too (``low``'s block sums, the same window). A
    laser's Lorentzian is wider in record bins than in the eighth's; a cluster of coherent lines is
    not. There a line also stands :data:`SMALL_MIN_SNR` above the median of the bins about it: a
    Lorentzian's periodogram at the record's resolution is a ragged top of spikes a bin or two wide
    (900 draws of 0.3-10 MHz lasers at 2^16: widths down to 1.9 bins, contrasts up to 39)."""
    f = fd if spec.complex_input else abs(fd)
    if widths_at(spec, [f], half_span=16) <= SMALL_MAX_WIDTH:
        return False
    if spec.record_n is None or low is None:
        return True
    width, contrast = low.line_at(f)
    return width > SMALL_MAX_WIDTH or contrast < SMALL_MIN_SNR


def _small_peak(fit: "_SmallFit", spec: Spectrum, fd0: float, lo: float, hi: float
                ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The joint energy's maximum within half a scan step of ``fd0`` (Hz, inside ``[lo, hi]`` in
    ``|f_d|``), and there: the fit's amplitudes ``c`` (held lines first), the mover's lines ``fm``
    (Hz), their exact DFTs ``dm``, the noise variance ``s2`` about each, each line's SNR, the beats
    held (lines and exact DFTs, :meth:`_SmallFit.beat_lines`), and the peak's shape: its curvature
    over a lone line's of the energy the mover's lines add (0.81-1.02 at SNR >= 100 on 474
    case-6-like fits, up to 1.55 a bin or two from 0 Hz, where the line's image bends it; ~3 for a
    bump that two nearly collinear fits make beside a held line, or a slope's edge:
    :data:`SMALL_SHAPE`)."""
    fs, n, iq = fit.fs, fit.x.size, fit.iq
    dfr = fs / n
    a_, b_ = abs(fd0) - 0.5 * SMALL_SCAN_STEP * dfr, abs(fd0) + 0.5 * SMALL_SCAN_STEP * dfr
    sgn = 1.0 if fd0 > 0 else -1.0
    top, curv = _parabola_peaks(lambda _, xs: [[j[0] for j in fit.joints(sgn * xs[0])]], 1,
                                SMALL_CURVATURE_STEP * dfr, max(a_, lo), min(b_, hi), 3, [abs(fd0)])
    fd = sgn * float(top[0])
    curv = float(curv[0])
    energy, c, fm, dm, beats = fit.joint(fd)
    # a line's own peak: the energy it adds falls off as sinc^2 about it, curvature -(2/3)(pi*N/fs)^2
    # times that energy
    shape = curv / (-(2.0 / 3.0) * (np.pi * n / fs) ** 2 * max(energy - fit.held_energy, 1e-300))
    s2, snr = _small_snr(fit, spec, c, fm)
    return fd, c, fm, dm, s2, snr, beats, shape


def _small_snr(fit: "_SmallFit", spec: Spectrum, c: np.ndarray, fm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The noise variance about each of a trial mover's lines ``fm`` (Hz) and each line's
    post-integration SNR from the joint fit's amplitudes ``c`` (the held lines' first), shape (K,)
    each. The floor: the spectrum's wide ring, or closer where more lies there (the pedestal of a
    carrier beat only partly coherent at the echo's delay, tens of bins wide)."""
    excl = list(fit.static) + list(fm) + [0.0]
    s2 = _small_floor(spec, fm, excl)
    snr = np.abs(c[fit.static.size:]) ** 2 * fit.x.size / ((0.5 if fit.iq else 2.0) * np.maximum(s2, 1e-300))
    return s2, snr


def _small_may_peak(fit: "_SmallFit", spec: Spectrum, fd0: float) -> bool:
    """Whether the joint fit could keep a mover about the scan's peak ``fd0`` (Hz): its baseband
    line's SNR in the fit at ``fd0`` itself at least :data:`SMALL_MIN_SNR` over
    :data:`SMALL_SCAN_MARGIN`. The energy's maximum (:func:`_small_peak`) lies within half a scan
    step: a lone line there is at most 5 % stronger. Over the honesty map's 8157 sub-guard peaks,
    every maximum at :data:`SMALL_MIN_SNR` or more was at most 1.43x the scan peak's SNR (90 and
    up), and 69 % of the peaks rejected were under 25 at the scan's peak: the scan's lone line holds
    what the fit explains by the movers' and the static lines' other lines. The peak's own search
    (three passes over the record of three trial line sets each, ~20 ms at 1e6 samples) runs only
    where a mover could be kept."""
    _, c, fm, _, _ = fit.joint(fd0)
    return bool(_small_snr(fit, spec, c, fm)[1][0] >= SMALL_MIN_SNR / SMALL_SCAN_MARGIN)


def quarters_resolve_hz(fs_hz: float, n: int) -> float:
    """Two movers closer than this (Hz) are one line to the phase refinement's quarters
    (:data:`PHASE_SEPARATION_BINS` bins of a quarter of the ``n``-sample record)."""
    return PHASE_SEPARATION_BINS * 4 * fs_hz / n


def within(d: DopplerEstimate, others: list[DopplerEstimate], sep_hz: float) -> bool:
    """Whether ``d``'s Doppler lies within ``sep_hz`` of one of ``others``' (in ``|f_d|``)."""
    return any(abs(abs(d.fd_hz) - abs(o.fd_hz)) < sep_hz for o in others)


#: the search may miss a mover this many guards either side of one it found (its own rule takes a
#: line 1-2 guards away only with a valley between them)
LOBE_GUARDS = 2.0


def _lobe_neighbours(x: np.ndarray, frame: Frame, spec: Spectrum, guard_bins: int, fd_max_hz: float,
                     threshold_factor: float, main: tuple[float, ...], small: list[DopplerEstimate],
                     below_hz: float, room: int) -> list[DopplerEstimate]:
    """Movers beside those the search found, within :data:`LOBE_GUARDS` guards of them, found on the
    whole record (:func:`search_small_doppler` on that band, every mover found held). A partial
    search spectrum (``fast``: movers 90 and 120 record bins up at 2^16 were one line in its
    eighth-record spectrum) hides them in a found mover's lobe, and the hidden one's lines leak
    through the rectangular window into every fit of the whole record (a mover at 30 bins came out
    35 sigma off); a whole-record spectrum keeps a second line within two guards of a first only
    across a noise-level valley (movers 8 and 16 record bins up at 2^16 gave one point in every
    profile, the movers probe's most frequent miss: 1930 -> 908 missed targets with this search).
    ``below_hz``: the top of the band already searched below the guard; ``room``: how many more
    movers may be reported."""
    fs, n = frame.fs_hz, x.size
    w = LOBE_GUARDS * guard_bins * spec.df_hz
    bands = [(max(abs(m) - w, below_hz), min(abs(m) + w, fd_max_hz)) for m in main]
    bands = [(a, b) for a, b in bands if b > a]
    if not bands or room <= 0:
        return []
    low = LowBand.of(x, fs, max(b for _, b in bands) * n / fs)
    found: list[DopplerEstimate] = []
    for a, b in bands:
        if len(found) >= room:
            break
        more = search_small_doppler(x, frame, spec, guard_bins, fd_max_hz, threshold_factor,
                                    (*main, *(d.fd_hz for d in small), *(d.fd_hz for d in found)), low, band=(a, b))
        if more is not None:
            found.append(replace(more, beside=True))
    return found


def remeasure_small(x: np.ndarray, frame: Frame, spec: Spectrum, found: list[DopplerEstimate], lo: float,
                    hi: float, held: tuple[float, ...] = ()) -> list[DopplerEstimate]:
    """Several sub-guard movers, each measured again with every other one's lines held.

    :func:`search_small_doppler` fits each further mover with the lines of those found before it,
    but the first was fitted alone: a second mover's lines a few record bins from its own leak
    into its fit through the rectangular window (``1/(pi*distance)``), a bias far beyond its white
    noise at high SNR (two movers 2 and 6.5 bins apart at ~90 dB: 18 Hz against a stated 0.1 Hz).
    Each mover is fitted again, in turn, with every other one's lines held at their latest
    frequencies, in rounds (a held line a few Hz off leaks too: the first refit of the first mover
    holds the second where its own fit, biased by the first, put it), until no mover moves by more
    than :data:`SMALL_REMEASURE_TOL` of its error, at most :data:`SMALL_REMEASURE_ROUNDS` times; a
    mover whose refit has no peak of its own keeps its estimate.

    Parameters
    ----------
    found : the movers :func:`search_small_doppler` found, in the order found
    lo, hi : the searched band (Hz, :func:`small_band`)
    held : the Dopplers (Hz) of movers the search found beyond the guard, held in every fit
    """
    iq = np.iscomplexobj(x)
    fs, n = frame.fs_hz, x.size
    tones = np.asarray(frame.tones_hz, float)
    spec = whole_record(spec, x, fs)  # floors at the record's resolution, as the movers were found
    out = list(found)
    for _ in range(SMALL_REMEASURE_ROUNDS):
        moved = False
        for i, est in enumerate(out):
            fit = _SmallFit(x, fs, tones, iq, (*held, *(o.fd_hz for j, o in enumerate(out) if j != i)),
                            frame.receiver == "single")
            # a mover found beside another beyond the guard keeps its own band
            fd, c, fm, dm, s2, snr, beats, shape = _small_peak(fit, spec, est.fd_hz, *((0.0, np.inf) if est.beside
                                                                                      else (lo, hi)))
            combined = (_small_lines(fit, fd, fm, dm, c[fit.static.size:], s2, snr, beats, spec)
                        if SMALL_SHAPE[0] <= shape <= SMALL_SHAPE[1] else None)
            if combined is not None:
                out[i] = replace(est, fd_hz=fd + combined[0], refine_error_hz=combined[1], lines_chi2=combined[2])
                moved |= abs(out[i].fd_hz - est.fd_hz) > SMALL_REMEASURE_TOL * combined[1]
        if not moved:
            break
    return out


def _small_scan(low: LowBand, lo: float, hi: float, iq: bool, fit: "_SmallFit | None" = None,
                others: tuple[float, ...] = (), contrast: float | None = None, beats: bool = True) -> float | None:
    """The sub-guard scan: the baseband line alone (the record's mean removed, from its block sums,
    :meth:`~.spectrum.LowBand.scan`), every ~:data:`SMALL_SCAN_STEP` record bins over
    ``[lo, hi]`` Hz (both signs for IQ); its strongest point, when that is a local maximum inside
    the band, else None. A line just outside has its peak at the band's edge and hides what lies
    inside: where its peak lies within :data:`SMALL_EDGE_BINS` of the edge it is taken out of the
    scan (:func:`_edge_line`) and the strongest point taken again (a stronger mover 16 record bins
    below a lobe search's band hid the one inside it) -- unless, at the lower edge, its fitted peak
    lies :data:`SMALL_EDGE_INSIDE` or more inside the band: that peak (Hz, off the grid) is then the
    scan's (at the upper edge, a guard short of movers found beyond it, a line is always taken
    out). A peak inside the band is no candidate where it could be a stronger point's sidelobe
    (:func:`_sidelobe`). ``others``: the movers already found; the points near them and their
    beats are left out (their beats only where the echoes beat with each other, ``beats``: one
    photodiode), and with ``fit`` (its ``others`` the same) their baseband lines taken out first.
    ``contrast``: the peak must stand this far above the scan's median power away from its own main
    lobe (:func:`_scan_median`), else None."""
    grid, xs = low.scan(lo, hi, SMALL_SCAN_STEP, iq)
    if grid.size < 3:
        return None
    dfr = low.fs_hz / low.n
    if fit is not None:
        xs = xs - _small_residual(fit, grid)
    near = [*others, *(a + sg * b for i, a in enumerate(others) for b in others[i + 1:] for sg in (1, -1) if beats)]
    mask = np.zeros(grid.size, dtype=bool)
    for f0 in near:
        mask |= np.abs((grid if iq else np.abs(grid)) - (f0 if iq else abs(f0))) < SMALL_OTHER_BINS * dfr
    side = int(np.sum(grid > 0))
    edge = None
    for _ in range(SMALL_EDGE_LINES + 1):
        power = np.abs(xs) ** 2
        p = np.where(mask, 0.0, power)
        k = int(np.argmax(p))
        i, count = (k, side) if k < side else (k - side, grid.size - side)
        if not p[k] > 0:
            return None
        if 0 < i < count - 1:
            edge = None
            break
        edge = _edge_line(low, grid, k, -1.0 if i == 0 else 1.0, iq)
        if edge is None:
            return None
        fp, line = edge
        if abs(grid[k]) < (lo + hi) / 2 and lo + SMALL_EDGE_INSIDE * dfr <= abs(fp) < hi:
            break  # its peak lies inside the band's lower edge: the band's own line (scene 5448)
        xs = xs - line  # and the scan keeps clear of it, as of a mover found (its kernel's last digits)
        mask |= np.abs((grid if iq else np.abs(grid)) - fp) < SMALL_OTHER_BINS * dfr
    else:
        return None
    if contrast is not None and not p[k] >= contrast * _scan_median(p, grid, k, dfr, mask):
        return None
    if edge is None and _sidelobe(power, grid, k, dfr):
        return None
    return float(grid[k]) if edge is None else float(fp if iq else math.copysign(fp, grid[k]))


#: :func:`_scan_median` reads the scan this many record bins or more from its peak (the rectangular
#: window's main lobe is +-1 bin)
SCAN_LOBE_BINS = 1.0


def _scan_median(p: np.ndarray, grid: np.ndarray, k: int, dfr: float, blanked: np.ndarray) -> float:
    """The median of the scan's power ``p`` (on ``grid``, Hz) outside the main lobe of its peak
    ``grid[k]`` (:data:`SCAN_LOBE_BINS`) and the points ``blanked`` near the movers found (0 in
    ``p``: no power of the scan's); the whole scan's, zeros and all, where fewer than three are left.
    The blanked points' zeros counted, the lobe out, made the median 0 and the test void where they
    were most of the rest (a review: an IQ scan whose other sign a mover found blanked passed a peak
    1.76x its old median).

    A peak stands out of the scan where it stands above what lies beside it, not above itself: in a
    band a few bins wide its own main lobe is most of the scan (the envelope probe's scene 19892: a
    mover 1.4 bins up, 2.5 dB under one 6.9 bins up on one photodiode, the band 1-3.9 bins; its peak
    stood 16.5x over a median its lobe made, under the 25x asked, 47x over the rest; it was missed,
    its lines unmodelled beside the other's, whose range came out 7.4 sigmas off)."""
    away = (np.abs(grid - grid[k]) >= SCAN_LOBE_BINS * dfr) & ~blanked
    return float(np.median(p[away] if np.count_nonzero(away) >= 3 else p))


#: a scan's peak stands this far above the sidelobe envelope (the rectangular window's
#: ``1/(pi*d)^2``, ``d`` record bins away) of every stronger point of the scan, those it keeps clear
#: of the movers found included (:func:`_sidelobe`)
SMALL_SIDELOBE_MARGIN = 4.0
#: ... from this many record bins on: nearer, the scan's peak and the stronger point may be the two
#: lines of a pair 1-2 bins apart and their skirts (the movers probe's close pairs: from 1.5 bins on,
#: 173 targets more were missed, 70 of them found before -- flagged ``blended`` -- within 5 sigmas)
SMALL_SIDELOBE_FROM = 3.0


def _sidelobe(p: np.ndarray, grid: np.ndarray, k: int, dfr: float) -> bool:
    """Whether the scan's peak ``grid[k]`` could be a sidelobe of a stronger point of the scan,
    :data:`SMALL_SIDELOBE_FROM` record bins or more away (every such point; the one that matters
    lies where the scan keeps clear, within :data:`SMALL_OTHER_BINS` of a mover found -- a second
    mover there, which the fit does not take out). ``p``: the scan's power at every point (shape
    (G,)), lines taken out as the scan took them; distances along the grid (a real record's image
    of a line, on the other side of 0 Hz, is not looked at). The envelope probe's scene 5854
    (balanced, 2^18 samples): movers 4.1 and 6.1 record bins up, 9 dB apart; the weaker one, 2 bins
    from the stronger, was kept clear of, and its sidelobe 4.6 bins below it (-23 dB) was taken for
    a mover at 1.5 bins, its speed 9 sigmas off at its range."""
    d = np.abs(grid - grid[k]) / dfr
    stronger = (p > p[k]) & (d >= SMALL_SIDELOBE_FROM)
    return bool(np.any(p[k] < SMALL_SIDELOBE_MARGIN * p[stronger] / (np.pi * d[stronger]) ** 2))


#: how far (record bins) past the scan band's edge a line's peak is looked for (:func:`_edge_line`) ...
SMALL_EDGE_BINS = 3.0
#: ... and how many such lines are taken out of one scan
SMALL_EDGE_LINES = 2
#: ... unless its peak lies this far (record bins) inside the band's lower edge: then it is the
#: band's own line
#: (the envelope probe's scene 5448: a mover 17 dB above a static target, 1.1 bins up at a band
#: starting at 1 bin, IQ, was taken out as a line beside the band, and its lines blended into the
#: static point's, ranged 414 sigmas off)
SMALL_EDGE_INSIDE = 0.05


def _edge_line(low: LowBand, grid: np.ndarray, k: int, outward: float, iq: bool
               ) -> tuple[float, np.ndarray] | None:
    """A line just outside the scan's band, the scan's strongest point ``grid[k]`` (Hz) lying on the
    band's edge and ``outward`` (+-1) the direction out of the band: its frequency (Hz; ``|f|`` for
    a real record) and what it puts into the scan (shape (G,), complex). Its peak is looked for
    from half a bin inside the edge to :data:`SMALL_EDGE_BINS` record bins past it (the block
    sums' DFT every 0.1 bin, a parabola through the top three); its amplitude there times its
    centred Dirichlet kernel over the grid (a real line's image too) is what it puts in. None
    where ``|X|`` still rises at the search's end (a line further out, or a slope) or where the
    search would reach within a bin of 0 Hz (a real record's static lines and the mean's notch)."""
    dfr = low.fs_hz / low.n
    f = grid[k] + outward * dfr * np.arange(-0.5, SMALL_EDGE_BINS + 1e-9, 0.1)  # from half a bin inside
    if not iq and np.any(np.abs(f) < dfr):
        return None  # toward 0 Hz: the static lines' skirt and the mean's notch
    a = np.abs(low.dft(f))
    j = int(np.argmax(a))
    if not 0 < j < f.size - 1:
        return None
    den = a[j - 1] - 2 * a[j] + a[j + 1]
    fp = float(f[j] + (0.5 * (a[j - 1] - a[j + 1]) / den if den < 0 else 0.0) * (f[1] - f[0]))
    amp = low.dft([fp]) * ((1.0 if iq else 2.0) / low.n)
    return (fp if iq else abs(fp)), _lines_in_dft(np.array([fp]), amp, grid, low.fs_hz, low.n, iq)


def _small_residual(fit: "_SmallFit", grid: np.ndarray) -> np.ndarray:
    """What the movers already found put into the record's DFT on ``grid`` (Hz), shape (G,),
    complex: each one's baseband line, fitted with the static lines and their other lines
    (``fit``), through the record's rectangular window (:func:`_lines_in_dft`)."""
    return _lines_in_dft(fit.other_base, fit.other_amps, grid, fit.fs, fit.x.size, fit.iq)


def _lines_in_dft(freqs: np.ndarray, amps: np.ndarray, grid: np.ndarray, fs: float, n: int, iq: bool) -> np.ndarray:
    """What lines at ``freqs`` (Hz) with amplitudes ``amps`` (V: ``X/N`` for IQ, ``2X/N`` for a real
    record, phase at the record's centre) put into the record's DFT on ``grid`` (Hz): the centred
    Dirichlet kernel of the record's rectangular window (a real line's image at ``-f`` too), shape
    (G,), complex."""
    out = np.zeros(grid.size, dtype=np.complex128)
    for f0, a in zip(freqs, amps):
        out += (a if iq else a / 2) * _dirichlet(2 * np.pi * (grid - f0) / fs, n)
        if not iq:
            out += np.conj(a) / 2 * _dirichlet(2 * np.pi * (grid + f0) / fs, n)
    return out


def _small_floor(spec: Spectrum, freqs, exclude) -> np.ndarray:
    """The sub-guard search's noise floor about each of ``freqs`` (Hz): the larger of the
    spectrum's wide ring and its near one (:data:`SMALL_NEAR_HALF_WIDTH`, where a partly coherent
    carrier's pedestal lies), ``exclude`` kept out of both. Shape (K,), V^2 per sample."""
    return np.maximum(spec.noise_variances(freqs, exclude),
                      spec.noise_variances(freqs, exclude, half_width=SMALL_NEAR_HALF_WIDTH, guard=SMALL_NEAR_GUARD))


def _small_worth_fitting(low: LowBand, spec: Spectrum, fd: float, tones: np.ndarray, iq: bool,
                         fit: "_SmallFit | None" = None) -> bool:
    """Whether the scan's peak at ``fd`` could pass :data:`SMALL_MIN_SNR` in the joint fit: its
    baseband line alone, ``2|X(fd)|^2/(N*s2)`` against the spectrum's wide floor there, with
    ``|X|`` raised by what the static lines may leak into it (:func:`_static_leakage`: the fit
    models them, the lone line does not), is at least that over :data:`SMALL_SCAN_MARGIN`. The
    fit's amplitude differs from the lone line's by the line's image and the mean's removal (at
    most ~0.2 each a bin or more from 0 Hz: -2 dB), and its floor, as the fit's, the larger of the
    wide and the near ring's (beside a mover, its phase-noise pedestal): so 6 dB leaves every line
    the fit would keep. The joint fit (tens of passes
    over the record) then runs only on a real line."""
    static = _static_lines(tones, iq)
    f_abs = [fd if iq else abs(fd)]
    s2 = float(_small_floor(spec, f_abs, static)[0])
    if not s2 > 0:
        return True
    x_fd = low.dft([fd])[0]
    if fit is not None:  # less the movers already found
        x_fd = x_fd - _small_residual(fit, np.array([fd]))[0]
    x_fd = abs(x_fd) + _static_leakage(spec, low, fd, tones, iq)
    return 2.0 * x_fd**2 / (low.n * s2) >= SMALL_MIN_SNR / SMALL_SCAN_MARGIN


def _static_leakage(spec: Spectrum, low: LowBand, fd: float, tones: np.ndarray, iq: bool) -> float:
    """An upper bound on ``|X(fd)|`` from the static lines (``f_i``; ``+-f_i`` for IQ) through the
    record's rectangular window: each line's exponential has the amplitude ``sqrt(P)/sum(w)`` in
    the search spectrum's power ``P`` (its largest within a bin of the line), at most
    ``sqrt(P)/sum(w^2)`` (``0 <= w <= 1``), times the Dirichlet kernel ``|D(f_i -+ f_d)|``.
    Negligible on long records (``1/(pi*distance in bins)``), not on a 2^14-sample record whose
    static lines are 60 dB above the noise."""
    f = np.concatenate([tones, -tones]) if iq else tones
    b = spec.bin_of(f)
    near = np.clip(b[:, None] + np.arange(-1, 2)[None, :], 0, spec.power.size - 1)
    amp = np.sqrt(np.max(np.asarray(spec.power[near], dtype=np.float64), axis=1)) / spec.window_power
    kern = np.abs(_dirichlet(2 * np.pi * (f - fd) / low.fs_hz, low.n))
    if not iq:
        kern = kern + np.abs(_dirichlet(2 * np.pi * (f + fd) / low.fs_hz, low.n))
    return float(np.sum(amp * kern))


#: the newest record's exact DFTs at the line sets asked of :func:`_record_dft` (per thread)
_RECORD_DFTS = threading.local()


def _record_dft(x: np.ndarray, freqs_hz: np.ndarray, fs: float) -> np.ndarray:
    """:func:`~mtcw_core.dsp.tones.exact_dft` of ``x`` at ``freqs_hz``, remembered for this record:
    the search below the guard and the search beside each mover found (:func:`_lobe_neighbours`)
    hold the same static and movers' lines, and each would take a pass over the record for them.
    Only the newest record's are kept (by identity, through a weak reference: nothing writes into
    a record after validate); the array returned is read-only."""
    memo = getattr(_RECORD_DFTS, "memo", None)
    if memo is None or memo[0]() is not x:
        memo = _RECORD_DFTS.memo = (weakref.ref(x), {})
    key = (np.asarray(freqs_hz, dtype=np.float64).tobytes(), float(fs))
    out = memo[1].get(key)
    if out is None:
        out = memo[1][key] = exact_dft(x, freqs_hz, fs)
        out.setflags(write=False)
    return out


class _FarMovers:
    """The baseband lines of movers found far from the sub-guard band, for :func:`_small_residual`:
    each line's amplitude from the record's exact DFT at it (``2X/N`` for a real record, ``X/N``
    for IQ; referred to the record's centre, as the fit's), less the record mean's leak there (the
    scan's record is the mean-free one; on one photodiode the LO's DC, through the rectangular
    window, is as large as a mover's line 22.2 bins up: the envelope probe's scene 32475, whose
    baseband line taken out that way doubled its sidelobes in the scan and hid a mover 7.9 bins
    from it), its image and the other lines far off."""

    def __init__(self, x: np.ndarray, fs: float, iq: bool, others: tuple[float, ...]):
        self.x, self.fs, self.iq = x, fs, iq
        self.other_base = np.array([o if iq else abs(o) for o in others], dtype=float)
        self.other_amps = (_record_dft(x, self.other_base, fs) - mean_leak(x, self.other_base, fs)) * (
            (1.0 if iq else 2.0) / x.size)


def cross_beats(fds: tuple[float, ...], iq: bool, bin_hz: float) -> list[float]:
    """The Dopplers (Hz) at which movers ``fds`` beat with each other on a square-law detector:
    one echo is the other's LO, ``E_a*conj(E_b)`` at ``|f_a - f_b|`` with the tones' lines about it
    (the pattern of a mover there, :func:`target_lines`). A real record gives ``|f_d|`` only: the
    signs unknown, the beat lies at ``|f_a| - |f_b|`` or ``|f_a| + |f_b|``, and both are held (the
    envelope probe's scene 30655: movers at 2.1 and -8.6 record bins, 30 dB apart, on one
    photodiode; their beat at 10.7 bins, unmodelled, pulled the weaker's Doppler 0.011 bin,
    noiseless, 21-43 of its sigmas). None for IQ (a balanced coherent receiver keeps only the LO's
    beats) and no difference within :data:`SMALL_MIN_BINS` record bins (``bin_hz``) of 0 Hz, where
    it lies on the static lines (two movers 2 bins apart beat 2 bins from them: fitted)."""
    if iq:
        return []
    return [f for i, a in enumerate(fds) for b in fds[i + 1:] for f in _beat_dopplers(a, b, bin_hz)]


def _beat_dopplers(a: float, b: float, bin_hz: float) -> list[float]:
    """:func:`cross_beats` of two movers on a real record: ``|f_a| + |f_b|``, and ``||f_a| - |f_b||``
    where it lies more than :data:`SMALL_MIN_BINS` record bins (``bin_hz``) from 0 Hz."""
    diff = abs(abs(a) - abs(b))
    return ([diff] if diff > SMALL_MIN_BINS * bin_hz else []) + [abs(a) + abs(b)]


def _add_apart(lines: np.ndarray, more: list[np.ndarray], tol_hz: float) -> np.ndarray:
    """``lines`` (Hz) and those of ``more`` that lie more than ``tol_hz`` from every line kept before
    them: a beat's line on a line already fitted (a mover at the sum of two others, a beat on a
    static line) would make the least-squares Gram matrix singular; the line there takes both."""
    out = list(np.asarray(lines, dtype=float))
    for f in (np.concatenate(more) if more else np.empty(0)):
        if not out or np.min(np.abs(np.asarray(out) - f)) > tol_hz:
            out.append(float(f))
    return np.asarray(out, dtype=float)


class _SmallFit:
    """The whole record's least-squares lines: the static ones (``f_i`` and the DC; ``+-f_i`` and
    0 Hz for IQ), every line of the movers already found (``others``, Hz) and, on a square-law
    detector, of their beats with each other (:func:`cross_beats`), held at their frequencies
    (``static`` holds them all, the static ones' ``n_static`` first, the movers' next), with a
    mover's at a trial Doppler (:func:`target_lines`)."""

    def __init__(self, x: np.ndarray, fs: float, tones: np.ndarray, iq: bool, others: tuple[float, ...] = (),
                 cross: bool | None = None):
        self.x, self.fs, self.tones, self.iq, self.others = x, fs, tones, iq, tuple(others)
        # the movers' beats with each other: a square-law record's (one photodiode; ``cross``, default
        # any real record), never a balanced or IQ one's -- held there, a beat that is no line sits on
        # a mover's own (90 and 120 record bins: their difference at a third mover's 30) and the fit
        # is singular
        self.cross = (not iq) if cross is None else bool(cross) and not iq
        self.total = 0.0 if iq else float(np.sum(x))
        static = _static_lines(tones, iq, dc=False)
        self.n_static = static.size
        self.other_base = np.array([o if iq else abs(o) for o in self.others], dtype=float)
        held = np.concatenate([static, *(target_lines(tones, o, iq)[0] for o in self.others)])
        crossed = cross_beats(self.others, iq, fs / x.size) if self.cross else []
        self.static = _add_apart(held, [target_lines(tones, b, iq)[0] for b in crossed], 0.5 * fs / x.size)
        self.d_static = _record_dft(x, self.static, fs)

    @cached_property
    def hann_x(self) -> np.ndarray:
        """The record less its mean through a Hann window (:func:`fit_neighbour_pull`'s probes), made
        once for every measurement of the fit's movers."""
        return windowed_record(self.x, "hann")

    @cached_property
    def held_amps(self) -> np.ndarray:
        """Every held line's amplitude (V, at the record's centre), fitted together; shape
        (len(static),), empty with no mover held."""
        if not self.others:
            return np.empty(0, dtype=np.complex128)
        return solve_lines(self.d_static, self.static, self.fs, self.x.size, self.total, self.iq)[1]

    @property
    def other_amps(self) -> np.ndarray:
        """The baseband amplitudes (V, at the record's centre) of the movers already found, fitted
        with the static lines and all their lines, shape (len(others),)."""
        return self.held_amps[self.n_static::1 + 2 * self.tones.size][:len(self.others)]

    def beat_lines(self, fd: float) -> np.ndarray:
        """The lines (Hz) of a mover at ``fd`` beating with the movers already found
        (:func:`cross_beats`; none but on one photodiode)."""
        fb = [target_lines(self.tones, f, self.iq)[0] for o in self.others
              for f in (cross_beats((fd, o), self.iq, self.fs / self.x.size) if self.cross else [])]
        base = np.concatenate([self.static, target_lines(self.tones, fd, self.iq)[0]])
        return _add_apart(base, fb, 0.5 * self.fs / self.x.size)[base.size:]

    def explained(self, fm: np.ndarray, dm: np.ndarray, beats: tuple[np.ndarray, np.ndarray] | None = None
                  ) -> tuple[float, np.ndarray]:
        """Energy explained by the static lines, ``fm`` (whose exact DFT is ``dm``) and ``beats``
        (lines and exact DFTs, :meth:`beat_lines`), and the amplitudes of the first two (the held
        lines', then ``fm``'s)."""
        fb, db = beats if beats is not None else (np.empty(0), np.empty(0, dtype=np.complex128))
        e, c = solve_lines(np.concatenate([self.d_static, dm, db]), np.concatenate([self.static, fm, fb]), self.fs,
                           self.x.size, self.total, self.iq)
        return e, c[:c.size - fb.size]

    def joints(self, fds) -> list[tuple[float, np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]]:
        """At each trial Doppler (Hz): the energy explained, the amplitudes (:meth:`explained`), the
        mover's lines and their exact DFTs, and its beats with the movers already found (lines,
        DFTs); every trial's lines read in one pass over the record."""
        sets = [(target_lines(self.tones, fd, self.iq)[0], self.beat_lines(fd)) for fd in fds]
        d_all = exact_dft(self.x, np.concatenate([f for pair in sets for f in pair]), self.fs)
        parts, at = [], 0
        for fm, fb in sets:
            parts.append((fm, d_all[at:at + fm.size], (fb, d_all[at + fm.size:at + fm.size + fb.size])))
            at += fm.size + fb.size
        if len(sets) == 1 or len({fm.size + fb.size for fm, fb in sets}) > 1:
            return [(*self.explained(fm, dm, beats), fm, dm, beats) for fm, dm, beats in parts]
        # every trial the same size: one batched solve
        f = np.stack([np.concatenate([self.static, fm, fb]) for fm, _, (fb, _) in parts])
        d = np.stack([np.concatenate([self.d_static, dm, db]) for _, dm, (_, db) in parts])
        energy, c = solve_lines_many(d, f, self.fs, self.x.size, self.total, self.iq)
        keep = self.static.size + sets[0][0].size
        return [(float(e), ci[:keep], fm, dm, beats) for e, ci, (fm, dm, beats) in zip(energy, c, parts)]

    def joint(self, fd: float) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
        return self.joints([fd])[0]

    @property
    def held_energy(self) -> float:
        """Energy the held lines explain alone."""
        if not hasattr(self, "_held_energy"):
            self._held_energy = self.explained(np.empty(0), np.empty(0, dtype=np.complex128))[0]
        return self._held_energy


def _small_decisive(spec: Spectrum, fd: float, c: np.ndarray, snr: np.ndarray, n_fixed: int, n_static: int,
                    tones: np.ndarray, guard_bins: float, fd_max_hz: float, threshold_factor: float,
                    width_test: bool = True, low: LowBand | None = None) -> bool:
    """Whether a sub-guard fit at ``fd`` is a mover: the baseband line's SNR (``snr[0]``) at least
    :data:`SMALL_MIN_SNR` and stronger than every sideband, :data:`SMALL_MIN_PAIRS` tones with both
    sidebands above ``threshold_factor``, a coherent line (:data:`SMALL_MAX_WIDTH`), and on a static
    intermodulation product within the guard, stronger than every static line. ``c``: the fit's
    amplitudes, the held lines' first (``n_fixed``: the static lines' ``n_static``, then those of
    the movers already found), then the mover's (baseband, U, L)."""
    cm, t = c[n_fixed:], tones.size
    pairs = int(np.sum(np.minimum(snr[1:1 + t], snr[1 + t:]) >= threshold_factor))
    base_pw = float(np.abs(cm[0]) ** 2)
    if not (snr[0] >= SMALL_MIN_SNR and base_pw > float(np.max(np.abs(cm[1:]) ** 2))
            and pairs >= min(SMALL_MIN_PAIRS, t)):
        return False
    if width_test and _too_wide(spec, low, fd):
        return False
    spurs = blind_spurs(spec, tones, fd_max_hz)
    on_spur = np.any(np.abs(spurs - abs(fd)) < guard_bins * spec.df_hz)
    return not (on_spur and base_pw <= float(np.max(np.abs(c[:n_static]) ** 2)))


def _small_lines(fit: _SmallFit, fd: float, fm: np.ndarray, dm: np.ndarray, cm: np.ndarray, s2: np.ndarray,
                 snr: np.ndarray, beats: tuple[np.ndarray, np.ndarray] | None = None,
                 spec: Spectrum | None = None) -> tuple[float, float, float] | None:
    """Each line's own frequency, the others held (``beats``: the mover's beats with the movers
    already found, :meth:`_SmallFit.beat_lines` with their exact DFTs, among them), and the lines'
    combined Doppler correction and error (Hz) and the lines' chi2 per dof (:func:`_combine_lines`);
    None when the baseband line has no peak of its own. With ``spec`` (the search spectrum) the
    error holds what a line the fit does not model could pull the baseband line by
    (:func:`unmodelled_pull`) and what a slowly moving static target's lines do
    (:func:`_static_offset_gap`)."""
    dfr = fit.fs / fit.x.size
    use = snr >= LINE_FREQUENCY_SNR
    use[0] = True
    fb, db = beats if beats is not None else (np.empty(0), np.empty(0, dtype=np.complex128))
    held_f, held_d = np.concatenate([fit.static, fm, fb]), np.concatenate([fit.d_static, dm, db])
    lines = np.flatnonzero(use)

    gains = _trial_gains(fit, held_f, held_d, fm[lines], fit.static.size + lines)
    # the energy's curvature there (V^2/Hz^2) is the Fisher information of the line's frequency with
    # every amplitude of the model free -- near 0 Hz, its image and the static line, less than an
    # isolated line's
    d_line, curv = np.zeros(fm.size), np.zeros(fm.size)
    d_line[lines], curv[lines] = _parabola_peaks(gains, lines.size, SMALL_CURVATURE_STEP * dfr, -0.5 * dfr,
                                                 0.5 * dfr, 2)
    # a line whose energy has no peak near its frequency (a weak line's noise: no concave top, or
    # one beyond the half bin searched) tells nothing of it; without the baseband, no estimate
    use &= (curv < 0) & (np.abs(d_line) < 0.5 * dfr)
    if not use[0]:
        return None
    # white noise of per-sample variance s2 (real; total s2 for IQ): var(f) = (2 or 1)*s2/(-E'');
    # the local floor may be the line's own phase-noise pedestal (laser phase over the echo delay,
    # flat near the line), which lies wholly in the phase quadrature: twice white noise's effect
    var_line = _line_frequency_var(fit, s2[use], curv[use])
    _, slope = target_lines(fit.tones, fd, fit.iq)
    delta, err, chi2, _ = _combine_lines(np.abs(cm[use]) ** 2, slope[use], d_line[use], var_line)
    if spec is not None:
        # a line the fit does not model: beyond the search's guard about the line, and within it
        # (1-6 record bins), probed on the record itself
        line = float(fm[0] + d_line[0])
        known = np.concatenate([np.delete(held_f, fit.static.size), [] if fit.iq else [0.0, -line]])
        err = math.hypot(err, unmodelled_pull(spec, float(fm[0]), held_f, dfr),
                         fit_neighbour_pull(fit.x, line, fit.fs, float(s2[0]), known, fit.hann_x),
                         _static_offset_gap(fit, float(fm[0]), held_f, held_d, float(d_line[0]), float(s2[0])))
    return delta, err, chi2


def _trial_gains(fit: _SmallFit, held_f: np.ndarray, held_d: np.ndarray, freqs: np.ndarray, moved: np.ndarray):
    """``gains(idx, offsets)`` for :func:`_parabola_peaks`: the energy line ``moved[i]`` of the held set
    (``held_f``, Hz, its exact DFTs ``held_d``; at ``freqs[i]``) adds at each offset (Hz, shape
    (len(idx), 3)), every other line held -- one pass over the record for all the trials."""
    def gains(idx: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        trial = freqs[idx, None] + offsets
        d_trial = exact_dft(fit.x, trial.ravel(), fit.fs).reshape(trial.shape)
        return line_gains(held_d, held_f, fit.fs, fit.x.size, fit.total, fit.iq, moved[idx], trial, d_trial)
    return gains


def _line_frequency_var(fit: _SmallFit, s2, curv):
    """A line's frequency variance (Hz^2) from white noise of per-sample variance ``s2`` (real; total
    for IQ) and the fit's energy curvature there (``curv`` < 0, V^2/Hz^2): ``(2 or 1)*s2/(-E'')``,
    times :data:`PEDESTAL_FACTOR` (a pedestal's floor lies wholly in the phase quadrature)."""
    return (1.0 if fit.iq else 2.0) * PEDESTAL_FACTOR * s2 / -curv


#: the baseband line's frequency with the static lines let off their exact frequencies must move more
#: than this many of its own sigmas there for the move to count (:func:`_static_offset_gap`): with
#: held lines a bin or so from it that sigma is several times the fit's own, and a real pull hides
#: under it (scene 2264's second frame: 240 Hz off at 32 Hz, moved 396 Hz at 154 Hz); ~5 % of
#: frames with no pull state their noise's move too
STATIC_OFFSET_SIGMAS = 2.0


def _static_flanks(fit: _SmallFit, base: np.ndarray, clear_of: np.ndarray, signed: bool) -> np.ndarray:
    """Lines half a record bin either side of the fit's static lines (Hz; 0 Hz's upper one only on a
    real record: its lower one is its image) to hold beside ``base`` (Hz, the lines the fit holds
    already): held, a static line's offset is taken up to second order (:func:`_static_offset_gap`,
    :func:`_decisive_off_static`). None within :data:`STATIC_FLANK_CLEAR_BINS` of ``clear_of`` (Hz;
    by signed frequency with ``signed``, else by absolute) -- the fit would be near-singular -- nor
    within a quarter bin of a line held before it."""
    dfr = fit.fs / fit.x.size
    static = fit.static[:fit.n_static]
    extra = np.concatenate([static + 0.5 * dfr, static - 0.5 * dfr] + ([] if fit.iq else [[0.5 * dfr]]))
    a, b = (extra, np.asarray(clear_of, dtype=float)) if signed else (np.abs(extra), np.abs(clear_of))
    extra = extra[np.min(np.abs(a[:, None] - b[None, :]), axis=1) > STATIC_FLANK_CLEAR_BINS * dfr]
    return _add_apart(base, [extra], 0.25 * dfr)[len(base):]


def _static_offset_gap(fit: _SmallFit, f0: float, held_f: np.ndarray, held_d: np.ndarray, d0: float,
                       s2: float) -> float:
    """How far (Hz) the baseband line's frequency moves when the static lines may lie up to half a
    record bin off their frequencies; 0 where it moves less than :data:`STATIC_OFFSET_SIGMAS` of its
    own sigma there.

    The fit holds a static target's lines at 0 Hz and ``f_i`` exactly. A "static" target slowly
    moving (0.1-0.35 record bins: below anything the search or this fit could call a mover) leaves
    ~``pi*delta/sqrt(3)`` of its lines unmodelled, beside the mover's baseband line a bin or two
    away: the envelope probe's scenes 2264, 3575 and 3689 (a 0.2, 0.35 and 0.13-bin target 17-27 dB
    under a mover 1.4, 2.2 and 3.1 bins up) had that line pulled 500, 290 and 66 Hz at stated errors
    of 26, 12 and 7 Hz. Held with lines half a bin either side (0 Hz's upper one only on a real
    record: its lower one is its image), a static line's offset is taken up to second order; the
    baseband line's frequency is found again against them (``line_gains``, from ``d0``, its offset
    from ``f0``; ``s2`` its noise variance, V^2), and the move is stated, not the new value (the
    second-order leak stays: scene 3689's line is still 38 Hz off, at 8 Hz). Three passes over the
    record, for a mover the fit reports only."""
    dfr = fit.fs / fit.x.size
    # none where the baseband line's trials reach (half a bin about it): the fit would be singular
    extra = _static_flanks(fit, held_f, np.array([f0]), False)
    if not extra.size:
        return 0.0
    hf = np.concatenate([held_f, extra])
    hd = np.concatenate([held_d, exact_dft(fit.x, extra, fit.fs)])
    # the mover's baseband line, first of its lines
    gains = _trial_gains(fit, hf, hd, np.array([f0]), np.array([fit.static.size]))
    d1, curv = _parabola_peaks(gains, 1, SMALL_CURVATURE_STEP * dfr, -0.5 * dfr, 0.5 * dfr, 2, np.array([d0]))
    if curv[0] >= 0:
        return 0.0
    sigma = math.sqrt(float(_line_frequency_var(fit, s2, curv[0])))
    gap = abs(float(d1[0]) - d0)
    return gap if gap > STATIC_OFFSET_SIGMAS * sigma else 0.0


#: the residual probes beside a reassigned line reach this many record bins either side (a
#: neighbour beyond ~5 bins lies outside the reassignment's Kaiser(14) main lobe and pulls it by
#: under 1e-4 bin per unit of its amplitude ratio)
NEIGHBOUR_PROBE_BINS = 6
#: the most a neighbour line pulls the reassignment (record bins) per unit of the largest residual
#: probe beside it, by that probe's distance (1, 2, 3, 4+ bins), measured with a line and a
#: neighbour 0.02-8 bins away at every phase: a neighbour under a bin away shows little in the
#: probes (the fit takes most of it in) and pulls ~``rho*delta``
NEIGHBOUR_PULL_PER_PROBE = (21.0, 5.0, 0.35, 0.1)


def _hann_kernel(theta: np.ndarray | float, n: int) -> np.ndarray:
    """A unit line's DFT through the symmetric Hann window of ``n`` samples, centred phases,
    ``theta = 2*pi*(f - f_line)/fs`` (rad per sample): ``D(theta)/2 + (D(theta - p) + D(theta + p))/4``
    with ``D`` the centred Dirichlet kernel and ``p = 2*pi/(n - 1)``; real."""
    p = 2 * np.pi / (n - 1)
    return 0.5 * _dirichlet(theta, n) + 0.25 * (_dirichlet(theta - p, n) + _dirichlet(theta + p, n))


def neighbour_pull(x: np.ndarray, line_hz: float, fs: float, s2: float, known_hz: np.ndarray) -> float:
    """The most (Hz) an unmodelled line within the reassignment's main lobe could pull ``line_hz``.

    The record ``x`` (its mean removed) is read through a Hann window at the line and at whole
    record bins either side (:data:`NEIGHBOUR_PROBE_BINS`). The line itself, and every line of
    ``known_hz`` within 32 bins (Hz: 0 Hz, other targets' lines, the image), their amplitudes
    solved together from the DFTs at them, are taken out of those probes through the window's
    kernel (:func:`_hann_kernel`: a strong static line 5.5 bins away leaks into the probes 40 dB
    under itself); probes within 3 bins of a known line are skipped. The largest residual, where
    it stands :data:`UNMODELLED_BUMP` times above the white floor (``s2``, V^2 per sample) and,
    with 6 probes or more, their median (a laser's pedestal), gives a neighbour's size ``q`` over
    the line's; the pull is at most
    :data:`NEIGHBOUR_PULL_PER_PROBE` times ``q`` record bins (:func:`_neighbour_probe`). 0 where fewer
    than 2 probes are left.
    The envelope probe's scene 4019: an ideal laser, a mover 34 dB under another 2.8 bins away,
    under the search's threshold, pulled its line by 52 Hz at a stated 3.7 Hz (0.15 bins per unit
    of its amplitude ratio, as measured here). One Hann-windowed pass and 13 exact DFTs over the
    record (and one per known line near), for a reassigned line only (none on the benchmark's
    scenes at 1e6 samples)."""
    probe = _neighbour_probe(x, line_hz, fs, s2, known_hz)
    if probe is None:
        return 0.0
    q, dist = probe
    return NEIGHBOUR_PULL_PER_PROBE[min(dist, len(NEIGHBOUR_PULL_PER_PROBE)) - 1] * q * fs / x.size


def _neighbour_probe(x: np.ndarray, line_hz: float, fs: float, s2: float, known_hz: np.ndarray,
                     xw: np.ndarray | None = None) -> tuple[float, int] | None:
    """The largest residual probe beside ``line_hz`` (:func:`neighbour_pull` says how it is read): a
    neighbour's amplitude over the line's, ``q``, and the probe's distance (whole record bins, 1 to
    :data:`NEIGHBOUR_PROBE_BINS`); None where no probe stands out, or fewer than 2 are left. ``xw``:
    the record's Hann-windowed copy, where the caller keeps one."""
    n = x.size
    dfr = fs / n
    k = np.arange(-NEIGHBOUR_PROBE_BINS, NEIGHBOUR_PROBE_BINS + 1)
    probes = line_hz + k * dfr
    known = np.atleast_1d(np.asarray(known_hz, dtype=float))
    near = np.unique(known[(np.abs(known - line_hz) <= 32 * dfr) & (np.abs(known - line_hz) > 0.5 * dfr)])
    near = near[np.concatenate([[True], np.diff(near) > 0.5 * dfr])] if near.size else near
    xk = exact_dft(windowed_record(x, "hann") if xw is None else xw, np.concatenate([probes, near]), fs)
    centre = xk[NEIGHBOUR_PROBE_BINS]
    if not abs(centre) > 0:
        return None
    # the line's and the known lines' amplitudes together (each one's DFT holds the others' leakage)
    lines = np.concatenate([[line_hz], near])
    at = np.concatenate([[centre], xk[k.size:]])
    amps = np.linalg.lstsq(_hann_kernel(2 * np.pi * (lines[:, None] - lines[None, :]) / fs, n), at, rcond=None)[0]
    model = _hann_kernel(2 * np.pi * (probes[:, None] - lines[None, :]) / fs, n) @ amps
    r2 = np.abs(xk[:k.size] - model) ** 2
    keep = k != 0
    if known.size:
        keep &= np.min(np.abs(probes[:, None] - known[None, :]), axis=1) > 3 * dfr
    if keep.sum() < 2:
        return None
    r2, dist = r2[keep], np.abs(k[keep])
    floor = s2 * window_power("hann", n)
    if r2.size >= 6:
        floor = max(floor, float(np.median(r2)) / math.log(2))
    j = int(np.argmax(r2))
    if not r2[j] > UNMODELLED_BUMP * floor:
        return None
    return math.sqrt(r2[j] - floor) / abs(centre), int(dist[j])


#: a Hann-windowed probe's amplitude response half a bin from a line (its scalloping: 1.42 dB)
SCALLOP_HANN = 0.85


def fit_neighbour_pull(x: np.ndarray, line_hz: float, fs: float, s2: float, known_hz: np.ndarray,
                       xw: np.ndarray | None = None) -> float:
    """The most (Hz) an unmodelled line 1-6 record bins away could pull a line that a record-long
    least-squares fit measures (the sub-guard fit's): the residual probes of
    :func:`neighbour_pull` (the neighbour's size ``q`` over the line's, read at the probe nearest it,
    up to :data:`SCALLOP_HANN` low) with the fit's own pull law, :func:`unmodelled_pull`'s, at the
    nearest the neighbour can lie, half a bin inside its probe (and at half a bin at the least,
    where a neighbour pulls ~``q*delta``, under ``q`` bins).

    :func:`unmodelled_pull` reads the search spectrum :data:`SMALL_NEAR_GUARD` of its bins clear of
    the line: blind to a neighbour within 5 record bins, 20 in ``fast``'s spectrum of a quarter
    record. The envelope probe's scene 4019 in ``fast``: a mover 8 record bins up fitted below
    ``fast``'s guard, a moving echo 34 dB under it 2.8 bins away, under the search's threshold,
    pulled it by 39 Hz at a stated 2.3 Hz (speed z 17). One Hann-windowed pass and 13 exact DFTs
    over the record, for a sub-guard mover only (``xw``: the record's Hann-windowed copy, kept by
    the fit for all its measurements)."""
    probe = _neighbour_probe(x, line_hz, fs, s2, known_hz, xw)
    if probe is None:
        return 0.0
    q, dist = probe
    return fit_pull_bins(q / SCALLOP_HANN, max(dist - 0.5, 0.5)) * fs / x.size


def fit_pull_bins(ratio: float, delta: float) -> float:
    """The most (record bins) an unmodelled line of ``ratio`` times a line's amplitude, ``delta``
    record bins away, pulls that line's frequency as a record-long least-squares fit measures it:
    ``ratio * 3/(pi^2*delta) * (1 + 1/(pi*delta))`` (the Dirichlet kernel's slope there over the
    periodogram's curvature at the peak; :func:`unmodelled_pull`, :func:`fit_neighbour_pull`)."""
    return ratio * 3 / (np.pi**2 * delta) * (1 + 1 / (np.pi * delta))


#: a Kaiser(14) window's amplitude response half a bin from a line (its scalloping)
SCALLOP_KAISER14 = 0.92
#: a bin of the search spectrum about a sub-guard mover's baseband line, outside every modelled line's
#: main lobe, counts as a line the fit does not model where it stands this many times the ring's mean
#: floor (an exponential bin exceeds 10x its mean with odds 4.5e-5: ~0.3 % over a ring)
UNMODELLED_BUMP = 10.0


def unmodelled_pull(spec: Spectrum, line_hz: float, modelled_hz: np.ndarray, dfr: float) -> float:
    """The most (Hz) a line the record-long fit does not model could pull a line's frequency.

    A record-long least-squares fit of a line of amplitude ``A`` beside an unmodelled one of
    amplitude ``a``, ``delta`` record bins away, has its frequency pulled by up to
    ``(a/A) * 3/(pi^2*delta) * (1 + 1/(pi*delta)) * fs/N`` (the Dirichlet kernel's slope there over the
    periodogram's curvature at the peak). The strongest bin of the search spectrum within
    :data:`SMALL_NEAR_HALF_WIDTH` bins of the line, :data:`SMALL_NEAR_GUARD` bins clear of every
    modelled line, counts where it stands :data:`UNMODELLED_BUMP` times the ring's mean floor; its
    power above that floor over the line's peak is ``(a/A)^2``. The envelope probe's scene 450: a
    sub-guard mover at 2.3 record bins, 80 dB over the floor, stated 0.8 Hz, was 16-40 Hz off
    beside a mover 43 dB weaker 5 bins away that the search had not taken (its score under a tenth
    of the first's). 0 where no such bin stands out.

    Parameters
    ----------
    spec : the search spectrum; line_hz : the line (Hz, signed for IQ)
    modelled_hz : ndarray, shape (M,), every line the fit models (Hz)
    dfr : the record's bin (Hz)
    """
    f = np.asarray(modelled_hz, dtype=float)
    line = line_hz if spec.complex_input else abs(line_hz)
    f = f if spec.complex_input else np.abs(f)
    b0 = int(spec.bin_of(line))
    idx, keep = spec.ring([line], np.concatenate([f, [line]]), SMALL_NEAR_HALF_WIDTH, SMALL_NEAR_GUARD)
    idx = idx[keep]
    if idx.size < 8:
        return 0.0
    p = np.asarray(spec.power[idx], dtype=np.float64)
    floor = float(np.median(p)) / math.log(2)  # the median of an exponential bin is ln 2 of its mean
    k = int(np.argmax(p))
    if not p[k] > UNMODELLED_BUMP * floor:
        return 0.0
    # both peaks read over their neighbours too (a ring's edge may cut into the bump's main lobe),
    # the bump's allowing the window's scalloping between bins
    top = float(np.max(np.asarray(spec.power[max(idx[k] - 1, 0):idx[k] + 2], dtype=np.float64)))
    peak = float(np.max(np.asarray(spec.power[max(b0 - 1, 0):b0 + 2], dtype=np.float64)))
    if not peak > 0:
        return 0.0
    delta = abs(spec.f0_hz + idx[k] * spec.df_hz - line) / dfr
    return fit_pull_bins(math.sqrt((top - floor) / peak) / SCALLOP_KAISER14, delta) * dfr
