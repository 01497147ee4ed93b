"""The API: consumes points from the workers, keeps the latest and a bounded history, serves HTTP.

A background thread binds the points socket (PULL), decodes, puts points back in ``seq`` order
(:class:`~services.ordering.Reorderer`) and updates the store and the Prometheus metrics; the
FastAPI app reads the store. Counters add up: ``received = processed + rejected`` (late and
repeated points are rejected with reason ``stale``); frames that never came are ``dropped``,
including those after the last arrival of a run, once the acquisition node's end-of-run notice
(forwarded by a worker) has said how many frames the run had.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from contextlib import asynccontextmanager
from typing import Optional

import zmq
from fastapi import FastAPI, HTTPException, Query, Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge, Histogram, generate_latest

from .ordering import Reorderer
from .settings import ApiSettings, log_settings
from .wire import END_TOPIC, WireError, decode_end, decode_points

log = logging.getLogger("mtcw.api")

_BUCKETS = (1e-4, 3e-4, 1e-3, 3e-3, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 30.0)


def reason_key(reason: Optional[str]) -> str:
    """The metric label of a rejection: its key, before any detail."""
    return (reason or "unknown").split(":", 1)[0].strip()[:40] or "unknown"


class Metrics:
    """The spec's Prometheus metrics, in their own registry (one per app)."""

    def __init__(self) -> None:
        r = self.registry = CollectorRegistry()
        self.received = Counter("mtcw_frames_received_total", "frames whose result reached the API", registry=r)
        self.processed = Counter("mtcw_frames_processed_total", "frames processed (ok or no_target)", registry=r)
        self.rejected = Counter("mtcw_frames_rejected_total", "frames rejected, by reason", ["reason"], registry=r)
        self.dropped = Counter("mtcw_frames_dropped_total", "frames that never arrived (seq gaps)", registry=r)
        self.stage = Histogram("mtcw_stage_duration_seconds", "chain stage duration", ["stage"], buckets=_BUCKETS,
                               registry=r)
        self.latency = Histogram("mtcw_frame_latency_seconds", "trigger to point at the API", buckets=_BUCKETS,
                                 registry=r)
        self.range = Gauge("mtcw_range_meters", "latest range", ["source"], registry=r)
        self.velocity = Gauge("mtcw_velocity_meters_per_second", "latest velocity", ["source"], registry=r)
        self.tone_snr = Gauge("mtcw_tone_snr_db", "latest post-integration SNR per tone", ["tone"], registry=r)
        self.age = Gauge("mtcw_last_frame_age_seconds", "seconds since the last point arrived", registry=r)
        self.malformed = Counter("mtcw_point_messages_malformed_total", "point messages that failed to decode",
                                 ["reason"], registry=r)
        self.rejected.labels("stale")  # present from the start, so that sums are complete


class PointStore:
    """Latest point per source, a bounded history, counters; thread-safe."""

    def __init__(self, settings: ApiSettings, metrics: Metrics) -> None:
        self.settings = settings
        self.m = metrics
        self.lock = threading.Lock()
        self.latest: dict[str, dict] = {}
        self.history: deque[dict] = deque(maxlen=settings.history)
        self.counts = {"received": 0, "processed": 0, "rejected": 0, "dropped": 0}
        self.last_arrival: Optional[float] = None  # monotonic
        self.started = time.monotonic()
        self.order = Reorderer(self._release, settings.reorder_timeout_s, settings.reorder_max)

    def add(self, msg: dict, now_mono: float) -> None:
        with self.lock:
            self.counts["received"] += 1
            self.m.received.inc()
            self.last_arrival = now_mono
            msg["latency_s"] = max(time.time_ns() - int(msg.get("t_ns") or 0), 0) * 1e-9 if msg.get("t_ns") else None
            if msg["seq"] < 0:  # a frame the worker could not even decode: counted, not ordered
                self._count_rejected(msg.get("reason"))
                return
            stale_before = self.order.stale
            dropped_before = self.order.dropped
            self.order.add(msg, now_mono)
            self._after_order(stale_before, dropped_before)

    def end(self, msg: dict, now_mono: float) -> None:
        """An end-of-run notice: the run had ``msg["frames"]`` frames; the missing tail is dropped."""
        with self.lock:
            stale_before, dropped_before = self.order.stale, self.order.dropped
            if self.order.end(msg["source"], msg.get("run"), msg["frames"], msg["t_ns"], now_mono) == "stale":
                log.info("api: end-of-run notice of an older run of %r ignored", msg["source"])
            self._after_order(stale_before, dropped_before)

    def poll(self, now_mono: float) -> None:
        with self.lock:
            stale_before, dropped_before = self.order.stale, self.order.dropped
            self.order.poll(now_mono)
            self._after_order(stale_before, dropped_before)
            if self.last_arrival is not None:
                self.m.age.set(now_mono - self.last_arrival)

    def _after_order(self, stale_before: int, dropped_before: int) -> None:
        for _ in range(self.order.stale - stale_before):
            self._count_rejected("stale")
        d = self.order.dropped - dropped_before
        if d:
            self.counts["dropped"] += d
            self.m.dropped.inc(d)

    def _count_rejected(self, reason: Optional[str]) -> None:
        self.counts["rejected"] += 1
        self.m.rejected.labels(reason_key(reason)).inc()

    def _release(self, msg: dict) -> None:
        """Called by the reorderer, in seq order, once per point (lock held)."""
        if msg["status"] == "rejected":
            self._count_rejected(msg.get("reason"))
        else:
            self.counts["processed"] += 1
            self.m.processed.inc()
        for stage, sec in (msg.get("stage_seconds") or {}).items():
            self.m.stage.labels(stage).observe(sec)
        if msg.get("latency_s") is not None:
            self.m.latency.observe(msg["latency_s"])
        if msg["targets"]:
            t = msg["targets"][0]
            self.m.range.labels(msg["source"]).set(t["range_m"])
            self.m.velocity.labels(msg["source"]).set(t["velocity_mps"])
        for tone, snr in (msg.get("tone_snr_db") or {}).items():
            self.m.tone_snr.labels(tone).set(snr)
        self.latest[msg["source"]] = msg
        self.history.append(msg)

    def snapshot(self) -> dict:
        with self.lock:
            now = time.monotonic()
            age = None if self.last_arrival is None else now - self.last_arrival
            return {**self.counts, "last_frame_age_s": age, "held_for_reordering": self.order.held(),
                    "awaited_after_end": self.order.awaited(),
                    "uptime_s": now - self.started}


