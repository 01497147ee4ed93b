"""Echoes as strong as the LO or stronger, beyond the honesty map's ladder: confident-wrong and
confident-false frames.

``python -m mtcw_bench.strong_probe [--frames 3] [--samples 65536,262144,1000000]``

The map's strongest rung is a line SNR of 45 dB; on the bundled ``moving-target`` bench the echo
passes the LO's power near 20 dB of loss, and on one photodiode its self-beat at the tones then
stands above its own LO beats, at the mover's range (issue 12, found in the 2026-11-27 review: the
self-beat reported as a confident ``static`` target). Every combination of receiver (single,
balanced, IQ), record length, echo loss (0, 3, 6, 10 dB) and speed (0, 0.1, 1 m/s) is simulated
once (its first ``--frames`` frames, one seed) and run through every profile twice: with the
bench's laser and jitter declared (as the map does) and with nothing declared (the chain's
defaults). Frames are judged as the map judges them (:func:`mtcw_core.evaluate.judge_frame`,
``|z| > 5`` on an unflagged point: confident wrong; an unflagged point answering no truth:
confident false).
"""

from __future__ import annotations

import argparse
import collections
import itertools

from tqdm import tqdm

from mtcw_core.chain import process_frame
from mtcw_core.evaluate import Z_WRONG, judge_frame
from mtcw_core.profiles import get_profile
from mtcw_core.scene import Scene, load_scene, scene_variant
from mtcw_core.simulate import Simulator

from .honesty import declared, tally

RECEIVERS = ("single", "balanced", "iq")
LOSSES_DB = (0.0, 3.0, 6.0, 10.0)
SPEEDS_MPS = (0.0, 0.1, 1.0)
PROFILES = ("fast", "balanced", "accurate")


def scenes(samples: tuple[int, ...]) -> list[tuple[str, Scene]]:
    """``moving-target`` at every (receiver, record length, loss, speed) of the probe, labelled."""
    mt = load_scene("moving-target")
    return [(f"{rx} N={n} loss={loss:g} dB v={v:g} m/s", scene_variant(
        mt, targets=[{"loss_db": loss, "velocity_mps": v}], digitizer={"samples": n}, receiver={"kind": rx}))
        for rx, n, loss, v in itertools.product(RECEIVERS, samples, LOSSES_DB, SPEEDS_MPS)]


def judge_scene(label: str, sc: Scene, frames: int, seed: int = 5) -> tuple[collections.Counter, list[str]]:
    """One scene's frames through every profile, declared and not: counts of ``frames``, ``cw``
    (confident wrong), ``cf`` (confident false), ``missed`` (truths no point answers) per
    (profile, declared), and a line per confident frame."""
    counts: collections.Counter = collections.Counter()
    lines: list[str] = []
    sims = list(Simulator(sc, seed).frames(frames))
    for prof, dec in itertools.product(PROFILES, (True, False)):
        st = get_profile(prof, **declared(sc)) if dec else get_profile(prof)
        tag = f"{prof}/{'declared' if dec else 'undeclared'}"
        for i, fr in enumerate(sims):
            v = judge_frame(process_frame(fr, st), fr.truth, Z_WRONG)
            if tally(counts, v, tag):
                lines.append(f"{label} {tag} frame {i}: " + "; ".join(
                    f"range z {p.range_z:+.1f} speed z {p.speed_z:+.1f} flags {p.flags}" for p in v.points))
    return counts, lines


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m mtcw_bench.strong_probe", description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=3, help="frames per scene (default 3)")
    ap.add_argument("--samples", default="65536,262144,1000000", help="record lengths (comma-separated)")
    a = ap.parse_args(argv)
    total: collections.Counter = collections.Counter()
    for label, sc in tqdm(scenes(tuple(int(s) for s in a.samples.split(","))), desc="strong probe", unit="scene"):
        counts, lines = judge_scene(label, sc, a.frames)
        total.update(counts)
        for line in lines:
            tqdm.write("CONFIDENT " + line)
    tags = sorted({t for t, _ in total})
    print(f"{sum(total[(t, 'frames')] for t in tags)} processed frames: confident wrong "
          f"{sum(total[(t, 'cw')] for t in tags)}, confident false {sum(total[(t, 'cf')] for t in tags)}")
    for t in tags:
        print(f"  {t}: frames {total[(t, 'frames')]}, confident wrong {total[(t, 'cw')]}, "
              f"confident false {total[(t, 'cf')]}, missed truths {total[(t, 'missed')]}, flagged points "
              f"{total[(t, 'flagged')]} ({total[(t, 'flagged_right')]} of them right within {Z_WRONG:g} sigma)")


if __name__ == "__main__":
    main()
