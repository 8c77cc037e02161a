"""Plays a sequence's frames: pacing, pause and step, drops and jumps (scripted and live), restart, stop.

The tracking thread iterates the player; a viewer (the viser page) calls its controls from other threads.
Every control only changes state under a lock and takes effect when the next frame is about to be handed
out, so the odometry always sees a clean sequence of frames, some of which are missing or come again.

Drops and jumps are the experiments of FDMO section 5.3.2: the odometry sees a large baseline between two
consecutive frames. Both are one mechanism, a move of the player's cursor (the position of the next frame
in the sequence) decided before the next frame is handed out:

    drop COUNT        the cursor moves COUNT frames ahead: those frames are never read nor seen
    jump to TARGET    the cursor moves to TARGET's position, back (the frames since are played again) or ahead

A scripted drop (``--drop FRAME:COUNT``) is requested when the player reaches FRAME, a scripted jump
(``--jump FRAME:TARGET``) once FRAME has been handed out; each fires once per pass (a replay does not fire it
again). A click on the page's "drop" or "jump back" button requests the same moves, so experiments and the
browser do the same thing. Each move is announced as an event: FRAMES_DROPPED or FRAMES_JUMPED.

Real time (``--realtime``) plays the sequence as a camera delivers it: frame i arrives at its timestamp (over
``speed``) after the first, whether or not the odometry is ready. The player hands out the newest frame that has
arrived and drops the older ones the odometry was too busy to take, announced as FRAMES_DROPPED with source
"realtime" (a live system skips them the same way); a frame not yet arrived is waited for. The camera's clock is
never re-anchored for a slow odometry, only after a pause or a move (a restart of the camera, in effect).
"""

from __future__ import annotations

import bisect
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

from app.kernel_build import playing_clock
from vo_core.events import Event, EventKind

# Waits wake at least this often so that Ctrl-C (KeyboardInterrupt) is handled promptly in the main thread.
WAIT_SLICE_S = 0.2
REAL_TIME = 1.0  # speed: the sequence's own frame rate, from its timestamps
REALTIME_SOURCE = "realtime"  # the source of the drops of frames that arrived while the odometry was busy


@dataclass(frozen=True)
class _Move:
    """A requested move of the cursor: a drop of ``count`` frames, a jump to frame ``target`` or ``count``
    frames back from the last frame handed out."""

    kind: EventKind  # FRAMES_DROPPED or FRAMES_JUMPED
    source: str  # "script" (--drop, --jump) or "live" (a viewer)
    count: int = 0
    target: int | None = None  # a frame index (jumps to a given frame)


class PlaybackState:
    """What a run asks of any source of frames (a player of a sequence, a live camera): whether its pass ended,
    whether it was stopped or interrupted (a stop signal), whether a restart is wanted."""

    def __init__(self) -> None:
        self._stopped = False
        self._interrupted = False
        self._finished = False
        self._restart_requested = False

    @property
    def finished(self) -> bool:
        """True once a pass has reached the end of its frames (until a restart)."""
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

    def interrupt(self) -> None:
        """A stop for a signal handler. A handler runs in the main thread between two of its bytecodes, maybe
        while that thread holds a lock: so no lock here, two plain assignments; every wait polls them."""
        self._interrupted = True
        self._stopped = True


