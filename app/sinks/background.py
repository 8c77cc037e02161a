"""A sink run on a thread of its own, so that the tracking thread only hands it each call and goes on (issue 18).

The Rerun recording spends about 7 ms of Python a frame (a JPEG, paths, clouds at keyframes); on the tracking
thread that is time no frame is tracked, which a live camera at 30 Hz (33 ms a frame) feels. Here the calls wait
in a queue, in order, and the sink works through them while the odometry is in its compiled kernels (they release
the GIL). What the odometry hands its sinks is never changed afterwards (results, snapshots and events are its
own objects), so the sink sees what it would have seen on the tracking thread.

The queue is bounded: a sink that falls behind slows the tracking thread down rather than holding every frame's
image. An exception in the sink is raised again on the tracking thread, at its next call or at ``close``.
"""

from __future__ import annotations

import queue
import threading
from typing import Any, Callable

MAX_QUEUED_CALLS = 16  # about half a second of frames at 30 Hz; each holds its frame's image


class BackgroundSink:
    """Forwards a sink's calls (``on_frame``, ``on_event``, ``on_map``, ``restart``, ``close``) to a thread."""

    def __init__(self, sink: Any, max_queued: int = MAX_QUEUED_CALLS):
        self.sink = sink
        self._calls: queue.Queue[tuple[Callable, tuple] | None] = queue.Queue(maxsize=max_queued)
        self._error: BaseException | None = None  # the sink's failure; it takes no more calls after one
        self._error_raised = False
        self._thread = threading.Thread(target=self._work, name=f"{type(sink).__name__}", daemon=True)
        self._thread.start()

    def on_frame(self, frame: Any, result: Any) -> None:
        self._call(self.sink.on_frame, frame, result)

    def on_event(self, event: Any) -> None:
        self._call(self.sink.on_event, event)

    def on_map(self, snapshot: Any) -> None:
        self._call(self.sink.on_map, snapshot)

    def restart(self) -> None:
        self._call(self.sink.restart)

    def close(self) -> None:
        """The queued calls, then the sink's own close; returns when the sink is closed."""
        if self._thread.is_alive():
            self._calls.put((self.sink.close, ()))
            self._calls.put(None)
            self._thread.join()
        self._raise_error()

    def _call(self, method: Callable, *args: Any) -> None:
        self._raise_error()
        self._calls.put((method, args))

    def _raise_error(self) -> None:
        if self._error is not None and not self._error_raised:
            self._error_raised = True
            raise self._error

    def _work(self) -> None:
        while (call := self._calls.get()) is not None:
            method, args = call
            if self._error is None:  # after a failure the calls are dropped: the sink's state is unknown
                try:
                    method(*args)
                except BaseException as error:  # noqa: BLE001 (handed to the tracking thread)
                    self._error = error
