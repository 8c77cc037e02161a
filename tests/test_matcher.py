"""Descriptor matching: Hamming distances, the rotation histogram, matching within vocabulary nodes, guided search
by projection and epipolar search, each checked against a known homography or known poses and depth."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vo_core.features.config import OrbConfig, VocabularyConfig
from vo_core.features.matcher import (
    epipolar_distance_squared,
    epipole_in_b,
    fundamental_matrix,
    hamming,
    hamming_rows,
    least_median_descriptors,
    match_by_bow,
    match_exhaustive,
    orientation_consistent,
    search_by_projection,
    search_epipolar,
)
from vo_core.features.orb import Features, OrbExtractor, level_sigma2s
from vo_core.features.vocabulary import train_vocabulary
from vo_core.geometry.lie import se3_inverse, transform_points
from vo_core.synthetic import make_sequence

TURN_DEG, ZOOM = 30.0, 1.2  # the known homography: a turn about the image centre and a zoom
CORRECT_PX = 3.0  # a match is right if it lies this close to where the truth puts it (times the level scale)


def _bits(descriptors: np.ndarray) -> np.ndarray:
    return np.unpackbits(descriptors, axis=1).astype(int)


def _truth_error(uv_expected: np.ndarray, features: Features, index: np.ndarray) -> np.ndarray:
    """Distance of the matched features to where the truth puts them, in units of their level's scale."""
    scale = OrbConfig().scale_factor ** features.level[index]
    return np.linalg.norm(uv_expected - features.uv[index], axis=1) / scale


@pytest.fixture(scope="module")
def homography_pair():
    image = make_sequence("planar", 1, seed=0)[0].image
    height, width = image.shape
    H = np.vstack([cv2.getRotationMatrix2D(((width - 1) / 2, (height - 1) / 2), TURN_DEG, ZOOM), [0, 0, 1]])
    warped = cv2.warpPerspective(image, H, (width, height), flags=cv2.INTER_LINEAR)
    extractor = OrbExtractor(OrbConfig())
    features_a, features_b = extractor.extract(image), extractor.extract(warped)
    mapped = cv2.perspectiveTransform(features_a.uv[None], H)[0]
    return features_a, features_b, mapped


@pytest.fixture(scope="module")
def small_vocabulary(homography_pair):
    features_a, features_b, _ = homography_pair
    config = VocabularyConfig(branching=6, depth=3, direct_index_levels_up=2)  # 6 direct-index nodes
    return train_vocabulary([features_a.descriptors, features_b.descriptors], config, seed=0)


# ------------------------------------------------------------------------------------------ distances


def test_hamming_counts_differing_bits():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (37, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (23, 32), dtype=np.uint8)
    expected = np.abs(_bits(a)[:, None, :] - _bits(b)[None, :, :]).sum(axis=2)
    np.testing.assert_array_equal(hamming(a, b), expected)
    np.testing.assert_array_equal(hamming_rows(a[:23], b), np.diag(expected[:23]))
    assert hamming(a[:0], b).shape == (0, 23) and hamming_rows(a[:0], b[:0]).shape == (0,)
    assert hamming(np.zeros((1, 32), np.uint8), np.full((1, 32), 255, np.uint8))[0, 0] == 256


# --------------------------------------------------------------------------------- rotation histogram


def test_orientation_histogram_keeps_the_dominant_rotations():
    rng = np.random.default_rng(1)
    angle_a = rng.uniform(0, 360, 300)
    consistent = (angle_a - 40.0 + rng.normal(0, 2.0, 300)) % 360  # a 40 degree turn
    outliers = rng.uniform(0, 360, 60)
    keep = orientation_consistent(np.concatenate([angle_a, angle_a[:60]]), np.concatenate([consistent, outliers]))
    assert keep[:300].mean() > 0.95  # 40 +- 2 degrees spans at most 3 bins of 12 degrees
    assert keep[300:].mean() < 0.2
    assert orientation_consistent(np.zeros(0), np.zeros(0)).shape == (0,)


def test_orientation_histogram_drops_bins_under_a_tenth_of_the_largest():
    rotation = np.concatenate([np.full(100, 0.0), np.full(9, 120.0), np.full(20, 240.0)])
    keep = orientation_consistent(rotation, np.zeros_like(rotation))
    np.testing.assert_array_equal(keep, np.concatenate([np.ones(100), np.zeros(9), np.ones(20)]).astype(bool))


# ------------------------------------------------------------- ratio test, distance threshold, one-to-one


