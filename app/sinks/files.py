"""The result files of a run (the CLI contract), written so that they are valid at every moment.

trajectory.tum, keyframes.tum, frames.csv and events.jsonl grow a line per frame or event, flushed at once (line
buffering), so a run that fails or is interrupted still leaves complete files behind. config.yaml is written
at the start.

A backward jump (``--jump``) plays frames again. frames.csv and events.jsonl keep a line per processing, in the
order of processing; the TUM files keep one line per timestamp, in time order (TUM readers and evo require
increasing timestamps): the outcome of the frame's latest processing, so a replayed frame's line is its new pose,
and a frame that got no pose when played again loses its line. The first frame of a start is posed when the start
succeeds, frames later (INITIALIZATION_SUCCEEDED): its line enters the TUM files then, and its frames.csv line says
tracked and keyframe. Poses the odometry takes back (a start found wrong, INITIALIZATION_REJECTED) leave the TUM
files, and frames.csv says their frames untracked. At the end, metrics.json, the final keyframes.tum, the ground
truth of the run (groundtruth.tum) and the maps (map_direct.ply, map_features.ply) replace the old files atomically
(write, then rename).
"""

from __future__ import annotations

import functools
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from app.sinks.scene import FEATURE_POINT_COLOR, inverse_depth_colors
from vo_core.config import Config, dump_config
from vo_core.events import POSE_CORRECTIONS, Event, EventKind, FrameResult, MapSnapshot
from vo_core.trajectory import Trajectory, loop_corrected, tum_line, write_trajectory

TRAJECTORY_FILE = "trajectory.tum"
KEYFRAMES_FILE = "keyframes.tum"
FRAMES_FILE = "frames.csv"
EVENTS_FILE = "events.jsonl"
METRICS_FILE = "metrics.json"
CONFIG_FILE = "config.yaml"
RESULT_FILES = (TRAJECTORY_FILE, KEYFRAMES_FILE, FRAMES_FILE, EVENTS_FILE, METRICS_FILE, CONFIG_FILE)
# Written when there is something to write: a ground truth, a non-empty map.
GROUND_TRUTH_FILE = "groundtruth.tum"
DIRECT_MAP_FILE = "map_direct.ply"
FEATURE_MAP_FILE = "map_features.ply"
TUM_HEADER = "# timestamp tx ty tz qx qy qz qw\n"  # the header vo_core.trajectory.write_trajectory writes
PLY_PROPERTIES = (("x", "<f4", "float"), ("y", "<f4", "float"), ("z", "<f4", "float"),
                  ("red", "u1", "uchar"), ("green", "u1", "uchar"), ("blue", "u1", "uchar"))  # name, numpy, PLY
FRAMES_COLUMNS = ("frame", "timestamp", "tracked", "is_keyframe", "rmse_before", "rmse_after", "num_inliers",
                  "divergence_threshold")


