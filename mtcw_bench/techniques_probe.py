"""Random scenes for the dissertation's other techniques (PE-MTCW, AB-MTCW, PToF): confident-wrong and
confident-false frames, as the envelope probe counts them for the PB chain.

``python -m mtcw_bench.techniques_probe --technique pe|ab|ptof [--scenes 400] [--first 0] [--frames 2]``

Scene ``i`` is drawn from its own seed (reproduced by ``--first i --scenes 1``):

- ``pe``: section 4.3's bench (``pe-fast-target``: 4 tones 75-2450 MHz, reference mirror 10 cm,
  16.384 GS/s, 2^16 samples, shot and thermal noise) with one target, or two (30 %), at 0.5-120 m
  (the tones fold it into 5.996 m), moving at 0.03-40 m/s either way, 10-75 dB of loss, under an
  ideal, 100 kHz or 1 MHz laser, declared;
- ``ab``: the AB bench (``ab-bench``: 6 tones 79-2623 MHz, 1540 nm, reference mirror 3 cm) at 2^16
  or 2^18 samples, with one target, or two (25 %), at 0.05-37 m (``c/(8*gcd)`` = 37.5 m), still
  (50 %) or moving at 0.01-3 m/s, 25-65 dB of loss, the reference arm 25-50 dB down, under an
  ideal, 500 kHz or 5 MHz laser; its reference-only calibration from 4 frames of the same bench
  with the target arm blocked (``ab.derive_reference``);
- ``ptof``: the mode-locked PToF bench (``ptof-bench``: 25 MHz pulses, 5 GHz detector, 20 GS/s,
  reference mirror 3 cm) at 2^14 or 2^16 samples behind an 8- or 12-bit ADC, pulses of 0.5-32 ps,
  one target, or two (25 %), at 0.1-5.9 m (the repetition's 6 m), 5-45 dB of loss, the reference
  arm 3-25 dB down; ranges from a zero at the reference mirror.

Each frame runs through ``balanced`` and is judged as the honesty map judges
(:func:`mtcw_core.evaluate.judge_frame`; a PE range modulo its unambiguous range). The summary also
gives the confident frames of one- and two-target scenes apart (AB fits one target) and the
unflagged points' speed z spread (rms).
"""

from __future__ import annotations

import argparse
import collections

import numpy as np
from tqdm import tqdm

from mtcw_core.calibration import Calibration
from mtcw_core.chain import process_frame
from mtcw_core.evaluate import Z_WRONG, judge_frame
from mtcw_core.phase import C
from mtcw_core.profiles import get_profile
from mtcw_core.ranging import ab
from mtcw_core.scene import Scene, SceneError, load_scene, scene_variant
from mtcw_core.simulate import Simulator

from .honesty import tally

TECHNIQUES = ("pe", "ab", "ptof")
BENCHES = {"pe": "pe-fast-target", "ab": "ab-bench", "ptof": "ptof-bench"}


def _signed_speed(rng: np.random.Generator, lo_exp: float, hi_exp: float) -> float:
    return float(rng.choice([-1.0, 1.0]) * 10 ** rng.uniform(lo_exp, hi_exp))


def draw(technique: str, i: int) -> dict:
    """Scene ``i``'s changes to the technique's bench (see the module docstring)."""
    if technique == "pe":
        rng = np.random.default_rng(i)

        def target() -> dict:
            return {"range_m": float(rng.uniform(0.5, 120.0)), "velocity_mps": _signed_speed(rng, -1.5, 1.6),
                    "loss_db": float(rng.uniform(10.0, 75.0))}
        targets = [target()]
        laser = {"linewidth_hz": float(rng.choice([0.0, 1e5, 1e6]))}
        if rng.random() < 0.3:
            targets.append(target())
        return {"targets": targets, "laser": laser}
    if technique == "ptof":
        return _draw_ptof(i)
    rng = np.random.default_rng(10_000 + i)
    samples = int(rng.choice([2**16, 2**18]))

    def target() -> dict:
        v = 0.0 if rng.random() < 0.5 else _signed_speed(rng, -2.0, 0.5)
        return {"range_m": float(rng.uniform(0.05, 37.0)), "velocity_mps": v, "loss_db": float(rng.uniform(25.0, 65.0))}
    targets = [target()] + ([target()] if rng.random() < 0.25 else [])
    return {"digitizer": {"samples": samples}, "targets": targets,
            "laser": {"linewidth_hz": float(rng.choice([0.0, 5e5, 5e6]))},
            "architecture": {"reference_loss_db": float(rng.uniform(25.0, 50.0))}}


