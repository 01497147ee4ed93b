"""Subscribers to the raw frame stream (PUB/SUB): the recorder behind ``mtcw record``.

A subscriber never slows the workers: when it falls behind, ZeroMQ drops frames at its
high-water mark, and the subscriber counts them from the ``seq`` gaps. The recorder skips and
counts (``refused``) a frame its recording cannot hold (one unlike the recording's first frame,
fields the SigMF reader would refuse) and goes on; its recording stays readable if it is killed
(:class:`~mtcw_core.recording.RecordingWriter` keeps the metadata current).
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Callable, Iterator

import zmq

from mtcw_core.frame import Frame
from mtcw_core.recording import RecordingError, RecordingWriter

from .ordering import GapCounter
from .settings import TransportSettings
from .sockets import monitor_sub, open_socket
from .wire import FRAME_TOPIC, WireError, decode_frame

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
