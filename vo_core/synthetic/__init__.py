"""Synthetic sequences with exact poses and depth: textured planar scenes ray-cast on the CPU (numpy and
cv2.remap) along preset trajectories, for tests and experiments that need the truth.

    from vo_core.synthetic import make_sequence
    sequence = make_sequence("smooth", num_frames=60, seed=0)   # 640x480, fx = fy = 500
    for frame in sequence:  # frame.image (uint8), frame.depth, frame.T_world_cam
        ...

Presets (``PRESETS``): smooth, forward, rotation, planar, jump, static, loop, circuit (see trajectories.py).
"""

from vo_core.synthetic.renderer import RenderConfig, Renderer, Rendering
from vo_core.synthetic.scene import SCENES, Scene, TexturedPlane, plane_scene, room_scene
from vo_core.synthetic.sequence import (
    DEFAULT_NUM_FRAMES,
    BrightnessConfig,
    SyntheticFrame,
    SyntheticSequence,
    default_camera,
    make_sequence,
)
from vo_core.synthetic.texture import TextureConfig, make_texture
from vo_core.synthetic.trajectories import PRESETS, SyntheticTrajectory, TrajectoryConfig, make_trajectory

__all__ = [
    "DEFAULT_NUM_FRAMES",
    "PRESETS",
    "SCENES",
    "BrightnessConfig",
    "RenderConfig",
    "Renderer",
    "Rendering",
    "Scene",
    "SyntheticFrame",
    "SyntheticSequence",
    "SyntheticTrajectory",
    "TextureConfig",
    "TexturedPlane",
    "TrajectoryConfig",
    "default_camera",
    "make_sequence",
    "make_texture",
    "make_trajectory",
    "plane_scene",
    "room_scene",
]
