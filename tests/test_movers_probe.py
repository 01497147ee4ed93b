"""The several-movers probe (``python -m mtcw_bench.movers_probe``): its sets and one configuration."""

from __future__ import annotations

import pytest

from mtcw_bench import movers_probe as mp


def test_every_set_builds_its_configurations():
    counts = {s: len(mp._runs(s)) for s in mp.SETS}
    assert all(n > 0 for n in counts.values())
    assert sum(counts.values()) == 619  # 619 configurations, 5451 frames over the 3 profiles
    with pytest.raises(ValueError, match="unknown set"):
        mp._runs("nope")


def test_one_configuration_is_judged_in_every_profile():
    """Two movers 40 and 90 bins up at 20 dB on one photodiode, 1 frame: judged
    against the truth in each profile, none confidently wrong (the map's own rule)."""
    cfg = mp._runs("main")[0] | {"bins": (40, 90), "losses": (20.0, 22.0), "rx": "single", "frames": 1}
    rows = mp.run_config(cfg)
    assert [r["profile"] for r in rows] == list(mp.PROFILES)
    assert all(r["cw"] == 0 and r["cf"] == 0 and r["frames"] == 1 for r in rows)
