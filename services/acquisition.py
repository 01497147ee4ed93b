"""The acquisition node: a frame source and a publisher.

Sources yield :class:`~mtcw_core.frame.Frame` objects; the node stamps their identity
(``source``, ``seq`` +1 per frame, the trigger time ``t_ns``, ``run``), the one place that does
on the wire, then sends each frame on a PUSH socket (workers share
them) and a PUB socket (recorders and monitors, never slowing the workers). When no worker can
take a frame the drop policy decides: ``drop`` counts it and goes on (the consumer sees the seq
gap), ``block`` waits. Sources live in :mod:`services.sources` (``sim``, ``replay``, ``scope``,
``scope-sim``); another digitizer plugs in as any class with a ``frames()`` iterator, named
``module:Class`` in the ``source`` setting. A source that fails (a scope's timeout, a broken
transfer) counts the failure by its reason (``mtcw_acquisition_errors_total{reason}``) and
retries by itself; the publisher's state (seq, run, ledger) goes on untouched. When a run ends (frame count reached, source
exhausted, or a clean stop) the node sends an end-of-run notice with the number of frames, so
that the consumer also counts frames lost after the last one it received.
"""

from __future__ import annotations

import collections
import importlib
import json
import logging
import secrets
import threading
import time
from pathlib import Path
from typing import Callable, Iterator, Optional, Protocol

import zmq

from mtcw_core.frame import Frame

from .auth import terminate
from .settings import AcquisitionSettings, log_settings
from .sockets import bound_endpoint, frames_push, monitor_pub, open_sockets, report_endpoints
from .sources import ReplaySource, SimulatorSource  # noqa: F401 -- kept importable from here
from .wire import encode_end, encode_frame, end_message

log = logging.getLogger("mtcw.acquisition")


class FrameSource(Protocol):
    """What the acquisition node needs from a source (simulator, recording, digitizer)."""

    def frames(self) -> Iterator[Frame]: ...


#: the built-in sources by name (:mod:`services.sources`); anything else is a ``module:Class`` plug-in
SOURCES = ("sim", "replay", "scope", "scope-sim")


def make_source(settings: AcquisitionSettings, stop: threading.Event | None = None,
                on_error: Callable[[str], None] | None = None,
                on_missed: Callable[[int], None] | None = None) -> FrameSource:
    """The frame source ``settings.source`` names.

    Parameters
    ----------
    settings : AcquisitionSettings
    stop : threading.Event, optional
        A clean stop; a scope source's retry waits end on it.
    on_error : callable, optional
        Called with the reason of each failed acquisition (scope sources;
        ``mtcw_acquisition_errors_total{reason}``).
    on_missed : callable, optional
        Called with the number of acquisitions the scope made that the node did not read.
    """
    if settings.source == "sim":
        return SimulatorSource(settings)
    if settings.source == "replay":
        if settings.recording is None:
            raise ValueError("recording: source 'replay' needs --recording")
        return ReplaySource(settings)
    if settings.source == "scope":
        from .sources.scope import ScopeSource

        return ScopeSource(settings, stop=stop, on_error=on_error, on_missed=on_missed)
    if settings.source == "scope-sim":
        from .sources.scope_sim import SimulatedScopeSource

        return SimulatedScopeSource(settings, stop=stop, on_error=on_error, on_missed=on_missed)
    if ":" in settings.source:
        mod, _, cls = settings.source.partition(":")
        try:
            return getattr(importlib.import_module(mod), cls)(settings)
        except (ImportError, AttributeError) as err:
            raise ValueError(f"source: cannot load plug-in {settings.source!r}: {err}") from None
    raise ValueError(f"source: {settings.source!r} is not {', '.join(SOURCES)} or module:Class")


