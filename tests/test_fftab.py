"""mtcw_bench.fftab: the chain on each FFT backend, alternated in one process."""

from __future__ import annotations

import pytest

from mtcw_bench import fftab
from mtcw_core.dsp.spectrum import fft_backend


def test_alternates_the_backends_and_leaves_the_default(capsys):
    pytest.importorskip("pyfftw")
    fftab.main(["--scenes", "cw-bench", "--profiles", "fast", "--samples", "16384", "--rounds", "1", "--frames", "1"])
    out = capsys.readouterr().out
    rows = [r for r in out.splitlines() if r.startswith("| cw-bench | fast |")]
    assert [r.split("|")[3].strip() for r in rows] == ["pocketfft", "pyfftw"]
    assert rows[0].rstrip().endswith("+0 % |")
    totals = [float(r.split("|")[-3]) for r in rows]
    assert all(t > 0 for t in totals)
    assert fft_backend() == "scipy default (pocketfft)"


def test_a_backend_not_installed_is_left_out_and_said(monkeypatch):
    import mtcw_bench.fftab as F

    real = F.fft_backend_module

    def fake(name):
        if name == "pyfftw":
            raise ValueError("fft_backend='pyfftw' needs pyFFTW")
        return real(name)

    monkeypatch.setattr(F, "fft_backend_module", fake)
    ok, missing = F.installed(["pocketfft", "pyfftw"])
    assert ok == ["pocketfft"] and missing == ["pyfftw: fft_backend='pyfftw' needs pyFFTW"]
