"""Matching ORB descriptors: blind within a vocabulary node, guided by a projection, along epipolar lines.

After ORB-SLAM2 src/ORBmatcher.cc (``SearchByBoW``, ``SearchByProjection``, ``SearchForTriangulation``,
``ComputeThreeMaxima``), rewritten for numpy: candidate pairs are built all at once, their Hamming distances
computed in one call, and best / second best / one-to-one resolved by sorting, never by a loop per feature.

Every search returns two index arrays of equal length (a pair per match), sorted by the first one. All are
one-to-one: where several queries pick the same feature, the one at the smallest distance keeps it (ORB-SLAM2
keeps the first or the last, depending on the search).

Hamming distances: descriptors are read as four 64-bit words, XORed, and their set bits counted with
``np.bitwise_count`` (numpy >= 2, a hardware popcount where there is one; several times faster than a
256-entry lookup table).
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial import cKDTree

from vo_core.features.config import OrbConfig
from vo_core.features.orb import DESCRIPTOR_BYTES, Features, level_sigma2s

# ORB-SLAM2 ORBmatcher::TH_LOW and TH_HIGH: thresholds on the Hamming distance (of 256 bits).
TH_LOW = 50
TH_HIGH = 100
DESCRIPTOR_BITS = 8 * DESCRIPTOR_BYTES
HISTO_LENGTH = 30  # ORB-SLAM2 HISTO_LENGTH: bins of the rotation histogram
ROTATION_BINS_KEPT = 3  # ORB-SLAM2 ComputeThreeMaxima
# ORB-SLAM2 ComputeThreeMaxima: the second and third bins count only with at least 10 % of the first's matches.
MIN_BIN_FRACTION = 0.1
# ORB-SLAM2 CheckDistEpipolarLine: squared distance to the line below 3.84 sigma^2, the 95 % quantile of
# chi-square with one degree of freedom.
CHI2_ONE_DOF_95 = 3.84
# ORB-SLAM2 SearchForTriangulation: no match closer to the epipole than 10 px (squared: 100 s^level), where
# depth is ill-conditioned.
EPIPOLE_MIN_DISTANCE_PX = 10.0
FULL_CIRCLE_DEG = 360.0
WORDS_PER_DESCRIPTOR = DESCRIPTOR_BYTES // 8
# Bytes of XOR scratch (one lane) one block of ``hamming`` may use (ours: 8 MiB, about a millisecond of work).
HAMMING_BLOCK_BYTES = 8 * 2**20

_DEFAULT_ORB = OrbConfig()


# -------------------------------------------------------------------------------------------- distances


def _words(descriptors: np.ndarray) -> np.ndarray:
    """(N, 32) uint8 -> (N, 4) uint64 views (copied only when not contiguous)."""
    descriptors = np.ascontiguousarray(descriptors, dtype=np.uint8).reshape(-1, DESCRIPTOR_BYTES)
    return descriptors.view(np.uint64)


def _popcount_words(xor: np.ndarray) -> np.ndarray:
    """Set bits of (..., 4) uint64 words, summed over the last axis as int32. The four lanes are added
    explicitly: numpy's reduction over a length-4 axis is an order of magnitude slower."""
    counts = np.bitwise_count(xor)
    total = counts[..., 0].astype(np.int32)
    for lane in range(1, WORDS_PER_DESCRIPTOR):
        total += counts[..., lane]
    return total


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) int32 Hamming distances between the rows of ``a`` (N, 32) and ``b`` (M, 32). One 64-bit lane at a
    time: an (N, M) XOR per lane is several times faster than broadcasting over a trailing axis of 4."""
    wa, wb = _words(a), _words(b)
    out = np.empty((len(wa), len(wb)), dtype=np.int32)
    rows = max(1, HAMMING_BLOCK_BYTES // max(1, len(wb) * 8))
    for start in range(0, len(wa), rows):
        block = wa[start : start + rows]
        total = out[start : start + rows]
        total[...] = np.bitwise_count(block[:, 0, None] ^ wb[None, :, 0])
        for lane in range(1, WORDS_PER_DESCRIPTOR):
            total += np.bitwise_count(block[:, lane, None] ^ wb[None, :, lane])
    return out


def hamming_within(groups: np.ndarray) -> np.ndarray:
    """(G, M, M) Hamming distances between the M descriptors of each of G groups ((G, M, 32) uint8)."""
    words = np.ascontiguousarray(groups, dtype=np.uint8).view(np.uint64)  # (G, M, 4)
    return _popcount_words(words[:, :, None, :] ^ words[:, None, :, :])


def hamming_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) int32 Hamming distances between row i of ``a`` and row i of ``b`` (both (N, 32))."""
    return _popcount_words(_words(a) ^ _words(b))


