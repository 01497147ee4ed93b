"""Direction claims of one photodiode (``ChainSettings.sideband_direction``) over the honesty map's
groups: how often the sidebands' modulation Doppler decides the sign of the motion, and whether
it is right.

``python -m mtcw_bench.direction_probe [--frames 4] [--slices length,six-tone]``

Every group of the map (:func:`mtcw_bench.honesty.plan`) with a moving target and a single or
balanced receiver is simulated (its first ``--frames`` frames, its own seed) and run through
``balanced`` with the setting on and the bench's laser and jitter declared, as the map does. A
point claims a direction when it says ``receding`` or ``approaching``; the claim is right when the
sign of its velocity is the truth's (the point it answers, paired as the map pairs them).
"""

from __future__ import annotations

import argparse
import collections

from tqdm import tqdm

from mtcw_core.chain import process_frame
from mtcw_core.evaluate import judge_frame
from mtcw_core.profiles import get_profile
from mtcw_core.simulate import Simulator

from .honesty import Group, MapSpec, declared, map_configs, plan


def judge_group(g: Group, frames: int) -> tuple[collections.Counter, list[str]]:
    """One group's direction claims: counts of ``points`` (answering a moving truth), ``right``,
    ``wrong`` (``/flagged`` appended for flagged points), and a line per wrong claim."""
    sc = g.scene
    st = get_profile("balanced", sideband_direction=True, **declared(sc))
    counts: collections.Counter = collections.Counter()
    wrong: list[str] = []
    for fr in Simulator(sc, g.seed).frames(min(frames, g.frames)):
        res = process_frame(fr, st)
        v = judge_frame(res, fr.truth, 5.0)
        for p, pv in zip(res.targets, v.points):
            if pv.truth_index is None or fr.truth[pv.truth_index].velocity_mps == 0:
                continue
            counts["points"] += 1
            if p.direction not in ("receding", "approaching"):
                continue
            truth_v = fr.truth[pv.truth_index].velocity_mps
            key = ("right" if (p.velocity_mps > 0) == (truth_v > 0) else "wrong") + ("/flagged" if pv.flagged else "")
            counts[key] += 1
            if key.startswith("wrong"):
                wrong.append(f"{g.config.slice} {g.config.label} {g.rung}: {p.velocity_mps:+.4g} m/s, truth "
                             f"{truth_v:+.4g} m/s, flags {pv.flags}")
    return counts, wrong


def groups(slices: list[str] | None = None, frames: int = 4) -> list[Group]:
    """The map's groups with a moving target on a single or balanced receiver (quasi-CW left out)."""
    cfgs = [c for c in map_configs(MapSpec(slices=slices)) if c.scene.receiver.kind != "iq"
            and c.slice != "quasi-cw" and any(t.velocity_mps for t in c.scene.targets)]
    return plan(cfgs, frames)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m mtcw_bench.direction_probe", description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=4, help="frames per group (default 4)")
    ap.add_argument("--slices", default=None, help="comma-separated slices of the map (default: all)")
    a = ap.parse_args(argv)
    total: collections.Counter = collections.Counter()
    per: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    for g in tqdm(groups(a.slices.split(",") if a.slices else None, a.frames), desc="direction probe",
                  unit="group"):
        counts, wrong = judge_group(g, a.frames)
        total.update(counts)
        per[g.config.slice].update(counts)
        for line in wrong:
            tqdm.write("WRONG " + line)
    claims = sum(v for k, v in total.items() if k != "points")
    print(f"{total['points']} mover points; {claims} claimed a direction: right {total['right']} "
          f"(+{total['right/flagged']} flagged), wrong {total['wrong']} (+{total['wrong/flagged']} flagged)")
    for sl, c in per.items():
        print(f"  {sl}: {dict(c)}")


if __name__ == "__main__":
    main()
