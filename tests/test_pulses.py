"""The simulator's PToF mode (mtcw_core.simulate.pulses) against the physics it claims."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mtcw_core.phase import C
from mtcw_core.scene import SceneError, load_scene, scene_variant
from mtcw_core.simulate import Simulator


def test_pulse_simulator_puts_each_pulse_at_its_round_trip_delay():
    """Centroids of the simulated pulses against 2*L/c (an independent reading of the samples)."""
    sc = scene_variant(load_scene("ptof-bench"), digitizer={"adc_bits": None}, noise={"shot": False, "thermal": False})
    fr = next(Simulator(sc).frames(1))
    x = fr.volts("pd")
    fs, period = fr.fs_hz, fr.pulse.period_s
    k = np.arange(x.size)
    for tau in (2 * 0.03 / C, 2 * sc.targets[0].range_m / C):
        c = tau * fs
        sel = np.abs(k - c) < 8  # the first pulse of this arm
        centroid = float(np.sum(k[sel] * x[sel]) / np.sum(x[sel]))
        assert centroid == pytest.approx(c, abs=0.05)
    # the energy of each pulse: R * a^2 * P_avg / f_rep, times the load
    sel = np.abs(k - 2 * 0.03 / C * fs) < 8
    energy = float(np.sum(x[sel])) / fs / sc.receiver.load_ohm
    expect = sc.receiver.responsivity_a_per_w * 10 ** (-sc.architecture.reference_loss_db / 10) * \
        sc.ptof.average_power_w / sc.ptof.repetition_hz
    assert energy == pytest.approx(expect, rel=1e-3)
    assert fr.tones_hz == () and fr.pulse.period_s == pytest.approx(40e-9)
    assert math.isclose(fr.pulse.duty, 1e-12 / 40e-9)


def test_a_pulse_longer_than_half_the_period_names_the_field():
    with pytest.raises(SceneError, match="ptof: .*pulse_width_s"):
        scene_variant(load_scene("ptof-bench"), ptof={"pulse_width_s": 30e-9})


def test_rectangular_pulse_with_a_reference_channel_is_the_generator_pulse():
    sc = scene_variant(load_scene("ptof-quasi-cw"), digitizer={"samples": 2**16}, noise={"shot": False, "thermal": False})
    fr = next(Simulator(sc).frames(1))
    assert fr.channels == ("pd", "pulse_ref")
    ref = fr.volts("pulse_ref")
    half = np.flatnonzero(ref >= 0.5 * ref.max())
    # on between half maxima for pulse_width_s, from delay_s
    assert half[0] / fr.fs_hz == pytest.approx(sc.ptof.delay_s, abs=1 / fr.fs_hz)
    assert (half[-1] - half[0] + 1) / fr.fs_hz == pytest.approx(sc.ptof.pulse_width_s, abs=1.5 / fr.fs_hz)
    echo = np.flatnonzero(fr.volts("pd") >= 0.5 * fr.volts("pd").max())
    assert (echo[0] - half[0]) / fr.fs_hz == pytest.approx(2 * 931.15 / C, abs=1 / fr.fs_hz)
