"""The feature half in a process of its own, for the mapping threads (issue 18).

With threaded mapping the feature map grows beside tracking and the direct mapper (FDMO Fig. 4). On a thread it did
not really: the feature mapping is Python around compiled kernels, it held the GIL 43 % of its time (py-spy), and
the other threads waited for it (teddy, threaded against synchronous: tracking 11.2 -> 15.7 ms a frame, the window
optimization 33 -> 46 ms a keyframe). A process has an interpreter of its own.

``FeatureProcess`` offers ``FeatureOdometry``'s methods and properties; each call is carried out there, one at a
time, in the order called (a check against the feature map waits for the keyframe being mapped there, as it waited
for the feature mapping thread's lock). The feature map lives only there: what a call returns is a copy, and the
computation is the same as in this process, so offline runs stay the synchronous ones. The process starts with the
odometry, or ahead of it (``start_ahead``), from a fresh interpreter (``spawn``: no copy of a multi-threaded parent),
and ends with ``close``, or with its parent.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import multiprocessing
import os
import signal
import threading
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # imported where used: ``start_ahead`` runs before the odometry's modules are imported
    from vo_core.features.config import FeatureConfig
    from vo_core.geometry.camera import PinholeCamera

CLOSE_TIMEOUT_S = 10.0  # a call in progress when the run ends finishes first

# The made-up scene on which a new process loads its compiled kernels (_load_kernels): a textured plane at
# WARM_UP_DEPTH seen from WARM_UP_VIEWS cameras WARM_UP_BASELINE apart, the middle view left out of the map and
# found again. Small, so that loading costs what numba and the kernels' caches cost, not the features' own work.
WARM_UP_SIZE = (320, 240)  # pixels, width x height
WARM_UP_FOCAL_PX = 250.0
WARM_UP_DEPTH = 2.0
WARM_UP_BASELINE = 0.04
WARM_UP_VIEWS = 5
WARM_UP_TEXTURE_CELL_PX = 6  # the random texture's grain: corners at about this spacing

_ahead: list[tuple[BaseProcess, Connection]] = []  # started by start_ahead, for the next FeatureProcess
_ahead_lock = threading.Lock()


def start_ahead() -> None:
    """Starts the next ``FeatureProcess``'s process now, unless one is waiting already. A process needs about 0.8 s
    of CPU before it can map (imports, numba's start, its kernels loaded): started before its parent imports the
    odometry, on the core those imports leave idle, it is ready when the run's first keyframes come (app/__main__.py;
    a live run's warm-up, app.pipeline.warm_up). A process started ahead and never used waits, idle, and ends
    with its parent."""
    with _ahead_lock:
        if not _ahead:
            _ahead.append(_spawn())


def _spawn() -> tuple[BaseProcess, Connection]:
    context = multiprocessing.get_context("spawn")
    ours, theirs = context.Pipe()
    process = context.Process(target=_serve, args=(theirs,), name="fdmo-feature-map", daemon=True)
    _start_deaf_to_ctrl_c(process)
    theirs.close()
    return process, ours


def _started_ahead_or_new() -> tuple[BaseProcess, Connection]:
    with _ahead_lock:
        while _ahead:
            process, connection = _ahead.pop()
            if process.is_alive():
                return process, connection
            connection.close()
    return _spawn()


class FeatureProcess:
    def __init__(self, config: FeatureConfig, camera: PinholeCamera, niceness: int = 0, idle: bool = False):
        """``niceness``: added to the process's (os.nice), so that on a busy machine the cores go to the callers;
        ``idle``: the process also runs in the idle scheduling class, where the platform has one (_schedule_idle)."""
        self._process, self._connection = _started_ahead_or_new()
        with contextlib.suppress(ConnectionError):  # it has ended: the first call says so
            self._connection.send((config, camera, niceness, idle))
        self._lock = threading.Lock()  # one call on the pipe at a time, from whichever thread
        self._ready = False  # the process answered that its FeatureOdometry is built

    def __getattr__(self, name: str):
        from vo_core.features.feature_odometry import FeatureOdometry

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
            except (EOFError, ConnectionError):  # its end of the pipe closed (ConnectionError: with data unread)
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


def _serve(connection: Connection) -> None:
    """The process: load the kernels, then build the feature half it is given, say whether that worked, and answer
    calls until told to stop (or until the parent is gone)."""
    try:
        try:
            _load_kernels()
        except Exception:  # only a warm-up: what is wrong with the run's feature half is raised at its first call
            pass
        config, camera, niceness, idle = connection.recv()
        from vo_core.features.feature_odometry import FeatureOdometry

        try:
            odometry = FeatureOdometry(config, camera)
        except Exception as error:  # raised in the parent at its first call (a missing vocabulary, say)
            connection.send((False, error))
            return
        connection.send((True, None))
        # What the process holds before the map (modules, numba's dispatchers and types) is never garbage: out of the
        # collector's sight, the full collections the growing map triggers take half the time (parking: 0.16 -> 0.09 s).
        gc.freeze()
        os.nice(niceness)  # from here: the start (imports, vocabulary) is waited for by the run's first keyframes
        if idle:
            _schedule_idle()
        while (request := connection.recv()) is not None:
            name, args = request
            try:
                member = getattr(odometry, name)
                answer = (True, member(*args) if callable(member) else member)
            except Exception as error:
                answer = (False, error)
            connection.send(answer)
    except (EOFError, ConnectionError):  # its end of the pipe closed (ConnectionError: with data unread)
        return
    # Told to stop: every answer is sent, and nothing here needs the interpreter's teardown (0.2 s of a run's end,
    # freeing the feature map object by object).
    os._exit(0)


def _schedule_idle() -> None:
    """Linux's idle scheduling class (SCHED_IDLE): the process gets a core only where no other process of normal
    priority wants it, lower than any niceness; where the platform has no such class, the niceness alone holds."""
    if hasattr(os, "SCHED_IDLE"):
        with contextlib.suppress(OSError):  # a sandbox that forbids it: the niceness still holds
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))


def _load_kernels() -> None:
    """The feature half's first keyframes and a recovery on a made-up scene, thrown away: what a process loads once
    (numba's start, the compiled kernels from its cache, the bundled vocabulary, OpenCV's first calls) is loaded
    before a run waits for it. The map is not kept: the run's FeatureOdometry is built afresh, and its results are
    those of a new process (a test compares them)."""
    import cv2

    from vo_core.features.config import FeatureConfig
    from vo_core.features.feature_odometry import FeatureOdometry
    from vo_core.geometry.camera import PinholeCamera

    width, height = WARM_UP_SIZE
    camera = PinholeCamera(width, height, WARM_UP_FOCAL_PX, WARM_UP_FOCAL_PX, width / 2, height / 2)
    grain = np.random.default_rng(0).integers(0, 256, (height // WARM_UP_TEXTURE_CELL_PX,
                                                       width // WARM_UP_TEXTURE_CELL_PX), dtype=np.uint8)
    texture = cv2.resize(grain, WARM_UP_SIZE, interpolation=cv2.INTER_CUBIC)
    odometry = FeatureOdometry(FeatureConfig(), camera)
    window, views = {}, []
    for index in range(WARM_UP_VIEWS):
        T_world_cam = np.eye(4)
        T_world_cam[0, 3] = WARM_UP_BASELINE * index
        # The plane z = depth seen from a camera moved along x: the homography K (I - t n^T / depth) K^-1.
        plane_motion = np.eye(3) - np.outer(T_world_cam[:3, 3], (0.0, 0.0, 1.0)) / WARM_UP_DEPTH
        views.append(cv2.warpPerspective(texture, camera.K @ plane_motion @ np.linalg.inv(camera.K), WARM_UP_SIZE,
                                         borderMode=cv2.BORDER_REFLECT))
        if index != WARM_UP_VIEWS // 2:
            window[index] = T_world_cam
            odometry.add_keyframe(index, float(index), views[index], T_world_cam, WARM_UP_DEPTH, window)
    odometry.recover(views[WARM_UP_VIEWS // 2], WARM_UP_VIEWS - 1)
