"""The similarity between two keyframes from their matched map points: what a loop closure needs to know how far
(and at what scale) the map has drifted between the two ends of the loop.

Convention: ``S_a_b`` = [sR t; 0 1] maps points of camera b's frame into camera a's frame, x_a = s R x_b + t
(vo_core/geometry/lie.py's naming of transforms, Sim(3) tangent (v, w, sigma), left updates).

Three steps, as ORB-SLAM2 takes them in its loop closing:
- ``ransac_sim3``: RANSAC over minimal sets of 3 matches, each giving a similarity in closed form (``umeyama``:
  Horn 1987, "Closed-form solution of absolute orientation using unit quaternions", JOSA A 4(4), whose quaternion
  form ORB-SLAM2's Sim3Solver::ComputeSim3 uses; here Umeyama 1991, "Least-squares estimation of transformation
  parameters between two point patterns", IEEE PAMI 13(4), its SVD form with the same minimizer);
- ``reprojection_inliers``: the test both steps share (ORB-SLAM2 Sim3Solver::CheckInliers), a match agreeing with
  a similarity when each of its points, mapped into the other camera, lands near where that camera observed it;
- ``refine_sim3``: least squares on the 7 parameters of the similarity over those reprojection errors both ways,
  map points fixed, twice, the outliers of the first round left out of the second (ORB-SLAM2 Optimizer::OptimizeSim3).

A loop joins two neighbourhoods, not two keyframes: ``Sim3Sightings`` are one side's points seen by the other side's
keyframes (each at its pose relative to its side's reference keyframe), and ``refine_sim3_on_sightings`` refines the
same similarity on all of them, so that its rotation, translation and scale rest on several views with baseline
between them (two keyframes' matches are one view each way; ``sightings_of`` writes them as sightings).

Errors are in units of the observation's variance: e = |pi(x) - uv|^2 / sigma2, sigma2 the squared scale of the
ORB pyramid level the keypoint was found at (ORB-SLAM2's mvLevelSigma2), so that one chi-square bound ``chi2`` holds
at every level.

Differences from ORB-SLAM2: the inlier test compares with the observed pixels (ORB-SLAM2's Sim3Solver compares with
the projection of each keyframe's own point, its OptimizeSim3 with the observed pixels) and calls a point behind
either camera an outlier; RANSAC runs an adaptive number of iterations and keeps the best model rather than
stopping at the first with enough inliers; the best model is fitted again to all its inliers; the refinement is
scipy's trust-region least squares, its Huber kernel on each pixel component rather than on each observation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import sim3, sim3_exp, sim3_inverse, sim3_scale, transform_points
from vo_core.geometry.reprojection import pose_jacobians, project_points, projection_jacobians

MINIMAL_SET = 3  # three non-collinear point pairs fix a similarity (7 unknowns, 3 equations each)
RANSAC_BATCH = 50  # minimal sets fitted and scored at once (ours: speed only, the result is the one-by-one loop's)
SIM3_DOF = 7


@dataclass(frozen=True)
class Sim3Matches:
    """Matched map points of two keyframes a and b, each in its own camera frame, and where each was observed."""

    points_a: np.ndarray  # (N, 3) point in camera a's frame
    points_b: np.ndarray  # (N, 3) the matched point in camera b's frame
    uv_a: np.ndarray  # (N, 2) pixel where a observed it
    uv_b: np.ndarray  # (N, 2) pixel where b observed it
    sigma2_a: np.ndarray  # (N,) pixel variance of the observation in a (ORB level scale^2)
    sigma2_b: np.ndarray  # (N,)

    def subset(self, selection: np.ndarray) -> "Sim3Matches":
        """The matches that ``selection`` (a boolean mask or indices) picks."""
        return Sim3Matches(self.points_a[selection], self.points_b[selection], self.uv_a[selection],
                           self.uv_b[selection], self.sigma2_a[selection], self.sigma2_b[selection])


@dataclass(frozen=True)
class Sim3Sightings:
    """One side's points seen by keyframes of the other side: what refines S_a_b on two neighbourhoods. Sightings
    into a: b's side's points, each in b's camera frame, seen by a keyframe of a's side whose camera is T_view_reference
    (rigid, a's map units) from a's; sightings into b likewise with a's points and b's side."""

    points: np.ndarray  # (N, 3) in the seen side's reference camera frame
    T_view_reference: np.ndarray  # (N, 4, 4) the seeing keyframe's camera from its side's reference camera
    uv: np.ndarray  # (N, 2) pixel where the seeing keyframe observed it
    sigma2: np.ndarray  # (N,) pixel variance of that observation

    def subset(self, selection: np.ndarray) -> "Sim3Sightings":
        return Sim3Sightings(self.points[selection], self.T_view_reference[selection], self.uv[selection],
                             self.sigma2[selection])

    @staticmethod
    def concatenate(parts: list["Sim3Sightings"]) -> "Sim3Sightings":
        if not parts:
            return Sim3Sightings(np.zeros((0, 3)), np.zeros((0, 4, 4)), np.zeros((0, 2)), np.zeros(0))
        return Sim3Sightings(*(np.concatenate([getattr(p, name) for p in parts])
                               for name in ("points", "T_view_reference", "uv", "sigma2")))


def sightings_of(matches: Sim3Matches) -> tuple[Sim3Sightings, Sim3Sightings]:
    """Two keyframes' matches as sightings (into a, into b): each keyframe the only one of its side."""
    identity = np.broadcast_to(np.eye(4), (len(matches.points_a), 4, 4))
    return (Sim3Sightings(matches.points_b, identity, matches.uv_a, matches.sigma2_a),
            Sim3Sightings(matches.points_a, identity, matches.uv_b, matches.sigma2_b))


@dataclass(frozen=True)
class Sim3Fit:
    """A similarity S_a_b (4x4 [sR t; 0 1], x_a = s R x_b + t), which matches agree with it, and the RANSAC
    iterations that found it (0 for a refinement)."""

    S_a_b: np.ndarray
    inliers: np.ndarray  # (N,) bool
    iterations: int

    @property
    def num_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))

    @property
    def scale(self) -> float:
        return sim3_scale(self.S_a_b)


