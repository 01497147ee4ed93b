"""The speed–accuracy benchmark: a grid of scenes x echo losses x profiles x cycle-resolution
methods, with the machine's reference costs measured in the same run.

Pure computation: returns records (dicts); ``mtcw bench`` writes them and the report
(:mod:`mtcw_bench.report`). Errors against truth and the bounds come from
:mod:`mtcw_core.evaluate`, as for ``mtcw process``.
"""

from __future__ import annotations

import statistics
import time
import tracemalloc
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import scipy.fft

from mtcw_core.chain import get_profile, process_frame
from mtcw_core.evaluate import ErrorLog, range_bound
from mtcw_core.phase import C
from mtcw_core.scene import Scene, load_scene, scene_from_dict, scene_variant
from mtcw_core.simulate import Simulator


@dataclass
class GridSpec:
    """What to run. ``losses_db`` None keeps each scene's own loss."""

    scenes: list[str]
    losses_db: list[float | None]
    profiles: list[str]
    methods: list[str]
    frames: int = 20
    samples: int | None = None  # override the scenes' record length
    seed: int = 7
    seed_points: int | None = None  # override the seed profile's resample length
    profile_losses: dict[str, list[float | None]] = field(default_factory=dict)  # per-profile subset


def _median_time(fn: Callable[[], object], repeat: int = 7) -> float:
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def reference_costs(n: int, seed: int = 0) -> dict[str, float]:
    """One pass over an n-sample float64 frame in memory, and one ``scipy.fft.rfft`` of it (s)."""
    x = np.random.default_rng(seed).standard_normal(n)
    scipy.fft.rfft(x)  # plan / warm caches
    return {"pass_s": _median_time(lambda: float(np.add.reduce(x))), "rfft_s": _median_time(lambda: scipy.fft.rfft(x))}


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
    """Process the frames with one profile and method; statistics against truth and bound."""
    over = {"method": method}
    if profile == "seed" and spec.seed_points:
        over["seed_points"] = spec.seed_points
    settings = get_profile(profile, **over)
    times, status = [], {}
    log = ErrorLog(outlier_m=_finest_wavelength(scene.modulator.tones_hz) / 4)
    peak = 0
    for i, fr in enumerate(frames):
        if i == 0:
            tracemalloc.start()
        t0 = time.perf_counter()
        res = process_frame(fr, settings)
        times.append(time.perf_counter() - t0)
        if i == 0:
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
        status[res.status] = status.get(res.status, 0) + 1
        if fr.truth:
            log.add(res, fr.truth[0])
    n_ok = status.get("ok", 0)
    err = log.summary()
    rec = {
        "profile": profile, "method": method, "frames": len(frames), "status": status,
        "median_time_s": statistics.median(times) if times else None,
        "frames_per_s": 1 / statistics.median(times) if times else None,
        "range_bias_m": err["range_bias_m"], "range_sigma_m": err["range_std_m"],
        "reported_sigma_m": err["median_reported_sigma_m"],
        "outlier_rate": log.outliers / n_ok if n_ok else None,
        "speed_bias_mps": err["speed_bias_mps"], "speed_sigma_mps": err["speed_std_mps"],
        "peak_memory_mb": peak / 2**20,
    }
    if bound is not None:
        rec["crb_range_m"] = bound.range_sigma_m
        rec["crb_speed_mps"] = bound.speed_sigma_mps
        rec["line_snr_db"] = bound.line_snr_db
        if rec["range_sigma_m"]:
            rec["sigma_over_crb"] = rec["range_sigma_m"] / bound.range_sigma_m
    return rec


def run_grid(spec: GridSpec, progress: Callable[[str], None] | None = None) -> dict:
    """Every cell of the grid, plus reference costs per record length. Returns a JSON-able dict."""
    cells, refs = [], {}
    for name in spec.scenes:
        for loss in spec.losses_db:
            sc = _scene_variant(name, loss, spec.samples)
            n = sc.digitizer.samples
            if n not in refs:
                refs[n] = reference_costs(n)
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
                    r = refs[n]
                    if rec["median_time_s"]:
                        rec["time_over_rfft"] = rec["median_time_s"] / r["rfft_s"]
                        rec["time_over_pass"] = rec["median_time_s"] / r["pass_s"]
                    cells.append(rec)
    return {"cells": cells, "reference_costs": {str(k): v for k, v in refs.items()}, "spec": spec.__dict__}


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


__all__ = ["GridSpec", "run_grid", "run_cell", "reference_costs", "simulation_costs"]
