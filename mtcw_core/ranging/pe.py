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
  against the DC level and the bound enters the reference lines' variance.

Limits (they are flags or rejections, never silent): a single photodiode is needed (balanced
and IQ receivers have no reference self-beat); a target with no Doppler line is not PE's
(``no_target``; AB-MTCW ranges static targets); quasi-CW frames are not gated here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2 as chi2_dist

from ..dsp.doppler import DopplerEstimate, intermod_frequencies
from ..dsp.extract import LineFamily
from ..dsp.spectrum import Spectrum
from ..dsp.tones import fit_lines
from ..frame import Frame
from ..phase import C, unambiguous_range, wrap_pi
from ..profiles import ChainSettings
from ..results import NoTarget, Rejected, TargetPoint
from .targets import Reference, velocity
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


def _fold(f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``|f|`` and the mask of lines that folded through 0 Hz (their amplitude is conjugated)."""
    return np.abs(f), f < 0


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
    res = 2 * fs_hz / n
    fd = abs(fd_hz)
    wanted = {"ref": t, "up": t + fd, "low": t - fd, "up2": 2 * t + fd, "low2": 2 * t - fd}
    static = intermod_frequencies(tuple(float(f) for f in t), nyq, 3)
    # second-order Doppler-shifted products: |n.t +- fd| for sum|n_i| <= 2 (incl. f_i, 2f_i, f_i +- f_j)
    combos = set(static[static <= 2 * t.max() + 1].tolist()) | {0.0}
    shifted = np.array(sorted({abs(c + s * fd) for c in combos for s in (1, -1)}))
    every = np.concatenate([static, shifted, [fd]])
    every = every[(every > res / 2) & (every < nyq)]
    usable = []
    for name in ("ref", "up", "low", "up2", "low2"):
        f = np.abs(wanted[name])
        # distance to the nearest *other* predicted line (a wanted line is itself in `every`)
        d = np.abs(f[:, None] - every[None, :])
        d = np.where(d < 1e-6 * res, np.inf, d)
        usable.append((d.min(axis=1) > res) & (f > res) & (f < nyq - res))
    usable = np.asarray(usable)
    keep: list[float] = []
    used = np.concatenate([np.abs(wanted[nm])[u] for nm, u in zip(("ref", "up", "low", "up2", "low2"), usable)])
    for f in np.concatenate([used, every]):
        if all(abs(f - k) > 0.75 * res for k in keep):
            keep.append(float(f))
    return wanted, usable, np.asarray(keep, float)


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
    out = []
    for k, dop in enumerate(moving, start=1):
        others = [abs(d.fd_hz) for d in moving if d is not dop]
        wanted, usable, fit_hz = line_plan(frame.tones_hz, dop.fd_hz, fs, n)
        # the other targets' lines are fitted too (a second mover's f_i +- f_d' must not leak in)
        extra = [f for o in others for f in line_plan(frame.tones_hz, o, fs, n)[2]]
        allf = np.unique(np.round(np.concatenate([fit_hz, np.asarray(extra, float)]), 6))
        if extra:
            res = 2 * fs / n
            for i, nm in enumerate(("ref", "up", "low", "up2", "low2")):
                if nm == "ref":
                    continue
                f = np.abs(wanted[nm])
                d = np.abs(f[:, None] - np.asarray(extra)[None, :]).min(axis=1)
                usable[i] &= d > res
        z_all = fit_lines(x, allf, fs)
        amps, vars_ = {}, {}
        for i, nm in enumerate(("ref", "up", "low", "up2", "low2")):
            f, folded = _fold(wanted[nm])
            idx = np.clip(np.searchsorted(allf, np.round(f, 6)), 0, allf.size - 1)
            z = z_all[idx].copy()
            z[folded] = np.conj(z[folded])
            ok = usable[i] & (np.abs(allf[idx] - f) < 1e-3)
            s2 = np.array([spec.noise_variance(fi, list(allf)) for fi in f])
            var = 2.0 * s2 / (n * np.maximum(np.abs(z) ** 2, 1e-300))
            var[~ok] = np.inf
            z[~ok] = 0.0
            amps[nm], vars_[nm] = z, var
        a_d = float(np.abs(z_all[np.argmin(np.abs(allf - abs(dop.fd_hz)))]))
        rho = min(a_d / abs(dc), 1.0) if dc != 0 else 1.0
        ratio = (1 - math.sqrt(1 - rho**2)) / rho if rho > 0 else 0.0
        out.append(PeLines(k, dop, np.asarray(frame.tones_hz, float), amps["ref"], amps["up"], amps["low"],
                           amps["up2"], amps["low2"], vars_["ref"], vars_["up"], vars_["low"], vars_["up2"],
                           vars_["low2"], ratio, n / fs, (n - 1) / (2 * fs)))
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
    var_ref = lines.var_ref + sys_ref
    v = abs(lines.doppler.fd_hz) * wavelength_m / 2
    delta = 2 * v * t / C
    kappa1 = _kappa(delta, lines.duration_s)
    kappa2 = _kappa(2 * delta, lines.duration_s)
    q1 = lines.z_up * lines.z_low * np.conj(lines.z_ref) ** 2
    q2 = lines.z2_up * lines.z2_low * np.conj(lines.z_ref) ** 4
    v1 = lines.var_up + lines.var_low + 4 * var_ref
    v2 = lines.var2_up + lines.var2_low + 16 * var_ref
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


def _kappa(delta_hz: np.ndarray, duration_s: float) -> np.ndarray:
    """The centred rectangular kernel of a record of ``duration_s`` at offset ``delta_hz``:
    ``sinc(delta*T)`` (the record's sample count changes it by far less than the blur itself)."""
    return np.sinc(np.asarray(delta_hz, float) * duration_s)


def _info_sigma(df_hz: np.ndarray, var: np.ndarray) -> float:
    """Range sigma (m) of absolute phase observations ``-2*pi*df*2*L/c`` with variances ``var``."""
    k = 4 * np.pi * df_hz / C
    info = float(np.sum(k**2 / var))
    return 1 / math.sqrt(info) if info > 0 else math.inf


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
    ro = po.ref_obs
    if ro.df_hz.size < 2:
        raise NoTarget("pe: reference_range_m not set and fewer than two reference self-beat lines to measure it")
    if tau_diff_s is not None:
        d = np.pi * ro.df_hz * tau_diff_s
        echo = np.angle(1 + ratio**2 * po.ref_kappa * np.exp(-2j * d))
        ro = Observations(ro.df_hz, wrap_pi(ro.phase_rad - echo), ro.weight)
    lu = unambiguous_range(ro.df_hz)
    sol = resolve_ml(ro, 0.0, (settings.range_min_m, settings.range_min_m + lu), settings.points_per_cycle)
    return sol.range_m, _info_sigma(ro.df_hz, po.ref_var)


def solve_pe(lines: PeLines, frame: Frame, settings: ChainSettings, ref: Reference) -> tuple[TargetPoint, float]:
    """One target's point and the unambiguous range (m) of the observations it used.

    Raises
    ------
    NoTarget
        Fewer than two usable observations.
    """
    po = pe_observations(lines, ref.tone_phases_rad, frame.wavelength_m, settings.min_line_snr_db)
    obs = po.obs
    if obs.df_hz.size < 2:
        raise NoTarget(f"pe: fewer than two tones with their f_i +- f_d and reference lines above "
                       f"{settings.min_line_snr_db} dB")
    l_ref, s_ref = reference_range(po, settings)
    l_unamb = unambiguous_range(obs.df_hz)
    lo = settings.range_min_m
    hi = settings.range_max_m if settings.range_max_m is not None else lo + l_unamb
    interval = (lo - l_ref, hi - l_ref)  # the path difference L - L_ref is what the phases give

    def solve(o: Observations):
        if settings.method == "seed":
            return resolve_seed(o, ref.tau0_s, interval[1], interval[0])
        return resolve_ml(o, ref.tau0_s, interval, settings.points_per_cycle)

    sol = solve(obs)
    # motion blur, evaluated at the solution, then solved again on the corrected phases
    var = po.var.copy()
    for _ in range(2):
        d = np.pi * obs.df_hz * (ref.tau0_s + 2 * sol.range_m / C)
        corr = blur_phase(po.kappa, d) + self_beat_phase(lines.arm_ratio, po.kappa_ref, d / po.order, po.order)
        var = po.var + np.where(po.order == 2, corr**2, 0.0)
        o2 = Observations(obs.df_hz, wrap_pi(obs.phase_rad - corr), 1 / var)
        sol = solve(o2)
    obs = o2
    l_ref, s_ref = reference_range(po, settings, lines.arm_ratio, ref.tau0_s + 2 * sol.range_m / C)
    sigma = _info_sigma(obs.df_hz, var)
    if settings.method == "seed":  # the candidate matrix reports its first column: the finest observation alone
        i = int(np.argmax(obs.df_hz))
        sigma = _info_sigma(obs.df_hz[i:i + 1], var[i:i + 1])
    # do the tones agree with one range within their noise? (Birge ratio, as the PB chain)
    res = wrap_pi(obs.phase_rad + 2 * np.pi * obs.df_hz * (ref.tau0_s + 2 * sol.range_m / C))
    chi2 = float(np.sum(res**2 / var))
    dof = obs.df_hz.size - 1
    ratio = chi2 / dof if dof > 0 else 1.0
    if dof > 0 and chi2_dist.sf(chi2, dof) < 1e-3:
        sigma *= math.sqrt(ratio)
    sigma = math.hypot(sigma, s_ref)
    # can the phases pick one cycle? The log-likelihood (von Mises, kappa = 1/var) of the best range
    # over the runner-up's, sum_l w_l*(cos r_l(best) - cos r_l(second)) = sum(w)*J(best)*margin;
    # below `pe_min_log_odds` the runner-up is not excluded and the point is flagged
    ml = sol if settings.method != "seed" else resolve_ml(obs, ref.tau0_s, interval, settings.points_per_cycle)
    w = 1 / var
    j_best = float(np.sum(w * np.cos(wrap_pi(obs.phase_rad + 2 * np.pi * obs.df_hz * (ref.tau0_s + 2 * ml.range_m / C)))))
    log_odds = j_best * ml.margin
    ambiguous = bool(log_odds < settings.pe_min_log_odds)
    # the dissertation's row spread may pick another cycle than the likelihood does: not trusted then
    finest = float(np.min(obs.synthetic_wavelengths_m))
    ambiguous |= abs(wrap_pi(2 * np.pi * (sol.range_m - ml.range_m) / l_unamb)) * l_unamb / (2 * np.pi) > finest / 2
    fams = [LineFamily("U", lines.tone_hz, np.abs(lines.tone_hz + lines.doppler.fd_hz), lines.z_up[None, :],
                       np.array([lines.duration_s / 2]), lines.var_up, lines.target),
            LineFamily("L", lines.tone_hz, np.abs(lines.tone_hz - lines.doppler.fd_hz), lines.z_low[None, :],
                       np.array([lines.duration_s / 2]), lines.var_low, lines.target)]
    v, vs, direction = velocity(lines.doppler, frame, fams, False)
    snr = -10 * np.log10(po.var)
    tone_snr: dict[str, float] = {}
    for f, o, s in zip(obs.df_hz, po.order, snr):
        key = f"{f / o:.0f}"
        tone_snr[key] = max(tone_snr.get(key, -np.inf), float(s))
    point = TargetPoint(
        range_m=float(sol.range_m + l_ref), range_sigma_m=float(sigma), velocity_mps=v, velocity_sigma_mps=vs,
        direction=direction, snr_db=float(np.max(snr)), margin=sol.margin, residual_rms_rad=sol.residual_rms_rad,
        near_edge=sol.near_edge, cycle_ambiguous=ambiguous, blended=bool(dof > 0 and ratio > settings.blended_chi2),
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
    points: list[tuple[int, TargetPoint]] = []
    l_unamb = None
    why = None
    for ln in lines:
        try:
            p, lu = solve_pe(ln, frame, settings, ref)
        except NoTarget as err:
            why = why or str(err)
            continue
        points.append((ln.target, p))
        l_unamb = lu if l_unamb is None else max(l_unamb, lu)
    if not points:
        raise NoTarget(why or "pe: nothing to range")
    return points, l_unamb
