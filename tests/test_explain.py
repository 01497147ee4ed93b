"""mtcw_core.explain and ``mtcw explain``: the triangulation made visible, checked against truth
and closed forms (not against numbers it printed before)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mtcw_core.chain import process_frame
from mtcw_core.explain import _peak_decimate, explain_frame
from mtcw_core.phase import C
from mtcw_core.simulate import simulate_frame

from .conftest import make_scene

ROOT = Path(__file__).resolve().parents[1]
TONES = (500e6, 700e6, 950e6)  # make_scene's: gcd 50 MHz, unambiguous range c/(2*50 MHz) = 3.0 m
L_UNAMB = C / (2 * 50e6)


def _noisy(**over):
    return make_scene(noise={"shot": True, "thermal": True}, digitizer={"sample_rate_hz": 5e9, "samples": 2**16},
                      **over)


@pytest.fixture(scope="module")
def static():
    fr = simulate_frame(_noisy(), seed=3)
    return fr, explain_frame(fr, "balanced")


@pytest.fixture(scope="module")
def moving():
    sc = _noisy(targets=[{"range_m": 2.1, "velocity_mps": 0.8, "loss_db": 20.0}])
    fr = simulate_frame(sc, seed=5)
    return fr, explain_frame(fr, "balanced")


def test_it_is_plain_json_and_matches_the_chain(static):
    fr, d = static
    json.dumps(d, allow_nan=False)  # builtins only, no NaN
    res = process_frame(fr, "balanced")
    assert d["status"] == res.status == "ok"
    assert d["targets"][0]["range_m"] == res.targets[0].range_m  # the same chain, the same answer
    assert list(d["stage_seconds"]) == list(res.stage_seconds)


def test_cost_curve_is_the_closed_form_at_truth_with_chosen_peak_and_runner_up(static):
    """Noise-free, the pair phases make J(L) = sum_l w_l cos(4 pi df_l (L - L_true)/c) / sum_l w_l:
    evaluated independently from the pairs' df and weights, it must be the curve explained."""
    fr, d = static
    truth = fr.truth[0].range_m
    cand = d["candidates"][0]
    cost, pairs = cand["cost"], cand["pairs"]
    df, w = np.asarray(pairs["df_hz"]), np.asarray(pairs["weight"])
    grid = np.asarray(cost["range_m"])
    model = (np.cos(4 * np.pi * df[None, :] * (grid[:, None] - truth) / C) @ w) / w.sum()
    assert np.max(np.abs(model - np.asarray(cost["j"]))) < 0.02
    assert abs(cost["chosen_m"] - truth) < 5 * d["targets"][0]["range_sigma_m"] + 1e-5
    assert cost["j_chosen"] > 0.99 and cost["j_chosen"] >= max(cost["j"]) - 1e-9
    # the runner-up: the closed form's best other local maximum, more than Lambda_min/2 from truth
    fine = np.arange(cost["interval_m"][0], cost["interval_m"][1], 1e-4)
    jm = (np.cos(4 * np.pi * df[None, :] * (fine[:, None] - truth) / C) @ w) / w.sum()
    peaks = np.flatnonzero((jm[1:-1] > jm[:-2]) & (jm[1:-1] > jm[2:])) + 1
    far = peaks[np.abs(fine[peaks] - truth) > 0.5 * C / (2 * df.max())]
    best_other = far[np.argmax(jm[far])]
    assert abs(cost["runner_up_m"] - fine[best_other]) < cost["step_m"]
    assert abs(cost["j_runner_up"] - jm[best_other]) < 0.03
    assert cost["margin"] == pytest.approx(d["targets"][0]["margin"], abs=1e-9)  # what the point says
    assert cost["unambiguous_range_m"] == pytest.approx(L_UNAMB)


def test_seed_matrix_picks_the_row_at_truth_and_is_the_seed_methods_answer(static):
    fr, d = static
    truth = fr.truth[0].range_m
    sd = d["candidates"][0]["seed"]
    lam = np.asarray(sd["synthetic_wavelengths_m"])
    assert np.allclose(np.sort(lam), np.sort(C / (2 * np.array([200e6, 250e6, 450e6]))))
    assert abs(sd["chosen_m"] - truth) < lam[0] / 20
    # at the right row every column agrees to noise; at every other row they disagree by a
    # sizeable part of a wavelength
    assert sd["sigma_k_chosen_m"] < 1e-3 and sd["sigma_k_second_m"] > 20 * sd["sigma_k_chosen_m"]
    row = sd["chosen_row"] - sd["first_row"]
    assert np.allclose(sd["candidates_m"][row], truth, atol=lam[0] / 20)
    seed = explain_frame(fr, "seed")
    assert seed["targets"][0]["range_m"] == pytest.approx(seed["candidates"][0]["seed"]["chosen_m"], abs=1e-12)


