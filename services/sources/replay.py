"""Source ``replay``: the frames of a SigMF recording, read from the file once."""

from __future__ import annotations

from typing import Iterator

from mtcw_core.frame import Frame
from mtcw_core.recording import read_recording

#: A looping replay keeps the frames it has read in memory up to this many bytes of samples, so
#: that each frame is read from the file once and then only sent (the publisher sends the array
#: itself, zero-copy). Reading a 1e6-sample frame from the page cache again on every loop cost
#: about 2 ms of the node's CPU per frame (issue 16); 1 GiB holds 256 such frames of float32.
#: Frames past the budget are read again on each loop, as before. A copy in memory rather than
#: a memory map: a recording cut while it is replayed then gives a clear error, not a SIGBUS.
CACHE_BYTES = 1 << 30


class ReplaySource:
    """Frames of a SigMF recording, in order, optionally looping.

    Each frame is read from the file once: with ``loop``, the frames read are kept (read-only,
    up to :data:`CACHE_BYTES` of samples) and replayed from memory on the following loops.

    Parameters
    ----------
    settings : AcquisitionSettings
        ``recording`` and ``loop``.
    cache_bytes : int, optional
        The memory budget (default :data:`CACHE_BYTES`; 0 reads every frame every time).
    """

    def __init__(self, settings, cache_bytes: int = CACHE_BYTES) -> None:
        assert settings.recording is not None, "replay needs a recording"
        self.rec = read_recording(settings.recording)
        self.loop = settings.loop
        if len(self.rec) == 0:
            raise ValueError(f"recording: {settings.recording} holds no frames")
        self.cache_bytes = cache_bytes if self.loop else 0  # played once: nothing to keep
        self._cache: list[Frame] = []
        self._cached_bytes = 0
        self.reads = 0  # frames read from the file (tests)

    def _frame(self, i: int) -> Frame:
        if i < len(self._cache):
            return self._cache[i]
        frame = self.rec.frame(i)
        self.reads += 1
        if i == len(self._cache) and self._cached_bytes + frame.samples.nbytes <= self.cache_bytes:
            frame.samples.setflags(write=False)  # sent zero-copy on every loop: nobody may write it
            self._cache.append(frame)
            self._cached_bytes += frame.samples.nbytes
        return frame

    @property
    def cached(self) -> int:
        """Frames held in memory."""
        return len(self._cache)

    def frames(self) -> Iterator[Frame]:
        while True:
            for i in range(len(self.rec)):
                yield self._frame(i)
            if not self.loop:
                return