class FilesSink:
    """A Sink that writes trajectory.tum, keyframes.tum, frames.csv and events.jsonl into ``out_dir`` as the run
    goes, and the files of the end of a run when told to."""

    def __init__(self, out_dir: str | Path):
        self.out_dir = Path(out_dir)
        self._timestamps: dict[int, float] = {}  # frame index -> timestamp, to date the final keyframe poses
        self._files: dict[str, Any] = {}
        self._trajectory: PoseLines | None = None
        self._keyframes: PoseLines | None = None
        self._retracted: set[float] = set()  # timestamps whose poses the odometry took back
        # timestamp -> (direct keyframe, T_ref_cam) the frame's latest pose hangs on (FrameResult.reference_keyframe)
        self._anchors: dict[float, tuple[int, np.ndarray]] = {}
        self._replayed = False  # a frame was played again (a backward jump): a frame number may be a keyframe twice
        self._latest_frame_time = -np.inf
        self._corrections: list[dict[str, Any]] = []  # POSE_CORRECTIONS events' details, in order: they move poses

    def begin(self, config: Config) -> None:
        """Create the folder, start the line files afresh (each pass over the sequence) and write config.yaml."""
        self._close_files()
        self._timestamps.clear()
        self._retracted.clear()
        self._anchors.clear()
        self._replayed, self._latest_frame_time = False, -np.inf
        self._corrections.clear()
        self.out_dir.mkdir(parents=True, exist_ok=True)
        # buffering=1: line-buffered text, every complete line reaches the OS at once.
        self._files = {name: open(self.out_dir / name, "w", buffering=1) for name in (FRAMES_FILE, EVENTS_FILE)}
        self._files[FRAMES_FILE].write(",".join(FRAMES_COLUMNS) + "\n")
        self._trajectory = PoseLines(self.out_dir / TRAJECTORY_FILE)
        self._keyframes = PoseLines(self.out_dir / KEYFRAMES_FILE)
        dump_config(config, self.out_dir / CONFIG_FILE)

    def estimate(self) -> Trajectory:
        """What trajectory.tum holds: the run's estimate, as ``fdmo eval`` reads it."""
        return self._trajectory.trajectory()

    # ------------------------------------------------------------------------------------ Sink protocol

    def on_frame(self, frame: Any, result: FrameResult) -> None:
        self._timestamps[result.frame_index] = result.timestamp
        self._files[FRAMES_FILE].write(frames_line(result) + "\n")
        self._replayed |= result.timestamp <= self._latest_frame_time
        self._latest_frame_time = max(self._latest_frame_time, result.timestamp)
        self._trajectory.record(result.timestamp, result.T_world_cam)
        if result.T_world_cam is not None and result.reference_keyframe is not None:
            self._anchors[result.timestamp] = (result.reference_keyframe, result.T_ref_cam)
        else:
            self._anchors.pop(result.timestamp, None)
        if result.T_world_cam is not None:
            self._retracted.discard(result.timestamp)  # posed again (a replayed frame)
        if result.is_keyframe:
            self._keyframes.record(result.timestamp, result.T_world_cam)

    def on_event(self, event: Event) -> None:
        self._files[EVENTS_FILE].write(to_json(event.to_json_dict()) + "\n")
        if event.kind is EventKind.INITIALIZATION_SUCCEEDED:
            self._pose_first_keyframe(event.details)
        elif event.kind is EventKind.INITIALIZATION_REJECTED:
            first = self._timestamps.get(event.details.get("first_frame"))
            self._retract([*event.details.get("retracted", []), *([] if first is None else [first])])
        elif event.kind in POSE_CORRECTIONS:
            self._corrections.append(event.details)
            if event.kind is EventKind.MAPS_MERGED:  # the header says which maps the trajectory joins
                start, end = event.details["segments"][0]
                self._trajectory.notes.append(
                    f"the map of {start:.9f}-{end:.9f} s merged into the final map at frame {event.frame_index} "
                    f"(scale {event.details['scale']}): one frame and scale")
            for lines in (self._trajectory, self._keyframes):
                lines.correct(functools.partial(loop_corrected, event.details))

    def _pose_first_keyframe(self, details: dict[str, Any]) -> None:
        """An initializer poses its first frame, as a keyframe, only when it succeeds, frames later: that frame's
        frames.csv line is rewritten (tracked, keyframe) and its pose enters both TUM files, so that every file
        agrees with keyframes.tum (issue 47: frame 0 was a keyframe there, and untracked everywhere else)."""
        timestamp = self._timestamps.get(details.get("first_frame"))
        if timestamp is None or details.get("first_T_world_cam") is None:
            return
        T_world_cam = np.asarray(details["first_T_world_cam"], dtype=float)
        self._trajectory.record(timestamp, T_world_cam)
        self._keyframes.record(timestamp, T_world_cam)
        self._retracted.discard(timestamp)
        self._set_frame_flags({f"{timestamp:.9f}"}, tracked=True, is_keyframe=True)

    def _retract(self, timestamps) -> None:
        """Poses taken back (posed in a start found wrong): their lines leave the TUM files, and their frames.csv
        lines say untracked (rewritten at once, as the TUM files are)."""
        timestamps = [float(t) for t in timestamps]
        self._trajectory.remove(timestamps)
        self._keyframes.remove(timestamps)
        self._retracted.update(timestamps)
        self._set_frame_flags({f"{t:.9f}" for t in timestamps}, tracked=False, is_keyframe=False)

    def _set_frame_flags(self, timestamps: set[str], tracked: bool, is_keyframe: bool) -> None:
        """The frames.csv lines of the frames at ``timestamps`` (as written) get these flags, rewritten at once."""
        if not timestamps:
            return
        path = self.out_dir / FRAMES_FILE
        self._files[FRAMES_FILE].close()
        lines = path.read_text().splitlines()
        for i, line in enumerate(lines[1:], start=1):
            fields = line.split(",")
            if fields[1] in timestamps:
                fields[2], fields[3] = str(int(tracked)), str(int(is_keyframe))
                lines[i] = ",".join(fields)
        self._files[FRAMES_FILE] = rewritten_line_file(path, "".join(line + "\n" for line in lines))

    def on_map(self, snapshot: MapSnapshot) -> None:
        pass  # the keyframes' final poses are written by write_keyframes at the end

    def close(self) -> None:
        self._close_files()

    # ------------------------------------------------------------------------------------ whole files

    def write_keyframes(self, keyframe_poses: dict[int, np.ndarray]) -> None:
        """Replace keyframes.tum by the keyframes' latest poses (a window optimization moves them), moved by every
        loop closed since (a loop moves the keyframes the window no longer holds)."""
        dated = sorted((self._timestamps[i], i) for i in keyframe_poses
                       if i in self._timestamps and self._timestamps[i] not in self._retracted)
        if not dated:
            return
        times = np.array([timestamp for timestamp, _ in dated])
        poses = np.array([keyframe_poses[i] for _, i in dated])
        for details in self._corrections:
            poses = loop_corrected(details, times, poses)
        self._keyframes.replace(dict(zip(times.tolist(), poses)))

    def write_final_poses(self, keyframe_poses: dict[int, np.ndarray]) -> None:
        """trajectory.tum at the end, as DSO's result (printResult) and ORB-SLAM2's (SaveTrajectoryTUM) are written:
        each pose that hangs on a direct keyframe, that keyframe's latest pose (``keyframe_poses``: a window
        optimization moves it after the frame was tracked) times the frame's pose relative to it, moved by every loop
        closed since (as keyframes.tum); the other poses as they were given. A young map's first frames, tracked
        before its window settled its scale, move most (KITTI's first frames: their steps at 85 % of the later
        scale as tracked). A run that played frames again keeps the poses as given: its keyframes are known by
        frame number, and a frame played twice may have been a keyframe twice."""
        if self._replayed:
            return
        anchored = sorted(t for t, (keyframe, _) in self._anchors.items()
                          if keyframe in keyframe_poses and t in self._trajectory)
        if not anchored:
            return
        times = np.array(anchored)
        poses = np.array([keyframe_poses[self._anchors[t][0]] @ self._anchors[t][1] for t in anchored])
        for details in self._corrections:
            poses = loop_corrected(details, times, poses)
        self._trajectory.update(dict(zip(anchored, poses)))

    def write_ground_truth(self, ground_truth: Trajectory | None) -> None:
        """groundtruth.tum: the poses the run is evaluated against (``fdmo plot`` and ``fdmo eval`` read it)."""
        self._write_or_remove(GROUND_TRUTH_FILE, ground_truth is not None and len(ground_truth) > 0,
                              lambda path: write_trajectory_atomically(path, ground_truth))

    def write_maps(self, snapshot: MapSnapshot) -> None:
        """The direct cloud (colored by inverse depth, as in the viewers) and the feature cloud as PLY files; an
        empty cloud has no file."""
        direct, features = snapshot.direct_points_world, snapshot.feature_points_world
        direct_colors = None if direct is None else inverse_depth_colors(snapshot.direct_inverse_depths)
        feature_colors = None if features is None else np.tile(np.uint8(FEATURE_POINT_COLOR), (len(features), 1))
        self._write_cloud(DIRECT_MAP_FILE, direct, direct_colors)
        self._write_cloud(FEATURE_MAP_FILE, features, feature_colors)

    def _write_cloud(self, name: str, points: np.ndarray | None, colors: np.ndarray | None) -> None:
        """Its finite points (no viewer draws NaN or infinity) as ``name``; no points, no file."""
        finite = np.zeros(0, bool) if points is None else np.all(np.isfinite(points), axis=1)
        self._write_or_remove(name, bool(finite.any()), lambda path: write_ply(path, points[finite], colors[finite]))

    def _write_or_remove(self, name: str, present: bool, write) -> None:
        """Write ``name`` with ``write(path)``, or remove the file a previous pass left if there is nothing now."""
        path = self.out_dir / name
        if present:
            write(path)
        else:
            path.unlink(missing_ok=True)

    def write_metrics(self, metrics: dict[str, Any]) -> None:
        write_text_atomically(self.out_dir / METRICS_FILE, to_json(metrics, indent=2) + "\n")

    def _close_files(self) -> None:
        for handle in [*self._files.values(), *filter(None, (self._trajectory, self._keyframes))]:
            handle.close()
        self._files = {}