class PointReceiver(threading.Thread):
    """Binds the points endpoint and feeds the store until stopped."""

    def __init__(self, store: PointStore, settings: ApiSettings, ctx: zmq.Context | None = None) -> None:
        super().__init__(name="points-receiver", daemon=True)
        self.store = store
        self.settings = settings
        self.ctx = ctx or zmq.Context.instance()
        self.stop_event = threading.Event()
        self.sock = self.ctx.socket(zmq.PULL)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.RCVHWM, max(settings.hwm, 1000))
        self.sock.bind(settings.points_endpoint)

    def run(self) -> None:
        poller = zmq.Poller()
        poller.register(self.sock, zmq.POLLIN)
        try:
            while not self.stop_event.is_set():
                if poller.poll(100):
                    parts = self.sock.recv_multipart()
                    is_end = bool(parts) and parts[0] == END_TOPIC
                    try:
                        msg = decode_end(parts) if is_end else decode_points(parts)
                    except WireError as err:
                        self.store.m.malformed.labels(err.reason).inc()
                        log.warning("api: dropped a malformed %s message: %s", "end" if is_end else "point", err)
                        continue
                    (self.store.end if is_end else self.store.add)(msg, time.monotonic())
                self.store.poll(time.monotonic())
        finally:
            self.sock.close()

    def stop(self) -> None:
        self.stop_event.set()


def create_app(settings: ApiSettings | None = None, start_receiver: bool = True) -> FastAPI:
    """The FastAPI app; with ``start_receiver`` the points thread runs for the app's lifetime."""
    settings = settings or ApiSettings()
    metrics = Metrics()
    store = PointStore(settings, metrics)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        recv = None
        if start_receiver:
            log_settings("api", settings)
            recv = PointReceiver(store, settings)
            recv.start()
            log.info("api: points on %s (PULL); HTTP on %s:%d", settings.points_endpoint, settings.host,
                     settings.port)
        yield
        if recv is not None:
            recv.stop()
            recv.join(timeout=2)

    app = FastAPI(title="mtcw", version="1", lifespan=lifespan,
                  description="Range and velocity from a multi-tone CW lidar (PB-MTCW), live.")
    app.state.store = store
    app.state.settings = settings

    @app.get("/v1/points/latest", summary="newest result per source")
    def latest(source: Optional[str] = Query(None, min_length=1, max_length=200)) -> dict:
        with store.lock:
            if source is not None:
                if source not in store.latest:
                    raise HTTPException(404, f"source {source!r}: no points (known: {sorted(store.latest)})")
                return store.latest[source]
            if not store.latest:
                raise HTTPException(404, "no points received yet")
            return {"points": dict(store.latest)}

    @app.get("/v1/points", summary="bounded history, oldest first")
    def points(since_seq: int = Query(-1, ge=-1, description="only points with seq greater than this"),
               limit: int = Query(100, ge=1, le=10_000),
               source: Optional[str] = Query(None, min_length=1, max_length=200)) -> dict:
        with store.lock:
            sel = [p for p in store.history if p["seq"] > since_seq and (source is None or p["source"] == source)]
        return {"points": sel[:limit], "count": min(len(sel), limit), "more": len(sel) > limit}

    @app.get("/healthz", summary="alive")
    def healthz() -> dict:
        return {"status": "alive", **store.snapshot()}

    @app.get("/readyz", summary="a frame arrived recently")
    def readyz(response: Response) -> dict:
        snap = store.snapshot()
        age = snap["last_frame_age_s"]
        ready = age is not None and age < settings.stale_after_s
        if not ready:
            response.status_code = 503
        why = "ok" if ready else ("no frame yet" if age is None else f"last frame {age:.1f} s ago")
        return {"status": "ready" if ready else "not_ready", "reason": why, **snap}

    @app.get("/metrics", summary="Prometheus text format", response_class=Response)
    def prom() -> Response:
        store.poll(time.monotonic())
        return Response(generate_latest(metrics.registry), media_type=CONTENT_TYPE_LATEST)

    return app


def serve(settings: ApiSettings) -> None:
    """Run the API under uvicorn until SIGINT/SIGTERM (uvicorn's own graceful shutdown)."""
    import uvicorn

    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level="warning")
