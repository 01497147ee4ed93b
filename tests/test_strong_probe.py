"""The strong-echo probe (``python -m mtcw_bench.strong_probe``): its scenes, one judged."""

from __future__ import annotations

from mtcw_bench import strong_probe as sp


def test_the_probe_spans_receivers_lengths_losses_and_speeds():
    got = sp.scenes((2**16,))
    assert len(got) == len(sp.RECEIVERS) * len(sp.LOSSES_DB) * len(sp.SPEEDS_MPS)
    assert {sc.receiver.kind for _, sc in got} == set(sp.RECEIVERS)
    assert {sc.targets[0].loss_db for _, sc in got} == set(sp.LOSSES_DB) and min(sp.LOSSES_DB) == 0.0


def test_an_echo_above_the_lo_gives_no_confident_frame():
    """One photodiode, 2^18 samples, 0 dB loss, 1 m/s: the echo's self-beat stands above its own
    Doppler lines at one range; before the 2026-11-27 fix ``balanced`` and ``accurate`` reported it
    as a ``static`` target, speed z -19.7, declared or not. Now: no confident frame, and with the
    laser declared the mover is found in every profile."""
    (label, sc), = [(lab, sc) for lab, sc in sp.scenes((2**18,))
                    if sc.receiver.kind == "single" and sc.targets[0].loss_db == 0.0 and sc.targets[0].velocity_mps == 1.0]
    counts, lines = sp.judge_scene(label, sc, 1)
    assert not lines, lines
    assert all(counts[(f"{p}/declared", "missed")] == 0 for p in sp.PROFILES), counts
    assert sum(v for (_, k), v in counts.items() if k == "frames") == 2 * len(sp.PROFILES)