class PoseLines:
    """A TUM file of one pose per timestamp, in time order, valid at every moment. A pose later than every line is
    appended; one at an earlier time (a frame played again after a backward jump) takes that time's line, or removes
    it when the frame got no pose this time, and the file is rewritten atomically (from lines kept formatted: a
    rewrite is a join, not a formatting of every pose)."""

    def __init__(self, path: Path):
        self.path = path
        self._lines: dict[float, tuple[np.ndarray, str]] = {}  # timestamp -> (T_world_cam, its line)
        self._latest = -np.inf
        self.notes: list[str] = []  # comment lines after the header (the map segments merged into the final map)
        self._handle = open(path, "w", buffering=1)
        self._handle.write(TUM_HEADER)

    def record(self, timestamp: float, T_world_cam: np.ndarray | None) -> None:
        """The outcome of processing the frame at ``timestamp``: its pose, or None (no pose)."""
        if timestamp > self._latest:
            if T_world_cam is not None:
                self._latest = timestamp
                self._lines[timestamp] = (T_world_cam, tum_line(timestamp, T_world_cam))
                self._handle.write(self._lines[timestamp][1] + "\n")
            return
        if T_world_cam is not None:
            self._lines[timestamp] = (T_world_cam, tum_line(timestamp, T_world_cam))
        elif self._lines.pop(timestamp, None) is None:
            return
        self._rewrite()

    def remove(self, timestamps) -> None:
        """The lines at ``timestamps`` go (poses retracted by the odometry); the file is rewritten if any went."""
        removed = [self._lines.pop(float(timestamp), None) for timestamp in timestamps]
        if any(line is not None for line in removed):
            self._rewrite()

    def replace(self, poses: dict[float, np.ndarray]) -> None:
        """The whole file anew: ``poses`` by timestamp."""
        self._lines = {}
        self.update(poses)

    def update(self, poses: dict[float, np.ndarray]) -> None:
        """The lines of ``poses``' timestamps anew (or added), the others kept."""
        self._lines.update({timestamp: (pose, tum_line(timestamp, pose)) for timestamp, pose in poses.items()})
        self._latest = max(self._lines, default=-np.inf)
        self._rewrite()

    def __contains__(self, timestamp: float) -> bool:
        return timestamp in self._lines

    def correct(self, correct) -> None:
        """Every pose anew, ``correct(timestamps, poses)`` (a loop closure moved them)."""
        if self._lines:
            times = sorted(self._lines)
            poses = correct(np.array(times), np.array([self._lines[t][0] for t in times]))
            self.replace(dict(zip(times, poses)))

    def trajectory(self) -> Trajectory:
        times = sorted(self._lines)
        return Trajectory(np.array(times), np.array([self._lines[t][0] for t in times]).reshape(-1, 4, 4))

    def close(self) -> None:
        self._handle.close()

    def _rewrite(self) -> None:
        self._handle.close()
        notes = "".join(f"# {note}\n" for note in self.notes)
        text = TUM_HEADER + notes + "".join(self._lines[t][1] + "\n" for t in sorted(self._lines))
        self._handle = rewritten_line_file(self.path, text)


