"""The API: consumes points from the workers, keeps them durably, serves HTTP.

A background thread (:class:`PointReceiver`) binds the points socket (PULL), decodes each
message into its schema (:mod:`services.wire`) and hands it to the :class:`PointStore`, which
puts points back in ``seq`` order (:class:`~services.ordering.Reorderer`); once per loop
iteration the store commits what was released, the counters and the reorder state to SQLite in
one transaction (:class:`~services.history.HistoryDB`), and only then shows it: the latest points,
``/healthz``'s counts and the Prometheus metrics are what is committed, so nothing is ever served
that a restart would take back. The receiver never dies of a message: a malformed one is logged,
counted in ``mtcw_messages_malformed_total{reason}`` and skipped; so is one the store refuses
(``seq_jump``, ``end_run``, ``end_frames``, ``future_t_ns``, ``out_of_range``: see
:mod:`services.ordering`).

Counters add up: ``received = processed + rejected + held_for_reordering`` (repeated points and
points of an older run are rejected with reason ``stale``); frames that never came are
``dropped``, including those after the last arrival of a run, once the acquisition node's
end-of-run notice (forwarded by a worker) has said how many frames the run had; so
``published = processed + rejected + dropped``. A point that comes after its frame was counted
dropped is ``late``: counted apart (``mtcw_frames_late_total``), not again. Refused messages are
in none of these.

Restart: history, latest points, counters and each source's reorder state (with the points held
for reordering) are read back at start-up. What a killed API had received after its last commit
(at most one loop iteration: :data:`BATCH_MAX` messages or 0.1 s) is gone; those frames are seq
gaps for the restarted API, counted as dropped like the frames published while it was down, so
``published = processed + rejected + dropped`` still holds (unless the lost messages included a
run's end-of-run notice, whose tail then stays uncounted).

``latency_s`` of a served point, and ``mtcw_frame_latency_seconds``, is the time from the
frame's trigger (``t_ns``, stamped by the acquisition node) to the point's arrival here, by this
process's clock; the worker's own time for the frame is the point's ``processing_s``.

Health: ``/livez`` answers while the process serves; ``/readyz`` checks the receiver, the store
(the last write succeeded, at most :data:`STORE_STALE_S` ago: the receiver writes at least every
:data:`PROBE_S`) and that a frame arrived within ``stale_after_s``; ``/healthz`` (kept for
existing users) is the receiver's state and the counts, 503 once the receiver has died. Under
:func:`serve`, a dead receiver stops the process (exit status 3), so that its supervisor
restarts it.
"""

from __future__ import annotations

import asyncio
import json
import logging
import platform
import sys
import threading
import time
from contextlib import asynccontextmanager
from importlib import metadata
from pathlib import Path
from typing import Callable, Optional

import msgspec
import zmq
from fastapi import FastAPI, HTTPException, Query, Request, Response
from fastapi.responses import FileResponse, StreamingResponse
from fastapi.staticfiles import StaticFiles
from starlette.concurrency import run_in_threadpool
from prometheus_client import (CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge, GCCollector, Histogram,
                               PlatformCollector, ProcessCollector, generate_latest)

from .history import INT64_MAX, HistoryDB, Segment
from .monitor import ViewFeed
from .ordering import Reorderer
from .settings import ApiSettings, log_settings
from .sockets import bound_endpoint, open_socket, points_pull, report_endpoints
from .wire import END_TOPIC, EndMessage, PointMessage, ServedPoint, WireError, decode_end, decode_points, topic

log = logging.getLogger("mtcw.api")

_BUCKETS = (1e-4, 3e-4, 1e-3, 3e-3, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 30.0)
#: Messages taken from the socket per receiver-loop iteration at most, i.e. per transaction: at
#: about 50 us per point to decode and order, a full batch is 50 ms of work before it is shown.
BATCH_MAX = 1000
#: With no traffic, the receiver still writes (a heartbeat, and retention by age) this often (s):
#: the store's readiness check is a real write at most this old.
PROBE_S = 2.0
#: ``/readyz`` fails when the last successful write is older than this (s).
STORE_STALE_S = 5 * PROBE_S
#: Points released but not yet committed, at most: beyond it (the disk is full or gone) the
#: receiver stops taking messages (the workers' sends time out and are counted there) until a
#: commit succeeds.
PENDING_MAX = 100_000
#: Exit status of :func:`serve` when the points receiver has died.
EXIT_RECEIVER_DEAD = 3

#: The books: ``received = processed + rejected + held``; ``dropped`` counts frames that never came.
BOOKS = ("received", "processed", "rejected", "dropped")


def reason_key(reason: Optional[str]) -> str:
    """The metric label of a rejection: its key, before any detail."""
    return (reason or "unknown").split(":", 1)[0].strip()[:40] or "unknown"


