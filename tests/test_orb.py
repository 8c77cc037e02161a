"""ORB extraction: coverage of the image, quotas per level, determinism, orientation, masks, degenerate images."""

from __future__ import annotations

import numpy as np
import pytest

from vo_core.features.config import OrbConfig
from vo_core.features.matcher import hamming_rows
from vo_core.features.orb import (
    Features,
    OrbExtractor,
    distribute_quadtree,
    features_per_level,
    level_inv_sigma2s,
    level_scales,
    level_sigma2s,
)
from vo_core.synthetic import make_sequence

GRID = (12, 16)  # rows, columns of the coverage grid: 40 px cells at 640x480
TEXTURED_STD = 6.0  # gray levels: a cell with less contrast than this has nothing FAST could find


@pytest.fixture(scope="module")
def image() -> np.ndarray:
    return make_sequence("smooth", 1, seed=0)[0].image


@pytest.fixture(scope="module")
def extractor() -> OrbExtractor:
    return OrbExtractor(OrbConfig())


@pytest.fixture(scope="module")
def features(extractor, image) -> Features:
    return extractor.extract(image)


def test_features_have_the_documented_layout(features, image):
    config = OrbConfig()
    assert len(features) == config.num_features
    assert features.uv.shape == (len(features), 2) and features.uv.dtype == np.float64
    assert features.descriptors.shape == (len(features), 32) and features.descriptors.dtype == np.uint8
    assert features.response.dtype == np.float32 and features.level.shape == features.angle.shape == (len(features),)
    assert np.all((features.angle >= 0.0) & (features.angle < 360.0))
    height, width = image.shape
    assert np.all((features.uv >= 0) & (features.uv <= [width - 1, height - 1]))
    # Each level delivers its quota on a well-textured image.
    np.testing.assert_array_equal(np.bincount(features.level, minlength=config.num_levels), features_per_level(config))


