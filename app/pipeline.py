"""One run of the odometry over a sequence, start to finish (the shape of kiss-icp's OdometryPipeline).

    open the sequence -> build the Odometry with its sinks -> play the frames through the Player
    -> collect what comes back -> evaluate against ground truth -> write the result files

``run_sequence`` is what ``fdmo run`` calls, and what benchmarks and tests call from Python. The result files
stay valid whatever ends the run (the end of the sequence, a stop, Ctrl-C, an exception): they are written
as the run goes, and metrics.json is (re)written in a ``finally``.
"""

from __future__ import annotations

import dataclasses
import time
from collections import Counter, defaultdict
from collections.abc import Iterable, Sequence as SequenceOf
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from app.kernel_build import kernel_build_seconds, watch_kernel_builds
from app.player import REALTIME_SOURCE, Player
from app.progress import ProgressBar
from app.sinks.files import FilesSink
from vo_core.config import Config, DatasetConfig
from vo_core.datasets import open_sequence
from vo_core.errors import InputError
from vo_core.eval import DEFAULT_MAX_DT_S, evaluate
from vo_core.events import Event, EventKind, FrameResult, MapSnapshot, Sink
from vo_core.features.feature_process import start_ahead
from vo_core.system import Odometry, maps_features_in_a_process
from vo_core.trajectory import Trajectory

SYNTHETIC = "synthetic"  # source synthetic:PRESET[:FRAMES[:WIDTHxHEIGHT]] (open_source)
SYNTHETIC_SIZE = (640, 480)
MIN_POSES_TO_EVALUATE = 3  # a Sim(3) alignment needs three non-collinear positions
# warm_up: long enough for an initialization, a full window of keyframes and its first marginalization (a direct
# keyframe every 2-3 frames of this preset, 7 in the window).
WARM_UP_PRESET, WARM_UP_FRAMES = "smooth", 30

# How a pass ended, as metrics.json reports it.
COMPLETED = "completed"  # the end of the sequence was reached
STOPPED = "stopped"  # player.stop() (a viewer or the caller)
RESTARTED = "restarted"  # a restart was requested; the next pass starts over
INTERRUPTED = "interrupted"  # player.interrupt() (Ctrl-C, SIGTERM) or an exception


@runtime_checkable
class Restartable(Protocol):
    """A sink that shows one pass at a time (the progress bar, the viewers): told when a new pass starts over."""

    def restart(self) -> None: ...


@dataclass
class RunSummary:
    """What a run produced: where its files are and the content of its metrics.json."""

    out_dir: Path
    metrics: dict[str, Any]

    @property
    def status(self) -> str:
        return self.metrics["status"]

    @property
    def tracked_frames(self) -> int:
        return self.metrics["tracked_frames"]

    @property
    def initialization_frame(self) -> int | None:
        return self.metrics["initialization_frame"]

    @property
    def ate_rmse(self) -> float | None:
        evaluation = self.metrics.get("evaluation") or {}
        return evaluation.get("ate", {}).get("rmse")


def open_dataset(source: str | Path, dataset: DatasetConfig, layout: str | None = None,
                 camera_file: str | Path | None = None, start: int | None = None, end: int | None = None,
                 ground_truth_file: str | Path | None = None, stride: int = 1):
    """Open a sequence with the dataset settings of the configuration, cut to frames start..end-1, every
    ``stride``-th."""
    sequence = open_sequence(
        source, layout=layout, camera_file=camera_file, undistort_output=dataset.undistort_output,
        on_bad_image=dataset.on_bad_image, read_ahead=dataset.read_ahead, ground_truth_file=ground_truth_file,
    )
    return _cut(sequence, start, end, stride)


def _cut(sequence, start: int | None, end: int | None, stride: int):
    return sequence.cut(start, end, stride) if start is not None or end is not None or stride != 1 else sequence


