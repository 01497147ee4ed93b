"""mtcw_core.ranging.gating: envelope, band signals, the transmitted gate, and coarse gating of
hand-built rectangular-gated multi-tone records with a known delay."""

from __future__ import annotations

import numpy as np
import pytest

from mtcw_core.frame import Frame, PulseInfo
from mtcw_core.profiles import ChainSettings
from mtcw_core.ranging.gating import (band_signals, coarse_gate, envelope, gate_frame, ramp_duration, ref_levels,
                                      refine_edges, transmit_centre)

FS = 1e9
TONES = (100e6, 170e6, 260e6)


def gate(n, start_s, width_s, period_s):
    """1 where (t - start) mod P < W, sampled at t = k/fs (a start at a half sample is exact)."""
    t = np.arange(n) / FS
    return (np.mod(t - start_s, period_s) < width_s).astype(float)


def tones_signal(n, amps=(1.0, 0.6, 0.4)):
    k = np.arange(n)
    return sum(a * np.cos(2 * np.pi * np.mod(k * f / FS, 1.0) + i) for i, (f, a) in enumerate(zip(TONES, amps)))


def pulsed(n, tau_s, period_s, duty, delay_s, noise, seed=0):
    x = gate(n, delay_s + tau_s, duty * period_s, period_s) * tones_signal(n)
    return x + noise * np.random.default_rng(seed).standard_normal(n)