def _with_flipped_bits(base: np.ndarray, counts: list[int]) -> np.ndarray:
    """Copies of one descriptor with the first ``count`` bits flipped: Hamming distance ``count`` to it."""
    bits = np.unpackbits(base)
    rows = []
    for count in counts:
        flipped = bits.copy()
        flipped[:count] ^= 1
        rows.append(np.packbits(flipped))
    return np.array(rows, dtype=np.uint8)


def _features(descriptors: np.ndarray, uv: np.ndarray | None = None) -> Features:
    count = len(descriptors)
    return Features(
        uv=np.zeros((count, 2)) if uv is None else uv,
        level=np.zeros(count, dtype=int),
        angle=np.zeros(count),
        response=np.ones(count, dtype=np.float32),
        descriptors=descriptors,
    )


@pytest.mark.parametrize(
    ("distances", "expected"),
    [
        ([10, 30], [0]),  # clear winner
        ([10, 11], []),  # ambiguous: 10 is not below 0.75 x 11
        ([60, 200], []),  # too far: above TH_LOW = 50
        ([10], [0]),  # a lone candidate passes the ratio test
    ],
)
def test_bow_matching_applies_the_ratio_test_and_the_distance_threshold(distances, expected):
    query = np.random.default_rng(5).integers(0, 256, (1, 32), dtype=np.uint8)
    features_a, features_b = _features(query), _features(_with_flipped_bits(query[0], distances))
    idx_a, idx_b = match_by_bow(features_a, np.zeros(1, int), features_b, np.zeros(len(distances), int))
    np.testing.assert_array_equal(idx_b, expected)
    # In different nodes nothing matches, however close.
    assert len(match_by_bow(features_a, np.ones(1, int), features_b, np.zeros(len(distances), int))[0]) == 0


def test_a_feature_claimed_twice_goes_to_the_nearest_query():
    base = np.random.default_rng(6).integers(0, 256, 32, dtype=np.uint8)
    features_b = _features(base[None])
    features_a = _features(_with_flipped_bits(base, [20, 5, 30]))
    idx_a, idx_b = match_by_bow(features_a, np.zeros(3, int), features_b, np.zeros(1, int))
    np.testing.assert_array_equal(idx_a, [1])
    np.testing.assert_array_equal(idx_b, [0])
    idx_p, idx_f = search_by_projection(features_b, np.zeros((3, 2)), features_a.descriptors, 0, 3.0)
    np.testing.assert_array_equal(idx_p, [1])


@pytest.mark.parametrize(("max_distance", "ratio"), [(50, 0.9), (100, 0.75), (256, 1.0)])
def test_exhaustive_matching_finds_what_opencvs_brute_force_matcher_finds(homography_pair, max_distance, ratio):
    """The epipolar witness's matching: the pairs of OpenCV's knnMatch (k = 2) that pass the distance and ratio
    tests, the same to the index (ORB descriptors of a turned, zoomed view; ties at the nearest fail the ratio
    test either way), several features of ``a`` allowed the same of ``b``."""
    features_a, features_b, _ = homography_pair
    doubled = Features.concatenate([features_a, features_a.subset(np.arange(20))])  # 20 share their nearest
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(doubled.descriptors, features_b.descriptors, k=2)
    expected = [(best.queryIdx, best.trainIdx) for best, second in pairs
                if best.distance <= max_distance and best.distance < ratio * second.distance]
    idx_a, idx_b = match_exhaustive(doubled, features_b, max_distance=max_distance, ratio=ratio)
    np.testing.assert_array_equal(np.stack([idx_a, idx_b], axis=1), np.array(expected).reshape(-1, 2))
    assert len(np.unique(idx_b)) < len(idx_b)
    assert len(idx_a) > 100


def test_projection_search_ratio_test_between_candidates_in_the_window():
    query = np.random.default_rng(7).integers(0, 256, (1, 32), dtype=np.uint8)
    candidates = _with_flipped_bits(query[0], [20, 24])  # 20 is not below 0.8 x 24
    features = _features(candidates, uv=np.array([[100.0, 100.0], [102.0, 100.0]]))
    assert len(search_by_projection(features, np.array([[101.0, 100.0]]), query, 0, 3.0)[0]) == 0
    # With the second candidate out of the window the first one is unambiguous.
    idx_p, idx_f = search_by_projection(features, np.array([[99.0, 100.0]]), query, 0, 2.0)
    np.testing.assert_array_equal(idx_f, [0])


