"""The compiled kernels of direct alignment agree with a plain numpy statement of the same equations."""

import cv2
import numpy as np

from vo_core.direct.config import PyramidConfig
from vo_core.direct.photometric_kernels import (
    TERM_COLUMNS, bilinear3, bilinear_gradient, normal_equations, search_line, warp_residuals,
)
from vo_core.direct.pyramid import ImagePyramid
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import se3_exp

WIDTH, HEIGHT = 96, 72
INTRINSICS = np.array([80.0, 82.0, 47.5, 35.5])
HUBER, CUTOFF, BORDER = 9.0, 40.0, 2.0


def packed_image(rng) -> np.ndarray:
    intensity = cv2.GaussianBlur(rng.uniform(0, 255, (HEIGHT, WIDTH)).astype(np.float32), (0, 0), 2.0)
    gx, gy = np.zeros_like(intensity), np.zeros_like(intensity)
    gx[:, 1:-1] = 0.5 * (intensity[:, 2:] - intensity[:, :-2])
    gy[1:-1] = 0.5 * (intensity[2:] - intensity[:-2])
    return np.dstack([intensity, gx, gy])


def reference_residuals(rays, idepth, color, T, packed, factor, offset):
    """calcRes in numpy: warp, bilinear lookup (cv2.remap), Huber weights, cutoff."""
    fx, fy, cx, cy = INTRINSICS
    warped = rays @ T[:3, :3].T + idepth[:, None] * T[:3, 3]
    u, v = warped[:, 0] / warped[:, 2], warped[:, 1] / warped[:, 2]
    Ku, Kv = fx * u + cx, fy * v + cy
    inside = (Ku > BORDER) & (Kv > BORDER) & (Ku < WIDTH - 1 - BORDER) & (Kv < HEIGHT - 1 - BORDER)
    valid = (warped[:, 2] > 0) & inside
    map_u, map_v = Ku[valid, None].astype(np.float32), Kv[valid, None].astype(np.float32)
    hit = np.stack([cv2.remap(packed[..., c], map_u, map_v, cv2.INTER_LINEAR)[:, 0] for c in range(3)], axis=1)
    residual = hit[:, 0] - (factor * color[valid] + offset)
    good = np.abs(residual) <= CUTOFF
    weight = np.minimum(1.0, HUBER / np.abs(residual))
    saturated_energy = (2 * HUBER * CUTOFF - HUBER**2) * np.sum(~good)
    energy = np.sum((weight * residual * residual * (2 - weight))[good]) + saturated_energy
    new_idepth = idepth[valid] / warped[valid, 2]
    columns = [u[valid], v[valid], new_idepth, hit[:, 1], hit[:, 2], residual, weight, color[valid]]
    return np.stack(columns, axis=1)[good], int(valid.sum()), int(np.sum(~good)), energy


def test_warp_residuals_and_normal_equations_match_numpy():
    rng = np.random.default_rng(4)
    packed = packed_image(rng)
    uv = np.c_[rng.uniform(0, WIDTH - 1, 600), rng.uniform(0, HEIGHT - 1, 600)]
    rays = np.c_[(uv - INTRINSICS[2:]) / INTRINSICS[:2], np.ones(len(uv))].astype(np.float32)
    idepth = rng.uniform(0.3, 2.0, len(uv)).astype(np.float32)
    color = rng.uniform(0, 255, len(uv)).astype(np.float32)
    T = se3_exp(np.array([0.03, -0.02, 0.05, 0.01, -0.02, 0.015]))
    factor, offset = 1.1, -4.0

    terms, count, num_terms, saturated, energy = warp_residuals(
        rays, idepth, color, T[:3, :3], T[:3, 3], INTRINSICS, BORDER, packed, factor, offset, HUBER, CUTOFF
    )
    expected, expected_terms, expected_saturated, expected_energy = reference_residuals(
        rays.astype(float), idepth.astype(float), color.astype(float), T, packed, factor, offset
    )
    assert terms.shape[1] == TERM_COLUMNS
    assert (num_terms, saturated, count) == (expected_terms, expected_saturated, len(expected))
    assert 0 < saturated < num_terms < len(uv)  # the case exercises out-of-view and saturated terms
    # cv2.remap interpolates with 1/32-pixel weights, the kernel exactly: agreement to that resolution.
    np.testing.assert_allclose(terms[:count], expected, rtol=1e-3, atol=0.3)
    assert abs(energy - expected_energy) < 1e-2 * expected_energy

    reference_b = 3.0
    H, b = normal_equations(terms, count, INTRINSICS[0], INTRINSICS[1], factor, reference_b)
    u, v, d, gx, gy, r, w, c = terms[:count].astype(float).T
    dx, dy = gx * INTRINSICS[0], gy * INTRINSICS[1]
    J = np.stack([d * dx, d * dy, -d * (u * dx + v * dy), -(u * v * dx + dy * (1 + v * v)),
                  u * v * dy + dx * (1 + u * u), u * dy - v * dx, factor * (reference_b - c), -np.ones(count)], axis=1)
    np.testing.assert_allclose(H, (J * w[:, None]).T @ J / count, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(b, (J * w[:, None]).T @ r / count, rtol=1e-6, atol=1e-9)
    assert np.allclose(H, H.T)


def test_the_line_search_finds_the_matching_step_and_rates_it():
    rng = np.random.default_rng(5)
    intensity = packed_image(rng)[..., 0].copy()
    rotated = np.array([[0, -2], [-1, -1], [1, -1], [-2, 0], [0, 0], [2, 0], [-1, 1], [0, 2]], float)
    start_u, start_v = np.array([20.0, 30.0]), np.array([30.0, 20.0])
    dx, dy = np.array([1.0, 0.6]), np.array([0.0, 0.8])
    true_step = np.array([13, 5])  # both land on whole pixels, where the colors were read
    true_u, true_v = start_u + true_step * dx, start_v + true_step * dy
    color = np.array([[intensity[int(round(v + o[1])), int(round(u + o[0]))] for o in rotated]
                      for u, v in zip(true_u, true_v)], dtype=np.float32)
    energies = np.empty(30)
    best_u, best_v, quality = np.array([
        search_line(intensity, start_u[i], start_v[i], dx[i], dy[i], 30, rotated, color[i], 1.0, 0.0, HUBER, 1e5, 2,
                    energies) for i in range(2)]).T
    np.testing.assert_allclose(best_u, true_u, atol=1e-6)
    np.testing.assert_allclose(best_v, true_v, atol=1e-6)
    assert np.all(quality > 10.0)  # the match is unambiguous on this texture


def test_gradients_from_the_intensity_are_the_packed_images_to_the_bit():
    """The window's linearization reads only the intensity; what it interpolates must be exactly what the tracker
    reads from the packed image, or the same window would optimize differently. Checked on an 8-bit image (level 0)
    and on a level of averaged, fractional intensities."""
    rng = np.random.default_rng(3)
    image = cv2.GaussianBlur(rng.uniform(0, 255, (4 * HEIGHT, 4 * WIDTH)), (0, 0), 3.0).round()
    camera = PinholeCamera(4 * WIDTH, 4 * HEIGHT, *(4 * INTRINSICS))
    for level in ImagePyramid(image, camera, PyramidConfig()).levels[:3]:
        height, width = level.intensity.shape
        for u, v in rng.uniform([1.0, 1.0], [width - 2.0, height - 2.0], (500, 2)):
            assert bilinear_gradient(level.intensity, u, v) == bilinear3(level.packed, u, v)
