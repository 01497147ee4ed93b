"""services.monitor: the recorder skips and counts the frames its recording refuses, and goes on.

(The recorder over real sockets, ``mtcw record`` end to end, is in tests/test_services.py.)
"""

from __future__ import annotations

import threading

import numpy as np

from mtcw_core.frame import Frame
from mtcw_core.recording import read_recording
from services import monitor
from services.settings import TransportSettings
from services.wire import decode_frame, encode_frame


def _frame(seq: int, **kw) -> Frame:
    """A frame as a subscriber yields it: through the wire's encoder and decoder."""
    base = dict(samples=np.full((2, 64), seq, "<i2"), fs_hz=1e9, tones_hz=(1e8, 2e8), wavelength_m=1.55e-6,
                channels=("pd", "pulse_ref"), scale=1e-3, seq=seq, t_ns=10**18 + seq, source="node")
    return decode_frame(encode_frame(Frame(**{**base, **kw})))


def test_the_recorder_skips_and_counts_refused_frames(tmp_path, monkeypatch):
    stream = [_frame(0, channels=("pd", "pd")),  # the wire accepts repeated names; a recording does not
              _frame(1), _frame(2),
              _frame(3, tones_hz=(1e8, 3e8)),  # unlike the recording's first frame
              _frame(4), _frame(5), _frame(6)]

    def frames(self, stop, timeout_ms=200):
        for fr in stream:
            self.gaps.see(fr.source, fr.seq)
            yield fr

    monkeypatch.setattr(monitor.Subscriber, "frames", frames)
    sub = monitor.record(TransportSettings(monitor_endpoint="tcp://127.0.0.1:1"), tmp_path / "cap", 4,
                         threading.Event())
    assert sub.refused == 2 and sub.malformed == 0
    rec = read_recording(tmp_path / "cap")
    assert [f.seq for f in rec] == [1, 2, 4, 5]  # count=4 counts frames written, not refused ones
    assert all((f.samples == f.seq).all() for f in rec)
