"""The SNR model (``mtcw_core.snr``) against closed forms and against the simulator's measured lines.

The simulator draws ASE and sunlight as optical fields and detects them by square law; the model
adds closed-form spectral densities. They share no code beyond the physical constants and the
definitions of the lights' densities, so agreement checks both.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mtcw_core.phase import C
from mtcw_core.scene import scene_from_dict
from mtcw_core.simulate import Simulator
from mtcw_core.snr import (H_PLANCK, K_B, Q_E, Link, ase_light, dissertation_eq_5_11, dissertation_eq_5_12,
                           line_snr, solar_light)

# a record on an exact 256 Hz grid: the Doppler line and the tone lines sit on bins
FS, N = 2.0**26, 2**18
FD = 19531 * 256.0  # Doppler line (Hz)
FT = 78125 * 256.0  # the tone (20 MHz)
M = 0.01  # small-signal MZM index: the sideband lines are 52 dB below the carrier line


def _scene(link: Link, attenuation_db: float, **over):
    """The link as a simulated bench: P_LO = beta*P0, echo carrier (1-beta)*P0/2 before attenuation."""
    p0 = link.p_lo_w + 2 * link.p_echo_w
    optical = {"amplifier": {"gain_db": link.gain_db, "spontaneous_emission_factor": link.n_sp,
                             "optical_bandwidth_hz": link.optical_bandwidth_hz}}
    if link.solar_irradiance_w_per_m2_nm > 0:
        optical["solar"] = {"spectral_irradiance_w_per_m2_nm": link.solar_irradiance_w_per_m2_nm,
                            "aperture_area_m2": link.area_m2, "filter_bandwidth_m": link.filter_bandwidth_m}
    d = {
        "laser": {"wavelength_m": link.wavelength_m, "power_w": p0},
        "lo_fraction": link.p_lo_w / p0,
        "modulator": {"transfer": "small_signal", "tones": [{"frequency_hz": FT, "modulation_index": M}]},
        "targets": [{"range_m": 3.0, "velocity_mps": FD * link.wavelength_m / 2, "loss_db": attenuation_db}],
        "receiver": {"kind": link.receiver, "responsivity_a_per_w": link.responsivity_a_per_w,
                     "load_ohm": link.load_ohm, "dark_current_a": link.dark_current_a},
        "noise": {"shot": True, "thermal": True, "temperature_k": link.temperature_k,
                  "rin_db_per_hz": link.rin_db_per_hz},
        "optical_noise": optical,
        "digitizer": {"sample_rate_hz": FS, "samples": N},
    }
    d.update(over)
    return scene_from_dict(d)


def _periodogram(scene, seed: int = 1) -> np.ndarray:
    """|DFT|^2/N of the detector current (A^2): E = per-sample noise variance off the lines."""
    fr = Simulator(scene, seed).frame(0)
    x = fr.volts(fr.channels[0]).astype(np.float64) / scene.receiver.load_ohm
    return np.abs(np.fft.rfft(x)) ** 2 / N


def _noise_psd(p: np.ndarray, lo_hz: float, hi_hz: float) -> float:
    """One-sided current PSD (A^2/Hz) measured over the bins between lo and hi."""
    k = np.arange(p.size) * FS / N
    return 2 * float(np.mean(p[(k > lo_hz) & (k < hi_hz)])) / FS


def measured_line_snr(p: np.ndarray, f_line_hz: float, bandwidth_hz: float) -> tuple[float, float]:
    """Line SNR in ``bandwidth_hz`` (dB) from a periodogram, and its standard error (dB).

    The line's mean square ``A^2/2`` from its bin (noise subtracted: E|X|^2/N = N*A^2/4 + s2), the
    noise PSD from the bins between the Doppler line and the lower tone line (2000-bin guards).
    """
    lo_hz, hi_hz = FD + 2000 * FS / N, FT - FD - 2000 * FS / N
    n0 = _noise_psd(p, lo_hz, hi_hz)
    bins = (hi_hz - lo_hz) * N / FS
    s2 = n0 * FS / 2
    k = int(round(f_line_hz * N / FS))
    a2 = 4 * (p[k] - s2) / N
    per_bin = N * a2 / (4 * s2)
    # the line's bin (noise beating with the line) and the floor's mean over its bins
    sd_db = 10 / math.log(10) * math.hypot(math.sqrt(2 * per_bin + 1) / per_bin, 1 / math.sqrt(bins))
    return 10 * math.log10((a2 / 2) / (n0 * bandwidth_hz)), sd_db


ATTENUATIONS_DB = (0.0, 20.0, 40.0, 60.0, 80.0, 100.0, 120.0)


@pytest.mark.parametrize("link", [
    Link(),  # Fig. 36 (the sun in one spatial mode: negligible)
    Link(aperture_area_m2=1e-6),  # the sun in 1 mm^2 counted as coherent: the LO x sun beat dominates
], ids=["fig36", "fig36-sun-1mm2"])
def test_model_matches_simulated_line_snr_over_fig36_range(link):
    """Fig. 36's parameters, attenuation 0..120 dB: the model's SNR of the Doppler line (LO x echo
    carrier) against the line the simulator makes, in a 1 MHz filter."""
    carrier_fraction = 1 / (1 + M**2 / 8)  # the carrier's share of the small-signal MZM's power
    for att in ATTENUATIONS_DB:
        p = _periodogram(_scene(link, att))
        meas_db, sd_db = measured_line_snr(p, FD, 1e6)
        model_db = float(link.terms(att, 1e6, line_fraction=carrier_fraction, line_frequency_hz=FD).snr_db)
        assert abs(meas_db - model_db) < 0.02 + 4 * sd_db, (att, meas_db, model_db, sd_db)


def test_model_matches_simulated_tone_line_snr():
    """A tone line (LO x upper sideband at f_i + f_d): its component is m^2/16 of the echo."""
    link = Link()
    att = 30.0
    p = _periodogram(_scene(link, att))
    meas_db, sd_db = measured_line_snr(p, FT + FD, 1e6)
    frac = (M**2 / 16) / (1 + M**2 / 8)
    model_db = float(link.terms(att, 1e6, line_fraction=frac, line_frequency_hz=FT + FD).snr_db)
    assert sd_db < 0.1
    assert abs(meas_db - model_db) < 0.02 + 4 * sd_db


NOISE_CASES = {
    # name: (link changes, scene changes): a single photodiode, no echo; the model's total noise
    # PSD against the simulator's, each case dominated by different terms
    "thermal+shot+dark": (dict(gain_db=0.0, solar_irradiance_w_per_m2_nm=0.0, dark_current_a=2e-3), {}),
    "rin": (dict(gain_db=0.0, solar_irradiance_w_per_m2_nm=0.0, rin_db_per_hz=-130.0), {}),
    "lo-ase": (dict(gain_db=10.0, solar_irradiance_w_per_m2_nm=0.0), {}),
    "ase-ase": (dict(gain_db=30.0, solar_irradiance_w_per_m2_nm=0.0, p_lo_w=1e-9), {}),
    "sun-sun+ase-sun": (dict(gain_db=20.0, aperture_area_m2=1e-7, p_lo_w=1e-9), {}),
}


@pytest.mark.parametrize("case", list(NOISE_CASES))
def test_model_noise_terms_match_simulated_single_photodiode(case):
    link_change, _ = NOISE_CASES[case]
    link = dataclasses.replace(Link(receiver="single"), **link_change)
    sc = _scene(link, 400.0)
    p = _periodogram(sc)
    measured = _noise_psd(p, 1e6, FS / 2 - 1e6)
    terms = link.terms(400.0, 1.0, line_frequency_hz=FS / 4)
    model = float(terms.noise_a2)
    parts = {k: float(v) / model for k, v in terms.terms_a2().items() if float(v) > 0.01 * model}
    # the case exercises what it names
    want = {"thermal+shot+dark": {"shot"}, "rin": {"rin"}, "lo-ase": {"sig_ase"}, "ase-ase": {"ase_ase"},
            "sun-sun+ase-sun": {"sun_sun", "ase_sun"}}[case]
    assert want <= set(parts), parts
    assert measured / model == pytest.approx(1.0, abs=0.02), parts


def test_shot_limit_closed_form_and_eq_5_12():
    """Only shot noise: SNR = R*G*P_line*P_lo/((P_lo + P_echo)*q*df) -- half of Eq. (5.12), which
    counts the peak-squared line (4 R^2 G^2 P_lo P_echo) and the LO alone in the shot term."""
    r, g, p_lo, p_s, df = 0.8, 2.0, 5e-3, 1e-9, 1e6
    t = line_snr(p_lo, p_s, df, responsivity_a_per_w=r, gain=g, load_ohm=1e30, receiver="balanced")
    assert float(t.snr) == pytest.approx(r * g * p_s * p_lo / ((p_lo + p_s) * Q_E * df), rel=1e-12)
    eq512 = float(dissertation_eq_5_12(p_s, df, responsivity_a_per_w=r, gain=g))
    assert float(t.snr) == pytest.approx(eq512 / 2, rel=1e-6)


def test_eq_5_11_as_printed_reduces_to_eq_5_12_when_shot_dominates():
    """The dissertation's own step from (5.11) to (5.12): strong LO, no amplifier noise, no sun."""
    kw = dict(responsivity_a_per_w=0.9, load_ohm=1e30, temperature_k=300.0, gain=1.0, n_sp=1.0, wavelength_m=1e-6,
              ase_bandwidth_hz=1e11, solar_power_w=0.0, solar_bandwidth_hz=1e11)
    full = dissertation_eq_5_11(0.05, 1e-12, 1e6, **kw)
    assert float(full) == pytest.approx(float(dissertation_eq_5_12(1e-12, 1e6, responsivity_a_per_w=0.9, gain=1.0)))


