"""Matching ORB descriptors: blind within a vocabulary node, guided by a projection, along epipolar lines.

After ORB-SLAM2 src/ORBmatcher.cc (``SearchByBoW``, ``SearchByProjection``, ``SearchForTriangulation``,
``ComputeThreeMaxima``), rewritten for numpy: candidate pairs are built all at once, their Hamming distances
computed in one call, and best / second best / one-to-one resolved by sorting, never by a loop per feature.

Every search returns two index arrays of equal length (a pair per match), sorted by the first one. All but the
exhaustive one are one-to-one: where several queries pick the same feature, the one at the smallest distance keeps
it (ORB-SLAM2 keeps the first or the last, depending on the search).

Hamming distances: descriptors are read as four 64-bit words, XORed, and their set bits counted with
``np.bitwise_count`` (numpy >= 2, a hardware popcount where there is one; several times faster than a
256-entry lookup table).
"""

from __future__ import annotations

import numpy as np

from vo_core.compiled import kernel
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


def least_median_descriptors(descriptors: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """For each group of descriptors (rows ``starts[g]:starts[g + 1]`` of ``descriptors`` (L, 32)), the row of the
    one whose median Hamming distance to the group's descriptors (itself included) is least, the first among
    equals: ORB-SLAM2 MapPoint::ComputeDistinctiveDescriptors, the lower median for an even count."""
    return _least_median_rows(_words(descriptors), np.asarray(starts, np.int64))


@kernel
def _least_median_rows(words, starts):
    best_rows = np.empty(len(starts) - 1, np.int64)
    for g in range(len(starts) - 1):
        first, count = starts[g], starts[g + 1] - starts[g]
        distances = np.empty(count, np.int64)
        best_median = DESCRIPTOR_BITS + 1
        best_rows[g] = first
        for i in range(count):
            for j in range(count):
                distances[j] = _hamming_words(words[first + i], words[first + j])
            median = np.sort(distances)[(count - 1) // 2]
            if median < best_median:
                best_median, best_rows[g] = median, first + i
    return best_rows


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
    i, j = _nearest_sharing_node(features_a, np.arange(len(features_a)), nodes_a, features_b,
                                 np.arange(len(features_b)), nodes_b, None, None, max_distance, ratio)
    return _keep_consistent_rotation(i, j, features_a.angle, features_b.angle, check_orientation)


# ------------------------------------------------------------------------------------------- exhaustive


def match_exhaustive(a: Features, b: Features, *, max_distance: float, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Every feature of ``a`` against all of ``b``: the nearest descriptor within ``max_distance`` that passes the
    ratio test against the second nearest (ORB-SLAM2's initialization matching without its search window; the
    same pairs as OpenCV's brute-force ``knnMatch`` with k = 2, at a quarter of its CPU time). Not one-to-one: a
    feature of ``b`` may be the nearest of several. Returns (idx_a, idx_b)."""
    if len(a) == 0 or len(b) == 0:
        return _empty_match()
    return _nearest_of_all(_words(a.descriptors), _words(b.descriptors), float(max_distance), float(ratio))


@kernel
def _nearest_of_all(words_a, words_b, max_distance, ratio):
    found_a, found_b = np.empty(len(words_a), np.int64), np.empty(len(words_a), np.int64)
    found = 0
    for i in range(len(words_a)):
        nearest = NO_NEAREST
        for j in range(len(words_b)):
            nearest = _nearest_update(nearest, _hamming_words(words_a[i], words_b[j]), j)
        if _accepted(nearest, max_distance, ratio):
            found_a[found], found_b[found] = i, nearest[1]
            found += 1
    return found_a[:found], found_b[:found]


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
    point, feature, distance = _nearest_within(
        features.uv, features.level, _words(features.descriptors), _mask_or_all(available, len(features)), uv, radius,
        predicted_level.astype(np.int64), _words(descriptors), finite, int(level_window), float(max_distance),
        float(ratio))
    point, feature, _ = _one_to_one(point, feature, distance)
    return point, feature


# Side of the grid's cells that _nearest_within buckets the features in (pixels): search radii are 3-60 px.
GRID_CELL_PX = 16.0


@kernel
def _nearest_within(feature_uv, feature_level, feature_words, usable, uv, radius, level, words, valid, level_window,
                    max_distance, ratio):
    """search_by_projection's candidates and choice in one pass: for each valid point, the usable features within
    its radius (distance <= radius) whose level is within ``level_window`` of its own, found through a grid of the
    features, and among them the nearest descriptor (``_nearest_update``). Returns (point, feature, distance) of
    the points whose nearest passes ``_accepted``, by point."""
    start, members, origin_u, origin_v, columns, rows = _feature_grid(feature_uv)
    chosen = np.empty((len(uv), 3), np.int64)  # (point, feature, distance)
    found = 0
    for i in range(len(uv)):
        if not valid[i]:
            continue
        u, v, r = uv[i, 0], uv[i, 1], radius[i]
        first_col, last_col = _cell_span(u - r - origin_u, u + r - origin_u, columns)
        first_row, last_row = _cell_span(v - r - origin_v, v + r - origin_v, rows)
        nearest = NO_NEAREST
        for row in range(first_row, last_row + 1):
            for cell in range(row * columns + first_col, row * columns + last_col + 1):
                for f in members[start[cell]:start[cell + 1]]:
                    du, dv = feature_uv[f, 0] - u, feature_uv[f, 1] - v
                    if usable[f] and abs(feature_level[f] - level[i]) <= level_window and du * du + dv * dv <= r * r:
                        nearest = _nearest_update(nearest, _hamming_words(words[i], feature_words[f]), f)
        if _accepted(nearest, max_distance, ratio):
            chosen[found, 0], chosen[found, 1], chosen[found, 2] = i, nearest[1], nearest[0]
            found += 1
    return chosen[:found, 0], chosen[:found, 1], chosen[:found, 2]


@kernel
def _feature_grid(feature_uv):
    """The features bucketed in cells of GRID_CELL_PX from their smallest (u, v): (start, members, origin_u,
    origin_v, columns, rows); cell c (row-major) holds ``members[start[c]:start[c + 1]]``, in index order."""
    origin_u, origin_v = feature_uv[:, 0].min(), feature_uv[:, 1].min()
    columns = int((feature_uv[:, 0].max() - origin_u) // GRID_CELL_PX) + 1
    rows = int((feature_uv[:, 1].max() - origin_v) // GRID_CELL_PX) + 1
    cell = np.empty(len(feature_uv), np.int64)
    start = np.zeros(columns * rows + 1, np.int64)
    for f in range(len(feature_uv)):
        cell[f] = int((feature_uv[f, 1] - origin_v) // GRID_CELL_PX) * columns + int(
            (feature_uv[f, 0] - origin_u) // GRID_CELL_PX)
        start[cell[f] + 1] += 1
    for c in range(columns * rows):
        start[c + 1] += start[c]
    members = np.empty(len(feature_uv), np.int64)
    filled = start[:-1].copy()
    for f in range(len(feature_uv)):
        members[filled[cell[f]]] = f
        filled[cell[f]] += 1
    return start, members, origin_u, origin_v, columns, rows


@kernel
def _cell_span(low, high, count):
    """The first and last of ``count`` cells that [low, high] (pixels from the grid's origin) overlaps; first > last
    where none."""
    first = max(int(np.floor(low / GRID_CELL_PX)), 0)
    last = min(int(np.floor(high / GRID_CELL_PX)), count - 1)
    return first, last


# The running choice of _nearest_update before any candidate: (distance, target, second distance).
NO_NEAREST = (DESCRIPTOR_BITS + 1, -1, DESCRIPTOR_BITS + 1)


@kernel
def _nearest_update(nearest, distance, target):
    """One more candidate for the running (distance, target, second distance): the nearest descriptor, ties to the
    lower target index, and the second smallest distance among all candidates (the ratio test's)."""
    best, best_target, second = nearest
    if distance < best or (distance == best and target < best_target):
        return distance, target, best
    return best, best_target, min(second, distance)


@kernel
def _accepted(nearest, max_distance, ratio):
    """Whether a running choice is a match: the nearest within ``max_distance`` and below ``ratio`` times the second
    nearest (Lowe's test; a lone candidate passes, as ORB-SLAM2's second best starts at the largest distance)."""
    best, target, second = nearest
    return target >= 0 and best <= max_distance and (second > DESCRIPTOR_BITS or best < ratio * second)


@kernel
def _hamming_words(a, b):
    """Hamming distance of two descriptors as (4,) uint64 words (SWAR popcount)."""
    total = 0
    for k in range(len(a)):
        x = a[k] ^ b[k]
        x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
        x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
        x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
        total += int((x * np.uint64(0x0101010101010101)) >> np.uint64(56))
    return total


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
    lines = np.column_stack([features_a.uv[index_a], np.ones(len(index_a))]) @ np.asarray(F_ba, float).T
    if nodes_a is None or nodes_b is None:  # every candidate pair: one node for all
        nodes_a, nodes_b = np.zeros(len(features_a), np.int64), np.zeros(len(features_b), np.int64)
    i, j = _nearest_sharing_node(features_a, index_a, nodes_a, features_b, index_b, nodes_b, lines, threshold_b,
                                 max_distance, ratio)
    return _keep_consistent_rotation(i, j, features_a.angle, features_b.angle, check_orientation)


def _nearest_sharing_node(features_a, index_a, nodes_a, features_b, index_b, nodes_b, lines, threshold_b,
                          max_distance, ratio) -> tuple[np.ndarray, np.ndarray]:
    """For each feature ``index_a[k]``: the nearest descriptor among the features of ``index_b`` in its vocabulary
    node (and, with ``lines``, within ``threshold_b`` squared pixels of its epipolar line ``lines[k]`` in b),
    passing the ratio test; then one-to-one. Returns (idx_a, idx_b)."""
    index_b = index_b[np.argsort(np.asarray(nodes_b)[index_b], kind="stable")]
    if lines is None:  # no line to be near: zero lines, met everywhere below an infinite threshold
        lines, threshold_b = np.zeros((len(index_a), 3)), np.full(len(features_b), np.inf)
    i, j, distance = _nearest_in_node(
        index_a, lines, np.asarray(nodes_a, dtype=np.int64), _words(features_a.descriptors), index_b,
        np.asarray(nodes_b, dtype=np.int64)[index_b], features_b.uv, threshold_b, _words(features_b.descriptors),
        float(max_distance), float(ratio))
    i, j, _ = _one_to_one(i, j, distance)
    return i, j


@kernel
def _nearest_in_node(index_a, lines, node_a, words_a, index_b, node_b, uv_b, threshold_b, words_b, max_distance,
                     ratio):
    """_nearest_sharing_node's candidates and choice in one pass: for each feature ``index_a[k]`` (epipolar line
    ``lines[k]`` in b), the features of ``index_b`` (sorted by their nodes ``node_b``) in its node whose squared
    distance to the line is below their ``threshold_b``, and among them the nearest descriptor
    (``_nearest_update``). Returns (idx_a, idx_b, distance) of the features of a whose nearest passes ``_accepted``,
    in a's order."""
    chosen = np.empty((len(index_a), 3), np.int64)
    found = 0
    for k in range(len(index_a)):
        i = index_a[k]
        l0, l1, l2 = lines[k, 0], lines[k, 1], lines[k, 2]
        norm_sq = max(l0 * l0 + l1 * l1, np.finfo(np.float64).tiny)
        nearest = NO_NEAREST
        first = np.searchsorted(node_b, node_a[i], side="left")
        last = np.searchsorted(node_b, node_a[i], side="right")
        for m in range(first, last):
            j = index_b[m]
            numerator = l0 * uv_b[j, 0] + l1 * uv_b[j, 1] + l2
            if numerator * numerator / norm_sq < threshold_b[j]:
                nearest = _nearest_update(nearest, _hamming_words(words_a[i], words_b[j]), j)
        if _accepted(nearest, max_distance, ratio):
            chosen[found, 0], chosen[found, 1], chosen[found, 2] = i, nearest[1], nearest[0]
            found += 1
    return chosen[:found, 0], chosen[:found, 1], chosen[:found, 2]


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
    "least_median_descriptors",
    "match_by_bow",
    "orientation_consistent",
    "search_by_projection",
    "search_epipolar",
]
