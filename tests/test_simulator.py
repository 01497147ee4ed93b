"""The simulator against independent physical facts (not against its own earlier output)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mtcw_core.phase import C
from mtcw_core.scene import SceneError, load_scene, bundled_scenes, scene_from_dict
from mtcw_core.simulate import Simulator, simulate_frame
from mtcw_core.simulate.engine import K_B, Q_E
from mtcw_core.simulate.optics import delayed_phase, wiener_phase

from .conftest import make_scene, spectrum, tones

LAM = 1.064e-6


def dft(x: np.ndarray, f: float, fs: float) -> complex:
    """Exact DFT (rectangular window) at frequency f, referred to the first sample, amplitude-normalised."""
    k = np.arange(x.size)
    return complex(np.sum(x * np.exp(-2j * np.pi * np.mod(k * (f / fs), 1.0))) * 2 / x.size)


def test_static_reference_frame_bit_exact(ref_dir):
    """An independent implementation of the spec gives the same noiseless frame."""
    ref = np.fromfile(ref_dir / "ref-static-3tone.sigmf-data", dtype="<f4")
    fr = simulate_frame(make_scene(digitizer={"samples": 2**16}))
    np.testing.assert_allclose(fr.samples[0], ref, rtol=0, atol=1e-6)


def test_doppler_line_at_2v_over_lambda():
    v = 1.064  # m/s -> f_d = 2 MHz, on the 500 kHz grid of a 10000-sample record
    fr = simulate_frame(make_scene(targets=[{"range_m": 1.0, "velocity_mps": v}], digitizer={"samples": 10_000}))
    f, X = spectrum(fr.signal(), fr.fs_hz, window=False)
    base = np.argmax(np.abs(X[1:200])) + 1
    assert f[base] == pytest.approx(2 * v / LAM, abs=f[1])
    fd = 2 * v / LAM
    # LO x sideband beats at f_i +- f_d (each R*|E_lo|*A/sqrt2*m/2) against the echo self-beat at
    # f_i (R*A^2/2*m): ratio |E_lo| / (sqrt2 * A), A = a*sqrt((1-beta)*P0)
    ratio = math.sqrt(0.1 * 0.05) / (math.sqrt(2) * 0.1 * math.sqrt(0.9 * 0.05))
    for fi in (500e6, 700e6, 950e6):
        up, lo, mid = (np.abs(X[int(round(x / f[1]))]) for x in (fi + fd, fi - fd, fi))
        assert up == pytest.approx(lo, rel=0.02)
        assert up / mid == pytest.approx(ratio, rel=0.03)


def test_self_beat_carries_tone_phase_minus_2pi_f_tau():
    """With the target moving, the line at f_i is the echo self-beat: phase phi_i - 2*pi*f_i*tau."""
    phis = [0.3, -1.1, 2.0]
    L = 3.21
    sc = make_scene(
        modulator={"tones": [{"frequency_hz": f, "phase_rad": p} for f, p in zip((500e6, 700e6, 950e6), phis)]},
        targets=[{"range_m": L, "velocity_mps": 1.064}],
        paths={"tau0_s": 2e-9},
        digitizer={"samples": 10_000},
    )
    fr = simulate_frame(sc)
    x = fr.signal()
    tau = 2e-9 + 2 * (L + 1.064 * fr.duration_s / 2) / C
    for fi, p in zip((500e6, 700e6, 950e6), phis):
        got = np.angle(dft(x - x.mean(), fi, fr.fs_hz))
        want = p - 2 * np.pi * fi * tau
        assert abs(np.angle(np.exp(1j * (got - want)))) < 2e-3


def test_static_target_has_no_doppler_line():
    fr = simulate_frame(make_scene(digitizer={"samples": 2**15}))
    f, X = spectrum(fr.signal(), fr.fs_hz)
    tone_level = np.abs(X[np.argmin(np.abs(f - 500e6))])
    low = np.abs(X[(f > 0.5e6) & (f < 40e6)])  # 2*500-950 = 50 MHz IMD lies above
    assert low.max() < 1e-4 * tone_level


def _balanced(transfer: str):
    sc = make_scene(modulator={"transfer": transfer, **tones(500e6, 700e6, 950e6)}, receiver={"kind": "balanced"},
                    digitizer={"samples": 10_000})
    fr = simulate_frame(sc)
    return fr, fr.signal()


def test_exact_modulator_products_where_predicted():
    """T = cos(pi/4 - x/2): the 2f_i line is m/8 and f_i+f_j is m/4 of the fundamental (to O(m^2))."""
    m = 0.07
    fr, x = _balanced("exact")
    a = {f: abs(dft(x, f, fr.fs_hz)) for f in (500e6, 700e6, 1000e6, 1200e6, 200e6, 300e6)}
    assert a[1000e6] / a[500e6] == pytest.approx(m / 8, rel=0.03)
    assert a[1200e6] / a[500e6] == pytest.approx(m / 4, rel=0.03)
    assert a[200e6] / a[500e6] == pytest.approx(m / 4, rel=0.03)
    assert a[300e6] / a[500e6] > 1e-5  # 2*500 - 700: third-order IMD is present


def test_small_signal_modulator_has_no_products():
    fr, x = _balanced("small_signal")
    fund = abs(dft(x, 500e6, fr.fs_hz))
    for f in (1000e6, 1200e6, 200e6, 300e6, 1450e6):
        assert abs(dft(x, f, fr.fs_hz)) < 1e-6 * fund  # float32 rounding only


def test_shot_and_thermal_noise_variance():
    """No echo: v = R_L*(R*P_lo + noise); var = R_L^2*(q*I*fs + 4kT*F*(fs/2)/R_L)."""
    sc = make_scene(targets=[{"range_m": 1.0, "loss_db": 400.0}], noise={"shot": True, "thermal": True},
                    digitizer={"samples": 2**17})
    fr = simulate_frame(sc)
    v = fr.signal()
    i_mean = 0.9 * 0.1 * 0.05
    fs = fr.fs_hz
    want = 50.0**2 * (Q_E * i_mean * fs + 4 * K_B * 300.0 * fs / 2 / 50.0)
    assert np.mean(v) == pytest.approx(i_mean * 50, rel=1e-3)
    assert np.var(v) == pytest.approx(want, rel=0.02)


def test_phase_noise_has_requested_linewidth():
    """Wiener phase: var[phi(t) - phi(t - tau)] = 2*pi*linewidth*tau, also for fractional delays."""
    rng = np.random.default_rng(0)
    fs, lw, n = 5e9, 2e6, 400_000
    pad = 200
    ph = wiener_phase(n + pad, fs, lw, rng)
    for tau in (10 / fs, 37.4 / fs, 150.5 / fs):
        d = ph[pad:] - delayed_phase(ph, pad, n, tau, fs, lw, rng)
        assert np.var(d) == pytest.approx(2 * np.pi * lw * tau, rel=0.06)


def test_adc_quantisation_and_clipping():
    sc = make_scene(digitizer={"samples": 2**14, "adc_bits": 8})
    sim = Simulator(sc)
    fr = sim.next_frame()
    ideal = simulate_frame(make_scene(digitizer={"samples": 2**14}))
    v = fr.volts("pd")
    assert fr.samples.dtype == np.int8
    assert np.max(np.abs(v - ideal.samples[0])) <= fr.scale / 2 + 1e-7
    # a full scale below the signal clips at the rails
    fs_v = 0.5 * float(np.max(np.abs(ideal.samples[0])))
    clipped = simulate_frame(make_scene(digitizer={"samples": 2**14, "adc_bits": 12, "full_scale_v": fs_v}))
    codes = clipped.samples[0]
    assert codes.max() == 2**11 - 1
    assert np.mean(codes == 2**11 - 1) > 0.1


def test_phase_exact_over_2_24_samples_float32_is_not():
    from fractions import Fraction

    from mtcw_core.phase import tone_cycles

    n = 2**24
    f, fs = 950_000_001.0, 5e9
    cyc = tone_cycles(f, fs, n)
    for k in (1, 12345, n - 1):
        exact = float(Fraction(k * int(f), int(fs)) % 1)
        assert abs(cyc[k] - exact) < 1e-12
    k = np.arange(n - 1000, n)
    t32 = (k / fs).astype(np.float32)
    naive = np.cos(2 * np.pi * f * t32.astype(np.float64))
    good = np.cos(2 * np.pi * cyc[n - 1000:])
    assert np.max(np.abs(naive - good)) > 0.5  # the hazard: float32 time destroys the phase
    assert np.max(np.abs(np.cos(2 * np.pi * (k * (f / fs))) - good)) < 1e-6


def test_same_seed_same_frame():
    sc = make_scene(laser={"linewidth_hz": 1e6}, noise={"shot": True, "thermal": True, "trigger_jitter_s": 1e-12})
    a = Simulator(sc, seed=7).next_frame().samples
    b = Simulator(sc, seed=7).next_frame().samples
    c = Simulator(sc, seed=8).next_frame().samples
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_pulsed_echo_arrives_2L_over_c_after_gate():
    L = 150.0
    sc = make_scene(
        targets=[{"range_m": L}], receiver={"kind": "balanced"},
        pulsing={"period_s": 4e-6, "duty": 0.25, "delay_s": 0.5e-6},
        digitizer={"samples": 2**15},
    )
    fr = simulate_frame(sc)
    ref = fr.volts("pulse_ref")
    echo = np.abs(fr.volts("pd"))
    t_ref = np.argmax(ref > 0.5)
    t_echo = np.argmax(echo > 0.5 * echo.max() * 0.2)
    assert (t_echo - t_ref) / fr.fs_hz == pytest.approx(2 * L / C, abs=2 / fr.fs_hz)
    # at equal average power the peak field scales by 1/sqrt(duty)
    cw = simulate_frame(make_scene(targets=[{"range_m": L}], receiver={"kind": "balanced"}, digitizer={"samples": 2**15}))
    assert np.max(echo) == pytest.approx(np.max(np.abs(cw.signal())) / math.sqrt(0.25), rel=1e-3)


def test_frame_sequence_moves_targets_and_truth_is_at_record_centre():
    sc = make_scene(targets=[{"range_m": 2.0, "velocity_mps": 0.5}], frames={"count": 3, "rate_hz": 100.0})
    fr = list(Simulator(sc).frames())
    T = fr[0].duration_s
    for i, f in enumerate(fr):
        assert f.truth[0].range_m == pytest.approx(2.0 + 0.5 * (i / 100.0 + (f.n - 1) / (2 * f.fs_hz)), abs=1e-12)
        assert f.seq == i
    assert fr[1].t_ns - fr[0].t_ns == 10_000_000
    assert T == pytest.approx(2**14 / 5e9)


def test_iq_receiver_resolves_doppler_sign():
    for v, sign in ((1.064, -1), (-1.064, 1)):
        fr = simulate_frame(make_scene(targets=[{"range_m": 1.0, "velocity_mps": v}], receiver={"kind": "iq"},
                                       digitizer={"samples": 10_000}))
        X = np.fft.fft(fr.signal())
        f = np.fft.fftfreq(fr.n, 1 / fr.fs_hz)
        band = np.abs(f) < 10e6
        peak = f[band][np.argmax(np.abs(X[band]))]
        assert peak == pytest.approx(sign * 2e6, abs=1e3)  # f_d = -2 v / lambda


def test_bad_scene_names_the_field():
    with pytest.raises(SceneError, match=r"targets\.0\.loss_db"):
        make_scene(targets=[{"range_m": 1.0, "loss_db": -3}])
    with pytest.raises(SceneError, match=r"modulator\.tones\.0\.frequency_hz"):
        make_scene(modulator=tones(3e9))
    with pytest.raises(SceneError, match=r"laser\.colour"):
        scene_from_dict({"laser": {"colour": "red"}, "modulator": tones(1e8), "targets": [{"range_m": 1}]})


@pytest.mark.parametrize("name", sorted(bundled_scenes()))
def test_bundled_scenes_load_and_simulate(name):
    sc = load_scene(name)
    small = scene_from_dict({**sc.model_dump(), "digitizer": {**sc.digitizer.model_dump(), "samples": 2**12}})
    fr = simulate_frame(small)
    assert fr.samples.shape[-1] == 2**12
    assert np.all(np.isfinite(fr.samples))


def test_moving_reference_frame_agrees_in_line_amplitudes(ref_dir):
    """ref-moving-6tone: our noiseless model gives the same f_i +- f_d and self-beat amplitudes."""
    from mtcw_core.recording import read_recording

    ref = read_recording(ref_dir / "ref-moving-6tone").frame(0)
    sc = make_scene(
        modulator=tones(20e6, 500e6, 670e6, 700e6, 890e6, 950e6),
        targets=[{"range_m": 7.89, "velocity_mps": 0.12}], digitizer={"samples": 2**17},
    )
    ours = simulate_frame(sc).signal()
    theirs = ref.signal()
    fd = 2 * 0.12 / LAM
    w = np.hanning(ours.size)
    for fi in (500e6, 700e6, 950e6):
        for f in (fi + fd, fi - fd):
            a, b = abs(dft((ours - ours.mean()) * w, f, 5e9)), abs(dft((theirs - theirs.mean()) * w, f, 5e9))
            assert a == pytest.approx(b, rel=0.1)


# -- optical noise: ASE of a booster amplifier, sunlight through a filter (scene.optical_noise) ----------------

H_PLANCK = 6.62607015e-34


def _psd(x: np.ndarray, fs: float, lo_hz: float, hi_hz: float) -> float:
    """One-sided PSD (unit^2/Hz) of x's fluctuation, averaged over lo..hi."""
    p = np.abs(np.fft.rfft(x - np.mean(x))) ** 2 / x.size
    f = np.fft.rfftfreq(x.size, 1 / fs)
    return 2 * float(np.mean(p[(f > lo_hz) & (f < hi_hz)])) / fs


