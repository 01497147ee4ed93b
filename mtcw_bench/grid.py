"""The speed–accuracy benchmark: a grid of scenes x echo losses x profiles x cycle-resolution
methods, each cell timed against reference costs measured interleaved with the chain.

How a cell is timed (issue 16, item 1): every repeat processes one frame and, in an order that
rotates from repeat to repeat, in the same process and on the same frame, times the references
of :data:`REFERENCES` (one pass over the volts, one FFT of the volts in float64, in the volts'
own dtype and of the raw codes as stored). The chain's cost of a repeat is its time over the
float64 FFT of *that* repeat; a cell reports the median of those ratios and their spread
(:func:`spread`, the interquartile range over the median), and marks the ratio noisy when the
spread exceeds :data:`NOISY_SPREAD`. Both the chain and the references are warmed up first: a
fresh 1e6-sample rfft costs about twice a warm one (page faults on memory the allocator has not
handed out yet), so a reference timed apart from the chain measures another machine state.

Memory (item 4) is measured in separate passes with :mod:`tracemalloc` (it slows numpy's
allocation paths, so no timing is taken with it on): the peak of one frame above the memory
already held before the call, after a warm-up frame so that caches (windows, plans) filled once
per record length are not counted; what the warm-up frame leaves behind is reported apart.

Pure computation: returns records (dicts); ``mtcw bench`` writes them and the report
(:mod:`mtcw_bench.report`). Errors against truth and the bounds come from
:mod:`mtcw_core.evaluate`, as for ``mtcw process``.
"""

from __future__ import annotations

import gc
import os
import platform
import statistics
import time
import tracemalloc
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import scipy
import scipy.fft

from mtcw_core.chain import STAGE_NAMES, get_profile, process_frame, run_stages
from mtcw_core.dsp.spectrum import fft_backend_name
from mtcw_core.evaluate import ErrorLog, range_bound
from mtcw_core.frame import Frame
from mtcw_core.phase import C
from mtcw_core.results import NoTarget, Rejected
from mtcw_core.scene import Scene, load_scene, scene_from_dict, scene_variant
from mtcw_core.simulate import Simulator

#: A ratio whose spread (:func:`spread`) exceeds this is marked noisy.
NOISY_SPREAD = 0.10
#: The references timed with every repeat of a cell (s each): one pass over the volts
#: (``np.add.reduce``), one FFT of the volts as float64 (``rfft``; ``fft`` of complex128 for an IQ
#: receiver), of the volts in their own dtype (the array the chain's validate stage produces)
#: and of the raw codes of the signal channel as stored.
REFERENCES: tuple[str, ...] = ("pass", "fft_f64", "fft_volts", "fft_raw")
#: The reference every ratio is taken against.
RATIO_REFERENCE = "fft_f64"
#: ... and, when another FFT backend is in force (``--fft-backend``), the same float64 transform
#: on scipy's own pocketfft, timed alongside: the chain on FFTW against the reference of the
#: default install (the targets' own ratio stays against the backend's own rfft)
POCKETFFT_REFERENCE = "fft_f64_pocketfft"
#: The key of the time inside ``process_frame`` that no stage accounts for.
UNACCOUNTED = "unaccounted"


@dataclass
class GridSpec:
    """What to run. ``losses_db`` None keeps each scene's own loss.

    ``repeats`` is the number of timed repeats per cell (at least ``frames``; frames are
    cycled when it is larger, and accuracy is taken over the first pass through them);
    ``profile_frames`` and ``profile_losses`` give a profile fewer frames or losses (``seed``
    costs ~1–3 s a frame).
    """

    scenes: list[str]
    losses_db: list[float | None]
    profiles: list[str]
    methods: list[str]
    frames: int = 20
    samples: int | None = None  # override the scenes' record length
    seed: int = 7
    seed_points: int | None = None  # override the seed profile's resample length
    profile_losses: dict[str, list[float | None]] = field(default_factory=dict)  # per-profile subset
    repeats: int | None = None  # timed repeats per cell (default: frames)
    profile_frames: dict[str, int] = field(default_factory=dict)  # per-profile frame count


def _median_time(fn: Callable[[], object], repeat: int = 7) -> float:
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def spread(values) -> float | None:
    """Relative spread of positive samples: (p75 − p25) / median (interquartile range over median).

    None for fewer than 2 values (no spread can be measured), inf for a zero median.
    """
    v = np.asarray([x for x in values if x is not None], dtype=float)
    if v.size < 2:
        return None
    p25, p50, p75 = np.percentile(v, [25, 50, 75])
    return float((p75 - p25) / p50) if p50 > 0 else float("inf")


