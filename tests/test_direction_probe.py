"""The direction probe (``python -m mtcw_bench.direction_probe``): one group judged, the groups chosen."""

from __future__ import annotations

from mtcw_bench import direction_probe as dp
from mtcw_bench.honesty import Config, Group

from .conftest import fast_mover_scene


def test_a_fast_movers_direction_is_claimed_and_judged_right():
    """47.9 m/s receding on one photodiode, 2^18 samples, 40 dB: the sidebands decide the sign;
    the probe counts the claim and finds it right (the truth's sign), none wrong."""
    sc = fast_mover_scene()
    counts, wrong = dp.judge_group(Group(Config("test", "fast mover", sc), "as is", None, sc, 2, 7), 2)
    assert counts["points"] == 2 and counts["right"] + counts["right/flagged"] == 2 and not wrong, counts


def test_only_movers_on_real_detectors_are_probed():
    gs = dp.groups(["receiver"], 1)
    assert gs and all(g.scene.receiver.kind == "balanced" and any(t.velocity_mps for t in g.scene.targets)
                      for g in gs)