def _git_commit() -> str:
    """The commit of the source tree this runs from, read from ``.git`` without running git;
    ``"unknown"`` when it is not a checkout (an installed package, an image)."""
    try:
        root = Path(__file__).resolve().parents[1]
        git = root / ".git"
        if git.is_file():  # a worktree: "gitdir: <path>"
            git = Path(git.read_text().split(":", 1)[1].strip())
        head = (git / "HEAD").read_text().strip()
        if not head.startswith("ref:"):
            return head[:40]
        ref = head.split(":", 1)[1].strip()
        common = Path((git / "commondir").read_text().strip()) if (git / "commondir").is_file() else None
        for base in (git, (git / common) if common else None):
            if base is not None and (base / ref).is_file():
                return (base / ref).read_text().strip()[:40]
            packed = base / "packed-refs" if base is not None else None
            if packed is not None and packed.is_file():
                for line in packed.read_text().splitlines():
                    if line.endswith(" " + ref):
                        return line.split()[0][:40]
    except (OSError, IndexError, ValueError):
        pass
    return "unknown"


def _version() -> str:
    try:
        return metadata.version("mtcw")
    except metadata.PackageNotFoundError:
        return "unknown"


class Metrics:
    """The API's Prometheus metrics, in their own registry (one per app), with the process,
    platform and garbage-collector collectors and ``mtcw_build_info``."""

    def __init__(self) -> None:
        r = self.registry = CollectorRegistry()
        self.received = Counter("mtcw_frames_received_total", "frames whose result reached the API", registry=r)
        self.processed = Counter("mtcw_frames_processed_total", "frames processed (ok or no_target)", registry=r)
        self.rejected = Counter("mtcw_frames_rejected_total", "frames rejected, by reason", ["reason"], registry=r)
        self.dropped = Counter("mtcw_frames_dropped_total", "frames that never arrived (seq gaps)", registry=r)
        self.late = Counter("mtcw_frames_late_total", "points that came after their frame was counted dropped (not "
                            "received, not counted again)", registry=r)
        self.stage = Histogram("mtcw_stage_duration_seconds", "chain stage duration", ["stage"], buckets=_BUCKETS,
                               registry=r)
        self.latency = Histogram("mtcw_frame_latency_seconds", "trigger to point at the API", buckets=_BUCKETS,
                                 registry=r)
        self.range = Gauge("mtcw_range_meters", "latest range", ["source"], registry=r)
        self.velocity = Gauge("mtcw_velocity_meters_per_second", "latest velocity", ["source"], registry=r)
        self.tone_snr = Gauge("mtcw_tone_snr_db", "latest post-integration SNR per tone", ["tone"], registry=r)
        self.age = Gauge("mtcw_last_frame_age_seconds", "seconds since the last point arrived", registry=r)
        self.peers_refused = Counter("mtcw_peers_refused_total", "peers refused for an unknown CURVE key (not in "
                                     "curve_dir/authorized), by socket", ["socket"], registry=r)
        self.malformed = Counter("mtcw_messages_malformed_total", "messages the API's receiver refused (malformed "
                                 "points and end notices; seq_jump, end_run, end_frames, future_t_ns, out_of_range: "
                                 "not believed), by reason", ["reason"], registry=r)
        self.receiver_errors = Counter("mtcw_receiver_errors_total", "messages the receiver decoded but could not "
                                       "store (a bug; logged with its traceback)", registry=r)
        self.store_rows = Gauge("mtcw_store_points", "points in the durable history", registry=r)
        self.store_commit = Histogram("mtcw_store_commit_seconds", "one batch written to the store", buckets=_BUCKETS,
                                      registry=r)
        self.store_errors = Counter("mtcw_store_errors_total", "store failures: commit (batch kept and retried), "
                                    "bad_row (a stored point that cannot be read, skipped)", ["kind"], registry=r)
        self.view_frames = Counter("mtcw_view_frames_total", "monitor frames seen by the live view's feed, by "
                                   "outcome (explained; passed_over: rate bound; lost: dropped before it by ZeroMQ)",
                                   ["outcome"], registry=r)
        self.view_skipped = Counter("mtcw_view_diagnostics_skipped_total", "live-view explanations a slow page never "
                                    "got (a newer one replaced them first)", registry=r)
        self.view_clients = Gauge("mtcw_view_streams", "open /v1/points/stream connections", registry=r)
        self.view_explain = Histogram("mtcw_view_explain_seconds", "one live-view explanation (spectrum, J(L), seed "
                                      "matrix) of a monitor frame", buckets=_BUCKETS, registry=r)
        for outcome in ("explained", "passed_over", "lost"):
            self.view_frames.labels(outcome)
        self.rejected.labels("stale")  # present from the start, so that sums are complete
        for kind in ("commit", "bad_row"):
            self.store_errors.labels(kind)
        ProcessCollector(registry=r)
        PlatformCollector(registry=r)
        GCCollector(registry=r)
        self.build = Gauge("mtcw_build_info", "mtcw version, Python version and git commit of this process (value 1)",
                           ["version", "python", "commit"], registry=r)
        self.build.labels(_version(), platform.python_version(), _git_commit()).set(1)


def served_json(point: ServedPoint) -> dict:
    """A served point as JSON-able builtins (absent optional keys left out)."""
    return msgspec.to_builtins(point)


