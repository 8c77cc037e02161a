"""A tiny ray-cast scene for the direct tests: textured planes rendered at known poses, with true depth.

Independent of vo_core/synthetic so that the direct tests check the direct half alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vo_core.direct.pyramid import remap_points
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3, so3_exp


def make_texture(seed: int, size: int = 512) -> np.ndarray:
    """Blobs at several scales plus sharp-edged shapes: gradients everywhere, as real images have."""
    rng = np.random.default_rng(seed)
    texture = np.zeros((size, size), np.float32)
    for cells, amplitude in ((8, 60.0), (32, 40.0), (96, 25.0)):
        noise = rng.uniform(-1.0, 1.0, (cells, cells)).astype(np.float32)
        texture += amplitude * cv2.resize(noise, (size, size), interpolation=cv2.INTER_CUBIC)
    for _ in range(60):
        centre = tuple(int(c) for c in rng.integers(0, size, 2))
        cv2.circle(texture, centre, int(rng.integers(4, 24)), float(rng.uniform(-60, 60)), -1)
    texture = cv2.GaussianBlur(texture, (0, 0), 1.0)
    return np.clip(texture + 128.0, 0.0, 255.0)


@dataclass
class Plane:
    normal: np.ndarray  # unit normal n, points X with n . X = offset
    offset: float
    origin: np.ndarray  # a point of the plane, texture (0, 0)
    axis_u: np.ndarray  # texture axes in the plane (metres)
    axis_v: np.ndarray
    texture: np.ndarray
    metres_per_texel: float = 0.02  # a texel covers about a pixel on the wall: no aliasing


class PlaneScene:
    """A back wall and a floor in front of a camera looking along +z (y down)."""

    def __init__(self, seed: int = 0, wall_depth: float = 4.0):
        wall = Plane(
            normal=np.array([0.0, 0.0, 1.0]), offset=wall_depth, origin=np.array([-5.12, -5.12, wall_depth]),
            axis_u=np.array([1.0, 0.0, 0.0]), axis_v=np.array([0.0, 1.0, 0.0]), texture=make_texture(seed),
        )
        floor = Plane(
            normal=np.array([0.0, 1.0, 0.0]), offset=1.0, origin=np.array([-5.12, 1.0, -1.0]),
            axis_u=np.array([1.0, 0.0, 0.0]), axis_v=np.array([0.0, 0.0, 1.0]), texture=make_texture(seed + 1),
        )
        self.planes = [wall, floor]

    def render(self, camera: PinholeCamera, T_world_cam: np.ndarray, gain: float = 1.0, offset: float = 0.0):
        """(image float32, depth) of the scene; ``gain``/``offset`` apply an affine brightness change."""
        us, vs = np.meshgrid(np.arange(camera.width, dtype=float), np.arange(camera.height, dtype=float))
        rays_cam = camera.unproject(np.stack([us.ravel(), vs.ravel()], axis=1))  # z = 1
        rays_world = rays_cam @ T_world_cam[:3, :3].T
        centre = T_world_cam[:3, 3]
        depth = np.full(len(rays_cam), np.inf)
        image = np.zeros(len(rays_cam), np.float32)
        for plane in self.planes:
            with np.errstate(divide="ignore", invalid="ignore"):
                s = (plane.offset - plane.normal @ centre) / (rays_world @ plane.normal)
            hit = (s > 0.05) & (s < depth)
            points = centre + s[hit, None] * rays_world[hit]
            relative = points - plane.origin
            size = plane.texture.shape[0] - 1
            # Mirror-repeat the texture over the plane (remap_points itself has a constant border).
            tu = np.abs((relative @ plane.axis_u / plane.metres_per_texel + size) % (2 * size) - size)
            tv = np.abs((relative @ plane.axis_v / plane.metres_per_texel + size) % (2 * size) - size)
            image[hit] = remap_points(plane.texture, tu, tv)
            depth[hit] = s[hit]
        shape = (camera.height, camera.width)
        return (gain * image + offset).reshape(shape).astype(np.float32), depth.reshape(shape)


def small_camera(width: int = 320, height: int = 240) -> PinholeCamera:
    return PinholeCamera(width, height, fx=0.8 * width, fy=0.8 * width, cx=(width - 1) / 2, cy=(height - 1) / 2)


def pose(rotation_vector=(0.0, 0.0, 0.0), translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    return se3(so3_exp(np.asarray(rotation_vector, float)), np.asarray(translation, float))


@dataclass
class SyntheticFrame:
    index: int
    timestamp: float
    image: np.ndarray  # uint8
    irradiance: np.ndarray  # float32
    exposure_ms: float | None = None
    depth: np.ndarray | None = None


def render_frame(scene: PlaneScene, camera: PinholeCamera, index: int, T_world_cam: np.ndarray, **brightness):
    image, depth = scene.render(camera, T_world_cam, **brightness)
    gray = np.clip(np.round(np.nan_to_num(image)), 0, 255).astype(np.uint8)
    return SyntheticFrame(index, index / 30.0, gray, gray.astype(np.float32), None, depth)


def umeyama_sim3(source: np.ndarray, target: np.ndarray):
    """Scale, rotation, translation minimizing |target - (s R source + t)| (Umeyama 1991)."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    xs, xt = source - mu_s, target - mu_t
    U, D, Vt = np.linalg.svd(xt.T @ xs / len(source))
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    s = np.trace(np.diag(D) @ S) / (xs**2).sum(1).mean()
    return s, R, mu_t - s * R @ mu_s


def aligned_ate(estimated: np.ndarray, truth: np.ndarray) -> float:
    """RMSE of camera positions after Sim(3) alignment."""
    s, R, t = umeyama_sim3(estimated, truth)
    aligned = s * estimated @ R.T + t
    return float(np.sqrt(np.mean(np.sum((aligned - truth) ** 2, axis=1))))


def test_scene_depth_is_consistent_between_views():
    """The renderer's depth reprojects a pixel onto the same texture in a second view."""
    scene = PlaneScene(seed=3)
    camera = small_camera(160, 120)
    T_a = pose()
    T_b = pose((0.0, 0.02, 0.0), (0.1, 0.0, 0.0))
    image_a, depth_a = scene.render(camera, T_a)
    image_b, _ = scene.render(camera, T_b)
    uv = np.array([[40.0, 30.0], [100.0, 60.0], [80.0, 100.0]])
    points = camera.unproject(uv) * depth_a[uv[:, 1].astype(int), uv[:, 0].astype(int)][:, None]
    in_b = (points - T_b[:3, 3] + T_a[:3, 3]) @ T_b[:3, :3]
    uv_b = camera.project(in_b)
    sampled = remap_points(image_b, uv_b[:, 0], uv_b[:, 1])
    np.testing.assert_allclose(sampled, image_a[uv[:, 1].astype(int), uv[:, 0].astype(int)], atol=2.0)