def test_projection_search_finds_what_a_search_of_every_feature_finds():
    """The search looks through a grid of the features: on features and points spread over the image (radii of
    2-60 px, some points outside it), it picks what comparing every point with every feature picks."""
    rng = np.random.default_rng(11)
    features = _features(rng.integers(0, 256, (600, 32), dtype=np.uint8), rng.uniform([0, 0], [640, 480], (600, 2)))
    features.level = rng.integers(0, 8, 600)
    # Points near features, with descriptors a few bits from theirs: most have one clear nearest.
    near = rng.integers(0, 600, 300)
    uv = features.uv[near] + rng.normal(0, 8, (300, 2))
    uv[:10] -= 700  # outside the image
    descriptors = np.array([_with_flipped_bits(features.descriptors[f], [int(k)])[0]
                            for f, k in zip(near, rng.integers(0, 40, 300))])
    level, radius = rng.integers(0, 8, 300), rng.uniform(2, 60, 300)
    found = search_by_projection(features, uv, descriptors, level, radius, level_window=2)
    assert len(found[0]) > 100
    # Every point against every feature:
    reach = radius * OrbConfig().scale_factor ** level
    candidate = (np.linalg.norm(uv[:, None] - features.uv[None], axis=2) <= reach[:, None]) & (
        np.abs(level[:, None] - features.level[None]) <= 2)
    distance = np.where(candidate, hamming(descriptors, features.descriptors), 10**6)
    order = np.lexsort((np.broadcast_to(np.arange(600), distance.shape), distance), axis=1)
    best, second = order[:, 0], np.take_along_axis(distance, order[:, 1:2], 1)[:, 0]
    best_distance = distance[np.arange(300), best]
    accepted = (best_distance <= 100) & ((second == 10**6) | (best_distance < 0.8 * second))
    point = np.flatnonzero(accepted)
    claimed = {}  # one point per feature: the nearest, ties to the lower point index
    for p in point:
        f = best[p]
        if f not in claimed or best_distance[p] < best_distance[claimed[f]]:
            claimed[f] = p
    expected = sorted((p, f) for f, p in claimed.items())
    assert list(zip(found[0].tolist(), found[1].tolist())) == expected


# ------------------------------------------------------------------------------------------------ BoW


def test_bow_matching_finds_the_homography(homography_pair, small_vocabulary):
    features_a, features_b, mapped = homography_pair
    _, nodes_a = small_vocabulary.transform(features_a.descriptors)
    _, nodes_b = small_vocabulary.transform(features_b.descriptors)
    idx_a, idx_b = match_by_bow(features_a, nodes_a, features_b, nodes_b)
    assert len(idx_a) > 150
    assert len(np.unique(idx_a)) == len(idx_a) and len(np.unique(idx_b)) == len(idx_b)  # one-to-one
    np.testing.assert_array_equal(nodes_a[idx_a], nodes_b[idx_b])  # only within a node
    assert np.mean(_truth_error(mapped[idx_a], features_b, idx_b) < CORRECT_PX) > 0.9
    # The rotation histogram holds the turn: matched orientations differ by about the turn.
    turn = (features_a.angle[idx_a] - features_b.angle[idx_b] - TURN_DEG + 180.0) % 360.0 - 180.0
    assert np.median(np.abs(turn)) < 6.0


def test_bow_matching_of_unrelated_images_finds_almost_nothing(homography_pair, small_vocabulary):
    features_a, _, _ = homography_pair
    other = OrbExtractor().extract(make_sequence("smooth", 1, seed=3)[0].image)
    _, nodes_a = small_vocabulary.transform(features_a.descriptors)
    _, nodes_o = small_vocabulary.transform(other.descriptors)
    idx_a, _ = match_by_bow(features_a, nodes_a, other, nodes_o)
    assert len(idx_a) < 0.1 * len(features_a)


# ------------------------------------------------------------------------------------------- projection


def test_search_by_projection_finds_the_features_where_points_project(homography_pair):
    features_a, features_b, mapped = homography_pair
    rng = np.random.default_rng(2)
    noisy = mapped + rng.normal(0.0, 1.0, mapped.shape)
    # Predicted level: a zoom of 1.2 moves a feature one level up.
    predicted = np.clip(features_a.level + 1, 0, OrbConfig().num_levels - 1)
    idx_p, idx_f = search_by_projection(features_b, noisy, features_a.descriptors, predicted, radius_px=4.0)
    assert len(idx_p) > 400
    assert len(np.unique(idx_f)) == len(idx_f)
    assert np.mean(_truth_error(mapped[idx_p], features_b, idx_f) < CORRECT_PX) > 0.95
    # Every match respects the radius and the level window.
    scale = OrbConfig().scale_factor ** predicted[idx_p]
    assert np.all(np.linalg.norm(noisy[idx_p] - features_b.uv[idx_f], axis=1) <= 4.0 * scale + 1e-9)
    assert np.all(np.abs(features_b.level[idx_f] - predicted[idx_p]) <= 1)


