"""services.acquisition: the publisher is the one identity stamp on the wire (injected clock),
counts what it drops, and ends a run with its notice; in-process, on port 0."""

from __future__ import annotations

import numpy as np
import pytest
import zmq

from mtcw_core.frame import Frame
from services.acquisition import Publisher
from services.settings import AcquisitionSettings
from services.wire import decode_end, decode_frame


def _frame(**kw) -> Frame:
    return Frame(samples=np.zeros((1, 32), "<f4"), fs_hz=1e9, tones_hz=(1e8,), wavelength_m=1.55e-6, **kw)


def test_publisher_stamps_identity_over_the_sources(ctx):
    st = AcquisitionSettings(frames_endpoint="tcp://127.0.0.1:0", monitor_endpoint="tcp://127.0.0.1:0",
                             source_name="lidar-1", drop_policy="block")
    clock = iter(range(1_000, 2_000, 10))
    pub = Publisher(st, ctx, clock_ns=lambda: next(clock))
    pull = ctx.socket(zmq.PULL)
    pull.connect(pub.frames_endpoint)
    try:
        assert pub.wait_for_worker(10)
        for seq in (41, 41, 7):  # whatever the source says (a replayed recording, a simulator) is replaced
            assert pub.send(_frame(seq=seq, t_ns=5, source="scene", run=3))
        got = [decode_frame(pull.recv_multipart()) for _ in range(3)]
        assert [(f.source, f.seq, f.t_ns, f.run) for f in got] == [("lidar-1", i, 1_000 + 10 * i, pub.run)
                                                                   for i in range(3)]
        assert pub.finish(5)
        end = decode_end(pull.recv_multipart())
        assert (end.source, end.run, end.frames, end.dropped, end.t_ns) == ("lidar-1", pub.run, 3, 0, 1_030)
    finally:
        pull.close(linger=0)
        pub.close()


def test_drop_policy_counts_frames_no_worker_takes(ctx):
    st = AcquisitionSettings(frames_endpoint="tcp://127.0.0.1:0", monitor_endpoint="tcp://127.0.0.1:0")
    pub = Publisher(st, ctx)
    try:
        assert [pub.send(_frame()) for _ in range(3)] == [False] * 3
        assert (pub.seq, pub.published, pub.dropped) == (3, 0, 3)  # published = taken + dropped
    finally:
        pub.close()
