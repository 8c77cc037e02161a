"""The time the process spends building compiled kernels (numba): the very first run on a machine builds them all
(about 80 s for the bundled sequence; later runs load them from the user's cache, vo_core/kernel_cache.py, and
start at once). That time is announced once, reported, and left out of every frame rate: the frame rates are taken
over ``playing_clock``, a monotonic clock that stands still while a kernel is built."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator

from numba.core import event

COMPILE_EVENT = "numba:compile"  # numba's event around the compilation of one kernel (not a load from its cache)


class KernelBuilds:
    """numba's compile events, timed: a kernel's build encloses those of the kernels it calls, so only the
    outermost count. numba builds under one lock, so builds never overlap."""

    def __init__(self, announce: Callable[[], None] | None = None, clock: Callable[[], float] = time.monotonic):
        self.announce = announce  # called at the next build, once
        self.clock = clock
        self._finished_s = 0.0
        self._depth = 0
        self._started: float | None = None
        self._lock = threading.Lock()

    def seconds(self) -> float:
        """Seconds spent building so far, the build under way included."""
        with self._lock:
            running = 0.0 if self._started is None else self.clock() - self._started
            return self._finished_s + running

    def started(self) -> None:
        with self._lock:
            self._depth += 1
            if self._depth > 1:
                return
            self._started = self.clock()
            announce, self.announce = self.announce, None
        if announce is not None:
            announce()

    def ended(self) -> None:
        with self._lock:
            self._depth -= 1
            if self._depth == 0 and self._started is not None:
                self._finished_s += self.clock() - self._started
                self._started = None


class _Listener(event.Listener):
    def __init__(self, builds: KernelBuilds):
        self.builds = builds

    def on_start(self, _event) -> None:
        self.builds.started()

    def on_end(self, _event) -> None:
        self.builds.ended()


_builds: KernelBuilds | None = None


def watch_kernel_builds() -> KernelBuilds:
    """Times the process's kernel builds from now on (the listener is registered once per process)."""
    global _builds
    if _builds is None:
        _builds = KernelBuilds()
        event.register(COMPILE_EVENT, _Listener(_builds))
    return _builds


@contextlib.contextmanager
def kernel_builds_announced(announce: Callable[[], None] | None) -> Iterator[KernelBuilds]:
    """Within the block, ``announce`` is called at the first kernel build, once (None: nothing is said)."""
    builds = watch_kernel_builds()
    builds.announce = announce
    try:
        yield builds
    finally:
        builds.announce = None


def kernel_build_seconds() -> float:
    """Seconds the process spent building kernels since ``watch_kernel_builds`` (0 before)."""
    return 0.0 if _builds is None else _builds.seconds()


def playing_clock() -> float:
    """``time.monotonic()`` less the time spent building kernels: the clock of the frame rates."""
    return time.monotonic() - kernel_build_seconds()
