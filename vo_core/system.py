"""The odometry: one object that takes frames in order and emits results and events to its sinks.

``Odometry.track`` is FDMO's per-frame flowchart (paper Fig. 2). It alone knows both halves and decides:
the direct half tracks the frame against its newest keyframe (a step that changes nothing), the system
tests the outcome, the direct half accepts the frame (immature points, keyframe, window optimization), and a
new direct keyframe grows the feature map. The KLT baseline is a pipeline of its own and only passes through.
"""

from __future__ import annotations

import time
from typing import Protocol

import numpy as np

from vo_core.config import Config
from vo_core.direct.odometry import DirectFrame, DirectOdometry, DirectTracking
from vo_core.errors import InputError
from vo_core.events import Event, EventBus, EventKind, FrameResult, MapSnapshot, Sink
from vo_core.geometry.camera import PinholeCamera
from vo_core.init.registry import initializer_factory

IMPLEMENTED_METHODS = ("klt", "direct")
DIRECT_METHODS = ("direct",)


class FrontEnd(Protocol):
    """A method that is a whole pipeline of its own. It never talks to sinks: it returns results, events
    included."""

    def process(self, frame) -> FrameResult: ...

    def map_snapshot(self) -> MapSnapshot: ...


def make_front_end(config: Config, camera: PinholeCamera) -> FrontEnd | None:
    """The pipeline of a method that runs on its own (the KLT baseline); None for the direct methods, whose
    per-frame flow is ``Odometry.track``'s. Methods that do not exist yet are refused, never faked."""
    if config.method == "klt":
        from vo_core.klt.pipeline import KltOdometry

        return KltOdometry(config.klt, camera, seed=config.seed)
    if config.method in DIRECT_METHODS:
        return None
    raise InputError(
        f"method '{config.method}' is not implemented yet (available: {', '.join(IMPLEMENTED_METHODS)})"
    )


class Odometry:
    def __init__(self, config: Config, camera: PinholeCamera, sinks: list[Sink] | None = None):
        self.config = config
        self.camera = camera
        self.bus = EventBus(sinks)
        self.front_end = make_front_end(config, camera)
        if self.front_end is None:
            make_initializer = initializer_factory(config.direct, config.init, camera, config.seed)
            self.direct = DirectOdometry(config.direct, camera, make_initializer, config.seed)

    def track(self, frame) -> FrameResult:
        """Process the next frame, then tell the sinks what happened."""
        result = self.front_end.process(frame) if self.front_end is not None else self._track_direct(frame)
        for event in result.events:
            self.bus.event(event)
        self.bus.frame(frame, result)
        if result.is_keyframe:
            self.bus.map(self.map_snapshot())
        return result

    def report(self, event: Event) -> None:
        """Tell the sinks about something that happened outside the odometry (a frame the loader skipped,
        frames the player dropped), on the same channel as the odometry's own events."""
        self.bus.event(event)

    def map_snapshot(self) -> MapSnapshot:
        if self.front_end is not None:
            return self.front_end.map_snapshot()
        return self.direct.map_snapshot()

    def close(self) -> None:
        self.bus.close()

    # ------------------------------------------------------------------------------------ FDMO Fig. 2

    def _track_direct(self, raw_frame) -> FrameResult:
        start = time.perf_counter()
        result = FrameResult(raw_frame.index, raw_frame.timestamp, None, tracked=False)
        frame = self.direct.prepare(raw_frame)
        result.timings_ms["pyramid"] = _ms_since(start)
        if not self.direct.initialized:
            self.direct.initialize(frame, result)
        else:
            tracking = self.direct.track(frame)
            result.timings_ms["track"] = tracking.ms
            if tracking.converged:
                self.direct.accept(frame, tracking, result)
            else:
                self._lost(frame, tracking, result)
        result.timings_ms["total"] = _ms_since(start)
        return result

    def _lost(self, frame: DirectFrame, tracking: DirectTracking, result: FrameResult) -> None:
        """No motion hypothesis converged (DSO's lost): report it and initialize again from this frame, the new
        map starting at the last good pose."""
        result.rmse_before = tracking.rmse_before
        details = {
            "reason": "no motion hypothesis converged",
            "reference_keyframe": tracking.reference.frame_index,
            "rmse_before": tracking.rmse_before if np.isfinite(tracking.rmse_before) else None,
        }
        result.events.append(_event(EventKind.TRACKING_FAILED, frame, details))
        origin = self.direct.last_pose.copy()
        result.events.append(_event(EventKind.REINITIALIZATION, frame, {"origin_from_frame_pose": origin.tolist()}))
        self.direct.reinitialize(origin)
        self.direct.initialize(frame, result)


def _ms_since(start: float) -> float:
    return (time.perf_counter() - start) * 1000.0


def _event(kind: EventKind, frame, details: dict) -> Event:
    return Event(kind, frame.index, float(frame.timestamp), details)
