"""Faults injected into a sequence, as a broken camera, driver, cable or disk would produce them (issue 17).

    case = inject(sequence, Fault("black", at=30, count=10))
    run_sequence(case.sequence, config, out_dir, drops=case.drops)     # app.pipeline

``inject`` works on any sequence that can be indexed (a dataset's ``Sequence``, a ``SyntheticSequence``):

- ``black``, ``grey`` (a covered lens), ``noise``, ``frozen`` (the image before the fault, repeated bit for bit):
  ``count`` frames from position ``at`` get that image instead of their own;
- ``exposure``: from position ``at`` to the end the brightness is multiplied by 4 and clipped (a sudden change of
  exposure that stays);
- ``sensor_noise``: from position ``at`` to the end every image gets its own Gaussian noise (sigma 2 grey levels),
  as a real sensor does: a static camera then no longer sees the same image twice;
- ``drop``: ``count`` frames from position ``at`` never reach the odometry: the player's drop, as
  ``fdmo run --drop``, so the run reports them (FRAMES_DROPPED);
- ``jump_back``: after position ``at`` the camera is back where it was ``count`` frames earlier and goes on from
  there: the frames ``at - count ..`` are played again. Time and frame numbers keep increasing (the camera went
  back; the clock did not), and the ground truth follows.

``corrupt_file`` and ``missing_file`` happen on disk: ``copy_with_file_fault`` makes a copy of a folder's layout
(links to its files) in which the image file of one frame is truncated or absent; the loader then meets it.
``write_tum_rgbd`` writes any sequence as a TUM RGB-D folder, so that synthetic sequences meet the loaders too.

``looping`` plays a closed loop again and again for as many frames as asked (the soak).
"""

from __future__ import annotations

import copy
import dataclasses
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml

from vo_core.datasets.base import Frame
from vo_core.errors import InputError
from vo_core.eval.associate import DEFAULT_MAX_DT_S, associate_timestamps
from vo_core.trajectory import Trajectory, write_trajectory

IMAGE_FAULTS = ("black", "grey", "noise", "frozen", "exposure", "sensor_noise")
ORDER_FAULTS = ("drop", "jump_back")
FILE_FAULTS = ("corrupt_file", "missing_file")
FAULT_KINDS = IMAGE_FAULTS + ORDER_FAULTS + FILE_FAULTS
# Faults whose images say nothing about where the camera is: a pose for one of them is a guess.
BLIND_FAULTS = ("black", "grey", "noise")
GREY_LEVEL = 128
EXPOSURE_GAIN = 4
SENSOR_NOISE_SIGMA = 2.0  # grey levels: a good camera in daylight
# Faults that last from their start to the end of the sequence.
LASTING_FAULTS = ("exposure", "sensor_noise")


@dataclass(frozen=True)
class Fault:
    kind: str  # one of FAULT_KINDS
    at: int = 0  # the position (0-based, in the sequence as given) where it starts
    count: int = 1  # frames it affects (LASTING_FAULTS: to the end; the file faults: one)

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"unknown fault '{self.kind}' (known: {', '.join(FAULT_KINDS)})")
        if self.at < 0 or self.count < 1:
            raise ValueError(f"a fault needs at >= 0 and count >= 1, not {self.at} and {self.count}")

    @property
    def name(self) -> str:
        """As tables name it: "black 10", "jump back 10", "exposure x4", "sensor noise", "missing file"."""
        if self.kind == "exposure":
            return f"exposure x{EXPOSURE_GAIN}"
        words = self.kind.replace("_", " ")
        return words if self.kind in LASTING_FAULTS + FILE_FAULTS else f"{words} {self.count}"


@dataclass
class Injected:
    """A sequence with a fault, ready for ``run_sequence(sequence, ..., drops=drops)``."""

    sequence: "FaultySequence"
    fault: Fault
    drops: list[tuple[int, int]] = field(default_factory=list)  # (frame index, count), the player's drops
    blind: range = range(0)  # positions whose image carries no information (BLIND_FAULTS)


