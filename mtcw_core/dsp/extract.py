"""Stage ``extract``: the complex amplitude of every line the targets put in the record.

The *line plan* (:func:`plan_lines`) lays out, per target candidate, the lines its physics
predicts -- the static candidate's at ``f_i``, each Doppler line's at ``f_i +- f_d`` -- and
marks those that cannot be told apart from another line. Extraction fits them all jointly by
least squares at their exact frequencies (:mod:`.tones`), on the whole record, on segments
(``settings.segments``), or on the echo windows of a quasi-CW record cut into segments short
enough for the laser to stay coherent; or, for the ``seed`` profile, by the dissertation's
resample + band-pass ``filtfilt`` + correlation path (:func:`seed_extract`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
from scipy import signal as sps

from ..frame import Frame
from ..profiles import ChainSettings
from ..results import Rejected
from .doppler import MIN_CARRIER_COHERENCE, DopplerEstimate, doppler_families, fd_max, self_beat_bound
from .spectrum import Spectrum, equivalent_width, still_line_doppler_bins, width_doppler_bins, windowed_record
from .tones import (centre_turn, exact_dft, exact_dft_tiled, fit_lines, fit_lines_segments, fit_noise_gain,
                    line_response, mean_leak)
from .validate import MIN_RAIL_SPAN_STEPS, code_steps


@dataclass(frozen=True)
class NoiseRing:
    """The search spectrum's noise about a family's lines, at offsets shared by every usable line
    of its target's families (their rows line up), mirrored and conjugated as the lines' ``z`` is
    and turned into each line's frame (:meth:`~.spectrum.Spectrum.line_rings`): how the lines'
    noise moves together. The carrier's own phase noise turns every line alike; at a tone's offset
    it moves that tone's upper and lower lines' phases oppositely; a strong echo's pedestal a few
    MHz off moves them together like a range shift.

    Attributes
    ----------
    rows : ndarray, shape (W, T), complex
        In phase units (rad): the mean over rows of ``|rows[:, i]|^2`` is line i's phase variance
        from the floor there. Unusable lines' columns are 0.
    shift : ndarray, shape (T,)
        Each line's offset from its rows' bins, scaled so that the window leaves two lines' rows
        ``exp(-(shift_i - shift_j)^2)`` as coherent as their noise is.
    near : ndarray of bool, shape (W,)
        The rows within :data:`RING_NEAR_BINS` beyond the guard: a floor rising toward the line
        (a strong neighbour's pedestal) is read there at the line's own level.
    """

    rows: np.ndarray
    shift: np.ndarray
    near: np.ndarray

    def columns(self, use: np.ndarray) -> NoiseRing:
        """The ring of the lines ``use`` picks (a mask or indices, over T)."""
        return NoiseRing(self.rows[:, use], self.shift[use], self.near)


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
    target : int
        Which target candidate the family belongs to: 0 the static one (Doppler 0), k >= 1 the
        k-th Doppler line.
    unexplained_v : ndarray, shape (T,), or None
        The static lines: the largest amplitude (V) that what no found mover explains could add to
        each -- on one photodiode the self-beats of Doppler lines
        (:func:`~mtcw_core.dsp.doppler.self_beat_bound`), on an IQ record the leak of an echo
        among them moving below one record bin (:func:`subbin_leak_bound`); None where not
        measured (balanced records, quasi-CW windows, segmented profiles, the ``filter``
        extraction, a Doppler stage that states no floor).
    cross_v : ndarray, shape (T,), or None
        A mover's lines: what an echo among the static lines could add to each (V) -- on one
        photodiode its beat with the mover, if the static lines are one (:func:`cross_beat_bound`;
        they may be the mover's own self-beat left over, which adds nothing); on an IQ record its
        leak, moving below one record bin (:func:`subbin_bounds`); on a balanced one its fading
        envelope's leak (:func:`envelope_leak_bound`); None where not measured.
    cross_x : float or None
        ... and the largest Doppler (record bins) that static echo could have, as its lines' width
        shows (:func:`~.spectrum.still_line_doppler_bins`): its beat lies that far from the mover's
        lines and pulls their frequency; None where not read (any Doppler up to the guard).
    echo_beats : bool
        A mover's lines on one photodiode where two movers or more were found and the echoes hold
        more of the record's mean than the LO (their self-beats' prediction took the LO for the
        smaller part): a Doppler line may then be the beat of a strong echo with an echo whose own
        LO beat is too weak to be seen, which no rule can tell from a mover (the point is
        ``blended``).
    static_echo : bool
        The static lines on one photodiode beside found movers: they stood mostly above what the
        movers' self-beats' prediction took out of them -- a static echo's own lines, not a
        self-beat left over (:func:`_self_beats`' ``mostly_self``), whatever range they fit.
    ring : NoiseRing or None
        The noise about the lines, read together with the target's other families'
        (:class:`NoiseRing`); None where not read.
    copy_v : ndarray, shape (T,), or None
        A mover's lines on integer ADC codes whose thermal noise is under ~1/2 LSB: what the
        quantizer's products could add to each (V), as its copies of the mover's lines where no
        line stands show them; every line's own size on a record of few codes (under-resolved)
        (:func:`quantizer_copies`); None where not measured.
    self_beats : dict or None
        The static lines on one photodiode beside found movers: per mover (target k), its self-beat
        as predicted from its LO beats and taken out of ``z`` at scale 1 (V, shape (S, T)). The
        prediction keeps the carrier's coherence at the mover's delay, the self-beat all of it
        (:func:`self_beat_scale`): where the laser is declared, the rest is taken out once the
        mover's range is known (:func:`~mtcw_core.ranging.targets.whole_self_beats`). None where
        none was taken at scale 1.
    envelope_chi2 : (float, int) or None
        The static lines of a real record on which no mover was found: their segments against one
        echo's real envelope (:func:`envelope_rank_chi2`), chi2 and degrees of freedom; None where
        not read.
    fast_fade : float or None
        The same static lines: the part of their envelope's energy that turns faster than the
        static claim's sigma (:func:`fast_fade`; 0 within the noise); None where not read.
    """

    name: str
    tone_hz: np.ndarray
    line_hz: np.ndarray
    z: np.ndarray
    seg_centre_s: np.ndarray
    phase_var: np.ndarray
    target: int = 0
    unexplained_v: np.ndarray | None = None
    cross_v: np.ndarray | None = None
    cross_x: float | None = None
    echo_beats: bool = False
    static_echo: bool = False
    ring: NoiseRing | None = None
    copy_v: np.ndarray | None = None
    self_beats: dict[int, np.ndarray] | None = None
    envelope_chi2: tuple[float, int] | None = None
    fast_fade: float | None = None

    @property
    def snr_db(self) -> np.ndarray:
        """Post-integration line SNR, ``1/phase_var`` in dB (``N*A^2/(2*sigma^2)`` for a real tone)."""
        return -10 * np.log10(self.phase_var)



#: a sub-guard mover's lines (``plan_lines``'s ``fine``) clash with another line within this many
#: record bins (its search keeps its baseband line a bin or more from 0 Hz: U and L a bin or more
#: from the static line)
FINE_CLASH_BINS = 0.9


def plan_lines(frame: Frame, fds: list[float], iq: bool, settings: ChainSettings, fit_samples: int | None = None,
               fine: list[bool] | None = None) -> tuple[list[tuple[int, str, np.ndarray, np.ndarray, np.ndarray]],
                                                        np.ndarray]:
    """Line families per target candidate, and every frequency to fit.

    Candidate 0 is static (Doppler 0: the S lines of a real detector, the +-f_i lines of an IQ
    one); candidate k >= 1 is the k-th Doppler line (U and L families). Lines that fall within
    2 record-bins of lines already planned (or of each other) cannot be separated: they are
    marked unusable and not fitted. ``fit_samples``: the length of the records the lines are
    fitted on (a segment's, when extraction is segmented), which sets the resolution. ``fine``
    (one per Doppler line): a mover found below the search's guard
    (:func:`~mtcw_core.dsp.doppler.search_small_doppler`, on the whole record) was itself measured
    with its lines fitted jointly a bin or more from the static ones, where the record's Dirichlet
    kernel leaves them at most 0.22 correlated: its lines clash only within
    :data:`FINE_CLASH_BINS` record bins.

    Returns
    -------
    families : list of (target, name, line freqs (Hz), conjugate mask, unusable mask), each (T,)
    freqs : ndarray, every frequency to fit (Hz): the usable lines, then the extra lines modelled
        (baseband Doppler lines, the IQ LO's 0 Hz, the MZM's products with ``model_products``)
    """
    t = np.asarray(frame.tones_hz, float)
    res = 2 * frame.fs_hz / (fit_samples or frame.n)
    none = np.zeros(t.size, bool)
    # (target, name, line freqs, conj mask, unusable mask)
    fams: list[tuple[int, str, np.ndarray, np.ndarray, np.ndarray]] = []
    if iq:  # a static target is the Doppler-0 case of the U/L layout
        fams += [(0, name, f, conj, none) for name, f, conj in doppler_families(t, 0.0, True)]
    else:
        fams.append((0, "S", t.copy(), none, none))
    used = np.concatenate([f for _, _, f, _, _ in fams])
    extra: list[float] = []
    sep: list[float] = []  # each extra line's clearance, in units of 1.5*res (a fine mover's baseband: less)
    for k, fd in enumerate(fds, start=1):
        cand = [(k, name, f, conj) for name, f, conj in doppler_families(t, fd, iq)]
        new = np.concatenate([f for _, _, f, _ in cand])
        # a line within 2 bins of another (e.g. f_i + f_d = f_j - f_d at half the tone spacing,
        # or another target's line) cannot be told apart: it is left out of this target
        res_k = FINE_CLASH_BINS * frame.fs_hz / frame.n if (fine and fine[k - 1] and not fit_samples) else res
        clash = np.abs(new[:, None] - used[None, :]).min(axis=1) <= res_k
        d = np.where(np.eye(new.size, dtype=bool), np.inf, np.abs(new[:, None] - new[None, :]))
        clash |= d.min(axis=1) <= res_k
        for j, (kk, name, f, conj) in enumerate(cand):
            bad = clash[j * t.size:(j + 1) * t.size]
            fams.append((kk, name, f, conj, bad))
            used = np.concatenate([used, f[~bad]])
        extra.append(fd if iq else abs(fd))
        sep.append(res_k / res)
    if iq:
        extra.append(0.0)  # the complex fit has no DC column: the LO's DC is a line at 0 Hz
        sep.append(1.0)
    if settings.model_products and not iq:
        prods = [2 * a for a in t] + [a + b for i, a in enumerate(t) for b in t[i + 1:]] + \
                [abs(a - b) for i, a in enumerate(t) for b in t[i + 1:]]
        extra += [p for p in prods if p < frame.fs_hz / 2]
    sep += [1.0] * (len(extra) - len(sep))
    # a product line too close to a used line cannot be told apart: keep the used ones
    ex = np.asarray(extra, float)
    clear = np.abs(ex[:, None] - used[None, :]).min(axis=1, initial=np.inf) > 1.5 * res * np.asarray(sep)
    keep: list[tuple[float, float]] = []  # (line Hz, its clearance Hz)
    for f, ok, c in zip(extra, clear, sep):
        # IQ: a sub-guard mover's baseband line is told from the 0 Hz line as its U and L lines from
        # the static ones, FINE_CLASH_BINS apart (leaving either out leaves its carrier, 30-60x its lines,
        # leaking its skirt onto every line: the envelope probe's scenes 17571 and 17879)
        gap = res * c if iq and c < 1.0 else 1.5 * res * c
        if (ok and all(abs(f - k) > (min(gap, g) if iq else gap) for k, g in keep)
                and (abs(f) > gap or (iq and f == 0.0))):
            keep.append((f, gap))
    return fams, np.concatenate([used, np.asarray([k for k, _ in keep], float)])


def segment_starts(n: int, fs: float, settings: ChainSettings, windows: list[tuple[int, int]] | None,
              fds: list[float] = ()) -> tuple[np.ndarray, int]:
    """Segment starts and common length: the whole record in ``settings.segments`` parts, or
    each echo window cut into pieces of ``gate_segment_s`` -- longer when a Doppler line ``fds``
    (Hz) is found, so that a mover's lines ``f_i +- f_d`` lie 3 segment-bins from ``f_i`` and
    are told apart from a static target's (the IF products cancel the laser's phase noise
    whatever the length; a longer segment only spreads an incoherent line over more bins)."""
    if not windows:
        length = n // settings.segments
        return np.arange(settings.segments) * length, length
    span = sum(b - a for a, b in windows)
    longest = max(b - a for a, b in windows)
    want = max(64, round(settings.gate_segment_s * fs))
    moving = [abs(f) for f in fds if f != 0.0]
    if moving:
        want = max(want, int(math.ceil(3 * fs / min(moving))))
    length = int(min(want, longest, span))
    starts = [a + k * length for a, b in windows for k in range((b - a) // length)] if length > 0 else []
    if not starts:
        raise Rejected("gate", f"echo windows ({span} samples) shorter than one segment")
    return np.asarray(starts, dtype=np.int64), length


def _line_index(uniq: np.ndarray, f_hz) -> np.ndarray:
    """Each frequency's index in the sorted modelled lines ``uniq`` (Hz, rounded to 1e-6 Hz as
    ``uniq`` is), clipped into range: the nearest line at or above it where it is not modelled."""
    return np.clip(np.searchsorted(uniq, np.round(f_hz, 6)), 0, uniq.size - 1)


def extract_lines(x: np.ndarray, frame: Frame, dops: list[DopplerEstimate], spec: Spectrum,
                  settings: ChainSettings, windows: list[tuple[int, int]] | None = None) -> list[LineFamily]:
    """The stage: complex amplitude of every used line, per segment, with its phase variance.

    Parameters
    ----------
    x : ndarray, shape (N,), float64 or complex128, V
    dops : the Doppler lines found (stage ``doppler``)
    spec : the search spectrum, for the lines' local noise floors
    windows : sample ranges ``[a, b)`` where a quasi-CW echo is on; extraction is restricted to them

    Returns
    -------
    list of LineFamily, the static candidate's first (target 0), then each Doppler line's U and L
    """
    iq, n, fs, fds = np.iscomplexobj(x), x.size, frame.fs_hz, [d.fd_hz for d in dops if d.detected]
    segmented = settings.extraction != "filter" and (windows or settings.segments > 1)
    if segmented:
        starts, length = segment_starts(n, fs, settings, windows, fds)
    fams, all_f = plan_lines(frame, fds, iq, settings,
                             length if segmented else None, [d.method == "fit" for d in dops if d.detected])
    uniq = np.unique(np.round(all_f, 6))
    fading = (not windows and settings.segments == 1 and settings.extraction != "filter"
              and (iq or not fds or frame.receiver == "balanced"))  # beside movers: the leak bounds' parts
    guard = max((d.min_detectable_hz for d in dops), default=0.0)  # the largest Doppler missed (Hz)
    seg_dft = seg_sums = None
    if settings.extraction == "filter":
        if windows:
            raise Rejected("unsupported", "the seed's filter extraction has no quasi-CW gating")
        z_all, centre = seed_extract(x, fs, uniq, settings)
        z_all, centres = z_all[None, :], np.array([centre])
    elif not windows and settings.segments == 1:
        whole, total, seg_dft, seg_sums = _whole_record_dfts(x, fs, uniq, spec, guard if fading else None, bool(fds))
        z_all, centres = fit_lines(x, uniq, fs, dft=whole, total=total)[None, :], np.array([(n - 1) / (2 * fs)])
    else:
        z_all = fit_lines_segments(x, starts, length, uniq, fs)
        centres = (starts + (length - 1) / 2) / fs
        n = int(starts.size * length)  # samples the amplitudes rest on
    kappa = 0.5 if iq else 2.0
    envelope = fade = None
    if seg_dft is not None and not iq and not fds:
        z_all, envelope, fade = _static_envelope(x, fs, uniq, fams[0][2], spec, guard, (seg_dft, seg_sums), z_all)
    zs = {}
    for target, name, freqs, conj, bad in fams:
        idx = _line_index(uniq, freqs)
        z = z_all[:, idx].copy()
        z[:, conj] = np.conj(z[:, conj])
        z[:, bad] = 0.0
        zs[target, name] = z
    # every family's local floors in one call (each row is its own line's statistic)
    s2_all = spec.noise_variances(np.concatenate([freqs for _, _, freqs, _, _ in fams]), uniq,
                                  guard=spec.line_floor_guard())
    first = np.cumsum([0] + [freqs.size for _, _, freqs, _, _ in fams])
    unexplained, cross, still, over_lo, own, parts = None, {}, None, False, False, None
    if (frame.receiver == "single" and frame.architecture == "unmodulated_lo" and settings.extraction != "filter"
            and not windows):
        dc = (np.array([x[a:a + length].mean() for a in starts]) if segmented else np.array([total / n]))
        unexplained, cross, still, over_lo, own, parts = _self_beats(zs, z_all, uniq, dops, dc, spec, frame, settings,
                                                                     fams[0][2], x, s2_all[:first[1]])
    elif seg_dft is not None:
        unexplained, cross = _leak_bounds(x, fs, uniq, z_all[0], fams, fds, guard, spec, seg_dft, seg_sums)
    rings = _target_rings(spec, fams, uniq, frame.receiver != "single" and any(d.detected for d in dops))
    copies = quantizer_copies(spec, frame, fams, zs, uniq, fds,
                              [s2_all[a:b] for a, b in zip(first[:-1], first[1:])])
    out = []
    for i, (target, name, freqs, conj, bad) in enumerate(fams):
        z = zs[target, name]
        amp2 = np.mean(np.abs(z) ** 2, axis=0)
        s2 = s2_all[first[i]:first[i + 1]]
        var = kappa * s2 / (n * np.maximum(amp2, 1e-300))
        var[bad] = np.inf
        ring = rings[i]
        if ring is not None:  # in phase units: the mean of |rows|^2 is the floor's phase variance
            ring = replace(ring, rows=ring.rows * np.sqrt(kappa / (n * np.maximum(amp2, 1e-300) * spec.window_power)))
        out.append(LineFamily(name, np.asarray(frame.tones_hz, float), freqs, z, centres, var, target,
                              unexplained if target == 0 else None, cross.get(target) if target else None,
                              still if target else None, bool(target and over_lo), bool(not target and own),
                              ring, copies[i], parts if target == 0 else None, envelope if target == 0 else None,
                              fade if target == 0 else None))
    return out


def _static_envelope(x: np.ndarray, fs: float, uniq: np.ndarray, static_hz: np.ndarray, spec: Spectrum,
                     guard_hz: float, seg_dfts: tuple[np.ndarray, np.ndarray], z_all: np.ndarray
                     ) -> tuple[np.ndarray, tuple[float, int] | None, float | None]:
    """No Doppler line found on a real record: the static lines (``static_hz``) may still fade
    within it (a mover below the search's guard, the carrier's phase noise). Their common real
    envelope is measured (:func:`fading_lines`, its lines put into ``z_all`` (1, K) where taken),
    their segments read against one (:func:`envelope_rank_chi2`: (chi2, dof), None where not
    read) and the part of that envelope beyond the guard (:func:`fast_fade`, None where not read),
    all from one read of the segments (:func:`static_segments`). ``seg_dfts``: the segments' DFTs
    and sums (:func:`_whole_record_dfts`)."""
    s_idx = _line_index(uniq, static_hz)
    seg = static_segments(x, fs, uniq, s_idx, guard_hz, *seg_dfts)
    s2 = spec.noise_variances(static_hz, uniq)  # its default ring, 12 bins clear of every line
    c = fading_lines(x, fs, uniq, s_idx, s2, guard_hz, *seg_dfts, segments=seg)
    # the test reads its noise as the lines' own is read: as near them as their floor may lie (a
    # floor ~15 % low further out inflates the chi2 by as much); the same ring on a whole-record spectrum
    guard = spec.line_floor_guard()
    s2_lines = s2 if guard == 12 else spec.noise_variances(static_hz, uniq, guard=guard)
    envelope = envelope_rank_chi2(x, fs, uniq, s_idx, s2_lines, guard_hz, *seg_dfts, segments=seg)
    fade = None if seg is None else fast_fade(seg[0], s2, x.size // seg[0].shape[0], guard_hz * x.size / fs)
    if c is not None:
        z_all = z_all.copy()
        z_all[0, s_idx] = c
    return z_all, envelope if envelope[1] else None, fade


#: :func:`quantizer_copies` reads a record whose white floor (per channel) is at most this many
#: times the quantizer's own ``LSB^2/12`` (the quantizer then at least a quarter of it): thermal
#: noise under ~1/2 LSB leaves the quantizer's error a function of the signal, with products (1/2 LSB
#: of Gaussian noise damps its first harmonic by exp(-2*pi^2/4) ~ 0.7 %; 1.3 LSB by ~1e-15)
QUANT_DOMINATED = 4.0
#: ... and counts the copies where their mean power stands this many of its own sigmas (``1/sqrt(K)``
#: of the floor for K copies of noise alone) above the floor
COPY_NOISE_SIGMAS = 3.0
#: ... of at least this many copies; or the largest, where K copies of noise alone would reach it
#: with these odds (an exponential's tail: ``log(K/odds)`` times the floor)
COPY_MIN = 4
COPY_FALSE_ODDS = 1e-3


def _copy_positions(spec: Spectrum, t: np.ndarray, fds: list[float], lines: np.ndarray, uniq: np.ndarray,
                    guard: int) -> np.ndarray:
    """Where :func:`quantizer_copies` reads the movers' ``lines`` (Hz) copied: each moved by a
    difference of two tones ``t`` or by a sum or difference of found Dopplers (or one), in the
    spectrum and more than ``guard`` bins from every fitted line (``uniq``) and from every product
    of two fields (each tone or 0 Hz with another, moved by 0, a found Doppler, or the difference of
    two); folded to positive frequencies on a real record. Shape (P,), Hz, sorted."""
    dops = np.unique([s * a + r * b for a in fds for b in [0.0, *fds] for s in (1, -1) for r in (1, -1)])
    moves = np.concatenate([(t[:, None] - t[None, :])[~np.eye(t.size, dtype=bool)], dops])
    base = np.concatenate([[0.0], t, -t])
    # the square law's shifts: none, a Doppler, two movers' beat (on a real record the Dopplers are
    # |f_d|, and two movers going opposite ways beat at the sum of theirs)
    shifts = np.unique(np.concatenate([[0.0], dops[np.isin(np.round(np.abs(dops), 3), np.round(np.abs(fds), 3))],
                                       [s * (a - b) for a in fds for b in fds for s in (1, -1)],
                                       [] if spec.complex_input else [s * (a + b) for a in fds for b in fds
                                                                      for s in (1, -1)]]))
    second = ((base[:, None] + base[None, :]).ravel()[:, None] + shifts[None, :]).ravel()
    taken = np.unique(np.concatenate([second, uniq, -uniq]))
    lo, hi = spec.f0_hz + guard * spec.df_hz, spec.f0_hz + (spec.power.size - 1 - guard) * spec.df_hz
    pos = (lines[:, None] + moves[None, :]).ravel()
    pos = np.unique(np.round(pos if spec.complex_input else np.abs(pos), 3))
    pos = pos[(pos > lo) & (pos < hi)]
    if not pos.size:
        return pos
    j = np.clip(np.searchsorted(taken, pos), 1, taken.size - 1)
    near = np.minimum(np.abs(pos - taken[j - 1]), np.abs(pos - taken[j]))
    return pos[near > guard * spec.df_hz]


def _copies_excess(p: np.ndarray, floor: np.ndarray) -> float:
    """The copies' power ``p`` above their floors ``floor`` (spectrum units, shape (P,)): their mean
    where it stands out of the noise (:data:`COPY_NOISE_SIGMAS`), their largest where no noise draw
    of as many would reach it (:data:`COPY_FALSE_ODDS`), the larger; 0 where neither."""
    ratio, top = float(np.mean(p / floor)), float(np.max(p / floor))
    mean = float(np.mean(p - floor)) if ratio > 1.0 + COPY_NOISE_SIGMAS / math.sqrt(p.size) else 0.0
    return max(mean, float(np.max(p - floor)) if top > math.log(p.size / COPY_FALSE_ODDS) else 0.0)


def quantizer_copies(spec: Spectrum, frame: Frame, fams: list[tuple[int, str, np.ndarray, np.ndarray, np.ndarray]],
                     zs: dict, uniq: np.ndarray, fds: list[float], s2: list[np.ndarray]) -> list[np.ndarray | None]:
    """Each mover's families' :attr:`LineFamily.copy_v` (V, shape (T,)) on integer ADC codes whose
    white floor is at most :data:`QUANT_DOMINATED` times the quantizer's own ``LSB^2/12`` (thermal
    noise under ~1/2 LSB); there, every family's, the static one's too, at its lines' own size
    where the codes span fewer than :data:`~.validate.MIN_RAIL_SPAN_STEPS` steps (under-resolved);
    None elsewhere.

    Under an LSB of noise the quantizer's error is the signal's function: a weak line ``m`` beside
    strong ones ``S`` passes as ``m(t)*g(S(t))``, a gain beating at the strong lines' differences,
    copying each of the mover's lines to ``f + f_i - f_j`` -- onto its other lines, with the strong
    lines' phases, and beside them (:func:`_copy_positions`: where no square-law product falls,
    only a nonlinearity puts power). Their mean power above the floor, where it stands out of the
    noise (:data:`COPY_NOISE_SIGMAS`), or their largest, is what each line may carry: its size times
    the root of that power over the line's own -- pooled over the movers, as a gain beating at two
    movers' Doppler difference copies one's lines onto the other's. Scene 6815 of the envelope
    probe (IQ, 8-bit codes, a static echo 40 dB above a mover): copies 8-18 dB over the floor
    beside lines 17-27 dB over it, the range 107 sigmas off, unflagged; on float volts 0 +- 5 dB.
    The modulator's third-order products fall there too (35 dB under a mover's lines on
    ``moving-target``), and count where the quantizer's floor rules.

    Parameters
    ----------
    fams : the planned families ``(target, name, freqs, conj, bad)`` (:func:`plan_lines`)
    zs : {(target, name): ndarray (S, T)} their lines
    uniq : every fitted line (Hz); fds : the Doppler lines found (Hz)
    s2 : each family's lines' noise floors (V^2 per sample, shape (T,) each), as the lines were judged
    """
    out: list[np.ndarray | None] = [None] * len(fams)
    if frame.samples.dtype.kind not in "iu" or frame.scale == 0:
        return out
    iq, guard = spec.complex_input, spec.line_floor_guard()
    # the signal channels' codes (not a pulse reference): the fewest steps any spans, and its LSB in
    # volts (8-bit codes sent as 16-bit words step by 256)
    steps = [code_steps(c, stride=16) for c, name in zip(frame.samples, frame.channels) if name != "pulse_ref"]
    span, step = min(steps)
    q2 = (step * frame.scale) ** 2 / 12.0 * (2.0 if iq else 1.0)  # the quantizer's own (IQ: both channels)
    if not np.median(spec.noise_variances(uniq, uniq, guard=guard)) <= QUANT_DOMINATED * q2:
        return out  # thermal noise over ~1/2 LSB: the quantizer's error is noise, its products damped
    if span < MIN_RAIL_SPAN_STEPS:
        # under-resolved: the record is a few codes, its quantizer error the signal's own function
        # at the size of every line (the envelope probe's scene 6487: 4 codes, the lines' phases
        # 2-4x their floor's sigmas off where 12-bit codes of the same frame are within them)
        return [np.sqrt(np.mean(np.abs(zs[f[0], f[1]]) ** 2, axis=0)) for f in fams]
    movers = [i for i, f in enumerate(fams) if f[0]]
    lines = np.concatenate([fams[i][2][~np.asarray(fams[i][4], bool)] for i in movers]) if movers else uniq[:0]
    pos = _copy_positions(spec, np.asarray(frame.tones_hz, dtype=float), fds, lines, uniq, guard)
    if pos.size < COPY_MIN:
        return out
    floor = spec.noise_variances(pos, uniq, guard=guard) * spec.window_power  # (per-sample variance x window)
    excess = _copies_excess(spec.power_at(pos), floor)
    for i in movers:
        own = spec.power_at(fams[i][2]) - s2[i] * spec.window_power
        amp = np.sqrt(np.mean(np.abs(zs[fams[i][0], fams[i][1]]) ** 2, axis=0))
        out[i] = amp * np.sqrt(excess / np.maximum(own, 1e-300))
    return out


#: :attr:`NoiseRing.near`: the rows this many of the spectrum's bins beyond each line's guard, on
#: either side -- near enough that a floor rising toward the line or a neighbour (the pedestal of a
#: strong echo's line a few MHz off) is read at the line's own level, not the ring's median
RING_NEAR_BINS = 32


def _target_rings(spec: Spectrum, fams: list[tuple[int, str, np.ndarray, np.ndarray, np.ndarray]],
                  uniq: np.ndarray, static: bool) -> list[NoiseRing | None]:
    """Each planned target's families' :attr:`LineFamily.ring` (not yet in phase units): its
    usable lines read together (one set of offsets per target, the noise floor's ring), split back
    per family with 0 in unusable lines' columns; the static candidate's only where ``static`` (a
    mover was found on a balanced or IQ receiver), else None."""
    out: list[NoiseRing | None] = [None] * len(fams)
    guard = spec.line_floor_guard()
    # the static candidate's ring only widens its sigma (targets.solve_target): on one photodiode
    # its lines at f_i mix the carrier's phase noise and its conjugate in shares its range sets,
    # tone by tone, so the noise at the line (the Lorentzian core, inside the guard) moves them
    # apart as the ring beyond the guard does not show (a static echo at 24.4 m on one photodiode:
    # range z rms 0.85 -> 1.30, one -5.9; IQ, two static echoes with the LO 1 % of the power: 5.4,
    # the envelope probe's scene 1689); but a mover's pedestal, flat across the static lines a few
    # bins off, moves them together as it moves its own lines
    # (scene 9322: IQ, a 1 MHz laser, a mover 11 dB above a static echo 2 bins off, the static
    # point 6 sigmas off; the ring reads 2.5x the sigma independent lines give). Not on one
    # photodiode, where the static candidate beside strong movers is mostly their beats: its
    # widened sigma made select take movers at its range for its own (the movers probe: 129 more
    # missed targets, echoes at 0-10 dB of loss)
    for t in sorted({f[0] for f in fams} - (set() if static else {0})):
        mine = [i for i, f in enumerate(fams) if f[0] == t]
        good = [~np.asarray(fams[i][4], bool) for i in mine]
        f = np.concatenate([fams[i][2][g] for i, g in zip(mine, good)])
        mirror = np.concatenate([np.asarray(fams[i][3], bool)[g] for i, g in zip(mine, good)])
        if f.size < 2:
            continue
        got = spec.line_rings(f, mirror, uniq, guard, spec.floor_half_width(guard))
        if got is None:
            continue
        rows, shift, offset = got
        near = np.abs(offset) <= guard + RING_NEAR_BINS
        o = 0
        for i, g in zip(mine, good):
            r, sh = np.zeros((rows.shape[0], g.size), complex), np.zeros(g.size)
            r[:, g], sh[g] = rows[:, o:o + int(g.sum())], shift[o:o + int(g.sum())]
            out[i] = NoiseRing(r, sh, near)
            o += int(g.sum())
    return out


def _still_bins(spec: Spectrum, static_hz: np.ndarray, beta: float, x: np.ndarray, strongest: int) -> float | None:
    """:func:`~.spectrum.still_line_doppler_bins`; where the search spectrum is of part of the
    record (``fast``'s, its bins 8x wider), the strongest static line ``static_hz[strongest]`` read
    at the record's own resolution instead: its Kaiser-windowed DFT at whole record bins about it
    (17 exact DFTs over the record; issue 12 case 3's mover in ``fast``)."""
    if spec.record_n is None:
        return still_line_doppler_bins(spec, static_hz, beta)
    n, f0 = x.size, float(abs(static_hz[strongest]))
    k = np.arange(-8, 9)
    p = np.abs(exact_dft(windowed_record(x, ("kaiser", beta)), f0 + k * spec.fs_hz / n, spec.fs_hz)) ** 2
    if abs(int(np.argmax(p)) - 8) > 1:
        return None  # its neighbourhood peaks elsewhere: split lines, a mover beside it
    w = equivalent_width(p)
    return None if w is None else width_doppler_bins(w, beta)


def _self_beats(zs: dict, z_all: np.ndarray, uniq: np.ndarray, dops: list[DopplerEstimate], dc: np.ndarray,
                spec: Spectrum, frame: Frame, settings: ChainSettings, static_hz: np.ndarray, x: np.ndarray,
                static_s2: np.ndarray
                ) -> tuple[np.ndarray, dict[int, np.ndarray], float | None, bool, bool, dict[int, np.ndarray] | None]:
    """One photodiode: each mover's echo also beats with itself, lines at ``f_i`` with no Doppler on
    top of the static target's (issue 12 cases 3 and 5): the found movers' are taken out of
    ``zs[0, "S"]`` (in place; the prediction holds for an unmodulated LO, a modulated reference
    adding its own sidebands to every product). Returned: the movers' predicted self-beats where
    they were taken at scale 1 (:attr:`LineFamily.self_beats`, else None), last; the bound on those
    of movers the search did not find or resolve (:func:`~mtcw_core.dsp.doppler.self_beat_bound`, V, shape (T,)), per
    found mover the static echo's beat on its lines (:func:`cross_beat_bound`), and the largest
    Doppler (record bins) that echo could have where the static lines (``static_hz``) are mostly its
    own (:func:`~.spectrum.still_line_doppler_bins`, the record ``x`` read about the strongest where
    the spectrum is of part of it; None where a mover's self-beat outweighs it there: a still
    self-beat narrows the lines whatever the echo under it does), and whether two movers or more were
    found with the echoes above the LO's power (:attr:`LineFamily.echo_beats`: the prediction with
    the LO the smaller part of the mean left less; the envelope probe's scene 2680, a 0 dB echo 100x
    the LO, and a "mover" at its beat with a 78 dB echo whose LO beat lay under the threshold), and
    whether movers were found and the static lines stood mostly above what their prediction took
    out (:attr:`LineFamily.static_echo`). ``static_s2``: the static lines' noise floors (V^2 per
    sample)."""
    found = [d.fd_hz for d in dops if d.detected]
    cross, still, over_lo, mostly_self, parts = {}, None, False, True, None
    if found:
        # the LO the larger part of the record's mean, or the echoes: whichever prediction leaves
        # less of the static lines (an echo above the LO's power had its self-beat predicted
        # 3-10x too small and 3x the subtracted part left, at 0 dB of loss)
        s = zs[0, "S"]
        left = []
        for lo_larger in (True, False):
            carriers = _carriers(z_all, uniq, found, dc, lo_larger)
            if not lo_larger and not np.all(carriers[1] > 1e-3 * np.abs(dc)):
                continue  # echoes under 0.1 % of the mean: no LO below them (their self-beat is negligible)
            each = _self_beat_parts(zs, *carriers)
            pred = sum(each.values(), np.zeros_like(s))
            scale = self_beat_scale(s, pred)
            rest = s - scale * pred
            left.append((float(np.sum(np.abs(rest) ** 2)), not lo_larger, rest, carriers, pred, scale, each))
        _, lo_smaller, zs[0, "S"], carriers, _, scale, each = min(left, key=lambda t: t[:2])
        parts = each if scale == 1.0 else None
        over_lo = lo_smaller and len(found) >= 2
        # what the prediction may have left, a part of what it took out, where that was the most of
        # the static lines (a static target's own lines outweighing it: left as they are)
        took = np.sqrt(np.mean(np.abs(s - zs[0, "S"]) ** 2, axis=0))
        kept = np.sqrt(np.mean(np.abs(zs[0, "S"]) ** 2, axis=0))
        mostly_self = np.sum(took**2) > np.sum(kept**2)
        taken = SELF_BEAT_LEFT * took if mostly_self else 0.0
        still = None if mostly_self else _still_bins(spec, static_hz, settings.window_beta, x, int(np.argmax(kept)))
        # a static echo beating with the movers is what stands above that leftover (a leftover at
        # a random range is no echo: it had flagged a lone 0 dB mover, right, in half its frames)
        # and above the noise (CROSS_NOISE_SIGMAS of each line's amplitude noise, ``static_s2`` its
        # floor: static lines of noise alone made a lone mover's speed sigma 1.5x its own at 2^16)
        noise = CROSS_NOISE_SIGMAS * np.sqrt(2.0 * static_s2 / frame.n)
        cross = _cross_beats(np.maximum(np.abs(zs[0, "S"]) - taken - noise, 0.0), *carriers)
        beating = [k for k, d in enumerate([d for d in dops if d.detected], start=1) if d.amplitude_p < BEATING_P]
        if beating and np.any(taken):
            # a mover's lines beat (their sizes move across the parts): a static echo may stand
            # under the leftover the prediction may have left; all of it counts there
            whole = _cross_beats(np.maximum(np.abs(zs[0, "S"]) - noise, 0.0), *carriers)
            cross.update({k: whole[k] for k in beating if k in whole})
        taken = np.maximum(taken, _other_root_left(left, lo_smaller, s))
        if len(carriers[0]) < len(found):  # a mover with no carrier modelled: no prediction taken
            taken = taken + np.minimum(_unmodelled_self_beats(zs, x, frame.fs_hz, found, carriers[0], dc, lo_smaller),
                                       np.sqrt(np.mean(np.abs(s) ** 2, axis=0)))
    else:
        taken = 0.0
    return taken + self_beat_bound(spec, frame.tones_hz, fd_max(frame.tones_hz, settings), settings.doppler_min_bins,
                                   found), cross, still, over_lo, bool(found) and not mostly_self, parts


def _unmodelled_self_beats(zs: dict, x: np.ndarray, fs: float, found: list[float],
                           base: list[tuple[int, np.ndarray]], dc: np.ndarray, lo_smaller: bool) -> np.ndarray:
    """The self-beat (V, shape (T,)) of the found movers whose carrier line was not modelled (within
    its clearance of 0 Hz: :func:`_carriers`' ``base`` has none for them), which no prediction took
    out: for each, :func:`_self_beat_parts`' size ``(|U_i| + |L_i|)*|B|/(2*A_L^2)`` (rms over the
    segments; twice the one sideband where the other is unusable), its carrier ``|B|`` read from the
    whole record's exact DFT at ``|f_d|`` less the record mean's leak (``2|X|/N``), times
    :data:`UNMODELLED_CARRIER_MARGIN` (the line's own image 2-3 bins off, the other lines near 0 Hz:
    0.87-1.08 of it at 1.2 bins), and ``A_L^2`` the root of :func:`_carriers` with every carrier's
    power in the mean (the one the prediction took: ``lo_smaller``). The envelope probe's scene
    34883: a lone echo at 9 dB of loss 1.2 bins up on one photodiode, its self-beat 6 dB under its
    LO-beat lines left whole on the static lines -- a static point at its range, unflagged."""
    have = {k for k, _ in base}
    lost = [(k, abs(fd)) for k, fd in enumerate(found, start=1) if k not in have and (k, "U") in zs]
    out = np.zeros(zs[0, "S"].shape[1])
    if not lost:
        return out
    f = np.array([fd for _, fd in lost])
    b = 2.0 / x.size * np.abs(exact_dft(x, f, fs) - mean_leak(x, f, fs))
    mean = float(np.mean(dc))
    echo_dc = float(np.mean(sum((np.abs(c) ** 2 for _, c in base), np.zeros(1)))) + float(np.sum(b**2))
    lo_power = max(float(_lo_power(mean, echo_dc, not lo_smaller)), 1e-300)
    for (k, _), bk in zip(lost, b):
        u, low = (np.sqrt(np.mean(np.abs(zs[k, side]) ** 2, axis=0)) for side in ("U", "L"))
        sides = np.where((u > 0) & (low > 0), u + low, 2.0 * (u + low))
        out += UNMODELLED_CARRIER_MARGIN * sides * bk / (2.0 * lo_power)
    return out


#: :func:`_unmodelled_self_beats` takes a carrier read from the whole record this many times its size
UNMODELLED_CARRIER_MARGIN = 1.5


def _other_root_left(left: list[tuple], lo_smaller: bool, s: np.ndarray) -> np.ndarray | float:
    """What an echo stronger than the LO may have left on the static lines ``s`` (S, T) where the
    prediction taken was the LO-larger one (:func:`_self_beats`' ``left``): the other root's
    predicted self-beat, per tone (V, shape (T,)), where it is admissible -- no larger than
    :data:`OTHER_ROOT_EXCLUDES` times the static lines, all tones together -- else 0.

    The record's mean and a mover's carrier line fit either root of :func:`_carriers`; the LO-larger
    one wins where its prediction leaves less of the static lines, which it also does where it
    takes out nothing: where the echo is the stronger and its predicted self-beat, the size of the
    static lines, misses their phases -- a second echo near the LO's power beats with the mover as a
    second LO and turns the mover's lines the prediction is made of --, those lines are then that
    self-beat, unexplained, not a static echo's (the envelope probe's scene 3359: a mover 64x the
    LO's power beside a static echo at 0.6x, its self-beat predicted at 0.7-2x the static lines'
    size 0.2-1.3 rad off their phases; the static point 2400 sigmas off, unflagged)."""
    if lo_smaller:
        return 0.0
    pred = next((t[4] for t in left if t[1]), None)
    if pred is None or np.sum(np.abs(pred) ** 2) > OTHER_ROOT_EXCLUDES**2 * np.sum(np.abs(s) ** 2):
        return 0.0
    return np.sqrt(np.mean(np.abs(pred) ** 2, axis=0))


#: the echo-larger root's self-beat is no reading of the static lines where it would be this many
#: times their size (all tones together): another echo would have to cancel most of it at every tone
OTHER_ROOT_EXCLUDES = 3.0


#: a static line counts toward a static echo's beat with the movers (:func:`cross_beat_bound`) by
#: what it stands above this many of its amplitude noise's sigmas (a line of noise alone exceeds 3
#: sigmas with odds ~1 %)
CROSS_NOISE_SIGMAS = 3.0


#: the part of a mover's self-beat its prediction may leave on the static lines (the strong-echo
#: cases: 0.02-3 % of what it takes out, the most under a 1 MHz laser whose pedestal the LO beats
#: lose and the self-beat does not); stated with the unexplained self-beats' bound where what was
#: taken out outweighs what is left, so a static point whose lines were mostly a mover's self-beat
#: is flagged ``blended`` (the envelope probe's scene 1749: a 3 dB echo's self-beat 50 dB above a
#: static target's lines, 1 % of it left and ranged, 323 sigmas off). Not where the static lines
#: are mostly a static target's own (issue 12 case 3: 9x what was taken, 80 dB over the noise,
#: right within its sigma: 3 % of the taken part would have flagged every frame)
SELF_BEAT_LEFT = 0.03
#: ... but counts toward a static echo's beat with a mover (:func:`cross_beat_bound`) where that
#: mover's lines' sizes scatter across the phase advance's parts beyond what white noise does with
#: odds below this (``DopplerEstimate.amplitude_p``): a beat is then on them, and the static lines
#: left under that leftover may be its echo (the envelope probe's scene 14739: a mover at 4 dB of
#: loss on an 8-bit ADC and a static echo 33 dB under it, wholly under the leftover: the mover's
#: speed 7 sigmas off at a stated 11 Hz; its lines' size chi2 27-120 per degree of freedom, a lone
#: mover's 0.9-1.7)
BEATING_P = 1e-4


#: the static lines' envelope is taken as varying when the segments' amplitudes less their mean
#: hold a rank-1 part this many times the largest a pure-noise matrix of that shape holds
#: (``(sqrt(S-1) + sqrt(2T))^2`` in units of the segment noise, the Marchenko-Pastur edge) ...
FADING_VARIATION_EDGES = 2.0
#: ... and the whole rank-1 part is this many times the edge of an (S, 2T) noise matrix: below
#: that the free envelope follows the noise and raises the lines' power with it (a pure-noise
#: frame at -6 dB line SNR came out 'ok' with an unflagged wrong range)
FADING_SIGNAL_EDGES = 6.0
#: segments of the envelope fit: enough that the guard's Doppler turns a segment's carrier by at
#: most a quarter cycle, within these bounds
FADING_SEGMENTS = (8, 64)
#: the fit's lines must lie this many segment bins apart (and from 0 Hz) for the segment fits to
#: separate them, and a segment must hold this many samples
FADING_MIN_SEPARATION_BINS, FADING_MIN_LENGTH = 3.0, 256


def fading_segments(n: int, fs: float, uniq: np.ndarray, guard_hz: float) -> int | None:
    """The segments :func:`fading_lines` cuts an ``n``-sample record into (enough that the
    guard's Doppler turns a segment's carrier by at most a quarter cycle, within
    :data:`FADING_SEGMENTS`), or None where the record cannot be cut that fine: fewer than 2
    segments of :data:`FADING_MIN_LENGTH` samples, or lines (``uniq``, Hz, sorted) closer than
    :data:`FADING_MIN_SEPARATION_BINS` segment bins to each other or to 0 Hz."""
    want = 4.0 * guard_hz * n / fs  # segments for a quarter cycle of the guard's envelope in each
    segs = int(2 ** math.ceil(math.log2(max(want, FADING_SEGMENTS[0]))))
    segs = min(segs, FADING_SEGMENTS[1], n // FADING_MIN_LENGTH)
    if segs < 2 or uniq.size < 2:
        return None
    gaps = np.diff(np.concatenate([[0.0], uniq]))
    return None if np.min(gaps) < FADING_MIN_SEPARATION_BINS * fs / (n // segs) else segs


def _whole_record_dfts(x: np.ndarray, fs: float, uniq: np.ndarray, spec: Spectrum, guard_hz: float | None,
                       parts: bool = False
                       ) -> tuple[np.ndarray | None, float | None, np.ndarray | None, np.ndarray | None]:
    """What the whole-record fit needs, in as few passes as the record allows: its DFTs at ``uniq``
    (Hz), its sum (a real record's DC projection; None for IQ) and, where its static lines may fade
    (``guard_hz``: the largest Doppler the search could have missed, None when fading is not
    fitted), the segments' DFTs and sums for :func:`fading_lines` -- for IQ, the two halves' DFTs
    for :func:`subbin_leak_bound` (no sums), and for a real record with ``parts`` (movers found)
    its :data:`ENVELOPE_PARTS` parts' for :func:`envelope_leak_bound` -- from the same pass as the
    whole record's.

    The whole record's DFTs then come from the envelope fit's segments (one pass for both), at
    0 Hz too: the record's sum and its segments' from the same pass. Otherwise the DFTs are left to
    :func:`~.tones.fit_lines` and the sum is the search spectrum's when it transformed the whole
    record (the same sum of the same array), else one pass.

    Returns
    -------
    whole : ndarray, shape (K,), complex, or None; total : float or None;
    seg_dft : ndarray, shape (S, K), complex, or None; seg_sums : ndarray, shape (S,), or None
    """
    n, iq = x.size, np.iscomplexobj(x)
    if iq and guard_hz:
        whole, halves = exact_dft_tiled(x, 2, uniq, fs)
        return whole, None, halves, None
    segs = ((ENVELOPE_PARTS if parts else fading_segments(n, fs, uniq, guard_hz))
            if guard_hz is not None and not iq else None)
    if segs:
        whole, each = exact_dft_tiled(x, segs, np.concatenate([[0.0], uniq]), fs)
        return whole[1:], float(whole[0].real), each[:, 1:], each[:, 0].real
    total = None if iq else (spec.total if spec.total is not None and spec.n == n and not spec.complex_input
                             else float(np.sum(x)))
    return None, total, None, None


def fading_lines(x: np.ndarray, fs: float, uniq: np.ndarray, s_idx: np.ndarray, s2: np.ndarray,
                 guard_hz: float, seg_dft: np.ndarray | None = None, seg_sums: np.ndarray | None = None,
                 segments: tuple | None = None) -> np.ndarray | None:
    """The static lines' whole-record amplitudes with a fading envelope taken out, or None.

    A real detector sees a target's LO beats at tone ``f_i`` as ``A_i*a(t)*cos(2*pi*f_i*t +
    theta_i)`` with ``a(t) = 2*cos(Phi(t))``, ``Phi`` the carrier phase between echo and LO: one
    real envelope shared by every tone. For a static target with a coherent laser ``a`` is constant
    and the whole-record fit at ``f_i`` is efficient. A mover whose Doppler ``f_d`` lies below the
    search's guard puts ``a(t) = 2*cos(2*pi*f_d*t + Phi_0)`` on the same lines: the whole-record fit
    then keeps ``|mean a|``, which a half-bin Doppler brings near 0 in some frames (the phases'
    variance grows as ``1/cos^2(Phi_0)``), though the lines carry all their power. Here the record
    is cut into S segments, the lines fitted on each (referred to the record's centre: ``Z``,
    shape (S, T)), and ``Z = a c^T`` fitted with ``a`` real (the leading singular pair of
    ``[Re Z, Im Z]``, each line whitened by its floor): ``c_i = mean_s a_s*Z_si`` with ``mean a^2 =
    1`` keeps every segment's power, ``|c_i|^2 = mean_s |Z_si|^2``, and its noise is the
    whole-record fit's, so the phases' variance ``2*s2/(N*|c|^2)`` holds as the chain states it.
    The envelope's sign is common to all tones (it cancels in the pair phases).

    Taken only where the data ask for it and can carry it: the whitened amplitudes less their mean
    over the segments must hold a rank-1 part well above what noise alone puts there
    (:data:`FADING_VARIATION_EDGES`), and the lines must be strong enough that the free envelope
    follows them, not the noise (:data:`FADING_SIGNAL_EDGES`: 19-21 dB per line for 3-6 tones on
    16-64 segments). Weaker lines take the sinusoidal envelope of a mover below one record bin
    (:func:`_sine_envelope`: two parameters, so it reaches ~10 dB a line) where it stands out of
    the constant one, else keep the whole-record fit.

    Parameters
    ----------
    x : ndarray, shape (N,), float64, V (a real record)
    fs : sample rate (Hz)
    uniq : ndarray, shape (K,), every fitted frequency (Hz), sorted
    s_idx : ndarray of int, shape (T,), the static lines' columns in ``uniq``
    s2 : ndarray, shape (T,), each static line's noise variance per sample (V^2, local floor)
    guard_hz : the largest Doppler the search could have missed (Hz)
    seg_dft : ndarray, shape (S, K), complex, optional: the segments' DFTs of ``uniq`` if already
        taken (:func:`~.tones.exact_dft_tiled` with :func:`fading_segments`' count, which ``S`` is then)
    seg_sums : ndarray, shape (S,), optional: the segments' sums (V) if already taken (the same
        pass at 0 Hz)
    segments : :func:`static_segments`' of the record, if already read

    Returns
    -------
    ndarray, shape (T,), complex (V, phase at the record's centre), or None where the envelope is
    constant within the noise or the record cannot be cut fine enough
    """
    seg = segments or static_segments(x, fs, uniq, s_idx, guard_hz, seg_dft, seg_sums)
    if seg is None or not np.all(s2 > 0):
        return None
    z, turn, dc = seg
    segs, length = z.shape[0], x.size // z.shape[0]
    m = _whitened(z, s2, length)
    cols = m.shape[1]
    varying = np.linalg.svd(m - m.mean(axis=0), compute_uv=False)[0] ** 2
    a = None
    if varying > FADING_VARIATION_EDGES * (math.sqrt(segs - 1) + math.sqrt(cols)) ** 2:
        u, sv, _ = np.linalg.svd(m, full_matrices=False)
        if sv[0] ** 2 > FADING_SIGNAL_EDGES * (math.sqrt(segs) + math.sqrt(cols)) ** 2:
            a = u[:, 0] * math.sqrt(segs)
    if a is None:
        a = _sine_envelope(m, guard_hz * x.size / fs)
    if a is None:
        return None
    if np.sum(a) < 0:
        a = -a
    if segs >= 3:  # the ramps from second-order differences across the segments
        z = z - ramp_leak(dc, z, turn, length, uniq, s_idx, fs) * turn
    return (a @ z) / segs


def static_segments(x: np.ndarray, fs: float, uniq: np.ndarray, s_idx: np.ndarray, guard_hz: float,
                    seg_dft: np.ndarray | None = None, seg_sums: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The static lines fitted on each of :func:`fading_segments`' segments (or ``seg_dft``'s),
    referred to the record's centre: ``z`` (S, T) complex (V), what turned them there from each
    segment's centre (S, T) and each segment's mean (S,) (V); None where the record cannot be cut
    or holds fewer than two lines (parameters: :func:`fading_lines`). Read once for
    :func:`fading_lines` and :func:`envelope_rank_chi2` (their ``segments``)."""
    n = x.size
    segs = seg_dft.shape[0] if seg_dft is not None else fading_segments(n, fs, uniq, guard_hz)
    if segs is None or s_idx.size < 2:
        return None
    length = n // segs
    starts = np.arange(segs) * length
    z = fit_lines_segments(x, starts, length, uniq, fs, seg_dft, seg_sums)[:, s_idx]  # (S, T), about each segment's centre
    turn = centre_turn(segs, length, n, uniq[s_idx], fs)  # about the record's centre
    dc = seg_sums / length if seg_sums is not None else x[:segs * length].reshape(segs, length).mean(axis=1)
    return z * turn, turn, dc


#: :func:`envelope_rank_chi2` allows each line's segments this much (relative, complex) beyond
#: their noise: what the one-echo model leaves at high SNR -- the fade's leaks past the slope and
#: bend :func:`ramp_leak` takes out (the envelope probe's scene 56: one echo fading 0.77 record bins
#: on a balanced receiver, 62 dB a segment, its 20 MHz line 0.2 % off the envelope, residual 188 on
#: 77 degrees of freedom)
ENVELOPE_TOLERANCE = 0.01


def envelope_rank_chi2(x: np.ndarray, fs: float, uniq: np.ndarray, s_idx: np.ndarray, s2: np.ndarray,
                       guard_hz: float, seg_dft: np.ndarray | None = None, seg_sums: np.ndarray | None = None,
                       segments: tuple | None = None) -> tuple[float, int]:
    """The static lines across the record against one echo's: chi2 and degrees of freedom of the
    best fit ``a_s * c_i`` with ``a`` real (one envelope, every tone), (0, 0) where not read.

    One still echo, or one moving below a record bin, puts ``A_i*a(t)*cos(2*pi*f_i*t + theta_i)``
    on a real record whatever else its carrier does (:func:`fading_lines`: ``a = 2*cos(Phi(t))``,
    the laser's phase noise and a sub-bin Doppler in ``Phi``; the echo's own intensity at the tones
    adds a constant to ``a``, its RIN a common factor): its lines' segments, real and imaginary
    parts side by side and whitened, form a matrix of rank one. Two echoes whose envelopes differ
    (two movers under one record bin, a still echo beside one) add a second rank wherever their
    lines differ -- in range, in size -- though the whole-record lines may fit one range between
    theirs: the envelope probe's scene 20925, two echoes 1 cm apart moving 0.67 and -0.32 record
    bins on six tones, ranged 7-18 sigmas off, residual 280-1470 on 77 degrees of freedom. The
    residual is the sum of the squared singular values after the first (the ramps the carrier's
    fade leaks into each segment's fit taken out first, :func:`ramp_leak`); with the rank-one part
    well above the noise it is chi2 with ``(S - 1)*(2T - 1)`` degrees of freedom, and below, where the
    first singular pair takes the largest noise direction too, it reads low (no flag from noise).
    Each line's noise is widened by :data:`ENVELOPE_TOLERANCE` of its size: where that exceeds the
    noise (lines above ~43 dB a segment) the residual reads below its degrees of freedom and only a
    second rank above ~1 % of the lines shows. What is not one real envelope and not a second echo
    would read as one too: quantizer products under half an LSB of noise, a front end's
    nonlinearity, a clock offset between synthesizer and digitizer (a phase ramp in ``f_i`` across
    the segments); and a partly coherent laser's pedestal (the 0 Hz carrier beat's, which each
    segment's fit gathers through its sidelobes, most where the envelope crosses zero, and the
    record's floor does not show; the target stage reads the test only where the declared laser
    keeps the carrier one line,
    :data:`~mtcw_core.ranging.targets.ENVELOPE_MIN_COHERENCE`).

    Parameters: :func:`fading_lines`' (``segments``: :func:`static_segments`' of the record, if read).
    """
    seg = segments or static_segments(x, fs, uniq, s_idx, guard_hz, seg_dft, seg_sums)
    if seg is None or not np.all(s2 > 0):
        return 0.0, 0
    z, turn, dc = seg
    length = x.size // z.shape[0]
    if z.shape[0] >= 3:
        z = z - ramp_leak(dc, z, turn, length, uniq, s_idx, fs) * turn
    # each real component's noise per segment, and the model's own tolerance on a line's segments
    sd = np.sqrt(2.0 * s2 / length)
    sd = np.sqrt(sd**2 + (ENVELOPE_TOLERANCE**2 / 2) * np.mean(np.abs(z) ** 2, axis=0))
    m = np.concatenate([z.real / sd, z.imag / sd], axis=1)  # (S, 2T), unit variance per entry
    sv = np.linalg.svd(m, compute_uv=False)
    return float(np.sum(sv[1:] ** 2)), (m.shape[0] - 1) * (m.shape[1] - 1)


def ramp_leak(dc: np.ndarray, z: np.ndarray, turn: np.ndarray, length: int, uniq: np.ndarray, s_idx: np.ndarray,
              fs: float) -> np.ndarray:
    """What the fading's change within each segment puts into the static lines' segment fits (V,
    about each segment's centre), shape (S, T).

    Each segment's fit holds a line's mean amplitude, not its slope (three segments at least: the
    slopes are second-order differences). A ramp of amplitude projects
    on a line ``k`` segment bins away by ~``1/(pi*k)`` of its change across the segment, and a real
    line's ramp on itself through its image at ``-f`` by ~``1/(4*pi*k)``. The baseband carrier
    beat of a mover below the guard is the envelope itself at 0 Hz, tens of dB above the
    sidebands: on the 6-tone plan's 20 MHz line (16 segment bins) its ramp turned the phase by 3e-4
    rad, 6 of its sigmas at 1.6 dB of echo loss (the envelope probe's scene 574: a 1.5 mm/s mover
    ranged 5.8 sigmas off on average); a faster fade bends it within the segment too (slope and
    bend are modelled, not the higher orders: a fade of 1.5 record bins under a carrier 40 dB above
    the lines keeps ~1/30 of the leak). The slopes
    are the segments' gradients over their length -- the means' for the carrier (the LO's DC is
    constant; its bend their second difference), the static lines' own complex amplitudes
    for theirs, across the segments about the record's centre (about their own, a line's phase
    turns from segment to segment) -- and the projections the fit's own responses to unit ramps
    (:func:`_ramp_responses`).

    Parameters
    ----------
    dc : ndarray, shape (S,), each segment's mean (V)
    z : ndarray, shape (S, T), complex, the static lines' segment amplitudes (V, about the record's
        centre)
    turn : ndarray, shape (S, T), complex, what turned them there from each segment's centre
        (:func:`~.tones.centre_turn`)
    length : samples per segment; uniq, s_idx, fs: the fit's lines (Hz), the static ones' columns
    """
    r0, r2, rc, rs = _ramp_responses(length, fs, np.asarray(uniq, np.float64).tobytes(),
                                     np.asarray(s_idx, np.int64).tobytes())
    dz = np.gradient(z, axis=0, edge_order=2) / length / turn  # each line's change per sample, (S, T)
    slope = np.gradient(dc, edge_order=2) / length
    bend = np.gradient(slope, edge_order=2) / length / 2  # the carrier's curvature: its u^2 coefficient
    return slope[:, None] * r0[None, :] + bend[:, None] * r2[None, :] + dz.real @ rc + dz.imag @ rs


@lru_cache(maxsize=8)
def _ramp_responses(length: int, fs: float, uniq_bytes: bytes, s_bytes: bytes
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The static lines' segment fits (:func:`~.tones.fit_lines`, columns ``s_idx``) of a unit ramp
    ``u`` and a unit bend ``u^2`` at 0 Hz, shape (T,) each, and of each static line's unit ramps
    ``u*cos(w*u)`` and ``-u*sin(w*u)`` (the real and imaginary parts of ``u*exp(j*w*u)``), shape
    (T, T) each, ``u`` the sample offset from the segment's centre. Cached: a stream's frames share
    them."""
    uniq, s_idx = np.frombuffer(uniq_bytes), np.frombuffer(s_bytes, dtype=np.int64)
    u = np.arange(length) - (length - 1) / 2.0
    r0 = fit_lines(u, uniq, fs)[s_idx]
    r2 = fit_lines(u**2, uniq, fs)[s_idx]  # the DC column takes its mean
    w = 2 * np.pi * np.mod(np.outer(uniq[s_idx], u) / fs, 1.0)  # (T, L), cycles reduced in float64
    rc = np.array([fit_lines(u * np.cos(row), uniq, fs)[s_idx] for row in w])
    rs = np.array([fit_lines(-u * np.sin(row), uniq, fs)[s_idx] for row in w])
    for arr in (r0, r2, rc, rs):
        arr.setflags(write=False)  # shared by every caller through the cache
    return r0, r2, rc, rs


#: the sinusoidal envelope (:func:`_sine_envelope`): its Doppler scanned from this many record bins
#: (a slower one is the constant envelope of the whole-record fit) ...
FADING_SINE_MIN_BINS = 0.2
#: ... up to the guard, at most this many, in steps of this many
FADING_SINE_MAX_BINS, FADING_SINE_STEP_BINS = 1.5, 0.05
#: it is taken when its energy (whitened) exceeds the constant envelope's by this much ...
FADING_SINE_GAIN = 30.0
#: ... and is at least this much in all
FADING_SINE_SIGNAL = 40.0


def _whitened(z: np.ndarray, s2: np.ndarray, length: int) -> np.ndarray:
    """The segments' lines ``z`` (S, T) as real and imaginary parts in units of their noise
    (``s2``: each line's noise variance per sample, V^2; ``length``: samples a segment), (S, 2T)."""
    sd = np.sqrt(2.0 * s2 / length)  # each real component's noise std per segment (V)
    return np.concatenate([z.real / sd, z.imag / sd], axis=1)


def _trial_envelopes(segs: int, fds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``cos`` and ``sin`` of each trial Doppler ``fds`` (F,) (record bins) at the ``segs`` segments'
    centres (in records about the record's centre), each (F, S)."""
    arg = 2 * np.pi * np.outer(fds, (np.arange(segs) + 0.5) / segs - 0.5)
    return np.cos(arg), np.sin(arg)


def _sine_energies(m: np.ndarray, fds: np.ndarray) -> tuple[np.ndarray, tuple, tuple, tuple]:
    """The best rank-1 energy of ``m`` (S, 2T, whitened) whose envelope lies in span{cos, sin} at
    each trial Doppler ``fds`` (F,) (record bins) over the segments' centres: ``lam`` (F,), with
    the basis (F, S) each, its Gram and the projections' Gram ((F,) each) for the eigenvectors."""
    c, s = _trial_envelopes(m.shape[0], fds)  # (F, S)
    pc, ps = c @ m, s @ m  # (F, 2T)
    # the largest root of det(H - lam*G) = 0 (H: the projections' Gram, G: the basis'): the best
    # rank-1 energy in span{cos, sin}, every trial at once (a 2x2 generalised eigenproblem)
    g11, g12, g22 = np.sum(c * c, axis=1), np.sum(c * s, axis=1), np.sum(s * s, axis=1)
    h11, h12, h22 = np.sum(pc * pc, axis=1), np.sum(pc * ps, axis=1), np.sum(ps * ps, axis=1)
    qa = g11 * g22 - g12**2
    qb = -(h11 * g22 + h22 * g11 - 2 * h12 * g12)
    qc = h11 * h22 - h12**2
    lam = (-qb + np.sqrt(np.maximum(qb**2 - 4 * qa * qc, 0.0))) / (2 * np.maximum(qa, 1e-300))
    return lam, (c, s), (g11, g12, g22), (h11, h12, h22)


#: a static point's speed is claimed only where its lines' envelope is slow: where more than this
#: part of their free rank-1 energy (:func:`fading_lines`) is beyond what an envelope no faster than
#: the static claim's sigma explains (a constant plus one sinusoid up to it: the echo's own
#: intensity and a mover below it), the carrier turns faster than that claim allows -- a mover
#: whose Doppler lines stayed under the search's threshold while the segments gathered its
#: sidebands (the envelope probe's scene 41777: 873 kHz, 11 record bins, read as an envelope fading
#: over 8 segments; 0.84 of the energy beyond in its first frame). A laser incoherent at the echo's
#: delay fades the lines randomly, by 0.06-0.8 of that energy for a carrier phase wandering 20-80
#: rad over the record: above this part such a static target's speed is reported unknown too (it
#: cannot be told from a mover there)
FAST_FADE_PART = 0.5


def _slow_energies(m: np.ndarray, fds: np.ndarray) -> np.ndarray:
    """The best rank-1 energy of ``m`` (S, 2T, whitened) whose envelope lies in span{1, cos, sin}
    at each trial Doppler ``fds`` (F,) (record bins) over the segments' centres: shape (F,)."""
    c, s = _trial_envelopes(m.shape[0], fds)
    basis = np.stack([np.ones_like(c), c, s], axis=2)  # (F, S, 3)
    q, _ = np.linalg.qr(basis)  # an orthonormal basis of each span
    proj = np.swapaxes(q, 1, 2) @ m  # (F, 3, 2T)
    return np.linalg.eigvalsh(proj @ np.swapaxes(proj, 1, 2))[:, -1]


def fast_fade(z: np.ndarray, s2: np.ndarray, length: int, guard_bins: float) -> float:
    """The part of the static lines' envelope energy that no envelope within the guard explains.

    ``z`` (S, T): the static lines on each segment (:func:`static_segments`); ``s2`` (T,): their
    noise variance per sample (V^2); ``length``: samples a segment; ``guard_bins``: the largest
    Doppler the static claim's sigma covers (``DopplerEstimate.min_detectable_hz``), in record
    bins. The free rank-1 energy (the leading singular value squared of the whitened lines,
    :func:`fading_lines`) less the best with an envelope in span{1, cos, sin} at a Doppler up to
    the guard (:func:`_slow_energies`), as a part of the free energy; 0 where that excess stays
    within what noise puts there (:data:`FADING_VARIATION_EDGES` times the largest a pure-noise
    matrix of ``S - 3`` rows holds, as :func:`fading_lines` reads a varying envelope) or the
    segments cannot show an envelope beyond the guard (fewer than 6 of them, or a guard within a
    record bin of their Nyquist).
    """
    segs = z.shape[0]
    if segs < 6 or guard_bins + 1 > segs / 2 or not np.all(s2 > 0):
        return 0.0
    m = _whitened(z, s2, length)
    free = float(np.linalg.svd(m, compute_uv=False)[0] ** 2)
    fds = np.arange(FADING_SINE_STEP_BINS, max(guard_bins, FADING_SINE_STEP_BINS) + 1e-9, FADING_SINE_STEP_BINS)
    excess = free - float(np.max(_slow_energies(m, fds)))
    if excess <= FADING_VARIATION_EDGES * (math.sqrt(segs - 3) + math.sqrt(m.shape[1])) ** 2:
        return 0.0
    return excess / free


def _sine_envelope(m: np.ndarray, guard_bins: float) -> np.ndarray | None:
    """A mover below one record bin: the envelope ``a_s = 2*cos(2*pi*f_d*t_s + Phi_0)`` its carrier
    puts on the static lines, fitted with two parameters instead of one per segment.

    ``m`` (S, 2T): the segments' lines, real and imaginary parts, whitened. For each trial
    ``f_d`` from :data:`FADING_SINE_MIN_BINS` record bins up to the guard (``guard_bins``, at most
    :data:`FADING_SINE_MAX_BINS`) the best rank-1 ``a b^T`` with ``a`` in the span of ``cos`` and
    ``sin`` at ``f_d`` over the segments' centres; taken where its energy exceeds the constant
    envelope's (the whole-record fit) by :data:`FADING_SINE_GAIN` and reaches
    :data:`FADING_SINE_SIGNAL`. Returns ``a`` (S,), ``mean a^2 = 1``, or None."""
    segs = m.shape[0]
    e0 = segs * float(np.sum(m.mean(axis=0) ** 2))
    fds = np.arange(FADING_SINE_MIN_BINS, min(guard_bins, FADING_SINE_MAX_BINS) + 1e-9, FADING_SINE_STEP_BINS)
    if not fds.size:
        return None
    lam, (c, s), (g11, g12, g22), (h11, h12, h22) = _sine_energies(m, fds)
    k = int(np.argmax(lam))
    best = float(lam[k])
    if best < FADING_SINE_SIGNAL or best - e0 < FADING_SINE_GAIN:
        return None
    # its eigenvector (the cos and sin weights) from the better-conditioned row of (H - lam*G) v = 0
    r1 = np.array([h12[k] - best * g12[k], -(h11[k] - best * g11[k])])
    r2 = np.array([h22[k] - best * g22[k], -(h12[k] - best * g12[k])])
    v = r1 if np.linalg.norm(r1) >= np.linalg.norm(r2) else r2
    a = v[0] * c[k] + v[1] * s[k]
    return a * math.sqrt(segs) / float(np.linalg.norm(a))


#: a fitted self-beat scale is taken when it leaves this part of the static lines' power at scale 1
SELF_BEAT_FIT_GAIN = 0.1


def self_beat_scale(s_lines: np.ndarray, pred: np.ndarray) -> float:
    """How much of the predicted self-beat ``pred`` to take from the static lines ``s_lines``: 1,
    or more where the carrier's coherence explains the rest.

    The prediction rests on a mover's LO beats, each of which carries the laser's phase noise over
    the echo's delay: their fitted amplitudes keep ``exp(-pi*linewidth*|dtau|)`` of the line, the
    self-beat (the echo with itself) all of it. So the prediction is low by ``1/coherence``, up to
    ``1/``:data:`~mtcw_core.dsp.doppler.MIN_CARRIER_COHERENCE` for a mover whose Doppler line was
    found at all. The scale is fitted (least squares, real, clipped to that interval) and taken
    only when the static lines are then mostly the self-beat: what is left of them at scale 1 falls
    by :data:`SELF_BEAT_FIT_GAIN` or more. A static target beside the mover keeps the scale 1 (a
    fitted scale would take part of its lines with it).

    Parameters
    ----------
    s_lines, pred : ndarray, shape (S, T), complex, V: the static lines and the prediction
    """
    den = float(np.sum(np.abs(pred) ** 2))
    if den <= 0:
        return 1.0
    fit = float(np.clip(np.sum((s_lines * np.conj(pred)).real) / den, 1.0, 1.0 / MIN_CARRIER_COHERENCE))
    left = float(np.sum(np.abs(s_lines - fit * pred) ** 2))
    return fit if left <= SELF_BEAT_FIT_GAIN * float(np.sum(np.abs(s_lines - pred) ** 2)) else 1.0


def self_beat_lines(zs: dict, z_all: np.ndarray, uniq: np.ndarray, fds: list[float], dc: np.ndarray,
                    lo_larger: bool = True) -> np.ndarray:
    """The movers' self-beat lines at the tones ``f_i``, predicted from their LO-beat lines.

    With an unmodulated LO ``A_L`` and a mover's echo field ``A_m * M(t - tau) * exp(j*Phi(t))``
    (``M = a_0 + sum_i a_i cos(...)``), a square-law detector sees the baseband line
    ``B = 2*A_L*A_m*a_0*exp(j*Phi)``, the sidebands ``U_i = A_L*A_m*a_i*exp(j*(theta_i + Phi))``
    and ``L_i = A_L*A_m*a_i*exp(j*(theta_i - Phi))`` (as this module orients them), and the echo's
    own beat at ``f_i``: ``2*A_m^2*a_0*a_i*exp(j*theta_i) = U_i*conj(B)/A_L^2 = L_i*B/A_L^2``. The
    carrier phase ``Phi`` (Doppler, laser phase noise) cancels; ``A_L^2`` is the record's DC less
    the echoes' own DC (``|B|^2/(4*A_L^2)`` each). Amplitudes are ``fit_lines``'s (cosine
    amplitudes, V), per segment.

    Parameters
    ----------
    zs : {(target, family name): ndarray (S, T)} the lines as extracted
    z_all, uniq : every fitted amplitude (S, K) and its frequency (K,), Hz
    fds : the Doppler lines found (Hz), target k = index + 1
    dc : ndarray, shape (S,), the mean of each segment (V)
    lo_larger : the LO the larger part of the mean (:func:`_carriers`; else the echoes)

    Returns
    -------
    ndarray, shape (S, T): the predicted lines (0 where a mover's baseband line was not fitted)
    """
    return _predicted_self_beats(zs, *_carriers(z_all, uniq, fds, dc, lo_larger))


def _predicted_self_beats(zs: dict, base: list[tuple[int, np.ndarray]], lo_power: np.ndarray) -> np.ndarray:
    """:func:`self_beat_lines` from the movers' carrier lines and the LO's power (:func:`_carriers`)."""
    return sum(_self_beat_parts(zs, base, lo_power).values(), np.zeros_like(zs[0, "S"]))


def _self_beat_parts(zs: dict, base: list[tuple[int, np.ndarray]], lo_power: np.ndarray) -> dict[int, np.ndarray]:
    """Each mover's term of :func:`_predicted_self_beats` (V, shape (S, T)), by target."""
    out = {}
    for k, b in base:
        if (k, "U") not in zs:
            continue
        u, low = zs[k, "U"], zs[k, "L"]
        have = (np.abs(u) > 0) & (np.abs(low) > 0)
        pred = np.where(have, 0.5 * (u * np.conj(b)[:, None] + low * b[:, None]), np.where(
            np.abs(u) > 0, u * np.conj(b)[:, None], low * b[:, None]))
        out[k] = pred / np.maximum(lo_power, 1e-300)[:, None]
    return out


def _carriers(z_all: np.ndarray, uniq: np.ndarray, fds: list[float], dc: np.ndarray, lo_larger: bool = True
              ) -> tuple[list[tuple[int, np.ndarray]], np.ndarray]:
    """Each found mover's baseband (carrier) line per segment where it was fitted, as (target,
    ndarray (S,)), and the LO's part of the record's mean, ``A_L^2`` (V, shape (S,)): the DC less
    the echoes' own (``|B|^2/(4*A_L^2)`` each), a root of ``A_L^4 - DC*A_L^2 + sum|B|^2/4``: the
    larger (``lo_larger``, the LO the stronger) or the smaller (an echo stronger than the LO: the
    mean and the carrier lines alone cannot tell which)."""
    base = []
    for k, fd in enumerate(fds, start=1):
        i = int(np.argmin(np.abs(uniq - abs(fd))))
        if abs(uniq[i] - abs(fd)) < 1e-3:
            base.append((k, z_all[:, i]))
    echo_dc = sum(np.abs(b) ** 2 for _, b in base) if base else 0.0
    return base, _lo_power(dc, echo_dc, lo_larger)


def _lo_power(dc, echo_dc, lo_larger: bool):
    """``A_L^2`` from the record's mean ``dc`` and the echoes' carrier powers ``echo_dc = sum|B|^2``
    (V^2; arrays per segment or floats): the larger or the smaller root of
    ``A_L^4 - DC*A_L^2 + echo_dc/4`` (:func:`_carriers`)."""
    root = np.sqrt(np.maximum(dc**2 - echo_dc, 0.0))
    return 0.5 * (dc + root if lo_larger else dc - root)


def _leak_bounds(x: np.ndarray, fs: float, uniq: np.ndarray, z: np.ndarray,
                 fams: list[tuple[int, str, np.ndarray, np.ndarray, np.ndarray]], fds: list[float], guard_hz: float,
                 spec: Spectrum, parts: np.ndarray, sums: np.ndarray | None
                 ) -> tuple[np.ndarray | None, dict[int, np.ndarray]]:
    """What an echo among the static lines moving below the Doppler stage's floor could leak, from
    the record's parts (IQ: its halves): the static lines' bound and each found mover's (IQ:
    :func:`subbin_bounds`; a real record beside movers: :func:`envelope_leak_bound`, the movers'
    only; a real record with none: nothing here, :func:`fading_lines` reads its envelope)."""
    if np.iscomplexobj(x):
        return subbin_bounds(x, fs, uniq, z, fams, fds, guard_hz, spec, parts)
    return None, (envelope_leak_bound(x, fs, uniq, fams, spec, parts, sums) if fds else {})


#: :func:`subbin_leak_bound` takes a mover's Doppler to lie up to this many of its sigmas beyond what
#: the two halves' common turn measured ...
SUBBIN_SIGMAS = 3.0
#: ... and no further than this many record bins: there the fit reads a line at ``sinc`` of its size
#: (0.1 at 0.9 bin; at 1 bin nothing, and any size would hide), and from
#: :data:`~.doppler.SMALL_MIN_BINS` on the sub-guard search's scan looks for the carrier itself
SUBBIN_MAX_BINS = 0.9
#: ... at this many Doppler values on each side, evenly spaced up to it (the leak is not monotone)
SUBBIN_STEPS = 8


def subbin_leak_bound(x: np.ndarray, fs: float, uniq: np.ndarray, z: np.ndarray, static: np.ndarray,
                      guard_hz: float, spec: Spectrum, halves: np.ndarray | None = None,
                      ratio: np.ndarray | None = None) -> np.ndarray | None:
    """IQ, one whole record: how much an echo among the static lines that moves below the Doppler
    stage's floor ``guard_hz`` could add to each modelled line by leaking through the fit that models
    its lines at no Doppler (V, shape (K,)), or None where nothing could.

    Such a mover puts every line of its echo -- its carrier beside the DC, ``+-f_i`` -- ``f_d`` off the
    frequencies the fit models them at: each is read at a fraction of its size, and the
    rectangular window's far skirt of the others, the carrier among them far the strongest, is no
    longer taken out (the envelope probe's scene 15860: 0.62 bin, the carrier 56x the lines; the
    range 4-6 sigmas off, the lines' chi2 0.5) -- nor from a mover's lines the search found a few
    bins off (scene 17879: an echo 0.3 bin up, 21 dB under a mover 2.2 bins up, the mover 6-10
    range sigmas off; 17571: 0.13 bin, 59 dB under one 1.2 bins up, its speed 7 sigmas off). Every
    static line turns with ``f_d`` alike, so the two halves of the record measure it (each half's
    phase turned to the record's centre: a static line turns not at all): the bound takes their
    weighted common turn plus :data:`SUBBIN_SIGMAS` of its sigma, no more than ``guard_hz`` or
    :data:`SUBBIN_MAX_BINS`, and sums, for each modelled line, every other static line's leak at
    Doppler shifts up to that, each static line's size read back through its own share
    (:func:`~.tones.line_response`); a found mover's lines are modelled where they lie and are not
    shifted.

    Parameters
    ----------
    x : ndarray, shape (N,), complex128, V
    uniq : ndarray, shape (K,), the modelled lines (Hz, sorted); ``z`` their amplitudes (V), shape (K,)
    static : ndarray of int, indices into ``uniq`` of the static plan's lines (``+-f_i`` and 0)
    halves : ndarray, shape (2, K), optional: the two halves' DFTs at ``uniq`` if already taken
        (:func:`~.tones.exact_dft_tiled`, each about its own centre)
    ratio : ndarray, shape (J,), optional: each static line's size relative to the static
        carrier's (the 0 Hz line, which ``static`` then holds), inf where unknown: an echo's lines
        are its carrier times the modulation's, as a found mover's show, and the carrier, 30-60x
        the lines, reads the echo's size far better than they do (a line at the noise is no echo:
        read for one, shifted near a bin beside a mover, a lone mover's speed sigma grew 100x).
    """
    n = x.size
    half = n // 2
    zh = fit_lines_segments(x, np.array([0, half]), half, uniq, fs, dft=halves)  # (2, K), about each half's centre
    turned = zh[:, static] * centre_turn(2, half, 2 * half, uniq[static], fs)  # both about the halves' common centre
    turn = turned[1] * np.conj(turned[0])
    s2 = spec.noise_variances(uniq[static], uniq, guard=spec.line_floor_guard())
    var_h = s2 * fit_noise_gain(uniq, fs, half, True)[static]  # a half's line (s2/half far from others)
    w = 1.0 / np.sum(0.5 * var_h / np.maximum(np.abs(zh[:, static]) ** 2, 1e-300), axis=0)
    mean = complex(np.sum(w * turn / np.maximum(np.abs(turn), 1e-300)))
    bins = min(abs(np.angle(mean)) / np.pi + SUBBIN_SIGMAS / (np.pi * math.sqrt(np.sum(w))),
               guard_hz * n / fs, SUBBIN_MAX_BINS)
    steps = np.linspace(bins / SUBBIN_STEPS, bins, SUBBIN_STEPS)
    shifts = np.concatenate([steps, -steps]) * fs / n  # Hz, (D,)
    # every shift's response in one solve (one Gram matrix): (D, K, J), [d, k, j] static line j read at k
    r = line_response(uniq, (uniq[static][None, :] + shifts[:, None]).ravel(), fs, n)
    r = np.abs(r.reshape(uniq.size, shifts.size, static.size).transpose(1, 0, 2))
    own = r[:, static, np.arange(static.size)]  # (D, J): each static line's own share
    # each static line's size from its share of the whole record or -- where that is cut more than
    # the halves' noise is larger (a line s record bins off is s/2 of a half's bins off) -- of the
    # halves', the noise's mean power taken out: a line at the noise, shifted near a bin, is no
    # echo ~10x its size
    own_h = np.abs(line_response(uniq, (uniq[static][None, :] + shifts[:, None]).ravel(), fs, half))
    own_h = own_h.reshape(uniq.size, shifts.size, static.size).transpose(1, 0, 2)[:, static, np.arange(static.size)]
    whole = np.sqrt(np.maximum(np.abs(z[static]) ** 2 - s2 / n, 0.0))
    halves_rms = np.sqrt(np.maximum(np.mean(np.abs(zh[:, static]) ** 2, axis=0) - var_h, 0.0))
    size = np.where(own * math.sqrt(n / half) >= own_h, whole[None, :] / np.maximum(own, 1e-12),
                    halves_rms[None, :] / np.maximum(own_h, 1e-12))
    if ratio is not None:
        # the carrier's times the ratio, but never less than what the line itself shows beyond 3
        # sigmas of its noise (two echoes' carriers may cancel at 0 Hz where their lines do not)
        zero = int(np.flatnonzero(uniq[static] == 0.0)[0])
        seen = np.maximum(np.abs(z[static]) - 3.0 * np.sqrt(s2 / n), 0.0)
        by_ratio = size[:, zero:zero + 1] * np.where(np.isfinite(ratio), ratio, 0.0)[None, :]
        size = np.where(np.isfinite(ratio)[None, :],
                        np.maximum(by_ratio, seen[None, :] / np.maximum(own, 1e-12)), size)
    leak = np.einsum("dkj,dj->dk", r, size)
    leak[:, static] -= own * size  # a static line's own share is no leak
    out = np.max(leak, axis=0)
    return out if np.any(out > 0) else None


def subbin_bounds(x: np.ndarray, fs: float, uniq: np.ndarray, z: np.ndarray,
                  fams: list[tuple[int, str, np.ndarray, np.ndarray, np.ndarray]], fds: list[float],
                  guard_hz: float, spec: Spectrum, halves: np.ndarray | None = None
                  ) -> tuple[np.ndarray | None, dict[int, np.ndarray]]:
    """:func:`subbin_leak_bound` per family: the static lines' bound (V, shape (T,), the larger of
    ``+-f_i``; None where there is none) and each found mover's (Doppler ``fds``, Hz), by target
    (the larger of its U and L lines), which its speed's and range's checks read as a static
    echo's beat on it (:attr:`LineFamily.cross_v`).

    The line at 0 Hz is the static echo's carrier only where every found mover's carrier is
    modelled too (:func:`plan_lines` leaves out one within its clearance of 0 Hz): else it holds
    that mover's carrier's leak, up to thousands of times the static lines (the envelope probe's
    scene 17571: a mover 1.2 bins up, its carrier 30x the 0 Hz line's static share), and is
    neither shifted nor read for the turn."""
    idx = [_line_index(uniq, f) for _, _, f, _, _ in fams]

    def at(f: np.ndarray) -> np.ndarray:  # each line's index in uniq, -1 where it is not modelled
        i = _line_index(uniq, f)
        return np.where(np.abs(uniq[i] - f) < 1e-6, i, -1)

    carriers = bool(np.all(at(np.asarray(fds, float)) >= 0))
    static = np.unique(np.concatenate([i for (t, *_), i in zip(fams, idx) if t == 0]
                                      + [np.flatnonzero(uniq == 0.0) if carriers else np.zeros(0, int)]))
    ratio = None
    if fds and carriers and np.any(uniq[static] == 0.0):
        # each static line's size against the static carrier's, as large as on any found mover
        # (a line it does not model: no cap)
        ratio = np.zeros(static.size)
        for fd in fds:
            i = at(uniq[static] + fd)
            r = np.abs(z[i]) / max(abs(z[at(np.array([fd]))[0]]), 1e-300)
            ratio = np.maximum(ratio, np.where(i >= 0, r, np.inf))
    leak = subbin_leak_bound(x, fs, uniq, z, static, guard_hz, spec, halves, ratio)
    if leak is None:
        return None, {}
    per: dict[int, np.ndarray] = {}
    for (t, *_), i in zip(fams, idx):
        per[t] = np.maximum(per[t], leak[i]) if t in per else leak[i]
    unexplained = per.pop(0)
    return (unexplained if np.any(unexplained > 0) else None), per


#: :func:`envelope_leak_bound` reads a static line's envelope on this many consecutive parts of the
#: record (a change symmetric about the record's centre -- a fading envelope's peak -- shows to
#: no fewer than 3)
ENVELOPE_PARTS = 4
#: ... states this many times the leak its deviations from its mean at the record's two ends make
#: on a line ``d`` record bins away, ``(|b(0)| + |b(T)|)/(2*pi*d)``, each end read from its outer
#: part and that part's slope to the next (for the envelope's curvature and the parts' means
#: falling short of the ends)
ENVELOPE_LEAK_MARGIN = 2.0
#: ... with this many sigmas of the parts' noise taken out of those deviations (a steady line's
#: noise read as a change put ~3e-4 of a 30 dB weaker mover's lines on them, tripling its speed
#: sigma of 1e-4 bin)
ENVELOPE_NOISE_SIGMAS = 3.0


def envelope_leak_bound(x: np.ndarray, fs: float, uniq: np.ndarray,
                        fams: list[tuple[int, str, np.ndarray, np.ndarray, np.ndarray]], spec: Spectrum,
                        parts_dft: np.ndarray, sums: np.ndarray) -> dict[int, np.ndarray]:
    """A real record with movers found (balanced): how much the static lines' envelope, changing
    across the record, could leak onto each mover's lines through the fit that models them as
    steady (V, per mover target, shape (T,), the larger of its U and L lines).

    An echo among the static lines that moves below the Doppler stage's floor puts ``f_i +- f_d``
    on a real record: the line at ``f_i`` fades as ``cos(2*pi*f_d*t + Phi)``, and what the steady
    fit leaves of it, ``b(t)`` (the envelope less its mean), leaks far through the rectangular
    window's skirt, falling only as one over the distance ``d`` (record bins) -- by its values at the
    record's ends, ``(|b(0)| + |b(T)|)/(2*pi*d)`` where the mover's lines lie off the record's bin
    grid (the envelope probe's scene 16541: an echo 0.47 bin up, 49 dB over a mover 16.6 bins from
    it, whose lines it outgrew ~4x: the mover ranged at the echo's range, 139 sigmas off). The
    record's :data:`ENVELOPE_PARTS` parts, each turned to the record's centre, measure each static
    line's envelope; the bound at a mover's line is :data:`ENVELOPE_LEAK_MARGIN` times that leak,
    ``(1 + 2/d)`` times more within a few bins, summed over the static lines, ``d`` at least one.

    Parameters
    ----------
    x : ndarray, shape (N,), float64, V
    uniq : ndarray, shape (K,), the modelled lines (Hz, sorted)
    parts_dft, sums : ndarray, shapes (P, K) and (P,): the parts' DFTs at ``uniq`` and their sums
        (:func:`~.tones.exact_dft_tiled`, P = :data:`ENVELOPE_PARTS`)
    """
    n, p = x.size, parts_dft.shape[0]
    m = n // p
    zp = fit_lines_segments(x, np.arange(p) * m, m, uniq, fs, dft=parts_dft, sums=sums)  # (P, K)
    s_lines = fams[0][2]
    s_idx = _line_index(uniq, s_lines)
    q = (zp * centre_turn(p, m, p * m, uniq, fs))[:, s_idx]  # (P, J), about the record's centre
    dev = q - q.mean(axis=0)
    ends = (np.abs(dev[0]) + np.abs(q[0] - q[1]) / 2) + (np.abs(dev[-1]) + np.abs(q[-1] - q[-2]) / 2)
    # a part's line: complex noise variance s2 times its fit's gain (4/m far from every other line,
    # more where a mover's line lies within a part's bin: 1.5 record bins is 0.4 of a quarter's,
    # whose fits then share the noise); the two ends' reading of noise alone: mean 2.8, sd 0.95
    # times its root, so the cut is its mean plus ~3 sd (the tail is not Gaussian: ~0.5 % beyond)
    s2 = spec.noise_variances(s_lines, uniq, guard=spec.line_floor_guard())
    var = s2 * fit_noise_gain(uniq, fs, m, False)[s_idx]
    ends = np.maximum(ends - ENVELOPE_NOISE_SIGMAS * np.sqrt(3.5 * var), 0.0)
    out: dict[int, np.ndarray] = {}
    for t, _, f, _, _ in fams[1:]:
        d = np.maximum(np.abs(f[:, None] - s_lines[None, :]) * n / fs, 1.0)  # (T, J) record bins
        # (1 + 2/d): within a few bins the far skirt's formula falls short (a fine mover a bin off:
        # 0.4-0.7 of the real shift with the margin alone, a review's measurement)
        leak = ENVELOPE_LEAK_MARGIN * np.sum(ends[None, :] * (1.0 + 2.0 / d) / (2 * np.pi * d), axis=1)
        out[t] = np.maximum(out[t], leak) if t in out else leak
    return out


def cross_beat_bound(s_lines: np.ndarray, z_all: np.ndarray, uniq: np.ndarray, fds: list[float], dc: np.ndarray,
                     lo_larger: bool = True) -> dict[int, np.ndarray]:
    """One photodiode: the static echo's beat with each mover's echo on the mover's own lines, the
    amplitude (V) that could add to each, per mover target, shape (T,).

    The static echo ``A_s*M(t - tau_s)*exp(j*Phi_s)`` and the mover's beat at ``f_i +- f_d`` too: the
    mover's sideband with the static carrier (``a_0*A_s/A_L`` of the mover's line, one complex factor
    for all tones: a common phase, no range) and the mover's carrier with the static sideband,
    ``A_m*a_0*A_s*a_i`` with the static target's tone phase -- a tone-dependent pull. The static
    lines give ``|S_i| = 2*A_L*A_s*a_i*|cos(Phi_s)|`` and the mover's carrier ``|B| = 2*A_L*A_m*a_0``,
    so that term is ``|S_i|*|B|/(4*A_L^2)`` at least (the static lines' fading only hides more; the
    static echo's own power stays in the mean taken for ``A_L^2``, which lowers the bound where that
    echo nears the LO's power).
    An echo near the LO's power on one photodiode (the envelope probe's scenes 725, 1385, 1937:
    static echoes at 0-10 dB loss, the LO a tenth of the power) puts it at the mover's lines' own
    size: their ranges came out 200-1000 sigmas off, unflagged.

    Parameters
    ----------
    s_lines : ndarray, shape (S, T): the static lines, the movers' self-beats taken out (V)
    z_all, uniq, fds, dc, lo_larger : as :func:`self_beat_lines`
    """
    return _cross_beats(np.abs(s_lines), *_carriers(z_all, uniq, fds, dc, lo_larger))


def _cross_beats(s: np.ndarray, base: list[tuple[int, np.ndarray]], lo_power: np.ndarray) -> dict[int, np.ndarray]:
    """:func:`cross_beat_bound` from the static lines' sizes ``s`` (S, T) and :func:`_carriers`."""
    return {k: np.sqrt(np.mean((s * (np.abs(b) / (4 * np.maximum(lo_power, 1e-300)))[:, None]) ** 2, axis=0))
            for k, b in base}


def seed_extract(x: np.ndarray, fs: float, freqs: np.ndarray, settings: ChainSettings) -> tuple[np.ndarray, float]:
    """The dissertation's path: resample, 1 MHz band-pass filtfilt, correlate with cosines.

    Parameters
    ----------
    x : ndarray, shape (N,), float64, V (single/balanced receivers only)
    freqs : ndarray, shape (K,), the lines (Hz)

    Returns
    -------
    (z, centre_s): complex amplitudes, shape (K,), referred to the resampled grid's centre,
    which lies ``centre_s`` seconds after the record's first sample
    """
    if np.iscomplexobj(x):
        raise Rejected("unsupported", "the seed profile handles single/balanced receivers only")
    npts = settings.seed_points
    y = sps.resample(x - x.mean(), npts)
    fs2 = fs * npts / x.size
    out = np.empty(freqs.size, complex)
    bw = settings.seed_bandwidth_hz
    for i, f in enumerate(freqs):
        lo, hi = max(f - bw / 2, 1.0), min(f + bw / 2, fs2 / 2 * 0.999)
        sos = sps.butter(2, [lo, hi], btype="bandpass", fs=fs2, output="sos")
        # forward-backward (zero-phase) filtering; sosfiltfilt's initial-state solve is singular
        # for a 1 MHz band at hundreds of GSa/s, so start both passes from rest instead
        yf = sps.sosfilt(sos, sps.sosfilt(sos, y)[::-1])[::-1]
        out[i] = exact_dft(yf, [f], fs2)[0] * 2 / npts
    # amplitudes refer to the centre of the resampled grid, (npts-1)/(2*fs2) after the start
    return out, (npts - 1) / (2 * fs2)