class PointStore:
    """Ordering, counting and the durable history of the points; the receiver thread's side.

    The receiver calls :meth:`add`, :meth:`end`, :meth:`refuse` and :meth:`poll` as messages come
    and :meth:`commit` once per loop iteration; HTTP threads read what was committed
    (:attr:`latest`, :meth:`snapshot`, ``db.points``).

    Parameters
    ----------
    settings : ApiSettings
    metrics : Metrics
    clock_ns : callable, optional
        Wall clock (Unix ns): the points' ``latency_s``, the future bound on ``t_ns``, ``served_ns``.
    db : HistoryDB, optional
        The store (default: opened at ``settings.store_path``).
    """

    def __init__(self, settings: ApiSettings, metrics: Metrics, clock_ns: Callable[[], int] = time.time_ns,
                 db: Optional[HistoryDB] = None) -> None:
        self.settings = settings
        self.m = metrics
        self.clock_ns = clock_ns
        self.db = db if db is not None else HistoryDB(settings.store_path, settings.retention_points,
                                                      settings.retention_s, on_bad_row=self._bad_row)
        self.lock = threading.Lock()  # guards the committed view below
        self.order: Reorderer[ServedPoint] = Reorderer(self._release, settings.reorder_timeout_s,
                                                        settings.reorder_max, settings.max_seq_jump)
        # working state: the receiver thread's
        self.counts: dict[str, int] = dict.fromkeys(BOOKS, 0)  # and "rejected:<reason>", "refused:<reason>"
        self._pending: list[tuple[int, ServedPoint]] = []  # released since the last commit
        self._segments: dict[str, Segment] = {}
        self._counts_changed = False
        self.last_arrival: Optional[float] = None  # monotonic
        self.started = time.monotonic()
        # committed view
        self.latest: dict[str, ServedPoint] = {}
        self._shown: dict[str, int] = {}
        self._view: dict = {}
        self._reasons: dict = {"rejected": {}, "refused": {}}
        self.last_write: Optional[float] = None  # monotonic time of the last successful commit
        self.write_error: Optional[str] = None
        self.commits = 0
        self._restore()

    # ------------------------------------------------------------------------------------------
    def _restore(self) -> None:
        got = self.db.load()
        now = time.monotonic()
        self.counts.update(got.counters)
        if got.bad_held:  # unreadable now: as if never received; their seqs are gaps, counted dropped
            self._count("received", -got.bad_held)
        for source, st in got.sources.items():
            self.order.restore(source, st, now)
        self._segments = got.segments
        self.latest = dict(got.latest)
        for p in got.latest.values():
            self._gauges(p)
        self._publish(now)
        self.last_write = now  # the store was just opened and read: writable is checked by the first commit
        if got.points or got.sources:
            log.info("api: store %s restored: %d points, %d sources (%d points held for reordering), counts %s",
                     self.db.path, got.points, len(got.sources), self.order.held(),
                     {k: self.counts[k] for k in BOOKS})

    def _bad_row(self, where: str) -> None:
        self.m.store_errors.labels("bad_row").inc()

    # ------------------------------------------------------------------------------------------
    # the receiver thread's side
    def add(self, msg: PointMessage, now_mono: float) -> str:
        """One point message, arrived at ``now_mono`` (monotonic s); its latency is measured now.

        Returns the reorderer's outcome (``"held"``, ``"released"``, ...), ``"rejected"`` for an
        unordered rejected point (``seq = -1``) or ``"refused"`` (counted as malformed, not in the books).
        """
        why = self._implausible(msg.seq, msg.t_ns, msg.run) if msg.seq >= 0 else None
        if why:
            self.refuse(why, f"point {msg.source!r} seq {msg.seq} t_ns {msg.t_ns}")
            return "refused"
        now_ns = self.clock_ns()
        latency_s = max(now_ns - msg.t_ns, 0) * 1e-9 if msg.t_ns else None
        point = ServedPoint(**msgspec.structs.asdict(msg), latency_s=latency_s)
        if point.seq < 0:  # a frame the worker could not even decode: counted, not ordered
            self._count("received")
            self.last_arrival = now_mono
            self._count_rejected(point.reason)
            return "rejected"
        stale0, dropped0 = self.order.stale, self.order.dropped
        outcome = self.order.add(point, now_mono)
        if outcome == "jump":
            self.refuse("seq_jump", f"point {msg.source!r} seq {msg.seq}: more than {self.order.max_jump} ahead of "
                                    f"the next expected seq (believed once a second point confirms the jump)")
            return "refused"
        self.last_arrival = now_mono
        if outcome == "late":  # its frame is counted already, as dropped: not again
            self._count("late")
            return outcome
        self._count("received")
        if outcome == "resync":
            log.warning("api: source %r jumped ahead to seq %d (confirmed by a second point); the gap is dropped",
                        msg.source, msg.seq)
        self._after_order(stale0, dropped0)
        return outcome

    def end(self, msg: EndMessage, now_mono: float) -> str:
        """An end-of-run notice: the run had ``msg.frames`` frames; the missing tail is dropped.
        Returns ``"ended"`` or ``"refused"``."""
        why = self._implausible(msg.frames, msg.t_ns, msg.run)
        if why:
            self.refuse(why, f"end notice of {msg.source!r}")
            return "refused"
        stale0, dropped0 = self.order.stale, self.order.dropped
        outcome = self.order.end(msg.source, msg.run, msg.frames, msg.t_ns, now_mono)
        if outcome != "ended":
            self.refuse("end_run" if outcome == "other_run" else "end_frames",
                        f"end notice of {msg.source!r} run {msg.run} with {msg.frames} frames: "
                        + ("not the run in progress" if outcome == "other_run" else "frame count out of bounds"))
            return "refused"
        self._after_order(stale0, dropped0)
        return outcome

    def refuse(self, reason: str, detail: str) -> None:
        """A message not believed (malformed, or implausible): counted by reason, logged."""
        self._count(f"refused:{reason}")
        log.warning("api: refused a message (%s): %s", reason, detail[:300])

    def _implausible(self, seq: int, t_ns: int, run: Optional[int]) -> Optional[str]:
        if seq > INT64_MAX or t_ns > INT64_MAX or (run is not None and run > INT64_MAX):
            return "out_of_range"
        if t_ns > self.clock_ns() + self.settings.max_future_s * 1e9:
            return "future_t_ns"
        return None

    def poll(self, now_mono: float) -> None:
        """Give up gaps that have waited longer than the reorder timeout."""
        stale0, dropped0 = self.order.stale, self.order.dropped
        self.order.poll(now_mono)
        self._after_order(stale0, dropped0)

    def _after_order(self, stale0: int, dropped0: int) -> None:
        for _ in range(self.order.stale - stale0):
            self._count_rejected("stale")
        if self.order.dropped > dropped0:
            self._count("dropped", self.order.dropped - dropped0)

    def _count(self, key: str, n: int = 1) -> None:
        self.counts[key] = self.counts.get(key, 0) + n
        self._counts_changed = True

    def _count_rejected(self, reason: Optional[str]) -> None:
        self._count("rejected")
        self._count(f"rejected:{reason_key(reason)}")

    def _release(self, p: ServedPoint) -> None:
        """Called by the reorderer, in seq order, once per point: counted and filed under its
        source's current segment (a new one when the run changes or seq goes back)."""
        if p.status == "rejected":
            self._count_rejected(p.reason)
        else:
            self._count("processed")
        seg = self._segments.get(p.source)
        if seg is None or seg.run != p.run or p.seq <= seg.last_seq:
            seg = self._segments[p.source] = Segment(0 if seg is None else seg.number + 1, p.run, p.seq)
        seg.last_seq = p.seq
        self._pending.append((seg.number, p))

    def backlogged(self) -> bool:
        """True when so much waits for a commit that no more should be taken in."""
        return len(self._pending) >= PENDING_MAX

    def commit(self, now_mono: Optional[float] = None) -> bool:
        """Write what changed since the last commit in one transaction, then show it.

        A write is made even with nothing new once :data:`PROBE_S` has passed (the heartbeat that
        ``/readyz`` relies on, and retention by age). On failure the batch is kept for the next
        try and ``/readyz`` says why. Returns whether the store is up to date.
        """
        now_mono = time.monotonic() if now_mono is None else now_mono
        dirty = set(self.order.dirty)
        due = self.last_write is None or now_mono - self.last_write >= PROBE_S
        if not (self._pending or dirty or self._counts_changed or due):
            return True
        sources = self.order.sources()
        t0 = time.perf_counter()
        try:
            self.db.write(self._pending, self.counts if self._counts_changed else {},
                          {s: sources[s] for s in dirty if s in sources}, self.clock_ns())
        except Exception as err:  # disk full, I/O error, a bug: keep everything, try again next time
            first = self.write_error is None
            self.write_error = f"{type(err).__name__}: {err}"[:300]
            self.m.store_errors.labels("commit").inc()
            (log.exception if first else log.debug)("api: store commit failed (%d points kept for the next try)",
                                                     len(self._pending))
            return False
        self.m.store_commit.observe(time.perf_counter() - t0)
        if self.write_error is not None:
            log.warning("api: store commits again after: %s", self.write_error)
        self.order.dirty -= dirty
        self._counts_changed = False
        released, self._pending = self._pending, []
        with self.lock:
            for _, p in released:
                self.latest[p.source] = p
        for _, p in released:
            self._observe(p)
        self._publish(now_mono)
        self.write_error = None
        self.last_write = now_mono
        self.commits += 1
        return True

    def flush(self) -> None:
        """Commit now (tests, and a clean stop)."""
        self.commit(time.monotonic())

    # ------------------------------------------------------------------------------------------
    def _observe(self, p: ServedPoint) -> None:
        for stage, sec in p.stage_seconds.items():
            self.m.stage.labels(stage).observe(sec)
        if p.latency_s is not None:
            self.m.latency.observe(p.latency_s)
        self._gauges(p)

    def _gauges(self, p: ServedPoint) -> None:
        if p.targets:
            self.m.range.labels(p.source).set(p.targets[0].range_m)
            self.m.velocity.labels(p.source).set(p.targets[0].velocity_mps)
        for tone, snr in p.tone_snr_db.items():
            self.m.tone_snr.labels(tone).set(snr)

    def _publish(self, now_mono: float) -> None:
        """Show the committed counts (and bring the Prometheus counters up to them)."""
        for key, value in list(self.counts.items()):
            inc = value - self._shown.get(key, 0)
            if inc <= 0:
                continue
            self._shown[key] = value
            name, _, reason = key.partition(":")
            if key in ("received", "processed", "dropped", "late"):
                getattr(self.m, key).inc(inc)
            elif name == "rejected" and reason:
                self.m.rejected.labels(reason).inc(inc)
            elif name == "refused":
                self.m.malformed.labels(reason).inc(inc)
        view = {k: self.counts[k] for k in BOOKS}
        view.update(late=self.counts.get("late", 0), held_for_reordering=self.order.held(),
                    awaited_after_end=self.order.awaited())
        reasons = {"rejected": {}, "refused": {}}
        for key, value in self.counts.items():
            name, _, reason = key.partition(":")
            if reason and name in reasons:
                reasons[name][reason] = value
        with self.lock:
            self._view = view
            self._reasons = reasons
        self.m.store_rows.set(self.db.rows)

    def snapshot(self) -> dict:
        """The committed counts (``received = processed + rejected + held_for_reordering``), the
        age of the last frame and the uptime."""
        now = time.monotonic()
        with self.lock:
            view = dict(self._view)
        last = self.last_arrival
        return {**view, "last_frame_age_s": None if last is None else now - last, "uptime_s": now - self.started}

    def reasons(self) -> dict:
        """The committed counts of rejected points by reason and of refused messages by reason."""
        with self.lock:
            return {k: dict(v) for k, v in self._reasons.items()}

    def store_status(self, receiver_running: bool) -> tuple[bool, str]:
        """Whether the store takes writes: the last commit succeeded, and (with a receiver running)
        not longer than :data:`STORE_STALE_S` ago."""
        if self.write_error is not None:
            return False, f"store {self.db.path}: last commit failed: {self.write_error}"
        if self.last_write is None:
            return False, f"store {self.db.path}: no write yet"
        age = time.monotonic() - self.last_write
        if receiver_running and age > STORE_STALE_S:
            return False, f"store {self.db.path}: no write for {age:.0f} s (the receiver writes every {PROBE_S:g} s)"
        return True, f"store {self.db.path}: last write {age:.1f} s ago, {self.db.rows} points" + (
            "" if self.db.durable else " (not durable: :memory:)")

    def close(self) -> None:
        """Commit what is left and close the store."""
        try:
            self.flush()
        finally:
            self.db.close()


