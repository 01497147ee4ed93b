"""mtcw_core.frame: the one Frame <-> dict mapping (SigMF recordings through it: tests/test_recording.py)."""

from __future__ import annotations

import numpy as np
import pytest

from mtcw_core.frame import SAMPLE_DTYPES, Frame, PulseInfo, TruthTarget, dtype_name, frame_from_dict, frame_to_dict


def _frame(dtype="<i2", receiver="single", seq=0, **kw) -> Frame:
    channels = ("i", "q", "pulse_ref") if receiver == "iq" else ("pd", "pulse_ref")
    x = np.arange(len(channels) * 16).reshape(len(channels), 16) - 20
    base = dict(samples=x.astype(dtype), fs_hz=2e9, tones_hz=(1e8, 3e8), wavelength_m=1.064e-6, receiver=receiver,
                channels=channels, scale=0.5 if np.dtype(dtype).kind == "i" else 1.0, offset=0.0,
                tone_phases_rad=(0.5, -0.5), pulse=PulseInfo(1e-6, 0.25, 1e-8), seq=seq,
                t_ns=1_700_000_000_123_456_000 + seq * 1000, source="bench", truth=(TruthTarget(2.0, 0.5),))
    return Frame(**{**base, **kw})


def test_dtype_names():
    assert [dtype_name(np.dtype(n)) for n in SAMPLE_DTYPES] == list(SAMPLE_DTYPES)
    assert dtype_name(np.dtype(">f4")) == "<f4" and dtype_name(np.dtype("int8")) == "<i1"
    with pytest.raises(ValueError, match="dtype"):
        dtype_name(np.dtype("u2"))


def test_mapping_round_trip_is_exact():
    fr = _frame(run=12, architecture="modulated_reference")
    d = frame_to_dict(fr)
    assert d["dtype"] == "<i2" and d["pulse"] == {"period_s": 1e-6, "duty": 0.25, "delay_s": 1e-8}
    back = frame_from_dict(d, fr.samples)
    assert back == fr
    minimal = frame_from_dict({"fs_hz": 1.0, "tones_hz": [0.25], "wavelength_m": 1e-6}, fr.samples[:1])
    assert (minimal.receiver, minimal.channels, minimal.pulse, minimal.run) == ("single", ("pd",), None, None)