class RunLedger:
    """How many frames the current run has stamped, kept in a small memory-mapped file that
    outlives the process: after a SIGKILL the next start of the node reads the killed run's
    count and sends the end-of-run notice it never sent, so that the frames it published after
    the last one that reached the API are counted as dropped, not lost.

    Updating costs a few microseconds per frame (a write into the mapping, no system call); the
    kernel keeps the page when the process dies. Two slots are written in turn, each a JSON
    object padded to :attr:`SLOT` bytes, so that a write torn by the kill leaves the other one
    readable: the reader takes the valid slot with the larger count.

    Parameters
    ----------
    path : Path
        The file (made, or taken over, by this run).
    """

    SLOT = 256

    def __init__(self, path: Path, pending: Optional[dict] = None) -> None:
        import mmap

        path = Path(path)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with open(path, "a+b") as fh:
                fh.truncate(3 * self.SLOT)
                self._map = mmap.mmap(fh.fileno(), 3 * self.SLOT)
        except (OSError, ValueError) as err:
            raise ValueError(f"state_file: cannot keep the run ledger in {path}: {err}") from None
        self._map[:] = b" " * (3 * self.SLOT)
        if pending is not None:  # an earlier run whose notice is still not delivered: kept for the next start
            self._map[2 * self.SLOT:] = json.dumps(pending).encode()[: self.SLOT].ljust(self.SLOT)

    def record(self, source: str, run: int, frames: int, ended: bool = False) -> None:
        """Run ``run`` of ``source`` has stamped ``frames`` frames (``ended``: its notice is sent)."""
        text = json.dumps({"source": source, "run": run, "frames": frames, "ended": ended}).encode()
        if len(text) >= self.SLOT:
            raise ValueError(f"state_file: source name too long for the ledger ({len(text)} bytes)")
        slot = (frames % 2) * self.SLOT
        self._map[slot:slot + self.SLOT] = text.ljust(self.SLOT)

    def close(self) -> None:
        self._map.close()

    @classmethod
    def read(cls, path: Path, include_ended: bool = False) -> list[dict]:
        """The runs ``path`` holds whose end-of-run notice was not sent (``source``, ``run``,
        ``frames``, ``ended``): the last run's state from slots 0 and 1 (the valid one with the
        larger count) and one carried-over run from slot 2; empty when there is none
        (``include_ended``: runs whose notice was sent too)."""
        try:
            raw = Path(path).read_bytes()
        except OSError:
            return []

        def parse(chunk: bytes) -> Optional[dict]:
            try:
                d = json.loads(chunk)
            except ValueError:
                return None
            ok = (isinstance(d, dict) and isinstance(d.get("source"), str) and isinstance(d.get("run"), int)
                  and isinstance(d.get("frames"), int) and d["frames"] >= 0)
            return d if ok else None

        best = None
        for d in (parse(raw[i:i + cls.SLOT]) for i in (0, cls.SLOT)):
            if d is not None and (best is None or (d["run"] == best["run"] and d["frames"] > best["frames"])):
                best = d
        carried = parse(raw[2 * cls.SLOT: 3 * cls.SLOT])
        return [d for d in (carried, best) if d is not None and (include_ended or not d.get("ended"))]


