"""A probe of several movers beyond the honesty map's grid: confident-wrong and confident-false frames.

Two and three movers, Dopplers from 1 to 300 record bins (2^16 samples at 0.65536 GS/s, 1550 nm: 10 kHz
and 7.75 mm/s a bin), echo losses from 0 dB (an echo as strong as the LO) to 40 dB, three receivers,
pairs closer than the search's guard, a mover at the sum of two others, 2^18 samples and a 100 kHz laser
for some: where one photodiode's echoes beat with each other (one is the other's LO), where two movers
share one Doppler line, where a line is another pair's beat. Every frame is judged against the truth
(:func:`mtcw_core.evaluate.judge_frame`, |z| > 5 unflagged = confident wrong; an unflagged point that
answers no truth = confident false).

Usage::

    python -m mtcw_bench.movers_probe [--sets main,sweep,near,lw,three,equal,long,ctrl,triplet] [--out FILE.json]

619 configurations, 5451 frames over the three profiles in all sets, ~10 min on one core. The honesty map keeps the probe's telling cases as
rows of its ``cases`` slice (``movers: ...``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from tqdm import tqdm

from mtcw_core.chain import process_frame
from mtcw_core.evaluate import judge_frame
from mtcw_core.profiles import get_profile
from mtcw_core.scene import scene_variant
from mtcw_core.simulate import Simulator

from .honesty import _movers

PROFILES = ("fast", "balanced", "accurate")
PAIRS = [(10, 25), (12, 40), (8, 16), (20, 40), (30, 45), (40, 42), (40, 90), (40, 80), (60, 200), (50, 150),
         (100, 103), (150, 300), (12, 300), (25, 50)]


def _runs(which: str) -> list[dict]:
    """The configurations of one set: bins, losses (first target's; each further one ``step`` dB
    more), receiver, frames, samples, laser linewidth."""
    out: list[dict] = []

    def add(bins, loss, rx, frames=3, n=2**16, lw=0.0, step=2.0):
        out.append(dict(bins=tuple(bins), losses=tuple(max(loss + step * i, 0.0) for i in range(len(bins))),
                        rx=rx, frames=frames, n=n, lw=lw))

    if which == "main":
        for rx in ("single", "balanced", "iq"):
            for pr in PAIRS:
                for loss in (0.0, 6.0, 20.0, 40.0):
                    add(pr, loss, rx)
    elif which == "sweep":  # across the echo-echo / echo-LO crossover, one photodiode
        for pr in ((12, 40), (40, 90), (60, 200), (12, 300), (50, 150), (10, 25)):
            for loss in (8.0, 10.0, 12.0, 14.0, 16.0):
                add(pr, loss, "single")
    elif which == "near":  # |fd1 - fd2| of a few bins
        for pr in ((40, 41), (40, 43), (40, 44), (60, 62), (100, 101), (100, 102), (200, 202), (40, 42), (45, 47)):
            for loss in (10.0, 20.0, 30.0, 40.0):
                for rx in ("single", "balanced", "iq"):
                    add(pr, loss, rx)
    elif which == "lw":  # a 100 kHz laser
        for pr in ((12, 40), (40, 90), (60, 200), (12, 300), (40, 42), (20, 40)):
            for loss in (0.0, 6.0, 20.0, 40.0):
                for rx in ("single", "iq"):
                    add(pr, loss, rx, lw=100e3)
    elif which == "three":
        for pr in ((12, 40, 90), (40, 90, 200), (20, 50, 130), (40, 80, 120), (15, 45, 60)):
            for loss in (0.0, 6.0, 20.0, 40.0):
                for rx in ("single", "balanced", "iq"):
                    add(pr, loss, rx)
    elif which == "long":
        for pr in ((12, 40), (40, 90), (12, 300), (40, 42), (60, 200)):
            for loss in (0.0, 6.0, 20.0, 40.0):
                for rx in ("single", "iq"):
                    add(pr, loss, rx, frames=2, n=2**18)
    elif which == "equal":  # equal losses, and the stronger echo on the faster mover
        for pr in ((12, 40), (40, 90), (60, 200), (12, 300), (40, 42)):
            for loss in (0.0, 6.0, 10.0, 20.0, 40.0):
                for step in (0.0, -2.0):
                    add(pr, loss, "single", step=step)
    elif which == "ctrl":
        for pr in ((40, 42), (40, 41), (100, 102), (60, 62)):
            for loss in (10.0, 20.0, 40.0):
                for rx in ("single", "balanced", "iq"):
                    add(pr, loss, rx, step=0.0)
        for pr in ((20, 40), (40, 80), (25, 50), (30, 90), (45, 60)):
            for loss in (8.0, 10.0, 12.0, 14.0, 16.0):
                add(pr, loss, "single")
        for pr in ((12, 40), (12, 300), (40, 90)):
            for loss in (8.0, 12.0, 16.0):
                for rx in ("balanced", "iq"):
                    add(pr, loss, rx)
    elif which == "triplet":  # fd3 = fd1 + fd2: a real mover on the other two's beat
        for pr in ((15, 45, 60), (20, 50, 70), (40, 60, 100), (30, 90, 120)):
            for loss in (20.0, 30.0, 40.0):
                for rx in ("single", "balanced", "iq"):
                    add(pr, loss, rx)
    else:
        raise ValueError(f"--sets: unknown set {which!r}")
    return out


SETS = ("main", "sweep", "near", "lw", "three", "equal", "long", "ctrl", "triplet")


def run_config(cfg: dict, seed: int = 7) -> list[dict]:
    """One configuration's frames through every profile: a row per profile with its counts."""
    sc = _movers(cfg["bins"], cfg["losses"], cfg["rx"])
    if cfg["n"] != 2**16 or cfg["lw"]:
        sc = scene_variant(sc, digitizer={"samples": cfg["n"]}, laser={"linewidth_hz": cfg["lw"]})
    frames = list(Simulator(sc, seed).frames(cfg["frames"]))
    rows = []
    for prof in PROFILES:
        st = get_profile(prof)
        counts = dict(cw=0, cf=0, missed=0, flagged_wrong=0)
        for fr in frames:
            v = judge_frame(process_frame(fr, st), fr.truth, 5.0)
            counts["cw"] += int(v.confident_wrong)
            counts["cf"] += int(v.confident_false)
            counts["missed"] += len(v.missed)
            counts["flagged_wrong"] += v.flagged_wrong
        rows.append({**cfg, "profile": prof, **counts})
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m mtcw_bench.movers_probe", description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", default=",".join(SETS), help="comma-separated sets: " + ", ".join(SETS))
    ap.add_argument("--out", type=Path, default=None, help="every row as JSON")
    args = ap.parse_args(argv)
    cfgs = [c for s in args.sets.split(",") if s for c in _runs(s.strip())]
    t0 = time.perf_counter()
    rows = [r for c in tqdm(cfgs, desc="movers probe", unit="config") for r in run_config(c)]
    bad = [r for r in rows if r["cw"] or r["cf"]]
    frames = sum(r["frames"] for r in rows)
    print(f"{len(cfgs)} configurations, {frames} processed frames, {time.perf_counter() - t0:.0f} s")
    print(f"confident wrong {sum(r['cw'] for r in rows)}, confident false {sum(r['cf'] for r in rows)}, "
          f"missed targets {sum(r['missed'] for r in rows)}")
    for prof in PROFILES:
        print(f"  {prof}: frames with a confident answer that is wrong or false "
              f"{sum(r['cw'] + r['cf'] for r in rows if r['profile'] == prof)}")
    for r in bad:
        print(f"  {r['rx']:8s} bins {r['bins']} losses {r['losses']} 2^{r['n'].bit_length() - 1} linewidth {r['lw']:g} "
              f"{r['profile']}: wrong {r['cw']}, false {r['cf']} of {r['frames']}")
    if args.out:
        args.out.write_text(json.dumps({"command": " ".join(["python -m mtcw_bench.movers_probe", *sys.argv[1:]]),
                                        "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
