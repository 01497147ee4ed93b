"""The triangulation made visible: what the chain saw and chose on one frame, as plain data.

:func:`explain_frame` walks the chain's stage table on one frame and reads, from the state the
stages leave (:class:`~mtcw_core.chain.FrameState`), what the dissertation draws in its
Figs. 18, 21, 23, 27 and 28:

* the **spectrum** the Doppler search used, decimated for display by the maximum of each block
  of bins (a line is never lost between two display points), in dB over the mean noise floor,
  with **every line marked**: the static lines at the tones (family ``S``), each Doppler line's
  baseband line and its lines at ``f_i +- f_d`` (``U``, ``L``), whether each was used (SNR
  above ``min_line_snr_db``, not clashing with another line), and the **ghosts left out**:
  intermodulation products of the tones (MZM harmonics and mixing products) and those products
  shifted by a found Doppler line or by the beat of two (the lines the Doppler search refuses
  as targets), where they stand above the search's detection threshold;
* per target candidate (0 static, k >= 1 the k-th Doppler line), the **cycle-resolution cost**
  ``J(L)`` of :func:`~mtcw_core.ranging.triangulation.resolve_ml` on the interval the chain
  searched, with the chosen peak and the runner-up (the best other local maximum more than half
  the finest synthetic wavelength away: the one the point's ``margin`` is computed from);
* the **seed's candidate matrix** (:func:`~mtcw_core.ranging.triangulation.candidate_matrix`)
  with its row spread ``sigma_k`` and the row the seed method would choose.

Nothing here is new maths: the cost, the matrix, the line plan and the products are the chain's
own functions, evaluated on the chain's own intermediate state. Everything returned is made of
builtins (dict, list, float, int, str, bool, None) and can be written with :func:`json.dumps`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .calibration import Calibration
from .chain import FrameState, _start, walk_total
from .dsp.doppler import fd_max, intermod_frequencies
from .dsp.spectrum import LN2, Spectrum, local_floor
from .frame import Frame
from .profiles import ChainSettings
from .ranging.targets import _search_interval
from .ranging.triangulation import Observations, candidate_matrix, cost, resolve_ml, unambiguous_range

#: display points of the spectrum, the cost curve and the sigma_k curve at most
MAX_POINTS = 2048
#: rows of the candidate matrix returned at most (centred on the chosen row)
MAX_ROWS = 64


def _f(x: Any) -> float | None:
    """A JSON-safe float: None for NaN and infinities."""
    x = float(x)
    return x if math.isfinite(x) else None


def _peak_decimate(x: np.ndarray, y: np.ndarray, max_points: int, keep: str = "max") -> tuple[np.ndarray, np.ndarray]:
    """At most ``max_points`` of (x, y), one per block of consecutive samples: the block's
    largest (``keep="max"``) or smallest ``y`` with its ``x``, so that peaks (or minima) survive."""
    n = y.size
    if n <= max_points:
        return x, y
    k = int(math.ceil(n / max_points))
    m = (n // k) * k
    blocks = y[:m].reshape(-1, k)
    pick = np.argmax(blocks, axis=1) if keep == "max" else np.argmin(blocks, axis=1)
    idx = np.arange(blocks.shape[0]) * k + pick
    if m < n:  # the tail block
        tail = np.arange(m, n)
        idx = np.r_[idx, tail[np.argmax(y[tail]) if keep == "max" else np.argmin(y[tail])]]
    return x[idx], y[idx]


def spectrum_view(spec: Spectrum, max_points: int = MAX_POINTS) -> dict:
    """The search spectrum for display: frequency (Hz) and power in dB over the mean noise floor.

    The floor is the median bin over ``ln 2`` (the mean of the exponential noise bins), so a
    line's height is close to its SNR per bin.
    """
    power = np.asarray(spec.power, float)
    floor = float(np.median(power)) / LN2
    f = spec.f0_hz + spec.df_hz * np.arange(power.size)
    db = 10 * np.log10(np.maximum(power, 1e-300) / max(floor, 1e-300))
    fx, dx = _peak_decimate(f, db, max_points)
    return {"f_hz": [float(v) for v in fx], "power_db": [round(float(v), 2) for v in dx],
            "df_hz": float(spec.df_hz), "bins": int(power.size), "complex": bool(spec.complex_input),
            "floor_v2": _f(floor / spec.window_power)}


def _line_marks(s: FrameState) -> list[dict]:
    """Every line the chain planned (used or not) and the baseband Doppler lines."""
    st = s.settings
    out = []
    kinds = {"S": "tone", "U": "doppler_upper", "L": "doppler_lower"}
    for fam in s.families:
        snr = fam.snr_db
        for i, tone in enumerate(fam.tone_hz):
            clash = not math.isfinite(float(fam.phase_var[i]))
            used = (not clash) and bool(snr[i] >= st.min_line_snr_db)
            why = "clash with another line" if clash else (None if used else f"SNR below {st.min_line_snr_db:g} dB")
            out.append({"f_hz": float(fam.line_hz[i]), "kind": kinds.get(fam.name, fam.name), "family": fam.name,
                        "tone_hz": float(tone), "target": int(fam.target), "snr_db": _f(snr[i]) if not clash else None,
                        "used": used, "why_not": why})
    iq = bool(s.spectrum is not None and s.spectrum.complex_input)
    for k, d in enumerate([d for d in s.dopplers if d.detected], start=1):
        out.append({"f_hz": float(d.fd_hz if iq else abs(d.fd_hz)), "kind": "doppler", "family": "D", "tone_hz": None,
                    "target": k, "snr_db": None, "used": True, "why_not": None})
    return out


def _ghost_marks(s: FrameState, marks: list[dict]) -> list[dict]:
    """Products of the tones, and their copies shifted by the Doppler lines found (or by the beat
    of two), that stand above the Doppler search's threshold: lines the chain left out."""
    spec, st, frame = s.spectrum, s.settings, s.frame
    if spec is None:
        return []
    tones = tuple(float(t) for t in frame.tones_hz)
    fmax = spec.f0_hz + spec.df_hz * (spec.power.size - 1)
    base = np.concatenate([[0.0], tones, intermod_frequencies(tones, max(float(fmax), max(tones) + fd_max(tones, st)),
                                                                  fs_hz=spec.fs_hz)])
    found = [d.fd_hz for d in s.dopplers if d.detected]
    shifts = [(0.0, "product", None)] + [(fd, "ghost", k) for k, fd in enumerate(found, start=1)]
    shifts += [(a + sg * b, "ghost", None) for i, a in enumerate(found) for b in found[i + 1:] for sg in (1, -1)]
    floor = local_floor(spec.power, mirror_dc=not spec.complex_input)
    taken = np.array([m["f_hz"] for m in marks] + list(tones) + [0.0], float)
    tol = max(st.doppler_min_bins, 2) * spec.df_hz
    out, seen = [], []
    for sh, kind, k in shifts:
        cand = np.concatenate([base + sh, -base + sh]) if spec.complex_input else np.abs(np.concatenate([base + sh,
                                                                                                       base - sh]))
        for f in np.unique(np.round(cand, 3)):
            if f < spec.f0_hz or f > fmax or (kind == "product" and f in (0.0, *tones)):
                continue
            if np.min(np.abs(taken - f)) < tol or any(abs(f - g) < tol for g in seen):
                continue
            b = int(spec.bin_of(f))
            lo, hi = max(b - 1, 0), min(b + 2, spec.power.size)
            ratio = float(np.max(spec.power[lo:hi]) / floor[b])
            if ratio > st.doppler_threshold:
                seen.append(float(f))
                out.append({"f_hz": float(f), "kind": kind, "family": "G", "tone_hz": None, "target": k,
                            "snr_db": _f(10 * math.log10(ratio)), "used": False,
                            "why_not": "intermodulation product of the tones" if kind == "product" else
                            "a product shifted by a Doppler line (or the beat of two targets): not a target"})
    return out


