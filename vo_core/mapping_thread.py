"""Mapping on its own thread (DSO's multi-threaded mode: FullSystem::mappingLoop).

The tracking thread tracks each frame against the newest published reference and hands the frame to the direct
mapper: it traces the window's immature points in it and, when tracking asked for a keyframe, runs the window
optimization, marginalization and activation, and publishes the new reference (``DirectOdometry`` assigns it
whole, so that tracking picks it up at its next frame); it then hands the keyframe, as it stands, to the feature
mapper, a second ``MappingThread`` on which the feature map grows (FDMO Fig. 4). The compiled kernels release the
GIL (numba ``nogil``, OpenCV), so the threads overlap where the work is in them; the Python around them does not.

Two modes (``mapping.wait_for_keyframes``):
- offline (DSO's linearizeOperation, but with the feature mapping and the tracing beside tracking): no frame is
  tracked before the pending keyframe's new reference is out (``wait_reference``: right after the window
  optimization), every frame is traced, and the jobs run in the order they came (a frame's tracing, or the keyframe
  it asks for, after the keyframe before it is mapped whole), so both maps are the synchronous run's and so are the
  poses (but a keyframe's own: its result goes out with the tracked pose, before the window optimization refines
  it); what runs beside tracking is the tracing of the frames, a keyframe's marginalization and new candidates
  (while the next frames are tracked and accepted: what accepting reads, the frame's own tracking and the motion
  model, the mapper does not change after the reference is out), and the feature map's growth at each keyframe (a
  job of its own, carried out by the feature half's process);
- live (DSO's real-time mode): tracking never waits for a keyframe; while one is pending no other is asked for (a
  later frame becomes the keyframe once the mapper is free), and when frames queue up the mapper catches up (DSO's
  needToKetchupMapping): a frame that is not a keyframe is no longer traced while more than ``max_queued_frames``
  wait; the next frame it maps reports how many it left untraced (``mapping_behind``).

In both:
- whatever changes the maps outside a keyframe (a recovery, a restart, a new initialization, a start on probation)
  waits for the mapper to be idle (``wait_idle``) and then runs on the tracking thread, as in synchronous mode.

What a job reports (its events, timings, the scale watch's reading, a map snapshot) is collected on the tracking
thread (``take_finished``) and passed on with the next frame, so that sinks are only ever called from the tracking
thread. An exception in the mapper is raised again there.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from typing import Callable

from vo_core.events import Event, EventKind, FrameResult, MapSnapshot

# A job maps one frame into the given result (its own, not the frame's: that one has gone to the sinks) and returns
# the maps' snapshot when they changed.
Job = Callable[[FrameResult], MapSnapshot | None]


@dataclass
class MappedFrame:
    """What mapping one frame produced: its events, timings and readings, and the maps after it when they changed."""

    result: FrameResult
    snapshot: MapSnapshot | None


@dataclass
class _Queued:
    result: FrameResult
    job: Job
    keyframe: bool  # a direct keyframe: tracking waits for it before it asks for the next one
    may_skip: bool  # only traces: left out when the mapper catches up
    released: bool = False  # a keyframe whose tracking reference is out (``release_tracking``)


class MappingThread:
    def __init__(self, max_queued_frames: int | None, name: str):
        """``max_queued_frames``: None never leaves a frame untraced."""
        self.max_queued_frames = max_queued_frames
        self._queue: deque[_Queued] = deque()
        self._finished: list[MappedFrame] = []
        self._running: _Queued | None = None  # the job being mapped
        self._untraced = 0  # frames left untraced while catching up, not yet reported
        self._error: BaseException | None = None
        self._stopping = False
        self._condition = threading.Condition()
        self._thread = threading.Thread(target=self._loop, name=f"fdmo-{name}", daemon=True)
        self._thread.start()

    @property
    def keyframe_pending(self) -> bool:
        """Whether a keyframe is queued or being mapped (tracking asks for no other meanwhile)."""
        with self._condition:
            return self._keyframe_queued()

    def _keyframe_queued(self, until_released: bool = False) -> bool:
        """Whether a keyframe is queued or being mapped; ``until_released``: or being mapped and its tracking reference
        not out yet."""
        running = self._running
        mapping = running is not None and running.keyframe and not (until_released and running.released)
        return mapping or any(q.keyframe for q in self._queue)

    def submit(self, frame_index: int, timestamp: float, job: Job, keyframe: bool = False,
               may_skip: bool = False) -> None:
        with self._condition:
            self._raise_error()
            result = FrameResult(frame_index, timestamp, None, tracked=True)
            self._queue.append(_Queued(result, job, keyframe, may_skip))
            self._condition.notify_all()

    def wait_idle(self) -> None:
        """Until every queued job is done: the maps are then the tracking thread's to change."""
        self._wait(lambda: not self._queue and self._running is None)

    def wait_reference(self) -> None:
        """Until the pending keyframe's tracking reference is published; the mapper may still be mapping the rest of
        it (marginalization, new immature points) while the next frame is tracked."""
        self._wait(lambda: not self._keyframe_queued(until_released=True))

    def release_tracking(self) -> None:
        """The running keyframe's tracking reference is published (DSO too hands its tracker the new keyframe right
        after the window optimization, before the marginalization). Called from elsewhere (a reference made on the
        tracking thread, while the mapper is idle), it does nothing."""
        with self._condition:
            if self._running is not None and threading.current_thread() is self._thread:
                self._running.released = True
                self._condition.notify_all()

    def _wait(self, done: Callable[[], bool]) -> None:
        with self._condition:
            self._condition.wait_for(lambda: self._error is not None or done())
            self._raise_error()

    def take_finished(self) -> list[MappedFrame]:
        """The frames mapped since the last call, oldest first."""
        with self._condition:
            self._raise_error()
            finished, self._finished = self._finished, []
            return finished

    def close(self) -> None:
        """Map what is queued, then stop the thread (the run ends, or was interrupted: the files stay complete)."""
        with self._condition:
            self._stopping = True
            self._condition.notify_all()
        self._thread.join()

    # ------------------------------------------------------------------------------------ the mapper's side

    def _loop(self) -> None:
        while True:
            with self._condition:
                self._condition.wait_for(lambda: self._queue or self._stopping)
                if not self._queue:
                    return
                queued = self._queue.popleft()
                if queued.may_skip and self.max_queued_frames is not None and \
                        len(self._queue) > self.max_queued_frames:
                    self._untraced += 1
                    self._condition.notify_all()
                    continue
                self._running = queued
                if self._untraced:
                    self._report_untraced(queued.result)
            try:
                snapshot = queued.job(queued.result)
            except BaseException as error:  # raised again on the tracking thread
                with self._condition:
                    self._error, self._running = error, None
                    self._queue.clear()
                    self._condition.notify_all()
                return
            with self._condition:
                self._finished.append(MappedFrame(queued.result, snapshot))
                self._running = None
                self._condition.notify_all()

    def _report_untraced(self, result: FrameResult) -> None:
        details = {"untraced_frames": self._untraced, "queued_frames": len(self._queue)}
        result.events.append(Event(EventKind.MAPPING_BEHIND, result.frame_index, float(result.timestamp), details))
        self._untraced = 0

    def _raise_error(self) -> None:
        if self._error is not None:
            error, self._error = self._error, None
            raise error