def test_lines_are_marked_where_physics_puts_them(static, moving):
    fr, d = static
    res_hz = 2 * fr.fs_hz / fr.n
    tones = [ln for ln in d["lines"] if ln["kind"] == "tone"]
    assert sorted(ln["f_hz"] for ln in tones) == pytest.approx(sorted(TONES))
    assert all(ln["used"] and ln["snr_db"] > 20 for ln in tones)
    # the MZM's products are marked as left out, at integer combinations of the tones
    products = [ln for ln in d["lines"] if ln["kind"] == "product"]
    assert products and not any(ln["used"] for ln in products)
    combos = {abs(a * TONES[0] + b * TONES[1] + c * TONES[2]) for a in range(-3, 4) for b in range(-3, 4)
              for c in range(-3, 4) if abs(a) + abs(b) + abs(c) <= 5}
    for ln in products:
        assert min(abs(ln["f_hz"] - f) for f in combos) < 2 * res_hz
    assert any(abs(ln["f_hz"] - 200e6) < 2 * res_hz for ln in products)  # 700 - 500 MHz, a strong one
    # a mover: baseband at 2v/lambda, U and L at f_i +- f_d
    fr, d = moving
    fd = 2 * 0.8 / fr.wavelength_m
    base = [ln for ln in d["lines"] if ln["kind"] == "doppler"]
    assert len(base) == 1 and abs(base[0]["f_hz"] - fd) < fr.fs_hz / fr.n
    for kind, sign in (("doppler_upper", 1), ("doppler_lower", -1)):
        got = sorted(ln["f_hz"] for ln in d["lines"] if ln["kind"] == kind and ln["target"] == 1)
        assert got == pytest.approx(sorted(t + sign * fd for t in TONES), abs=fr.fs_hz / fr.n)
    ghosts = [ln for ln in d["lines"] if ln["kind"] == "ghost"]
    for ln in ghosts:  # a product shifted by the Doppler line
        assert min(abs(ln["f_hz"] - abs(f + s * fd)) for f in combos | {0.0} for s in (1, -1)) < 2 * res_hz
    truth = fr.truth[0].range_m
    reported = next(c for c in d["candidates"] if c["reported"])
    assert abs(reported["cost"]["chosen_m"] - truth % L_UNAMB) < 1e-3


def test_spectrum_is_decimated_keeping_every_peak(static):
    fr, d = static
    sp = d["spectrum"]
    assert len(sp["f_hz"]) <= 2048 and sp["bins"] == fr.n // 2 + 1
    for tone in TONES:  # the tone lines survive the decimation at their full height (> 60 dB here)
        i = int(np.argmin(np.abs(np.asarray(sp["f_hz"]) - tone)))
        assert abs(sp["f_hz"][i] - tone) < 2 * sp["df_hz"] and sp["power_db"][i] > 40
    x = np.arange(10_001.0)
    y = np.sin(x / 7.0) + (x == 5003) * 10
    dx, dy = _peak_decimate(x, y, 100)
    assert dy.size <= 101
    assert dx[np.argmax(dy)] == 5003 and dy.max() == y.max()
    mx, my = _peak_decimate(x, -y, 100, keep="min")
    assert mx[np.argmin(my)] == 5003


def test_a_frame_with_nothing_to_range_is_explained_not_raised():
    fr = simulate_frame(_noisy(targets=[{"range_m": 1.0, "velocity_mps": 0.0, "loss_db": 150.0}]), seed=1)
    d = explain_frame(fr, "fast")
    assert d["status"] == "no_target" and d["reason"] and d["targets"] == []
    assert d["spectrum"]["f_hz"] and json.dumps(d, allow_nan=False)


def test_cli_writes_the_pngs_and_json_and_names_a_bad_frame(tmp_path):
    rec = tmp_path / "rec"
    env_py = [sys.executable, "-m", "services.cli"]
    scene = tmp_path / "s.toml"
    scene.write_text('name = "t"\n[modulator]\ntones = [{frequency_hz = 500e6}, {frequency_hz = 700e6}, '
                     '{frequency_hz = 950e6}]\n[[targets]]\nrange_m = 1.7\nloss_db = 20.0\n[digitizer]\n'
                     'samples = 65536\n[frames]\ncount = 2\n')
    subprocess.run(env_py + ["simulate", str(scene), "-o", str(rec), "-n", "2"], cwd=ROOT, check=True,
                   capture_output=True, timeout=300)
    out = subprocess.run(env_py + ["explain", str(rec), "--frame", "1", "-o", str(tmp_path / "x")], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)
    assert abs(summary["targets"][0]["range_m"] - 1.7) < 1e-3
    for name in ("explain.json", "spectrum.png", "cost.png", "seed.png"):
        f = tmp_path / "x" / name
        assert f.stat().st_size > 1000, name
        if name.endswith(".png"):
            assert f.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((tmp_path / "x" / "explain.json").read_text())["seq"] == 1
    bad = subprocess.run(env_py + ["explain", str(rec), "--frame", "7", "-o", str(tmp_path / "y")], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and "--frame" in bad.stderr and "Traceback" not in bad.stderr