def ratio_stats(chain_s, ref_s) -> dict:
    """Per-repeat ratios chain/reference (paired: repeat i of each) and their summary.

    Parameters
    ----------
    chain_s, ref_s : sequences of float, shape (R,), s
        The chain's and the reference's times of the same R repeats.

    Returns
    -------
    dict with ``ratios`` (R,), ``median``, ``spread`` (:func:`spread`), ``noisy`` (spread >
    :data:`NOISY_SPREAD`, or unmeasurable with fewer than 2 repeats) and ``repeats``.
    """
    if len(chain_s) != len(ref_s):
        raise ValueError(f"chain_s and ref_s: {len(chain_s)} vs {len(ref_s)} repeats (they must pair up)")
    ratios = [c / r for c, r in zip(chain_s, ref_s) if r > 0]
    sp = spread(ratios)
    return {"ratios": ratios, "median": statistics.median(ratios) if ratios else None, "spread": sp,
            "noisy": sp is None or sp > NOISY_SPREAD, "repeats": len(ratios)}


def _volts(frame: Frame, settings) -> np.ndarray:
    """The array the chain's validate stage produces for ``frame`` (its dtype is the chain's own)."""
    try:
        return run_stages(frame, settings, until="validate").x
    except (Rejected, NoTarget):
        return frame.signal()


def reference_tasks(frame: Frame, settings) -> dict[str, Callable[[], object]]:
    """The references of :data:`REFERENCES` for one frame, as callables to time.

    The inputs are prepared here (outside any timing): the volts as validate produces them
    (shape (N,), float64 or complex128 today), their float64/complex128 copy and the raw codes of
    the signal channel (for IQ the i channel) as stored (float32 from the simulator; scipy
    converts integer codes to float64 inside the transform, which is then part of its time).
    ``fft_volts`` is left out when the volts are float64 already (it would be ``fft_f64`` again).
    """
    x = _volts(frame, settings)
    x64 = np.ascontiguousarray(x, dtype=np.complex128 if np.iscomplexobj(x) else np.float64)
    raw = np.ascontiguousarray(frame.samples[frame.channels.index("i" if frame.receiver == "iq" else "pd")])
    fft_x = scipy.fft.fft if np.iscomplexobj(x) else scipy.fft.rfft
    tasks = {"pass": lambda: float(np.add.reduce(x).real), "fft_f64": lambda: fft_x(x64),
             "fft_volts": lambda: fft_x(x), "fft_raw": lambda: scipy.fft.rfft(raw)}
    if x64 is x:  # the volts are float64 already: one transform, timed once (its time serves both)
        del tasks["fft_volts"]
    if fft_backend_name() != "pocketfft":
        def pocketfft() -> object:
            with scipy.fft.set_backend("scipy", only=True):
                return fft_x(x64)

        tasks[POCKETFFT_REFERENCE] = pocketfft
    return tasks


def reference_costs(n: int, seed: int = 0) -> dict[str, float]:
    """One pass over an n-sample float64 frame and one ``scipy.fft.rfft`` of it (s), timed alone.

    Kept for quick look-ups only: the benchmark's ratios come from references interleaved with
    the chain (:func:`run_cell`), since a reference timed apart measures another machine state.
    """
    x = np.random.default_rng(seed).standard_normal(n)
    scipy.fft.rfft(x)  # plan / warm caches
    return {"pass_s": _median_time(lambda: float(np.add.reduce(x))), "rfft_s": _median_time(lambda: scipy.fft.rfft(x))}


def peak_memory(frame: Frame, settings, warmup: Frame | None = None) -> dict:
    """Peak memory of one ``process_frame`` call, by :mod:`tracemalloc` (never time with it on).

    The warm-up frame (``warmup``, default ``frame``) is processed first under tracing: what it
    leaves held afterwards (caches filled on first use, e.g. windows) is ``retained_bytes`` and
    is not counted in the peak. The peak is that of the measured call above what was held just
    before it. Allocations outside Python's and numpy's tracked allocators (e.g. pocketfft's
    scratch buffers and plan cache in C++) are not seen.

    Returns
    -------
    dict: ``peak_bytes``, ``retained_bytes`` (B), ``frame_f64_bytes`` (the frame's samples as
    float64: channels x N x 8 B) and ``peak_over_frame_f64``.
    """
    was_tracing = tracemalloc.is_tracing()
    if not was_tracing:
        tracemalloc.start()
    try:
        gc.collect()
        before = tracemalloc.get_traced_memory()[0]
        process_frame(warmup if warmup is not None else frame, settings)
        gc.collect()
        base = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        process_frame(frame, settings)
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        if not was_tracing:
            tracemalloc.stop()
    f64 = int(frame.samples.size) * 8
    return {"peak_bytes": int(peak), "retained_bytes": int(base - before), "frame_f64_bytes": f64,
            "peak_over_frame_f64": peak / f64}


