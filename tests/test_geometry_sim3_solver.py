"""The Sim(3) solver of loop closing (vo_core/geometry/sim3_solver.py): RANSAC over minimal sets and the refinement
recover a known similarity between two keyframes from matches 40 % of which are wrong; too few or only wrong
matches give nothing; a seed gives one answer; the inlier test refuses points behind a camera; the closed form
that eval's alignment now borrows still is Umeyama's. On two neighbourhoods (sightings of one side's points by the
other side's keyframes) the information is still J^T J, baseline within a side pins what one view leaves free, and
the refinement recovers the similarity."""

from __future__ import annotations

import numpy as np
import pytest

from vo_core.eval.align import umeyama as eval_umeyama
from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import (sim3, sim3_exp, sim3_inverse, sim3_scale, so3_exp, so3_geodesic_angle,
                                  transform_points)
from vo_core.geometry.sim3_solver import (
    Sim3Fit,
    Sim3Matches,
    Sim3Sightings,
    ransac_sim3,
    refine_sim3,
    refine_sim3_on_sightings,
    reprojection_inliers,
    sim3_information,
    sim3_information_on_sightings,
    sightings_of,
    umeyama,
)

CAMERA = PinholeCamera(640, 480, 500.0, 500.0, 319.5, 239.5)
CHI2 = 9.210  # ORB-SLAM2 Sim3Solver: chi-square 99 %, 2 DOF
REFINE_CHI2 = 10.0  # ORB-SLAM2 LoopClosing::ComputeSim3 passes th2 = 10 to OptimizeSim3
LEVEL_SCALE = 1.2
LEVELS = 4
PIXEL_NOISE = 0.5  # in units of the level's sigma: true matches sit well inside the chi2 bound
POINT_NOISE = 0.002  # relative 3D noise of each keyframe's own map point
WRONG_MATCH_MIN_PX = 20.0  # how far from the right point a wrong match's point projects in a
RANSAC = dict(min_inliers=20, max_iterations=300, chi2=CHI2, probability=0.99)


def true_similarity(scale: float) -> np.ndarray:
    """S_a_b (x_a = s R x_b + t): camera b a little turned and shifted from a, its map at 1/s of a's units."""
    return sim3(scale, so3_exp(np.radians([4.0, -9.0, 3.0])), np.array([1.0, -0.2, 0.3]))


def random_points(rng: np.random.Generator, count: int) -> np.ndarray:
    """Points of a's view, 3 to 8 m ahead."""
    return np.column_stack([rng.uniform(-2.0, 2.0, count), rng.uniform(-1.5, 1.5, count), rng.uniform(3.0, 8.0, count)])


def scene(rng: np.random.Generator, S_a_b: np.ndarray, count: int, wrong_fraction: float):
    """Matches of ``count`` points seen by both cameras, ``wrong_fraction`` of them wrong (b's side replaced by
    another point that b sees), and the truth mask of the right ones."""
    points_a = random_points(rng, count)
    points_b = transform_points(sim3_inverse(S_a_b), points_a)
    right = np.ones(count, bool)
    right[rng.choice(count, int(round(wrong_fraction * count)), replace=False)] = False
    wrong = ~right
    # A wrong match: b's side is some other point of b's view, with its own observation, one that a sees well
    # away from the right one (a point on nearly the same ray at nearly the same depth would be a right match).
    others = random_points(rng, count)
    near = np.ones(count, bool)
    while near.any():
        others[near] = random_points(rng, int(near.sum()))
        near = np.linalg.norm(CAMERA.project(others) - CAMERA.project(points_a), axis=1) < WRONG_MATCH_MIN_PX
    points_b[wrong] = transform_points(sim3_inverse(S_a_b), others[wrong])
    levels_a, levels_b = rng.integers(0, LEVELS, count), rng.integers(0, LEVELS, count)
    sigma2_a, sigma2_b = LEVEL_SCALE ** (2.0 * levels_a), LEVEL_SCALE ** (2.0 * levels_b)
    uv_a = CAMERA.project(points_a) + rng.normal(0.0, PIXEL_NOISE, (count, 2)) * np.sqrt(sigma2_a)[:, None]
    uv_b = CAMERA.project(points_b) + rng.normal(0.0, PIXEL_NOISE, (count, 2)) * np.sqrt(sigma2_b)[:, None]
    # Each keyframe's own estimate of its map point is a little off (triangulated, not known).
    noisy_a = points_a * (1.0 + rng.normal(0.0, POINT_NOISE, (count, 1)))
    noisy_b = points_b * (1.0 + rng.normal(0.0, POINT_NOISE, (count, 1)))
    return Sim3Matches(noisy_a, noisy_b, uv_a, uv_b, sigma2_a, sigma2_b), right