def frames_line(result: FrameResult) -> str:
    """The frames.csv line of a frame: flags as 1/0, and an empty field where a method has no value."""
    values = (result.frame_index, f"{result.timestamp:.9f}", int(result.tracked), int(result.is_keyframe),
              result.rmse_before, result.rmse_after, result.num_inliers, result.divergence_threshold)
    return ",".join("" if value is None else f"{value:.9g}" if isinstance(value, float) else str(value)
                    for value in values)


def rewritten_line_file(path: Path, text: str):
    """A line file (its handle closed) replaced by ``text`` atomically, then opened again to grow line by line."""
    write_text_atomically(path, text)
    return open(path, "a", buffering=1)


def write_text_atomically(path: Path, text: str) -> None:
    """Readers never see a half-written file: write beside it, then rename over it."""
    _write_atomically(path, lambda partial: partial.write_text(text))


def write_trajectory_atomically(path: Path, trajectory: Trajectory) -> None:
    _write_atomically(path, lambda partial: write_trajectory(partial, trajectory, "tum"))


def write_ply(path: Path, points: np.ndarray, colors: np.ndarray) -> None:
    """A colored point cloud as binary little-endian PLY: x y z as float32, red green blue as uint8."""
    vertices = np.empty(len(points), dtype=[(name, dtype) for name, dtype, _ in PLY_PROPERTIES])
    for column, axis in enumerate("xyz"):
        vertices[axis] = points[:, column]
    for column, channel in enumerate(("red", "green", "blue")):
        vertices[channel] = colors[:, column]
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
              + "".join(f"property {ply_type} {name}\n" for name, _, ply_type in PLY_PROPERTIES) + "end_header\n")
    _write_atomically(path, lambda partial: partial.write_bytes(header.encode("ascii") + vertices.tobytes()))


def _write_atomically(path: Path, write) -> None:
    """Readers never see a half-written file: ``write`` a file beside ``path``, then rename it over ``path``."""
    partial = path.with_name(path.name + ".partial")
    write(partial)
    os.replace(partial, path)


def to_json(value: Any, indent: int | None = None) -> str:
    """Strict JSON (any parser reads it back): numpy values as plain ones, NaN and infinities as null."""
    return json.dumps(_plain(value), indent=indent, allow_nan=False)


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(key): _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(item) for item in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value
