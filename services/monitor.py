"""Subscribers to the raw frame stream (PUB/SUB): the recorder behind ``mtcw record``, and the
live view's feed of spectra and cost curves (:class:`ViewFeed`).

A subscriber never slows the workers: when it falls behind, ZeroMQ drops frames at its
high-water mark, and the subscriber counts them from the ``seq`` gaps. The recorder skips and
counts (``refused``) a frame its recording cannot hold (one unlike the recording's first frame,
fields the SigMF reader would refuse) and goes on; its recording stays readable if it is killed
(:class:`~mtcw_core.recording.RecordingWriter` keeps the metadata current).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path
from typing import Callable, Iterator

import zmq

from mtcw_core.frame import Frame
from mtcw_core.recording import RecordingError, RecordingWriter

from .ordering import GapCounter
from .settings import TransportSettings
from .sockets import monitor_sub, open_socket
from .wire import FRAME_TOPIC, WireError, decode_frame, decode_header

log = logging.getLogger("mtcw.monitor")


class Subscriber:
    """Connects to the monitor endpoint and yields decoded frames, counting gaps and bad messages."""

    def __init__(self, settings: TransportSettings, ctx: zmq.Context | None = None, rcvhwm: int | None = None) -> None:
        self.ctx = ctx or zmq.Context.instance()
        self.sock = open_socket(self.ctx, monitor_sub(settings, rcvhwm, FRAME_TOPIC))
        self.gaps = GapCounter()
        self.malformed = 0
        #: frames decoded but refused by the consumer (the recorder: frames its recording cannot hold)
        self.refused = 0

    def frames(self, stop: threading.Event, timeout_ms: int = 200) -> Iterator[Frame]:
        poller = zmq.Poller()
        poller.register(self.sock, zmq.POLLIN)
        while not stop.is_set():
            if not poller.poll(timeout_ms):
                continue
            parts = self.sock.recv_multipart(copy=False)
            try:
                fr = decode_frame(parts)
            except WireError as err:
                self.malformed += 1
                log.warning("monitor: malformed frame message: %s", err)
                continue
            gap = self.gaps.see(fr.source, fr.seq)
            if gap:
                log.warning("monitor: %d frame(s) lost before seq %d (subscriber too slow)", gap, fr.seq)
            yield fr

    def close(self) -> None:
        self.sock.close()


def record(settings: TransportSettings, output: Path, count: int, stop: threading.Event,
           progress: Callable[[int], None] | None = None) -> Subscriber:
    """Write ``count`` frames (0 = until stopped) from the monitor stream to a SigMF recording.

    A frame the recording refuses (:class:`~mtcw_core.recording.RecordingError`) is logged,
    counted in ``refused`` of the returned subscriber, and skipped; it does not count towards
    ``count``.
    """
    sub = Subscriber(settings)
    n = 0
    try:
        with RecordingWriter(output, description="mtcw record: frames from the monitor stream") as w:
            for fr in sub.frames(stop):
                try:
                    w.write(fr)
                except RecordingError as err:
                    sub.refused += 1
                    if sub.refused <= 10 or sub.refused % 1000 == 0:  # the first ones, then a reminder
                        log.warning("record: frame refused (%d so far): %s", sub.refused, err)
                    continue
                n += 1
                if progress:
                    progress(n)
                if count and n >= count:
                    break
    finally:
        sub.close()
    return sub


class ViewFeed(threading.Thread):
    """Spectra and cost curves for the live view (``mtcw_core.explain``), from the monitor stream.

    Never slows the pipeline: it is one more subscriber of the acquisition node's PUB socket,
    which drops frames for a slow subscriber rather than wait (its queue holds ``rcvhwm``
    frames). It is connected only while a page wants diagnostics (and ``idle_s`` after the last
    one left); it takes every frame that arrives, keeps the newest, and explains one at most every
    ``1/rate_hz`` seconds, only the newest: the frames passed over are counted (``passed_over``),
    and so are the frames ZeroMQ dropped before they reached it (``lost``, from the seq gaps).
    Between explanations it unsubscribes, so that the acquisition node (which filters for its
    subscribers) sends it no frame until the next one is due: an open page costs the node and
    the API a few frames a second, not every frame (a 1e6-sample frame is 4 MB through the
    kernel twice); the frames already on their way when it unsubscribed arrive and are passed
    over.
    Each explanation replaces the previous one (:meth:`latest`): a page that takes them slower
    than they come gets the newest and skips the rest (the API counts those).

    Parameters
    ----------
    settings : TransportSettings
        ``monitor_endpoint`` and the CurveZMQ keys.
    rate_hz : float
        Explanations per second at most.
    profile : str
        Chain profile of the explanations.
    idle_s : float
        Stay connected this long after the last subscriber left.
    on_explained : callable(seconds), optional
        Called with the time each explanation took (the API's histogram).
    """

    def __init__(self, settings: TransportSettings, rate_hz: float = 1.0, profile: str = "balanced",
                 idle_s: float = 5.0, rcvhwm: int = 2, ctx: zmq.Context | None = None,
                 on_explained: Callable[[float], None] | None = None) -> None:
        super().__init__(name="view-feed", daemon=True)
        self.settings = settings
        self.period_s = 1.0 / rate_hz
        self.profile = profile
        self.idle_s = idle_s
        self.rcvhwm = rcvhwm
        self.ctx = ctx or zmq.Context.instance()
        self.on_explained = on_explained
        self.stop_event = threading.Event()
        self._lock = threading.Lock()
        self._subscribers = 0
        self._wanted_until = 0.0  # monotonic
        self._latest: tuple[int, bytes] | None = None  # (version, JSON)
        self.counts = {"received": 0, "explained": 0, "passed_over": 0, "lost": 0, "malformed": 0, "errors": 0}
        self.connected = False

    # -- the HTTP side -------------------------------------------------------------------------
    def subscribe(self) -> None:
        with self._lock:
            self._subscribers += 1

    def unsubscribe(self) -> None:
        with self._lock:
            self._subscribers -= 1
            self._wanted_until = time.monotonic() + self.idle_s

    def want(self) -> None:
        """A one-off request (``GET /v1/view/diagnostics``): stay connected for ``idle_s``."""
        with self._lock:
            self._wanted_until = max(self._wanted_until, time.monotonic() + self.idle_s)

    def latest(self) -> tuple[int, bytes] | None:
        """The newest explanation as (version, JSON bytes); versions count up from 1."""
        return self._latest

    def subscribers(self) -> int:
        return self._subscribers

    def stats(self) -> dict:
        return {**self.counts, "connected": self.connected, "subscribers": self._subscribers,
                "rate_hz": 1.0 / self.period_s, "profile": self.profile}

    def stop(self) -> None:
        self.stop_event.set()

    # -- the thread ----------------------------------------------------------------------------
    def _wanted(self) -> bool:
        with self._lock:
            return self._subscribers > 0 or time.monotonic() < self._wanted_until

    def _explain(self, parts) -> None:
        from mtcw_core.explain import explain_frame  # the chain: imported when a page first asks

        try:
            fr = decode_frame(parts)
        except WireError as err:
            self.counts["malformed"] += 1
            log.warning("view: malformed frame message: %s", err)
            return
        t0 = time.perf_counter()
        try:
            d = explain_frame(fr, self.profile)
            body = json.dumps(d, allow_nan=False).encode()
        except Exception:  # a chain bug must not stop the view; the workers are not affected
            self.counts["errors"] += 1
            log.exception("view: explain failed on seq %d", fr.seq)
            return
        dt = time.perf_counter() - t0
        version = (self._latest[0] if self._latest else 0) + 1
        self._latest = (version, body)
        self.counts["explained"] += 1
        if self.on_explained:
            self.on_explained(dt)

    def run(self) -> None:
        sub: Subscriber | None = None
        gaps = GapCounter()
        next_due = 0.0
        listening = False
        try:
            while not self.stop_event.is_set():
                if not self._wanted():
                    if sub is not None:
                        sub.close()
                        sub, self.connected = None, False
                    self.stop_event.wait(0.2)
                    continue
                if sub is None:
                    sub = Subscriber(self.settings, self.ctx, rcvhwm=self.rcvhwm)
                    gaps, self.connected, listening = GapCounter(), True, True  # frames before connecting are not lost
                now = time.monotonic()
                if not listening and now >= next_due:  # an explanation is due: frames again
                    while sub.sock.poll(0):  # frames still on their way from before: passed over
                        sub.sock.recv_multipart(copy=False)
                        self.counts["received"] += 1
                        self.counts["passed_over"] += 1
                    sub.sock.setsockopt(zmq.SUBSCRIBE, FRAME_TOPIC)
                    gaps, listening = GapCounter(), True  # frames while unsubscribed were not lost
                wait_ms = 100 if listening else int(1000 * min(max(next_due - now, 0.0), 0.1)) + 1
                if not sub.sock.poll(wait_ms):
                    continue
                newest = None
                while True:  # take what is queued; only the newest may be explained
                    try:
                        parts = sub.sock.recv_multipart(zmq.NOBLOCK, copy=False)
                    except zmq.Again:
                        break
                    self.counts["received"] += 1
                    if newest is not None:
                        self.counts["passed_over"] += 1
                    newest = parts
                    try:
                        hdr = decode_header(parts[1]) if len(parts) > 1 else None
                    except WireError:
                        hdr = None
                    if hdr is not None:
                        self.counts["lost"] += gaps.see(hdr.source, hdr.seq)
                now = time.monotonic()
                if newest is None:
                    continue
                if now < next_due:
                    self.counts["passed_over"] += 1
                    continue
                next_due = now + self.period_s
                if listening:  # the publisher filters: no frame is sent here until the next one is due
                    sub.sock.setsockopt(zmq.UNSUBSCRIBE, FRAME_TOPIC)
                    listening = False
                self._explain(newest)
        except Exception:
            log.exception("view: the feed stopped")
        finally:
            if sub is not None:
                sub.close()
            self.connected = False