def open_source(source: str | Path, dataset: DatasetConfig, layout: str | None = None,
                camera_file: str | Path | None = None, start: int | None = None, end: int | None = None,
                ground_truth_file: str | Path | None = None, stride: int = 1):
    """A dataset folder or video as ``open_dataset`` opens it, or ``synthetic:PRESET[:FRAMES[:WIDTHxHEIGHT]]``: a
    sequence rendered by vo_core.synthetic (seed 0), with its exact ground truth."""
    kind, _, spec = str(source).partition(":")
    if kind != SYNTHETIC:
        return open_dataset(source, dataset, layout, camera_file, start, end, ground_truth_file, stride)
    if layout or camera_file or ground_truth_file:
        raise InputError(f"{source}: a synthetic sequence has its own layout, camera and ground truth")
    from vo_core.synthetic import DEFAULT_NUM_FRAMES, make_sequence

    preset, _, rest = spec.partition(":")
    frames, _, size = rest.partition(":")
    try:
        num_frames = int(frames) if frames else DEFAULT_NUM_FRAMES
        width, height = (int(n) for n in size.split("x")) if size else SYNTHETIC_SIZE
    except ValueError:
        raise InputError(f"{source}: expected synthetic:PRESET[:FRAMES[:WIDTHxHEIGHT]]") from None
    sequence = make_sequence(preset, num_frames, width=width, height=height)
    return _cut(sequence, start, end, stride)


def warm_up(config: Config, camera, num_frames: int = WARM_UP_FRAMES) -> float:
    """Run ``config.method`` over a short synthetic sequence at the camera's image size and throw it away: what
    the first frames, the first keyframes and the first window marginalization load once per process (the
    compiled kernels from numba's cache, numba's typed lists, OpenCV's first calls) is loaded before a live run
    starts, as a live system gets ready before it opens the camera. Returns the seconds it took.

    The throwaway odometry maps on this thread. A run whose feature half maps in a process of its own has that
    process started now (``start_ahead``): it gets ready beside this warm-up, for the run, instead of being the
    throwaway's and closed with it."""
    from vo_core.synthetic import make_sequence

    started = time.perf_counter()
    if maps_features_in_a_process(config):
        start_ahead()
    sequence = make_sequence(WARM_UP_PRESET, num_frames, width=camera.width, height=camera.height)
    track(_synchronous(config), sequence.camera, sequence)
    return time.perf_counter() - started


@dataclass
class Tracked:
    """What ``track`` gives: each frame's result, and the keyframes' poses at the end (a window optimization moves
    them after their frames were tracked: the final trajectory hangs frames on them, FrameResult.reference_keyframe)."""

    results: list[FrameResult]
    keyframe_poses: dict[int, np.ndarray]


def track(config: Config, camera, frames: Iterable) -> Tracked:
    """A fresh odometry fed ``frames`` in order, without sinks (the experiments, the warm-up); frames the loader
    could not read are skipped, as ``fdmo run`` skips them."""
    odometry = Odometry(config, camera)
    try:
        results = [odometry.track(frame) for frame in frames if frame.image is not None]
        return Tracked(results, odometry.final_keyframe_poses())
    finally:
        odometry.close()


def check_method(config: Config, camera) -> None:
    """Build the odometry once, without sinks, so that a method that does not exist yet (or a setting its front
    end refuses) raises InputError before any viewer starts or any file is written. Built without mapping threads:
    what they add (a process for the feature half) would start only to be stopped."""
    Odometry(_synchronous(config), camera).close()


def _synchronous(config: Config) -> Config:
    return dataclasses.replace(config, mapping=dataclasses.replace(config.mapping, threaded=False))


def run_sequence(
    sequence,
    config: Config,
    out_dir: str | Path,
    sinks: Iterable[Sink] = (),
    drops: SequenceOf[tuple[int, int]] = (),
    jumps: SequenceOf[tuple[int, int]] = (),
    *,
    player: Player | None = None,
    show_progress: bool = False,
    keep_alive: bool = False,
) -> RunSummary:
    """Run ``config.method`` over ``sequence``, writing the result files into ``out_dir``.

    ``drops`` are scripted ``(frame_index, count)`` drops and ``jumps`` scripted ``(frame_index, target)`` jumps;
    pass ``player`` instead when a viewer controls playback. With ``keep_alive`` (the live viewer) the run waits
    at the end of the sequence for a restart or a stop; a restart, at any time, starts a fresh odometry from the
    first frame, rewrites the files and restarts the sinks that show a pass (``Restartable``).
    Returns the summary of the last pass.
    """
    watch_kernel_builds()  # the frame rates leave out the time spent building compiled kernels
    if player is None:
        player = Player(sequence, drops, jumps)
    elif drops or jumps:
        raise ValueError("give scripted drops and jumps to the Player, not to run_sequence, when passing a player")
    files = FilesSink(out_dir)
    progress = [ProgressBar(len(sequence), clock=player.playing_time)] if show_progress else []
    run = _Run(sequence, config, files, [*progress, *sinks])
    try:
        while True:
            summary = run.play_once(player)
            restart = player.wait_for_restart() if keep_alive else player.restart_requested
            if not restart:
                return summary
            run.next_pass()
    finally:
        run.close()