def test_optical_noise_off_by_default_and_a_0_db_amplifier_changes_nothing():
    base = make_scene(noise={"shot": True}, digitizer={"samples": 2**12})
    same = make_scene(noise={"shot": True}, digitizer={"samples": 2**12},
                      optical_noise={"amplifier": {"gain_db": 0.0, "optical_bandwidth_hz": 1e12}})
    assert base.optical_noise.amplifier is None and base.optical_noise.solar is None
    np.testing.assert_array_equal(simulate_frame(base).samples, simulate_frame(same).samples)


def test_amplifier_gain_scales_the_beat_by_g():
    """LO and echo both pass the amplifier: the beat's amplitude grows by G (power by G^2)."""
    kw = dict(targets=[{"range_m": 1.0, "velocity_mps": 1.064}], digitizer={"samples": 10_000}, receiver={"kind": "balanced"})
    plain = simulate_frame(make_scene(**kw)).signal()
    amp = simulate_frame(make_scene(**kw, optical_noise={"amplifier": {"gain_db": 10.0, "spontaneous_emission_factor": 1.0,
                                                                        "optical_bandwidth_hz": 1.0}})).signal()
    # 1 Hz of ASE: its beat is far below float32 resolution here
    fs = 5e9
    assert abs(dft(amp, 2e6, fs)) / abs(dft(plain, 2e6, fs)) == pytest.approx(10.0, rel=1e-5)