def _draw_ptof(i: int) -> dict:
    rng = np.random.default_rng(20_000 + i)

    def target() -> dict:
        v = 0.0 if rng.random() < 0.6 else _signed_speed(rng, -2.0, 1.0)
        return {"range_m": float(rng.uniform(0.1, 5.9)), "loss_db": float(rng.uniform(5.0, 45.0)), "velocity_mps": v}
    targets = [target()] + ([target()] if rng.random() < 0.25 else [])
    return {"targets": targets,
            "digitizer": {"samples": int(rng.choice([2**14, 2**16])), "adc_bits": int(rng.choice([8, 12]))},
            "ptof": {"pulse_width_s": float(10 ** rng.uniform(-12.3, -10.5))},
            "architecture": {"reference_loss_db": float(rng.uniform(3.0, 25.0))}}


def _calibration(technique: str, sc: Scene, seed: int) -> Calibration | None:
    """AB's reference-only calibration: the same bench, its target arm blocked; PToF's zero at
    the reference mirror (``tau0 = -2*L_ref/c``: ranges from the calibrated zero, as the truth's)."""
    if technique == "ptof":
        return Calibration(tones_hz=tuple(sc.tones_hz), tone_phases_rad=tuple(0.0 for _ in sc.tones_hz),
                           tau0_s=-2 * sc.architecture.reference_range_m / C)
    if technique != "ab":
        return None
    blocked = scene_variant(sc, targets=[{"loss_db": 300.0, "velocity_mps": 0.0}])  # still: it must not reach the sensor
    return ab.derive_reference(Simulator(blocked, seed).frames(4), sc.architecture.reference_range_m)


def judge_scene(technique: str, i: int, frames: int) -> tuple[collections.Counter, list[str], list[float]]:
    """Scene ``i``: counts (as :func:`mtcw_bench.honesty.tally`, with statuses and ``refused``
    scenes), a line per confident frame, and the unflagged points' speed z."""
    counts: collections.Counter = collections.Counter()
    changes = draw(technique, i)
    base = load_scene(BENCHES[technique])
    try:
        sc = scene_variant(base, **changes)
        sims = list(Simulator(sc, i).frames(frames))
        cal = _calibration(technique, sc, i)
    except SceneError as err:
        counts["refused" if "reached the sensor" in str(err) else "invalid"] += 1
        return counts, [], []
    settings = get_profile("balanced", technique=technique, laser_linewidth_hz=sc.laser.linewidth_hz)
    lines, zs = [], []
    for j, fr in enumerate(sims):
        res = process_frame(fr, settings, cal)
        v = judge_frame(res, fr.truth, Z_WRONG)
        counts[res.status] += 1
        zs += [p.speed_z for p in v.points if p.truth_index is not None and not p.flagged and p.speed_z is not None]
        confident = tally(counts, v)
        counts[f"confident_{len(fr.truth)}"] += int(confident)  # AB assumes one target: counted apart
        if confident:
            lines.append(f"scene {i} frame {j}: " + "; ".join(
                f"{q.range_m:.4f} m {q.velocity_mps:+.4f} m/s range z {p.range_z} speed z {p.speed_z}"
                for p, q in zip(v.points, res.targets)) + f" truth {[(t.range_m, t.velocity_mps) for t in fr.truth]}"
                + f" {changes}")
    return counts, lines, zs


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m mtcw_bench.techniques_probe", description=__doc__.split("\n\n")[0])
    ap.add_argument("--technique", choices=TECHNIQUES, required=True)
    ap.add_argument("--scenes", type=int, default=400, help="scenes drawn (default 400)")
    ap.add_argument("--first", type=int, default=0, help="index of the first scene (default 0)")
    ap.add_argument("--frames", type=int, default=2, help="frames per scene (default 2)")
    a = ap.parse_args(argv)
    total: collections.Counter = collections.Counter()
    zs: list[float] = []
    for i in tqdm(range(a.first, a.first + a.scenes), desc=f"{a.technique} probe", unit="scene"):
        counts, lines, z = judge_scene(a.technique, i, a.frames)
        total.update(counts)
        zs += z
        for line in lines:
            tqdm.write("CONFIDENT " + line)
    z = np.abs(np.asarray(zs, float))
    spread = (f"unflagged speed z: {z.size} points, rms {np.sqrt(np.mean(z**2)):.2f}, largest {z.max():.2f}"
              if z.size else "no unflagged speed")
    print(f"{a.technique}: {a.scenes} scenes ({total['refused']} refused by the simulator), {total['frames']} frames: "
          f"confident wrong {total['cw']}, confident false {total['cf']}; ok {total['ok']}, no_target "
          f"{total['no_target']}, rejected {total['rejected']}, missed truths {total['missed']}; flagged points "
          f"{total['flagged']} ({total['flagged_right']} of them right within {Z_WRONG:g} sigma); confident frames of "
          f"one-target scenes {total['confident_1']}, of two-target scenes {total['confident_2']}; {spread}")


if __name__ == "__main__":
    main()
