"""The worker: frames in (PULL), PB-MTCW chain, points out (PUSH to the API).

A worker holds at most ``hwm`` frames in its queue, so that frames are shared fairly between
workers and a killed worker loses little (the consumer counts the loss from seq gaps). A message
that is not a valid frame becomes a ``rejected`` point with the decoder's reason, so that the
consumer's counters still add up. Each point carries ``processing_s``, the worker's own time
for the frame (decode, chain, point); the API measures the trigger-to-point latency. The acquisition node's end-of-run notice is passed on to the
API unchanged. Reconnection after a publisher restart is ZeroMQ's.
"""

from __future__ import annotations

import logging
import os
import threading
import time

import zmq

from mtcw_core.calibration import Calibration
from mtcw_core.chain import get_profile, process_frame
from mtcw_core.dsp.spectrum import fft_backend, use_fft_backend
from mtcw_core.ranging.accumulate import AccumulateSettings, Accumulator
from mtcw_core.ranging.track import Tracker, TrackSettings

from .auth import terminate
from .settings import WorkerSettings, log_settings
from .sockets import frames_pull, open_sockets, points_push
from .wire import END_TOPIC, PointMessage, WireError, decode_frame, encode_points, point_from_result, rejection_point, \
    rejected_point, topic

log = logging.getLogger("mtcw.worker")
#: sources a worker keeps an accumulator for (``--accumulate``); more and it starts over
MAX_SOURCES = 64


class Worker:
    """Frames in (PULL), chain, points out (PUSH); see the module docstring.

    Parameters
    ----------
    settings : WorkerSettings
    ctx : zmq.Context, optional
        A context of the caller's (who terminates it). By default the worker makes its own and
        terminates it when :meth:`run` ends, which is what makes the point socket's LINGER
        hold: closing a socket alone does not wait for its queue, and a process that exits
        without terminating the context loses the last points.
    """

    #: ``--accumulate K`` (None: the chain per frame) and its accumulators by source
    _accumulate: AccumulateSettings | None = None
    _accumulators: dict[str, Accumulator]
    #: ``--track K`` (None: off): range rate over frames, per source
    tracker: Tracker | None = None

    def __init__(self, settings: WorkerSettings, ctx: zmq.Context | None = None) -> None:
        self.settings = settings
        self.chain = get_profile(settings.profile, technique=settings.technique,
                                 timing_jitter_s=settings.timing_jitter_s,
                                 tone_phase_sigma_rad=settings.tone_phase_sigma_rad,
                                 laser_linewidth_hz=settings.laser_linewidth_hz,
                                 lo_path_difference_m=settings.lo_path_difference_m,
                                 sideband_direction=settings.sideband_direction)
        self.calibration = Calibration.load(settings.calibration) if settings.calibration else None
        # --accumulate K: one accumulator per source (mtcw_core.ranging.accumulate); frames shared
        # between several workers are each worker's share of the source
        self._accumulators: dict[str, Accumulator] = {}
        self._accumulate = AccumulateSettings(frames=settings.accumulate) if settings.accumulate else None
        if self._accumulate is not None and settings.technique != "pb":
            raise ValueError(f"accumulate: technique {settings.technique!r} has no accumulation (pb only)")
        # --track K: range rate over frames, per source (tracks of this worker's share of each)
        self.tracker = (Tracker(TrackSettings(frames=settings.track, max_speed_mps=settings.track_max_speed_mps),
                                max_sources=MAX_SOURCES) if settings.track else None)
        self._own_ctx = ctx is None
        self.ctx = zmq.Context() if ctx is None else ctx
        self.pull, self.push = open_sockets(self.ctx, [frames_pull(settings), points_push(settings)], self._own_ctx)
        self.received = self.sent = self.unsent = 0
        self._metrics = _exporter(settings.metrics_port, settings.metrics_host, settings.name)

    def handle(self, parts) -> PointMessage:
        """One message in, one point message out (never raises).

        A message that is not a valid frame becomes a ``rejected`` point (reason
        ``malformed_<reason>``); a frame on which the chain fails unexpectedly becomes a
        ``rejected`` point with reason ``chain_error``: every frame received is accounted for.
        """
        t0 = time.perf_counter()
        try:
            frame = decode_frame(parts)
        except WireError as err:
            return rejection_point(err, parts, processing_s=time.perf_counter() - t0)
        try:
            if self._accumulate is None:
                res = process_frame(frame, self.chain, self.calibration)
            else:
                acc = self._accumulators.get(frame.source)
                if acc is None:
                    if len(self._accumulators) >= MAX_SOURCES:  # bounded memory: forget the others
                        self._accumulators.clear()
                    acc = self._accumulators[frame.source] = Accumulator(self._accumulate, self.chain,
                                                                         self.calibration)
                res = acc.add(frame)
            if self.tracker is not None:
                res = self.tracker.update(res, run=frame.run)
        except Exception as err:  # a chain bug must not stop the worker; the frame is counted
            log.exception("worker %s: chain failed on seq %d", self.settings.name, frame.seq)
            return rejected_point(frame.source, frame.seq, frame.t_ns, f"chain_error: {type(err).__name__}: {err}",
                                  run=frame.run, profile=self.settings.profile,
                                  processing_s=time.perf_counter() - t0)
        return point_from_result(res, run=frame.run, processing_s=time.perf_counter() - t0)

    def run(self, stop: threading.Event) -> None:
        log_settings(f"worker {self.settings.name}", self.settings)
        if self.calibration is None:
            log.warning("worker %s: no calibration: using the frames' tone phases and tau0 = 0", self.settings.name)
        limits = limit_threads(self.settings.threads)  # for as long as the worker runs
        fft_before = use_fft_backend(self.settings.fft_backend)  # process-wide: restored when the worker stops
        log.info("worker %s: FFT backend %s", self.settings.name, fft_backend())
        poller = zmq.Poller()
        poller.register(self.pull, zmq.POLLIN)
        try:
            while not stop.is_set():
                if not poller.poll(200):
                    continue
                parts = self.pull.recv_multipart(copy=False)
                if topic(parts) == END_TOPIC and len(parts) == 2:  # end of a run: the API checks it
                    try:
                        self.push.send_multipart([p.bytes for p in parts])
                    except zmq.Again:
                        log.warning("worker %s: API not reachable; end-of-run notice not delivered",
                                    self.settings.name)
                    continue
                self.received += 1
                msg = self.handle(parts)
                if self._metrics:
                    self._metrics[0].labels(msg.status).inc()
                try:
                    self.push.send_multipart(encode_points(msg))  # SNDTIMEO: points_send_timeout_ms
                    self.sent += 1
                except zmq.Again:  # the API is gone: the point is lost, and said so
                    self.unsent += 1
                    if self._metrics:
                        self._metrics[1].inc()
                    log.warning("worker %s: API not reachable; point seq %s not delivered", self.settings.name,
                                msg.seq)
        finally:
            log.info("worker %s: stopped (received %d, sent %d, undelivered %d)", self.settings.name,
                     self.received, self.sent, self.unsent)
            if limits is not None:
                limits.restore_original_limits()
            use_fft_backend(fft_before)
            self.pull.close()
            self.push.close()  # LINGER points_linger_ms: the last points still go out while the context terminates
            if self._own_ctx:
                terminate(self.ctx)


