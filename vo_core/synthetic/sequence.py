"""Synthetic sequences: a scene, a trajectory and a camera, played like a dataset sequence.

``SyntheticSequence`` offers what the odometry and the app use of ``vo_core.datasets.Sequence`` (``name``,
``layout``, ``camera``, ``ground_truth``, ``timestamps``, ``len``, indexing, iteration, ``cut``, ``reversed``,
``describe``) and renders each frame when it is asked for. Its frames are ``vo_core.datasets.Frame``s that also
carry the truth: ``depth`` (z in the camera frame, float32, inf where nothing is hit), ``T_world_cam`` and the
brightness change applied (``gain``, ``offset``: image = gain * radiance + offset).

``Frame.index`` is the frame number at the trajectory's frame rate, so after a jump it skips the dropped frames,
as a dataset's frame numbers skip the frames that ``fdmo run --drop`` leaves out.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vo_core.datasets.base import Frame, FrameSelection
from vo_core.errors import InputError
from vo_core.geometry.camera import PinholeCamera, camera_to_dict
from vo_core.synthetic.renderer import RenderConfig, Renderer
from vo_core.synthetic.scene import SCENES
from vo_core.synthetic.trajectories import SyntheticTrajectory, TrajectoryConfig, make_trajectory, smooth_signal
from vo_core.trajectory import Trajectory

DEFAULT_NUM_FRAMES = 60  # two seconds at 30 Hz
# The same field of view at every resolution: fx = fy = 500 px at 640 px wide (64.6 x 51.2 degrees at 640x480,
# between TUM RGB-D's 62 and TUM monoVO's cropped 90 degrees).
FOCAL_PER_WIDTH = 500.0 / 640.0


@dataclass(frozen=True)
class BrightnessConfig:
    """The mild per-frame affine brightness change of ``brightness_change=True`` (auto exposure, flicker): the
    image is gain * radiance + offset with log(gain) and offset smooth random curves within these bounds."""

    log_gain_amplitude: float = 0.15  # gain within e^+-0.15: +-16 %
    offset_amplitude: float = 8.0  # gray levels


@dataclass
class SyntheticFrame(Frame):
    depth: np.ndarray | None = field(default=None, repr=False)
    T_world_cam: np.ndarray | None = field(default=None, repr=False)
    gain: float = 1.0
    offset: float = 0.0


def default_camera(width: int = 640, height: int = 480) -> PinholeCamera:
    """A pinhole camera with fx = fy = 500 at 640 px wide (scaled with the width), centred principal point."""
    focal = FOCAL_PER_WIDTH * width
    return PinholeCamera(width, height, focal, focal, (width - 1) / 2, (height - 1) / 2)


class SyntheticSequence(FrameSelection):
    """Frames rendered on demand along a trajectory. Views made by ``cut`` and ``reversed`` share the renderer."""

    layout = "synthetic"

    def __init__(
        self,
        name: str,
        renderer: Renderer,
        trajectory: SyntheticTrajectory,
        gains: np.ndarray | None = None,
        offsets: np.ndarray | None = None,
    ):
        count = len(trajectory.timestamps)
        self.name = name
        self.renderer = renderer
        self.trajectory = trajectory
        self._gains = np.ones(count) if gains is None else np.asarray(gains, float)
        self._offsets = np.zeros(count) if offsets is None else np.asarray(offsets, float)
        self._selection = np.arange(count)

    # ------------------------------------------------------------------------------------------- views

    @property
    def camera(self) -> PinholeCamera:
        return self.renderer.camera

    @property
    def timestamps(self) -> np.ndarray:
        return self.trajectory.timestamps[self._selection]

    @property
    def indices(self) -> np.ndarray:
        """Frame numbers of the frames of this view, in order."""
        return self.trajectory.frame_numbers[self._selection]

    @property
    def ground_truth(self) -> Trajectory:
        """The true camera-to-world poses of this view's frames (strictly increasing times unless reversed)."""
        return Trajectory(self.timestamps, self.trajectory.poses[self._selection])

    def __len__(self) -> int:
        return len(self._selection)

    def __repr__(self) -> str:
        return (
            f"SyntheticSequence({self.name!r}, frames={len(self)}, "
            f"camera={self.camera.width}x{self.camera.height}, scene={self.renderer.scene.name!r})"
        )

    # ------------------------------------------------------------------------------------------ frames

    def __getitem__(self, position: int) -> SyntheticFrame:
        return self._render(int(self._selection[position]))

    def __iter__(self) -> Iterator[SyntheticFrame]:
        return (self._render(int(row)) for row in self._selection)

    def _render(self, row: int) -> SyntheticFrame:
        pose = self.trajectory.poses[row]
        gain, offset = float(self._gains[row]), float(self._offsets[row])
        rendering = self.renderer.render(pose, gain, offset)
        number = int(self.trajectory.frame_numbers[row])
        return SyntheticFrame(
            index=number,
            timestamp=float(self.trajectory.timestamps[row]),
            image=rendering.image,
            path=f"synthetic:{self.name}/{number}",
            depth=rendering.depth,
            T_world_cam=pose.copy(),
            gain=gain,
            offset=offset,
        )

    # ---------------------------------------------------------------------------------------- describe

    def describe(self) -> dict[str, Any]:
        """What the sequence holds, JSON-serializable, with the keys of ``Sequence.describe``."""
        timestamps = self.timestamps
        span = [float(timestamps.min()), float(timestamps.max())]
        return {
            "name": self.name,
            "layout": self.layout,
            "scene": self.renderer.scene.name,
            "frames": len(self),
            "first_frame_index": int(self.indices[0]),
            "dropped_frames": [int(number) for number in self.trajectory.dropped],
            "resolution": [self.camera.width, self.camera.height],
            "camera": camera_to_dict(self.camera),
            "time_span_s": span,
            "duration_s": span[1] - span[0],
            "exposure_times": False,
            "photometric_calibration": False,
            "ground_truth": {"poses": len(self), "time_span_s": span},
        }


def make_sequence(
    preset: str,
    num_frames: int = DEFAULT_NUM_FRAMES,
    seed: int = 0,
    width: int = 640,
    height: int = 480,
    brightness_change: bool = False,
    trajectory_config: TrajectoryConfig = TrajectoryConfig(),
    render_config: RenderConfig = RenderConfig(),
    brightness_config: BrightnessConfig = BrightnessConfig(),
) -> SyntheticSequence:
    """A synthetic sequence of ``preset`` (one of ``PRESETS``: smooth, forward, rotation, planar, jump, static, loop,
    circuit):
    the scene the preset is made for and its trajectory, both drawn from ``seed``, seen by ``default_camera``.
    With ``brightness_change`` each frame gets its own mild affine brightness change (``BrightnessConfig``)."""
    if width < 1 or height < 1:
        raise InputError(f"a synthetic camera needs a positive size, not {width}x{height}")
    trajectory = make_trajectory(preset, num_frames, seed, trajectory_config)
    renderer = Renderer(SCENES[trajectory.scene](seed), default_camera(width, height), render_config)
    gains = offsets = None
    if brightness_change:
        rng = np.random.default_rng([seed, 3])
        bounds = (brightness_config.log_gain_amplitude, brightness_config.offset_amplitude)
        log_gains, offsets = smooth_signal(rng, trajectory.timestamps, bounds, trajectory_config).T
        gains = np.exp(log_gains)
    return SyntheticSequence(f"synthetic_{preset}_seed{seed}", renderer, trajectory, gains, offsets)

