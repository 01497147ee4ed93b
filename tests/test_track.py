"""Range rate over frames (mtcw_core.ranging.track): against the least-squares slope's own
variance, truth, wrapped ranges, several targets, flags, manoeuvres and the chain's Doppler; and
issue 12 case 4's low-coherence mover end to end (a speed the carrier's Doppler cannot give)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from mtcw_core.chain import get_profile, process_frame
from mtcw_core.evaluate import judge_frame
from mtcw_core.ranging.track import Tracker, TrackSettings
from mtcw_core.results import FrameResult, TargetPoint
from mtcw_core.scene import load_scene, scene_variant
from mtcw_core.simulate import Simulator

T0_NS = 1_767_225_600_000_000_000  # a trigger stamp of today's size (float64 s keeps 0.2 us there)
#: the bench's declared largest speed (m/s) for points whose speed is unknown (the helper's default)
SLOW = 2.0


def point(r: float, sigma: float, **kw) -> TargetPoint:
    base = dict(range_m=r, range_sigma_m=sigma, velocity_mps=0.0, velocity_sigma_mps=60.0, direction="unknown",
                snr_db=30.0, margin=10.0, speed_min_mps=60.0)  # speed unknown (a laser incoherent there)
    base.update(kw)
    return TargetPoint(**base)


def result(points, k: int, dt: float = 0.1, period: float | None = 3.0, source: str = "s") -> FrameResult:
    return FrameResult(status="ok", profile="balanced", seq=k, t_ns=T0_NS + round(k * dt * 1e9), source=source,
                       targets=list(points), unambiguous_range_m=period)


def feed(tracker: Tracker, ranges, sigma: float, dt: float = 0.1, period: float | None = 3.0, **kw):
    return [tracker.update(result([point(float(r), sigma, **kw)], k, dt, period)).targets[0]
            for k, r in enumerate(ranges)]


def test_rate_is_the_weighted_slope_with_its_least_squares_variance():
    """A constant-velocity target: the rate is the slope, its sigma ``s*sqrt(12/(K(K^2-1)))/dt``
    (equal sigmas, K equally spaced points), and none before ``min_frames``."""
    rng = np.random.default_rng(1)
    k, s, dt, v = 12, 0.004, 0.1, 0.1
    t = np.arange(20) * dt
    out = feed(Tracker(TrackSettings(frames=k, max_speed_mps=SLOW)), 1.12 + v * t + rng.normal(0, s, t.size), s, dt)
    assert [p.range_rate_mps is None for p in out[:2]] == [True, True] and out[2].range_rate_mps is not None
    assert [p.track_frames for p in out] == list(range(1, k + 1)) + [k] * (20 - k)
    assert len({p.track_id for p in out}) == 1
    last = out[-1]
    ideal = s * math.sqrt(12 / (k * (k**2 - 1))) / dt
    assert ideal <= last.range_rate_sigma_mps <= 2.5 * ideal  # Birge-scaled only upwards
    assert abs(last.range_rate_mps - v) < 5 * last.range_rate_sigma_mps


def test_rate_sigma_covers_its_error_over_many_tracks():
    """Over 600 independent tracks the z of the rate has std within 0.9-1.15 (Birge scaling makes it
    a little conservative where a window's residuals scatter wider by chance)."""
    rng = np.random.default_rng(7)
    z = []
    for _ in range(600):
        v, s = rng.uniform(-1, 1), rng.uniform(1e-3, 1e-2)
        t = np.arange(8) * 0.1
        p = feed(Tracker(TrackSettings(frames=8, max_speed_mps=SLOW)), 1.0 + v * t + rng.normal(0, s, t.size), s)[-1]
        z.append((p.range_rate_mps - v) / p.range_rate_sigma_mps)
    assert abs(np.mean(z)) < 0.15 and 0.8 <= np.std(z) <= 1.05, (np.mean(z), np.std(z))


def test_ranges_wrapped_at_the_unambiguous_range_are_unwrapped_along_the_track():
    """A target receding through the end of a 3 m unambiguous range reads 2.9, 2.95, 0.0, ...: one
    track, rate +0.5 m/s; approaching through 0 likewise."""
    for v in (0.5, -0.5):
        t = np.arange(10) * 0.1
        out = feed(Tracker(TrackSettings(max_speed_mps=SLOW)), np.mod(2.8 + v * t if v > 0 else 0.2 + v * t, 3.0), 1e-3)
        assert len({p.track_id for p in out}) == 1
        assert abs(out[-1].range_rate_mps - v) < 1e-6 and out[-1].range_rate_sigma_mps < 1e-2


@pytest.mark.parametrize("period", [3.0, None])
def test_each_target_keeps_its_track_and_flagged_points_join_none(period):
    """Two targets 1 m apart at +0.2 and -0.3 m/s, listed in either order: two tracks, each with its
    own rate -- with CW ranges (3 m unambiguous) and with absolute ones (quasi-CW: any step may
    join a one-point track, the nearest does); a point flagged ``cycle_ambiguous`` joins no track
    and carries no rate."""
    tr = Tracker(TrackSettings(max_speed_mps=SLOW))
    rng = np.random.default_rng(3)
    for k in range(10):
        t = k * 0.1
        pts = [point(1.0 + 0.2 * t + rng.normal(0, 1e-3), 1e-3), point(2.0 - 0.3 * t + rng.normal(0, 1e-3), 1e-3),
               point(0.4, 1e-3, cycle_ambiguous=True)]
        res = tr.update(result(pts[::-1] if k % 2 else pts, k, period=period))
    a, b = sorted((p for p in res.targets if not p.flagged), key=lambda p: p.range_m)
    assert a.track_id != b.track_id and a.track_frames == b.track_frames == 10
    assert abs(a.range_rate_mps - 0.2) < 5 * a.range_rate_sigma_mps and abs(b.range_rate_mps + 0.3) < 5 * b.range_rate_sigma_mps
    (f,) = [p for p in res.targets if p.flagged]
    assert f.track_id is None and f.range_rate_mps is None


def test_a_manoeuvre_ends_the_window_and_the_rate_follows():
    """The target stops after 10 frames at 0.5 m/s: the first point at rest lies 35 sigma off the
    track's prediction and starts a new track, whose rate is 0 within its sigma (never a confident
    0.5). A gentler change, within the gate, makes the window's chi-square improbable: the window
    restarts from its newest point."""
    t = np.arange(24) * 0.1
    r = np.where(t < 1.0, 1.0 + 0.5 * t, 1.5) + np.random.default_rng(2).normal(0, 1e-3, t.size)
    out = feed(Tracker(TrackSettings(frames=12, max_speed_mps=SLOW)), r, 1e-3)
    assert out[-1].track_id != out[0].track_id and abs(out[-1].range_rate_mps) < 5 * out[-1].range_rate_sigma_mps
    tr = Tracker(TrackSettings(frames=12, gate_sigmas=50, max_speed_mps=SLOW))  # a wide gate: the 0.1 m/s change stays in the track
    r = np.where(t < 1.0, 1.0 + 0.5 * t, 1.5 + 0.4 * (t - 1.0)) + np.random.default_rng(2).normal(0, 1e-3, t.size)
    out = feed(tr, r, 1e-3)
    assert tr.restarts >= 1 and len({p.track_id for p in out}) == 1
    assert abs(out[-1].range_rate_mps - 0.4) < 5 * out[-1].range_rate_sigma_mps


def test_a_rate_the_doppler_line_contradicts_is_withheld():
    """One photodiode, the chain measured |v| = 1.0 m/s from its Doppler line (no sign): a track at
    0.1 m/s is not reported; at -1.0 m/s it is (the sign is the direction the line lacks)."""
    for v, shown in ((0.1, False), (-1.0, True)):
        tr = Tracker()
        t = np.arange(6) * 0.1
        out = feed(tr, 1.5 + v * t, 1e-3, velocity_mps=1.0, velocity_sigma_mps=1e-3, speed_min_mps=0.01)
        assert (out[-1].range_rate_mps is not None) == shown and tr.disagree == (0 if shown else 4)
        if shown:
            assert out[-1].range_rate_mps < 0  # approaching


def test_max_speed_bounds_a_tracks_second_step():
    """``max_speed_mps``: a second point further than it allows starts its own track; where the
    allowed step reaches half the unambiguous range the step's cycle is unknown (its own track)."""
    tr = Tracker(TrackSettings(max_speed_mps=1.0))
    out = feed(tr, [1.0, 1.5], 1e-3)  # 5 m/s between them
    assert out[0].track_id != out[1].track_id
    tr = Tracker(TrackSettings(max_speed_mps=20.0))  # 2 m in 0.1 s: beyond 1.5 m
    out = feed(tr, [1.0, 1.01], 1e-3)
    assert out[0].track_id != out[1].track_id


def test_a_step_whose_cycle_is_unknown_gives_no_rate():
    """A target at 20 m/s, its speed unknown (a laser incoherent at it: the search's largest speed,
    60 m/s, as its sigma), 3 m unambiguous range, 10 frames/s: each 2 m step wraps to -1 m. Taking the
    nearest cycle once made a confident -10 m/s. Without a declared max speed the step's cycle is
    unknown: no track joins, no rate. Where the chain measured the speed (1.0 m/s) it bounds the step
    itself, and a 1 m/s target is tracked without any declaration."""
    t = np.arange(6) * 0.1
    tr = Tracker()
    out = feed(tr, np.mod(1.0 + 20.0 * t, 3.0), 1e-3)
    assert all(p.range_rate_mps is None and p.track_frames == 1 for p in out) and tr.ambiguous >= 5
    out = feed(Tracker(), 1.0 + 1.0 * t, 1e-3, velocity_mps=1.0, velocity_sigma_mps=1e-3, speed_min_mps=0.01)
    assert len({p.track_id for p in out}) == 1 and abs(out[-1].range_rate_mps - 1.0) < 5 * out[-1].range_rate_sigma_mps


def test_a_new_run_a_new_plan_or_time_going_back_ends_the_tracks():
    tr = Tracker(TrackSettings(max_speed_mps=SLOW))
    feed(tr, [1.0, 1.01], 1e-3)
    p = tr.update(result([point(1.02, 1e-3)], 2), run=5).targets[0]
    assert p.track_frames == 1 and tr.ends == {"run": 1}
    tr.update(result([point(1.02, 1e-3)], 3, period=7.5), run=5)
    tr.update(result([point(1.02, 1e-3)], 1, period=7.5), run=5)
    assert tr.ends == {"run": 1, "plan": 1, "time": 1}
    tr.update(result([point(1.02, 1e-3)], 200, period=7.5), run=5)  # 20 s later
    assert tr.ends["gap"] == 1


def test_settings_name_the_field():
    with pytest.raises(ValidationError, match="frames"):
        TrackSettings(frames=2)
    with pytest.raises(ValidationError, match="max_speed_mps"):
        TrackSettings(max_speed_mps=-1.0)
    with pytest.raises(ValidationError, match="min_frames"):
        TrackSettings(frames=4, min_frames=5)


def test_issue12_case4_low_coherence_mover_gets_its_speed_from_its_ranges():
    """Case 4: 5.3 GHz laser, LO 9 m longer, target at 1.12 m receding at 10 cm/s (2^16 samples, 10
    frames/s). Each frame's point says speed unknown (no Doppler line); over 10 frames the range rate
    is 0.10 m/s within 5 sigma with a sigma under 2 cm/s, receding, and the judge counts it."""
    low = load_scene("low-coherence")
    sc = scene_variant(low, targets=[{"range_m": 1.12, "velocity_mps": 0.10, "loss_db": 20.0}],
                       digitizer={"samples": 2**16})
    st = get_profile("fast", laser_linewidth_hz=sc.laser.linewidth_hz,
                     lo_path_difference_m=sc.paths.lo_path_difference_m)
    tr = Tracker(TrackSettings(frames=10, max_speed_mps=SLOW))  # the bench declares its target slow
    for fr in Simulator(sc, 4).frames(10):
        res = tr.update(process_frame(fr, st))
        v = judge_frame(res, fr.truth)
        assert not v.confident_wrong
    (p,) = res.targets
    assert not p.speed_measured and p.range_rate_mps is not None
    assert abs(p.range_rate_mps - 0.10) < 5 * p.range_rate_sigma_mps and p.range_rate_sigma_mps < 0.02
    assert p.range_rate_mps > 0  # receding
    (pv,) = v.points
    assert pv.rate_z == pytest.approx((p.range_rate_mps - 0.10) / p.range_rate_sigma_mps)


def test_one_photodiode_mover_gets_its_direction_from_its_ranges():
    """The coherent moving target on one photodiode, approaching at 0.1 m/s: the Doppler line gives
    |v| (direction unknown); the range rate over 8 frames is negative, agrees with |v| and its truth."""
    sc = scene_variant(load_scene("moving-target"), targets=[{"velocity_mps": -0.10}], digitizer={"samples": 2**16})
    tr = Tracker(TrackSettings(frames=8))
    for fr in Simulator(sc, 5).frames(8):
        res = tr.update(process_frame(fr, "fast"))
    (p,) = res.targets
    assert p.direction == "unknown" and p.speed_measured
    assert p.range_rate_mps < 0 and abs(p.range_rate_mps + 0.10) < 5 * p.range_rate_sigma_mps
    assert tr.disagree == 0