class TestEnvelope:
    def test_high_where_the_gate_is_on(self):
        n, block = 4096, 64
        f = 10 * FS / block  # on the block's bin grid: |X| = A*block/2 in bin 10
        g = gate(n, 1024e-9, 1024e-9, 4096e-9)
        x = g * np.cos(2 * np.pi * np.mod(np.arange(n) * f / FS, 1.0))
        e = envelope(x, block, 1)
        assert e.shape == (n // block,)
        on = g.reshape(-1, block).min(axis=1) == 1
        off = g.reshape(-1, block).max(axis=1) == 0
        np.testing.assert_allclose(e[on], (block / 2) ** 2, rtol=1e-9)
        np.testing.assert_allclose(e[off], 0.0, atol=1e-18)

    def test_dc_ignored(self):
        e = envelope(np.full(1024, 3.0), 64, 3)
        np.testing.assert_allclose(e, 0.0, atol=1e-18)

    def test_complex_input(self):
        n, block = 2048, 64
        g = gate(n, 512e-9, 512e-9, 2048e-9)
        x = g * np.exp(-2j * np.pi * np.arange(n) * 5 / block)  # negative frequency, bin -5
        e = envelope(x, block, 1)
        on = g.reshape(-1, block).min(axis=1) == 1
        np.testing.assert_allclose(e[on], block**2, rtol=1e-9)
        assert np.all(e[~on] <= e[on].min())


class TestBandSignals:
    def test_dc_and_tone_phasors(self):
        n = 4096
        f = 400 * FS / n  # periodic in the record: the circular band filter is exact
        x = 0.3 + 0.8 * np.cos(2 * np.pi * np.mod(np.arange(n) * f / FS, 1.0) + 0.7)
        b = band_signals(x, FS, [f], 20e6)
        assert b.shape == (2, n)
        np.testing.assert_allclose(b[0], 0.3, atol=1e-9)
        np.testing.assert_allclose(b[1], 0.4 * np.exp(0.7j), atol=1e-9)  # analytic band: A/2 e^{jp}


class TestRefLevels:
    def test_levels_of_a_rectangle(self):
        r = 0.1 + 2.0 * gate(4096, 300.5e-9, 1e-6, 4e-6)
        lo, hi = ref_levels(r)
        assert lo == pytest.approx(0.1) and hi == pytest.approx(2.1)


class TestTransmitCentre:
    P, W = 4e-6, 1e-6

    def test_from_a_clean_reference(self):
        ref = gate(2**14, 300.5e-9, self.W, self.P)
        c, w = transmit_centre(ref, FS, self.P, 0.25, 0.0)
        assert c == pytest.approx(300.5e-9 + self.W / 2, abs=1e-15)
        assert w == pytest.approx(self.W, abs=1e-15)

    def test_wraps_modulo_the_period(self):
        ref = gate(2**14, 3.7005e-6, self.W, self.P)  # centre 4.2005 us -> 0.2005 us
        c, w = transmit_centre(ref, FS, self.P, 0.25, 0.0)
        assert c == pytest.approx(0.2005e-6, abs=1e-15) and w == pytest.approx(self.W, abs=1e-15)

    def test_known_timing_without_reference(self):
        c, w = transmit_centre(None, FS, self.P, 0.25, 3.9e-6)
        assert c == pytest.approx((3.9e-6 + 0.5e-6) % self.P) and w == pytest.approx(self.W)

    def test_one_edge_uses_the_known_width(self):
        ref = gate(1024, 500.5e-9, self.W, self.P)  # the record ends while the gate is on
        c, w = transmit_centre(ref, FS, self.P, 0.25, 0.0)
        assert c == pytest.approx(1000.5e-9, abs=1e-15) and w == pytest.approx(self.W)

    def test_flat_reference_falls_back(self):
        c, _ = transmit_centre(np.ones(1024), FS, self.P, 0.25, 1e-6)
        assert c == pytest.approx(1.5e-6)


class TestRampDuration:
    def test_raised_cosine_ramp(self):
        n, r = 2**13, 20e-9
        t = np.arange(n) / FS
        u = np.mod(t - 500.3e-9, 4e-6)
        ref = np.clip(u / r, 0, 1)
        ref = np.where(u < 2e-6, np.sin(0.5 * np.pi * ref) ** 2, 0.0)
        assert ramp_duration(ref, FS) == pytest.approx(r, rel=0.05)

    def test_no_reference(self):
        assert ramp_duration(None, FS) == 0.0
        assert ramp_duration(np.zeros(512), FS) == 0.0


class TestCoarseGate:
    N = 2**14
    P, D, DELAY = 4e-6, 0.25, 0.3005e-6

    @pytest.mark.parametrize("tau", [1.2345e-6, 3.1e-6, 0.05e-6])
    @pytest.mark.parametrize("use_ref", [False, True])
    def test_delay_within_its_sigma(self, tau, use_ref):
        x = pulsed(self.N, tau, self.P, self.D, self.DELAY, 0.01)
        ref = gate(self.N, self.DELAY, self.D * self.P, self.P) if use_ref else None
        g = coarse_gate(x, FS, self.P, self.D, self.DELAY, TONES, ref=ref)
        assert g.detected and g.snr > 8
        assert abs(g.tau_s - tau) < 3 * g.sigma_s
        assert g.sigma_s < 256 / FS  # below one envelope block
        assert g.width_s == pytest.approx(self.D * self.P, rel=1e-3)

    def test_windows_inside_the_echo(self):
        tau = 1.2345e-6
        x = pulsed(self.N, tau, self.P, self.D, self.DELAY, 0.01)
        g = coarse_gate(x, FS, self.P, self.D, self.DELAY, TONES)
        on = gate(self.N, self.DELAY + tau, self.D * self.P, self.P)
        assert len(g.windows) >= 3
        for a, b in g.windows:
            assert b - a >= 16 and on[a:b].all()

    def test_no_echo_not_detected(self):
        x = 0.01 * np.random.default_rng(1).standard_normal(self.N)
        g = coarse_gate(x, FS, self.P, self.D, self.DELAY, TONES)
        assert not g.detected and g.windows == []

    @pytest.mark.xfail(strict=True, reason="coarse_gate's fine edge stage (refine_edges) is overconfident on a clean "
                                           "rectangular-gated record: P=8 us, duty 0.5, delay 300.5 ns, tau 1.2345 "
                                           "us, tones 100/170/260 MHz, white noise 0.01, 2^14 samples at 1 GS/s: "
                                           "sigma 0.52 ns while the error is -2.5 ns for seeds 0, 1, 3 (|z| ~ 4.8)")
    def test_fine_edges_sigma_covers_the_error(self):
        p, d, tau = 8e-6, 0.5, 1.2345e-6
        ref = gate(self.N, self.DELAY, d * p, p)
        z = []
        for seed in range(4):
            x = pulsed(self.N, tau, p, d, self.DELAY, 0.01, seed)
            g = coarse_gate(x, FS, p, d, self.DELAY, TONES, ref=ref)
            z.append((g.tau_s - tau) / g.sigma_s)
        assert np.max(np.abs(z)) < 4.0, z


class TestRefineEdges:
    def test_centre_of_a_clean_gate(self):
        p, w, start = 8e-6, 4e-6, 1.5345e-6
        x = gate(2**14, start, w, p) * tones_signal(2**14) + 0.01 * np.random.default_rng(0).standard_normal(2**14)
        out = refine_edges(x, FS, start + 5e-9, w, p, 0.0, 64e-9, TONES, 1e-9)
        assert out is not None
        c, s = out
        assert abs(c - (start + w / 2)) < 5 * s + 1e-9

    def test_too_small_window_returns_none(self):
        p, w, start = 8e-6, 4e-6, 1.5345e-6
        x = gate(2**14, start, w, p) * tones_signal(2**14) + 0.01 * np.random.default_rng(0).standard_normal(2**14)
        assert refine_edges(x, FS, start, w, p, 0.0, 20e-9, TONES, 1e-9) is None


class TestGateFrame:
    def test_cw_frame_has_no_gate(self):
        fr = Frame(np.zeros((1, 1024)), FS, TONES, 1.064e-6)
        assert gate_frame(np.zeros(1024), fr, ChainSettings()) is None

    def test_gate_off(self):
        fr = Frame(np.zeros((1, 1024)), FS, TONES, 1.064e-6, pulse=PulseInfo(4e-6, 0.25))
        assert gate_frame(np.zeros(1024), fr, ChainSettings(gate="off")) is None

    def test_pulsed_frame_uses_the_reference_channel(self):
        n, p, d, delay, tau = 2**14, 4e-6, 0.25, 0.3005e-6, 1.2345e-6
        x = pulsed(n, tau, p, d, delay, 0.01)
        ref = gate(n, delay, d * p, p)
        fr = Frame(np.stack([x, ref]), FS, TONES, 1.064e-6, channels=("pd", "pulse_ref"),
                   pulse=PulseInfo(p, d, 0.0))  # the wrong delay: the reference channel knows better
        g = gate_frame(x, fr, ChainSettings())
        assert g.detected and abs(g.tau_s - tau) < 3 * g.sigma_s


def test_a_record_toggling_between_the_rails_is_no_echo_not_a_crash():
    """A pulsed frame whose samples alternate between the int16 rails (found by fuzzing the worker)
    made the gate fit's delay infinite and the window placement raise OverflowError; it is no echo."""
    from mtcw_core.chain import process_frame

    x = np.resize(np.array([32767, -32768], "<i2"), (1, 4096))
    fr = Frame(samples=x, fs_hz=5e9, tones_hz=(500e6, 700e6, 950e6), channels=("pd",), scale=0.00015894517924293028,
               wavelength_m=1.064e-6, receiver="balanced", pulse=PulseInfo(period_s=1.6384e-6, duty=0.75, delay_s=0.0))
    for profile in ("fast", "balanced"):
        res = process_frame(fr, profile)
        assert res.status == "no_target" and res.reason.startswith("no echo pulse"), res.reason
