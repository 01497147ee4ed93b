"""Reach beyond the laser's coherence (issue 12 case 9): the echo loss to which a point is right
and sigma <= 1 cm, one frame and K frames (``docs/reach.md``).

    python -m mtcw_bench.reach --samples 65536 262144 --frames 1 32 --losses 60 70 80 90 --runs 4

The bundled ``low-coherence`` scene (5.3 GHz linewidth, LO 9 m longer: ~500x the coherence
length, target at 0.55 m) at each echo loss and record length; per (loss, length, K): ``runs``
independent runs (seeds) of K frames through :class:`mtcw_core.ranging.accumulate.Accumulator`,
the last point of each judged against the truth averaged over its frames. A loss is *reached*
when every run gives an ``ok`` point, without a flag, with sigma <= 1 cm and |z| < 5. The
chain's own answer (``balanced``, one frame) is given beside it.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import numpy as np

from mtcw_core.chain import get_profile, process_frame
from mtcw_core.ranging.accumulate import AccumulateSettings, Accumulator, mean_truth
from mtcw_core.scene import load_scene, scene_variant
from mtcw_core.simulate import Simulator

SIGMA_MAX_M = 0.01


def measure(loss_db: float, samples: int, k: int, runs: int) -> dict:
    """One (loss, length, K) cell: per run the last point's status, sigma, z and flags."""
    sc = scene_variant(load_scene("low-coherence"), targets=[{"loss_db": loss_db}], digitizer={"samples": samples})
    prof = get_profile("balanced", laser_linewidth_hz=sc.laser.linewidth_hz,
                       lo_path_difference_m=sc.paths.lo_path_difference_m)
    out, chain = [], []
    for r in range(runs):
        acc = Accumulator(AccumulateSettings(frames=k), prof)
        truths = {}
        for fr in Simulator(sc, 1000 * r + k).frames(k):
            res = acc.add(fr)
            truths[fr.seq] = fr.truth
        truth = mean_truth([truths[s] for s in acc.window_seqs()])
        if res.status == "ok":
            p = res.targets[0]
            z = (p.range_m - truth[0].range_m) / p.range_sigma_m
            out.append({"status": "ok", "sigma_m": p.range_sigma_m, "z": z, "frames": p.accumulated_frames,
                        "flagged": p.flagged})
        else:
            out.append({"status": res.status, "reason": res.reason})
        chain.append(process_frame(fr, prof).status)
    ok = [o for o in out if o["status"] == "ok"]
    reached = len(ok) == runs and all(not o["flagged"] and o["sigma_m"] <= SIGMA_MAX_M and abs(o["z"]) < 5 for o in ok)
    return {"loss_db": loss_db, "samples": samples, "k": k, "runs": runs, "reached": reached,
            "ok": len(ok), "flagged": sum(o["flagged"] for o in ok),
            "sigma_median_m": statistics.median(o["sigma_m"] for o in ok) if ok else None,
            "z_max": max(abs(o["z"]) for o in ok) if ok else None,
            "chain_balanced": {s: chain.count(s) for s in set(chain)}, "runs_detail": out}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", type=int, nargs="+", default=[2**16, 2**18])
    ap.add_argument("--frames", type=int, nargs="+", default=[1, 32], help="K values (1-32)")
    ap.add_argument("--losses", type=float, nargs="+", default=[40, 60, 70, 75, 80, 85, 90])
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("-o", "--out", type=Path, default=None, help="write the cells as JSON here")
    a = ap.parse_args(argv)
    cells = []
    print("| samples | K | loss (dB) | reached | ok / runs | flagged | median sigma (mm) | max abs z | chain (balanced, 1 frame) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for n in a.samples:
        for k in a.frames:
            for loss in a.losses:
                c = measure(loss, n, k, a.runs)
                cells.append(c)
                sig = f"{1e3 * c['sigma_median_m']:.1f}" if c["sigma_median_m"] is not None else "-"
                zm = f"{c['z_max']:.1f}" if c["z_max"] is not None else "-"
                print(f"| {n} | {k} | {loss:g} | {'yes' if c['reached'] else 'no'} | {c['ok']} / {c['runs']} | "
                      f"{c['flagged']} | {sig} | {zm} | {c['chain_balanced']} |", flush=True)
    if a.out:
        a.out.write_text(json.dumps(cells, indent=1, default=float))
    reach = {}
    for c in cells:
        key = f"{c['samples']} samples, K={c['k']}"
        if c["reached"]:
            reach[key] = max(reach.get(key, -np.inf), c["loss_db"])
    print(json.dumps({"reach_db": reach}), file=sys.stderr)


if __name__ == "__main__":
    main()
