"""PToF mode of the simulator: short pulses, direct detection, the digitizer of the scene.

The dissertation compares AB-MTCW with a pulsed time-of-flight measurement on the same bench
(its Sec. 3.4: a mode-locked laser at 25 MHz, both mirrors' pulses on one detector, sampled every
50 ps) and measures the quasi-CW bench's path with a 4 ns pulse cross-correlated with the pulse
generator's own output (its Sec. 5.5). A scene with a ``ptof`` section simulates that mode.

Physics: the pulses are far shorter than the delay between the arms and far less coherent than
the CW laser (a mode-locked pulse of 1 ps is 0.3 mm long), so the echoes do not interfere and
the photocurrent is the sum of their powers, ``i(t) = R * sum_k P_k(t) + I_dark``, each
``P_k(t) = a_k^2 * p(t - tau_k(t))`` with ``tau_k(t) = tau0 + 2*(L_k + v_k*t)/c`` (the reference
mirror: ``2*L_ref/c``), ``p`` the transmitted power. Then the scene's receiver and noise:

- ``gaussian`` (mode-locked): the optical pulse (FWHM ``w``) through a detector of bandwidth
  ``B`` (``receiver.bandwidth_hz``) is taken as a Gaussian of variance ``s_p^2 + s_d^2``,
  ``s_p = w/(2*sqrt(2 ln 2))``, ``s_d = sqrt(ln 2)/(2*pi*B)`` (a Gaussian impulse response with
  -3 dB at ``B``), evaluated in closed form at every sample time: an exact sub-sample delay with
  no resampling. Pulse energy ``P_avg / f_rep``.
- ``rectangular`` (generator pulse): ``p(t)`` the raised-cosine-edged gate of
  :func:`.optics.gate` at peak power ``P_avg / (f_rep * width)``, through the receiver's
  2nd-order Butterworth like the CW simulator; the ``pulse_ref`` channel is the gate itself.
- shot (``2*q*mean(i)*B``), thermal and dark current as in :mod:`.engine`; then its digitizer.

Frames carry no tones (``tones_hz = ()``), ``pulse`` = (period, width/period, delay) and the
scene's architecture (``modulated_reference``: the reference mirror's pulse is in the record).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy import signal

from ..frame import Frame, PulseInfo, TruthTarget
from ..phase import C
from .optics import gate

#: the engine's Simulator (not imported: the engine imports this module; core has no import cycles)
Simulator = Any

Q_E = 1.602176634e-19
K_B = 1.380649e-23
FWHM_PER_SIGMA = 2 * math.sqrt(2 * math.log(2))


def detector_sigma_s(bandwidth_hz: float | None) -> float:
    """Standard deviation (s) of a Gaussian impulse response whose power response is -3 dB at
    ``bandwidth_hz`` (0 for an unlimited detector)."""
    return 0.0 if bandwidth_hz is None else math.sqrt(math.log(2)) / (2 * math.pi * bandwidth_hz)


def _gaussian_train(t: np.ndarray, t0_s: float, period_s: float, sigma_s: float, energy_j: float,
                    v_delay_per_s: float) -> np.ndarray:
    """Power (W) of Gaussian pulses of ``energy_j`` centred at ``t0 + m*P + v_delay*t`` at times ``t`` (s).

    Only the pulses that reach the record are summed (each within 10 sigma of its centre).
    """
    out = np.zeros(t.size)
    fs = 1.0 / (t[1] - t[0])
    peak = energy_j / (math.sqrt(2 * math.pi) * sigma_s)
    half = int(math.ceil(10 * sigma_s * fs)) + 1
    m0 = math.floor((t[0] - t0_s) / period_s) - 1
    m = m0
    while True:
        c = t0_s + m * period_s
        c = c + v_delay_per_s * c  # the moving target's delay at the pulse's time (to first order)
        if c - 10 * sigma_s > t[-1]:
            break
        i = int(round((c - t[0]) * fs))
        a, b = max(i - half, 0), min(i + half + 1, t.size)
        if b > a:
            u = (t[a:b] - c) / sigma_s
            out[a:b] += peak * np.exp(-0.5 * u * u)
        m += 1
    return out


def pulse_frame(sim: Simulator, index: int) -> Frame:
    """Frame ``index`` of a scene in PToF mode (``scene.ptof`` set); draws from ``sim.rng``."""
    sc = sim.scene
    pt = sc.ptof
    assert pt is not None
    dig, rx, nz = sc.digitizer, sc.receiver, sc.noise
    fs, n = dig.sample_rate_hz, dig.samples
    rng = sim.rng
    period = 1.0 / pt.repetition_hz
    t_start = index / sc.frames.rate_hz
    t_centre = (n - 1) / (2 * fs)
    dt_trig = rng.normal(0.0, nz.trigger_jitter_s) if nz.trigger_jitter_s > 0 else 0.0
    t = np.arange(n, dtype=np.float64) / fs + dt_trig  # sample times in the transmitter's clock

    # (amplitude^2, round-trip delay at the frame's start, delay rate) of every copy
    copies = [(10 ** (-tg.loss_db / 10), sc.paths.tau0_s + 2 * (tg.range_m + tg.velocity_mps * t_start) / C,
               2 * tg.velocity_mps / C) for tg in sc.targets]
    if sc.architecture.kind == "modulated_reference":
        copies.insert(0, (10 ** (-sc.architecture.reference_loss_db / 10), 2 * sc.architecture.reference_range_m / C,
                          0.0))

    if pt.shape == "gaussian":
        sigma = math.hypot(pt.pulse_width_s / FWHM_PER_SIGMA, detector_sigma_s(rx.bandwidth_hz))
        energy = pt.average_power_w / pt.repetition_hz
        power = sum(_gaussian_train(t, pt.delay_s + tau, period, sigma, a2 * energy, rate) for a2, tau, rate in copies)
        tx = None
    else:
        peak = pt.average_power_w / (pt.repetition_hz * pt.pulse_width_s)
        # the gate's on time runs between the ramps' half points when start and duty include one ramp
        duty = (pt.pulse_width_s + pt.rise_time_s) * pt.repetition_hz
        start = pt.delay_s - pt.rise_time_s / 2

        def pulses(delay: float) -> np.ndarray:
            return gate(n, fs, period, duty, start + delay - dt_trig, pt.rise_time_s)

        power = sum(a2 * peak * pulses(tau) for a2, tau, _ in copies)  # a target's motion over one frame: < 1 fs
        tx = pulses(0.0) if pt.reference_channel else None

    i = rx.responsivity_a_per_w * power + rx.dark_current_a
    var = 0.0
    if nz.shot:
        var += Q_E * float(np.mean(i)) * fs
    if nz.thermal:
        var += 4 * K_B * nz.temperature_k * nz.noise_figure * (fs / 2) / rx.load_ohm
    if var > 0:
        i = i + rng.normal(0.0, math.sqrt(var), n)
    if pt.shape == "rectangular" and rx.bandwidth_hz is not None and rx.bandwidth_hz < fs / 2:
        i = signal.sosfilt(signal.butter(2, rx.bandwidth_hz, fs=fs, output="sos"), i)
    volts = i * (rx.load_ohm * rx.gain)
    samples, scale, offset = sim._digitize([volts], tx, ["pd"])
    names = ("pd", "pulse_ref") if tx is not None else ("pd",)
    truth = tuple(TruthTarget(range_m=tg.range_m + tg.velocity_mps * (t_start + t_centre), velocity_mps=tg.velocity_mps)
                  for tg in sc.targets)
    return Frame(
        samples=samples, fs_hz=fs, tones_hz=(), wavelength_m=sc.laser.wavelength_m, receiver="single",
        channels=names, scale=scale, offset=offset, tone_phases_rad=None,
        pulse=PulseInfo(period, pt.pulse_width_s / period, pt.delay_s), architecture=sc.architecture.kind,
        seq=index, t_ns=sc.frames.start_time_ns + round(t_start * 1e9), source=sc.name, truth=truth,
    )
