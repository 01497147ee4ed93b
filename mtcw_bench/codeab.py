"""Two code trees' chain times alternated on one machine: ``python -m mtcw_bench.codeab --old PATH``.

``mtcw bench`` reports medians over repeats of one frame per cell: the right statistic for the
issue's ratios, blind to work done in some frames only (a candidate searched and rejected in a
quarter of them moves the mean, the throughput a worker sustains, and not the median). Two runs
of anything on one machine also differ by 5-30 % with its state alone. This runs the same
simulated frames through the chain under an older checkout (``--old``, by ``PYTHONPATH``) and
this one, alternated ``--rounds`` times, each in a fresh process with one BLAS thread, and prints
the mean and median wall time per frame of the whole chain and of the ``doppler`` stage: the A/B
the README quotes for a change that only skips work.

Usage::

    git worktree add /tmp/old <commit>
    python -m mtcw_bench.codeab --old /tmp/old --scene moving-target --profiles balanced accurate
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

#: what one child process runs: the chain on ``frames`` frames of the scene at 20 dB, ``repeats``
#: passes after two untimed frames; prints its per-frame times (ms) as JSON
_CHILD = """
import json, sys, time
from mtcw_bench.grid import _scene_variant
from mtcw_core.chain import process_frame
from mtcw_core.profiles import get_profile
from mtcw_core.simulate import Simulator
scene, prof, samples, frames, repeats = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
frs = list(Simulator(_scene_variant(scene, 20.0, samples), seed=3).frames(frames))
st = get_profile(prof)
for fr in frs[:2]:
    process_frame(fr, st)
total, doppler = [], []
for _ in range(repeats):
    for fr in frs:
        t0 = time.perf_counter()
        r = process_frame(fr, st)
        total.append((time.perf_counter() - t0) * 1e3)
        doppler.append(r.stage_seconds["doppler"] * 1e3)
print(json.dumps({"total": total, "doppler": doppler}))
"""


def run_tree(tree: Path, scene: str, profile: str, samples: int, frames: int, repeats: int) -> dict[str, list[float]]:
    """Per-frame times (ms) of the chain in ``tree`` (a checkout's root), in a child process."""
    env = dict(os.environ, PYTHONPATH=str(tree), OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", _CHILD, scene, profile, str(samples), str(frames), str(repeats)],
                         cwd=tree, env=env, capture_output=True, text=True)
    lines = out.stdout.strip().splitlines()
    if out.returncode != 0 or not lines:
        tail = "\n".join(out.stderr.strip().splitlines()[-8:])
        raise RuntimeError(f"the chain in {tree} ({scene}, {profile}) failed (exit {out.returncode}):\n{tail}")
    return json.loads(lines[-1])


def summary(times: dict[str, list[float]]) -> str:
    """``total mean M median D | doppler mean M median D ms``."""
    return " | ".join(f"{k} mean {statistics.mean(v):.1f} median {statistics.median(v):.1f}" for k, v in times.items()) + " ms"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m mtcw_bench.codeab", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--old", type=Path, required=True, help="root of the older checkout (e.g. a git worktree)")
    ap.add_argument("--new", type=Path, default=Path(__file__).resolve().parents[1], help="root of the newer one (this)")
    ap.add_argument("--scene", default="moving-target")
    ap.add_argument("--profiles", nargs="+", default=["balanced"])
    ap.add_argument("--samples", type=int, default=1_000_000)
    ap.add_argument("--frames", type=int, default=8, help="frames per run (its first two, run once untimed, warm it)")
    ap.add_argument("--repeats", type=int, default=3, help="passes over the frames per run")
    ap.add_argument("--rounds", type=int, default=3, help="old/new alternations")
    args = ap.parse_args(argv)
    for name in ("samples", "frames", "repeats", "rounds"):
        if getattr(args, name) < 1:
            ap.error(f"--{name}: must be at least 1 (got {getattr(args, name)})")
    for tree in (args.old, args.new):
        if not (tree / "mtcw_core" / "chain.py").is_file():
            ap.error(f"--old/--new: {tree} holds no mtcw_core/chain.py")
    t0 = time.monotonic()
    pooled: dict[tuple[str, str], dict[str, list[float]]] = {}
    for rnd in range(args.rounds):
        for prof in args.profiles:
            for tag, tree in (("old", args.old), ("new", args.new)):
                try:
                    times = run_tree(tree, args.scene, prof, args.samples, args.frames, args.repeats)
                except RuntimeError as err:
                    print(f"round {rnd + 1} {tag}: {err}", file=sys.stderr)
                    return 1
                print(f"round {rnd + 1} {tag} {args.scene} {prof}: {summary(times)}", flush=True)
                for k, v in times.items():
                    pooled.setdefault((prof, tag), {}).setdefault(k, []).extend(v)
    for prof in args.profiles:
        old, new = pooled[(prof, "old")], pooled[(prof, "new")]
        ratio = statistics.median(new["total"]) / statistics.median(old["total"])
        print(f"all rounds {args.scene} {prof}: old {summary(old)}; new {summary(new)}; "
              f"new/old total median {ratio:.3f}")
    print(f"{time.monotonic() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
