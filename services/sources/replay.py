"""Source ``replay``: the frames of a SigMF recording."""

from __future__ import annotations

from typing import Iterator

from mtcw_core.frame import Frame
from mtcw_core.recording import read_recording


class ReplaySource:
    """Frames of a SigMF recording, in order, optionally looping."""

    def __init__(self, settings) -> None:
        assert settings.recording is not None, "replay needs a recording"
        self.rec = read_recording(settings.recording)
        self.loop = settings.loop
        if len(self.rec) == 0:
            raise ValueError(f"recording: {settings.recording} holds no frames")

    def frames(self) -> Iterator[Frame]:
        while True:
            yield from self.rec
            if not self.loop:
                return