# ----------------------------------------------------------------------------------- rotation histogram


def orientation_consistent(
    angle_a: np.ndarray, angle_b: np.ndarray, bins: int = HISTO_LENGTH, keep: int = ROTATION_BINS_KEPT
) -> np.ndarray:
    """Mask of the matches whose rotation angle_a - angle_b (degrees) falls in one of the ``keep`` most
    populated of ``bins`` equal bins over 360 degrees (ORB-SLAM2's rotation histogram): a rigid motion
    rotates every feature by about the same angle. Bins after the first count only with at least
    ``MIN_BIN_FRACTION`` of its matches, as in ComputeThreeMaxima.

    ORB-SLAM2 computes the bin as round(rot / HISTO_LENGTH), i.e. 12 bins of 30 degrees; here the bins are
    what the argument says: ``bins`` bins of 360 / bins degrees (30 bins of 12 degrees by default)."""
    rotation = (np.asarray(angle_a, float) - np.asarray(angle_b, float)) % FULL_CIRCLE_DEG
    if rotation.size == 0:
        return np.zeros(0, dtype=bool)
    bin_of_match = np.rint(rotation * bins / FULL_CIRCLE_DEG).astype(int) % bins
    counts = np.bincount(bin_of_match, minlength=bins)
    ranked = np.argsort(-counts, kind="stable")[:keep]
    kept = ranked[(counts[ranked] > 0) & (counts[ranked] >= MIN_BIN_FRACTION * counts[ranked[0]])]
    return np.isin(bin_of_match, kept)


# ------------------------------------------------------------------------------------- shared machinery