# ------------------------------------------------------------------------------------------ closed form


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """(R, t, s) minimizing sum_i ||target_i - (s R source_i + t)||^2 for (N, 3) point sets (Umeyama 1991).

    ValueError when a scale is asked of source points that all coincide (it is then undefined)."""
    R, t, s, variance_source = _umeyama_of_each(source[None], target[None], with_scale)
    if with_scale and not variance_source[0] > 0.0:
        raise ValueError("umeyama: the source points all coincide, the scale is undefined")
    return R[0], t[0], float(s[0])


def _umeyama_of_each(source: np.ndarray, target: np.ndarray,
                     with_scale: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``umeyama`` of K pairs of point sets at once, (K, N, 3) each: R (K, 3, 3), t (K, 3), s (K,) (inf or nan where
    the source points coincide) and the source's variance sigma_x^2 (K,)."""
    mean_source, mean_target = source.mean(axis=1), target.mean(axis=1)
    centred_source, centred_target = source - mean_source[:, None], target - mean_target[:, None]
    variance_source = np.mean(np.sum(centred_source**2, axis=2), axis=1)  # sigma_x^2, eq. (36)
    covariance = np.swapaxes(centred_target, 1, 2) @ centred_source / source.shape[1]  # Sigma_xy, eq. (38)
    U, d, Vt = np.linalg.svd(covariance)
    # S = diag(1, 1, -1) when det(U) det(V) < 0: the best proper rotation, not a reflection, eq. (43)
    signs = np.ones_like(d)
    signs[:, 2] = np.where(np.linalg.det(U) * np.linalg.det(Vt) < 0.0, -1.0, 1.0)
    R = (U * signs[:, None, :]) @ Vt  # eq. (40)
    if with_scale:
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.sum(d * signs, axis=1) / variance_source  # c = tr(D S) / sigma_x^2, eq. (42)
    else:
        s = np.ones(len(source))
    t = mean_target - ((s[:, None, None] * R) @ mean_source[:, :, None])[:, :, 0]  # eq. (41)
    return R, t, s, variance_source


def _closed_form_sim3(matches: Sim3Matches) -> np.ndarray | None:
    """S_a_b fitted to the matches' 3D points (b's mapped onto a's), or None where they fix no similarity."""
    try:
        R, t, s = umeyama(matches.points_b, matches.points_a, with_scale=True)
    except ValueError:
        return None
    # A scale of zero (the target points all coincide) maps everything onto one point: no similarity to score.
    return sim3(s, R, t) if s > 0.0 and np.isfinite(s) else None


# ------------------------------------------------------------------------------------------ errors


def _two_way_errors(matches: Sim3Matches, camera: PinholeCamera,
                    S_a_b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normalized squared errors of b's points in a and of a's points in b (``_sighting_errors``), and where both
    lie in front of their camera (behind it, the projection means nothing)."""
    into_a, into_b = sightings_of(matches)
    errors_a, front_a = _sighting_errors(into_a, camera, S_a_b)
    errors_b, front_b = _sighting_errors(into_b, camera, sim3_inverse(S_a_b))
    return errors_a, errors_b, front_a & front_b


def reprojection_inliers(matches: Sim3Matches, camera: PinholeCamera, S_a_b: np.ndarray, chi2: float) -> np.ndarray:
    """(N,) bool: b's point mapped into a projects within chi2 * sigma2_a (squared pixels) of uv_a, a's point
    mapped into b by the inverse within chi2 * sigma2_b of uv_b, and both lie in front of their camera."""
    errors_a, errors_b, in_front = _two_way_errors(matches, camera, S_a_b)
    # NaN errors (a point on a camera's plane) compare False: outliers too.
    return in_front & (errors_a < chi2) & (errors_b < chi2)


# ------------------------------------------------------------------------------------------ RANSAC


def _iterations_needed(inlier_ratio: float, probability: float, max_iterations: int) -> int:
    """RANSAC iterations after which a minimal set of inliers only was drawn with ``probability``, given the
    inlier ratio: log(1 - p) / log(1 - w^3) (Fischler & Bolles 1981), capped by max_iterations."""
    all_inliers = inlier_ratio**MINIMAL_SET
    if all_inliers >= 1.0:
        return 1
    if all_inliers <= 0.0 or probability >= 1.0:
        return max_iterations
    needed = np.ceil(np.log(1.0 - probability) / np.log(1.0 - all_inliers))
    return int(min(max(needed, 1.0), max_iterations))


def _refit_on_inliers(matches: Sim3Matches, camera: PinholeCamera, S_a_b: np.ndarray, inliers: np.ndarray,
                      chi2: float) -> tuple[np.ndarray, np.ndarray]:
    """The closed form on all of the model's inliers, where it explains at least as many matches: a minimal set
    fits its own three points' noise, all inliers average it out. Kept only when no worse, because the closed form
    weighs 3D distances, not pixels, and distant points' depth errors can pull it away."""
    refit = _closed_form_sim3(matches.subset(inliers))
    if refit is None:
        return S_a_b, inliers
    refit_inliers = reprojection_inliers(matches, camera, refit, chi2)
    if np.count_nonzero(refit_inliers) >= np.count_nonzero(inliers):
        return refit, refit_inliers
    return S_a_b, inliers


def ransac_sim3(matches: Sim3Matches, camera: PinholeCamera, rng: np.random.Generator, *, min_inliers: int,
                max_iterations: int, chi2: float, probability: float) -> Sim3Fit | None:
    """The similarity S_a_b most matches agree with (``reprojection_inliers`` at ``chi2``), from minimal sets of 3
    drawn with ``rng`` until one of inliers only was drawn with ``probability`` (or ``max_iterations``), fitted
    again to all its inliers; None when it has fewer than ``min_inliers`` or there are fewer than 3 matches.

    The minimal sets are drawn, fitted and scored ``RANSAC_BATCH`` at a time and then taken in turn, as one at a
    time would take them (the iterations after the stopping one are not counted): a wrong loop candidate runs all
    300 iterations, one by one 70 ms of numpy calls (fr1/desk with loop closure: 36 s a run)."""
    count = len(matches.points_a)
    if count < MINIMAL_SET or count < min_inliers:
        return None
    best_S, best_inliers, best_count = None, None, 0
    iterations, needed = 0, max_iterations
    while iterations < needed:
        samples = np.array([rng.choice(count, size=MINIMAL_SET, replace=False)
                            for _ in range(min(RANSAC_BATCH, needed - iterations))])
        similarities, fitted = _minimal_similarities(matches, samples)
        inliers = _inliers_of_each(matches, camera, similarities, fitted, chi2)
        for S_a_b, model_inliers in zip(similarities, inliers):
            if iterations >= needed:
                break
            iterations += 1
            inlier_count = int(np.count_nonzero(model_inliers))
            if inlier_count > best_count:
                best_S, best_inliers, best_count = S_a_b, model_inliers, inlier_count
                needed = _iterations_needed(inlier_count / count, probability, max_iterations)
    if best_S is None or best_count < max(min_inliers, MINIMAL_SET):
        return None
    S_a_b, inliers = _refit_on_inliers(matches, camera, best_S, best_inliers, chi2)
    return Sim3Fit(S_a_b, inliers, iterations)


def _minimal_similarities(matches: Sim3Matches, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``_closed_form_sim3`` of each minimal set (rows of ``samples``, (K, 3) match indices) at once: S_a_b (K, 4, 4)
    and whether each set fixes a similarity (points not all coincident, a positive finite scale)."""
    R, t, scale, variance_source = _umeyama_of_each(matches.points_b[samples], matches.points_a[samples], True)
    S = np.zeros((len(samples), 4, 4))
    S[:, :3, :3] = scale[:, None, None] * R
    S[:, :3, 3] = t
    S[:, 3, 3] = 1.0
    return S, (variance_source > 0.0) & (scale > 0.0) & np.isfinite(scale)


def _inliers_of_each(matches: Sim3Matches, camera: PinholeCamera, similarities: np.ndarray, fitted: np.ndarray,
                     chi2: float) -> np.ndarray:
    """(K, N) ``reprojection_inliers`` of each of the similarities S_a_b (K, 4, 4); none where not ``fitted``."""
    sR, t = similarities[:, :3, :3], similarities[:, :3, 3]
    scale = np.sqrt(np.sum(sR**2, axis=(1, 2)) / 3.0)  # as sim3_scale
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse_sR = np.swapaxes(sR, 1, 2) / (scale**2)[:, None, None]  # [sR]^-1 = R^T / s
        in_a = np.einsum("kij,nj->kni", sR, matches.points_b) + t[:, None]
        in_b = np.einsum("kij,knj->kni", inverse_sR, matches.points_a[None] - t[:, None])
        inliers = (in_a[..., 2] > 0.0) & (in_b[..., 2] > 0.0)
        for points, uv, sigma2 in ((in_a, matches.uv_a, matches.sigma2_a), (in_b, matches.uv_b, matches.sigma2_b)):
            pixels = project_points(camera, points.reshape(-1, 3)).reshape(points.shape[:2] + (2,))
            inliers &= np.sum((pixels - uv) ** 2, axis=2) / sigma2 < chi2  # NaN (on a camera's plane): False
    return inliers & fitted[:, None]


# ------------------------------------------------------------------------------------------ refinement


def _in_seeing_cameras(sightings: Sim3Sightings, S_seer_seen: np.ndarray) -> np.ndarray:
    """The sighted points in the cameras of the keyframes that saw them: T_view_reference S x, (N, 3)."""
    mapped = transform_points(S_seer_seen, sightings.points)
    T = sightings.T_view_reference
    return np.einsum("nij,nj->ni", T[:, :3, :3], mapped) + T[:, :3, 3]


def _sighting_errors(sightings: Sim3Sightings, camera: PinholeCamera,
                     S_seer_seen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per sighting, the squared reprojection error in units of its sigma2, and whether it is in front."""
    seen = _in_seeing_cameras(sightings, S_seer_seen)
    errors = np.sum((project_points(camera, seen) - sightings.uv) ** 2, axis=1) / sightings.sigma2
    return errors, seen[:, 2] > 0.0


def _sighting_inliers(sightings: Sim3Sightings, camera: PinholeCamera, S_seer_seen: np.ndarray,
                      chi2: float) -> np.ndarray:
    errors, in_front = _sighting_errors(sightings, camera, S_seer_seen)
    return in_front & (errors < chi2)  # NaN errors (a point on the camera's plane) compare False


def _residuals(into_a: Sim3Sightings, into_b: Sim3Sightings, camera: PinholeCamera, S_a_b: np.ndarray) -> np.ndarray:
    """Reprojection errors of b's points in a's side and of a's points in b's side, each pixel component divided by
    its observation's sigma: (2 (N_a + N_b),)."""
    in_a = project_points(camera, _in_seeing_cameras(into_a, S_a_b)) - into_a.uv
    in_b = project_points(camera, _in_seeing_cameras(into_b, sim3_inverse(S_a_b))) - into_b.uv
    return np.concatenate([
        (in_a / np.sqrt(into_a.sigma2)[:, None]).ravel(),
        (in_b / np.sqrt(into_b.sigma2)[:, None]).ravel(),
    ])


def _optimize(into_a: Sim3Sightings, into_b: Sim3Sightings, camera: PinholeCamera, S_a_b: np.ndarray, chi2: float,
              iterations: int) -> np.ndarray:
    """S_a_b after ``iterations`` (at most, >= 1) of trust-region least squares over a left update exp(delta) S_a_b,
    with Huber's kernel at sqrt(chi2): an error beyond the inlier bound counts linearly, as with ORB-SLAM2's
    deltaHuber = sqrt(th2) (scipy applies it to each pixel component, g2o to each observation's 2-vector)."""
    if len(into_a.points) + len(into_b.points) == 0:
        return S_a_b
    # Imported here: scipy.optimize takes 0.1 s to import, and only loop closure refines a similarity; the rest of this
    # module (Umeyama's alignment) is in every evaluated run.
    from scipy.optimize import least_squares

    solution = least_squares(
        lambda delta: _residuals(into_a, into_b, camera, sim3_exp(delta) @ S_a_b),
        np.zeros(SIM3_DOF), loss="huber", f_scale=np.sqrt(chi2), max_nfev=iterations, method="trf",
    )
    return sim3_exp(solution.x) @ S_a_b


def _left_update_jacobians(points: np.ndarray) -> np.ndarray:
    """d(exp(delta) x)/d delta at delta = 0 for the similarity's tangent (v, w, sigma): [I, -[x]x, x], (L, 3, 7)."""
    return np.concatenate([pose_jacobians(points), points[:, :, None]], axis=2)


def sim3_information_on_sightings(into_a: Sim3Sightings, into_b: Sim3Sightings, camera: PinholeCamera,
                                  S_a_b: np.ndarray) -> np.ndarray:
    """J^T J (7, 7) of the reprojection residuals ``refine_sim3_on_sightings`` minimizes (each in units of its
    observation's sigma), for the left update exp(delta) S_a_b: the Gauss-Newton information of S_a_b in its
    tangent (v, w, sigma) with the map points and the keyframes within each side held. Large along what the
    sightings pin down, small along what they leave free (a narrow view of a far scene trades rotation against
    translation, and says so here)."""
    mapped_b = transform_points(S_a_b, into_a.points)  # b's points in a: exp(delta) moves them
    in_a = (projection_jacobians(camera, _in_seeing_cameras(into_a, S_a_b)) @ into_a.T_view_reference[:, :3, :3]
            @ _left_update_jacobians(mapped_b))
    inverse = sim3_inverse(S_a_b)  # a's points in b: S^-1 exp(-delta) moves them
    in_b = (-projection_jacobians(camera, _in_seeing_cameras(into_b, inverse)) @ into_b.T_view_reference[:, :3, :3]
            @ inverse[:3, :3] @ _left_update_jacobians(into_b.points))
    J = np.concatenate([in_a / np.sqrt(into_a.sigma2)[:, None, None],
                        in_b / np.sqrt(into_b.sigma2)[:, None, None]]).reshape(-1, SIM3_DOF)
    return J.T @ J


def sim3_information(matches: Sim3Matches, camera: PinholeCamera, S_a_b: np.ndarray) -> np.ndarray:
    """``sim3_information_on_sightings`` of two keyframes' matches: J^T J of their two-way reprojection residuals."""
    return sim3_information_on_sightings(*sightings_of(matches), camera, S_a_b)


def refine_sim3_on_sightings(into_a: Sim3Sightings, into_b: Sim3Sightings, camera: PinholeCamera,
                             S_a_b: np.ndarray, *, chi2: float,
                             iterations: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """S_a_b refined on both sides' sightings of the other's points, map points and each side's keyframes held
    (``refine_sim3`` on neighbourhoods): a first round on the sightings in front of their cameras, a second on those
    within ``chi2`` after it. Returns (S_a_b, inliers into a, inliers into b), at ``chi2`` of the result."""
    first = _optimize(into_a.subset(_sighting_errors(into_a, camera, S_a_b)[1]),
                      into_b.subset(_sighting_errors(into_b, camera, sim3_inverse(S_a_b))[1]),
                      camera, S_a_b, chi2, iterations)
    second = _optimize(into_a.subset(_sighting_inliers(into_a, camera, first, chi2)),
                       into_b.subset(_sighting_inliers(into_b, camera, sim3_inverse(first), chi2)),
                       camera, first, chi2, iterations)
    return (second, _sighting_inliers(into_a, camera, second, chi2),
            _sighting_inliers(into_b, camera, sim3_inverse(second), chi2))


def refine_sim3(matches: Sim3Matches, camera: PinholeCamera, S_a_b: np.ndarray, *, chi2: float,
                iterations: int) -> Sim3Fit:
    """S_a_b refined on the matches' reprojection errors both ways, map points fixed (ORB-SLAM2 OptimizeSim3):
    a first round on the matches in front of both cameras, a second on those whose errors both ways are
    within ``chi2`` after it, ``iterations`` at most each. Its inliers are ``reprojection_inliers`` of the result."""
    # A point behind a camera has a projection that means nothing, and one near its plane a huge error: leave
    # them out from the start rather than let the kernel fight them.
    _, _, in_front = _two_way_errors(matches, camera, S_a_b)
    first = _optimize(*sightings_of(matches.subset(in_front)), camera, S_a_b, chi2, iterations)
    errors_a, errors_b, in_front = _two_way_errors(matches, camera, first)
    kept = in_front & (errors_a <= chi2) & (errors_b <= chi2)
    second = _optimize(*sightings_of(matches.subset(kept)), camera, first, chi2, iterations)
    return Sim3Fit(second, reprojection_inliers(matches, camera, second, chi2), 0)
