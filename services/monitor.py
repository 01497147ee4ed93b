"""Subscribers to the raw frame stream (PUB/SUB): the recorder behind ``mtcw record``.

A subscriber never slows the workers: when it falls behind, ZeroMQ drops frames at its
high-water mark, and the subscriber counts them from the ``seq`` gaps.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Callable, Iterator

import zmq

from mtcw_core.frame import Frame
from mtcw_core.recording import RecordingWriter

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
    """Write ``count`` frames (0 = until stopped) from the monitor stream to a SigMF recording."""
    sub = Subscriber(settings)
    n = 0
    try:
        with RecordingWriter(output, description="mtcw record: frames from the monitor stream") as w:
            for fr in sub.frames(stop):
                w.write(fr)
                n += 1
                if progress:
                    progress(n)
                if count and n >= count:
                    break
    finally:
        sub.close()
    return sub