def stage_breakdown(stage_seconds: list[dict[str, float]], total_s: list[float]) -> dict[str, float]:
    """Median time (s) per stage over repeats, and of the time inside no stage.

    Parameters
    ----------
    stage_seconds : one ``FrameResult.stage_seconds`` per repeat (a stage that did not run in a
        repeat counts 0 there)
    total_s : the measured ``process_frame`` time of each repeat (s), shape (R,)

    Returns
    -------
    dict keyed by every name of ``mtcw_core.chain.STAGE_NAMES`` (plus any other stage a
    technique ran), then :data:`UNACCOUNTED` (total minus the sum of stages, per repeat) and
    ``total``. Medians do not add up exactly.
    """
    names = list(STAGE_NAMES) + sorted({k for d in stage_seconds for k in d} - set(STAGE_NAMES))
    out = {k: statistics.median([d.get(k, 0.0) for d in stage_seconds]) if stage_seconds else 0.0 for k in names}
    out[UNACCOUNTED] = statistics.median([t - sum(d.values()) for d, t in zip(stage_seconds, total_s)]) \
        if total_s else 0.0
    out["total"] = statistics.median(total_s) if total_s else 0.0
    return out


def _scene_variant(name: str, loss_db: float | None, samples: int | None) -> Scene:
    sc = load_scene(name)
    upd: dict = {}
    if loss_db is not None:
        upd["targets"] = [{"loss_db": float(loss_db)}]
    if samples is not None:
        upd["digitizer"] = {"samples": int(samples)}
    return scene_variant(sc, **upd) if upd else sc


def _finest_wavelength(tones) -> float:
    t = sorted(tones)
    return C / (2 * (t[-1] - t[0]))


def run_cell(frames: list, scene: Scene, profile: str, method: str, spec: GridSpec, bound) -> dict:
    """Process the frames with one profile and method: accuracy against truth and bound, time
    per frame against the interleaved references, stage breakdown and peak memory."""
    over = {"method": method}
    if profile == "seed" and spec.seed_points:
        over["seed_points"] = spec.seed_points
    settings = get_profile(profile, **over)
    n_frames = min(len(frames), spec.profile_frames.get(profile, len(frames)))
    frames = frames[:n_frames]
    repeats = n_frames if profile in spec.profile_frames else max(n_frames, spec.repeats or 0)
    # 1. memory, tracemalloc on (a pass of its own: no timing with it on)
    mem = peak_memory(frames[-1], settings, warmup=frames[0])
    # 2. warm-up of the chain and the references, untimed, tracemalloc off (a profile given its own
    #    frame count, i.e. seed at ~1-3 s a frame, goes on from the memory pass's two frames)
    if profile not in spec.profile_frames:
        process_frame(frames[0], settings)
    for fn in reference_tasks(frames[0], settings).values():
        fn()
    # 3. timed repeats, references interleaved in rotating order
    status: dict[str, int] = {}
    log = ErrorLog(outlier_m=_finest_wavelength(scene.modulator.tones_hz) / 4)
    times: dict[str, list[float]] = {k: [] for k in ("chain",) + REFERENCES + (POCKETFFT_REFERENCE,)}
    stages: list[dict[str, float]] = []
    for i in range(repeats):
        fr = frames[i % n_frames]
        tasks = reference_tasks(fr, settings)
        out: dict = {}
        tasks["chain"] = lambda: out.setdefault("res", process_frame(fr, settings))
        order = list(tasks)
        k = i % len(order)
        for name in order[k:] + order[:k]:
            t0 = time.perf_counter()
            tasks[name]()
            times[name].append(time.perf_counter() - t0)
        if "fft_volts" not in tasks:
            times["fft_volts"].append(times["fft_f64"][-1])
        res = out["res"]
        stages.append(dict(res.stage_seconds))
        if i < n_frames:
            status[res.status] = status.get(res.status, 0) + 1
            if fr.truth:
                log.add(res, fr.truth[0])
    n_ok = status.get("ok", 0)
    err = log.summary()
    ratio = ratio_stats(times["chain"], times[RATIO_REFERENCE])
    med = {k: statistics.median(v) for k, v in times.items() if v}
    breakdown = stage_breakdown(stages, times["chain"])
    rec = {
        "profile": profile, "method": method, "frames": n_frames, "repeats": repeats, "status": status,
        "median_time_s": med["chain"], "time_spread": spread(times["chain"]),
        "frames_per_s": 1 / med["chain"],
        "time_over_rfft": ratio["median"], "ratio_spread": ratio["spread"], "ratio_noisy": ratio["noisy"],
        "ratios": ratio["ratios"],
        "time_over_rfft_volts": ratio_stats(times["chain"], times["fft_volts"])["median"],
        "time_over_rfft_raw": ratio_stats(times["chain"], times["fft_raw"])["median"],
        "time_over_pass": ratio_stats(times["chain"], times["pass"])["median"],
        "time_over_rfft_pocketfft": (ratio_stats(times["chain"], times[POCKETFFT_REFERENCE])["median"]
                                     if times[POCKETFFT_REFERENCE] else None),
        "pocketfft_rfft_s": med.get(POCKETFFT_REFERENCE),
        "reference_s": {k: med[k] for k in REFERENCES},
        "reference_spread": {k: spread(times[k]) for k in REFERENCES},
        "volts_dtype": str(_volts(frames[0], settings).dtype), "raw_dtype": str(frames[0].samples.dtype),
        "stage_s": breakdown,
        "range_bias_m": err["range_bias_m"], "range_sigma_m": err["range_std_m"],
        "reported_sigma_m": err["median_reported_sigma_m"],
        "outlier_rate": log.outliers / n_ok if n_ok else None,
        "speed_bias_mps": err["speed_bias_mps"], "speed_sigma_mps": err["speed_std_mps"],
        "peak_memory_mb": mem["peak_bytes"] / 2**20, "peak_memory_x_f64": mem["peak_over_frame_f64"],
        "frame_f64_mb": mem["frame_f64_bytes"] / 2**20, "warmup_retained_mb": mem["retained_bytes"] / 2**20,
    }
    for k, v in breakdown.items():
        rec[f"stage_{k}_s"] = v
    if bound is not None:
        rec["crb_range_m"] = bound.range_sigma_m
        rec["crb_speed_mps"] = bound.speed_sigma_mps
        rec["line_snr_db"] = bound.line_snr_db
        if rec["range_sigma_m"]:
            rec["sigma_over_crb"] = rec["range_sigma_m"] / bound.range_sigma_m
    return rec


