"""Procedural textures for the synthetic scenes: something for both halves of the odometry to hold on to.

A direct method needs intensity gradients in every 32x32 block (DSO's point selector), at several scales so
that its coarse pyramid levels see structure too; ORB needs corners. Real surfaces offer both, so a texture
here is a sum of layers (texel units throughout):

1. smooth value noise at several octaves (stains, shading: gradients everywhere, at every pyramid level),
2. soft blobs (spots at a range of sizes),
3. sharp-edged shapes painted over it (rectangles and polygons at random angles: corners) and lines,

then stretched to a fixed intensity range and blurred by about a texel, so that bilinear lookups give smooth
gradients (Gauss-Newton converges on smooth images) and edges are anti-aliased. Everything is drawn from a
numpy Generator seeded by the caller: the same seed gives the same texture, bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

# Feature counts are given per tile of this many texels squared, so that a large wall is as busy as a small box.
TILE_TEXELS = 256 * 256


@dataclass(frozen=True)
class TextureConfig:
    # Value-noise octaves: (period in texels, amplitude in gray levels) from stains to grain.
    octaves: tuple[tuple[float, float], ...] = ((160.0, 45.0), (56.0, 30.0), (18.0, 22.0), (6.0, 16.0), (2.5, 10.0))
    blobs_per_tile: float = 10.0
    blob_radius_texels: tuple[float, float] = (3.0, 22.0)
    blob_amplitude: float = 45.0  # gray levels, either sign
    shapes_per_tile: float = 9.0  # opaque rectangles and polygons: strong corners for ORB
    shape_size_texels: tuple[float, float] = (8.0, 45.0)
    lines_per_tile: float = 1.5
    line_length_texels: float = 60.0  # standard deviation of the stroke's extent along each axis
    line_thickness_texels: tuple[int, int] = (1, 3)
    # The 2nd..98th percentiles are stretched onto this range (room to spare for brightness changes).
    intensity_range: tuple[float, float] = (25.0, 235.0)
    blur_sigma_texels: float = 0.8  # anti-aliases the painted edges


def make_texture(
    width: int, height: int, rng: np.random.Generator, config: TextureConfig = TextureConfig()
) -> np.ndarray:
    """A (height, width) float32 texture: its 2nd..98th percentiles stretched onto ``config.intensity_range``."""
    texture = _value_noise(width, height, rng, config.octaves)
    tiles = width * height / TILE_TEXELS
    _add_blobs(texture, rng, _count(config.blobs_per_tile * tiles, rng), config)
    _paint_shapes(texture, rng, _count(config.shapes_per_tile * tiles, rng), config)
    _draw_lines(texture, rng, _count(config.lines_per_tile * tiles, rng), config)
    texture = _stretch(texture, config.intensity_range)
    return cv2.GaussianBlur(texture, (0, 0), config.blur_sigma_texels)


def _count(expected: float, rng: np.random.Generator) -> int:
    return int(rng.poisson(expected))


def _value_noise(width: int, height: int, rng: np.random.Generator, octaves) -> np.ndarray:
    """Sum of octaves of smooth noise. Each octave is white noise on a grid of half its period, low-passed on
    the grid (so that no grid pattern shows) and bicubically upsampled: cheap even for the longest periods."""
    texture = np.zeros((height, width), np.float32)
    for period, amplitude in octaves:
        spacing = period / 2
        # A margin of 3 cells on each side keeps the filter's and the interpolation's borders out of view.
        cells_x, cells_y = int(np.ceil(width / spacing)) + 6, int(np.ceil(height / spacing)) + 6
        grid = cv2.GaussianBlur(rng.standard_normal((cells_y, cells_x)).astype(np.float32), (0, 0), 1.0)
        grid *= amplitude / grid.std()
        upsampled = cv2.resize(grid, (int(cells_x * spacing), int(cells_y * spacing)), interpolation=cv2.INTER_CUBIC)
        margin = int(3 * spacing)
        texture += upsampled[margin : margin + height, margin : margin + width]
    return texture


def _add_blobs(texture: np.ndarray, rng: np.random.Generator, count: int, config: TextureConfig) -> None:
    """Soft round spots: a Gaussian-blurred disc layer added to the texture."""
    layer = np.zeros_like(texture)
    height, width = texture.shape
    for _ in range(count):
        radius = rng.uniform(*config.blob_radius_texels)
        centre = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        axes = (int(radius), int(radius * rng.uniform(0.5, 1.0)))
        value = float(rng.uniform(-config.blob_amplitude, config.blob_amplitude))
        cv2.ellipse(layer, centre, axes, float(rng.uniform(0, 180)), 0, 360, value, -1)
    # Softened by a third of the mean radius: blobs stay distinct but have no hard rim.
    texture += cv2.GaussianBlur(layer, (0, 0), np.mean(config.blob_radius_texels) / 3.0)


def _paint_shapes(texture: np.ndarray, rng: np.random.Generator, count: int, config: TextureConfig) -> None:
    """Opaque rotated rectangles and random convex polygons in a random gray: sharp corners."""
    height, width = texture.shape
    low, high = np.percentile(texture, (2, 98)) if count else (0.0, 0.0)
    for _ in range(count):
        size = rng.uniform(*config.shape_size_texels)
        centre = rng.uniform((0, 0), (width, height))
        corners = _rectangle(size, rng) if rng.random() < 0.5 else _convex_polygon(size, rng)
        angle = rng.uniform(0, np.pi)
        rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        polygon = np.round(corners @ rotation.T + centre).astype(np.int32)
        # Anywhere in the noise's range and a little beyond: most shapes contrast with what lies under them.
        value = float(rng.uniform(low - 0.3 * (high - low), high + 0.3 * (high - low)))
        cv2.fillPoly(texture, [polygon], value)


def _rectangle(size: float, rng: np.random.Generator) -> np.ndarray:
    half_w, half_h = size / 2, size * rng.uniform(0.3, 1.0) / 2
    return np.array([[-half_w, -half_h], [half_w, -half_h], [half_w, half_h], [-half_w, half_h]])


def _convex_polygon(size: float, rng: np.random.Generator) -> np.ndarray:
    """3 to 6 vertices at sorted random angles on an ellipse: convex, with corners of varied sharpness."""
    angles = np.sort(rng.uniform(0, 2 * np.pi, int(rng.integers(3, 7))))
    return np.column_stack([np.cos(angles), rng.uniform(0.4, 1.0) * np.sin(angles)]) * size / 2


def _draw_lines(texture: np.ndarray, rng: np.random.Generator, count: int, config: TextureConfig) -> None:
    """Straight dark or bright strokes (cracks, seams): long edges and, where they cross, corners."""
    height, width = texture.shape
    low, high = np.percentile(texture, (5, 95)) if count else (0.0, 0.0)
    for _ in range(count):
        start = rng.uniform((0, 0), (width, height))
        end = start + rng.normal(0, config.line_length_texels, 2)
        thickness = int(rng.integers(config.line_thickness_texels[0], config.line_thickness_texels[1] + 1))
        value = float(low if rng.random() < 0.5 else high)
        cv2.line(texture, tuple(int(c) for c in start), tuple(int(c) for c in end), value, thickness)


def _stretch(texture: np.ndarray, intensity_range: tuple[float, float]) -> np.ndarray:
    low, high = np.percentile(texture, (2, 98))
    target_low, target_high = intensity_range
    stretched = target_low + (texture - low) * (target_high - target_low) / max(high - low, 1e-6)
    return np.clip(stretched, 0.0, 255.0).astype(np.float32)