def _pairs_with_same_key(keys_a: np.ndarray, keys_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All pairs (i, j) with keys_a[i] == keys_b[j], without a loop: both sides are grouped by key, and pair p
    of a key with n_a x n_b pairs takes member p // n_b of a's group and p % n_b of b's."""
    keys_a, keys_b = np.asarray(keys_a), np.asarray(keys_b)
    order_a, order_b = np.argsort(keys_a, kind="stable"), np.argsort(keys_b, kind="stable")
    unique_a, start_a, count_a = np.unique(keys_a[order_a], return_index=True, return_counts=True)
    unique_b, start_b, count_b = np.unique(keys_b[order_b], return_index=True, return_counts=True)
    _, in_a, in_b = np.intersect1d(unique_a, unique_b, assume_unique=True, return_indices=True)
    start_a, count_a, start_b, count_b = start_a[in_a], count_a[in_a], start_b[in_b], count_b[in_b]
    pairs_per_key = count_a * count_b
    total = int(pairs_per_key.sum())
    if total == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    key = np.repeat(np.arange(len(pairs_per_key)), pairs_per_key)
    local = np.arange(total) - np.repeat(np.cumsum(pairs_per_key) - pairs_per_key, pairs_per_key)
    i = order_a[start_a[key] + local // count_b[key]]
    j = order_b[start_b[key] + local % count_b[key]]
    return i, j


def _best_per_query(
    query: np.ndarray, target: np.ndarray, distance: np.ndarray, max_distance: float, ratio: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each query among the candidate pairs, its nearest target if the distance is at most
    ``max_distance`` and below ``ratio`` times the second nearest (Lowe's test; a lone candidate passes, as
    ORB-SLAM2's second best starts at the largest distance). Returns (query, target, distance)."""
    if len(query) == 0:
        return query, target, distance
    order = np.lexsort((target, distance, query))  # by query, then nearest first
    query, target, distance = query[order], target[order], distance[order]
    first = np.ones(len(query), dtype=bool)
    first[1:] = query[1:] != query[:-1]
    best = np.flatnonzero(first)
    has_second = np.zeros(len(best), dtype=bool)
    has_second[:-1] = ~first[best[:-1] + 1]
    has_second[-1] = best[-1] + 1 < len(query)
    second_distance = np.where(has_second, distance[np.minimum(best + 1, len(query) - 1)], np.inf)
    accepted = (distance[best] <= max_distance) & (distance[best] < ratio * second_distance)
    best = best[accepted]
    return query[best], target[best], distance[best]


def _one_to_one(
    query: np.ndarray, target: np.ndarray, distance: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keep, for each target chosen by several queries, the query at the smallest distance (ties: the lowest
    query index). Input has one row per query; output is sorted by query."""
    order = np.lexsort((query, distance, target))
    keep = np.ones(len(order), dtype=bool)
    keep[1:] = target[order][1:] != target[order][:-1]
    chosen = np.sort(order[keep])  # rows were sorted by query
    return query[chosen], target[chosen], distance[chosen]


def _mask_or_all(mask: np.ndarray | None, count: int) -> np.ndarray:
    return np.ones(count, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)


def _empty_match() -> tuple[np.ndarray, np.ndarray]:
    return np.zeros(0, dtype=int), np.zeros(0, dtype=int)


def _keep_consistent_rotation(
    idx_a: np.ndarray, idx_b: np.ndarray, angle_a: np.ndarray, angle_b: np.ndarray, check: bool
) -> tuple[np.ndarray, np.ndarray]:
    if check and len(idx_a):
        consistent = orientation_consistent(angle_a[idx_a], angle_b[idx_b])
        idx_a, idx_b = idx_a[consistent], idx_b[consistent]
    return idx_a, idx_b


# ----------------------------------------------------------------------------------------------- by BoW


def match_by_bow(
    features_a: Features,
    nodes_a: np.ndarray,
    features_b: Features,
    nodes_b: np.ndarray,
    *,
    max_distance: float = TH_LOW,
    ratio: float = 0.75,
    check_orientation: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Blind matching of two images restricted to features that share a vocabulary node (ORB-SLAM2
    SearchByBoW; its default ratio mfNNratio = 0.75 in relocalization). ``nodes_*`` are the per-feature
    nodes of ``Vocabulary.transform``. For each feature of a: its nearest feature of b in the same node,
    within ``max_distance`` and passing the ratio test; then one-to-one and the rotation histogram.
    Returns (idx_a, idx_b)."""
    if len(features_a) == 0 or len(features_b) == 0:
        return _empty_match()
    i, j = _pairs_with_same_key(nodes_a, nodes_b)
    distance = hamming_rows(features_a.descriptors[i], features_b.descriptors[j])
    i, j, distance = _one_to_one(*_best_per_query(i, j, distance, max_distance, ratio))
    return _keep_consistent_rotation(i, j, features_a.angle, features_b.angle, check_orientation)


# ---------------------------------------------------------------------------------------- by projection


def search_by_projection(
    features: Features,
    uv: np.ndarray,
    descriptors: np.ndarray,
    predicted_level: np.ndarray,
    radius_px: float | np.ndarray,
    *,
    max_distance: float = TH_HIGH,
    ratio: float = 0.8,
    level_window: int = 1,
    scale_factor: float = _DEFAULT_ORB.scale_factor,
    available: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Guided search of map points projected into an image (ORB-SLAM2 SearchByProjection(Frame, MapPoints)).

    Point i at ``uv[i]`` looks at the features within ``radius_px * scale_factor ** predicted_level[i]``
    pixels (``radius_px`` scalar or per point) whose level is within ``predicted_level[i] +- level_window``
    (ORB-SLAM2 looks at [level - 1, level]), and ``available`` ones only if given (e.g. those without a map
    point yet). It takes the nearest descriptor within ``max_distance`` that passes the ratio test against
    the second nearest (ORB-SLAM2 applies it only when both are on the same level; here always). A feature
    claimed by several points goes to the nearest. Returns (idx_points, idx_features)."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    count = len(uv)
    if count == 0 or len(features) == 0:
        return _empty_match()
    predicted_level = np.broadcast_to(np.asarray(predicted_level, dtype=int), (count,))
    radius = np.broadcast_to(np.asarray(radius_px, dtype=float), (count,)) * scale_factor**predicted_level
    finite = np.all(np.isfinite(uv), axis=1) & np.isfinite(radius)
    point, feature = _features_within(features.uv, uv, radius, finite)
    level_gap = np.abs(features.level[feature] - predicted_level[point])
    keep = (level_gap <= level_window) & _mask_or_all(available, len(features))[feature]
    point, feature = point[keep], feature[keep]
    distance = hamming_rows(np.asarray(descriptors)[point], features.descriptors[feature])
    point, feature, distance = _best_per_query(point, feature, distance, max_distance, ratio)
    point, feature, _ = _one_to_one(point, feature, distance)
    return point, feature


def _features_within(
    feature_uv: np.ndarray, uv: np.ndarray, radius: np.ndarray, valid: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """All (point, feature) pairs with the feature within the point's radius, flattened without a Python
    loop per point (the KD-tree returns one list per point; chain them in C)."""
    points = np.flatnonzero(valid)
    if len(points) == 0:
        return _empty_match()
    neighbours = cKDTree(feature_uv).query_ball_point(uv[points], radius[points], return_sorted=False)
    lengths = np.fromiter(map(len, neighbours), dtype=int, count=len(points))
    feature = np.fromiter(itertools.chain.from_iterable(neighbours), dtype=int, count=int(lengths.sum()))
    return np.repeat(points, lengths), feature


# ------------------------------------------------------------------------------------------- epipolar


def _skew(vector: np.ndarray) -> np.ndarray:
    x, y, z = vector
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def fundamental_matrix(camera_a, camera_b, T_a_b: np.ndarray) -> np.ndarray:
    """F_ba with u_b^T F_ba u_a = 0 for homogeneous pixels u_a of camera a and u_b of camera b seeing the
    same point; F_ba u_a is the epipolar line of u_a in image b.

    ``T_a_b`` maps points from frame b to frame a (X_a = R_ab X_b + t_ab); with keyframe poses
    ``T_a_b = inv(T_world_a) @ T_world_b``. Then X_b = R_ba X_a + t_ba, E_ba = [t_ba]x R_ba and
    F_ba = K_b^-T E_ba K_a^-1 (Hartley & Zisserman 9.6; ORB-SLAM2 ComputeF12 is this with a = 1, b = 2)."""
    T_b_a = np.linalg.inv(np.asarray(T_a_b, dtype=float))
    essential = _skew(T_b_a[:3, 3]) @ T_b_a[:3, :3]
    return np.linalg.inv(camera_b.K).T @ essential @ np.linalg.inv(camera_a.K)


def epipole_in_b(camera_b, T_a_b: np.ndarray) -> np.ndarray | None:
    """Pixel of camera a's centre seen from camera b (the epipole in image b), None when it is at infinity
    (a sideways motion). ORB-SLAM2 SearchForTriangulation projects it the same way, sign of depth ignored."""
    centre_a_in_b = np.linalg.inv(np.asarray(T_a_b, dtype=float))[:3, 3]
    if abs(centre_a_in_b[2]) <= np.finfo(float).eps * np.linalg.norm(centre_a_in_b):
        return None
    return camera_b.K[:2] @ (centre_a_in_b / centre_a_in_b[2])


def epipolar_distance_squared(F_ba: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray) -> np.ndarray:
    """Squared pixel distance of uv_b[i] to the epipolar line F_ba u_a[i] in image b, per row."""
    line = np.column_stack([uv_a, np.ones(len(uv_a))]) @ np.asarray(F_ba, float).T
    numerator = np.einsum("ij,ij->i", line[:, :2], uv_b) + line[:, 2]
    return numerator**2 / np.maximum(np.einsum("ij,ij->i", line[:, :2], line[:, :2]), np.finfo(float).tiny)


def search_epipolar(
    features_a: Features,
    features_b: Features,
    F_ba: np.ndarray,
    candidates_a: np.ndarray | None = None,
    candidates_b: np.ndarray | None = None,
    nodes_a: np.ndarray | None = None,
    nodes_b: np.ndarray | None = None,
    *,
    max_distance: float = TH_LOW,
    ratio: float = 0.6,
    check_orientation: bool = True,
    level_sigma2: np.ndarray | None = None,
    epipole_b: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Matches for triangulation between two images of known relative pose (ORB-SLAM2
    SearchForTriangulation): feature j of b may match feature i of a if its squared distance to the
    epipolar line of i (``F_ba`` from ``fundamental_matrix(camera_a, camera_b, T_a_b)``) is below
    3.84 sigma^2 of j's level (``level_sigma2`` per level, default ``level_sigma2s(OrbConfig())``), if it is
    not within 10 sqrt(s^level) px of ``epipole_b`` (when given), and if both share a node when ``nodes_*``
    are given. Only ``candidates_*`` (masks, e.g. features without a map point) take part. Each feature of a
    takes its nearest candidate within ``max_distance`` passing the ratio test (ORB-SLAM2 has none here; 0.6
    is the ratio LocalMapping builds its matcher with), then one-to-one and the rotation histogram.
    Returns (idx_a, idx_b)."""
    sigma2 = level_sigma2s(_DEFAULT_ORB) if level_sigma2 is None else np.asarray(level_sigma2, dtype=float)
    index_a = np.flatnonzero(_mask_or_all(candidates_a, len(features_a)))
    index_b = np.flatnonzero(_mask_or_all(candidates_b, len(features_b)))
    if epipole_b is not None and len(index_b):
        scale = np.sqrt(sigma2[features_b.level[index_b]])  # s^level
        far = np.linalg.norm(features_b.uv[index_b] - epipole_b, axis=1) >= EPIPOLE_MIN_DISTANCE_PX * np.sqrt(scale)
        index_b = index_b[far]
    if len(index_a) == 0 or len(index_b) == 0:
        return _empty_match()
    threshold_b = CHI2_ONE_DOF_95 * sigma2[features_b.level]  # per feature of b
    if nodes_a is not None and nodes_b is not None:
        i, j = _pairs_with_same_key(np.asarray(nodes_a)[index_a], np.asarray(nodes_b)[index_b])
        i, j = index_a[i], index_b[j]
        near = epipolar_distance_squared(F_ba, features_a.uv[i], features_b.uv[j]) < threshold_b[j]
        i, j = i[near], j[near]
    else:  # every candidate pair: the distances to the (unit-normal) lines as one (n_a, n_b) matrix
        line = np.column_stack([features_a.uv[index_a], np.ones(len(index_a))]) @ np.asarray(F_ba, float).T
        line /= np.maximum(np.linalg.norm(line[:, :2], axis=1, keepdims=True), np.finfo(float).tiny)
        distance_to_line = line[:, :2] @ features_b.uv[index_b].T
        distance_to_line += line[:, 2:]
        np.abs(distance_to_line, out=distance_to_line)
        near_a, near_b = np.nonzero(distance_to_line < np.sqrt(threshold_b[index_b]))
        i, j = index_a[near_a], index_b[near_b]
    distance = hamming_rows(features_a.descriptors[i], features_b.descriptors[j])
    i, j, distance = _one_to_one(*_best_per_query(i, j, distance, max_distance, ratio))
    return _keep_consistent_rotation(i, j, features_a.angle, features_b.angle, check_orientation)


__all__ = [
    "CHI2_ONE_DOF_95",
    "HISTO_LENGTH",
    "TH_HIGH",
    "TH_LOW",
    "epipolar_distance_squared",
    "epipole_in_b",
    "fundamental_matrix",
    "hamming",
    "hamming_rows",
    "hamming_within",
    "match_by_bow",
    "orientation_consistent",
    "search_by_projection",
    "search_epipolar",
]