def cost_view(obs: Observations, tau0_s: float, interval_m: tuple[float, float], chosen_m: float,
              points_per_cycle: int = 16, max_points: int = MAX_POINTS) -> dict:
    """``J(L)`` on the grid :func:`~mtcw_core.ranging.triangulation.resolve_ml` searches, the chosen
    range and the runner-up (the highest of its refined runners-up: local maxima more than half the
    finest synthetic wavelength from the chosen one; ``None`` when there is none), whose J gives
    the point's margin."""
    lo, hi = interval_m
    lam_min = float(np.min(obs.synthetic_wavelengths_m))
    step = lam_min / points_per_cycle
    grid = np.arange(lo, hi + step, step)
    vals = np.concatenate([cost(obs, grid[i: i + 65536], tau0_s) for i in range(0, grid.size, 65536)])
    alts = np.asarray(resolve_ml(obs, tau0_s, interval_m, points_per_cycle).alternatives_m, float)
    j_alts = cost(obs, alts, tau0_s) if alts.size else np.zeros(0)
    ru = int(np.argmax(j_alts)) if alts.size else None
    j_best = float(cost(obs, [chosen_m], tau0_s)[0])
    gx, gy = _peak_decimate(grid, vals, max_points)
    return {"range_m": [float(v) for v in gx], "j": [round(float(v), 5) for v in gy],
            "interval_m": [float(lo), float(hi)], "step_m": step, "chosen_m": float(chosen_m), "j_chosen": j_best,
            "runner_up_m": None if ru is None else float(alts[ru]),
            "j_runner_up": None if ru is None else float(j_alts[ru]),
            "margin": None if ru is None or j_best <= 0 else float(np.clip(1 - max(j_alts[ru], 0.0) / j_best, 0, 1)),
            "unambiguous_range_m": _f(unambiguous_range(obs.df_hz))}


