"""Camera trajectories for the synthetic scenes, deterministic from a seed.

Each preset gives timestamps and ``T_world_cam`` poses at a fixed frame rate, in the world frame of
``scene.py`` (x right, y down, z forward; the identity pose looks at the room's back wall or at the plane):

- ``smooth``: handheld motion, translation and rotation both smooth random curves (sums of a few sinusoids
  of random frequency and phase), about 1-3 cm and 0.3-1 degree between frames at 30 Hz;
- ``forward``: straight along the optical axis at constant speed, no rotation;
- ``rotation``: smooth rotation about the camera centre, which stays fixed;
- ``planar``: smooth motion facing the single plane of the "plane" scene;
- ``jump``: ``smooth`` with a block of consecutive frames left out: a large baseline between two
  consecutive frames of the sequence (FDMO sec. 5.3.2's frame-drop experiment);
- ``static``: the identity pose in every frame;
- ``loop``: a closed handheld loop through the room that ends where it starts: the frame after the last would be
  the first again, so a sequence played twice in a row moves on smoothly (TUM monoVO's sequences start and end
  at the same place; FDMO sec. 5.3.1's two-loop experiment).
- ``circuit``: one turn round a circle in the room's front half, facing outwards, so that the walls and objects
  pass by in turn and the place of the start cannot be seen from the middle (unlike ``loop``'s): played twice, a
  loop a loop closer can find; closed like ``loop``.

Sums of sinusoids are bounded by the sum of their amplitudes, so the camera stays inside a known box and
orientation range: the room is closed, the plane large enough, and every view is filled.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from vo_core.errors import InputError
from vo_core.geometry.lie import se3, so3_exp


@dataclass(frozen=True)
class TrajectoryConfig:
    frame_rate_hz: float = 30.0  # TUM RGB-D, EuRoC (20 Hz) and TUM monoVO (~25-50 Hz) are all near this
    # Smooth random curves: this many sinusoids per coordinate, frequencies drawn in this range (handheld sway).
    sinusoids: int = 3
    frequency_range_hz: tuple[float, float] = (0.15, 0.5)
    # Bounds of the handheld motion in the room (x, y, z): clear of the walls (>= 3 m) and objects (>= 1.5 m).
    smooth_translation_m: tuple[float, float, float] = (0.5, 0.25, 0.4)
    # Rotation vector bounds (pitch about x, yaw about y, roll about z), radians.
    smooth_rotation_rad: tuple[float, float, float] = (0.15, 0.3, 0.06)
    rotation_only_rad: tuple[float, float, float] = (0.2, 0.4, 0.08)
    # In front of the plane 2.5 m away: the 9 x 7 m plane fills every view of these poses.
    planar_translation_m: tuple[float, float, float] = (0.4, 0.3, 0.3)
    planar_rotation_rad: tuple[float, float, float] = (0.12, 0.15, 0.06)
    forward_step_m: float = 0.02  # per frame: 0.6 m/s at 30 Hz, a walking pace
    forward_start_z_m: float = -1.5
    forward_max_travel_m: float = 3.0  # stops 0.7 m before the nearest panel; longer sequences move slower
    jump_dropped_frames: int = 15  # half a second at 30 Hz: a baseline of 10-40 cm and several degrees
    # The loop: harmonics 1, 2, ... of one turn per sequence (periodic, hence closed), within these bounds.
    loop_translation_m: tuple[float, float, float] = (0.5, 0.2, 0.4)
    loop_rotation_rad: tuple[float, float, float] = (0.1, 0.25, 0.05)
    # The circuit: 1.3 m from the objects and 2 m from the walls at its closest.
    circuit_centre_m: tuple[float, float, float] = (0.0, 0.0, -0.2)
    circuit_radius_m: float = 0.8


@dataclass(frozen=True)
class SyntheticTrajectory:
    timestamps: np.ndarray  # (N,) seconds, frame_numbers / frame rate
    poses: np.ndarray  # (N, 4, 4) T_world_cam
    frame_numbers: np.ndarray  # (N,) ints: consecutive, except across the frames a jump leaves out
    dropped: np.ndarray  # frame numbers left out (the jump preset; empty otherwise)
    scene: str  # the scene preset the trajectory is made for (scene.SCENES)


def smooth_signal(
    rng: np.random.Generator, times: np.ndarray, amplitudes, config: TrajectoryConfig = TrajectoryConfig()
) -> np.ndarray:
    """(N, D) smooth random curves, |curve_d| <= amplitudes[d]: per coordinate, ``config.sinusoids`` sinusoids with
    random frequencies and phases whose amplitudes (random, summing to the bound) split ``amplitudes[d]``."""
    amplitudes = np.asarray(amplitudes, float)
    shape = (config.sinusoids, len(amplitudes))
    frequencies = rng.uniform(*config.frequency_range_hz, shape)
    return _sinusoids(rng, times, amplitudes, frequencies)


def _sinusoids(rng: np.random.Generator, times: np.ndarray, amplitudes: np.ndarray, frequencies: np.ndarray):
    """(N, D) sums of sinusoids of the given (sinusoids, D) ``frequencies`` (Hz) with random phases and random
    amplitudes that split ``amplitudes[d]``."""
    phases = rng.uniform(0.0, 2 * np.pi, frequencies.shape)
    weights = rng.dirichlet(np.ones(len(frequencies)), len(amplitudes)).T  # (sinusoids, D), columns sum to 1
    angles = 2 * np.pi * frequencies[None] * times[:, None, None] + phases[None]
    return np.sum(weights * amplitudes * np.sin(angles), axis=1)


def _poses(rotation_vectors: np.ndarray, positions: np.ndarray) -> np.ndarray:
    return np.array([se3(so3_exp(w), p) for w, p in zip(rotation_vectors, positions)])


def _times(num_frames: int, config: TrajectoryConfig) -> np.ndarray:
    return np.arange(num_frames) / config.frame_rate_hz


def _handheld(num_frames, rng, config, translation_m, rotation_rad) -> np.ndarray:
    times = _times(num_frames, config)
    positions = smooth_signal(rng, times, translation_m, config)
    return _poses(smooth_signal(rng, times, rotation_rad, config), positions)


def _smooth_poses(num_frames: int, rng: np.random.Generator, config: TrajectoryConfig) -> np.ndarray:
    return _handheld(num_frames, rng, config, config.smooth_translation_m, config.smooth_rotation_rad)


def _planar_poses(num_frames: int, rng: np.random.Generator, config: TrajectoryConfig) -> np.ndarray:
    return _handheld(num_frames, rng, config, config.planar_translation_m, config.planar_rotation_rad)


def _rotation_poses(num_frames: int, rng: np.random.Generator, config: TrajectoryConfig) -> np.ndarray:
    rotations = smooth_signal(rng, _times(num_frames, config), config.rotation_only_rad, config)
    return _poses(rotations, np.zeros((num_frames, 3)))


def _forward_poses(num_frames: int, rng: np.random.Generator, config: TrajectoryConfig) -> np.ndarray:
    step = min(config.forward_step_m, config.forward_max_travel_m / max(num_frames - 1, 1))
    positions = np.zeros((num_frames, 3))
    positions[:, 2] = config.forward_start_z_m + step * np.arange(num_frames)
    return _poses(np.zeros((num_frames, 3)), positions)


def _loop_poses(num_frames: int, rng: np.random.Generator, config: TrajectoryConfig) -> np.ndarray:
    """Sinusoids of 1, 2, ... turns per ``num_frames`` frames: every curve repeats after the last frame, so the
    pose of frame ``num_frames`` would be frame 0's."""
    times = _times(num_frames, config)
    turn_hz = config.frame_rate_hz / num_frames
    harmonics = np.arange(1, config.sinusoids + 1, dtype=float)[:, None] * turn_hz
    positions = _sinusoids(rng, times, np.asarray(config.loop_translation_m), np.repeat(harmonics, 3, axis=1))
    rotations = _sinusoids(rng, times, np.asarray(config.loop_rotation_rad), np.repeat(harmonics, 3, axis=1))
    return _poses(rotations, positions)