def _reference_summary(cells: list[dict]) -> dict[str, dict]:
    """Per record length: the median over all cells' medians of each reference (s), for reading."""
    out: dict[str, dict] = {}
    for n in sorted({c["samples"] for c in cells}):
        cs = [c for c in cells if c["samples"] == n]
        r = {f"{k}_s": statistics.median(c["reference_s"][k] for c in cs) for k in REFERENCES}
        r["rfft_s"] = r["fft_f64_s"]  # the name earlier reports used
        r["fft_f64_spread"] = spread([c["reference_s"]["fft_f64"] for c in cs])
        r["volts_dtype"], r["raw_dtype"] = cs[0]["volts_dtype"], cs[0]["raw_dtype"]
        out[str(n)] = r
    return out


def cell_count(spec: GridSpec) -> int:
    """How many cells :func:`run_grid` will run (for a progress bar)."""
    return len(spec.scenes) * len(spec.methods) * sum(
        len([x for x in spec.losses_db if spec.profile_losses.get(p) is None or x in spec.profile_losses[p]])
        for p in spec.profiles)


def run_grid(spec: GridSpec, progress: Callable[[str], None] | None = None) -> dict:
    """Every cell of the grid, with its interleaved reference costs. Returns a JSON-able dict."""
    cells = []
    t_start = time.perf_counter()
    for name in spec.scenes:
        for loss in spec.losses_db:
            sc = _scene_variant(name, loss, spec.samples)
            n = sc.digitizer.samples
            sim = Simulator(sc, spec.seed)
            t0 = time.perf_counter()
            frames = [sim.next_frame() for _ in range(spec.frames)]
            sim_s = (time.perf_counter() - t0) / spec.frames
            bound = range_bound(sc, spec.seed)
            for profile in spec.profiles:
                allowed = spec.profile_losses.get(profile)
                if allowed is not None and loss not in allowed:
                    continue
                for method in spec.methods:
                    if progress:
                        progress(f"{name} loss={loss} {profile}/{method}")
                    rec = run_cell(frames, sc, profile, method, spec, bound)
                    rec.update({"scene": name, "loss_db": sc.targets[0].loss_db, "samples": n,
                                "sim_s_per_frame": sim_s})
                    cells.append(rec)
            del frames
    return {"cells": cells, "reference_costs": _reference_summary(cells), "spec": spec.__dict__,
            "noisy_spread": NOISY_SPREAD, "stage_names": list(STAGE_NAMES), "grid_s": time.perf_counter() - t_start}


