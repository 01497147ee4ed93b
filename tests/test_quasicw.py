"""Quasi-CW coarse gating: km ranges far beyond the tones' unambiguous range, without cycle slips.

The dissertation's bench (130/510/710/950 MHz, 200 us period, 20 % duty, 1e6 samples) is
scaled in time to keep the tests quick: 2^18 samples (52 us) with a 50 us period and the same
duty; the gate's ambiguity is then c*P/2 = 7.5 km. The full-size bench runs in bench/quasicw.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from mtcw_core.chain import get_profile, process_frame
from mtcw_core.ranging.gating import coarse_gate
from mtcw_core.ranging.triangulation import C, unambiguous_range
from mtcw_core.simulate import Simulator

from .conftest import make_scene, tones

PLAN = (130e6, 510e6, 710e6, 950e6)
L_UNAMB = unambiguous_range(np.diff(PLAN))  # 7.5 m from the pair differences


def pulsed_scene(range_m: float, loss_db: float = 40.0, ref: bool = True, linewidth: float = 100e3,
                 frames: int = 4, velocity_mps: float = 0.0, receiver: str = "single", rise_s: float = 5e-9):
    return make_scene(
        laser={"linewidth_hz": linewidth}, modulator=tones(*PLAN), receiver={"kind": receiver},
        targets=[{"range_m": range_m, "loss_db": loss_db, "velocity_mps": velocity_mps}],
        noise={"shot": True, "thermal": True},
        digitizer={"samples": 2**18}, frames={"count": frames},
        pulsing={"period_s": 50e-6, "duty": 0.2, "delay_s": 3e-6, "rise_time_s": rise_s, "reference_channel": ref},
    )


@pytest.mark.parametrize("range_m", [930.0, 5000.0])
@pytest.mark.parametrize("ref", [True, False])
def test_km_ranges_without_cycle_slips(range_m, ref):
    assert range_m > 100 * L_UNAMB
    for fr in Simulator(pulsed_scene(range_m, ref=ref), seed=2).frames():
        res = process_frame(fr, "balanced")
        assert res.status == "ok", res.reason
        p = res.targets[0]
        truth = fr.truth[0].range_m
        # the coarse range is right within its sigma, and tight enough to pick one cycle
        assert abs(res.coarse_range_m - truth) < 4 * res.coarse_sigma_m
        assert not p.cycle_ambiguous
        # the fine range: no slip of one synthetic wavelength (7.5 m / its finer ones)
        assert abs(p.range_m - truth) < max(5 * p.range_sigma_m, 1e-3), (p.range_m - truth, p.range_sigma_m)


@pytest.mark.parametrize("receiver,v,ref", [("single", 8.0, False), ("iq", -3.0, True)])
def test_a_moving_target_at_km_range_gets_its_speed_and_range(receiver, v, ref):
    """A mover's lines f_i +- f_d sit a few MHz from f_i: the segments of the gated extraction
    are made long enough to tell them apart (else the static fit at f_i takes them in)."""
    for fr in Simulator(pulsed_scene(930.0, ref=ref, velocity_mps=v, receiver=receiver, frames=2), seed=1).frames():
        res = process_frame(fr, "balanced")
        assert res.status == "ok", res.reason
        p = res.targets[0]
        truth = fr.truth[0]
        assert abs(2 * abs(v) / fr.wavelength_m - abs(res.doppler_hz)) < 5 * p.velocity_sigma_mps * 2 / fr.wavelength_m
        if receiver == "iq":
            assert p.direction == "approaching" and p.velocity_mps == pytest.approx(v, abs=5 * p.velocity_sigma_mps)
        else:
            assert p.direction == "unknown" and p.velocity_mps == pytest.approx(abs(v), abs=5 * p.velocity_sigma_mps)
        assert not p.cycle_ambiguous
        assert abs(p.range_m - truth.range_m) < max(5 * p.range_sigma_m, 1e-3), (p.range_m - truth.range_m)


def test_coarse_gate_delay_against_2L_over_c():
    fr = Simulator(pulsed_scene(2500.0, linewidth=0.0), seed=1).frame(0)
    g = coarse_gate(fr.volts("pd"), fr.fs_hz, fr.pulse.period_s, fr.pulse.duty, fr.pulse.delay_s, fr.tones_hz,
                    fr.volts("pulse_ref"))
    assert g.detected
    assert abs(g.tau_s - 2 * 2500.0 / C) < 4 * g.sigma_s
    assert C * g.sigma_s / 2 < 1.5  # below a fifth of the 7.5 m the phases can resolve
    # the echo windows lie inside the echo gate (delay 3 us + 2L/c, 10 us long)
    t_on = 3e-6 + 2 * 2500.0 / C
    for a, b in g.windows:
        assert t_on < a / fr.fs_hz and b / fr.fs_hz < t_on + 10e-6


def test_a_slow_gate_ramp_measured_on_the_reference_keeps_the_coarse_sigma_honest():
    """An AOM-like 60 ns ramp, four times the band filters' rise: the edge model takes the ramp
    measured on the reference channel (a step model was 10-30 sigma off here)."""
    z = []
    for fr in Simulator(pulsed_scene(930.0, rise_s=60e-9, frames=6), seed=1).frames():
        res = process_frame(fr, "balanced")
        z.append((res.coarse_range_m - fr.truth[0].range_m) / res.coarse_sigma_m)
        assert not res.targets[0].cycle_ambiguous
    assert np.max(np.abs(z)) < 4, z


@pytest.mark.parametrize("seed", range(4))
def test_an_echo_faded_at_its_rising_edge_is_no_confident_wrong_delay(seed):
    """A single detector sees the echo as a*cos(psi(t)); here psi passes pi/2 exactly at the
    rising edge (a Wiener phase, 200 kHz beat linewidth), so that edge is invisible until psi has
    wandered off. A step fit put such an edge where the echo came back, 20-40 ns late with a
    0.3 ns sigma (the cycle slips of the 930 m bench); the delay must stay within 4 sigma, and
    the falling edge keep it below the block-level sigma."""
    fs, n, period, duty, delay, tau = 5e9, 2**17, 50e-6, 0.2, 1e-6, 3.2e-6
    t = np.arange(n) / fs
    t_r = delay + tau
    rng = np.random.default_rng(seed)
    k_r = int(np.ceil(t_r * fs))
    steps = rng.standard_normal(n) * np.sqrt(2 * np.pi * 2e5 / fs)
    psi = np.empty(n)  # a Wiener phase pinned to 0 at the edge: sin(psi) = cos(psi + pi/2) fades there
    psi[k_r:] = np.cumsum(steps[k_r:]) - steps[k_r]
    psi[:k_r] = -np.cumsum(steps[:k_r][::-1])[::-1]
    gate = (t >= t_r) & (t < t_r + duty * period)
    beat = sum(np.cos(2 * np.pi * f * t + k) for k, f in enumerate(PLAN))
    x = 1.0 + 0.05 * gate * np.sin(psi) * beat + 0.02 * rng.standard_normal(n)
    g = coarse_gate(x, fs, period, duty, delay, PLAN)
    assert g.detected
    assert abs(g.tau_s - tau) < 4 * g.sigma_s, ((g.tau_s - tau) * 1e9, g.sigma_s * 1e9)
    assert g.sigma_s < 40e-9


def test_coarse_sigma_too_large_to_pick_a_cycle_is_said():
    """The period is picked only when k coarse sigmas stay within half of it; otherwise say so."""
    fr = Simulator(pulsed_scene(930.0), seed=3).frame(0)
    sigma = process_frame(fr, "balanced").coarse_sigma_m
    k_edge = (L_UNAMB / 2) / sigma  # k at which k sigmas reach half the unambiguous range
    res = process_frame(fr, get_profile("balanced", gate_k_sigma=1.5 * k_edge))
    assert res.status == "ok" and res.targets[0].cycle_ambiguous
    res = process_frame(fr, get_profile("balanced", gate_k_sigma=0.6 * k_edge))
    assert res.status == "ok" and not res.targets[0].cycle_ambiguous
    assert abs(res.targets[0].range_m - 930.0) < 5 * res.targets[0].range_sigma_m


def test_no_echo_pulse_is_no_target():
    fr = Simulator(pulsed_scene(930.0, loss_db=140.0), seed=1).frame(0)
    res = process_frame(fr, "balanced")
    assert res.status == "no_target" and "echo pulse" in res.reason