class PointReceiver(threading.Thread):
    """Binds the points endpoint and feeds the store until stopped; a bad message never stops it.

    Parameters
    ----------
    store : PointStore
    settings : ApiSettings
    ctx : zmq.Context, optional
    on_death : callable(why), optional
        Called from the thread when it ends other than by :meth:`stop` (``serve`` exits then).
    """

    def __init__(self, store: PointStore, settings: ApiSettings, ctx: zmq.Context | None = None,
                 on_death: Optional[Callable[[str], None]] = None) -> None:
        super().__init__(name="points-receiver", daemon=True)
        self.store = store
        self.settings = settings
        self.ctx = ctx or zmq.Context.instance()
        self.on_death = on_death
        self.stop_event = threading.Event()
        self.sock = open_socket(self.ctx, points_pull(settings),
                                on_refused=lambda socket: store.m.peers_refused.labels(socket).inc())
        self.endpoint = bound_endpoint(self.sock)
        self.messages = 0
        self.malformed = 0
        self.last_error: Optional[str] = None
        self.last_error_at: Optional[float] = None  # monotonic
        self.died: Optional[str] = None  # why the thread ended other than by stop()

    def handle(self, parts: list, now_mono: float) -> str:
        """Decode one message and give it to the store; returns ``"point"``, ``"end"``,
        ``"malformed"``, ``"refused"`` or ``"error"`` (never raises)."""
        self.messages += 1
        kind = "end" if topic(parts) == END_TOPIC else "point"
        try:
            msg = decode_end(parts) if kind == "end" else decode_points(parts)
        except WireError as err:
            self.malformed += 1
            self.store.refuse(err.reason, f"malformed {kind} message: {err}")
            self._error(f"malformed {kind} message: {err}")
            return "malformed"
        try:
            outcome = (self.store.end if kind == "end" else self.store.add)(msg, now_mono)
        except Exception as err:  # a bug, not a bad message: logged loudly, counted, and go on
            self.store.m.receiver_errors.inc()
            self._error(f"{kind} message not stored: {type(err).__name__}: {err}")
            log.exception("api: could not store a %s message", kind)
            return "error"
        if outcome == "refused":
            self._error(f"{kind} message refused (see mtcw_messages_malformed_total)")
            return "refused"
        return kind

    def _error(self, what: str) -> None:
        self.last_error, self.last_error_at = what[:500], time.monotonic()

    def run(self) -> None:
        poller = zmq.Poller()
        poller.register(self.sock, zmq.POLLIN)
        try:
            while not self.stop_event.is_set():
                if self.store.backlogged():  # the store cannot keep up (or write): leave messages queued
                    self.stop_event.wait(0.2)
                elif poller.poll(100):
                    for _ in range(BATCH_MAX):
                        try:
                            parts = self.sock.recv_multipart(zmq.NOBLOCK)
                        except zmq.Again:
                            break
                        self.handle(parts, time.monotonic())
                now = time.monotonic()
                self.store.poll(now)
                self.store.commit(now)
        except Exception as err:  # the receiver is dead: /healthz and /readyz say so, and why
            self.died = f"{type(err).__name__}: {err}"
            log.exception("api: points receiver died")
        finally:
            self.sock.close()
        if self.died is None:
            try:
                self.store.commit()  # a clean stop keeps what was received
            except Exception:
                log.exception("api: last commit failed")
        elif self.on_death is not None:
            self.on_death(self.died)

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