class Player(PlaybackState):
    """Frames of ``sequence`` in order, with ``drops`` as ``(frame, count)`` and ``jumps`` as ``(frame, target)``.

    ``sequence`` is a vo_core sequence (or anything with ``len``, iteration, ``indices``, ``timestamps`` and
    ``cut(start)``): frames are read ahead from the cursor, and read afresh from wherever a move lands.
    Frame numbers are ``Frame.index``, the positions in the original sequence (stable under --start/--end).
    Iterate with ``for frame in player`` or ``player.play(on_event=callback)``; the callback receives one
    FRAMES_DROPPED or FRAMES_JUMPED event per move, on the iterating thread, before the next frame is handed out.
    A pass ends at the end of the sequence, on ``stop()``, or on ``request_restart()`` (then the caller starts
    over: ``wait_for_restart()`` returns True and the next ``play()`` begins at the first frame).
    """

    def __init__(self, sequence, drops: Iterable[tuple[int, int]] = (), jumps: Iterable[tuple[int, int]] = (),
                 realtime: bool = False):
        super().__init__()
        self.sequence = sequence
        self.realtime = realtime  # frames arrive at their timestamps; those the odometry misses are dropped
        self.drops = _pairs(drops, "a drop needs a frame index >= 0 and a count >= 1", minimum=(0, 1))
        self.jumps = _pairs(jumps, "a jump needs a frame index >= 0 and a target >= 0", minimum=(0, 0))
        self._indices = [int(index) for index in sequence.indices]
        self._timestamps = [float(timestamp) for timestamp in sequence.timestamps]
        self._positions = {index: position for position, index in enumerate(self._indices)}
        self._condition = threading.Condition()
        self._paused = False
        self._steps = 0  # frames allowed through while paused
        self._speed = REAL_TIME if realtime else 0.0
        self._moves: deque[_Move] = deque()
        self._pace_anchor: tuple[float, float] | None = None  # (wall clock, dataset timestamp)
        self._played_s = 0.0  # playing time of the stretches that ended
        self._playing_since: float | None = None  # start of the current stretch (None: not playing)
        self._in_pass = False  # inside play(): the clock may run

    # ------------------------------------------------------------------------------------ controls

    @property
    def paused(self) -> bool:
        return self._paused

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

    def playing_time(self) -> float:
        """Seconds spent playing since the player was made: inside ``play()``, not paused and not building compiled
        kernels (app/kernel_build.py). Frame rates are taken over this clock, so that a pause, the wait for a
        browser, or the first run's kernel builds do not lower them."""
        since = self._playing_since
        return self._played_s + (0.0 if since is None else playing_clock() - since)

    def pause(self) -> None:
        with self._condition:
            self._paused = True
            self._stop_the_clock()
            self._changed()

    def resume(self) -> None:
        with self._condition:
            self._paused, self._steps = False, 0
            self._start_the_clock()
            self._changed()

    def step(self) -> None:
        """Let exactly one frame through; pauses playback if it was running."""
        with self._condition:
            self._paused = True
            self._stop_the_clock()
            self._steps += 1
            self._changed()

    def drop_next(self, count: int, source: str = "live") -> None:
        """Skip the next ``count`` frames: the odometry never sees them."""
        self._request(_Move(EventKind.FRAMES_DROPPED, source, count=_at_least_one(count, "drop_next")))

    def jump_back(self, count: int, source: str = "live") -> None:
        """Continue from ``count`` frames before the last frame handed out (the first frame at most): those frames
        are played again."""
        self._request(_Move(EventKind.FRAMES_JUMPED, source, count=_at_least_one(count, "jump_back")))

    def jump_to(self, target: int, source: str = "live") -> None:
        """Continue from frame ``target`` (a frame index of the sequence), back or ahead."""
        if int(target) not in self._positions:
            raise ValueError(f"jump_to: frame {target} is not in the sequence")
        self._request(_Move(EventKind.FRAMES_JUMPED, source, target=int(target)))

    def request_restart(self) -> None:
        """End the current pass at the next frame; the pipeline resets the odometry and starts over."""
        self._update(_restart_requested=True)

    def stop(self) -> None:
        """End playback for good (the pass ends at the next frame, a pending wait returns)."""
        self._update(_stopped=True)

    def wait_for_restart(self) -> bool:
        """Block until a restart is requested (True) or the player is stopped (False)."""
        with self._condition:
            while not (self._restart_requested or self._stopped):
                self._condition.wait(WAIT_SLICE_S)
            return self._restart_requested and not self._stopped

    def _request(self, move: _Move) -> None:
        with self._condition:
            self._moves.append(move)
            self._changed()

    def _update(self, **state: Any) -> None:
        with self._condition:
            for name, value in state.items():
                setattr(self, name, value)
            self._changed()

    def _changed(self) -> None:
        """Any control resets the pacing anchor (so a resume does not rush) and wakes a waiting player."""
        self._pace_anchor = None
        self._condition.notify_all()

    def _start_the_clock(self) -> None:
        if self._in_pass and not self._paused and self._playing_since is None:
            self._playing_since = playing_clock()

    def _stop_the_clock(self) -> None:
        if self._playing_since is not None:
            self._played_s += playing_clock() - self._playing_since
            self._playing_since = None

    # ------------------------------------------------------------------------------------ playback

    def __iter__(self) -> Iterator[Any]:
        return self.play()

    def play(self, on_event: Callable[[Event], None] | None = None) -> Iterator[Any]:
        """One pass over the sequence, from the first frame."""
        with self._condition:
            self._restart_requested = False
            self._finished = False
            self._moves.clear()
            self._pace_anchor = None
            self._in_pass = True
            self._start_the_clock()
        script = _Script(self.drops, self.jumps)
        reader = _Reader(self.sequence)
        cursor, last = 0, -1  # the positions of the next frame and of the last one handed out (-1: none yet)
        try:
            while True:
                if not self._wait_until_frame_may_pass():
                    return
                cursor = self._move(cursor, last, script, on_event)
                if self.realtime:
                    skipped_from, cursor = cursor, self._skip_missed(cursor, last, on_event)
                    if script.passed_over(self._indices[skipped_from:cursor], self):
                        cursor = self._move(cursor, last, script, on_event)
                if cursor >= len(self._indices):
                    with self._condition:
                        self._finished = True
                    return
                frame = reader.read(cursor)
                self._pace(frame.timestamp)
                with self._condition:
                    if self._steps > 0:
                        self._steps -= 1
                yield frame
                last, cursor = cursor, cursor + 1
                script.handed_out(frame.index, self)
        finally:
            reader.close()
            with self._condition:
                self._stop_the_clock()
                self._in_pass = False

    def _move(self, cursor: int, last: int, script: "_Script", on_event) -> int:
        """Apply the moves requested so far (a scripted drop of the frame at the cursor first), each announced."""
        script.reached(self._frame_at(cursor), self)
        while True:
            with self._condition:
                if not self._moves:
                    return cursor
                move = self._moves.popleft()
                self._pace_anchor = None  # dataset time jumps: pacing starts afresh
            target = self._target(move, cursor, last)
            if on_event is not None and target != cursor:
                on_event(self._announcement(move, cursor, last, target))
            cursor = target
            script.reached(self._frame_at(cursor), self)

    def _skip_missed(self, cursor: int, last: int, on_event) -> int:
        """Real time: the position of the newest frame that has arrived by now (frames at the cursor and after it
        whose timestamps have passed on the camera's clock); the older ones are dropped, and announced."""
        with self._condition:
            anchor, speed = self._pace_anchor, self._speed
            if anchor is None or speed <= 0.0 or self._paused or cursor >= len(self._indices):
                return cursor
            camera_time = anchor[1] + (time.monotonic() - anchor[0]) * speed
        newest = min(bisect.bisect_right(self._timestamps, camera_time, lo=cursor) - 1, len(self._indices) - 1)
        if newest <= cursor:
            return cursor
        if on_event is not None:
            on_event(self._announcement(_Move(EventKind.FRAMES_DROPPED, REALTIME_SOURCE, count=newest - cursor),
                                        cursor, last, newest))
        return newest

    def _frame_at(self, position: int) -> int | None:
        return self._indices[position] if position < len(self._indices) else None

    def _target(self, move: _Move, cursor: int, last: int) -> int:
        if move.kind is EventKind.FRAMES_DROPPED:
            return min(cursor + move.count, len(self._indices))
        if move.target is not None:
            return self._positions[move.target]
        return max(last - move.count, 0)

    def _announcement(self, move: _Move, cursor: int, last: int, target: int) -> Event:
        if move.kind is EventKind.FRAMES_DROPPED:
            first, final = cursor, target - 1
            details = {"count": target - cursor, "requested": move.count, "first_frame": self._indices[first],
                       "last_frame": self._indices[final], "source": move.source}
            return Event(move.kind, self._indices[first], self._timestamps[first], details)
        details = {"from_frame": self._indices[last] if last >= 0 else None, "to_frame": self._indices[target],
                   "direction": "backward" if target <= last else "forward",
                   "frames": abs(target - last - 1),  # skipped (forward) or played again (backward)
                   "source": move.source}
        where = max(last, 0)  # the frame after which it jumped
        return Event(move.kind, self._indices[where], self._timestamps[where], details)

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
            if now > due and not self.realtime:
                # Tracking was slower than real time: re-anchor instead of rushing the next frames (in real time
                # the camera does not wait: _skip_missed drops the frames it delivered meanwhile).
                self._pace_anchor = (now, timestamp)

    def _changed_since(self, anchor_wall: float) -> bool:
        anchor = self._pace_anchor
        return anchor is None or anchor[0] != anchor_wall or self._stopped or self._restart_requested