def inject(sequence, fault: Fault, seed: int = 0) -> Injected:
    """``sequence`` with ``fault`` (an image or an order fault; the file faults are made on disk)."""
    if fault.kind in FILE_FAULTS:
        raise ValueError(f"'{fault.kind}' happens on disk: see copy_with_file_fault")
    if fault.at >= len(sequence) or (fault.kind == "jump_back" and fault.count > fault.at):
        raise ValueError(f"{fault} does not fit a sequence of {len(sequence)} frames")
    name = f"{sequence.name}+{fault.name.replace(' ', '_')}"
    if fault.kind == "drop":
        index = int(sequence.indices[fault.at])
        return Injected(FaultySequence(sequence, name), fault, drops=[(index, fault.count)])
    if fault.kind == "jump_back":
        plan = [range(0, fault.at), range(fault.at - fault.count, len(sequence))]
        return Injected(FaultySequence(sequence, name, plan), fault)
    end = len(sequence) if fault.kind in LASTING_FAULTS else min(fault.at + fault.count, len(sequence))
    affected = range(fault.at, end)
    edit = _image_edit(sequence, fault, affected, seed)
    blind = affected if fault.kind in BLIND_FAULTS else range(0)
    return Injected(FaultySequence(sequence, name, edit=edit), fault, blind=blind)


def looping(sequence, count: int, name: str | None = None, keep_frames: bool = True) -> "FaultySequence":
    """``count`` frames of ``sequence`` played again and again from its first frame, time going on: for a closed loop
    (the "loop" preset, whose frame after the last would be the first) a camera that goes round and round. With
    ``keep_frames`` each frame is read (rendered) once and kept, without its depth."""
    plan = [range(len(sequence))[: count - start] for start in range(0, count, len(sequence))]
    return FaultySequence(sequence, name or f"{sequence.name}_x{count}", plan, keep_frames=keep_frames)


class FaultySequence:
    """The frames of ``source`` at the positions of ``plan`` (a list of ranges, played one after the other), each
    passed through ``edit(position_played, frame)``. Within a range frames keep their time intervals and frame
    number steps; each new range starts one nominal frame interval (the median) and one frame number after the
    previous frame, so time and frame numbers always increase. Offers what ``app.pipeline.run_sequence`` and the
    player use of a sequence (``cut`` included)."""

    def __init__(self, source, name: str, plan: list[range] | None = None,
                 edit: Callable[[int, Frame], Frame] | None = None, keep_frames: bool = False):
        self.source = source
        self.name = name
        self.plan = plan if plan is not None else [range(len(source))]
        self._edit = edit
        self._kept: dict[int, Frame] | None = {} if keep_frames else None
        self.positions = np.concatenate([np.arange(r.start, r.stop, r.step) for r in self.plan]).astype(int)
        self.timestamps, self.indices = self._retimed()
        self._played = np.arange(len(self.positions))  # what ``edit`` is told: the position in the whole play

    @property
    def camera(self):
        return self.source.camera

    @property
    def layout(self) -> str:
        return getattr(self.source, "layout", "unknown")

    @property
    def is_reordered(self) -> bool:
        return len(self.plan) != 1 or self.plan[0] != range(len(self.source))

    @property
    def ground_truth(self) -> Trajectory | None:
        truth = getattr(self.source, "ground_truth", None)
        if truth is None or not self.is_reordered:
            return truth
        return self.retime(truth)

    def __len__(self) -> int:
        return len(self.positions)

    def __iter__(self) -> Iterator[Frame]:
        for played, position, timestamp, index in zip(self._played, self.positions, self.timestamps, self.indices):
            frame = dataclasses.replace(self._read(int(position)), index=int(index), timestamp=float(timestamp))
            yield frame if self._edit is None else self._edit(int(played), frame)

    def cut(self, start: int | None = None, end: int | None = None) -> "FaultySequence":
        """The frames played from ``start`` to ``end`` - 1 (Python slice rules), as they are played in the whole."""
        view = copy.copy(self)
        window = slice(start, end)
        view.positions, view.timestamps = self.positions[window], self.timestamps[window]
        view.indices, view._played = self.indices[window], self._played[window]
        return view

    def retime(self, trajectory: Trajectory, max_dt: float = DEFAULT_MAX_DT_S) -> Trajectory:
        """``trajectory`` (timed as the source) as this sequence plays it: the pose nearest each source frame's time
        (within ``max_dt``) at the time the frame is played. The ground truth, or a clean run's estimate."""
        source_times = np.asarray(self.source.timestamps, float)
        association = associate_timestamps(source_times, trajectory.timestamps, max_dt)
        row_of_position = np.full(len(source_times), -1)
        row_of_position[association.first] = association.second
        rows = row_of_position[self.positions]
        known = rows >= 0
        return Trajectory(self.timestamps[known], trajectory.poses[rows[known]])

    def _read(self, position: int) -> Frame:
        if self._kept is None:
            return self.source[position]
        if position not in self._kept:
            frame = self.source[position]
            self._kept[position] = dataclasses.replace(frame, depth=None) if hasattr(frame, "depth") else frame
        return self._kept[position]

    def _retimed(self) -> tuple[np.ndarray, np.ndarray]:
        source_times = np.asarray(self.source.timestamps, float)
        source_indices = np.asarray(self.source.indices, int)
        interval = float(np.median(np.abs(np.diff(source_times)))) if len(source_times) > 1 else 1.0
        times, indices = [], []
        for part in self.plan:
            first = part.start
            positions = np.arange(part.start, part.stop, part.step)
            time_base = source_times[first] if not times else times[-1][-1] + interval
            index_base = source_indices[first] if not indices else indices[-1][-1] + 1
            # Offsets from the range's first frame, so that a range played as recorded keeps its times exactly.
            if part.step > 0:
                times.append(source_times[positions] + (time_base - source_times[first]))
                indices.append(source_indices[positions] + (index_base - source_indices[first]))
            else:
                times.append(time_base + (source_times[first] - source_times[positions]))
                indices.append(index_base + (source_indices[first] - source_indices[positions]))
        return np.concatenate(times), np.concatenate(indices)