def test_slope_and_bandwidth_scaling():
    """Far from the LO power, SNR falls 1 dB per dB of attenuation and 10 dB per decade of filter."""
    link = Link()
    att = np.arange(40.0, 121.0, 10.0)
    snr = np.stack([link.terms(att, b).snr_db for b in (1e6, 1e7, 1e8)])
    np.testing.assert_allclose(np.diff(snr, axis=1), -10.0, atol=0.01)
    np.testing.assert_allclose(snr[0] - snr[1], 10.0, atol=0.01)
    np.testing.assert_allclose(snr[1] - snr[2], 10.0, atol=0.01)


def test_light_densities_closed_form():
    lam = 1e-6
    ase = ase_light(2.0, 1.0, lam, 1e12)  # G = 2, n_sp = 1: one photon per mode, h*f0 per Hz
    assert ase.psd_w_per_hz == pytest.approx(H_PLANCK * C / lam, rel=1e-12, abs=0)
    sun = solar_light(0.75, 1e-4, 2e-9, lam)  # 0.75 W/m^2/nm * 1 cm^2 * 2 nm = 150 uW over c*2nm/lam^2
    assert sun.bandwidth_hz == pytest.approx(599.584916e9)
    assert sun.power_w == pytest.approx(150e-6, rel=1e-12, abs=0)