class Publisher:
    """Binds the PUSH (workers) and PUB (monitors) sockets, stamps each frame's identity and sends it.

    The publisher is the one place that stamps a frame's identity on the wire (see
    :mod:`mtcw_core.frame`): ``source`` (``source_name``), ``seq`` (+1 per frame, from 0),
    ``t_ns`` (its wall clock when it takes the frame, Unix ns) and ``run`` (random, per
    publisher). When no worker can take a frame the drop policy (the PUSH socket's ``SNDTIMEO``,
    :mod:`services.sockets`) decides: ``drop`` counts it and goes on, ``block`` waits.

    Parameters
    ----------
    settings : AcquisitionSettings
    ctx : zmq.Context, optional
        A context of the caller's, who must then terminate it (after :meth:`close`) before the
        process exits: frames still queued are sent from their arrays until then. By default
        the publisher makes its own and terminates it in :meth:`close`.
    clock_ns : callable, optional
        Wall clock for ``t_ns`` (``time.time_ns``); for tests.
    """

    def __init__(self, settings: AcquisitionSettings, ctx: zmq.Context | None = None,
                 clock_ns: Callable[[], int] = time.time_ns,
                 on_refused: Callable[[str], None] | None = None) -> None:
        self.settings = settings
        self._own_ctx = ctx is None
        self.ctx = zmq.Context() if ctx is None else ctx
        self.clock_ns = clock_ns
        self.peers_refused: collections.Counter[str] = collections.Counter()
        self._on_refused = on_refused
        self.push, self.pub = open_sockets(self.ctx, [frames_push(settings), monitor_pub(settings)], self._own_ctx,
                                           self._refused)
        # watch for workers from the moment of binding, so that none connects unseen before wait_for_worker
        self._monitor: zmq.Socket | None = self.push.get_monitor_socket(zmq.EVENT_HANDSHAKE_SUCCEEDED)
        self.run = secrets.randbits(63)  # tells this run's frames from a previous run's
        self.seq = 0
        self.published = 0
        self.dropped = 0
        # runs killed before their end-of-run notice: the file is left as it is until their notices
        # are handed over (or this run's first frame), so a stop or a kill before then loses nothing
        self.unfinished: list[dict] = RunLedger.read(settings.state_file) if settings.state_file else []
        self.ledger: Optional[RunLedger] = None

    def _refused(self, socket: str) -> None:
        """A peer with an unknown CURVE key was refused on ``socket`` (the ZAP handler's thread)."""
        self.peers_refused[socket] += 1
        if self._on_refused is not None:
            self._on_refused(socket)

    @property
    def frames_endpoint(self) -> str:
        """The bound endpoint of the PUSH socket (the port actually taken when bound to port 0)."""
        return bound_endpoint(self.push)

    @property
    def monitor_endpoint(self) -> str:
        """The bound endpoint of the PUB socket."""
        return bound_endpoint(self.pub)

    def wait_for_worker(self, timeout_s: float, count: int = 1, stop: threading.Event | None = None) -> bool:
        """Wait until ``count`` workers have connected to the PUSH socket (True), the timeout
        passes or ``stop`` is set (False)."""
        from zmq.utils.monitor import recv_monitor_message

        mon = self._monitor or self.push.get_monitor_socket(zmq.EVENT_HANDSHAKE_SUCCEEDED)
        self._monitor = None
        try:
            deadline = time.monotonic() + timeout_s
            seen = 0
            while (left := deadline - time.monotonic()) > 0 and not (stop is not None and stop.is_set()):
                if (mon.poll(int(min(left, 0.2) * 1000))
                        and recv_monitor_message(mon)["event"] == zmq.EVENT_HANDSHAKE_SUCCEEDED):
                    seen += 1
                    if seen >= count:
                        return True
            return False
        finally:
            self.push.disable_monitor()
            mon.close()

    def send(self, frame: Frame) -> bool:
        """Stamp and send one frame; returns False when it was dropped (no worker free).

        The samples are not copied: libzmq reads them from the frame's array, which pyzmq keeps
        alive until libzmq is done with it; the array must not be written to afterwards.
        """
        frame = frame.with_(source=self.settings.source_name, seq=self.seq, t_ns=self.clock_ns(), run=self.run)
        self.seq += 1
        if self.settings.state_file is not None:  # counted before it leaves: a kill now leaves it counted
            if self.ledger is None:
                self._open_ledger()
            self.ledger.record(self.settings.source_name, self.run, self.seq)
        parts = encode_frame(frame)
        # PUB never blocks: a slow subscriber loses frames and sees the seq gap
        self.pub.send_multipart(parts, copy=False)
        try:
            self.push.send_multipart(parts, copy=False)  # the socket's SNDTIMEO is the drop policy
        except zmq.Again:
            self.dropped += 1
            return False
        self.published += 1
        return True

    def finish_unfinished(self, timeout_s: float) -> int:
        """Send the end-of-run notices that killed earlier runs of this node never sent (their
        frame counts from the ledger); returns how many a worker took. A notice no worker took is
        carried over in the ledger, for the next start to send."""
        sent = 0
        carry = []
        for prev in self.unfinished:
            log.warning("acquisition: run %d of %r ended without its end-of-run notice (killed?) after %d frames; "
                        "sending it now", prev["run"], prev["source"], prev["frames"])
            if self._send_end(end_message(prev["source"], prev["run"], prev["frames"], self.clock_ns(), 0),
                              timeout_s):
                sent += 1
            else:
                carry.append(prev)
        self.unfinished = carry
        if self.settings.state_file is not None:
            self._open_ledger()
        return sent

    def _open_ledger(self) -> None:
        """Start this run's ledger, carrying over the one notice still undelivered (if several
        are, the others are logged as lost: their tails will not be counted)."""
        for lost in self.unfinished[1:]:
            log.error("acquisition: the end-of-run notice of run %d (%d frames) could not be delivered and is lost",
                      lost["run"], lost["frames"])
        self.ledger = RunLedger(self.settings.state_file, self.unfinished[0] if self.unfinished else None)
        if self.seq:
            self.ledger.record(self.settings.source_name, self.run, self.seq)
        self.unfinished = []

    def finish(self, timeout_s: float) -> bool:
        """Send the end-of-run notice to a worker (waiting up to ``timeout_s``); True if handed over.

        The PUSH socket then lingers up to ``timeout_s`` so that the notice and the frames still
        queued for workers are delivered rather than discarded on close.
        """
        ok = self._send_end(end_message(self.settings.source_name, self.run, self.seq, self.clock_ns(),
                                        self.dropped), timeout_s)
        if ok and self.ledger is not None:
            self.ledger.record(self.settings.source_name, self.run, self.seq, ended=True)
        return ok

    def _send_end(self, msg, timeout_s: float) -> bool:
        parts = encode_end(msg)
        ok = bool(self.push.poll(int(timeout_s * 1000), zmq.POLLOUT))
        if ok:
            try:
                self.push.send_multipart(parts, flags=zmq.NOBLOCK)
            except zmq.Again:  # the pipe filled between the poll and the send
                ok = False
        if ok:
            linger_ms = max(self.settings.linger_ms, int(timeout_s * 1000))
            self.push.setsockopt(zmq.LINGER, linger_ms)
            log.info("acquisition: end-of-run notice sent; frames socket lingers %d ms on close",
                     self.push.getsockopt(zmq.LINGER))
        else:
            log.warning("acquisition: no worker took the end-of-run notice within %.1f s", timeout_s)
        return ok

    def close(self) -> None:
        """Close the sockets and, if the publisher made its context, terminate it.

        Terminating waits until every queued message is sent or discarded: up to the frames
        socket's LINGER (:meth:`finish` raises it so that the end-of-run notice and the frames
        before it are delivered; otherwise 0, nothing waits). Only then is no buffer of a
        zero-copy frame still in libzmq's hands, so that the process may exit.
        """
        if self._monitor is not None:
            self.push.disable_monitor()
            self._monitor.close()
            self._monitor = None
        if self.ledger is not None:
            self.ledger.close()
            self.ledger = None
        linger_ms = self.push.getsockopt(zmq.LINGER) if not self.push.closed else 0
        self.push.close()
        self.pub.close()
        if self._own_ctx and not self.ctx.closed:
            t0 = time.monotonic()
            terminate(self.ctx)
            log.info("acquisition: queued messages sent or discarded in %.2f s (frames socket LINGER %d ms)",
                     time.monotonic() - t0, linger_ms)


