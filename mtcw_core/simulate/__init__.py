"""Physics simulator of an MTCW lidar bench (fields, square-law detection, digitizer)."""

from .engine import Simulator, simulate_frame

__all__ = ["Simulator", "simulate_frame"]