def seed_view(obs: Observations, tau0_s: float, interval_m: tuple[float, float], max_rows: int = MAX_ROWS,
              max_points: int = MAX_POINTS) -> dict:
    """The seed's candidate matrix: its rows around the chosen one, the whole ``sigma_k`` curve
    (decimated keeping the minima) and the chosen row."""
    lo, hi = interval_m
    m, sigma_k, lam = candidate_matrix(obs, tau0_s, hi, lo)
    k = int(np.argmin(sigma_k))
    a = max(0, min(k - max_rows // 2, m.shape[0] - max_rows))
    rows = slice(a, a + max_rows)
    cx, cy = _peak_decimate(m[:, 0], sigma_k, max_points, keep="min")
    second = np.sort(sigma_k)[1] if sigma_k.size > 1 else None
    return {"synthetic_wavelengths_m": [float(v) for v in lam], "first_row": a,
            "candidates_m": [[float(v) for v in row] for row in m[rows]],
            "sigma_k_m": [float(v) for v in sigma_k[rows]],
            "curve_range_m": [float(v) for v in cx], "curve_sigma_k_m": [float(v) for v in cy],
            "rows": int(m.shape[0]), "chosen_row": k, "chosen_m": float(m[k, 0]), "sigma_k_chosen_m": float(sigma_k[k]),
            "sigma_k_second_m": None if second is None else float(second)}


def _candidates(s: FrameState) -> list[dict]:
    """Per target candidate with observations: its cost curve, its seed matrix, its point."""
    out = []
    reported = {id(t) for t in s.result.targets}
    points = dict(s.candidates)
    dets = [d for d in s.dopplers if d.detected]
    for k, obs in sorted(s.observations.items()):
        p = points.get(k)
        lo, hi, ambiguous = _search_interval(s.settings, unambiguous_range(obs.df_hz), s.coarse)
        entry: dict[str, Any] = {
            "candidate": k, "doppler_hz": float(dets[k - 1].fd_hz) if k else 0.0,
            "reported": p is not None and id(p) in reported, "cycle_ambiguous": bool(ambiguous),
            "pairs": {"df_hz": [float(v) for v in obs.df_hz], "phase_rad": [float(v) for v in obs.phase_rad],
                      "weight": [float(v) for v in obs.weight]},
            "point": None if p is None else {key: (_f(v) if isinstance(v, float) else v) for key, v in vars(p).items()},
        }
        tau0 = s.reference.tau0_s
        chosen = p.range_m if p is not None and math.isfinite(p.range_m) else 0.5 * (lo + hi)
        entry["cost"] = cost_view(obs, tau0, (lo, hi), chosen, s.settings.points_per_cycle)
        entry["seed"] = seed_view(obs, tau0, (lo, hi))
        out.append(entry)
    return out


def explain_frame(frame: Frame, settings: ChainSettings | str = "balanced", calibration: Calibration | None = None,
                  max_points: int = MAX_POINTS) -> dict:
    """Run the chain on ``frame`` and return what it saw and chose, as JSON-able data.

    Parameters
    ----------
    frame : Frame
    settings : ChainSettings or profile name
    calibration : Calibration, optional
    max_points : int
        Display points of the spectrum at most.

    Returns
    -------
    dict
        ``seq``, ``source``, ``t_ns``, ``profile``, ``status`` (``ok``, ``no_target``, ``rejected``),
        ``reason``, ``stage_seconds``, ``tones_hz``, ``fs_hz``, ``receiver``, ``truth`` (list of
        {range_m, velocity_mps} or None), ``targets`` (the reported points), ``spectrum``
        (:func:`spectrum_view`, or None when the chain stopped before it), ``lines`` (every line
        marked: ``f_hz``, ``kind`` in tone, doppler_upper, doppler_lower, doppler, product, ghost;
        ``used``, ``why_not``, ``snr_db``, ``target``) and ``candidates`` (per target candidate:
        ``cost`` (:func:`cost_view`), ``seed`` (:func:`seed_view`), ``point``, ``pairs``).
    """
    s = _start(frame, settings, calibration)
    res = s.result
    walk_total(s)
    marks = _line_marks(s)
    out = {
        "seq": int(frame.seq), "source": frame.source, "t_ns": int(frame.t_ns), "profile": res.profile,
        "status": res.status, "reason": res.reason, "stage_seconds": dict(res.stage_seconds),
        "tones_hz": [float(t) for t in frame.tones_hz], "fs_hz": float(frame.fs_hz), "receiver": frame.receiver,
        "truth": None if frame.truth is None else [t.to_dict() for t in frame.truth],
        "coarse_range_m": _f(res.coarse_range_m) if res.coarse_range_m is not None else None,
        "targets": [{k: (_f(v) if isinstance(v, float) else v) for k, v in vars(t).items()} for t in res.targets],
        "spectrum": None if s.spectrum is None else spectrum_view(s.spectrum, max_points),
        "lines": marks + _ghost_marks(s, marks),
        "candidates": _candidates(s) if s.reference is not None else [],
    }
    return out


__all__ = ["explain_frame", "spectrum_view", "cost_view", "seed_view", "MAX_POINTS", "MAX_ROWS"]