def assert_close_to(S: np.ndarray, truth: np.ndarray) -> None:
    assert sim3_scale(S) == pytest.approx(sim3_scale(truth), rel=0.01)
    rotation_error = so3_geodesic_angle(S[:3, :3] / sim3_scale(S), truth[:3, :3] / sim3_scale(truth))
    assert np.degrees(rotation_error) < 0.2


@pytest.mark.parametrize("scale", [0.6, 1.7])
def test_ransac_and_refinement_recover_the_similarity_and_the_right_matches(scale):
    truth = true_similarity(scale)
    matches, right = scene(np.random.default_rng(7), truth, 120, 0.4)
    found = ransac_sim3(matches, CAMERA, np.random.default_rng(1), **RANSAC)
    assert isinstance(found, Sim3Fit) and 0 < found.iterations <= RANSAC["max_iterations"]
    np.testing.assert_array_equal(found.inliers, right)
    assert_close_to(found.S_a_b, truth)
    refined = refine_sim3(matches, CAMERA, found.S_a_b, chi2=REFINE_CHI2, iterations=10)
    assert refined.iterations == 0 and refined.num_inliers == right.sum()
    np.testing.assert_array_equal(refined.inliers, right)
    assert refined.scale == pytest.approx(scale, rel=0.01)
    assert_close_to(refined.S_a_b, truth)


def test_refinement_pulls_a_rough_similarity_to_the_truth_and_drops_the_wrong_matches():
    truth = true_similarity(1.7)
    matches, right = scene(np.random.default_rng(3), truth, 80, 0.3)
    rough = sim3(1.7 * 1.03, so3_exp(np.radians([4.5, -8.5, 3.3])), truth[:3, 3] + [0.02, 0.01, -0.03])
    refined = refine_sim3(matches, CAMERA, rough, chi2=REFINE_CHI2, iterations=10)
    assert not reprojection_inliers(matches, CAMERA, rough, REFINE_CHI2).any()  # 3 % off: nothing agrees with it
    np.testing.assert_array_equal(refined.inliers, right)
    assert_close_to(refined.S_a_b, truth)


def test_too_few_matches_give_nothing():
    matches, _ = scene(np.random.default_rng(0), true_similarity(0.6), 30, 0.0)
    two = Sim3Matches(*(field[:2] for field in (matches.points_a, matches.points_b, matches.uv_a, matches.uv_b,
                                                 matches.sigma2_a, matches.sigma2_b)))
    assert ransac_sim3(two, CAMERA, np.random.default_rng(0), **RANSAC) is None
    # 30 right matches, but 40 asked for
    assert ransac_sim3(matches, CAMERA, np.random.default_rng(0), **{**RANSAC, "min_inliers": 40}) is None


def test_only_wrong_matches_give_nothing():
    matches, right = scene(np.random.default_rng(5), true_similarity(1.7), 60, 1.0)
    assert not right.any()
    assert ransac_sim3(matches, CAMERA, np.random.default_rng(0), **RANSAC) is None


def test_the_minimal_sets_fitted_and_scored_at_once_are_the_one_by_one_closed_forms_and_inlier_tests():
    from vo_core.geometry.sim3_solver import _closed_form_sim3, _inliers_of_each, _minimal_similarities

    rng = np.random.default_rng(13)
    matches, _ = scene(rng, true_similarity(1.7), 60, 0.4)
    samples = np.array([rng.choice(60, size=3, replace=False) for _ in range(100)])
    samples[0] = [4, 4, 4]  # three times one point: no similarity
    similarities, fitted = _minimal_similarities(matches, samples)
    inliers = _inliers_of_each(matches, CAMERA, similarities, fitted, CHI2)
    for sample, S_a_b, fits, model_inliers in zip(samples, similarities, fitted, inliers):
        one = _closed_form_sim3(matches.subset(sample))
        assert fits == (one is not None)
        if one is None:
            assert not model_inliers.any()
            continue
        np.testing.assert_allclose(S_a_b, one, atol=1e-12)
        np.testing.assert_array_equal(model_inliers, reprojection_inliers(matches, CAMERA, one, CHI2))


