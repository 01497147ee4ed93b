"""Soak and fault test of the services (mtcw_bench/soak.py), short: overload at 2x the measured
capacity, a SIGKILL of a worker, the API and the acquisition node, each restarted at once; the
books must balance exactly, nothing served twice or stale, memory bounded, every kill recovered.
``pytest --long`` runs 5 minutes with 24 kills; the full run is ``mtcw-bench-soak`` (README)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from mtcw_bench.soak import soak


@pytest.fixture(scope="module")
def small_recording(tmp_path_factory):
    out = tmp_path_factory.mktemp("soak") / "cwb"
    subprocess.run([sys.executable, "-m", "services.cli", "simulate", "cw-bench", "-o", str(out), "-n", "4",
                    "--samples", str(2**14)], check=True, capture_output=True, timeout=120)
    return out


@pytest.mark.slow
def test_kills_under_overload_leave_exact_books(small_recording, long_run):
    seconds, kills = (300.0, 24) if long_run else (24.0, 3)
    res = soak(small_recording, seconds, kills, workers=2, overload=2.0, seed=7, profile="fast",
               progress=lambda s: print(s, file=sys.stderr))
    s = res.summary()
    assert s["kills"] == {"worker": kills // 3, "api": kills // 3, "acquisition": kills // 3}, s
    assert s["counts"]["dropped"] > 0, "no overload: the test would not see lost frames"
    assert s["published"] == s["counts"]["processed"] + s["counts"]["rejected"] + s["counts"]["dropped"], s
    assert res.ok, s
