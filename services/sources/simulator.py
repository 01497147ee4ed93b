"""Source ``sim``: frames from the physics simulator for a scene."""

from __future__ import annotations

import logging
from typing import Iterator

from mtcw_core.frame import Frame
from mtcw_core.scene import SceneError, load_scene
from mtcw_core.simulate import Simulator

log = logging.getLogger("mtcw.acquisition")


class SimulatorSource:
    """Frames from the physics simulator for a scene; targets move from frame to frame.

    The stream goes on beyond the scene's own ``frames.count``; where an approaching target
    reaches the sensor (its echo delay would fall below 0) the scene can go no further and the
    run ends there, logged (the node then sends its end-of-run notice: nothing is lost uncounted).
    """

    def __init__(self, settings) -> None:
        self.scene = load_scene(settings.scene)
        self.sim = Simulator(self.scene, settings.seed)

    def frames(self) -> Iterator[Frame]:
        while True:
            try:
                frame = self.sim.next_frame()
            except SceneError as err:
                log.error("acquisition: the scene ends the run: %s", err)
                return
            yield frame
