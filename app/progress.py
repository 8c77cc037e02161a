"""A one-line progress bar on stderr for headless runs: frames per second, tracked fraction, last event.

It is a Sink like the others, so it sees exactly what the odometry reports. On a terminal the line is
redrawn in place; in a log file (not a terminal) a plain line is written every tenth of the sequence.
Its frame rate (``FrameRate``) is the one the viser page shows: frames over the player's playing time.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any, TextIO

from vo_core.events import Event, EventKind, FrameResult, MapSnapshot

REDRAW_INTERVAL_S = 0.1  # a terminal redraw at most ten times a second
LOG_LINES_PER_RUN = 10  # without a terminal: a line every 10 % of the sequence
BAR_WIDTH = 24


class FrameRate:
    """Frames per second of a pass over ``clock``: the player's playing time (``Player.playing_time``), so that a
    pause, or the wait for a browser, does not count; the terminal, the page and metrics.json agree."""

    def __init__(self, clock: Callable[[], float] = time.monotonic):
        self.clock = clock
        self.restart()

    def restart(self) -> None:
        self.started = self.clock()
        self.frames = 0

    def count(self) -> None:
        self.frames += 1

    def fps(self) -> float:
        elapsed = self.clock() - self.started
        return self.frames / elapsed if elapsed > 0 else 0.0


class ProgressBar:
    def __init__(self, total_frames: int, stream: TextIO | None = None, clock: Callable[[], float] = time.monotonic):
        self.total_frames = max(int(total_frames), 1)
        self.stream = stream if stream is not None else sys.stderr
        self.clock = clock
        self.interactive = bool(getattr(self.stream, "isatty", lambda: False)())
        self.restart()

    def restart(self) -> None:
        """A new pass (Restart on the page): count from zero."""
        self.rate = FrameRate(self.clock)  # frames the odometry processed, and how fast
        self.tracked = 0
        self.passed = 0  # frames processed, skipped or dropped: how far into the sequence we are
        self.last_event = ""
        self._last_draw = -float("inf")
        self._last_logged_tenth = -1
        self._logged_passed = -1

    # ------------------------------------------------------------------------------------ Sink protocol

    def on_frame(self, frame: Any, result: FrameResult) -> None:
        self.rate.count()
        self.passed += 1
        self.tracked += bool(result.tracked)
        self._draw()

    def on_event(self, event: Event) -> None:
        if event.kind is EventKind.FRAMES_DROPPED:
            self.passed += int(event.details.get("count", 0))
        elif event.kind is EventKind.FRAMES_JUMPED:  # back: the frames played again are ahead once more
            backward = event.details.get("direction") == "backward"
            self.passed += (-1 if backward else 1) * int(event.details.get("frames", 0))
        elif event.kind is EventKind.FRAME_SKIPPED:
            self.passed += 1
        if event.kind is not EventKind.TRACKING_OK:
            self.last_event = f"{event.kind.value}@{event.frame_index}"

    def on_map(self, snapshot: MapSnapshot) -> None:
        pass

    def close(self) -> None:
        self._draw(force=True)
        if self.interactive:
            self.stream.write("\n")
        self.stream.flush()

    # ------------------------------------------------------------------------------------ drawing

    def line(self) -> str:
        fraction = min(self.passed / self.total_frames, 1.0)
        filled = int(round(fraction * BAR_WIDTH))
        tracked = self.tracked / self.rate.frames if self.rate.frames else 0.0
        text = (
            f"[{'#' * filled}{'.' * (BAR_WIDTH - filled)}] {self.passed}/{self.total_frames} frames"
            f" | {self.rate.fps():5.1f} fps | tracked {100 * tracked:3.0f}%"
        )
        return text + (f" | {self.last_event}" if self.last_event else "")

    def _draw(self, force: bool = False) -> None:
        if self.interactive:
            now = self.clock()
            if force or now - self._last_draw >= REDRAW_INTERVAL_S:
                self._last_draw = now
                self.stream.write("\r\033[K" + self.line())  # carriage return, clear to the end of the line
                self.stream.flush()
            return
        tenth = int(LOG_LINES_PER_RUN * self.passed / self.total_frames)
        if tenth > self._last_logged_tenth or (force and self.passed != self._logged_passed):
            self._last_logged_tenth, self._logged_passed = tenth, self.passed
            self.stream.write(self.line() + "\n")


class CellProgress:
    """``fdmo bench``'s line over cells: how many finished (and failed), the time so far and an estimate of the
    time left: the cells left at the pace the cells finished so far (with several workers, the time between two
    cells finishing, not the time a cell takes)."""

    def __init__(self, total_cells: int, stream: TextIO | None = None, clock: Callable[[], float] = time.monotonic):
        self.total = total_cells
        self.stream = stream if stream is not None else sys.stderr
        self.clock = clock
        self.interactive = bool(getattr(self.stream, "isatty", lambda: False)())
        self.started = clock()
        self.finished = 0
        self.failed = 0

    def done(self, row: dict[str, Any]) -> None:
        self.finished += 1
        self.failed += row["status"] != "ok"
        last = f"{row['sequence']}/{row['method']}/{row['setting']}/{row['task']}/seed{row['seed']} {row['status']}"
        self.stream.write(("\r\033[K" if self.interactive else "") + f"{self.line()} | {last}"
                          + ("" if self.interactive else "\n"))
        self.stream.flush()

    def line(self) -> str:
        filled = int(round(BAR_WIDTH * self.finished / max(self.total, 1)))
        elapsed = self.clock() - self.started
        left = self.total - self.finished
        eta = elapsed / self.finished * left if self.finished else float("nan")
        failed = f" ({self.failed} failed)" if self.failed else ""
        return (f"[{'#' * filled}{'.' * (BAR_WIDTH - filled)}] {self.finished}/{self.total} cells{failed}"
                f" | {_clock_time(elapsed)} elapsed, ETA {_clock_time(eta)}")

    def close(self) -> None:
        if self.interactive and self.finished:
            self.stream.write("\n")
        self.stream.flush()


def _clock_time(seconds: float) -> str:
    if seconds != seconds:  # NaN: nothing to estimate from yet
        return "?"
    minutes, secs = divmod(int(round(seconds)), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"