def test_balanced_receiver_cancels_direct_terms_single_keeps_them():
    kw = dict(ase=ase_light(100.0, 1.5, 1.55e-6, 1e12), sun=solar_light(0.3, 1e-4, 1e-9, 1.55e-6, 100.0),
              rin_db_per_hz=-140.0, gain=100.0)
    bal = line_snr(1e-3, 1e-9, 1e6, receiver="balanced", **kw)
    one = line_snr(1e-3, 1e-9, 1e6, receiver="single", **kw)
    for k in ("rin", "ase_ase", "sun_sun", "ase_sun"):
        assert float(getattr(bal, f"{k}_a2")) == 0.0 and float(getattr(one, f"{k}_a2")) > 0.0
    assert float(one.sig_ase_a2) > float(bal.sig_ase_a2) > 0.0
    assert float(bal.thermal_a2) == pytest.approx(4 * K_B * 300.0 / 50.0 * 1e6, rel=1e-12, abs=0)


def test_bad_inputs_name_the_argument():
    with pytest.raises(ValueError, match="receiver"):
        line_snr(1e-3, 1e-9, 1e6, receiver="iq")
    with pytest.raises(ValueError, match="bandwidth_hz"):
        line_snr(1e-3, 1e-9, 0.0)
    with pytest.raises(ValueError, match="gain"):
        ase_light(0.5, 1.0, 1e-6, 1e9)


def test_cli_snr_writes_table_json_png_and_names_bad_options(tmp_path):
    import csv as _csv

    from typer.testing import CliRunner

    from services.cli import app

    r = CliRunner().invoke(app, ["snr", "-o", str(tmp_path), "--step", "10"])
    assert r.exit_code == 0, r.output
    rows = list(_csv.DictReader(open(tmp_path / "snr.csv")))
    assert [float(x["attenuation_db"]) for x in rows] == [10.0 * k for k in range(13)]
    # the table is the model: at 60 dB in 1 MHz, shot + LO x ASE + thermal (+ dark) with Fig. 36's numbers
    g, rr, p_lo, p_s = 10**0.3, 0.7, 5e-3, 10e-3 * 1e-6
    s_ase = (g - 1) * 1.5 * H_PLANCK * C / 1e-6
    noise = (2 * Q_E * (rr * g * (p_lo + p_s) + 1.5e-9) + 4 * rr**2 * g * p_lo * s_ase + 4 * K_B * 300 / 50) * 1e6
    want_db = 10 * math.log10(2 * rr**2 * g**2 * p_lo * p_s / noise)
    assert float(rows[6]["snr_db_1MHz"]) == pytest.approx(want_db, abs=0.02)
    assert (tmp_path / "snr.png").stat().st_size > 10_000 and (tmp_path / "snr.json").exists()
    assert "20 dB at" in r.output
    bad = CliRunner().invoke(app, ["snr", "-o", str(tmp_path), "--bandwidths", "1e6,-5"])
    assert bad.exit_code != 0 and "bandwidths" in bad.output and "Traceback" not in bad.output
    bad = CliRunner().invoke(app, ["snr", "-o", str(tmp_path), "--receiver", "iq"])
    assert bad.exit_code != 0 and "receiver" in bad.output
