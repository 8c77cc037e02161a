"""The result files of a run (the CLI contract), written so that they are valid at every moment.

trajectory.tum, keyframes.tum and events.jsonl grow a line per frame or event, flushed at once (line
buffering), so a run that fails or is interrupted still leaves complete files behind. config.yaml is written
at the start; metrics.json and the final keyframes.tum replace the old file atomically (write, then rename).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from vo_core.config import Config, dump_config
from vo_core.events import Event, FrameResult, MapSnapshot
from vo_core.trajectory import Trajectory, tum_line, write_trajectory

TRAJECTORY_FILE = "trajectory.tum"
KEYFRAMES_FILE = "keyframes.tum"
EVENTS_FILE = "events.jsonl"
METRICS_FILE = "metrics.json"
CONFIG_FILE = "config.yaml"
RESULT_FILES = (TRAJECTORY_FILE, KEYFRAMES_FILE, EVENTS_FILE, METRICS_FILE, CONFIG_FILE)
TUM_HEADER = "# timestamp tx ty tz qx qy qz qw\n"  # the header vo_core.trajectory.write_trajectory writes


class FilesSink:
    """A Sink that writes trajectory.tum, keyframes.tum and events.jsonl into ``out_dir`` as the run goes."""

    def __init__(self, out_dir: str | Path):
        self.out_dir = Path(out_dir)
        self._timestamps: dict[int, float] = {}  # frame index -> timestamp, to date the final keyframe poses
        self._files: dict[str, Any] = {}

    def begin(self, config: Config) -> None:
        """Create the folder, start the line files afresh (each pass over the sequence) and write config.yaml."""
        self._close_files()
        self._timestamps.clear()
        self.out_dir.mkdir(parents=True, exist_ok=True)
        # buffering=1: line-buffered text, every complete line reaches the OS at once.
        self._files = {name: open(self.out_dir / name, "w", buffering=1) for name in
                       (TRAJECTORY_FILE, KEYFRAMES_FILE, EVENTS_FILE)}
        self._files[TRAJECTORY_FILE].write(TUM_HEADER)
        self._files[KEYFRAMES_FILE].write(TUM_HEADER)
        dump_config(config, self.out_dir / CONFIG_FILE)

    # ------------------------------------------------------------------------------------ Sink protocol

    def on_frame(self, frame: Any, result: FrameResult) -> None:
        self._timestamps[result.frame_index] = result.timestamp
        if result.T_world_cam is None:
            return
        line = tum_line(result.timestamp, result.T_world_cam) + "\n"
        self._files[TRAJECTORY_FILE].write(line)
        if result.is_keyframe:
            self._files[KEYFRAMES_FILE].write(line)

    def on_event(self, event: Event) -> None:
        self._files[EVENTS_FILE].write(to_json(event.to_json_dict()) + "\n")

    def on_map(self, snapshot: MapSnapshot) -> None:
        pass  # the keyframes' final poses are written by write_keyframes at the end

    def close(self) -> None:
        self._close_files()

    # ------------------------------------------------------------------------------------ whole files

    def write_keyframes(self, keyframe_poses: dict[int, np.ndarray]) -> None:
        """Replace keyframes.tum by the keyframes' latest poses (a window optimization moves them)."""
        dated = sorted((self._timestamps[i], i) for i in keyframe_poses if i in self._timestamps)
        if not dated:
            return
        self._files[KEYFRAMES_FILE].close()
        keyframes = Trajectory(np.array([t for t, _ in dated]), np.array([keyframe_poses[i] for _, i in dated]))
        path = self.out_dir / KEYFRAMES_FILE
        partial = path.with_name(path.name + ".partial")
        write_trajectory(partial, keyframes, "tum")
        os.replace(partial, path)  # readers never see a half-written file
        self._files[KEYFRAMES_FILE] = open(path, "a", buffering=1)

    def write_metrics(self, metrics: dict[str, Any]) -> None:
        write_text_atomically(self.out_dir / METRICS_FILE, to_json(metrics, indent=2) + "\n")

    def _close_files(self) -> None:
        for handle in self._files.values():
            handle.close()
        self._files = {}


def write_text_atomically(path: Path, text: str) -> None:
    """Readers never see a half-written file: write beside it, then rename over it."""
    partial = path.with_name(path.name + ".partial")
    partial.write_text(text)
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