_TRUE = {"", "1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}


#: what a boolean query parameter may be, in the OpenAPI schema too (FastAPI refuses the rest with 422)
_FLAG_PATTERN = r"^(|1|0|[Tt]rue|TRUE|[Ff]alse|FALSE|[Yy]es|YES|[Nn]o|NO|[Oo]n|ON|[Oo]ff|OFF)$"


def _flag(value: Optional[str], name: str) -> bool:
    """A boolean query parameter: absent = false; ``?name``, ``=1``, ``=true`` (yes, on) = true."""
    if value is None:
        return False
    v = value.strip().lower()
    if v in _TRUE:
        return True
    if v in _FALSE:
        return False
    raise HTTPException(422, f"{name}: {value!r} is not a boolean (1, true, yes, on; 0, false, no, off)")



#: the live view's page and its vendored scripts (package data)
WEB_DIR = Path(__file__).resolve().parent / "web"
#: points per ``points`` event of the stream at most
STREAM_BATCH = 500
#: how often (s) a stream looks for new commits, a newer explanation and the time to send status
STREAM_POLL_S = 0.05
#: a comment line this often (s) keeps proxies and browsers from closing a quiet stream
STREAM_KEEPALIVE_S = 15.0


def _last_ids(db: HistoryDB, tail: int) -> int:
    """The cursor before the last ``tail`` points of the history (0 when it holds fewer), read on
    the calling thread's reader connection."""
    conn = db._reader()  # the store's per-thread read connection (WAL: beside the writer)
    # fetchall: a statement left unfinished would hold this connection's read snapshot open
    rows = conn.execute("SELECT id FROM points ORDER BY id DESC LIMIT 1 OFFSET ?", (tail,)).fetchall()
    return int(rows[0][0]) if rows else 0


def _sse(event: str, data: bytes, event_id: Optional[int] = None) -> bytes:
    """One Server-Sent Event (``data`` is one line of JSON)."""
    head = (b"id: %d\n" % event_id) if event_id is not None else b""
    return head + b"event: " + event.encode() + b"\ndata: " + data + b"\n\n"


def _add_view(app: FastAPI, store: PointStore, settings: ApiSettings, metrics: Metrics, feed: Optional[ViewFeed],
              receiver_status: Callable[[], dict]) -> None:
    """The live view at ``/``, its files under ``/web``, the push stream and the view's JSON."""
    app.mount("/web", StaticFiles(directory=WEB_DIR), name="web")
    closing: threading.Event = app.state.closing

    @app.get("/", include_in_schema=False)
    def page() -> FileResponse:
        return FileResponse(WEB_DIR / "index.html", media_type="text/html")

    def status_doc() -> dict:
        recv = receiver_status()
        return {"books": store.snapshot(), "reasons": store.reasons(), "receiver": recv["state"],
                "receiver_error": recv.get("last_error"), "store": store.store_status(recv["state"] == "alive")[1],
                "view": feed.stats() if feed is not None else None, "stale_after_s": settings.stale_after_s}

    @app.get("/v1/view/status", summary="counts (with rejections and refusals by reason), receiver, store and the "
                                        "live view's feed, as the page shows them")
    def view_status() -> dict:
        return status_doc()

    @app.get("/v1/view/diagnostics", summary="the live view's newest explained frame: spectrum with every line "
                                             "marked, J(L) with chosen peak and runner-up, the seed's candidate "
                                             "matrix (mtcw explain's JSON)",
             responses={404: {"description": "none yet (the feed is off, or starts now: ask again)",
                              "content": {"application/json": {"schema": {
                                  "type": "object", "properties": {"detail": {"type": "string"}},
                                  "required": ["detail"]}}}}})
    def diagnostics() -> Response:
        if feed is None:
            raise HTTPException(404, "the live view's feed is off (view_rate_hz = 0, or no receiver)")
        feed.want()
        got = feed.latest()
        if got is None:
            raise HTTPException(404, f"no frame explained yet (the feed subscribes to {settings.monitor_endpoint} "
                                     f"while asked; ask again)")
        return Response(got[1], media_type="application/json")

    @app.get("/v1/points/stream", include_in_schema=False)
    async def stream(request: Request,
                     source: Optional[str] = Query(None, min_length=1, max_length=200),
                     after: Optional[int] = Query(None, ge=0, le=INT64_MAX),
                     tail: int = Query(0, ge=0, le=10_000),
                     diagnostics: Optional[str] = Query(None, pattern=_FLAG_PATTERN),
                     status: Optional[str] = Query(None, pattern=_FLAG_PATTERN)) -> StreamingResponse:
        last = request.headers.get("last-event-id")
        if last is not None:
            try:
                after = int(last.strip())
                if not 0 <= after <= INT64_MAX:
                    raise ValueError
            except ValueError:
                raise HTTPException(422, f"Last-Event-ID: {last[:40]!r} is not a cursor (an integer "
                                         f"0..{INT64_MAX}, the id of an event of this stream)") from None
        want_diag = _flag(diagnostics, "diagnostics") and feed is not None
        want_status = _flag(status, "status")
        cursor = after if after is not None else await run_in_threadpool(_last_ids, store.db, tail)

        async def events():
            nonlocal cursor
            metrics.view_clients.inc()
            if want_diag:
                feed.subscribe()
            try:
                yield b"retry: 1000\n\n"
                seen_commit, sent_diag, sent_status, sent_any = -1, 0, 0.0, time.monotonic()
                while not closing.is_set():
                    now = time.monotonic()
                    if store.commits != seen_commit:
                        seen_commit = store.commits
                        more = True
                        while more:
                            docs, more, nxt = await run_in_threadpool(store.db.points, -1, STREAM_BATCH, source,
                                                                      cursor)
                            if not docs:
                                break
                            cursor = nxt
                            yield _sse("points", b'{"points":[%s]}' % b",".join(docs), cursor)
                            sent_any = now
                    if want_diag:
                        got = feed.latest()
                        if got is not None and got[0] > sent_diag:
                            if sent_diag:
                                metrics.view_skipped.inc(got[0] - sent_diag - 1)
                            sent_diag = got[0]
                            yield _sse("diagnostics", b'{"version":%d,"explain":%s}' % got)
                            sent_any = now
                    if want_status and now - sent_status >= 1.0:
                        sent_status = now
                        yield _sse("status", json.dumps(status_doc(), default=str).encode())
                        sent_any = now
                    if now - sent_any >= STREAM_KEEPALIVE_S:
                        sent_any = now
                        yield b": keep-alive\n\n"
                    await asyncio.sleep(STREAM_POLL_S)
            finally:
                metrics.view_clients.dec()
                if want_diag:
                    feed.unsubscribe()

        return StreamingResponse(events(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


def create_app(settings: ApiSettings | None = None, start_receiver: bool = True,
               clock_ns: Callable[[], int] = time.time_ns,
               on_receiver_death: Optional[Callable[[str], None]] = None) -> FastAPI:
    """The FastAPI app; with ``start_receiver`` the points thread runs for the app's lifetime.

    The store is opened here (raises :class:`~services.history.StoreError` naming
    ``store_path``) and closed when the app stops. Once the receiver has bound, its endpoint (and
    ``app.state.http_url``, when :func:`serve` set it) are written to ``settings.endpoints_file``.
    ``clock_ns`` is the store's wall clock; ``on_receiver_death`` is called (from the receiver
    thread) if it dies.
    """
    settings = settings or ApiSettings()
    metrics = Metrics()
    store = PointStore(settings, metrics, clock_ns)

    # the points socket is bound now, so that an endpoint that cannot be bound (or CURVE keys that
    # cannot be read) is an error of create_app naming the field, not a failed server start-up
    try:
        early = PointReceiver(store, settings, on_death=on_receiver_death) if start_receiver else None
    except Exception:
        store.close()
        raise

    feed = None
    if start_receiver and settings.view_rate_hz > 0:
        m = metrics

        def explained(dt: float) -> None:
            m.view_explain.observe(dt)

        feed = ViewFeed(settings, settings.view_rate_hz, settings.view_profile, on_explained=explained)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        recv = None
        if feed is not None:
            feed.start()
        try:
            if early is not None:
                log_settings("api", settings)
                recv = app.state.receiver = early
                recv.start()
                http_url = getattr(app.state, "http_url", None)
                report_endpoints(settings.endpoints_file, {"points_endpoint": recv.endpoint,
                                                           **({"http_url": http_url} if http_url else {})})
                log.info("api: points on %s (PULL); HTTP on %s; store %s", recv.endpoint,
                         http_url or f"{settings.host}:{settings.port}", store.db.path if store.db.durable
                         else ":memory: (nothing kept across restarts)")
            yield
        finally:
            app.state.closing.set()
            if feed is not None:
                feed.stop()
                feed.join(timeout=5)
            if recv is not None:
                recv.stop()
                recv.join(timeout=5)
            # the store is the app's while its receiver runs; without one (tests, an ASGI
            # harness that enters and leaves the lifespan per request) it stays open with the app
            if recv is not None and not recv.is_alive():
                store.close()

    app = FastAPI(title="mtcw", version="1", lifespan=lifespan,
                  description="Range and velocity from a multi-tone CW lidar (PB-MTCW), live.")
    app.state.store = store
    app.state.settings = settings
    app.state.receiver = None
    app.state.feed = feed
    app.state.closing = threading.Event()  # set when the server stops: open streams end

    def receiver_status() -> dict:
        recv = app.state.receiver
        return recv.status() if recv is not None else {"state": "not_started"}

    _add_view(app, store, settings, metrics, feed, receiver_status)
    view_shown: dict[str, int] = {}

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

    @app.get("/v1/points", summary="history, oldest first (release order), paged by a cursor",
             responses={200: {"content": {"application/json": {"example": {"points": [], "count": 0, "more": False,
                                                                           "next": None}}}}})
    def points(since_seq: int = Query(-1, ge=-1, le=INT64_MAX, description="only points with seq greater than this"),
               limit: int = Query(100, ge=1, le=10_000),
               source: Optional[str] = Query(None, min_length=1, max_length=200),
               after: int = Query(0, ge=0, le=INT64_MAX, description="a cursor: the `next` of an earlier answer "
                                                                     "(only points released after it)")) -> Response:
        docs, more, nxt = store.db.points(since_seq, limit, source, after)
        body = b'{"points":[%s],"count":%d,"more":%s,"next":%s}' % (
            b",".join(docs), len(docs), b"true" if more else b"false", b"null" if nxt is None else b"%d" % nxt)
        return Response(body, media_type="application/json")

    @app.get("/livez", summary="the process serves HTTP (always 200 while it does)")
    def livez() -> dict:
        return {"status": "alive", "uptime_s": time.monotonic() - store.started}

    @app.get("/healthz", summary="the points receiver's state and the counts (503 once the receiver died)",
             responses={503: {"description": "the points receiver has died (status receiver_dead)",
                              "content": {"application/json": {"schema": {"type": "object"}}}}})
    def healthz(response: Response) -> dict:
        recv = receiver_status()
        dead = recv["state"] == "dead"
        if dead:
            response.status_code = 503
        return {"status": "receiver_dead" if dead else "alive", "receiver": recv, **store.snapshot()}

    @app.get("/readyz", summary="receiver alive, store writable, a frame arrived recently (?verbose: each check)",
             responses={503: {"description": "not ready: the first failing check is the reason (receiver, store, "
                                             "frames)",
                              "content": {"application/json": {"schema": {"type": "object"}}}}})
    def readyz(response: Response, verbose: Optional[str] = Query(
            None, pattern=_FLAG_PATTERN, description="list every check (?verbose, =1, =true)")) -> dict:
        show = _flag(verbose, "verbose")
        snap = store.snapshot()
        recv = receiver_status()
        checks: dict[str, dict] = {}
        alive = recv["state"] in ("alive", "not_started")
        checks["receiver"] = {"ok": alive, "why": "points receiver " + (
            recv["state"] if alive else f"{recv['state']}: {recv.get('last_error')}")}
        ok, why = store.store_status(receiver_running=recv["state"] == "alive")
        checks["store"] = {"ok": ok, "why": why}
        age = snap["last_frame_age_s"]
        fresh = age is not None and age < settings.stale_after_s
        checks["frames"] = {"ok": fresh, "why": "no frame yet" if age is None else
                            f"last frame {age:.1f} s ago (stale after {settings.stale_after_s:g} s)"}
        failed = [c["why"] for c in checks.values() if not c["ok"]]
        if failed:
            response.status_code = 503
        out = {"status": "not_ready" if failed else "ready", "reason": failed[0] if failed else "ok",
               "receiver": recv, **snap}
        if show:
            out["checks"] = checks
        return out

    @app.get("/metrics", summary="Prometheus text format", response_class=Response)
    def prom() -> Response:
        last = store.last_arrival
        if last is not None:
            metrics.age.set(time.monotonic() - last)
        if feed is not None:  # the feed's own counts, brought up to date here
            for outcome in ("explained", "passed_over", "lost"):
                inc = feed.counts[outcome] - view_shown.get(outcome, 0)
                if inc > 0:
                    metrics.view_frames.labels(outcome).inc(inc)
                    view_shown[outcome] = feed.counts[outcome]
        return Response(generate_latest(metrics.registry), media_type=CONTENT_TYPE_LATEST)

    return app


def _streaming_server():
    import uvicorn

    class _Server(uvicorn.Server):
        """uvicorn's server that, on shutdown, first tells the open streams to end (uvicorn waits
        for every running response, and a stream never ends by itself)."""

        async def shutdown(self, sockets=None) -> None:
            app = self.config.app
            closing = getattr(getattr(app, "state", None), "closing", None)
            if closing is not None:
                closing.set()
            await super().shutdown(sockets)

    return _Server


def StreamingServer(config):  # noqa: N802 - a class made on first use (uvicorn is imported lazily)
    """A ``uvicorn.Server`` for this app: open ``/v1/points/stream`` responses end on shutdown."""
    return _streaming_server()(config)


def serve(settings: ApiSettings) -> None:
    """Run the API under uvicorn until SIGINT/SIGTERM (uvicorn's own graceful shutdown).

    The HTTP socket is bound here (``port`` 0 takes a free one), so that its URL can be
    reported with the points endpoint (``endpoints_file``). A store that cannot be opened ends
    the process with a message naming ``store_path``; a points receiver that dies stops the
    server and ends the process with status :data:`EXIT_RECEIVER_DEAD`, for its supervisor
    (docker's restart policy, ``mtcw run``) to start it again: history and books survive that.
    """
    import uvicorn

    from .history import StoreError

    server: Optional[uvicorn.Server] = None
    died: list[str] = []

    def receiver_died(why: str) -> None:
        died.append(why)
        log.error("api: the points receiver died (%s); stopping, exit status %d", why, EXIT_RECEIVER_DEAD)
        if server is not None:
            server.should_exit = True

    try:
        app = create_app(settings, on_receiver_death=receiver_died)
    except (StoreError, ValueError) as err:  # ValueError: SocketError, CurveKeyError (they name the field)
        raise SystemExit(f"error: settings: {err}" if not isinstance(err, StoreError) else f"error: {err}") from None
    # log_config=None: uvicorn's own loggers go through the process's handler (text or JSON lines)
    config = uvicorn.Config(app, host=settings.host, port=settings.port, log_level="warning", log_config=None)
    sock = config.bind_socket()
    host = f"[{settings.host}]" if ":" in settings.host else settings.host
    app.state.http_url = f"http://{host}:{sock.getsockname()[1]}"
    server = StreamingServer(config)
    server.run(sockets=[sock])
    if died:
        sys.exit(EXIT_RECEIVER_DEAD)