def test_search_by_projection_honours_radius_levels_and_availability(homography_pair):
    features_a, features_b, mapped = homography_pair
    wrong_place = mapped + [60.0, 0.0]
    idx_p, _ = search_by_projection(features_b, wrong_place, features_a.descriptors, features_a.level, 3.0)
    assert len(idx_p) < 0.02 * len(mapped)
    far_levels = (features_b.level.max() + 5) * np.ones(len(mapped), dtype=int)
    assert len(search_by_projection(features_b, mapped, features_a.descriptors, far_levels, 3.0)[0]) == 0
    nothing = np.zeros(len(features_b), dtype=bool)
    assert len(search_by_projection(features_b, mapped, features_a.descriptors, 1, 3.0, available=nothing)[0]) == 0
    per_point = np.where(np.arange(len(mapped)) % 2 == 0, 4.0, 0.0)  # odd points see nothing
    idx_p, _ = search_by_projection(features_b, mapped, features_a.descriptors, 1, per_point, level_window=8)
    assert len(idx_p) > 100 and np.all(idx_p % 2 == 0)
    with_nan = mapped.copy()
    with_nan[::2] = np.nan
    idx_p, _ = search_by_projection(features_b, with_nan, features_a.descriptors, 1, 4.0, level_window=8)
    assert np.all(idx_p % 2 == 1)


# --------------------------------------------------------------------------------------------- epipolar


@pytest.fixture(scope="module")
def two_views():
    sequence = make_sequence("smooth", 12, seed=0)
    first, second = sequence[0], sequence[11]
    extractor = OrbExtractor(OrbConfig())
    features_a, features_b = extractor.extract(first.image), extractor.extract(second.image)
    T_a_b = se3_inverse(first.T_world_cam) @ second.T_world_cam
    camera = sequence.camera
    # Where each feature of a truly is in b: its depth from the renderer, moved into b and projected.
    pixel = np.rint(features_a.uv).astype(int)
    depth = first.depth[pixel[:, 1], pixel[:, 0]].astype(float)
    points_b = transform_points(se3_inverse(T_a_b), camera.unproject(features_a.uv) * depth[:, None])
    return features_a, features_b, camera, T_a_b, camera.project(points_b)


def test_fundamental_matrix_convention_holds_for_true_correspondences(two_views):
    features_a, _, camera, T_a_b, truth_b = two_views
    F_ba = fundamental_matrix(camera, camera, T_a_b)
    visible = camera.in_image(truth_b)
    residual = np.sqrt(epipolar_distance_squared(F_ba, features_a.uv[visible], truth_b[visible]))
    assert np.median(residual) < 0.05 and np.percentile(residual, 90) < 0.5
    swapped = np.sqrt(epipolar_distance_squared(F_ba.T, features_a.uv[visible], truth_b[visible]))
    assert np.median(swapped) > 10 * np.median(residual)  # the transpose is the other direction's matrix


def test_epipolar_search_returns_only_pairs_the_geometry_allows(two_views):
    features_a, features_b, camera, T_a_b, truth_b = two_views
    F_ba = fundamental_matrix(camera, camera, T_a_b)
    sigma2 = level_sigma2s(OrbConfig())
    idx_a, idx_b = search_epipolar(features_a, features_b, F_ba, level_sigma2=sigma2)
    assert len(idx_a) > 200
    assert len(np.unique(idx_a)) == len(idx_a) and len(np.unique(idx_b)) == len(idx_b)
    on_line = epipolar_distance_squared(F_ba, features_a.uv[idx_a], features_b.uv[idx_b])
    assert np.all(on_line < 3.84 * sigma2[features_b.level[idx_b]])
    assert np.mean(_truth_error(truth_b[idx_a], features_b, idx_b) < CORRECT_PX) > 0.9
    # With the truth's F, random pairs hardly ever pass: the search is not returning arbitrary pairs.
    wrong = fundamental_matrix(camera, camera, np.linalg.inv(T_a_b))
    idx_wrong, _ = search_epipolar(features_a, features_b, wrong, level_sigma2=sigma2)
    assert len(idx_wrong) < 0.25 * len(idx_a)