def test_one_seed_gives_one_answer():
    matches, _ = scene(np.random.default_rng(11), true_similarity(0.6), 60, 0.4)
    first, second = (ransac_sim3(matches, CAMERA, np.random.default_rng(42), **RANSAC) for _ in range(2))
    np.testing.assert_array_equal(first.S_a_b, second.S_a_b)
    np.testing.assert_array_equal(first.inliers, second.inliers)
    assert first.iterations == second.iterations


def test_a_point_behind_either_camera_is_an_outlier():
    # Two keyframes at one place (S_a_b the identity), each observing its point exactly where it projects.
    points = np.column_stack([np.linspace(-1.0, 1.0, 6), np.linspace(0.5, -0.5, 6), np.linspace(2.0, 6.0, 6)])
    identity = np.eye(4)
    seen = CAMERA.project(points)
    matches = Sim3Matches(points, points.copy(), seen, seen, np.ones(6), np.ones(6))
    assert reprojection_inliers(matches, CAMERA, identity, CHI2).all()
    # -x projects where x does (same x/z, y/z), but from behind the camera.
    matches.points_b[0] *= -1.0  # b's point behind a
    matches.points_a[1] *= -1.0  # a's point behind b
    assert reprojection_inliers(matches, CAMERA, identity, CHI2).tolist() == [False, False, True, True, True, True]


def test_the_inlier_bound_scales_with_the_level_variance():
    truth = true_similarity(1.0)
    matches, _ = scene(np.random.default_rng(4), truth, 5, 0.0)
    exact_a = CAMERA.project(transform_points(truth, matches.points_b))
    exact_b = CAMERA.project(transform_points(sim3_inverse(truth), matches.points_a))
    offset = np.sqrt(CHI2) * 1.1  # just beyond the bound at level 0, well within it at level 1 (sigma 1.2)
    shifted = Sim3Matches(matches.points_a, matches.points_b, exact_a + [offset, 0.0], exact_b,
                          np.array([1.0, LEVEL_SCALE**2, 1.0, LEVEL_SCALE**2, 1.0]), np.ones(5))
    assert reprojection_inliers(shifted, CAMERA, truth, CHI2).tolist() == [False, True, False, True, False]


def test_umeyama_recovers_a_similarity_and_eval_still_refuses_a_still_camera():
    rng = np.random.default_rng(9)
    source = rng.normal(size=(20, 3))
    R, t, s = so3_exp([0.3, -1.2, 2.0]), np.array([1.0, 2.0, -3.0]), 0.37
    target = s * source @ R.T + t
    for closed_form in (umeyama, eval_umeyama):
        R_found, t_found, s_found = closed_form(source, target, True)
        np.testing.assert_allclose(R_found, R, atol=1e-12)
        np.testing.assert_allclose(t_found, t, atol=1e-12)
        assert s_found == pytest.approx(s, rel=1e-12)
    with pytest.raises(ValueError, match="coincide"):
        umeyama(np.ones((4, 3)), target[:4], True)
    from vo_core.errors import InputError

    with pytest.raises(InputError, match="do not move"):
        eval_umeyama(np.ones((4, 3)), target[:4], True)


def two_way_residuals(matches: Sim3Matches, S_a_b: np.ndarray) -> np.ndarray:
    """The residuals refine_sim3 documents: b's points in a and a's in b, each pixel over its sigma."""
    in_a = CAMERA.project(transform_points(S_a_b, matches.points_b)) - matches.uv_a
    in_b = CAMERA.project(transform_points(sim3_inverse(S_a_b), matches.points_a)) - matches.uv_b
    return np.concatenate([(in_a / np.sqrt(matches.sigma2_a)[:, None]).ravel(),
                           (in_b / np.sqrt(matches.sigma2_b)[:, None]).ravel()])


def test_the_information_is_j_transpose_j_of_the_two_way_residuals_in_the_left_tangent():
    matches, _ = scene(np.random.default_rng(11), true_similarity(1.3), 40, wrong_fraction=0.0)
    S_a_b = true_similarity(1.3)
    step = 1e-6
    J = np.column_stack([(two_way_residuals(matches, sim3_exp(step * e) @ S_a_b)
                          - two_way_residuals(matches, sim3_exp(-step * e) @ S_a_b)) / (2.0 * step)
                         for e in np.eye(7)])
    np.testing.assert_allclose(sim3_information(matches, CAMERA, S_a_b), J.T @ J, rtol=1e-6,
                               atol=1e-6 * np.abs(J.T @ J).max())


