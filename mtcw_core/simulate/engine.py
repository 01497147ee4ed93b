"""The frame simulator: optical fields, square-law detection, noise, digitizer.

Implements ``shared/spec/physics.md``: the echo is the transmitted *field* delayed by
``tau(t) = tau0 + 2*(L + v*t)/c`` and the photocurrent is ``R*|E_lo + sum_k E_k|^2`` (or the
balanced / IQ forms), so carrier beats, sideband beats, self-beats, harmonics and
intermodulation appear by themselves. Only what a scene declares is computed: no phase-noise
process for an ideal laser, no per-sample carrier phase for static targets, no gate for CW,
no noise generator that is switched off.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from scipy import signal

from ..frame import Frame, PulseInfo, TruthTarget
from ..phase import C, tone_cycles
from ..scene import Scene, SceneError, target_delay_problem
from ..snr import K_B, Q_E, BroadbandLight, ase_light, solar_light
from .optics import beyond_band, broadband_field, carrier_cycles, delayed_phase, gate, mzm_transmission, wiener_phase

__all__ = ["Simulator", "simulate_frame", "K_B", "Q_E"]


@dataclass
class _Copy:
    """A delayed copy of the transmitted field: amplitude, delay, velocity, range at frame start."""

    amplitude: float
    tau0_s: float
    range_m: float
    velocity_mps: float


class Simulator:
    """Frames of a scene, deterministic for a given seed.

    Parameters
    ----------
    scene : Scene
    seed : int, optional
        Overrides ``scene.seed``. Frames drawn in the same order from the same seed are
        identical.
    """

    def __init__(self, scene: Scene, seed: int | None = None) -> None:
        self.scene = scene
        self.rng = np.random.default_rng(scene.seed if seed is None else seed)
        self._drift = np.zeros(len(scene.modulator.tones))
        self._next = 0
        self._auto_full_scale: float | None = None
        self._gain, self._broadband = self._optical_noise(scene)

    @staticmethod
    def _optical_noise(scene: Scene) -> tuple[float, list[BroadbandLight]]:
        """The amplifier's linear gain and the broadband lights at the detector (ASE, sunlight)."""
        on = scene.optical_noise
        lam = scene.laser.wavelength_m
        gain, lights = 1.0, []
        if on.amplifier is not None:
            amp = on.amplifier
            gain = 10 ** (amp.gain_db / 10)
            if gain > 1:
                lights.append(ase_light(gain, amp.spontaneous_emission_factor, lam, amp.optical_bandwidth_hz))
        if on.solar is not None:
            sol = on.solar
            lights.append(solar_light(sol.spectral_irradiance_w_per_m2_nm, sol.aperture_area_m2,
                                      sol.filter_bandwidth_m, lam, gain))
        return gain, lights

    # -- public ------------------------------------------------------------------------
    def frames(self, count: int | None = None) -> Iterator[Frame]:
        """Yield ``count`` frames (default: the scene's frame count)."""
        for _ in range(self.scene.frames.count if count is None else count):
            yield self.next_frame()

    def next_frame(self) -> Frame:
        idx = self._next
        self._next += 1
        return self.frame(idx)

    def frame(self, index: int) -> Frame:
        """Simulate frame ``index`` of the sequence (its RNG draws follow the previous call)."""
        if self.scene.ptof is not None:  # PToF mode (issue 14): short pulses, direct detection
            from .pulses import pulse_frame
            return pulse_frame(self, index)
        sc = self.scene
        dig = sc.digitizer
        fs, n = dig.sample_rate_hz, dig.samples
        t_start = index / sc.frames.rate_hz
        t_centre = (n - 1) / (2 * fs)
        rng = self.rng

        dt_trig = rng.normal(0.0, sc.noise.trigger_jitter_s) if sc.noise.trigger_jitter_s > 0 else 0.0
        if sc.noise.rf_phase_drift_rad > 0:
            self._drift += rng.normal(0.0, sc.noise.rf_phase_drift_rad, self._drift.size)

        for k in range(len(sc.targets)):  # the scene checked its own frames; a stream goes on beyond them
            late = target_delay_problem(sc, k, index)
            if late:
                raise SceneError(late)
        copies = [
            _Copy(10 ** (-t.loss_db / 20), sc.paths.tau0_s, t.range_m + t.velocity_mps * t_start, t.velocity_mps)
            for t in sc.targets
        ]
        field_lo, echoes, gate_tx = self._fields(copies, fs, n, dt_trig, rng)
        i_sig = self._detect(field_lo, echoes, fs, rng)
        volts = i_sig * (sc.receiver.load_ohm * sc.receiver.gain)

        if sc.receiver.kind == "iq":
            chans = [volts.real, volts.imag]
            names = ["i", "q"]
        else:
            chans = [volts]
            names = ["pd"]
        samples, scale, offset = self._digitize(chans, gate_tx, names)

        truth = tuple(
            TruthTarget(range_m=c.range_m + c.velocity_mps * t_centre, velocity_mps=c.velocity_mps)
            for c in copies
        )
        pulse = None
        if sc.pulsing is not None:
            pulse = PulseInfo(sc.pulsing.period_s, sc.pulsing.duty, sc.pulsing.delay_s)
        return Frame(
            samples=samples,
            fs_hz=fs,
            tones_hz=tuple(sc.tones_hz),
            wavelength_m=sc.laser.wavelength_m,
            receiver=sc.receiver.kind,
            channels=tuple(names),
            scale=scale,
            offset=offset,
            tone_phases_rad=tuple(t.phase_rad for t in sc.modulator.tones),
            pulse=pulse,
            architecture=sc.architecture.kind,
            # the offline default identity (mtcw_core.frame: whoever emits a stream stamps it; on the
            # wire the acquisition node's publisher replaces these)
            seq=index,
            t_ns=sc.frames.start_time_ns + round(t_start * 1e9),
            source=sc.name,
            truth=truth,
        )

    # -- fields ------------------------------------------------------------------------
    def _fields(self, copies: list[_Copy], fs: float, n: int, dt_trig: float, rng: np.random.Generator):
        sc = self.scene
        lam = sc.laser.wavelength_m
        p0 = sc.laser.power_w
        beta = sc.lo_fraction
        lw = sc.laser.linewidth_hz
        tones = sc.modulator.tones
        f = [t.frequency_hz for t in tones]
        m = [t.modulation_index for t in tones]
        phi = [t.phase_rad / (2 * math.pi) + d / (2 * math.pi) for t, d in zip(tones, self._drift)]
        pul = sc.pulsing
        a_tx = math.sqrt((1 - beta) * p0)

        # delays of every copy that reaches the detector (needed for the phase-noise span)
        tau_lo = sc.paths.tau0_s + sc.paths.lo_path_difference_m / C
        ref = sc.architecture
        ref_copy = None
        if ref.kind == "modulated_reference":
            ref_copy = _Copy(10 ** (-ref.reference_loss_db / 20), 0.0, ref.reference_range_m, 0.0)

        phase = None
        pad = 0
        if lw > 0:
            taus = [tau_lo] + [c.tau0_s + 2 * c.range_m / C for c in copies]
            if ref_copy is not None:
                taus.append(2 * ref_copy.range_m / C)
            pad = int(math.ceil(max(max(taus), 0.0) * fs)) + 2
            phase = wiener_phase(n + pad, fs, lw, rng)

        def tx_delayed(c: _Copy) -> np.ndarray:
            """a * E_tx(t - tau(t)) * exp(-j*2*pi*f0*tau(t)), shape (n,)."""
            tau = c.tau0_s + 2 * c.range_m / C
            chirp = [-2 * fi * c.velocity_mps / C for fi in f] if c.velocity_mps else None
            offs = [fi * (dt_trig - tau) + p for fi, p in zip(f, phi)]
            e = mzm_transmission(f, m, offs, fs, n, sc.modulator.transfer, chirp)
            if pul is not None:
                g = gate(n, fs, pul.period_s, pul.duty, pul.delay_s + tau - dt_trig, pul.rise_time_s)
                e = e * (g / math.sqrt(pul.duty))
            cyc0 = carrier_cycles(lam, c.tau0_s, c.range_m)
            if c.velocity_mps:
                # carrier Doppler: -f0 * 2*v*t/c, exact cycles from the integer sample index
                fd = -2 * c.velocity_mps / lam
                carrier = np.exp(2j * np.pi * tone_cycles(fd, fs, n, -cyc0))
            else:
                carrier = np.exp(-2j * np.pi * cyc0)
            if phase is not None:
                # the phase-noise delay is taken at the record's centre (v*T/c is far below 1/fs)
                tau_c = tau + 2 * c.velocity_mps * (n / (2 * fs)) / C
                carrier = carrier * np.exp(1j * delayed_phase(phase, pad, n, tau_c, fs, lw, rng))
            return (c.amplitude * a_tx) * e * carrier

        if ref_copy is None:
            lo_amp = math.sqrt(beta * p0) * np.exp(-2j * np.pi * carrier_cycles(lam, tau_lo, 0.0))
            if phase is not None:
                field_lo = lo_amp * np.exp(1j * delayed_phase(phase, pad, n, tau_lo, fs, lw, rng))
            else:
                field_lo = lo_amp  # a constant: no array needed
        else:
            field_lo = tx_delayed(ref_copy)
        echoes = sum(tx_delayed(c) for c in copies)

        gate_tx = None
        if pul is not None and pul.reference_channel:
            gate_tx = gate(n, fs, pul.period_s, pul.duty, pul.delay_s - dt_trig, pul.rise_time_s)
        return field_lo, echoes, gate_tx

    # -- detection -----------------------------------------------------------------------
    def _detect(self, e_lo, e_sig: np.ndarray, fs: float, rng: np.random.Generator) -> np.ndarray:
        sc = self.scene
        rx = sc.receiver
        r = rx.responsivity_a_per_w
        nz = sc.noise
        bb = self._broadband
        if self._gain != 1.0:
            e_lo, e_sig = e_lo * math.sqrt(self._gain), e_sig * math.sqrt(self._gain)
        bb_power = sum(b.power_w for b in bb)
        if bb:
            n = e_sig.shape[0]
            n_par = sum(broadband_field(n, fs, b.psd_w_per_hz, b.bandwidth_hz, rng) for b in bb)
        if rx.kind == "single":
            if bb:
                # the polarisation matching the LO beats with LO and echo, both beat with themselves;
                # what a band wider than fs adds beyond its sampled part is Gaussian (beyond_band)
                n_perp = sum(broadband_field(n, fs, b.psd_w_per_hz, b.bandwidth_hz, rng) for b in bb)
                extra_mean, extra_var = beyond_band([(b.psd_w_per_hz, b.bandwidth_hz) for b in bb], fs)
                intensity = np.abs(e_lo + e_sig + n_par) ** 2 + np.abs(n_perp) ** 2
                if extra_var > 0:
                    intensity += rng.normal(extra_mean, math.sqrt(extra_var), n)
                i = r * intensity + rx.dark_current_a
            else:
                i = r * np.abs(e_lo + e_sig) ** 2 + rx.dark_current_a
            mean_i = float(np.mean(i))
        else:
            # an ideal balanced / IQ receiver keeps only the beats with the LO
            mix = 2 * r * np.conj(e_lo) * (e_sig + n_par if bb else e_sig)
            i = mix.real if rx.kind == "balanced" else mix
            mean_i = r * float(np.mean(np.abs(e_lo) ** 2 + np.abs(e_sig) ** 2)) + rx.dark_current_a + r * bb_power
        var = 0.0
        if nz.shot:
            var += Q_E * mean_i * fs  # 2*q*I*B with B = fs/2
        if nz.thermal:
            var += 4 * K_B * nz.temperature_k * nz.noise_figure * (fs / 2) / rx.load_ohm
        if nz.rin_db_per_hz is not None and rx.kind == "single":
            # the laser's light (and, as always here, the dark current); not ASE or sunlight
            i_laser = mean_i - r * bb_power if bb else mean_i
            var += 10 ** (nz.rin_db_per_hz / 10) * i_laser**2 * (fs / 2)
        if var > 0:
            sd = math.sqrt(var)
            if np.iscomplexobj(i):
                i = i + sd * (rng.standard_normal(i.shape) + 1j * rng.standard_normal(i.shape))
            else:
                i = i + rng.normal(0.0, sd, i.shape)
        if rx.bandwidth_hz is not None and rx.bandwidth_hz < fs / 2:
            sos = signal.butter(2, rx.bandwidth_hz, fs=fs, output="sos")
            if np.iscomplexobj(i):
                i = signal.sosfilt(sos, i.real) + 1j * signal.sosfilt(sos, i.imag)
            else:
                i = signal.sosfilt(sos, i)
        return i

    # -- digitizer -----------------------------------------------------------------------
    def _digitize(self, chans: list[np.ndarray], gate_tx: np.ndarray | None, names: list[str]):
        dig = self.scene.digitizer
        if dig.adc_bits is None:
            fs_v = dig.full_scale_v
            out = [c.astype(np.float32) if fs_v is None else np.clip(c, -fs_v, fs_v).astype(np.float32) for c in chans]
            if gate_tx is not None:
                out.append(gate_tx.astype(np.float32))
                names.append("pulse_ref")
            return np.stack(out), 1.0, 0.0
        bits = dig.adc_bits
        fs_v = dig.full_scale_v or self._auto_full_scale
        if fs_v is None:
            # auto range once, on the first frame, then keep it like a scope would
            fs_v = 1.05 * max(float(np.max(np.abs(c))) for c in chans)
            fs_v = fs_v if fs_v > 0 else 1.0
            self._auto_full_scale = fs_v
        top = 2 ** (bits - 1)
        scale = fs_v / top
        dtype = np.int8 if bits <= 8 else np.int16
        out = [np.clip(np.rint(c / scale), -top, top - 1).astype(dtype) for c in chans]
        if gate_tx is not None:
            out.append(np.rint(gate_tx * (top // 2)).astype(dtype))
            names.append("pulse_ref")
        return np.stack(out), scale, 0.0


def simulate_frame(scene: Scene, index: int = 0, seed: int | None = None) -> Frame:
    """Convenience: frame ``index`` of a fresh simulator (draws of earlier frames are skipped)."""
    sim = Simulator(scene, seed)
    frame = None
    for _ in range(index + 1):
        frame = sim.next_frame()
    assert frame is not None
    return frame
