"""The API: consumes points from the workers, keeps the latest and a bounded history, serves HTTP.

A background thread (:class:`PointReceiver`) binds the points socket (PULL), decodes each
message into its schema (:mod:`services.wire`) and hands it to the :class:`PointStore`, which
puts points back in ``seq`` order (:class:`~services.ordering.Reorderer`) and updates the
Prometheus metrics; the FastAPI app reads the store. The receiver never dies of a message: a
malformed one is logged, counted in ``mtcw_messages_malformed_total{reason}`` and skipped, and
``/healthz`` says whether the receiver thread is alive and what went wrong last.

Counters add up: ``received = processed + rejected`` (late and repeated points are rejected
with reason ``stale``); frames that never came are ``dropped``, including those after the last
arrival of a run, once the acquisition node's end-of-run notice (forwarded by a worker) has said
how many frames the run had.

``latency_s`` of a served point, and ``mtcw_frame_latency_seconds``, is the time from the
frame's trigger (``t_ns``, stamped by the acquisition node) to the point's arrival here, by this
process's clock; the worker's own time for the frame is the point's ``processing_s``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from contextlib import asynccontextmanager
from typing import Callable, Optional

import msgspec
import zmq
from fastapi import FastAPI, HTTPException, Query, Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge, Histogram, generate_latest

from .ordering import Reorderer
from .settings import ApiSettings, log_settings
from .sockets import bound_endpoint, open_socket, points_pull, report_endpoints
from .wire import END_TOPIC, EndMessage, PointMessage, ServedPoint, WireError, decode_end, decode_points, topic

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
        self.malformed = Counter("mtcw_messages_malformed_total", "messages the API's receiver refused (points, "
                                 "end notices), by reason", ["reason"], registry=r)
        self.receiver_errors = Counter("mtcw_receiver_errors_total", "messages the receiver decoded but could not "
                                       "store (a bug; logged with its traceback)", registry=r)
        self.rejected.labels("stale")  # present from the start, so that sums are complete


def served_json(point: ServedPoint) -> dict:
    """A served point as JSON-able builtins (absent optional keys left out)."""
    return msgspec.to_builtins(point)


class PointStore:
    """Latest point per source, a bounded history, counters; thread-safe.

    Parameters
    ----------
    settings : ApiSettings
    metrics : Metrics
    clock_ns : callable, optional
        Wall clock (Unix ns) for the points' ``latency_s`` (``time.time_ns``); for tests.
    """

    def __init__(self, settings: ApiSettings, metrics: Metrics, clock_ns: Callable[[], int] = time.time_ns) -> None:
        self.settings = settings
        self.m = metrics
        self.clock_ns = clock_ns
        self.lock = threading.Lock()
        self.latest: dict[str, ServedPoint] = {}
        self.history: deque[ServedPoint] = deque(maxlen=settings.history)
        self.counts = {"received": 0, "processed": 0, "rejected": 0, "dropped": 0}
        self.last_arrival: Optional[float] = None  # monotonic
        self.started = time.monotonic()
        self.order: Reorderer[ServedPoint] = Reorderer(self._release, settings.reorder_timeout_s,
                                                        settings.reorder_max)

    def add(self, msg: PointMessage, now_mono: float) -> None:
        """One point message, arrived at ``now_mono`` (monotonic s); its latency is measured now."""
        latency_s = max(self.clock_ns() - msg.t_ns, 0) * 1e-9 if msg.t_ns else None
        point = ServedPoint(**msgspec.structs.asdict(msg), latency_s=latency_s)
        with self.lock:
            self.counts["received"] += 1
            self.m.received.inc()
            self.last_arrival = now_mono
            if point.seq < 0:  # a frame the worker could not even decode: counted, not ordered
                self._count_rejected(point.reason)
                return
            stale_before = self.order.stale
            dropped_before = self.order.dropped
            self.order.add(point, now_mono)
            self._after_order(stale_before, dropped_before)

    def end(self, msg: EndMessage, now_mono: float) -> None:
        """An end-of-run notice: the run had ``msg.frames`` frames; the missing tail is dropped."""
        with self.lock:
            stale_before, dropped_before = self.order.stale, self.order.dropped
            if self.order.end(msg.source, msg.run, msg.frames, msg.t_ns, now_mono) == "stale":
                log.info("api: end-of-run notice of an older run of %r ignored", msg.source)
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

    def _release(self, p: ServedPoint) -> None:
        """Called by the reorderer, in seq order, once per point (lock held)."""
        if p.status == "rejected":
            self._count_rejected(p.reason)
        else:
            self.counts["processed"] += 1
            self.m.processed.inc()
        for stage, sec in p.stage_seconds.items():
            self.m.stage.labels(stage).observe(sec)
        if p.latency_s is not None:
            self.m.latency.observe(p.latency_s)
        if p.targets:
            self.m.range.labels(p.source).set(p.targets[0].range_m)
            self.m.velocity.labels(p.source).set(p.targets[0].velocity_mps)
        for tone, snr in p.tone_snr_db.items():
            self.m.tone_snr.labels(tone).set(snr)
        self.latest[p.source] = p
        self.history.append(p)

    def snapshot(self) -> dict:
        with self.lock:
            now = time.monotonic()
            age = None if self.last_arrival is None else now - self.last_arrival
            return {**self.counts, "last_frame_age_s": age, "held_for_reordering": self.order.held(),
                    "awaited_after_end": self.order.awaited(),
                    "uptime_s": now - self.started}


class PointReceiver(threading.Thread):
    """Binds the points endpoint and feeds the store until stopped; a bad message never stops it.

    Parameters
    ----------
    store : PointStore
    settings : ApiSettings
    ctx : zmq.Context, optional
    """

    def __init__(self, store: PointStore, settings: ApiSettings, ctx: zmq.Context | None = None) -> None:
        super().__init__(name="points-receiver", daemon=True)
        self.store = store
        self.settings = settings
        self.ctx = ctx or zmq.Context.instance()
        self.stop_event = threading.Event()
        self.sock = open_socket(self.ctx, points_pull(settings))
        self.endpoint = bound_endpoint(self.sock)
        self.messages = 0
        self.malformed = 0
        self.last_error: Optional[str] = None
        self.last_error_at: Optional[float] = None  # monotonic
        self.died: Optional[str] = None  # why the thread ended other than by stop()

    def handle(self, parts: list, now_mono: float) -> str:
        """Decode one message and give it to the store; returns ``"point"``, ``"end"``,
        ``"malformed"`` or ``"error"`` (never raises)."""
        self.messages += 1
        kind = "end" if topic(parts) == END_TOPIC else "point"
        try:
            msg = decode_end(parts) if kind == "end" else decode_points(parts)
        except WireError as err:
            self.malformed += 1
            self.store.m.malformed.labels(err.reason).inc()
            self._error(f"malformed {kind} message: {err}")
            log.warning("api: dropped a malformed %s message: %s", kind, err)
            return "malformed"
        try:
            (self.store.end if kind == "end" else self.store.add)(msg, now_mono)
        except Exception as err:  # a bug, not a bad message: logged loudly, counted, and go on
            self.store.m.receiver_errors.inc()
            self._error(f"{kind} message not stored: {type(err).__name__}: {err}")
            log.exception("api: could not store a %s message", kind)
            return "error"
        return kind

    def _error(self, what: str) -> None:
        self.last_error, self.last_error_at = what[:500], time.monotonic()

    def run(self) -> None:
        poller = zmq.Poller()
        poller.register(self.sock, zmq.POLLIN)
        try:
            while not self.stop_event.is_set():
                if poller.poll(100):
                    self.handle(self.sock.recv_multipart(), time.monotonic())
                self.store.poll(time.monotonic())
        except Exception as err:  # the receiver is dead: /healthz and /readyz say so, and why
            self.died = f"{type(err).__name__}: {err}"
            log.exception("api: points receiver died")
        finally:
            self.sock.close()

    def status(self) -> dict:
        """``state`` (``not_started``, ``alive``, ``stopped`` or ``dead``), ``endpoint``, message counts and the
        last error (with its age in seconds)."""
        if self.ident is None:
            state = "not_started"
        elif self.is_alive():
            state = "alive"
        else:
            state = "dead" if self.died or not self.stop_event.is_set() else "stopped"
        age = None if self.last_error_at is None else time.monotonic() - self.last_error_at
        return {"state": state, "endpoint": self.endpoint, "messages": self.messages, "malformed": self.malformed,
                "last_error": self.died or self.last_error, "last_error_age_s": age}

    def stop(self) -> None:
        self.stop_event.set()


def create_app(settings: ApiSettings | None = None, start_receiver: bool = True,
               clock_ns: Callable[[], int] = time.time_ns) -> FastAPI:
    """The FastAPI app; with ``start_receiver`` the points thread runs for the app's lifetime.

    Once the receiver has bound, its endpoint (and ``app.state.http_url``, when :func:`serve`
    set it) are written to ``settings.endpoints_file``. ``clock_ns`` is the store's wall clock.
    """
    settings = settings or ApiSettings()
    metrics = Metrics()
    store = PointStore(settings, metrics, clock_ns)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        recv = None
        if start_receiver:
            log_settings("api", settings)
            recv = app.state.receiver = PointReceiver(store, settings)
            recv.start()
            http_url = getattr(app.state, "http_url", None)
            report_endpoints(settings.endpoints_file, {"points_endpoint": recv.endpoint,
                                                       **({"http_url": http_url} if http_url else {})})
            log.info("api: points on %s (PULL); HTTP on %s", recv.endpoint, http_url or f"{settings.host}:"
                                                                                      f"{settings.port}")
        yield
        if recv is not None:
            recv.stop()
            recv.join(timeout=2)

    app = FastAPI(title="mtcw", version="1", lifespan=lifespan,
                  description="Range and velocity from a multi-tone CW lidar (PB-MTCW), live.")
    app.state.store = store
    app.state.settings = settings
    app.state.receiver = None

    def receiver_status() -> dict:
        recv = app.state.receiver
        return recv.status() if recv is not None else {"state": "not_started"}

    @app.get("/v1/points/latest", summary="newest result per source",
             responses={404: {"description": "no point yet (from this source, when one is named)",
                              "content": {"application/json": {"schema": {
                                  "type": "object", "properties": {"detail": {"type": "string"}},
                                  "required": ["detail"]}}}}})
    def latest(source: Optional[str] = Query(None, min_length=1, max_length=200)) -> dict:
        with store.lock:
            if source is not None:
                if source not in store.latest:
                    raise HTTPException(404, f"source {source!r}: no points (known: {sorted(store.latest)})")
                return served_json(store.latest[source])
            if not store.latest:
                raise HTTPException(404, "no points received yet")
            return {"points": {s: served_json(p) for s, p in store.latest.items()}}

    @app.get("/v1/points", summary="bounded history, oldest first")
    def points(since_seq: int = Query(-1, ge=-1, description="only points with seq greater than this"),
               limit: int = Query(100, ge=1, le=10_000),
               source: Optional[str] = Query(None, min_length=1, max_length=200)) -> dict:
        with store.lock:
            sel = [p for p in store.history if p.seq > since_seq and (source is None or p.source == source)]
        return {"points": [served_json(p) for p in sel[:limit]], "count": min(len(sel), limit),
                "more": len(sel) > limit}

    @app.get("/healthz", summary="alive, and the points receiver's state",
             responses={503: {"description": "the points receiver has died (status receiver_dead)",
                              "content": {"application/json": {"schema": {"type": "object"}}}}})
    def healthz(response: Response) -> dict:
        recv = receiver_status()
        dead = recv["state"] == "dead"
        if dead:
            response.status_code = 503
        return {"status": "receiver_dead" if dead else "alive", "receiver": recv, **store.snapshot()}

    @app.get("/readyz", summary="receiver alive and a frame arrived recently",
             responses={503: {"description": "not ready: no recent frame, or the receiver is not alive",
                              "content": {"application/json": {"schema": {"type": "object"}}}}})
    def readyz(response: Response) -> dict:
        snap = store.snapshot()
        recv = receiver_status()
        age = snap["last_frame_age_s"]
        if recv["state"] not in ("alive", "not_started"):
            why = f"points receiver {recv['state']}: {recv.get('last_error')}"
        elif age is None:
            why = "no frame yet"
        elif age >= settings.stale_after_s:
            why = f"last frame {age:.1f} s ago"
        else:
            why = "ok"
        ready = why == "ok"
        if not ready:
            response.status_code = 503
        return {"status": "ready" if ready else "not_ready", "reason": why, "receiver": recv, **snap}

    @app.get("/metrics", summary="Prometheus text format", response_class=Response)
    def prom() -> Response:
        store.poll(time.monotonic())
        return Response(generate_latest(metrics.registry), media_type=CONTENT_TYPE_LATEST)

    return app


def serve(settings: ApiSettings) -> None:
    """Run the API under uvicorn until SIGINT/SIGTERM (uvicorn's own graceful shutdown).

    The HTTP socket is bound here (``port`` 0 takes a free one), so that its URL can be
    reported with the points endpoint (``endpoints_file``).
    """
    import uvicorn

    app = create_app(settings)
    config = uvicorn.Config(app, host=settings.host, port=settings.port, log_level="warning")
    sock = config.bind_socket()
    host = f"[{settings.host}]" if ":" in settings.host else settings.host
    app.state.http_url = f"http://{host}:{sock.getsockname()[1]}"
    uvicorn.Server(config).run(sockets=[sock])
