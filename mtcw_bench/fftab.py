"""The chain on each FFT backend, alternated in one process: ``python -m mtcw_bench.fftab``.

``mtcw bench --fft-backend`` times one backend per run, and two runs of it differ by 5-15 % with
the machine's state alone (the rfft reference itself moves that much); what a backend buys is
smaller than that. This runs the same frames through the chain on each backend in turn, several
rounds, in one process, and reports the median CPU time (``time.process_time``) of the whole
chain and of every stage per backend: the A/B the README quotes for ``MTCW_FFT_BACKEND``.

Usage::

    python -m mtcw_bench.fftab --scenes cw-bench moving-target six-tone --profiles fast balanced accurate

Backends not installed (pyFFTW: ``pip install 'mtcw[fftw]'``) are left out, and said so.
"""

from __future__ import annotations

import argparse
import statistics
import time

from mtcw_core.chain import STAGE_NAMES, process_frame
from mtcw_core.dsp.spectrum import FFT_BACKENDS, fft_backend_module, use_fft_backend
from mtcw_core.simulate import Simulator

from .grid import _scene_variant


def alternate(scene: str, profiles: list[str], backends: list[str], samples: int, rounds: int, frames: int
              ) -> dict[tuple[str, str], dict[str, float]]:
    """Median CPU seconds per (profile, backend): ``total`` and each stage that ran, over
    ``rounds`` alternations of ``frames`` frames each (one untimed frame first on each backend)."""
    sc = _scene_variant(scene, None, samples)
    frs = list(Simulator(sc, seed=3).frames(frames))
    times: dict[tuple[str, str], dict[str, list[float]]] = {}
    before = use_fft_backend(backends[0])
    try:
        for prof in profiles:
            for _ in range(rounds):
                for be in backends:
                    use_fft_backend(be)
                    process_frame(frs[0], prof)
                    acc = times.setdefault((prof, be), {})
                    for fr in frs:
                        t0 = time.process_time()
                        res = process_frame(fr, prof)
                        acc.setdefault("total", []).append(time.process_time() - t0)
                        for k, v in res.stage_seconds.items():
                            acc.setdefault(k, []).append(v)
    finally:
        use_fft_backend(before)
    return {k: {s: statistics.median(v) for s, v in acc.items()} for k, acc in times.items()}


def installed(backends: list[str]) -> tuple[list[str], list[str]]:
    """The backends of ``backends`` this process can use, and those it cannot (with why)."""
    ok, missing = [], []
    for be in backends:
        try:
            fft_backend_module(be)  # the check alone: nothing switched
            ok.append(be)
        except ValueError as err:
            missing.append(f"{be}: {err}")
    return ok, missing


def table(scene: str, result: dict[tuple[str, str], dict[str, float]], backends: list[str]) -> list[str]:
    """Markdown rows: per profile and backend, ms per stage and in all, and the change against the first backend."""
    stages = [s for s in STAGE_NAMES if any(s in v for v in result.values())]
    lines = [f"| scene | profile | backend | {' | '.join(stages)} | total | vs {backends[0]} |",
             "| --- " * (len(stages) + 5) + "|"]
    for (prof, be), v in result.items():
        base = result[(prof, backends[0])]["total"]
        cells = " | ".join(f"{1e3 * v[s]:.2f}" if s in v else "–" for s in stages)
        lines.append(f"| {scene} | {prof} | {be} | {cells} | {1e3 * v['total']:.2f} | "
                     f"{100 * (v['total'] / base - 1):+.0f} % |")
    return lines


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m mtcw_bench.fftab", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["cw-bench", "moving-target", "six-tone"])
    ap.add_argument("--profiles", nargs="+", default=["fast", "balanced", "accurate"])
    ap.add_argument("--backends", nargs="+", default=list(FFT_BACKENDS), choices=FFT_BACKENDS)
    ap.add_argument("--samples", type=int, default=1_000_000)
    ap.add_argument("--rounds", type=int, default=3, help="alternations of the backends (default 3)")
    ap.add_argument("--frames", type=int, default=6, help="frames per backend per round (default 6)")
    a = ap.parse_args(argv)
    backends, missing = installed(a.backends)
    for m in missing:
        print(f"left out: {m}")
    if not backends:
        raise SystemExit("no FFT backend available")
    print(f"CPU ms per frame (time.process_time), median over {a.rounds} rounds x {a.frames} frames, "
          f"{a.samples} samples, backends alternated in one process\n")
    for i, scene in enumerate(a.scenes):
        rows = table(scene, alternate(scene, a.profiles, backends, a.samples, a.rounds, a.frames), backends)
        print("\n".join(rows if i == 0 else rows[2:]))


if __name__ == "__main__":
    main()
