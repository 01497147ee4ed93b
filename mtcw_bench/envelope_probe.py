"""Random scenes across the bench's envelope, between the honesty map's rows: confident-wrong and
confident-false frames.

``python -m mtcw_bench.envelope_probe [--scenes 300] [--first 0] [--frames 2]``

The map varies one or two axes at a time; this draws every axis at once, scene ``i`` from its own
seed (``1000 + i``, so any scene is reproduced by ``--first i --scenes 1``):

- tone plan: 500/700/950 MHz, 130/510/710/950 MHz, the 6-tone plan, or 3-4 random tones on a
  10 MHz grid in 100-990 MHz;
- 1064 or 1550 nm; linewidth 0, 100 kHz or 1 MHz; LO fraction 0.01, 0.1 or 0.5;
- one target, or two (35 %): 0.2-20 m, 0-80 dB loss, static (35 %) or moving at up to 0.001,
  0.01 or 0.4 x the smallest tone spacing in Doppler, either way;
- receiver single, balanced or IQ; shot and thermal noise, 20 ps trigger jitter or none, RF tone
  drift 0.01 rad per frame or none, RIN -150 dB/Hz (30 %); 2^16 or 2^18 samples, float volts or
  an 8/12-bit ADC (30 %).

Each scene's first ``--frames`` frames run through every profile with the bench declared as the map
declares it (:func:`mtcw_bench.honesty.declared`) and its drift as its random walk's rms at that
frame (``tone_phase_sigma_rad``). Judged as the map judges (:func:`mtcw_core.evaluate.judge_frame`).
A scene the simulator refuses (a target reaching the sensor) is counted and skipped. The summary
also gives the cycle slips the chain expects among its unflagged points (the sum of their
``cycle_slip_prob``, each under ``ChainSettings.cycle_slip_max``): a confident wrong range that is a
slipped cycle is that many times expected, not a failure of the slip model, while they are few.
"""

from __future__ import annotations

import argparse
import collections
import json

import numpy as np
from tqdm import tqdm

from mtcw_core.chain import process_frame
from mtcw_core.evaluate import Z_WRONG, judge_frame
from mtcw_core.profiles import get_profile
from mtcw_core.scene import Scene, SceneError, load_scene, scene_variant
from mtcw_core.simulate import Simulator

from .honesty import SIX_TONES, declared, tally

TONE_PLANS = ((500e6, 700e6, 950e6), (130e6, 510e6, 710e6, 950e6), SIX_TONES)
PROFILES = ("fast", "balanced", "accurate")


def draw(i: int) -> dict:
    """Scene ``i``'s changes to ``moving-target`` (for :func:`~mtcw_core.scene.scene_variant`)."""
    r = np.random.default_rng(1000 + i)
    plan = int(r.integers(4))
    tones = list(TONE_PLANS[plan]) if plan < 3 else sorted(
        (r.choice(np.arange(10, 100), int(r.integers(3, 5)), replace=False) * 10e6).tolist())
    lam = (1.064e-6, 1.55e-6)[r.integers(2)]
    linewidth = (0.0, 1e5, 1e6)[r.integers(3)]
    spacing = float(np.min(np.diff(sorted(tones))))
    targets = []
    for _ in range(1 + int(r.random() < 0.35)):
        v = 0.0 if r.random() < 0.35 else float(r.uniform(-1, 1) * r.choice([1e-3, 1e-2, 0.4]) * spacing * lam / 2)
        targets.append({"range_m": float(r.uniform(0.2, 20)), "velocity_mps": v, "loss_db": float(r.uniform(0, 80))})
    noise = {"shot": True, "thermal": True, "trigger_jitter_s": (0.0, 2e-11)[r.integers(2)],
             "rf_phase_drift_rad": (0.0, 0.01)[r.integers(2)]}
    if r.random() < 0.3:
        noise["rin_db_per_hz"] = -150.0
    digitizer = {"samples": int((2**16, 2**18)[r.integers(2)])}
    if r.random() < 0.3:
        digitizer["adc_bits"] = int((8, 12)[r.integers(2)])
    return {"targets": targets, "digitizer": digitizer, "noise": noise,
            "receiver": {"kind": ("single", "balanced", "iq")[r.integers(3)]},
            "laser": {"wavelength_m": lam, "linewidth_hz": linewidth},
            "lo_fraction": float(r.choice([0.01, 0.1, 0.5])),
            "modulator": {"tones": [{"frequency_hz": f} for f in tones]}}


def judge_scene(i: int, frames: int, base: Scene | None = None) -> tuple[collections.Counter, list[str]]:
    """Scene ``i`` through every profile: counts (``frames``, ``cw``, ``cf``, ``missed``, statuses,
    ``invalid``/``refused`` scenes) and a line per confident frame."""
    counts: collections.Counter = collections.Counter()
    changes = draw(i)
    try:
        sc = scene_variant(base or load_scene("moving-target"), **changes)
        sims = list(Simulator(sc, i).frames(frames))
    except SceneError as err:
        counts["refused" if "reached the sensor" in str(err) else "invalid"] += 1
        return counts, []
    lines = []
    for prof in PROFILES:
        for j, fr in enumerate(sims):
            st = get_profile(prof, tone_phase_sigma_rad=sc.noise.rf_phase_drift_rad * (j + 1) ** 0.5, **declared(sc))
            res = process_frame(fr, st)
            v = judge_frame(res, fr.truth, Z_WRONG)
            counts[res.status] += 1
            # the cycle slips the chain itself expects among the points it reports unflagged
            counts["slips_expected"] += sum(t.cycle_slip_prob for t, q in zip(res.targets, v.points) if not q.flagged)
            if tally(counts, v):
                lines.append(f"scene {i} {prof} frame {j}: " + "; ".join(
                    f"{q.range_m:.4f} m {q.velocity_mps:+.4f} m/s range z {p.range_z} speed z {p.speed_z} flags "
                    f"{p.flags}" for p, q in zip(v.points, res.targets)) + " " + json.dumps(changes))
    return counts, lines


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m mtcw_bench.envelope_probe", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=int, default=300, help="scenes drawn (default 300)")
    ap.add_argument("--first", type=int, default=0, help="index of the first scene (default 0)")
    ap.add_argument("--frames", type=int, default=2, help="frames per scene (default 2)")
    a = ap.parse_args(argv)
    base = load_scene("moving-target")
    total: collections.Counter = collections.Counter()
    for i in tqdm(range(a.first, a.first + a.scenes), desc="envelope probe", unit="scene"):
        counts, lines = judge_scene(i, a.frames, base)
        total.update(counts)
        for line in lines:
            tqdm.write("CONFIDENT " + line)
    print(f"{a.scenes} scenes ({total['refused']} refused by the simulator: a target reaching the sensor), "
          f"{total['frames']} processed frames: confident wrong {total['cw']}, confident false {total['cf']}; "
          f"ok {total['ok']}, no_target {total['no_target']}, rejected {total['rejected']}, "
          f"missed truths {total['missed']}; flagged points {total['flagged']} ({total['flagged_right']} of them "
          f"right within {Z_WRONG:g} sigma); cycle slips the chain expects among its unflagged points "
          f"(the sum of their cycle_slip_prob) {total['slips_expected']:.3g}")


if __name__ == "__main__":
    main()