def test_epipolar_search_respects_candidates_nodes_and_the_epipole(two_views):
    features_a, features_b, camera, T_a_b, _ = two_views
    F_ba = fundamental_matrix(camera, camera, T_a_b)
    half_a = np.arange(len(features_a)) % 2 == 0
    no_b = np.zeros(len(features_b), dtype=bool)
    assert len(search_epipolar(features_a, features_b, F_ba, half_a, no_b)[0]) == 0
    idx_a, _ = search_epipolar(features_a, features_b, F_ba, half_a)
    assert len(idx_a) > 50 and np.all(idx_a % 2 == 0)
    nodes_a = (features_a.uv[:, 0] > 320).astype(int)  # any labels: pairs must share one
    nodes_b = (features_b.uv[:, 0] > 320).astype(int)
    idx_a, idx_b = search_epipolar(features_a, features_b, F_ba, nodes_a=nodes_a, nodes_b=nodes_b)
    assert len(idx_a) > 50
    np.testing.assert_array_equal(nodes_a[idx_a], nodes_b[idx_b])
    # The epipole of this motion is outside the image; the exclusion is checked around any given point.
    centre = np.array([camera.cx, camera.cy])
    idx_a, idx_b = search_epipolar(features_a, features_b, F_ba, epipole_b=centre)
    distance = np.linalg.norm(features_b.uv - centre, axis=1)
    near_centre = distance < 10.0 * np.sqrt(OrbConfig().scale_factor ** features_b.level)
    assert near_centre.sum() > 0 and len(idx_b) > 200
    assert not np.any(near_centre[idx_b])


def test_epipole_is_the_other_camera_centre(two_views):
    _, _, camera, T_a_b, _ = two_views
    centre_a_in_b = se3_inverse(T_a_b)[:3, 3]
    expected = camera.project(centre_a_in_b[None])[0]
    np.testing.assert_allclose(epipole_in_b(camera, T_a_b), expected)
    sideways = np.eye(4)
    sideways[:3, 3] = [1.0, 0.0, 0.0]
    assert epipole_in_b(camera, sideways) is None


def test_empty_inputs_give_empty_matches(homography_pair):
    features_a, _, _ = homography_pair
    empty = Features.empty()
    for idx in (
        match_by_bow(empty, np.zeros(0, int), features_a, np.zeros(len(features_a), int)),
        search_by_projection(empty, np.zeros((3, 2)), np.zeros((3, 32), np.uint8), 0, 3.0),
        search_by_projection(features_a, np.zeros((0, 2)), np.zeros((0, 32), np.uint8), 0, 3.0),
        search_epipolar(empty, features_a, np.eye(3)),
        match_exhaustive(empty, features_a, max_distance=50, ratio=0.9),
        match_exhaustive(features_a, empty, max_distance=50, ratio=0.9),
    ):
        assert len(idx[0]) == len(idx[1]) == 0


def test_least_median_descriptor_is_orb_slam2s_distinctive_descriptor():
    """Each group keeps the descriptor with the least median distance to its group, itself included (the lower
    median of an even count, the first among equals), as MapPoint::ComputeDistinctiveDescriptors does."""
    rng = np.random.default_rng(4)
    counts = [1, 2, 3, 4, 7, 12]
    descriptors = rng.integers(0, 256, (sum(counts), 32), dtype=np.uint8)
    starts = np.concatenate([[0], np.cumsum(counts)])

    chosen = least_median_descriptors(descriptors, starts)

    for group, (first, end) in enumerate(zip(starts[:-1], starts[1:])):
        distances = _bits(descriptors[first:end])[:, None, :] != _bits(descriptors[first:end])[None, :, :]
        medians = np.sort(distances.sum(axis=2), axis=1)[:, (end - first - 1) // 2]
        assert chosen[group] == first + int(np.argmin(medians))


def test_least_median_descriptor_avoids_an_outlying_view():
    """Two views of a point that agree and one that does not (a wrong match): one of the two is kept."""
    view = np.random.default_rng(5).integers(0, 256, 32, dtype=np.uint8)
    close = view.copy()
    close[0] ^= 0b11  # two bits away
    far = ~view
    assert least_median_descriptors(np.stack([far, view, close]), np.array([0, 3]))[0] in (1, 2)
