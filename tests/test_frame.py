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


class TestVolts:
    """``Frame.volts``/``signal``: ``code*scale + offset`` in float64, written out plainly here."""

    @staticmethod
    def _frame(samples, **kw):
        return Frame(samples=samples, fs_hz=1e9, tones_hz=(1e8, 2e8), wavelength_m=1.55e-6, **kw)

    @pytest.mark.parametrize("dtype", ["<i2", "<i1", "<f4", "<f8", ">i2", ">f4"])
    @pytest.mark.parametrize("scale, offset", [(1.0, 0.0), (3.1e-4, 0.0), (1.0, -0.25), (2.5e-3, 0.125)])
    def test_codes_to_volts(self, dtype, scale, offset):
        codes = np.random.default_rng(1).integers(-120, 120, size=(1, 1000)).astype(dtype)
        v = self._frame(codes, scale=scale, offset=offset).signal()
        want = np.array([float(c) * scale + offset for c in codes[0]])  # one sample at a time
        assert v.dtype == np.float64 and v.shape == (1000,)
        np.testing.assert_array_equal(v, want)

    @pytest.mark.parametrize("scale, offset", [(1.0, 0.0), (1e-3, 0.5)])
    def test_iq_is_i_plus_jq(self, scale, offset):
        codes = np.random.default_rng(2).integers(-3000, 3000, size=(2, 500)).astype(np.int16)
        v = self._frame(codes, receiver="iq", channels=("i", "q"), scale=scale, offset=offset).signal()
        want = np.array([complex(float(i) * scale + offset, float(q) * scale + offset) for i, q in codes.T])
        assert v.dtype == np.complex128
        np.testing.assert_array_equal(v, want)

    def test_float64_without_scale_is_not_copied(self):
        x = np.random.default_rng(3).standard_normal((1, 64))
        assert np.shares_memory(self._frame(x).signal(), x)
