"""services/sources/replay.py: a looping replay reads each frame of the file once, then sends the
same read-only arrays zero-copy; what arrives over a socket is the file's samples to the bit."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import zmq

from mtcw_core import recording as R
from mtcw_core.recording import RecordingWriter
from mtcw_core.simulate import simulate_frame
from services.acquisition import Publisher
from services.settings import AcquisitionSettings
from services.sources.replay import ReplaySource
from services.wire import decode_frame, encode_frame

from .conftest import make_scene

N_FRAMES, N_SAMPLES = 3, 2**14


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A 3-frame single-channel recording (float32 samples, as the simulator writes them)."""
    prefix = tmp_path_factory.mktemp("replay") / "rec"
    sc = make_scene(digitizer={"samples": N_SAMPLES})
    with RecordingWriter(prefix) as w:
        for i in range(N_FRAMES):
            w.write(simulate_frame(sc, seed=i).with_(seq=i))
    return prefix


def _file_samples(prefix, i: int) -> np.ndarray:
    """Frame ``i``'s samples straight from the data file (one channel: consecutive values), not
    through the recording reader."""
    raw = np.fromfile(str(prefix) + ".sigmf-data", dtype="<f4")
    return raw[i * N_SAMPLES:(i + 1) * N_SAMPLES]


def _counting(monkeypatch) -> list[int]:
    """Count the frames the recording reader reads from the file."""
    reads: list[int] = []
    real = R.Recording.frame

    def frame(self, i):
        reads.append(i)
        return real(self, i)

    monkeypatch.setattr(R.Recording, "frame", frame)
    return reads


def test_a_looping_replay_reads_each_frame_once(recording, monkeypatch):
    reads = _counting(monkeypatch)
    src = ReplaySource(AcquisitionSettings(source="replay", recording=recording, loop=True))
    got = list(itertools.islice(src.frames(), 4 * N_FRAMES))
    assert sorted(reads) == list(range(N_FRAMES)) and src.reads == N_FRAMES and src.cached == N_FRAMES
    for k, fr in enumerate(got):
        assert np.array_equal(fr.samples[0], _file_samples(recording, k % N_FRAMES))
        assert fr.samples is got[k % N_FRAMES].samples  # the same array, not a copy, on every loop
        assert not fr.samples.flags.writeable  # sent zero-copy: nobody may write into it
    assert [fr.seq for fr in got[:N_FRAMES]] == list(range(N_FRAMES))


def test_past_the_memory_budget_frames_are_read_again(recording, monkeypatch):
    """With room for one frame, the first is kept and the others are read on every loop."""
    reads = _counting(monkeypatch)
    st = AcquisitionSettings(source="replay", recording=recording, loop=True)
    src = ReplaySource(st, cache_bytes=4 * N_SAMPLES)  # one float32 frame
    list(itertools.islice(src.frames(), 3 * N_FRAMES))
    assert src.cached == 1 and reads == [0, 1, 2, 1, 2, 1, 2]


def test_a_single_pass_keeps_nothing(recording, monkeypatch):
    reads = _counting(monkeypatch)
    src = ReplaySource(AcquisitionSettings(source="replay", recording=recording, loop=False))
    frames = list(src.frames())
    assert len(frames) == N_FRAMES and reads == [0, 1, 2] and src.cached == 0


def test_zero_copy_send_round_trips_bit_exact(recording, ctx):
    """The samples part of the message is a view of the replayed array (no copy in the node); a
    worker's decoder gets the file's samples back to the bit, frame after frame and loop after loop."""
    src = ReplaySource(AcquisitionSettings(source="replay", recording=recording, loop=True))
    st = AcquisitionSettings(frames_endpoint="tcp://127.0.0.1:0", monitor_endpoint="tcp://127.0.0.1:0",
                             drop_policy="block")
    pub = Publisher(st, ctx)
    pull = ctx.socket(zmq.PULL)
    pull.connect(pub.frames_endpoint)
    try:
        assert pub.wait_for_worker(10)
        frames = list(itertools.islice(src.frames(), 2 * N_FRAMES))
        part = encode_frame(frames[0])[2]
        assert np.shares_memory(np.frombuffer(part, dtype="<f4"), frames[0].samples)
        for fr in frames:
            assert pub.send(fr)
        for k in range(2 * N_FRAMES):
            assert pull.poll(10_000)
            got = decode_frame(pull.recv_multipart(copy=False))
            assert got.seq == k and got.samples.dtype == np.dtype("<f4")
            assert got.samples.tobytes() == _file_samples(recording, k % N_FRAMES).tobytes()
    finally:
        pull.close(linger=0)
        pub.close()