def run_acquisition(settings: AcquisitionSettings, stop: threading.Event | None = None,
                    on_frame: Callable[[Publisher], None] | None = None) -> Publisher:
    """Publish frames until the source ends, ``settings.frames`` are sent, or ``stop`` is set.

    However the run ends (``stop`` included), the end-of-run notice is sent once a frame was,
    and the publisher is closed: its context is terminated, which waits (up to the LINGER that
    :meth:`Publisher.finish` sets) until the notice and the frames queued before it are
    delivered. The caller may then exit; no zero-copy buffer is left in libzmq's hands.

    Parameters
    ----------
    settings : AcquisitionSettings
    stop : threading.Event, optional
        Set by a clean stop (SIGINT/SIGTERM in ``mtcw acquire``).
    on_frame : callable, optional
        Called with the publisher after each frame (tests).

    Returns
    -------
    Publisher
        Closed; its counters (``seq``, ``published``, ``dropped``) tell what the run did.
    """
    stop = stop or threading.Event()
    log_settings("acquisition", settings)
    metrics = _exporter(settings.metrics_port, settings.metrics_host)
    source = make_source(settings, stop,
                         on_error=(lambda reason: metrics[3].labels(reason).inc()) if metrics else None,
                         on_missed=(lambda n: metrics[4].inc(n)) if metrics else None)
    pub = Publisher(settings, on_refused=(lambda sock: metrics[2].labels(sock).inc()) if metrics else None)
    try:
        report_endpoints(settings.endpoints_file, {"frames_endpoint": pub.frames_endpoint,
                                                   "monitor_endpoint": pub.monitor_endpoint})
        if settings.wait_for_worker_s > 0 and not pub.wait_for_worker(settings.wait_for_worker_s,
                                                                       settings.wait_for_workers, stop):
            if stop.is_set():
                return pub
            log.warning("acquisition: fewer than %d worker(s) after %.1f s; frames are dropped (and counted) while "
                        "no worker is free", settings.wait_for_workers, settings.wait_for_worker_s)
        pub.finish_unfinished(settings.end_timeout_s)
        period = 1.0 / settings.rate_hz if settings.rate_hz > 0 else 0.0
        next_t = time.monotonic()
        log.info("acquisition: publishing %s frames on %s (PUSH) and %s (PUB)", settings.source,
                 pub.frames_endpoint, pub.monitor_endpoint)
        for frame in source.frames():
            if stop.is_set():
                break
            if period:
                next_t += period
                delay = next_t - time.monotonic()
                if delay > 0 and stop.wait(delay):
                    break
                if delay < -period:  # fell behind: do not burst to catch up
                    next_t = time.monotonic()
            ok = pub.send(frame)
            if metrics:
                metrics[0].inc()
                if not ok:
                    metrics[1].inc()
            if on_frame:
                on_frame(pub)
            if settings.frames and pub.seq >= settings.frames:
                break
        if pub.seq:
            pub.finish(settings.end_timeout_s)
    finally:
        log.info("acquisition: stopped after %d frames (%d sent to workers, %d dropped: no worker free)",
                 pub.seq, pub.published, pub.dropped)
        pub.close()
        close_source = getattr(source, "close", None)
        if close_source is not None:  # a scope's VISA session, the simulated instrument's server
            close_source()
    return pub


def _exporter(port: int, host: str):
    if not port:
        return None
    from prometheus_client import CollectorRegistry, Counter, start_http_server

    reg = CollectorRegistry()
    c_pub = Counter("mtcw_frames_published_total", "frames the acquisition node published", registry=reg)
    c_drop = Counter("mtcw_acquisition_dropped_total", "frames dropped because no worker was free", registry=reg)
    c_refused = Counter("mtcw_peers_refused_total", "peers refused for an unknown CURVE key, by socket", ["socket"],
                        registry=reg)
    c_err = Counter("mtcw_acquisition_errors_total", "acquisitions that failed (no frame published), by reason",
                    ["reason"], registry=reg)
    c_missed = Counter("mtcw_acquisitions_missed_total", "acquisitions the scope made that the node did not read "
                       "(ACQuire:NUMACq?)", registry=reg)
    from .sources.scope import REASONS

    for reason in REASONS:  # every reason is exported from the start, at 0
        c_err.labels(reason)
    start_http_server(port, addr=host, registry=reg)
    return c_pub, c_drop, c_refused, c_err, c_missed