def _circuit_poses(num_frames: int, rng: np.random.Generator, config: TrajectoryConfig) -> np.ndarray:
    """Frame i at angle 2 pi i / num_frames round the circle, looking outwards along its radius (a yaw of that
    angle): frame ``num_frames`` would be frame 0."""
    angles = 2.0 * np.pi * np.arange(num_frames) / num_frames
    outwards = np.stack([np.sin(angles), np.zeros(num_frames), np.cos(angles)], axis=1)
    positions = np.asarray(config.circuit_centre_m) + config.circuit_radius_m * outwards
    return _poses(np.stack([np.zeros(num_frames), angles, np.zeros(num_frames)], axis=1), positions)


def _static_poses(num_frames: int, rng: np.random.Generator, config: TrajectoryConfig) -> np.ndarray:
    return np.repeat(np.eye(4)[None], num_frames, axis=0)


# preset -> (poses of consecutive frames, the scene they are made for)
_PRESETS: dict[str, tuple[Callable[[int, np.random.Generator, TrajectoryConfig], np.ndarray], str]] = {
    "smooth": (_smooth_poses, "room"),
    "forward": (_forward_poses, "room"),
    "rotation": (_rotation_poses, "room"),
    "planar": (_planar_poses, "plane"),
    "jump": (_smooth_poses, "room"),
    "static": (_static_poses, "room"),
    "loop": (_loop_poses, "room"),
    "circuit": (_circuit_poses, "room"),
}
PRESETS = tuple(_PRESETS)


def make_trajectory(
    preset: str, num_frames: int, seed: int = 0, config: TrajectoryConfig = TrajectoryConfig()
) -> SyntheticTrajectory:
    """``num_frames`` poses of ``preset`` (one of ``PRESETS``). For "jump" they are what is left of
    ``num_frames + config.jump_dropped_frames`` consecutive frames once the block after the middle one is left out."""
    if preset not in _PRESETS:
        raise InputError(f"unknown synthetic preset '{preset}' (known: {', '.join(PRESETS)})")
    if num_frames < 1:
        raise InputError(f"a synthetic sequence needs at least one frame, not {num_frames}")
    make_poses, scene = _PRESETS[preset]
    dropped = np.zeros(0, int)
    if preset == "jump":
        first_dropped = num_frames // 2
        dropped = np.arange(first_dropped, first_dropped + config.jump_dropped_frames)
    total = num_frames + len(dropped)
    poses = make_poses(total, np.random.default_rng([seed, 2]), config)
    frame_numbers = np.setdiff1d(np.arange(total), dropped)
    return SyntheticTrajectory(
        timestamps=frame_numbers / config.frame_rate_hz,
        poses=poses[frame_numbers],
        frame_numbers=frame_numbers,
        dropped=dropped,
        scene=scene,
    )
