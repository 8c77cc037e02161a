"""The odometry: one object that takes frames in order and emits results and events to its sinks.

``Odometry.track`` is the per-frame flow of the system. It hands the frame to the front end of the chosen
method and fans what comes back out to the sinks; the FDMO flowchart (paper Fig. 2: direct tracking,
divergence test, feature-based recovery, keyframe decision) will live here once both halves exist.
"""

from __future__ import annotations

from typing import Protocol

from vo_core.config import Config
from vo_core.errors import InputError
from vo_core.events import EventBus, FrameResult, MapSnapshot, Sink
from vo_core.geometry.camera import PinholeCamera

IMPLEMENTED_METHODS = ("klt", "direct")


class FrontEnd(Protocol):
    """One method's per-frame pipeline. It never talks to sinks: it returns results, events included."""

    def process(self, frame) -> FrameResult: ...

    def map_snapshot(self) -> MapSnapshot: ...


def make_front_end(config: Config, camera: PinholeCamera) -> FrontEnd:
    """The front end of ``config.method``; methods that do not exist yet are refused, never faked."""
    if config.method == "klt":
        from vo_core.klt.pipeline import KltOdometry

        return KltOdometry(config.klt, camera, seed=config.seed)
    if config.method == "direct":
        from vo_core.direct.odometry import DirectOdometry

        return DirectOdometry(config.direct, config.init, camera, seed=config.seed)
    raise InputError(
        f"method '{config.method}' is not implemented yet (available: {', '.join(IMPLEMENTED_METHODS)})"
    )


class Odometry:
    def __init__(self, config: Config, camera: PinholeCamera, sinks: list[Sink] | None = None):
        self.config = config
        self.camera = camera
        self.bus = EventBus(sinks)
        self.front_end = make_front_end(config, camera)

    def track(self, frame) -> FrameResult:
        """Process the next frame: track it, then tell the sinks what happened."""
        result = self.front_end.process(frame)
        for event in result.events:
            self.bus.event(event)
        self.bus.frame(frame, result)
        if result.is_keyframe:
            self.bus.map(self.front_end.map_snapshot())
        return result

    def close(self) -> None:
        self.bus.close()
