"""Scenes of textured rectangles: a closed room with boxes and panels in it, and a single plane.

World frame: x right, y down, z forward (the camera frame of the identity pose), metres. A camera at the origin
looking along +z sees the room's back wall, with the floor 1.5 m below it.

Every surface is a ``TexturedPlane``: a rectangle origin + a axis_u + b axis_v with 0 <= a <= width_m and
0 <= b <= height_m, whose texture maps texel (column, row) = (a, b) x texels_per_metre (texel centres, as
pixel (0, 0) is the centre of the top-left pixel). Textures are sized so that a texel covers about a pixel of a
640x480 view (fx = 500) from the distances the trajectories keep: the renderer mip-maps what is farther.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np

from vo_core.geometry.lie import so3_exp
from vo_core.synthetic.texture import TextureConfig, make_texture


@dataclass(frozen=True)
class TexturedPlane:
    name: str
    origin: np.ndarray  # (3,) world point of texel (0, 0)
    axis_u: np.ndarray  # (3,) unit vector along texture columns
    axis_v: np.ndarray  # (3,) unit vector along texture rows, orthogonal to axis_u
    width_m: float
    height_m: float
    texels_per_metre: float
    texture: np.ndarray = field(repr=False)  # float32 (rows, columns) covering the whole rectangle
    two_sided: bool = True  # False for box faces: seen only from the side normal = axis_u x axis_v points to

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.axis_u, self.axis_v)

    @property
    def corners(self) -> np.ndarray:
        """(4, 3) world corners, in order around the rectangle."""
        u, v = self.width_m * self.axis_u, self.height_m * self.axis_v
        return self.origin + np.array([np.zeros(3), u, u + v, v])

    def point(self, a: float, b: float) -> np.ndarray:
        """The world point at (a, b) metres along (axis_u, axis_v)."""
        return self.origin + a * self.axis_u + b * self.axis_v


@dataclass(frozen=True)
class Scene:
    name: str
    planes: tuple[TexturedPlane, ...]


def textured_plane(
    name: str,
    origin,
    axis_u,
    axis_v,
    size_m: tuple[float, float],
    texels_per_metre: float,
    rng: np.random.Generator,
    two_sided: bool = True,
    texture_config: TextureConfig = TextureConfig(),
) -> TexturedPlane:
    """A rectangle with a fresh texture drawn from ``rng``, one texel wider and taller than the rectangle so that
    its far edges (a = width_m, b = height_m) fall on texel centres."""
    width_m, height_m = size_m
    columns = int(np.ceil(width_m * texels_per_metre)) + 1
    rows = int(np.ceil(height_m * texels_per_metre)) + 1
    texture = make_texture(columns, rows, rng, texture_config)
    texture.setflags(write=False)  # scenes are cached and shared
    return TexturedPlane(
        name=name,
        origin=np.asarray(origin, float),
        axis_u=np.asarray(axis_u, float),
        axis_v=np.asarray(axis_v, float),
        width_m=float(width_m),
        height_m=float(height_m),
        texels_per_metre=float(texels_per_metre),
        texture=texture,
        two_sided=two_sided,
    )


def box(
    name: str, centre, size_m, yaw_rad: float, texels_per_metre: float, rng: np.random.Generator
) -> list[TexturedPlane]:
    """The 6 one-sided faces of a box rotated by ``yaw_rad`` about the vertical (y) axis, normals outward."""
    rotation = so3_exp(np.array([0.0, yaw_rad, 0.0]))
    half = np.asarray(size_m, float) / 2
    centre = np.asarray(centre, float)
    faces = []
    # Each face: (outward axis, its sign, the face's u axis). v = normal x u keeps u x v = the outward normal.
    for axis, sign, u_axis in ((0, 1, 2), (0, -1, 2), (1, 1, 0), (1, -1, 0), (2, 1, 0), (2, -1, 0)):
        normal_local = np.eye(3)[axis] * sign
        u_local = np.eye(3)[u_axis]
        v_local = np.cross(normal_local, u_local)
        v_axis = int(np.argmax(np.abs(v_local)))
        origin_local = normal_local * half - u_local * half - v_local * half
        faces.append(
            textured_plane(
                f"{name}_{'+-'[sign < 0]}{'xyz'[axis]}",
                centre + rotation @ origin_local,
                rotation @ u_local,
                rotation @ v_local,
                (2 * half[u_axis], 2 * half[v_axis]),
                texels_per_metre,
                rng,
                two_sided=False,
            )
        )
    return faces


# ------------------------------------------------------------------------------------------------- presets

# The room: x in [-4, 4], y in [-2.5, 1.5] (floor 1.5 m below the origin), z in [-3, 8]. Closed on all six sides,
# so that a camera inside it sees a surface at every pixel whatever its orientation.
ROOM_MIN = np.array([-4.0, -2.5, -3.0])
ROOM_MAX = np.array([4.0, 1.5, 8.0])
ROOM_TEXELS_PER_METRE = 80.0  # 1.25 cm texels: walls 4-8 m away (0.8-1.6 cm a pixel), the floor nearer
OBJECT_TEXELS_PER_METRE = 150.0  # objects 2-5 m away: 0.4-1 cm a pixel
# Shading of the room: a distant light above, right of and behind the camera, plus ambient light. Constant on
# each plane (Lambert), so views stay photometrically consistent, while surfaces meeting at an edge differ.
LIGHT_DIRECTION = np.array([0.3, -1.0, -0.5]) / np.linalg.norm([0.3, -1.0, -0.5])  # towards the light
AMBIENT_SHARE = 0.6
PLANE_DEPTH_M = 2.5  # the planar scene's plane, fronto-parallel to the identity pose
PLANE_SIZE_M = (9.0, 7.0)  # fills the view of the planar trajectory's poses with a margin
PLANE_TEXELS_PER_METRE = 180.0  # 5 mm texels: about a pixel at 2.5 m


# Scenes take a fraction of a second to texture and are immutable: sequences of the same seed share them.
SCENE_CACHE_SIZE = 4


@lru_cache(maxsize=SCENE_CACHE_SIZE)
def room_scene(seed: int = 0) -> Scene:
    """A closed room with two boxes on the floor, one hanging box and two floating panels at 2-6 m from the
    origin, overlapping in the view from the origin so that there are occlusion edges at several depths."""
    rng = np.random.default_rng([seed, 0])
    lo, hi = ROOM_MIN, ROOM_MAX
    x, y, z = np.eye(3)
    size = hi - lo
    walls_tpm = ROOM_TEXELS_PER_METRE
    planes = [
        textured_plane("back_wall", (lo[0], lo[1], hi[2]), x, y, (size[0], size[1]), walls_tpm, rng),
        textured_plane("front_wall", (lo[0], lo[1], lo[2]), x, y, (size[0], size[1]), walls_tpm, rng),
        textured_plane("left_wall", (lo[0], lo[1], lo[2]), z, y, (size[2], size[1]), walls_tpm, rng),
        textured_plane("right_wall", (hi[0], lo[1], lo[2]), z, y, (size[2], size[1]), walls_tpm, rng),
        textured_plane("floor", (lo[0], hi[1], lo[2]), x, z, (size[0], size[2]), walls_tpm, rng),
        textured_plane("ceiling", (lo[0], lo[1], lo[2]), x, z, (size[0], size[2]), walls_tpm, rng),
    ]
    floor_y, tpm = hi[1], OBJECT_TEXELS_PER_METRE
    planes += box("box_left", (-1.3, floor_y - 0.5, 3.2), (1.0, 1.0, 1.0), 0.5, tpm, rng)
    planes += box("box_right", (1.6, floor_y - 0.7, 4.6), (1.4, 1.4, 1.0), -0.35, tpm, rng)
    planes += box("box_hanging", (-0.4, -1.1, 5.5), (0.9, 0.6, 0.7), 0.9, tpm, rng)
    tilt = so3_exp(np.array([0.15, -0.5, 0.05]))
    planes += [
        textured_plane("panel_near", (-0.1, -0.6, 2.2), x, y, (1.1, 0.8), tpm, rng),
        textured_plane("panel_tilted", (0.6, -1.3, 3.6), tilt @ x, tilt @ y, (1.3, 1.0), tpm, rng),
    ]
    return Scene("room", tuple(_lit(plane) for plane in planes))


@lru_cache(maxsize=SCENE_CACHE_SIZE)
def plane_scene(seed: int = 0) -> Scene:
    """One textured plane at ``PLANE_DEPTH_M`` facing the identity pose, centred on its optical axis."""
    rng = np.random.default_rng([seed, 1])
    width, height = PLANE_SIZE_M
    x, y, _ = np.eye(3)
    origin = (-width / 2, -height / 2, PLANE_DEPTH_M)
    plane = textured_plane("plane", origin, x, y, PLANE_SIZE_M, PLANE_TEXELS_PER_METRE, rng)
    return Scene("plane", (plane,))


def _lit(plane: TexturedPlane) -> TexturedPlane:
    """The plane with its texture scaled by ambient + diffuse Lambertian shading (both sides of a two-sided plane
    are lit alike: its normal's sign is arbitrary)."""
    cosine = plane.normal @ LIGHT_DIRECTION
    diffuse = abs(cosine) if plane.two_sided else max(cosine, 0.0)
    texture = plane.texture * np.float32(AMBIENT_SHARE + (1.0 - AMBIENT_SHARE) * diffuse)
    texture.setflags(write=False)
    return replace(plane, texture=texture)


SCENES = {"room": room_scene, "plane": plane_scene}