def _image_edit(sequence, fault: Fault, affected: range, seed: int) -> Callable[[int, Frame], Frame]:
    """The edit that gives the frames at ``affected`` positions the fault's image."""
    frozen = sequence[fault.at - 1].image if fault.kind == "frozen" and fault.at > 0 else None

    def faulty_image(position: int, image: np.ndarray) -> np.ndarray:
        if fault.kind == "black":
            return np.zeros_like(image)
        if fault.kind == "grey":
            return np.full_like(image, GREY_LEVEL)
        if fault.kind == "noise":
            return np.random.default_rng([seed, position]).integers(0, 256, image.shape, dtype=np.uint8)
        if fault.kind == "exposure":
            return np.clip(image.astype(np.uint16) * EXPOSURE_GAIN, 0, 255).astype(np.uint8)
        if fault.kind == "sensor_noise":
            noise = np.random.default_rng([seed, position]).normal(0.0, SENSOR_NOISE_SIGMA, image.shape)
            return np.clip(np.rint(image + noise), 0, 255).astype(np.uint8)
        return image if frozen is None else frozen  # frozen at the first frame: nothing to repeat

    def edit(position: int, frame: Frame) -> Frame:
        if position not in affected or frame.image is None:
            return frame
        # The irradiance is derived from the new image: a photometrically corrected one would be the old image's.
        return dataclasses.replace(frame, image=faulty_image(position, frame.image), corrected_irradiance=None)

    return edit


# ------------------------------------------------------------------------------------------------ on disk


def copy_with_file_fault(sequence, destination: Path, kind: str, position: int) -> Path:
    """A copy of ``sequence``'s folder at ``destination`` (every file a link to the original) in which the image file
    of the frame at ``position`` is truncated to half its bytes (``corrupt_file``) or absent (``missing_file``).
    Returns the copy's path, to open with the same loader options."""
    if kind not in FILE_FAULTS:
        raise ValueError(f"'{kind}' is not a file fault ({', '.join(FILE_FAULTS)})")
    root = Path(sequence.root).resolve()
    victim = Path(sequence[position].path).resolve()
    if root not in victim.parents:
        raise InputError(f"{victim}: not a file inside {root}: cannot make a copy without it")
    for folder, _, files in os.walk(root):
        target = destination / Path(folder).relative_to(root)
        target.mkdir(parents=True, exist_ok=True)
        for name in files:
            original = Path(folder) / name
            if original != victim:
                (target / name).symlink_to(original)
    if kind == "corrupt_file":
        content = victim.read_bytes()
        (destination / victim.relative_to(root)).write_bytes(content[: len(content) // 2])
    return destination


def write_tum_rgbd(sequence, folder: Path) -> Path:
    """``sequence`` as a TUM RGB-D folder: rgb/<timestamp>.png listed in rgb.txt, its ground truth as
    groundtruth.txt, and its camera (pinhole) in camera.yaml."""
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    lines = ["# timestamp filename"]
    for frame in sequence:
        name = f"rgb/{frame.timestamp:.6f}.png"
        cv2.imwrite(str(folder / name), frame.image)
        lines.append(f"{frame.timestamp:.6f} {name}")
    (folder / "rgb.txt").write_text("\n".join(lines) + "\n")
    camera = sequence.camera
    (folder / "camera.yaml").write_text(yaml.safe_dump({
        "model": "pinhole", "intrinsics": [float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)],
        "resolution": [camera.width, camera.height]}))
    if sequence.ground_truth is not None:
        write_trajectory(folder / "groundtruth.txt", sequence.ground_truth, "tum")
    return folder