def test_features_cover_every_textured_part_of_the_image(features, image):
    rows, cols = GRID
    height, width = image.shape
    cells = image[: height // rows * rows, : width // cols * cols].reshape(rows, height // rows, cols, width // cols)
    textured = cells.std(axis=(1, 3)) > TEXTURED_STD
    row = np.clip((features.uv[:, 1] // (height // rows)).astype(int), 0, rows - 1)
    col = np.clip((features.uv[:, 0] // (width // cols)).astype(int), 0, cols - 1)
    covered = np.zeros(GRID, dtype=bool)
    covered[row, col] = True
    assert textured.sum() > 0.5 * textured.size  # the test image is textured almost everywhere
    assert covered[textured].mean() >= 0.9


def test_quadtree_spreads_corners_instead_of_keeping_the_strongest_cluster():
    rng = np.random.default_rng(0)
    cluster = rng.uniform(0, 50, (400, 2)).astype(int)  # strong corners packed in one corner of the image
    spread = rng.uniform(0, 400, (400, 2)).astype(int)  # weaker ones everywhere
    xy = np.concatenate([cluster, spread])
    response = np.concatenate([np.full(400, 100.0), np.full(400, 10.0)])
    keep = distribute_quadtree(xy, response, (0, 0, 400, 400), 100)
    assert len(keep) == 100 and len(np.unique(keep)) == 100
    in_cluster = np.all(xy[keep] < 50, axis=1)
    assert in_cluster.mean() < 0.3  # the top 100 by response would all be in the cluster
    quadrants = {(x >= 200, y >= 200) for x, y in xy[keep]}
    assert len(quadrants) == 4


def test_quadtree_keeps_everything_when_there_are_fewer_corners_than_wanted():
    xy = np.array([[10, 10], [20, 20], [30, 30]])
    keep = distribute_quadtree(xy, np.array([1.0, 3.0, 2.0]), (0, 0, 100, 100), 10)
    np.testing.assert_array_equal(keep, [1, 2, 0])


def test_extraction_is_deterministic(extractor, image, features):
    again = extractor.extract(image)
    for name in ("uv", "level", "angle", "response", "descriptors"):
        np.testing.assert_array_equal(getattr(again, name), getattr(features, name))


@pytest.mark.parametrize("value", [0, 128, 255])
def test_uniform_images_give_no_features(extractor, value):
    empty = extractor.extract(np.full((480, 640), value, dtype=np.uint8))
    assert len(empty) == 0 and empty.descriptors.shape == (0, 32) and empty.uv.shape == (0, 2)


@pytest.mark.parametrize("size", [(160, 120), (1241, 376)])
def test_any_image_size_works(extractor, size):
    width, height = size
    image = make_sequence("smooth", 1, seed=1, width=width, height=height)[0].image
    found = extractor.extract(image)
    assert 0 < len(found) <= OrbConfig().num_features
    assert np.all((found.uv >= 0) & (found.uv <= [width - 1, height - 1]))


def test_colour_images_are_converted(extractor, image, features):
    colour = np.repeat(image[:, :, None], 3, axis=2)
    np.testing.assert_array_equal(extractor.extract(colour).descriptors, features.descriptors)


def test_a_mask_keeps_features_off_the_masked_pixels(extractor, image):
    mask = np.zeros_like(image)
    mask[:, 320:] = 1
    found = extractor.extract(image, mask=mask)
    assert len(found) > 300
    assert np.all(found.uv[:, 0] >= 319.5 - OrbConfig().scale_factor ** (OrbConfig().num_levels - 1))


def test_weak_corners_only_where_a_cell_has_no_strong_one(extractor, image):
    """ORB-SLAM2's two FAST thresholds: minThFAST corners are taken only in the cells where iniThFAST found none.
    The left half's contrast is tripled (every cell has strong corners), the right half's cut to 0.3 (most respond
    below iniThFAST)."""
    config = OrbConfig()
    contrast = image.astype(np.float64)
    mean = contrast.mean()
    contrast[:, :320] = mean + (contrast[:, :320] - mean) * 3.0
    contrast[:, 320:] = mean + (contrast[:, 320:] - mean) * 0.3
    found = extractor.extract(np.clip(contrast, 0, 255).astype(np.uint8))
    level0 = found.subset(found.level == 0)
    left, right = level0.uv[:, 0] < 280, level0.uv[:, 0] > 360  # away from the cells astride the seam
    assert left.sum() > 100 and right.sum() > 20
    assert np.all(level0.response[left] >= config.fast_threshold)
    assert np.any(level0.response[right] < config.fast_threshold)


def test_orientation_turns_with_the_image(extractor, image, features):
    """np.rot90 turns pixel (u, v) to (v, W - 1 - u): level-0 corners land on exact pixels, their intensity
    centroid turns by -90 degrees, and the steered descriptors stay close."""
    turned = extractor.extract(np.ascontiguousarray(np.rot90(image)))
    width = image.shape[1]
    level0 = features.subset(features.level == 0)
    expected = np.column_stack([level0.uv[:, 1], width - 1 - level0.uv[:, 0]])
    turned0 = turned.subset(turned.level == 0)
    gap = np.linalg.norm(expected[:, None, :] - turned0.uv[None, :, :], axis=2)
    same = gap.min(axis=1) < 1e-6
    partner = gap.argmin(axis=1)[same]
    assert same.sum() > 100
    turn = (turned0.angle[partner] - level0.angle[same] + 90.0 + 180.0) % 360.0 - 180.0
    assert np.median(np.abs(turn)) < 1.0
    distance = hamming_rows(level0.descriptors[same], turned0.descriptors[partner])
    assert np.median(distance) < 20


def test_subset_and_empty():
    empty = Features.empty()
    assert len(empty) == 0 and len(empty.subset(np.zeros(0, dtype=int))) == 0
    features = Features(
        uv=np.arange(6.0).reshape(3, 2),
        level=np.array([0, 1, 2]),
        angle=np.array([10.0, 20.0, 30.0]),
        response=np.array([1, 2, 3], dtype=np.float32),
        descriptors=np.arange(96, dtype=np.uint8).reshape(3, 32),
    )
    picked = features.subset(np.array([True, False, True]))
    np.testing.assert_array_equal(picked.level, [0, 2])
    np.testing.assert_array_equal(features.subset([2, 0]).descriptors[0], features.descriptors[2])


def test_scale_helpers_follow_fdmo_equation_6(extractor):
    config = OrbConfig()
    np.testing.assert_allclose(level_scales(config), 1.2 ** np.arange(8))
    np.testing.assert_allclose(level_sigma2s(config), 1.2 ** (2 * np.arange(8)))
    np.testing.assert_allclose(level_inv_sigma2s(config) * level_sigma2s(config), 1.0)
    assert extractor.level_scale(3) == pytest.approx(1.2**3)
    assert extractor.level_sigma2(3) == pytest.approx(1.2**6)
    np.testing.assert_allclose(extractor.level_inv_sigma2(np.array([0, 2])), [1.0, 1.2**-4])


def test_quota_is_a_geometric_series_summing_to_the_total():
    quota = features_per_level(OrbConfig(num_features=1000))
    assert quota.sum() == 1000 and len(quota) == 8
    np.testing.assert_allclose(quota[1:-1] / quota[:-2], 1 / 1.2, atol=0.02)
