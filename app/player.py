"""Plays a sequence's frames in order: pacing, pause and step, scripted and live frame drops, restart, stop.

The tracking thread iterates the player; a viewer (the viser page) calls its controls from other threads.
Every control only changes state under a lock and takes effect when the next frame is about to be handed
out, so the odometry always sees a clean sequence of frames, some of which are simply missing.

Frame drops are the experiment of FDMO section 5.3.2: frames ``index .. index+count-1`` are read but never
given to the odometry, which then sees a large baseline between two consecutive frames. A scripted drop
(``--drop FRAME:COUNT``) is queued through ``drop_next`` when the player reaches FRAME, exactly like a click
on the page's "drop" button, so experiments and the browser do the same thing.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

from vo_core.events import Event, EventKind

# Waits wake at least this often so that Ctrl-C (KeyboardInterrupt) is handled promptly in the main thread.
WAIT_SLICE_S = 0.2


@dataclass
class _DropRequest:
    count: int
    source: str  # "script" (--drop) or "live" (a viewer)


class Player:
    """Frames of ``sequence`` in order, with ``drops`` as ``(frame_index, count)`` pairs.

    ``frame_index`` is ``Frame.index``, the position in the original sequence (stable under --start/--end).
    Iterate with ``for frame in player`` or ``player.play(on_drop=callback)``; the callback receives one
    FRAMES_DROPPED event per drop request, on the iterating thread, before the next frame is handed out.
    A pass ends at the end of the sequence, on ``stop()``, or on ``request_restart()`` (then the caller
    starts over: ``wait_for_restart()`` returns True and the next ``play()`` begins at the first frame).
    """

    def __init__(self, sequence: Iterable[Any], drops: Iterable[tuple[int, int]] = ()):
        self.sequence = sequence
        self.drops = _validated_drops(drops)
        self._condition = threading.Condition()
        self._paused = False
        self._steps = 0  # frames allowed through while paused
        self._speed = 0.0
        self._drop_requests: deque[_DropRequest] = deque()
        self._restart_requested = False
        self._stopped = False
        self._interrupted = False
        self._finished = False
        self._pace_anchor: tuple[float, float] | None = None  # (wall clock, dataset timestamp)

    # ------------------------------------------------------------------------------------ controls

    @property
    def paused(self) -> bool:
        return self._paused

    @property
    def finished(self) -> bool:
        """True once a pass has reached the end of the sequence (until a restart)."""
        return self._finished

    @property
    def stopped(self) -> bool:
        return self._stopped

    @property
    def interrupted(self) -> bool:
        """True once ``interrupt()`` was called (a stop signal)."""
        return self._interrupted

    @property
    def restart_requested(self) -> bool:
        return self._restart_requested

    @property
    def speed(self) -> float:
        """Playback rate as a multiple of the dataset's frame rate; 0 means as fast as possible."""
        return self._speed

    @speed.setter
    def speed(self, value: float) -> None:
        value = float(value)
        if not value >= 0.0:
            raise ValueError(f"speed must be >= 0 (0 = as fast as possible), got {value}")
        self._update(_speed=value)

    def pause(self) -> None:
        self._update(_paused=True)

    def resume(self) -> None:
        self._update(_paused=False, _steps=0)

    def step(self) -> None:
        """Let exactly one frame through; pauses playback if it was running."""
        with self._condition:
            self._paused = True
            self._steps += 1
            self._changed()

    def drop_next(self, count: int, source: str = "live") -> None:
        """Skip the next ``count`` frames: they are read but the odometry never sees them."""
        count = int(count)
        if count < 1:
            raise ValueError(f"drop_next needs a count >= 1, got {count}")
        with self._condition:
            self._drop_requests.append(_DropRequest(count, source))
            self._changed()

    def request_restart(self) -> None:
        """End the current pass at the next frame; the pipeline resets the odometry and starts over."""
        self._update(_restart_requested=True)

    def stop(self) -> None:
        """End playback for good (the pass ends at the next frame, a pending wait returns)."""
        self._update(_stopped=True)

    def interrupt(self) -> None:
        """``stop()`` for a signal handler. A handler runs in the main thread between two of its bytecodes, maybe
        while that thread holds the player's lock: so no lock here, two plain assignments; every wait polls them."""
        self._interrupted = True
        self._stopped = True

    def wait_for_restart(self) -> bool:
        """Block until a restart is requested (True) or the player is stopped (False)."""
        with self._condition:
            while not (self._restart_requested or self._stopped):
                self._condition.wait(WAIT_SLICE_S)
            return self._restart_requested and not self._stopped

    def _update(self, **state: Any) -> None:
        with self._condition:
            for name, value in state.items():
                setattr(self, name, value)
            self._changed()

    def _changed(self) -> None:
        """Any control resets the pacing anchor (so a resume does not rush) and wakes a waiting player."""
        self._pace_anchor = None
        self._condition.notify_all()

    # ------------------------------------------------------------------------------------ playback

    def __iter__(self) -> Iterator[Any]:
        return self.play()

    def play(self, on_drop: Callable[[Event], None] | None = None) -> Iterator[Any]:
        """One pass over the sequence, from the first frame."""
        with self._condition:
            self._restart_requested = False
            self._finished = False
            self._drop_requests.clear()
            self._pace_anchor = None
        script = dict(self.drops)
        dropping: _DropRequest | None = None
        dropped: list[Any] = []
        for frame in self.sequence:
            if frame.index in script:
                self.drop_next(script.pop(frame.index), source="script")
            if not self._wait_until_frame_may_pass():
                break
            with self._condition:
                if dropping is None and self._drop_requests:
                    dropping = self._drop_requests.popleft()
                if dropping is not None:
                    dropped.append(frame)
                    if len(dropped) < dropping.count:
                        continue
            if dropping is not None:
                _announce(on_drop, dropping, dropped)
                dropping, dropped = None, []
                continue
            self._pace(frame.timestamp)
            with self._condition:
                if self._steps > 0:
                    self._steps -= 1
            yield frame
        else:
            with self._condition:
                self._finished = True
        if dropping is not None and dropped:
            _announce(on_drop, dropping, dropped)  # the drop ran past the end (or the pass was cut short)

    def _wait_until_frame_may_pass(self) -> bool:
        """Wait while paused (unless a step is pending); False when the pass must end (stop or restart)."""
        with self._condition:
            while self._paused and self._steps == 0 and not (self._stopped or self._restart_requested):
                self._condition.wait(WAIT_SLICE_S)
            return not (self._stopped or self._restart_requested)

    def _pace(self, timestamp: float) -> None:
        """Sleep so that dataset time advances at ``speed`` x wall time; never catch up after being slow."""
        with self._condition:
            if self._speed <= 0.0 or self._paused:
                return
            now = time.monotonic()
            if self._pace_anchor is None:
                self._pace_anchor = (now, timestamp)
                return
            anchor_wall, anchor_time = self._pace_anchor
            due = anchor_wall + (timestamp - anchor_time) / self._speed
            while now < due and not self._changed_since(anchor_wall):
                self._condition.wait(min(due - now, WAIT_SLICE_S))
                now = time.monotonic()
            if now > due:
                # Tracking was slower than real time: re-anchor instead of rushing the next frames.
                self._pace_anchor = (now, timestamp)

    def _changed_since(self, anchor_wall: float) -> bool:
        anchor = self._pace_anchor
        return anchor is None or anchor[0] != anchor_wall or self._stopped or self._restart_requested


def _announce(on_drop: Callable[[Event], None] | None, request: _DropRequest, frames: list[Any]) -> None:
    if on_drop is None:
        return
    first, last = frames[0], frames[-1]
    on_drop(
        Event(
            EventKind.FRAMES_DROPPED,
            first.index,
            first.timestamp,
            {"count": len(frames), "requested": request.count, "first_frame": first.index,
             "last_frame": last.index, "source": request.source},
        )
    )


def _validated_drops(drops: Iterable[tuple[int, int]]) -> list[tuple[int, int]]:
    validated = []
    for index, count in drops:
        if index < 0 or count < 1:
            raise ValueError(f"a drop needs a frame index >= 0 and a count >= 1, got {index}:{count}")
        validated.append((int(index), int(count)))
    return validated
