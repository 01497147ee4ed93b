"""PE-MTCW (the dissertation's chapter 4): range from the phases of the Doppler-shifted lines.

Architecture ``modulated_reference``: the local oscillator is the *modulated* beam back from a
reference mirror at ``L_ref``. For a target moving at Doppler ``f_d`` a single photodiode sees,
per tone ``f_i`` (``shared/spec/physics.md``; derivation in ``docs/techniques.md``, "PE-MTCW"):

==============  ======================================================  =========================
line            complex amplitude (phase; ``x`` a positive real)        from
==============  ======================================================  =========================
``f_i``         ``exp(j*(phi_i - 2*pi*f_i*tau_r))``                     the reference's self-beat
``f_i + f_d``   ``s_i*x*exp(j*(phi_i - theta - pi*f_i*(tau + tau_r)))``  LO x echo (both sidebands)
``|f_i - f_d|`` ``s_i*x*exp(j*(phi_i + theta - pi*f_i*(tau + tau_r)))``  (conjugated if folded)
``2f_i +- f_d`` ``s'_i*x*exp(j*(2*phi_i -+ theta - 2*pi*f_i*(tau+tau_r)))`` MZM 2nd order, LO x echo
==============  ======================================================  =========================

``tau = tau0 + 2*L/c`` (echo), ``tau_r = 2*L_ref/c`` (reference), ``theta`` the optical carrier's
phase (``2*pi*f0*(tau - tau_r)`` plus laser noise: random, micrometre-scale), ``s_i = sign(cos(pi*
f_i*(tau - tau_r)))`` (the AB-MTCW fading). The carrier phase and the sign cancel in the product
of a line pair, and the RF phase ``phi_i`` (trigger jitter, drift) cancels against the reference
self-beat:

    Q_i = z(f_i + f_d) * z(|f_i - f_d|) * conj(z(f_i))**2  ->  phase  -2*pi*f_i*(tau - tau_r)
    Q2_i = z(2f_i + f_d) * z(|2f_i - f_d|) * conj(z(f_i))**4  ->  phase  -2*pi*(2f_i)*(tau - tau_r)

So each tone gives the path difference ``L - L_ref`` modulo ``c/(2*f_i)`` (the second-order
lines modulo ``c/(4*f_i)``), and together they give it modulo ``c/(2*gcd(f_i))`` -- the
unambiguous range. The Doppler-shifted line *frequencies* ``f_i +- f_d`` carry no range: the
shift is the optical carrier's, whose phase is the range modulo ``lambda/2``. ``L_ref`` is a
setting (``reference_range_m``) or, when not set, measured in the same frame from the reference
self-beat phases and the tone phases in force (calibration or frame).

Cycle resolution is the PB chain's (:func:`~mtcw_core.ranging.triangulation.resolve_ml`, or the
dissertation's candidate matrix :func:`~mtcw_core.ranging.triangulation.resolve_seed` with the
``seed`` method), on observations whose "frequency difference" is ``f_i`` (or ``2f_i``). Line
amplitudes come from the joint least-squares fit of :func:`mtcw_core.dsp.tones.fit_lines`, with
every other line the physics predicts (MZM products of the reference's self-beat, the second-
order Doppler-shifted products) modelled so that none leaks into the used ones.

Two effects are modelled rather than hidden:

- *Motion blur*: within the record the echo's modulation is itself Doppler-shifted by
  ``delta_i = 2*v*f_i/c`` (490 Hz for 2.45 GHz at 30 m/s), the reference's is not, so the two
  halves of a line are weighted ``kappa_i = sinc(delta_i*T) < 1`` against each other and the
  line phase moves by ``atan((1 - kappa)/(1 + kappa)*tan(d_i))``, ``d_i = pi*f_i*(tau - tau_r)``.
  It is corrected at the solution (one iteration); for second-order lines the correction is
  approximate and its size is added to their variance.
- *The echo's own self-beat* lies on the reference line ``f_i`` at ``(a_m/a_ref)**2`` of it and
  moves its phase by up to that (rad); the arm ratio is read from the baseband Doppler line
  against the DC level, the shift is corrected at the solution (in ``Q`` and in the in-frame
  ``L_ref``), and 10 % of it stays in the reference lines' variance.
- *Doppler*: refined by PE itself (:func:`refine_doppler`), not by the PB chain's refinements,
  which the reference's strong static products pull on short records.

Limits (they are flags or rejections, never silent): a single photodiode is needed (balanced
and IQ receivers have no reference self-beat); a target with no Doppler line is not PE's
(``no_target``; AB-MTCW ranges static targets); quasi-CW frames are not gated here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np
from scipy.stats import chi2 as chi2_dist
from scipy.stats import gamma as gamma_dist

from ..dsp.doppler import DopplerEstimate, estimate_doppler, fd_max, l1_ball, white_floor
from ..dsp.extract import LineFamily
from ..dsp.spectrum import Spectrum, local_floor, whole_record
from ..dsp.tones import fit_lines
from ..frame import Frame
from ..phase import C, unambiguous_range, wrap_pi
from ..profiles import ChainSettings
from ..results import NoTarget, Rejected, TargetPoint
from .targets import BIRGE_P, BLENDED_P, Reference, shared_phase_error_hz, velocity
from .triangulation import Observations, resolve_ml, resolve_seed


@dataclass(frozen=True)
class PeLines:
    """The lines of one moving target, per tone.

    Attributes
    ----------
    target : int
        1 for the strongest Doppler line, 2 for the next, ...
    doppler : DopplerEstimate
    tone_hz : ndarray, shape (T,), Hz
    z_ref, z_up, z_low, z2_up, z2_low : ndarray, shape (T,), complex128, V
        Amplitudes (at the record's centre) of the lines at ``f_i``, ``f_i + f_d``,
        ``|f_i - f_d|``, ``2f_i + f_d``, ``|2f_i - f_d|``; a folded line is conjugated so that it
        carries ``+theta`` like an unfolded one.
    var_ref, var_up, var_low, var2_up, var2_low : ndarray, shape (T,), rad^2
        Phase variance of each line from the local noise floor (inf: not usable -- it lies on
        another line or above Nyquist).
    arm_ratio : float
        ``a_m/a_ref``, echo to reference field amplitude, from the baseband Doppler line over DC.
    duration_s : float
        Record length the amplitudes rest on (s).
    centre_s : float
        The instant the amplitudes refer to, after the record's first sample (s).
    spill : dict of ndarray, shape (T,), rad^2, keyed as the lines (``"ref"``, ``"up"``, ...)
        What the moving lines' phase-noise pedestals add to each line's phase variance
        (:func:`pedestal_spill`): in the observations' variances, not in the lines' SNR test (a
        worst-case delay's spill would drop lines a short delay leaves clear). Empty: none.
    """

    target: int
    doppler: DopplerEstimate
    tone_hz: np.ndarray
    z_ref: np.ndarray
    z_up: np.ndarray
    z_low: np.ndarray
    z2_up: np.ndarray
    z2_low: np.ndarray
    var_ref: np.ndarray
    var_up: np.ndarray
    var_low: np.ndarray
    var2_up: np.ndarray
    var2_low: np.ndarray
    arm_ratio: float
    duration_s: float
    centre_s: float
    spill: dict = field(default_factory=dict)


def _fold(f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``|f|`` and the mask of lines that folded through 0 Hz (their amplitude is conjugated)."""
    return np.abs(f), f < 0


#: two lines to fit closer than this (record bins) are fitted as one; further apart, both (their
#: joint least squares holds at 0.13 bins, a Gram condition ~70): a mover's strong baseband line
#: 0.13 bins from a static product, fitted as that product alone before (1.1 bins apart or less),
#: left +-1-bin residuals 9 % of it that leaked 0.6 rad into another mover's 75 MHz lines 54 bins
#: away (the techniques probe's scene 1709: the range 0.55 m off, 411 sigmas, unflagged)
FIT_APART_BINS = 0.05


def line_plan(tones_hz, fd_hz: float, fs_hz: float, n: int) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """Where a PE target's lines lie, which of them are usable, and every line to fit.

    Parameters
    ----------
    tones_hz : array_like, shape (T,), Hz
    fd_hz : float, the Doppler line (Hz, > 0 for a real detector)
    fs_hz : float; n : int, record length (samples), which sets the resolution ``fs/n``

    Returns
    -------
    wanted : dict name -> ndarray shape (T,) of signed frequencies (Hz) for ``ref``, ``up``,
        ``low``, ``up2``, ``low2`` (a negative one folds through 0 Hz)
    usable : ndarray of bool, shape (5, T), in that order: no other predicted line within two
        record bins, below Nyquist
    fit_hz : ndarray, every frequency to fit jointly (Hz): the usable wanted lines, the baseband
        Doppler line, and the static (third-order MZM products of the reference's self-beat) and
        Doppler-shifted (second-order) lines that do not lie on a wanted one
    """
    t = np.asarray(tones_hz, float)
    nyq = fs_hz / 2
    res = 1.5 * fs_hz / n
    fd = abs(fd_hz)
    wanted = {"ref": t, "up": t + fd, "low": t - fd, "up2": 2 * t + fd, "low2": 2 * t - fd}
    vecs, static, pairs = _products(tuple(float(f) for f in t), nyq)
    shifted = np.abs(pairs[:, 0] + pairs[:, 1] * fd)
    # every physical line, one entry per product (two products on one frequency are two lines)
    src_f = np.concatenate([static, shifted, [fd]])
    src_id = [("s", v) for v in vecs] + [("d", c, sg) for c, sg in _pair_ids(t.size)] + [("b",)]
    ids = {"ref": [("s", _unit(t.size, i)) for i in range(t.size)],
           "up": [("d", _unit(t.size, i), 1.0) for i in range(t.size)],
           "low": [("d", _unit(t.size, i), -1.0) for i in range(t.size)],
           "up2": [("d", tuple(2 * x for x in _unit(t.size, i)), 1.0) for i in range(t.size)],
           "low2": [("d", tuple(2 * x for x in _unit(t.size, i)), -1.0) for i in range(t.size)]}
    usable = []
    for name in ("ref", "up", "low", "up2", "low2"):
        f = np.abs(wanted[name])
        ok = []
        for fi, own in zip(f, ids[name]):
            near = np.flatnonzero(np.abs(src_f - fi) <= res)
            ok.append(all(src_id[k] == own for k in near) and res < fi < nyq - res)
        usable.append(ok)
    usable = np.asarray(usable, bool)
    every = np.unique(np.round(src_f[(src_f > res / 3) & (src_f < nyq)], 3))
    used = np.concatenate([np.abs(wanted[nm])[u] for nm, u in zip(("ref", "up", "low", "up2", "low2"), usable)])
    return wanted, usable, kept_apart(np.concatenate([used, every]), FIT_APART_BINS * fs_hz / n)


def kept_apart(freqs: np.ndarray, apart_hz: float) -> np.ndarray:
    """``freqs`` (Hz) with each one closer than ``apart_hz`` to one before it left out (the first of
    a cluster kept: pass the wanted lines first), rounded to the micro-hertz and sorted."""
    keep: list[float] = []
    for f in np.round(np.asarray(freqs, float), 6):
        if all(abs(f - k) > apart_hz for k in keep):
            keep.append(float(f))
    return np.sort(np.asarray(keep, float))


def _unit(size: int, i: int) -> tuple[int, ...]:
    return tuple(1 if k == i else 0 for k in range(size))


@lru_cache(maxsize=64)
def _canonical_vectors(size: int, order: int) -> tuple[tuple[int, ...], ...]:
    """Integer vectors n with ``1 <= sum|n_i| <= order``, one of each pair ``+-n`` (first nonzero > 0)."""
    return tuple(n for n in l1_ball(size, order) if any(n) and next(x for x in n if x != 0) > 0)


def _pair_ids(size: int) -> list[tuple[tuple[int, ...], float]]:
    """The Doppler-shifted products as (vector, sign): the line ``|n.t + sign*f_d|``, n of order <= 2
    (the zero vector is the baseband line, listed apart)."""
    return [(n, sg) for n in _canonical_vectors(size, 2) for sg in (1.0, -1.0)]


@lru_cache(maxsize=64)
def _products(tones: tuple[float, ...], nyq: float):
    """Static products (third-order MZM products of the reference's self-beat): their vectors and
    frequencies (Hz, ``|n.t|``), and the Doppler-shifted ones as (c, s) rows, line ``|c + s*f_d|``
    (all vectors listed, none dropped: :func:`line_plan` keeps their identities aligned)."""
    t = np.asarray(tones, float)
    vecs = list(_canonical_vectors(t.size, 3))
    static = np.array([abs(float(np.dot(n, t))) for n in vecs])
    pairs = np.array([(float(np.dot(n, t)), sg) for n, sg in _pair_ids(t.size)])
    return vecs, static, pairs


def _static_and_shifted(t: np.ndarray, nyq: float) -> tuple[np.ndarray, np.ndarray]:
    """Static line frequencies (Hz) below ``nyq`` and the Doppler-shifted ones as (c, s) rows,
    the baseband line ``(0, +1)`` included (see :func:`_products`)."""
    _, static, pairs = _products(tuple(float(f) for f in t), nyq)
    return static[(static > 0) & (static < nyq)], np.vstack([pairs, [[0.0, 1.0]]])


def _plan_with_others(tones_hz, fd_hz: float, others: list[float], fs: float, n: int):
    """:func:`line_plan` of a target at ``fd_hz``, with the other targets' lines fitted too (a
    second mover's ``f_i +- f_d'`` must not leak in) and the wanted lines near them unusable."""
    wanted, usable, fit_hz = line_plan(tones_hz, fd_hz, fs, n)
    extra = [f for o in others for f in line_plan(tones_hz, o, fs, n)[2]]
    allf = kept_apart(np.concatenate([fit_hz, np.asarray(extra, float)]), FIT_APART_BINS * fs / n)
    if extra:
        res = 2 * fs / n
        for i, nm in enumerate(("ref", "up", "low", "up2", "low2")):
            if nm != "ref":
                d = np.abs(np.abs(wanted[nm])[:, None] - np.asarray(extra)[None, :]).min(axis=1)
                usable[i] &= d > res
    return wanted, usable, allf


#: a line no plan models that stands this many times its local floor in the whole record's spectrum
#: (:func:`unmodelled_lines`) is fitted with the plan's ...
UNMODELLED_MIN_RATIO = 100.0
#: ... where it lies this many spectrum bins clear of every modelled line and a bin clear of 0 Hz:
#: a local maximum further out than a line's own peak is not that line's (its Kaiser(14) main lobe
#: falls monotonically to +-4.6 bins); at 5 bins, a mover's baseband line 4.7 bins from another's
#: lower sideband and 30 times it went unmodelled and turned that tone by pi (the techniques
#: probe's scene 4010: half the 6 m period off, 4743 sigmas)
UNMODELLED_CLEAR_BINS = 1.5


def _strong_peaks(spec: Spectrum) -> np.ndarray:
    """The spectrum's local maxima :data:`UNMODELLED_MIN_RATIO` times their local floor, each placed
    by a parabola through the log power of its three bins (Hz), shape (M,)."""
    p = np.asarray(spec.power[:], dtype=np.float64)
    if p.size < 3:
        return np.empty(0)
    # an exact zero (a float32 spectrum's underflow, a filtered band) would sink the log floor 48 bins about it
    p = np.maximum(p, 1e-6 * float(np.median(p)) + np.finfo(np.float64).tiny)
    floor = local_floor(p, mirror_dc=True)
    k = np.arange(1, p.size - 1)
    k = k[(p[k] > p[k - 1]) & (p[k] >= p[k + 1]) & (p[k] > UNMODELLED_MIN_RATIO * floor[k])]
    if not k.size:
        return np.empty(0)
    a, b, c = (np.log(p[j]) for j in (k - 1, k, k + 1))
    curv = a - 2 * b + c
    off = np.where(curv < 0, 0.5 * (a - c) / np.where(curv < 0, curv, -1.0), 0.0)
    return spec.f0_hz + (k + np.clip(off, -0.5, 0.5)) * spec.df_hz


def unmodelled_lines(spec: Spectrum, modelled_hz: np.ndarray) -> np.ndarray:
    """The lines (Hz) the spectrum shows that no plan models: local maxima :data:`UNMODELLED_MIN_RATIO`
    times their local floor (:func:`~mtcw_core.dsp.spectrum.local_floor`), :data:`UNMODELLED_CLEAR_BINS`
    clear of ``modelled_hz`` (Hz), each placed by a parabola through the log power of its three bins.

    A mover PE's search did not find -- below its guard, where the parabolic search does not look --
    puts a carrier beat near 0 Hz as strong as the found mover's baseband line, hundreds of times its
    sidebands; the rectangular least-squares fit leaks it as ``A/(pi*D)`` ``D`` bins away, so a line
    290 bins off still carries 1/900 of it: ~6e-6 V on sidebands of 3.6e-5 V (the techniques probe's
    scene 1426: a 0.21 m/s mover beside one at 1.10 m/s, 75 MHz lines 0.4 rad off, the range 1.8 m
    off, 800 sigmas, unflagged). Fitted with the plan, it leaks nothing into the used lines.

    Parameters
    ----------
    spec : the whole record's spectrum (:func:`~mtcw_core.dsp.spectrum.whole_record`), real record
    modelled_hz : ndarray, shape (K,), every line the plan fits (Hz)

    Returns
    -------
    ndarray, shape (M,), Hz
    """
    if "pe_peaks" not in spec.memo:  # the spectrum's peaks, once a frame (each mover filters its own)
        spec.memo["pe_peaks"] = _strong_peaks(spec)
    f = spec.memo["pe_peaks"]
    if not f.size:
        return f
    near = np.abs(f[:, None] - np.asarray(modelled_hz, float)[None, :]).min(axis=1) if np.size(modelled_hz) else np.inf
    return f[(near > UNMODELLED_CLEAR_BINS * spec.df_hz) & (f > spec.df_hz)]


def refine_doppler(x: np.ndarray, frame: Frame, dop: DopplerEstimate, others: list[float], spec: Spectrum,
                   held: np.ndarray | None = None) -> DopplerEstimate:
    """The Doppler line below one spectrum bin: the shift whose lines (baseband, ``f_i +- f_d``,
    ``2f_i +- f_d`` and the other Doppler-shifted products) take the most power in the joint
    least-squares fit with every static line modelled -- the maximum-likelihood frequency in
    white noise.

    Why not the PB chain's refinements: next to the reference's strong static lines (the MZM
    products of its self-beat, on a grid of the tones' gcd) they are pulled by up to a bin on
    short records (measured: 0.95 MHz at 2^14-2^15 samples on the section 4.3 scene, with a
    stated error of 0.1 MHz). Searched within 3 times the parabola's stated error of its estimate;
    the moving lines that would cross a static line there are left out (none left: the parabola's
    estimate is kept, with its error). ``held``: further lines (Hz) fitted as static ones (the
    lines no plan models, :func:`unmodelled_lines`: a strong one leaks into every fit of the search
    span as into the lines' own, the techniques probe's scene 2564: 18.6 kHz off at a stated 3 kHz).
    """
    from scipy.optimize import minimize_scalar

    fs, n = frame.fs_hz, x.size
    f0 = abs(dop.fd_hz)
    t = np.asarray(frame.tones_hz, float)
    static, pairs = _static_and_shifted(t, fs / 2)
    for o in others:  # the other targets' lines are static here
        static = np.concatenate([static, np.abs(pairs[:, 0] + pairs[:, 1] * o)])
    if held is not None:
        static = np.concatenate([static, np.asarray(held, float)])
    res = 1.5 * fs / n

    def lines_at(fd: float) -> np.ndarray:
        mv = np.abs(pairs[:, 0] + pairs[:, 1] * fd)
        return mv[(mv > res) & (mv < fs / 2 - res)]

    # the line set is fixed at the search's estimate, so that the objective is smooth in fd: every
    # static line, and the moving lines that stay clear of them over the searched span (those that
    # would cross one are neither fitted nor counted)
    mv0 = lines_at(f0)
    span = 3 * max(dop.refine_error_hz, 0.01 * fs / n)  # the search's parabola: ~0.1 bin
    st = kept_apart(static[(static > res / 3) & (static < fs / 2 - res)], FIT_APART_BINS * fs / n)
    clear = np.abs(mv0[:, None] - st[None, :]).min(axis=1) > span + 0.5 * fs / n if st.size else \
        np.ones(mv0.size, bool)
    if not clear.any():
        return dop

    def neg_power(fd: float) -> float:
        mv = lines_at(fd)
        mv = np.unique(np.round(mv[clear] if mv.size == clear.size else mv[:0], 3))
        z = fit_lines(x, np.concatenate([st, mv]), fs)
        return -float(np.sum(np.abs(z[st.size:]) ** 2))

    r = minimize_scalar(neg_power, bounds=(max(f0 - span, 0.5 * f0), f0 + span), method="bounded",
                        options={"xatol": 1e-4 * fs / n})
    # an optimum at the edge of the span is no optimum: the parabola was further off than it said
    at_edge = min(r.x - (f0 - span), (f0 + span) - r.x) < 0.05 * span
    # the echo's sidebands sit 2*v*f_i/c below the reference's (module docstring): the line's power
    # centre is pulled by up to half of that for the highest tone
    err = spec.df_hz if at_edge else 0.5 * f0 * float(np.max(t)) * frame.wavelength_m / C
    # a bias of up to 0.6 % of a record bin is measured on the section 4.4 scene at 2^17 samples,
    # noiseless and with an ideal laser (not yet explained; products of order 3 and above are not
    # modelled): stated as a floor of 1 % of a bin
    err = max(err, 0.01 * fs / n)
    # (what the search said of the movers' beats with each other stays: one photodiode's beat_pulls)
    return DopplerEstimate(float(r.x), True, dop.score, dop.threshold, dop.min_detectable_hz, err, dop.wander_hz,
                           beat_ambiguous=dop.beat_ambiguous, beat_pull_hz=dop.beat_pull_hz)


#: :func:`echo_delay_bound` probes the pedestal this many record bins either side of the line ...
PROBE_BINS = tuple(range(2, 11))
#: ... excludes a delay whose pedestal the probes' power would have shown with odds below this ...
PROBE_FALSE_ODDS = 1e-4
#: ... scanning the delay on this many points up to the longest the bench allows: its declared
#: largest range, or the delay at which the line would keep :data:`DELAY_CAP_COHERENCE` of the beat
DELAY_SCAN_POINTS = 512
DELAY_CAP_COHERENCE = 0.01


def probe_pedestal(bins: np.ndarray, taus_s: np.ndarray, linewidth_hz: float, duration_s: float) -> np.ndarray:
    """Expected power of a record-long fit ``bins`` record bins from a line, over the power of the
    line's own fit, for echo delays ``taus_s`` relative to the LO: ``P_k/(1 + P_0)``, shape (S, P).

    The line is ``B*exp(j*Phi(t))`` with ``Phi`` the delayed self-heterodyne phase of a Lorentzian
    laser (``D = 2*pi*linewidth``): its autocorrelation ``exp(-D*min(|u|, tau))`` is the coherent
    part ``exp(-D*tau)`` plus ``exp(-D*tau)*K(u)``, ``K = expm1(D*(tau - |u|)_+)``. A fit over
    ``T`` gathers it through the Fejer kernel, whose transform is the triangle ``1 - |u|/T``: at a
    whole bin ``k`` the coherent part gives nothing, and ``P_k = (2/T) int_0^min(tau,T) (1 - u/T)
    K(u) cos(2*pi*k*u/T) du`` over the coherent power; the line's own fit (``k = 0``) holds
    ``1 + P_0`` of it. For a small ``D*tau`` this is the phase's spectrum
    ``2*linewidth*sin^2(pi*f*tau)/(pi*f^2)`` seen through the kernel.

    Parameters
    ----------
    bins : ndarray, shape (P,), whole record bins from the line (>= 1)
    taus_s : ndarray, shape (S,), delays (s)
    """
    d = 2 * math.pi * linewidth_hz
    s = np.linspace(0.0, 1.0, 129)
    span = np.minimum(taus_s, duration_s)[:, None]  # (S, 1)
    u = span * s[None, :]  # (S, M)
    k_u = np.expm1(d * (taus_s[:, None] - u)) * (1 - u / duration_s)  # (S, M)
    w = np.full(s.size, 1.0)
    w[[0, -1]] = 0.5
    w = w * span / (s.size - 1) * 2 / duration_s  # trapezoid weights times 2/T, (S, M)
    p0 = np.sum(w * k_u, axis=1)  # (S,)
    pk = np.einsum("sm,smp->sp", w * k_u, np.cos(2 * np.pi * u[:, :, None] * bins[None, None, :] / duration_s))
    return pk / (1 + p0[:, None])


def echo_delay_bound(x: np.ndarray, fs: float, lines_hz: np.ndarray, line_hz: float, white: float,
                     settings: ChainSettings) -> float:
    """The longest echo delay (s) relative to the reference arm that the pedestal about the target's
    line at ``line_hz`` allows, for the declared laser (0 for a laser declared coherent). It sets
    the Doppler's error from the phase every moving line shares
    (:func:`~mtcw_core.ranging.targets.shared_phase_error_hz`) and what each moving line's pedestal
    spills onto its neighbours (:func:`pedestal_spill`).

    The delay is what the phases cannot give: they fold the range into ``c/(2*gcd)`` (6 m for
    section 4.3's tones), and a target at 103.5 m under a 100 kHz laser read 1.58 m, its speed
    10-17 of its sigmas off (the speed's scatter 0.025 m/s, the model's 0.017). The pedestal
    witnesses the delay: about the line lies, to first order, the phase's spectrum ``S(f) =
    2*linewidth*sin^2(pi*f*dtau)/(pi*f^2)`` times the line's density (flat at
    ``2*pi*linewidth*dtau^2`` below ``1/(pi*dtau)``, beyond it a tail that no longer grows with the
    delay; exactly, :func:`probe_pedestal`). Probes fitted jointly with every line
    (:data:`PROBE_BINS` record bins either side: no window's lobe hides them) read it, and each
    delay under which their power would have stood higher than seen, with odds below
    :data:`PROBE_FALSE_ODDS` (their powers over the expected, summed: gamma-distributed), is
    excluded; the longest left is the one stated. Close probes pin a delay up to ``~T/(2*pi)``
    (a long record); beyond, only the tail's rise with the coherence's fall bounds it, and the
    bound is loose (a short record: the honest worst case). Capped by the declared largest range
    (``range_max_m``) or the delay at which the line would keep :data:`DELAY_CAP_COHERENCE` of the
    beat. 0 for a laser declared coherent.

    Parameters
    ----------
    x : ndarray, shape (N,), float64, V
    fs : sample rate (Hz)
    lines_hz : ndarray, shape (M,), every line the frame's fit holds (Hz), sorted
    line_hz : the target's strongest moving line (Hz)
    white : the white floor (V^2 per sample, :func:`~mtcw_core.dsp.doppler.white_floor`)
    """
    lw, n = settings.laser_linewidth_hz, x.size
    if lw <= 0:
        return 0.0
    cap = math.log(1 / DELAY_CAP_COHERENCE) / (2 * math.pi * lw)
    if settings.range_max_m is not None:
        cap = min(cap, 2 * settings.range_max_m / C)
    delta = np.concatenate([-np.array(PROBE_BINS), PROBE_BINS]) * fs / n  # Hz from the line
    probes = line_hz + delta
    keep = (np.abs(probes[:, None] - lines_hz[None, :]).min(axis=1) > 1.5 * fs / n) & (probes > fs / n) & \
        (probes < fs / 2 - fs / n)
    tau = cap
    if keep.any():
        freqs = np.concatenate([lines_hz, probes[keep]])
        order = np.argsort(freqs)
        z = fit_lines(x, freqs[order], fs)[np.argsort(order)]
        line = abs(z[np.argmin(np.abs(lines_hz - line_hz))]) ** 2
        power = np.abs(z[lines_hz.size:]) ** 2
        taus = np.linspace(0.0, cap, DELAY_SCAN_POINTS)
        expected = 4 * white / n + line * probe_pedestal(np.abs(delta[keep]) * n / fs, taus, lw, n / fs)
        seen = np.sum(power / expected, axis=1)  # each term ~ Exp(1)
        allowed = np.flatnonzero(seen >= gamma_dist.ppf(PROBE_FALSE_ODDS, power.size))
        # the bound lies before the next point excluded; none allowed (a floor under the white
        # one): the cap
        tau = float(taus[min(allowed[-1] + 1, taus.size - 1)]) if allowed.size else cap
    return tau


def pedestal_spill(lines_hz: np.ndarray, z: np.ndarray, movers_hz: np.ndarray, z_movers: np.ndarray, tau_s: float,
                   linewidth_hz: float, duration_s: float) -> np.ndarray:
    """Phase variance (rad^2) that the moving lines' pedestals spill onto each of ``lines_hz``.

    Every Doppler-shifted line carries the laser's phase over the echo's delay; the joint fit
    takes out its coherent part, not its pedestal, which a neighbour ``D`` Hz away gathers as
    ``|z_N|^2 * P`` (:func:`probe_pedestal` at ``D*T`` bins), half of it across the line's phase.
    Beside the baseband Doppler line, hundreds of times a tone's sideband, that is the sideband's
    leading noise: section 4.3's 75 MHz tone, its lower line 1.5 MHz from a target's 36.8 MHz
    Doppler (18.4 m/s) at 103 m under a 100 kHz laser, put the range half a period off, 11600
    sigmas, unflagged (the techniques probe's scene 1348).

    Parameters
    ----------
    lines_hz, z : ndarray, shape (L,), the lines' frequencies (Hz) and fitted amplitudes (V)
    movers_hz, z_movers : ndarray, shape (M,), the moving lines (Hz) and their amplitudes (V)
    tau_s : the echo delay (s), :func:`echo_delay_bound`'s
    """
    if tau_s <= 0 or not movers_hz.size:
        return np.zeros(lines_hz.size)
    gap = np.abs(lines_hz[:, None] - movers_hz[None, :]) * duration_s  # record bins, (L, M)
    far = gap > 0.5  # a line is not its own neighbour
    p = probe_pedestal(np.maximum(gap.ravel(), 0.5), np.array([tau_s]), linewidth_hz, duration_s)[0]
    spill = np.sum(np.where(far, p.reshape(gap.shape) * np.abs(z_movers[None, :]) ** 2, 0.0), axis=1)
    return spill / (2 * np.maximum(np.abs(z) ** 2, 1e-300))


def _amplitude_near(allf: np.ndarray, z: np.ndarray, f_hz: float, bin_hz: float) -> float:
    """A line's amplitude (V) from the fit's columns within half a record bin of ``f_hz``: lines kept
    0.05 bins apart share one line's amplitude between them where its frequency is a little off
    (0.03 bins off, 0.06 apart: half in each)."""
    near = np.abs(allf - f_hz) < 0.5 * bin_hz
    return float(np.abs(np.sum(z[near]))) if near.any() else float(np.abs(z[np.argmin(np.abs(allf - f_hz))]))


def arm_ratio(baseband_v: float, dc_v: float) -> float:
    """``a_m/a_ref``, an echo's field amplitude over the reference's, from its baseband Doppler line
    (``2*a_ref*a_m``, V) over the record's mean (``a_ref^2 + a_m^2``, V): the smaller root of
    ``rho = 2r/(1 + r^2)``, ``rho`` their ratio (at most 1)."""
    rho = min(baseband_v / abs(dc_v), 1.0) if dc_v != 0 else 1.0
    return (1 - math.sqrt(1 - rho**2)) / rho if rho > 0 else 0.0


def other_echo_spill(fd_hz: float, carriers: list[tuple[float, float]], duration_s: float) -> tuple[float, float]:
    """Phase variance (rad^2) other echoes put on a target's lines: on its reference lines (each
    ``f_i``) and on its Doppler-shifted ones.

    Every other echo ``k`` (``carriers``: its baseband line, Hz, and arm ratio ``r_k``,
    :func:`arm_ratio`) squares into a self-beat on each reference line ``f_i``, ``r_k^2`` of it
    (the target's own is corrected at the solution, another's is not: a 14.8 dB echo of arm ratio
    0.18 moved a weaker mover's reference lines by 3 %, the techniques probe's scene 1238), and
    beats with this target's sidebands as a second local oscillator, ``r_k`` of them, ``|f_k|``
    or ``||f_k| - 2|f_d||`` away (one photodiode: the signs are unknown), where the record's
    rectangular fit lets ``1/(pi*D)`` of it in ``D`` bins off (all of it within a bin).
    """
    ref = side = 0.0
    for f_k, r in carriers:
        ref += r**4
        gap = min(abs(f_k), abs(abs(f_k) - 2 * abs(fd_hz))) * duration_s
        side += (r * min(1.0, 1.0 / (math.pi * gap)) if gap > 0 else r) ** 2
    return ref, side


def _refine_movers(x: np.ndarray, frame: Frame, moving: list[DopplerEstimate], spec: Spectrum,
                   settings: ChainSettings) -> tuple[list[DopplerEstimate], np.ndarray]:
    """Every mover refined (:func:`refine_doppler`), the found ones first, then the carriers of
    those the search did not find, and the strong lines no plan models beyond the search's
    largest Doppler (Hz), which every fit holds."""
    n, fs = x.size, frame.fs_hz
    whole = whole_record(spec, x, fs)
    # every strong line no plan models is fitted too, in the refinement and with the lines: a mover
    # unfound leaks through every least-squares fit (found about the search's estimate; the
    # refinement moves the plan by under a bin, the lines stay clear of it). Below the search's
    # largest Doppler such a line is the carrier of a mover it did not find (below its guard): its
    # whole line family is fitted as another mover's -- its sidebands lie within a few bins of the
    # reference lines, where no peak is seen apart (the techniques probe's scene 3346: a mover 30 dB
    # over a found one 5.5 bins away gave the found one its phases, 1359 sigmas off)
    extra = np.round(unmodelled_lines(whole, _plan_with_others(
        frame.tones_hz, moving[0].fd_hz, [abs(o.fd_hz) for o in moving[1:]], fs, n)[2]), 6)
    below = extra < fd_max(frame.tones_hz, settings)
    every = moving + [DopplerEstimate(float(g), True, 0.0, 0.0, 0.0, refine_error_hz=0.5 * fs / n) for g in extra[below]]
    extra = extra[~below]
    refined = list(every)
    for _ in range(2):
        refined = [refine_doppler(x, frame, d, [abs(o.fd_hz) for j, o in enumerate(refined) if j != i], spec, extra)
                   for i, d in enumerate(every)]
        # with several movers, again with the others' lines where their refinement put them, where
        # it moved them (held at the search's estimate, up to a tenth of a bin off, a strong mover's
        # baseband line left residuals that pulled a weaker one's Doppler: the techniques probe's 2631)
        if len(every) < 2 or all(abs(r.fd_hz - d.fd_hz) < 0.02 * fs / n for r, d in zip(refined, every)):
            break
    return refined, extra


def extract_pe(x: np.ndarray, frame: Frame, dops: list[DopplerEstimate], spec: Spectrum,
               settings: ChainSettings) -> list[PeLines]:
    """The stage ``pe_lines``: per moving target, the complex amplitude of its PE lines.

    Parameters
    ----------
    x : ndarray, shape (N,), float64, V (single photodiode)
    dops : the Doppler lines found (stage ``doppler``)
    spec : the search spectrum, for the lines' local noise floors

    Raises
    ------
    Rejected
        ``architecture`` (not ``modulated_reference``), ``receiver`` (not a single photodiode),
        ``pulse`` (quasi-CW frames are not gated by PE).
    NoTarget
        No Doppler line: PE ranges moving targets only.
    """
    if frame.architecture != "modulated_reference":
        raise Rejected("architecture", f"pe needs the modulated_reference architecture, the frame has "
                                       f"{frame.architecture}")
    if frame.receiver != "single" or np.iscomplexobj(x):
        raise Rejected("receiver", f"pe needs a single photodiode (the reference self-beat lines), "
                                   f"the frame has {frame.receiver}")
    if frame.pulse is not None:
        raise Rejected("pulse", "pe has no quasi-CW gating")
    moving = [d for d in dops if d.detected and d.fd_hz != 0.0]
    if not moving:
        raise NoTarget("pe: no Doppler line (PE ranges moving targets from f_i +- f_d; a static target is AB-MTCW's)")
    n, fs = x.size, frame.fs_hz
    dc = float(np.mean(x))
    refined, extra = _refine_movers(x, frame, moving, spec, settings)
    out = []
    for k, dop in enumerate(refined[:len(moving)], start=1):
        others = [abs(d.fd_hz) for d in refined if d is not dop]
        wanted, usable, allf = _plan_with_others(frame.tones_hz, dop.fd_hz, others, fs, n)
        allf = kept_apart(np.concatenate([allf, extra]), FIT_APART_BINS * fs / n)
        z_all = fit_lines(x, allf, fs)
        amps, vars_, line_hz = {}, {}, {}
        for i, nm in enumerate(("ref", "up", "low", "up2", "low2")):
            f, folded = _fold(wanted[nm])
            line_hz[nm] = f
            idx = np.clip(np.searchsorted(allf, np.round(f, 6)), 0, allf.size - 1)
            z = z_all[idx].copy()
            z[folded] = np.conj(z[folded])
            ok = usable[i] & (np.abs(allf[idx] - f) < 1e-3)
            s2 = spec.noise_variances(f, allf)
            var = 2.0 * s2 / (n * np.maximum(np.abs(z) ** 2, 1e-300))
            var[~ok] = np.inf
            z[~ok] = 0.0
            amps[nm], vars_[nm] = z, var
        a_d = _amplitude_near(allf, z_all, abs(dop.fd_hz), fs / n)
        lw = settings.laser_linewidth_hz
        tau = echo_delay_bound(x, fs, allf, abs(dop.fd_hz), white_floor(spec, allf)[0], settings)
        dop = replace(dop, wander_hz=max(dop.wander_hz, shared_phase_error_hz(lw, tau, n / fs)))
        # the moving lines' pedestals onto every line used (the baseband line's the largest)
        movers = np.concatenate([[abs(dop.fd_hz)]] + [line_hz[nm] for nm in ("up", "low", "up2", "low2")])
        at = np.clip(np.searchsorted(allf, np.round(movers, 6)), 0, allf.size - 1)
        z_movers = np.where(np.abs(allf[at] - movers) < 1e-3, z_all[at], 0.0)  # a line not fitted: none
        spill = {nm: pedestal_spill(f, amps[nm], movers, z_movers, tau, lw, n / fs) for nm, f in line_hz.items()}
        # the other echoes, found or not (the lines no plan models), as self-beats and second LOs
        carriers = [(f, arm_ratio(_amplitude_near(allf, z_all, f, fs / n), dc)) for f in [*others, *extra]]
        on_ref, on_side = other_echo_spill(dop.fd_hz, carriers, n / fs)
        spill = {nm: v + (on_ref if nm == "ref" else on_side) for nm, v in spill.items()}
        ratio = arm_ratio(a_d, dc)
        out.append(PeLines(k, dop, np.asarray(frame.tones_hz, float), amps["ref"], amps["up"], amps["low"],
                           amps["up2"], amps["low2"], vars_["ref"], vars_["up"], vars_["low"], vars_["up2"],
                           vars_["low2"], ratio, n / fs, (n - 1) / (2 * fs), spill))
    return out


def blur_phase(kappa: np.ndarray, d_rad: np.ndarray) -> np.ndarray:
    """Phase (rad) that motion blur adds to a line *pair product* (``U*L``) whose echo half is
    weighted ``kappa`` against its reference half: ``2*atan((1-kappa)/(1+kappa)*tan(d))``,
    ``d = pi*f*(tau - tau_r)`` (modulo pi: the sign of the line cancels in the product)."""
    g = (1 - kappa) / (1 + kappa)
    return 2 * np.arctan(g * np.tan(d_rad))


@dataclass(frozen=True)
class PeObservations:
    """The phase observations of one target.

    ``obs`` holds ``Q_i`` (df = f_i) and, where usable, ``Q2_i`` (df = 2 f_i), not yet corrected
    for blur and the echo's self-beat; ``var`` their variances (rad^2); ``kappa`` each one's blur
    weight; ``order`` 1 or 2; ``kappa_ref`` the blur of the echo self-beat on the tone's reference
    line. ``ref_obs`` holds the reference lines' phases at the record's start less the tone phases
    (model ``-2*pi*f_i*tau_r``), ``ref_var`` their variances and ``ref_kappa`` their echo self-beat's blur.
    """

    obs: Observations
    var: np.ndarray
    kappa: np.ndarray
    order: np.ndarray
    ref_obs: Observations
    ref_var: np.ndarray
    kappa_ref: np.ndarray
    ref_kappa: np.ndarray


def pe_observations(lines: PeLines, tone_phases_rad: dict[float, float], wavelength_m: float,
                    min_snr_db: float) -> PeObservations:
    """The carrier-free, RF-phase-free observations of a target (module docstring).

    Lines below ``min_snr_db`` (post-integration, ``-10*log10(var)``) are left out.
    """
    t = lines.tone_hz
    # the echo self-beat on the reference line is corrected at the solution (see solve_pe); what
    # is left is the error of the arm ratio read from the baseband line over DC (which counts the
    # sidebands' power in DC: a few % at m = 0.1 per tone; taken as 10 %)
    sys_ref = 0.5 * (0.1 * lines.arm_ratio**2) ** 2
    sp = {nm: lines.spill.get(nm, 0.0) for nm in ("ref", "up", "low", "up2", "low2")}
    var_ref = lines.var_ref + sys_ref + sp["ref"]
    v = abs(lines.doppler.fd_hz) * wavelength_m / 2
    delta = 2 * v * t / C
    kappa1 = _kappa(delta, lines.duration_s)
    kappa2 = _kappa(2 * delta, lines.duration_s)
    q1 = lines.z_up * lines.z_low * np.conj(lines.z_ref) ** 2
    q2 = lines.z2_up * lines.z2_low * np.conj(lines.z_ref) ** 4
    v1 = lines.var_up + sp["up"] + lines.var_low + sp["low"] + 4 * var_ref
    v2 = lines.var2_up + sp["up2"] + lines.var2_low + sp["low2"] + 16 * var_ref
    lim = 10 ** (-min_snr_db / 10)
    ok1 = np.isfinite(v1) & (lines.var_up <= lim) & (lines.var_low <= lim) & (lines.var_ref <= lim)
    ok2 = np.isfinite(v2) & (lines.var2_up <= lim) & (lines.var2_low <= lim) & (lines.var_ref <= lim)
    df = np.concatenate([t[ok1], 2 * t[ok2]])
    ph = np.concatenate([np.angle(q1[ok1]), np.angle(q2[ok2])])
    var = np.concatenate([v1[ok1], v2[ok2]])
    kappa = np.concatenate([kappa1[ok1], kappa2[ok2]])
    order = np.concatenate([np.ones(int(ok1.sum()), int), np.full(int(ok2.sum()), 2)])
    kappa_ref = np.concatenate([kappa1[ok1], kappa1[ok2]])
    obs = Observations(df, wrap_pi(ph), 1 / var)
    okr = np.isfinite(var_ref) & (lines.var_ref <= lim)
    phi = np.array([tone_phases_rad.get(float(f), 0.0) for f in t[okr]])
    # the reference line's phase at the record's first sample (where the tone phases are referred)
    z0 = lines.z_ref[okr] * np.exp(-2j * np.pi * np.mod(t[okr] * lines.centre_s, 1.0))
    ref_obs = Observations(t[okr], wrap_pi(np.angle(z0) - phi), 1 / var_ref[okr])
    return PeObservations(obs, var, kappa, order, ref_obs, var_ref[okr], kappa_ref, kappa1[okr])


def self_beat_phase(ratio: float, kappa: np.ndarray, d_rad: np.ndarray, order: np.ndarray) -> np.ndarray:
    """Phase (rad) the echo's own self-beat adds to ``Q`` (order 1) or ``Q2`` (order 2).

    The line at ``f_i`` is the reference's self-beat ``exp(-j*2*pi*f_i*tau_r)`` plus the echo's,
    ``ratio**2 * kappa * exp(-j*2*pi*f_i*tau)`` (the same intensity waveform, scaled by the power
    ratio of the arms and blurred by the echo's motion); ``Q`` holds its conjugate squared
    (``Q2``: to the fourth), so it moves by ``-2*order*arg(1 + ratio**2*kappa*exp(-j*2*d))``,
    ``d = pi*f_i*(tau - tau_r)``.
    """
    return -2 * order * np.angle(1 + ratio**2 * kappa * np.exp(-2j * d_rad))


def _subset(po: PeObservations, mask: np.ndarray) -> PeObservations:
    """The observations of ``po`` where ``mask`` (the reference lines unchanged)."""
    o = po.obs
    return PeObservations(Observations(o.df_hz[mask], o.phase_rad[mask], o.weight[mask]), po.var[mask],
                          po.kappa[mask], po.order[mask], po.ref_obs, po.ref_var, po.kappa_ref[mask], po.ref_kappa)


def _kappa(delta_hz: np.ndarray, duration_s: float) -> np.ndarray:
    """The centred rectangular kernel of a record of ``duration_s`` at offset ``delta_hz``:
    ``sinc(delta*T)`` (the record's sample count changes it by far less than the blur itself)."""
    return np.sinc(np.asarray(delta_hz, float) * duration_s)


def _info_sigma(df_hz: np.ndarray, var: np.ndarray) -> float:
    """Range sigma (m) of absolute phase observations ``-2*pi*df*2*L/c`` with variances ``var``."""
    k = 4 * np.pi * df_hz / C
    info = float(np.sum(k**2 / var))
    return 1 / math.sqrt(info) if info > 0 else math.inf


def runner_up_log_odds(obs: Observations, tau0_s: float, interval_m: tuple[float, float], best_m: float,
                       points_per_cycle: int = 16, candidates: int = 8) -> float:
    """Log-likelihood of ``best_m`` over the best other cycle in ``interval_m``.

    With phase noise of variance ``1/w`` the log-likelihood is ``sum_l w_l*cos(r_l(L))`` (von Mises,
    concentration ``w``). The ``candidates`` highest other local maxima of the grid (step
    ``Lambda_min/points_per_cycle``, as :func:`resolve_ml`) are refined before comparing: on the
    grid alone a peak is under-rated by up to ``sum(w)*(1 - cos(pi/points_per_cycle))``, far more
    than the difference that matters.
    """
    from scipy.optimize import minimize_scalar

    k = 2 * np.pi * obs.df_hz

    def loglik(l_m):
        l_m = np.atleast_1d(np.asarray(l_m, float))
        return np.cos(obs.phase_rad[None, :] + k[None, :] * (tau0_s + 2 * l_m[:, None] / C)) @ obs.weight

    lam = float(np.min(obs.synthetic_wavelengths_m))
    step = lam / points_per_cycle
    grid = np.arange(interval_m[0], interval_m[1] + step, step)
    vals = np.concatenate([loglik(grid[i:i + 65536]) for i in range(0, grid.size, 65536)])
    is_max = np.r_[False, (vals[1:-1] >= vals[:-2]) & (vals[1:-1] >= vals[2:]), False]
    far = np.abs(grid - best_m) > 0.5 * lam
    idx = np.flatnonzero(is_max & far)
    if idx.size == 0:
        return math.inf
    top = idx[np.argsort(vals[idx])[::-1][:candidates]]
    second = max(-minimize_scalar(lambda l: -loglik(l)[0], bounds=(grid[i] - step, grid[i] + step),
                                  method="bounded", options={"xatol": 1e-6 * lam}).fun for i in top)
    return float(loglik(best_m)[0] - second)


def _reference_less_echo(po: PeObservations, ratio: float, tau_diff_s: float | None) -> Observations:
    """The reference lines' observations with the echo's own self-beat removed where ``tau_diff_s``
    (``tau - tau_r`` of the solution, s) is given (:func:`self_beat_phase`, ``ratio`` ``a_m/a_ref``)."""
    ro = po.ref_obs
    if tau_diff_s is None:
        return ro
    d = np.pi * ro.df_hz * tau_diff_s
    echo = np.angle(1 + ratio**2 * po.ref_kappa * np.exp(-2j * d))
    return Observations(ro.df_hz, wrap_pi(ro.phase_rad - echo), ro.weight)


def reference_range(po: PeObservations, settings: ChainSettings, ratio: float = 0.0,
                    tau_diff_s: float | None = None) -> tuple[float, float]:
    """``L_ref`` (m) and its sigma: the setting (sigma 0) or the reference self-beat phases.

    Parameters
    ----------
    ratio : float
        ``a_m/a_ref``; with ``tau_diff_s`` (``tau - tau_r`` of the solution, s), the echo's own
        self-beat on the reference lines is removed first (:func:`self_beat_phase`).

    Raises
    ------
    NoTarget
        ``reference_range_m`` not set and fewer than two reference lines above the SNR threshold.
    """
    if settings.reference_range_m is not None:
        return settings.reference_range_m, 0.0
    if po.ref_obs.df_hz.size < 2:
        raise NoTarget("pe: reference_range_m not set and fewer than two reference self-beat lines to measure it")
    ro = _reference_less_echo(po, ratio, tau_diff_s)
    lu = unambiguous_range(ro.df_hz)
    sol = resolve_ml(ro, 0.0, (settings.range_min_m, settings.range_min_m + lu), settings.points_per_cycle)
    return sol.range_m, _info_sigma(ro.df_hz, po.ref_var)


def reference_chi2(po: PeObservations, l_ref_m: float, ratio: float = 0.0,
                   tau_diff_s: float | None = None) -> tuple[float, int]:
    """Whether the reference lines are one mirror's: chi2 of their phases (the echo's own
    self-beat removed, :func:`_reference_less_echo`) about ``-2*pi*f_i*2*L_ref/c``, on as many
    degrees of freedom as lines less one (``L_ref`` fitted to them).

    A strong still echo squares onto the same lines and beats with the reference there (its
    intensity and the two arms' cross term): the lines no longer follow one delay, ``L_ref`` read
    from them is neither's, and every target's range with it (the reviewer's scene, a still echo
    at 10 dB of loss beside a mover under a 100 kHz laser at 2^20 samples: ``L_ref`` 5.79 m for a
    mirror at 0.10 m, chi2 3.7e6 on 3 dof, the mover 2800 sigmas off and unflagged). One mirror:
    0.02-5.4 on 3 (a few frames of the section 4.3 scene). (0, 0) with no line to read."""
    _, res = _reference_residuals(po, l_ref_m, ratio, tau_diff_s)
    dof = res.size - 1
    return (float(np.sum(res**2 / po.ref_var)), dof) if dof > 0 else (0.0, 0)


def _reference_residuals(po: PeObservations, l_ref_m: float, ratio: float, tau_diff_s: float | None
                         ) -> tuple[Observations, np.ndarray]:
    """The reference lines' observations (the echo's own self-beat removed,
    :func:`_reference_less_echo`) and their phases less one mirror's at ``l_ref_m``,
    ``-2*pi*f_i*2*L_ref/c`` (rad), shape (R,)."""
    ro = _reference_less_echo(po, ratio, tau_diff_s)
    return ro, wrap_pi(ro.phase_rad + 2 * np.pi * ro.df_hz * 2 * l_ref_m / C)


def _velocity(lines: PeLines, frame: Frame) -> tuple[float, float, str]:
    """Speed, sigma and direction from the refined Doppler line, by the PB chain's
    :func:`~mtcw_core.ranging.targets.velocity` on the target's U and L lines."""
    fams = [LineFamily("U", lines.tone_hz, np.abs(lines.tone_hz + lines.doppler.fd_hz), lines.z_up[None, :],
                       np.array([lines.centre_s]), lines.var_up, lines.target),
            LineFamily("L", lines.tone_hz, np.abs(lines.tone_hz - lines.doppler.fd_hz), lines.z_low[None, :],
                       np.array([lines.centre_s]), lines.var_low, lines.target)]
    return velocity(lines.doppler, frame, fams, False)[:3]


#: a target's two sidebands of one tone are one size (``s_i*x``, module docstring) to within this
#: part of each beyond their noise: what a strong echo's own products leave (10 dB of loss, arm
#: ratio 0.32: 1.2 % apart, the techniques probe's scene 283); at 5 % a mover's 75 MHz sidebands
#: 28 % apart under an unfound strong echo passed (scene 1980: 429 sigmas off)
SIDEBAND_SIZE_TOLERANCE = 0.02


def sideband_sizes_p(lines: PeLines) -> float:
    """The odds that noise (and :data:`SIDEBAND_SIZE_TOLERANCE`) alone set each tone's two sidebands
    ``|z(f_i + f_d)|`` and ``|z(|f_i - f_d|)|`` as far apart as they are: chi2 over the tones with both
    usable, each difference over its radial noise (``|z|^2`` times the phase variance, spill
    included) and the tolerance. Another echo's lines or beats on one of them part them: the
    techniques probe's scene 144, a strong mover unfound below the guard beside one at 11.4 m/s,
    whose 75 MHz sidebands stood 55 % apart (chi2 75 on 4) with its range 188 sigmas off, unflagged.
    1 where no tone has both."""
    u, lo = np.abs(lines.z_up), np.abs(lines.z_low)
    vu = lines.var_up + lines.spill.get("up", 0.0)
    vl = lines.var_low + lines.spill.get("low", 0.0)
    ok = np.isfinite(vu) & np.isfinite(vl) & (u > 0) & (lo > 0)
    if not ok.any():
        return 1.0
    u, lo, vu, vl = u[ok], lo[ok], vu[ok], vl[ok]
    var = vu * u**2 + vl * lo**2 + SIDEBAND_SIZE_TOLERANCE**2 * (u**2 + lo**2)
    return float(chi2_dist.sf(np.sum((u - lo) ** 2 / var), int(ok.sum())))


def _scale_and_blend(chi2: float, dof: int, settings: ChainSettings) -> tuple[float, bool]:
    """Phases against one delay, as the PB chain reads them: the sigma's scale (the Birge ratio's
    root from p < ``BIRGE_P``, else 1) and whether they fit no one delay (chi2/dof above
    ``settings.blended_chi2`` or p < ``BLENDED_P``: ``blended``). (1, False) with no dof."""
    if dof <= 0:
        return 1.0, False
    p = chi2_dist.sf(chi2, dof)
    return (math.sqrt(chi2 / dof) if p < BIRGE_P else 1.0), bool(chi2 / dof > settings.blended_chi2 or p < BLENDED_P)


def _checked_reference(po: PeObservations, settings: ChainSettings, ratio: float, tau_diff_s: float
                       ) -> tuple[float, float, float, bool]:
    """``L_ref`` (m) (:func:`reference_range`), its sigma (m), the phase variance per reference line
    (rad^2) beyond the lines' noise and whether ``L_ref``'s cycle is then in doubt.

    Where ``L_ref`` is measured, the reference lines' misfit of one mirror (their chi2 as
    :func:`reference_chi2`'s, improbable at p < ``BIRGE_P``) is read as an error ``e`` per line, the
    residuals' mean square beyond their noise. It enters ``L_ref``'s sigma, and (twice the phase:
    ``conj(z_ref)^2``) every target's observations in ``solve_pe``; with the lines' noise so
    widened, a runner-up mirror delay not excluded (:func:`runner_up_log_odds` under
    ``settings.pe_min_log_odds``) flags the point ``blended``. A strong still echo on the lines (10
    dB of loss: chi2 3.7e6 on 3, ``L_ref`` 5.79 m for a 0.10 m mirror; 20 dB: the mover 1680 sigmas
    off, unflagged, before) widens the targets' phases by more than their own noise; a weak one
    (50-60 dB: chi2 10-190 per dof) by under 1 % of it (a flag on the chi2 alone flagged every right
    point beside any still clutter: found in review). A declared ``L_ref`` is not read against the
    lines: that needs the tones' own phases, which PE does not otherwise need."""
    l_ref, s_ref = reference_range(po, settings, ratio, tau_diff_s)
    if settings.reference_range_m is not None:
        return l_ref, s_ref, 0.0, False
    ro, res = _reference_residuals(po, l_ref, ratio, tau_diff_s)
    dof = res.size - 1
    if dof <= 0 or chi2_dist.sf(float(np.sum(res**2 / po.ref_var)), dof) >= BIRGE_P:
        return l_ref, s_ref, 0.0, False
    e = max(float(np.sum(res**2) - np.sum(po.ref_var) * dof / res.size) / dof, 0.0)
    widened = Observations(ro.df_hz, ro.phase_rad, 1 / (po.ref_var + e))
    lu = unambiguous_range(ro.df_hz)
    odds = runner_up_log_odds(widened, 0.0, (settings.range_min_m, settings.range_min_m + lu), l_ref,
                              settings.points_per_cycle)
    return l_ref, _info_sigma(ro.df_hz, po.ref_var + e), e, bool(odds < settings.pe_min_log_odds)


def solve_pe(lines: PeLines, frame: Frame, settings: ChainSettings, ref: Reference) -> tuple[TargetPoint, float]:
    """One target's point and the unambiguous range (m) of the observations it used.

    Raises
    ------
    NoTarget
        Fewer than two usable observations.
    """
    po_all = pe_observations(lines, ref.tone_phases_rad, frame.wavelength_m, settings.min_line_snr_db)
    po = _subset(po_all, po_all.order == 1)
    obs = po.obs
    if obs.df_hz.size < 2:
        raise NoTarget(f"pe: fewer than two tones with lines f_i and f_i +- f_d above {settings.min_line_snr_db} dB")
    l_ref, s_ref = reference_range(po, settings)
    l_unamb = unambiguous_range(obs.df_hz)
    lo = settings.range_min_m
    hi = settings.range_max_m if settings.range_max_m is not None else lo + l_unamb
    interval = (lo - l_ref, hi - l_ref)  # the path difference L - L_ref is what the phases give

    def solve(o: Observations):
        if settings.method == "seed":
            return resolve_seed(o, ref.tau0_s, interval[1], interval[0])
        return resolve_ml(o, ref.tau0_s, interval, settings.points_per_cycle)

    def corrected(p: PeObservations, range_m: float) -> tuple[Observations, np.ndarray]:
        """Blur and the echo's self-beat at ``range_m`` (the path difference) removed; a
        second-order line's correction is approximate, its size joins its variance; a first-order
        line's two-term model leaves ~10 % of it (the exact MZM's higher products: 11.5 um left
        against 5 um stated at 2^22 samples on the section 4.3 scene without this term)."""
        d = np.pi * p.obs.df_hz * (ref.tau0_s + 2 * range_m / C)
        corr = blur_phase(p.kappa, d) + self_beat_phase(lines.arm_ratio, p.kappa_ref, d / p.order, p.order)
        v = p.var + np.where(p.order == 2, corr**2, (0.1 * corr) ** 2)
        return Observations(p.obs.df_hz, wrap_pi(p.obs.phase_rad - corr), 1 / v), v

    sol = solve(obs)
    for _ in range(2):  # corrections evaluated at the solution, then solved again
        obs, var = corrected(po, sol.range_m)
        sol = solve(obs)
    if settings.pe_second_order and np.any(po_all.order == 2):
        # the 2f_i +- f_d lines carry products of other tones too (m^3 terms) that can rival them
        # where their bracket fades: each joins only if it agrees with the first-order solution
        o_all, v_all = corrected(po_all, sol.range_m)
        r = wrap_pi(o_all.phase_rad + 2 * np.pi * o_all.df_hz * (ref.tau0_s + 2 * sol.range_m / C))
        po = _subset(po_all, (po_all.order == 1) | (np.abs(r) < 3 * np.sqrt(v_all)))
        obs, var = corrected(po, sol.range_m)
        sol = solve(obs)
        obs, var = corrected(po, sol.range_m)
    l_ref, s_ref, e_ref, r_blend = _checked_reference(po, settings, lines.arm_ratio, ref.tau0_s + 2 * sol.range_m / C)
    var = var + 4 * e_ref  # the reference lines' error beyond one mirror, twice in each phase (conj(z_ref)^2)
    obs = Observations(obs.df_hz, obs.phase_rad, 1 / var)
    sigma = _info_sigma(obs.df_hz, var)
    if settings.method == "seed":  # the candidate matrix reports its first column: the finest observation alone
        i = int(np.argmax(obs.df_hz))
        sigma = _info_sigma(obs.df_hz[i:i + 1], var[i:i + 1])
    # do the tones agree with one range within their noise? (Birge ratio from p < BIRGE_P, as the PB chain)
    res = wrap_pi(obs.phase_rad + 2 * np.pi * obs.df_hz * (ref.tau0_s + 2 * sol.range_m / C))
    chi2, dof = float(np.sum(res**2 / var)), obs.df_hz.size - 1
    ratio = chi2 / dof if dof > 0 else 1.0
    scale, blend = _scale_and_blend(chi2, dof, settings)
    sigma = math.hypot(sigma * scale, s_ref)
    # can the phases pick one cycle? The log-likelihood (von Mises, kappa = 1/var) of the best range over
    # the runner-up's; below `pe_min_log_odds` the runner-up is not excluded and the point is flagged
    ml = sol if settings.method != "seed" else resolve_ml(obs, ref.tau0_s, interval, settings.points_per_cycle)
    log_odds = runner_up_log_odds(obs, ref.tau0_s, interval, ml.range_m, settings.points_per_cycle)
    ambiguous = bool(log_odds < settings.pe_min_log_odds)
    # the dissertation's row spread may pick another cycle than the likelihood does: not trusted then
    finest = float(np.min(obs.synthetic_wavelengths_m))
    ambiguous |= abs(wrap_pi(2 * np.pi * (sol.range_m - ml.range_m) / l_unamb)) * l_unamb / (2 * np.pi) > finest / 2
    v, vs, direction = _velocity(lines, frame)
    snr = -10 * np.log10(po.var)
    tone_snr: dict[str, float] = {}
    for f, o, s in zip(obs.df_hz, po.order, snr):
        key = f"{f / o:.0f}"
        tone_snr[key] = max(tone_snr.get(key, -np.inf), float(s))
    point = TargetPoint(
        range_m=float(sol.range_m + l_ref), range_sigma_m=float(sigma), velocity_mps=v, velocity_sigma_mps=vs,
        direction=direction, snr_db=float(np.max(snr)), margin=sol.margin, residual_rms_rad=sol.residual_rms_rad,
        near_edge=sol.near_edge, cycle_ambiguous=ambiguous,
        # tones disagreeing beyond chance, as in the PB chain (techniques probe's scene 1823: chi2 23/3), the
        # reference lines not one mirror's, or sidebands not one size (another echo's lines on one)
        blended=bool(blend or r_blend or sideband_sizes_p(lines) < BLENDED_P),
        doppler_hz=lines.doppler.fd_hz, chi2_per_dof=float(ratio), tone_snr_db=tone_snr,
        seed_sigma_k_m=sol.seed_sigma_k_m,
    )
    return point, l_unamb


def resolve_pe(lines: list[PeLines], frame: Frame, settings: ChainSettings, ref: Reference
               ) -> tuple[list[tuple[int, TargetPoint]], float | None]:
    """The stage ``pe_resolve``: a point per moving target that can be ranged, and the largest
    unambiguous range (m) among them (``c/(2*gcd)`` of the tones used).

    Raises
    ------
    NoTarget
        No target had enough lines (the reason of the first is given).
    """
    solved: list[tuple[int, TargetPoint, float]] = []
    why = None
    for ln in lines:
        try:
            p, lu = solve_pe(ln, frame, settings, ref)
        except NoTarget as err:
            why = why or str(err)
            continue
        solved.append((ln.target, p, lu))
    if not solved:
        raise NoTarget(why or "pe: nothing to range")
    l_unamb = max(lu for _, _, lu in solved)
    # a point whose tones repeat sooner than the frame's stated period is known only modulo its own
    # (as the PB chain reads its points): a mover whose 75 MHz lines fell under the threshold beside
    # another, ranged modulo 2.998 m in a 5.996 m frame, half a period off and unflagged (the
    # techniques probe's scene 2478)
    return [(k, p if lu >= l_unamb * (1 - 1e-9) else replace(p, cycle_ambiguous=True))
            for k, p, lu in solved], l_unamb


# -------------------------------------------------------------------------------------------
# the stage table
def _doppler(s) -> None:
    # the search and its parabola only: pe_lines refines each line itself (see extract_pe)
    s.dopplers = estimate_doppler(s.x, s.frame, s.spectrum, s.settings.model_copy(update={"doppler_refine": "parabolic"}))
    s.result.doppler_hz = s.dopplers[0].fd_hz


def _lines(s) -> None:
    s.pe_lines = extract_pe(s.x, s.frame, s.dopplers, s.spectrum, s.settings)


def _resolve(s) -> None:
    s.candidates, s.result.unambiguous_range_m = resolve_pe(s.pe_lines, s.frame, s.settings, s.reference)


def stages(pb: tuple) -> tuple:
    """The PE stage table: pb's ``validate`` and ``spectrum``, then ``doppler`` (the search and its
    parabola), ``pe_lines`` (every line refined), ``pe_resolve`` (Table 1 relations) and pb's
    ``select`` (which ends a frame without target as ``no_target``: no ``square`` here, the
    reference arm's intensity would share the squared lines)."""
    row = type(pb[0])  # the chain's Stage
    by = {st.name: st for st in pb}
    return (by["validate"], by["spectrum"], row("doppler", _doppler), row("pe_lines", _lines),
            row("pe_resolve", _resolve), by["select"])
