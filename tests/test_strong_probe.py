"""The strong-echo probe (``python -m mtcw_bench.strong_probe``): its scenes, one judged."""

from __future__ import annotations

import math

from mtcw_bench import strong_probe as sp


def test_the_probe_puts_the_echo_at_and_above_the_los_power():
    """What the probe is for: on moving-target the echo (the laser's 1 - lo_fraction after its
    loss) is above the LO's power (lo_fraction) at the lowest loss and within 10 dB of it at the
    highest, on every receiver."""
    got = sp.scenes((2**16,))
    assert {sc.receiver.kind for _, sc in got} == set(sp.RECEIVERS)
    ratio_db = {sc.targets[0].loss_db: 10 * math.log10((1 - sc.lo_fraction) / sc.lo_fraction) - sc.targets[0].loss_db
                for _, sc in got}
    assert ratio_db[min(ratio_db)] > 0 and -10 < ratio_db[max(ratio_db)] < 0, ratio_db


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


def test_the_summary_counts_flagged_points(capsys, monkeypatch):
    """Each tag's line states its flagged points and how many of them were right (what a flag cost),
    as the envelope probe's summary does: here the one 2^16 single-photodiode scene at 0 dB and 1 m/s."""
    one = [(lab, sc) for lab, sc in sp.scenes((2**16,))
           if sc.receiver.kind == "single" and sc.targets[0].loss_db == 0.0 and sc.targets[0].velocity_mps == 1.0]
    monkeypatch.setattr(sp, "scenes", lambda samples: one)
    sp.main(["--frames", "1", "--samples", "65536"])
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if ln.startswith("  ") and "frames 1," in ln]
    assert len(lines) == 2 * len(sp.PROFILES), out
    assert all("flagged points" in ln and "right within 5 sigma" in ln for ln in lines), out
