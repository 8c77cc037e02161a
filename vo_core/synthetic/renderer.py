"""Ray casting of a scene of textured rectangles: exact images and depth at any pose, on the CPU.

For a plane seen by a pinhole camera, texture coordinates are a homography of pixel coordinates and inverse
depth is affine in them (Hartley & Zisserman, 2nd ed., sec. 13.1). With the plane's camera-frame axes u, v and
origin o, the plane point (a, b) metres along its axes is the camera point M (a, b, 1)^T, M = [u v o]; pixel
p = (x, y, 1) sees it at depth z where z K^-1 p = M (a, b, 1)^T, so

    (a, b, 1)^T = z H p  with  H = M^-1 K^-1,   and the last row gives  1 / z = H_3 . p.

(The third row of M^-1 is n^T / (n . o) with n = u x v, so H_3 . p = n . K^-1 p / (n . o), the inverse depth of
the ray K^-1 p.) Rendering is deferred, in two passes:

1. geometry: for each plane, over the bounding box of its projection, a few affine images (row and column terms
   broadcast) and two divisions give inverse depth and texel coordinates; a z-buffer on inverse depth keeps the
   nearest surface's index and texel coordinates at each pixel;
2. shading: every texture and its mip levels sit in one atlas, so two cv2.remap calls over the whole image
   (bilinear, in the two mip levels around each pixel's level, blended: trilinear filtering) shade all planes.

The mip level is log2 of the texels a pixel covers. A pixel on the ray r = K^-1 p subtends about 1 / (f |r|)
radians at distance z |r|: z / f metres across the ray, z / (f cos(incidence)) along the plane's steepest
direction, cos(incidence) = |n . r| / |r|. The level takes their geometric mean, tpm z / f sqrt(|r| / |n . r|)
texels (tpm: texels per metre), which with n . r = w (n . o) and z = 1 / w is
log2(tpm / (f sqrt|n . o|)) + log2|r| / 2 - 3/2 log2 w: floors stay sharp at grazing angles with little aliasing.
A light Gaussian blur of the final image anti-aliases occlusion edges.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3_inverse, transform_points
from vo_core.synthetic.scene import Scene, TexturedPlane

ATLAS_WIDTH = 4096  # texels
ATLAS_MAX_HEIGHT = 32767  # cv2.remap takes sources smaller than SHRT_MAX on each side
ATLAS_PADDING = 1  # replicated texels around each image in the atlas: bilinear lookups at its edges stay in it
NO_SURFACE = -1  # plane index of pixels that see nothing


@dataclass(frozen=True)
class RenderConfig:
    blur_sigma_px: float = 0.5  # anti-aliasing: smooths occlusion edges while keeping texture detail
    mip_levels: int = 6  # down to 1/32 of the texels: the floor 10 m away at a grazing angle
    near_m: float = 0.05  # surfaces nearer than this are clipped off when bounding a plane's projection
    # |n . o| below this (metres): the camera lies in the plane, which it then sees edge-on (not at all)
    edge_on_distance_m: float = 1e-9


@dataclass
class Rendering:
    image: np.ndarray  # (H, W) uint8, after the brightness change
    depth: np.ndarray  # (H, W) float32, z in the camera frame, inf where no surface is hit


@dataclass
class _GBuffer:
    """What the geometry pass keeps of the nearest surface at each pixel."""

    inverse_depth: np.ndarray  # float32, 0 where nothing was hit (so that any surface in front wins)
    plane: np.ndarray  # int32 plane index, NO_SURFACE where nothing was hit
    texel_x: np.ndarray  # float32 level-0 texel coordinates in that plane's texture
    texel_y: np.ndarray

    @classmethod
    def empty(cls, height: int, width: int) -> "_GBuffer":
        zeros = np.zeros((height, width), np.float32)
        return cls(zeros, np.full((height, width), NO_SURFACE, np.int32), zeros.copy(), zeros.copy())


class Renderer:
    """Renders ``scene`` as seen by ``camera``; per-camera and per-texture work is done once, here."""

    def __init__(self, scene: Scene, camera: PinholeCamera, config: RenderConfig = RenderConfig()):
        self.scene = scene
        self.camera = camera
        self.config = config
        self._columns = np.arange(camera.width, dtype=np.float32)[None, :]
        self._rows = np.arange(camera.height, dtype=np.float32)[:, None]
        self._K_inv = np.linalg.inv(camera.K)
        x = (self._columns - camera.cx) / camera.fx
        y = (self._rows - camera.cy) / camera.fy
        self._half_log2_ray_length = (0.25 * np.log2(1.0 + x**2 + y**2)).astype(np.float32)  # log2|r| / 2
        self._atlas = _TextureAtlas([plane.texture for plane in scene.planes], config.mip_levels)

    def render(self, T_world_cam: np.ndarray, gain: float = 1.0, offset: float = 0.0) -> Rendering:
        """The view from ``T_world_cam``; intensities become gain * I + offset (an affine brightness change)."""
        gbuffer = _GBuffer.empty(self.camera.height, self.camera.width)
        T_cam_world = se3_inverse(T_world_cam)
        # The pose-dependent part of each plane's mip level; the entry after the last is for NO_SURFACE.
        level_offsets = np.zeros(len(self.scene.planes) + 1, np.float32)
        for index, plane in enumerate(self.scene.planes):
            level_offsets[index] = self._rasterize(index, plane, T_cam_world, gbuffer)
        with np.errstate(divide="ignore"):  # log2(0) where nothing was hit: the coarsest level, never shown
            level = self._half_log2_ray_length - np.float32(1.5) * np.log2(gbuffer.inverse_depth)
        level += np.take(level_offsets, gbuffer.plane)
        radiance = self._atlas.sample(gbuffer.plane, gbuffer.texel_x, gbuffer.texel_y, level)
        blurred = cv2.GaussianBlur(radiance, (0, 0), self.config.blur_sigma_px)
        image = np.clip(np.rint(gain * blurred + offset), 0, 255).astype(np.uint8)
        with np.errstate(divide="ignore"):
            depth = np.float32(1.0) / gbuffer.inverse_depth  # 1 / 0 = inf where nothing was hit
        return Rendering(image, depth)

    def _rasterize(self, index: int, plane: TexturedPlane, T_cam_world: np.ndarray, gbuffer: _GBuffer) -> float:
        """Z-buffer ``plane`` into ``gbuffer`` over the bounding box of its projection; return the plane's mip level
        offset log2(tpm / (f sqrt|n . o|)) (0 when it cannot be seen)."""
        R, t = T_cam_world[:3, :3], T_cam_world[:3, 3]
        axis_u, axis_v, origin = R @ plane.axis_u, R @ plane.axis_v, R @ plane.origin + t
        normal_distance = np.cross(axis_u, axis_v) @ origin  # n . o < 0: the camera is on the normal's side
        if abs(normal_distance) < self.config.edge_on_distance_m or (not plane.two_sided and normal_distance > 0):
            return 0.0
        box = self._bounding_box(transform_points(T_cam_world, plane.corners))
        if box is None:
            return 0.0
        H = np.linalg.inv(np.column_stack([axis_u, axis_v, origin])) @ self._K_inv
        w = self._affine(H[2], box)  # inverse depth
        nearest = w > gbuffer.inverse_depth[box]  # implies w > 0: in front of the camera
        with np.errstate(divide="ignore", invalid="ignore"):  # where w <= 0 nothing is kept
            texel_x = self._affine(plane.texels_per_metre * H[0], box) / w
            texel_y = self._affine(plane.texels_per_metre * H[1], box) / w
        for texel, extent in ((texel_x, plane.width_m), (texel_y, plane.height_m)):
            nearest &= texel >= 0
            nearest &= texel <= extent * plane.texels_per_metre
        for target, value in (
            (gbuffer.inverse_depth, w), (gbuffer.texel_x, texel_x), (gbuffer.texel_y, texel_y), (gbuffer.plane, index)
        ):
            np.copyto(target[box], value, where=nearest)
        f = min(self.camera.fx, self.camera.fy)
        return float(np.log2(plane.texels_per_metre / (f * np.sqrt(abs(normal_distance)))))

    def _bounding_box(self, corners_cam: np.ndarray) -> tuple[slice, slice] | None:
        """Row and column slices of the image that the rectangle (camera-frame corners) can cover, or None."""
        polygon = _clip_in_front(corners_cam, self.config.near_m)
        if len(polygon) == 0:
            return None
        uv = self.camera.project(polygon)
        x0, y0 = np.maximum(np.floor(uv.min(axis=0)).astype(int), 0)
        x1 = min(int(np.ceil(uv[:, 0].max())) + 1, self.camera.width)
        y1 = min(int(np.ceil(uv[:, 1].max())) + 1, self.camera.height)
        if x0 >= x1 or y0 >= y1:
            return None
        return slice(y0, y1), slice(x0, x1)

    def _affine(self, coefficients: np.ndarray, box: tuple[slice, slice]) -> np.ndarray:
        """c0 x + c1 y + c2 over the box, float32 (Python floats keep numpy from promoting to float64)."""
        c0, c1, c2 = (float(c) for c in coefficients)
        rows, columns = box
        return (c0 * self._columns[:, columns] + c2) + c1 * self._rows[rows]


class _TextureAtlas:
    """All textures and their mip levels packed in one float32 image, for lookups by (plane, level, texel).

    Mip level l of a texture is cv2.pyrDown applied l times; pyrDown keeps the even texels of the blurred image,
    so level-0 texel x is x / 2^l at level l. Images are packed on shelves (rows of images of similar height), each
    padded by replicated texels.
    """

    def __init__(self, textures: list[np.ndarray], levels: int):
        self.levels = levels
        images = [level for texture in textures for level in _mipmap(texture, levels)]
        padded = [cv2.copyMakeBorder(image, *[ATLAS_PADDING] * 4, cv2.BORDER_REPLICATE) for image in images]
        positions, height = _pack_shelves([image.shape for image in padded], ATLAS_WIDTH)
        if height >= ATLAS_MAX_HEIGHT:
            raise ValueError(f"the scene's textures need a {height}-texel high atlas, more than cv2.remap takes")
        self.image = np.zeros((height, ATLAS_WIDTH), np.float32)
        for image, (row, column) in zip(padded, positions):
            self.image[row : row + image.shape[0], column : column + image.shape[1]] = image
        # Lookup tables by plane * levels + level; NO_SURFACE (-1) wraps around to the last ``levels`` entries,
        # which point far outside the atlas, where cv2.remap's constant border gives 0.
        rows, columns = (np.array(positions, np.float32) + ATLAS_PADDING).T
        outside = np.full(levels, -2.0 * ATLAS_WIDTH, np.float32)
        self._origin_x, self._origin_y = np.concatenate([columns, outside]), np.concatenate([rows, outside])
        self._scale = np.float32(0.5) ** np.arange(levels, dtype=np.float32)

    def sample(self, plane: np.ndarray, texel_x: np.ndarray, texel_y: np.ndarray, level: np.ndarray) -> np.ndarray:
        """Trilinear lookup: bilinear in the mip levels floor(level) and the next, blended linearly."""
        level = np.clip(level, 0, self.levels - 1)
        finer = np.floor(level)
        blend = level - finer
        finer = finer.astype(np.int32)
        coarser = np.minimum(finer + 1, self.levels - 1)
        first_entry = plane * self.levels
        fine = self._lookup(first_entry + finer, finer, texel_x, texel_y)
        if not blend.any():  # every pixel magnified or 1:1
            return fine
        coarse = self._lookup(first_entry + coarser, coarser, texel_x, texel_y)
        return fine + blend * (coarse - fine)

    def _lookup(self, entry, level, texel_x, texel_y) -> np.ndarray:
        scale = np.take(self._scale, level)
        map_x = np.take(self._origin_x, entry) + texel_x * scale
        map_y = np.take(self._origin_y, entry) + texel_y * scale
        return cv2.remap(self.image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def _mipmap(texture: np.ndarray, levels: int) -> list[np.ndarray]:
    """The texture and ``levels - 1`` successive cv2.pyrDown halvings of it."""
    pyramid = [texture]
    while len(pyramid) < levels:
        pyramid.append(cv2.pyrDown(pyramid[-1]))
    return pyramid


def _pack_shelves(shapes: list[tuple[int, int]], width: int) -> tuple[list[tuple[int, int]], int]:
    """(row, column) of each (height, width) image on shelves of ``width``, tallest first; and the total height."""
    positions: list[tuple[int, int]] = [(0, 0)] * len(shapes)
    shelf_top, shelf_height, column = 0, 0, 0
    for index in sorted(range(len(shapes)), key=lambda i: -shapes[i][0]):
        height, image_width = shapes[index]
        if image_width > width:
            raise ValueError(f"a {image_width}-texel wide texture does not fit the {width}-texel atlas")
        if column + image_width > width:
            shelf_top, shelf_height, column = shelf_top + shelf_height, 0, 0
        positions[index] = (shelf_top, column)
        shelf_height = max(shelf_height, height)
        column += image_width
    return positions, shelf_top + shelf_height


def _clip_in_front(polygon: np.ndarray, near: float) -> np.ndarray:
    """The part of a convex camera-frame polygon with z >= near (Sutherland-Hodgman against one plane)."""
    clipped = []
    for start, end in zip(polygon, np.roll(polygon, -1, axis=0)):
        start_in, end_in = start[2] >= near, end[2] >= near
        if start_in:
            clipped.append(start)
        if start_in != end_in:
            clipped.append(start + (near - start[2]) / (end[2] - start[2]) * (end - start))
    return np.array(clipped).reshape(-1, 3)