@pytest.mark.parametrize("band_hz", [50e6, 20e12], ids=["narrower-than-fs", "wider-than-fs"])
def test_ase_beats_with_the_lo_at_4_r2_g_plo_s_within_half_the_band(band_hz):
    """Single PD, no echo, G = 40 dB, n_sp = 1.5, a weak LO: mean current R*(G*P_lo + 2*S*B); below B/2
    the LO x ASE beat 4*R^2*G*P_lo*S plus ASE x ASE 4*R^2*S^2*(B - f) (S per polarisation, both
    polarisations); between B/2 and B (narrow band) only the ASE x ASE triangle; above B nothing."""
    fs, r, g, n_sp, lam = 250e6, 0.9, 1e4, 1.5, LAM
    p_lo = 1e-6 * 0.05
    sc = make_scene(targets=[{"range_m": 1.0, "loss_db": 400.0}], modulator=tones(10e6), lo_fraction=1e-6,
                    digitizer={"sample_rate_hz": fs, "samples": 2**16},
                    optical_noise={"amplifier": {"gain_db": 40.0, "spontaneous_emission_factor": n_sp,
                                                 "optical_bandwidth_hz": band_hz}})
    i = simulate_frame(sc).signal() / 50.0
    s = (g - 1) * n_sp * H_PLANCK * C / lam
    assert np.mean(i) / (r * (g * p_lo + 2 * s * band_hz)) == pytest.approx(1.0, abs=2e-3)

    def psd(f_hz):  # the closed form at f
        lo_ase = 4 * r**2 * g * p_lo * s if f_hz < band_hz / 2 else 0.0
        return lo_ase + 4 * r**2 * s**2 * max(band_hz - f_hz, 0.0)

    # (the closed form is linear in f over each band: its mean is its value at the band's middle)
    assert _psd(i, fs, 1e6, 24e6) / psd(12.5e6) == pytest.approx(1.0, abs=0.05)
    if band_hz < fs:
        assert _psd(i, fs, 26e6, 49e6) / psd(37.5e6) == pytest.approx(1.0, abs=0.05)
        assert _psd(i, fs, 70e6, 120e6) < 1e-4 * psd(5e6)