class _Script:
    """The scripted moves of one pass, each fired once: a drop when its frame is reached, a jump once its frame
    has been handed out (so a frame played again does not jump again)."""

    def __init__(self, drops: list[tuple[int, int]], jumps: list[tuple[int, int]]):
        self.drops = {frame: deque() for frame, _ in drops}
        for frame, count in drops:
            self.drops[frame].append(count)
        self.jumps = {frame: deque() for frame, _ in jumps}
        for frame, target in jumps:
            self.jumps[frame].append(target)

    def reached(self, frame: int | None, player: Player) -> None:
        if self.drops.get(frame):
            player.drop_next(self.drops[frame].popleft(), source="script")

    def handed_out(self, frame: int, player: Player) -> None:
        if self.jumps.get(frame):
            player.jump_to(self.jumps[frame].popleft(), source="script")

    def passed_over(self, frames: list[int], player: Player) -> bool:
        """Real time: ``frames`` arrived while the odometry was busy and were dropped as late. The moves scripted at
        them still happen, as if the frames had been reached or handed out: a drop hides what it covers beyond
        them (one wholly inside them is what they already are: dropped, and announced as late), a jump jumps.
        Returns whether a move was requested."""
        requested = False
        for position, frame in enumerate(frames):
            while self.drops.get(frame):
                beyond = self.drops[frame].popleft() - (len(frames) - position)
                if beyond > 0:
                    player.drop_next(beyond, source="script")
                    requested = True
            while self.jumps.get(frame):
                self.handed_out(frame, player)
                requested = True
        return requested


class _Reader:
    """Frames from a position on, read ahead by the sequence's own iterator, which starts afresh where a move lands."""

    def __init__(self, sequence):
        self.sequence = sequence
        self._frames: Iterator[Any] | None = None
        self._next = 0  # the position the iterator yields next

    def read(self, position: int):
        if self._frames is None or position != self._next:
            self.close()
            self._frames = iter(self.sequence if position == 0 else self.sequence.cut(position))
        self._next = position + 1
        return next(self._frames)

    def close(self) -> None:
        if self._frames is not None and hasattr(self._frames, "close"):
            self._frames.close()  # stops the read-ahead thread
        self._frames = None


def _at_least_one(count: int, what: str) -> int:
    count = int(count)
    if count < 1:
        raise ValueError(f"{what} needs a count >= 1, got {count}")
    return count


def _pairs(pairs: Iterable[tuple[int, int]], requirement: str, minimum: tuple[int, int]) -> list[tuple[int, int]]:
    validated = [(int(first), int(second)) for first, second in pairs]
    for first, second in validated:
        if first < minimum[0] or second < minimum[1]:
            raise ValueError(f"{requirement}, got {first}:{second}")
    return validated
