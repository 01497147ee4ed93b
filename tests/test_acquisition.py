"""services.acquisition: the publisher is the one identity stamp on the wire (injected clock),
counts what it drops, and ends a run with its notice (in-process, on port 0); the node stops
cleanly on SIGTERM under backlog and the API's books then balance (processes, on port 0)."""

from __future__ import annotations

import random
import re
import signal
import time
from pathlib import Path

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


# ---------------------------------------------------------------------------------------------
# clean stops of the node under backlog, end to end (issue 11)
def _replay_recording(path: Path, frames: int = 3, samples: int = 1_000_000) -> Path:
    """A recording of ``frames`` float32 frames of ``samples`` samples (4 MB each at 1e6: the
    samples travel zero-copy, and a freed buffer of that size is unmapped)."""
    from mtcw_core.recording import RecordingWriter
    from mtcw_core.simulate import Simulator

    from .conftest import make_scene

    with RecordingWriter(path, description="clean-stop test") as w:
        for fr in Simulator(make_scene(digitizer={"samples": samples}), 1).frames(frames):
            w.write(fr)
    return path


def _accounted(h: dict) -> int:
    return h["processed"] + h["rejected"] + h["dropped"]


def test_acquisition_node_stops_cleanly_under_backlog_and_the_books_balance(tmp_path, long_run):
    """SIGTERM the node at a random moment of a full-speed replay (``--rate 0``: the frame queue
    to the one worker is always full, frames are dropped and counted) K times, a new run each
    time, with the same worker and API. Every stop must exit 0 after handing over its end-of-run
    notice, and the API's books must then hold exactly what the node says it published:
    ``processed + rejected + dropped == frames`` of every run so far. Then the worker, the node
    and the API are stopped in turn while the node floods the worker: each exits 0, no traceback.

    Before the fix every stop under backlog ended the node in SIGSEGV/SIGABRT (``Bad address
    (src/tcp.cpp:227)``): it exited without terminating its ZeroMQ context, and pyzmq's atexit
    hook released the zero-copy sample buffers libzmq was still sending; the notice was lost
    with the frames queued before it. K = 3 here, 100 under ``pytest --long``.
    """
    from .test_services import Bench

    stops = 100 if long_run else 3
    rng = random.Random(11)
    rec = _replay_recording(tmp_path / "rec")
    bench = Bench(tmp_path)
    try:
        bench.api()
        expected = 0  # frames of every run so far, as the node stated them
        for i in range(stops):
            name = f"acquisition-{i}"
            bench.start(name, "acquire", "--source", "replay", "--recording", str(rec), "--rate", "0", "--loop",
                        "--source-name", "replay", reports=True)
            if i == 0:
                bench.start("worker", "worker", "--profile", "fast", "--name", "w0")
            before = _accounted(bench.health())
            bench.wait(lambda: _accounted(bench.health()) > before, f"a point of run {i}", 60)
            time.sleep(rng.uniform(0.2, 0.7))  # by then the queue to the worker is full: frames are being dropped
            rc = bench.stop(name, signal.SIGTERM, timeout=30)
            log = bench.log(name)
            assert rc == 0, f"stop {i}: the node exited {rc}:\n{log[-2000:]}"
            assert "Traceback" not in log, log
            assert "end-of-run notice sent" in log, log
            m = re.search(r"stopped after (\d+) frames \((\d+) sent to workers, (\d+) dropped", log)
            assert m, log
            frames, sent, dropped = map(int, m.groups())
            assert dropped > 0 and sent + dropped == frames, m.group(0)  # a backlog: the worker could not keep up
            expected += frames
            try:
                bench.wait(lambda: (lambda h: _accounted(h) >= expected and h["held_for_reordering"] == 0
                                    and h["awaited_after_end"] == 0)(bench.health()), f"run {i} accounted for", 30)
            except AssertionError:
                pass  # the books are checked, and shown, below
            h = bench.health()
            assert (_accounted(h), h["held_for_reordering"], h["awaited_after_end"]) == (expected, 0, 0), \
                f"stop {i}: {frames} frames published; books {h}"
        # the other services stop cleanly under backlog too: the worker while the node floods it
        bench.start("acquisition-last", "acquire", "--source", "replay", "--recording", str(rec), "--rate", "0",
                    "--loop", "--source-name", "replay", env={"MTCW_END_TIMEOUT_S": "1"}, reports=True)
        before = _accounted(bench.health())
        bench.wait(lambda: _accounted(bench.health()) > before, "a point of the last run", 60)
        for name in ("worker", "acquisition-last", "api"):
            rc = bench.stop(name, signal.SIGTERM, timeout=30)
            assert rc == 0 and "Traceback" not in bench.log(name), f"{name} exited {rc}:\n{bench.log(name)[-2000:]}"
    finally:
        bench.close()