def test_sunlight_adds_ssi_times_area_times_filter_at_the_detector():
    """0.75 W/m^2/nm into 1 cm^2 through 2 nm: 150 uW, unpolarised; mean current R*(P_lo + P_sun);
    the LO beats with its polarisation, S = P_sun/(2*B), B = c*2nm/lambda^2."""
    fs, r = 250e6, 0.9
    p_lo = 0.1 * 0.05
    sc = make_scene(targets=[{"range_m": 1.0, "loss_db": 400.0}], modulator=tones(10e6), digitizer={"sample_rate_hz": fs, "samples": 2**16},
                    optical_noise={"solar": {"spectral_irradiance_w_per_m2_nm": 0.75, "aperture_area_m2": 1e-4,
                                             "filter_bandwidth_m": 2e-9}})
    i = simulate_frame(sc).signal() / 50.0
    p_sun, b = 150e-6, C * 2e-9 / LAM**2
    assert np.mean(i) / (r * (p_lo + p_sun)) == pytest.approx(1.0, abs=1e-4)
    s = p_sun / (2 * b)
    assert _psd(i, fs, 1e6, 120e6) / (4 * r**2 * p_lo * s + 4 * r**2 * s**2 * b) == pytest.approx(1.0, abs=0.02)


def test_bad_optical_noise_names_the_field():
    with pytest.raises(SceneError, match=r"optical_noise\.amplifier\.gain_db"):
        make_scene(optical_noise={"amplifier": {"gain_db": -3, "optical_bandwidth_hz": 1e12}})
    with pytest.raises(SceneError, match=r"optical_noise\.solar\.filter_bandwidth_m"):
        make_scene(optical_noise={"solar": {"spectral_irradiance_w_per_m2_nm": 0.7, "aperture_area_m2": 1e-4,
                                            "filter_bandwidth_m": float("nan")}})
    with pytest.raises(SceneError, match=r"optical_noise\.amplifier\.optical_bandwidth_hz"):
        make_scene(optical_noise={"amplifier": {"gain_db": 3.0}})


