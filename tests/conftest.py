from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, settings as hsettings


from mtcw_core.scene import Scene, scene_from_dict

REF_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "testdata" / "reference-frames"


#: Fuzz profiles (Hypothesis): ``ci`` (the default, a few hundred cases per parser) and ``long``
#: (>= 10^4 cases per parser), chosen by ``pytest --long`` or ``MTCW_FUZZ=long``. Fuzz tests use
#: ``@hsettings(max_examples=FUZZ_EXAMPLES)``-free decorators and read the loaded profile.
hsettings.register_profile("ci", max_examples=300, deadline=None,
                           suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
hsettings.register_profile("long", max_examples=10_000, deadline=None,
                           suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def pytest_addoption(parser):
    parser.addoption("--long", action="store_true", default=False,
                     help="long fuzz (>= 10^4 cases per parser) and soak runs")


def pytest_configure(config):
    import os

    long = config.getoption("--long") or os.environ.get("MTCW_FUZZ") == "long"
    config.mtcw_long = long
    hsettings.load_profile("long" if long else "ci")


@pytest.fixture(autouse=True)
def _api_store(monkeypatch):
    """Every API a test starts (in process or a child) keeps its history in memory, its own
    (``MTCW_STORE_PATH=:memory:``), never in the checkout's default ``out/mtcw-api.sqlite3``:
    history would leak from test to test. Tests of restarts give a file of their own."""
    monkeypatch.setenv("MTCW_STORE_PATH", ":memory:")


@pytest.fixture
def long_run(request) -> bool:
    """True under ``pytest --long`` (or ``MTCW_FUZZ=long``): soak and stop tests run their long versions."""
    return bool(request.config.mtcw_long)


def make_scene(**over) -> Scene:
    """A small noiseless 3-tone scene, overridable by nested dicts (``digitizer={"samples": ...}``)."""
    base = {
        "name": "test",
        "laser": {"wavelength_m": 1.064e-6, "power_w": 0.05, "linewidth_hz": 0.0},
        "modulator": {"tones": [{"frequency_hz": f} for f in (500e6, 700e6, 950e6)]},
        "targets": [{"range_m": 1.234, "velocity_mps": 0.0, "loss_db": 20.0}],
        "digitizer": {"sample_rate_hz": 5e9, "samples": 2**14},
    }
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(base.get(k), dict):
            base[k] = {**base[k], **v}
        else:
            base[k] = v
    return scene_from_dict(base)


def fast_mover_scene(v: float = 47.9, kind: str = "single") -> Scene:
    """A mover at ``v`` m/s (47.9: 0.45x the 200 MHz spacing) at 1.234 m, 40 dB, 2^18 samples, shot
    and thermal noise: its sidebands' own Doppler shift (160-300 Hz) far above its lines' errors.
    Frames at 10 kHz: an approach at 47.9 m/s moves 4.8 mm a frame (at 10/s it had passed the
    sensor by the second frame)."""
    return make_scene(receiver={"kind": kind}, digitizer={"samples": 2**18}, noise={"shot": True, "thermal": True},
                      targets=[{"range_m": 1.234, "velocity_mps": v, "loss_db": 40.0}], frames={"rate_hz": 1e4})


def tones(*f, m=0.07):
    return {"tones": [{"frequency_hz": x, "modulation_index": m} for x in f]}


def spectrum(x: np.ndarray, fs: float, window: bool = True):
    """One-sided amplitude spectrum (amplitude of each real sinusoid) and its frequencies."""
    x = np.asarray(x, float) - np.mean(x)
    w = np.hanning(x.size) if window else np.ones(x.size)
    X = np.fft.rfft(x * w) * 2 / np.sum(w)
    return np.fft.rfftfreq(x.size, 1 / fs), X


@pytest.fixture
def ref_dir() -> Path:
    if not REF_DIR.exists():
        pytest.skip("shared reference frames not present")
    return REF_DIR


@pytest.fixture
def ctx():
    """A ZeroMQ context of the test's own, destroyed without lingering."""
    import zmq

    c = zmq.Context()
    yield c
    c.destroy(linger=0)

