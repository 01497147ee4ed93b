"""Source ``sim``: frames from the physics simulator for a scene."""

from __future__ import annotations

from typing import Iterator

from mtcw_core.frame import Frame
from mtcw_core.scene import load_scene
from mtcw_core.simulate import Simulator


class SimulatorSource:
    """Frames from the physics simulator for a scene; targets move from frame to frame."""

    def __init__(self, settings) -> None:
        self.scene = load_scene(settings.scene)
        self.sim = Simulator(self.scene, settings.seed)

    def frames(self) -> Iterator[Frame]:
        while True:
            yield self.sim.next_frame()