def test_a_stream_ends_with_the_scene_error_where_a_target_reaches_the_sensor():
    """2 m at -15 m/s, 10 frames/s, 100 kHz laser: the scene's own 2 frames are fine; the stream's
    frame 2 (t = 0.2 s) would put the target behind the sensor. It raised numpy's broadcast error
    in the laser's delayed phase; now a SceneError naming the target and the frame."""
    sc = make_scene(targets=[{"range_m": 2.0, "velocity_mps": -15.0}], laser={"linewidth_hz": 1e5},
                    frames={"count": 2, "rate_hz": 10.0})
    sim = Simulator(sc, seed=1)
    assert len(list(sim.frames())) == 2
    with pytest.raises(SceneError, match=r"targets\.0\.range_m: .* by frame 2 .*reached the sensor"):
        sim.next_frame()


def test_the_sim_source_ends_its_run_where_the_scene_ends(tmp_path, caplog):
    """The acquisition node's ``sim`` source streams beyond the scene's frames; where the target
    reaches the sensor it logs why and ends the run (the node then sends its end-of-run notice)."""
    from services.sources.simulator import SimulatorSource

    path = tmp_path / "approach.toml"
    path.write_text('[modulator]\ntones = [{ frequency_hz = 500e6 }, { frequency_hz = 700e6 }]\n'
                    '[[targets]]\nrange_m = 2.0\nvelocity_mps = -15.0\n[digitizer]\nsamples = 1024\n'
                    '[frames]\ncount = 1\nrate_hz = 10\n')

    class Settings:
        scene, seed = str(path), 3

    with caplog.at_level("ERROR", logger="mtcw.acquisition"):
        frames = list(SimulatorSource(Settings()).frames())
    assert len(frames) == 2 and "targets.0.range_m" in caplog.text