def test_a_far_scene_leaves_a_rotation_translation_combination_weak():
    """Pixels of a far scene barely tell a small turn from a sideways shift: the weakest direction of the
    information mixes both, and it is weaker the farther the points are."""
    rng = np.random.default_rng(12)
    weakest = []
    for distance in (1.0, 10.0):
        matches, _ = scene(rng, true_similarity(1.0), 60, wrong_fraction=0.0)
        far = Sim3Matches(matches.points_a * distance, matches.points_b * distance, matches.uv_a, matches.uv_b,
                          matches.sigma2_a, matches.sigma2_b)
        values = np.linalg.eigvalsh(sim3_information(far, CAMERA, true_similarity(1.0)))
        weakest.append(values[0] / values[-1])
    assert weakest[1] < 0.1 * weakest[0]


def side_views(offsets_m: list[float]) -> np.ndarray:
    """Keyframes of one side, shifted sideways from its reference keyframe and turned a little: T_view_reference."""
    views = np.array([np.eye(4) for _ in offsets_m])
    for view, offset in zip(views, offsets_m):
        view[:3, :3] = so3_exp(np.radians([0.0, 2.0 * offset, 0.0]))
        view[:3, 3] = [-offset, 0.0, 0.0]
    return views


def sightings(rng: np.random.Generator, points_seen: np.ndarray, points_in_seer_reference: np.ndarray,
              views: np.ndarray) -> Sim3Sightings:
    """Every point seen by every view of the seeing side, its pixel noisy, the point held in its own side's frame."""
    count = len(points_seen)
    T = np.repeat(views, count, axis=0)
    in_views = np.einsum("nij,nj->ni", T[:, :3, :3], np.tile(points_in_seer_reference, (len(views), 1))) + T[:, :3, 3]
    uv = CAMERA.project(in_views) + rng.normal(0.0, PIXEL_NOISE, (len(T), 2))
    return Sim3Sightings(np.tile(points_seen, (len(views), 1)), T, uv, np.ones(len(T)))


def neighbourhood_scene(rng: np.random.Generator, S_a_b: np.ndarray, offsets_m: list[float], count: int,
                        point_noise: float = POINT_NOISE):
    """Sightings both ways between two sides of ``offsets_m`` keyframes each: ``count`` points of a's side and
    ``count`` of b's, each side's points ``point_noise`` (relative) off, every point seen by each keyframe."""
    points_a, other_a = random_points(rng, count), random_points(rng, count)
    points_b = transform_points(sim3_inverse(S_a_b), other_a)  # b's side's points, in b's frame
    noisy_a = points_a * (1.0 + rng.normal(0.0, point_noise, (count, 1)))
    noisy_b = points_b * (1.0 + rng.normal(0.0, point_noise, (count, 1)))
    views = side_views(offsets_m)
    return (sightings(rng, noisy_b, other_a, views),
            sightings(rng, noisy_a, transform_points(sim3_inverse(S_a_b), points_a), views))


def sighting_residuals(into_a: Sim3Sightings, into_b: Sim3Sightings, S_a_b: np.ndarray) -> np.ndarray:
    """The residuals refine_sim3_on_sightings documents: each side's sightings of the other's points."""
    def residuals(seen: Sim3Sightings, S: np.ndarray) -> np.ndarray:
        mapped = transform_points(S, seen.points)
        in_view = np.einsum("nij,nj->ni", seen.T_view_reference[:, :3, :3], mapped) + seen.T_view_reference[:, :3, 3]
        return ((CAMERA.project(in_view) - seen.uv) / np.sqrt(seen.sigma2)[:, None]).ravel()
    return np.concatenate([residuals(into_a, S_a_b), residuals(into_b, sim3_inverse(S_a_b))])