#: the thread-count variables the numerical libraries read when they load
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def limit_threads(threads: int):
    """Limit the numerical libraries' thread pools (OpenBLAS, OpenMP) of this process to ``threads``
    (0: leave them as they are); returns the :class:`threadpoolctl.threadpool_limits` in force
    (None for 0). The libraries already loaded are limited by threadpoolctl; for one loaded
    later, :data:`THREAD_VARS` are set in the environment (they stay set).

    A worker handles one frame at a time and more cores are used by more workers; OpenBLAS's own
    threads (as many as cores by default) busy-wait between calls, and on the 1e6-sample cw-bench
    frames they doubled the worker's CPU per frame (64 ms for a 32 ms frame) for no gain in speed,
    so that two workers on two cores went no faster than one (issue 16). Which thread computes a
    product does not change the chain's results (``tests/test_worker.py`` checks they are
    identical). threadpoolctl rather than ``OPENBLAS_NUM_THREADS``: the environment is read
    only when the library loads, and numpy is loaded before the settings are read.
    """
    if threads <= 0:
        return None
    from threadpoolctl import threadpool_limits

    for var in THREAD_VARS:  # a library loaded later (lazily, at the first frame) reads these when it loads
        os.environ[var] = str(threads)
    return threadpool_limits(limits=threads)  # the ones loaded already (numpy's and scipy's OpenBLAS)


def _exporter(port: int, host: str, name: str):
    """The worker's own counters on ``host:port`` (0 = off), for Prometheus and healthchecks."""
    if not port:
        return None
    from prometheus_client import CollectorRegistry, Counter, start_http_server

    reg = CollectorRegistry()
    frames = Counter("mtcw_worker_frames_total", "frames this worker handled, by result", ["status"], registry=reg)
    unsent = Counter("mtcw_worker_points_undelivered_total", "points the API did not take", registry=reg)
    start_http_server(port, addr=host, registry=reg)
    log.info("worker %s: metrics on http://%s:%d/metrics", name, host, port)
    return frames, unsent