class _Run:
    """The odometry, the sinks and the statistics of the pass being played."""

    def __init__(self, sequence, config: Config, files: FilesSink, sinks: list[Sink]):
        self.sequence = sequence
        self.config = config
        self.files = files
        self.sinks = sinks
        self._new_odometry()

    def next_pass(self) -> None:
        """A fresh odometry (and statistics) for the next pass; the sinks are kept, and those that show a pass
        start over."""
        self._new_odometry()
        for sink in self.sinks:
            if isinstance(sink, Restartable):
                sink.restart()

    def _new_odometry(self) -> None:
        self.statistics = _Statistics()
        self.odometry = Odometry(self.config, self.sequence.camera, [self.files, self.statistics, *self.sinks])

    def play_once(self, player: Player) -> RunSummary:
        """One pass from the first frame; the files are finished whatever ends it."""
        self.files.begin(self.config)
        status = INTERRUPTED
        started, started_playing, built = time.perf_counter(), player.playing_time(), kernel_build_seconds()
        try:
            self._play(player)
            status = (COMPLETED if player.finished else RESTARTED if player.restart_requested
                      else INTERRUPTED if player.interrupted else STOPPED)
        finally:
            self.odometry.flush()  # a mapping thread maps what it was given: its events count, its maps are written
            summary = self._finish(status, time.perf_counter() - started, player.playing_time() - started_playing,
                                   kernel_build_seconds() - built)
        return summary

    def _play(self, player: Player) -> None:
        emit = self.odometry.report
        for frame in player.play(on_event=emit):
            if frame.image is None:
                # The loader could not read this image (policy "skip"): the odometry must not see a hole.
                emit(Event(EventKind.FRAME_SKIPPED, frame.index, frame.timestamp,
                           {"path": frame.path, "error": frame.error}))
                continue
            started = time.perf_counter()
            self.odometry.track(frame)
            self.statistics.step_ms.append(1000.0 * (time.perf_counter() - started))

    def _finish(self, status: str, wall_s: float, playing_s: float, kernel_build_s: float) -> RunSummary:
        """metrics.json and the files of the end of a pass. ``playing_s`` is the wall time less the pauses and the
        kernel builds (``kernel_build_s``, the first run's): the frame rate is taken over it, as the progress bar
        and the viser page take theirs."""
        snapshot = self.odometry.map_snapshot()
        self.files.write_keyframes(snapshot.keyframe_poses)
        self.files.write_final_poses(self.odometry.final_keyframe_poses())
        estimate = self.files.estimate()  # trajectory.tum: metrics.json's ATE is what fdmo eval gives on it
        self.files.write_maps(snapshot)
        self.files.write_ground_truth(self._ground_truth_of_the_run())
        metrics = {
            "sequence": self.sequence.name,
            "layout": getattr(self.sequence, "layout", None),
            "stride": getattr(self.sequence, "stride", 1),
            "method": self.config.method,
            "status": status,
            "frames": len(self.sequence),
            **self.statistics.counts(),
            "posed_frames": len(estimate),
            "wall_s": wall_s,
            "playing_s": playing_s,
            "kernel_build_s": kernel_build_s,
            "fps": self.statistics.processed / playing_s if playing_s > 0 else None,
            "timing_ms": self.statistics.timing_ms(),
            "evaluation": _evaluate(estimate, getattr(self.sequence, "ground_truth", None)),
            "map_segments": self.odometry.map_segments_summary(),
        }
        self.files.write_metrics(metrics)
        return RunSummary(self.files.out_dir, metrics)

    def _ground_truth_of_the_run(self) -> Trajectory | None:
        """The sequence's ground truth over the time of the frames played, with the association's tolerance on
        either side: evaluating trajectory.tum against it gives the ATE of metrics.json."""
        ground_truth = getattr(self.sequence, "ground_truth", None)
        if ground_truth is None:
            return None
        timestamps = self.sequence.timestamps
        return ground_truth.within(timestamps.min() - DEFAULT_MAX_DT_S, timestamps.max() + DEFAULT_MAX_DT_S)

    def close(self) -> None:
        self.odometry.close()