def test_the_information_on_sightings_is_j_transpose_j_of_their_residuals_and_a_pairs_is_sim3_information():
    truth = true_similarity(1.3)
    into_a, into_b = neighbourhood_scene(np.random.default_rng(21), truth, [0.0, 0.4, -0.3], 40)
    step = 1e-6
    J = np.column_stack([(sighting_residuals(into_a, into_b, sim3_exp(step * e) @ truth)
                          - sighting_residuals(into_a, into_b, sim3_exp(-step * e) @ truth)) / (2.0 * step)
                         for e in np.eye(7)])
    np.testing.assert_allclose(sim3_information_on_sightings(into_a, into_b, CAMERA, truth), J.T @ J, rtol=1e-6,
                               atol=1e-6 * np.abs(J.T @ J).max())
    matches, _ = scene(np.random.default_rng(22), truth, 30, wrong_fraction=0.0)
    np.testing.assert_array_equal(sim3_information_on_sightings(*sightings_of(matches), CAMERA, truth),
                                  sim3_information(matches, CAMERA, truth))


def test_a_neighbourhood_pins_the_similarity_better_than_its_keyframe():
    """Each keyframe's points are a little off (triangulated), and one keyframe's matches carry their errors into
    the similarity: a side of three keyframes, a metre apart with 40 points each, brings independent points and
    views, and the refined similarity's rotation, translation and scale errors (20 scenes) halve at least."""
    truth = true_similarity(1.0)
    errors = []
    for offsets in ([0.0], [0.0, 1.0, -1.0]):
        per_scene = []
        for seed in range(20):
            into_a, into_b = neighbourhood_scene(np.random.default_rng(seed), truth, offsets, 40 * len(offsets),
                                                 point_noise=10 * POINT_NOISE)
            S_a_b, _, _ = refine_sim3_on_sightings(into_a, into_b, CAMERA, truth, chi2=REFINE_CHI2, iterations=10)
            error = S_a_b @ sim3_inverse(truth)
            per_scene.append([so3_geodesic_angle(error[:3, :3] / sim3_scale(error), np.eye(3)),
                              np.linalg.norm(error[:3, 3]), abs(np.log(sim3_scale(error)))])
        errors.append(np.sqrt(np.mean(np.square(per_scene), axis=0)))
    assert np.all(errors[1] < 0.5 * errors[0]), errors


def test_the_refinement_on_sightings_recovers_the_similarity_and_refuses_wrong_sightings():
    truth = true_similarity(1.7)
    rng = np.random.default_rng(24)
    into_a, into_b = neighbourhood_scene(rng, truth, [0.0, 0.5, -0.5], 40)
    wrong = rng.choice(len(into_a.uv), 20, replace=False)
    into_a.uv[wrong] += WRONG_MATCH_MIN_PX
    rough = sim3_exp(np.array([0.02, -0.01, 0.03, 0.01, -0.01, 0.005, 0.03])) @ truth
    S_a_b, inliers_a, inliers_b = refine_sim3_on_sightings(into_a, into_b, CAMERA, rough, chi2=REFINE_CHI2,
                                                           iterations=10)
    assert_close_to(S_a_b, truth)
    assert not inliers_a[wrong].any() and np.count_nonzero(inliers_a) >= len(inliers_a) - 20 - 3
    assert inliers_b.all()


def test_two_keyframes_at_one_place_do_not_see_the_scale():
    """A loop between two views of one place (no translation between them) is the case where their matches say
    nothing of the scale: x_a = s R x_b projects where R x_b does. Their information has none along it, and every
    match agrees with the similarity at a scale three times too large or too small as with the true one; loop
    closing therefore also starts the neighbourhoods' refinement, whose baselines see the scale, from the similarity
    without its change of scale (LoopCloser.verify)."""
    truth = sim3(1.0, so3_exp(np.radians([2.0, -5.0, 1.0])), np.zeros(3))
    matches, right = scene(np.random.default_rng(21), truth, 80, 0.0)
    information = sim3_information(matches, CAMERA, truth)
    assert information[6, 6] < 1e-9 * np.abs(information).max()
    for scale in (1.0, 0.3, 3.0):
        agreeing = reprojection_inliers(matches, CAMERA, sim3(scale, truth[:3, :3], np.zeros(3)), REFINE_CHI2)
        np.testing.assert_array_equal(agreeing, right)
    # With a baseline between the two views the same matches do tell the scale.
    assert sim3_information(*scene(np.random.default_rng(21), true_similarity(1.0), 80, 0.0)[:1], CAMERA,
                            true_similarity(1.0))[6, 6] > 1e-3 * np.abs(information).max()
