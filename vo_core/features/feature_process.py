"""The feature half in a process of its own, for the mapping threads (issue 18).

With threaded mapping the feature map grows beside tracking and the direct mapper (FDMO Fig. 4). On a thread it did
not really: the feature mapping is Python around compiled kernels, it held the GIL 43 % of its time (py-spy), and
the other threads waited for it (teddy, threaded against synchronous: tracking 11.2 -> 15.7 ms a frame, the window
optimization 33 -> 46 ms a keyframe). A process has an interpreter of its own.

``FeatureProcess`` offers ``FeatureOdometry``'s methods and properties; each call is carried out there, one at a
time, in the order called (a check against the feature map waits for the keyframe being mapped there, as it waited
for the feature mapping thread's lock). The feature map lives only there: what a call returns is a copy, and the
computation is the same as in this process, so offline runs stay the synchronous ones. The process starts with the
odometry (``spawn``: no copy of a multi-threaded parent) and ends with ``close``, or with its parent.
"""

from __future__ import annotations

import functools
import multiprocessing
import os
import signal
import threading
from multiprocessing.connection import Connection

from vo_core.features.config import FeatureConfig
from vo_core.features.feature_odometry import FeatureOdometry
from vo_core.geometry.camera import PinholeCamera

CLOSE_TIMEOUT_S = 10.0  # a call in progress when the run ends finishes first


class FeatureProcess:
    def __init__(self, config: FeatureConfig, camera: PinholeCamera, niceness: int = 0):
        """``niceness``: added to the process's (os.nice), so that on a busy machine the cores go to the callers."""
        context = multiprocessing.get_context("spawn")
        self._connection, theirs = context.Pipe()
        self._process = context.Process(target=_serve, args=(theirs, config, camera, niceness),
                                        name="fdmo-feature-map", daemon=True)
        _start_deaf_to_ctrl_c(self._process)
        theirs.close()
        self._lock = threading.Lock()  # one call on the pipe at a time, from whichever thread
        self._ready = False  # the process answered that its FeatureOdometry is built

    def __getattr__(self, name: str):
        member = getattr(FeatureOdometry, name, None) if not name.startswith("_") else None
        if member is None:
            raise AttributeError(f"FeatureProcess offers FeatureOdometry's methods, not {name!r}")
        if isinstance(member, property):
            return self._call(name)
        return functools.partial(self._call, name)

    def _call(self, name: str, *args):
        with self._lock:
            if self._process is None:
                raise RuntimeError(f"the feature map's process was closed before {name}")
            try:
                if not self._ready:
                    self._answer()
                    self._ready = True
                self._connection.send((name, args))
                return self._answer()
            except (EOFError, BrokenPipeError):
                self._process.join(CLOSE_TIMEOUT_S)
                raise RuntimeError(f"the feature map's process ended unexpectedly during {name} (exit code "
                                   f"{self._process.exitcode})") from None

    def _answer(self):
        succeeded, value = self._connection.recv()
        if not succeeded:
            raise value
        return value

    def close(self) -> None:
        with self._lock:
            if self._process is None:
                return
            try:
                self._connection.send(None)
            except OSError:  # it has already ended
                pass
            self._process.join(CLOSE_TIMEOUT_S)
            if self._process.is_alive():
                self._process.terminate()
                self._process.join()
            self._connection.close()
            self._process = None


def _start_deaf_to_ctrl_c(process) -> None:
    """Ctrl-C reaches the whole process group: the parent ends the run, and then the process it started. So the
    process must not hear it from its first instruction on (its imports included; one that came then killed it, and
    the run failed at its next feature call instead of ending with complete files). An ignored signal stays ignored
    across exec, and Python then installs no KeyboardInterrupt for it; only the main thread may change that, and
    elsewhere a signal blocked in the starting thread stays blocked in the process."""
    if threading.current_thread() is threading.main_thread():
        handler = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            process.start()
        finally:
            signal.signal(signal.SIGINT, handler)
        return
    unblocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        process.start()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, unblocked)


def _serve(connection: Connection, config: FeatureConfig, camera: PinholeCamera, niceness: int) -> None:
    """The process: build the feature half, say whether that worked, then answer calls until told to stop (or
    until the parent is gone)."""
    try:
        try:
            odometry = FeatureOdometry(config, camera)
        except Exception as error:  # raised in the parent at its first call (a missing vocabulary, say)
            connection.send((False, error))
            return
        connection.send((True, None))
        os.nice(niceness)  # from here: the start (imports, vocabulary) is waited for by the run's first keyframes
        while (request := connection.recv()) is not None:
            name, args = request
            try:
                member = getattr(odometry, name)
                answer = (True, member(*args) if callable(member) else member)
            except Exception as error:
                answer = (False, error)
            connection.send(answer)
    except (EOFError, BrokenPipeError):
        return
    # Told to stop: every answer is sent, and nothing here needs the interpreter's teardown (0.2 s of a run's end,
    # freeing the feature map object by object).
    os._exit(0)
