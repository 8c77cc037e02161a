"""Two-view reconstruction as ORB-SLAM initializes (Mur-Artal et al. 2015, section IV; paper 004 section 3.2): the
one the project has, used by the feature initializer of the direct system and by the KLT baseline's bootstrap.

A homography and a fundamental matrix are estimated in parallel by RANSAC over the same 8-point samples,
each scored by its symmetric transfer error (004 eqs. 2-5); the homography wins when
S_H / (S_H + S_F) > 0.4 (eq. 1). The winner is decomposed into motion hypotheses (the homography by Faugeras'
method through cv2.decomposeHomographyMat, the fundamental matrix through E = K^T F K and its four
(R, t) solutions), and the hypothesis with clearly the most points triangulated in front of both cameras,
reprojecting well and seen under enough parallax is kept. When two hypotheses are close, or too few points
or too little parallax support the best, there is no answer: a wrong map is worse than a later one.

Conventions: ``uv_first`` / ``uv_second`` are (N, 2) pixels; the pose returned is ``T_first_second`` with a
unit baseline.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vo_core.geometry.camera import PinholeCamera
from vo_core.geometry.lie import motion_angles_deg, se3, se3_inverse
from vo_core.geometry.multiview import bearing_angles, triangulate

MIN_CORRESPONDENCES = 8  # both minimal solvers use eight points


@dataclass
class TwoViewConfig:
    """Homography and fundamental matrix in parallel (004 section 3.2, after ORB-SLAM IV)."""

    ransac_iterations: int = 200  # ORB-SLAM: 200 sets of 8 correspondences, shared by both models
    sample_size: int = 8  # ORB-SLAM: 8 points for both the normalized DLT (H) and the 8-point algorithm (F)
    sigma_px: float = 1.0  # ORB-SLAM: measurement noise of one pixel
    essential_confidence: float = 0.999  # of the five-point RANSAC on F's inliers (cv2.findEssentialMat's default)
    chi2_homography: float = 5.99  # 3.2 eq. 3: T_H (chi-square 95 %, 2 DOF)
    chi2_fundamental: float = 3.84  # 3.2 eq. 3: T_F (chi-square 95 %, 1 DOF)
    score_gamma: float = 5.99  # 3.2 eq. 3: Gamma = T_H, so both models score on the same scale
    homography_ratio: float = 0.4  # 3.2 eq. 1: homography when S_H / (S_H + S_F) > 0.4
    max_reprojection_px: float = 2.0  # ORB-SLAM CheckRT: squared error < 4 sigma^2 in both views
    min_parallax_deg: float = 1.0  # ORB-SLAM Initialize(): minParallax = 1 degree
    # The baseline over the median depth of the good points. A start is a triangulation, and FDMO (4.4) triangulates
    # none below baseline / depth 0.02 (the feature map's rule); DSO's coarse initializer snaps at translation x
    # mean inverse depth sqrt(alphaK / alphaW) = 2.5 / 150 = 0.017. ORB-SLAM's parallax rule alone passed a start at
    # 0.014 taken from 1.3 degrees of its 50th largest angle (EuRoC MH05, a drone taking off): the map's scale was
    # 50x off for 30 frames. Right starts on the shared folders: 0.043-0.091.
    min_baseline_depth_ratio: float = 0.02
    min_triangulated: int = 50  # ORB-SLAM: minTriangulated = 50 good points for a hypothesis
    min_good_ratio: float = 0.9  # ORB-SLAM: the best hypothesis explains 90 % of the model's inliers
    ambiguity_ratio: float = 0.75  # ORB-SLAM ReconstructH: second best < 0.75 best; ReconstructF uses 0.7
    parallax_rank: int = 50  # ORB-SLAM CheckRT: the parallax of a hypothesis is its 50th largest angle
    # A homography's motion must be the essential matrix's too (the five-point E of F's inliers holds for planar and
    # general scenes alike), where that E explains its inliers: with little parallax both fit the views, and a
    # homography fitted to a scene that is not a plane decomposes into a motion that points elsewhere. Each is
    # trusted to within 5 degrees of the true direction (tests/test_init_two_view.py: 0.5-3 measured), so two that
    # differ by more than twice that are not the same motion. Measured: planar synthetic scenes 0-2.8 degrees,
    # right homography starts on EuRoC MH05 0.6-1.1, its wrong ones (fdmo and the features method) 127-128.
    max_motion_disagreement_deg: float = 10.0


@dataclass
class ModelScores:
    """The outcome of the parallel RANSAC: both models, their scores and inliers."""

    H: np.ndarray  # 3x3, x_second ~ H x_first
    F: np.ndarray  # 3x3, x_second^T F x_first = 0
    score_h: float
    score_f: float
    inliers_h: np.ndarray  # (N,) bool
    inliers_f: np.ndarray

    @property
    def ratio(self) -> float:
        """R_H = S_H / (S_H + S_F) (004 eq. 1)."""
        total = self.score_h + self.score_f
        return self.score_h / total if total > 0 else 0.0


@dataclass
class TwoViewResult:
    model: str  # "H" or "F"
    T_first_second: np.ndarray  # 4x4, |t| = 1
    points_first: np.ndarray  # (N, 3) in the first camera, valid where ``good``
    good: np.ndarray  # (N,) bool: model inlier, in front of both cameras, reprojecting well
    parallax_deg: float
    baseline_depth_ratio: float  # the baseline over the median depth of the good points
    scores: ModelScores
    hypotheses_good: list[int]  # good points of every hypothesis, for the event

    @property
    def inliers(self) -> np.ndarray:
        """(N,) bool: the correspondences the chosen model explains (triangulated or not)."""
        return self.scores.inliers_h if self.model == "H" else self.scores.inliers_f


class TwoViewFailure(Exception):
    """No reliable relative pose; the message says why (it goes into the caller's status or event)."""


# ------------------------------------------------------------------------------------------ estimation


def _normalizing_transform(uv: np.ndarray) -> np.ndarray:
    """Hartley normalization: centroid to the origin, mean absolute deviation 1 per axis (ORB-SLAM Normalize)."""
    mean = uv.mean(axis=0)
    spread = np.abs(uv - mean).mean(axis=0)
    spread[spread == 0] = 1.0
    return np.array([[1 / spread[0], 0, -mean[0] / spread[0]], [0, 1 / spread[1], -mean[1] / spread[1]], [0, 0, 1]])


def _homogeneous(uv: np.ndarray) -> np.ndarray:
    return np.concatenate([uv, np.ones((*uv.shape[:-1], 1))], axis=-1)


def _null_vectors(A: np.ndarray) -> np.ndarray:
    """Right singular vectors of the smallest singular value of a stack of matrices (S, m, 9) -> (S, 9)."""
    return np.linalg.svd(A)[2][:, -1, :]


def _homographies(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Normalized DLT per sample, x1/x2 (S, 8, 2) normalized pixels -> (S, 3, 3) (Hartley-Zisserman alg. 4.1)."""
    S, n, _ = x1.shape
    u1, v1, u2, v2 = x1[..., 0], x1[..., 1], x2[..., 0], x2[..., 1]
    zero, one = np.zeros_like(u1), np.ones_like(u1)
    rows_a = np.stack([zero, zero, zero, -u1, -v1, -one, v2 * u1, v2 * v1, v2], axis=-1)
    rows_b = np.stack([u1, v1, one, zero, zero, zero, -u2 * u1, -u2 * v1, -u2], axis=-1)
    A = np.concatenate([rows_a, rows_b], axis=1)
    return _null_vectors(A).reshape(S, 3, 3)


def _fundamentals(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Eight-point algorithm per sample with the rank-2 constraint enforced (Hartley-Zisserman alg. 11.1)."""
    S = len(x1)
    u1, v1, u2, v2 = x1[..., 0], x1[..., 1], x2[..., 0], x2[..., 1]
    A = np.stack([u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, np.ones_like(u1)], axis=-1)
    F = _null_vectors(A).reshape(S, 3, 3)
    U, singular, Vt = np.linalg.svd(F)
    singular[:, 2] = 0.0
    return U @ (singular[:, :, None] * Vt)


def _homography_errors(H: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Squared transfer errors d_cr^2 and d_rc^2 (004 eqs. 4, 5) of every model (S, 3, 3) and point: (S, N)."""

    def transfer(M, source, target):
        # (3, S, N) through one batched matmul: np.einsum took 10x longer, and component planes avoid strided slices
        x, y, z = np.moveaxis(source @ M.transpose(0, 2, 1), -1, 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            dx = x / z - target[:, 0]
            dy = y / z - target[:, 1]
        error = dx * dx + dy * dy
        return np.where(np.isfinite(error), error, np.inf)

    return transfer(H, p1, p2), transfer(np.linalg.inv(H), p2, p1)


def _epipolar_errors(F: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Squared distances of each point to its epipolar line in the other image (004 eqs. 4, 5): (S, N) each."""
    lines_2 = np.moveaxis(p1 @ F.transpose(0, 2, 1), -1, 0)  # F x1: lines in the second image, (3, S, N)
    lines_1 = np.moveaxis(p2 @ F, -1, 0)  # F^T x2: lines in the first image
    algebraic = lines_2[0] * p2[:, 0] + lines_2[1] * p2[:, 1] + lines_2[2] * p2[:, 2]  # x2^T F x1, for both lines
    with np.errstate(divide="ignore", invalid="ignore"):
        d2 = algebraic**2 / (lines_2[0] ** 2 + lines_2[1] ** 2)
        d1 = algebraic**2 / (lines_1[0] ** 2 + lines_1[1] ** 2)
    return np.nan_to_num(d2, nan=np.inf), np.nan_to_num(d1, nan=np.inf)


def _scores(
    errors: tuple[np.ndarray, np.ndarray], threshold: float, config: TwoViewConfig
) -> tuple[np.ndarray, np.ndarray]:
    """S_M = sum rho_M(d_cr^2) + rho_M(d_rc^2), rho_M(d^2) = Gamma - d^2 below T_M (004 eqs. 2, 3), and the
    inliers (both directions below the threshold), of every model: (S,), (S, N)."""
    score = np.zeros(errors[0].shape[0])
    inliers = np.ones(errors[0].shape, bool)
    for squared in errors:
        chi2 = squared / config.sigma_px**2
        below = chi2 < threshold
        score += np.where(below, config.score_gamma - chi2, 0.0).sum(axis=1)
        inliers &= below
    return score, inliers


def estimate_models(
    uv_first: np.ndarray, uv_second: np.ndarray, config: TwoViewConfig, rng: np.random.Generator
) -> ModelScores:
    """Homography and fundamental matrix by RANSAC on the same samples, each the best scored of its kind."""
    n = len(uv_first)
    if n < MIN_CORRESPONDENCES:
        raise TwoViewFailure(f"{n} correspondences, two-view geometry needs {MIN_CORRESPONDENCES}")
    samples = np.stack([rng.choice(n, config.sample_size, replace=False) for _ in range(config.ransac_iterations)])
    T1, T2 = _normalizing_transform(uv_first), _normalizing_transform(uv_second)
    p1, p2 = _homogeneous(uv_first), _homogeneous(uv_second)
    x1 = (p1 @ T1.T)[:, :2][samples]
    x2 = (p2 @ T2.T)[:, :2][samples]
    # Denormalize: x2 = H x1 in pixels is T2^-1 Hn T1; x2^T F x1 = 0 in pixels is T2^T Fn T1.
    H = np.linalg.inv(T2) @ _homographies(x1, x2) @ T1
    F = T2.T @ _fundamentals(x1, x2) @ T1
    score_h, inliers_h = _scores(_homography_errors(H, p1, p2), config.chi2_homography, config)
    score_f, inliers_f = _scores(_epipolar_errors(F, p1, p2), config.chi2_fundamental, config)
    best_h, best_f = int(np.argmax(score_h)), int(np.argmax(score_f))
    return ModelScores(
        H[best_h] / H[best_h][2, 2] if H[best_h][2, 2] != 0 else H[best_h], F[best_f],
        float(score_h[best_h]), float(score_f[best_f]), inliers_h[best_h], inliers_f[best_f],
    )


# -------------------------------------------------------------------------------------- reconstruction


@dataclass
class MotionHypothesis:
    T_first_second: np.ndarray
    points: np.ndarray
    good: np.ndarray
    parallax_deg: float


def _check_motion(
    camera: PinholeCamera, R: np.ndarray, t: np.ndarray, uv_first: np.ndarray, uv_second: np.ndarray,
    inliers: np.ndarray, config: TwoViewConfig,
) -> MotionHypothesis:
    """ORB-SLAM CheckRT: triangulate the inliers under x_second = R x_first + t; good points lie in front of
    both cameras and reproject within the threshold into both. The parallax is the 50th largest angle (ORB-SLAM):
    enough points must see it, so that a handful of near points does not pass a hypothesis."""
    t = t.ravel() / max(np.linalg.norm(t), 1e-12)
    T_first_second = se3_inverse(se3(R, t))
    points, valid = triangulate(
        camera, np.eye(4), uv_first, T_first_second, uv_second, max_reprojection_px=config.max_reprojection_px,
        min_depth=0.0,
    )
    good = valid & inliers
    parallax = 0.0
    if good.any():
        angles = np.degrees(bearing_angles(camera, np.eye(4), uv_first[good], T_first_second, uv_second[good]))
        parallax = float(np.sort(angles)[::-1][min(config.parallax_rank, len(angles) - 1)])
    return MotionHypothesis(T_first_second, points, good, parallax)


def _motion_hypotheses(model: str, scores: ModelScores, K: np.ndarray, uv_first: np.ndarray, uv_second: np.ndarray,
                       config: TwoViewConfig) -> list[tuple[np.ndarray, np.ndarray]]:
    """(R, t) candidates: Faugeras' decomposition of H (up to 4), or the 4 solutions of the essential matrix of the
    fundamental matrix's inliers.

    That essential matrix is estimated anew by the calibrated five-point solver (cv2.findEssentialMat, USAC_ACCURATE:
    RANSAC with local optimization and a final fit to all its inliers; deterministic), where
    ORB-SLAM and 004 decompose E = K^T F K: an eight-point F carries no essential constraint (two equal singular
    values), and its projection onto one moved the geometry enough that no motion triangulated the inliers within
    the reprojection threshold (TUM fr1/desk at half its frame rate, 10 degrees of rotation: 0 of 115, 182 and 258
    inliers; with the five-point E: 114, 181 and 256)."""
    if model == "H":
        _, rotations, translations, _ = cv2.decomposeHomographyMat(scores.H, K)
        return list(zip(rotations, translations))
    inliers = scores.inliers_f
    if inliers.sum() < 5:
        return []
    E, _ = cv2.findEssentialMat(uv_first[inliers], uv_second[inliers], K, cv2.USAC_ACCURATE,
                                config.essential_confidence, config.sigma_px)
    return [] if E is None else _essential_motions(E[:3])


def _essential_motions(E: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    R1, R2, t = cv2.decomposeEssentialMat(E)
    return [(R1, t), (R1, -t), (R2, t), (R2, -t)]


def motion_from_essential(
    camera: PinholeCamera, E: np.ndarray, uv_first: np.ndarray, uv_second: np.ndarray, inliers: np.ndarray,
    config: TwoViewConfig,
) -> MotionHypothesis:
    """The solution of an essential matrix that triangulates the most ``inliers`` in front of both views within the
    reprojection threshold (ORB-SLAM CheckRT on each). cv2.recoverPose chooses the same way, with a distance limit
    in place of the reprojection test, but triangulates point by point: 90 ms for a pair of 3000-feature images."""
    hypotheses = [_check_motion(camera, R, t, uv_first, uv_second, inliers, config) for R, t in _essential_motions(E)]
    return max(hypotheses, key=lambda hypothesis: int(hypothesis.good.sum()))


def _pnp_error(camera: PinholeCamera, points: np.ndarray, uv: np.ndarray) -> float:
    """Median reprojection error (px) of ``points`` in a further view after EPnP: how well a hypothesis'
    structure explains a third frame."""
    ok, rvec, tvec = cv2.solvePnP(
        np.ascontiguousarray(points, float), np.ascontiguousarray(uv, float), camera.K, None, flags=cv2.SOLVEPNP_EPNP
    )
    if not ok:
        return np.inf
    projected, _ = cv2.projectPoints(points, rvec, tvec, camera.K, None)
    return float(np.median(np.linalg.norm(projected.reshape(-1, 2) - uv, axis=1)))


def _resolve_with_other_views(
    camera: PinholeCamera, rivals: list[MotionHypothesis], uv_others: list[np.ndarray], config: TwoViewConfig
) -> MotionHypothesis | None:
    """A plane seen in two views leaves two valid motions (Faugeras' two-fold ambiguity); a third view of the
    same tracks tells them apart, since only the true structure projects into it consistently. Returns the
    rival whose structure explains the other views clearly best, or None."""
    if not uv_others:
        return None
    errors = []
    for rival in rivals:
        good = rival.good
        if good.sum() < MIN_CORRESPONDENCES:
            errors.append(np.inf)
            continue
        errors.append(max(_pnp_error(camera, rival.points[good], uv[good]) for uv in uv_others))
    order = np.argsort(errors)
    best, second = errors[order[0]], errors[order[1]]
    if best <= config.max_reprojection_px and second > best / config.ambiguity_ratio:
        return rivals[order[0]]
    return None


def _checked_motions(camera: PinholeCamera, model: str, scores: ModelScores, uv_first: np.ndarray,
                     uv_second: np.ndarray, config: TwoViewConfig) -> tuple[list[MotionHypothesis], float]:
    """Every motion of ``model`` checked on its inliers (ORB-SLAM CheckRT), and how many good points the best must
    have (ORB-SLAM: 90 % of the model's inliers, and at least minTriangulated)."""
    inliers = scores.inliers_h if model == "H" else scores.inliers_f
    hypotheses = [_check_motion(camera, R, t, uv_first, uv_second, inliers, config)
                  for R, t in _motion_hypotheses(model, scores, camera.K, uv_first, uv_second, config)]
    return hypotheses, max(config.min_good_ratio * inliers.sum(), config.min_triangulated)


def _essential_disagreement(camera: PinholeCamera, chosen: MotionHypothesis, scores: ModelScores, uv_first: np.ndarray,
                            uv_second: np.ndarray, config: TwoViewConfig) -> float:
    """The angle (degrees) between the translation of a homography's motion and that of the essential matrix of F's
    inliers, where that essential matrix explains them as a start must (0 where it does not: a pure rotation, or
    too few inliers, leaves the homography alone to say)."""
    hypotheses, needed = _checked_motions(camera, "F", scores, uv_first, uv_second, config)
    explaining = [h for h in hypotheses if h.good.sum() >= needed]
    if not explaining:
        return 0.0
    essential = max(explaining, key=lambda hypothesis: int(hypothesis.good.sum()))
    return motion_angles_deg(chosen.T_first_second, essential.T_first_second)[1]


def reconstruct(
    camera: PinholeCamera, uv_first: np.ndarray, uv_second: np.ndarray, config: TwoViewConfig,
    rng: np.random.Generator, uv_others: list[np.ndarray] | None = None,
) -> TwoViewResult:
    """Relative pose (unit baseline) and structure of two views, or TwoViewFailure saying why not.

    ``uv_others``: the same tracks in further frames (e.g. between the two), used only to resolve two
    hypotheses that explain the two views equally well."""
    uv_first = np.asarray(uv_first, float)
    uv_second = np.asarray(uv_second, float)
    scores = estimate_models(uv_first, uv_second, config, rng)
    model = "H" if scores.ratio > config.homography_ratio else "F"
    hypotheses, needed = _checked_motions(camera, model, scores, uv_first, uv_second, config)
    counts = [int(h.good.sum()) for h in hypotheses]
    best_count = max(counts, default=0)
    prefix = f"{model} (R_H {scores.ratio:.2f})"
    if best_count < needed:
        raise TwoViewFailure(f"{prefix}: best motion explains {best_count} points, needs {needed:.0f}")
    rivals = [h for h, c in zip(hypotheses, counts) if c >= config.ambiguity_ratio * best_count]
    best = rivals[0] if len(rivals) == 1 else _resolve_with_other_views(camera, rivals, uv_others or [], config)
    if best is None:
        ranked = sorted(counts, reverse=True)
        raise TwoViewFailure(f"{prefix}: ambiguous, two motions explain {ranked[0]} and {ranked[1]} points")
    if best.parallax_deg < config.min_parallax_deg:
        raise TwoViewFailure(f"{prefix}: parallax {best.parallax_deg:.2f} deg below {config.min_parallax_deg}")
    ratio = 1.0 / float(np.median(best.points[best.good, 2]))  # the baseline is 1
    if ratio < config.min_baseline_depth_ratio:
        raise TwoViewFailure(f"{prefix}: baseline / median depth {ratio:.4f} below {config.min_baseline_depth_ratio}")
    if model == "H":
        disagreement = _essential_disagreement(camera, best, scores, uv_first, uv_second, config)
        if disagreement > config.max_motion_disagreement_deg:
            raise TwoViewFailure(f"{prefix}: the homography's and the essential matrix's motions point "
                                 f"{disagreement:.0f} deg apart: the views do not determine the motion yet")
    return TwoViewResult(model, best.T_first_second, best.points, best.good, best.parallax_deg, ratio, scores, counts)