class _Statistics:
    """A sink that collects what metrics.json reports: counts, the estimated trajectory, timings per stage."""

    def __init__(self) -> None:
        self.processed = 0
        self.tracked = 0
        self.keyframes = 0
        self.initialization_frame: int | None = None
        self.stage_ms: dict[str, list[float]] = defaultdict(list)
        self.step_ms: list[float] = []  # the whole Odometry.track call, sinks included
        self.events: Counter[str] = Counter()
        self.dropped = 0  # on purpose: --drop, the page's button
        self.late = 0  # --realtime: arrived while the odometry was busy
        self.jumps: list[dict[str, Any]] = []
        self._untracked: set[int] = set()  # frames whose latest processing got no pose
        self._posed_by_start: set[int] = set()  # of those, the first frames of starts: posed when the start succeeded

    def on_frame(self, frame: Any, result: FrameResult) -> None:
        self.processed += 1
        self.tracked += bool(result.tracked)
        self._posed_by_start.discard(result.frame_index)  # processed again (a backward jump): this time counts
        if result.tracked:
            self._untracked.discard(result.frame_index)
        else:
            self._untracked.add(result.frame_index)
        if self.initialization_frame is None and result.tracked:
            self.initialization_frame = result.frame_index
        for stage, ms in result.timings_ms.items():
            self.stage_ms[stage].append(ms)

    def on_event(self, event: Event) -> None:
        self.events[event.kind.value] += 1
        # Counted by event, not by FrameResult.is_keyframe: an initializer makes its first frame a keyframe only
        # once it succeeds, frames later.
        self.keyframes += event.kind is EventKind.KEYFRAME_ADDED
        if event.kind is EventKind.INITIALIZATION_SUCCEEDED and self.initialization_frame is None:
            self.initialization_frame = event.frame_index
        if event.kind is EventKind.FRAMES_DROPPED and event.details.get("source") == REALTIME_SOURCE:
            self.late += int(event.details["count"])
        elif event.kind is EventKind.FRAMES_DROPPED:
            self.dropped += int(event.details["count"])
        if event.kind is EventKind.INITIALIZATION_SUCCEEDED:
            self._count_first_frame_posed(event.details)
        if event.kind is EventKind.INITIALIZATION_REJECTED:
            self.tracked -= len(event.details.get("retracted", []))  # their poses were taken back
            first = event.details.get("first_frame")
            if first in self._posed_by_start:  # so was the first frame's
                self._posed_by_start.remove(first)
                self._untracked.add(first)
                self.tracked -= 1
        if event.kind is EventKind.FRAMES_JUMPED:
            self.jumps.append({key: event.details[key] for key in ("from_frame", "to_frame")})

    def _count_first_frame_posed(self, details: dict[str, Any]) -> None:
        """The start's first frame, untracked when it was processed, is tracked now (as frames.csv says)."""
        first = details.get("first_frame")
        if details.get("first_T_world_cam") is not None and first in self._untracked:
            self._untracked.remove(first)
            self._posed_by_start.add(first)
            self.tracked += 1

    def on_map(self, snapshot: MapSnapshot) -> None:
        pass

    def close(self) -> None:
        pass

    def counts(self) -> dict[str, Any]:
        return {
            "processed_frames": self.processed,
            "tracked_frames": self.tracked,
            "tracked_fraction": self.tracked / self.processed if self.processed else 0.0,
            "keyframes": self.keyframes,
            "skipped_frames": self.events[EventKind.FRAME_SKIPPED.value],
            "dropped_frames": self.dropped,
            "late_frames": self.late,
            "jumps": self.jumps,
            "initialization_frame": self.initialization_frame,
            "events": dict(sorted(self.events.items())),
        }

    def timing_ms(self) -> dict[str, dict[str, float]]:
        stages = {**self.stage_ms, "step": self.step_ms}
        return {
            stage: {"mean": float(np.mean(ms)), "median": float(np.median(ms)), "max": float(np.max(ms))}
            for stage, ms in stages.items() if ms
        }


def _evaluate(estimate: Trajectory, ground_truth: Trajectory | None) -> dict[str, Any] | None:
    """ATE and RPE after Sim(3) alignment; None without ground truth, the reason when it cannot be done."""
    if ground_truth is None:
        return None
    if len(estimate) < MIN_POSES_TO_EVALUATE:
        return {"error": f"only {len(estimate)} estimated poses, at least {MIN_POSES_TO_EVALUATE} are needed"}
    try:
        return evaluate(estimate, ground_truth, align="sim3")
    except InputError as error:  # no estimate timestamp near the ground truth, an estimate that never moves
        return {"error": str(error)}