# ---------------------------------------------------------------------------------------------
# the run ledger: a killed run's frame count outlives it
def test_ledger_keeps_the_count_and_survives_a_torn_slot(tmp_path):
    from services.acquisition import RunLedger

    path = tmp_path / "state"
    assert RunLedger.read(path) == []
    led = RunLedger(path)
    for n in range(1, 8):
        led.record("bench", 42, n)
    assert RunLedger.read(path) == [{"source": "bench", "run": 42, "frames": 7, "ended": False}]
    raw = bytearray(path.read_bytes())
    raw[RunLedger.SLOT + 5: RunLedger.SLOT + 9] = b"\x00\xff{]"  # the write of frame 7 torn by a kill
    path.write_bytes(bytes(raw))
    assert RunLedger.read(path)[0]["frames"] == 6  # the other slot: one frame less, never garbage
    led.record("bench", 42, 8, ended=True)
    assert RunLedger.read(path) == []  # ended: nothing to send
    led.close()
    carried = {"source": "bench", "run": 41, "frames": 3, "ended": False}
    led = RunLedger(path, pending=carried)
    led.record("bench", 43, 1)
    assert RunLedger.read(path) == [carried, {"source": "bench", "run": 43, "frames": 1, "ended": False}]
    led.close()
    path.write_bytes(b"\x00" * 10)
    assert RunLedger.read(path) == []


def _st_ledger(tmp_path, policy: str = "block") -> AcquisitionSettings:
    return AcquisitionSettings(frames_endpoint="tcp://127.0.0.1:0", monitor_endpoint="tcp://127.0.0.1:0",
                               drop_policy=policy, state_file=tmp_path / "acq.state")


def _ledger(st: AcquisitionSettings) -> list[dict]:
    """The unsent runs the node's state file holds."""
    from services.acquisition import RunLedger

    return RunLedger.read(st.state_file)


def _killed_run(ctx, st, frames: int) -> int:
    """A run that stamps ``frames`` frames and is then 'killed' (no finish, the file left as it is)."""
    pub = Publisher(st, ctx)
    pull = ctx.socket(zmq.PULL)
    pull.connect(pub.frames_endpoint)
    assert pub.wait_for_worker(10)
    for _ in range(frames):
        pub.send(_frame())
        pull.recv_multipart()
    pull.close(linger=0)
    pub.ledger = None  # as after SIGKILL: the mapping left as it was
    pub.push.close(linger=0)
    pub.pub.close(linger=0)
    return pub.run


def test_a_restarted_node_sends_the_end_notice_its_killed_run_never_sent(ctx, tmp_path):
    """Run 1 is 'killed' after 5 frames; the next publisher on the same state file first sends run
    1's notice with those 5 frames, once."""
    st = _st_ledger(tmp_path)
    killed_run = _killed_run(ctx, st, 5)
    second = Publisher(st, ctx)
    assert second.unfinished == [{"source": "bench", "run": killed_run, "frames": 5, "ended": False}]
    pull = ctx.socket(zmq.PULL)
    pull.connect(second.frames_endpoint)
    try:
        assert second.wait_for_worker(10)
        assert second.finish_unfinished(5.0) == 1
        end = decode_end(pull.recv_multipart())
        assert (end.run, end.frames, end.source) == (killed_run, 5, "bench")
        assert _ledger(st) == []  # delivered: not sent again
        second.send(_frame())
        assert second.finish(5.0)
        pull.recv_multipart()
        assert decode_end(pull.recv_multipart()).frames == 1
    finally:
        pull.close(linger=0)
        second.close()
    third = Publisher(st, ctx)  # run 2 ended cleanly: nothing to send for it
    assert third.unfinished == []
    third.close()


def test_a_notice_no_worker_took_or_a_stop_before_it_is_kept_for_the_next_start(ctx, tmp_path):
    """The killed run's record is never overwritten before its notice is handed over: a start
    stopped before sending it, or one whose notice no worker took, leaves it for the next."""
    st = _st_ledger(tmp_path)
    killed_run = _killed_run(ctx, st, 4)
    want = [{"source": "bench", "run": killed_run, "frames": 4, "ended": False}]
    stopped = Publisher(st, ctx)  # stopped while waiting for workers: never got to the notice
    stopped.close()
    assert _ledger(st) == want
    lonely = Publisher(_st_ledger(tmp_path, "drop"), ctx)  # no worker: the notice is not taken
    assert lonely.finish_unfinished(0.2) == 0
    lonely.send(_frame())  # its own first frame (dropped: no worker) is counted beside the carried record
    assert _ledger(st) == [want[0], {"source": "bench", "run": lonely.run, "frames": 1, "ended": False}]
    lonely.ledger = None  # killed too
    lonely.push.close(linger=0)
    lonely.pub.close(linger=0)
    last = Publisher(st, ctx)
    assert [r["run"] for r in last.unfinished] == [killed_run, lonely.run]
    last.close()


def test_a_stranger_is_refused_by_the_frames_socket_and_counted(tmp_path):
    from services.auth import CurveClient, make_keys, server_keys

    make_keys(tmp_path / "k")
    st = AcquisitionSettings(frames_endpoint="tcp://127.0.0.1:0", monitor_endpoint="tcp://127.0.0.1:0",
                             curve_dir=tmp_path / "k")
    refused: list[str] = []
    pub = Publisher(st, on_refused=refused.append)
    c = zmq.Context()
    stranger = c.socket(zmq.PULL)
    pk, sk = zmq.curve_keypair()
    from services.auth import apply_client

    apply_client(stranger, CurveClient(pk, sk, server_keys(tmp_path / "k").public))
    stranger.connect(pub.frames_endpoint)
    try:
        deadline = time.monotonic() + 10
        while not pub.peers_refused["frames"] and time.monotonic() < deadline:
            time.sleep(0.05)
        assert pub.peers_refused["frames"] >= 1 and refused[0] == "frames"
        assert not pub.wait_for_worker(0.5)  # a refused peer is no worker
    finally:
        stranger.close(linger=0)
        c.term()
        pub.close()
