"""The worker: frames in (PULL), PB-MTCW chain, points out (PUSH to the API).

A worker holds at most ``hwm`` frames in its queue, so that frames are shared fairly between
workers and a killed worker loses little (the consumer counts the loss from seq gaps). A message
that is not a valid frame becomes a ``rejected`` point with the decoder's reason, so that the
consumer's counters still add up. The acquisition node's end-of-run notice is passed on to the
API unchanged. Reconnection after a publisher restart is ZeroMQ's.
"""

from __future__ import annotations

import logging
import threading
import time

import zmq

from mtcw_core.calibration import Calibration
from mtcw_core.chain import get_profile, process_frame

from .settings import WorkerSettings, log_settings
from .wire import END_TOPIC, VERSION, WireError, decode_frame, encode_points, result_message

log = logging.getLogger("mtcw.worker")


def rejection_message(err: WireError, parts) -> dict:
    """A point message for a frame the decoder refused, keeping ``source``/``seq`` when readable."""
    source, seq, t_ns = "", -1, 0
    try:
        import msgpack

        h = msgpack.unpackb(bytes(parts[1]), raw=False)
        if isinstance(h, dict):
            source = h.get("source", "") if isinstance(h.get("source"), str) else ""
            seq = h["seq"] if isinstance(h.get("seq"), int) else -1
            t_ns = h["t_ns"] if isinstance(h.get("t_ns"), int) else 0
    except Exception:
        pass
    return {"v": VERSION, "source": source, "seq": seq, "t_ns": t_ns, "status": "rejected",
            "reason": f"malformed_{err.reason}: {err.detail}", "profile": "", "targets": [],
            "unambiguous_range_m": None, "coarse_range_m": None, "stage_seconds": {}}


class Worker:
    def __init__(self, settings: WorkerSettings, ctx: zmq.Context | None = None) -> None:
        self.settings = settings
        self.chain = get_profile(settings.profile)
        self.calibration = Calibration.load(settings.calibration) if settings.calibration else None
        self.ctx = ctx or zmq.Context.instance()
        self.pull = self.ctx.socket(zmq.PULL)
        self.pull.setsockopt(zmq.RCVHWM, settings.hwm)
        self.pull.setsockopt(zmq.LINGER, 0)
        self.pull.connect(settings.frames_endpoint)
        self.push = self.ctx.socket(zmq.PUSH)
        self.push.setsockopt(zmq.SNDHWM, max(settings.hwm, 1000))
        self.push.setsockopt(zmq.LINGER, 2000)  # deliver the last points on a clean stop
        self.push.setsockopt(zmq.SNDTIMEO, 1000)
        self.push.connect(settings.points_endpoint)
        self.received = self.sent = self.unsent = 0
        self._metrics = _exporter(settings.metrics_port, settings.metrics_host, settings.name)

    def handle(self, parts) -> dict:
        """One message in, one point message out (never raises)."""
        try:
            frame = decode_frame(parts)
        except WireError as err:
            return rejection_message(err, parts)
        res = process_frame(frame, self.chain, self.calibration)
        return result_message(res, latency_s=(time.time_ns() - frame.t_ns) * 1e-9 if frame.t_ns else None,
                              run=frame.extra.get("run"))

    def run(self, stop: threading.Event) -> None:
        log_settings(f"worker {self.settings.name}", self.settings)
        if self.calibration is None:
            log.warning("worker %s: no calibration: using the frames' tone phases and tau0 = 0", self.settings.name)
        poller = zmq.Poller()
        poller.register(self.pull, zmq.POLLIN)
        try:
            while not stop.is_set():
                if not poller.poll(200):
                    continue
                parts = self.pull.recv_multipart(copy=False)
                if len(parts) == 2 and parts[0].bytes == END_TOPIC:  # end of a run: the API checks it
                    try:
                        self.push.send_multipart([p.bytes for p in parts])
                    except zmq.Again:
                        log.warning("worker %s: API not reachable; end-of-run notice not delivered",
                                    self.settings.name)
                    continue
                self.received += 1
                msg = self.handle(parts)
                if self._metrics:
                    self._metrics[0].labels(msg["status"]).inc()
                try:
                    self.push.send_multipart(encode_points(msg))
                    self.sent += 1
                except zmq.Again:  # the API is gone: the point is lost, and said so
                    self.unsent += 1
                    if self._metrics:
                        self._metrics[1].inc()
                    log.warning("worker %s: API not reachable; point seq %s not delivered", self.settings.name,
                                msg["seq"])
        finally:
            log.info("worker %s: stopped (received %d, sent %d, undelivered %d)", self.settings.name,
                     self.received, self.sent, self.unsent)
            self.pull.close()
            self.push.close()


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