def fft_backend() -> str:
    """The FFT backend the chain uses: ``mtcw_core``'s own answer when it has one
    (``mtcw_core.dsp.spectrum.fft_backend()``), else scipy's default."""
    try:
        from mtcw_core.dsp import spectrum
    except ImportError:  # pragma: no cover - mtcw_core is always there
        spectrum = None
    fn = getattr(spectrum, "fft_backend", None)
    if callable(fn):
        try:
            return str(fn())
        except Exception as err:  # a report line must not end the benchmark
            return f"unknown (mtcw_core.dsp.spectrum.fft_backend() raised {type(err).__name__}: {err})"
    return "scipy default (pocketfft)"


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def machine_info() -> dict:
    """What the timings depend on: CPU, cores, load, versions, FFT backend and workers."""
    try:
        usable = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        usable = os.cpu_count()
    try:
        load = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        load = None
    return {"cpu": _cpu_model(), "arch": platform.machine(), "cores": os.cpu_count(), "usable_cores": usable,
            "load_avg": load, "python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__, "fft_backend": fft_backend(), "scipy_fft_workers": scipy.fft.get_workers(),
            "blas_threads": _blas_threads()}


def _blas_threads() -> list[int] | None:
    """Threads of every BLAS/OpenMP pool loaded in this process (threadpoolctl), None without it."""
    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        return None
    return [int(p.get("num_threads", 0)) for p in threadpool_info()]


def simulation_costs(samples: int, repeat: int = 3, seed: int = 1) -> list[dict]:
    """Simulator time per frame as the scene grows: the cost follows what the scene models."""
    base = {
        "name": "ladder", "laser": {"wavelength_m": 1.064e-6, "power_w": 0.05, "linewidth_hz": 0.0},
        "modulator": {"tones": [{"frequency_hz": f} for f in (500e6, 700e6, 950e6)]},
        "targets": [{"range_m": 1.2, "loss_db": 20.0}], "digitizer": {"sample_rate_hz": 5e9, "samples": samples},
    }
    ladder = scene_from_dict(base)

    def variant(**over) -> Scene:
        return scene_variant(ladder, **over)

    steps: list[tuple[str, Scene]] = [
        ("static coherent 3-tone, noiseless", variant()),
        ("+ shot & thermal noise", variant(noise={"shot": True, "thermal": True})),
        ("+ 12-bit ADC", variant(noise={"shot": True, "thermal": True}, digitizer={"adc_bits": 12})),
        ("+ laser phase noise (100 kHz)", variant(noise={"shot": True, "thermal": True},
                                                  laser={"linewidth_hz": 100e3})),
        ("+ moving target", variant(noise={"shot": True, "thermal": True}, laser={"linewidth_hz": 100e3},
                                    targets=[{"range_m": 1.2, "velocity_mps": 0.5, "loss_db": 20.0}])),
        ("+ 6 tones", variant(noise={"shot": True, "thermal": True}, laser={"linewidth_hz": 100e3},
                              targets=[{"range_m": 1.2, "velocity_mps": 0.5, "loss_db": 20.0}],
                              modulator={"tones": [{"frequency_hz": f} for f in
                                                   (20e6, 500e6, 670e6, 700e6, 890e6, 950e6)]})),
        ("+ quasi-CW gate and reference", variant(noise={"shot": True, "thermal": True},
                                                  laser={"linewidth_hz": 100e3},
                                                  pulsing={"period_s": samples / 5e9, "duty": 0.2,
                                                           "reference_channel": True})),
        ("+ IQ receiver", variant(noise={"shot": True, "thermal": True}, laser={"linewidth_hz": 100e3},
                                  targets=[{"range_m": 1.2, "velocity_mps": 0.5, "loss_db": 20.0}],
                                  receiver={"kind": "iq"})),
    ]
    out = []
    for label, sc in steps:
        sim = Simulator(sc, seed)
        sim.frame(0)
        t = _median_time(lambda: sim.frame(1), repeat)
        out.append({"scene": label, "samples": samples, "sim_s_per_frame": t})
    return out


__all__ = ["GridSpec", "run_grid", "run_cell", "reference_tasks", "reference_costs", "ratio_stats", "spread",
           "peak_memory", "stage_breakdown", "cell_count", "machine_info", "fft_backend", "simulation_costs",
           "NOISY_SPREAD", "REFERENCES", "RATIO_REFERENCE", "UNACCOUNTED"]
